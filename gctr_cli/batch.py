"""Batch registration: a manifest of pairs -> a pool of worker processes -> streamed CSV outputs.

This module knows nothing about the algorithm; it only calls a ``register(source, target, config,
seed)`` function (the GCTR engine by default) and turns whatever happens into one output row per pair.

Guarantees (see the README, "what happens when..."):

* **Every pair gets a row.** Loading errors, invalid ground truth, exceptions in the engine, a worker
  process that dies (segfault, out-of-memory kill) and pairs exceeding ``batch.time_limit_s`` all give
  a ``failed`` row with a specific message; the batch goes on with a fresh worker.
* **Nothing half-written.** Output rows are appended as pairs finish, each with a single ``write`` of a
  complete line followed by ``fsync``; matrices are written to a temporary file and renamed. A trailing
  partial line (impossible in practice, but cheap to check) is removed on start. ``transforms.csv`` is
  the commit log: a pair is done when its row is there; its ``tm_errors.csv`` row and matrix file are
  written *before* it, and on ``resume`` any error row without a committed pair is dropped.
* **Reproducible.** Each pair's seed derives from the config seed and the pair id only
  (:func:`derive_seed`), and workers run with one BLAS/OpenMP/Open3D thread, so results do not depend
  on the number of workers or on the order of completion.
* **One writer per folder.** ``OUTDIR/.gctr.lock`` refuses a second concurrent batch on the same folder;
  a lock left by a killed process is detected as stale and taken over.

Executors. The per-pair work (:func:`run_pair`) runs on an *executor*: a generator that takes the
``(spec, seed)`` tasks and yields one :class:`PairOutcome` per task, in completion order, turning any
fault of its workers into a failed outcome and cleaning up in ``finally``. ``"local"`` is the
crash-proof process pool of this module (:func:`_pool_outcomes`, the default); ``"dask"`` runs the same
tasks on a dask.distributed cluster (:mod:`gctr_cli.dask_executor`). :func:`run_batch` consumes either
with the same code, so the output files, the commit order, ``resume`` and the lock do not depend on the
executor. With ``snapshots=True`` the workers also render a PNG per pair (they have the clouds in
memory) and return it in the outcome; the batch process writes it to ``OUTDIR/snapshots/`` before the
pair's commit. Every batch ends by writing ``OUTDIR/report.html`` (:mod:`gctr_cli.report`).
"""

from __future__ import annotations

import csv
import hashlib
import importlib
import io as _stdio
import logging
import math
import multiprocessing
import os
import re
import signal
import socket
import statistics
import sys
import time
from collections import deque
from collections.abc import Callable, Iterable, Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass, field
from multiprocessing.connection import wait as _mp_wait
from pathlib import Path
from typing import Any

import numpy as np

from gctr_cli.config import Config, ConfigError, config_to_yaml, load_config
from gctr_cli.fsutil import THREAD_ENV_VARS, atomic_write

logger = logging.getLogger(__name__)

__all__ = [
    "BatchError",
    "BatchSummary",
    "ERRORS_COLUMNS",
    "EXECUTORS",
    "LOCK_NAME",
    "LockError",
    "OutdirLock",
    "PairOutcome",
    "TRANSFORMS_COLUMNS",
    "derive_seed",
    "resolve_workers",
    "run_batch",
    "run_pair",
    "summarize",
]

MATRIX_COLUMNS = tuple(f"m{i}{j}" for i in range(4) for j in range(4))
TRANSFORMS_COLUMNS = (
    ("pair_id", "source", "target", "status", "message", "scale")
    + MATRIX_COLUMNS
    + ("fitness", "inlier_rmse", "runtime_s", "seed")
)
ERRORS_COLUMNS = ("pair_id", "rot_err_deg", "trans_err", "trans_err_rel", "scale_err", "tm_err", "success")

TRANSFORMS_FILE = "transforms.csv"
ERRORS_FILE = "tm_errors.csv"
MATRICES_DIR = "matrices"
SNAPSHOTS_DIR = "snapshots"
REPORT_FILE = "report.html"
CONFIG_FILE = "config.yaml"
LOCK_NAME = ".gctr.lock"

#: executors :func:`run_batch` can run the pairs on
EXECUTORS = ("local", "dask")


RegisterFn = Callable[..., Any]


class BatchError(Exception):
    """The batch cannot start (output folder in use or inconsistent, bad arguments); nothing was run."""


class LockError(BatchError):
    """Another gctr batch holds the lock of the output folder."""


# ----------------------------------------------------------------------------------------------------
# Seeds
# ----------------------------------------------------------------------------------------------------


def derive_seed(base_seed: int, pair_id: str) -> int:
    """Seed of one pair: a stable hash (SHA-256) of the config seed and the pair id, in ``[0, 2**31)``.

    Independent of the process, the platform, ``PYTHONHASHSEED`` and the order in which pairs run.
    """
    digest = hashlib.sha256(f"{int(base_seed)}\x1f{pair_id}".encode("utf-8")).digest()
    return int.from_bytes(digest[:8], "big") % (2**31)


# ----------------------------------------------------------------------------------------------------
# One pair
# ----------------------------------------------------------------------------------------------------


def _fmt(x: float | None) -> str:
    """Full-precision text of a number (``repr``, round-trips exactly); empty for None."""
    return "" if x is None else repr(float(x))


