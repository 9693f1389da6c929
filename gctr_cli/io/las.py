"""LAS and LAZ (laspy, with the lazrs backend for LAZ): reader and writer.

Coordinates are ``X * scale + offset`` computed in float64, so UTM-size offsets keep full precision.
Every point dimension other than X Y Z (intensity, classification, return numbers, colours, GPS time,
extra bytes ...) is kept as an attribute; an extra dimension of k elements (``normals``, 3 doubles) as
k columns ``normals_0 normals_1 normals_2``, which a LAS output of the same source joins again.

Before laspy sees a file, its header is checked here against the file size: the point count times
the record length must fit in an uncompressed LAS file (and in at most :data:`LAZ_MAX_RATIO` times
a LAZ file's compressed point data), so a corrupt count can never allocate more memory than a small
multiple of the file size. Points are read in chunks. The header's count wins over the data: point
records after the declared ones (up to the first EVLR) are named in a warning, and a count of 0 over
records is an error saying so; of a LAZ file only what its chunk table tells is known without
decompressing (a count short by more than one chunk, typically 50,000 points).
"""

from __future__ import annotations

import errno
import io as _stdio
import logging
import math
import os
import re
import signal
import struct
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

from gctr_cli.io.cloud import PointCloud, ascii_name, element_columns, integer_misfit, unique_name
from gctr_cli.io.errors import PointCloudError, clean, quote

__all__ = ["crs_description", "las_bytes", "read_las"]

logger = logging.getLogger("gctr_cli.io")

#: a LAZ file's point data decompresses to at most this many times its size (LASzip reaches 5-15x
#: on real data and about 50x on constant points)
LAZ_MAX_RATIO = 200
CHUNK_POINTS = 1 << 20
#: smallest record length of each LAS point format
_MIN_RECORD = {0: 20, 1: 28, 2: 26, 3: 34, 4: 57, 5: 63, 6: 30, 7: 36, 8: 38, 9: 59, 10: 67}


def _check_header(path: Path, head: bytes, size: int, compressed_ext: bool) -> tuple[int, bool]:
    """Validate the fixed LAS header against the file size; return (point count, compressed)."""
    if head[:4] != b"LASF":
        raise PointCloudError(f"{path}: not a LAS/LAZ file (missing 'LASF' signature)")
    if len(head) < 227:
        raise PointCloudError(f"{path}: truncated LAS file: {size} bytes, but the LAS header alone takes 227")
    major, minor = head[24], head[25]
    if major != 1 or minor > 4:
        raise PointCloudError(f"{path}: unsupported LAS version {major}.{minor} (1.0 to 1.4 are read)")
    header_size, offset_to_points = struct.unpack_from("<HI", head, 94)
    fmt_byte, record_len, legacy_count = struct.unpack_from("<BHI", head, 104)
    compressed = bool(fmt_byte & 0x80)
    fmt = fmt_byte & 0x3F
    if header_size < 227 or offset_to_points < header_size or offset_to_points > size:
        raise PointCloudError(
            f"{path}: corrupt LAS header: the point data would start at byte {offset_to_points} "
            f"(header size {header_size}, file size {size})"
        )
    if fmt not in _MIN_RECORD or record_len < _MIN_RECORD[fmt]:
        raise PointCloudError(
            f"{path}: corrupt LAS header: point format {fmt} with records of {record_len} bytes"
        )
    count = legacy_count
    if minor >= 4 and len(head) >= 375:
        (count64,) = struct.unpack_from("<Q", head, 247)
        count = count64 or legacy_count
    scales = struct.unpack_from("<3d", head, 131)
    offsets = struct.unpack_from("<3d", head, 155)
    if not all(math.isfinite(s) and s != 0 for s in scales) or not all(math.isfinite(o) for o in offsets):
        raise PointCloudError(f"{path}: corrupt LAS header: scale factors must be finite and non-zero, "
                              "offsets finite")
    data = size - offset_to_points
    need = count * record_len
    if compressed or compressed_ext:
        if need > LAZ_MAX_RATIO * data + 1_000_000:
            raise PointCloudError(
                f"{path}: corrupt LAZ header: it declares {count} points ({need} bytes uncompressed) but "
                f"holds only {data} bytes of compressed point data"
            )
    elif need > data:
        raise PointCloudError(
            f"{path}: truncated: the header declares {count} points of {record_len} bytes but only "
            f"{data} bytes of point data follow the header (expected {need})"
        )
    return count, compressed


