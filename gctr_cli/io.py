"""Point cloud and transform-matrix I/O with strict validation.

Open3D only *warns* on unreadable files and hands back an empty cloud, so gctr parses the formats it
supports itself and checks what it reads:

* ``.ply`` — ASCII, binary little endian and binary big endian; the ``vertex`` element must have
  scalar ``x``, ``y`` and ``z`` properties of any numeric type. Other properties and elements (faces,
  ``range_grid`` lists, ...) are skipped.
* ``.pcd`` — ``DATA ascii``, ``binary`` and ``binary_compressed`` (LZF, decompressed here).
* ``.xyz`` / ``.pts`` / ``.txt`` — whitespace- or comma-separated text, the first three columns are
  x y z; extra columns are ignored; leading header lines that are not numbers, a leading point-count
  line (one number on its own) and ``#`` / ``//`` comment lines are skipped. Read in blocks of whole
  lines (``np.loadtxt`` for plain numeric blocks), so memory follows the number of points, not the
  size of the text: about 180 MB and 7 s for 2 million points.

Every cloud is returned as an ``(N, 3)`` float64 array (doubles in the file stay doubles). Non-finite
points are dropped with a warning; too few points, all-identical points and collinear points are errors.
Every error names the file and the specific problem.

Matrices are 4x4 similarity transforms stored as four lines of four numbers (``%.17g`` on write, so a
round trip is bit-exact). All writers are atomic: they write a temporary file in the target folder and
``os.replace`` it over the destination.
"""

from __future__ import annotations

import io as _stdio
import logging
import re
import struct
import warnings
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from gctr_cli.fsutil import atomic_write

__all__ = [
    "MatrixError",
    "PointCloudError",
    "SUPPORTED_EXTENSIONS",
    "format_matrix",
    "load_point_cloud",
    "read_matrix",
    "save_point_cloud",
    "write_matrix",
]

logger = logging.getLogger(__name__)

SUPPORTED_EXTENSIONS = (".ply", ".pcd", ".xyz", ".pts", ".txt")
_TEXT_EXTENSIONS = (".xyz", ".pts", ".txt")

#: relative singular-value threshold below which a cloud counts as collinear
COLLINEAR_RTOL = 1e-9
_MAX_HEADER_BYTES = 1 << 20
_MAX_HEADER_LINE = 1 << 16


class PointCloudError(ValueError):
    """A point cloud file is missing, unreadable, malformed or degenerate."""


class MatrixError(ValueError):
    """A matrix file is missing, malformed, or the matrix is not a valid 4x4 transform."""


# ----------------------------------------------------------------------------------------------------
# Point clouds: public API
# ----------------------------------------------------------------------------------------------------


def load_point_cloud(path: str | Path, *, min_points: int = 10) -> np.ndarray:
    """Read a point cloud file and return its points as a validated ``(N, 3)`` float64 array.

    The format is chosen by extension (see :data:`SUPPORTED_EXTENSIONS`, case-insensitive).
    Non-finite points (NaN/inf in any coordinate) are dropped with a warning on the ``gctr_cli.io``
    logger. Raises :class:`PointCloudError` if the file does not exist, is empty, is malformed or
    truncated, has fewer than ``min_points`` finite points, or if all points are identical or collinear.
    Planar clouds are accepted.
    """
    path = Path(path)
    ext = path.suffix.lower()
    if ext not in SUPPORTED_EXTENSIONS:
        raise PointCloudError(
            f"{path}: unsupported extension '{path.suffix}' (supported: {', '.join(SUPPORTED_EXTENSIONS)})"
        )
    _check_readable_file(path, PointCloudError)

    try:
        if ext == ".ply":
            pts = _read_ply(path)
        elif ext == ".pcd":
            pts = _read_pcd(path)
        else:
            pts = _read_text_cloud(path)
    except PointCloudError:
        raise
    except OSError as exc:
        raise PointCloudError(f"{path}: cannot read file ({exc.strerror or exc})") from exc
    except (ValueError, struct.error, IndexError) as exc:  # safety net: keep the file name in the message
        raise PointCloudError(f"{path}: malformed file ({exc})") from exc

    pts = np.ascontiguousarray(pts, dtype=np.float64).reshape(-1, 3)
    return _validate_points(pts, path, min_points)


