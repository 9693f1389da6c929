"""The output folder of a batch: the row logs, their repair on ``--resume``, and committing one pair.

Layout (README, "Outputs"): ``transforms.csv`` (one row per pair, the commit log), ``tm_errors.csv``
(pairs with ground truth), ``matrices/<pair_id>.txt``, ``snapshots/<pair_id>.png`` (``--snapshots``),
``config.yaml`` (the resolved config), ``report.html`` (written by :mod:`gctr_cli.batch` at the end, or when
a run that recorded pairs is stopped), ``.gctr-inputs.csv`` (each pair's input paths and file stamps).

* **Nothing half-written.** Rows are appended with a single ``write`` of a complete line followed by
  ``fsync`` (:class:`RowLog`); matrices go to a temporary file that is renamed. A trailing partial
  line (left by a kill mid-write) is removed on ``--resume``.
* **Commit order.** Per pair: matrix file, snapshot, ``tm_errors.csv`` row, then the
  ``transforms.csv`` row (the commit). A pair is done when its ``transforms.csv`` row is there; on
  ``--resume`` error rows without a committed pair are dropped.
* **A pair whose outputs cannot be written does not end the batch.** Any exception while committing
  it (a file name the filesystem refuses, a matrix path that is a folder, a full disk, ...) undoes
  what was written for it and records it as a failed row (failure ``"output"``) naming the problem;
  ``--resume`` runs such pairs again.
  Only when even that row cannot be written does the batch stop (:class:`~gctr_cli.errors.BatchError`).
"""

from __future__ import annotations

import csv
import io as _stdio
import logging
import os
import tempfile
from collections.abc import Iterable, Sequence
from pathlib import Path
from typing import Any

from gctr_cli.config import Config, ConfigError, flatten_dict, load_config
from gctr_cli.errors import BatchError
from gctr_cli.fsutil import atomic_write
from gctr_cli.outcome import ERRORS_COLUMNS, TRANSFORMS_COLUMNS, PairOutcome, exc_message, failed_outcome

logger = logging.getLogger(__name__)

__all__ = [
    "CONFIG_FILE",
    "ERRORS_FILE",
    "INPUTS_FILE",
    "MATRICES_DIR",
    "Outputs",
    "REPORT_FILE",
    "RowLog",
    "SNAPSHOTS_DIR",
    "TRANSFORMS_FILE",
    "check_same_config",
    "batch_outputs",
    "file_stamp",
    "pair_inputs",
    "prepare_outdir",
    "read_rows",
    "record_inputs",
]

TRANSFORMS_FILE = "transforms.csv"
ERRORS_FILE = "tm_errors.csv"
MATRICES_DIR = "matrices"
ALIGNED_DIR = "aligned"
SNAPSHOTS_DIR = "snapshots"
REPORT_FILE = "report.html"
CONFIG_FILE = "config.yaml"
#: the inputs each pair id was run with (source, target, ground truth, as the manifest gave them), so that
#: ``--resume`` runs a pair again when its manifest entry has changed
INPUTS_FILE = ".gctr-inputs.csv"
INPUTS_COLUMNS = ("pair_id", "source", "target", "gt", "source_stamp", "target_stamp", "gt_stamp")
#: the columns of an inputs file written before the stamps (gctr 0.x of 2026-12-06), still read
_INPUTS_COLUMNS_WITHOUT_STAMPS = INPUTS_COLUMNS[:4]
#: every file and folder a batch writes into its output folder
OUTPUT_NAMES = frozenset({TRANSFORMS_FILE, ERRORS_FILE, MATRICES_DIR, ALIGNED_DIR, SNAPSHOTS_DIR, REPORT_FILE,
                          CONFIG_FILE, INPUTS_FILE})



