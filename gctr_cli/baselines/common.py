"""What every comparison method shares: the bounding-box normalisation, Open3D helpers, the scaled ICP
refinement, the fitness evaluation and the construction of the result record.

**Outlier removal** (``baselines.outlier_removal: statistical``, on by default): what a competent user
does first with noisy sensor data — Open3D's statistical outlier removal with its tutorial values
(20 neighbours, 2 standard deviations). Without it, uniform outliers dominate the voxel-downsampled
clouds (a surface voxel merges many points, an outlier voxel one) and the FPFH baselines fail on
nearly every pair that has outliers (measured in ``bench/RESULTS.md``: 2/30 ``cross`` pairs without it,
25/30 and 19/30 with it).

**Normalisation** (the paper's protocol for its comparison methods, after Huang et al. 2016): each
cloud is centred on its centroid and scaled to a bounding-box diagonal of 1. In these coordinates the
identity is "centroids aligned, source scaled by the ratio of diagonals"; a method estimates
``T_n`` (normalised source -> normalised target) and the reported matrix is the composition
``inv(N_t) @ T_n @ N_s`` in the original coordinates. The axis-aligned box changes with the
rotation, crops and outliers, so this initial scale is biased (typically by 5-15 %); the methods
are expected to correct it (scaled ICP / CPD) — that is what the comparison measures.

**Fitness** (same definition as the GCTR engine's, with the bounding-box diagonal as the unit): the
fraction of the source points (voxel-downsampled at ``baselines.icp.voxel_ratio``) that, once
transformed, have a target point within ``baselines.inlier_distance_ratio`` x the target's bounding-box
diagonal; ``inlier_rmse`` is the RMS of those distances in target units.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from scipy.spatial import cKDTree

from gctr_cli.config import BaselineConfig
from gctr_cli.engine.preprocess import DegenerateCloudError, NormalisedCloud, denormalise, validate_cloud
from gctr_cli.engine.result import RegistrationResult
from gctr_cli.geometry import apply

#: fewer points than this after downsampling: the method cannot run (failed status)
MIN_WORKING_POINTS = 10


class BaselineFailure(Exception):
    """A comparison method could not produce a transform; the message goes into the failed row."""


def box_normalise(points: np.ndarray) -> NormalisedCloud:
    """Centre on the centroid, scale to a bounding-box diagonal of 1 (the comparison methods'
    protocol; biased under rotation and crops, which is the point of comparing)."""
    centroid = points.mean(axis=0)
    diagonal = float(np.linalg.norm(points.max(axis=0) - points.min(axis=0)))
    return NormalisedCloud(points=(points - centroid) / diagonal, centre=centroid, size=diagonal)


# ---------------------------------------------------------------------------------------------- Open3D
def open3d_deterministic(seed: int) -> Any:
    """Import Open3D, seed its global random generator and run it on one thread.

    Both are needed for run-to-run identical RANSAC/FGR results (GUIDE §3): with several threads
    the hypotheses are drawn in a scheduling-dependent order even with a fixed seed. This changes
    process-wide Open3D state, as batch workers do anyway.
    """
    import open3d as o3d

    o3d.utility.set_verbosity_level(o3d.utility.VerbosityLevel.Error)
    o3d.utility.random.seed(int(seed) % (2**31))
    o3d.utility.set_max_threads(1)
    return o3d


def to_o3d(points: np.ndarray) -> Any:
    import open3d as o3d

    pcd = o3d.geometry.PointCloud()
    pcd.points = o3d.utility.Vector3dVector(np.ascontiguousarray(points, dtype=np.float64))
    return pcd


def voxel_down(pcd: Any, voxel: float, name: str) -> Any:
    """Open3D voxel downsampling (``voxel`` <= 0: unchanged); too few points left is a failure."""
    down = pcd.voxel_down_sample(voxel) if voxel > 0 else pcd
    if len(down.points) < MIN_WORKING_POINTS:
        raise BaselineFailure(f"{name}: only {len(down.points)} points after voxel downsampling at {voxel:.4g} "
                              f"x bbox diagonal (need {MIN_WORKING_POINTS})")
    return down


def scaled_icp(source: Any, target: Any, T0: np.ndarray, threshold: float, iterations: int) -> np.ndarray:
    """Open3D point-to-point ICP with scale estimation (``with_scaling=True``) from ``T0``."""
    import open3d as o3d

    reg = o3d.pipelines.registration
    result = reg.registration_icp(
        source, target, threshold, np.asarray(T0, dtype=np.float64),
        reg.TransformationEstimationPointToPoint(with_scaling=True),
        reg.ICPConvergenceCriteria(max_iteration=int(iterations)),
    )
    return np.asarray(result.transformation, dtype=np.float64).copy()


def refine_scaled_icp(prep: Prepared, cfg: BaselineConfig, T0: np.ndarray, timer: Timer) -> np.ndarray:
    """The refinement every global method ends with (fpfh_ransac, fgr, kiss_matcher): scaled ICP from
    ``T0`` on both normalised clouds voxel-downsampled at ``icp.voxel_ratio``, distance
    ``icp.refine_threshold_ratio``, at most ``icp.iterations`` iterations."""
    src = voxel_down(to_o3d(prep.src.points), cfg.icp.voxel_ratio, "source")
    tgt = voxel_down(to_o3d(prep.tgt.points), cfg.icp.voxel_ratio, "target")
    T = scaled_icp(src, tgt, T0, cfg.icp.refine_threshold_ratio, cfg.icp.iterations)
    timer.lap("refine")
    return T


# ---------------------------------------------------------------------------------------------- result
@dataclass
class Timer:
    timings: dict[str, float] = field(default_factory=dict)
    last: float = field(default_factory=time.perf_counter)

    def lap(self, stage: str) -> None:
        now = time.perf_counter()
        self.timings[stage] = self.timings.get(stage, 0.0) + now - self.last
        self.last = now


@dataclass(frozen=True)
class Prepared:
    """Both clouds validated and normalised, plus the evaluation cloud and target tree."""

    src: NormalisedCloud
    tgt: NormalisedCloud
    src_eval: np.ndarray  # normalised source, voxel-downsampled for fitness evaluation
    tgt_tree: cKDTree  # over the normalised target


def prepare(source: np.ndarray, target: np.ndarray, cfg: BaselineConfig, timer: Timer | None = None) -> Prepared:
    """Validate (engine rules), remove outliers, normalise; raises :class:`DegenerateCloudError`."""
    timer = timer if timer is not None else Timer()
    clouds = []
    for points, name in ((source, "source"), (target, "target")):
        pts = validate_cloud(points, name)
        timer.lap("validate")
        if cfg.outlier_removal == "statistical":
            pts = validate_cloud(remove_outliers(pts, cfg.outlier_neighbours, cfg.outlier_std_ratio),
                                 f"{name} after outlier removal")
            timer.lap("outlier_removal")
        clouds.append(box_normalise(pts))
    src, tgt = clouds
    voxel = cfg.icp.voxel_ratio
    if voxel > 0:
        from gctr_cli.engine.preprocess import voxel_downsample

        src_eval = voxel_downsample(src.points, voxel)
    else:
        src_eval = src.points
    return Prepared(src=src, tgt=tgt, src_eval=src_eval, tgt_tree=cKDTree(tgt.points))


def remove_outliers(points: np.ndarray, neighbours: int, std_ratio: float) -> np.ndarray:
    """Open3D statistical outlier removal: drop points whose mean distance to their ``neighbours``
    nearest neighbours exceeds the mean of those distances by ``std_ratio`` standard deviations."""
    _, kept = to_o3d(points).remove_statistical_outlier(nb_neighbors=min(neighbours, len(points) - 1),
                                                         std_ratio=std_ratio)
    return points[np.asarray(kept, dtype=np.int64)]


def _decompose(T: np.ndarray) -> tuple[float, np.ndarray]:
    det = float(np.linalg.det(T[:3, :3]))
    s = abs(det) ** (1.0 / 3.0) if np.isfinite(det) and det != 0 else 1.0
    return s, T[:3, :3] / s


def failed(message: str, seed: int, start: float, timings: dict[str, float],
           transform: np.ndarray | None = None, fitness: float = 0.0, inlier_rmse: float = float("nan"),
           n_inliers: int = 0, iterations: int = 0) -> RegistrationResult:
    T = np.eye(4) if transform is None else transform
    s, R = _decompose(T)
    return RegistrationResult(transform=T, scale=s, rotation=R, translation=T[:3, 3].copy(), fitness=fitness,
                              inlier_rmse=inlier_rmse, n_inliers=n_inliers, iterations=iterations, status="failed",
                              message=message, runtime_s=time.perf_counter() - start, seed=seed, timings=timings)


def finish(prep: Prepared, T_n: np.ndarray, cfg: BaselineConfig, seed: int, start: float, timer: Timer,
           iterations: int = 0, message: str = "") -> RegistrationResult:
    """Evaluate ``T_n`` (normalised frames), compose it back and build the result record."""
    if not np.all(np.isfinite(T_n)) or np.linalg.det(T_n[:3, :3]) <= 0:
        return failed("the method returned an invalid transform (non-finite or reflection)", seed, start,
                      timer.timings, iterations=iterations)
    d, _ = prep.tgt_tree.query(apply(T_n, prep.src_eval), distance_upper_bound=cfg.inlier_distance_ratio)
    ok = np.isfinite(d)
    n_inliers = int(ok.sum())
    fitness = n_inliers / max(len(prep.src_eval), 1)
    rmse = float(np.sqrt(np.mean(d[ok] ** 2))) * prep.tgt.size if n_inliers else float("nan")
    T = denormalise(T_n, prep.src, prep.tgt)
    timer.lap("evaluate")
    if fitness < cfg.min_fitness:
        return failed(f"too weak evidence: fitness {fitness:.3f} below {cfg.min_fitness}", seed, start, timer.timings,
                      transform=T, fitness=fitness, inlier_rmse=rmse, n_inliers=n_inliers, iterations=iterations)
    s, R = _decompose(T)
    return RegistrationResult(transform=T, scale=s, rotation=R, translation=T[:3, 3].copy(), fitness=fitness,
                              inlier_rmse=rmse, n_inliers=n_inliers, iterations=iterations, status="ok",
                              message=message, runtime_s=time.perf_counter() - start, seed=seed,
                              timings=timer.timings)


def run_guarded(body, source: np.ndarray, target: np.ndarray, cfg: BaselineConfig | None,
                seed: int) -> RegistrationResult:
    """Common frame of every baseline: validation, normalisation, failures as ``failed`` results.

    ``body(prep, cfg, seed, timer) -> (T_n, iterations)``.
    """
    cfg = cfg if cfg is not None else BaselineConfig()
    start = time.perf_counter()
    timer = Timer()
    try:
        prep = prepare(source, target, cfg, timer)
    except DegenerateCloudError as err:
        return failed(str(err), seed, start, timer.timings)
    timer.lap("normalise")
    try:
        T_n, iterations = body(prep, cfg, seed, timer)
    except BaselineFailure as err:
        return failed(str(err), seed, start, timer.timings)
    return finish(prep, T_n, cfg, seed, start, timer, iterations=iterations)
