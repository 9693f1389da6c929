"""Stage 1: validate, centre and normalise a cloud, downsample it early, estimate normals.

Everything later works in *normalised* coordinates where each cloud has its robust centre at the
origin and a robust diameter of 1, so that every relative length in the config means the same
thing on both clouds whatever their (unknown) relative scale. The caller composes the
normalisations back into the reported transform.
"""

from __future__ import annotations

import os
from dataclasses import dataclass

import numpy as np

from gctr_cli.engine.scipy_parts import cKDTree
from gctr_cli.geometry import coordinate_range_problem, cross, robust_core, row_norms, stats_sample


class DegenerateCloudError(ValueError):
    """The cloud cannot constrain a similarity transform (too few points, collinear, planar...)."""


@dataclass(frozen=True)
class NormalisedCloud:
    """A cloud in normalised coordinates: ``points = (original - centre) / size``."""

    points: np.ndarray
    centre: np.ndarray
    size: float

    def to_original(self) -> np.ndarray:
        """4x4 similarity from normalised to original coordinates."""
        T = np.eye(4)
        T[:3, :3] *= self.size
        T[:3, 3] = self.centre
        return T


def denormalise(T_n: np.ndarray, src: NormalisedCloud, tgt: NormalisedCloud) -> np.ndarray:
    """Turn a transform between two normalised clouds into one between the original clouds:
    ``target = tgt.size * (T_n (source - src.centre) / src.size) + tgt.centre``.

    Written out instead of multiplying 4x4 matrices so that large coordinates (e.g. UTM offsets
    of 1e6) keep full precision: the translation is ``c_t + size_t * t_n - A c_s``.
    """
    A = T_n[:3, :3] * (tgt.size / src.size)
    T = np.eye(4)
    T[:3, :3] = A
    T[:3, 3] = tgt.centre + tgt.size * T_n[:3, 3] - A @ src.centre
    return T