def batch_outputs(outdir: str | Path, pairs: Sequence[Any], snapshots: bool, write_aligned: bool) -> dict[Path, str]:
    """Every file a batch of ``pairs`` into ``outdir`` may write, by its real path (links and ``..``
    resolved), with words for a message: an input file at one of them (a manifest named
    ``tm_errors.csv``, ground truth kept in ``OUTDIR/matrices/``) would be overwritten by the run it feeds."""
    out = Path(os.path.realpath(outdir))
    written = {out / name: name for name in (TRANSFORMS_FILE, ERRORS_FILE, REPORT_FILE, CONFIG_FILE)}
    for p in pairs:
        written[out / MATRICES_DIR / f"{p.pair_id}.txt"] = (f"{MATRICES_DIR}/{p.pair_id}.txt "
                                                           f"(the matrix of pair {p.pair_id!r})")
        if snapshots:
            written[out / SNAPSHOTS_DIR / f"{p.pair_id}.png"] = (f"{SNAPSHOTS_DIR}/{p.pair_id}.png "
                                                                f"(the snapshot of pair {p.pair_id!r})")
        if write_aligned:
            name = aligned_path(out, p.pair_id, p.source).name
            written[out / ALIGNED_DIR / name] = f"{ALIGNED_DIR}/{name} (the aligned cloud of pair {p.pair_id!r})"
    return written

#: start of the message of a pair whose outputs could not be written; ``--resume`` runs such pairs again
OUTPUT_FAILURE = "cannot write its outputs: "


def csv_line(fields: Iterable[str]) -> str:
    buf = _stdio.StringIO()
    csv.writer(buf, lineterminator="\n").writerow(list(fields))
    return buf.getvalue()


def fsync_dir(path: Path) -> None:
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


def truncate_partial_line(path: Path) -> bool:
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


class RowLog:
    """Append-only CSV: one ``write`` of a complete line, then ``fsync``, per row.

    A row whose write or fsync fails (an exception, not an interrupt) is cut off again (the file ends
    with a complete line), so the caller can record something else for the pair.
    """

    def __init__(self, path: Path, header: Sequence[str]) -> None:
        self.path = path
        self.fd = os.open(path, os.O_WRONLY | os.O_APPEND | os.O_CREAT, 0o644)
        if os.fstat(self.fd).st_size == 0:
            self.append(header)

    def size(self) -> int:
        return os.fstat(self.fd).st_size

    def append(self, fields: Iterable[str]) -> None:
        data = csv_line(fields).encode("utf-8")
        before = self.size()
        try:
            view = memoryview(data)
            while view:
                n = os.write(self.fd, view)
                view = view[n:]
            os.fsync(self.fd)
        except Exception:  # not on Ctrl-C/SIGTERM: a complete row stays, a torn one is cut on --resume
            self.truncate(before)
            raise

    def truncate(self, size: int) -> None:
        """Cut the file back to ``size`` bytes (best effort: the repair on ``--resume`` covers the rest)."""
        try:
            if self.size() > size:
                os.ftruncate(self.fd, size)
                os.fsync(self.fd)
        except OSError:
            logger.warning("%s: could not remove an incomplete row", self.path)

    def close(self) -> None:
        os.close(self.fd)


def read_rows(path: Path, header: Sequence[str]) -> list[dict[str, str]]:
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
            missing = [c for c in header if c not in got]
            if missing and [c for c in header if c not in missing] == got:
                raise BatchError(
                    f"{path} was written by an earlier gctr (no {', '.join(missing)} column); finish that run "
                    "with the gctr version that started it, or choose another output folder"
                )
            raise BatchError(
                f"{path} does not look like a gctr output (header {','.join(got)[:120]!r}); "
                "choose another output folder"
            )
        rows = []
        for row in reader:
            if not row:
                continue
            if len(row) != len(header):  # a line damaged after it was written (a torn last line is cut before)
                raise BatchError(
                    f"{path}: line {reader.line_num} has {len(row)} cells, expected {len(header)}: the file was "
                    "changed after gctr wrote it; repair or remove that line, or choose another output folder"
                )
            rows.append(dict(zip(header, row, strict=True)))
        return rows


