"""Stage 5b: an accepted answer's last ICP, trimmed down to the clouds' own noise.

The verdict refines and compares on the working clouds (voxels of about 2% of the cloud's size) and ends its
ICP at ``refine.end_ratio`` (2%). On clouds with little noise that leaves errors the data can resolve: a
LiDAR window 26 m wide and 114 m long came back rolled 7.3° about its long axis (the ground moves 1.7 m at
its edges, inside the 2% trimming), while 44% of the source lay within 10 cm of the target at the truth
against 3% at the answer. This stage runs the same two-way scaled point-to-plane ICP from the answer on
clouds of ``polish.voxel_ratio`` voxels (at most ``polish.icp_points`` points each, a seeded subset: on a
large cloud as many points as the working cloud, so what it adds is mostly the tighter trimming), its
trimming distance shrinking from where the refinement ended to the larger of ``polish.end_ratio`` and
``polish.noise_factor`` times the clouds' combined noise (the flattest quarter of about 1,000
neighbourhoods of each cloud). It runs only where that final distance is at most ``polish.max_end_share``
of the refinement's, for time: on noisier clouds (the benchmark's generated levels with added noise) it
costs only the noise estimate, about 0.015 s (the source's: where that alone closes the gate, the target's
is not measured). It is skipped when ``refine.enabled`` is false or
``refine.method`` is point_to_point. The polished transform is kept only when it stays the same alignment
(moves the source by at most ``verdict.distinct_ratio``, normalised target units, as every "distinct" test)
and its surface agreement at the polish's final distance does not drop. The engine calls it on accepted
answers, after every check: the status, the confidence and the verdict's evidence are those of the
verdict's transform.
"""

from __future__ import annotations

import time

import numpy as np

from gctr_cli.config import EngineConfig
from gctr_cli.engine.decide import similarity_scale, smaller_cloud
from gctr_cli.engine.prepare import RefinementCloud, StageTimer
from gctr_cli.engine.preprocess import downsample_to, nearest_neighbours, normals_and_roughness, smallest_eigenpairs
from gctr_cli.engine.refine import scaled_point_to_plane_icp
from gctr_cli.engine.scipy_parts import cKDTree
from gctr_cli.engine.verdict import Surface, displacement, surface_agreement

#: points of each polish cloud scored for the keep-or-not test (a strided sample, unweighted)
POLISH_SAMPLE_POINTS = 1500
#: the roughness percentile read as the cloud's noise (the flattest quarter of its neighbourhoods: the
#: median on a LiDAR window is vegetation and edges, ten times the sensor noise)
NOISE_PERCENTILE = 25.0
#: points of each polish cloud whose neighbourhoods estimate its noise (every k-th), before the polish
#: decides whether to run at all: noisy clouds, most of the benchmark's, then cost only the downsampling
NOISE_SAMPLE_POINTS = 1000


