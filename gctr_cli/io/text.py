"""Text clouds: ``.xyz`` / ``.pts`` / ``.txt`` / ``.csv`` (reader and writer).

The first three columns are x y z (a header line that names them as other columns is an error:
:func:`_check_xyz_first`); leading header lines that are not numbers, a leading point-count
line (one number on its own) and ``#`` / ``//`` comment lines are skipped. Columns are separated by
blanks, tabs, commas or semicolons. Exports with decimal commas are read when the separator makes
them unambiguous (tabs or semicolons: ``1,5;2,25;3`` is x=1.5 y=2.25 z=3); the x y z cells alone
decide, so a later ``14.03.2024 10:15:00,000`` or ``Punkt 1, Gruppe A`` changes nothing. Decimal
commas separated by blanks (``1,5 2,25 3,0``) are refused with a message saying so, because they
cannot be told apart from comma-separated columns. Double-quoted cells of spreadsheet and pandas
exports are unquoted first (``"1.5","2.25"``; ``"1,5","2,25"`` is a quoted decimal comma, and a quoted
label with commas stays one cell: :func:`_unquoted`). The dialect is read off the first data line and
held to: a later line that does not fit it, or has an empty x/y/z cell, is an error naming the line,
never a silent shift of the columns. A leading point-count line that promises more points than
follow is an error (a truncated file); a count line further down starts the next section of a
multi-section PTS file (one section per scan).

The columns after x y z are read as float64 attributes when attributes are asked for (``gctr
apply``, ``--aligned``; a registration reads x y z only) and every data line has as many columns as
the first one, all numbers. Their names come from the last leading header or comment line (``# x y z
intensity red`` as gctr writes it, ``X Y Z R G B``, ``//X,Y,Z,Intensity``), else a ``.pts`` file's
Leica layout, else ``column_4`` ... (:func:`_attribute_names`). Otherwise x y z are read and one
warning names the first line that does not fit: columns are never dropped without a word.

Written (:func:`text_chunks`, :func:`csv_chunks`, :func:`pts_chunks`) as ``%.17g`` rows: ``.xyz`` / ``.txt``
with every numeric attribute after x y z, named in a ``# x y z name ...`` line; ``.csv`` the same
comma-separated under an ``x,y,z,name,...`` header line; ``.pts`` as the point count
and rows ``x y z [intensity] [red green blue]`` only, the layouts PTS readers know by their number of
columns (a comment line made Open3D read every point as (0, 0, 0)).

Read in blocks of whole lines (``np.loadtxt`` for plain numeric blocks), so memory follows the number
of points, not the size of the text: about 180 MB and 7 s for 2 million points. A line longer than
:data:`MAX_LINE` bytes (e.g. a 100 MB file without line ends) is an error, never a huge allocation.
"""

from __future__ import annotations

import io as _stdio
import itertools
import logging
import re
import warnings
from collections.abc import Iterable, Iterator
from pathlib import Path
from typing import Any

import numpy as np

from gctr_cli.io.cloud import ATTRIBUTE_NOTE, PointCloud, eight_bit_colours, integer_misfit
from gctr_cli.io.errors import PointCloudError, clean, quote
from gctr_cli.io.ply import format_column_blocks

logger = logging.getLogger("gctr_cli.io")

__all__ = ["csv_chunks", "pts_chunks", "read_text", "text_chunks"]

