"""GCTR — geometric constraint tensor-based registration: the pipeline that composes the stages.

``register(source, target, config, seed)`` → :class:`RegistrationResult` with the similarity that
maps the source onto the target, in the original coordinates of the inputs, and a ``confidence``.
:func:`run_search` is its stages 1-4 alone, for developer tools that look at every candidate.

Pipeline (paper, Algorithm 1, with the extensions measured in bench/ENGINE.md):

1. validate both clouds, normalise each (robust centre at the origin, robust diameter 1 — the
   relative scale is unknown, so every length in the config is relative), voxel-downsample early;
2. supervoxel centroids (VCCS-like) are the salient points; when either cloud has fewer than four (a
   cloud of a few hundred points, whose voxels do not touch), the pair is run once more with coarser
   supervoxels (:data:`SPARSE_SUPERVOXELS`) and the result's message says so;
3. overlap hypotheses (:mod:`~gctr_cli.engine.search`, :func:`search_plan`): equal shares r of
   both clouds (the paper's search over 0.25/0.5/0.75/1.0) and one cloud as a part of the other.
   Each hypothesis draws its own random wide-baseline triangles, *local* to an overlap region of
   its size, describes them by the cosines of their inner angles (+ optional vertex-normal terms),
   and matches them by k nearest neighbours in descriptor space into a sparse third-order tensor
   (matches whose implied scale the hypothesis rules out are dropped);
4. per hypothesis, the outer loop: first-order term under the current transform → tensor power
   iteration → RANSAC over minimal samples from the best-supported triangle matches and the soft
   assignment → surface-agreement verification of the best hypotheses → closed-form similarity
   (SVD; Umeyama or edge-ratio scale) — until the salient points stop moving. The search stops
   early once two hypotheses settle on the same well-supported transform, or one hypothesis alone
   explains most of both clouds;
4b. when the verdict (5) on those candidates is unsure (confidence below ``source_halves_below``, and
   below ``min_confidence`` whatever that is: an answer is not refused without it) or its answer has no
   support (no search run ended within the distinct distance of it), the
   search again from each half of the source (:mod:`~gctr_cli.engine.halves`: an overlap that is a slab
   at one end of the source), and the verdict decides among all candidates;
5. verdict (:mod:`~gctr_cli.engine.decide`, measures in :mod:`~gctr_cli.engine.verdict`): the best
   few *distinct* transforms the search saw are refined (scaled point-to-plane ICP on the working
   clouds, or finer ones with ``refine.voxel_ratio``) and compared by surface agreement (proximity
   with agreeing normals, both directions) at tight tolerances; the best is the answer, and the
   confidence is its lead over the best distinct rival (an answer short of confidence 1 is also tried
   slid both ways along the direction its surface contact leaves free, refined, and the choice made again);
5b. an accepted answer's polish (:mod:`~gctr_cli.engine.polish`, ``engine.polish``, off by default, on in
   ``configs/scene.yaml`` and ``configs/rigid.yaml``), after every check of 6:
   the same ICP once more, trimmed down to a distance set by the clouds' own noise, kept only when it stays
   the same alignment: the verdict says which alignment, the polish makes it as precise as the data allow
   (run only where the noise lets the trimming go to at most half the refinement's end distance);
6. the transform is composed back into the original coordinates and checked (inliers, fitness,
   scale bounds, confidence ≥ ``min_confidence``) — weak or ambiguous evidence gives
   ``status='failed'`` with a message rather than a silently wrong matrix; an answer below
   ``verdict.reverse_below`` must be found again target onto source, and one scoring below
   ``verdict.mirror_below`` must fit better than the source's mirror image (:func:`mirror_config`).

Stages 1-2 for each cloud are in :mod:`~gctr_cli.engine.prepare`. All random draws come from
generators spawned from ``seed`` (the polish's from ``seed`` and :data:`POLISH_STREAM`).
"""

from __future__ import annotations

import dataclasses
import time
from dataclasses import dataclass

import numpy as np

from gctr_cli.config import Config, EngineConfig
from gctr_cli.engine.decide import (
    MIRROR,
    decide,
    icp,
    reflected_fit,
    refusal_message,
    similarity_scale,
    tight_agreement,
    tight_test,
    truncated,
)
from gctr_cli.engine.halves import half_candidates
from gctr_cli.engine.polish import polish
from gctr_cli.engine.prepare import PreparedCloud, RefinementCloud, StageTimer, prepare_cloud
from gctr_cli.engine.preprocess import DegenerateCloudError, NormalisedCloud, denormalise, normalise, validate_cloud
from gctr_cli.engine.refine import evaluate_fit
from gctr_cli.engine.result import RegistrationResult
from gctr_cli.engine.search import Candidate, Tensors, search, search_plan
from gctr_cli.engine.verdict import Agreement, Verdict, displacement, surface_agreement
from gctr_cli.geometry import split