def _records_after(head: bytes, size: int, count: int) -> int:
    """Whole point records between the end of the ``count`` declared points of an uncompressed LAS file
    and the end of its point data: the first EVLR (LAS 1.4), the waveform data (LAS 1.3), else the end
    of the file."""
    offset_to_points, record_len = struct.unpack_from("<I", head, 96)[0], struct.unpack_from("<H", head, 105)[0]
    declared_end = offset_to_points + count * record_len
    end = size
    if head[25] >= 3 and len(head) >= 235:
        (waveform,) = struct.unpack_from("<Q", head, 227)
        if declared_end <= waveform < end:
            end = waveform
    if head[25] >= 4 and len(head) >= 247:
        evlr_start, n_evlrs = struct.unpack_from("<QI", head, 235)
        if n_evlrs and declared_end <= evlr_start < end:
            end = evlr_start
    return max(end - declared_end, 0) // record_len


def _laz_chunk_table_offset(fh, head: bytes) -> int | None:
    """Where a LAZ file's chunk table starts, as the 8 bytes at the start of its point data say; None when
    they do not say (-1: written to a stream, with the offset at the end of the file). A file cut short
    (an interrupted copy) ends before it: said as such, where lazrs only fails to decompress."""
    (offset_to_points,) = struct.unpack_from("<I", head, 96)
    fh.seek(offset_to_points)
    raw = fh.read(8)
    table = struct.unpack("<q", raw)[0] if len(raw) == 8 else -1
    return None if table == -1 else table


def _laz_points_at_least(fh, head: bytes, size: int) -> int | None:
    """A lower bound of the points a LAZ file holds, from its chunk table: more than ``chunks - 1`` chunks
    of the LASzip record's chunk size. None when that cannot be told from a few bytes (variable-size
    chunks, no chunk table, an odd header): the chunks' point counts are known only by decompressing."""
    header_size, offset_to_points, n_vlrs = struct.unpack_from("<HII", head, 94)
    fh.seek(header_size)
    vlrs = fh.read(offset_to_points - header_size)
    chunk_size, pos = None, 0
    for _ in range(n_vlrs):  # VLR header: reserved, user id (16 bytes), record id, length, description
        if pos + 54 > len(vlrs):
            return None
        record_id, length = struct.unpack_from("<HH", vlrs, pos + 18)
        if pos + 54 + length > len(vlrs):
            return None
        if vlrs[pos + 2 : pos + 18].rstrip(b"\0") == b"laszip encoded" and record_id == 22204 and length >= 16:
            (chunk_size,) = struct.unpack_from("<I", vlrs, pos + 54 + 12)
        pos += 54 + length
    if not chunk_size or chunk_size == 0xFFFFFFFF:
        return None
    fh.seek(offset_to_points)
    raw = fh.read(8)
    table = struct.unpack("<q", raw)[0] if len(raw) == 8 else -1
    if table == -1 and size >= 8:  # written to a stream: the table's offset is in the file's last 8 bytes
        fh.seek(size - 8)
        table = struct.unpack("<q", fh.read(8))[0]
    if not offset_to_points + 8 <= table <= size - 8:
        return None
    fh.seek(table)
    version, chunks = struct.unpack("<II", fh.read(8))
    if version != 0 or not 0 < chunks <= size - offset_to_points:
        return None
    return (chunks - 1) * chunk_size + 1


def _say_records_after(path: Path, count: int, extra: int, at_least: str = "") -> None:
    """The error (no point declared) or warning (more points than declared) for ``extra`` point records
    after the header's ``count``: the header wins, as for the text formats, but not without a word."""
    if not extra:
        return
    if count == 0:
        raise PointCloudError(f"{path}: the header declares 0 points but {at_least}{extra} point records follow "
                              "(a writer that never filled in the point count?)")
    logger.warning("%s: %s%d more point records after the %d points the header declares (ignored)", clean(path),
                   at_least, extra, count)


def read_las(path: Path, fh, size: int, attributes: bool = True) -> PointCloud:
    head = fh.read(375)
    count, compressed = _check_header(path, head, size, path.suffix.lower() == ".laz")
    if not compressed:
        _say_records_after(path, count, _records_after(head, size, count))
        fh.seek(0)
        return _read_points(path, fh, count, compressed, attributes)
    table = _laz_chunk_table_offset(fh, head)
    if table is not None and table > size - 8:
        raise PointCloudError(f"{path}: truncated or corrupt LAZ file: its chunk table should start at byte {table} "
                              f"but the file has only {size} bytes (an interrupted copy or download?)")
    present = _laz_points_at_least(fh, head, size)
    _say_records_after(path, count, max((present or 0) - count, 0), "at least ")
    raw_bytes = count * int.from_bytes(head[105:107], "little")
    try:
        tmp_dir = tempfile.TemporaryDirectory(prefix="gctr-laz-")
    except OSError as exc:
        raise PointCloudError(f"{path}: cannot decompress the LAZ file: cannot create a temporary folder in "
                              f"{clean(tempfile.gettempdir())} ({exc.strerror or 'operating system error'}; set "
                              "TMPDIR to a writable folder with room)") from None
    with tmp_dir as tmp:
        plain = _decompress_isolated(path, Path(tmp), raw_bytes)
        with open(plain, "rb") as fh2:
            plain_size = os.fstat(fh2.fileno()).st_size
            count2, _ = _check_header(path, fh2.read(375), plain_size, False)
            if count2 != count:
                raise PointCloudError(f"{path}: corrupt LAZ file: the header declares {count} points but the "
                                      f"data decompresses to {count2}")
            fh2.seek(0)
            return _read_points(path, fh2, count, True, attributes)


