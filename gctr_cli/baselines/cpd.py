"""``cpd``: rigid Coherent Point Drift with scale (Myronenko & Song, PAMI 2010, Fig. 2), in numpy.

The target points ``X`` (N) are samples of a Gaussian mixture whose centroids are the moving source
points ``Y`` (M) under ``s R y + t``, plus a uniform component of weight ``w`` for outliers. EM:
the E-step computes the posteriors ``P`` (M x N); the M-step has a closed form (SVD of the weighted
cross-covariance for R, then s, t and the isotropic variance sigma^2). Memory and time per
iteration grow as M x N, so both clouds are subsampled (seeded) to at most ``cpd.max_points``.
Like ICP, CPD is local: it starts from the bounding-box normalisation (identity).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from gctr_cli.baselines.common import Timer, run_guarded
from gctr_cli.config import BaselineConfig
from gctr_cli.engine.result import RegistrationResult


@dataclass(frozen=True)
class CpdResult:
    scale: float
    rotation: np.ndarray
    translation: np.ndarray
    sigma2: float
    iterations: int
    converged: bool


def _sq_dists(Y: np.ndarray, X: np.ndarray) -> np.ndarray:
    """(M, N) squared distances."""
    d2 = (Y * Y).sum(axis=1)[:, None] + (X * X).sum(axis=1)[None, :] - 2.0 * (Y @ X.T)
    np.maximum(d2, 0.0, out=d2)
    return d2


def cpd_rigid(X: np.ndarray, Y: np.ndarray, w: float = 0.1, max_iterations: int = 150,
              tol: float = 1e-6) -> CpdResult:
    """Rigid CPD with scale: ``X ~ s R Y + t`` (X target (N, D), Y source (M, D)).

    Stops when the relative change of the EM objective ``Q`` is below ``tol`` or after
    ``max_iterations`` iterations.
    """
    X = np.asarray(X, dtype=np.float64)
    Y = np.asarray(Y, dtype=np.float64)
    N, D = X.shape
    M = len(Y)
    R, s, t = np.eye(D), 1.0, np.zeros(D)
    sigma2 = float(_sq_dists(Y, X).sum() / (D * M * N))
    tiny = np.finfo(float).tiny
    q_prev = np.inf
    converged = False
    it = 0  # iterations run; reported in the result
    while it < max_iterations:
        it += 1
        # E-step
        TY = s * Y @ R.T + t
        P = np.exp(_sq_dists(TY, X) / (-2.0 * sigma2))
        c = (2.0 * np.pi * sigma2) ** (D / 2.0) * (w / (1.0 - w)) * (M / N) if w > 0 else 0.0
        P /= P.sum(axis=0, keepdims=True) + c + tiny
        # M-step
        Pt1, P1 = P.sum(axis=0), P.sum(axis=1)
        Np = float(P1.sum())
        if Np <= tiny:
            break
        mu_x, mu_y = X.T @ Pt1 / Np, Y.T @ P1 / Np
        Xh, Yh = X - mu_x, Y - mu_y
        A = Xh.T @ (P.T @ Yh)
        U, _, Vt = np.linalg.svd(A)
        C = np.eye(D)
        C[-1, -1] = np.sign(np.linalg.det(U @ Vt)) or 1.0
        R = U @ C @ Vt
        tr_ar = float(np.trace(A.T @ R))
        ypy = float(P1 @ (Yh * Yh).sum(axis=1))
        xpx = float(Pt1 @ (Xh * Xh).sum(axis=1))
        s = tr_ar / ypy
        t = mu_x - s * R @ mu_y
        sigma2 = max((xpx - s * tr_ar) / (Np * D), 1e-12)
        q = (xpx - 2.0 * s * tr_ar + s * s * ypy) / (2.0 * sigma2) + Np * D / 2.0 * np.log(sigma2)
        if abs(q_prev - q) <= tol * abs(q):
            converged = True
            break
        q_prev = q
    return CpdResult(scale=float(s), rotation=R, translation=t, sigma2=sigma2, iterations=it, converged=converged)


def _cpd(prep, cfg: BaselineConfig, seed: int, timer: Timer) -> tuple[np.ndarray, int]:
    c = cfg.cpd
    rng_src, rng_tgt = (np.random.default_rng(s) for s in np.random.SeedSequence(seed).spawn(2))

    def subsample(points: np.ndarray, rng: np.random.Generator) -> np.ndarray:
        if len(points) <= c.max_points:
            return points
        return points[np.sort(rng.choice(len(points), c.max_points, replace=False))]

    Y = subsample(prep.src.points, rng_src)
    X = subsample(prep.tgt.points, rng_tgt)
    timer.lap("preprocess")
    r = cpd_rigid(X, Y, w=c.w, max_iterations=c.max_iterations, tol=c.tol)
    timer.lap("cpd")
    T = np.eye(4)
    T[:3, :3] = r.scale * r.rotation
    T[:3, 3] = r.translation
    return T, r.iterations


def register_cpd(source: np.ndarray, target: np.ndarray, cfg: BaselineConfig | None = None,
                 seed: int = 0) -> RegistrationResult:
    """Register ``source`` onto ``target`` with rigid CPD with scale after the bounding-box normalisation.

    Each cloud is subsampled (seeded by ``seed``) to at most ``cpd.max_points`` points; ``cpd.w`` is
    the outlier weight; EM runs until the relative change of its objective is below ``cpd.tol`` or
    ``cpd.max_iterations`` iterations (reported in ``iterations``). Never raises for degenerate
    inputs: returns ``status='failed'`` with a message.
    """
    return run_guarded(_cpd, source, target, cfg, seed)
