"""Errors of an estimated similarity against ground truth (the paper's R, T, S and TM errors)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from gctr_cli.geometry import split

#: how far R·Rᵀ of a ground-truth matrix may differ from the identity (entry by entry): a matrix typed or
#: printed with three decimals is off by up to about 3e-3 and still measures errors to a small fraction of
#: a degree; a shear or a non-uniform scale is off by far more
GT_ORTHOGONALITY_TOL = 1e-2


def is_similarity(T: np.ndarray, tol: float = 1e-4, orthogonality_tol: float | None = None) -> tuple[bool, str]:
    """Check that T is a finite 4x4 similarity with a proper rotation; returns (ok, reason).

    ``tol`` bounds the last row's difference from 0 0 0 1; ``orthogonality_tol`` (default ``10 * tol``) the
    difference of R·Rᵀ from the identity, R the 3x3 block over its scale (``GT_ORTHOGONALITY_TOL`` for a
    ground truth a person may have rounded)."""
    T = np.asarray(T, dtype=float)
    if T.shape != (4, 4):
        return False, f"expected a 4x4 matrix, got shape {T.shape}"
    if not np.all(np.isfinite(T)):
        return False, "matrix has non-finite entries"
    if not np.allclose(T[3], [0, 0, 0, 1], atol=tol):
        return False, f"last row must be 0 0 0 1, got {T[3].tolist()}"
    A = T[:3, :3]
    det = np.linalg.det(A)
    if det <= 0:
        return False, "3x3 block has a non-positive determinant (reflection or singular)"
    s = det ** (1.0 / 3.0)
    R = A / s
    allowed = tol * 10 if orthogonality_tol is None else orthogonality_tol
    deviation = float(np.max(np.abs(R @ R.T - np.eye(3))))
    if deviation > allowed:
        return False, (f"3x3 block is not a scaled rotation (not orthogonal up to scale: R·Rᵀ differs from the "
                       f"identity by up to {deviation:.2g}, allowed {allowed:.2g})")
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