#: exit codes of the decompressing child: done, corrupt data, no room for / no right to write the copy
_CHILD_OK, _CHILD_CORRUPT, _CHILD_NO_SPACE, _CHILD_NO_PERMISSION = 0, 3, 4, 5
_NO_SPACE = {errno.ENOSPC, errno.EFBIG, errno.EDQUOT}
_NO_PERMISSION = {errno.EACCES, errno.EPERM, errno.EROFS}


def _child_code(exc: BaseException) -> int:
    """The child's exit code for ``exc``: a full disk or file-size limit (``ulimit -f``) or a refused
    write anywhere in its chain (laspy's writer may raise again while closing), else corrupt data."""
    seen: BaseException | None = exc
    while seen is not None:
        if isinstance(seen, OSError) and seen.errno in _NO_SPACE:
            return _CHILD_NO_SPACE
        if isinstance(seen, OSError) and seen.errno in _NO_PERMISSION:
            return _CHILD_NO_PERMISSION
        seen = seen.__cause__ or seen.__context__
    return _CHILD_CORRUPT


def _decompress_isolated(path: Path, tmp: Path, raw_bytes: int) -> Path:
    """Decompress a LAZ file to a plain LAS file in a forked child process.

    lazrs *aborts the process* on some corrupt files (e.g. a garbage chunk count asks for 60 GB, and
    Rust aborts when an allocation fails), so a corrupt LAZ must not be decoded in the process that
    reports the error. The child's address space is capped at its current size plus a few times the
    declared point data; a crash, a refused allocation or a hang becomes a :class:`PointCloudError`.
    The child writes the copy to ``tmp`` and says by its exit code (:func:`_child_code`) whether it failed
    for want of room or rights there, which is not the file's fault and is said so.
    Where ``fork`` is unavailable the file is decoded in-process.
    """
    out = tmp / "points.las"
    if not hasattr(os, "fork"):  # pragma: no cover - Windows
        _decompress(path, out)
        return out
    limit = _current_vm_bytes() + 4 * raw_bytes + (768 << 20)
    pid = os.fork()
    if pid == 0:  # child: never returns
        code = 3
        try:
            # a crash report of the child (Rust's allocation failure, faulthandler) is not for the user
            null = os.open(os.devnull, os.O_WRONLY)
            os.dup2(null, 2)
            try:
                import faulthandler

                faulthandler.disable()
            except Exception:  # noqa: BLE001
                pass
            try:
                import resource

                resource.setrlimit(resource.RLIMIT_AS, (limit, limit))
            except (ImportError, ValueError, OSError):
                pass
            _decompress(path, out)
            code = _CHILD_OK
        except BaseException as exc:  # noqa: BLE001
            code = _child_code(exc)
        finally:
            os._exit(code)
    deadline = time.monotonic() + 60 + raw_bytes / 20e6
    while True:
        done, status = os.waitpid(pid, os.WNOHANG)
        if done:
            break
        if time.monotonic() > deadline:
            os.kill(pid, signal.SIGKILL)
            os.waitpid(pid, 0)
            raise PointCloudError(f"{path}: corrupt LAZ file: decompressing the point data did not finish")
        time.sleep(0.005)
    exit_code = os.WEXITSTATUS(status) if os.WIFEXITED(status) else None
    # a batch worker's own folder (gctr-worker-*, removed with it) lies in the TMPDIR the user set: name that
    where = clean(tmp.parent.parent if tmp.parent.name.startswith("gctr-worker-") else tmp.parent)
    if exit_code == _CHILD_NO_SPACE:
        need = max(1, math.ceil((raw_bytes + 65536) / 1e6))
        raise PointCloudError(f"{path}: cannot decompress the LAZ file: no space for its temporary copy in {where} "
                              f"(needs about {need} MB; set TMPDIR to a folder with room)")
    if exit_code == _CHILD_NO_PERMISSION:
        raise PointCloudError(f"{path}: cannot decompress the LAZ file: no permission to write its temporary copy "
                              f"in {where} (set TMPDIR to a writable folder)")
    if not (exit_code == _CHILD_OK and out.exists()):
        raise PointCloudError(f"{path}: corrupt or unsupported LAZ file: the point data cannot be decompressed")
    return out


