"""Pair manifests: CSV files listing the (source, target[, ground truth]) pairs of a batch run.

Format (see GUIDE §1): a header row ``pair_id,source,target`` with an optional ``gt`` column; extra
columns are allowed and ignored; column names are matched case-insensitively after stripping
whitespace. Cells are stripped, blank lines are skipped, and relative paths are resolved against the
manifest's own folder. An empty ``gt`` cell means "no ground truth".

Structural problems are fatal (:class:`ManifestError`, naming the file and the line). Whether the
listed files exist is deliberately *not* checked here: the batch runner reports missing inputs per
pair so one bad row does not stop a batch.
"""

from __future__ import annotations

import csv
import io
import logging
import os
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

from gctr_cli.fsutil import atomic_write, write_error
from gctr_cli.io import SUPPORTED_EXTENSIONS

#: the extensions folder pairing takes as point clouds: every readable one but ``.csv``, which in a folder
#: of scans is far more often a table (a log, a manifest, gctr's own outputs) than a cloud; a ``.csv``
#: cloud is read when a manifest or the command line names it
FOLDER_EXTENSIONS = tuple(e for e in SUPPORTED_EXTENSIONS if e != ".csv")

__all__ = ["ManifestError", "PairSpec", "build_manifest", "read_manifest", "write_manifest"]

logger = logging.getLogger(__name__)

REQUIRED_COLUMNS = ("pair_id", "source", "target")
OPTIONAL_COLUMNS = ("gt",)
_MAX_LISTED = 20  # at most this many names / errors are spelled out in one message


class ManifestError(ValueError):
    """A manifest is missing, unreadable or structurally invalid."""


@dataclass(frozen=True)
class PairSpec:
    """One registration pair: ``source`` is mapped onto ``target``; ``gt`` is a 4x4 matrix file or None."""

    pair_id: str
    source: Path
    target: Path
    gt: Path | None = None


#: longest pair_id, in UTF-8 bytes: it names files (``matrices/<pair_id>.txt``, written through a temporary
#: ``.<pair_id>.txt.<pid>.<8 hex>.tmp`` of up to 226 bytes), and file names are limited to 255 bytes
MAX_PAIR_ID_BYTES = 200


def pair_id_problem(pair_id: str) -> str | None:
    """Return why ``pair_id`` cannot be used as a file name stem, or None if it is fine."""
    if not pair_id:
        return "is empty"
    n_bytes = len(pair_id.encode("utf-8", "surrogatepass"))
    if n_bytes > MAX_PAIR_ID_BYTES:
        return f"is too long ({n_bytes} bytes in UTF-8, at most {MAX_PAIR_ID_BYTES})"
    for bad, label in (("/", "'/'"), ("\\", "'\\'"), ("\x00", "NUL")):
        if bad in pair_id:
            return f"contains {label}"
    if pair_id in (".", ".."):  # a folder's name wherever a script makes one of it ('x..y' is a plain name)
        return f"is {pair_id!r}"
    if not _utf8(pair_id):
        return "is not valid UTF-8"
    if any(ord(c) < 32 or ord(c) == 127 for c in pair_id):
        return "contains a control character"
    if pair_id != pair_id.strip():  # a manifest's cells are stripped: ' a' would be read back as 'a'
        return "begins or ends with blank space"
    return None


def _utf8(text: str) -> bool:
    """Whether ``text`` (a name from the file system) is valid UTF-8: a Latin-1 ``café.ply`` of an old share
    comes as ``caf\\udce9.ply``, which no UTF-8 file (a manifest, transforms.csv) can hold."""
    try:
        text.encode("utf-8")
    except UnicodeEncodeError:
        return False
    return True


def shown_name(text: str) -> str:
    """``text`` for a message, its undecodable bytes as ``\\xe9`` (:func:`~gctr_cli.io.errors.escaped`)."""
    from gctr_cli.io.errors import escaped

    return escaped(text)


def _listing(items: Sequence[str]) -> str:
    shown = ", ".join(items[:_MAX_LISTED])
    return shown + (f", ... ({len(items) - _MAX_LISTED} more)" if len(items) > _MAX_LISTED else "")


