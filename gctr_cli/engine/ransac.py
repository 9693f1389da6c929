"""Stage 6a: RANSAC with a similarity model, guided by the tensor's soft assignment.

Minimal samples are triples of correspondences. They come from the power iteration's result in
two ways: the tensor entries (triangle matches) with the highest support ``x_a x_b x_c h_abc``,
tried in that order (PROSAC-style), and random triples drawn from the top candidates of each
source row with probability proportional to their assignment weight. All hypotheses of a chunk
are solved at once with a batched Umeyama; scales outside the bounds are rejected; a hypothesis
scores the number of source salient points whose nearest target salient point, after the
transform, lies within ``threshold``. The winner is refit on its inliers.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from gctr_cli.engine.similarity import batched_umeyama, umeyama


@dataclass(frozen=True)
class RansacResult:
    scale: float
    rotation: np.ndarray
    translation: np.ndarray
    inliers_src: np.ndarray  # indices of inlier source points
    inliers_tgt: np.ndarray  # their nearest target points
    n_inliers: int


def sample_from_assignment(X: np.ndarray, n: int, k: int, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """``n`` random triples of correspondences from the top-``k`` targets of each source row,
    drawn with probability proportional to the assignment weight; returns (src (n,3), tgt (n,3))."""
    n1, n2 = X.shape
    k = min(k, n2)
    top = np.argpartition(-X, k - 1, axis=1)[:, :k] if k < n2 else np.tile(np.arange(n2), (n1, 1))
    src = np.repeat(np.arange(n1), k)
    tgt = top.ravel()
    w = np.clip(X[src, tgt], 0, None)
    if n <= 0 or w.sum() <= 0:
        return np.empty((0, 3), dtype=np.int64), np.empty((0, 3), dtype=np.int64)
    pick = rng.choice(len(src), size=(n, 3), p=w / w.sum())
    return src[pick], tgt[pick]


def count_inliers(s: np.ndarray, R: np.ndarray, t: np.ndarray, S: np.ndarray, tgt_tree: cKDTree,
                  threshold: float) -> np.ndarray:
    """For each hypothesis, how many of the points ``S`` land within ``threshold`` of the target."""
    moved = s[:, None, None] * np.einsum("hij,kj->hki", R, S) + t[:, None, :]
    d, _ = tgt_tree.query(moved.reshape(-1, 3), distance_upper_bound=threshold)
    return np.isfinite(d).reshape(len(s), len(S)).sum(axis=1)


def ransac_similarity(S: np.ndarray, Q: np.ndarray, tgt_tree: cKDTree, samples_src: np.ndarray,
                      samples_tgt: np.ndarray, threshold: float,
                      scale_bounds: tuple[float, float] = (0.0, np.inf), min_spread: float = 0.0,
                      chunk: int = 1024) -> RansacResult | None:
    """Best similarity ``Q ~ s R S + t`` among the minimal samples (index triples into S and Q).

    Returns None when no sample passes the checks (degenerate, or scale out of bounds).
    """
    best_score, best = -1, None
    for start in range(0, len(samples_src), chunk):
        si = samples_src[start:start + chunk]
        ti = samples_tgt[start:start + chunk]
        distinct = ((si[:, 0] != si[:, 1]) & (si[:, 1] != si[:, 2]) & (si[:, 0] != si[:, 2])
                    & (ti[:, 0] != ti[:, 1]) & (ti[:, 1] != ti[:, 2]) & (ti[:, 0] != ti[:, 2]))
        a, b = S[si], Q[ti]
        area = np.linalg.norm(np.cross(a[:, 1] - a[:, 0], a[:, 2] - a[:, 0]), axis=1)
        ok = distinct & (area > min_spread ** 2)
        if not ok.any():
            continue
        s, R, t = batched_umeyama(a[ok], b[ok])
        good = (s >= scale_bounds[0]) & (s <= scale_bounds[1])
        if not good.any():
            continue
        s, R, t = s[good], R[good], t[good]
        score = count_inliers(s, R, t, S, tgt_tree, threshold)
        j = int(np.argmax(score))
        if score[j] > best_score:
            best_score, best = int(score[j]), (float(s[j]), R[j], t[j])
    if best is None:
        return None
    s, R, t = best
    for _ in range(3):
        src_in, tgt_in = inlier_matches(s, R, t, S, tgt_tree, threshold)
        if len(src_in) < 3:
            break
        s2, R2, t2 = umeyama(S[src_in], Q[tgt_in])
        if not scale_bounds[0] <= s2 <= scale_bounds[1]:
            break
        s, R, t = s2, R2, t2
    src_in, tgt_in = inlier_matches(s, R, t, S, tgt_tree, threshold)
    return RansacResult(scale=s, rotation=R, translation=t, inliers_src=src_in, inliers_tgt=tgt_in,
                        n_inliers=len(src_in))


def inlier_matches(s: float, R: np.ndarray, t: np.ndarray, S: np.ndarray, tgt_tree: cKDTree,
                   threshold: float) -> tuple[np.ndarray, np.ndarray]:
    """Source points within ``threshold`` of a target point after the transform, and those targets."""
    d, j = tgt_tree.query(s * S @ R.T + t, distance_upper_bound=threshold)
    ok = np.flatnonzero(np.isfinite(d))
    return ok, j[ok]
