"""E57 (ASTM E2807, terrestrial scanner projects) via pye57: reader.

Every scan of the file is read with its stored pose (rotation quaternion and translation) applied,
and the scans are merged into one cloud in the file's common frame (said at info level, with the
scans' names); spherical scans are converted to cartesian. Points flagged invalid (no coordinates
measured) are dropped, with a warning giving their count. Intensity and colours are kept as
attributes (``intensity``, ``red``/``green``/``blue``) when every scan has them; one warning names
what is not kept (an attribute some scans lack, the point fields gctr does not read).

The point counts the file declares are checked against its size (at least one byte per point)
before any buffer is allocated.
"""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np

from gctr_cli.io.cloud import ATTRIBUTE_NOTE, PointCloud
from gctr_cli.io.errors import PointCloudError, clean, quote

__all__ = ["read_e57"]

logger = logging.getLogger("gctr_cli.io")

_COLOR = {"colorRed": "red", "colorGreen": "green", "colorBlue": "blue"}
#: point fields the reader uses: coordinates, their invalid-state flags, intensity, colours
_READ = {"cartesianX", "cartesianY", "cartesianZ", "sphericalRange", "sphericalAzimuth", "sphericalElevation",
         "cartesianInvalidState", "sphericalInvalidState", "intensity", *_COLOR}


def _scan_name(header, i: int) -> str:
    """``scan 3 'Station 4'`` (the scan's E57 name when it has one), for messages."""
    try:
        name = header["name"].value() if "name" in header.scan_fields else ""
    except Exception:  # noqa: BLE001 - an unreadable name is only not shown
        name = ""
    return f"scan {i} {quote(name)}" if name else f"scan {i}"


def _list(names: list[str], limit: int = 8) -> str:
    return ", ".join(names[:limit]) + (f" and {len(names) - limit} more" if len(names) > limit else "")


def _not_kept(path: Path, names: list[str], fields: list[set[str]], want_int: bool, want_rgb: bool) -> None:
    """One warning naming what an attribute read does not keep: intensity or colours that some scans lack
    (an attribute is kept only when every scan has it) and the point fields gctr does not read."""
    parts = []
    for what, needed, kept in (("intensity", {"intensity"}, want_int), ("colours", set(_COLOR), want_rgb)):
        lacking = [names[i] for i, f in enumerate(fields) if not needed <= f]
        if not kept and len(lacking) < len(fields):
            parts.append(f"{what} (missing from {_list(lacking)}; kept only when every scan has it)")
    other = sorted(set().union(*fields) - _READ)
    if other:
        parts.append(f"{_list([quote(f) for f in other])} (point fields gctr does not read)")
    if parts:
        logger.warning("%s: not kept: %s", clean(path), "; ".join(parts), extra=ATTRIBUTE_NOTE)


def _colour_limit(header) -> float | None:
    """The largest colour value the scan's ``colorLimits`` allow, or None when it does not say."""
    try:
        limits = header["colorLimits"]
        return max(float(limits[f"color{c}Maximum"].value()) for c in ("Red", "Green", "Blue"))
    except Exception:  # noqa: BLE001 - an optional node; absent or odd means "not said"
        return None


def _scan_colours(e57, header) -> dict[str, np.ndarray]:
    """The colours of a scan (its ``header``) as float64, its invalid points dropped as pye57 drops them.

    Read here, not by pye57's ``read_scan(colors=True)``, whose 8-bit buffers refuse the 16-bit colours
    (limits 0..65535) that the standard allows and scanners write."""
    from pye57 import libe57

    n = int(header.point_count)
    state = "cartesianInvalidState" if "cartesianX" in header.point_fields else "sphericalInvalidState"
    fields = [*_COLOR, *([state] if state in header.point_fields else [])]
    data = {f: np.empty(n, np.int8 if f == state else np.float64) for f in fields}
    buffers = libe57.VectorSourceDestBuffer()
    for f in fields:
        buffers.append(libe57.SourceDestBuffer(e57.image_file, f, data[f], n, True, True))
    header.points.reader(buffers).read()
    keep = data[state] == 0 if state in data else slice(None)
    return {v: data[k][keep] for k, v in _COLOR.items()}


def _colour_type(parts: dict[str, list[np.ndarray]], limit: float | None) -> dict[str, np.ndarray]:
    """Merged colours in the type their range needs: 8 bits for 0..255, 16 bits for 0..65535 (as LAS
    stores them; the writers narrow them where a format holds 8), 0..1 floats as 8 bits. The range is
    the scans' ``colorLimits`` when they give it (a dark 16-bit image stays 16-bit), else the values'."""
    merged = {k: np.concatenate(v) for k, v in parts.items()}
    top = limit if limit is not None else max((float(v.max()) for v in merged.values() if len(v)), default=0.0)
    fractional = any(len(v) and not np.array_equal(v, np.round(v)) for v in merged.values())
    if top <= 1.0 and fractional:
        return {k: np.round(np.clip(v, 0, 1) * 255).astype(np.uint8) for k, v in merged.items()}
    if top <= 255:
        return {k: np.clip(np.round(v), 0, 255).astype(np.uint8) for k, v in merged.items()}
    scale = 65535.0 / top if top > 65535 else 1.0
    return {k: np.clip(np.round(v * scale), 0, 65535).astype(np.uint16) for k, v in merged.items()}