def validate_cloud(points: np.ndarray, name: str, min_points: int = 10) -> np.ndarray:
    """Return a finite (N, 3) float64 array or raise :class:`DegenerateCloudError`.

    Planar clouds are rejected too: a plane leaves the rotation about its normal (and, with a
    similarity, the scale/translation along it) undetermined.
    """
    if isinstance(points, (str, bytes, os.PathLike)):
        raise DegenerateCloudError(f"{name}: expected an (N, 3) array of point coordinates, got the path "
                                   f"{os.fsdecode(points)!r}: read it with gctr_cli.io.load_point_cloud")
    try:  # a ragged list ... is an answer naming the problem, not numpy's exception
        if np.ma.isMaskedArray(points):  # masked points are left out, like non-finite ones
            points = np.ma.filled(np.ma.asarray(points, dtype=np.float64), np.nan)
        raw = np.asarray(points)
        kind = raw.dtype.kind
        pts = raw if kind in "cmM" else raw.astype(np.float64, copy=False)
    except (TypeError, ValueError) as exc:
        raise DegenerateCloudError(f"{name}: expected an (N, 3) array of point coordinates, got "
                                   f"{type(points).__name__} ({str(exc).split(chr(10))[0][:200]}); read a file "
                                   "with gctr_cli.io.load_point_cloud") from None
    if kind in "cmM":
        raise DegenerateCloudError(f"{name}: expected an (N, 3) array of point coordinates, got "
                                   f"{'complex numbers' if kind == 'c' else 'dates or durations'}")
    if kind == "b":
        raise DegenerateCloudError(f"{name}: expected an (N, 3) array of point coordinates, got booleans")
    if pts.ndim != 2 or pts.shape[1] != 3:
        raise DegenerateCloudError(f"{name}: expected an (N, 3) array of points, got shape {pts.shape}")
    if not np.isfinite(pts).all():  # (the whole array at once: 10 times faster than row by row)
        pts = pts[np.all(np.isfinite(pts), axis=1)]
    if len(pts) < min_points:
        raise DegenerateCloudError(f"{name}: only {len(pts)} finite point{'' if len(pts) == 1 else 's'} "
                                  f"(need at least {min_points})")
    problem = coordinate_range_problem(pts)
    if problem:
        raise DegenerateCloudError(f"{name}: {problem}")
    # The shape tests look at the cloud without its far outliers (a stray 0 0 0 beside UTM
    # coordinates would otherwise make any cloud look flat).
    sample = pts[:: max(1, len(pts) // 20000)]
    core = robust_core(sample)
    sv = np.linalg.svd(core - core.mean(axis=0), compute_uv=False)
    if sv[0] == 0.0:
        if len(core) == len(sample):
            raise DegenerateCloudError(f"{name}: all {len(pts)} points are identical")
        of = f"{len(sample)} sampled" if len(sample) < len(pts) else f"its {len(pts)}"
        rest = len(sample) - len(core)
        others = "the other one lies" if rest == 1 else f"the other {rest} lie"
        raise DegenerateCloudError(f"{name}: {len(core)} of {of} points are identical; {others} far from them")
    if sv[1] < 1e-9 * sv[0]:
        raise DegenerateCloudError(f"{name}: points are collinear")
    if sv[1] < 1e-3 * sv[0]:  # a needle: both other extents under 0.1%
        raise DegenerateCloudError(f"{name}: points are nearly collinear (width {sv[1] / sv[0]:.1e} and thickness "
                                   f"{sv[2] / sv[0]:.1e} of the length; registration would be ambiguous)")
    if sv[2] < 1e-3 * sv[0]:
        # Thinner than 0.1% of its extent: flat up to noise, so the rotation about the normal and
        # the scale are not observable; better a clear failure than a confident wrong matrix.
        raise DegenerateCloudError(f"{name}: points are planar (thickness {sv[2] / sv[0]:.1e} of the extent; "
                                   "registration would be ambiguous)")
    return pts


def robust_centre_and_size(points: np.ndarray) -> tuple[np.ndarray, float]:
    """Robust centre and diameter: the mean of the 80% of points nearest the coordinate-wise median
    (nearly rotation-equivariant, unlike the median itself), and twice the 90th percentile of the
    distances to that centre.

    Unlike the bounding-box diagonal this barely moves under rotation, moderate crops and outliers.
    Taken on :func:`~gctr_cli.geometry.stats_sample` of the cloud (all of it up to a million points).
    """
    points = stats_sample(points)
    median = np.median(points, axis=0)
    r0 = row_norms(points - median)
    centre = points[r0 <= np.percentile(r0, 80)].mean(axis=0)
    r = row_norms(points - centre)
    size = 2.0 * float(np.percentile(r, 90))
    if size <= 0:
        size = 2.0 * float(r.max())
    return centre, size


def normalise(points: np.ndarray) -> NormalisedCloud:
    """Centre a cloud on its robust centre and scale it to a robust diameter of 1."""
    centre, size = robust_centre_and_size(points)
    normalised = points - centre
    normalised /= size  # in place: one copy of a large cloud, not two
    return NormalisedCloud(points=normalised, centre=centre, size=size)


def voxel_keys(points: np.ndarray, size: float) -> np.ndarray:
    """One int64 key per point identifying its voxel (a 1-D key makes ``np.unique`` fast)."""
    cells = np.floor(points / size)
    cells -= cells.min(axis=0)
    dims = cells.max(axis=0) + 1
    if float(dims[0]) * float(dims[1]) * float(dims[2]) >= 2.0**62:
        # A far outlier spans a grid whose flat index (or even a cell index) would overflow int64
        # and merge voxels silently: number the occupied cells instead.
        return np.unique(cells, axis=0, return_inverse=True)[1].reshape(-1)
    ijk, d = cells.astype(np.int64), dims.astype(np.int64)
    return (ijk[:, 0] * d[1] + ijk[:, 1]) * d[2] + ijk[:, 2]


def voxel_downsample(points: np.ndarray, voxel: float) -> np.ndarray:
    """Centroid of the points in each occupied voxel (equalises density across sensors)."""
    _, inverse, counts = np.unique(voxel_keys(points, voxel), return_inverse=True, return_counts=True)
    out = np.empty((len(counts), 3))
    for d in range(3):
        out[:, d] = np.bincount(inverse, weights=points[:, d], minlength=len(counts)) / counts
    return out


def downsample_to(points: np.ndarray, voxel: float, max_points: int, rng: np.random.Generator) -> np.ndarray:
    """Voxel downsampling at ``voxel``; if still above ``max_points``, a seeded random subset."""
    if len(points) > 4 * max_points:
        # Cheap first cut for huge inputs, before any sort-based step.
        points = points[rng.choice(len(points), 4 * max_points, replace=False)]
    down = voxel_downsample(points, voxel)
    if len(down) > max_points:
        down = down[np.sort(rng.choice(len(down), max_points, replace=False))]
    return down


def nearest_neighbours(points: np.ndarray, k: int, tree: cKDTree | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Distances (sorted) and indices of each point's ``k`` nearest neighbours, itself included
    (distance 0), as (N, k) arrays (``k`` is capped at the number of points). ``tree``: a k-d tree over
    ``points`` if the caller has one."""
    k = min(k, len(points))
    dist, idx = (tree if tree is not None else cKDTree(points)).query(points, k=k)
    return dist.reshape(len(points), k), idx.reshape(len(points), k)


def normals_from_neighbours(points: np.ndarray, idx: np.ndarray) -> np.ndarray:
    """Unit normals from PCA of each point's neighbours ``idx`` (N, k) (batched 3x3 eigen-decomposition)."""
    return normals_and_roughness(points, idx)[0]


def normals_and_roughness(points: np.ndarray, idx: np.ndarray) -> tuple[np.ndarray, float]:
    """Unit normals as :func:`normals_from_neighbours`, and the cloud's surface roughness: the median
    RMS distance of a point's neighbours from their PCA plane (the square root of the smallest
    eigenvalue; sensor noise, plus curvature and the sampling at the neighbourhood's scale)."""
    if len(points) == 0:
        return np.zeros((0, 3)), 0.0
    # The six covariance entries one coordinate at a time, in local coordinates (better conditioned
    # sums): (N, k) arrays are faster to reduce than a batched (N, 3, k) @ (N, k, 3) product.
    k = idx.shape[1]
    x, y, z = (points[idx, c] - points[:, c, None] for c in range(3))
    mx, my, mz = x.mean(axis=1), y.mean(axis=1), z.mean(axis=1)
    cov = np.empty((len(points), 6))
    cov[:, 0] = np.einsum("ij,ij->i", x, x) / k - mx * mx
    cov[:, 1] = np.einsum("ij,ij->i", y, y) / k - my * my
    cov[:, 2] = np.einsum("ij,ij->i", z, z) / k - mz * mz
    cov[:, 3] = np.einsum("ij,ij->i", x, y) / k - mx * my
    cov[:, 4] = np.einsum("ij,ij->i", x, z) / k - mx * mz
    cov[:, 5] = np.einsum("ij,ij->i", y, z) / k - my * mz
    smallest, normals = smallest_eigenpairs(cov)
    roughness = float(np.median(np.sqrt(np.maximum(smallest, 0.0))))
    return normals, roughness


def smallest_eigenpairs(cov: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Smallest eigenvalue and its unit eigenvector of each symmetric 3x3 matrix, given as (N, 6) rows
    (xx, yy, zz, xy, xz, yz).

    Closed form, about 7x faster than a batched ``np.linalg.eigh``: the eigenvalue by the
    trigonometric solution of the characteristic cubic (Smith 1961), the eigenvector as the longest
    cross product of two rows of ``A - lambda I``. Where that is ill-defined (two smallest eigenvalues
    equal to within 1e-8 of the spread: isotropic or line-like neighbourhoods, whose normal is
    arbitrary anyway) the rows fall back to ``eigh``. Near a repeated eigenvalue the cubic's solution
    keeps about half the digits (1e-8 of the largest eigenvalue): far below any roughness that matters.
    """
    a00, a11, a22, a01, a02, a12 = cov.T
    q = (a00 + a11 + a22) / 3.0
    b00, b11, b22 = a00 - q, a11 - q, a22 - q
    p = np.sqrt((b00 * b00 + b11 * b11 + b22 * b22 + 2.0 * (a01 * a01 + a02 * a02 + a12 * a12)) / 6.0)
    det = b00 * (b11 * b22 - a12 * a12) - a01 * (a01 * b22 - a12 * a02) + a02 * (a01 * a12 - b11 * a02)
    with np.errstate(invalid="ignore", divide="ignore"):
        half_det = np.where(p > 0, det / (2.0 * p ** 3), 0.0)
    lam = q + 2.0 * p * np.cos(np.arccos(np.clip(half_det, -1.0, 1.0)) / 3.0 + 2.0 * np.pi / 3.0)
    r0 = np.stack([a00 - lam, a01, a02], axis=1)
    r1 = np.stack([a01, a11 - lam, a12], axis=1)
    r2 = np.stack([a02, a12, a22 - lam], axis=1)
    crosses = np.stack([cross(r0, r1), cross(r0, r2), cross(r1, r2)], axis=1)
    sq = np.einsum("nij,nij->ni", crosses, crosses)
    best = sq.argmax(axis=1)
    rows = np.arange(len(cov))
    length = np.sqrt(sq[rows, best])
    vec = crosses[rows, best]
    bad = ~(length > 1e-8 * p * p) | ~np.isfinite(length)
    vec[~bad] /= length[~bad, None]
    if bad.any():
        full = np.empty((int(bad.sum()), 3, 3))
        full[:, 0, 0], full[:, 1, 1], full[:, 2, 2] = a00[bad], a11[bad], a22[bad]
        full[:, 0, 1] = full[:, 1, 0] = a01[bad]
        full[:, 0, 2] = full[:, 2, 0] = a02[bad]
        full[:, 1, 2] = full[:, 2, 1] = a12[bad]
        vals, vecs = np.linalg.eigh(full)
        lam[bad], vec[bad] = vals[:, 0], vecs[:, :, 0]
    return lam, vec


def estimate_normals(points: np.ndarray, k: int = 16) -> np.ndarray:
    """Unit normals from PCA of the k nearest neighbours."""
    return normals_from_neighbours(points, nearest_neighbours(points, k)[1])