def _one_line(message: str) -> str:
    """Messages go into one CSV cell on one physical line."""
    return re.sub(r"\s*[\r\n]+\s*", " | ", str(message).strip())


@dataclass(frozen=True)
class PairOutcome:
    """What happened to one pair; carries its ``transforms.csv`` and ``tm_errors.csv`` rows.

    ``failure`` says where a failed pair failed: ``"input"`` (a point cloud could not be used),
    ``"ground_truth"`` (the gt file is missing, malformed or not a similarity), ``"register"`` (the
    engine raised or reported failure), ``"worker"`` (the worker process died) or ``"timeout"``.
    ``transform`` is set only for ``ok`` pairs; ``errors``/``success`` only when the pair also has
    ground truth.
    """

    pair_id: str
    source: str
    target: str
    status: str
    message: str
    seed: int
    runtime_s: float
    transform: np.ndarray | None = None
    scale: float | None = None
    fitness: float | None = None
    inlier_rmse: float | None = None
    errors: Any = None  # gctr_cli.metrics.TransformErrors
    success: bool | None = None
    failure: str = ""
    warnings: tuple[str, ...] = ()
    #: PNG bytes of the pair's snapshot (``run_pair(..., snapshot=True)``); written by the batch process
    snapshot_png: bytes | None = field(default=None, repr=False, compare=False)

    @property
    def ok(self) -> bool:
        return self.status == "ok"

    @property
    def transforms_row(self) -> list[str]:
        cells = [""] * 16 if self.transform is None else [_fmt(v) for v in np.asarray(self.transform).ravel()]
        return [
            self.pair_id,
            self.source,
            self.target,
            self.status,
            _one_line(self.message),
            _fmt(self.scale) if self.transform is not None else "",
            *cells,
            _fmt(self.fitness),
            _fmt(self.inlier_rmse),
            _fmt(self.runtime_s),
            str(self.seed),
        ]

    @property
    def errors_row(self) -> list[str] | None:
        if self.errors is None or self.transform is None:
            return None
        e = self.errors
        return [
            self.pair_id,
            _fmt(e.rot_err_deg),
            _fmt(e.trans_err),
            _fmt(e.trans_err_rel),
            _fmt(e.scale_err),
            _fmt(e.tm_err),
            "true" if self.success else "false",
        ]


def _failed(spec: Any, seed: int, message: str, failure: str, runtime_s: float, **kw: Any) -> PairOutcome:
    return PairOutcome(
        pair_id=spec.pair_id,
        source=str(spec.source),
        target=str(spec.target),
        status="failed",
        message=message,
        seed=seed,
        runtime_s=runtime_s,
        failure=failure,
        **kw,
    )


def _default_register(config: Config) -> RegisterFn:
    from gctr_cli.methods import get_register_fn

    return get_register_fn(config.method)


def _exc_message(exc: BaseException) -> str:
    text = str(exc)
    return f"{type(exc).__name__}: {text}" if text else type(exc).__name__


#: logger of snapshot problems: reported as batch warnings, never in the pair's message
SNAPSHOT_LOGGER = "gctr_cli.snapshots"


def _name_files(message: str, spec: Any) -> str:
    """The engine names the clouds ``source``/``target`` (it sees arrays); a row names the files."""
    for role, path in (("source", spec.source), ("target", spec.target)):
        if message.startswith(f"{role}: "):
            return f"{role} {path}: {message[len(role) + 2:]}"
    return message


def run_pair(
    spec: Any,
    config: Config,
    register_fn: RegisterFn | None = None,
    *,
    seed: int | None = None,
    snapshot: bool = False,
) -> PairOutcome:
    """Register one pair and return its outcome; never raises for a problem of the pair itself.

    ``spec`` is a :class:`gctr_cli.manifest.PairSpec`. ``register_fn`` defaults to the GCTR engine's
    ``register``; ``seed`` defaults to :func:`derive_seed` of the config seed and the pair id.
    Loading errors give the loader's message (file and problem); ground-truth problems give
    ``ground truth <file>: <problem>``; any exception during registration gives ``Type: message``.
    The target diagonal for the relative translation error is the bounding-box diagonal of the loaded
    target cloud.

    ``snapshot=True`` also renders the pair's PNG snapshot (:mod:`gctr_cli.snapshots`; input only for
    a failed pair, nothing when neither cloud could be loaded) into ``outcome.snapshot_png``, after the
    clock of ``runtime_s`` stopped. A rendering problem is logged as a warning and never fails the pair.
    """
    clouds: dict[str, np.ndarray] = {}
    outcome = _run_pair(spec, config, register_fn, seed, clouds)
    if snapshot and outcome.failure == "input":
        _load_other_clouds(spec, clouds)
    if snapshot and clouds:
        try:
            from dataclasses import replace

            from gctr_cli.snapshots import snapshot_of_outcome

            png = snapshot_of_outcome(outcome, clouds.get("source"), clouds.get("target"))
            outcome = replace(outcome, snapshot_png=png)
        except Exception as exc:  # noqa: BLE001 - a snapshot must never fail the pair
            logging.getLogger(SNAPSHOT_LOGGER).warning("snapshot failed: %s", _exc_message(exc))
    return outcome


