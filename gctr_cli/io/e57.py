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


def _colour_range(header, values: dict[str, np.ndarray]) -> tuple[float, float]:
    """The range ``(lo, hi)`` of a scan's colours: its ``colorLimits``, else its integer prototype's
    range, else the values' own (0..1 when they are fractions, 0..255 or 0..65535 by their largest)."""
    try:
        limits = header["colorLimits"]
        return (min(float(limits[f"color{c}Minimum"].value()) for c in ("Red", "Green", "Blue")),
                max(float(limits[f"color{c}Maximum"].value()) for c in ("Red", "Green", "Blue")))
    except Exception:  # noqa: BLE001 - an optional node; absent or odd means "not said"
        pass
    nodes = _colour_nodes(header)
    if nodes is not None:
        return float(min(lo for lo, _ in nodes)), float(max(hi for _, hi in nodes))
    top = max((float(v.max()) for v in values.values() if len(v)), default=0.0)
    fractional = any(len(v) and not np.array_equal(v, np.round(v)) for v in values.values())
    return 0.0, 1.0 if top <= 1.0 and fractional else 255.0 if top <= 255 else max(top, 65535.0)


def _colour_nodes(header) -> list[tuple[int, int]] | None:
    """The ``(minimum, maximum)`` of the scan's colour fields when all three are integers, else None."""
    from pye57 import libe57

    try:
        proto = libe57.StructureNode(header.points.prototype())
        nodes = [proto.get(f) for f in _COLOR]
        if any(n.type() != libe57.NodeType.E57_INTEGER for n in nodes):
            return None
        return [(int(libe57.IntegerNode(n).minimum()), int(libe57.IntegerNode(n).maximum())) for n in nodes]
    except Exception:  # noqa: BLE001 - an unreadable prototype: read the colours as float64
        return None


def _read_scan(e57, header, intensity: bool, colours: bool) -> dict[str, np.ndarray]:
    """One pass over a scan: ``xyz`` in the file's frame (spherical converted, the pose applied), and
    ``intensity`` and ``red green blue`` when asked, as pye57's ``read_scan`` gives them but for the
    colours, read in a buffer of their own width (pye57's 8-bit buffers refuse the 16-bit colours the
    standard allows and scanners write), their invalid points dropped alike."""
    from pye57 import libe57
    from pye57.e57 import SUPPORTED_POINT_FIELDS, convert_spherical_to_cartesian

    n = int(header.point_count)
    cartesian = "cartesianX" in header.point_fields
    coords = (["cartesianX", "cartesianY", "cartesianZ"] if cartesian
              else ["sphericalRange", "sphericalAzimuth", "sphericalElevation"])
    state = "cartesianInvalidState" if cartesian else "sphericalInvalidState"
    fields = coords + (["intensity"] if intensity else []) + (list(_COLOR) if colours else [])
    fields += [state] if state in header.point_fields else []
    colour_type: type = np.float64
    nodes = _colour_nodes(header) if colours else None
    if nodes is not None and min(lo for lo, _ in nodes) >= 0:
        top = max(hi for _, hi in nodes)
        colour_type = np.uint8 if top <= 255 else np.uint16 if top <= 65535 else np.float64
    data = {f: np.empty(n, colour_type if f in _COLOR else SUPPORTED_POINT_FIELDS[f]) for f in fields}
    buffers = libe57.VectorSourceDestBuffer()
    for f in fields:
        buffers.append(libe57.SourceDestBuffer(e57.image_file, f, data[f], n, True, True))
    header.points.reader(buffers).read()
    if state in data:
        keep = data.pop(state) == 0
        data = {k: v[keep] for k, v in data.items()}
    xyz = np.stack([data.pop(c) for c in coords], axis=1).astype(np.float64, copy=False)
    if not cartesian:
        xyz = convert_spherical_to_cartesian(xyz)
    if header.has_pose():
        xyz = e57.to_global(xyz, header.rotation, header.translation)
    out = {"xyz": xyz}
    if intensity:
        out["intensity"] = data["intensity"]
    if colours:
        rgb = {v: data[k] for k, v in _COLOR.items()}
        out.update(_colour_bits(rgb, _colour_range(header, rgb)))
    return out


def _colour_bits(rgb: dict[str, np.ndarray], limits: tuple[float, float]) -> dict[str, np.ndarray]:
    """A scan's colours by its own range ``limits``: 0..255 kept as 8 bits, 0..65535 as 16 bits (as LAS
    stores them), any other range (0..1 floats, 12-bit 0..4095) stretched to 16 bits."""
    lo, hi = limits
    if lo == 0 and hi == 255:
        return {k: np.clip(np.round(v), 0, 255).astype(np.uint8) for k, v in rgb.items()}
    if lo == 0 and hi == 65535:
        return {k: np.clip(np.round(v), 0, 65535).astype(np.uint16) for k, v in rgb.items()}
    span = hi - lo if hi > lo else 1.0
    return {k: np.clip(np.round((v.astype(np.float64) - lo) / span * 65535), 0, 65535).astype(np.uint16)
            for k, v in rgb.items()}


def _merged_colours(parts: dict[str, list[np.ndarray]]) -> dict[str, np.ndarray]:
    """The scans' colours in one array each: 8 bits when every scan's are, else 16 (8-bit ones × 257)."""
    if all(a.dtype == np.uint8 for v in parts.values() for a in v):
        return {k: np.concatenate(v) for k, v in parts.items()}
    return {k: np.concatenate([a.astype(np.uint16) * (257 if a.dtype == np.uint8 else 1) for a in v])
            for k, v in parts.items()}


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
        for i in range(n_scans):
            try:
                data = _read_scan(e57, e57.get_header(i), want_int, want_rgb)
            except MemoryError:
                raise PointCloudError(f"{path}: too large to load into memory ({total} points)") from None
            except Exception as exc:  # noqa: BLE001
                raise corrupt(exc, f"the points of scan {i} cannot be decoded") from None
            parts.append(data["xyz"])
            if want_int:
                attrs["intensity"].append(np.asarray(data["intensity"]))
            for k in colours:
                if want_rgb:
                    colours[k].append(data[k])
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
        out.update(_merged_colours(colours))
    return PointCloud(pts, {k: v for k, v in out.items() if len(v) == len(pts)}, "e57",
                      {"e57_scans": n_scans})
