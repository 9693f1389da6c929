"""Stage 8: optional dense refinement — trimmed scaled ICP on the downsampled clouds.

Plain scaled ICP drifts the scale on partially overlapping clouds with outliers, so pairs are
trimmed by a distance threshold that shrinks geometrically from ``start`` to ``end`` and the
caller keeps the refined transform only when the robust fitness improves.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from gctr_cli.engine.similarity import apply, to_matrix, umeyama


@dataclass(frozen=True)
class Fit:
    fitness: float  # fraction of source points with a target point within the distance
    rmse: float  # RMS of those distances
    n_inliers: int


def evaluate_fit(src: np.ndarray, tgt_tree: cKDTree, T: np.ndarray, distance: float) -> Fit:
    """Robust fitness of ``T`` mapping ``src`` onto the target behind ``tgt_tree``."""
    d, _ = tgt_tree.query(apply(T, src), distance_upper_bound=distance)
    ok = np.isfinite(d)
    n = int(ok.sum())
    rmse = float(np.sqrt(np.mean(d[ok] ** 2))) if n else float("inf")
    return Fit(fitness=n / max(len(src), 1), rmse=rmse, n_inliers=n)


def trimmed_scaled_icp(src: np.ndarray, tgt: np.ndarray, T0: np.ndarray, iterations: int,
                       start: float, end: float, scale_bounds: tuple[float, float],
                       tgt_tree: cKDTree | None = None) -> tuple[np.ndarray, int]:
    """Scaled point-to-point ICP with a shrinking trimming distance; returns (T, iterations run)."""
    tree = tgt_tree if tgt_tree is not None else cKDTree(tgt)
    T = T0.copy()
    taus = np.geomspace(start, end, max(iterations, 1))
    it = 0
    for it, tau in enumerate(taus, start=1):
        d, j = tree.query(apply(T, src), distance_upper_bound=tau)
        keep = np.isfinite(d)
        if keep.sum() < 10:
            break
        s, R, t = umeyama(src[keep], tgt[j[keep]])
        if not scale_bounds[0] <= s <= scale_bounds[1]:
            break
        T_new = to_matrix(s, R, t)
        change = np.linalg.norm(T_new - T)
        T = T_new
        if change < 1e-7 and tau <= end * 1.001:
            break
    return T, it
