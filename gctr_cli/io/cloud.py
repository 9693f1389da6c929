"""The in-memory cloud every reader returns and every writer takes, its validation and its transform."""

from __future__ import annotations

import logging
import unicodedata
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from gctr_cli.geometry import coordinate_range_problem, extent, robust_core, stats_sample
from gctr_cli.io.errors import PointCloudError, clean

__all__ = ["COLLINEAR_RTOL", "NORMAL_NAMES", "PointCloud", "ascii_attribute_names", "ascii_name", "eight_bit_colours",
           "element_columns", "named_normals", "transform_cloud", "unique_name", "validate_cloud"]

logger = logging.getLogger("gctr_cli.io")

#: relative singular-value threshold below which a cloud counts as collinear
COLLINEAR_RTOL = 1e-9
#: attribute triples that are normal vectors: rotated (not scaled or moved) by a transform
NORMAL_NAMES = (("nx", "ny", "nz"), ("normal_x", "normal_y", "normal_z"),
                ("normals_0", "normals_1", "normals_2"))  # a LAS extra dimension 'normals' of 3 elements


#: coordinates stored on a lattice coarser than this share of the cloud's size (the bounding-box diagonal of
#: its core) get a warning. Measured on the bunny (2026-12-06): quanta of 0.25–1% of its size register as
#: well as the float64 cloud (the engine works at about 1%); at 1.5% the errors grow (0.3 deg), at 4% they
#: leave the success limits. Float32 at UTM-size offsets keeps 0.5 m steps; a LAS scale of 0.01 on a 15 cm
#: object is 4%.
COARSE_STEP_RATIO = 0.01
#: fewer points than this are not checked: a few random values have wide gaps by chance
COARSE_STEP_MIN_POINTS = 200
#: the lattice is looked for in a random sample of this many points of the core (a fixed seed: the same
#: file gives the same note); every k-th point would see a row-major grid's columns k apart
COARSE_STEP_SAMPLE = 200_000
#: an axis counts as quantised only when it holds at least this many distinct values, all on one lattice
#: (two levels, a floor and a table top or a flat sheet and one stray point, are no lattice), or when
#: float32 storage at its distance from the origin explains the step
COARSE_STEP_MIN_VALUES = 3

#: text values within this relative distance of float32 values are float32 values written with 9 or more
#: digits (``%.9g`` is within 5e-9; a float64 value is on average 1.5e-8 from the nearest float32)
FLOAT32_PRINTED_RTOL = 1e-8

#: ``extra`` of a reader's warning that concerns an attribute (read only with ``attributes=True``)
ATTRIBUTE_NOTE = {"gctr_attribute_note": True}


def integer_misfit(values: np.ndarray, lo: int, hi: int) -> str | None:
    """The first value an integer type holding ``lo..hi`` cannot store exactly (NaN, a fraction, a
    value beyond the range), formatted for a message; None when every value fits. Integer arrays are
    compared as integers (exact for 64-bit values); floats against ``hi + 1``, which float64 rounds
    up, not down, at 64 bits."""
    v = np.asarray(values)
    if not len(v):
        return None
    if v.dtype.kind in "iub":
        low, high = int(v.min()), int(v.max())
        return str(low) if low < lo else str(high) if high > hi else None
    f = v.astype(np.float64)
    bad = ~np.isfinite(f) | (f != np.round(f)) | (f < lo) | (f >= float(hi) + 1.0)
    if not bad.any():
        return None
    x = float(f[np.argmax(bad)])
    return str(int(x)) if np.isfinite(x) and x.is_integer() else f"{x:.10g}"


def element_columns(name: str, count: int) -> list[str]:
    """The attribute columns of a field of ``count`` elements (a PCD ``COUNT 3`` field, a LAS extra
    dimension ``normals`` '3f8'): the name itself for one, else ``name_0 name_1 ...``."""
    return [name] if count == 1 else [f"{name}_{j}" for j in range(count)]


@dataclass(frozen=True)
class PointCloud:
    """Points and their per-point attributes.

    ``points`` is an ``(N, 3)`` float64 array in the file's coordinates (scaled/offset LAS and E57
    coordinates already applied, at full float64 precision). ``attributes`` maps a name (``intensity``,
    ``red``, ``green``, ``blue``, ``classification``, ``nx`` ...) to a 1-D array of length N in the
    file's own type. ``source_format`` names the reader (``"ply"``, ``"las"`` ...) and ``meta`` holds
    format hints a writer of the same family may reuse (e.g. the LAS header: its scales, CRS records);
    ``meta["transform"]``, when present, is the 4x4 matrix the cloud was moved by since it was read
    (:func:`transform_cloud`), for hints that change with the points (a LAS quantum, a sensor pose).
    """

    points: np.ndarray
    attributes: dict[str, np.ndarray] = field(default_factory=dict)
    source_format: str = ""
    meta: dict = field(default_factory=dict)

    def __len__(self) -> int:
        return len(self.points)

    def subset(self, mask: np.ndarray) -> PointCloud:
        return PointCloud(self.points[mask], {k: v[mask] for k, v in self.attributes.items()},
                          self.source_format, self.meta)


