"""Point cloud and transform-matrix I/O with strict validation.

Public API (the rest of gctr and user scripts use only these names):

* :func:`load_point_cloud` — a validated ``(N, 3)`` float64 array of a cloud file;
  :func:`read_point_cloud` — the same as a :class:`PointCloud` with its per-point attributes.
* :func:`write_point_cloud` / :func:`save_point_cloud` — write a cloud (format by extension).
* :func:`write_aligned` — read a cloud, move it by a 4x4 similarity, write it (``gctr apply``,
  ``gctr register --aligned``; the one call the batch runner needs for aligned outputs).
* :func:`read_matrix`, :func:`write_matrix`, :func:`format_matrix` — 4x4 matrices (GUIDE §1).
* :class:`PointCloudError`, :class:`MatrixError` — every problem, with a message that names the
  path the user wrote and says what is wrong in words.

Formats (one module each, chosen by the extension of the name the user gave: a link named
``scan.ply`` to an extension-less cache file is read as PLY):

====================  ===========================  ==========================================
extension             read                         write
====================  ===========================  ==========================================
``.ply``              ASCII, binary LE/BE          binary LE, float64 x y z + attributes
``.pcd``              ascii, binary, compressed    binary float64 x y z + attributes (aligned
                                                   clouds: binary float32, or ASCII float64)
``.xyz .txt .pts``    text columns (+ attributes)  ``%.17g`` text (+ attribute columns; .pts:
``.csv``              (quoted cells too)           intensity, red green blue; .csv: a
                                                   ``x,y,z,...`` header, commas)
``.las .laz``         LAS 1.0-1.4, LAZ (lazrs)     LAS/LAZ 1.4 with attributes; from a LAS
                                                   source: its version, point format, CRS
                                                   records and header ids
``.e57``              all scans, poses applied     --
====================  ===========================  ==========================================

Open3D only *warns* on unreadable files and hands back an empty cloud, so gctr parses the formats
itself and checks what it reads: declared sizes are checked against the file size before anything
is allocated, so memory stays within a small multiple of the file size; non-finite points are
dropped with a warning; too few points, all-identical points and collinear points are errors.
"""

from __future__ import annotations

import contextlib
import dataclasses
import logging
import os
import threading
from collections.abc import Iterable
from pathlib import Path

import numpy as np

from gctr_cli.fsutil import atomic_write, write_error
from gctr_cli.io.cloud import COLLINEAR_RTOL, PointCloud, ascii_attribute_names, transform_cloud, validate_cloud
from gctr_cli.io.errors import MatrixError, PointCloudError, clean
from gctr_cli.io.matrix import format_matrix, read_matrix, write_matrix
from gctr_cli.io.paths import check_input_file
from gctr_cli.io.registry import FORMATS, READ_EXTENSIONS, WRITE_EXTENSIONS, format_of

__all__ = [
    "COLLINEAR_RTOL",
    "FORMATS",
    "MatrixError",
    "PointCloud",
    "PointCloudError",
    "SUPPORTED_EXTENSIONS",
    "WRITE_EXTENSIONS",
    "format_matrix",
    "load_point_cloud",
    "read_matrix",
    "read_point_cloud",
    "save_point_cloud",
    "transform_cloud",
    "write_aligned",
    "write_matrix",
    "write_point_cloud",
]

logger = logging.getLogger(__name__)

#: extensions gctr reads (lower case); :data:`WRITE_EXTENSIONS` those it writes
SUPPORTED_EXTENSIONS = READ_EXTENSIONS


def read_point_cloud(path: str | Path, *, min_points: int = 10, attributes: bool = True,
                     degenerate_ok: bool = False) -> PointCloud:
    """Read and validate a point cloud file; return its points and (with ``attributes``) per-point
    attributes as a :class:`PointCloud`.

    The format is chosen by the extension of ``path`` as given (case-insensitive; a symbolic link is
    judged by its own name, not its target's). Raises :class:`PointCloudError` if the path does not
    name a readable regular file (missing, folder, device, broken link, link loop, empty), if the file
    is malformed or truncated, has fewer than ``min_points`` finite points, or if all points are
    identical or collinear (unless ``degenerate_ok``). Non-finite points are dropped with a warning on
    the ``gctr_cli.io`` logger.
    """
    path = Path(path)
    fmt = format_of(path)
    if fmt is None:
        if os.path.isdir(path):  # (False, not an exception, for a name the system refuses)
            raise PointCloudError(f"{path}: is a folder, not a point cloud file")
        raise PointCloudError(
            f"{path}: unsupported extension '{path.suffix}' (supported: {', '.join(SUPPORTED_EXTENSIONS)})"
        )
    size = check_input_file(path, PointCloudError)
    try:
        with open(path, "rb") as fh:
            cloud = fmt.read(path, fh, size, attributes)
    except PointCloudError:
        raise
    except MemoryError:
        raise PointCloudError(f"{path}: too large to load into memory") from None
    except OSError as exc:
        raise PointCloudError(f"{path}: cannot read file ({exc.strerror or 'operating system error'})") from None
    except Exception as exc:  # a reader bug must still name the file, in words
        logger.debug("%s: unexpected error in the %s reader", path, fmt.name, exc_info=exc)
        raise PointCloudError(f"{path}: malformed {fmt.name} file (its data does not match its header)") from None
    pts = np.ascontiguousarray(cloud.points, dtype=np.float64).reshape(-1, 3)
    cloud = PointCloud(pts, cloud.attributes, cloud.source_format, cloud.meta)
    return validate_cloud(cloud, path, min_points, degenerate_ok)