def check_same_config(outdir: Path, config: Config) -> None:
    """On resume the engine/seed/success settings must match the ones the folder was started with."""
    path = outdir / CONFIG_FILE
    if not path.exists():
        if _has_data_rows(outdir / TRANSFORMS_FILE):  # deleted: nothing says what the rows were made with
            raise BatchError(f"cannot resume: {path}, the config the rows of {outdir / TRANSFORMS_FILE} were made "
                             "with, is missing, so this run's config cannot be checked against it: restore it "
                             "(or copy the config of that run there), or choose another output folder")
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


def _has_data_rows(path: Path) -> bool:
    """Whether the CSV file ``path`` exists and holds a line after its header."""
    try:
        with open(path, "rb") as fh:
            fh.readline()
            return bool(fh.readline().strip())
    except OSError:
        return False


def case_insensitive(folder: Path) -> bool:
    """Whether ``folder``'s filesystem treats names that differ only in case as one (macOS and Windows by
    default, many network shares): a probe file is created and looked up with its case swapped."""
    fd, name = tempfile.mkstemp(prefix=".gctr-case-probe-", dir=folder)
    os.close(fd)
    try:
        return os.path.exists(os.path.join(folder, os.path.basename(name).swapcase()))
    finally:
        os.unlink(name)


def check_case_collisions(outdir: Path, pair_ids: Iterable[str]) -> None:
    """Raise :class:`BatchError` when two pair ids differ only in case and ``outdir`` does not tell such
    names apart: their matrices (``matrices/A.txt``, ``matrices/a.txt``) would overwrite each other."""
    first: dict[str, str] = {}
    clashes = []
    for pid in pair_ids:
        other = first.setdefault(pid.lower(), pid)
        if other != pid:
            clashes.append((other, pid))
    if clashes and case_insensitive(outdir):  # probed once, and only when such ids occur
        other, pid = clashes[0]
        raise BatchError(f"pair ids {other!r} and {pid!r} differ only in case, and the filesystem of {outdir} "
                         f"does not tell such file names apart: {MATRICES_DIR}/{pid}.txt would overwrite "
                         f"{MATRICES_DIR}/{other}.txt; rename one of them (nothing was run)")


Inputs = dict[str, tuple[str, ...]]  # pair_id -> (source, target, ground truth or "", and their stamps)
_FILE_ROLES = (("source", "source"), ("target", "target"), ("gt", "ground truth"))


MISSING_STAMP = "missing"


def file_stamp(path: str | Path) -> str:
    """``size:mtime_ns`` of a file (``missing`` when it cannot be looked up), the test ``make`` and ``rsync``
    use for "changed since": a file rewritten in place gets another stamp. A path through a symbolic link
    adds ``:`` and the file it resolves to, so that a link pointed at another file of the same size and
    time counts as changed (inode numbers would tell that too, but some network shares renumber them on
    every mount, which would run every pair again)."""
    try:
        st = os.stat(path)
    except OSError:
        return MISSING_STAMP
    real = os.path.realpath(path)
    return f"{st.st_size}:{st.st_mtime_ns}" + (f":{real}" if real != os.path.abspath(path) else "")


def pair_inputs(pairs: Iterable[Any]) -> Inputs:
    """The inputs of each pair of a manifest, as :data:`INPUTS_FILE` records them: the three paths, then
    the :func:`file_stamp` of each (the ground truth's empty when there is none)."""
    inputs: Inputs = {}
    for p in pairs:
        paths = (str(p.source), str(p.target), "" if p.gt is None else str(p.gt))
        inputs[p.pair_id] = (*paths, *(file_stamp(path) if path else "" for path in paths))
    return inputs