#: the first block of a text cloud is small (header detection runs line by line); later ones are large
_TEXT_FIRST_BLOCK = 1 << 16
_TEXT_BLOCK = 1 << 23
#: longest text line accepted (bytes)
MAX_LINE = 1 << 20
#: bytes that make a block take the line-by-line path: characters that ``str.splitlines`` or
#: ``str.split`` treat as line breaks or blanks but ``np.loadtxt`` may not, a lone ``\r``, comments
_TEXT_SLOW_BYTES = re.compile(rb"[\x0b\x0c\x1c-\x1f\x85\xa0#_]|//|\r(?!\n)")
#: the two byte translations, decided on the first data line: commas or semicolons between columns
#: (-> blanks; also for blank-separated files, whose lines may mix in commas); tabs or semicolons
#: between columns and decimal commas (commas -> points)
_PLAIN = bytes.maketrans(b",;", b"  ")
_DECIMAL_COMMA = bytes.maketrans(b",;", b". ")
_DEC_COMMA_TOKEN = re.compile(r"^[+-]?\d+,\d+(?:[eE][+-]?\d+)?$")
#: a line whose x, y or z cell is empty (two commas or semicolons in a row among the first three
#: columns), which the translation to blanks would otherwise close up, shifting the columns silently;
#: blanks and tabs, runs of which align columns, never make an empty cell
_EMPTY_CELL = {
    _PLAIN: r"^[ \t]*(?:[^,;\s]+[ \t]*[,;][ \t]*){0,2}[,;]",
    _DECIMAL_COMMA: r"^[ \t]*(?:[^;\s]+[ \t]*;[ \t]*){0,2};",
}
_EMPTY_CELL_TEXT = {table: re.compile(pattern) for table, pattern in _EMPTY_CELL.items()}
_EMPTY_CELL_BYTES = {table: re.compile(pattern.encode(), re.M) for table, pattern in _EMPTY_CELL.items()}
#: the quick test for a block: its separators as commas, blanks between them deleted (translation
#: and deletion), so that two separators in a row anywhere show as ",,"; only then the exact test
_SEPARATORS_AS_COMMAS = {_PLAIN: (bytes.maketrans(b";", b","), b" \t"),
                         _DECIMAL_COMMA: (bytes.maketrans(b",;", b".,"), b" \t")}
#: an empty cell anywhere in a line (two separators in a row), which would shift the later columns
_EMPTY_LATER_CELL = {_PLAIN: re.compile(r"[,;][ \t]*[,;]"), _DECIMAL_COMMA: re.compile(r";[ \t]*;")}
#: the short column names of exports, as gctr's attribute names
_NAME_ALIASES = {"r": "red", "g": "green", "b": "blue", "i": "intensity"}
#: the columns after x y z of a Leica PTS file without names, by its number of columns
_PTS_COLUMNS = {4: ["intensity"], 6: ["red", "green", "blue"], 7: ["intensity", "red", "green", "blue"]}
#: an attribute name every writer takes: a PLY/PCD field name and a LAS extra-bytes name (32 bytes)
_FIELD_NAME = re.compile(r"[a-z_][a-z0-9_]{0,31}")


#: a double-quoted cell of a spreadsheet or pandas export (``"1.5","2.25"``), within one line
_QUOTED_CELL = re.compile(rb'"([^"\r\n]*)"')
#: what :func:`_unquoted` turns blanks and separators inside a quoted text cell into
_IN_QUOTES = bytes.maketrans(b",; \t", b"____")


def _unquoted(block: bytes) -> bytes:
    """``block`` with its double-quoted cells unquoted: a number as the number (``"1,5"``, a decimal
    comma quoted in a comma-separated export, as ``1.5``), any other text with its blanks and
    separators as ``_``, so that it stays one cell (``"Scalar field"`` -> ``Scalar_field``,
    ``"Punkt 1, Gruppe A"`` one non-numeric cell, never three columns). A stray quote stays, and the
    line is then reported as having a non-numeric value."""
    if b'"' not in block:
        return block

    def plain(cell: re.Match[bytes]) -> bytes:
        text = cell.group(1).strip()
        if _DEC_COMMA_TOKEN.match(text.decode("latin-1")):
            return text.replace(b",", b".")
        return text.translate(_IN_QUOTES)

    return _QUOTED_CELL.sub(plain, block)


def _is_number(tok: str) -> bool:
    if "_" in tok:
        return False
    try:
        float(tok)
    except ValueError:
        return False
    return True


def _blocks(fh, path: Path) -> Iterator[bytes]:
    """The file in pieces that each end with a line end (except maybe the last): whole lines only.

    A file whose lines end in a lone ``\\r`` (classic Mac) is cut there. A line longer than
    :data:`MAX_LINE` bytes is an error, so memory stays bounded whatever the file holds.
    """
    carry = b""
    size = _TEXT_FIRST_BLOCK
    while True:
        chunk = fh.read(size)
        size = _TEXT_BLOCK
        if not chunk:
            if carry:
                yield carry
            return
        data = carry + chunk if carry else chunk
        cut = data.rfind(b"\n") + 1
        if cut == 0:  # a lone \r ends a line only when the next byte is known (no \r\n split)
            cut = data.rfind(b"\r", 0, len(data) - 1) + 1
        if cut == 0:  # no line end yet: keep reading, up to the line length cap
            if len(data) > MAX_LINE:
                raise PointCloudError(
                    f"{path}: a line is longer than {MAX_LINE // 1024} KiB (the file is not a text point cloud)"
                )
            carry = data
            continue
        carry = data[cut:]
        if len(carry) > MAX_LINE:
            raise PointCloudError(
                f"{path}: a line is longer than {MAX_LINE // 1024} KiB (the file is not a text point cloud)"
            )
        yield data[:cut] if carry else data


