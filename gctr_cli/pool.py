"""The local executor: a crash-proof pool of worker processes on this machine (the default).

:func:`pool_outcomes` takes the ``(spec, seed)`` tasks of a batch and yields one
:class:`~gctr_cli.outcome.PairOutcome` per task in completion order. Each worker is a long-lived
``spawn``ed process fed one pair at a time through a pipe; it runs :func:`gctr_cli.pair.run_pair`
with one BLAS/OpenMP/Open3D thread. A worker that dies (segfault, out-of-memory kill) gives its pair
a failed outcome and is replaced; a pair over ``batch.time_limit_s`` has its worker killed and
replaced. Workers die with the batch process (``PR_SET_PDEATHSIG`` on Linux).
"""

from __future__ import annotations

import logging
import multiprocessing
import os
import shutil
import signal
import socket
import sys
import tempfile
import time
from collections import deque
from collections.abc import Iterator, Sequence
from multiprocessing.connection import wait as _mp_wait
from typing import Any

from gctr_cli.allocator import keep_freed_memory
from gctr_cli.config import Config
from gctr_cli.fsutil import (
    THREAD_ENV_VARS,
    environment,
    processes_ignore_ctrl_c,
    set_parent_death_signal,
    single_thread_env,
    start_resource_tracker,
)
from gctr_cli.outcome import PairOutcome, exc_message, failed_outcome, with_warnings
from gctr_cli.pair import limit_native_threads, resolve_register_fn, run_pair

logger = logging.getLogger(__name__)

__all__ = ["STARTUP_GRACE_S", "pool_outcomes"]


class _ListHandler(logging.Handler):
    """Collects the warnings logged while one pair runs in a worker."""

    def __init__(self) -> None:
        super().__init__(logging.WARNING)
        self.records: list[tuple[str, str]] = []

    def emit(self, record: logging.LogRecord) -> None:
        try:
            self.records.append((record.name, record.getMessage()))
        except Exception:  # noqa: BLE001
            pass


#: seconds a fresh worker may take to import everything before its first pair's clock starts
STARTUP_GRACE_S = 120.0


def _worker_main(conn: Any, config: Config, register_ref: str | None, parent_pid: int,
                 snapshots: bool = False, log_level: int = logging.WARNING) -> None:
    """Loop of one worker process (``log_level``: the parent's, so that ``-v``/``-vv`` show the pairs'
    info and debug lines, on the stderr the worker shares with it).

    Receives ``(spec, seed)``; answers ``("start", None)`` when it begins the pair (the parent starts
    the pair's clock then, so import time does not count against the time limit) and
    ``("done", PairOutcome)`` when it is finished. ``None`` or a closed pipe ends the loop.
    """
    set_parent_death_signal()
    keep_freed_memory()
    if os.getppid() != parent_pid:  # parent died before prctl took effect
        os._exit(1)
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # Ctrl-C is the parent's business
    for var in THREAD_ENV_VARS:
        os.environ[var] = "1"
    try:  # keep the parent's stdout clean (native libraries print warnings there)
        if sys.stdout is not None:  # None when the batch runs with stdout closed (cron: >&-)
            sys.stdout.flush()
        os.dup2(2, 1)
    except (OSError, ValueError):
        pass

    handler = _ListHandler()
    root = logging.getLogger()
    root.addHandler(handler)
    root.setLevel(logging.WARNING)
    logging.captureWarnings(True)
    if log_level < logging.WARNING:  # -v / -vv: info and debug lines go to stderr; warnings travel with the outcome
        verbose = logging.StreamHandler(sys.stderr)
        verbose.setLevel(log_level)
        verbose.addFilter(lambda record: record.levelno < logging.WARNING)
        verbose.setFormatter(logging.Formatter(f"gctr: %(levelname)s: worker {os.getpid()}: %(message)s"))
        package = logging.getLogger("gctr_cli")
        package.addHandler(verbose)
        package.setLevel(log_level)

    startup_error = None
    register_fn = None
    try:
        import gctr_cli.io  # load everything a pair needs before the first pair

        if snapshots:
            import matplotlib.backends.backend_agg
            import matplotlib.figure  # noqa: F401

            import gctr_cli.snapshots  # noqa: F401
        register_fn = resolve_register_fn(register_ref, config)
    except BaseException as exc:  # noqa: BLE001
        startup_error = f"worker start-up failed: {exc_message(exc)}"
    limit_native_threads()

    while True:
        try:
            task = conn.recv()
        except (EOFError, OSError):
            break
        if task is None:
            break
        spec, seed = task
        handler.records.clear()
        limit_native_threads()
        try:
            conn.send(("start", None))
            if startup_error is not None:
                outcome = failed_outcome(spec, seed, startup_error, "worker", 0.0)
            else:
                outcome = run_pair(spec, config, register_fn, seed=seed, snapshot=snapshots)
            if handler.records:
                outcome = with_warnings(outcome, handler.records)
            try:
                conn.send(("done", outcome))
            except (BrokenPipeError, OSError):
                raise
            except Exception as exc:  # noqa: BLE001 - an outcome that does not pickle
                conn.send(("done", failed_outcome(spec, seed, f"cannot return the result: {exc_message(exc)}", "worker",
                                           outcome.runtime_s)))
        except (BrokenPipeError, OSError):
            break
    conn.close()


