"""Typed, validated configuration for gctr (engine, success thresholds, batch settings).

Every length in the engine section is *relative* to a cloud's own size (its robust diameter),
because the scale between the two clouds is unknown until registration is done.

Load with :func:`load_config`; an unknown key or a value of the wrong type raises
:class:`ConfigError` whose message names the key path and the expected type.
"""

from __future__ import annotations

import functools
import typing
from pathlib import Path
from typing import Annotated, Any, Literal

from pydantic import BaseModel, ConfigDict, Field, ValidationError, field_validator, model_validator

from gctr_cli.methods import METHODS

#: the accepted values of ``method``: the names of :data:`gctr_cli.methods.REGISTRY`, nothing to keep in sync
MethodName = Literal[METHODS]  # type: ignore[valid-type]


class ConfigError(ValueError):
    """A configuration file is unreadable, not valid YAML, or does not match the schema."""


class _Strict(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True, validate_default=True, allow_inf_nan=False)

    @field_validator("*", mode="before")
    @classmethod
    def _no_boolean_for_a_number(cls, value: Any, info: Any) -> Any:
        """``iterations: true`` is a mistake, not 1: where a field takes numbers, a boolean (YAML's
        true/false, yes/no, on/off) is refused, alone or in a list, although pydantic would convert it."""
        annotation = cls.model_fields[info.field_name].annotation
        values = value if isinstance(value, (list, tuple)) and typing.get_origin(annotation) is tuple else [value]
        if any(isinstance(v, bool) for v in values) and _takes_numbers(annotation):
            raise ValueError("expected a number, got a boolean")
        return value


def _takes_numbers(annotation: Any) -> bool:
    """Whether a field annotation accepts int or float (alone, in a union, or as tuple items)."""
    if annotation in (int, float):
        return True
    return any(_takes_numbers(arg) for arg in typing.get_args(annotation) if arg is not Ellipsis)


class PreprocessConfig(_Strict):
    """Early downsampling: clouds are reduced to a working size before anything quadratic."""

    max_points: int = Field(6000, ge=100, description="working size of each cloud (voxel downsampling)")
    normal_neighbours: int = Field(30, ge=5, le=100, description="k of the kNN used for PCA normals")
    drop_isolated: bool = Field(
        True, description="drop voxels no supervoxel reaches (outliers) before refinement and scoring")


class SupervoxelConfig(_Strict):
    """VCCS-like supervoxels; their centroids are the salient points."""

    voxel_ratio: float = Field(0.02, gt=0, lt=0.5, description="voxel size / robust cloud diameter")
    seed_ratio: float = Field(0.12, gt=0, lt=1, description="seed spacing / robust cloud diameter")
    spatial_weight: float = Field(1.0, ge=0)
    normal_weight: float = Field(1.0, ge=0)
    iterations: int = Field(3, ge=1, le=20, description="seed refinement rounds")
    min_voxels: int = Field(2, ge=1, description="drop supervoxels with fewer voxels")
    max_salient: int = Field(150, ge=10, description="cap on salient points per cloud")


class TripletConfig(_Strict):
    """Random wide-baseline triangles on the salient points."""

    n_source: int = Field(1500, ge=10, description="source triangles per pair")
    n_target: int = Field(25000, ge=10, description="target triangles per pair")
    min_edge_ratio: float = Field(0.5, gt=0, le=1, description="edges >= ratio * overlap-region diameter (sqrt(r))")
    max_edge_ratio: float = Field(
        1.0, gt=0, description="edges <= ratio * overlap-region diameter when the region is a part of the cloud")
    min_angle_deg: float = Field(12.0, ge=0, lt=60, description="reject near-degenerate triangles")