def validate_cloud(cloud: PointCloud, path: Path, min_points: int, degenerate_ok: bool = False) -> PointCloud:
    """Drop non-finite points (with their attributes), then check the count and degeneracy.

    The "dropped N non-finite points" warning is logged only for a cloud that is accepted; when the
    cloud is rejected the error itself says how many points were dropped. A shape-checked cloud (not
    ``degenerate_ok``) whose coordinates are stored coarsely gets :func:`coarse_step_note` as a warning.
    """
    pts = cloud.points
    n_total = len(pts)
    n_bad = 0
    if not np.isfinite(pts).all():  # (the whole array at once: 10 times faster than row by row)
        finite = np.isfinite(pts).all(axis=1)
        n_bad = int(n_total - finite.sum())
        cloud = cloud.subset(finite)
        pts = cloud.points
    n = len(pts)
    dropped = f" after dropping {n_bad} non-finite" if n_bad else ""
    if n == 0:
        if n_total:
            raise PointCloudError(f"{path}: contains no finite points (all {n_total} points are non-finite)")
        raise PointCloudError(f"{path}: contains no points (at least {min_points} required)")
    if n < min_points:
        raise PointCloudError(
            f"{path}: too few points: only {n} finite point{'' if n == 1 else 's'}{dropped} "
            f"(at least {min_points} required)"
        )
    core = _check_shape(pts, path, dropped) if not degenerate_ok else None
    if n_bad:
        logger.warning("%s: dropped %d of %d points with non-finite (NaN/inf) coordinates", clean(path), n_bad, n_total)
    # a registration's read only: a cloud read to be moved (degenerate_ok) is not registered, and its core,
    # which the note needs, is not worked out (a batch rereads each source it writes aligned)
    note = coarse_step_note(pts, core) if core is not None else None
    if note:
        logger.warning("%s: %s", clean(path), note)
    return cloud