def _read_inputs(path: Path) -> dict[str, dict[str, str]]:
    """The rows of :data:`INPUTS_FILE` by pair id; one written before the stamps has them empty."""
    if not path.exists():
        return {}
    with open(path, newline="", encoding="utf-8") as fh:
        header = next(csv.reader(fh), [])
    if tuple(header) == _INPUTS_COLUMNS_WITHOUT_STAMPS:
        rows = [r | {c: "" for c in INPUTS_COLUMNS[4:]} for r in read_rows(path, _INPUTS_COLUMNS_WITHOUT_STAMPS)]
    else:
        rows = read_rows(path, INPUTS_COLUMNS)
    return {r["pair_id"]: r for r in rows}


def record_inputs(outdir: Path, inputs: Inputs, kept: set[str] | None = None) -> None:
    """Record ``inputs`` in :data:`INPUTS_FILE` (atomically), keeping the entries of other pair ids (an
    earlier run with another manifest). A pair of ``kept`` (its earlier row stays) whose file is gone for
    now keeps the stamp that file had: moved back unchanged, it is the file its row was made of."""
    path = outdir / INPUTS_FILE
    recorded = _read_inputs(path)
    for pid, entry in inputs.items():
        row = dict(zip(INPUTS_COLUMNS, (pid, *entry), strict=True))
        before = recorded.get(pid, {}) if kept and pid in kept else {}
        for key, _ in _FILE_ROLES:
            if row[f"{key}_stamp"] == MISSING_STAMP and before.get(key) == row[key]:
                row[f"{key}_stamp"] = before.get(f"{key}_stamp") or MISSING_STAMP
        recorded[pid] = row
    atomic_write(path, csv_line(INPUTS_COLUMNS) + "".join(csv_line(r[c] for c in INPUTS_COLUMNS)
                                                          for r in recorded.values()))


def _changed_inputs(outdir: Path, rows: list[dict[str, str]], with_errors: set[str], inputs: Inputs,
                    aligned_wanted: bool) -> dict[str, str]:
    """The pairs of ``inputs`` with a row among ``rows`` that must run again, each with the reason: their
    source, target or ground truth is another file than the earlier run's, or the same file changed on
    disk since (another size or modification time; by :data:`INPUTS_FILE`; a folder written before it
    existed tells only the source and target, and, for an ``ok`` pair, whether it had ground truth:
    ``with_errors``, the pairs with a ``tm_errors.csv`` row), or the run now writes aligned clouds
    (``aligned_wanted``) and an ``ok`` pair has none."""
    recorded = _read_inputs(outdir / INPUTS_FILE)
    changed: dict[str, str] = {}
    for row in rows:
        pid = row["pair_id"]
        if pid not in inputs:
            continue
        now = dict(zip(INPUTS_COLUMNS[1:], inputs[pid], strict=True))
        before = recorded.get(pid, {"source": row["source"], "target": row["target"]})
        why = [f"{what} {before[key]} -> {now[key]}" for key, what in _FILE_ROLES[:2] if before[key] != now[key]]
        if "gt" in before and before["gt"] != now["gt"]:
            why.append(f"ground truth {before['gt'] or 'none'} -> {now['gt'] or 'none'}")
        elif "gt" not in before and row["status"] == "ok" and (pid in with_errors) != bool(now["gt"]):
            why.append("ground truth added" if now["gt"] else "ground truth removed")
        if not why:
            # the same paths: has a file changed on disk? Not known without a recorded stamp; a file gone
            # since keeps the earlier result (a batch that archives its inputs must not lose its rows)
            why = [f"{what} {now[key]} changed on disk" for key, what in _FILE_ROLES
                   if now[key] and before.get(f"{key}_stamp") and now[f"{key}_stamp"] != MISSING_STAMP
                   and before[f"{key}_stamp"] != now[f"{key}_stamp"]]
        gone = any(now[key] and now[f"{key}_stamp"] == MISSING_STAMP for key, _ in _FILE_ROLES)
        if (not why and aligned_wanted and row["status"] == "ok" and not gone  # (a file gone: the row stays)
                and not aligned_path(outdir, pid, now["source"]).exists()):
            why.append("no aligned cloud yet (--write-aligned)")
        if not why and row["status"] == "ok" and not gone and not (outdir / MATRICES_DIR / f"{pid}.txt").exists():
            why.append(f"its matrix {MATRICES_DIR}/{pid}.txt is missing")  # deleted since: made again
        if why:
            changed[pid] = "; ".join(why)
    return changed