def _fast(block: bytes, table: bytes, blank_separated: bool, ncols: int | None = None) -> np.ndarray | None:
    """x y z of a block of plain numeric lines via numpy's C parser; None if the block needs the
    line-by-line path (comments, unusual separators, an empty cell, a comma in a blank-separated
    file, a bad line: that path gives the exact error). With ``ncols`` (attributes are read): all
    columns, and None unless every line has ``ncols`` numbers and no empty cell (that path then says
    why the columns after x y z are not kept)."""
    if _TEXT_SLOW_BYTES.search(block) or (blank_separated and b"," in block):
        return None
    if table in _SEPARATORS_AS_COMMAS:
        plain_csv = table == _PLAIN and not any(c in block for c in (b" ", b"\t", b";"))
        squeezed = block if plain_csv else block.translate(*_SEPARATORS_AS_COMMAS[table])  # a copy only if needed
        if (b",," in squeezed or b"\n," in squeezed or squeezed.startswith(b",")) \
                and (ncols or _EMPTY_CELL_BYTES[table].search(block)):  # an empty x, y or z, or any with ncols
            return None
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # "input contained no data" for blank blocks
        try:
            arr = np.loadtxt(
                _stdio.BytesIO(block.translate(table)), dtype=np.float64, comments=None,
                usecols=None if ncols else (0, 1, 2), ndmin=2, encoding="latin-1",
            )
        except ValueError:  # a bad value, or (all columns) a line with another number of columns
            return None
    if not ncols:
        return arr.reshape(-1, 3)
    if arr.size == 0:
        return np.empty((0, ncols))
    return arr if arr.shape[1] == ncols else None


def read_text(path: Path, fh, size: int, attributes: bool = True) -> PointCloud:  # noqa: ARG001
    """Text clouds, read in blocks of whole lines so that memory stays proportional to the points.

    With ``attributes``, the columns after x y z become float64 attributes (:func:`_attribute_names`)
    when every data line has as many columns as the first one, all numbers; else x y z are read and one
    warning names the first line that does not fit. Without, only x y z are parsed (registration)."""
    if b"\x00" in fh.read(4096):
        raise PointCloudError(f"{path}: not a text point cloud (binary data found)")
    fh.seek(0)
    parts: list[np.ndarray] = []
    extra_parts: list[np.ndarray] = []
    # extras: the columns after x y z are still being read; ncols: the first data line's columns;
    # names_line: the last leading header or comment line; extras_problem: why they are not kept
    state: dict[str, Any] = {"header": True, "seen_count_line": False, "table": _PLAIN, "count": None,
                             "blank": False, "extras": attributes, "ncols": 3, "names_line": None,
                             "extras_problem": None}
    lines_before = 0
    for k, block in enumerate(_blocks(fh, path)):
        if k == 0 and block.startswith(b"\xef\xbb\xbf"):  # UTF-8 byte order mark
            block = block[3:]
        block = _unquoted(block)
        ncols = state["ncols"] if state["extras"] else None
        arr = None if state["header"] else _fast(block, state["table"], state["blank"], ncols)
        if arr is not None:
            n_lines = block.count(b"\n") + (not block.endswith(b"\n"))
            arr, extras = (arr[:, :3], arr[:, 3:]) if ncols else (arr, None)
        else:
            arr, extras, n_lines = _block_lines(path, block, lines_before, state)
        parts.append(arr)
        if not state["extras"]:
            extra_parts.clear()
        elif extras is not None and len(extras):
            extra_parts.append(extras)
        lines_before += n_lines
    pts = np.concatenate(parts) if parts else np.empty((0, 3))
    if len(pts) == 0:
        raise PointCloudError(f"{path}: contains no points (no lines with numeric x y z columns)")
    if state.get("count") and state["count"][0] != len(pts):
        declared, lineno, sections = state["count"]
        what = f"line {lineno} declares" if sections == 1 else f"its {sections} point-count lines declare"
        if declared > len(pts):
            raise PointCloudError(f"{path}: {what} {declared} points but the file has {len(pts)} (truncated?)")
        logger.warning("%s: %s %d points but the file has %d (all %d read)", path, what, declared, len(pts),
                       len(pts))
    attrs: dict[str, np.ndarray] = {}
    if state["extras_problem"]:
        logger.warning("%s: columns after x y z are not kept: %s", clean(path), state["extras_problem"],
                       extra=ATTRIBUTE_NOTE)
    elif state["extras"] and state["ncols"] > 3:
        values = np.concatenate(extra_parts)
        names = _attribute_names(state["names_line"], state["ncols"], state["table"], path.suffix.lower() == ".pts")
        attrs = _whole_colours_as_bytes({name: np.ascontiguousarray(values[:, j]) for j, name in enumerate(names)})
    # a .pts intensity follows Leica's -2048..2047: a LAS writer shifts it into LAS's range
    return PointCloud(pts, attrs, "xyz", {"pts_intensity": True} if path.suffix.lower() == ".pts" else {})