#: the start of a worker's temporary folder's name: ``gctr-worker-<batch pid>@<host>-<random>``
TMP_PREFIX = "gctr-worker-"


def _tmp_prefix() -> str:
    return f"{TMP_PREFIX}{os.getpid()}@{socket.gethostname()}-"


def _sweep_orphan_tmp() -> None:
    """Remove the workers' temporary folders of batches of this host that no longer run (a SIGKILLed
    batch cannot remove them; a LAZ read may have left an 86 MB copy in one). Best effort: a folder whose
    name does not parse, or of another host (a TMPDIR shared between machines), is left alone."""
    try:
        base = tempfile.gettempdir()
        host = socket.gethostname()
        names = [n for n in os.listdir(base) if n.startswith(TMP_PREFIX)]
        for name in names:
            pid, at, rest = name[len(TMP_PREFIX):].partition("@")
            if not (at and pid.isascii() and pid.isdigit() and len(pid) <= 9) or rest.rpartition("-")[0] != host:
                continue
            if int(pid) == os.getpid():
                continue
            try:
                os.kill(int(pid), 0)
                continue  # that batch still runs (or the pid is another user's process: leave it)
            except ProcessLookupError:
                pass
            path = os.path.join(base, name)
            if os.path.isdir(path) and not os.path.islink(path):
                shutil.rmtree(path, ignore_errors=True)
    except Exception:  # a sweep must never stop a batch
        logger.debug("sweeping orphan worker folders failed", exc_info=True)


class _Worker:
    """One long-lived worker process, fed one pair at a time through a pipe."""

    def __init__(self, ctx: Any, config: Config, register_ref: str | None, snapshots: bool = False) -> None:
        # the worker's own temporary folder (its TMPDIR): a worker killed at the time limit or by the
        # kernel cannot remove what it made (a LAZ file's decompressed copy, 86 MB per 3 million
        # points, night after night); the batch removes the folder with the worker
        # (named by the batch's pid: one left by a batch that was SIGKILLed is removed by the next)
        self.conn, child_conn = ctx.Pipe(duplex=True)
        try:
            self.tmp: str | None = tempfile.mkdtemp(prefix=_tmp_prefix())
        except OSError:
            self.tmp = None  # the worker uses the system's; a full TMPDIR is reported when a pair needs it
        self.process = ctx.Process(
            target=_worker_main,
            args=(child_conn, config, register_ref, os.getpid(), snapshots,
                  logging.getLogger("gctr_cli").level or logging.WARNING),  # as the CLI's -v set it
            name="gctr-worker",
            daemon=True,
        )
        try:
            # SIGINT ignored from its start: no KeyboardInterrupt traceback while it imports
            with single_thread_env(), processes_ignore_ctrl_c(), environment({"TMPDIR": self.tmp} if self.tmp else {}):
                self.process.start()
        except BaseException:
            child_conn.close()
            self.kill()  # not started, or not tracked yet: its folder goes now
            raise
        child_conn.close()
        self.spec: Any = None
        self.seed = 0
        self.assigned = 0.0  # when the pair was sent
        self.running_since: float | None = None  # when the worker acknowledged it

    @property
    def busy(self) -> bool:
        return self.spec is not None

    def assign(self, spec: Any, seed: int) -> None:
        self.conn.send((spec, seed))
        self.spec, self.seed = spec, seed
        self.assigned, self.running_since = time.monotonic(), None

    def deadline(self, time_limit_s: float) -> float:
        if self.running_since is None:
            return self.assigned + STARTUP_GRACE_S + time_limit_s
        return self.running_since + time_limit_s

    def runtime(self) -> float:
        return time.monotonic() - (self.running_since if self.running_since is not None else self.assigned)

    def death_message(self) -> str:
        self.process.join(timeout=5)
        code = self.process.exitcode
        if code is None:
            self.kill()
            return "worker died (closed its pipe)"
        if code < 0:
            return f"worker died (signal {-code})"
        return f"worker died (exit code {code})"

    def kill(self) -> None:
        if self.process.pid is not None:
            if self.process.is_alive():
                self.process.kill()
            self.process.join(timeout=5)
        self.conn.close()
        self.remove_tmp()

    def remove_tmp(self) -> None:
        """Remove the worker's temporary folder (once it has exited)."""
        if self.tmp is not None and (self.process.pid is None or not self.process.is_alive()):
            shutil.rmtree(self.tmp, ignore_errors=True)
            self.tmp = None

    def stop(self) -> None:
        try:
            self.conn.send(None)
        except (OSError, ValueError):
            pass


