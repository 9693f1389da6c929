"""Run the pairs of a batch on a dask.distributed cluster (``gctr batch --executor dask``).

An executor for :func:`gctr_cli.batch.run_batch` (see :mod:`gctr_cli.executors`): it takes the
``(spec, seed)`` tasks and yields one :class:`~gctr_cli.outcome.PairOutcome` per task as the futures
complete; the batch process writes the outputs exactly as with the local pool (same files, same commit
order, ``--resume``, lock).

* **Cluster.** With a ``scheduler`` address (``tcp://HOST:8786``) it connects to a running cluster (started by hand,
  by dask-jobqueue on Slurm/PBS/..., by dask-kubernetes, ...). Without one it starts a ``LocalCluster`` of
  ``n_workers`` processes with one thread each, which it closes at the end.
* **Same work, same results.** Each task calls :func:`gctr_cli.pair.run_pair` with the seed derived from the config
  seed and the pair id, as a local worker does, with native thread pools capped to one thread
  (:func:`_single_threaded`: ``OMP_NUM_THREADS`` and friends for pools created later, ``threadpoolctl`` for loaded
  BLAS/OpenMP, Open3D's ``set_max_threads(1)``): the transforms equal the local pool's bit for bit. LocalCluster
  workers get the variables before they start, and ignore Ctrl-C.
* **Bounded submission.** At most twice as many tasks are in flight as the cluster has worker threads (at least
  one): one running and one waiting per thread, so memory stays bounded for any manifest size, and workers added to
  an adaptive cluster are used as they join. A worker plugin (:class:`GctrWorkerSetup`) prepares every worker, also
  those that join later: one-thread native pools and the imports a pair needs, so import time does not count against
  the first pair's limit.
* **Failures.** A task whose worker dies (segfault, out-of-memory kill by the nanny) ends in ``KilledWorker`` and
  gives a failed row ``worker died (...)``. The LocalCluster is started with
  ``distributed.scheduler.allowed-failures = 0`` so that, as with the local pool, the first death fails the pair; an
  external scheduler keeps its own setting (default 3 retries on other workers, which also covers preempted nodes);
  a pair whose result dies with a worker another pair crashed runs again, and so does a pair that was waiting on
  that worker and had not started, when the pair that had started there is known (starts are announced, see the
  time limit; an announcement can die with the worker, and then no pair runs again). Any other exception of a
  task gives a failed row naming it.
* **Time limit** (best effort): a pair running longer than ``batch.time_limit_s`` (measured from when its task
  starts executing on a worker, which the task announces with a dask event; waiting for a worker does not count)
  gets the failed row ``timed out after N s``; its future is cancelled and its worker process replaced (a Python
  thread cannot be stopped otherwise): killed at once in our own LocalCluster (its nanny starts a fresh one),
  restarted through its nanny on an external cluster. A worker without a nanny keeps computing until the pair ends.
* **Lost scheduler.** If the connection to the scheduler is lost (the scheduler process died, the network went
  away), the batch stops with :class:`~gctr_cli.errors.ExecutorLost` (one line from the CLI, exit 2); the pairs in
  flight get no row, the finished pairs are saved and ``--resume`` against a running scheduler finishes with the
  same transforms.

Input paths in the manifest are resolved to absolute paths by the client (relative ones against the manifest's
folder) and must be readable at those same paths on every worker (shared filesystem). The outputs are written by the
batch process only; snapshots travel back inside the outcomes, so the output folder need not be shared.
"""

from __future__ import annotations

import contextlib
import logging
import math
import os
import sys
import threading
import time
import uuid
from collections import deque
from collections.abc import Iterator, Sequence
from typing import Any

from gctr_cli.config import Config
from gctr_cli.dask_cluster import connect
from gctr_cli.errors import BatchError, ExecutorLost
from gctr_cli.fsutil import THREAD_ENV_VARS
from gctr_cli.outcome import PairOutcome, exc_message, failed_outcome, with_warnings
from gctr_cli.pair import limit_native_threads, resolve_register_fn, run_pair

try:  # the class must exist at import time for the plugin to pickle by reference
    from distributed.diagnostics.plugin import WorkerPlugin as _WorkerPluginBase