def prepare_outdir(outdir: Path, config: Config, resume: bool, inputs: Inputs | None = None,
                   written: dict[Path, str] | None = None, aligned_wanted: bool = False,
                   retry_failed: bool = False) -> set[str]:
    """Make the folder consistent for appending; return the pair ids already committed. On ``resume``
    the rows of pairs whose outputs could not be written are dropped, so that they run again, and so
    are those whose inputs changed since (:func:`_changed_inputs`; only of pairs in ``inputs``, the
    batch's, when given: another manifest's rows stay), and with ``retry_failed`` every failed one.

    ``written`` (:func:`batch_outputs`): in a folder without ``transforms.csv`` (no gctr run started there)
    a file at one of these paths is someone else's, and :class:`BatchError` is raised rather than
    overwriting it."""
    transforms = outdir / TRANSFORMS_FILE
    errors = outdir / ERRORS_FILE
    if written and not os.path.lexists(transforms):
        # a folder in a file's place is not overwritten: writing there fails that pair (an "output" row)
        found = [(path, what) for path, what in written.items() if os.path.lexists(path) and not path.is_dir()]
        if found:
            path, what = found[0]
            path = outdir / path.relative_to(os.path.realpath(outdir))  # as OUTDIR was given, not resolved
            more = f" (and {len(found) - 1} more of its files)" if len(found) > 1 else ""
            raise BatchError(f"{path} already exists, but {outdir} holds no gctr run (no {TRANSFORMS_FILE}): the "
                             f"batch would overwrite it with {what}{more}; choose another output folder or move "
                             "the files away (nothing was run)")
    (outdir / MATRICES_DIR).mkdir(exist_ok=True)

    if not resume:
        # a file with only its header (a run stopped before its first pair, e.g. no dask scheduler) holds
        # nothing: start afresh; one with rows, or not written by gctr, is never overwritten
        if transforms.exists() and transforms.stat().st_size > 0 and (
            transforms.read_bytes()[:4096].count(b"\n") > 1 or read_rows(transforms, TRANSFORMS_COLUMNS)
        ):
            raise BatchError(
                f"{transforms} already exists: pass --resume to finish that run, or choose another output folder"
            )
        # nothing was committed: any tm_errors rows or recorded inputs are leftovers
        for path in (transforms, errors, outdir / INPUTS_FILE):
            if path.exists():
                path.unlink()
        return set()

    check_same_config(outdir, config)
    truncate_partial_line(transforms)
    truncate_partial_line(errors)
    rows = read_rows(transforms, TRANSFORMS_COLUMNS)

    def unwritten(row: dict[str, str]) -> bool:  # the folder's fault (a full disk, ...), not the pair's
        return (row["status"] == "failed" and (retry_failed or row["message"].startswith(OUTPUT_FAILURE))
                and (inputs is None or row["pair_id"] in inputs))

    kept_rows = [r for r in rows if not unwritten(r)]
    if len(kept_rows) < len(rows):  # run them again
        logger.info("%s: running again %d pairs %s", transforms, len(rows) - len(kept_rows),
                    "that failed (--retry-failed)" if retry_failed else "whose outputs could not be written")
    err_rows = read_rows(errors, ERRORS_COLUMNS)
    changed = (_changed_inputs(outdir, kept_rows, {r["pair_id"] for r in err_rows}, inputs, aligned_wanted)
               if inputs else {})
    if changed:
        shown = "; ".join(f"{pid} ({why})" for pid, why in list(changed.items())[:5])
        more = f"; and {len(changed) - 5} more" if len(changed) > 5 else ""
        many = len(changed) > 1
        logger.warning("resuming: %d %s done by the earlier run %s run again: %s%s", len(changed),
                       "pairs" if many else "pair", "are" if many else "is", shown, more)
        kept_rows = [r for r in kept_rows if r["pair_id"] not in changed]
    if len(kept_rows) < len(rows):
        rows = kept_rows
        atomic_write(transforms, csv_line(TRANSFORMS_COLUMNS)
                     + "".join(csv_line(r[c] for c in TRANSFORMS_COLUMNS) for r in rows))
    done = {r["pair_id"] for r in rows}
    # keep exactly one error row per committed pair (drop rows of pairs killed before their commit)
    kept: dict[str, dict[str, str]] = {}
    for r in err_rows:
        if r["pair_id"] in done:
            kept[r["pair_id"]] = r
    if len(kept) != len(err_rows):
        logger.info("%s: dropped %d rows of unfinished pairs", errors, len(err_rows) - len(kept))
        text = csv_line(ERRORS_COLUMNS) + "".join(csv_line(r[c] for c in ERRORS_COLUMNS) for r in kept.values())
        atomic_write(errors, text)
    return done


