"""Which reader and writer handle a file, chosen by the extension of the name the user gave."""

from __future__ import annotations

from collections.abc import Callable, Iterable
from dataclasses import dataclass
from pathlib import Path

from gctr_cli.io.cloud import PointCloud

__all__ = ["FORMATS", "Format", "READ_EXTENSIONS", "WRITE_EXTENSIONS", "format_of"]

Reader = Callable[[Path, object, int, bool], PointCloud]
# (cloud, binary, the path: for messages) -> the file's bytes, whole or in pieces (text formatted as it is written)
Writer = Callable[[PointCloud, bool, Path], bytes | Iterable[bytes]]


def _reader(module: str, name: str) -> Reader:
    """A reader imported on first use (laspy and pye57 load only for their files)."""

    def read(path: Path, fh, size: int, attributes: bool = True) -> PointCloud:
        import importlib

        return getattr(importlib.import_module(f"gctr_cli.io.{module}"), name)(path, fh, size, attributes)

    return read


def _write_ply(cloud: PointCloud, binary: bool, path: Path) -> Iterable[bytes]:
    from gctr_cli.io.ply import ply_chunks

    return ply_chunks(cloud, binary, path)


def _write_pcd(cloud: PointCloud, binary: bool, path: Path) -> Iterable[bytes]:  # noqa: ARG001
    from gctr_cli.io.pcd import pcd_chunks

    return pcd_chunks(cloud, binary)


def _write_text(cloud: PointCloud, binary: bool, path: Path) -> Iterable[bytes]:  # noqa: ARG001
    from gctr_cli.io.text import text_chunks

    return text_chunks(cloud)


def _write_csv(cloud: PointCloud, binary: bool, path: Path) -> Iterable[bytes]:  # noqa: ARG001
    from gctr_cli.io.text import csv_chunks

    return csv_chunks(cloud)


def _write_pts(cloud: PointCloud, binary: bool, path: Path) -> Iterable[bytes]:  # noqa: ARG001
    from gctr_cli.io.text import pts_chunks

    return pts_chunks(cloud, path)


def _write_las(cloud: PointCloud, binary: bool, path: Path) -> bytes:  # noqa: ARG001
    from gctr_cli.io.las import las_bytes

    return las_bytes(cloud, compress=False, path=path)


def _write_laz(cloud: PointCloud, binary: bool, path: Path) -> bytes:  # noqa: ARG001
    from gctr_cli.io.las import las_bytes

    return las_bytes(cloud, compress=True, path=path)


@dataclass(frozen=True)
class Format:
    """A file format: its name, extensions (lower case, with the dot), reader and optional writer."""

    name: str
    extensions: tuple[str, ...]
    read: Reader
    write: Writer | None = None


FORMATS: tuple[Format, ...] = (
    Format("PLY", (".ply",), _reader("ply", "read_ply"), _write_ply),
    Format("PCD", (".pcd",), _reader("pcd", "read_pcd"), _write_pcd),
    Format("XYZ text", (".xyz",), _reader("text", "read_text"), _write_text),
    Format("PTS text", (".pts",), _reader("text", "read_text"), _write_pts),
    Format("text", (".txt",), _reader("text", "read_text"), _write_text),
    Format("CSV text", (".csv",), _reader("text", "read_text"), _write_csv),
    Format("LAS", (".las",), _reader("las", "read_las"), _write_las),
    Format("LAZ", (".laz",), _reader("las", "read_las"), _write_laz),
    Format("E57", (".e57",), _reader("e57", "read_e57"), None),
)

READ_EXTENSIONS: tuple[str, ...] = tuple(e for f in FORMATS for e in f.extensions)
WRITE_EXTENSIONS: tuple[str, ...] = tuple(e for f in FORMATS if f.write is not None for e in f.extensions)


def format_of(path: Path) -> Format | None:
    """The format of ``path`` by its extension (case-insensitive), or None."""
    ext = path.suffix.lower()
    return next((f for f in FORMATS if ext in f.extensions), None)
