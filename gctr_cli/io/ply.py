"""PLY: ASCII, binary little endian and binary big endian (reader and writer).

The ``vertex`` element must have scalar ``x``, ``y`` and ``z`` properties of any numeric type; its
other scalar properties (colours, intensity, normals ...) are kept as attributes; its list properties
are not (one warning names them). Other elements (faces, ``range_grid`` lists ...) are skipped,
wherever they are in the file.

Robustness rules: every element's declared size is checked against the bytes left in the file
before anything is allocated (ASCII: at least two bytes per value); ASCII elements are read one line
per instance with the declared number of values (a list line must hold exactly the items its length
announces); list lengths must be non-negative and fit in the file.
"""

from __future__ import annotations

import itertools
import logging
from collections.abc import Iterable, Iterator
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from gctr_cli.io.cloud import ATTRIBUTE_NOTE, PointCloud, eight_bit_colours, named_normals
from gctr_cli.io.errors import PointCloudError, clean, quote
from gctr_cli.io.lines import (
    LineReader,
    as_declared,
    binary_data,
    content_note,
    header_line,
    numeric_text,
    parse_float,
    read_rows,
)

__all__ = ["ply_bytes", "read_ply"]

logger = logging.getLogger("gctr_cli.io")

MAX_HEADER_BYTES = 1 << 20
MAX_HEADER_LINE = 1 << 16

PLY_TYPES = {
    "char": "i1", "int8": "i1",
    "uchar": "u1", "uint8": "u1",
    "short": "i2", "int16": "i2",
    "ushort": "u2", "uint16": "u2",
    "int": "i4", "int32": "i4",
    "uint": "u4", "uint32": "u4",
    "float": "f4", "float32": "f4",
    "double": "f8", "float64": "f8",
}  # fmt: skip
_TYPE_NAMES = {"i1": "char", "u1": "uchar", "i2": "short", "u2": "ushort", "i4": "int", "u4": "uint",
               "f4": "float", "f8": "double"}


@dataclass
class _Prop:
    name: str
    dtype: str  # numpy type code without byte order ("f4"); for lists: the item type
    count_dtype: str | None = None  # list length type, None for scalar properties
    declared: str = ""  # the type as the header writes it ("uchar", "uint8" ...)


@dataclass
class _Element:
    name: str
    count: int
    props: list[_Prop] = field(default_factory=list)

    @property
    def has_list(self) -> bool:
        return any(p.count_dtype is not None for p in self.props)

    def min_ascii_bytes(self) -> int:
        """Fewest bytes an ASCII instance can take: one digit and one separator per value."""
        return 2 * len(self.props)

    def min_binary_bytes(self) -> int:
        """Fewest bytes a binary instance can take (lists empty)."""
        return sum(np.dtype(p.count_dtype or p.dtype).itemsize for p in self.props)