except ImportError:  # pragma: no cover - dask is an optional extra; check_available() reports it
    _WorkerPluginBase = object  # type: ignore[assignment,misc]

logger = logging.getLogger(__name__)

__all__ = ["check_available", "dask_outcomes"]

INSTALL_HINT = "pip install '.[dask]' in gctr's checkout (make setup does)"
PLUGIN_NAME = "gctr-worker-setup"  #: name of the worker plugin (re-registering replaces it)
#: a task lost with a worker killed by gctr (time limit) or by another pair is resubmitted at most this often
MAX_RESUBMITS = 2
POLL_S = 0.5  #: the loop wakes up at least this often (new workers, time limits, lost scheduler)
WAITING_LOG_S = 10.0  #: seconds with no pair started before the batch says it waits for workers
#: tasks in flight per worker thread: one running, one queued at the scheduler, so a worker starts its
#: next pair while the batch process commits the last one (time limits count from a task's start)
IN_FLIGHT_PER_SLOT = 2
#: seconds between two looks at the cluster's number of worker threads (adaptive clusters grow)
SLOTS_REFRESH_S = 2.0
RESTART_TIMEOUT_S = 60.0  #: seconds given to a nanny to restart a worker whose pair timed out


def check_available() -> None:
    """Raise :class:`BatchError` with the install command when dask.distributed is missing."""
    try:
        import distributed  # noqa: F401
    except ImportError as exc:
        raise BatchError(f"the dask executor needs dask.distributed ({exc}); install it with: {INSTALL_HINT}") from None


# ----------------------------------------------------------------------------------------------------
# the task (runs on a worker)
# ----------------------------------------------------------------------------------------------------


class _ThreadRecords(logging.Handler):
    """Collects the warnings logged by the current thread while one pair runs."""

    def __init__(self) -> None:
        super().__init__(logging.WARNING)
        self.thread = threading.get_ident()
        self.records: list[tuple[str, str]] = []

    def emit(self, record: logging.LogRecord) -> None:
        if record.thread != self.thread:
            return
        try:
            self.records.append((record.name, record.getMessage()))
        except Exception:  # noqa: BLE001
            pass


@contextlib.contextmanager
def _single_threaded() -> Iterator[None]:
    """One thread for BLAS/OpenMP/Open3D while a pair runs on a dask worker (see the module docstring)."""
    for var in THREAD_ENV_VARS:
        os.environ[var] = "1"
    try:
        from threadpoolctl import threadpool_limits
    except ImportError:  # the dask extra installs it; the env variables still cover fresh workers
        limits: Any = contextlib.nullcontext()
    else:
        limits = threadpool_limits(limits=1)
    with limits:
        limit_native_threads()
        yield


class GctrWorkerSetup(_WorkerPluginBase):
    """Worker plugin: prepares every worker, including those that join or restart later.

    Caps native thread pools to one thread (environment variables for pools not yet created,
    ``threadpoolctl`` for loaded BLAS/OpenMP libraries, Open3D's ``set_max_threads``) and imports
    what a pair needs (readers, the register function, matplotlib for snapshots), so that import time
    does not count against the first pair's time limit. Problems are left for the task to report.
    """

    def __init__(self, config: Config, register_ref: str | None, snapshots: bool, own_cluster: bool = False) -> None:
        self.config = config
        self.register_ref = register_ref
        self.snapshots = snapshots
        self.own_cluster = own_cluster  # gctr's LocalCluster: its workers are gctr's alone

    def setup(self, worker: Any = None) -> None:
        for var in THREAD_ENV_VARS:
            os.environ[var] = "1"
        local = getattr(worker, "local_directory", None)
        if getattr(self, "own_cluster", False) and local and os.path.isdir(local):  # not another cluster's
            # temporary files (a LAZ file's decompressed copy) in the worker's own folder, which dask removes
            # when the worker ends, and purges when a killed worker's replacement starts
            import tempfile

            tempfile.tempdir = str(local)
        try:
            import gctr_cli.io

            resolve_register_fn(self.register_ref, self.config)
            if self.snapshots:
                import matplotlib.backends.backend_agg
                import matplotlib.figure  # noqa: F401

                import gctr_cli.snapshots  # noqa: F401
        except Exception:  # run_task reports it per pair
            logger.debug("gctr worker setup failed", exc_info=True)
        try:
            from threadpoolctl import threadpool_limits

            threadpool_limits(limits=1)
        except Exception:  # noqa: BLE001
            pass
        limit_native_threads()