def _load_other_clouds(spec: Any, clouds: dict[str, np.ndarray]) -> None:
    """For the snapshot of a pair whose loading failed: load the clouds that were not tried, silently
    (the pair's row already names its problem; no new warning must change its message)."""
    from gctr_cli.io import load_point_cloud

    io_logger = logging.getLogger("gctr_cli.io")
    level = io_logger.level
    io_logger.setLevel(logging.ERROR)
    try:
        for role, path in (("source", spec.source), ("target", spec.target)):
            if role not in clouds:
                try:
                    clouds[role] = load_point_cloud(path)
                except Exception:  # noqa: BLE001
                    pass
    finally:
        io_logger.setLevel(level)


def _run_pair(spec: Any, config: Config, register_fn: RegisterFn | None, seed: int | None,
              clouds: dict[str, np.ndarray]) -> PairOutcome:
    """:func:`run_pair` without the snapshot; the loaded clouds are left in ``clouds``."""
    from gctr_cli.io import MatrixError, PointCloudError, load_point_cloud, read_matrix
    from gctr_cli.metrics import is_similarity, transform_errors

    t0 = time.perf_counter()
    if seed is None:
        seed = derive_seed(config.seed, spec.pair_id)

    def elapsed() -> float:
        return time.perf_counter() - t0

    # 1. point clouds
    for role, path in (("source", spec.source), ("target", spec.target)):
        try:
            clouds[role] = load_point_cloud(path)
        except PointCloudError as exc:
            return _failed(spec, seed, str(exc), "input", elapsed())
        except Exception as exc:  # noqa: BLE001 - a loader bug must still name the file
            return _failed(spec, seed, f"{path}: {_exc_message(exc)}", "input", elapsed())
    source, target = clouds["source"], clouds["target"]

    # 2. ground truth (checked before the expensive part)
    T_gt = None
    if spec.gt is not None:
        try:
            T_gt = read_matrix(spec.gt)
            ok, reason = is_similarity(T_gt)
            if not ok:
                raise MatrixError(f"{spec.gt}: not a similarity transform: {reason}")
        except MatrixError as exc:
            return _failed(spec, seed, f"ground truth {exc}", "ground_truth", elapsed())
        except Exception as exc:  # noqa: BLE001
            return _failed(spec, seed, f"ground truth {spec.gt}: {_exc_message(exc)}", "ground_truth", elapsed())

    # 3. registration
    from gctr_cli.methods import method_config

    fn = register_fn if register_fn is not None else _default_register(config)
    try:
        result = fn(source, target, method_config(config), seed=seed)
    except Exception as exc:  # noqa: BLE001 - every problem becomes a failed row
        logger.debug("pair %s: register raised", spec.pair_id, exc_info=True)
        return _failed(spec, seed, _exc_message(exc), "register", elapsed())

    try:
        runtime = float(getattr(result, "runtime_s", float("nan")))
        if not math.isfinite(runtime):
            runtime = elapsed()
        fitness = float(result.fitness)
        rmse = float(result.inlier_rmse)
        if result.status != "ok":
            return _failed(
                spec, seed, _name_files(result.message or "registration failed", spec), "register", runtime,
                fitness=fitness, inlier_rmse=rmse,
            )
        T = np.array(result.transform, dtype=np.float64)
        ok, reason = is_similarity(T)
        if not ok:
            return _failed(
                spec, seed, f"engine returned an invalid transform: {reason}", "register", runtime,
                fitness=fitness, inlier_rmse=rmse,
            )
        errors = success = None
        if T_gt is not None:
            diagonal = float(np.linalg.norm(target.max(axis=0) - target.min(axis=0)))
            errors = transform_errors(T, T_gt, diagonal, source_centre=source.mean(axis=0))
            s = config.success
            success = errors.success(s.rotation_deg, s.translation_rel, s.scale)
        return PairOutcome(
            pair_id=spec.pair_id,
            source=str(spec.source),
            target=str(spec.target),
            status="ok",
            message=str(result.message or ""),
            seed=seed,
            runtime_s=runtime,
            transform=T,
            scale=float(result.scale),
            fitness=fitness,
            inlier_rmse=rmse,
            errors=errors,
            success=success,
        )
    except Exception as exc:  # noqa: BLE001 - a malformed result object
        return _failed(spec, seed, f"invalid registration result: {_exc_message(exc)}", "register", elapsed())


# ----------------------------------------------------------------------------------------------------
# Worker processes
# ----------------------------------------------------------------------------------------------------


def _register_ref(register_fn: RegisterFn | str | None) -> str | None:
    """A ``module:qualname`` reference that a freshly spawned worker can import."""
    if register_fn is None or isinstance(register_fn, str):
        if isinstance(register_fn, str):
            _resolve_ref(register_fn)  # fail early, in the parent
        return register_fn
    module = getattr(register_fn, "__module__", None)
    qualname = getattr(register_fn, "__qualname__", None)
    if not module or not qualname or "<" in qualname:
        raise BatchError(f"register_fn {register_fn!r} must be a module-level function (workers import it)")
    ref = f"{module}:{qualname}"
    try:
        resolved = _resolve_ref(ref)
    except Exception as exc:  # noqa: BLE001
        raise BatchError(f"register_fn {ref} cannot be imported: {exc}") from None
    if resolved is not register_fn:
        raise BatchError(f"register_fn {ref} is not importable under that name")
    return ref


def _resolve_ref(ref: str) -> RegisterFn:
    module, _, qualname = ref.partition(":")
    obj: Any = importlib.import_module(module)
    for part in qualname.split("."):
        obj = getattr(obj, part)
    return obj