def _whole_colours_as_bytes(attrs: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    """``red green blue`` columns of whole numbers 0..255 as uint8: colours, as the binary formats hold
    them, so that a LAS output widens them to its 16 bits (as floats they were written as 0..255 of
    65535: nearly black)."""
    rgb = ("red", "green", "blue")
    if all(k in attrs and integer_misfit(attrs[k], 0, 255) is None for k in rgb):
        return {**attrs, **{k: attrs[k].astype(np.uint8) for k in rgb}}
    return attrs


def _dialect(line: str, path: Path, lineno: int) -> bytes:
    """The byte translation for the file, decided on the x y z cells of its first data line.

    Tabs or semicolons between columns: commas are decimal commas unless the first three cells use
    them between columns too (a later ``1,5`` after a first line of whole numbers is then 1.5, and a
    later comma between columns is an error, never a silent split). Only x y z decide: a later cell
    such as ``14.03.2024 10:15:00,000`` or ``Punkt 1, Gruppe A`` made every comma a column separator
    and x y z wrong numbers. Commas between columns: commas and semicolons become blanks; the same
    for blanks between columns, where a later line may mix in commas (``1.5,2.5,3.5``) but not
    decimal commas (``1,5 2,5 3,5`` is an error, not six columns:
    :func:`_decimal_commas_between_blanks`)."""
    if ";" in line or "\t" in line:
        xyz = [f.strip() for f in re.split(r"[;\t]", line) if f.strip()][:3]
        if any("," in f and not _DEC_COMMA_TOKEN.match(f) for f in xyz):
            return _PLAIN
        return _DECIMAL_COMMA
    toks = line.split()
    if len(toks) >= 3 and all(_DEC_COMMA_TOKEN.match(t) for t in toks[:3]):
        raise PointCloudError(
            f"{path}: line {lineno}: values look like decimal commas separated by blanks "
            f"({quote(line, 40)}), which cannot be told apart from comma-separated columns; export with "
            "'.' as the decimal separator, or separate the columns with tabs or semicolons"
        )
    return _PLAIN


def _header_line(toks: list[str]) -> bool:
    """Whether a leading line of these words is a header to skip: it starts with a word, or has at most
    one number among its first three words ("X Y Z", "20 points", "1.0 ASCII export"). "0.1 0.2 0.x3"
    is a bad data line (reported as such), "20" alone a point-count line."""
    numbers = sum(_is_number(t) for t in toks[:3])
    return not _is_number(toks[0]) or (len(toks) > 1 and numbers < 2)


def _decimal_commas_between_blanks(line: str) -> bool:
    """Whether one of the first three blank-separated values of ``line`` looks like a decimal comma."""
    return any(_DEC_COMMA_TOKEN.match(t) for t in line.split(None, 3)[:3])


def _header_names(line: str, table: bytes, keep_empty: bool = False) -> list[str]:
    """The names of a header or comment line (``X Y Z R G B``, ``//X,Y,Z,R,G,B,Scalar field``,
    ``# x y z intensity``), split at the separators of the data (``;`` or tabs for decimal commas; else
    commas, semicolons or tabs when the line has any, blanks otherwise: ``Scalar field`` is one name).
    With ``keep_empty``, an empty cell stays as ``""`` (pandas' ``,x,y,z``: one name per column)."""
    text = line.lstrip("#/").strip()
    seps = r"[;\t]" if table == _DECIMAL_COMMA else r"[,;\t]"
    parts = re.split(seps, text) if re.search(seps, text) else text.split()
    return [p.strip() for p in parts if keep_empty or p.strip()]


def _check_xyz_first(path: Path, header: str | None, table: bytes, ncols: int) -> None:
    """Refuse a file whose header line names x, y and z as other columns than the first three (``id,x,y,z``,
    pandas' ``,x,y,z`` with its index first, ``z,y,x``): x y z are read from the first three columns, and
    such a file was read as the wrong cloud (a planar one, or a mirror image) without a word. Judged only
    when the header has one name per column of the first data line."""
    if not header:
        return
    names = [name.lower() for name in _header_names(header, table, keep_empty=True)]
    if len(names) != ncols or not all(names.count(axis) == 1 for axis in "xyz"):
        return
    where = [names.index(axis) for axis in "xyz"]
    if where == [0, 1, 2]:
        return
    hint = " (pandas: to_csv(..., index=False))" if names[0] == "" else ""
    raise PointCloudError(
        f"{path}: the header line {quote(header.strip(), 60)} names x, y and z as columns "
        f"{where[0] + 1}, {where[1] + 1} and {where[2] + 1}, but x y z are read from the first three columns; "
        f"write x y z first{hint}"
    )


def _attribute_names(header: str | None, ncols: int, table: bytes, pts: bool) -> list[str]:
    """The attribute names of columns 4..``ncols``.

    From the last leading header or comment line when it has exactly ``ncols`` names: lower case,
    blanks as ``_``, ``r g b`` (all three) as ``red green blue`` and ``i`` as ``intensity``; a name
    that is not a field name every writer takes (ASCII letters, digits and ``_``, not starting with a
    digit, at most 32 characters, not x y z) is ``column_N``, and so is every column when names
    repeat. Without such a line: a ``.pts`` file's columns by Leica's convention (4: intensity; 6: red
    green blue; 7: intensity red green blue), else ``column_4``, ``column_5`` ..."""
    numbered = [f"column_{j}" for j in range(4, ncols + 1)]
    names = _header_names(header, table) if header else []
    if len(names) != ncols:
        return list(_PTS_COLUMNS[ncols]) if pts and ncols in _PTS_COLUMNS else numbered
    lower = ["_".join(name.lower().split()) for name in names[3:]]
    aliases = _NAME_ALIASES if {"r", "g", "b"} <= set(lower) else {"i": "intensity"}  # "b" alone is no colour
    out = []
    for name, fallback in zip(lower, numbered, strict=True):
        name = aliases.get(name, name)
        out.append(name if _FIELD_NAME.fullmatch(name) and name not in ("x", "y", "z") else fallback)
    return out if len(set(out)) == len(out) else numbered


def _section_count(toks: list[str], state: dict) -> bool:
    """Whether a line of ``toks`` is the count line of the next section of a multi-section PTS file (one
    per scan, Leica) after a leading count line; its count is added to the declared points."""
    if len(toks) == 1 and state.get("count") and toks[0].isdigit():
        declared, lineno, sections = state["count"]
        state["count"] = (declared + int(toks[0]), lineno, sections + 1)
        return True
    return False


def _block_lines(path: Path, block: bytes, lines_before: int,
                 state: dict) -> tuple[np.ndarray, np.ndarray | None, int]:
    """x y z of a block, line by line; returns (points, the columns after x y z or None, number of
    lines of the block).

    Leading header lines of the file (``state["header"]``) are skipped: non-numeric lines, and one
    leading point-count line (a single number). ``#`` / ``//`` comment lines and blank lines are
    skipped anywhere; every other line needs at least three columns, the first three numeric. While
    ``state["extras"]``, the columns after x y z are read too; the first line with another number of
    columns than the first data line, an empty cell or a non-numeric value there ends that, and
    ``state["extras_problem"]`` says which line (columns None).
    """
    raw_lines = block.decode("latin-1").splitlines()

    def is_comment(s: str) -> bool:
        return not s or s.startswith("#") or s.startswith("//")

    start = 0
    if state["header"]:
        while start < len(raw_lines):
            s = raw_lines[start].strip()
            if is_comment(s):
                state["names_line"] = s or state["names_line"]
                start += 1
                continue
            table = _dialect(s, path, lines_before + start + 1)
            toks = s.encode("latin-1").translate(table).decode("latin-1").split()
            if not toks:  # only separators (an empty spreadsheet row): blank, as further down
                start += 1
                continue
            if _header_line(toks):
                state["names_line"] = s
                start += 1
                continue
            if len(toks) == 1 and not state["seen_count_line"]:
                state["seen_count_line"] = True
                value = float(toks[0])
                if value.is_integer() and value > 0:
                    state["count"] = (int(value), lines_before + start + 1, 1)
                start += 1
                continue
            if _section_count(toks, state):  # an empty first section: the first data line is further down
                start += 1
                continue
            state["header"] = False
            state["table"] = table
            state["blank"] = not any(c in s for c in ",;\t")
            state["ncols"] = len(toks)
            _check_xyz_first(path, state["names_line"], table, len(toks))
            break
    lines = block.translate(state["table"]).decode("latin-1").splitlines()

    def first_non_numeric(stop: int) -> None:
        """Raise for the first non-numeric x/y/z value before line index ``stop`` of the block."""
        for i in range(start, stop):
            s = lines[i].strip()
            if is_comment(s):
                continue
            for tok in s.split(None, 3)[:3]:
                if not _is_number(tok):
                    raise PointCloudError(f"{path}: line {lines_before + i + 1}: non-numeric value {quote(tok)}")

    empty_cell = _EMPTY_CELL_TEXT.get(state["table"])
    flat: list[str] = []
    add = flat.extend
    ncols = state["ncols"]
    collect = state["extras"] and not state["header"]  # the columns after x y z, while they fit
    empty_later = None if state["blank"] else _EMPTY_LATER_CELL[state["table"]]
    extra_rows: list[list[str]] = []
    extra_lines: list[int] = []
    for i in range(start, len(lines)):
        s = lines[i].strip()
        if is_comment(s):
            continue
        if state["blank"] and "," in raw_lines[i] and _decimal_commas_between_blanks(raw_lines[i]):
            first_non_numeric(i)
            raise PointCloudError(
                f"{path}: line {lines_before + i + 1}: values look like decimal commas separated by blanks "
                f"({quote(raw_lines[i].strip(), 40)}) in a file whose first point has none; export with '.' as "
                "the decimal separator"
            )
        if empty_cell and empty_cell.match(raw_lines[i].strip()):
            first_non_numeric(i)
            raise PointCloudError(
                f"{path}: line {lines_before + i + 1}: empty x, y or z value ({quote(raw_lines[i], 60)})"
            )
        toks = s.split() if collect else s.split(None, 3)
        if _section_count(toks, state):
            continue
        if len(toks) < 3:
            first_non_numeric(i)  # the first bad line of the file is the one reported
            raise PointCloudError(
                f"{path}: line {lines_before + i + 1} has {len(toks)} column(s), expected at least 3 (x y z)"
            )
        add(toks[:3])
        if collect:
            lineno = lines_before + i + 1
            if len(toks) != ncols:
                state["extras_problem"] = f"line {lineno} has {len(toks)} columns, the first data line {ncols}"
            elif empty_later and empty_later.search(raw_lines[i]):
                state["extras_problem"] = f"line {lineno} has an empty cell after x y z ({quote(raw_lines[i], 60)})"
            else:
                extra_rows.append(toks[3:])
                extra_lines.append(lineno)
            collect = not state["extras_problem"]
    if any("_" in t for t in flat):  # float() accepts 1_000; no point cloud writer does
        first_non_numeric(len(lines))
    try:
        values = np.fromiter(map(float, flat), dtype=np.float64, count=len(flat))
    except ValueError:
        first_non_numeric(len(lines))
        raise
    extras = _extra_values(extra_rows, extra_lines, ncols, state) if state["extras"] and not state["header"] else None
    return values.reshape(-1, 3), extras, len(raw_lines)


def _extra_values(rows: list[list[str]], linenos: list[int], ncols: int, state: dict) -> np.ndarray | None:
    """The columns after x y z of ``rows`` (read from lines ``linenos``, all before any line
    ``state["extras_problem"]`` names) as an ``(n, ncols - 3)`` float64 array. A non-numeric value
    comes first in the file, so its line replaces that problem; with a problem, ``state["extras"]``
    goes off and the result is None."""
    flat = [t for row in rows for t in row]
    try:
        if any("_" in t for t in flat):  # float() accepts 1_000; no point cloud writer does
            raise ValueError
        values = np.fromiter(map(float, flat), dtype=np.float64, count=len(flat))
    except ValueError:
        lineno, j, tok = next((n, j, t) for row, n in zip(rows, linenos, strict=True)
                              for j, t in enumerate(row) if not _is_number(t))
        state["extras_problem"] = f"line {lineno} has a non-numeric value {quote(tok)} in column {j + 4}"
    if state["extras_problem"]:
        state["extras"] = False
        return None
    return values.reshape(len(rows), max(ncols - 3, 0))


def _numeric_attributes(cloud: PointCloud) -> list[tuple[str, np.ndarray]]:
    """The attributes a text row can hold: one number per point."""
    n = len(cloud.points)
    return [(k, np.asarray(v)) for k, v in cloud.attributes.items()
            if np.asarray(v).shape == (n,) and np.asarray(v).dtype.kind in "fiu"]


def text_chunks(cloud: PointCloud) -> Iterable[bytes]:
    """Text rows ``x y z [attributes...]`` (``%.17g``, exact round trip) of an ``.xyz`` / ``.txt`` file;
    with attributes, a ``# x y z name ...`` comment line names the columns. In pieces, the rows formatted
    block by block as the file is written."""
    pts = np.asarray(cloud.points, dtype=np.float64)
    extra = _numeric_attributes(cloud)
    head = ""
    if extra:
        head += "# x y z " + " ".join("_".join(str(k).split()) for k, _ in extra) + "\n"
    return itertools.chain([head.encode("ascii")],
                           format_column_blocks([pts[:, 0], pts[:, 1], pts[:, 2]] + [v for _, v in extra]))


def csv_chunks(cloud: PointCloud) -> Iterable[bytes]:
    """A ``.csv`` file: a header line ``x,y,z,name,...`` and comma-separated rows (``%.17g``), with every
    numeric attribute after x y z (as :func:`text_chunks`), in pieces."""
    pts = np.asarray(cloud.points, dtype=np.float64)
    extra = _numeric_attributes(cloud)
    head = ",".join(["x", "y", "z"] + ["_".join(str(k).split()) for k, _ in extra]) + "\n"
    return itertools.chain([head.encode("ascii")],
                           format_column_blocks([pts[:, 0], pts[:, 1], pts[:, 2]] + [v for _, v in extra], ","))


def pts_chunks(cloud: PointCloud, path: Path | None = None) -> Iterable[bytes]:
    """A ``.pts`` file in pieces: the point count, then rows ``x y z [intensity] [red green blue]`` and nothing else.

    PTS has no comments and no names: readers know the columns by their number (Open3D takes 3, 4, 6
    or 7 and read a ``# x y z ...`` line as points (0, 0, 0), or no points at all). Colours are written
    when all three are whole numbers 0..255 (16-bit colours as their high byte), which Open3D reads
    with ``%d``; every other attribute is left out with one warning naming them (``path``)."""
    pts = np.asarray(cloud.points, dtype=np.float64)
    n = len(pts)
    attrs = eight_bit_colours({k: np.asarray(v) for k, v in cloud.attributes.items()})
    cols = [pts[:, 0], pts[:, 1], pts[:, 2]]
    written = []
    intensity = attrs.get("intensity")
    if intensity is not None and intensity.shape == (n,) and intensity.dtype.kind in "fiu":
        cols.append(intensity)
        written.append("intensity")
    rgb = [attrs.get(k) for k in ("red", "green", "blue")]
    if all(v is not None and v.shape == (n,) and v.dtype.kind in "fiu" and integer_misfit(v, 0, 255) is None
           for v in rgb):
        cols += [np.asarray(v).astype(np.uint8) for v in rgb]  # whole numbers: written as integers
        written += ["red", "green", "blue"]
    left_out = [str(k) for k in cloud.attributes if k not in written]
    if left_out:
        logger.warning("%s: attributes not written: %s (a .pts file holds x y z, intensity and red green blue "
                       "0..255 only); write .ply, .pcd or .las to keep them", clean(path or "PTS output"),
                       clean(", ".join(left_out)))
    return itertools.chain([f"{n}\n".encode("ascii")], format_column_blocks(cols))
