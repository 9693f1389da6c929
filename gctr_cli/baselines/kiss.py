"""``kiss_matcher``: KISS-Matcher global registration (Faster-PFH, ROBIN pruning, GNC), then scaled ICP.

KISS-Matcher (Lim et al., ICRA 2025, https://github.com/MIT-SPARK/KISS-Matcher) is a C++ library with
Python bindings (pip package ``kiss-matcher``). It is *not* a dependency of gctr: its wheel links the
PMC max-clique library, which is GPL-3.0-or-later, while gctr is MIT. Install it yourself
(``pip install kiss-matcher``) to use this method; without it the method reports every pair as failed
with a message saying so.

Pipeline, after the same cleaning and bounding-box normalisation as every comparison method
(:mod:`gctr_cli.baselines.common`):

1. KISS-Matcher is tuned for metric scenes (its default voxel is 0.3 m, it refuses voxels under 5 mm
   and clamps noise bounds above 1 m, switched off here), so both normalised clouds (diagonal 1) are
   multiplied by ``kiss_matcher.metric_diagonal`` (default 20: a room-to-building-sized scene, voxel 0.4 m at the
   default ``voxel_ratio`` 0.02, the same relative voxel as ``fpfh_ransac``). On a bunny pair every
   diagonal from 1 to 200 registered (0.3-0.8 degrees before ICP); 20 keeps the voxel next to
   KISS-Matcher's own default and the noise bounds (0.4 / 0.3 m) under its usual 1 m clamp;
2. ``KISSMatcher.estimate`` (its own voxelisation, Faster-PFH features, mutual matching with a ratio
   test, ROBIN max-core pruning, GNC-TLS rotation + component-wise translation) gives a rigid
   ``[R, t]`` in those metric frames, i.e. ``[R, t / metric_diagonal]`` in the normalised ones;
3. the same scaled ICP refinement as ``fpfh_ransac``/``fgr`` (``baselines.icp``) estimates the scale
   the rigid solver cannot.

A solution KISS-Matcher marks invalid, or one with fewer than ``kiss_matcher.min_inliers`` final inliers
(default 3, the minimum for a rigid transform: the method's own acceptance rule), is a failed result;
then ``baselines.min_fitness`` applies as for every comparison method. (On the quick benchmark's 3 ``hard``
and 3 ``part`` pairs, min_inliers 5 gave 0 successes and 0 silent wrong answers, 3 gave 2 and 1.)
KISS-Matcher has no random generator: the result does not depend on
``seed`` (recorded as usual). It runs on TBB threads (limit the process' CPUs with ``taskset`` to pin
it); repeated runs gave identical matrices on one core, and very rarely differed with two threads.
"""

from __future__ import annotations

from typing import Any

import numpy as np
from scipy.spatial import cKDTree

from gctr_cli.baselines.common import MIN_WORKING_POINTS, BaselineFailure, Timer, refine_scaled_icp, run_guarded
from gctr_cli.config import BaselineConfig
from gctr_cli.engine.result import RegistrationResult

NOT_INSTALLED = ("kiss_matcher needs the optional package kiss-matcher (pip install kiss-matcher; note: its wheel "
                 "contains GPL-3.0 code, which is why gctr does not install it)")


def _kiss_module() -> Any:
    try:
        import kiss_matcher
    except ImportError as err:
        raise BaselineFailure(f"{NOT_INSTALLED}: {err}") from None
    return kiss_matcher