def read_ply(path: Path, fh, size: int, attributes: bool = True) -> PointCloud:
    magic = fh.read(4)
    if not (magic[:3] == b"ply" and magic[3:4] in (b"\n", b"\r")):
        raise PointCloudError(f"{path}: not a PLY file (missing 'ply' magic{content_note(fh)})")
    if magic[3:4] == b"\r" and fh.read(1) != b"\n":
        raise PointCloudError(f"{path}: PLY header lines end in a carriage return only (classic Mac OS line ends); "
                              "PLY needs LF or CR LF line ends: convert them (an ASCII PLY with e.g. tr '\\r' '\\n'; "
                              "in a binary PLY only the header's)")
    fmt, elements, header_lines = _parse_header(fh, path)
    data_bytes = size - fh.tell()

    vidx = next((i for i, e in enumerate(elements) if e.name == "vertex"), None)
    if vidx is None:
        names = ", ".join(quote(e.name) for e in elements[:20]) or "none"
        raise PointCloudError(f"{path}: PLY header has no 'vertex' element (elements: {names})")
    vertex = elements[vidx]
    pnames = [p.name for p in vertex.props]
    for c in "xyz":
        if c not in pnames:
            missing = [m for m in "xyz" if m not in pnames]
            shown = " ".join(quote(n) for n in pnames[:20]) or "none"
            raise PointCloudError(
                f"{path}: PLY vertex element has no {'/'.join(missing)} field{'s' if len(missing) > 1 else ''} "
                f"(fields: {shown})"
            )
        if vertex.props[pnames.index(c)].count_dtype is not None:
            raise PointCloudError(f"{path}: PLY vertex property '{c}' is a list, expected a scalar")

    if fmt != "ascii" and numeric_text(fh):
        raise PointCloudError(f"{path}: the PLY header says {fmt} but the data is numbers written as text "
                              "(write 'format ascii 1.0' in the header)")
    if fmt == "ascii" and binary_data(fh):
        raise PointCloudError(f"{path}: the PLY header says ascii but the data is binary (write 'format "
                              "binary_little_endian 1.0' in the header, or 'binary_big_endian' for big-endian data)")
    # every declared size up to the vertex element must fit in the file before anything is allocated
    need = 0
    for el in elements[: vidx + 1]:
        per = el.min_ascii_bytes() if fmt == "ascii" else el.min_binary_bytes()
        need += el.count * per
        if need > data_bytes:
            unit = "at least 2 bytes per value" if fmt == "ascii" else f"at least {per} bytes each"
            raise PointCloudError(
                f"{path}: truncated or corrupt: the header declares {el.count} {_plural(el.name)} "
                f"({unit}) but only {data_bytes} bytes follow the header"
            )

    if fmt == "ascii":
        table = _read_ascii(path, fh, elements, vidx, header_lines)
    else:
        table = _read_binary(path, fh.read(), elements, vidx, "<" if fmt == "binary_little_endian" else ">")
    pts = np.empty((vertex.count, 3), dtype=np.float64)
    for j, c in enumerate("xyz"):
        pts[:, j] = table[c]
    attrs = {}
    if attributes and (lists := [quote(p.name) for p in vertex.props if p.count_dtype is not None]):
        logger.warning("%s: vertex list %s %s not kept (gctr keeps one value per vertex and property)", clean(path),
                       "properties" if len(lists) > 1 else "property", ", ".join(lists), extra=ATTRIBUTE_NOTE)
    if attributes:
        for p in vertex.props:
            if p.count_dtype is None and p.name not in ("x", "y", "z") and p.name in table:
                column = np.ascontiguousarray(table[p.name])
                # binary values were decoded from their declared type; text may hold what it cannot
                attrs[p.name] = (as_declared(path, p.name, p.declared, column, np.dtype(p.dtype)) if fmt == "ascii"
                                 else column.astype(p.dtype))
    return PointCloud(pts, attrs, "ply")


def _parse_header(fh, path: Path) -> tuple[str, list[_Element], int]:
    fmt: str | None = None
    elements: list[_Element] = []
    lineno = 1
    consumed = 4
    while True:
        raw = fh.readline(MAX_HEADER_LINE)
        lineno += 1
        consumed += len(raw)
        if not raw:
            raise PointCloudError(f"{path}: PLY header is not terminated by 'end_header'")
        if consumed > MAX_HEADER_BYTES or (len(raw) == MAX_HEADER_LINE and not raw.endswith(b"\n")):
            raise PointCloudError(f"{path}: PLY header is malformed (no 'end_header' in the first bytes)")
        line = header_line(raw)
        if not line:
            continue
        words = line.split()
        key = words[0]
        if key == "end_header":
            break
        if key in ("comment", "obj_info"):
            continue

        def bad(what: str, lineno: int = lineno) -> PointCloudError:
            return PointCloudError(f"{path}: PLY header line {lineno}: {what}")

        if key == "format":
            if len(words) != 3 or words[1] not in ("ascii", "binary_little_endian", "binary_big_endian"):
                raise bad(f"unsupported format line {quote(line, 80)}")
            fmt = words[1]
            if words[2] not in ("1.0", "1"):
                logger.warning("%s: PLY header line %d: version %s (only 1.0 is defined); read as 1.0", path, lineno,
                               quote(words[2], 20))
        elif key == "element":
            if len(words) != 3:
                raise bad(f"malformed element line {quote(line, 80)}")
            count = int(words[2]) if words[2].isascii() and words[2].isdigit() else -1
            if count < 0:
                raise bad(f"bad element count {quote(words[2])} (expected a non-negative integer)")
            elements.append(_Element(words[1], count))
        elif key == "property":
            if not elements:
                raise bad("property before any element")
            names = {p.name for p in elements[-1].props}
            if elements[-1].name == "vertex" and words[-1] in ("x", "y", "z") and words[-1] in names:
                # which copy is the coordinate would be a guess (a duplicate attribute keeps its last copy)
                raise bad(f"duplicate vertex property {quote(words[-1])}")
            if len(words) == 5 and words[1] == "list":
                ct, it = PLY_TYPES.get(words[2]), PLY_TYPES.get(words[3])
                if ct is None or it is None or ct[0] == "f":
                    raise bad(f"unknown list types in {quote(line, 80)}")
                elements[-1].props.append(_Prop(words[4], it, ct))
            elif len(words) == 3 and words[1] in PLY_TYPES:
                elements[-1].props.append(_Prop(words[2], PLY_TYPES[words[1]], declared=words[1]))
            else:
                raise bad(f"unknown property type in {quote(line, 80)}")
        elif parse_float(key.encode("utf-8")) is not None:
            raise PointCloudError(
                f"{path}: PLY header is not terminated by 'end_header' (numeric data on line {lineno})"
            )
        else:
            raise bad(f"unrecognised keyword {quote(key)}")
    if fmt is None:
        raise PointCloudError(f"{path}: PLY header has no 'format' line")
    return fmt, elements, lineno


