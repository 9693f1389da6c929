"""Stage 5: the verdict. The best few distinct transforms of the search are refined (scaled ICP)
and compared at tight tolerances; the best is the answer and its lead over the best distinct rival
is the confidence (:mod:`gctr_cli.engine.verdict` has the measures)."""

from __future__ import annotations

import functools
import time
from collections.abc import Callable
from dataclasses import dataclass
from itertools import islice

import numpy as np

from gctr_cli.config import EngineConfig
from gctr_cli.engine.height import HeightMap
from gctr_cli.engine.prepare import PreparedCloud, RefinementCloud, StageTimer
from gctr_cli.engine.refine import scaled_point_to_plane_icp, trimmed_scaled_icp
from gctr_cli.engine.search import Candidate
from gctr_cli.engine.verdict import (
    Agreement,
    SharedData,
    Verdict,
    confidence,
    displacement,
    sample_weight,
    shared_displacement,
    surface_agreement,
)
from gctr_cli.geometry import apply

#: below this share of the two surfaces explained (the plain agreement), a refused answer explains too
#: little to call the data "ambiguous"
AMBIGUITY_MIN_AGREEMENT = 0.15


def tight_tolerances(src_ref: RefinementCloud, tgt_ref: RefinementCloud, scale: float,
                     cfg: EngineConfig) -> tuple[float, float]:
    """The verdict's tight distance (normalised target units) and normal angle (degrees).

    The distance is ``verdict.tight_distance_ratio``, widened on noisy clouds to
    ``verdict.tight_noise_factor`` times their combined roughness (the source's carried into target
    units by ``scale``); the angle ``verdict.tight_normal_angle_deg`` widens by the same factor (noise
    tilts the PCA normals as it spreads the points), at most 90°. Fixed tolerances near the noise
    level leave every transform, the right one included, explaining only a small share of the data,
    and right answers lose their lead over the rivals.
    """
    v = cfg.verdict
    noise = float(np.hypot(scale * src_ref.roughness, tgt_ref.roughness))
    base = v.tight_distance_ratio * smaller_cloud(scale)
    distance = max(base, v.tight_noise_factor * noise)
    return distance, min(90.0, v.tight_normal_angle_deg * distance / base)


def similarity_scale(T: np.ndarray) -> float:
    """Scale of the similarity ``T`` (cube root of its 3x3 block's determinant)."""
    return float(np.cbrt(np.linalg.det(T[:3, :3])))


def smaller_cloud(scale: float) -> float:
    """Size of the smaller of the two clouds in normalised target units (each cloud is normalised to
    size 1; the source's size there is the transform's ``scale``): the length that the verdict's and
    the refinement's relative tolerances refer to. A scale that is not a positive number (no
    similarity) falls back to the target's size."""
    return min(1.0, scale) if np.isfinite(scale) and scale > 0 else 1.0


@dataclass(frozen=True)
class TightTest:
    """How the verdict's final comparison scores a transform: the tight distance (normalised target
    units) and normal angle (degrees) of :func:`tight_tolerances`, and the conflicts — points within
    ``near`` of the other cloud but off its surface, each costing ``conflict_weight`` of an agreeing
    point (0: not counted)."""

    distance: float
    angle_deg: float
    near: float = 0.0
    conflict_weight: float = 0.0


def tight_test(src_ref: RefinementCloud, tgt_ref: RefinementCloud, scale: float, cfg: EngineConfig) -> TightTest:
    """The verdict's final test for transforms of about ``scale`` (normalised units): the tolerances of
    :func:`tight_tolerances` and the configured conflicts (``verdict.conflict_ratio`` of the smaller
    cloud, ``verdict.conflict_weight``)."""
    v = cfg.verdict
    return TightTest(*tight_tolerances(src_ref, tgt_ref, scale, cfg), near=v.conflict_ratio * smaller_cloud(scale),
                     conflict_weight=v.conflict_weight)