def pool_outcomes(
    tasks: Sequence[tuple[Any, int]],
    config: Config,
    n_workers: int,
    register_ref: str | None,
    time_limit_s: float,
    *,
    snapshots: bool = False,
) -> Iterator[PairOutcome]:
    """Run ``(spec, seed)`` tasks on ``n_workers`` processes; yield outcomes in completion order.

    Survives anything a pair can do to its worker: a worker that dies gives a failed outcome for its
    pair and is replaced; a pair over the time limit has its worker killed and replaced.
    """
    ctx = multiprocessing.get_context("spawn")
    start_resource_tracker()  # with SIGHUP ignored, before any worker
    _sweep_orphan_tmp()
    pending: deque[tuple[Any, int]] = deque(tasks)
    workers: list[_Worker] = []
    send_retries: dict[str, int] = {}
    n_workers = max(1, min(n_workers, len(pending)))

    def retire(w: _Worker) -> None:
        w.kill()
        workers.remove(w)

    def feed() -> Iterator[PairOutcome]:
        """Give pending pairs to idle workers (started lazily, dead ones replaced)."""
        while pending:
            idle = next((w for w in workers if not w.busy), None)
            if idle is not None and not idle.process.is_alive():  # died between pairs
                logger.info("a worker exited between pairs (%s); starting a new one", idle.death_message())
                retire(idle)
                continue
            if idle is None:
                if len(workers) >= n_workers:
                    break
                idle = _Worker(ctx, config, register_ref, snapshots)
                workers.append(idle)
            spec, seed = pending.popleft()
            try:
                idle.assign(spec, seed)
            except (BrokenPipeError, OSError):
                # the worker died before taking the pair: retry it once on a fresh worker
                message = idle.death_message()
                retire(idle)
                n = send_retries.get(spec.pair_id, 0)
                if n < 1:
                    send_retries[spec.pair_id] = n + 1
                    pending.appendleft((spec, seed))
                else:
                    yield failed_outcome(spec, seed, message, "worker", 0.0)

    try:
        while pending or any(w.busy for w in workers):
            yield from feed()
            busy = [w for w in workers if w.busy]
            if not busy:
                continue
            timeout = max(0.0, min(w.deadline(time_limit_s) for w in busy) - time.monotonic()) + 0.01
            _mp_wait([w.conn for w in busy] + [w.process.sentinel for w in busy], timeout=timeout)

            ready: list[PairOutcome] = []
            for w in busy:
                spec, seed = w.spec, w.seed
                outcome: PairOutcome | None = None
                broken = ""
                try:
                    while outcome is None and w.conn.poll():
                        kind, payload = w.conn.recv()
                        if kind == "start":
                            w.running_since = time.monotonic()
                        else:
                            outcome = payload
                except (EOFError, OSError):
                    broken = "eof"
                except Exception as exc:  # noqa: BLE001 - a message that does not unpickle
                    broken = f"bad result from worker: {exc_message(exc)}"
                if outcome is not None:
                    w.spec = None
                    ready.append(outcome)
                    continue
                runtime = w.runtime()
                if broken and broken != "eof":
                    retire(w)
                    yield failed_outcome(spec, seed, broken, "worker", runtime)
                elif broken or not w.process.is_alive():
                    message = w.death_message()
                    retire(w)
                    yield failed_outcome(spec, seed, message, "worker", runtime)
                elif time.monotonic() >= w.deadline(time_limit_s):
                    retire(w)  # kills the worker
                    if w.running_since is None:
                        message = f"worker did not start within {STARTUP_GRACE_S + time_limit_s:g} s"
                    else:
                        message = f"timed out after {time_limit_s:g} s"
                    yield failed_outcome(spec, seed, message, "timeout", runtime)
            # the workers that finished get their next pair before the batch process commits these (fsyncs)
            yield from feed()
            yield from ready
    finally:
        for w in workers:
            if w.busy:
                w.kill()
            else:
                w.stop()
        deadline = time.monotonic() + 5
        for w in workers:
            w.process.join(timeout=max(0.0, deadline - time.monotonic()))
            if w.process.is_alive():
                w.kill()
            try:
                w.conn.close()
            except OSError:
                pass
            w.remove_tmp()
