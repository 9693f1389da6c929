"""Batch registration: a manifest of pairs -> an executor -> streamed outputs (the orchestration).

:func:`run_batch` ties the batch modules together; each does one job:

* :mod:`gctr_cli.outcome` — the outcome record of one pair and its output rows;
* :mod:`gctr_cli.pair` — running one pair (all that ``gctr register`` loads);
* :mod:`gctr_cli.executors` — where the pairs run: :mod:`gctr_cli.pool` (local process pool) or
  :mod:`gctr_cli.dask_executor` (a dask.distributed cluster);
* :mod:`gctr_cli.outdir` — the output folder: row logs, their repair, committing a pair;
* :mod:`gctr_cli.lock` — one writer per output folder;
* :mod:`gctr_cli.summary` — totals and median errors (and :mod:`gctr_cli.report`, the HTML page).

Imports run one way: cli -> batch -> executors -> pool/dask_executor -> pair -> engine/io, and
report -> summary -> outdir (checked by ``tests/test_layers.py``).

Guarantees (see the README, "what happens when..."):

* **Every pair gets a row.** Loading errors, invalid ground truth, exceptions in the engine, a worker
  that dies, pairs over ``batch.time_limit_s`` and outputs that cannot be written all give a
  ``failed`` row with a specific message; the batch goes on.
* **Nothing half-written**, **one writer per folder**: see :mod:`gctr_cli.outdir` and
  :mod:`gctr_cli.lock`. An interrupted run (kill, Ctrl-C, lost dask scheduler) keeps every finished
  pair; ``resume`` finishes it.
* **Reproducible.** Each pair's seed derives from the config seed and the pair id only
  (:func:`~gctr_cli.pair.derive_seed`), and workers run with one BLAS/OpenMP/Open3D thread, so results
  do not depend on the executor, the number of workers or the order of completion.

The names other code imports from here (columns, ``run_pair``, ``derive_seed``, ``summarize``, the
lock, the errors) are re-exported from their modules.
"""

from __future__ import annotations

import dataclasses
import logging
import os
import shutil
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

from gctr_cli.config import Config, config_to_yaml, flatten_dict
from gctr_cli.errors import BatchError, ExecutorLost, LockError
from gctr_cli.executors import EXECUTORS, check_executor, outcomes, register_ref
from gctr_cli.fsutil import THREAD_ENV_VARS, atomic_write
from gctr_cli.lock import LOCK_NAME, OutdirLock
from gctr_cli.manifest import pair_ids_problem
from gctr_cli.outcome import ERRORS_COLUMNS, MATRIX_COLUMNS, TRANSFORMS_COLUMNS, PairOutcome, exc_message
from gctr_cli.outdir import (
    ALIGNED_DIR,
    CONFIG_FILE,
    ERRORS_FILE,
    INPUTS_FILE,
    OUTPUT_NAMES,
    REPORT_FILE,
    SNAPSHOTS_DIR,
    TRANSFORMS_FILE,
    Outputs,
    batch_outputs,
    check_case_collisions,
    pair_inputs,
    prepare_outdir,
    record_inputs,
)
from gctr_cli.pair import RegisterFn, derive_seed, run_pair
from gctr_cli.summary import BatchSummary, summarize

logger = logging.getLogger(__name__)

__all__ = [
    "BatchError",
    "BatchSummary",
    "ERRORS_COLUMNS",
    "EXECUTORS",
    "ExecutorLost",
    "LOCK_NAME",
    "LockError",
    "MATRIX_COLUMNS",
    "OutdirLock",
    "PairOutcome",
    "THREAD_ENV_VARS",
    "TRANSFORMS_COLUMNS",
    "derive_seed",
    "flatten_dict",
    "resolve_workers",
    "run_batch",
    "run_pair",
    "summarize",
]