def load_point_cloud(path: str | Path, *, min_points: int = 10) -> np.ndarray:
    """Read a point cloud file and return its points as a validated ``(N, 3)`` float64 array.

    See :func:`read_point_cloud` for formats, checks and errors (:class:`PointCloudError`).
    Planar clouds are accepted.
    """
    return read_point_cloud(path, min_points=min_points, attributes=False).points


def write_point_cloud(path: str | Path, cloud: PointCloud | np.ndarray, *, binary: bool = True,
                      open3d_pcd: bool = False) -> None:
    """Write ``cloud`` (a :class:`PointCloud`, or an ``(N, 3)`` array) to ``path``; the format follows
    the extension (:data:`WRITE_EXTENSIONS`).

    Coordinates are written at full precision: float64 in PLY and PCD (binary little endian when
    ``binary``, else ASCII), ``%.17g`` in text files (``.pts`` starts with a point-count line), and
    in LAS/LAZ 1.4 with a power-of-ten scale that quantises each axis to at most span / 4e8 (2.5 µm on
    a 1 km tile), or, for a cloud read from LAS/LAZ, with the source's scale (times the scale factor
    of the transform since) and offset, which keeps every digit the source had. Attributes are kept
    where the format allows: PLY and PCD keep every numeric attribute, LAS fills its standard dimensions
    (intensity, classification, colours ...) and stores the others as extra bytes, ``.xyz``/``.txt``
    files get one column per attribute after ``x y z`` (named in a ``# x y z ...`` line; ``.csv`` files
    in an ``x,y,z,...`` header line, comma-separated), ``.pts`` files
    only intensity and 8-bit red green blue, the columns PTS readers know (the others are named in a
    warning). A LAS/LAZ output of a LAS source keeps the source's version, point format, CRS records and
    header ids (:func:`gctr_cli.io.las.las_bytes`); any other output of it logs a warning when the
    source's CRS is lost. Missing parent folders are created; the write is atomic (temporary file in the
    same folder, then ``os.replace``).

    Interoperability note: Open3D 0.20's legacy PCD reader silently returns zeros for ``SIZE 8``
    (double) fields in binary PCD files, but reads them exactly from ASCII ones. With ``open3d_pcd``, a
    binary PCD gets float32 x y z when that keeps every coordinate within 1e-7 of the cloud's extent
    (:func:`gctr_cli.io.pcd.float32_is_enough`), and is written as ASCII float64 otherwise (UTM-size
    coordinates); the aligned clouds gctr writes use it. Raises :class:`PointCloudError`.
    """
    path = Path(path)
    fmt = format_of(path)
    if fmt is None or fmt.write is None:
        raise PointCloudError(
            f"{path}: unsupported extension '{path.suffix}' for writing (supported: {', '.join(WRITE_EXTENSIONS)})"
        )
    if not isinstance(cloud, PointCloud):
        try:
            pts = np.asarray(cloud, dtype=np.float64)
        except (TypeError, ValueError):
            raise PointCloudError(f"{path}: points are not numeric") from None
        if pts.ndim != 2 or pts.shape[1] != 3:
            raise PointCloudError(f"{path}: points must have shape (N, 3), got {pts.shape}")
        cloud = PointCloud(pts)
    text = [str(k) for k, v in cloud.attributes.items() if np.asarray(v).dtype.kind not in "fiub"]
    if text:  # no format takes text or objects per point: said once, not skipped without a word
        logger.warning("%s: attributes not written (not numeric): %s", clean(path), clean(", ".join(text)))
        cloud = dataclasses.replace(cloud, attributes={k: v for k, v in cloud.attributes.items() if str(k) not in text})
    if fmt.name not in ("LAS", "LAZ"):  # the LAS writer names its extra dimensions itself, ASCII included
        cloud = dataclasses.replace(cloud, attributes=ascii_attribute_names(cloud.attributes, clean(path)))
    if fmt.name not in ("LAS", "LAZ") and cloud.source_format == "las" and "las_header" in cloud.meta:
        from gctr_cli.io.las import crs_description

        crs = crs_description(cloud.meta["las_header"])
        if crs:  # the registration kept the frame; the output no longer says which it is
            logger.warning("%s: the coordinate reference system of the LAS source (%s) is not kept: %s files "
                           "cannot hold it", clean(path), crs, fmt.name)
    if open3d_pcd and binary and fmt.name == "PCD":
        from gctr_cli.io.pcd import float32_is_enough, pcd_chunks

        # float32 binary where it is exact enough, else float64 as text: Open3D reads both correctly
        as_float32 = float32_is_enough(cloud.points)
        data: bytes | Iterable[bytes] = pcd_chunks(cloud, binary=as_float32, float32=as_float32)
    else:
        data = fmt.write(cloud, binary, path)
    try:
        atomic_write(path, data)
    except OSError as exc:
        raise PointCloudError(f"{path}: cannot write file ({write_error(path, exc)})") from None