def _failed(message: str, refusal: str, seed: int, start: float, timings: dict[str, float],
            transform: np.ndarray | None = None) -> RegistrationResult:
    T = np.eye(4) if transform is None else transform
    s, R, t = split(T)
    return RegistrationResult(transform=T, scale=s, rotation=R, translation=t,
                              fitness=0.0, inlier_rmse=float("nan"), n_inliers=0, iterations=0, status="failed",
                              message=message, runtime_s=time.perf_counter() - start, seed=seed, confidence=0.0,
                              timings=timings, refusal=refusal)


@dataclass(frozen=True)
class SearchRun:
    """Stages 1-4 of one pair (:func:`run_search`): the candidates the verdict chooses among, and what
    it needs besides them. Everything in normalised coordinates."""

    norm_source: NormalisedCloud
    norm_target: NormalisedCloud
    source: PreparedCloud
    target: PreparedCloud
    bounds_n: tuple[float, float]  # the configured scale bounds in normalised units
    candidates: list[Candidate]  # one per hypothesis run that found one, in the plan's order
    rng_refine: np.random.Generator  # the verdict's generator (spawned with the others; builds both refinement clouds)
    tensors: Tensors  # the search's tensors by hypothesis (reused by the mirror check's search)


def run_search(source: np.ndarray, target: np.ndarray, cfg: EngineConfig, seed: int,
               timer: StageTimer) -> SearchRun:
    """Validate, normalise and prepare both clouds and run the overlap search (stages 1-4).

    :func:`register` continues with the verdict; developer tools (``data_scripts.settle_margin``)
    score the candidates themselves. Raises :class:`DegenerateCloudError` for clouds the engine
    cannot work on.
    """
    plan = search_plan(cfg)
    ns, nt, src, tgt, rng_refine, rng_overlaps = _prepared_pair(source, target, cfg, seed, timer, len(plan))
    if len(src.salient) < 4 or len(tgt.salient) < 4:
        raise SparseCloudError(len(src.salient), len(tgt.salient), len(ns.points), len(nt.points),
                               cfg.preprocess.max_points)
    # Scale bounds in normalised units: s_orig = s_norm * size_t / size_s.
    lo, hi = cfg.scale_bounds
    ratio = ns.size / nt.size
    bounds_n = (lo * ratio, hi * ratio)
    tensors: Tensors = {}
    candidates = search(src, tgt, plan, rng_overlaps, bounds_n, cfg, timer, tensors)
    return SearchRun(ns, nt, src, tgt, bounds_n, candidates, rng_refine, tensors)


#: the polish's own random stream (its clouds' subsets), apart from the pair's spawned generators so that
#: turning the polish on or off leaves every other draw as it was
POLISH_STREAM = 0x706F6C
#: an answer within this factor of a finite ``scale_bounds`` end is checked by :func:`settle_at_bound`
NEAR_BOUND = 1.25
#: how far beyond a bound the unbounded refinement may end before the answer counts as held there
BOUND_TOLERANCE = 0.005
#: the end of a ``mirrored`` refusal: a flipped axis is one cause; the other is a nearly mirror-symmetric shape
#: seen from two sides that barely overlap (raw bunny scans 180 and 45 degrees apart), where a flipped copy
#: fits at confidence 1 and is just as wrong
MIRROR_ADVICE = ("; either one of the clouds has a flipped axis (a left-handed coordinate system? flip it and "
                 "register again), or the clouds share too little of a nearly mirror-symmetric shape to be "
                 "registered (a flipped copy would fit and be just as wrong)")