def tight_agreement(T: np.ndarray, src_ref: RefinementCloud, tgt_ref: RefinementCloud, test: TightTest,
                    known: dict[bytes, Agreement] | None = None) -> Agreement:
    """Surface agreement (and conflicts) of ``T`` by the verdict's tight ``test``, on the refinement clouds.

    ``known``: the agreements already computed by this test on these clouds, by the transform's bytes (looked
    up, and filled in): :func:`decide` scores a finalist before its refinement and again as an unrefined
    rival, and the whole rival pool again when slides join the finalists."""
    key = T.tobytes() if known is not None else b""
    if known is not None and key in known:
        return known[key]
    agreement = surface_agreement(T, src_ref.surface, tgt_ref.surface, test.distance, test.angle_deg, test.near,
                                  test.conflict_weight)
    if known is not None:
        known[key] = agreement
    return agreement


def _refine(T_n: np.ndarray, src_ref: RefinementCloud, tgt_ref: RefinementCloud, cfg: EngineConfig,
            bounds_n: tuple[float, float], timer: StageTimer, test: TightTest,
            known: dict[bytes, Agreement] | None = None) -> tuple[np.ndarray, Agreement]:
    """Scaled ICP polish of a coarse transform on the refinement clouds, kept only when its tight surface
    agreement does not drop (ICP can drift the scale on outlier-ridden, partial clouds, and the
    verdict's objective exposes it). Returns the transform and its tight agreement (``known``: as
    :func:`tight_agreement`)."""
    before = tight_agreement(T_n, src_ref, tgt_ref, test, known)
    if not cfg.refine.enabled:
        return T_n, before
    t = time.perf_counter()
    T_r = icp(T_n, src_ref, tgt_ref, cfg, bounds_n)
    timer.add("refine", t)
    after = tight_agreement(T_r, src_ref, tgt_ref, test, known)
    return (T_r, after) if after.score >= before.score else (T_n, before)


def icp(T_n: np.ndarray, src_ref: RefinementCloud, tgt_ref: RefinementCloud, cfg: EngineConfig,
        bounds_n: tuple[float, float]) -> np.ndarray:
    """The refinement's scaled ICP from ``T_n`` on the refinement clouds (normalised units); a step that
    would leave ``bounds_n`` is taken with the scale held at the bound."""
    r, v = cfg.refine, cfg.verdict
    size = smaller_cloud(similarity_scale(T_n))
    start, end = r.start_ratio * size, r.end_ratio * size
    if r.method == "point_to_plane":
        return scaled_point_to_plane_icp(src_ref.points, tgt_ref.points, tgt_ref.normals, T_n, r.iterations,
                                         start, end, bounds_n, tgt_ref.tree,
                                         src_normals=src_ref.normals, max_normal_angle_deg=v.max_normal_angle_deg,
                                         src_tree=src_ref.tree, symmetric=r.symmetric,
                                         max_matches=r.max_matches)[0]
    return trimmed_scaled_icp(src_ref.points, tgt_ref.points, T_n, r.iterations, start, end, bounds_n,
                              tgt_ref.tree)[0]