class TensorConfig(_Strict):
    """Sparse third-order tensor from k nearest neighbours in descriptor space."""

    knn: int = Field(50, ge=1, le=1000, description="target triangles matched per source triangle")
    knn_eps: float = Field(
        0.0, ge=0,
        description="approximate neighbour search: neighbours within (1 + eps) of the exact k-th distance; 0 = exact")
    normal_weight: float = Field(
        1.0, ge=0, description="weight of the vertex-normal terms of the descriptor; 0 = angles only")
    sigma: float = Field(0.0, ge=0, description="descriptor bandwidth; 0 = mean kNN distance")
    first_order_weight: float = Field(1.0, ge=0, description="weight of the point-to-point term")
    scale_filter: bool = Field(
        True, description="drop triangle matches whose perimeter ratio the overlap's scale prior rules out")
    first_order_sigma: float = Field(0.05, gt=0, description="point-term bandwidth / robust diameter")


class PowerIterationConfig(_Strict):
    iterations: int = Field(8, ge=1, le=1000)
    tol: float = Field(1e-6, gt=0)
    normalisation_rounds: int = Field(3, ge=0, le=50, description="row/column L2 normalisations per step")


class RansacConfig(_Strict):
    iterations: int = Field(1500, ge=1, description="hypotheses from the best-supported tensor entries")
    random_samples: int = Field(750, ge=0, description="extra hypotheses drawn from the soft assignment")
    verify_top: int = Field(200, ge=1, description="best hypotheses re-ranked by dense symmetric fitness")
    refine_fraction: float = Field(0.25, gt=0, le=1, description="share of hypotheses once a transform exists")
    candidates: int = Field(3, ge=1, le=10, description="targets per source point for the random samples")
    inlier_ratio: float = Field(0.05, gt=0, lt=1, description="salient inlier distance / robust diameter")
    min_inliers: int = Field(6, ge=3, description="fewer inliers = too weak evidence: failed status")


class OuterLoopConfig(_Strict):
    max_iterations: int = Field(3, ge=1, le=50)
    tol: float = Field(0.002, gt=0, description="stop when salient points move less (RMS, / diameter)")
    settle_support: int = Field(
        2, ge=0, description="stop the overlap search once this many hypotheses found the same transform; 0 = never")
    settle_agreement: float = Field(0.5, ge=0, le=1, description="... and its surface agreement is at least this")
    settle_alone: float = Field(
        0.52, ge=0, le=1, description="stop the search after a hypothesis whose surface agreement reaches this; "
                                     "1 = never (with settle_full 1)")
    settle_full: float = Field(
        0.45, ge=0, le=1, description="... the lower of this and settle_alone for the full-overlap hypothesis "
                                     "(overlap 1 in overlap_candidates, run first); 1 = no lower threshold for it")
    settle_round: float = Field(
        0.5, ge=0, le=1, description="stop a hypothesis' outer loop after a round whose best surface agreement "
                                     "reaches this (later rounds only polish what the verdict's ICP refines); "
                                     "1 = never")


class RefineConfig(_Strict):
    """Refinement of the verdict's finalists: scaled ICP (point-to-plane, dropping matches with incompatible
    normals); a finalist keeps the refined transform only if its tight surface agreement does not drop."""

    enabled: bool = True
    method: Literal["point_to_plane", "point_to_point"] = "point_to_plane"
    symmetric: bool = Field(
        True, description="point_to_plane also matches the target back onto the source (two-way; one-way ICP "
                          "shrinks the moving cloud on noisy data)")
    iterations: int = Field(
        15, ge=1, le=500, description="ICP iterations; the trimming distance shrinks geometrically from start_ratio "
                                      "to end_ratio over them (10 measured: faster, but wrong answers' confidence "
                                      "rose to 0.55 on tuning seed 1)")
    max_matches: int = Field(
        2000, ge=0, description="point_to_plane: points of each cloud moved and matched per iteration (every k-th); "
                                "0 = all")
    start_ratio: float = Field(
        0.08, gt=0, description="initial trimming distance / robust diameter of the smaller cloud")
    end_ratio: float = Field(0.02, gt=0, description="final trimming distance / robust diameter of the smaller cloud")
    voxel_ratio: float = Field(
        0.0, ge=0, lt=0.5,
        description="voxel size of the refinement clouds / robust diameter; 0 = refine on the working clouds")
    max_points: int = Field(12000, ge=100, description="working size of each refinement cloud")