def register(source: np.ndarray, target: np.ndarray, config: EngineConfig | Config | None = None, seed: int = 0, *,
             source_normals: np.ndarray | None = None,
             target_normals: np.ndarray | None = None, _confirm: bool = True) -> RegistrationResult:
    """Estimate the similarity mapping ``source`` (N, 3) onto ``target`` (M, 3).

    ``config`` is the engine section (``load_config(...).engine``) or the whole loaded config (its
    engine section is used); None for the defaults. Normals are re-estimated on the working
    (downsampled) clouds, so the optional normal arguments are accepted for API symmetry but not
    required. ``seed`` (a non-negative integer, else a ValueError) seeds every random draw: the same
    inputs, config and seed give the same transform. Returns a result with ``status='failed'`` and a
    message (never raises on data: arrays of another shape, a path or a ragged list are such results
    too) when the inputs are degenerate or the evidence is too weak; a config of another type is a
    TypeError.
    """
    del source_normals, target_normals  # normals are recomputed on the downsampled clouds
    _check_seed(seed)
    if isinstance(config, Config):
        config = config.engine
    if config is not None and not isinstance(config, EngineConfig):
        raise TypeError(f"config must be an EngineConfig (load_config(...).engine) or a Config, "
                        f"got {type(config).__name__}")
    cfg = config if config is not None else EngineConfig()
    start = time.perf_counter()
    timer = StageTimer({})
    try:
        run = run_search(source, target, cfg, seed, timer)
        note = ""
    except SparseCloudError as err:
        # Sparse clouds (a few hundred points over the object): the supervoxels' voxels do not touch, and no
        # supervoxel grows. Coarser ones, once, with the same seed; the verdict judges the answer as always.
        coarse = coarser_supervoxels(cfg)
        if coarse is None:
            return _failed(f"{err}; engine.supervoxel is already as coarse as the retry for sparse clouds "
                           f"({SPARSE_SETTINGS_TEXT})", "invalid_input", seed, start, timer.timings)
        try:
            run = run_search(source, target, coarse, seed, timer)
        except SparseCloudError as again:
            return _failed(f"{err}; with coarser supervoxels for sparse clouds ({SPARSE_SETTINGS_TEXT}) too (source "
                           f"{again.salient[0]}, target {again.salient[1]})", "invalid_input", seed, start,
                           timer.timings)
        cfg = coarse
        note = f"with coarser supervoxels for sparse clouds ({SPARSE_SETTINGS_TEXT}): at the configured ones, {err}"
    except DegenerateCloudError as err:
        return _failed(str(err), "invalid_input", seed, start, timer.timings)
    result = _registered(run, source, target, cfg, seed, start, timer, _confirm)
    if not note:
        return result
    note = f"{'registered' if result.ok else 'tried'} {note}"  # a refused retry was no registration
    return dataclasses.replace(result, message=note if not result.message else f"{result.message}; {note}")


#: the supervoxel settings of the one retry for clouds too sparse for the configured ones: voxels large
#: enough to touch on a cloud of a few hundred points, seeds spread accordingly, single-voxel supervoxels kept
SPARSE_SUPERVOXELS = {"voxel_ratio": 0.05, "seed_ratio": 0.2, "min_voxels": 1}
SPARSE_SETTINGS_TEXT = "engine.supervoxel." + ", ".join(f"{key} {value}" for key, value in SPARSE_SUPERVOXELS.items())


class SparseCloudError(DegenerateCloudError):
    """Too few salient points at the configured supervoxel resolution (:func:`register` retries coarser)."""

    def __init__(self, source_salient: int, target_salient: int, source_points: int, target_points: int,
                 max_points: int | None = None) -> None:
        self.salient = (source_salient, target_salient)
        self._args = (source_salient, target_salient, source_points, target_points, max_points)
        # a working size below the clouds' own is the config's doing, not the clouds'
        working = (f"; the working clouds hold at most engine.preprocess.max_points {max_points} points"
                   if max_points is not None and max_points < max(source_points, target_points) else "")
        super().__init__(f"too few salient points (source {source_salient}, target {target_salient}); the clouds "
                         f"are too small or too sparse for the supervoxel resolution (source {source_points} "
                         f"points, target {target_points}){working}")

    def __reduce__(self) -> tuple[type, tuple[int, int, int, int, int | None]]:  # picklable across processes
        return type(self), self._args


def coarser_supervoxels(cfg: EngineConfig) -> EngineConfig | None:
    """``cfg`` with supervoxels at least as coarse as :data:`SPARSE_SUPERVOXELS` (larger voxels and seed
    spacing, a smaller minimum size), or None when it is that coarse already."""
    sv = cfg.supervoxel
    update = {"voxel_ratio": max(sv.voxel_ratio, SPARSE_SUPERVOXELS["voxel_ratio"]),
              "seed_ratio": max(sv.seed_ratio, SPARSE_SUPERVOXELS["seed_ratio"]),
              "min_voxels": min(sv.min_voxels, SPARSE_SUPERVOXELS["min_voxels"])}
    if all(getattr(sv, key) == value for key, value in update.items()):
        return None
    return cfg.model_copy(update={"supervoxel": sv.model_copy(update=update)})