def _absolute(p: Path) -> Path:
    """``p`` made absolute and normalised *without following symbolic links*: messages name the path
    the user wrote, a link keeps its own name (and extension), and a link loop cannot raise here."""
    return Path(os.path.normpath(os.path.abspath(p)))


def _resolve(cell: str, base: Path) -> Path:
    p = Path(cell).expanduser()
    if not p.is_absolute():
        p = base / p
    return _absolute(p)


def read_manifest(path: str | Path) -> list[PairSpec]:
    """Read and validate a pair manifest; return its pairs in file order with absolute paths.

    Raises :class:`ManifestError` for: a missing/unreadable/empty file, a missing required column,
    duplicate column names, an empty ``pair_id``/``source``/``target`` cell, a ``pair_id`` that is
    unsafe as a file name (``/``, ``\\``, NUL, ``.`` or ``..``, control characters, not UTF-8), a duplicate ``pair_id``,
    or a manifest without data rows. All row problems are reported together, with line numbers.
    """
    path = Path(path)
    if not path.exists():
        raise ManifestError(f"{path}: manifest does not exist")
    if not path.is_file():
        raise ManifestError(f"{path}: manifest is not a regular file")
    try:
        raw = path.read_bytes()
    except OSError as exc:
        raise ManifestError(f"{path}: cannot read manifest ({exc.strerror or exc})") from exc
    if not raw.strip():
        raise ManifestError(f"{path}: manifest is empty")
    try:
        text = raw.decode("utf-8-sig")
    except UnicodeDecodeError as exc:
        raise ManifestError(f"{path}: manifest is not UTF-8 text (bad byte at offset {exc.start})") from exc
    base = _absolute(path).parent

    reader = csv.reader(io.StringIO(text, newline=""))
    header: list[str] | None = None
    header_line = 0
    try:
        for row in reader:
            if any(c.strip() for c in row):
                header = [c.strip().lower() for c in row]
                header_line = reader.line_num
                break
        if header is None:  # pragma: no cover - guarded by the strip() check above
            raise ManifestError(f"{path}: manifest is empty")

        dupes = sorted({c for c in header if c and header.count(c) > 1})
        if dupes:
            raise ManifestError(f"{path}: line {header_line}: duplicate column name(s) {', '.join(dupes)}")
        for col in REQUIRED_COLUMNS:
            if col not in header:
                raise ManifestError(
                    f"{path}: line {header_line}: missing required column '{col}' "
                    f"(header must contain {','.join(REQUIRED_COLUMNS)}[,gt]; found {','.join(header)})"
                )
        idx = {c: header.index(c) for c in REQUIRED_COLUMNS + OPTIONAL_COLUMNS if c in header}

        pairs: list[PairSpec] = []
        errors: list[str] = []
        seen: dict[str, int] = {}
        end = header_line
        for row in reader:
            line, end = end + 1, reader.line_num  # a quoted cell may span lines: name the record's first
            if not any(c.strip() for c in row):
                continue
            cells = {c: (row[i].strip() if i < len(row) else "") for c, i in idx.items()}
            row_errors = [f"line {line}: empty '{c}' cell" for c in REQUIRED_COLUMNS if not cells[c]]
            pid = cells["pair_id"]
            if pid:
                problem = pair_id_problem(pid)
                if problem:
                    row_errors.append(f"line {line}: pair_id {pid!r} {problem} (unsafe as a file name)")
                elif pid in seen:
                    row_errors.append(f"line {line}: duplicate pair_id '{pid}' "
                                      f"(first on line {seen[pid]}, again on line {line})")
                else:
                    seen[pid] = line
            if row_errors:
                errors.extend(row_errors)
                continue
            gt_cell = cells.get("gt", "")
            spec = PairSpec(
                pair_id=pid,
                source=_resolve(cells["source"], base),
                target=_resolve(cells["target"], base),
                gt=_resolve(gt_cell, base) if gt_cell else None,
            )
            # the folder a relative path is resolved in may have a Latin-1 name, which no UTF-8 row can hold
            odd = [f"{c} {shown_name(str(v))}" for c, v in (("source", spec.source), ("target", spec.target),
                                                             ("gt", spec.gt)) if v is not None and not _utf8(str(v))]
            if odd:
                errors.append(f"line {line}: path not valid UTF-8 ({'; '.join(odd)}): gctr's CSV files are UTF-8 "
                              "text; rename the folder or file")
                continue
            pairs.append(spec)
    except csv.Error as exc:
        raise ManifestError(f"{path}: line {reader.line_num}: malformed CSV ({exc})") from exc

    if errors:
        more = f"; ... ({len(errors) - _MAX_LISTED} more)" if len(errors) > _MAX_LISTED else ""
        raise ManifestError(f"{path}: {len(errors)} problem(s): {'; '.join(errors[:_MAX_LISTED])}{more}")
    if not pairs:
        raise ManifestError(f"{path}: manifest has a header but no data rows")
    return pairs


