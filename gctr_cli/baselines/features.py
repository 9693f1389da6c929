"""``fpfh_ransac`` and ``fgr``: global registration on FPFH features (Open3D), then scaled ICP.

Recipe of Open3D's global-registration tutorial, after the bounding-box normalisation: voxel
downsampling at ``features.voxel_ratio`` (of the diagonal, i.e. in normalised units), normals in a
radius of ``normal_radius_factor`` voxels, FPFH in a radius of ``feature_radius_factor`` voxels; then
either RANSAC on feature matches (mutual filter off, edge-length and distance checkers) or Fast
Global Registration; then point-to-point ICP with scale estimation on the clouds downsampled at
``icp.voxel_ratio`` with a distance of ``icp.refine_threshold_ratio``.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from gctr_cli.baselines.common import (
    BaselineFailure,
    Timer,
    open3d_deterministic,
    refine_scaled_icp,
    run_guarded,
    to_o3d,
    voxel_down,
)
from gctr_cli.config import BaselineConfig
from gctr_cli.engine.result import RegistrationResult


def _features(prep, cfg: BaselineConfig) -> tuple[Any, Any, Any, Any, float]:
    """Downsampled clouds with normals and their FPFH features (normalised coordinates)."""
    import open3d as o3d

    f = cfg.features
    voxel = f.voxel_ratio
    out = []
    for name, cloud in (("source", prep.src), ("target", prep.tgt)):
        down = voxel_down(to_o3d(cloud.points), voxel, name)
        down.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=f.normal_radius_factor * voxel,
                                                                   max_nn=f.normal_max_nn))
        # open3d's stubs omit the default of `indices` (empty = every point), which the binding has
        feat = o3d.pipelines.registration.compute_fpfh_feature(  # type: ignore[call-arg]
            down, o3d.geometry.KDTreeSearchParamHybrid(radius=f.feature_radius_factor * voxel, max_nn=f.feature_max_nn))
        if feat.data.shape[1] != len(down.points) or not np.all(np.isfinite(feat.data)):
            raise BaselineFailure(f"{name}: FPFH features could not be computed")
        out += [down, feat]
    return out[0], out[2], out[1], out[3], voxel


def _fpfh_ransac(prep, cfg: BaselineConfig, seed: int, timer: Timer) -> tuple[np.ndarray, int]:
    o3d = open3d_deterministic(seed)
    reg = o3d.pipelines.registration
    src, tgt, src_f, tgt_f, voxel = _features(prep, cfg)
    timer.lap("features")
    r = cfg.ransac
    distance = r.distance_factor * voxel
    result = reg.registration_ransac_based_on_feature_matching(
        src, tgt, src_f, tgt_f, False, distance,
        reg.TransformationEstimationPointToPoint(with_scaling=r.with_scaling), r.ransac_n,
        [reg.CorrespondenceCheckerBasedOnEdgeLength(r.edge_length_ratio),
         reg.CorrespondenceCheckerBasedOnDistance(distance)],
        reg.RANSACConvergenceCriteria(r.max_iterations, r.confidence),
    )
    timer.lap("ransac")
    if len(result.correspondence_set) < 3:
        raise BaselineFailure("RANSAC found no hypothesis passing the checkers")
    return refine_scaled_icp(prep, cfg, np.asarray(result.transformation), timer), 0


def _fgr(prep, cfg: BaselineConfig, seed: int, timer: Timer) -> tuple[np.ndarray, int]:
    o3d = open3d_deterministic(seed)
    reg = o3d.pipelines.registration
    src, tgt, src_f, tgt_f, voxel = _features(prep, cfg)
    timer.lap("features")
    g = cfg.fgr
    option = reg.FastGlobalRegistrationOption(maximum_correspondence_distance=g.distance_factor * voxel,
                                              iteration_number=g.iterations, tuple_scale=g.tuple_scale,
                                              maximum_tuple_count=g.max_tuples)
    result = reg.registration_fgr_based_on_feature_matching(src, tgt, src_f, tgt_f, option)
    timer.lap("fgr")
    T0 = np.asarray(result.transformation)
    if not np.all(np.isfinite(T0)):
        raise BaselineFailure("FGR returned a non-finite transform")
    return refine_scaled_icp(prep, cfg, T0, timer), 0


def register_fpfh_ransac(source: np.ndarray, target: np.ndarray, cfg: BaselineConfig | None = None,
                         seed: int = 0) -> RegistrationResult:
    """Register ``source`` onto ``target``: normalisation, FPFH, Open3D RANSAC, scaled ICP.

    RANSAC: ``registration_ransac_based_on_feature_matching`` without the mutual filter, inlier
    distance ``ransac.distance_factor`` voxels, ``ransac.ransac_n`` correspondences per hypothesis
    (a similarity when ``ransac.with_scaling``), edge-length and distance checkers, at most
    ``ransac.max_iterations`` hypotheses (early stop at ``ransac.confidence``). Open3D's generator is
    seeded with ``seed`` and limited to one thread, so two runs give identical results. Never raises
    for degenerate inputs: returns ``status='failed'`` with a message.
    """
    return run_guarded(_fpfh_ransac, source, target, cfg, seed)


def register_fgr(source: np.ndarray, target: np.ndarray, cfg: BaselineConfig | None = None,
                 seed: int = 0) -> RegistrationResult:
    """Register ``source`` onto ``target``: normalisation, FPFH, Open3D Fast Global Registration, scaled ICP.

    FGR (Zhou et al. 2016) estimates a rigid transform in the normalised frame (the scale comes
    from the normalisation and the final scaled ICP). Seeded and single-threaded like
    :func:`register_fpfh_ransac`. Never raises for degenerate inputs.
    """
    return run_guarded(_fgr, source, target, cfg, seed)