def _registered(run: SearchRun, source: np.ndarray, target: np.ndarray, cfg: EngineConfig, seed: int, start: float,
                timer: StageTimer, confirm: bool) -> RegistrationResult:
    """Stages 4b-6 of :func:`register` on the search ``run`` of the pair (``source``, ``target``, as given):
    the verdict, the checks and, when ``confirm``, the reverse confirmation and the mirror check."""
    ns, nt, src, tgt, bounds_n, candidates = (run.norm_source, run.norm_target, run.source, run.target,
                                              run.bounds_n, run.candidates)
    refinement: tuple[RefinementCloud, RefinementCloud] | None = None

    def judge(pool: list[Candidate]) -> tuple[np.ndarray, Verdict]:
        """The verdict on ``pool`` (refinement clouds built once, on first use), its time booked."""
        nonlocal refinement
        t = time.perf_counter()
        refine_before = timer.timings.get("refine", 0.0)
        if refinement is None:
            refinement = (RefinementCloud.of(src, ns.points, cfg, run.rng_refine),
                          RefinementCloud.of(tgt, nt.points, cfg, run.rng_refine))
        answer = decide(pool, src, *refinement, cfg, bounds_n, timer)
        # the verdict stage: finer clouds, rival scoring and the final choice (ICP itself is "refine")
        timer.timings["verdict"] = timer.timings.get("verdict", 0.0) + (time.perf_counter() - t) - (
            timer.timings.get("refine", 0.0) - refine_before)
        return answer

    verdict: Verdict | None = None
    if candidates:
        T_n, verdict = judge(candidates)
    halves_below = max(cfg.source_halves_below, cfg.min_confidence) if cfg.source_halves_below > 0 else 0.0
    if verdict is None or verdict.confidence < halves_below or (halves_below > 0 and verdict.support == 0):
        # The first search left the answer in doubt (or would be refused), or no search run ended at the
        # answer (its refinement carried a candidate a long way: a confident answer that nothing else
        # supports was a half-turn of a part-in-whole pair, measured in docs/how-it-works.md): search
        # again from each half of the source (an overlap that is a slab at one end of it), and decide
        # among all candidates.
        extra = half_candidates(ns.points, src, tgt, bounds_n, cfg, seed, timer)
        if extra:
            candidates = candidates + extra
            T_n, verdict = judge(candidates)
    if verdict is None:
        message = "no consistent correspondences found (RANSAC found no valid similarity"
        hint = units_hint(nt.size / ns.size, cfg.scale_bounds)  # the sizes say how far: the ratio when far
        message += f"){hint}" if hint else (f"; if the clouds' units may differ by more than engine.scale_bounds "
                                            f"{list(cfg.scale_bounds)} allows, widen it)")
        return _failed(message, "no_correspondences", seed, start, timer.timings)
    lo, hi = cfg.scale_bounds
    ratio = ns.size / nt.size  # normalised scale per original scale
    T_n, held, free = settle_at_bound(T_n, refinement, cfg, ratio, timer) if refinement else (T_n, "", float("nan"))
    fit = evaluate_fit(src.points, tgt.tree, T_n, cfg.inlier_distance_ratio)
    # The search run that found the answer (the nearest candidate) reports inliers and overlap.
    best = min(candidates, key=lambda c: displacement(T_n, c.transform, src.surface.sample))
    T = denormalise(T_n, ns, nt)
    scale, rotation, translation = split(T)
    status, message, refusal = "ok", "", ""
    if best.n_inliers < cfg.ransac.min_inliers:
        status, refusal = "failed", "weak_evidence"
        message = f"too weak evidence: {best.n_inliers} RANSAC inliers (need {cfg.ransac.min_inliers})"
    elif fit.fitness < cfg.min_fitness:
        status, refusal = "failed", "weak_evidence"
        message = f"too weak evidence: fitness {fit.fitness:.3f} below {cfg.min_fitness}"
    elif not lo * (1.0 - BOUND_TOLERANCE) <= scale <= hi * (1.0 + BOUND_TOLERANCE):
        status, refusal = "failed", "scale_bounds"
        message = f"scale {scale:.4g} outside the configured bounds [{lo}, {hi}]"
    elif verdict.confidence < cfg.min_confidence:
        # held at a bound as well: a lower threshold would refuse it as held, so no threshold accepts it
        status, refusal, message = "failed", "scale_held" if held else "low_confidence", refusal_message(verdict, cfg)
        if held:
            message += "; " + held_message(scale, held, free, (lo, hi), confident=False)
    elif held:
        status, refusal, message = "failed", "scale_held", held_message(scale, held, free, (lo, hi), confident=True)
    if status == "ok" and confirm and verdict.confidence < cfg.verdict.reverse_below:
        t = time.perf_counter()
        moved = reverse_displacement(source, target, cfg, seed, T_n, ns, nt, src.surface.sample)
        timer.add("verdict", t)
        if not moved <= cfg.verdict.distinct_ratio:
            status, refusal, message = "failed", "not_confirmed", (
                f"not confirmed: registered the other way round (target onto source), the pair ends at another "
                f"alignment ({moved:.2f} of the target's size away); at confidence "
                f"{truncated(verdict.confidence)}, below verdict.reverse_below "
                f"{cfg.verdict.reverse_below:.2f}, an answer needs that confirmation")
    if refusal in ("weak_evidence", "low_confidence", "not_confirmed"):  # the others name scale_bounds already
        message += units_hint(nt.size / ns.size, cfg.scale_bounds)
    mirror: dict[str, float] = {}
    if status == "ok" and confirm and cfg.verdict.reflection_check and refinement is not None:
        # A mirror image that fits well (a whole bunny, score 0.4 at confidence 1) passes the full check
        # below, which runs only on poor fits: the answer reflected through the clouds' principal planes.
        t = time.perf_counter()
        answer_score, reflected = reflected_fit(T_n, *refinement, cfg, bounds_n)
        timer.add("verdict", t)
        mirror["reflection_lead"] = reflected - answer_score
        if reflected - answer_score >= cfg.verdict.mirror_margin:
            status, refusal, message = "failed", "mirrored", (
                f"mirrored: the source reflected fits the target better than any rotation of it (score "
                f"{reflected:.2f} against {answer_score:.2f}, the answer reflected through a principal plane of a "
                f"cloud and refined){MIRROR_ADVICE}")
    if status == "ok" and confirm and verdict.score < cfg.verdict.mirror_below:
        # A mirror image (a cloud with a flipped axis) has no right rotation, but the best one can stand out
        # among the other poor ones (confidence 1 on a mirrored bunny): is the source's reflection a better fit?
        t = time.perf_counter()
        cfg_m, timer_m = mirror_config(cfg, best.overlap), StageTimer({})  # the whole check is booked as verdict
        mirrored = _registered(mirrored_run(run, cfg_m, seed, timer_m), np.asarray(source, dtype=float) * MIRROR,
                               target, cfg_m, seed, t, timer_m, False)
        timer.add("verdict", t)
        mirror |= {"mirror_score": mirrored.evidence.get("score", float("nan")),
                  "mirror_confidence": mirrored.confidence, "mirror_ok": float(mirrored.status == "ok")}
        if mirrored.status == "ok" and mirror["mirror_score"] - verdict.score >= cfg.verdict.mirror_margin:
            status, refusal, message = "failed", "mirrored", (
                f"mirrored: the source reflected (x -> -x) fits the target better than any rotation of it (score "
                f"{mirror['mirror_score']:.2f} against {verdict.score:.2f}){MIRROR_ADVICE}")
    polished: dict[str, float] = {}
    if status == "ok" and confirm:
        # Stage 5b, after every check (they judge the verdict's alignment): precision only, on accepted answers.
        T_p, polished = polish(T_n, ns.points, nt.points, cfg, bounds_n, np.random.default_rng([seed, POLISH_STREAM]),
                               timer)
        if polished["polished"]:
            fit = evaluate_fit(src.points, tgt.tree, T_p, cfg.inlier_distance_ratio)
            T = denormalise(T_p, ns, nt)
            scale, rotation, translation = split(T)
    return RegistrationResult(
        transform=T, scale=scale, rotation=rotation, translation=translation, fitness=fit.fitness,
        inlier_rmse=fit.rmse * nt.size, n_inliers=best.n_inliers, iterations=best.iterations, status=status,
        message=message, runtime_s=time.perf_counter() - start, seed=seed, overlap=best.overlap,
        confidence=verdict.confidence, timings=timer.timings,
        evidence={"score": verdict.score, "rival_score": verdict.rival_score,
                  "source_agreement": verdict.agreement.source, "target_agreement": verdict.agreement.target,
                  "source_conflict": verdict.agreement.conflict_source,
                  "target_conflict": verdict.agreement.conflict_target, "support": verdict.support,
                  "relief_confidence": verdict.relief_confidence, **mirror, **polished},
        refusal=refusal,
    )