def _format_path(p: Path, base: Path) -> str:
    p = Path(p)
    if not p.is_absolute():
        return p.as_posix()
    try:
        return _absolute(p).relative_to(base).as_posix()
    except ValueError:
        return str(p)


def pair_ids_problem(pairs: Sequence[PairSpec], unsafe_hint: str) -> str | None:
    """The first problem among the pair ids of ``pairs`` in words (an id unsafe as a file name, with
    ``unsafe_hint`` appended in brackets, or a duplicate), or None. For pairs built in code; the
    manifest reader reports the same problems with line numbers."""
    seen: set[str] = set()
    for p in pairs:
        problem = pair_id_problem(p.pair_id)
        if problem:
            return f"pair_id {p.pair_id!r} {problem} ({unsafe_hint})"
        if p.pair_id in seen:
            return f"duplicate pair_id {p.pair_id!r}"
        seen.add(p.pair_id)
    return None


def write_manifest(path: str | Path, pairs: Sequence[PairSpec], *, relative_to: Path | None = None) -> None:
    """Write ``pairs`` as a manifest CSV (header ``pair_id,source,target`` plus ``gt`` if any pair has one).

    Paths inside ``relative_to`` (default: the manifest's own folder, which is what
    :func:`read_manifest` resolves against) are written relative to it with ``/`` separators; other
    paths are written absolute. The file is written atomically; missing parent folders are created.
    Raises :class:`ManifestError` for an empty pair list, unsafe or duplicate pair ids.
    """
    path = Path(path)
    if not pairs:
        raise ManifestError(f"{path}: refusing to write a manifest without pairs")
    problem = pair_ids_problem(pairs, "unsafe as a file name")
    if problem:
        raise ManifestError(f"{path}: {problem}")

    base = Path(relative_to) if relative_to is not None else path.parent
    base = _absolute(base)
    with_gt = any(p.gt is not None for p in pairs)
    buf = io.StringIO(newline="")
    writer = csv.writer(buf, lineterminator="\n")
    writer.writerow(list(REQUIRED_COLUMNS) + (["gt"] if with_gt else []))
    for p in pairs:
        row = [p.pair_id, _format_path(p.source, base), _format_path(p.target, base)]
        if with_gt:
            row.append(_format_path(p.gt, base) if p.gt is not None else "")
        writer.writerow(row)

    try:
        atomic_write(path, buf.getvalue())
    except OSError as exc:
        raise ManifestError(f"{path}: cannot write manifest ({write_error(path, exc)})") from exc


def _cloud_files_by_stem(folder: Path, role: str) -> tuple[dict[str, Path], dict[str, list[Path]]]:
    """The point cloud files of ``folder`` by stem, and those of the stems held by several files (left out)."""
    found: dict[str, list[Path]] = {}
    not_utf8 = []
    not_files_named_like_clouds = []
    for f in sorted(folder.iterdir()):
        # a link counts whatever it points to (a DVC cache file without extension, or something
        # unreadable: the pair's row then says what is wrong with it)
        hidden_or_other = f.name.startswith(".") or f.suffix.lower() not in FOLDER_EXTENSIONS
        if hidden_or_other:
            continue
        if not (f.is_symlink() or f.is_file()):  # a folder, a FIFO, a socket: named below
            not_files_named_like_clouds.append(shown_name(f.name))
            continue
        if not _utf8(f.name):
            not_utf8.append(shown_name(f.name))
            continue
        found.setdefault(f.stem, []).append(f)
    if not_utf8:  # one odd name must not cost a nightly run its other pairs: left out, with a warning
        logger.warning("%s: %s folder has point cloud files whose names are not valid UTF-8, left out (rename "
                       "them: a manifest and gctr's CSV files are UTF-8 text): %s", shown_name(str(folder)), role,
                       _listing(not_utf8))
    if not_files_named_like_clouds:  # else the stem shows only as "unmatched" on the other side
        logger.warning("%s: %s folder has subfolders or other entries named like point cloud files, left out "
                       "(not files): %s",
                       shown_name(str(folder)), role, _listing(not_files_named_like_clouds))
    ambiguous = {s: fs for s, fs in found.items() if len(fs) > 1}
    if ambiguous:  # one such stem must not cost a nightly run its other pairs: left out, with a warning
        desc = _listing([f"{s} ({', '.join(f.name for f in fs)})" for s, fs in sorted(ambiguous.items())])
        logger.warning("%s: %s folder has several point cloud files with the same stem, left out (move or rename "
                       "one): %s", folder, role, desc)
    return {s: _absolute(fs[0]) for s, fs in found.items() if s not in ambiguous}, ambiguous


