"""``icp``: bounding-box normalisation, then Open3D point-to-point ICP with scale estimation.

ICP is a local method: it converges to the right answer only when the normalisation already puts
the source close to its true pose (small rotation, small scale bias).
"""

from __future__ import annotations

import numpy as np

from gctr_cli.baselines.common import Timer, open3d_deterministic, run_guarded, scaled_icp, to_o3d, voxel_down
from gctr_cli.config import BaselineConfig
from gctr_cli.engine.result import RegistrationResult


def _icp(prep, cfg: BaselineConfig, seed: int, timer: Timer) -> tuple[np.ndarray, int]:
    open3d_deterministic(seed)
    voxel = cfg.icp.voxel_ratio
    src = voxel_down(to_o3d(prep.src.points), voxel, "source")
    tgt = voxel_down(to_o3d(prep.tgt.points), voxel, "target")
    timer.lap("preprocess")
    T = scaled_icp(src, tgt, np.eye(4), cfg.icp.threshold_ratio, cfg.icp.iterations)
    timer.lap("icp")
    return T, 0


def register_icp(source: np.ndarray, target: np.ndarray, cfg: BaselineConfig | None = None,
                 seed: int = 0) -> RegistrationResult:
    """Register ``source`` (N, 3) onto ``target`` (M, 3) by normalisation + scaled point-to-point ICP.

    Both clouds are centred on their centroids and scaled to a bounding-box diagonal of 1, voxel
    downsampled at ``cfg.icp.voxel_ratio``, then Open3D's ``registration_icp`` with
    ``TransformationEstimationPointToPoint(with_scaling=True)``, a maximum correspondence distance of
    ``cfg.icp.threshold_ratio`` (x diagonal) and at most ``cfg.icp.iterations`` iterations starts from
    the identity. The reported transform is composed back to the original coordinates.
    ``iterations`` is 0: Open3D does not report how many ICP iterations ran. Never raises for
    degenerate inputs: returns ``status='failed'`` with a message.
    """
    return run_guarded(_icp, source, target, cfg, seed)