def _announce_start(topic: str | None) -> None:
    """Tell the client that this task started executing (the start of its time limit)."""
    if not topic:
        return
    try:
        from distributed import get_worker

        worker = get_worker()
        worker.log_event(topic, {"key": str(worker.get_current_task()), "worker": worker.address})
    except Exception:  # noqa: BLE001 - only the time limit depends on it
        pass


def run_task(spec: Any, seed: int, config: Config, register_ref: str | None, snapshots: bool,
             start_topic: str | None = None) -> PairOutcome:
    """One pair on a dask worker: :func:`run_pair` single-threaded, with its warnings attached."""
    _announce_start(start_topic)
    root = logging.getLogger()
    handler = _ThreadRecords()
    root.addHandler(handler)
    try:
        with _single_threaded():
            try:
                import gctr_cli.io  # noqa: F401

                register_fn = resolve_register_fn(register_ref, config)
            except Exception as exc:  # noqa: BLE001
                return failed_outcome(spec, seed, f"worker start-up failed: {exc_message(exc)}", "worker", 0.0)
            limit_native_threads()  # Open3D may have been loaded just now
            outcome = run_pair(spec, config, register_fn, seed=seed, snapshot=snapshots)
    finally:
        root.removeHandler(handler)
    if handler.records:
        outcome = with_warnings(outcome, handler.records)
    return outcome


# ----------------------------------------------------------------------------------------------------
# the client side (connecting, or starting the local cluster: :mod:`gctr_cli.dask_cluster`)
# ----------------------------------------------------------------------------------------------------


class _InFlight:
    __slots__ = ("spec", "seed", "submitted", "started", "worker")

    def __init__(self, spec: Any, seed: int) -> None:
        self.spec = spec
        self.seed = seed
        self.submitted = time.monotonic()
        self.started: float | None = None
        self.worker: str | None = None

    def deadline(self, time_limit_s: float) -> float:
        if self.started is None:  # waiting for a worker (e.g. Slurm jobs still queued): no limit yet
            return math.inf
        return self.started + time_limit_s

    def runtime(self) -> float:
        return time.monotonic() - (self.started if self.started is not None else self.submitted)


def _killed_message(exc: BaseException) -> str:
    worker = getattr(getattr(exc, "last_worker", None), "address", None)
    attempts = getattr(exc, "allowed_failures", None)
    where = f"dask worker {worker}" if worker else "its dask worker"
    tries = f"; {attempts + 1} attempts" if isinstance(attempts, int) and attempts > 0 else ""
    return f"worker died ({where} was lost while running the pair{tries})"


def _killed_worker_address(future: Any) -> str | None:
    """The address of the last worker of a future that failed with ``KilledWorker``, else None."""
    if future.status != "error":
        return None
    from distributed import KilledWorker

    try:
        exc = future.exception()
    except Exception:  # noqa: BLE001
        return None
    if isinstance(exc, KilledWorker):
        return getattr(exc.last_worker, "address", None)
    return None


def _outcome_of(future: Any, job: _InFlight) -> PairOutcome:
    """The outcome of a completed future; a task error becomes a failed outcome."""
    from distributed import KilledWorker

    status = future.status
    if status == "finished":
        try:
            outcome = future.result()
        except OSError:  # CommClosedError: the result cannot be fetched, the scheduler is going away
            raise
        except Exception as exc:  # noqa: BLE001 - e.g. the result cannot be deserialised
            return failed_outcome(job.spec, job.seed, f"bad result from worker: {exc_message(exc)}", "worker",
                                  job.runtime())
        if not isinstance(outcome, PairOutcome):
            return failed_outcome(job.spec, job.seed, f"bad result from worker: {type(outcome).__name__}", "worker",
                           job.runtime())
        return outcome
    if status == "error":
        try:
            error = future.exception()
        except OSError:
            raise
        except Exception as err:  # noqa: BLE001
            error = err
        if isinstance(error, KilledWorker):
            return failed_outcome(job.spec, job.seed, _killed_message(error), "worker", job.runtime())
        return failed_outcome(job.spec, job.seed, f"task failed on its dask worker: {exc_message(error)}", "worker",
                              job.runtime())
    return failed_outcome(job.spec, job.seed, f"task {status} by the dask cluster", "worker", job.runtime())