class PolishConfig(_Strict):
    """The answer's last ICP on finer clouds than the verdict's, down to a trimming distance set by the
    clouds' own noise (gctr_cli.engine.polish): on clouds with little noise the verdict's working clouds
    leave errors of a few degrees that the data can resolve. It never changes which alignment is chosen. Off by
    default (it costs about 0.015 s a pair even where its noise gate skips it, 0.1-0.25 s where it runs, and the
    speed goal of issue 10 has little room for that); on in configs/scene.yaml and configs/rigid.yaml."""

    enabled: bool = False
    voxel_ratio: float = Field(0.0025, gt=0, lt=0.5, description="voxel size of the polish clouds / robust diameter")
    max_points: int = Field(15000, ge=100, description="size of each polish cloud, on which the noise is measured")
    icp_points: int = Field(6000, ge=100, description="points of each polish cloud the ICP runs on (a seeded subset)")
    iterations: int = Field(15, ge=1, le=500, description="ICP iterations (trimming shrinks geometrically)")
    end_ratio: float = Field(0.005, gt=0, description="final trimming distance / robust diameter of the smaller cloud")
    noise_factor: float = Field(
        3.0, ge=0, description="... at least this times the clouds' combined noise (25th-percentile roughness)")
    max_end_share: float = Field(
        0.5, gt=0, le=1, description="runs only where that final distance is at most this share of the refinement's "
                                     "end distance (refine.end_ratio): not on noisy clouds")
    max_matches: int = Field(1500, ge=0, description="points of each cloud moved and matched per iteration; 0 = all")