def aligned_path(outdir: Path, pair_id: str, source: str | Path) -> Path:
    """``OUTDIR/aligned/<pair_id>.<ext>``: the source's own format when gctr can write it (PLY, PCD,
    LAS/LAZ, XYZ/PTS/TXT), else PLY (e.g. for an E57 source)."""
    from gctr_cli.io import WRITE_EXTENSIONS

    ext = Path(source).suffix.lower()
    return outdir / ALIGNED_DIR / f"{pair_id}{ext if ext in WRITE_EXTENSIONS else '.ply'}"


def aligned_paths(outdir: Path, pair_id: str) -> list[Path]:
    """Every path :func:`aligned_path` can give ``pair_id``, whatever its source's format."""
    from gctr_cli.io import WRITE_EXTENSIONS

    return [outdir / ALIGNED_DIR / f"{pair_id}{ext}" for ext in sorted({*WRITE_EXTENSIONS, ".ply"})]


def _remove_stale(path: Path, pair_id: str) -> None:
    """Remove a file an earlier run wrote for ``pair_id`` that its new row must not stand beside; one that
    cannot be removed is named in a warning (it never fails the pair, let alone the batch)."""
    try:
        if path.is_file():
            path.unlink()
    except OSError as exc:
        logger.warning("pair %s: cannot remove %s of an earlier run, which does not belong to its new row: %s",
                       pair_id, path, exc_message(exc))


def _problem(exc: BaseException) -> str:
    """gctr's own errors name the file and the problem already; others get their type too."""
    return str(exc) if type(exc).__module__.startswith("gctr_cli") and str(exc) else exc_message(exc)