def _n_slots(client: Any) -> int:
    """Worker threads of the cluster (0 without a worker; 1 when the scheduler cannot be asked)."""
    try:
        return sum(int(n) for n in client.nthreads().values())
    except Exception:  # noqa: BLE001
        return 1


def _lost(scheduler: str | None, n_running: int) -> ExecutorLost:
    """The one-line error of a batch whose scheduler went away (the cause is chained for ``-vv``)."""
    where = f"at {scheduler}" if scheduler else "of the LocalCluster"
    return ExecutorLost(
        f"lost the connection to the dask scheduler {where} ({n_running} pair{'' if n_running == 1 else 's'} "
        "sent to it unfinished)"
    )


def _check_connected(client: Any, scheduler: str | None, n_running: int) -> None:
    """A client that is not ``running`` lost its scheduler: its futures are cancelled, nothing can go
    on (it would only try to reconnect, and block RPCs for the connect timeout meanwhile)."""
    if client.status != "running":
        raise _lost(scheduler, n_running)


def dask_outcomes(
    tasks: Sequence[tuple[Any, int]],
    config: Config,
    n_workers: int,
    register_ref: str | None,
    time_limit_s: float,
    *,
    scheduler: str | None = None,
    snapshots: bool = False,
) -> Iterator[PairOutcome]:
    """Run ``(spec, seed)`` tasks on a dask cluster; yield the outcomes as the futures complete."""
    check_available()
    from distributed import wait

    quiet = _QuietDistributed()
    client, cluster = connect(scheduler, max(1, min(n_workers, len(tasks))))
    quiet.start()
    pending: deque[tuple[Any, int]] = deque(tasks)
    inflight: dict[Any, _InFlight] = {}
    run_id = uuid.uuid4().hex[:8]
    waiting_logged = False
    closing = threading.Event()
    restarts: list[threading.Thread] = []  # restarts of the workers of timed-out pairs (external cluster)
    killed_workers: set[str] = set()  # workers gctr replaced because a pair timed out
    crashed_workers: set[str] = set()  # workers that died under a pair that had announced its start
    resubmits: dict[str, int] = {}
    n_submitted = 0
    slots, slots_checked = 1, -math.inf
    start_topic = f"gctr-start-{run_id}"
    starts: dict[str, tuple[float, str]] = {}  # task key -> (monotonic time it started, worker)

    def on_start(event: Any) -> None:  # runs in the client's event-loop thread
        try:
            _, msg = event
            starts[str(msg["key"])] = (time.monotonic(), str(msg.get("worker") or ""))
        except Exception:  # noqa: BLE001
            pass

    try:
        try:
            client.subscribe_topic(start_topic, on_start)
        except Exception as exc:  # noqa: BLE001
            logger.warning("cannot follow task starts (%s): the per-pair time limit is not enforced",
                           exc_message(exc))
        try:
            client.register_plugin(GctrWorkerSetup(config, register_ref, snapshots, cluster is not None),
                                   name=PLUGIN_NAME)
        except Exception as exc:  # noqa: BLE001 - typically: gctr is not installed on the workers
            raise BatchError(
                f"the dask workers cannot set up gctr ({exc_message(exc)}); every worker needs the same "
                f"Python environment as this machine, with gctr installed ({INSTALL_HINT})"
            ) from None
        while pending or inflight:
            _check_connected(client, scheduler, len(inflight))
            if time.monotonic() >= slots_checked + SLOTS_REFRESH_S:  # an RPC: not once per pair
                slots, slots_checked = _n_slots(client), time.monotonic()
            while pending and len(inflight) < IN_FLIGHT_PER_SLOT * max(1, slots):
                spec, seed = pending[0]
                n_submitted += 1  # unique keys, also for a resubmitted pair
                try:
                    future = client.submit(run_task, spec, seed, config, register_ref, snapshots, start_topic,
                                           key=f"gctr-{run_id}-{n_submitted}-{spec.pair_id}", pure=False, retries=0)
                except Exception as exc:  # the client cannot reach the scheduler
                    raise _lost(scheduler, len(inflight)) from exc
                pending.popleft()
                inflight[future] = _InFlight(spec, seed)

            _track_starts(starts, inflight)
            now = time.monotonic()
            next_deadline = min(job.deadline(time_limit_s) for job in inflight.values())
            timeout = min(POLL_S, max(0.0, next_deadline - now) + 0.01)
            try:
                with client.as_current():  # `wait` uses the current client; ours is not made the default
                    done, _ = wait(list(inflight), timeout=timeout, return_when="FIRST_COMPLETED")
            except TimeoutError:
                done = set()
            except Exception as exc:  # FuturesCancelledError: scheduler-connection-lost
                # gctr cancels only futures it no longer waits for: a cancelled one means the scheduler is gone
                raise _lost(scheduler, len(inflight)) from exc
            _track_starts(starts, inflight)  # (starts announced while waiting: who was running when a worker died)
            finished = [f for f in inflight if f in done]  # submission order among the finished
            lost_on_of = {f: _killed_worker_address(f) for f in finished}  # the worker each KilledWorker died with
            crashed_workers.update(a for f, a in lost_on_of.items()
                                   if a is not None and inflight[f].started is not None)
            for future in finished:
                if future.status == "cancelled":  # not by us (see above): the scheduler is gone or restarted
                    raise _lost(scheduler, len(inflight))
                job = inflight.pop(future)
                starts.pop(future.key, None)
                result_lost = future.status == "lost"  # its result died with a worker another pair crashed
                try:
                    lost_on = lost_on_of[future]
                    outcome = _outcome_of(future, job)
                except OSError as exc:  # the result or error cannot be fetched any more
                    raise _lost(scheduler, len(inflight) + 1) from exc
                future.release()
                # queued on a worker that another pair, known to have started there, crashed: it never started
                # (the scheduler sends a worker more than one task when they are not "root-ish", and fails them
                # all when it dies). Without a known culprit (its start announcement died with the worker) no
                # pair is resubmitted: the one that crashed it would crash another worker.
                never_started = lost_on is not None and job.started is None and lost_on in crashed_workers
                if ((result_lost or lost_on in killed_workers or never_started)
                        and resubmits.get(job.spec.pair_id, 0) < MAX_RESUBMITS):
                    resubmits[job.spec.pair_id] = resubmits.get(job.spec.pair_id, 0) + 1  # an innocent pair
                    logger.info("pair %s: %s; resubmitting", job.spec.pair_id, "its result was lost with its worker"
                                if result_lost else "its worker was replaced (another pair timed out)"
                                if lost_on in killed_workers else "its worker died under another pair before this one "
                                "started there")
                    pending.appendleft((job.spec, job.seed))
                    continue
                yield outcome
            if not inflight:
                continue

            _track_starts(starts, inflight)
            if (not waiting_logged and not any(job.started is not None for job in inflight.values())
                    and time.monotonic() - min(j.submitted for j in inflight.values()) > WAITING_LOG_S):
                if slots:
                    logger.info("waiting for dask workers (%d threads known)", slots)
                else:  # a warning: under -q (cron) the batch would wait without a word
                    logger.warning("no dask worker has joined %s yet: the batch waits for one (start workers, or "
                                   "stop it with Ctrl-C: finished pairs are kept, --resume goes on)",
                                   scheduler or "the local cluster")
                waiting_logged = True
            now = time.monotonic()
            for future, job in list(inflight.items()):
                if future.done() or now < job.deadline(time_limit_s):
                    continue
                del inflight[future]
                starts.pop(future.key, None)
                runtime = job.runtime()
                future.cancel()
                if job.worker:
                    killed_workers.add(job.worker)
                    if not (cluster is not None and _kill_local_worker(cluster, job.worker)):
                        # in the background: the nanny takes seconds to stop and respawn a busy worker
                        restart = threading.Thread(target=_restart_worker, name="gctr-restart-worker", daemon=True,
                                                   args=(client, job.worker, job.spec.pair_id, closing))
                        restart.start()
                        restarts.append(restart)
                yield failed_outcome(job.spec, job.seed, f"timed out after {time_limit_s:g} s", "timeout", runtime)
    finally:
        if sys.exc_info()[0] is None and client.status == "running":
            # a batch that ends normally lets its worker restarts finish: closing the client in the middle
            # of one can leave the nanny without its worker (the cluster would lose a worker for good)
            deadline = time.monotonic() + RESTART_TIMEOUT_S
            for restart in restarts:
                restart.join(timeout=max(0.0, deadline - time.monotonic()))
        quiet.close()  # a lost scheduler makes distributed log reconnection tracebacks while closing
        for future in inflight:
            with contextlib.suppress(Exception):
                future.cancel()
        closing.set()
        with contextlib.suppress(Exception):
            client.unsubscribe_topic(start_topic)
        with contextlib.suppress(Exception):
            client.close(timeout=10)
        if cluster is not None:
            with contextlib.suppress(Exception):
                cluster.close(timeout=10)
        if sys.exc_info()[0] is None:
            quiet.restore()
        # else (Ctrl-C, SIGTERM, a lost scheduler) the process is ending: the half-closed connections'
        # records, logged until it has, stay off stderr too


