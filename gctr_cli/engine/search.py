"""Stages 3-4: the overlap search. Each overlap hypothesis gets its own triangles and tensor
(:func:`hypothesis_tensor`) and runs Algorithm 1's outer loop (:func:`outer_loop`: power iteration,
tensor-guided RANSAC, dense verification, closed-form similarity); :func:`search` runs the
hypotheses in order and stops early once the answer is settled.
"""

from __future__ import annotations

import copy
import logging
import time
from dataclasses import dataclass

import numpy as np

from gctr_cli.config import EngineConfig
from gctr_cli.engine.descriptor import described_with_permutations
from gctr_cli.engine.power_iteration import power_iteration
from gctr_cli.engine.prepare import PreparedCloud, StageTimer
from gctr_cli.engine.ransac import Hypotheses, ransac_hypotheses, refit, sample_from_assignment
from gctr_cli.engine.similarity import best_similarity
from gctr_cli.engine.tensor import SparseTensor3, build_first_order, build_third_order, decode, entry_scores
from gctr_cli.engine.triplets import sample_triangles
from gctr_cli.engine.verdict import Agreement, displacement, surface_agreement
from gctr_cli.geometry import apply, invert, to_matrix

log = logging.getLogger(__name__)

#: points of each working cloud used by the coarse occupancy score of every RANSAC hypothesis
COARSE_SCORE_POINTS = 150
#: minimal samples whose source triangle is thinner than this (sqrt of its area, normalised units) are skipped
MIN_SAMPLE_SPREAD = 0.05
#: how far the scale of an overlap hypothesis may stray from its expected value (factor either way)
SCALE_PRIOR_SLACK = 1.5
#: extra slack of the triangle-match scale filter beyond the prior (perimeter ratios are noisy)
SCALE_FILTER_SLACK = 1.2


@dataclass(frozen=True)
class Candidate:
    transform: np.ndarray  # normalised source -> normalised target
    n_inliers: int
    iterations: int
    agreement: Agreement
    overlap: float
    alternatives: tuple[tuple[np.ndarray, Agreement], ...]  # runners-up seen on the way (verdict rivals)

    @property
    def score(self) -> float:
        return self.agreement.score

    def reversed(self) -> Candidate:
        """The same candidate for the swapped pair (target -> source): inverted transforms, the two
        agreement shares exchanged."""
        def swap(a: Agreement) -> Agreement:
            return Agreement(source=a.target, target=a.source)
        return Candidate(transform=invert(self.transform), n_inliers=self.n_inliers, iterations=self.iterations,
                         agreement=swap(self.agreement), overlap=self.overlap,
                         alternatives=tuple((invert(T), swap(a)) for T, a in self.alternatives))