def decide(candidates: list[Candidate], src: PreparedCloud, src_ref: RefinementCloud, tgt_ref: RefinementCloud,
           cfg: EngineConfig, bounds_n: tuple[float, float], timer: StageTimer) -> tuple[np.ndarray, Verdict]:
    """Choose the answer among everything the search saw and judge it.

    The search ranks transforms by their surface agreement at the inlier distance; the best few
    *distinct* ones (each moves the source by more than ``verdict.distinct_ratio`` from the others)
    are refined and compared by their score at the verdict's tight tolerances (agreement less
    conflicts), so that no transform wins by precision alone. The best is the answer; the confidence
    weighs its score against the best rival's (a rival aligns the data the answer aligns differently:
    :func:`shared_displacement`). An answer short of confidence 1 is also tried slid along the
    direction its surface contact leaves free (:func:`slid_transforms`, ``verdict.slide_steps``): two
    low-overlap room fragments can slide along a wall, and a wrong slide is found there or refused. Every
    answer is also turned half a turn about the clouds' principal axes (:func:`likely_turns`,
    ``verdict.turned_finalists``): a symmetric shape's other pose is a rival the search may not propose."""
    v = cfg.verdict
    pool = [(c.transform, c.agreement) for c in candidates] + [alt for c in candidates for alt in c.alternatives]
    pool.sort(key=lambda item: -item[1].score)
    sample = src.surface.sample
    finalists = first_distinct([T for T, _ in pool], sample, v.distinct_ratio, v.refined_finalists)
    test = tight_test(src_ref, tgt_ref, similarity_scale(pool[0][0]), cfg)
    known: dict[bytes, Agreement] = {}  # tight agreements by transform: each computed once
    refined = [_refine(T, src_ref, tgt_ref, cfg, bounds_n, timer, test, known) for T in finalists]
    height_map = functools.cache(lambda: target_heights(tgt_ref, test, cfg))  # built once, if the relief is asked
    T_answer, verdict, shared = _judged(refined, pool, candidates, src, src_ref, tgt_ref, cfg, test, height_map,
                                        known)

    def new_alignments(starts: list[np.ndarray]) -> list[tuple[np.ndarray, Agreement]]:
        """``starts`` refined, those that end at another alignment than the answer (a rival by the
        shared-data test): the others only polish the answer's own score."""
        return [(T, a) for T, a in (_refine(S, src_ref, tgt_ref, cfg, bounds_n, timer, test, known) for S in starts)
                if shared_displacement(T, T_answer, shared, sample) > v.distinct_ratio]

    if v.turned_finalists:
        # The answer turned half a turn about a principal axis of either cloud: a symmetric shape fits
        # as well turned (a box, a tube, a patch of a round surface), and the search need not have
        # proposed that alignment. Turns that agree well are refined and join the finalists: one that
        # fits better becomes the answer, one that fits as well makes the answer ambiguous.
        turned = new_alignments(likely_turns(T_answer, src_ref, tgt_ref, cfg, v.turned_finalists, sample))
        if turned:
            refined = refined + turned
            T_answer, verdict, shared = _judged(refined, pool, candidates, src, src_ref, tgt_ref, cfg, test,
                                                height_map, known)
    free = (contact_freedom(T_answer, src_ref, tgt_ref, test.distance)
            if v.slide_steps and (verdict.confidence < 1.0 or v.slide_free_ratio > 0) else None)
    if free is not None and (verdict.confidence < 1.0 or free[1] < v.slide_free_ratio):
        # An answer that is not clearly ahead: try it slid both ways along the direction its surface
        # contact constrains least (a wall or a floor lets a low-overlap pair slide along it), refined.
        # Those that end at a different alignment (a rival by the shared-data test) join the finalists
        # and the verdict chooses again; those that return to the answer are dropped, so that the
        # slides never just polish the answer's own score.
        slid = new_alignments(slid_transforms(T_answer, free[0], v.slide_steps))
        if slid:
            T_answer, verdict, _ = _judged(refined + slid, pool, candidates, src, src_ref, tgt_ref, cfg, test,
                                           height_map, known)
    return T_answer, verdict


#: a half-turn start of :func:`likely_turns` is refined only when, unrefined, it agrees with the target at the
#: inlier distance at least this share of the answer's agreement there
TURN_START_RATIO = 0.5