# ----------------------------------------------------------------------------------------------------
# ASCII: one line per element instance
# ----------------------------------------------------------------------------------------------------


def _read_ascii(path: Path, fh, elements: list[_Element], vidx: int, header_lines: int) -> dict[str, np.ndarray]:
    reader = LineReader(fh, path, header_lines)
    for el in elements[:vidx]:
        if el.has_list:
            _ascii_list_element(reader, el, want=())
        else:
            for done in range(0, el.count, 1 << 16):  # skipped in slices: memory stays small
                read_rows(reader, min(1 << 16, el.count - done), len(el.props), f"element {quote(el.name)}",
                          f"{quote(el.name)} elements")
    vertex = elements[vidx]
    if not vertex.has_list:
        rows = read_rows(reader, vertex.count, len(vertex.props), "vertex", "vertices")
        table = {p.name: rows[:, i] for i, p in enumerate(vertex.props)}
    else:
        want = tuple(p.name for p in vertex.props if p.count_dtype is None)
        table = _ascii_list_element(reader, vertex, want)
    if vidx == len(elements) - 1 and (extra := reader.lines_left()):  # nothing may follow the last element
        logger.warning("%s: %d more data lines after the %d vertices the header declares (ignored)", path, extra,
                       vertex.count)
    return table


def _ascii_list_element(reader: LineReader, el: _Element, want: tuple[str, ...]) -> dict[str, np.ndarray]:
    """Walk an element with list properties line by line; return the scalar properties in ``want``."""
    out = {name: np.empty(el.count, dtype=np.float64) for name in want}
    path = reader.path
    r = 0
    while r < el.count:
        raw = reader.line()
        if raw is None:
            raise PointCloudError(
                f"{path}: truncated: the header declares {el.count} {quote(el.name)} elements but the data "
                f"ends after {r}"
            )
        toks = raw.split()
        if not toks:
            continue
        lineno = reader.lineno
        pos = 0
        for p in el.props:
            if pos >= len(toks):
                raise PointCloudError(
                    f"{path}: line {lineno}: {quote(el.name)} element has {len(toks)} values, too few for "
                    f"its properties (ends before {quote(p.name)})"
                )
            if p.count_dtype is None:
                if p.name in out:
                    v = parse_float(toks[pos])
                    if v is None:
                        raise PointCloudError(
                            f"{path}: line {lineno}: non-numeric value {quote(toks[pos])} in {quote(el.name)}")
                    out[p.name][r] = v
                pos += 1
                continue
            t = toks[pos]
            n = int(t) if t.isdigit() else -1
            if n < 0:
                raise PointCloudError(
                    f"{path}: line {lineno}: bad list length {quote(t)} for {quote(p.name)} "
                    "(expected a non-negative integer)"
                )
            if pos + 1 + n > len(toks):
                raise PointCloudError(
                    f"{path}: line {lineno}: list {quote(p.name)} declares {n} items but the line has "
                    f"only {len(toks) - pos - 1} after it"
                )
            pos += 1 + n
        if pos != len(toks):
            raise PointCloudError(
                f"{path}: line {lineno}: {quote(el.name)} element has {len(toks)} values, its properties "
                f"and list lengths account for {pos}"
            )
        r += 1
    return out


# ----------------------------------------------------------------------------------------------------
# binary
# ----------------------------------------------------------------------------------------------------