def _limit_native_threads() -> None:
    """One thread for Open3D too (its RANSAC is not reproducible otherwise), if it is loaded."""
    o3d = sys.modules.get("open3d")
    if o3d is not None:
        try:
            o3d.utility.set_max_threads(1)
        except Exception:  # noqa: BLE001 - older Open3D without the call
            pass


def _set_parent_death_signal() -> None:
    """Linux: die with the parent (a SIGKILLed batch must not leave orphans computing)."""
    if not sys.platform.startswith("linux"):
        return
    try:
        import ctypes

        libc = ctypes.CDLL(None, use_errno=True)
        PR_SET_PDEATHSIG = 1
        libc.prctl(PR_SET_PDEATHSIG, signal.SIGKILL, 0, 0, 0)
    except Exception:  # noqa: BLE001
        pass


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
                 snapshots: bool = False) -> None:
    """Loop of one worker process.

    Receives ``(spec, seed)``; answers ``("start", None)`` when it begins the pair (the parent starts
    the pair's clock then, so import time does not count against the time limit) and
    ``("done", PairOutcome)`` when it is finished. ``None`` or a closed pipe ends the loop.
    """
    _set_parent_death_signal()
    if os.getppid() != parent_pid:  # parent died before prctl took effect
        os._exit(1)
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # Ctrl-C is the parent's business
    for var in THREAD_ENV_VARS:
        os.environ[var] = "1"
    try:  # keep the parent's stdout clean (native libraries print warnings there)
        sys.stdout.flush()
        os.dup2(2, 1)
    except OSError:
        pass

    handler = _ListHandler()
    root = logging.getLogger()
    root.addHandler(handler)
    root.setLevel(logging.WARNING)
    logging.captureWarnings(True)

    startup_error = None
    register_fn = None
    try:
        import gctr_cli.io  # noqa: F401 - load everything a pair needs before the first pair

        if snapshots:
            import gctr_cli.snapshots  # noqa: F401
            import matplotlib.backends.backend_agg  # noqa: F401
            import matplotlib.figure  # noqa: F401
        register_fn = _resolve_ref(register_ref) if register_ref else _default_register(config)
    except BaseException as exc:  # noqa: BLE001
        startup_error = f"worker start-up failed: {_exc_message(exc)}"
    _limit_native_threads()

    while True:
        try:
            task = conn.recv()
        except (EOFError, OSError):
            break
        if task is None:
            break
        spec, seed = task
        handler.records.clear()
        _limit_native_threads()
        try:
            conn.send(("start", None))
            if startup_error is not None:
                outcome = _failed(spec, seed, startup_error, "worker", 0.0)
            else:
                outcome = run_pair(spec, config, register_fn, seed=seed, snapshot=snapshots)
            if handler.records:
                outcome = _with_warnings(outcome, handler.records)
            try:
                conn.send(("done", outcome))
            except (BrokenPipeError, OSError):
                raise
            except Exception as exc:  # noqa: BLE001 - an outcome that does not pickle
                conn.send(("done", _failed(spec, seed, f"cannot return the result: {_exc_message(exc)}", "worker",
                                           outcome.runtime_s)))
        except (BrokenPipeError, OSError):
            break
    conn.close()


def _with_warnings(outcome: PairOutcome, records: list[tuple[str, str]]) -> PairOutcome:
    """Attach warnings; gctr's own (e.g. "dropped 5 non-finite points") also go into the message."""
    from dataclasses import replace

    ours = [msg for name, msg in records if name.startswith("gctr_cli") and name != SNAPSHOT_LOGGER]
    message = "; ".join([m for m in [outcome.message] if m] + [f"warning: {m}" for m in ours])
    return replace(outcome, warnings=tuple(msg for _, msg in records), message=message)


@contextmanager
def _single_thread_env() -> Iterator[None]:
    """Temporarily set the thread-count variables so a spawned child sees them before numpy loads."""
    saved = {var: os.environ.get(var) for var in THREAD_ENV_VARS}
    try:
        for var in THREAD_ENV_VARS:
            os.environ[var] = "1"
        yield
    finally:
        for var, value in saved.items():
            if value is None:
                os.environ.pop(var, None)
            else:
                os.environ[var] = value


class _Worker:
    """One long-lived worker process, fed one pair at a time through a pipe."""

    def __init__(self, ctx: Any, config: Config, register_ref: str | None, snapshots: bool = False) -> None:
        self.conn, child_conn = ctx.Pipe(duplex=True)
        self.process = ctx.Process(
            target=_worker_main,
            args=(child_conn, config, register_ref, os.getpid(), snapshots),
            name="gctr-worker",
            daemon=True,
        )
        with _single_thread_env():
            self.process.start()
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
        if self.process.is_alive():
            self.process.kill()
        self.process.join(timeout=5)
        self.conn.close()

    def stop(self) -> None:
        try:
            self.conn.send(None)
        except (OSError, ValueError):
            pass