def dense_scores(src: PreparedCloud, tgt: PreparedCloud, hyp: Hypotheses, distance: float,
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


def select_dense(src: PreparedCloud, tgt: PreparedCloud, hyp: Hypotheses, cfg: EngineConfig
                  ) -> tuple[int, list[tuple[np.ndarray, Agreement]]]:
    """Index of the best hypothesis and the finalists with their surface agreement: a coarse
    occupancy score for all, the surface agreement (proximity + normals) for the finalists."""
    coarse = dense_scores(src, tgt, hyp, cfg.inlier_distance_ratio, n_points=COARSE_SCORE_POINTS)
    top = np.argsort(-coarse, kind="stable")[:cfg.verdict.finalists]
    scored = []
    for j in top:
        T = to_matrix(float(hyp.scale[j]), hyp.rotation[j], hyp.translation[j])
        scored.append((T, surface_agreement(T, src.surface, tgt.surface, cfg.inlier_distance_ratio,
                                            cfg.verdict.max_normal_angle_deg)))
    k = int(np.argmax([a.score for _, a in scored]))
    return int(top[k]), scored


def outer_loop(src: PreparedCloud, tgt: PreparedCloud, H3: SparseTensor3, overlap: float, cfg: EngineConfig,
                rng: np.random.Generator, bounds_n: tuple[float, float], timer: StageTimer) -> Candidate | None:
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
        H1 = (build_first_order(apply(T, S), Q, cfg.tensor.first_order_sigma, tgt_tree=tgt.salient_tree)
              if T is not None else None)
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
        guided_src, guided_tgt = decode(np.stack([H3.a[top], H3.b[top], H3.c[top]], axis=1), n2)
        n_random = (cfg.ransac.random_samples if T is None
                    else int(cfg.ransac.random_samples * cfg.ransac.refine_fraction))
        rand_src, rand_tgt = sample_from_assignment(X, n_random, cfg.ransac.candidates, rng)
        hyp = ransac_hypotheses(S, Q, np.vstack([guided_src, rand_src]), np.vstack([guided_tgt, rand_tgt]),
                                threshold, bounds_n, min_spread=MIN_SAMPLE_SPREAD, keep=cfg.ransac.verify_top)
        t = timer.add("ransac", t)
        if len(hyp) == 0:
            break
        # Dense verification: the salient-inlier count is a coarse vote; re-rank the best
        # hypotheses by the symmetric fitness on the working clouds.
        j, finalists = select_dense(src, tgt, hyp, cfg)
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
        # Converged when the salient points stop moving (RMS displacement, normalised units), or
        # settled: this round's best hypothesis already explains so much of both clouds
        # (``outer.settle_round``) that further rounds would only polish what the verdict's ICP refines.
        converged = T is not None and displacement(T_new, T, S) < cfg.outer.tol
        settled_now = max(a.score for _, a in finalists) >= cfg.outer.settle_round
        T, n_inliers = T_new, rr.n_inliers
        if converged or settled_now:
            break
    if T is None:
        return None
    t = time.perf_counter()
    agreement = surface_agreement(T, src.surface, tgt.surface, cfg.inlier_distance_ratio,
                                  cfg.verdict.max_normal_angle_deg)
    timer.add("scoring", t)
    return Candidate(transform=T, n_inliers=n_inliers, iterations=it, agreement=agreement, overlap=overlap,
                      alternatives=tuple(seen))


@dataclass(frozen=True)
class OverlapHypothesis:
    """Where the clouds may overlap: the diameter of the overlapping region in each cloud
    (normalised units; 1 = the whole cloud). ``overlap`` is the ratio reported in the result."""

    name: str
    region_src: float
    region_tgt: float
    overlap: float

    @property
    def target_is_part(self) -> bool:
        """The target is the part (the whole target overlaps a smaller region of the source): the search
        runs from the target to the source (see :func:`search`)."""
        return self.region_src < self.region_tgt

    def swapped(self) -> OverlapHypothesis:
        """The same hypothesis with the roles of the clouds exchanged."""
        return OverlapHypothesis(self.name, self.region_tgt, self.region_src, self.overlap)

    def scale_prior(self, bounds_n: tuple[float, float]) -> tuple[float, float]:
        """Normalised scales this hypothesis allows, intersected with the configured bounds.

        Equal regions (a shared fraction r of each cloud, region sqrt(r)) allow any scale between
        region / slack and slack / region (``SCALE_PRIOR_SLACK``): the overlap may be a larger share
        of one cloud than of the other. A part inside a whole expects region_tgt / region_src, within
        that factor.
        """
        if self.region_src == self.region_tgt:
            lo, hi = self.region_src / SCALE_PRIOR_SLACK, SCALE_PRIOR_SLACK / self.region_src
        else:
            expected = self.region_tgt / self.region_src
            lo, hi = expected / SCALE_PRIOR_SLACK, expected * SCALE_PRIOR_SLACK
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


@dataclass(frozen=True)
class TriangleMatchInput:
    """What the third-order tensor of one hypothesis is built from: both sides' triangles (vertex
    indices in canonical order), their descriptors, and the perimeter-ratio scale filter."""

    src_tri: np.ndarray
    tgt_tri: np.ndarray
    f_src: np.ndarray
    f_tgt: np.ndarray
    size_filter: tuple[np.ndarray, np.ndarray, float, float] | None


def hypothesis_triangles(src: PreparedCloud, tgt: PreparedCloud, hypothesis: OverlapHypothesis,
                         prior: tuple[float, float], cfg: EngineConfig, rng: np.random.Generator) -> TriangleMatchInput:
    """One hypothesis' local triangles on both sides and their descriptors; the scale filter keeps
    matches whose perimeter ratio (the scale they imply) the prior allows."""
    tri, w = cfg.triplets, cfg.tensor.normal_weight
    S, Q = src.salient, tgt.salient
    src_tri, f_src, src_size = described_with_permutations(
        S, src.salient_normals, _local_triangles(S, hypothesis.region_src, tri.n_source, cfg, rng), w, permute=False)
    tgt_tri, f_tgt, tgt_size = described_with_permutations(
        Q, tgt.salient_normals, _local_triangles(Q, hypothesis.region_tgt, tri.n_target, cfg, rng), w)
    size_filter = None
    if cfg.tensor.scale_filter:
        size_filter = (src_size, tgt_size, prior[0] / SCALE_FILTER_SLACK, prior[1] * SCALE_FILTER_SLACK)
    return TriangleMatchInput(src_tri, tgt_tri, f_src, f_tgt, size_filter)


def hypothesis_tensor(src: PreparedCloud, tgt: PreparedCloud, hypothesis: OverlapHypothesis, prior: tuple[float, float],
                      cfg: EngineConfig, rng: np.random.Generator) -> SparseTensor3:
    """Third-order tensor of one overlap hypothesis: its own local triangles on both sides
    (:func:`hypothesis_triangles`), matched in descriptor space; matches the prior rules out are
    dropped before the power iteration."""
    m = hypothesis_triangles(src, tgt, hypothesis, prior, cfg, rng)
    return build_third_order(len(src.salient), m.src_tri, m.f_src, len(tgt.salient), m.tgt_tri, m.f_tgt,
                             cfg.tensor.knn, cfg.tensor.sigma, eps=cfg.tensor.knn_eps, size_filter=m.size_filter)


def oriented(src: PreparedCloud, tgt: PreparedCloud, hypothesis: OverlapHypothesis, prior: tuple[float, float]
             ) -> tuple[PreparedCloud, PreparedCloud, OverlapHypothesis, tuple[float, float], bool]:
    """The clouds, hypothesis and scale prior in the order the search runs them: a hypothesis whose
    target is the part runs from the target to the source (the last value says so; its result is
    then inverted)."""
    if hypothesis.target_is_part:
        return tgt, src, hypothesis.swapped(), (1.0 / prior[1], 1.0 / prior[0]), True
    return src, tgt, hypothesis, prior, False


#: the third-order tensors of a search, each with its generator as it was once the tensor was built
#: (:func:`search`), keyed by :func:`tensor_key`
Tensors = dict[tuple[object, ...], tuple[SparseTensor3, np.random.Generator]]


def tensor_key(hypothesis: OverlapHypothesis, prior: tuple[float, float], cfg: EngineConfig) -> tuple[object, ...]:
    """What a hypothesis' tensor depends on besides the two clouds' salient points and normals: its regions,
    the scale prior (the perimeter-ratio filter) and the triangle and tensor settings. A search with another
    config (the mirror check's lighter one) reuses a tensor only where all of these are the same."""
    return (hypothesis, prior, cfg.triplets.model_dump_json(), cfg.tensor.model_dump_json())


def _run_hypothesis(src: PreparedCloud, tgt: PreparedCloud, hypothesis: OverlapHypothesis, prior: tuple[float, float],
                    cfg: EngineConfig, rng: np.random.Generator, timer: StageTimer,
                    tensors: Tensors | None = None) -> Candidate | None:
    """The tensor and the outer loop of one overlap hypothesis (``None`` when nothing was found); the tensor
    is taken from ``tensors`` when it holds the hypothesis, else built (and kept there)."""
    t = time.perf_counter()
    key = tensor_key(hypothesis, prior, cfg)
    if tensors is not None and key in tensors:
        H3, state = tensors[key]
        rng = copy.deepcopy(state)
    else:
        H3 = hypothesis_tensor(src, tgt, hypothesis, prior, cfg, rng)
        if tensors is not None:
            tensors[key] = (H3, copy.deepcopy(rng))
    timer.add("tensor", t)
    if len(H3.values) < 3:
        return None
    return outer_loop(src, tgt, H3, hypothesis.overlap, cfg, rng, prior, timer)


def settle_threshold(overlap: float, settle_alone: float, settle_full: float) -> float:
    """The surface agreement at which a candidate of the hypothesis ``overlap`` settles the search
    alone: ``settle_alone``, or the lower of it and ``settle_full`` for the full-overlap hypothesis
    (see :func:`settled`)."""
    return min(settle_alone, settle_full) if overlap >= 1.0 else settle_alone


def settled(best: Candidate, candidates: list[Candidate], src: PreparedCloud, cfg: EngineConfig) -> bool:
    """The search can stop early when independent overlap hypotheses already ended at the same,
    well-supported transform (``outer.settle_support`` of them, agreement at least
    ``outer.settle_agreement``), or when one hypothesis alone explains so much of both clouds
    (``outer.settle_alone``) that the verdict's ICP refines the benchmarks' few wrong candidates above
    it into right answers; the remaining hypotheses would only cost time.

    The full-overlap hypothesis (overlap 1, run first) settles the search from the lower
    ``outer.settle_full``: its triangles span both whole clouds, and its wrong candidates on the tuning
    sets stayed far below the threshold (at most 0.35, apart from one 12 degrees off at 0.555 that the
    verdict's ICP makes right; ``data_scripts.settle_margin``), unlike those of the local hypotheses,
    which find wrong alignments of self-similar parts (up to 0.56). (Stopping any hypothesis at a
    lower agreement when more hypotheses agree was tried: faster on noisy pairs, but the verdict then
    misses the rivals of the skipped hypotheses and becomes over-confident.)"""
    o = cfg.outer
    if best.agreement.score >= settle_threshold(best.overlap, o.settle_alone, o.settle_full):
        return True
    if o.settle_support <= 0 or best.agreement.score < o.settle_agreement:
        return False
    same = sum(displacement(best.transform, c.transform, src.surface.sample) <= cfg.verdict.distinct_ratio
               for c in candidates)
    return same >= o.settle_support


def search(src: PreparedCloud, tgt: PreparedCloud, plan: list[OverlapHypothesis], rngs: list[np.random.Generator],
           bounds_n: tuple[float, float], cfg: EngineConfig, timer: StageTimer,
           tensors: Tensors | None = None) -> list[Candidate]:
    """Run the overlap hypotheses of ``plan`` in order (one generator each) and return the candidate
    transform of each that found one; stops early once the answer is settled (:func:`settled`).

    ``tensors``, when given, keeps each hypothesis' tensor, and a hypothesis already in it (the same
    regions, scale prior and triangle and tensor settings: :func:`tensor_key`) reuses its tensor and
    generator state: the triangles, their descriptors and so the tensor depend only on lengths and angles,
    which a reflection leaves unchanged, so the mirror check (``gctr.mirrored_run``) searches the reflected
    source with the forward search's tensors, as it would have built them.

    A hypothesis whose *target* is the part runs with the clouds swapped (target -> source, then
    inverted): the part always takes the role of the source, whose few triangles all lie inside
    the overlap, while the whole gets the many local triangles. Run the other way round, only the
    few source triangles that happen to fall inside the part could match.
    """
    best: Candidate | None = None
    candidates: list[Candidate] = []
    for hypothesis, rng in zip(plan, rngs):
        prior = hypothesis.scale_prior(bounds_n)
        if prior[0] >= prior[1]:
            continue
        a, b, run_as, run_prior, swapped = oriented(src, tgt, hypothesis, prior)
        cand = _run_hypothesis(a, b, run_as, run_prior, cfg, rng, timer, tensors)
        if cand is None:
            continue
        if swapped:
            cand = cand.reversed()
        log.debug("%s: agreement source %.3f target %.3f, %d inliers", hypothesis.name, cand.agreement.source,
                  cand.agreement.target, cand.n_inliers)
        candidates.append(cand)
        if best is None or (cand.score, cand.n_inliers) > (best.score, best.n_inliers):
            best = cand
        if settled(best, candidates, src, cfg):
            log.debug("settled after %d of %d overlap hypotheses", len(candidates), len(plan))
            break
    return candidates