def likely_turns(T: np.ndarray, src_ref: RefinementCloud, tgt_ref: RefinementCloud, cfg: EngineConfig,
                 count: int, sample: np.ndarray) -> list[np.ndarray]:
    """``T`` followed by a half-turn about each principal axis of the moved source and of the target (through
    its centroid): the ``count`` that agree best with the target at the inlier distance, of those that agree
    at least :data:`TURN_START_RATIO` as well as ``T`` does, each distinct from the better ones (it moves the
    source ``sample`` by more than ``verdict.distinct_ratio``: where the answer lines the two clouds' axes
    up, the turn about the source's axis and about the target's are one pose) — starts for the verdict's
    refinement."""
    starts = []
    for axis, centre in both_principal_planes(T, src_ref, tgt_ref):
        turn = np.eye(4)
        turn[:3, :3] = 2.0 * np.outer(axis, axis) - np.eye(3)  # half a turn about ``axis``
        turn[:3, 3] = centre - turn[:3, :3] @ centre
        starts.append(turn @ T)
    floor = TURN_START_RATIO * coarse_agreement(T, src_ref, tgt_ref, cfg)
    ranked = sorted(((score, i) for i, S in enumerate(starts)
                     if (score := coarse_agreement(S, src_ref, tgt_ref, cfg)) >= floor), reverse=True)
    return first_distinct([starts[i] for _, i in ranked], sample, cfg.verdict.distinct_ratio, count)


def first_distinct(transforms: list[np.ndarray], sample: np.ndarray, distinct_ratio: float,
                   count: int) -> list[np.ndarray]:
    """The first ``count`` of ``transforms`` (best first) that each move ``sample`` by more than
    ``distinct_ratio`` from every one kept before: the verdict's finalists, and its half-turn starts."""
    chosen: list[np.ndarray] = []
    for T in transforms:
        if len(chosen) == count:
            break
        if all(displacement(T, S, sample) > distinct_ratio for S in chosen):
            chosen.append(T)
    return chosen


#: the reflection the mirror checks apply to the source (any reflection is this one up to a rotation)
MIRROR = np.array([-1.0, 1.0, 1.0])


def reflected_fit(T: np.ndarray, src_ref: RefinementCloud, tgt_ref: RefinementCloud, cfg: EngineConfig,
                  bounds_n: tuple[float, float]) -> tuple[float, float]:
    """How much better the source's mirror image fits where the answer ``T`` put the source: the answer's
    tight score, and the best tight score of ``T`` reflected through one of six planes — the three
    principal planes of the moved source (through its centroid) and the three of the target (through
    its centroid) — and refined as a finalist is, in :data:`REFLECTION_ICP_ITERATIONS` iterations: only
    the one that agrees best with the target at the inlier distance, and only if it agrees at least
    :data:`REFLECTION_START_RATIO` as well as the answer does there (else the reflected score is NaN).
    A mirror image (a cloud with a flipped axis) has no right rotation, but on a nearly symmetric object
    its best rotation lays it on the mirror-image place (a bunny scan on the other flank), which the
    object's plane of symmetry — about a principal plane of the whole, source or target — takes back to
    the true place; the refinement finishes it. The
    refinement runs on the source reflected by :data:`MIRROR` (so that it works on a proper similarity);
    its time is not booked. Both scores are by the verdict's tight test at ``T``'s scale
    (:func:`tight_test`)."""
    test = tight_test(src_ref, tgt_ref, similarity_scale(T), cfg)
    answer = tight_agreement(T, src_ref, tgt_ref, test).score
    mirrored = src_ref.reflected(MIRROR, cfg)
    starts = reflection_starts(T, src_ref, tgt_ref)
    # Only the likeliest start is refined (ICP is the cost), ranked as the search ranks, at the inlier
    # distance; and only when it agrees with the target nearly as well as the answer does there.
    ranked = sorted(((coarse_agreement(S, mirrored, tgt_ref, cfg), i) for i, S in enumerate(starts)), reverse=True)
    if ranked[0][0] < REFLECTION_START_RATIO * coarse_agreement(T, src_ref, tgt_ref, cfg):
        return answer, float("nan")
    short = cfg.model_copy(update={"refine": cfg.refine.model_copy(update={"iterations": REFLECTION_ICP_ITERATIONS})})
    return answer, _refine(starts[ranked[0][1]], mirrored, tgt_ref, short, bounds_n, StageTimer({}), test)[1].score