def coarse_step_note(points: np.ndarray, core: np.ndarray | None = None) -> str | None:
    """Why the stored coordinates may limit the registration's precision, or None: along some axis the
    values of the cloud's ``core`` (:func:`robust_core` of ``points`` unless given: a stray ``0 0 0`` must
    not hide the problem) lie on a lattice coarser than :data:`COARSE_STEP_RATIO` of the core's diagonal,
    with the likely cause (float32 storage far from the origin, or the file's digits)."""
    core = robust_core(points) if core is None else core
    if len(core) < COARSE_STEP_MIN_POINTS:
        return None
    diagonal = float(np.linalg.norm(extent(core)))
    if not diagonal > 0:
        return None
    rng = np.random.default_rng(0)
    sample = core[rng.integers(0, len(core), size=COARSE_STEP_SAMPLE)] if len(core) > COARSE_STEP_SAMPLE else core
    found = []  # (axis, step, far, float32 storage explains the step)
    for axis in range(3):
        values = np.unique(sample[:, axis])
        if len(values) < 2:  # the core is flat along it: the axis may hold two levels a coarse step apart
            values = np.unique(points[:: max(1, len(points) // COARSE_STEP_SAMPLE), axis])
            if len(values) < 2:
                continue
        with np.errstate(over="ignore"):  # beyond float32's range: inf, which no value is near
            snapped = values.astype(np.float32).astype(np.float64)
        # float32 values written as text: their steps are float32's (unless they all fall on one float32
        # value: a float64 axis thinner than that tolerance, which is no lattice)
        if (np.all(np.abs(snapped - values) <= FLOAT32_PRINTED_RTOL * np.abs(values))
                and len(snapped_values := np.unique(snapped)) >= 2):
            values = snapped_values
        gaps = np.diff(values)
        step = float(gaps.min())
        if step <= COARSE_STEP_RATIO * diagonal:
            continue
        far = float(np.abs(values).max())
        float32 = (bool(np.all(values.astype(np.float32).astype(np.float64) == values))
                   and float(np.spacing(np.float32(far))) >= 0.5 * step)
        multiples = gaps / step
        if not float32 and (len(values) < COARSE_STEP_MIN_VALUES
                            or np.abs(multiples - np.round(multiples)).max() > 0.01):
            continue  # two levels, or a few at arbitrary heights: not a lattice
        found.append((axis, step, far, float32))
    if not found:
        return None
    axis, step, far, float32 = max(found, key=lambda f: f[1])
    axes = " and ".join("xyz"[a] for a, st, _, _ in found if st >= 0.99 * step)
    if float32:
        cause = (f"float32 values as far from the origin as {far:.6g} keep no finer steps: store the coordinates "
                 "as float64, or subtract an offset before exporting")
    else:
        cause = "the file keeps no more digits (a LAS scale factor, a text export's decimals, integer units?)"
    return (f"coordinates are stored in steps of {step:.3g} along {axes}, {step / diagonal:.2g} of the cloud's "
            f"size {diagonal:.3g}, no finer than the registration's working resolution (about 0.01): expect "
            f"errors of that order; {cause}")


def _check_shape(pts: np.ndarray, path: Path, dropped: str) -> np.ndarray:
    """Refuse coordinates float64 cannot register, and clouds whose core (without far outliers: one
    stray point must not decide) is a single point or a line; return that core (of
    :func:`~gctr_cli.geometry.stats_sample` of a cloud that passes)."""
    problem = coordinate_range_problem(pts)
    if problem:
        raise PointCloudError(f"{path}: {problem}")
    n = len(pts)
    sample = stats_sample(pts)  # a large cloud is cleared on a sample of it, not by sorting every point
    core = robust_core(sample)
    if sample is not pts and ((core == core[0]).all() or _collinear(core) is not None):
        core = robust_core(pts, exact=True)  # a problem seen on the sample: decided, and counted, on every point
    outliers = f", apart from {n - len(core)} far outlier(s)" if len(core) < n else ""
    if (core == core[0]).all():
        if len(core) == n:
            raise PointCloudError(f"{path}: degenerate cloud: all {n} points{dropped} are identical")
        rest = n - len(core)
        others = "the other one lies" if rest == 1 else f"the other {rest} lie"
        raise PointCloudError(f"{path}: degenerate cloud: {len(core)} of its {n} points{dropped} are identical; "
                              f"{others} far from them")
    elif (line := _collinear(core)) is not None:
        raise PointCloudError(f"{path}: degenerate cloud: points are collinear ({len(core)} points{dropped} on one "
                              f"line{outliers}{line})")
    return core


def transform_cloud(cloud: PointCloud, T: np.ndarray) -> PointCloud:
    """``cloud`` moved by the 4x4 matrix ``T`` (``p' = A·p + t``; ``A = s·R`` for a similarity), in float64.

    Points are moved about their mean, so UTM-size coordinates keep their precision; normal
    attributes (``nx ny nz`` / ``normal_x ...`` / a LAS ``normals`` triple) are mapped by the inverse
    transpose of ``A`` (rotated, for a similarity) and renormalised, so they stay perpendicular to the
    moved surface; every other attribute is copied unchanged. ``meta["transform"]`` accumulates ``T``.
    """
    M = np.asarray(T, dtype=np.float64)
    A, t = M[:3, :3], M[:3, 3]
    pts = cloud.points
    c = pts.mean(axis=0) if len(pts) else np.zeros(3)
    moved = (pts - c) @ A.T + (A @ c + t)
    attrs = dict(cloud.attributes)
    # normals follow the inverse transpose (for a similarity s·R that is R): a shear or an unequal
    # stretch turns a surface's normals differently from its points, and they must stay perpendicular
    normal_map = np.linalg.pinv(A)
    for names in NORMAL_NAMES:
        if all(n in attrs for n in names):
            nrm = np.stack([attrs[n].astype(np.float64) for n in names], axis=1) @ normal_map
            length = np.linalg.norm(nrm, axis=1, keepdims=True)
            nrm = np.divide(nrm, length, out=nrm.copy(), where=length > 0)
            for j, n in enumerate(names):
                kind = attrs[n].dtype
                attrs[n] = nrm[:, j].astype(kind) if kind.kind == "f" else nrm[:, j]
    meta = {**cloud.meta, "transform": M @ np.asarray(cloud.meta.get("transform", np.eye(4)), dtype=np.float64)}
    return PointCloud(moved, attrs, cloud.source_format, meta)


def named_normals(attributes: dict[str, np.ndarray], names: tuple[str, str, str]) -> dict[str, np.ndarray]:
    """``attributes`` with a normal triple of another convention (:data:`NORMAL_NAMES`) renamed to
    ``names``, in place of the old names: PLY readers look for ``nx ny nz``, PCD readers for
    ``normal_x normal_y normal_z``, so a cloud converted between them keeps readable normals. Nothing
    is renamed when any of ``names`` is taken already (a renamed column must not replace another)."""
    if any(n in attributes for n in names):
        return dict(attributes)
    for other in NORMAL_NAMES:
        if other != names and all(n in attributes for n in other):
            renamed = dict(zip(other, names, strict=True))
            return {renamed.get(k, k): v for k, v in attributes.items()}
    return dict(attributes)


def eight_bit_colours(attributes: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    """``attributes`` with integer ``red``/``green``/``blue`` wider than a byte (LAS and E57 store 16
    bits) as the 8 bits that PLY and PCD readers expect: their high byte when any value exceeds 255
    (exact for both 16-bit conventions, ``v * 256`` and the LAS writer's ``v * 257``), else only
    narrowed. Other attributes unchanged."""
    out = dict(attributes)
    rgb = [np.asarray(out.get(k)) for k in ("red", "green", "blue")]
    if any(v.ndim != 1 or v.dtype.kind not in "ui" or v.dtype.itemsize == 1 for v in rgb):
        return out
    wide = max(int(v.max(initial=0)) for v in rgb) > 255
    for k, v in zip(("red", "green", "blue"), rgb, strict=True):
        v = v.astype(np.int64)
        out[k] = np.clip(v >> 8 if wide else v, 0, 255).astype(np.uint8)
    return out


def _plain(name: str) -> bool:
    """Whether ``name`` is printable ASCII without blanks, as every format's header holds it."""
    return name.isascii() and name.isprintable() and not any(c.isspace() for c in name)


def ascii_name(name: str) -> str:
    """``name`` in printable ASCII without blanks: accents dropped (``intensité`` -> ``intensite``), any
    other character as ``_``."""
    plain = unicodedata.normalize("NFKD", name).encode("ascii", "ignore").decode("ascii")
    plain = "".join(c if _plain(c) else "_" for c in plain)
    return plain.strip("_") or "attribute"


def unique_name(base: str, taken: set[str], limit: int | None = None) -> str:
    """``base``, or the first of ``base_2``, ``base_3`` ... not in ``taken`` (cut to ``limit`` characters)."""
    new, j = base, 1
    while new in taken:
        j += 1
        tail = f"_{j}"
        new = (base[: limit - len(tail)].rstrip("_") if limit else base) + tail
    return new


def ascii_attribute_names(attributes: dict[str, np.ndarray], where: str) -> dict[str, np.ndarray]:
    """``attributes`` with every name in printable ASCII without blanks, as PLY, PCD, LAS and text headers
    need (their headers are ASCII; a name with a blank would split into two). A renamed attribute is
    named in one warning; a new name that is taken gets ``_2``, ``_3`` ... Names that are fine, and the
    order, are unchanged."""
    if all(_plain(str(k)) for k in attributes):
        return attributes
    out: dict[str, np.ndarray] = {}
    renamed = []
    taken = {str(k) for k in attributes} | {"x", "y", "z", "X", "Y", "Z"}  # ``ẑ`` must not become ``z``
    for k, v in attributes.items():
        name = str(k)
        if not _plain(name):
            new = unique_name(ascii_name(name), taken)
            taken.add(new)
            renamed.append(f"{name!r} as {new!r}")
            name = new
        out[name] = v
    logger.warning("%s: attribute names written in ASCII (the format's header holds no other characters): %s",
                   where, ", ".join(renamed))
    return out


def _collinear(pts: np.ndarray) -> str | None:
    """Whether ``pts`` lie on one line: None if not, else "" or the note that the line holds within the
    float32 rounding of the stored coordinates (a line written as float32 is that far off a straight line:
    about 1e-7 of the coordinates' size, far more than :data:`COLLINEAR_RTOL` of a short line)."""
    centred = pts - pts.mean(axis=0)
    spread = np.linalg.svd(centred, compute_uv=False) / np.sqrt(len(pts))  # RMS along each principal direction
    if spread[1] < COLLINEAR_RTOL * spread[0]:
        return ""
    with np.errstate(over="ignore"):  # beyond float32's range: inf, never equal
        ulp = float(np.spacing(np.float32(np.abs(pts).max())))
        # only where the line is long against float32's step (from about 100 steps along its length the
        # coarse-coordinates note no longer covers it; a strip 3 steps wide is no wider than its rounding),
        # and only for coordinates stored as float32 (or as few digits): the cast last, as it reads every point
        if spread[1] <= ulp and spread[0] >= 30.0 * ulp and np.array_equal(pts.astype(np.float32), pts):
            return ", within the float32 rounding of its coordinates"
    return None