def polish_points(points: np.ndarray, cfg: EngineConfig, rng: np.random.Generator) -> tuple[np.ndarray, cKDTree, float]:
    """One normalised input downsampled for the polish (voxels of ``polish.voxel_ratio``, at most
    ``polish.max_points`` points), its tree, and its noise: the :data:`NOISE_PERCENTILE` roughness of the
    ``preprocess.normal_neighbours`` neighbourhoods of :data:`NOISE_SAMPLE_POINTS` of its points."""
    pts = downsample_to(points, cfg.polish.voxel_ratio, cfg.polish.max_points, rng)
    tree = cKDTree(pts)
    k = min(cfg.preprocess.normal_neighbours, len(pts))
    _, idx = tree.query(pts[::max(1, len(pts) // NOISE_SAMPLE_POINTS)], k)
    neighbours = pts[idx.reshape(len(idx), -1)]
    centred = neighbours - neighbours.mean(axis=1, keepdims=True)
    cov = np.matmul(centred.transpose(0, 2, 1), centred) / k  # a batched product: 2.5x faster than einsum here
    smallest, _ = smallest_eigenpairs(cov[:, [0, 1, 2, 0, 0, 1], [0, 1, 2, 1, 2, 2]])  # the working clouds' solver
    return pts, tree, float(np.percentile(np.sqrt(np.maximum(smallest, 0.0)), NOISE_PERCENTILE))


def polish_cloud(pts: np.ndarray, tree: cKDTree, noise: float, cfg: EngineConfig,
                 rng: np.random.Generator) -> RefinementCloud:
    """The ICP cloud of :func:`polish_points`' output: at most ``polish.icp_points`` of its points (a seeded
    subset), normals as the working clouds', a strided sample of :data:`POLISH_SAMPLE_POINTS` for the
    keep-or-not test, and ``roughness`` = the noise."""
    if len(pts) > cfg.polish.icp_points:
        pts = pts[np.sort(rng.choice(len(pts), cfg.polish.icp_points, replace=False))]
        tree = cKDTree(pts)
    k = min(cfg.preprocess.normal_neighbours, len(pts))
    normals, _ = normals_and_roughness(pts, nearest_neighbours(pts, k, tree)[1])
    return RefinementCloud(pts, normals, tree, Surface.build(pts, normals, tree, POLISH_SAMPLE_POINTS, 0.0), noise)


def polish(T_n: np.ndarray, source: np.ndarray, target: np.ndarray, cfg: EngineConfig,
           bounds_n: tuple[float, float], rng: np.random.Generator,
           timer: StageTimer) -> tuple[np.ndarray, dict[str, float]]:
    """The answer ``T_n`` (normalised units, source -> target) polished on the normalised input clouds
    ``source`` and ``target``: ``T_n`` itself when the polish is off, would not go finer than the
    refinement, moves to another alignment or lowers the fine surface agreement. Also returns what the
    polish saw (the result's ``evidence``): ``polish_end`` (its final trimming distance / the smaller cloud's
    size; 0 when the stage is off; where the source's noise alone closes the gate, the target's is not
    measured and this is the source's share, a lower bound), ``polished`` (1 when the result is the polished
    transform, 0 otherwise, also when the noise gate skipped it), and when its ICP ran ``polish_before`` and
    ``polish_fine`` (the surface agreement at the final distance of the given and of the returned transform)."""
    p, v = cfg.polish, cfg.verdict
    info = {"polish_end": 0.0, "polished": 0.0}
    if not (p.enabled and cfg.refine.enabled and cfg.refine.method == "point_to_plane"):
        return T_n, info
    t = time.perf_counter()
    try:
        scale = similarity_scale(T_n)
        size = smaller_cloud(scale)
        start = cfg.refine.end_ratio * size

        def gate(noise: float) -> float | None:
            """The final trimming distance for ``noise`` (recorded as polish_end); None where the gate closes."""
            end = max(p.end_ratio * size, p.noise_factor * noise)
            info["polish_end"] = end / size
            return end if np.isfinite(noise) and end <= p.max_end_share * start else None

        src_pts = polish_points(source, cfg, rng)
        # The combined noise is at least the source's: where that alone closes the gate, the target's noise is
        # not measured (half the cost of a skipped polish; polish_end is then the source's share, a lower bound).
        if gate(scale * src_pts[2]) is None:
            return T_n, info
        tgt_pts = polish_points(target, cfg, rng)
        end = gate(float(np.hypot(scale * src_pts[2], tgt_pts[2])))
        if end is None:
            return T_n, info
        src_f, tgt_f = polish_cloud(*src_pts, cfg, rng), polish_cloud(*tgt_pts, cfg, rng)
        T_p = scaled_point_to_plane_icp(src_f.points, tgt_f.points, tgt_f.normals, T_n, p.iterations, start, end,
                                        bounds_n, tgt_f.tree, src_normals=src_f.normals,
                                        max_normal_angle_deg=v.max_normal_angle_deg, src_tree=src_f.tree,
                                        symmetric=cfg.refine.symmetric, max_matches=p.max_matches)[0]
        before = surface_agreement(T_n, src_f.surface, tgt_f.surface, end, v.tight_normal_angle_deg).score
        after = float("nan")
        if np.all(np.isfinite(T_p)) and displacement(T_p, T_n, src_f.surface.sample) <= v.distinct_ratio:
            after = surface_agreement(T_p, src_f.surface, tgt_f.surface, end, v.tight_normal_angle_deg).score
        keep = after >= before  # False for NaN: another alignment, or a non-finite ICP
        info |= {"polished": float(keep), "polish_before": before, "polish_fine": after if keep else before}
        return (T_p if keep else T_n), info
    finally:
        timer.add("polish", t)