class _QuietDistributed:
    """distributed's informational records stay off stderr while the batch runs, and all of its records
    while the client shuts down (they are tracebacks of a reconnection that no longer matters; gctr says
    what happened in one line), unless gctr logs at DEBUG level (``-vv``)."""

    NAMES = ("distributed", "tornado", "asyncio")  # asyncio: "Future exception was never retrieved" of a closed comm

    def __init__(self) -> None:
        self.saved: dict[str, int] = {}

    def start(self) -> None:
        """While the batch runs, distributed's informational messages stay off stderr (a lost scheduler
        makes its I/O thread log "Batched Comm Closed" with a traceback before gctr notices)."""
        self._raise_to(logging.WARNING)

    def close(self) -> None:
        self._raise_to(logging.CRITICAL + 1)

    def _raise_to(self, level: int) -> None:
        if logger.isEnabledFor(logging.DEBUG):
            return
        # dask's logging config gives some children their own level (distributed.client): set each one
        names = [n for n in list(logging.root.manager.loggerDict)
                 if any(n == p or n.startswith(p + ".") for p in self.NAMES)]
        for name in set(names) | set(self.NAMES):
            log = logging.getLogger(name)
            self.saved.setdefault(name, log.level)  # the level before gctr touched it
            if log.getEffectiveLevel() < level:
                log.setLevel(level)

    def restore(self) -> None:
        for name, level in self.saved.items():
            logging.getLogger(name).setLevel(level)
        self.saved.clear()