def _read_binary(path: Path, body: bytes, elements: list[_Element], vidx: int, order: str) -> dict[str, np.ndarray]:
    offset = 0
    for el in elements[:vidx]:
        offset = _skip_element(path, body, el, offset, order)
    vertex = elements[vidx]
    n = vertex.count
    if not vertex.has_list:
        dtype = np.dtype([(f"p{i}", order + p.dtype) for i, p in enumerate(vertex.props)])
        if len(body) - offset < n * dtype.itemsize:
            raise PointCloudError(
                f"{path}: truncated: the header declares {n} vertices but only {len(body) - offset} bytes of "
                f"vertex data follow (expected {n * dtype.itemsize})"
            )
        rec = np.frombuffer(body, dtype=dtype, count=n, offset=offset)
        left = len(body) - offset - n * dtype.itemsize
        if vidx == len(elements) - 1 and left >= dtype.itemsize:  # nothing may follow the last element
            logger.warning("%s: %d more bytes after the %d vertices the header declares (%d vertices' worth; "
                           "ignored)", path, left, n, left // dtype.itemsize)
        return {p.name: rec[f"p{i}"] for i, p in enumerate(vertex.props)}
    out = {p.name: np.empty(n, dtype=np.float64) for p in vertex.props if p.count_dtype is None}
    for r in range(n):
        for p in vertex.props:
            if p.count_dtype is None:
                size = np.dtype(p.dtype).itemsize
                if offset + size > len(body):
                    raise _truncated(path, vertex, r)
                out[p.name][r] = np.frombuffer(body, order + p.dtype, 1, offset)[0]
                offset += size
            else:
                offset = _skip_list(path, body, vertex, p, offset, order, r)
    return out


def _plural(name: str) -> str:
    return "vertices" if name == "vertex" else f"{quote(name)} elements"


def _truncated(path: Path, el: _Element, row: int) -> PointCloudError:
    return PointCloudError(
        f"{path}: truncated: the header declares {el.count} {quote(el.name)} elements but the data ends "
        f"in element {row}"
    )


def _skip_list(path: Path, body: bytes, el: _Element, p: _Prop, offset: int, order: str, row: int) -> int:
    assert p.count_dtype is not None, "a list property"
    csize = np.dtype(p.count_dtype).itemsize
    if offset + csize > len(body):
        raise _truncated(path, el, row)
    cnt = int(np.frombuffer(body, order + p.count_dtype, 1, offset)[0])
    if cnt < 0:
        raise PointCloudError(
            f"{path}: corrupt PLY data: negative list length {cnt} in {quote(p.name)} of {quote(el.name)} "
            f"element {row}"
        )
    end = offset + csize + cnt * np.dtype(p.dtype).itemsize
    if end > len(body):
        raise _truncated(path, el, row)
    return end


def _skip_element(path: Path, body: bytes, el: _Element, offset: int, order: str) -> int:
    if not el.has_list:
        return offset + el.count * el.min_binary_bytes()
    if el.count == 0:
        return offset
    # Fast path: every list of the element has the length of the first row's (e.g. all triangles).
    lengths, pos = [], offset
    for p in el.props:
        if p.count_dtype is None:
            pos += np.dtype(p.dtype).itemsize
        else:
            end = _skip_list(path, body, el, p, pos, order, 0)
            lengths.append((end - pos - np.dtype(p.count_dtype).itemsize) // np.dtype(p.dtype).itemsize)
            pos = end
    row_size = pos - offset
    if offset + el.count * row_size <= len(body):
        fields: list[tuple[str, str] | tuple[str, str, tuple[int]]] = []
        k = 0
        for i, p in enumerate(el.props):
            if p.count_dtype is None:
                fields.append((f"s{i}", order + p.dtype))
            else:
                fields.append((f"c{i}", order + p.count_dtype))
                if lengths[k]:
                    fields.append((f"l{i}", order + p.dtype, (lengths[k],)))
                k += 1
        rec = np.frombuffer(body, dtype=np.dtype(fields), count=el.count, offset=offset)
        k = 0
        uniform = True
        for i, p in enumerate(el.props):
            if p.count_dtype is not None:
                uniform &= bool((rec[f"c{i}"] == lengths[k]).all())
                k += 1
        if uniform:
            return offset + el.count * row_size
    for r in range(el.count):  # lists of varying length: row by row
        for p in el.props:
            if p.count_dtype is None:
                offset += np.dtype(p.dtype).itemsize
                if offset > len(body):
                    raise _truncated(path, el, r)
            else:
                offset = _skip_list(path, body, el, p, offset, order, r)
    return offset


# ----------------------------------------------------------------------------------------------------
# writer
# ----------------------------------------------------------------------------------------------------


def _ply_type(name: str, v: np.ndarray, where: str) -> str | None:
    """The PLY type code for attribute ``v`` (None: not written): its own where PLY has it; a 64-bit
    integer as 32 bits when its values fit, else as double, with a warning when that loses digits
    (a nanosecond time stamp: PLY has no 64-bit integer); a flag as uchar; a half float as float."""
    code = v.dtype.str[1:]
    if code in _TYPE_NAMES:
        return code
    if v.dtype.kind == "b":
        return "u1"
    if v.dtype.kind == "f":
        return "f4" if v.dtype.itemsize < 4 else "f8"
    if v.dtype.kind not in "iu":
        return None
    low, high = (int(v.min()), int(v.max())) if len(v) else (0, 0)
    if low >= 0 and high <= np.iinfo(np.uint32).max:
        return "u4"
    if low >= np.iinfo(np.int32).min and high <= np.iinfo(np.int32).max:
        return "i4"
    if max(-low, high) > 2**53:
        logger.warning("%s: attribute %r written as double, which keeps integers up to 2^53 exactly (it holds "
                       "%d..%d; PLY has no 64-bit integer): write .pcd or .las to keep every digit", where, name,
                       low, high)
    return "f8"


def ply_bytes(cloud: PointCloud, binary: bool = True, path: Path | None = None) -> bytes:
    """The bytes of a PLY file (:func:`ply_chunks` joined)."""
    return b"".join(ply_chunks(cloud, binary, path))


def ply_chunks(cloud: PointCloud, binary: bool = True, path: Path | None = None) -> Iterable[bytes]:
    """A PLY file in pieces: float64 x y z plus every 1-D attribute in its own type, or the nearest
    PLY has (:func:`_ply_type`; binary little endian when ``binary``, else ASCII with ``%.17g``, formatted
    block by block as the file is written). Normals are written as ``nx ny nz``, 16-bit colours as 8-bit
    (:func:`~gctr_cli.io.cloud.eight_bit_colours`)."""
    pts = np.asarray(cloud.points, dtype=np.float64)
    n = len(pts)
    where = clean(path) if path is not None else "PLY output"
    cols: list[tuple[str, np.ndarray]] = [("x", pts[:, 0]), ("y", pts[:, 1]), ("z", pts[:, 2])]
    for name, values in eight_bit_colours(named_normals(cloud.attributes, ("nx", "ny", "nz"))).items():
        v = np.asarray(values)
        if v.shape != (n,) or name in ("x", "y", "z"):
            continue
        code = _ply_type(str(name), v, where)
        if code is None:
            continue
        cols.append(("_".join(str(name).split()) or "attr", v.astype("<" + code)))
    fmt = "binary_little_endian" if binary else "ascii"
    header = f"ply\nformat {fmt} 1.0\ncomment written by gctr\nelement vertex {n}\n"
    header += "".join(f"property {_TYPE_NAMES[v.dtype.str[1:]]} {name}\n" for name, v in cols) + "end_header\n"
    if binary:
        return [header.encode("ascii"), pack_columns([v for _, v in cols])]
    return itertools.chain([header.encode("ascii")], format_column_blocks([v for _, v in cols]))


def pack_columns(cols: list[np.ndarray]) -> bytes:
    """Interleave equal-length columns into packed binary records (each column keeps its dtype)."""
    rec = np.empty(len(cols[0]) if cols else 0, dtype=[(f"c{i}", v.dtype) for i, v in enumerate(cols)])
    for i, v in enumerate(cols):
        rec[f"c{i}"] = v
    return rec.tobytes()


#: rows formatted at a time by :func:`format_column_blocks`
TEXT_BLOCK_ROWS = 65536


def format_column_blocks(cols: list[np.ndarray], separator: str = " ") -> Iterator[bytes]:
    """Text rows of the columns (floats as ``%.17g``, exact round trip; integers as integers), block by
    block (:data:`TEXT_BLOCK_ROWS` rows each), formatted as they are asked for: a writer that writes each
    block as it comes never holds the whole text (10 million rows of 7 columns are 740 MB of text, and were
    built whole, then copied, before being written)."""
    if not cols or len(cols[0]) == 0:
        return
    fmts = ["%.17g" if c.dtype.kind == "f" else "%d" for c in cols]
    line_fmt = separator.join(fmts) + "\n"
    for start in range(0, len(cols[0]), TEXT_BLOCK_ROWS):
        rows = zip(*(c[start:start + TEXT_BLOCK_ROWS].tolist() for c in cols))
        yield "".join(line_fmt % row for row in rows).encode("ascii")