def _os_problem(exc: OSError) -> str:
    """``file: problem`` of an OS error while setting up the output folder (which of its files: a read-only
    transforms.csv and a full disk read alike without it), else its text."""
    problem = exc.strerror or exc_message(exc)
    name = exc.filename2 or exc.filename  # os.replace(a, b) and the like: b is the file being set up
    return f"{name}: {problem}" if exc.strerror and name else problem


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


def _check_pair_ids(pairs: Sequence[Any]) -> None:
    """The manifest reader checks these with line numbers; pairs built in code are checked here."""
    problem = pair_ids_problem(pairs, "it names files: matrices/<pair_id>.txt")
    if problem:
        raise BatchError(problem)


def check_inputs_not_overwritten(pairs: Sequence[Any], outdir: str | Path, snapshots: bool, write_aligned: bool,
                                 manifest: str | Path | None = None) -> None:
    """Raise :class:`BatchError` (nothing run) when the batch would overwrite one of its own inputs."""
    written = batch_outputs(outdir, pairs, snapshots, write_aligned)
    inputs = [(manifest, "it is the manifest")] if manifest is not None else []
    for p in pairs:
        inputs += [(p.source, f"pair {p.pair_id!r} reads it as its source"),
                   (p.target, f"pair {p.pair_id!r} reads it as its target"),
                   (p.gt, f"pair {p.pair_id!r} reads it as its ground truth")]
    for path, role in inputs:
        if path is not None and (what := written.get(Path(os.path.realpath(path)))):
            raise BatchError(f"{path}: {role}, but the batch writes {what} there; move the file or choose "
                             "another output folder (nothing was run)")