def _decompress(path: Path, out: Path) -> None:
    import laspy

    # single-threaded lazrs: thread pools and their malloc arenas would make the address-space cap
    # depend on the number of cores
    las = laspy.read(str(path), laz_backend=laspy.LazBackend.Lazrs)
    las.write(str(out), do_compress=False)


def _current_vm_bytes() -> int:
    try:
        with open("/proc/self/status", "rb") as fh:
            for line in fh:
                if line.startswith(b"VmSize:"):
                    return int(line.split()[1]) * 1024
    except (OSError, ValueError, IndexError):
        pass
    return 8 << 30


def _read_points(path: Path, fh, count: int, compressed: bool, attributes: bool) -> PointCloud:
    """The points of an uncompressed LAS file object (its header already checked), in chunks."""
    import laspy

    try:
        with laspy.open(fh, closefd=False) as reader:
            hdr = reader.header
            names = [n for n in reader.header.point_format.dimension_names if n not in ("X", "Y", "Z")]
            pts = np.empty((count, 3), dtype=np.float64)
            attrs: dict[str, list[np.ndarray]] = {n: [] for n in names} if attributes else {}
            got = 0
            scales, offsets = np.asarray(hdr.scales, np.float64), np.asarray(hdr.offsets, np.float64)
            for chunk in reader.chunk_iterator(CHUNK_POINTS):
                k = len(chunk)
                if got + k > count:
                    raise PointCloudError(f"{path}: corrupt LAS/LAZ file: more points than the header declares")
                for j, dim in enumerate(("X", "Y", "Z")):
                    raw = np.asarray(chunk[dim], dtype=np.int64)
                    pts[got : got + k, j] = raw * scales[j] + offsets[j]
                for n in attrs:
                    attrs[n].append(np.array(chunk[n]))
                got += k
    except PointCloudError:
        raise
    except MemoryError:
        raise PointCloudError(f"{path}: too large to load into memory ({count} points)") from None
    except Exception as exc:  # laspy/lazrs errors carry library text; say it in words
        logger.debug("%s: laspy failed", path, exc_info=exc)
        what = "LAZ point data cannot be decompressed" if compressed else "LAS point data cannot be decoded"
        raise PointCloudError(f"{path}: corrupt or unsupported LAS/LAZ file: the {what}") from None
    if got != count:
        raise PointCloudError(f"{path}: truncated: the header declares {count} points but only {got} could be read")
    out: dict[str, np.ndarray] = {}
    for name, parts in attrs.items():
        v: np.ndarray = np.concatenate(parts) if parts else np.empty(0)
        if v.ndim == 2:  # an extra dimension of several elements (normals '3f8'): one column each
            out.update({col: v[:, j] for j, col in enumerate(element_columns(name, v.shape[1]))})
        elif len(v) == count:
            out[name] = v
    # the whole header: a LAS/LAZ writer carries its CRS records, encoding bits and ids (:func:`las_bytes`)
    meta = {"las_header": hdr}
    return PointCloud(pts, out, "las", meta)


# ----------------------------------------------------------------------------------------------------
# writer
# ----------------------------------------------------------------------------------------------------

_RGB = ("red", "green", "blue")


def _scale_offset(values: np.ndarray) -> tuple[float, float]:
    """The smallest power-of-ten scale that spreads the axis over at most 2e9 integer steps (int32),
    and an offset near its minimum: the quantisation error is at most half a step, i.e. at most
    span / 4e8 (2.5 µm on a 1 km tile)."""
    lo, hi = float(values.min()), float(values.max())
    span = max(hi - lo, abs(lo) * 1e-12, 1e-9)
    scale = 10.0 ** math.ceil(math.log10(span / 2e9))
    offset = math.floor(lo / scale / 1000) * scale * 1000
    return scale, offset


def _nice_scale(x: float) -> float:
    """The largest 1, 2 or 5 × 10^k not above ``x`` (1 % slack: a registration's scale of 0.9999 keeps a
    millimetre grid instead of halving it)."""
    k = math.floor(math.log10(x))
    for m in (10, 5, 2, 1):
        v = m * 10.0**k if k >= 0 else m / 10.0**-k  # 1 / 1000, not 1 * 1e-3: the same double as 0.001
        if v <= x * 1.01:
            return v
    return 10.0**k  # pragma: no cover - 1 × 10^k <= x


def _fits_int32(values: np.ndarray, scale: float, offset: float) -> bool:
    ints = np.round((values - offset) / scale)
    return bool(ints.min() >= -(2**31) and ints.max() <= 2**31 - 1)