def read_e57(path: Path, fh, size: int, attributes: bool = True) -> PointCloud:
    import pye57

    if fh.read(8) != b"ASTM-E57":
        raise PointCloudError(f"{path}: not an E57 file (missing 'ASTM-E57' signature)")

    def corrupt(exc: BaseException, what: str) -> PointCloudError:
        logger.debug("%s: pye57 failed", path, exc_info=exc)
        return PointCloudError(f"{path}: corrupt or unsupported E57 file: {what}")

    try:
        e57 = pye57.E57(str(path))
    except Exception as exc:  # noqa: BLE001 - libE57 text is not for users
        raise corrupt(exc, "its structure (XML section or checksums) cannot be read") from None
    try:
        n_scans = e57.scan_count
        if n_scans == 0:
            raise PointCloudError(f"{path}: contains no points (the E57 file has no scans)")
        headers = []
        names = []
        total = 0
        for i in range(n_scans):
            try:
                h = e57.get_header(i)
                count = int(h.point_count)
                fields = set(h.point_fields)
                q, t = np.asarray(h.rotation, dtype=np.float64), np.asarray(h.translation, dtype=np.float64)
            except Exception as exc:  # noqa: BLE001
                raise corrupt(exc, f"the header of scan {i} cannot be read") from None
            names.append(_scan_name(h, i))
            if not (np.isfinite(q).all() and np.isfinite(t).all() and np.linalg.norm(q) > 1e-9):
                # a zero quaternion would put every point of the scan at its translation
                raise PointCloudError(f"{path}: scan {i} has an invalid pose (rotation quaternion "
                                      f"{np.array2string(q, separator=', ')}, translation "
                                      f"{np.array2string(t, separator=', ')}): its points cannot be placed")
            total += count
            headers.append(fields)
        if total > size:
            raise PointCloudError(
                f"{path}: corrupt E57 file: its scans declare {total} points but the file has only {size} bytes"
            )
        want_int = attributes and all("intensity" in f for f in headers)
        want_rgb = attributes and all(all(c in f for c in _COLOR) for f in headers)
        if attributes:
            _not_kept(path, names, headers, want_int, want_rgb)
        parts: list[np.ndarray] = []
        attrs: dict[str, list[np.ndarray]] = {"intensity": []} if want_int else {}
        colours: dict[str, list[np.ndarray]] = {v: [] for v in _COLOR.values()}
        limits: list[float | None] = []
        for i in range(n_scans):
            try:
                data = e57.read_scan(i, intensity=want_int, transform=True, ignore_missing_fields=True)
            except MemoryError:
                raise PointCloudError(f"{path}: too large to load into memory ({total} points)") from None
            except Exception as exc:  # noqa: BLE001
                raise corrupt(exc, f"the points of scan {i} cannot be decoded") from None
            xyz = np.stack([np.asarray(data[k], dtype=np.float64) for k in ("cartesianX", "cartesianY", "cartesianZ")],
                           axis=1)
            parts.append(xyz)
            if want_int:
                attrs["intensity"].append(np.asarray(data["intensity"]))
            if want_rgb:
                h = e57.get_header(i)
                try:
                    scan_rgb = _scan_colours(e57, h)
                except MemoryError:
                    raise PointCloudError(f"{path}: too large to load into memory ({total} points)") from None
                except Exception as exc:  # the points are fine; only the colours are lost
                    logger.debug("%s: colours of scan %d", path, i, exc_info=exc)
                    logger.warning("%s: colours not kept: those of %s cannot be decoded", clean(path), names[i],
                                   extra=ATTRIBUTE_NOTE)
                    want_rgb = False
                    continue
                if len(scan_rgb["red"]) != len(xyz):  # invalid points judged otherwise: better none than shifted
                    logger.warning("%s: colours not kept: %s has %d colours for %d points", clean(path), names[i],
                                   len(scan_rgb["red"]), len(xyz), extra=ATTRIBUTE_NOTE)
                    want_rgb = False
                    continue
                limits.append(_colour_limit(h))
                for k, v in scan_rgb.items():
                    colours[k].append(v)
    finally:
        try:
            e57.close()
        except Exception:  # noqa: BLE001
            pass
    pts = np.concatenate(parts) if parts else np.empty((0, 3))
    if n_scans > 1:
        logger.info("%s: merged %d scans, each placed by its pose: %s", clean(path), n_scans, _list(names))
    if invalid := total - len(pts):  # pye57 drops the points whose invalid state is set
        logger.warning("%s: dropped %d of %d points the E57 file flags invalid (no coordinates measured)",
                       clean(path), invalid, total)
    out = {k: np.concatenate(v) for k, v in attrs.items() if v}
    if want_rgb and colours["red"]:
        limit = None if any(x is None for x in limits) else max(x for x in limits if x is not None)
        out.update(_colour_type(colours, limit))
    return PointCloud(pts, {k: v for k, v in out.items() if len(v) == len(pts)}, "e57",
                      {"e57_scans": n_scans})
