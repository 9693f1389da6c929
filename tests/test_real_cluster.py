"""The dask executor against real ``dask scheduler`` / ``dask worker`` processes on localhost.

Not a LocalCluster: separate processes on free ports (the scheduler picks one and writes it to its
scheduler file), started with this Python and stopped (their process groups) at the end. The batch
runs as ``gctr batch`` in a subprocess, with the fake engine's ``slow_register`` (0.4 s per pair) so
that processes can be killed mid-run. Only 127.0.0.1 is used.
"""

from __future__ import annotations

import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

distributed = pytest.importorskip("distributed")

from conftest import Dataset, make_subprocess_env, read_csv  # noqa: E402
from real_cluster import RealCluster  # noqa: E402

from data_scripts import fake_engine  # noqa: E402
from gctr_cli.batch import run_batch  # noqa: E402
from gctr_cli.config import config_from_dict  # noqa: E402

N_PAIRS = 12
CONFIG = {"seed": 7, "batch": {"workers": 2, "time_limit_s": 60}}
#: ``gctr`` with the fake engine (the CLI has no option to choose a register function)
DRIVER = ("import functools, sys; from data_scripts import fake_engine; from gctr_cli import batch, cli; "
          "batch.run_batch = functools.partial(batch.run_batch, register_fn=fake_engine.slow_register); "
          "sys.argv[0] = 'gctr'; cli.main()")


@pytest.fixture(scope="module")
def env():
    return make_subprocess_env()


@pytest.fixture(scope="module")
def data(tmp_path_factory):
    """Manifest, config file and the local pool's rows (the reference) for N_PAIRS pairs."""
    root = tmp_path_factory.mktemp("real_cluster")
    ds = Dataset(root=root / "data", rng=np.random.default_rng(2024))
    ds.root.mkdir()
    for i in range(N_PAIRS):
        ds.add_pair(f"pair{i:02d}", with_gt=i % 3 != 0)
    config_path = root / "config.yaml"
    config_path.write_text("seed: 7\nbatch:\n  workers: 2\n  time_limit_s: 60\n")
    run_batch(ds.specs(), config_from_dict(CONFIG), root / "local", register_fn=fake_engine.register)
    return ds.manifest(), config_path, root, stable_rows(root / "local")


@pytest.fixture(scope="module")
def cluster(data, env):
    """A running cluster: one scheduler, two one-thread worker processes under nannies."""
    with RealCluster(data[2] / "cluster", env) as c:
        yield c


def stable_rows(outdir: Path) -> dict[str, dict[str, str]]:
    _header, rows = read_csv(outdir / "transforms.csv")
    ids = [r["pair_id"] for r in rows]
    assert len(ids) == len(set(ids)), "a pair has two rows"
    return {r["pair_id"]: {k: v for k, v in r.items() if k != "runtime_s"} for r in rows}


def n_rows(outdir: Path) -> int:
    try:
        return len((outdir / "transforms.csv").read_bytes().splitlines()) - 1
    except OSError:
        return 0


def start_batch(env, manifest: Path, config: Path, outdir: Path, scheduler: str, *extra: str) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, "-c", DRIVER, "batch", str(manifest), "-c", str(config), "-o",
                             str(outdir), "--scheduler", scheduler, "-q", *extra],
                            env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)


def wait_rows(proc: subprocess.Popen, outdir: Path, n: int, timeout: float = 60.0) -> None:
    deadline = time.monotonic() + timeout
    while n_rows(outdir) < n:
        assert proc.poll() is None, f"batch ended early: {proc.communicate()}"
        assert time.monotonic() < deadline, "batch too slow"
        time.sleep(0.02)


@pytest.mark.slow  # ~7.5 s, plus ~7 s to start the module's cluster
def test_worker_sigkilled_mid_run_costs_nothing(data, cluster, env, tmp_path):
    manifest, config, _, local = data
    before = cluster.worker_pids()
    out = tmp_path / "out"
    proc = start_batch(env, manifest, config, out, cluster.address)
    try:
        wait_rows(proc, out, 2)
        victim = next(iter(before.values()))
        os.kill(victim, 9)  # both workers are busy (2 slots, 0.4 s pairs): this one dies mid-pair
        stdout, stderr = proc.communicate(timeout=90)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.communicate()
    assert proc.returncode == 0, stderr
    assert stable_rows(out) == local  # every pair once, ok, transforms identical to the local pool
    assert all(r["status"] == "ok" for r in local.values())
    after = cluster.worker_pids()
    assert victim not in after.values() and len(after) == 2  # the nanny replaced the killed worker
    assert f"pairs: {N_PAIRS} ({N_PAIRS} ok, 0 failed)" in stdout


@pytest.mark.slow  # ~14 s
def test_scheduler_killed_exit_2_then_resume_on_a_new_cluster(data, cluster, env, tmp_path):
    manifest, config, _, local = data
    out = tmp_path / "out"
    with RealCluster(tmp_path / "doomed", env) as doomed:
        proc = start_batch(env, manifest, config, out, doomed.address)
        try:
            wait_rows(proc, out, 3)
            t0 = time.monotonic()
            doomed.kill_scheduler()
            stdout, stderr = proc.communicate(timeout=60)
            stopped_after = time.monotonic() - t0
        finally:
            if proc.poll() is None:
                proc.kill()
                proc.communicate()
    assert proc.returncode == 2, stderr
    assert stopped_after < 20, stopped_after  # typically < 1 s
    lines = [line for line in stderr.splitlines() if line.strip()]
    assert len(lines) == 1 and "Traceback" not in stderr, stderr
    assert lines[0].startswith(f"gctr: error: lost the connection to the dask scheduler at {doomed.address}")
    assert "--resume" in lines[0]
    kept = stable_rows(out)
    assert 3 <= len(kept) < N_PAIRS
    assert all(kept[pid] == local[pid] for pid in kept)  # finished rows kept as they were
    assert not (out / ".gctr.lock").exists()

    # --resume against another cluster finishes the run: every pair once, the same transforms
    proc = start_batch(env, manifest, config, out, cluster.address, "--resume")
    stdout, stderr = proc.communicate(timeout=90)
    assert proc.returncode == 0, stderr
    assert stable_rows(out) == local
    assert f"({len(kept)} done by an earlier run)" in stdout