def _source_scales_offsets(pts: np.ndarray, source: Any, transform: np.ndarray) -> list[tuple[float, float]]:
    """Scale and offset per axis for a cloud read from the LAS ``source`` header and since moved by
    ``transform``: its coordinates are no finer than the source's quantum times the transform's stretch
    of that axis (its scale factor, for a similarity), so that (rounded down to 1, 2 or 5 × 10^k; after a
    rotation, the finest of the source axes an output axis mixes) keeps them without inventing digits, and
    the file stays as small as the source. The offset is the source's when every coordinate fits in int32
    with it (an identity apply rewrites the same integers), else a multiple of 1000 steps below the axis's
    minimum; an axis that still does not fit gets :func:`_scale_offset`'s."""
    A = np.asarray(transform, dtype=np.float64)[:3, :3]
    s = abs(float(np.linalg.det(A))) ** (1 / 3)
    src_scales = np.abs(np.asarray(source.scales, dtype=np.float64))
    reach = np.abs(A) > 1e-9 * s  # the source axes each output axis is made of
    # each output axis by its own stretch (its row's length: s for a similarity), so that an axis shrunk
    # more than the others (feet to metres in z only) keeps its digits
    finest = np.linalg.norm(A, axis=1) * np.where(reach, src_scales[None, :], np.inf).min(axis=1)
    out = []
    for j in range(3):
        values = pts[:, j]
        if not (s > 0 and math.isfinite(finest[j]) and finest[j] > 0):
            out.append(_scale_offset(values))
            continue
        scale = _nice_scale(float(finest[j]))
        step = 1000 * scale
        for offset in (float(source.offsets[j]), math.floor(float(values.min()) / step) * step):
            if _fits_int32(values, scale, offset):
                out.append((scale, offset))
                break
        else:
            out.append(_scale_offset(values))
    return out


#: the range of a Leica PTS intensity (a cloud read from a ``.pts`` file has ``meta["pts_intensity"]``)
PTS_INTENSITY = (-2048, 2047)


def _unit_intensity(name: str, values: np.ndarray) -> bool:
    """Whether ``values`` are an intensity in [0, 1] (E57's and Open3D's convention), which LAS stretches."""
    return bool(name == "intensity" and values.dtype.kind == "f" and len(values) and np.isfinite(values).all()
                and values.min() >= 0.0 and values.max() <= 1.0)


def _fit_dimension(name: str, values: np.ndarray, dim: Any, where: str, pts: bool = False) -> np.ndarray | None:
    """``values`` as LAS dimension ``dim`` holds them, or None (with a warning naming the file
    ``where`` and the attribute) when they do not fit: laspy would wrap 70000 to 4464 and truncate
    0.37 to 0 without a word. A float intensity in [0, 1] (E57's and Open3D's convention) is
    stretched to LAS's 0..65535; the intensity of a ``.pts`` file (``pts``), whole numbers in -2048..2047 by
    Leica's convention, is shifted and stretched to 0..65520 (every value, whatever its sign: scans of one
    project keep one mapping), with a warning."""
    if values.dtype.kind not in "fiub":
        logger.warning("%s: attribute %r is not numeric; LAS dimension %r not written", where, name, name)
        return None
    if dim.kind.name == "FloatingPoint":
        return values
    if _unit_intensity(name, values):
        return np.round(values.astype(np.float64) * dim.max).astype(np.uint16)
    if pts and name == "intensity" and len(values) and integer_misfit(values, *PTS_INTENSITY) is None:
        logger.warning("%s: intensity -2048..2047 (the PTS convention) written as (value + 2048) x 16, "
                       "LAS's 0..65535", where)
        return ((values.astype(np.int64) - PTS_INTENSITY[0]) * 16).astype(np.uint16)
    misfit = integer_misfit(values, int(dim.min), int(dim.max))
    if misfit is not None:
        logger.warning("%s: attribute %r holds a value LAS dimension %r cannot (%s; it holds whole numbers "
                       "%d..%d); not written", where, name, name, misfit, dim.min, dim.max)
        return None
    return values


#: (user id, record id) of the records laspy writes itself from the new file's layout (extra bytes, LASzip)
_REBUILT = {("LASF_Spec", 4), ("laszip encoded", 22204)}
#: records that index the source file's point layout or hold data beside the points: wrong or lost once
#: the points are rewritten, so not copied
_STALE = {("copc", 1): "the COPC info record", ("copc", 1000): "the COPC hierarchy record",
          ("LAStools", 30): "the LAStools spatial index", ("LASF_Spec", 65535): "the waveform data"}
#: record ids of user id ``LASF_Projection`` that hold a coordinate reference system
_CRS_RECORDS = {34735, 34736, 34737, 2111, 2112}


def _record_bytes(vlr: Any) -> bytes:
    return bytes(vlr.record_data_bytes())