def _pool_outcomes(
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
    pending: deque[tuple[Any, int]] = deque(tasks)
    workers: list[_Worker] = []
    send_retries: dict[str, int] = {}
    n_workers = max(1, min(n_workers, len(pending)))

    def retire(w: _Worker) -> None:
        w.kill()
        workers.remove(w)

    try:
        while pending or any(w.busy for w in workers):
            # feed idle workers (start them lazily, replace dead ones)
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
                        yield _failed(spec, seed, message, "worker", 0.0)

            busy = [w for w in workers if w.busy]
            if not busy:
                continue
            timeout = max(0.0, min(w.deadline(time_limit_s) for w in busy) - time.monotonic()) + 0.01
            _mp_wait([w.conn for w in busy] + [w.process.sentinel for w in busy], timeout=timeout)

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
                    broken = f"bad result from worker: {_exc_message(exc)}"
                if outcome is not None:
                    w.spec = None
                    yield outcome
                    continue
                runtime = w.runtime()
                if broken and broken != "eof":
                    retire(w)
                    yield _failed(spec, seed, broken, "worker", runtime)
                elif broken or not w.process.is_alive():
                    message = w.death_message()
                    retire(w)
                    yield _failed(spec, seed, message, "worker", runtime)
                elif time.monotonic() >= w.deadline(time_limit_s):
                    retire(w)  # kills the worker
                    if w.running_since is None:
                        message = f"worker did not start within {STARTUP_GRACE_S + time_limit_s:g} s"
                    else:
                        message = f"timed out after {time_limit_s:g} s"
                    yield _failed(spec, seed, message, "timeout", runtime)
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


# ----------------------------------------------------------------------------------------------------
# Output files
# ----------------------------------------------------------------------------------------------------


def _csv_line(fields: Iterable[str]) -> str:
    buf = _stdio.StringIO()
    csv.writer(buf, lineterminator="\n").writerow(list(fields))
    return buf.getvalue()


def _fsync_dir(path: Path) -> None:
    try:
        fd = os.open(path, os.O_RDONLY)
    except OSError:
        return
    try:
        os.fsync(fd)
    except OSError:
        pass
    finally:
        os.close(fd)


def _truncate_partial_line(path: Path) -> bool:
    """Remove a trailing line without its final newline (left by a crash mid-write). True if cut."""
    try:
        size = path.stat().st_size
    except FileNotFoundError:
        return False
    if size == 0:
        return False
    with open(path, "rb+") as fh:
        fh.seek(size - 1)
        if fh.read(1) == b"\n":
            return False
        pos = size
        keep = 0
        while pos > 0:
            step = min(65536, pos)
            pos -= step
            fh.seek(pos)
            chunk = fh.read(step)
            idx = chunk.rfind(b"\n")
            if idx >= 0:
                keep = pos + idx + 1
                break
        fh.truncate(keep)
        fh.flush()
        os.fsync(fh.fileno())
    logger.warning("%s: removed an incomplete last line (%d bytes) left by an interrupted run", path, size - keep)
    return True


class _RowLog:
    """Append-only CSV: one ``write`` of a complete line, then ``fsync``, per row."""

    def __init__(self, path: Path, header: Sequence[str]) -> None:
        self.path = path
        self.fd = os.open(path, os.O_WRONLY | os.O_APPEND | os.O_CREAT, 0o644)
        if os.fstat(self.fd).st_size == 0:
            self.append(header)

    def append(self, fields: Iterable[str]) -> None:
        data = _csv_line(fields).encode("utf-8")
        view = memoryview(data)
        while view:
            n = os.write(self.fd, view)
            view = view[n:]
        os.fsync(self.fd)

    def close(self) -> None:
        os.close(self.fd)


def _read_rows(path: Path, header: Sequence[str]) -> list[dict[str, str]]:
    """Rows of an output CSV whose header must be exactly ``header`` (empty/missing file: no rows)."""
    if not path.exists() or path.stat().st_size == 0:
        return []
    with open(path, newline="", encoding="utf-8") as fh:
        reader = csv.reader(fh)
        try:
            got = next(reader)
        except StopIteration:
            return []
        if tuple(got) != tuple(header):
            raise BatchError(
                f"{path} does not look like a gctr output (header {','.join(got)[:120]!r}); "
                "choose another output folder"
            )
        return [dict(zip(header, row)) for row in reader if row]


def flatten_dict(data: Any, prefix: str = "") -> dict[str, Any]:
    """Nested mapping -> ``{"a.b.c": value}`` (used to compare and fingerprint configs)."""
    if isinstance(data, dict):
        out: dict[str, Any] = {}
        for k, v in data.items():
            out.update(flatten_dict(v, f"{prefix}{k}."))
        return out
    return {prefix[:-1]: data}


def _check_same_config(outdir: Path, config: Config) -> None:
    """On resume the engine/seed/success settings must match the ones the folder was started with."""
    path = outdir / CONFIG_FILE
    if not path.exists():
        return
    try:
        old = load_config(path)
    except ConfigError as exc:
        raise BatchError(f"cannot resume: {exc}") from None
    a = flatten_dict(old.model_dump(mode="json", exclude={"batch"}))
    b = flatten_dict(config.model_dump(mode="json", exclude={"batch"}))
    diff = sorted(k for k in a.keys() | b.keys() if a.get(k) != b.get(k))
    if diff:
        shown = ", ".join(f"{k}: {a.get(k)!r} -> {b.get(k)!r}" for k in diff[:5])
        more = f" (and {len(diff) - 5} more)" if len(diff) > 5 else ""
        raise BatchError(
            f"cannot resume: the config differs from {path} ({shown}{more}); resume with "
            f"-c {path} or choose another output folder"
        )


# ----------------------------------------------------------------------------------------------------
# Lock file
# ----------------------------------------------------------------------------------------------------


def _proc_stat(pid: int) -> list[str] | None:
    """Fields of /proc/<pid>/stat from the state onwards (Linux), or None."""
    try:
        text = Path(f"/proc/{pid}/stat").read_text()
    except OSError:
        return None
    return text.rsplit(")", 1)[-1].split()


def _process_start_time(pid: int) -> str:
    fields = _proc_stat(pid)
    return fields[19] if fields and len(fields) > 19 else "?"


def _pid_alive(pid: int, start_time: str = "?") -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    except OSError:
        return False
    fields = _proc_stat(pid)
    if fields is not None:
        if fields[0] in ("Z", "X"):  # zombie: killed, not yet reaped
            return False
        if start_time != "?" and len(fields) > 19 and fields[19] != start_time:
            return False  # the pid was reused by another process
    return True


class OutdirLock:
    """``OUTDIR/.gctr.lock``: created with ``O_CREAT | O_EXCL``, holds ``pid start-time host``.

    A lock whose process no longer exists (on this host) is stale and taken over.
    """

    def __init__(self, outdir: Path) -> None:
        self.path = Path(outdir) / LOCK_NAME
        self.content = f"{os.getpid()} {_process_start_time(os.getpid())} {socket.gethostname()}\n"
        self.held = False

    def _holder(self) -> tuple[str, bool]:
        """(description, alive) of the current lock holder."""
        try:
            text = self.path.read_text()
            age = time.time() - self.path.stat().st_mtime
        except FileNotFoundError:
            return "", False
        except OSError as exc:
            return f"unreadable lock ({exc})", True
        parts = text.split()
        if not parts:
            # a lock being created right now has no content for a moment
            return "a process that is starting", age < 10
        try:
            pid = int(parts[0])
        except ValueError:
            return f"unparseable lock {text[:40]!r}", age < 10
        start = parts[1] if len(parts) > 1 else "?"
        host = parts[2] if len(parts) > 2 else socket.gethostname()
        if host != socket.gethostname():
            return f"pid {pid} on host {host}", True
        return f"pid {pid}", _pid_alive(pid, start)

    def acquire(self) -> None:
        for _ in range(5):
            try:
                fd = os.open(self.path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o644)
            except FileExistsError:
                who, alive = self._holder()
                if alive:
                    raise LockError(
                        f"another gctr batch ({who}) is writing to {self.path.parent}; wait for it to finish "
                        f"or choose another output folder (if no such batch is running, delete {self.path})"
                    ) from None
                self._break_stale(who)
                continue
            try:
                os.write(fd, self.content.encode())
                os.fsync(fd)
            finally:
                os.close(fd)
            self.held = True
            return
        raise LockError(f"could not acquire {self.path} (it keeps changing); is another batch starting?")

    def _break_stale(self, who: str) -> None:
        aside = self.path.with_name(f"{LOCK_NAME}.stale.{os.getpid()}")
        try:
            before = self.path.read_text()
            os.rename(self.path, aside)
        except FileNotFoundError:
            return
        try:
            if aside.read_text() != before:  # somebody replaced it meanwhile: put theirs back
                try:
                    os.link(aside, self.path)
                except FileExistsError:
                    pass
                return
            logger.warning("removed a stale lock %s left by %s (no longer running)", self.path, who)
        finally:
            try:
                aside.unlink()
            except FileNotFoundError:
                pass

    def release(self) -> None:
        if not self.held:
            return
        self.held = False
        try:
            if self.path.read_text() == self.content:
                self.path.unlink()
        except FileNotFoundError:
            pass

    def __enter__(self) -> "OutdirLock":
        self.acquire()
        return self

    def __exit__(self, *exc: Any) -> None:
        self.release()


# ----------------------------------------------------------------------------------------------------
# Summary
# ----------------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class BatchSummary:
    """Totals over all pairs of the manifest (including pairs finished by an earlier, resumed run).

    ``success_rate`` is over pairs with ground truth (a failed pair with gt counts as no success);
    ``None`` when no pair has ground truth. Medians are over the ``tm_errors.csv`` rows.
    """

    outdir: Path
    n_pairs: int
    n_ok: int
    n_failed: int
    n_run: int
    n_resumed: int
    n_gt: int
    n_success: int
    success_rate: float | None
    median_rot_err_deg: float | None
    median_trans_err: float | None
    median_trans_err_rel: float | None
    median_scale_err: float | None
    median_tm_err: float | None
    wall_time_s: float
    failures: tuple[tuple[str, str], ...] = field(default_factory=tuple)

    @property
    def all_ok(self) -> bool:
        return self.n_failed == 0


def _median(values: list[float]) -> float | None:
    values = [v for v in values if not math.isnan(v)]
    return float(statistics.median(values)) if values else None


def summarize(pairs: Sequence[Any], outdir: str | Path, *, wall_time_s: float = 0.0, n_run: int = 0,
              n_resumed: int = 0) -> BatchSummary:
    """Summarise the output files of ``outdir`` for the pairs of a manifest."""
    outdir = Path(outdir)
    rows = {r["pair_id"]: r for r in _read_rows(outdir / TRANSFORMS_FILE, TRANSFORMS_COLUMNS)}
    errs = {r["pair_id"]: r for r in _read_rows(outdir / ERRORS_FILE, ERRORS_COLUMNS)}
    n_ok = 0
    failures: list[tuple[str, str]] = []
    gt_ids = [p.pair_id for p in pairs if p.gt is not None]
    for p in pairs:
        row = rows.get(p.pair_id)
        if row is None:
            failures.append((p.pair_id, "no result recorded"))
        elif row["status"] == "ok":
            n_ok += 1
        else:
            failures.append((p.pair_id, row["message"]))
    err_rows = [errs[i] for i in gt_ids if i in errs and rows.get(i, {}).get("status") == "ok"]
    n_success = sum(r["success"] == "true" for r in err_rows)

    def med(key: str) -> float | None:
        return _median([float(r[key]) for r in err_rows])

    return BatchSummary(
        outdir=outdir,
        n_pairs=len(pairs),
        n_ok=n_ok,
        n_failed=len(failures),
        n_run=n_run,
        n_resumed=n_resumed,
        n_gt=len(gt_ids),
        n_success=n_success,
        success_rate=(n_success / len(gt_ids)) if gt_ids else None,
        median_rot_err_deg=med("rot_err_deg"),
        median_trans_err=med("trans_err"),
        median_trans_err_rel=med("trans_err_rel"),
        median_scale_err=med("scale_err"),
        median_tm_err=med("tm_err"),
        wall_time_s=wall_time_s,
        failures=tuple(failures),
    )


# ----------------------------------------------------------------------------------------------------
# The batch
# ----------------------------------------------------------------------------------------------------


def resolve_workers(requested: int | None, config: Config) -> int:
    """``requested`` (or ``config.batch.workers``); 0 means one per available core."""
    n = config.batch.workers if requested is None else int(requested)
    if n < 0:
        raise BatchError(f"number of workers must be >= 0, got {n}")
    if n == 0:
        try:
            n = len(os.sched_getaffinity(0))
        except (AttributeError, OSError):
            n = os.cpu_count() or 1
    return max(1, n)


_SAFE_ID = re.compile(r"^[^/\\\x00-\x1f]+$")


def _check_pair_ids(pairs: Sequence[Any]) -> None:
    seen: set[str] = set()
    for p in pairs:
        pid = p.pair_id
        if not pid or pid in (".", "..") or not _SAFE_ID.match(pid):
            raise BatchError(f"pair_id {pid!r} cannot be used as a file name (matrices/<pair_id>.txt)")
        if pid in seen:
            raise BatchError(f"duplicate pair_id {pid!r}")
        seen.add(pid)


def _prepare_outdir(outdir: Path, config: Config, resume: bool) -> set[str]:
    """Make the folder consistent for appending; return the pair ids already committed."""
    transforms = outdir / TRANSFORMS_FILE
    errors = outdir / ERRORS_FILE
    (outdir / MATRICES_DIR).mkdir(exist_ok=True)

    if not resume:
        # a file with only its header (a run stopped before its first pair, e.g. no dask scheduler) holds
        # nothing: start afresh; one with rows, or not written by gctr, is never overwritten
        if transforms.exists() and transforms.stat().st_size > 0 and (
            transforms.read_bytes()[:4096].count(b"\n") > 1 or _read_rows(transforms, TRANSFORMS_COLUMNS)
        ):
            raise BatchError(
                f"{transforms} already exists: pass --resume to finish that run, or choose another output folder"
            )
        # nothing was committed: any tm_errors rows are leftovers
        for path in (transforms, errors):
            if path.exists():
                path.unlink()
        return set()

    _check_same_config(outdir, config)
    _truncate_partial_line(transforms)
    _truncate_partial_line(errors)
    done = {r["pair_id"] for r in _read_rows(transforms, TRANSFORMS_COLUMNS)}
    # keep exactly one error row per committed pair (drop rows of pairs killed before their commit)
    err_rows = _read_rows(errors, ERRORS_COLUMNS)
    kept: dict[str, dict[str, str]] = {}
    for r in err_rows:
        if r["pair_id"] in done:
            kept[r["pair_id"]] = r
    if len(kept) != len(err_rows):
        logger.info("%s: dropped %d rows of unfinished pairs", errors, len(err_rows) - len(kept))
        text = _csv_line(ERRORS_COLUMNS) + "".join(_csv_line(r[c] for c in ERRORS_COLUMNS) for r in kept.values())
        atomic_write(errors, text)
    return done


def _check_executor(executor: str, scheduler: str | None) -> None:
    if executor not in EXECUTORS:
        raise BatchError(f"unknown executor {executor!r} (choose one of: {', '.join(EXECUTORS)})")
    if scheduler is not None and executor != "dask":
        raise BatchError("a scheduler address needs the dask executor (--executor dask)")
    if executor == "dask":
        from gctr_cli.dask_executor import check_available

        check_available()


def _outcomes(executor: str, tasks: Sequence[tuple[Any, int]], config: Config, n_workers: int,
              register_ref: str | None, *, scheduler: str | None, snapshots: bool) -> Iterator[PairOutcome]:
    """The outcomes of ``tasks`` from the chosen executor (see the module docstring)."""
    time_limit_s = config.batch.time_limit_s
    if executor == "dask":
        from gctr_cli.dask_executor import dask_outcomes

        return dask_outcomes(tasks, config, n_workers, register_ref, time_limit_s, scheduler=scheduler,
                             snapshots=snapshots)
    return _pool_outcomes(tasks, config, n_workers, register_ref, time_limit_s, snapshots=snapshots)


class _Outputs:
    """The output files of a running batch; :meth:`commit` records one finished pair.

    Order per pair: matrix file, snapshot, ``tm_errors.csv`` row, then the ``transforms.csv`` row (the
    commit). A kill between two steps leaves files that ``resume`` repairs or overwrites.
    """

    def __init__(self, outdir: Path) -> None:
        self.outdir = outdir
        self.transforms = _RowLog(outdir / TRANSFORMS_FILE, TRANSFORMS_COLUMNS)
        try:
            self.errors = _RowLog(outdir / ERRORS_FILE, ERRORS_COLUMNS)
        except BaseException:
            self.transforms.close()
            raise
        _fsync_dir(outdir)

    def commit(self, outcome: PairOutcome) -> None:
        from gctr_cli.io import write_matrix

        for w in outcome.warnings:
            logger.warning("pair %s: %s", outcome.pair_id, w)  # gctr's own are in the message too
        if outcome.transform is not None:
            write_matrix(self.outdir / MATRICES_DIR / f"{outcome.pair_id}.txt", outcome.transform)
        if outcome.snapshot_png is not None:
            try:
                from gctr_cli.snapshots import write_png

                write_png(self.outdir / SNAPSHOTS_DIR / f"{outcome.pair_id}.png", outcome.snapshot_png)
            except OSError as exc:
                logger.warning("pair %s: cannot write its snapshot: %s", outcome.pair_id, exc)
        row = outcome.errors_row
        if row is not None:
            self.errors.append(row)
        self.transforms.append(outcome.transforms_row)  # the commit
        if not outcome.ok:
            level = logging.WARNING if outcome.failure in ("worker", "timeout") else logging.INFO
            logger.log(level, "pair %s failed: %s", outcome.pair_id, outcome.message)

    def close(self) -> None:
        self.transforms.close()
        self.errors.close()


def _write_report(outdir: Path, summary: BatchSummary, config: Config) -> None:
    """``OUTDIR/report.html``; a problem is logged, never fails the batch."""
    try:
        from gctr_cli.report import write_report

        write_report(outdir, summary=summary, config=config)
    except Exception as exc:  # noqa: BLE001
        logger.warning("could not write %s: %s", outdir / REPORT_FILE, _exc_message(exc))
        logger.debug("report failure", exc_info=True)


def run_batch(
    pairs: Sequence[Any],
    config: Config,
    outdir: str | Path,
    *,
    workers: int | None = None,
    resume: bool = False,
    register_fn: RegisterFn | str | None = None,
    on_outcome: Callable[[PairOutcome], None] | None = None,
    on_start: Callable[[int, int], None] | None = None,
    executor: str = "local",
    scheduler: str | None = None,
    snapshots: bool = False,
) -> BatchSummary:
    """Register every pair of ``pairs`` (a manifest) and stream the outputs into ``outdir``.

    ``workers``: processes (``None``: ``config.batch.workers``; 0: one per core); with the dask
    executor and no ``scheduler``, the number of workers of the LocalCluster it starts. ``resume``:
    skip pairs already in ``transforms.csv``; without it an existing non-empty ``transforms.csv`` raises
    :class:`BatchError`. ``register_fn``: a module-level function (or ``"module:name"``) with the
    signature of :func:`gctr_cli.engine.register`; default: the GCTR engine. ``on_start(n_todo,
    n_done)`` is called once before the first pair, ``on_outcome`` after each pair is written (e.g.
    to advance a progress bar). ``executor``: ``"local"`` (process pool) or ``"dask"``
    (``scheduler``: address of a running dask scheduler; ``None`` starts a LocalCluster).
    ``snapshots``: also write ``OUTDIR/snapshots/<pair_id>.png``. At the end ``OUTDIR/report.html``
    is written (all rows of ``transforms.csv``, including resumed ones). Raises :class:`BatchError`
    (nothing run) when the output folder is in use or inconsistent, or the executor cannot start.
    """
    t0 = time.monotonic()
    outdir = Path(outdir)
    _check_pair_ids(pairs)
    _check_executor(executor, scheduler)
    register_ref = _register_ref(register_fn)
    n_workers = resolve_workers(workers, config)
    try:
        outdir.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise BatchError(f"cannot create output folder {outdir}: {exc.strerror or exc}") from None

    with OutdirLock(outdir):
        done = _prepare_outdir(outdir, config, resume)
        todo = [p for p in pairs if p.pair_id not in done]
        n_resumed = len(pairs) - len(todo)
        resolved = config.model_copy(update={"batch": config.batch.model_copy(update={"workers": n_workers})})
        atomic_write(outdir / CONFIG_FILE, config_to_yaml(resolved))
        if snapshots:
            (outdir / SNAPSHOTS_DIR).mkdir(exist_ok=True)
        if n_resumed:
            logger.info("resuming: %d of %d pairs already done", n_resumed, len(pairs))
        if on_start is not None:
            on_start(len(todo), n_resumed)

        tasks = [(p, derive_seed(config.seed, p.pair_id)) for p in todo]
        outputs = _Outputs(outdir)
        n_run = 0
        try:
            if tasks:
                for outcome in _outcomes(executor, tasks, config, n_workers, register_ref, scheduler=scheduler,
                                         snapshots=snapshots):
                    outputs.commit(outcome)
                    n_run += 1
                    if on_outcome is not None:
                        on_outcome(outcome)
        finally:
            outputs.close()

        summary = summarize(pairs, outdir, wall_time_s=time.monotonic() - t0, n_run=n_run, n_resumed=n_resumed)
        _write_report(outdir, summary, config)
        return summary
