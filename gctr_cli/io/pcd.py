"""PCD (PCL's format): ``DATA ascii``, ``binary`` and ``binary_compressed`` (reader and writer).

Fields other than x y z are kept as attributes, a field of ``COUNT k`` (a histogram, a descriptor) as
k columns ``name_0 .. name_{k-1}``; a packed ``rgb``/``rgba`` is unpacked into ``red``/``green``/``blue``
(uint8), and ``rgba``'s alpha into ``alpha``. A non-identity ``VIEWPOINT`` (the sensor's pose) is not
applied to the points, as in PCL, with a warning; a PCD output of the cloud writes it back, moved with
the points (:func:`pcd_chunks`). ``binary_compressed`` data is LZF, decompressed
with python-lzf after the declared sizes have been checked: the uncompressed size must equal the
header's points x point size and LZF expands at most about 88-fold, so a 200-byte file can never ask
for gigabytes.
"""

from __future__ import annotations

import itertools
import logging
import struct
from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from gctr_cli.io.cloud import PointCloud, eight_bit_colours, element_columns, named_normals
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
from gctr_cli.io.ply import format_column_blocks, pack_columns

__all__ = ["pcd_chunks", "read_pcd"]

logger = logging.getLogger("gctr_cli.io")

MAX_HEADER_BYTES = 1 << 20
MAX_HEADER_LINE = 1 << 16
#: an LZF stream of c bytes decompresses to at most this many times c bytes (a 3-byte back
#: reference copies up to 264 bytes)
LZF_MAX_RATIO = 88

_KEYS = ("VERSION", "FIELDS", "COLUMNS", "SIZE", "TYPE", "COUNT", "WIDTH", "HEIGHT", "VIEWPOINT", "POINTS", "DATA")
_TYPES = {("F", 4), ("F", 8), ("I", 1), ("I", 2), ("I", 4), ("I", 8), ("U", 1), ("U", 2), ("U", 4), ("U", 8)}


@dataclass
class _Header:
    fields: list[str]
    sizes: list[int]
    types: list[str]
    counts: list[int]
    points: int
    data: str
    lines: int  # header lines
    viewpoint: tuple[float, ...] | None = None  # tx ty tz qw qx qy qz, when the header has a valid one

    def dtypes(self) -> list[np.dtype]:
        return [np.dtype("<" + t.lower() + str(s)) for t, s in zip(self.types, self.sizes)]

    def point_size(self) -> int:
        return sum(s * c for s, c in zip(self.sizes, self.counts))


def _whole_u32(values: np.ndarray) -> bool:
    """Whether ``values`` are whole numbers in 0..2^32-1, some of them 1 or more: the uint32 bits of packed
    colours written as text, not float values."""
    v = np.asarray(values, dtype=np.float64)
    return bool(len(v) and np.isfinite(v).all() and (v == np.round(v)).all() and v.min() >= 0
                and v.max() >= 1 and v.max() < 2.0**32)