def crs_description(header: Any) -> str | None:
    """A short name of the coordinate reference system the LAS ``header``'s records hold (``WKT 'WGS 84 /
    UTM zone 33N'``, ``GeoTIFF keys, EPSG 32633``), or None when it has no CRS record; for messages."""
    records = [v for v in [*header.vlrs, *(header.evlrs or [])]
               if v.user_id == "LASF_Projection" and v.record_id in _CRS_RECORDS]
    if not records:
        return None
    wkt = next((v for v in records if v.record_id == 2112), None)
    if wkt is not None:
        text = _record_bytes(wkt).decode("latin-1").strip("\0 ")
        name = re.match(r'\s*\w+\s*\[\s*"([^"]*)"', text)
        return f"WKT {quote(name.group(1), 60)}" if name else "WKT"
    keys = next((v for v in records if v.record_id == 34735), None)
    if keys is not None:
        raw = _record_bytes(keys)
        # rows of 4 shorts: the directory header, then entries (key id, location, count, value); location
        # 0: the value itself
        shorts = np.frombuffer(raw[: len(raw) // 8 * 8], dtype="<u2").reshape(-1, 4)
        for entry in shorts[1:]:
            if entry[0] in (3072, 2048) and entry[1] == 0 and 0 < entry[3] < 32767:
                return f"GeoTIFF keys, EPSG {int(entry[3])}"
    return "GeoTIFF keys"


def _copyable_records(records: Any, extended: bool, dropped: list[str]) -> list[Any]:
    """The ``records`` (VLRs, or EVLRs with ``extended``) a new file can carry, as raw laspy VLRs with the
    bytes read (no re-encoding by laspy's record classes); what is left out is added to ``dropped``."""
    import laspy
    from laspy.vlrs.vlrlist import VLRList

    kept = []
    for v in records or ():
        key = (v.user_id, v.record_id)
        if key in _REBUILT:
            continue
        if key in _STALE:
            dropped.append(_STALE[key])
            continue
        try:
            raw = laspy.VLR(v.user_id, v.record_id, v.description, _record_bytes(v))
            VLRList([raw]).write_to(_stdio.BytesIO(), as_extended=extended)
        except Exception as exc:  # laspy's text is not for users
            logger.debug("record %r %s cannot be written", v.user_id, v.record_id, exc_info=exc)
            dropped.append(f"record {quote(v.user_id, 20)} {v.record_id} (laspy cannot write it)")
            continue
        kept.append(raw)
    return kept


def _carry_header(header: Any, source: Any, where: str) -> None:
    """Copy into the new ``header`` what the ``source`` LAS header says about the data: every VLR and EVLR
    (the coordinate reference system above all), the global-encoding bits (GPS time type, WKT, synthetic
    return numbers), the system identifier, file source id and project GUID.

    The CRS records are the *source's*: the matrix puts the source into the target's frame, and a
    registration within one georeferenced frame (the usual case: scans of one project, tiles of one
    survey) keeps that frame's CRS. Records laspy writes itself (extra bytes, LASzip) are rebuilt; those
    that index the source's point layout (COPC, LAStools spatial index) or hold its waveform data would
    be wrong in the new file and are left out, with one warning naming them."""
    from laspy.header import GlobalEncoding
    from laspy.vlrs.vlrlist import VLRList

    dropped: list[str] = []
    header.vlrs = VLRList(_copyable_records(source.vlrs, False, dropped))
    evlrs = source.evlrs or []
    if header.version.minor >= 4:
        header.evlrs = VLRList(_copyable_records(evlrs, True, dropped)) or None
    elif evlrs:  # pragma: no cover - only 1.4 sources have EVLRs, and they keep 1.4
        dropped.append(f"{len(evlrs)} extended records (LAS {header.version} has none)")
    encoding = int(source.global_encoding.value)
    if encoding & GlobalEncoding.WAVEFORM_INTERNAL_MASK:
        encoding &= ~GlobalEncoding.WAVEFORM_INTERNAL_MASK
        if "the waveform data" not in dropped:
            dropped.append("the waveform data")
    header.global_encoding.value = encoding
    header.system_identifier = source.system_identifier
    header.file_source_id = source.file_source_id
    header.uuid = source.uuid
    if dropped:
        logger.warning("%s: not kept from the LAS source: %s", where, ", ".join(dict.fromkeys(dropped)))


#: a scan angle of point formats 6-10 counts steps of this many degrees; formats 0-5 store whole degrees
SCAN_ANGLE_STEP = 0.006


def _scan_angle_as(standard: set[str], attrs: dict[str, np.ndarray]) -> None:
    """Put the scan angle into the field the output point format has: ``scan_angle_rank`` (whole
    degrees, formats 0-5) or ``scan_angle`` (0.006° steps, formats 6-10), instead of writing one as an
    extra dimension and leaving the other 0."""
    if "scan_angle_rank" in attrs and "scan_angle_rank" not in standard and "scan_angle" not in attrs:
        attrs["scan_angle"] = np.round(attrs.pop("scan_angle_rank").astype(np.float64) / SCAN_ANGLE_STEP)
    elif "scan_angle" in attrs and "scan_angle" not in standard and "scan_angle_rank" not in attrs:
        attrs["scan_angle_rank"] = np.round(attrs.pop("scan_angle").astype(np.float64) * SCAN_ANGLE_STEP)


def _join_elements(source_extra: dict[str, Any], attrs: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    """``attrs`` with the columns ``name_0 name_1 ...`` the reader made of a source extra dimension of
    several elements put back together in the first one's place, so that it is written as it was read
    (``normals`` as one '3f8' dimension)."""
    joined = {}
    for name, dim in source_extra.items():
        parts = element_columns(name, dim.num_elements)
        if dim.num_elements > 1 and name not in attrs and all(p in attrs for p in parts):
            joined[parts[0]] = (name, parts)
    out = {}
    for k, v in attrs.items():
        if k in joined:
            name, parts = joined[k]
            out[name] = np.stack([attrs[p] for p in parts], axis=1)
        elif not any(k in parts for _, parts in joined.values()):
            out[k] = v
    return out


#: the longest name a LAS extra dimension can have (bytes of its ExtraBytes record)
EXTRA_NAME_BYTES = 32


def _fits(name: str, values: np.ndarray, dim: Any) -> bool:
    """Whether :func:`_fit_dimension` takes ``values`` for ``dim`` (without its warnings)."""
    if values.dtype.kind not in "fiub":
        return False
    if dim.kind.name == "FloatingPoint":
        return True
    if _unit_intensity(name, values):
        return True
    return integer_misfit(values, int(dim.min), int(dim.max)) is None


def _standard_case(names: set[str], attrs: dict[str, np.ndarray], point_format: Any = None) -> dict[str, np.ndarray]:
    """``attrs`` with a name that is one of ``names`` (standard LAS dimensions) but for its case
    (``Intensity``, ``Red`` of a PLY or PCD) under that name, so that it fills the standard dimension
    instead of an extra one. Not when the standard name is taken too, nor (given the ``point_format``)
    when the values do not fit the dimension: they are kept as an extra dimension then."""
    out = {}
    for k, v in attrs.items():
        low = k.lower()
        use = (k not in names and low in names and low not in attrs and low not in out
               and (point_format is None or _fits(low, v, point_format.dimension_by_name(low))))
        out[low if use else k] = v
    return out


def _extra_names(standard: set[str], attrs: dict[str, np.ndarray],
                 where: str) -> tuple[dict[str, np.ndarray], dict[str, str]]:
    """``attrs`` with every name that will be an extra dimension made an ASCII identifier of at most
    :data:`EXTRA_NAME_BYTES` (a CloudCompare scalar field such as ``scalar_C2C_absolute_distances_(XY)``
    is neither; ``intensité`` becomes ``intensite``), distinct from every other name, the coordinates'
    and the standard dimensions' (``(z)`` is ``z_2``, not ``z``); and the map from each new name to the
    old one. The renamed ones are named in one warning."""
    taken = set(attrs) | set(standard) | {"X", "Y", "Z", "x", "y", "z"}
    renamed = {}
    for k, v in attrs.items():
        if k in standard or k in ("X", "Y", "Z", "x", "y", "z") or v.dtype.kind not in "fiu":
            continue
        new = k if k.isidentifier() and k.isascii() else re.sub(r"_*\W+_*", "_", ascii_name(k)).strip("_")
        new = new or "attribute"
        new = "_" + new if new[0].isdigit() else new
        new = new[:EXTRA_NAME_BYTES]
        if new == k:
            continue
        new = unique_name(new, taken, EXTRA_NAME_BYTES)
        taken.add(new)
        renamed[k] = new
    if renamed:
        logger.warning("%s: attribute names changed for LAS extra dimensions (at most %d bytes of ASCII letters, "
                       "digits and _, unlike the standard dimensions' names): %s", where, EXTRA_NAME_BYTES,
                       ", ".join(f"{k!r} as {v!r}" for k, v in renamed.items()))
    return {renamed.get(k, k): v for k, v in attrs.items()}, {v: k for k, v in renamed.items()}


def _extra_dim(name: str, values: np.ndarray, source_dim: Any) -> Any:
    """The extra dimension for ``values``: the source's own declaration (type, scale, offset, description)
    when it had one of that name and shape, else one of the values' type."""
    import laspy

    elements = values.shape[1] if values.ndim == 2 else 1
    if source_dim is not None and source_dim.num_elements == elements and source_dim.dtype is not None:
        return laspy.ExtraBytesParams(name=name, type=source_dim.dtype, description=source_dim.description,
                                      offsets=source_dim.offsets, scales=source_dim.scales,
                                      no_data=source_dim.no_data)
    kind = values.dtype.str[1:]  # "f8"
    return laspy.ExtraBytesParams(name=name, type=kind if elements == 1 else f"{elements}{kind}")


def las_bytes(cloud: PointCloud, compress: bool, path: Path | None = None) -> bytes:
    """The bytes of a LAS file (LAZ when ``compress``).

    From a LAS/LAZ source the file keeps the source's version and point format (unless the cloud has
    colours the format lacks), what its header says about the data (:func:`_carry_header`: CRS
    records, GPS time type, system identifier ...) and its quantum (:func:`_source_scales_offsets`).
    Otherwise it is LAS 1.4 point format 6, or 7 with colours, quantised by :func:`_scale_offset`.
    Attributes matching a standard dimension fill it (8-bit colours are widened to LAS's 16 bits), other
    numeric attributes become extra bytes."""
    import laspy

    pts = np.asarray(cloud.points, dtype=np.float64)
    n = len(pts)
    where = clean(path) if path is not None else "LAS output"
    attrs = {k: np.asarray(v) for k, v in cloud.attributes.items() if np.asarray(v).shape == (n,)}
    # flags as 0/1; LAS extra bytes have no 16-bit float
    attrs = {k: v.astype(np.uint8) if v.dtype.kind == "b" else v.astype(np.float32) if v.dtype == np.float16 else v
             for k, v in attrs.items()}
    source = cloud.meta.get("las_header") if cloud.source_format == "las" else None
    if source is None and len({k.lower() for k in attrs} & set(_RGB)) == 3 and not set(_RGB) & set(attrs):
        mapped = _standard_case(set(_RGB), attrs, laspy.PointFormat(7))
        if set(_RGB) <= set(mapped):  # ``Red Green Blue`` that fit LAS colours: a point format with colours
            attrs = mapped
    has_rgb = all(k in attrs for k in _RGB)
    if source is not None and (not has_rgb or "red" in source.point_format.dimension_names):
        # laspy writes LAS 1.1-1.4; 1.2 has the point formats of 1.0 (0 and 1) and the same header
        version = "1.2" if str(source.version) == "1.0" else str(source.version)
        header = laspy.LasHeader(point_format=int(source.point_format.id), version=version)
    else:
        header = laspy.LasHeader(point_format=7 if has_rgb else 6, version="1.4")
    if source is not None:
        _carry_header(header, source, where)
    standard = set(header.point_format.dimension_names)
    if source is None:  # a LAS source's own extra dimensions stay what they were
        attrs = _standard_case(standard, attrs, header.point_format)
    _scan_angle_as(standard, attrs)
    source_extra = {d.name: d for d in source.point_format.extra_dimensions} if source is not None else {}
    attrs = _join_elements(source_extra, attrs)
    attrs, old_names = _extra_names(standard, attrs, where)
    extra = [k for k, v in attrs.items() if k not in standard and v.dtype.kind in "fiu" and k.isidentifier()]
    for k in sorted(attrs.keys() - standard - set(extra) - {"X", "Y", "Z", "x", "y", "z"}):
        logger.warning("%s: attribute %r not written (LAS extra bytes hold numbers)", where, k)
    if extra:
        header.add_extra_dims([_extra_dim(k, attrs[k], source_extra.get(old_names.get(k, k))) for k in extra])
    if not n:
        so = [(0.001, 0.0)] * 3
    elif source is not None:
        so = _source_scales_offsets(pts, source, cloud.meta.get("transform", np.eye(4)))
    else:
        so = [_scale_offset(pts[:, j]) for j in range(3)]
    header.scales = np.array([s for s, _ in so])
    header.offsets = np.array([o for _, o in so])
    las = laspy.LasData(header)
    for j, dim in enumerate(("X", "Y", "Z")):
        ints = np.round((pts[:, j] - so[j][1]) / so[j][0])
        las[dim] = ints.astype(np.int32)
    for k, v in attrs.items():
        if k in ("X", "Y", "Z", "x", "y", "z"):
            continue
        if k in standard:
            if k in _RGB and v.dtype == np.uint8:
                v = v.astype(np.uint16) * 257
            fitted = _fit_dimension(k, v, header.point_format.dimension_by_name(k), where,
                                    bool(cloud.meta.get("pts_intensity")))
            if fitted is not None:
                las[k] = fitted
        elif k in extra:
            las[k] = v
    buf = _stdio.BytesIO()
    las.write(buf, do_compress=compress)
    return buf.getvalue()