def save_point_cloud(path: str | Path, points: np.ndarray, *, binary: bool = True) -> None:
    """Write ``points`` (``(N, 3)``) to ``path``; the format follows the extension.

    ``.ply`` and ``.pcd`` store float64 coordinates (binary little endian when ``binary``, else ASCII
    with ``%.17g``); ``.xyz`` / ``.pts`` / ``.txt`` are always text, one ``x y z`` line per point
    (``%.17g``; ``.pts`` starts with a point-count line), so every format round-trips exactly through
    :func:`load_point_cloud`. Missing parent folders are created. The write is atomic (temporary file
    in the same folder, then ``os.replace``).

    Interoperability note: Open3D 0.20's legacy PCD reader silently returns zeros for ``SIZE 8``
    (double) fields in binary PCD files; write ``.ply`` (or ASCII ``.pcd``) when Open3D must read the
    result. Open3D itself writes PCD as float32 only.
    """
    path = Path(path)
    ext = path.suffix.lower()
    if ext not in SUPPORTED_EXTENSIONS:
        raise PointCloudError(
            f"{path}: unsupported extension '{path.suffix}' (supported: {', '.join(SUPPORTED_EXTENSIONS)})"
        )
    try:
        pts = np.asarray(points, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise PointCloudError(f"{path}: points are not numeric ({exc})") from exc
    if pts.ndim != 2 or pts.shape[1] != 3:
        raise PointCloudError(f"{path}: points must have shape (N, 3), got {pts.shape}")
    n = pts.shape[0]

    if ext == ".ply":
        fmt = "binary_little_endian" if binary else "ascii"
        header = (
            f"ply\nformat {fmt} 1.0\ncomment written by gctr\nelement vertex {n}\n"
            "property double x\nproperty double y\nproperty double z\nend_header\n"
        ).encode("ascii")
        body = pts.astype("<f8").tobytes() if binary else _format_rows(pts)
    elif ext == ".pcd":
        header = (
            "# .PCD v0.7 - Point Cloud Data file format\nVERSION 0.7\nFIELDS x y z\nSIZE 8 8 8\n"
            f"TYPE F F F\nCOUNT 1 1 1\nWIDTH {n}\nHEIGHT 1\nVIEWPOINT 0 0 0 1 0 0 0\nPOINTS {n}\n"
            f"DATA {'binary' if binary else 'ascii'}\n"
        ).encode("ascii")
        body = pts.astype("<f8").tobytes() if binary else _format_rows(pts)
    else:
        # .pts conventionally starts with a point-count line (Open3D requires it); .xyz/.txt do not.
        header = f"{n}\n".encode("ascii") if ext == ".pts" else b""
        body = _format_rows(pts)
    _atomic_write_bytes(path, header + body, PointCloudError)


# ----------------------------------------------------------------------------------------------------
# Matrices
# ----------------------------------------------------------------------------------------------------


def read_matrix(path: str | Path) -> np.ndarray:
    """Read a 4x4 transform: four lines of four numbers (whitespace- or comma-separated).

    Blank lines, ``#`` comment lines and trailing ``# ...`` comments are ignored. The numbers must be
    finite and the last row must be ``0 0 0 1``. Raises :class:`MatrixError` naming the file and the
    problem (with the line number where relevant).
    """
    path = Path(path)
    _check_readable_file(path, MatrixError)
    try:
        text = path.read_bytes().decode("utf-8-sig")
    except UnicodeDecodeError as exc:
        raise MatrixError(f"{path}: not a text file ({exc.reason} at byte {exc.start})") from exc
    except OSError as exc:
        raise MatrixError(f"{path}: cannot read file ({exc.strerror or exc})") from exc

    rows: list[list[float]] = []
    for lineno, raw in enumerate(text.splitlines(), start=1):
        line = raw.split("#", 1)[0].replace(",", " ").strip()
        if not line:
            continue
        tokens = line.split()
        if len(tokens) != 4:
            raise MatrixError(f"{path}: line {lineno} has {len(tokens)} numbers, expected 4: {raw.strip()!r}")
        if len(rows) == 4:
            raise MatrixError(f"{path}: more than 4 rows of numbers (extra row on line {lineno})")
        try:
            rows.append([float(t) for t in tokens])
        except ValueError:
            raise MatrixError(f"{path}: line {lineno} contains a non-numeric value: {raw.strip()!r}") from None
    if len(rows) != 4:
        raise MatrixError(f"{path}: expected 4 rows of 4 numbers, found {len(rows)}")
    T = np.array(rows, dtype=np.float64)
    _check_matrix(T, str(path))
    return T


def write_matrix(path: str | Path, T: np.ndarray) -> None:
    """Write a 4x4 matrix as four lines of four ``%.17g`` numbers (bit-exact round trip), atomically.

    Missing parent folders are created.
    """
    path = Path(path)
    try:
        M = np.asarray(T, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise MatrixError(f"{path}: matrix is not numeric ({exc})") from exc
    if M.shape != (4, 4):
        raise MatrixError(f"{path}: matrix must be 4x4, got shape {M.shape}")
    if not np.isfinite(M).all():
        raise MatrixError(f"{path}: matrix contains non-finite values")
    _atomic_write_bytes(path, format_matrix(M).encode("ascii"), MatrixError)


def format_matrix(T: np.ndarray) -> str:
    """Return the text of a 4x4 matrix: four lines of four space-separated ``%.17g`` numbers."""
    M = np.asarray(T, dtype=np.float64)
    if M.shape != (4, 4):
        raise MatrixError(f"matrix must be 4x4, got shape {M.shape}")
    return "".join(" ".join("%.17g" % v for v in row) + "\n" for row in M)


def _check_matrix(T: np.ndarray, where: str) -> None:
    if not np.isfinite(T).all():
        bad = [f"({i},{j})" for i, j in zip(*np.nonzero(~np.isfinite(T)))]
        raise MatrixError(f"{where}: matrix contains non-finite values at {', '.join(bad)}")
    if not np.allclose(T[3], [0.0, 0.0, 0.0, 1.0], rtol=0.0, atol=1e-9):
        raise MatrixError(
            f"{where}: last row must be '0 0 0 1' for a similarity transform, got {' '.join('%g' % v for v in T[3])}"
        )


# ----------------------------------------------------------------------------------------------------
# Shared helpers
# ----------------------------------------------------------------------------------------------------


def _check_readable_file(path: Path, err: type[ValueError]) -> None:
    if not path.exists():
        raise err(f"{path}: file does not exist")
    if not path.is_file():
        raise err(f"{path}: is not a regular file")
    try:
        size = path.stat().st_size
    except OSError as exc:
        raise err(f"{path}: cannot read file ({exc.strerror or exc})") from exc
    if size == 0:
        raise err(f"{path}: file is empty (0 bytes)")


def _atomic_write_bytes(path: Path, data: bytes, err: type[ValueError]) -> None:
    """Write ``data`` atomically (:func:`gctr_cli.fsutil.atomic_write`); errors become ``err``."""
    try:
        atomic_write(path, data)
    except OSError as exc:
        raise err(f"{path}: cannot write file ({exc.strerror or exc})") from exc


def _format_rows(pts: np.ndarray) -> bytes:
    if len(pts) == 0:
        return b""
    return ("\n".join(" ".join("%.17g" % v for v in row) for row in pts.tolist()) + "\n").encode("ascii")


def _tokens_to_float(tokens: list[bytes], path: Path, what: str) -> np.ndarray:
    try:
        return np.array(tokens, dtype=np.float64)
    except ValueError:
        for i, tok in enumerate(tokens):
            try:
                float(tok)
            except ValueError:
                raise PointCloudError(
                    f"{path}: non-numeric value {tok[:40].decode('latin-1')!r} in {what} (value #{i + 1})"
                ) from None
        raise


def _validate_points(pts: np.ndarray, path: Path, min_points: int) -> np.ndarray:
    """Drop non-finite rows, then check count and degeneracy.

    The "dropped N non-finite points" warning is logged only for a cloud that is accepted; when the
    cloud is rejected the error itself says how many points were dropped.
    """
    n_total = len(pts)
    finite = np.isfinite(pts).all(axis=1)
    n_bad = int(n_total - finite.sum())
    if n_bad:
        pts = pts[finite]
    n = len(pts)
    dropped = f" after dropping {n_bad} non-finite" if n_bad else ""
    if n == 0:
        if n_total:
            raise PointCloudError(f"{path}: contains no finite points (all {n_total} points are non-finite)")
        raise PointCloudError(f"{path}: contains no points (at least {min_points} required)")
    if n < min_points:
        raise PointCloudError(
            f"{path}: too few points: only {n} finite points{dropped} (at least {min_points} required)"
        )
    if (pts == pts[0]).all():
        raise PointCloudError(f"{path}: degenerate cloud: all {n} points{dropped} are identical")
    centred = pts - pts.mean(axis=0)
    sv = np.linalg.svd(centred, compute_uv=False)
    if sv[1] < COLLINEAR_RTOL * sv[0]:
        raise PointCloudError(f"{path}: degenerate cloud: points are collinear ({n} points{dropped} on one line)")
    if n_bad:
        logger.warning("%s: dropped %d of %d points with non-finite (NaN/inf) coordinates", path, n_bad, n_total)
    return pts


def _missing_xyz_error(path: Path, what: str, names: list[str]) -> PointCloudError:
    missing = [c for c in "xyz" if c not in names]
    return PointCloudError(
        f"{path}: {what} has no {'/'.join(missing)} field{'s' if len(missing) > 1 else ''} "
        f"(fields: {' '.join(names) or 'none'})"
    )


# ----------------------------------------------------------------------------------------------------
# PLY
# ----------------------------------------------------------------------------------------------------

_PLY_TYPES = {
    "char": "i1", "int8": "i1",
    "uchar": "u1", "uint8": "u1",
    "short": "i2", "int16": "i2",
    "ushort": "u2", "uint16": "u2",
    "int": "i4", "int32": "i4",
    "uint": "u4", "uint32": "u4",
    "float": "f4", "float32": "f4",
    "double": "f8", "float64": "f8",
}  # fmt: skip


@dataclass
class _PlyProperty:
    name: str
    dtype: str  # numpy type code without byte order ("f4"); for lists: the item type
    count_dtype: str | None = None  # list length type, None for scalar properties


@dataclass
class _PlyElement:
    name: str
    count: int
    props: list[_PlyProperty] = field(default_factory=list)

    @property
    def has_list(self) -> bool:
        return any(p.count_dtype is not None for p in self.props)


def _read_ply(path: Path) -> np.ndarray:
    with open(path, "rb") as fh:
        magic = fh.read(4)
        if not (magic[:3] == b"ply" and magic[3:4] in (b"\n", b"\r")):
            raise PointCloudError(f"{path}: not a PLY file (missing 'ply' magic)")
        if magic[3:4] == b"\r" and fh.read(1) != b"\n":
            fh.seek(4)
        fmt, elements = _parse_ply_header(fh, path)
        body = fh.read()

    vidx = next((i for i, e in enumerate(elements) if e.name == "vertex"), None)
    if vidx is None:
        names = ", ".join(e.name for e in elements) or "none"
        raise PointCloudError(f"{path}: PLY header has no 'vertex' element (elements: {names})")
    vertex = elements[vidx]
    pnames = [p.name for p in vertex.props]
    for c in "xyz":
        if c not in pnames:
            raise _missing_xyz_error(path, "PLY vertex element", pnames)
        if vertex.props[pnames.index(c)].count_dtype is not None:
            raise PointCloudError(f"{path}: PLY vertex property '{c}' is a list, expected a scalar")
    cols = [pnames.index(c) for c in "xyz"]

    if fmt == "ascii":
        return _read_ply_ascii(path, body, elements, vidx, cols)
    order = "<" if fmt == "binary_little_endian" else ">"
    return _read_ply_binary(path, body, elements, vidx, cols, order)


def _parse_ply_header(fh, path: Path) -> tuple[str, list[_PlyElement]]:
    fmt: str | None = None
    elements: list[_PlyElement] = []
    lineno = 1
    consumed = 4
    while True:
        raw = fh.readline(_MAX_HEADER_LINE)
        lineno += 1
        consumed += len(raw)
        if not raw:
            raise PointCloudError(f"{path}: PLY header is not terminated by 'end_header'")
        if consumed > _MAX_HEADER_BYTES or (len(raw) == _MAX_HEADER_LINE and not raw.endswith(b"\n")):
            raise PointCloudError(f"{path}: PLY header is malformed (no 'end_header' in the first bytes)")
        line = raw.decode("latin-1").strip()
        if not line:
            continue
        words = line.split()
        key = words[0]
        if key == "end_header":
            break
        if key in ("comment", "obj_info"):
            continue
        if key == "format":
            if len(words) != 3 or words[1] not in ("ascii", "binary_little_endian", "binary_big_endian"):
                raise PointCloudError(f"{path}: PLY header line {lineno}: unsupported format line {line!r}")
            fmt = words[1]
        elif key == "element":
            if len(words) != 3:
                raise PointCloudError(f"{path}: PLY header line {lineno}: malformed element line {line!r}")
            try:
                count = int(words[2])
            except ValueError:
                count = -1
            if count < 0:
                raise PointCloudError(f"{path}: PLY header line {lineno}: bad element count {words[2]!r}")
            elements.append(_PlyElement(words[1], count))
        elif key == "property":
            if not elements:
                raise PointCloudError(f"{path}: PLY header line {lineno}: property before any element")
            if len(words) == 5 and words[1] == "list":
                ct, it = _PLY_TYPES.get(words[2]), _PLY_TYPES.get(words[3])
                if ct is None or it is None or ct[0] == "f":
                    raise PointCloudError(f"{path}: PLY header line {lineno}: unknown list types in {line!r}")
                elements[-1].props.append(_PlyProperty(words[4], it, ct))
            elif len(words) == 3 and words[1] in _PLY_TYPES:
                elements[-1].props.append(_PlyProperty(words[2], _PLY_TYPES[words[1]]))
            else:
                raise PointCloudError(f"{path}: PLY header line {lineno}: unknown property type in {line!r}")
        elif _is_number(key):
            raise PointCloudError(
                f"{path}: PLY header is not terminated by 'end_header' (numeric data on line {lineno})"
            )
        else:
            raise PointCloudError(f"{path}: PLY header line {lineno}: unrecognised keyword {key[:40]!r}")
    if fmt is None:
        raise PointCloudError(f"{path}: PLY header has no 'format' line")
    return fmt, elements


def _read_ply_ascii(
    path: Path, body: bytes, elements: list[_PlyElement], vidx: int, cols: list[int]
) -> np.ndarray:
    vertex = elements[vidx]
    n = vertex.count
    nprops = len(vertex.props)
    if vidx == 0 and not vertex.has_list:
        # Fast path: only split off as many tokens as the vertex block needs.
        need = n * nprops
        tokens = body.split(None, need)[:need] if need else []
        if len(tokens) < need:
            raise PointCloudError(
                f"{path}: truncated: header declares {n} vertices ({need} values) "
                f"but only {len(tokens)} values follow the header"
            )
        return _tokens_to_float(tokens, path, "PLY vertex data").reshape(n, nprops)[:, cols]

    # General path: walk the tokens of every element up to and including the vertex element.
    tokens = body.split()
    pos = 0

    def truncated() -> PointCloudError:
        return PointCloudError(
            f"{path}: truncated: header declares {n} vertices but the data ends early "
            f"(after {len(tokens)} values)"
        )

    for el in elements[:vidx]:
        if not el.has_list:
            pos += el.count * len(el.props)
            continue
        for _ in range(el.count):
            for p in el.props:
                if p.count_dtype is None:
                    pos += 1
                else:
                    if pos >= len(tokens):
                        raise truncated()
                    pos += 1 + int(tokens[pos])
    xyz_tokens: list[bytes] = []
    for _ in range(n):
        row_start = pos
        for p in vertex.props:
            if p.count_dtype is None:
                pos += 1
            else:
                if pos >= len(tokens):
                    raise truncated()
                pos += 1 + int(tokens[pos])
        if pos > len(tokens):
            raise truncated()
        row = tokens[row_start:pos]
        # scalar properties before a list shift the index; compute offsets for this row
        xyz_tokens.extend(row[_ascii_row_offset(vertex, row, c)] for c in cols)
    return _tokens_to_float(xyz_tokens, path, "PLY vertex data").reshape(n, 3)


def _ascii_row_offset(el: _PlyElement, row: list[bytes], prop_index: int) -> int:
    off = 0
    for p in el.props[:prop_index]:
        off += 1 if p.count_dtype is None else 1 + int(row[off])
    return off


def _read_ply_binary(
    path: Path, body: bytes, elements: list[_PlyElement], vidx: int, cols: list[int], order: str
) -> np.ndarray:
    vertex = elements[vidx]
    n = vertex.count
    offset = 0
    for el in elements[:vidx]:
        if el.has_list:
            offset = _skip_binary_list_element(path, body, el, offset, order)
        else:
            offset += el.count * np.dtype([(f"p{i}", order + p.dtype) for i, p in enumerate(el.props)]).itemsize
    if offset > len(body):
        raise PointCloudError(
            f"{path}: truncated: the elements before 'vertex' need {offset} bytes but only {len(body)} bytes follow the header"
        )

    if not vertex.has_list:
        dtype = np.dtype([(f"p{i}", order + p.dtype) for i, p in enumerate(vertex.props)])
        need = n * dtype.itemsize
        avail = len(body) - offset
        if avail < need:
            raise PointCloudError(
                f"{path}: truncated: header declares {n} vertices but only {avail} bytes of vertex data "
                f"follow the header (expected {need})"
            )
        rec = np.frombuffer(body, dtype=dtype, count=n, offset=offset)
        out = np.empty((n, 3), dtype=np.float64)
        for j, c in enumerate(cols):
            out[:, j] = rec[f"p{c}"]
        return out

    # Vertex element with list properties: walk it row by row.
    out = np.empty((n, 3), dtype=np.float64)
    want = {c: j for j, c in enumerate(cols)}
    for r in range(n):
        for i, p in enumerate(vertex.props):
            if p.count_dtype is None:
                size = np.dtype(p.dtype).itemsize
                if offset + size > len(body):
                    raise _binary_truncated(path, n, r, len(body))
                if i in want:
                    out[r, want[i]] = np.frombuffer(body, order + p.dtype, 1, offset)[0]
                offset += size
            else:
                offset = _skip_binary_list(path, body, p, offset, order, n, r)
    return out


def _binary_truncated(path: Path, n: int, row: int, nbytes: int) -> PointCloudError:
    return PointCloudError(
        f"{path}: truncated: header declares {n} vertices but only {nbytes} bytes follow the header "
        f"(data ends in vertex {row})"
    )


def _skip_binary_list(path: Path, body: bytes, p: _PlyProperty, offset: int, order: str, n: int, row: int) -> int:
    csize = np.dtype(p.count_dtype).itemsize
    if offset + csize > len(body):
        raise _binary_truncated(path, n, row, len(body))
    cnt = int(np.frombuffer(body, order + p.count_dtype, 1, offset)[0])
    if cnt < 0:
        raise PointCloudError(f"{path}: negative list length {cnt} in property '{p.name}'")
    return offset + csize + cnt * np.dtype(p.dtype).itemsize


def _skip_binary_list_element(path: Path, body: bytes, el: _PlyElement, offset: int, order: str) -> int:
    for r in range(el.count):
        for p in el.props:
            if p.count_dtype is None:
                offset += np.dtype(p.dtype).itemsize
            else:
                offset = _skip_binary_list(path, body, p, offset, order, el.count, r)
    return offset


# ----------------------------------------------------------------------------------------------------
# PCD
# ----------------------------------------------------------------------------------------------------

_PCD_KEYS = ("VERSION", "FIELDS", "COLUMNS", "SIZE", "TYPE", "COUNT", "WIDTH", "HEIGHT", "VIEWPOINT", "POINTS", "DATA")


@dataclass
class _PcdHeader:
    fields: list[str]
    sizes: list[int]
    types: list[str]
    counts: list[int]
    points: int
    data: str


def _read_pcd(path: Path) -> np.ndarray:
    with open(path, "rb") as fh:
        hdr = _parse_pcd_header(fh, path)
        body = fh.read()

    for c in "xyz":
        if c not in hdr.fields:
            raise _missing_xyz_error(path, "PCD header", hdr.fields)
        if hdr.counts[hdr.fields.index(c)] != 1:
            raise PointCloudError(f"{path}: PCD field '{c}' has COUNT {hdr.counts[hdr.fields.index(c)]}, expected 1")
    fidx = [hdr.fields.index(c) for c in "xyz"]
    n = hdr.points

    if hdr.data == "ascii":
        ncols = sum(hdr.counts)
        need = n * ncols
        tokens = body.split(None, need)[:need] if need else []
        if len(tokens) < need:
            raise PointCloudError(
                f"{path}: truncated: header declares {n} points ({need} values) but only {len(tokens)} values follow"
            )
        arr = _tokens_to_float(tokens, path, "PCD data").reshape(n, ncols)
        starts = np.cumsum([0] + hdr.counts[:-1])
        return arr[:, [starts[i] for i in fidx]]

    dtypes = [np.dtype("<" + t.lower() + str(s)) for t, s in zip(hdr.types, hdr.sizes)]
    if hdr.data == "binary":
        rec_dtype = np.dtype([(f"f{i}", dt, (c,)) if c > 1 else (f"f{i}", dt) for i, (dt, c) in enumerate(zip(dtypes, hdr.counts))])
        need = n * rec_dtype.itemsize
        if len(body) < need:
            raise PointCloudError(
                f"{path}: truncated: header declares {n} points but only {len(body)} bytes of binary data "
                f"follow the header (expected {need})"
            )
        rec = np.frombuffer(body, dtype=rec_dtype, count=n)
        return np.stack([rec[f"f{i}"].astype(np.float64) for i in fidx], axis=1)

    # binary_compressed: uint32 compressed size, uint32 uncompressed size, LZF data; column-major fields.
    if len(body) < 8:
        raise PointCloudError(f"{path}: truncated: binary_compressed PCD has no size fields after the header")
    csize, usize = struct.unpack("<II", body[:8])
    point_size = sum(dt.itemsize * c for dt, c in zip(dtypes, hdr.counts))
    if usize != n * point_size:
        raise PointCloudError(
            f"{path}: corrupt binary_compressed PCD: uncompressed size {usize} bytes does not match "
            f"{n} points x {point_size} bytes declared by the header"
        )
    if len(body) - 8 < csize:
        raise PointCloudError(
            f"{path}: truncated: binary_compressed PCD declares {csize} compressed bytes but only "
            f"{len(body) - 8} follow"
        )
    raw = _lzf_decompress(body[8 : 8 + csize], usize, path) if n else b""
    out = np.empty((n, 3), dtype=np.float64)
    offs = np.cumsum([0] + [n * dt.itemsize * c for dt, c in zip(dtypes, hdr.counts)])
    for j, i in enumerate(fidx):
        out[:, j] = np.frombuffer(raw, dtype=dtypes[i], count=n, offset=int(offs[i]))
    return out


def _parse_pcd_header(fh, path: Path) -> _PcdHeader:
    vals: dict[str, list[str]] = {}
    lineno = 0
    consumed = 0
    data_line = None
    while True:
        raw = fh.readline(_MAX_HEADER_LINE)
        lineno += 1
        consumed += len(raw)
        if not raw:
            break
        if consumed > _MAX_HEADER_BYTES or (len(raw) == _MAX_HEADER_LINE and not raw.endswith(b"\n")):
            raise PointCloudError(f"{path}: not a PCD file (header line {lineno} is too long / not text)")
        line = raw.decode("latin-1").strip()
        if not line or line.startswith("#"):
            continue
        words = line.split()
        key = words[0].upper()
        if key not in _PCD_KEYS:
            if not vals:
                raise PointCloudError(
                    f"{path}: not a PCD file (header line {lineno} does not start with a PCD keyword)"
                )
            if _is_number(words[0]):
                raise PointCloudError(f"{path}: broken PCD header: missing DATA line (numeric data on line {lineno})")
            raise PointCloudError(f"{path}: broken PCD header: unknown keyword {words[0][:40]!r} on line {lineno}")
        if key == "COLUMNS":
            key = "FIELDS"
        if key in vals:
            raise PointCloudError(f"{path}: broken PCD header: {key} appears twice (line {lineno})")
        vals[key] = words[1:]
        if key == "DATA":
            data_line = lineno
            break
    if not vals:
        raise PointCloudError(f"{path}: not a PCD file (no header found)")
    if data_line is None:
        raise PointCloudError(f"{path}: broken PCD header: missing DATA line")

    def bad(msg: str) -> PointCloudError:
        return PointCloudError(f"{path}: broken PCD header: {msg}")

    fields = vals.get("FIELDS")
    if not fields:
        raise bad("missing FIELDS line")
    nf = len(fields)
    if len(set(f for f in fields if f != "_")) != len([f for f in fields if f != "_"]):
        raise bad(f"duplicate names in FIELDS {' '.join(fields)}")

    def int_list(key: str, default: int | None) -> list[int]:
        if key not in vals:
            if default is None:
                raise bad(f"missing {key} line")
            return [default] * nf
        items = vals[key]
        if len(items) != nf:
            raise bad(f"{key} has {len(items)} entries but FIELDS has {nf}")
        try:
            out = [int(v) for v in items]
        except ValueError:
            raise bad(f"{key} must be integers, got {' '.join(items)}") from None
        return out

    sizes = int_list("SIZE", None)
    counts = int_list("COUNT", 1)
    if "TYPE" not in vals:
        raise bad("missing TYPE line")
    types = [t.upper() for t in vals["TYPE"]]
    if len(types) != nf:
        raise bad(f"TYPE has {len(types)} entries but FIELDS has {nf}")
    for f, t, s, c in zip(fields, types, sizes, counts):
        if (t, s) not in {("F", 4), ("F", 8), ("I", 1), ("I", 2), ("I", 4), ("I", 8), ("U", 1), ("U", 2), ("U", 4), ("U", 8)}:
            raise bad(f"unsupported TYPE/SIZE {t}/{s} for field '{f}'")
        if c < 1:
            raise bad(f"COUNT {c} for field '{f}' must be >= 1")

    def one_int(key: str) -> int | None:
        if key not in vals:
            return None
        items = vals[key]
        try:
            v = int(items[0]) if len(items) == 1 else -1
        except ValueError:
            v = -1
        if v < 0:
            raise bad(f"bad {key} value {' '.join(items)!r} (expected a non-negative integer)")
        return v

    points = one_int("POINTS")
    width, height = one_int("WIDTH"), one_int("HEIGHT")
    if points is None:
        if width is None:
            raise bad("missing POINTS (and WIDTH) line")
        points = width * (height if height is not None else 1)
    elif width is not None and width * (height if height is not None else 1) != points:
        logger.warning(
            "%s: PCD header WIDTH*HEIGHT = %d does not match POINTS = %d; using POINTS",
            path, width * (height or 1), points,
        )
    data = " ".join(vals["DATA"]).lower()
    if data not in ("ascii", "binary", "binary_compressed"):
        raise bad(f"unknown DATA type {data!r} (expected ascii, binary or binary_compressed)")
    return _PcdHeader(fields, sizes, types, counts, points, data)


def _lzf_decompress(data: bytes, out_len: int, path: Path) -> bytes:
    """Decompress an LZF stream (liblzf format, as used by PCL/Open3D for binary_compressed PCD)."""
    out = bytearray(out_len)
    ip = op = 0
    n_in = len(data)

    def corrupt(msg: str) -> PointCloudError:
        return PointCloudError(f"{path}: corrupt binary_compressed PCD data: {msg}")

    while ip < n_in:
        ctrl = data[ip]
        ip += 1
        if ctrl < 32:  # literal run
            length = ctrl + 1
            if ip + length > n_in:
                raise corrupt("literal run past end of input")
            if op + length > out_len:
                raise corrupt("output larger than declared size")
            out[op : op + length] = data[ip : ip + length]
            ip += length
            op += length
        else:  # back reference
            length = ctrl >> 5
            if length == 7:
                if ip >= n_in:
                    raise corrupt("back reference past end of input")
                length += data[ip]
                ip += 1
            if ip >= n_in:
                raise corrupt("back reference past end of input")
            ref = op - ((ctrl & 0x1F) << 8) - data[ip] - 1
            ip += 1
            length += 2
            if ref < 0:
                raise corrupt("back reference before start of output")
            if op + length > out_len:
                raise corrupt("output larger than declared size")
            dist = op - ref
            if dist >= length:
                out[op : op + length] = out[ref : ref + length]
            else:  # overlapping copy: repeat the pattern
                pattern = bytes(out[ref:op])
                reps = -(-length // dist)
                out[op : op + length] = (pattern * reps)[:length]
            op += length
    if op != out_len:
        raise corrupt(f"decompressed {op} bytes, header declares {out_len}")
    return bytes(out)


# ----------------------------------------------------------------------------------------------------
# Text formats: .xyz / .pts / .txt
# ----------------------------------------------------------------------------------------------------


#: the first block of a text cloud is small (header detection runs line by line); later ones are large
_TEXT_FIRST_BLOCK = 1 << 16
_TEXT_BLOCK = 1 << 23
#: bytes that make a block take the line-by-line path: characters that ``str.splitlines`` or
#: ``str.split`` treat as line breaks or blanks but ``np.loadtxt`` may not, a lone ``\r``, comments
_TEXT_SLOW_BYTES = re.compile(rb"[\x0b\x0c\x1c-\x1f\x85\xa0#]|//|\r(?!\n)")


def _is_number(tok: str) -> bool:
    try:
        float(tok)
    except ValueError:
        return False
    return True


def _text_blocks(fh) -> Iterator[bytes]:
    """The file in pieces that each end with a ``\\n`` (except maybe the last): whole lines only."""
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
        if cut == 0:  # no line end yet: keep reading
            carry = data
            continue
        carry = data[cut:]
        yield data[:cut] if carry else data


def _text_block_fast(block: bytes) -> np.ndarray | None:
    """x y z of a block of plain numeric lines via numpy's C parser; None if the block needs the
    line-by-line path (comments, unusual separators, a bad line: that path gives the exact error)."""
    if _TEXT_SLOW_BYTES.search(block):
        return None
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # "input contained no data" for blank blocks
        try:
            arr = np.loadtxt(
                _stdio.BytesIO(block.replace(b",", b" ")), dtype=np.float64, comments=None,
                usecols=(0, 1, 2), ndmin=2, encoding="latin-1",
            )
        except ValueError:
            return None
    return arr.reshape(-1, 3)


def _read_text_cloud(path: Path) -> np.ndarray:
    """Text clouds, read in blocks of whole lines so that memory stays proportional to the points.

    Plain numeric blocks go through ``np.loadtxt``; the first block (header detection), blocks with
    comments or unusual characters, and any block ``np.loadtxt`` rejects go line by line, which
    defines the format and gives the exact error (with the line number).
    """
    with open(path, "rb") as fh:
        if b"\x00" in fh.read(4096):
            raise PointCloudError(f"{path}: not a text point cloud (binary data found)")
        fh.seek(0)
        parts: list[np.ndarray] = []
        state = {"header": True, "seen_count_line": False}
        lines_before = 0
        for k, block in enumerate(_text_blocks(fh)):
            if k == 0 and block.startswith(b"\xef\xbb\xbf"):  # UTF-8 byte order mark
                block = block[3:]
            arr = None if state["header"] else _text_block_fast(block)
            if arr is not None:
                n_lines = block.count(b"\n") + (not block.endswith(b"\n"))
            else:
                arr, n_lines = _text_block_lines(path, block, lines_before, state)
            parts.append(arr)
            lines_before += n_lines
    pts = np.concatenate(parts) if parts else np.empty((0, 3))
    if len(pts) == 0:
        raise PointCloudError(f"{path}: contains no points (no lines with numeric x y z columns)")
    return pts


def _text_block_lines(path: Path, block: bytes, lines_before: int, state: dict) -> tuple[np.ndarray, int]:
    """x y z of a block, line by line; returns (points, number of lines of the block).

    Leading header lines of the file (``state["header"]``) are skipped: non-numeric lines, and one
    leading point-count line (a single number). ``#`` / ``//`` comment lines and blank lines are
    skipped anywhere; every other line needs at least three columns, the first three numeric.
    """
    lines = block.decode("latin-1").replace(",", " ").splitlines()

    def is_comment(s: str) -> bool:
        return not s or s.startswith("#") or s.startswith("//")

    start = 0
    if state["header"]:
        while start < len(lines):
            s = lines[start].strip()
            if is_comment(s):
                start += 1
                continue
            toks = s.split()
            if not all(_is_number(t) for t in toks[:3]):
                start += 1
                continue
            if len(toks) == 1 and not state["seen_count_line"]:
                state["seen_count_line"] = True
                start += 1
                continue
            state["header"] = False
            break

    def first_non_numeric(stop: int) -> None:
        """Raise for the first non-numeric x/y/z value before line index ``stop`` of the block."""
        for i in range(start, stop):
            s = lines[i].strip()
            if is_comment(s):
                continue
            for tok in s.split(None, 3)[:3]:
                if not _is_number(tok):
                    raise PointCloudError(f"{path}: line {lines_before + i + 1}: non-numeric value {tok[:40]!r}")

    flat: list[str] = []
    add = flat.extend
    for i in range(start, len(lines)):
        s = lines[i].strip()
        if is_comment(s):
            continue
        toks = s.split(None, 3)
        if len(toks) < 3:
            first_non_numeric(i)  # the first bad line of the file is the one reported
            raise PointCloudError(
                f"{path}: line {lines_before + i + 1} has {len(toks)} column(s), expected at least 3 (x y z)"
            )
        add(toks[:3])
    try:
        values = np.fromiter(map(float, flat), dtype=np.float64, count=len(flat))
    except ValueError:
        first_non_numeric(len(lines))
        raise
    return values.reshape(-1, 3), len(lines)