class VerdictConfig(_Strict):
    """How candidates are ranked and how sure the engine is (see gctr_cli.engine.verdict)."""

    sample_points: int = Field(800, ge=50, description="points of each cloud moved and looked up per candidate")
    finalists: int = Field(10, ge=1, description="hypotheses per round scored by surface agreement")
    max_normal_angle_deg: float = Field(30.0, gt=0, le=90, description="normals agree below this angle")
    distinct_ratio: float = Field(
        0.1, gt=0, description="finalists differ when they move the source by more (RMS / robust diameter); "
                               "a rival must move the data the answer aligns by more")
    refined_finalists: int = Field(
        6, ge=1, description="distinct transforms refined and compared at the tight tolerances")
    rival_pool: int = Field(30, ge=0, description="best unrefined transforms of the search also checked as rivals")
    tight_distance_ratio: float = Field(
        0.02, gt=0, lt=1, description="final comparison: distance / robust diameter of the smaller cloud")
    tight_noise_factor: float = Field(
        1.0, ge=0, le=10,
        description="... at least this times the clouds' combined surface roughness, the normal angle "
                    "widened alike (noisy clouds); 0 = fixed")
    tight_normal_angle_deg: float = Field(
        20.0, gt=0, le=90, description="final comparison: normals agree below this angle")
    full_margin: float = Field(
        0.25, gt=0, le=1, description="lead over the best distinct rival at which confidence reaches 1")
    reverse_below: float = Field(
        0.3, ge=0, le=1,
        description="an answer accepted below this confidence is registered the other way round (target onto "
                    "source) and refused unless that ends at the same alignment (within distinct_ratio); 0 = off")
    mirror_below: float = Field(
        0.3, ge=0, le=1,
        description="an accepted answer whose score (the verdict's surface agreement) is below this is also "
                    "registered with the source mirrored, and refused when the mirror image fits clearly better "
                    "(mirror_margin): the clouds' axis conventions differ (a flipped axis); 0 = off")
    mirror_margin: float = Field(
        0.1, ge=0, le=1, description="... the lead of the mirrored source's score over the answer's that refuses it")
    reflection_check: bool = Field(
        True,
        description="every accepted answer is also reflected through the principal planes of both clouds and the "
                    "best reflection refined when it agrees well; if it scores mirror_margin more than the answer, "
                    "the pair is refused as mirrored (a mirror image that fits well, which the check above does not "
                    "look at); false = off")
    full_margin_points: int = Field(
        800, ge=0,
        description="verdict samples of fewer points (sparse clouds) need a larger lead: the confidence is "
                    "multiplied by sqrt(n / this) for a smaller sample of n points; 0 = off")
    ambiguity_ratio: float = Field(
        0.8, gt=0, le=1,
        description="a refused answer is called ambiguous when its rival reaches this share of its score")
    normal_balance: float = Field(
        0.5, ge=0, le=1,
        description="agreement weights each point by (points sharing its normal direction)^-this; 0 = all equal")
    conflict_weight: float = Field(
        0.25, ge=0, le=2,
        description="final comparison: each point that lands near the other cloud but not on its surface costs "
                    "this much of an agreeing point; 0 = off")
    conflict_ratio: float = Field(
        0.1, gt=0, lt=1, description="... 'near': distance / robust diameter of the smaller cloud")
    height_weight: float = Field(
        0.5, ge=0, le=2,
        description="confidence: weight of the relief agreement over the target's dominant plane "
                    "(gctr_cli.engine.height) in a second lead, which can only raise the confidence; 0 = off")
    height_full_margin: float = Field(
        0.5, gt=0, le=2, description="... that lead at which the confidence reaches 1")
    height_cell_ratio: float = Field(0.04, gt=0, lt=1, description="... its cells' side / robust target diameter")
    height_tolerance_ratio: float = Field(
        0.01, gt=0, lt=1, description="... heights within this (/ robust target diameter) agree")
    slide_steps: tuple[Annotated[float, Field(gt=0, lt=1)], ...] = Field(
        (0.1, 0.2),
        description="an answer short of confidence 1 is also tried slid both ways by these shares of the smaller "
                    "cloud along the direction its surface contact constrains least, refined; [] = off")
    turned_finalists: int = Field(
        2, ge=0, le=6,
        description="every answer is also turned half a turn about the principal axes of both clouds, and up to "
                    "this many distinct turns that agree well are refined and judged as finalists: a symmetric "
                    "shape (a box, a cylinder, a patch that fits turned) has a rival the search may not have proposed; "
                    "0 = off")
    slide_free_ratio: float = Field(
        0.05, ge=0, lt=1,
        description="... and so is a confident answer whose contact leaves a direction nearly free: the smallest "
                    "eigenvalue of the contact normals' scatter below this share of the largest (a cylinder's "
                    "axis, the line where two walls meet); 0 = only answers short of confidence 1")