def read_pcd(path: Path, fh, size: int, attributes: bool = True) -> PointCloud:
    hdr = _parse_header(fh, path)
    data_bytes = size - fh.tell()
    for c in "xyz":
        if c not in hdr.fields:
            missing = [m for m in "xyz" if m not in hdr.fields]
            shown = " ".join(quote(f) for f in hdr.fields[:20]) or "none"
            raise PointCloudError(
                f"{path}: PCD header has no {'/'.join(missing)} field{'s' if len(missing) > 1 else ''} "
                f"(fields: {shown})"
            )
        if hdr.counts[hdr.fields.index(c)] != 1:
            raise PointCloudError(f"{path}: PCD field '{c}' has COUNT {hdr.counts[hdr.fields.index(c)]}, expected 1")
    n = hdr.points
    keep = [i for i, f in enumerate(hdr.fields) if f != "_" and (attributes or f in "xyz")]
    dtypes = hdr.dtypes()

    if hdr.data == "ascii":
        ncols = sum(hdr.counts)
        if n * ncols * 2 > data_bytes:
            raise PointCloudError(
                f"{path}: truncated or corrupt: the header declares {n} points of {ncols} values (at least "
                f"2 bytes per value) but only {data_bytes} bytes follow the header"
            )
        if binary_data(fh):
            raise PointCloudError(f"{path}: the PCD header says DATA ascii but the data is binary (write "
                                  "'DATA binary' in the header)")
        reader = LineReader(fh, path, hdr.lines)
        rows = read_rows(reader, n, ncols, "point", "points")
        if extra := reader.lines_left():
            logger.warning("%s: %d more data lines after the %d points the header declares (ignored)", path,
                           extra, n)
        starts = np.cumsum([0] + hdr.counts[:-1])
        # x y z keep the text's value (float64); attributes get their declared type, a field of COUNT k
        # one column per element
        table = {}
        for i in keep:
            name = hdr.fields[i]
            if name in ("x", "y", "z"):
                table[name] = rows[:, starts[i]]
                continue
            raw = rows[:, starts[i]]
            if name in ("rgb", "rgba") and hdr.types[i] == "F" and hdr.counts[i] == 1 and _whole_u32(raw):
                # PCL's ASCII writer stores a float rgb as its uint32 bits ("4291322930"); a packed float
                # itself, as text, is a tiny or NaN number, never a whole number from 1 up
                table[name] = raw.astype(np.uint32)
                continue
            for j, col in enumerate(element_columns(name, hdr.counts[i])):
                table[col] = as_declared(path, col, f"{hdr.types[i]} {hdr.sizes[i]}", rows[:, starts[i] + j],
                                         dtypes[i])
    elif hdr.data == "binary":
        point_size = hdr.point_size()
        if numeric_text(fh):
            raise PointCloudError(f"{path}: the PCD header says DATA binary but the data is numbers written as text "
                                  "(write 'DATA ascii' in the header)")
        if n * point_size > data_bytes:
            raise PointCloudError(
                f"{path}: truncated: the header declares {n} points of {point_size} bytes but only "
                f"{data_bytes} bytes of binary data follow the header (expected {n * point_size})"
            )
        if point_size and (extra := (data_bytes - n * point_size) // point_size):
            if n == 0:
                raise PointCloudError(f"{path}: the header declares 0 points but {extra} point records follow "
                                      "(a writer that never filled in POINTS/WIDTH?)")
            logger.warning("%s: %d more point records after the %d points the header declares (ignored)",
                           clean(path), extra, n)
        body = fh.read(n * point_size)
        rec_dtype = np.dtype([(f"f{i}", dt, (c,)) if c > 1 else (f"f{i}", dt)
                              for i, (dt, c) in enumerate(zip(dtypes, hdr.counts))])
        rec = np.frombuffer(body, dtype=rec_dtype, count=n)
        table = {hdr.fields[i]: rec[f"f{i}"] for i in keep}
    else:
        table = _read_compressed(path, fh, hdr, data_bytes, keep)

    pts = np.empty((n, 3), dtype=np.float64)
    for j, c in enumerate("xyz"):
        pts[:, j] = table.pop(c)
    attrs = {}
    if attributes:
        for name, v in table.items():
            if name in ("rgb", "rgba") and v.dtype.itemsize == 4 and v.ndim == 1:
                packed = np.ascontiguousarray(v).view("<u4")
                attrs["red"] = ((packed >> 16) & 0xFF).astype(np.uint8)
                attrs["green"] = ((packed >> 8) & 0xFF).astype(np.uint8)
                attrs["blue"] = (packed & 0xFF).astype(np.uint8)
                if name == "rgba":  # PCL's rgb has no alpha (its high byte is padding); rgba's is the alpha
                    attrs["alpha"] = ((packed >> 24) & 0xFF).astype(np.uint8)
            elif v.ndim == 2:
                names = element_columns(name, v.shape[1])
                attrs.update({col: np.ascontiguousarray(v[:, j]) for j, col in enumerate(names)})
            else:
                attrs[name] = np.ascontiguousarray(v)
    meta = {}
    if hdr.viewpoint is not None and hdr.viewpoint != IDENTITY_VIEWPOINT:
        logger.warning("%s: the PCD VIEWPOINT (the sensor's pose: translation %s, rotation quaternion w x y z %s) is "
                       "not applied to the points, as in PCL; only a PCD output keeps it, moved with the points",
                       clean(path), " ".join(f"{v:g}" for v in hdr.viewpoint[:3]),
                       " ".join(f"{v:g}" for v in hdr.viewpoint[3:]))
        meta["pcd_viewpoint"] = hdr.viewpoint
    return PointCloud(pts, attrs, "pcd", meta)


def _read_compressed(path: Path, fh, hdr: _Header, data_bytes: int, keep: list[int]) -> dict[str, np.ndarray]:
    """binary_compressed: uint32 compressed size, uint32 uncompressed size, LZF data; column-major."""
    import lzf

    n = hdr.points
    head = fh.read(8)
    if len(head) < 8:
        raise PointCloudError(f"{path}: truncated: binary_compressed PCD has no size fields after the header")
    csize, usize = struct.unpack("<II", head)
    point_size = hdr.point_size()
    if usize != n * point_size:
        raise PointCloudError(
            f"{path}: corrupt binary_compressed PCD: uncompressed size {usize} bytes does not match "
            f"{n} points x {point_size} bytes declared by the header"
        )
    if data_bytes - 8 < csize:
        raise PointCloudError(
            f"{path}: truncated: binary_compressed PCD declares {csize} compressed bytes but only "
            f"{max(data_bytes - 8, 0)} follow"
        )
    if usize > LZF_MAX_RATIO * csize + 64:
        raise PointCloudError(
            f"{path}: corrupt binary_compressed PCD: it declares {usize} uncompressed bytes from only "
            f"{csize} compressed bytes (LZF expands at most {LZF_MAX_RATIO}-fold)"
        )
    raw: bytes | None = b""
    if n:
        comp = fh.read(csize)
        try:
            raw = lzf.decompress(comp, usize + 1) if csize else None  # +1: detect output longer than declared
        except ValueError:  # python-lzf: invalid LZF data
            raw = None
        if raw is None or len(raw) != usize:
            got = "more" if raw is not None and len(raw) > usize else ("fewer" if raw is not None else "invalid")
            detail = ("the LZF data is invalid" if got == "invalid"
                      else f"the LZF data decompresses to {got} bytes than declared")
            raise PointCloudError(f"{path}: corrupt binary_compressed PCD data: {detail}")
    assert raw is not None  # checked above
    dtypes = hdr.dtypes()
    offs = np.cumsum([0] + [n * dt.itemsize * c for dt, c in zip(dtypes, hdr.counts)])
    return {hdr.fields[i]: np.frombuffer(raw, dtype=dtypes[i], count=n * hdr.counts[i], offset=int(offs[i]))
            .reshape((n, hdr.counts[i]) if hdr.counts[i] > 1 else (n,)) for i in keep}


def _parse_header(fh, path: Path) -> _Header:
    vals: dict[str, list[str]] = {}
    lineno = 0
    consumed = 0
    data_line = None
    while True:
        raw = fh.readline(MAX_HEADER_LINE)
        lineno += 1
        consumed += len(raw)
        if not raw:
            break
        if consumed > MAX_HEADER_BYTES or (len(raw) == MAX_HEADER_LINE and not raw.endswith(b"\n")):
            raise PointCloudError(f"{path}: not a PCD file (header line {lineno} is too long / not text"
                                  f"{content_note(fh) if not vals else ''})")
        line = header_line(raw)
        if not line or line.startswith("#"):
            continue
        words = line.split()
        key = words[0].upper()
        if key not in _KEYS:
            if not vals:
                raise PointCloudError(f"{path}: not a PCD file (header line {lineno} does not start with a PCD "
                                      f"keyword{content_note(fh)})")
            if parse_float(words[0].encode("utf-8")) is not None:
                raise PointCloudError(f"{path}: broken PCD header: missing DATA line (numeric data on line {lineno})")
            raise PointCloudError(f"{path}: broken PCD header: unknown keyword {quote(words[0])} on line {lineno}")
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

    def shown(items: list[str]) -> str:
        return quote(" ".join(items), 60)

    fields = vals.get("FIELDS")
    if not fields:
        raise bad("missing FIELDS line")
    nf = len(fields)
    named = [f for f in fields if f != "_"]
    if len(set(named)) != len(named):
        raise bad(f"duplicate names in FIELDS {shown(fields)}")

    def int_list(key: str, default: int | None) -> list[int]:
        if key not in vals:
            if default is None:
                raise bad(f"missing {key} line")
            return [default] * nf
        items = vals[key]
        if len(items) != nf:
            raise bad(f"{key} has {len(items)} entries but FIELDS has {nf}")
        if not all(v.isascii() and v.isdigit() and len(v) < 10 for v in items):
            raise bad(f"{key} must be small non-negative integers, got {shown(items)}")
        return [int(v) for v in items]

    sizes = int_list("SIZE", None)
    counts = int_list("COUNT", 1)
    if "TYPE" not in vals:
        raise bad("missing TYPE line")
    types = [t.upper() for t in vals["TYPE"]]
    if len(types) != nf:
        raise bad(f"TYPE has {len(types)} entries but FIELDS has {nf}")
    for f, t, s, c in zip(fields, types, sizes, counts):
        if (t, s) not in _TYPES:
            raise bad(f"unsupported TYPE/SIZE {quote(t, 8)}/{s} for field {quote(f)}")
        if c < 1:
            raise bad(f"COUNT {c} for field {quote(f)} must be >= 1")

    def one_int(key: str) -> int | None:
        if key not in vals:
            return None
        items = vals[key]
        if len(items) != 1 or not (items[0].isascii() and items[0].isdigit()):
            raise bad(f"bad {key} value {shown(items)} (expected a non-negative integer)")
        return int(items[0])

    points = one_int("POINTS")
    width, height = one_int("WIDTH"), one_int("HEIGHT")
    if points is None:
        if width is None:
            raise bad("missing POINTS (and WIDTH) line")
        points = width * (height if height is not None else 1)
    elif width is not None and width * (height if height is not None else 1) != points:
        logger.warning("%s: PCD header WIDTH*HEIGHT = %d does not match POINTS = %d; using POINTS",
                       clean(path), width * (height or 1), points)
    data = " ".join(vals["DATA"]).lower()
    if data not in ("ascii", "binary", "binary_compressed"):
        raise bad(f"unknown DATA type {quote(data)} (expected ascii, binary or binary_compressed)")
    viewpoint = None
    if "VIEWPOINT" in vals:
        numbers = [parse_float(w.encode("utf-8")) for w in vals["VIEWPOINT"]]
        if len(numbers) == 7 and all(v is not None and np.isfinite(v) for v in numbers):
            viewpoint = tuple(float(v) for v in numbers if v is not None)
    return _Header(fields, sizes, types, counts, points, data, lineno, viewpoint)


# ----------------------------------------------------------------------------------------------------
# writer
# ----------------------------------------------------------------------------------------------------

_PCD_TYPE = {"f": "F", "i": "I", "u": "U"}
#: PCL's default VIEWPOINT: the sensor at the origin, not turned (tx ty tz qw qx qy qz)
IDENTITY_VIEWPOINT = (0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0)


def _viewpoint(cloud: PointCloud) -> tuple[float, ...]:
    """The VIEWPOINT to write: a PCD source's own (non-identity) one, moved by the transform applied since
    it was read, else PCL's default. The viewpoint is the sensor's pose in the cloud's frame, so it moves
    with the points: its position by the matrix, its orientation by the matrix's rotation (the nearest
    rotation of the linear part). A default viewpoint stays the default: most writers put it there
    without knowing where the sensor was."""
    vp = cloud.meta.get("pcd_viewpoint") if cloud.source_format == "pcd" else None
    if vp is None:
        return IDENTITY_VIEWPOINT
    T = np.asarray(cloud.meta.get("transform", np.eye(4)), dtype=np.float64)
    if np.array_equal(T, np.eye(4)):
        return tuple(vp)
    from scipy.spatial.transform import Rotation

    t = T[:3, :3] @ np.asarray(vp[:3]) + T[:3, 3]
    w, x, y, z = vp[3:]
    turned = T[:3, :3] @ Rotation.from_quat([x, y, z, w]).as_matrix()
    u, _, vt = np.linalg.svd(turned)
    if np.linalg.det(u @ vt) < 0:  # a reflection (an axis flipped): the nearest proper rotation
        u[:, -1] = -u[:, -1]
    qx, qy, qz, qw = Rotation.from_matrix(u @ vt).as_quat()
    return (*map(float, t), float(qw), float(qx), float(qy), float(qz))


#: aligned clouds get float32 coordinates (``write_point_cloud(..., open3d_pcd=True)``) when their
#: rounding stays below this share of the cloud's extent: 10 µm on a 100 m scan, far below any sensor's noise
FLOAT32_TOLERANCE = 1e-7


def float32_is_enough(points: np.ndarray) -> bool:
    """Whether float32 keeps every coordinate of ``points`` within ``FLOAT32_TOLERANCE`` of the cloud's
    extent (its largest bounding-box side): false for UTM-size offsets, true for clouds near the origin."""
    if len(points) == 0:
        return True
    extent = float(np.max(np.ptp(points, axis=0)))
    error = float(np.max(np.abs(points.astype(np.float32).astype(np.float64) - points)))
    return extent > 0 and error <= FLOAT32_TOLERANCE * extent


def _number(v: float) -> str:
    """``v`` as the shortest text that reads back as the same double (``1``, ``0.5``, ``1e-05``)."""
    return str(int(v)) if v.is_integer() and abs(v) < 1e15 else repr(v)


def pcd_chunks(cloud: PointCloud, binary: bool = True, float32: bool = False) -> Iterable[bytes]:
    """A PCD file in pieces (ASCII rows formatted block by block as the file is written): float64 x y z
    plus the 1-D numeric attributes in their own types (``red``/``green``/``blue`` packed into PCL's
    ``rgb`` float, or with an 8-bit ``alpha`` into its ``rgba`` uint32; 16-bit colours as 8-bit); binary,
    or ASCII with ``%.17g``. The VIEWPOINT is a PCD source's own, moved with the points (:func:`_viewpoint`).
    With ``float32`` the coordinates and normals are float32 (Open3D's legacy reader cannot read float64
    binary PCD files; check :func:`float32_is_enough` first). Normals are written as PCL's ``normal_x
    normal_y normal_z``."""
    pts = np.asarray(cloud.points, dtype=np.float64)
    if float32:
        pts = pts.astype(np.float32)
    n = len(pts)
    cols: list[tuple[str, np.ndarray]] = [("x", pts[:, 0]), ("y", pts[:, 1]), ("z", pts[:, 2])]
    normal_names = ("normal_x", "normal_y", "normal_z")
    attrs = eight_bit_colours(named_normals(cloud.attributes, normal_names))
    if float32:  # Open3D reads float64 normals of a binary PCD as zeros too
        attrs.update({k: np.asarray(attrs[k], dtype=np.float32) for k in normal_names if k in attrs})
    if all(k in attrs for k in ("red", "green", "blue")):
        r, g, b = (np.asarray(attrs.pop(k)).astype(np.uint32) & 0xFF for k in ("red", "green", "blue"))
        alpha = np.asarray(attrs.get("alpha", []))
        if alpha.shape == (n,) and alpha.dtype.kind in "ui" and (not n or 0 <= alpha.min() <= alpha.max() <= 255):
            a = attrs.pop("alpha").astype(np.uint32)  # PCL's rgba: a uint32 with alpha in the high byte
            cols.append(("rgba", ((a << 24) | (r << 16) | (g << 8) | b).astype("<u4")))
        else:
            cols.append(("rgb", ((r << 16) | (g << 8) | b).astype("<u4").view("<f4")))
    for name, v in attrs.items():
        v = np.asarray(v)
        if v.shape != (n,) or v.dtype.kind not in "fiub" or name in ("x", "y", "z"):
            continue
        if v.dtype.kind == "b":
            v = v.astype(np.uint8)
        cols.append(("_".join(str(name).split()) or "attr", v.astype(v.dtype.newbyteorder("<"))))
    header = (
        "# .PCD v0.7 - Point Cloud Data file format\nVERSION 0.7\n"
        f"FIELDS {' '.join(c for c, _ in cols)}\n"
        f"SIZE {' '.join(str(v.dtype.itemsize) for _, v in cols)}\n"
        f"TYPE {' '.join(_PCD_TYPE[v.dtype.kind] for _, v in cols)}\n"
        f"COUNT {' '.join('1' for _ in cols)}\n"
        f"WIDTH {n}\nHEIGHT 1\nVIEWPOINT {' '.join(_number(v) for v in _viewpoint(cloud))}\nPOINTS {n}\n"
        f"DATA {'binary' if binary else 'ascii'}\n"
    )
    if binary:
        return [header.encode("ascii"), pack_columns([v for _, v in cols])]
    return itertools.chain([header.encode("ascii")],
                           format_column_blocks([v if name != "rgb" else v.astype(np.float64) for name, v in cols]))