#: the ICP iterations of the one reflection :func:`reflected_fit` refines: on mirrored probe pairs of the bunny
#: and the dragon (tuning offset 0) and a flipped bunny scan, the best unrefined reflection refined in 8
#: iterations led the answer by as much as the best two in 15 (+0.16 to +0.55) at a third of the time, and
#: right answers' leads stayed at -0.04 or below
REFLECTION_ICP_ITERATIONS = 8
#: ... and only when, unrefined, it agrees with the target at the inlier distance at least this share of the
#: answer's agreement there: 0.50-1.07 on those mirror images, under 0.4 on 127 of 184 right answers of
#: the tuning set's easy, cross, real, sfm, hard and part levels (it costs a mirror image nothing and a right
#: answer the refinement's time)
REFLECTION_START_RATIO = 0.4


def reflection_starts(T: np.ndarray, src_ref: RefinementCloud, tgt_ref: RefinementCloud) -> list[np.ndarray]:
    """``T`` reflected through the three principal planes of the moved source and the three of the target,
    each as a proper similarity of the source mirrored by :data:`MIRROR` (the starts of :func:`reflected_fit`)."""
    flip = np.diag([*MIRROR, 1.0])
    starts = []
    for normal, centre in both_principal_planes(T, src_ref, tgt_ref):
        plane = np.eye(4)
        plane[:3, :3] -= 2.0 * np.outer(normal, normal)
        plane[:3, 3] = 2.0 * float(centre @ normal) * normal
        starts.append(plane @ T @ flip)
    return starts


def coarse_agreement(T: np.ndarray, src_ref: RefinementCloud, tgt_ref: RefinementCloud, cfg: EngineConfig) -> float:
    """Surface agreement of ``T`` at the inlier distance, as the search ranks transforms: how a start of the
    reflection and half-turn checks is judged before it is worth an ICP."""
    return surface_agreement(T, src_ref.surface, tgt_ref.surface, cfg.inlier_distance_ratio,
                             cfg.verdict.max_normal_angle_deg).score


def both_principal_planes(T: np.ndarray, src_ref: RefinementCloud,
                          tgt_ref: RefinementCloud) -> list[tuple[np.ndarray, np.ndarray]]:
    """The principal planes of the source moved by ``T`` and of the target (:func:`principal_planes`)."""
    return principal_planes(apply(T, src_ref.points)) + principal_planes(tgt_ref.points)


def principal_planes(points: np.ndarray) -> list[tuple[np.ndarray, np.ndarray]]:
    """The three principal planes of ``points``: (unit normal, a point on it, the centroid) each."""
    centre = points.mean(axis=0)
    return [(normal, centre) for normal in np.linalg.svd(points - centre, full_matrices=False)[2]]


def contact_freedom(T: np.ndarray, src_ref: RefinementCloud, tgt_ref: RefinementCloud,
                    distance: float) -> tuple[np.ndarray, float] | None:
    """The translation along which ``T``'s point-to-plane contact is least constrained and how free it is:
    the eigenvector of the smallest eigenvalue of the sum of ``n nᵀ`` over the target normals of the moved
    source points within ``distance`` of the target, and that eigenvalue over the largest (near 0 along a
    cylinder's axis or the line where two walls meet). None when fewer than three points are in contact."""
    d, j = tgt_ref.tree.query(apply(T, src_ref.points), distance_upper_bound=distance)
    normals = tgt_ref.normals[j[np.isfinite(d)]]
    if len(normals) < 3:
        return None
    values, vectors = np.linalg.eigh(normals.T @ normals)
    return vectors[:, 0], float(values[0] / values[-1]) if values[-1] > 0 else 0.0


def slid_transforms(T: np.ndarray, direction: np.ndarray, steps: tuple[float, ...]) -> list[np.ndarray]:
    """``T`` shifted both ways by each of ``steps`` (× the smaller cloud's size) along ``direction``."""
    size = smaller_cloud(similarity_scale(T))
    shifted = []
    for step in steps:
        for sign in (-1.0, 1.0):
            T_s = T.copy()
            T_s[:3, 3] += sign * step * size * direction
            shifted.append(T_s)
    return shifted