def _clouds(n: int) -> str:
    return f"{n} cloud" if n == 1 else f"{n} clouds"


def _csv_files(folder: Path) -> list[str]:
    """The visible ``.csv`` files of ``folder``, which folder pairing leaves out (:data:`FOLDER_EXTENSIONS`)."""
    return sorted(f.name for f in folder.iterdir() if f.suffix.lower() == ".csv" and not f.name.startswith(".")
                  and (f.is_symlink() or f.is_file()))


def _nested_clouds(folder: Path) -> list[str]:
    """The visible subfolders of ``folder`` that hold point cloud files themselves (not searched: a
    manifest pairs a folder's own files)."""
    nested = []
    for d in sorted(folder.iterdir()):
        if d.name.startswith(".") or not d.is_dir():
            continue
        try:
            if any(f.suffix.lower() in FOLDER_EXTENSIONS and not f.name.startswith(".") for f in d.iterdir()):
                nested.append(d.name + "/")
        except OSError:
            continue
    return nested


def _gt_files_by_stem(gt_dir: Path) -> dict[str, Path]:
    """The ground-truth files of ``gt_dir`` by stem: ``<stem>.txt``, the extension in any case (``a.TXT``,
    as clouds' extensions are). Of several for one stem (``a.txt`` beside ``a.TXT`` on a case-sensitive
    file system) the exact ``.txt`` is taken, else the first by name, and the others are named in a warning.
    Any entry counts, not only a regular file: a broken link or a folder named ``a.txt`` left out would
    leave pair ``a`` without ground truth, and a ``--min-success`` gate would pass it unmeasured; kept,
    the pair's row says what is wrong with it."""
    found: dict[str, Path] = {}
    ignored: list[str] = []
    entries = [f for f in gt_dir.iterdir() if f.suffix.lower() == ".txt" and not f.name.startswith(".")]
    # a regular file first (a broken link or a folder only where the stem has no file), then the exact ".txt"
    for f in sorted(entries, key=lambda f: (not f.is_file(), f.suffix != ".txt", f.name)):
        if f.stem in found:
            ignored.append(f"{f.name} (beside {found[f.stem].name})")
        else:
            found[f.stem] = f
    if ignored:
        logger.warning("%d ground-truth file(s) in %s ignored, their stem has one already: %s", len(ignored),
                       gt_dir, _listing(ignored))
    return found