def faster_pfh_keypoints(points: np.ndarray, voxel: float, normal_radius: float, feature_radius: float) -> int:
    """How many Faster-PFH descriptors KISS-Matcher will compute for ``points`` (metric frame).

    Mirrors its rules: voxel-grid centroids; a point has a normal when at least 3 centroids lie within
    ``normal_radius``; it gets a descriptor when at least 3 points with a normal lie within
    ``feature_radius``. KISS-Matcher 1.0.2 crashes (segmentation fault) instead of failing when a cloud
    has no descriptor, so the method checks this first (its own count on test clouds was within 0.5 %).
    """
    cells = np.floor(points / voxel).astype(np.int64)
    cells -= cells.min(axis=0)
    dims = cells.max(axis=0) + 1
    _, inverse, counts = np.unique((cells[:, 0] * dims[1] + cells[:, 1]) * dims[2] + cells[:, 2],
                                   return_inverse=True, return_counts=True)
    centroids = np.column_stack([np.bincount(inverse, weights=points[:, d]) for d in range(3)]) / counts[:, None]
    has_normal = cKDTree(centroids).query_ball_point(centroids, normal_radius, return_length=True) >= 3
    if not has_normal.any():
        return 0
    support = cKDTree(centroids[has_normal]).query_ball_point(centroids, feature_radius, return_length=True)
    return int(np.count_nonzero(has_normal & (support >= 3)))


def _kiss_matcher(prep, cfg: BaselineConfig, seed: int, timer: Timer) -> tuple[np.ndarray, int]:  # noqa: ARG001
    km = _kiss_module()
    k = cfg.kiss_matcher
    scale = k.metric_diagonal
    voxel = k.voxel_ratio * scale
    clouds = []
    for name, cloud in (("source", prep.src), ("target", prep.tgt)):
        points = np.ascontiguousarray(cloud.points * scale, dtype=np.float32)
        n = faster_pfh_keypoints(points.astype(np.float64), voxel, k.normal_radius_factor * voxel,
                                 k.feature_radius_factor * voxel)
        if n < MIN_WORKING_POINTS:
            raise BaselineFailure(f"{name}: only {n} points with a Faster-PFH descriptor at voxel "
                                  f"{k.voxel_ratio:.4g} x bbox diagonal (need {MIN_WORKING_POINTS})")
        clouds.append(points)
    timer.lap("preprocess")
    try:
        params = km.KISSMatcherConfig(
            voxel_size=voxel, use_voxel_sampling=True, use_quatro=k.use_quatro, thr_linearity=1.0,
            num_max_corr=k.max_correspondences, normal_r_gain=k.normal_radius_factor,
            fpfh_r_gain=k.feature_radius_factor, robin_noise_bound_gain=k.robin_noise_bound_gain,
            solver_noise_bound_gain=k.solver_noise_bound_gain, enable_noise_bound_clamping=False,
        )
        matcher = km.KISSMatcher(params)
        solution = matcher.estimate(clouds[0], clouds[1])
        n_inliers = int(matcher.get_num_final_inliers())
    except (RuntimeError, ValueError, TypeError) as err:
        raise BaselineFailure(f"KISS-Matcher: {err}") from None
    timer.lap("kiss_matcher")
    if not solution.valid:
        raise BaselineFailure(f"KISS-Matcher found no valid solution ({n_inliers} inliers)")
    if n_inliers < k.min_inliers:
        raise BaselineFailure(f"KISS-Matcher: too weak evidence, {n_inliers} final inliers "
                              f"(kiss_matcher.min_inliers {k.min_inliers})")
    T0 = np.eye(4)
    T0[:3, :3] = np.asarray(solution.rotation, dtype=np.float64)
    T0[:3, 3] = np.asarray(solution.translation, dtype=np.float64).reshape(3) / scale
    if not np.all(np.isfinite(T0)):
        raise BaselineFailure("KISS-Matcher returned a non-finite transform")
    return refine_scaled_icp(prep, cfg, T0, timer), 0


def register_kiss_matcher(source: np.ndarray, target: np.ndarray, cfg: BaselineConfig | None = None,
                          seed: int = 0) -> RegistrationResult:
    """Register ``source`` onto ``target``: normalisation, KISS-Matcher at metric size, scaled ICP.

    Both clouds are cleaned and normalised like every comparison method's, scaled to a bounding-box
    diagonal of ``cfg.kiss_matcher.metric_diagonal`` for KISS-Matcher (voxel ``voxel_ratio`` x that
    diagonal), its rigid solution is brought back to the normalised frames, refined by scaled ICP and
    composed back to the original coordinates. Never raises for degenerate inputs or a missing
    ``kiss-matcher`` package: returns ``status='failed'`` with a message.
    """
    return run_guarded(_kiss_matcher, source, target, cfg, seed)
