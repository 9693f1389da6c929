"""Stage 4: closed-form similarity from correspondences.

Rotation from the SVD of the cross-covariance (with the reflection fix), scale either by
Umeyama's closed form or by the paper's mean ratio of corresponding edge lengths, translation
``t = mu_B - s R mu_A``. Convention: ``B ~ s R A + t`` (A source, B target).
"""

from __future__ import annotations

import numpy as np


def batched_umeyama(A: np.ndarray, B: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Umeyama similarity for a batch: A, B of shape (H, k, 3) → s (H,), R (H, 3, 3), t (H, 3)."""
    mu_a = A.mean(axis=1, keepdims=True)
    mu_b = B.mean(axis=1, keepdims=True)
    Ac, Bc = A - mu_a, B - mu_b
    cov = np.einsum("hki,hkj->hij", Bc, Ac) / A.shape[1]
    U, D, Vt = np.linalg.svd(cov)
    sign = np.sign(np.linalg.det(U) * np.linalg.det(Vt))
    sign[sign == 0] = 1.0
    S = np.ones((len(A), 3))
    S[:, 2] = sign
    R = np.einsum("hij,hj,hjk->hik", U, S, Vt)
    var_a = np.einsum("hki,hki->h", Ac, Ac) / A.shape[1]
    s = np.einsum("hi,hi->h", D, S) / np.maximum(var_a, 1e-300)
    t = mu_b[:, 0] - s[:, None] * np.einsum("hij,hj->hi", R, mu_a[:, 0])
    return s, R, t


def umeyama(A: np.ndarray, B: np.ndarray) -> tuple[float, np.ndarray, np.ndarray]:
    """Least-squares similarity ``B ~ s R A + t`` (Umeyama 1991)."""
    s, R, t = batched_umeyama(A[None], B[None])
    return float(s[0]), R[0], t[0]


def edge_ratio_scale(A: np.ndarray, B: np.ndarray, min_edge: float = 0.0) -> float:
    """The paper's scale: mean of |B_{i+1} - B_i| / |A_{i+1} - A_i| over consecutive matched pairs.

    Pairs whose source edge is shorter than ``min_edge`` are skipped (their ratio is dominated by
    noise); returns NaN if none is left.
    """
    la = np.linalg.norm(np.diff(A, axis=0), axis=1)
    lb = np.linalg.norm(np.diff(B, axis=0), axis=1)
    ok = la > max(min_edge, 1e-300)
    if not ok.any():
        return float("nan")
    return float(np.mean(lb[ok] / la[ok]))


def similarity_with_scale(A: np.ndarray, B: np.ndarray, scale: float,
                          R: np.ndarray) -> np.ndarray:
    """Translation for a fixed scale and rotation: ``t = mu_B - s R mu_A``."""
    return B.mean(axis=0) - scale * R @ A.mean(axis=0)


def best_similarity(A: np.ndarray, B: np.ndarray, method: str = "auto",
                    rng: np.random.Generator | None = None) -> tuple[float, np.ndarray, np.ndarray, str]:
    """Similarity from inlier correspondences with the configured scale estimator.

    ``method='auto'`` computes both Umeyama's scale and the paper's edge-ratio scale (over a random
    ordering of the pairs, edges shorter than 10% of the source spread skipped) and keeps the one
    with the lower median residual. Returns (s, R, t, method_used).
    """
    s_u, R, t_u = umeyama(A, B)
    if method == "umeyama" or len(A) < 3:
        return s_u, R, t_u, "umeyama"
    order = rng.permutation(len(A)) if rng is not None else np.arange(len(A))
    spread = float(np.sqrt(((A - A.mean(axis=0)) ** 2).sum(axis=1).mean()))
    s_e = edge_ratio_scale(A[order], B[order], min_edge=0.1 * spread)
    if not np.isfinite(s_e) or s_e <= 0:
        return s_u, R, t_u, "umeyama"
    t_e = similarity_with_scale(A, B, s_e, R)
    if method == "edge_ratio":
        return s_e, R, t_e, "edge_ratio"
    res_u = np.median(np.linalg.norm(s_u * A @ R.T + t_u - B, axis=1))
    res_e = np.median(np.linalg.norm(s_e * A @ R.T + t_e - B, axis=1))
    if res_e < res_u:
        return s_e, R, t_e, "edge_ratio"
    return s_u, R, t_u, "umeyama"