def save_point_cloud(path: str | Path, points: np.ndarray, *, binary: bool = True) -> None:
    """Write ``points`` (``(N, 3)``) to ``path``; :func:`write_point_cloud` without attributes.

    Every format round-trips exactly through :func:`load_point_cloud` (LAS/LAZ: to within the
    quantisation described there).
    """
    write_point_cloud(path, points, binary=binary)


class _NotesDropped:
    """Within (in this thread): the readers' warnings about the file as a whole (``dropped 3 of 50000
    points with non-finite coordinates`` ...) are not logged. Errors are, and so are the notes about
    attributes, which a registration's read (coordinates only) never gave."""

    def __init__(self) -> None:
        self.thread = threading.get_ident()

    def filter(self, record: logging.LogRecord) -> bool:
        return (record.thread != self.thread or record.levelno >= logging.ERROR
                or getattr(record, "gctr_attribute_note", False))

    def __enter__(self) -> None:
        logger.addFilter(self)

    def __exit__(self, *exc: object) -> None:
        logger.removeFilter(self)


def write_aligned(input_path: str | Path, matrix: np.ndarray, output_path: str | Path, *,
                  reread: bool = False) -> PointCloud:
    """Read the cloud ``input_path``, move it by the 4x4 similarity ``matrix`` (``p' = s·R·p + t``,
    the source->target matrix of a registration) and write it to ``output_path``, keeping its
    attributes where the output format allows (normals are turned with the surface). Formats follow the
    extensions (any readable format in; PLY, PCD, LAS/LAZ, XYZ/PTS/TXT out).

    This is the one call a caller needs to write an aligned cloud, e.g. the batch runner's
    ``OUTDIR/aligned/<pair_id>.<ext>``. With ``reread`` (the caller registered this file, so its
    reading warnings were shown), the reader's warnings are not repeated. Returns the moved cloud.
    Raises :class:`PointCloudError` (unreadable input, unsupported output extension, write failure)
    or :class:`MatrixError` (a matrix that is not 4x4, not finite, or whose last row is not
    ``0 0 0 1``).
    """
    from gctr_cli.io.matrix import _check_matrix

    try:
        M = np.asarray(matrix, dtype=np.float64)
    except (TypeError, ValueError):
        raise MatrixError("matrix is not numeric") from None
    if M.shape != (4, 4):
        raise MatrixError(f"matrix must be 4x4, got shape {M.shape}")
    _check_matrix(M, "matrix")
    output_path = Path(output_path)
    fmt = format_of(output_path)
    if fmt is None or fmt.write is None:  # before the (possibly long) read
        raise PointCloudError(
            f"{output_path}: unsupported extension '{output_path.suffix}' for writing "
            f"(supported: {', '.join(WRITE_EXTENSIONS)})"
        )
    # The registration that made the matrix read this file and reported its warnings already.
    read_notes = _NotesDropped() if reread else contextlib.nullcontext()
    with read_notes:
        cloud = read_point_cloud(input_path, min_points=1, degenerate_ok=True)
    moved = transform_cloud(cloud, M)
    write_point_cloud(output_path, moved, open3d_pcd=True)
    return moved