class Outputs:
    """The output files of a running batch; :meth:`commit` records one finished pair (see the module
    docstring for the order and what happens when writing fails)."""

    def __init__(self, outdir: Path, write_aligned: bool = False) -> None:
        self.outdir = outdir
        self.write_aligned = write_aligned
        self.transforms = RowLog(outdir / TRANSFORMS_FILE, TRANSFORMS_COLUMNS)
        self.rows_start = self.transforms.size()  # after the header, or after the rows of an earlier run
        try:
            self.errors = RowLog(outdir / ERRORS_FILE, ERRORS_COLUMNS)
        except BaseException:
            self.transforms.close()
            raise
        fsync_dir(outdir)

    def has_new_rows(self) -> bool:
        """Whether a pair has been recorded (its ``transforms.csv`` row written) since the files were opened."""
        try:
            return self.transforms.size() > self.rows_start
        except OSError:
            return True  # cannot tell: keep everything

    def commit(self, outcome: PairOutcome) -> PairOutcome:
        """Write the pair's files and rows; return the outcome as recorded (a failed ``"output"``
        outcome when its files could not be written). Raises :class:`BatchError` only when not even
        a failed row can be appended to ``transforms.csv``."""
        for w in outcome.warnings:
            logger.warning("pair %s: %s", outcome.pair_id, w)  # gctr's own are in the message too
        try:
            self._write(outcome)
        except Exception as exc:  # one pair's outputs must never end the batch
            logger.debug("pair %s: cannot write its outputs", outcome.pair_id, exc_info=True)
            failed = failed_outcome(
                outcome, outcome.seed, f"{OUTPUT_FAILURE}{_problem(exc)}", "output", outcome.runtime_s,
                fitness=outcome.fitness, inlier_rmse=outcome.inlier_rmse, confidence=outcome.confidence,
            )
            try:
                self._write(failed)
            except Exception as exc2:
                raise BatchError(
                    f"cannot record pair {outcome.pair_id!r} in {self.transforms.path}: {exc_message(exc2)}; the "
                    "pairs finished so far are saved: fix the problem, then rerun with --resume"
                ) from exc2
            outcome = failed
        if not outcome.ok:
            level = logging.WARNING if outcome.failure in ("worker", "timeout", "output") else logging.INFO
            logger.log(level, "pair %s failed: %s", outcome.pair_id, outcome.message)
        return outcome

    def _write(self, outcome: PairOutcome) -> None:
        """All files of one pair, or (on an exception) none of its rows and no matrix."""
        transforms_row = outcome.transforms_row  # formatted first: a bad value fails before any write
        errors_row = outcome.errors_row
        matrix = self.outdir / MATRICES_DIR / f"{outcome.pair_id}.txt"
        aligned = aligned_path(self.outdir, outcome.pair_id, outcome.source) if self.write_aligned else None
        errors_size = self.errors.size()
        # a row never stands beside a file of an earlier run of its pair id (one that --resume runs again
        # because its inputs changed): a failed row beside no matrix, and no aligned cloud or snapshot
        # that this run does not write (the source's format changed, no --write-aligned / --snapshots)
        stale = [] if outcome.transform is not None else [matrix]
        stale += [old for old in aligned_paths(self.outdir, outcome.pair_id)
                  if outcome.transform is None or old != aligned]
        if outcome.snapshot_png is None:
            stale.append(self.outdir / SNAPSHOTS_DIR / f"{outcome.pair_id}.png")
        for old in stale:
            _remove_stale(old, outcome.pair_id)
        try:
            if outcome.transform is not None:
                from gctr_cli.io import write_matrix

                write_matrix(matrix, outcome.transform)
                if aligned is not None:
                    from gctr_cli.io import write_aligned

                    write_aligned(outcome.source, outcome.transform, aligned, reread=True)
            if outcome.snapshot_png is not None:
                self._write_snapshot(outcome.pair_id, outcome.snapshot_png)
            if errors_row is not None:
                self.errors.append(errors_row)
            self.transforms.append(transforms_row)  # the commit
        except Exception:  # (an interrupt leaves what was written: --resume repairs or overwrites it)
            self.errors.truncate(errors_size)
            if outcome.transform is not None:
                for path in (matrix, aligned):
                    try:
                        if path is not None:
                            path.unlink()
                    except OSError:
                        pass
            raise

    def _write_snapshot(self, pair_id: str, png: bytes) -> None:
        try:
            from gctr_cli.snapshots import write_png

            write_png(self.outdir / SNAPSHOTS_DIR / f"{pair_id}.png", png)
        except Exception as exc:  # noqa: BLE001 - a snapshot never fails the pair
            logger.warning("pair %s: cannot write its snapshot: %s", pair_id, exc_message(exc))
            _remove_stale(self.outdir / SNAPSHOTS_DIR / f"{pair_id}.png", pair_id)  # an earlier run's picture

    def close(self) -> None:
        self.transforms.close()
        self.errors.close()
