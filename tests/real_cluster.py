"""Real dask processes on localhost for the cluster tests: a ``dask scheduler`` and ``dask worker``
processes started with the project's own Python, on free ports, and stopped (process group) at the end.
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

BIN = Path(sys.executable).parent


class RealCluster:
    """``dask scheduler`` + one ``dask worker`` command running ``n_workers`` one-thread worker processes."""

    def __init__(self, workdir: Path, env: dict[str, str], n_workers: int = 2, timeout: float = 60.0) -> None:
        self.workdir = Path(workdir)
        self.workdir.mkdir(parents=True, exist_ok=True)
        self.env = env
        self.n_workers = n_workers
        self.timeout = timeout
        self.scheduler_file = self.workdir / "scheduler.json"
        self.scheduler: subprocess.Popen | None = None
        self.worker: subprocess.Popen | None = None
        self.address = ""

    def _popen(self, args: list[str], log: str) -> subprocess.Popen:
        with open(self.workdir / log, "wb") as fh:  # the child keeps its own copy of the descriptor
            return subprocess.Popen([str(BIN / "dask"), *args], env=self.env, stdout=fh, stderr=subprocess.STDOUT,
                                    cwd=self.workdir, start_new_session=True)

    def start(self) -> RealCluster:
        self.scheduler = self._popen(["scheduler", "--host", "127.0.0.1", "--port", "0", "--no-dashboard",
                                      "--scheduler-file", str(self.scheduler_file)], "scheduler.log")
        deadline = time.monotonic() + self.timeout
        while not self.address:
            if time.monotonic() > deadline or self.scheduler.poll() is not None:
                log = (self.workdir / "scheduler.log").read_text()[-2000:]
                raise RuntimeError(f"dask scheduler did not start: {log}")
            try:
                self.address = json.loads(self.scheduler_file.read_text())["address"]
            except (OSError, ValueError, KeyError):
                time.sleep(0.1)
        self.worker = self._popen(["worker", self.address, "--nworkers", str(self.n_workers), "--nthreads", "1",
                                   "--host", "127.0.0.1", "--no-dashboard", "--death-timeout", "30"], "worker.log")
        self.wait_for_workers(self.n_workers, deadline)
        return self

    def client(self):
        from distributed import Client

        return Client(self.address, timeout=30, set_as_default=False)

    def wait_for_workers(self, n: int, deadline: float) -> None:
        with self.client() as c:
            c.wait_for_workers(n, timeout=max(1.0, deadline - time.monotonic()))

    def worker_pids(self) -> dict[str, int]:
        with self.client() as c:
            return c.run(os.getpid)

    def kill_scheduler(self) -> None:
        assert self.scheduler is not None
        self.scheduler.send_signal(signal.SIGKILL)
        self.scheduler.wait(timeout=10)

    def stop(self) -> None:
        for proc in (self.worker, self.scheduler):
            if proc is None:
                continue
            try:
                os.killpg(proc.pid, signal.SIGKILL)  # the process group we created: nannies and workers too
            except (ProcessLookupError, PermissionError):
                pass
            try:
                proc.wait(timeout=10)
            except subprocess.TimeoutExpired:
                pass

    def __enter__(self) -> RealCluster:
        return self.start()

    def __exit__(self, *exc) -> None:
        self.stop()
