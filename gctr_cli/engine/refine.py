"""Stage 5 (inside the verdict): scaled ICP that polishes each finalist on the working clouds.

Point-to-plane by default (trimmed point-to-point optionally). Plain scaled ICP drifts the scale on
partially overlapping clouds with outliers, so matches are trimmed by a distance threshold that
shrinks geometrically from ``start`` to ``end`` and matches with incompatible normals are dropped;
the caller (``decide._refine``) keeps the result only if the tight surface agreement does not drop.
A step that would take the scale beyond ``scale_bounds`` is taken with the scale held at the bound (the
rotation and translation solved for it). The ICP used to stop before such a step, so an answer whose
refinement leans past a bound was not refined at all: under ``configs/rigid.yaml`` ([0.99, 1.01]) noisy
pairs, whose refinement with a free scale ends 1.5-4% low, came back near the truth but 5-14° off (17 of
124 noisy pairs made rigid; 10 of them end within 5° now).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from gctr_cli.engine.scipy_parts import cKDTree
from gctr_cli.engine.similarity import similarity_with_scale, umeyama
from gctr_cli.engine.verdict import surface_matches
from gctr_cli.geometry import apply, cross, to_matrix


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
    for it, tau in enumerate(taus, start=1):  # noqa: B007 (the count is returned)
        d, j = tree.query(apply(T, src), distance_upper_bound=tau)
        keep = np.isfinite(d)
        if keep.sum() < 10:
            break
        s, R, t = umeyama(src[keep], tgt[j[keep]])
        if not scale_bounds[0] <= s <= scale_bounds[1]:
            # the best similarity at the bound: Umeyama's rotation does not depend on the scale
            s = float(np.clip(s, *scale_bounds))
            t = similarity_with_scale(src[keep], tgt[j[keep]], s, R)
        T_new = to_matrix(s, R, t)
        change = np.linalg.norm(T_new - T)
        T = T_new
        if change < 1e-7 and tau <= end * 1.001:
            break
    return T, it


def _small_similarity(x: np.ndarray) -> np.ndarray:
    """4x4 similarity from the linearised update (wx, wy, wz, tx, ty, tz, log-scale)."""
    w, t, ds = x[:3], x[3:6], x[6]
    theta = float(np.linalg.norm(w))
    K = np.array([[0, -w[2], w[1]], [w[2], 0, -w[0]], [-w[1], w[0], 0]])
    if theta > 1e-12:
        R = np.eye(3) + np.sin(theta) / theta * K + (1 - np.cos(theta)) / theta**2 * K @ K
    else:
        R = np.eye(3) + K
    return to_matrix(float(np.exp(ds)), R, t)


def scaled_point_to_plane_icp(src: np.ndarray, tgt: np.ndarray, tgt_normals: np.ndarray, T0: np.ndarray,
                              iterations: int, start: float, end: float, scale_bounds: tuple[float, float],
                              tgt_tree: cKDTree | None = None, src_normals: np.ndarray | None = None,
                              max_normal_angle_deg: float = 90.0, src_tree: cKDTree | None = None,
                              symmetric: bool = False, max_matches: int = 0) -> tuple[np.ndarray, int]:
    """Scaled point-to-plane ICP, linearised Gauss-Newton with trimming and Huber weights.

    Minimises ``sum w_i ((s R p_i + t - q_i) . n_i)^2`` over matches closer than a trimming
    distance that shrinks geometrically from ``start`` to ``end``. Point-to-plane lets the clouds
    slide along the surface, which avoids the scale and rotation bias that point-to-point matching
    of differently sampled, noisy surfaces shows. With ``src_normals``, matches whose normals differ
    by more than ``max_normal_angle_deg`` are dropped: outlier points have random normals, and
    uniform outliers inside the target's volume otherwise pull the scale inwards.

    With ``symmetric``, the target points are also matched back onto the moved source (residuals along
    the source normals, held fixed within an iteration); the two directions weigh half each, however
    many matches each has (weights inversely proportional to the counts): on noisy clouds one-way ICP
    shrinks the moving cloud by 1-20% (measured from the true pose on the benchmark's part pairs;
    without noise it does not), and matching the other way shrinks the other cloud by about as much,
    so the two biases cancel. Without ``src_normals`` the ICP is one-way whatever ``symmetric`` says.

    ``max_matches`` > 0 moves only a subset of at most that many points of each cloud, every k-th by
    index (their partners are still looked up among all points): seven parameters need far fewer
    matches than a working cloud has, and the neighbour queries are the cost of every iteration.
    """
    min_cos = float(np.cos(np.radians(max_normal_angle_deg)))
    tree = tgt_tree if tgt_tree is not None else cKDTree(tgt)
    T = T0.copy()
    taus = np.geomspace(start, end, max(iterations, 1))
    it = 0
    src_all, src_normals_all = src, src_normals
    if 0 < max_matches < len(src):
        stride = -(-len(src) // max_matches)
        src, src_normals = src[::stride], (src_normals[::stride] if src_normals is not None else None)
    s_tree: cKDTree | None = None
    tgt_back, tgt_back_normals = tgt, tgt_normals
    if symmetric and src_normals_all is not None:
        s_tree = src_tree if src_tree is not None else cKDTree(src_all)
        stride = -(-len(tgt) // max_matches) if 0 < max_matches < len(tgt) else 1
        tgt_back, tgt_back_normals = tgt[::stride], tgt_normals[::stride]
    for it, tau in enumerate(taus, start=1):  # noqa: B007 (the count is returned)
        A_lin = T[:3, :3]
        s_cur = float(np.cbrt(np.linalg.det(A_lin)))
        R = A_lin / s_cur
        moved_normals = src_normals @ R.T if src_normals is not None else None
        moved = apply(T, src)
        i, j = surface_matches(moved, moved_normals, tgt_normals, tree, tau, min_cos)
        p, q, n = moved[i], tgt[j], tgt_normals[j]
        weight = np.ones(len(p))
        if s_tree is not None and src_normals_all is not None:
            # Back matches: each target point, pulled back into the source frame, to its nearest
            # source point; residual (moved source point - target point) . moved source normal.
            back = (tgt_back - T[:3, 3]) @ R / s_cur
            ib, jb = surface_matches(back, tgt_back_normals @ R, src_normals_all, s_tree, tau / s_cur, min_cos)
            if len(ib):
                weight = np.r_[np.full(len(p), 0.5 / max(len(p), 1)), np.full(len(ib), 0.5 / len(ib))]
                weight *= len(weight)  # each direction weighs half, whatever its number of matches
                p = np.vstack([p, apply(T, src_all[jb])])
                q = np.vstack([q, tgt_back[ib]])
                n = np.vstack([n, src_normals_all[jb] @ R.T])
        if len(p) < 20:
            break
        centre = p.mean(axis=0)  # linearise about the matched points' centroid (better conditioned)
        pc = p - centre
        r = np.einsum("ij,ij->i", p - q, n)
        # d(residual) / d(w, t, log s): [pc x n, n, pc . n]
        J = np.hstack([cross(pc, n), n, np.einsum("ij,ij->i", pc, n)[:, None]])
        huber = np.maximum(np.abs(r), 1e-12)
        w = weight * np.where(huber < tau / 3, 1.0, (tau / 3) / huber)
        A = J.T @ (J * w[:, None])
        b = -J.T @ (w * r)
        try:
            x = np.linalg.solve(A + 1e-9 * np.eye(7), b)
            s_step = s_cur * float(np.exp(x[6]))
            if not scale_bounds[0] <= s_step <= scale_bounds[1]:
                # the step at the bound: the log-scale fixed there, rotation and translation solved for it
                ds = float(np.log(np.clip(s_step, *scale_bounds) / s_cur))
                x = np.r_[np.linalg.solve(A[:6, :6] + 1e-9 * np.eye(6), b[:6] - A[:6, 6] * ds), ds]
        except np.linalg.LinAlgError:
            break
        if not np.isfinite(x).all():  # (the bound check stopped a non-finite step before)
            break
        step = _small_similarity(x)
        C = np.eye(4)
        C[:3, 3] = centre
        Ci = np.eye(4)
        Ci[:3, 3] = -centre
        T = C @ step @ Ci @ T
        if np.linalg.norm(x) < 1e-7 and tau <= end * 1.001:
            break
    return T, it