def mirrored_run(run: SearchRun, cfg: EngineConfig, seed: int, timer: StageTimer) -> SearchRun:
    """The search of the mirror check: ``run``'s prepared clouds with the source reflected (:data:`MIRROR`;
    the target and the scale bounds as they were), searched with ``cfg`` (:func:`mirror_config`). A
    hypothesis the forward search ran reuses its tensor and generator (a reflection changes no triangle
    descriptor: the same tensor, checked entry for entry in the tests); the others get the generators
    ``seed`` gives a search. Preparing the reflected source again would give the same cloud up to the voxel
    grid's alignment, at the cost of preparing both clouds and building the tensor a second time."""
    plan = search_plan(cfg)
    _, _, rng_refine, *rngs = _generators(seed, len(plan))
    ns = run.norm_source
    src = run.source.reflected(MIRROR, cfg)
    candidates = search(src, run.target, plan, rngs, run.bounds_n, cfg, timer, run.tensors)
    return SearchRun(NormalisedCloud(ns.points * MIRROR, ns.centre * MIRROR, ns.size), run.norm_target, src,
                     run.target, run.bounds_n, candidates, rng_refine, run.tensors)


def settle_at_bound(T_n: np.ndarray, refinement: tuple[RefinementCloud, RefinementCloud], cfg: EngineConfig,
                    ratio: float, timer: StageTimer) -> tuple[np.ndarray, str, float]:
    """The answer ``T_n`` (normalised; ``ratio`` = normalised scale per original one) settled against
    ``scale_bounds``: ``(transform, held, scale without bounds)``, ``held`` being ``"lower"``,
    ``"upper"`` or ``""``.

    Every hypothesis and every refinement step keeps within the bounds, so a pair whose true scale lies
    beyond them came back pinned at a bound (before the refinement held the scale there, it stopped a step
    inside: 2-13% off the true scale, turned 2-6°) and was accepted, at confidence 1 for a true scale 5%
    beyond. So an answer within :data:`NEAR_BOUND` of a finite end is refined once more without bounds.
    If that ends beyond the end by more than :data:`BOUND_TOLERANCE`, the answer is held there (refused by
    the caller).
    Otherwise the unbounded refinement is the answer when the verdict's tight test scores it at least
    as well (and ``refine.enabled``): a true scale on a bound (10 for a cm/mm pair) or just beyond came
    back held a step inside it and turned 3-5° (before the refinement held the scale at the bound). The
    refinement's time is booked under ``refine``.
    """
    lo, hi = cfg.scale_bounds
    scale = similarity_scale(T_n) / ratio
    if not (scale < lo * NEAR_BOUND or scale > hi / NEAR_BOUND):
        return T_n, "", float("nan")
    src_ref, tgt_ref = refinement
    t = time.perf_counter()
    T_free = icp(T_n, src_ref, tgt_ref, cfg, (0.0, np.inf))
    timer.add("refine", t)
    free = similarity_scale(T_free) / ratio
    if free < lo * (1.0 - BOUND_TOLERANCE):
        return T_n, "lower", free
    if free > hi * (1.0 + BOUND_TOLERANCE):
        return T_n, "upper", free
    if not cfg.refine.enabled:
        return T_n, "", free
    test = tight_test(src_ref, tgt_ref, similarity_scale(T_n), cfg)
    if tight_agreement(T_free, src_ref, tgt_ref, test).score >= tight_agreement(T_n, src_ref, tgt_ref, test).score:
        return T_free, "", free
    return T_n, "", free