class EngineConfig(_Strict):
    """All parameters of the GCTR engine."""

    preprocess: PreprocessConfig = PreprocessConfig()
    supervoxel: SupervoxelConfig = SupervoxelConfig()
    triplets: TripletConfig = TripletConfig()
    tensor: TensorConfig = TensorConfig()
    power_iteration: PowerIterationConfig = PowerIterationConfig()
    ransac: RansacConfig = RansacConfig()
    outer: OuterLoopConfig = OuterLoopConfig()
    refine: RefineConfig = RefineConfig()
    polish: PolishConfig = PolishConfig()
    verdict: VerdictConfig = VerdictConfig()
    overlap: Literal["auto"] | float = Field(
        "auto", description="'auto' searches overlap_candidates, largest first, then part_regions")
    overlap_candidates: tuple[float, ...] = Field((0.25, 0.5, 0.75, 1.0), description="ratios tried by 'auto'")
    part_regions: tuple[float, ...] = Field(
        (0.45,), description="'auto' also tries one cloud as a part of the other: the part's diameter / the whole's")
    source_halves_below: float = Field(
        0.4, ge=0, le=1,
        description="below this confidence of the first answer, search again from each half of the source (split "
        "at the median along its principal axes): finds an overlap that is a slab at one end of the source; "
        "it also runs below min_confidence, so an answer is not refused without it, and whatever the confidence "
        "when no search run ended at the answer (support 0); 0 = never (then use min_confidence >= 0.4: the "
        "default threshold counts on this search)")
    scale_method: Literal["auto", "edge_ratio", "umeyama"] = "auto"
    scale_bounds: tuple[float, Annotated[float, Field(allow_inf_nan=True)]] = Field(
        (0.1, 10.0), description="accepted range of the source->target scale (high may be .inf: no upper bound); "
        "an answer held by a bound is refused: the true scale lies beyond it")
    inlier_distance_ratio: float = Field(0.03, gt=0, lt=1, description="fitness distance / robust target diameter")
    min_fitness: float = Field(0.05, ge=0, le=1, description="below this the pair is reported failed")
    min_confidence: float = Field(
        0.15, ge=0, le=1,
        description="below this confidence the pair is reported failed (see bench/ENGINE.md for the trade-off)")

    @field_validator("overlap")
    @classmethod
    def _overlap_range(cls, value: Any) -> Any:
        if value != "auto" and not 0.0 < float(value) <= 1.0:
            raise ValueError("overlap must be 'auto' or a number in (0, 1]")
        return value

    @field_validator("overlap_candidates")
    @classmethod
    def _candidates_range(cls, value: tuple[float, ...]) -> tuple[float, ...]:
        if not value or any(not 0.0 < v <= 1.0 for v in value):
            raise ValueError("overlap_candidates must be a non-empty list of numbers in (0, 1]")
        return value

    @field_validator("part_regions")
    @classmethod
    def _part_range(cls, value: tuple[float, ...]) -> tuple[float, ...]:
        if any(not 0.0 < v < 1.0 for v in value):
            raise ValueError("part_regions must be numbers in (0, 1)")
        return value

    @field_validator("scale_bounds")
    @classmethod
    def _bounds_order(cls, value: tuple[float, float]) -> tuple[float, float]:
        if not 0.0 < value[0] < value[1]:  # also refuses a NaN high
            raise ValueError("scale_bounds must be [low, high] with 0 < low < high")
        if value[1] < value[0] * 1.002:  # [1, 1.0001] gave confident answers turned 6-12°
            raise ValueError("scale_bounds narrower than 0.2% (high < 1.002 x low) leave the search and the "
                             "refinement no room to move (their scale estimates scatter by about 1e-4); for a "
                             "pair known to be rigid use [0.99, 1.01]")
        return value


class FeatureConfig(_Strict):
    """Voxel downsampling, normals and FPFH features of fpfh_ransac and fgr (Open3D's tutorial recipe)."""

    voxel_ratio: float = Field(0.02, gt=0, lt=0.5, description="voxel size / bbox diagonal (after normalisation)")
    normal_radius_factor: float = Field(2.0, gt=0, description="normal estimation radius / voxel size")
    normal_max_nn: int = Field(30, ge=3, description="max neighbours for normal estimation")
    feature_radius_factor: float = Field(5.0, gt=0, description="FPFH radius / voxel size")
    feature_max_nn: int = Field(100, ge=3, description="max neighbours for FPFH")


class BaselineRansacConfig(_Strict):
    """Open3D registration_ransac_based_on_feature_matching (fpfh_ransac)."""

    max_iterations: int = Field(100000, ge=1, description="RANSAC hypotheses at most")
    confidence: float = Field(0.999, gt=0, lt=1, description="early stop confidence")
    distance_factor: float = Field(1.5, gt=0, description="inlier distance / voxel size (also the distance checker)")
    edge_length_ratio: float = Field(0.9, gt=0, lt=1, description="edge-length checker similarity threshold")
    ransac_n: int = Field(3, ge=3, le=10, description="correspondences per hypothesis")
    with_scaling: bool = Field(True, description="estimate a scale in each hypothesis (normalisation is approximate)")


