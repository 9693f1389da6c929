"""4x4 similarity transforms: compose, split, apply, invert; and a cloud's robust core (pure numpy;
imports nothing of gctr_cli).

Convention (GUIDE §1): ``T = [[s·R, t], [0 0 0 1]]`` maps source points onto the target,
``target ≈ s·R·source + t``; points are ``(N, 3)`` float arrays, one point per row.
"""

from __future__ import annotations

import numpy as np
import numpy.typing as npt

__all__ = ["MAX_COORDINATE", "MIN_EXTENT", "STATS_POINTS", "apply", "coordinate_range_problem", "cross", "extent",
           "invert", "random_rotation", "robust_core", "row_norms", "split", "stats_sample", "to_matrix"]

#: coordinates gctr can register: squared distances and covariances stay finite and nonzero in float64
MAX_COORDINATE = 1e100
MIN_EXTENT = 1e-100
#: a cloud's order statistics (medians, percentiles) and shape tests are taken on at most this many of
#: its points (:func:`stats_sample`): a LiDAR tile's 10 million points took 7 s of sorting to read, for
#: statistics a million points give as well; a cloud this size or smaller is used whole, as before
STATS_POINTS = 1_000_000


def to_matrix(s: float, R: npt.ArrayLike, t: npt.ArrayLike) -> np.ndarray:
    """The 4x4 float64 matrix ``[[s·R, t], [0, 0, 0, 1]]`` of scale ``s``, 3x3 rotation ``R`` and translation ``t``."""
    T = np.eye(4)
    T[:3, :3] = s * np.asarray(R, dtype=np.float64)
    T[:3, 3] = np.asarray(t, dtype=np.float64)
    return T


def split(T: npt.ArrayLike) -> tuple[float, np.ndarray, np.ndarray]:
    """``(s, R, t)`` of a 4x4 similarity: ``s = |det A|^(1/3)`` of its 3x3 block ``A``, ``R = A / s``, ``t``.

    The inverse of :func:`to_matrix` for a similarity. ``R`` is returned as computed (a reflection or a
    non-similarity block is not rejected here; ``gctr_cli.metrics.is_similarity`` checks that). Raises
    ValueError if the 3x3 block is singular.
    """
    M = np.asarray(T, dtype=np.float64)
    A = M[:3, :3]
    s = abs(float(np.linalg.det(A))) ** (1.0 / 3.0)
    if s == 0.0:
        raise ValueError("matrix has a singular 3x3 block")
    return s, A / s, M[:3, 3].copy()


def apply(T: np.ndarray, points: np.ndarray) -> np.ndarray:
    """``points`` ``(N, 3)`` moved by the 4x4 transform ``T``: ``p' = A·p + t`` for each row ``p``."""
    return points @ T[:3, :3].T + T[:3, 3]