def held_message(scale: float, held: str, free: float, bounds: tuple[float, float], confident: bool) -> str:
    """Why an answer held at the ``held`` end of ``bounds`` is refused (``free``: its scale refined without
    them). Wide bounds are a search range: a scale pinned at one end suggests the true one lies beyond
    (other units), so the message says to widen them. Bounds narrower than ``NEAR_BOUND ** 2`` state a
    known scale (a rigid pair: [0.99, 1.01]): every answer lies near an end, and one that drifts beyond
    it when the scale is freed is an alignment that does not hold at that scale (36 wrong answers on 302 raw
    range scan pairs, at confidence 0.15-0.60, drifted 0.7-35% beyond the bound); widening them would let
    it through. But on noisy clouds a right answer refined with a free scale ends 1.5-4% low,
    so such bounds suit low-noise scans only (docs/config.md, ``configs/rigid.yaml``). Under such bounds
    ``confident`` makes no difference: a low-confidence refusal gets the same words after its own."""
    lo, hi = bounds
    if hi / lo <= NEAR_BOUND ** 2:
        return (f"refined with a free scale, the alignment moves to scale {free:.4g}, beyond the {held} end of "
                f"engine.scale_bounds [{lo}, {hi}] (the answer's scale: {scale:.4g}): it does not hold at the "
                "scale the bounds allow (widen scale_bounds only if the true scale may lie beyond them)")
    if confident:
        return (f"scale {scale:.4g} is held by the {held} end of engine.scale_bounds [{lo}, {hi}]: refined "
                f"without it, the alignment moves to scale {free:.4g} (widen scale_bounds)")
    return (f"its scale {scale:.4g} is held by the {held} end of engine.scale_bounds [{lo}, {hi}] (refined without "
            f"it: {free:.4g}; at this confidence that alone does not show that the units differ: widen "
            "scale_bounds only if they may)")