class BaselineFgrConfig(_Strict):
    """Open3D registration_fgr_based_on_feature_matching (fgr)."""

    distance_factor: float = Field(0.5, gt=0, description="maximum correspondence distance / voxel size")
    iterations: int = Field(64, ge=1, description="FGR graduated non-convexity iterations")
    tuple_scale: float = Field(0.95, gt=0, lt=1, description="tuple test similarity threshold")
    max_tuples: int = Field(1000, ge=1, description="maximum tuple count")


class BaselineIcpConfig(_Strict):
    """Open3D point-to-point ICP with scale estimation: the icp method, and the refinement of fpfh_ransac/fgr."""

    voxel_ratio: float = Field(0.01, ge=0, lt=0.5, description="voxel size / bbox diagonal; 0 = all points")
    iterations: int = Field(100, ge=1, le=10000, description="maximum ICP iterations")
    threshold_ratio: float = Field(0.05, gt=0, description="icp method: max correspondence distance / bbox diagonal")
    refine_threshold_ratio: float = Field(
        0.02, gt=0, description="refinement after fpfh_ransac/fgr: same, / bbox diagonal")


class BaselineCpdConfig(_Strict):
    """Rigid Coherent Point Drift with scale (Myronenko & Song 2010), numpy."""

    w: float = Field(0.1, ge=0, lt=1, description="weight of the uniform outlier component")
    max_points: int = Field(1500, ge=10, le=20000, description="random subsample of each cloud (memory ~ n^2)")
    max_iterations: int = Field(150, ge=1, le=10000, description="EM iterations at most")
    tol: float = Field(1e-6, gt=0, description="stop when the relative change of the EM objective is below")


class BaselineKissConfig(_Strict):
    """KISS-Matcher (Lim et al. 2025; optional package kiss-matcher): Faster-PFH, ROBIN pruning, GNC solver.

    It is tuned for metric scenes: the normalised clouds (bounding-box diagonal 1) are scaled to a
    diagonal of ``metric_diagonal`` "metres" before the call, and the scale is undone afterwards.
    Its voxel must be at least 5 mm (it throws below); its clamping of noise bounds above 1 m (a heuristic
    for large maps) is switched off, the bounds are voxel x gains."""

    metric_diagonal: float = Field(
        20.0, gt=0, description="bbox diagonal the clouds are scaled to before the call (metres)")
    voxel_ratio: float = Field(0.02, gt=0, lt=0.5, description="voxel size / bbox diagonal (0.4 m at a 20 m diagonal)")
    normal_radius_factor: float = Field(3.0, gt=0, description="normal estimation radius / voxel size")
    feature_radius_factor: float = Field(5.0, gt=0, description="Faster-PFH radius / voxel size")
    robin_noise_bound_gain: float = Field(1.0, gt=0, description="ROBIN pruning noise bound / voxel size")
    solver_noise_bound_gain: float = Field(
        0.75, gt=0, description="GNC solver noise bound / voxel size (<= the ROBIN gain)")
    max_correspondences: int = Field(5000, ge=10, description="feature correspondences kept at most")
    use_quatro: bool = Field(
        False, description="Quatro solver (4-DoF, gravity-aligned scenes) instead of the 6-DoF GNC")
    min_inliers: int = Field(
        3, ge=3, description="fewer final inliers (or an invalid solution): the method reports failure")

    @model_validator(mode="after")
    def _metric_limits(self) -> BaselineKissConfig:
        voxel = self.voxel_ratio * self.metric_diagonal
        if voxel < 0.005:
            raise ValueError(f"voxel_ratio x metric_diagonal = {voxel:.4g} m is below KISS-Matcher's 5 mm limit")
        if self.solver_noise_bound_gain > self.robin_noise_bound_gain:
            raise ValueError("solver_noise_bound_gain must not exceed robin_noise_bound_gain")
        return self