def _judged(refined: list[tuple[np.ndarray, Agreement]], pool: list[tuple[np.ndarray, Agreement]],
            candidates: list[Candidate], src: PreparedCloud, src_ref: RefinementCloud, tgt_ref: RefinementCloud,
            cfg: EngineConfig, test: TightTest, height_map: Callable[[], HeightMap | None],
            known: dict[bytes, Agreement] | None = None) -> tuple[np.ndarray, Verdict, SharedData]:
    """The best of the ``refined`` finalists by tight score, the verdict on it, and the data it aligns
    (what a rival must move differently). ``known``: as :func:`tight_agreement`."""
    v = cfg.verdict
    sample = src.surface.sample
    refined = sorted(refined, key=lambda x: -x[1].score)
    T_answer, agreement = refined[0]
    # Rivals: the other refined finalists, and (unrefined, so at a disadvantage) the best of the
    # rest of the pool — finalists can converge onto the answer when refined. A rival must align the
    # data the answer aligns differently (shared_displacement): a near copy of the answer that only
    # swings the unshared rest of a cloud elsewhere is no alternative.
    shared = SharedData.of(T_answer, src_ref.surface, tgt_ref.surface, cfg.inlier_distance_ratio)

    def rival(T: np.ndarray) -> bool:
        return shared_displacement(T, T_answer, shared, sample) > v.distinct_ratio

    rivals = [(T, a) for T, a in refined[1:] if rival(T)]
    unrefined = islice((T for T, _ in pool if rival(T)), v.rival_pool)
    rivals += [(T, tight_agreement(T, src_ref, tgt_ref, test, known)) for T in unrefined]
    rival_score = max((a.score for _, a in rivals), default=0.0)  # confidence() floors it at 0: "no alignment" scores 0
    support = sum(displacement(T_answer, c.transform, sample) <= v.distinct_ratio for c in candidates)
    conf = confidence(agreement.score, rival_score, v.full_margin)
    relief = (relief_confidence(T_answer, agreement, rivals, src_ref, tgt_ref, test, cfg, height_map)
              if v.height_weight > 0 and conf < 1.0 else 0.0)
    # a sparse cloud's sample is smaller than the threshold was calibrated on: its lead counts for less
    n_sample = min(len(src_ref.surface.sample), len(tgt_ref.surface.sample))
    weight = sample_weight(n_sample, v.full_margin_points)
    return T_answer, Verdict(confidence=weight * max(conf, relief), score=agreement.score, rival_score=rival_score,
                             agreement=agreement, support=support / max(len(candidates), 1),
                             relief_confidence=weight * relief, sample_points=n_sample,
                             sample_weight=weight), shared


def relief_confidence(T_answer: np.ndarray, agreement: Agreement, rivals: list[tuple[np.ndarray, Agreement]],
                      src_ref: RefinementCloud, tgt_ref: RefinementCloud, test: TightTest,
                      cfg: EngineConfig, height_map: Callable[[], HeightMap | None] | None = None) -> float:
    """The answer's confidence when the relief over the target's dominant plane counts as well
    (:mod:`gctr_cli.engine.height`): each score plus ``verdict.height_weight`` times its relief
    agreement, the lead measured against ``verdict.height_full_margin``. The relief is coarse (cells
    of ``verdict.height_cell_ratio``): it tells *which* alignment is right, where noisy structure
    leaves the surface agreement of the right one no better than a wrong one's (outdoor LiDAR), but
    not how precise it is — so it never chooses the answer, and counts against a wider margin. 0 when
    the target has no relief. ``height_map``: returns the target's height map (:func:`target_heights`),
    for a caller that judges several times on the same target and test; built here when not given."""
    v = cfg.verdict
    heights = height_map() if height_map is not None else target_heights(tgt_ref, test, cfg)
    if heights is None:
        return 0.0

    def with_relief(T: np.ndarray, a: Agreement) -> float:
        return a.score + v.height_weight * heights.agreement(apply(T, src_ref.points), test.conflict_weight)

    rival_score = max((with_relief(T, a) for T, a in rivals), default=0.0)
    return confidence(with_relief(T_answer, agreement), rival_score, v.height_full_margin)