def mirror_config(cfg: EngineConfig, overlap: float) -> EngineConfig:
    """The config of the mirror check's run, a lighter search: only the answer's overlap hypothesis when it
    was one of ``overlap_candidates`` (a mirror image is found where the answer was), one round of the outer
    loop, no search from the source's halves, two refined finalists and no slides. On the mirrored probe
    pairs it finds the same mirror images as the full search (scores within 0.02); the full search cost 4-5
    times the answer's time. Run by :func:`mirrored_run` on the forward run's clouds and tensors, it costs
    about half of a clean 20k-point pair's time (0.13-0.17 s against 0.22-0.28 s on tuning seed 1's
    `cross`, `real` and `sfm` pairs it ran on)."""
    update: dict[str, object] = {
        "source_halves_below": 0.0,
        "outer": cfg.outer.model_copy(update={"max_iterations": 1}),
        "verdict": cfg.verdict.model_copy(update={"refined_finalists": 2, "slide_steps": (), "turned_finalists": 0}),
    }
    if cfg.overlap == "auto" and any(abs(overlap - r) < 1e-9 for r in cfg.overlap_candidates):
        update["overlap"] = overlap
    return cfg.model_copy(update=update)


#: a size ratio this far beyond a scale bound suggests other units (:func:`units_hint`)
UNITS_FACTOR = 3.0


def units_hint(size_ratio: float, scale_bounds: tuple[float, float]) -> str:
    """What to add to a refusal when the target is far more than ``scale_bounds`` allows larger (or smaller)
    than the source, by more than :data:`UNITS_FACTOR` beyond a bound: clouds in different units (inches
    and metres, 39x) otherwise fail as "too weak evidence" or "low confidence", with nothing that points
    at the scale. Just beyond a bound, unequal extents (a part of a whole, tight bounds for a rigid pair)
    explain the ratio as well."""
    lo, hi = scale_bounds
    if lo / UNITS_FACTOR <= size_ratio <= hi * UNITS_FACTOR:
        return ""
    return (f"; the target is {size_ratio:.3g} times the source's size, far outside engine.scale_bounds "
            f"[{lo}, {hi}]: if their units differ (mm and m: 1000), widen scale_bounds")


def reverse_displacement(source: np.ndarray, target: np.ndarray, cfg: EngineConfig, seed: int, T_n: np.ndarray,
                         ns: NormalisedCloud, nt: NormalisedCloud, sample: np.ndarray) -> float:
    """How far the pair registered the other way round (target onto source, same config and seed), inverted,
    moves the normalised source ``sample`` from the answer ``T_n``: RMS, in normalised target units (inf when
    the reverse run returns no invertible transform). A low-confidence answer that is right is usually found
    from both sides; a coincidental fit of unrelated clouds (a manifest pairing the wrong files) rarely is.
    ``scale_bounds`` hold the source->target scale, so the reverse run gets them inverted (with ``[1.2, 3]``
    as given, it was held at 1.2 and ended half the target's size away from a right answer)."""
    lo, hi = cfg.scale_bounds
    # not re-validated: 1 / inf = 0 is a valid lower bound for the engine, though not for a config file
    inverted = cfg.model_copy(update={"scale_bounds": (1.0 / hi, 1.0 / lo)})
    back = register(target, source, inverted, seed, _confirm=False).transform
    if not (np.all(np.isfinite(back)) and abs(np.linalg.det(back[:3, :3])) > 1e-12):
        return float("inf")
    return displacement(T_n, _normalised(np.linalg.inv(back), ns, nt), sample)