class BaselineConfig(_Strict):
    """Comparison methods (method: icp | fpfh_ransac | fgr | cpd | kiss_matcher). Each removes outliers, aligns the
    centroids and scales the source by the ratio of bounding-box diagonals (the paper's protocol for comparison
    methods)."""

    features: FeatureConfig = FeatureConfig()
    ransac: BaselineRansacConfig = BaselineRansacConfig()
    fgr: BaselineFgrConfig = BaselineFgrConfig()
    icp: BaselineIcpConfig = BaselineIcpConfig()
    cpd: BaselineCpdConfig = BaselineCpdConfig()
    kiss_matcher: BaselineKissConfig = BaselineKissConfig()
    outlier_removal: Literal["statistical", "none"] = Field(
        "statistical", description="clean both clouds first (Open3D remove_statistical_outlier)")
    outlier_neighbours: int = Field(20, ge=2, description="statistical outlier removal: neighbours")
    outlier_std_ratio: float = Field(2.0, gt=0, description="statistical outlier removal: std ratio")
    inlier_distance_ratio: float = Field(0.03, gt=0, lt=1, description="fitness distance / target bbox diagonal")
    min_fitness: float = Field(0.05, ge=0, le=1, description="below this the pair is reported failed")


class SuccessConfig(_Strict):
    """Thresholds that decide the `success` column of tm_errors.csv."""

    rotation_deg: float = Field(5.0, gt=0)
    translation_rel: float = Field(0.05, gt=0, description="translation error / target bbox diagonal")
    scale: float = Field(0.05, gt=0, description="|s_est / s_gt - 1|")


class BatchConfig(_Strict):
    workers: int = Field(0, ge=0, description="worker processes; 0 = one per core")
    time_limit_s: float = Field(600.0, gt=0, description="per-pair time limit")


class Config(_Strict):
    """The whole configuration file."""

    seed: int = Field(0, ge=0, description="base seed; each pair's seed derives from it and the pair id")
    method: MethodName = Field(
        "gctr", description="gctr, or a comparison method configured in the baselines section")
    engine: EngineConfig = EngineConfig()
    baselines: BaselineConfig = BaselineConfig()
    success: SuccessConfig = SuccessConfig()
    batch: BatchConfig = BatchConfig()

    @model_validator(mode="after")
    def _refine_ratios(self) -> Config:
        r = self.engine.refine
        if r.end_ratio > r.start_ratio:
            raise ValueError("engine.refine.end_ratio must not exceed engine.refine.start_ratio")
        return self


def _format_validation_error(err: ValidationError, source: str) -> str:
    lines = [f"invalid config {source}:"]
    for e in err.errors():
        path = ".".join(str(p) for p in e["loc"]) or "(top level)"
        if e["type"] == "extra_forbidden":
            lines.append(f"  {path}: unknown key")
        elif e["type"] == "value_error" and isinstance(e.get("input"), dict):
            # a check across the keys of a section: its message names them; the input is the whole section
            message = e["msg"].removeprefix("Value error, ")
            lines.append(f"  {message}" if not e["loc"] else f"  {path}: {message}")
        else:
            lines.append(f"  {path}: {e['msg']} (got {e.get('input')!r})")
    return "\n".join(lines)


def config_from_dict(data: dict[str, Any] | None, source: str = "<dict>") -> Config:
    """Validate a plain mapping (e.g. parsed YAML) into a :class:`Config`."""
    if data is None:
        data = {}
    if not isinstance(data, dict):
        raise ConfigError(f"invalid config {source}: top level must be a mapping, got {type(data).__name__}")
    try:
        return Config.model_validate(data)
    except ValidationError as err:
        raise ConfigError(_format_validation_error(err, source)) from None


def load_config(path: str | Path | None) -> Config:
    """Read and validate a YAML config; ``None`` gives the defaults."""
    if path is None:
        return Config()
    p = Path(path)
    return config_from_dict(read_config_yaml(p), str(p))


