"""GCTR — geometric constraint tensor-based registration: the pipeline that composes the stages.

``register(source, target, config, seed)`` → :class:`RegistrationResult` with the similarity that
maps the source onto the target, in the original coordinates of the inputs, and a ``confidence``.

Pipeline (paper, Algorithm 1, with the extensions measured in bench/ENGINE.md):

1. validate both clouds, normalise each (robust centre at the origin, robust diameter 1 — the
   relative scale is unknown, so every length in the config is relative), voxel-downsample early;
2. supervoxel centroids (VCCS-like) are the salient points;
3. overlap hypotheses (:func:`search_plan`): equal shares r of both clouds (the paper's search over
   0.25/0.5/0.75/1.0) and one cloud as a part of the other. Each hypothesis draws its own random
   wide-baseline triangles, *local* to an overlap region of its size, describes them by the cosines
   of their inner angles (+ optional vertex-normal terms), and matches them by k nearest neighbours
   in descriptor space into a sparse third-order tensor (matches whose implied scale the hypothesis
   rules out are dropped);
4. per hypothesis, the outer loop: first-order term under the current transform → tensor power
   iteration → RANSAC over minimal samples from the best-supported triangle matches and the soft
   assignment → surface-agreement verification of the best hypotheses → closed-form similarity
   (SVD; Umeyama or edge-ratio scale) — until the salient points stop moving. The search stops
   early once two hypotheses settle on the same well-supported transform;
5. verdict (:mod:`gctr_cli.engine.verdict`): the best few *distinct* transforms the search saw are
   refined (scaled point-to-plane ICP on finer clouds) and compared by surface agreement (proximity
   with agreeing normals, both directions) at tight tolerances; the best is the answer, and the
   confidence is its lead over the best distinct rival;
6. the transform is composed back into the original coordinates and checked (inliers, fitness,
   scale bounds, confidence ≥ ``min_confidence``) — weak or ambiguous evidence gives
   ``status='failed'`` with a message rather than a silently wrong matrix.

All random draws come from generators spawned from ``seed``.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass, field

import numpy as np
from scipy.spatial import cKDTree

from gctr_cli.config import EngineConfig
from gctr_cli.engine.descriptor import triangle_descriptors, with_ambiguous_permutations
from gctr_cli.engine.power_iteration import power_iteration
from gctr_cli.engine.preprocess import (
    DegenerateCloudError,
    denormalise,
    downsample_to,
    estimate_normals,
    normalise,
    validate_cloud,
)
from gctr_cli.engine.ransac import Hypotheses, OccupancyGrid, ransac_hypotheses, refit, sample_from_assignment
from gctr_cli.engine.refine import evaluate_fit, scaled_point_to_plane_icp, trimmed_scaled_icp
from gctr_cli.engine.result import RegistrationResult
from gctr_cli.engine.similarity import best_similarity
from gctr_cli.engine.supervoxel import supervoxels
from gctr_cli.engine.tensor import SparseTensor3, build_first_order, build_third_order, entry_scores
from gctr_cli.engine.triplets import sample_triangles
from gctr_cli.engine.verdict import Agreement, Surface, Verdict, confidence, displacement, surface_agreement
from gctr_cli.geometry import apply, split, to_matrix

log = logging.getLogger(__name__)


@dataclass
class _Timer:
    timings: dict[str, float]

    def add(self, stage: str, start: float) -> float:
        now = time.perf_counter()
        self.timings[stage] = self.timings.get(stage, 0.0) + now - start
        return now


@dataclass(frozen=True)
class _Prepared:
    """One cloud after stages 1-2, in normalised coordinates."""

    points: np.ndarray  # downsampled working cloud
    normals: np.ndarray  # unit normals of ``points``
    tree: cKDTree  # over ``points``
    salient: np.ndarray  # supervoxel centroids
    salient_normals: np.ndarray
    salient_tree: cKDTree
    surface: Surface  # what the verdict moves and looks up
    grids: dict = field(default_factory=dict, compare=False)

    def grid(self, radius: float) -> OccupancyGrid:
        """Occupancy grid of the working cloud at ``radius`` (built once, then cached)."""
        if radius not in self.grids:
            self.grids[radius] = OccupancyGrid(self.points, radius)
        return self.grids[radius]


@dataclass(frozen=True)
class _Candidate:
    transform: np.ndarray  # normalised source -> normalised target
    n_inliers: int
    iterations: int
    agreement: Agreement
    overlap: float
    alternatives: tuple[tuple[np.ndarray, Agreement], ...]  # runners-up seen on the way (verdict rivals)

    @property
    def score(self) -> float:
        return self.agreement.score


def _prepare(points: np.ndarray, cfg: EngineConfig, rng: np.random.Generator, timer: _Timer) -> _Prepared:
    t = time.perf_counter()
    work = downsample_to(points, cfg.supervoxel.voxel_ratio, cfg.preprocess.max_points, rng)
    normals = estimate_normals(work, cfg.preprocess.normal_neighbours)
    t = timer.add("preprocess", t)
    sv = supervoxels(work, normals, voxel=cfg.supervoxel.voxel_ratio, seed_spacing=cfg.supervoxel.seed_ratio,
                     spatial_weight=cfg.supervoxel.spatial_weight, normal_weight=cfg.supervoxel.normal_weight,
                     iterations=cfg.supervoxel.iterations, min_voxels=cfg.supervoxel.min_voxels)
    # Voxels that no supervoxel reached are isolated — typically outliers. Dropping them from the
    # working cloud keeps outliers out of the refinement and the fitness (with 30% uniform
    # outliers they otherwise pull scaled ICP's scale inwards).
    surface = sv.labels >= 0
    if cfg.preprocess.drop_isolated and surface.sum() >= max(50, len(work) // 4):
        work, normals = work[surface], normals[surface]
    salient, salient_normals = sv.centroids, sv.normals
    if len(salient) > cfg.supervoxel.max_salient:
        keep = np.sort(np.argsort(-sv.sizes, kind="stable")[: cfg.supervoxel.max_salient])
        salient, salient_normals = salient[keep], salient_normals[keep]
    timer.add("supervoxels", t)
    tree = cKDTree(work)
    return _Prepared(points=work, normals=normals, tree=tree, salient=salient, salient_normals=salient_normals,
                     salient_tree=cKDTree(salient),
                     surface=Surface.build(work, normals, tree, cfg.verdict.sample_points))


def _dense_scores(src: _Prepared, tgt: _Prepared, hyp: Hypotheses, distance: float,
                  n_points: int = 800) -> np.ndarray:
    """sqrt(fitness * coverage) of each hypothesis on ~``n_points`` of each working cloud.

    fitness: share of source points landing near the target; coverage: share of target points
    whose inverse image lands near the source. Both are occupancy-grid lookups.
    """
    ps = src.points[:: max(1, len(src.points) // n_points)]
    pt = tgt.points[:: max(1, len(tgt.points) // n_points)]
    fwd = np.matmul(hyp.scale[:, None, None] * hyp.rotation, ps.T).transpose(0, 2, 1) + hyp.translation[:, None]
    fitness = tgt.grid(distance).contains(fwd).mean(axis=1)
    back = np.matmul(hyp.rotation.transpose(0, 2, 1), (pt[None] - hyp.translation[:, None]).transpose(0, 2, 1))
    back = back.transpose(0, 2, 1) / hyp.scale[:, None, None]
    coverage = src.grid(distance).contains(back).mean(axis=1)
    return np.sqrt(fitness * coverage)


def _select_dense(src: _Prepared, tgt: _Prepared, hyp: Hypotheses, cfg: EngineConfig
                  ) -> tuple[int, list[tuple[np.ndarray, Agreement]]]:
    """Index of the best hypothesis and the finalists with their surface agreement: a coarse
    occupancy score for all, the surface agreement (proximity + normals) for the finalists."""
    coarse = _dense_scores(src, tgt, hyp, cfg.inlier_distance_ratio, n_points=150)
    top = np.argsort(-coarse, kind="stable")[:cfg.verdict.finalists]
    scored = []
    for j in top:
        T = to_matrix(float(hyp.scale[j]), hyp.rotation[j], hyp.translation[j])
        scored.append((T, surface_agreement(T, src.surface, tgt.surface, cfg.inlier_distance_ratio,
                                            cfg.verdict.max_normal_angle_deg)))
    k = int(np.argmax([a.score for _, a in scored]))
    return int(top[k]), scored


def _outer_loop(src: _Prepared, tgt: _Prepared, H3: SparseTensor3, overlap: float, cfg: EngineConfig,
                rng: np.random.Generator, bounds_n: tuple[float, float], timer: _Timer) -> _Candidate | None:
    """Algorithm 1's outer loop for one overlap ratio (normalised coordinates): power iteration with
    the current first-order term, tensor-guided RANSAC, closed-form refit, until T stops changing."""
    S, Q = src.salient, tgt.salient
    n2 = len(Q)
    threshold = cfg.ransac.inlier_ratio
    T: np.ndarray | None = None
    X: np.ndarray | None = None
    n_inliers, it = 0, 0
    seen: list[tuple[np.ndarray, Agreement]] = []
    for it in range(1, cfg.outer.max_iterations + 1):  # noqa: B007 (the count is reported)
        t = time.perf_counter()
        H1 = build_first_order(apply(T, S), Q, cfg.tensor.first_order_sigma) if T is not None else None
        t = timer.add("tensor", t)
        X, _ = power_iteration(H3, H1, cfg.tensor.first_order_weight, cfg.power_iteration.iterations,
                               cfg.power_iteration.tol, cfg.power_iteration.normalisation_rounds, start=X)
        t = timer.add("power_iteration", t)
        scores = entry_scores(H3, X.ravel())
        # Later rounds start from a transform and a sharper assignment: fewer hypotheses suffice.
        budget = cfg.ransac.iterations if T is None else max(1, int(cfg.ransac.iterations * cfg.ransac.refine_fraction))
        n_guided = min(budget, len(scores))
        top = np.argpartition(-scores, n_guided - 1)[:n_guided] if n_guided < len(scores) else np.arange(len(scores))
        top = top[np.argsort(-scores[top], kind="stable")]
        guided_src = np.stack([H3.a[top] // n2, H3.b[top] // n2, H3.c[top] // n2], axis=1)
        guided_tgt = np.stack([H3.a[top] % n2, H3.b[top] % n2, H3.c[top] % n2], axis=1)
        n_random = (cfg.ransac.random_samples if T is None
                    else int(cfg.ransac.random_samples * cfg.ransac.refine_fraction))
        rand_src, rand_tgt = sample_from_assignment(X, n_random, cfg.ransac.candidates, rng)
        hyp = ransac_hypotheses(S, Q, np.vstack([guided_src, rand_src]), np.vstack([guided_tgt, rand_tgt]),
                                threshold, bounds_n, min_spread=0.05, keep=cfg.ransac.verify_top)
        t = timer.add("ransac", t)
        if len(hyp) == 0:
            break
        # Dense verification: the salient-inlier count is a coarse vote; re-rank the best
        # hypotheses by the symmetric fitness on the working clouds.
        j, finalists = _select_dense(src, tgt, hyp, cfg)
        seen += finalists
        rr = refit(float(hyp.scale[j]), hyp.rotation[j], hyp.translation[j], S, Q, tgt.salient_tree, threshold,
                   bounds_n)
        t = timer.add("verify", t)
        if rr.n_inliers < 3:
            break
        s, R, tr, _ = best_similarity(S[rr.inliers_src], Q[rr.inliers_tgt], cfg.scale_method, rng)
        if not bounds_n[0] <= s <= bounds_n[1]:
            s, R, tr = rr.scale, rr.rotation, rr.translation
        T_new = to_matrix(s, R, tr)
        timer.add("similarity", t)
        # Converged when the salient points stop moving (RMS displacement, normalised units).
        converged = T is not None and displacement(T_new, T, S) < cfg.outer.tol
        T, n_inliers = T_new, rr.n_inliers
        if converged:
            break
    if T is None:
        return None
    t = time.perf_counter()
    agreement = surface_agreement(T, src.surface, tgt.surface, cfg.inlier_distance_ratio,
                                  cfg.verdict.max_normal_angle_deg)
    timer.add("scoring", t)
    return _Candidate(transform=T, n_inliers=n_inliers, iterations=it, agreement=agreement, overlap=overlap,
                      alternatives=tuple(seen))


@dataclass(frozen=True)
class OverlapHypothesis:
    """Where the clouds may overlap: the diameter of the overlapping region in each cloud
    (normalised units; 1 = the whole cloud). ``overlap`` is the ratio reported in the result."""

    name: str
    region_src: float
    region_tgt: float
    overlap: float

    def scale_prior(self, bounds_n: tuple[float, float]) -> tuple[float, float]:
        """Normalised scales this hypothesis allows, intersected with the configured bounds.

        Equal regions (a shared fraction r of each cloud, region sqrt(r)) allow any scale between
        region/1.5 and 1.5/region: the overlap may be a larger share of one cloud than of the
        other. A part inside a whole expects region_tgt / region_src, within a factor 1.5.
        """
        if self.region_src == self.region_tgt:
            lo, hi = self.region_src / 1.5, 1.5 / self.region_src
        else:
            expected = self.region_tgt / self.region_src
            lo, hi = expected / 1.5, expected * 1.5
        return max(bounds_n[0], lo), min(bounds_n[1], hi)


def search_plan(cfg: EngineConfig) -> list[OverlapHypothesis]:
    """The overlap hypotheses the engine tries, in order: equal shares of both clouds (the
    paper's overlap search, ``overlap_candidates``), then one cloud as a part of the other
    (``part_regions``: the part's diameter relative to the whole)."""
    overlaps = cfg.overlap_candidates if cfg.overlap == "auto" else (float(cfg.overlap),)
    plan = [OverlapHypothesis(f"overlap {r:.2f}", float(np.sqrt(r)), float(np.sqrt(r)), r)
            for r in sorted(overlaps, reverse=True)]  # the common, cheap-to-settle cases first
    if cfg.overlap == "auto":
        for rho in cfg.part_regions:
            plan.append(OverlapHypothesis(f"source inside target ({rho:.2f})", 1.0, rho, rho * rho))
            plan.append(OverlapHypothesis(f"target inside source ({rho:.2f})", rho, 1.0, rho * rho))
    return plan


def _local_triangles(points: np.ndarray, region: float, n: int, cfg: EngineConfig,
                     rng: np.random.Generator) -> np.ndarray:
    """Triangles wide enough for an overlap region of diameter ``region`` and no wider than it."""
    tri = cfg.triplets
    max_edge = tri.max_edge_ratio * region if region < 1.0 else np.inf
    return sample_triangles(points, n, tri.min_edge_ratio * region, rng, tri.min_angle_deg, max_edge=max_edge)


def _perimeters(points: np.ndarray, triangles: np.ndarray) -> np.ndarray:
    """Perimeter of each triangle (i, j, k)."""
    a, b, c = points[triangles[:, 0]], points[triangles[:, 1]], points[triangles[:, 2]]
    return np.linalg.norm(a - b, axis=1) + np.linalg.norm(b - c, axis=1) + np.linalg.norm(c - a, axis=1)


def _build_tensor(src: _Prepared, tgt: _Prepared, hypothesis: OverlapHypothesis, prior: tuple[float, float],
                  cfg: EngineConfig, rng: np.random.Generator) -> SparseTensor3:
    """Third-order tensor of one overlap hypothesis: its own local triangles on both sides, matched
    in descriptor space; matches whose perimeter ratio (the scale they imply) the prior rules out
    are dropped before the power iteration."""
    tri, w = cfg.triplets, cfg.tensor.normal_weight
    S, Q = src.salient, tgt.salient
    src_tri = _local_triangles(S, hypothesis.region_src, tri.n_source, cfg, rng)
    tgt_tri = with_ambiguous_permutations(Q, _local_triangles(Q, hypothesis.region_tgt, tri.n_target, cfg, rng))
    size_filter = None
    if cfg.tensor.scale_filter:
        size_filter = (_perimeters(S, src_tri), _perimeters(Q, tgt_tri), prior[0] / 1.2, prior[1] * 1.2)
    return build_third_order(len(S), src_tri, triangle_descriptors(S, src.salient_normals, src_tri, w),
                             len(Q), tgt_tri, triangle_descriptors(Q, tgt.salient_normals, tgt_tri, w),
                             cfg.tensor.knn, cfg.tensor.sigma, eps=cfg.tensor.knn_eps, size_filter=size_filter)


@dataclass(frozen=True)
class _Fine:
    """A finer working cloud for the refinement and the final verdict (precision needs more points
    than the search)."""

    points: np.ndarray
    normals: np.ndarray
    tree: cKDTree
    surface: Surface

    @classmethod
    def build(cls, points: np.ndarray, cfg: EngineConfig, rng: np.random.Generator) -> _Fine:
        pts = downsample_to(points, cfg.refine.voxel_ratio, cfg.refine.max_points, rng)
        normals = estimate_normals(pts, cfg.preprocess.normal_neighbours)
        tree = cKDTree(pts)
        return cls(pts, normals, tree, Surface.build(pts, normals, tree, cfg.verdict.sample_points))

    @classmethod
    def of(cls, prepared: _Prepared, points: np.ndarray, cfg: EngineConfig, rng: np.random.Generator) -> _Fine:
        """The refinement cloud of one input: the search's working cloud itself when
        ``refine.voxel_ratio`` is 0, else a finer downsampling of ``points``."""
        if cfg.refine.voxel_ratio == 0:
            return cls(prepared.points, prepared.normals, prepared.tree, prepared.surface)
        return cls.build(points, cfg, rng)


def _tight_agreement(T: np.ndarray, src_fine: _Fine, tgt_fine: _Fine, cfg: EngineConfig) -> Agreement:
    """Surface agreement at the verdict's tight tolerances, on the fine clouds."""
    v = cfg.verdict
    return surface_agreement(T, src_fine.surface, tgt_fine.surface, v.tight_distance_ratio, v.tight_normal_angle_deg)


def _refine(T_n: np.ndarray, src_fine: _Fine, tgt_fine: _Fine, cfg: EngineConfig,
            bounds_n: tuple[float, float], timer: _Timer) -> tuple[np.ndarray, Agreement]:
    """Scaled ICP polish of a coarse transform on the fine clouds, kept only when its tight surface
    agreement does not drop (ICP can drift the scale on outlier-ridden, partial clouds, and the
    verdict's objective exposes it). Returns the transform and its tight agreement."""
    r, v = cfg.refine, cfg.verdict
    before = _tight_agreement(T_n, src_fine, tgt_fine, cfg)
    if not r.enabled:
        return T_n, before
    t = time.perf_counter()
    if r.method == "point_to_plane":
        T_r, _ = scaled_point_to_plane_icp(src_fine.points, tgt_fine.points, tgt_fine.normals, T_n, r.iterations,
                                           r.start_ratio, r.end_ratio, bounds_n, tgt_fine.tree,
                                           src_normals=src_fine.normals, max_normal_angle_deg=v.max_normal_angle_deg)
    else:
        T_r, _ = trimmed_scaled_icp(src_fine.points, tgt_fine.points, T_n, r.iterations, r.start_ratio, r.end_ratio,
                                    bounds_n, tgt_fine.tree)
    timer.add("refine", t)
    after = _tight_agreement(T_r, src_fine, tgt_fine, cfg)
    return (T_r, after) if after.score >= before.score else (T_n, before)


def _decide(candidates: list[_Candidate], src: _Prepared, src_fine: _Fine, tgt_fine: _Fine, cfg: EngineConfig,
            bounds_n: tuple[float, float], timer: _Timer) -> tuple[np.ndarray, Verdict]:
    """Choose the answer among everything the search saw and judge it.

    The search ranks transforms by their surface agreement at the inlier distance; the best few
    *distinct* ones (each moves the source by more than ``verdict.distinct_ratio`` from the others)
    are refined and compared at the verdict's tight tolerances, so that no transform wins by
    precision alone. The best is the answer; the confidence weighs its tight agreement against the
    best distinct rival's.
    """
    v = cfg.verdict
    pool = [(c.transform, c.agreement) for c in candidates] + [alt for c in candidates for alt in c.alternatives]
    pool.sort(key=lambda item: -item[1].score)
    sample = src.surface.sample

    def distinct(T1: np.ndarray, T2: np.ndarray) -> bool:
        return displacement(T1, T2, sample) > v.distinct_ratio

    finalists: list[np.ndarray] = []
    for T, _ in pool:
        if all(distinct(T, F) for F in finalists):
            finalists.append(T)
            if len(finalists) == v.refined_finalists:
                break
    refined = sorted((_refine(T, src_fine, tgt_fine, cfg, bounds_n, timer) for T in finalists),
                     key=lambda x: -x[1].score)
    T_answer, agreement = refined[0]
    # Rivals: the other refined finalists, and (unrefined, so at a disadvantage) the best of the
    # rest of the pool — finalists can converge onto the answer when refined.
    others = [(T, a) for T, a in refined[1:]]
    unrefined = [T for T, _ in pool if distinct(T, T_answer)][:v.rival_pool]
    others += [(T, _tight_agreement(T, src_fine, tgt_fine, cfg)) for T in unrefined]
    rival_score = max([a.score for T, a in others if distinct(T, T_answer)], default=0.0)
    support = sum(not distinct(T_answer, c.transform) for c in candidates)
    conf = confidence(agreement.score, rival_score, v.full_margin)
    return T_answer, Verdict(confidence=conf, score=agreement.score, rival_score=rival_score, agreement=agreement,
                             support=support / max(len(candidates), 1))


def _settled(best: _Candidate, candidates: list[_Candidate], src: _Prepared, cfg: EngineConfig) -> bool:
    """The search can stop early when independent overlap hypotheses already ended at the same,
    well-supported transform (``outer.settle_support`` of them, agreement at least
    ``outer.settle_agreement``), or when one hypothesis alone explains so much of both clouds
    (``outer.settle_alone``) that no wrong alignment in the benchmarks came near it; the
    remaining hypotheses would only cost time."""
    o = cfg.outer
    if best.agreement.score >= o.settle_alone:
        return True
    if o.settle_support <= 0 or best.agreement.score < o.settle_agreement:
        return False
    same = sum(displacement(best.transform, c.transform, src.surface.sample) <= cfg.verdict.distinct_ratio
               for c in candidates)
    return same >= o.settle_support


def _refusal(verdict: Verdict, cfg: EngineConfig) -> str:
    """Why an answer below the confidence threshold is refused, in words: *ambiguous* when a distinct
    rival explains nearly as much of a well-explained pair (agreement ≥ 0.15), else *low confidence*
    with how much of the data the best alignment explains."""
    scores = f"agreement {verdict.score:.2f} vs {verdict.rival_score:.2f}"
    lead = verdict.score - verdict.rival_score
    if verdict.rival_score >= cfg.verdict.ambiguity_ratio * verdict.score and verdict.score >= 0.15:
        return (f"ambiguous: two distinct alignments explain the data almost equally well ({scores}; "
                f"confidence {verdict.confidence:.2f}, threshold {cfg.min_confidence:.2f})")
    return (f"low confidence {verdict.confidence:.2f} (threshold {cfg.min_confidence:.2f}): the best alignment puts "
            f"{100 * verdict.score:.0f}% of the points on the other surface, only {100 * lead:.0f} points more "
            f"than a distinct alternative ({scores})")


def _failed(message: str, seed: int, start: float, timings: dict[str, float],
            transform: np.ndarray | None = None) -> RegistrationResult:
    T = np.eye(4) if transform is None else transform
    s, R, t = split(T)
    return RegistrationResult(transform=T, scale=s, rotation=R, translation=t,
                              fitness=0.0, inlier_rmse=float("nan"), n_inliers=0, iterations=0, status="failed",
                              message=message, runtime_s=time.perf_counter() - start, seed=seed, confidence=0.0,
                              timings=timings)


def register(source: np.ndarray, target: np.ndarray, config: EngineConfig | None = None, seed: int = 0, *,
             source_normals: np.ndarray | None = None,
             target_normals: np.ndarray | None = None) -> RegistrationResult:
    """Estimate the similarity mapping ``source`` (N, 3) onto ``target`` (M, 3).

    Normals are re-estimated on the working (downsampled) clouds, so the optional normal arguments
    are accepted for API symmetry but not required. Returns a result with ``status='failed'`` and a
    message (never raises) when the inputs are degenerate or the evidence is too weak.
    """
    del source_normals, target_normals  # normals are recomputed on the downsampled clouds
    cfg = config if config is not None else EngineConfig()
    start = time.perf_counter()
    timer = _Timer({})
    try:
        src_raw = validate_cloud(source, "source")
        tgt_raw = validate_cloud(target, "target")
    except DegenerateCloudError as err:
        return _failed(str(err), seed, start, timer.timings)

    plan = search_plan(cfg)
    root = np.random.SeedSequence(seed)
    rng_src, rng_tgt, rng_refine, *rng_overlaps = [np.random.default_rng(s) for s in root.spawn(3 + len(plan))]
    ns, nt = normalise(src_raw), normalise(tgt_raw)
    src = _prepare(ns.points, cfg, rng_src, timer)
    tgt = _prepare(nt.points, cfg, rng_tgt, timer)
    if len(src.salient) < 4 or len(tgt.salient) < 4:
        return _failed(f"too few salient points (source {len(src.salient)}, target {len(tgt.salient)}); "
                       "the clouds are too small or too sparse for the supervoxel resolution", seed, start,
                       timer.timings)

    # Scale bounds in normalised units: s_orig = s_norm * size_t / size_s.
    lo, hi = cfg.scale_bounds
    ratio = ns.size / nt.size
    bounds_n = (lo * ratio, hi * ratio)

    best: _Candidate | None = None
    candidates: list[_Candidate] = []
    for hypothesis, rng in zip(plan, rng_overlaps):
        prior = hypothesis.scale_prior(bounds_n)
        if prior[0] >= prior[1]:
            continue
        t = time.perf_counter()
        H3 = _build_tensor(src, tgt, hypothesis, prior, cfg, rng)
        timer.add("tensor", t)
        if len(H3.values) < 3:
            continue
        cand = _outer_loop(src, tgt, H3, hypothesis.overlap, cfg, rng, prior, timer)
        if cand is None:
            continue
        log.debug("%s: agreement source %.3f target %.3f, %d inliers", hypothesis.name, cand.agreement.source,
                  cand.agreement.target, cand.n_inliers)
        candidates.append(cand)
        if best is None or (cand.score, cand.n_inliers) > (best.score, best.n_inliers):
            best = cand
        if _settled(best, candidates, src, cfg):
            log.debug("settled after %d of %d overlap hypotheses", len(candidates), len(plan))
            break
    if best is None:
        return _failed("no consistent correspondences found (RANSAC found no valid similarity)", seed, start,
                       timer.timings)

    t = time.perf_counter()
    refine_before = timer.timings.get("refine", 0.0)
    src_fine, tgt_fine = _Fine.of(src, ns.points, cfg, rng_refine), _Fine.of(tgt, nt.points, cfg, rng_refine)
    T_n, verdict = _decide(candidates, src, src_fine, tgt_fine, cfg, bounds_n, timer)
    fit = evaluate_fit(src.points, tgt.tree, T_n, cfg.inlier_distance_ratio)
    # The search run that found the answer (the nearest candidate) reports inliers and overlap.
    best = min(candidates, key=lambda c: displacement(T_n, c.transform, src.surface.sample))
    # the verdict stage: finer clouds, rival scoring and the final choice (ICP itself is "refine")
    timer.timings["verdict"] = timer.timings.get("verdict", 0.0) + (time.perf_counter() - t) - (
        timer.timings.get("refine", 0.0) - refine_before)
    T = denormalise(T_n, ns, nt)
    scale, rotation, translation = split(T)
    status, message = "ok", ""
    if best.n_inliers < cfg.ransac.min_inliers:
        status, message = "failed", (f"too weak evidence: {best.n_inliers} RANSAC inliers "
                                     f"(need {cfg.ransac.min_inliers})")
    elif fit.fitness < cfg.min_fitness:
        status, message = "failed", f"too weak evidence: fitness {fit.fitness:.3f} below {cfg.min_fitness}"
    elif not lo <= scale <= hi:
        status, message = "failed", f"scale {scale:.4g} outside the configured bounds [{lo}, {hi}]"
    elif verdict.confidence < cfg.min_confidence:
        status, message = "failed", _refusal(verdict, cfg)
    return RegistrationResult(
        transform=T, scale=scale, rotation=rotation, translation=translation, fitness=fit.fitness,
        inlier_rmse=fit.rmse * nt.size, n_inliers=best.n_inliers, iterations=best.iterations, status=status,
        message=message, runtime_s=time.perf_counter() - start, seed=seed, overlap=best.overlap,
        confidence=verdict.confidence, timings=timer.timings,
        evidence={"score": verdict.score, "rival_score": verdict.rival_score,
                  "source_agreement": verdict.agreement.source, "target_agreement": verdict.agreement.target,
                  "support": verdict.support},
    )


def score_transform(source: np.ndarray, target: np.ndarray, transform: np.ndarray,
                    config: EngineConfig | None = None, seed: int = 0) -> float:
    """The engine's own score of any transform ``transform`` (original coordinates, source -> target).

    Uses the same preparation and the same objective the engine ranks its candidates with, so
    comparing the score of the ground truth with the score of the engine's answer tells whether a
    failure is a search miss (truth scores higher), an objective that cannot separate them (answer
    scores higher) or a precision problem (equal within noise).
    """
    cfg = config if config is not None else EngineConfig()
    timer = _Timer({})
    src_raw, tgt_raw = validate_cloud(source, "source"), validate_cloud(target, "target")
    rng_src, rng_tgt = (np.random.default_rng(s) for s in np.random.SeedSequence(seed).spawn(2))
    ns, nt = normalise(src_raw), normalise(tgt_raw)
    src = _prepare(ns.points, cfg, rng_src, timer)
    tgt = _prepare(nt.points, cfg, rng_tgt, timer)
    T_n = np.linalg.inv(nt.to_original()) @ np.asarray(transform, dtype=float) @ ns.to_original()
    return surface_agreement(T_n, src.surface, tgt.surface, cfg.inlier_distance_ratio,
                             cfg.verdict.max_normal_angle_deg).score