def _check_seed(seed: object) -> None:
    """A ValueError unless ``seed`` is a non-negative integer (``None`` would draw fresh entropy: the
    answer could not be reproduced)."""
    if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or seed < 0:
        raise ValueError(f"seed must be a non-negative integer (every random draw comes from it), got {seed!r}")


def _prepared_pair(source: np.ndarray, target: np.ndarray, cfg: EngineConfig, seed: int, timer: StageTimer,
                   n_extra: int = 0) -> tuple[NormalisedCloud, NormalisedCloud, PreparedCloud, PreparedCloud,
                                               np.random.Generator, list[np.random.Generator]]:
    """Stages 1-2 of both clouds, the verdict's generator and ``n_extra`` more generators (the search's
    hypotheses'): the pair's seed spawns the source's, the target's, the verdict's and then the extra
    generators, in that order, so that :func:`run_search` and the scoring tools below prepare the clouds
    identically."""
    src_raw, tgt_raw = validate_cloud(source, "source"), validate_cloud(target, "target")
    rng_src, rng_tgt, rng_refine, *extra = _generators(seed, n_extra)
    ns, nt = normalise(src_raw), normalise(tgt_raw)
    return (ns, nt, prepare_cloud(ns.points, cfg, rng_src, timer), prepare_cloud(nt.points, cfg, rng_tgt, timer),
            rng_refine, extra)


def _generators(seed: int, n_extra: int) -> list[np.random.Generator]:
    """The pair's generators: the source's, the target's, the verdict's, then ``n_extra`` more (the search's
    hypotheses'), all spawned from ``seed``."""
    return [np.random.default_rng(s) for s in np.random.SeedSequence(seed).spawn(3 + n_extra)]


def _normalised(transform: np.ndarray, ns: NormalisedCloud, nt: NormalisedCloud) -> np.ndarray:
    """A transform between the original clouds as one between their normalised versions."""
    return np.linalg.inv(nt.to_original()) @ np.asarray(transform, dtype=float) @ ns.to_original()


def score_transform(source: np.ndarray, target: np.ndarray, transform: np.ndarray,
                    config: EngineConfig | None = None, seed: int = 0) -> float:
    """The engine's own score of any transform ``transform`` (original coordinates, source -> target).

    Uses the same preparation and the same objective the search ranks its candidates with (surface
    agreement at the inlier distance; the verdict's final score also subtracts conflicts, see
    :mod:`~gctr_cli.engine.verdict`), so comparing the score of the ground truth with the score of the
    engine's answer tells whether a failure is a search miss (truth scores higher), an objective that
    cannot separate them (answer scores higher) or a precision problem (equal within noise).
    """
    _check_seed(seed)
    cfg = config if config is not None else EngineConfig()
    ns, nt, src, tgt, _, _ = _prepared_pair(source, target, cfg, seed, StageTimer({}))
    return surface_agreement(_normalised(transform, ns, nt), src.surface, tgt.surface, cfg.inlier_distance_ratio,
                             cfg.verdict.max_normal_angle_deg).score


def verdict_agreement(source: np.ndarray, target: np.ndarray, transform: np.ndarray,
                      config: EngineConfig | None = None, seed: int = 0) -> Agreement:
    """How the verdict's final test judges any transform (original coordinates, source -> target): the
    shares of each cloud it lays on the other surface and beside it, and its score (agreement less
    conflicts), on the same clouds as :func:`register`'s verdict. The tight tolerances are taken at the
    transform's own scale; ``register`` takes them at the scale of the search's best candidate, so where
    they are widened for noise the two can differ by a few hundredths of score.

    Applied to the ground truth, it tells roughly what the engine can accept: an answer's confidence is
    its score's lead over its best rival (or over 0) divided by ``verdict.full_margin``, and a right
    answer scores about what the truth scores (its refinement may fit the noise a little better), so a
    pair whose truth scores ``x`` can be accepted at about confidence ``x / full_margin`` at best
    (``data_scripts.truth_score``).
    """
    cfg = config if config is not None else EngineConfig()
    ns, nt, src, tgt, rng_refine, _ = _prepared_pair(source, target, cfg, seed, StageTimer({}))
    src_ref = RefinementCloud.of(src, ns.points, cfg, rng_refine)
    tgt_ref = RefinementCloud.of(tgt, nt.points, cfg, rng_refine)
    T_n = _normalised(transform, ns, nt)
    return tight_agreement(T_n, src_ref, tgt_ref, tight_test(src_ref, tgt_ref, similarity_scale(T_n), cfg))