def read_config_yaml(path: str | Path) -> Any:
    """The parsed YAML of the config file ``path``, not yet validated (:func:`config_from_dict` does that);
    a :class:`ConfigError` naming the file, and the line and column where known, when it cannot be read,
    is not UTF-8 text or not YAML, or gives a key twice in one mapping. Shared by the CLI and the
    benchmark scripts (which apply ``--set`` overrides before validating)."""
    p = Path(path)
    if not p.exists():
        raise ConfigError(f"config file {p} does not exist")
    if not p.is_file():
        raise ConfigError(f"config file {p} is not a regular file (a folder?)")
    import yaml  # here, not at the top: `gctr register` without -c never reads YAML

    try:
        text = p.read_text(encoding="utf-8").removeprefix("\ufeff")  # a BOM is not part of line 1's columns
    except UnicodeDecodeError as err:
        raise ConfigError(f"config file {p} is not UTF-8 text (bad byte at offset {err.start}); "
                          "is it a YAML file?") from None
    except OSError as err:
        raise ConfigError(f"cannot read config file {p}: {err.strerror or err}") from None
    try:
        data = yaml.load(text, Loader=_unique_key_loader())  # a SafeLoader subclass
    except yaml.MarkedYAMLError as err:
        mark, problem = err.problem_mark, err.problem
        if mark is not None and err.context_mark is not None and mark.index >= len(text.rstrip()):
            # found missing only at the end of the file (line 5 of a 4-line file): the line it belongs to
            mark, problem = err.context_mark, f"{err.context}, {err.problem}"
        where = f" (line {mark.line + 1}, column {mark.column + 1})" if mark is not None else ""
        raise ConfigError(f"config file {p} is not valid YAML{where}: {problem}") from None
    except yaml.reader.ReaderError as err:  # a control character (NUL, \x01, ...): no mark, a character offset
        line = text.count("\n", 0, err.position) + 1
        column = err.position - (text.rfind("\n", 0, err.position) + 1) + 1
        char = err.character if isinstance(err.character, str) else chr(err.character)
        raise ConfigError(f"config file {p} is not valid YAML (line {line}, column {column}): control character "
                          f"{ord(char):#04x} is not allowed; is it a YAML file?") from None
    except yaml.YAMLError as err:
        raise ConfigError(f"config file {p} is not valid YAML: {err}") from None
    return data


@functools.cache
def _unique_key_loader() -> type:
    """A YAML SafeLoader that rejects a key given twice in one mapping (plain YAML keeps the last one,
    so a second ``engine:`` section would silently replace the first)."""
    import yaml

    class UniqueKeyLoader(yaml.SafeLoader):
        def construct_mapping(self, node: Any, deep: bool = False) -> dict:
            seen: set = set()
            for key_node, _ in node.value:  # the mapping's own keys: merged ones (<<) may be overridden
                if not isinstance(key_node, yaml.ScalarNode) or key_node.tag == "tag:yaml.org,2002:merge":
                    continue
                key = self.construct_object(key_node, deep=deep)
                if key in seen:
                    raise yaml.constructor.ConstructorError(
                        None, None, f"key {key!r} is given twice", key_node.start_mark)
                seen.add(key)
            return super().construct_mapping(node, deep=deep)

    return UniqueKeyLoader


def config_to_yaml(config: Config) -> str:
    """Serialise a resolved config (all defaults filled in) as YAML."""
    data = config.model_dump(mode="json")
    import yaml

    return yaml.safe_dump(data, sort_keys=False)


def flatten_dict(data: Any, prefix: str = "") -> dict[str, Any]:
    """Nested mapping -> ``{"a.b.c": value}`` (used to compare and fingerprint configs)."""
    if isinstance(data, dict):
        out: dict[str, Any] = {}
        for k, v in data.items():
            out.update(flatten_dict(v, f"{prefix}{k}."))
        return out
    return {prefix[:-1]: data}