def cross(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Cross products of the rows of two ``(N, 3)`` float arrays: ``np.cross(a, b)`` bit for bit (the same
    products and differences, each rounded once) without its axis handling and copies, which cost it
    about twice the arithmetic on the engine's arrays."""
    a0, a1, a2 = a[:, 0], a[:, 1], a[:, 2]
    b0, b1, b2 = b[:, 0], b[:, 1], b[:, 2]
    out = np.empty((len(a), 3), dtype=np.result_type(a, b))
    out[:, 0] = a1 * b2 - a2 * b1
    out[:, 1] = a2 * b0 - a0 * b2
    out[:, 2] = a0 * b1 - a1 * b0
    return out


def row_norms(v: np.ndarray) -> np.ndarray:
    """Euclidean lengths of the rows of an ``(N, 3)`` float array: ``np.linalg.norm(v, axis=1)`` bit for bit
    (the same squares summed in the same order, first two first) and about 5x faster (numpy reduces a
    length-3 axis row by row)."""
    v0, v1, v2 = v[:, 0], v[:, 1], v[:, 2]
    return np.sqrt(v0 * v0 + v1 * v1 + v2 * v2)


def invert(T: npt.ArrayLike) -> np.ndarray:
    """The inverse 4x4 transform (``apply(invert(T), apply(T, p)) ≈ p``).

    ``np.linalg.inv``: exact to rounding for any invertible affine matrix, and the same bits as the
    benchmark generator has always used, so its seeded data sets stay byte-identical.
    """
    return np.linalg.inv(np.asarray(T, dtype=np.float64))


def random_rotation(rng: np.random.Generator) -> np.ndarray:
    """A 3x3 rotation uniform on SO(3): a normalised Gaussian quaternion (Shoemake).

    Draws ``rng.normal(size=4)`` and returns the same matrix as
    ``scipy.spatial.transform.Rotation.random(random_state=rng).as_matrix()`` (scipy 1.17; equal to
    the last bit on some CPUs, within 1 ulp on others, where scipy's compiled code rounds differently).
    """
    q = rng.normal(size=4)
    x, y, z, w = q / np.linalg.norm(q)
    x2, y2, z2, w2 = x * x, y * y, z * z, w * w
    xy, zw, xz, yw, yz, xw = x * y, z * w, x * z, y * w, y * z, x * w
    return np.array([
        [x2 - y2 - z2 + w2, 2 * (xy - zw), 2 * (xz + yw)],
        [2 * (xy + zw), -x2 + y2 - z2 + w2, 2 * (yz - xw)],
        [2 * (xz - yw), 2 * (yz + xw), -x2 - y2 + z2 + w2],
    ])


def stats_sample(points: np.ndarray, n: int | None = None) -> np.ndarray:
    """``points`` itself when it has at most ``n`` (default :data:`STATS_POINTS`) rows, else ``n`` rows drawn
    at random with a fixed seed (with replacement, in stored order): the same rows for the same cloud, and
    no stride that a repeating record pattern could alias (every k-th row of a scan whose every 4th record
    is a ``0 0 0`` "no return" was all zeros for k = 4)."""
    n = STATS_POINTS if n is None else n
    if len(points) <= n:
        return points
    return points[np.sort(np.random.default_rng(0).integers(0, len(points), n))]


def extent(points: np.ndarray) -> np.ndarray:
    """The bounding box's size along x, y and z (``np.ptp(points, axis=0)`` exactly, column by column:
    about 7 times faster on an ``(N, 3)`` array, which numpy reduces along its first axis row by row)."""
    return np.array([np.ptp(points[:, k]) if len(points) else 0.0 for k in range(points.shape[1])])


def robust_core(points: np.ndarray, spread: float = 3.0, exact: bool = False) -> np.ndarray:
    """The points of ``points`` ``(N, 3)`` within ``spread`` times the 90th-percentile distance of the
    coordinate-wise median: the cloud without its far outliers (a stray ``0 0 0`` "no return" in a
    georeferenced export, a corrupt value), for the shape tests that one point must not decide. The
    median and the percentile are those of :func:`stats_sample` (the whole cloud up to :data:`STATS_POINTS`),
    or of every point with ``exact``."""
    reference = points if exact else stats_sample(points)
    median = np.median(reference, axis=0)
    d_ref = row_norms(reference - median)
    d = d_ref if reference is points else row_norms(points - median)
    return points[d <= spread * np.percentile(d_ref, 90)]


def coordinate_range_problem(points: np.ndarray) -> str | None:
    """Why finite ``points`` cannot be registered in float64 (squared distances overflow or underflow),
    or None: coordinates beyond ±:data:`MAX_COORDINATE` (a corrupt value; no scanner's units reach it),
    or a cloud whose extent is below :data:`MIN_EXTENT` without being a single point."""
    if not len(points):
        return None
    big = max(abs(float(points.min())), abs(float(points.max())))  # |points|.max() without a copy
    if big > MAX_COORDINATE:
        return (f"coordinates too large to register (|value| up to {big:.3g}, limit {MAX_COORDINATE:.0e}): "
                "a corrupt value, or units far outside any scanner's")
    size = float(extent(points).max())
    if 0.0 < size < MIN_EXTENT:
        return f"cloud too small to register (extent {size:.3g}, limit {MIN_EXTENT:.0e}): rescale it"
    return None