def target_heights(tgt_ref: RefinementCloud, test: TightTest, cfg: EngineConfig) -> HeightMap | None:
    """The target's relief over its dominant plane at the verdict's cells and tolerance (None: no relief)."""
    v = cfg.verdict
    return HeightMap.build(tgt_ref.points, tgt_ref.normals, 2 * test.distance, v.height_cell_ratio,
                           v.height_tolerance_ratio)


def truncated(value: float) -> str:
    """``value`` with two decimals, truncated (not rounded): a confidence just below a threshold never
    reads as reaching it."""
    return f"{np.floor(value * 100) / 100:.2f}"


def refusal_message(verdict: Verdict, cfg: EngineConfig) -> str:
    """Why an answer below the confidence threshold is refused, in words: *ambiguous* when a distinct
    rival scores nearly as much on a well-explained pair (the answer puts at least
    ``AMBIGUITY_MIN_AGREEMENT`` of the two surfaces on each other), else *low confidence* with how much
    of the data the best alignment explains and by how many points of score it leads (or that it lays
    more of the clouds beside each other than on each other), that the relief gave the confidence, when
    it did (:func:`relief_confidence`), and that the clouds are sparse when the verdict's samples
    were too small for a full confidence (:func:`gctr_cli.engine.verdict.sample_weight`). The confidence
    is shown truncated to two decimals, so that a refused answer never reads as reaching the threshold.
    A rival that scores more than the answer is named as unrefined (the only kind that can)."""
    shown = truncated(verdict.confidence)
    scores = f"score {verdict.score:.2f} vs {verdict.rival_score:.2f}"
    if verdict.rival_score > verdict.score:
        # the refined finalists are ranked, so only an unrefined transform of the search's pool outscores
        # the answer: say so, or "the best alignment" reads as scoring below its alternative
        scores += ", the alternative found by the search and not refined"
    relief = ("" if not 0 < verdict.confidence <= verdict.relief_confidence else
              "; that confidence comes from the relief (the heights above the target's dominant plane, such as "
              "a ground or a floor)")
    sparse = ("" if verdict.sample_weight >= 1 else
              f"; the clouds are sparse: the verdict compared only {verdict.sample_points} points a cloud, so its "
              f"confidence counts sqrt({verdict.sample_points}/{cfg.verdict.full_margin_points}) = "
              f"{verdict.sample_weight:.2f} of the lead (verdict.full_margin_points)")
    explained = 0.5 * (verdict.agreement.source + verdict.agreement.target)
    lead = verdict.score - verdict.rival_score
    if (verdict.score > 0 and verdict.rival_score >= cfg.verdict.ambiguity_ratio * verdict.score
            and explained >= AMBIGUITY_MIN_AGREEMENT):
        return (f"ambiguous: two distinct alignments explain the data almost equally well ({scores}; "
                f"confidence {shown}, threshold {cfg.min_confidence:.2f}){relief}{sparse}")
    head = (f"low confidence {shown} (threshold {cfg.min_confidence:.2f}): the best alignment lays "
            f"{100 * explained:.0f}% of the two surfaces on each other (at the verdict's tight tolerance, finer "
            "than fitness's)")
    if verdict.score <= 0:
        return f"{head} and as much of them or more near each other but off the surface ({scores}){relief}{sparse}"
    points = round(100 * lead)
    margin = ("scores no more than" if points <= 0 else
              f"scores only {points} point{'' if points == 1 else 's'} more than")
    return f"{head} and {margin} a distinct alternative ({scores}){relief}{sparse}"