def _track_starts(starts: dict[str, tuple[float, str]], inflight: dict[Any, _InFlight]) -> None:
    """Start the clock of the in-flight tasks that announced their start (see :func:`run_task`).

    A task that starts again (rescheduled after its worker was lost) gets a fresh clock.
    """
    for future, job in inflight.items():
        seen = starts.get(future.key)
        if seen is not None and (job.started is None or seen[0] > job.started):
            job.started, job.worker = seen


def _kill_local_worker(cluster: Any, worker: str) -> bool:
    """SIGKILL a worker process of our own LocalCluster (its nanny starts a fresh one). True if done."""
    import signal

    for nanny in list(getattr(cluster, "workers", {}).values()):
        if getattr(nanny, "worker_address", None) == worker and getattr(nanny, "pid", None):
            try:
                os.kill(nanny.pid, signal.SIGKILL)
            except OSError:
                return False
            return True
    return False


def _restart_worker(client: Any, worker: str, pair_id: str, closing: threading.Event) -> None:
    """Stop a timed-out pair for good: restart its worker through the nanny (best effort).

    Runs in a background thread; a batch that ends normally waits for it (at most
    ``RESTART_TIMEOUT_S``); one that is interrupted abandons it.
    """
    try:
        result = client.restart_workers([worker], timeout=RESTART_TIMEOUT_S, raise_for_error=False)
    except Exception as exc:  # noqa: BLE001
        if closing.is_set():
            return
        logger.warning("pair %s timed out; could not restart dask worker %s (%s): it keeps computing until the "
                       "pair ends", pair_id, worker, exc_message(exc))
        return
    status = result.get(worker) if isinstance(result, dict) else None
    if status not in (None, "OK"):
        logger.warning("pair %s timed out; restarting dask worker %s: %s", pair_id, worker, status)
