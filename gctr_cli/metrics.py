"""Errors of an estimated similarity against ground truth (the paper's R, T, S and TM errors)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from gctr_cli.geometry import split

#: how far R·Rᵀ of a ground-truth matrix may differ from the identity (entry by entry; R the 3x3 block over
#: its scale): a matrix typed or printed with three decimals is off by 0.001–0.008 at scales 0.2–0.5 (more
#: at smaller scales). A stretch or shear of up to about 1.5% passes as well; any matrix off by more than
#: :data:`STRICT_ORTHOGONALITY_TOL` is measured against its nearest similarity, with a warning
GT_ORTHOGONALITY_TOL = 1e-2
#: what a similarity computed in float64 (the engine's answers) is held to
STRICT_ORTHOGONALITY_TOL = 1e-3


def orthogonality_deviation(T: np.ndarray) -> float:
    """The largest entry of |R·Rᵀ − I|, R the 3x3 block of ``T`` over its scale (det^(1/3), det > 0)."""
    A = np.asarray(T, dtype=float)[:3, :3]
    R = A / np.linalg.det(A) ** (1.0 / 3.0)
    return float(np.max(np.abs(R @ R.T - np.eye(3))))


def nearest_similarity(T: np.ndarray) -> np.ndarray:
    """``T`` with its 3x3 block replaced by the nearest scaled rotation (Frobenius norm: the polar
    factor U·Vᵀ times the mean singular value); a proper similarity is returned unchanged (to rounding)."""
    M = np.array(T, dtype=float)
    U, S, Vt = np.linalg.svd(M[:3, :3])
    M[:3, :3] = float(S.mean()) * (U @ Vt)
    return M


def is_similarity(T: np.ndarray, tol: float = 1e-4, orthogonality_tol: float = STRICT_ORTHOGONALITY_TOL
                  ) -> tuple[bool, str]:
    """Check that T is a finite 4x4 similarity with a proper rotation; returns (ok, reason).

    ``tol`` bounds the last row's difference from 0 0 0 1; ``orthogonality_tol`` the difference of R·Rᵀ
    from the identity, R the 3x3 block over its scale (:func:`orthogonality_deviation`;
    :data:`GT_ORTHOGONALITY_TOL` for a ground truth a person may have rounded)."""
    T = np.asarray(T, dtype=float)
    if T.shape != (4, 4):
        return False, f"expected a 4x4 matrix, got shape {T.shape}"
    if not np.all(np.isfinite(T)):
        return False, "matrix has non-finite entries"
    if not np.allclose(T[3], [0, 0, 0, 1], atol=tol):
        return False, f"last row must be 0 0 0 1, got {T[3].tolist()}"
    if np.linalg.det(T[:3, :3]) <= 0:
        return False, "3x3 block has a non-positive determinant (reflection or singular)"
    deviation = orthogonality_deviation(T)
    if deviation > orthogonality_tol:
        return False, (f"3x3 block is not a scaled rotation (not orthogonal up to scale: R·Rᵀ differs from the "
                       f"identity by up to {deviation:.2g}, allowed {orthogonality_tol:.2g})")
    return True, ""


def rotation_angle_deg(R: np.ndarray) -> float:
    """Geodesic angle of a rotation matrix, in degrees."""
    c = (np.trace(R) - 1.0) / 2.0
    return float(np.degrees(np.arccos(np.clip(c, -1.0, 1.0))))


@dataclass(frozen=True)
class TransformErrors:
    rot_err_deg: float
    trans_err: float
    trans_err_rel: float
    scale_err: float
    tm_err: float

    def success(self, rotation_deg: float, translation_rel: float, scale: float) -> bool:
        return bool(
            self.rot_err_deg < rotation_deg and self.trans_err_rel < translation_rel and self.scale_err < scale
        )


def transform_errors(T_est: np.ndarray, T_gt: np.ndarray, target_diagonal: float,
                     source_centre: np.ndarray | None = None) -> TransformErrors:
    """Compare two source->target similarities.

    rotation: geodesic angle between the rotation parts; translation: the distance between where
    the two transforms put ``source_centre`` (the source cloud's centroid; the coordinate origin if
    not given, which makes it ``||t_est - t_gt||``), absolute and relative to the target's
    bounding-box diagonal — measured at the cloud, so a UTM-like offset of the coordinates does not
    turn a tiny rotation error into a huge translation error; scale: ``|s_est/s_gt - 1|``;
    TM: ``||T_est - T_gt||_F`` (the paper's TM error, which does depend on the origin).
    """
    s_e, R_e, t_e = split(T_est)
    s_g, R_g, t_g = split(T_gt)
    c = np.zeros(3) if source_centre is None else np.asarray(source_centre, dtype=float)
    # Written as (s R c + t) differences so large coordinates cancel as early as possible.
    trans = float(np.linalg.norm((t_e - t_g) + (s_e * R_e - s_g * R_g) @ c))
    return TransformErrors(
        rot_err_deg=rotation_angle_deg(R_e.T @ R_g),
        trans_err=trans,
        trans_err_rel=trans / target_diagonal if target_diagonal > 0 else float("inf"),
        scale_err=abs(s_e / s_g - 1.0),
        tm_err=float(np.linalg.norm(np.asarray(T_est, float) - np.asarray(T_gt, float))),
    )