def _write_report(outdir: Path, summary: BatchSummary, config: Config) -> bool:
    """Write ``OUTDIR/report.html``; whether it was written. A problem is logged, never fails the batch. A
    report that cannot be written does not leave an earlier run's in its place: that one is out of date (the
    rows have changed)."""
    try:
        from gctr_cli.report import write_report

        write_report(outdir, summary=summary, config=config)
        return True
    except Exception as exc:
        path = outdir / REPORT_FILE
        try:
            path.unlink()
            removed = "; removed the earlier one, which is out of date"
        except FileNotFoundError:
            removed = ""
        except OSError:
            removed = "; the earlier one there is out of date"
        logger.warning("could not write %s: %s%s", path, exc_message(exc), removed)
        logger.debug("report failure", exc_info=True)
        return False


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
    write_aligned: bool = False,
    manifest: str | Path | None = None,
    retry_failed: bool = False,
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
    ``snapshots``: also write ``OUTDIR/snapshots/<pair_id>.png``. ``write_aligned``: also write each
    ok pair's source moved onto the target, ``OUTDIR/aligned/<pair_id>.<ext>`` (committed with the
    pair: if it cannot be written, the pair gets a failed row and no matrix). At the end ``OUTDIR/report.html``
    is written (the manifest's pairs, resumed ones included; rows of other pair ids listed apart), also when the
    run is stopped after recording pairs. Raises :class:`BatchError`
    (nothing run) when the output folder is in use or inconsistent, or the executor cannot start; and
    when the batch cannot go on (:class:`ExecutorLost`: the dask scheduler went away; or not even a
    failed row can be appended to ``transforms.csv``): the finished pairs are saved, ``resume`` goes on.
    Problems of single pairs never raise: they are failed rows. ``manifest``: the file the pairs came
    from, which the run must not overwrite either (nor any input of a pair: :class:`BatchError`).
    ``retry_failed`` (with ``resume``): also run again the pairs whose earlier row is failed (a time limit
    since raised, a worker killed for memory, a file whose permissions were fixed).
    """
    t0 = time.monotonic()
    outdir = Path(outdir)
    _check_pair_ids(pairs)
    check_inputs_not_overwritten(pairs, outdir, snapshots, write_aligned, manifest)
    check_executor(executor, scheduler)
    ref = register_ref(register_fn)
    n_workers = resolve_workers(workers, config)
    recorded = False  # this run recorded a pair, or finished: the paths it prints must exist

    def note(outcome: PairOutcome) -> None:
        nonlocal recorded
        recorded = True
        if on_outcome is not None:
            on_outcome(outcome)

    try:
        created = _missing_folders(outdir)
        outdir.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise BatchError(f"cannot create output folder {outdir}: {exc.strerror or exc}") from None
    try:
        lock = OutdirLock(outdir)
        try:
            lock.acquire()
        except OSError as exc:  # LockError (another batch) is not an OSError
            raise BatchError(f"cannot set up output folder {outdir}: {_os_problem(exc)}; nothing "
                             "was run") from exc
        try:
            summary = _run_locked(pairs, config, outdir, resume, n_workers, ref, executor, scheduler, snapshots,
                                  write_aligned, on_start, note, t0, retry_failed)
            recorded = True
            return summary
        finally:
            lock.release()
    finally:
        # The folders this run created, if it left nothing in them; after a run that recorded pairs,
        # the folders on the way to OUTDIR as written stay too (``new/../results`` keeps an empty
        # ``new``), or the paths the summary prints would not exist.
        if not recorded:
            for folder in created:
                _remove_if_empty(folder)


def _remove_if_empty(folder: Path) -> None:
    try:
        folder.rmdir()
    except OSError:
        pass  # not empty: the run (or someone else) left something in it; or gone already


def _missing_folders(outdir: Path) -> list[Path]:
    """The folders that creating ``outdir`` will create, deepest first: those on its real path
    (symbolic links and ``..`` resolved, as the system creates it), and those on the way to it as
    written (``new/../results`` creates ``new`` too)."""
    missing = []
    real = Path(os.path.realpath(outdir))
    for folder in (real, *real.parents):
        if folder.exists():
            break
        missing.append(folder)
    written = outdir if outdir.is_absolute() else Path.cwd() / outdir  # not normalised: new/.. passes new
    for i in range(1, len(written.parts)):
        prefix = Path(*written.parts[:i])
        if prefix.name in ("..", ".") or os.path.lexists(prefix):
            continue
        folder = Path(os.path.realpath(prefix))  # missing as written, but maybe reached another way
        if not os.path.lexists(folder) and folder not in missing:
            missing.append(folder)
    return sorted(missing, key=lambda folder: len(folder.parts), reverse=True)


def _run_locked(pairs: Sequence[Any], config: Config, outdir: Path, resume: bool, n_workers: int, ref: Any,
                executor: str, scheduler: str | None, snapshots: bool, write_aligned: bool,
                on_start: Callable[[int, int], None] | None, on_outcome: Callable[[PairOutcome], None] | None,
                t0: float, retry_failed: bool = False) -> BatchSummary:
    """:func:`run_batch` in its locked output folder. A run that stops before ``transforms.csv`` has a
    new row (a full disk while setting up, an executor that cannot start, Ctrl-C) leaves the folder as
    it was: what it created is removed and a ``transforms.csv`` it rewrote (``--resume``) is restored."""
    before: set[str] | None = None
    originals: dict[str, bytes] = {}
    n_run = 0
    outputs: Outputs | None = None
    setting_up = True
    stopped_with_rows = False
    n_resumed = 0
    try:
        before = set(os.listdir(outdir))
        # what setting up may rewrite
        rewritten = (TRANSFORMS_FILE, ERRORS_FILE, CONFIG_FILE, INPUTS_FILE) if resume else (CONFIG_FILE,)
        for name in rewritten:
            if (outdir / name).is_file():
                originals[name] = (outdir / name).read_bytes()
        check_case_collisions(outdir, (p.pair_id for p in pairs))
        inputs = pair_inputs(pairs)
        done = prepare_outdir(outdir, config, resume, inputs, batch_outputs(outdir, pairs, snapshots, write_aligned),
                              aligned_wanted=write_aligned, retry_failed=retry_failed)
        todo = [p for p in pairs if p.pair_id not in done]
        n_resumed = len(pairs) - len(todo)
        # transforms.csv first: it marks the folder as a gctr run's, so that a kill before the first pair
        # leaves a folder the next run accepts (prepare_outdir refuses one with outputs but no transforms.csv)
        outputs = Outputs(outdir, write_aligned=write_aligned)
        resolved = config.model_copy(update={"batch": config.batch.model_copy(update={"workers": n_workers})})
        atomic_write(outdir / CONFIG_FILE, config_to_yaml(resolved))
        record_inputs(outdir, inputs, kept=done)
        if snapshots:
            (outdir / SNAPSHOTS_DIR).mkdir(exist_ok=True)
        if write_aligned:
            (outdir / ALIGNED_DIR).mkdir(exist_ok=True)
        setting_up = False
        if n_resumed:
            logger.info("resuming: %d of %d pairs already done", n_resumed, len(pairs))
        if on_start is not None:
            on_start(len(todo), n_resumed)
        tasks = [(p, derive_seed(config.seed, p.pair_id)) for p in todo]
        if tasks:
            for outcome in outcomes(executor, tasks, config, n_workers, ref, scheduler=scheduler,
                                    snapshots=snapshots):
                outcome = outputs.commit(outcome)
                n_run += 1
                if on_outcome is not None:
                    on_outcome(outcome)
    except BaseException as exc:
        stopped_with_rows = outputs is not None and outputs.has_new_rows()
        if not stopped_with_rows:
            if outputs is not None:
                try:
                    outputs.close()
                except OSError:
                    pass
                outputs = None
            if before is not None:
                _undo_setup(outdir, before, originals)
            if setting_up and isinstance(exc, OSError):
                raise BatchError(f"cannot set up output folder {outdir}: {_os_problem(exc)}; nothing was run") from exc
        raise
    finally:
        if outputs is not None:
            outputs.close()
            if stopped_with_rows:  # stopped (Ctrl-C, SIGTERM, a lost scheduler): the report says so far
                try:
                    _summarize_and_report(pairs, outdir, config, t0, n_run, n_resumed)
                except Exception:  # the stop's own error is the one to raise
                    logger.warning("could not write %s of the pairs recorded so far", outdir / REPORT_FILE,
                                   exc_info=logger.isEnabledFor(logging.DEBUG))
    return _summarize_and_report(pairs, outdir, config, t0, n_run, n_resumed)


def _summarize_and_report(pairs: Sequence[Any], outdir: Path, config: Config, t0: float, n_run: int,
                          n_resumed: int) -> BatchSummary:
    """The summary of ``outdir`` for the manifest ``pairs``, after ``report.html`` is written of it."""
    summary = summarize(pairs, outdir, wall_time_s=time.monotonic() - t0, n_run=n_run, n_resumed=n_resumed)
    return dataclasses.replace(summary, report_written=_write_report(outdir, summary, config))


def _undo_setup(outdir: Path, before: set[str], originals: dict[str, bytes]) -> None:
    """Undo what a run that recorded no pair did to ``outdir``: remove the output files and folders
    it created (nothing else: a file someone else put there meanwhile stays) and put back the files
    it rewrote (``originals``, by name); best effort, never raises. The lock is left to its owner."""
    for name in sorted(OUTPUT_NAMES - before):
        path = outdir / name
        try:
            if path.is_dir():
                shutil.rmtree(path)  # created by this run: holds only what it wrote for its first pair
            elif path.exists():
                path.unlink()
        except OSError:
            logger.debug("cannot remove %s", path)
    for name, content in originals.items():
        path = outdir / name
        try:
            if not path.is_file() or path.read_bytes() != content:
                atomic_write(path, content)
        except OSError:
            logger.warning("%s: could not put back its content from before this run", path)