def build_manifest(
    source_dir: str | Path, target_dir: str | Path, gt_dir: str | Path | None = None
) -> list[PairSpec]:
    """Pair the point clouds of two folders by file stem (``a.ply`` in source with ``a.pcd`` in target).

    Only files with a point-cloud extension are considered (:data:`FOLDER_EXTENSIONS`: not ``.csv``;
    hidden files are ignored); ``pair_id`` is the
    stem, and the ground truth is ``<gt_dir>/<stem>.txt`` (or ``.TXT``) when that file exists. Pairs are sorted by
    ``pair_id``. Stems present on one side only are logged as a warning; stems unsafe as a pair_id are
    skipped with a warning, and so are stems held by several clouds of one folder (``a.ply`` beside
    ``a.laz``). Raises :class:`ManifestError` if a folder is missing or no stem matches.
    """
    sdir, tdir = Path(source_dir), Path(target_dir)
    for d, role in ((sdir, "source"), (tdir, "target")) + (((Path(gt_dir), "ground-truth"),) if gt_dir else ()):
        if not d.is_dir():
            raise ManifestError(f"{d}: {role} folder does not exist" if not d.exists()
                                else f"{d}: {role} path is not a folder")
        if not _utf8(str(_absolute(d))):
            raise ManifestError(f"{shown_name(str(_absolute(d)))}: {role} folder's path is not valid UTF-8, which "
                                "a manifest (UTF-8 text) cannot hold: rename the folder")
    if os.path.realpath(sdir) == os.path.realpath(tdir):
        raise ManifestError(f"{sdir}: source and target folders are the same; every file would pair with itself")

    src, ambiguous_s = _cloud_files_by_stem(sdir, "source")
    tgt, ambiguous_t = _cloud_files_by_stem(tdir, "target")
    ambiguous = set(ambiguous_s) | set(ambiguous_t)  # left out on both sides (named once, as ambiguous)
    common = sorted((set(src) & set(tgt)) - ambiguous)
    only_src = sorted(set(src) - set(tgt) - ambiguous)
    only_tgt = sorted(set(tgt) - set(src) - ambiguous)
    if only_src or only_tgt:
        sides = [f"{len(only)} only in {d} [{_listing(only)}]" for only, d in ((only_src, sdir), (only_tgt, tdir))
                 if only]
        logger.warning("unmatched stems: %s", "; ".join(sides))
    nested = [f"{d}: {len(sub)} subfolder(s) with point clouds ({_listing(sub)})"
              for d in (sdir, tdir) if (sub := _nested_clouds(d))]
    hint = ""
    if nested:
        hint = "; subfolders are not searched: " + "; ".join(nested)
        logger.warning("only the folders' own files pair%s", hint)
    # .csv files are left out; said where it matters: when nothing pairs, or when one would have paired
    csv_s, csv_t = _csv_files(sdir), _csv_files(tdir)
    stems_s, stems_t = {Path(n).stem for n in csv_s}, {Path(n).stem for n in csv_t}
    would_pair = ((stems_s & (set(tgt) | stems_t)) | (stems_t & (set(src) | stems_s))) - (set(src) & set(tgt))
    why = "in a folder of scans they are usually tables; name .csv clouds in a manifest"
    if not (set(src) & set(tgt)) and (csv_s or csv_t):
        listed = "; ".join(f"{d}: {_listing(names)}" for d, names in ((sdir, csv_s), (tdir, csv_t)) if names)
        hint += f"; .csv files are left out ({why}): {listed}"
    elif would_pair:
        logger.warning("%d stem(s) would pair with .csv files, which are left out (%s): %s", len(would_pair), why,
                       _listing(sorted(would_pair)))
    unsafe = [s for s in common if pair_id_problem(s)]
    if unsafe:
        logger.warning("skipping %d stem(s) unsafe as pair_id: %s", len(unsafe),
                       _listing([f"{s!r} ({pair_id_problem(s)})" for s in unsafe]))
        common = [s for s in common if s not in unsafe]
    if ambiguous:
        hint += f"; left out as ambiguous (several files with one stem): {_listing(sorted(ambiguous))}"
    if not common:
        raise ManifestError(
            f"no matching file stems between {sdir} ({_clouds(len(src) + sum(map(len, ambiguous_s.values())))}) and "
            f"{tdir} ({_clouds(len(tgt) + sum(map(len, ambiguous_t.values())))}){hint}"
        )

    pairs = []
    missing_gt = []
    gts = _gt_files_by_stem(Path(gt_dir)) if gt_dir is not None else {}
    for stem in common:
        gt = None
        if gt_dir is not None:
            if stem in gts:
                gt = _absolute(gts[stem])
            else:
                missing_gt.append(stem)
        pairs.append(PairSpec(stem, src[stem], tgt[stem], gt))
    if missing_gt:
        logger.warning("%d pair(s) have no ground truth in %s: %s", len(missing_gt), gt_dir, _listing(missing_gt))
    if gt_dir is not None:
        paired = set(common)
        unused = sorted(shown_name(path.name) for stem, path in gts.items() if stem not in paired)
        if unused:
            logger.warning("%d ground-truth file(s) in %s match no pair: %s", len(unused), gt_dir, _listing(unused))
    return pairs
