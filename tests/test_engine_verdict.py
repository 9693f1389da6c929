"""The engine's verdict (issue 9): partial overlap as a first-class case, photogrammetry-like data, and
an honest ``failed`` instead of a confident wrong matrix.

End-to-end cases are built from the shipped models with the benchmark generator's own pair makers
(``data_scripts.make_benchmark``), so the ground truth is exact; every case is seeded.
"""

from __future__ import annotations

import functools
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from data_scripts.make_benchmark import make_lowoverlap_pair, make_part_pair, make_sfm_pair
from data_scripts.probe_pairs import sparse_pair
from gctr_cli.config import EngineConfig
from gctr_cli.engine import register, score_transform
from gctr_cli.engine.halves import source_halves
from gctr_cli.engine.verdict import (
    Agreement,
    SharedData,
    Surface,
    confidence,
    displacement,
    normal_space_weights,
    sample_weight,
    shared_displacement,
    surface_agreement,
)
from gctr_cli.geometry import apply
from gctr_cli.io import load_point_cloud
from gctr_cli.metrics import transform_errors

pytestmark = pytest.mark.engine

MODELS = Path(__file__).resolve().parent.parent / "data" / "models"


@functools.cache
def _model(name: str) -> np.ndarray:
    return np.asarray(load_point_cloud(MODELS / f"{name}.ply"), dtype=float)


def _errors(T_est: np.ndarray, T_gt: np.ndarray, source: np.ndarray, target: np.ndarray):
    diag = float(np.linalg.norm(target.max(axis=0) - target.min(axis=0)))
    return transform_errors(T_est, T_gt, diag, source.mean(axis=0))


def _assert_correct(res, T_gt, source, target):
    err = _errors(res.transform, T_gt, source, target)
    assert res.status == "ok", res.message
    assert err.rot_err_deg < 2.0 and err.scale_err < 0.02 and err.trans_err_rel < 0.02, err
    assert cfg_default().min_confidence <= res.confidence <= 1.0


def cfg_default() -> EngineConfig:
    return EngineConfig()


# ---------------------------------------------------------------------------------------- the measures
def _sphere(n: int, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    v = rng.normal(size=(n, 3))
    v /= np.linalg.norm(v, axis=1, keepdims=True)
    return v, v.copy()  # points on the unit sphere, normals = positions


def _surface(points: np.ndarray, normals: np.ndarray, n_sample: int = 400) -> Surface:
    from scipy.spatial import cKDTree

    return Surface.build(points, normals, cKDTree(points), n_sample, normal_balance=0.0)


def test_surface_agreement_counts_proximity_and_normals():
    rng = np.random.default_rng(0)
    pts, nrm = _sphere(4000, rng)
    half = pts[:, 0] > 0  # the target is the +x half of the sphere
    src, tgt = _surface(pts, nrm), _surface(pts[half], nrm[half])
    a = surface_agreement(np.eye(4), src, tgt, distance=0.05)
    # half of the source lies on the target; all of the target lies on the source
    assert a.source == pytest.approx(0.5, abs=0.05)
    assert a.target == pytest.approx(1.0, abs=0.01)
    assert a.score == pytest.approx(0.5 * (a.source + a.target))
    # the same points with normals turned 90 degrees agree nowhere
    turned = np.cross(nrm, np.array([0.0, 0.0, 1.0]))
    turned /= np.maximum(np.linalg.norm(turned, axis=1, keepdims=True), 1e-12)
    far = np.abs(turned[:, 2]) < 0.5  # avoid the poles, where the cross product degenerates
    a2 = surface_agreement(np.eye(4), _surface(pts[far], turned[far]), _surface(pts[far], nrm[far]), 0.05)
    assert a2.score < 0.1
    # scale is handled both ways: a sphere of radius 2 mapped by s = 0.5 matches the unit sphere
    T = np.diag([0.5, 0.5, 0.5, 1.0])
    a3 = surface_agreement(T, _surface(2 * pts, nrm), _surface(pts, nrm), 0.05)
    assert a3.source > 0.95 and a3.target > 0.95


def test_normal_space_weights_balance_a_dominant_plane():
    rng = np.random.default_rng(3)
    up = np.tile([0.0, 0.0, 1.0], (900, 1))  # a ground plane: 90% of the points
    other = rng.normal(size=(100, 3))
    other /= np.linalg.norm(other, axis=1, keepdims=True)
    normals = np.vstack([up, other])
    w = normal_space_weights(normals, 0.5)
    assert w.mean() == pytest.approx(1.0)
    # count^-0.5: the plane's 900 points weigh as much as sqrt(900) = 30 points would alone
    share_plane = w[:900].sum() / w.sum()
    assert 0.1 < share_plane < 0.5
    w1 = normal_space_weights(normals, 1.0)
    assert w1[:900].sum() / w1.sum() < share_plane
    # normals are lines: n and -n fall into the same bin, whichever rows are flipped
    flip = np.where(rng.random(len(normals)) < 0.5, -1.0, 1.0)[:, None]
    assert np.array_equal(normal_space_weights(flip * normals, 0.5), w)


def test_weighted_agreement_discounts_the_dominant_plane():
    """A scene that is mostly floor: a transform aligning only the floor explains most points, but far
    less of the weighted agreement, which the walls' and posts' directions count in full."""
    rng = np.random.default_rng(4)
    floor = np.column_stack([rng.uniform(-1, 1, (3000, 2)), np.zeros(3000)])
    wall = np.column_stack([np.full(500, 1.0), rng.uniform(-1, 1, 500), rng.uniform(0, 0.5, 500)])
    wall2 = np.column_stack([rng.uniform(-1, 1, 500), np.full(500, 1.0), rng.uniform(0, 0.5, 500)])
    pts = np.vstack([floor, wall, wall2])
    nrm = np.vstack([np.tile([0.0, 0, 1], (3000, 1)), np.tile([1.0, 0, 0], (500, 1)), np.tile([0.0, 1, 0], (500, 1))])
    from scipy.spatial import cKDTree

    def surf(p: np.ndarray, balance: float) -> Surface:
        return Surface.build(p, nrm, cKDTree(p), 800, normal_balance=balance)

    slide = np.eye(4)
    slide[:2, 3] = [0.2, 0.1]  # slides along the floor: the walls no longer meet
    plain = surface_agreement(slide, surf(pts, 0.0), surf(pts, 0.0), 0.05)
    balanced = surface_agreement(slide, surf(pts, 0.5), surf(pts, 0.5), 0.05)
    truth = surface_agreement(np.eye(4), surf(pts, 0.5), surf(pts, 0.5), 0.05)
    assert plain.score > 0.45  # the floor (75% of the points) still matches where it overlaps itself
    assert balanced.score < plain.score - 0.1
    assert truth.score == pytest.approx(1.0)


def test_engine_surfaces_are_weighted_by_default():
    """The default config weights the working cloud's sample (``verdict.normal_balance`` 0.5); 0 turns
    the weights off."""
    from gctr_cli.engine.prepare import StageTimer, prepare_cloud
    from gctr_cli.engine.preprocess import normalise

    points = normalise(_model("bunny")).points
    weighted = prepare_cloud(points, EngineConfig(), np.random.default_rng(0), StageTimer({})).surface
    assert weighted.sample_weights is not None and len(weighted.sample_weights) == len(weighted.sample)
    assert weighted.sample_weights.mean() == pytest.approx(1.0) and weighted.sample_weights.std() > 0.1
    off = EngineConfig.model_validate({"verdict": {"normal_balance": 0.0}})
    assert prepare_cloud(points, off, np.random.default_rng(0), StageTimer({})).surface.sample_weights is None


def test_conflict_counts_near_misses_against_the_agreement():
    """``conflict_weight``: a point that lands near the other cloud (within ``near``) but off its surface
    is evidence against the transform, not merely no evidence for it. A pose that puts the source
    just beside the target (a flipped slab, a half-turned low-overlap crop) scores below one that puts
    it nowhere near, which scores 0; the right pose has no near misses and keeps its full agreement."""
    rng = np.random.default_rng(5)
    pts, nrm = _sphere(4000, rng)
    src, tgt = _surface(pts, nrm), _surface(pts, nrm)
    beside = np.diag([1.06, 1.06, 1.06, 1.0])  # every point 0.06 off the surface: near (0.1), not on (0.02)
    away = np.eye(4)
    away[:3, 3] = [5.0, 0.0, 0.0]
    truth = surface_agreement(np.eye(4), src, tgt, 0.02, 30.0, near=0.1, conflict_weight=0.25)
    near_miss = surface_agreement(beside, src, tgt, 0.02, 30.0, near=0.1, conflict_weight=0.25)
    nowhere = surface_agreement(away, src, tgt, 0.02, 30.0, near=0.1, conflict_weight=0.25)
    assert truth.conflict_source == 0.0 and truth.conflict_target == 0.0 and truth.score == pytest.approx(1.0)
    assert near_miss.source == 0.0 and near_miss.target == 0.0
    assert near_miss.conflict_source == pytest.approx(1.0) and near_miss.conflict_target == pytest.approx(1.0)
    assert near_miss.score == pytest.approx(-0.25)
    assert nowhere.score == 0.0 and nowhere.conflict_source == 0.0
    # weight 0 (or no ``near``) is the plain agreement: conflicts are not even counted
    plain = surface_agreement(beside, src, tgt, 0.02, 30.0, near=0.1, conflict_weight=0.0)
    assert plain.conflict_source == 0.0 and plain.score == 0.0
    # the backward test works in source units (near / s): a shrinking map (s = 0.905, the points 0.095
    # inside the target sphere) is near in target units, and the target pulled back lies 0.105 / s
    # outside the source sphere in source units — still near once near is divided by s
    shrink = surface_agreement(np.diag([0.905, 0.905, 0.905, 1.0]), src, tgt, 0.02, 30.0, near=0.1,
                               conflict_weight=0.25)
    assert shrink.conflict_source == pytest.approx(1.0) and shrink.conflict_target == pytest.approx(1.0)
    # right place, wrong normals: near the surface but not on it, so a conflict
    turned = np.cross(nrm, np.array([0.0, 0.0, 1.0]))
    turned /= np.maximum(np.linalg.norm(turned, axis=1, keepdims=True), 1e-12)
    far = np.abs(turned[:, 2]) < 0.5  # avoid the poles, where the cross product degenerates
    crossed = surface_agreement(np.eye(4), _surface(pts[far], turned[far]), _surface(pts[far], nrm[far]), 0.02, 30.0,
                                near=0.1, conflict_weight=0.25)
    assert crossed.source < 0.05 and crossed.conflict_source > 0.95
    # conflicts are weighted by normal direction as the agreement is: a plane (90% of the points, one
    # direction) laid beside itself costs less when the rare directions are on the surface
    from scipy.spatial import cKDTree

    plane = np.column_stack([rng.uniform(-1, 1, (3600, 2)), np.zeros(3600)])
    post = np.column_stack([np.full(400, 0.5), np.full(400, 0.5), rng.uniform(0.0, 1.0, 400)])
    post[:, 0] += rng.normal(scale=0.05, size=400)
    scene = np.vstack([plane, post])
    up = np.tile([0.0, 0.0, 1.0], (3600, 1))
    side = np.column_stack([np.ones(400), np.zeros(400), np.zeros(400)])
    normals = np.vstack([up, side])
    weighted = Surface.build(scene, normals, cKDTree(scene), 1000, normal_balance=0.5)
    unweighted = Surface.build(scene, normals, cKDTree(scene), 1000, normal_balance=0.0)
    lift = np.eye(4)
    lift[2, 3] = 0.05  # the plane 0.05 above itself: beside; the vertical post still on itself
    w = surface_agreement(lift, weighted, weighted, 0.02, 30.0, near=0.1, conflict_weight=0.25)
    u = surface_agreement(lift, unweighted, unweighted, 0.02, 30.0, near=0.1, conflict_weight=0.25)
    assert u.conflict_source == pytest.approx(0.9, abs=0.03)
    assert w.conflict_source < u.conflict_source - 0.1
    assert w.source + w.conflict_source == pytest.approx(1.0) and u.source + u.conflict_source == pytest.approx(1.0)


def test_confidence_is_the_lead_over_the_rival():
    assert confidence(0.6, 0.0, 0.25) == 1.0
    assert confidence(0.5, 0.45, 0.25) == pytest.approx(0.2)
    assert confidence(0.3, 0.3, 0.25) == 0.0
    assert confidence(0.2, 0.4, 0.25) == 0.0  # a better rival never gives a negative confidence
    # scores below 0 (more of the clouds beside each other than on each other) are no evidence: the
    # lead is over max(rival, 0), the score of putting the source nowhere near the target
    assert confidence(0.0, -0.10, 0.25) == 0.0
    assert confidence(-0.05, -0.30, 0.25) == 0.0
    assert confidence(0.05, -0.30, 0.25) == pytest.approx(0.2)
    assert Agreement(0.2, 0.6).score == pytest.approx(0.4)


def _turn_about(centre: np.ndarray, degrees: float) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = Rotation.from_rotvec(np.radians(degrees) * np.array([0.0, 0.0, 1.0])).as_matrix()
    T[:3, 3] = centre - T[:3, :3] @ centre
    return T


def _similarity(scale: float, rotvec: list[float], translation: list[float]) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = scale * Rotation.from_rotvec(rotvec).as_matrix()
    T[:3, 3] = translation
    return T


def test_rivals_are_judged_on_the_shared_data():
    """Whole bunny as source, a quarter of it, moved by a similarity (scale 0.5), as target; the answer
    is that similarity. A 4-degree turn about the patch moves the far side of the whole by much more
    than the patch itself: on the whole source sample it looks like a distinct alignment, on the shared
    data it is a near copy of the answer. A shift of the patch by its own size is distinct either way,
    by exactly that size (in target units) on both sides."""
    whole = _model("bunny")
    whole = (whole - whole.mean(axis=0)) / np.ptp(whole, axis=0).max()
    normals = np.tile([0.0, 0.0, 1.0], (len(whole), 1))
    centre = whole[np.argmax(whole[:, 0])]  # a patch at the tip of the model
    near = np.linalg.norm(whole - centre, axis=1)
    patch = whole[near <= np.quantile(near, 0.25)]
    answer = _similarity(0.5, [0.3, -1.1, 0.7], [2.0, -1.0, 0.5])
    src = _surface(whole, normals)
    tgt = _surface(apply(answer, patch), np.tile([0.0, 0.0, 1.0], (len(patch), 1)))
    shared = SharedData.of(answer, src, tgt, distance=0.005)
    assert 0.15 * len(src.sample) < len(shared.source) < 0.4 * len(src.sample)  # the patch's share of the whole
    assert len(shared.target) == len(tgt.sample)  # every patch point maps back onto the whole

    turn = answer @ _turn_about(patch.mean(axis=0), 4.0)
    on_whole = displacement(turn, answer, src.sample)
    on_shared = shared_displacement(turn, answer, shared, src.sample)
    assert on_shared < 0.5 * on_whole
    patch_size = float(np.linalg.norm(np.ptp(patch, axis=0)))
    shift = np.eye(4)
    shift[:3, 3] = [0.0, patch_size, 0.0]  # in source units
    shifted = answer @ shift
    assert shared_displacement(shifted, answer, shared, src.sample) == pytest.approx(0.5 * patch_size)
    only_target = SharedData(source=src.sample[:0], target=shared.target)  # the source side falls back
    whole_turn = displacement(turn, answer, src.sample)
    assert shared_displacement(turn, answer, only_target, src.sample) == pytest.approx(whole_turn)
    assert shared_displacement(shifted, answer, only_target, src.sample) == pytest.approx(0.5 * patch_size)
    # halving the source about the patch centre c moves the shared source points by |p - c| / 2, but
    # the target side by |p - c| (T_answer T^-1 doubles them about c): the larger side counts
    c = patch.mean(axis=0)
    halve = np.diag([0.5, 0.5, 0.5, 1.0])
    halve[:3, 3] = 0.5 * c
    on_patch = apply(np.linalg.inv(answer), shared.target) - c
    expected = 0.5 * float(np.sqrt(np.mean(np.sum(on_patch ** 2, axis=1))))  # answer's scale 0.5 x |p - c|
    assert shared_displacement(answer @ halve, answer, shared, src.sample) == pytest.approx(expected)
    assert displacement(answer @ halve, answer, shared.source) < 0.75 * expected
    # no shared data (an answer that puts the source nowhere near the target): the whole sample decides
    away = _similarity(0.5, [0.0, 0.0, 0.0], [10.0, 0.0, 0.0])
    nothing = SharedData.of(away, src, tgt, distance=0.005)
    assert len(nothing.source) == len(nothing.target) == 0
    assert shared_displacement(turn, away, nothing, src.sample) == pytest.approx(displacement(turn, away, src.sample))
    flat = np.diag([1.0, 1.0, 0.0, 1.0])  # not a similarity (zero scale): nothing shared, no division by zero
    degenerate = SharedData.of(flat, src, tgt, distance=0.005)
    assert len(degenerate.source) == len(degenerate.target) == 0


def test_shared_data_tolerance_is_in_each_clouds_units():
    """A plane of source points and its image at scale 0.5, lifted 0.3 target units off the plane: with
    a 0.4 tolerance in target units every source point lands near a target point, and every target
    point lands within 0.4 / 0.5 = 0.8 source units of the source (0.6 away): the backward test uses
    the tolerance divided by the scale."""
    grid = np.stack(np.meshgrid(np.arange(10.0), np.arange(10.0), [0.0], indexing="ij"), -1).reshape(-1, 3)
    answer = _similarity(0.5, [0.0, 0.0, 0.4], [1.0, 2.0, 3.0])
    lifted = apply(answer, grid) + [0.0, 0.0, 0.3]
    up = np.tile([0.0, 0.0, 1.0], (len(grid), 1))
    shared = SharedData.of(answer, _surface(grid, up, 100), _surface(lifted, up, 100), distance=0.4)
    assert len(shared.source) == len(shared.target) == 100
    assert len(SharedData.of(answer, _surface(grid, up, 100), _surface(lifted, up, 100), distance=0.25).target) == 0


# ------------------------------------------------------------------------------------- part in whole
@pytest.mark.parametrize("patch_is_source, seed",
                         [pytest.param(True, 0, id="part_as_source"),
                          pytest.param(False, 1, id="part_as_target", marks=pytest.mark.slow)])  # ~7 s
def test_part_inside_whole(patch_is_source, seed):
    """A 15-40% patch of the bunny against the whole bunny at 1/4 density, 0.5% noise, 10% outliers,
    random similarity — in both directions."""
    pair, fraction = make_part_pair(_model("bunny"), np.random.default_rng([7, seed]), patch_is_source,
                                    n_source=8000)
    assert 0.15 <= fraction <= 0.40
    res = register(pair.source, pair.target, cfg_default(), seed=0)
    _assert_correct(res, pair.T_gt, pair.source, pair.target)


def test_photogrammetry_like_target():
    """A clean scan-like source against an sfm-like target (20x density variation, holes, depth noise,
    clustered floaters)."""
    pair = make_sfm_pair(_model("dragon"), np.random.default_rng([7, 2]), n_source=8000)
    res = register(pair.source, pair.target, cfg_default(), seed=0)
    _assert_correct(res, pair.T_gt, pair.source, pair.target)


@pytest.mark.slow  # ~6 s: the first search and six more, one from each half of the source
def test_low_overlap_slab_is_found_from_a_half_of_the_source():
    """Two slab crops of the bunny sharing 25-50% of their points (1/4 density, 0.5% noise, outliers,
    random similarity): the overlap is a slab at one end of each, into which few of the first search's
    triangles fit. Its best answer is a half-turn at a confidence below ``source_halves_below`` (0.21:
    above the default threshold, which counts on this second search); searched again from each half of
    the source, the engine finds the truth and accepts it."""
    pair = make_lowoverlap_pair(_model("bunny"), np.random.default_rng([7, 7]), n_source=8000)
    halves_below = cfg_default().source_halves_below
    first = register(pair.source, pair.target, EngineConfig(source_halves_below=0.0, min_confidence=halves_below),
                     seed=0)
    assert first.status == "failed" and first.confidence < halves_below
    assert _errors(first.transform, pair.T_gt, pair.source, pair.target).rot_err_deg > 90
    res = register(pair.source, pair.target, cfg_default(), seed=0)
    _assert_correct(res, pair.T_gt, pair.source, pair.target)


def test_source_halves_split_at_the_median_along_each_principal_axis():
    rng = np.random.default_rng(0)
    axes = Rotation.random(random_state=1).as_matrix()
    points = (rng.normal(size=(1001, 3)) * [3.0, 2.0, 1.0]) @ axes.T + [5.0, -2.0, 1.0]
    masks = source_halves(points)
    assert len(masks) == 6
    for a in range(3):
        lower, upper = masks[2 * a], masks[2 * a + 1]
        assert lower.sum() == upper.sum() == 501  # the median point is in both halves
        assert np.all(lower | upper)
        # the split direction is the a-th principal axis (ascending variance): the halves' centres lie
        # on either side along it
        gap = points[upper].mean(axis=0) - points[lower].mean(axis=0)
        assert abs(gap @ axes[:, 2 - a]) / np.linalg.norm(gap) > 0.95


def test_score_of_the_truth_beats_a_wrong_pose():
    """The diagnostic the benchmark uses: the engine's own score of the ground truth is higher than
    that of a pose turned by 90 degrees."""
    pair, _ = make_part_pair(_model("bunny"), np.random.default_rng([7, 0]), True, n_source=8000)
    wrong = pair.T_gt.copy()
    wrong[:3, :3] = wrong[:3, :3] @ Rotation.from_euler("z", 90, degrees=True).as_matrix()
    assert score_transform(pair.source, pair.target, pair.T_gt) > score_transform(pair.source, pair.target, wrong) + 0.2


# ------------------------------------------------------------------------------ honest failure
def test_unrelated_clouds_fail_with_a_message():
    """The bunny against the kitchen: no transform explains the data; failed, not a matrix."""
    res = register(_model("bunny")[::3], _model("redkitchen")[::3], cfg_default(), seed=0)
    assert res.status == "failed"
    assert res.message.startswith(("low confidence", "ambiguous", "too weak evidence")), res.message
    assert res.confidence < cfg_default().min_confidence


def _ellipsoid(n: int, rng: np.random.Generator, axes=(1.0, 0.6, 0.35)) -> np.ndarray:
    v = rng.normal(size=(n, 3))
    v /= np.linalg.norm(v, axis=1, keepdims=True)
    return v * np.asarray(axes)


def test_symmetric_shape_cropped_is_ambiguous():
    """An ellipsoid whose only asymmetric feature (a bump at one end) is cropped away in the target:
    the half-turns of the ellipsoid fit equally well, so the engine must say so instead of picking one."""
    rng = np.random.default_rng(0)
    src = _ellipsoid(12000, rng)
    src = np.vstack([src, src[src[:, 0] > 0.9] + [0.05, 0.0, 0.0]])  # the bump
    tgt = _ellipsoid(4000, rng)
    tgt = tgt[np.abs(tgt[:, 0]) < 0.8]  # cropped symmetrically: the bump's place is gone
    tgt = tgt @ (1.5 * Rotation.random(random_state=3).as_matrix()).T + [1.0, 2.0, 3.0]
    res = register(src, tgt, cfg_default(), seed=0)
    assert res.status == "failed"
    ambiguous = "ambiguous: two distinct alignments explain the data almost equally well"
    assert res.message.startswith(ambiguous), res.message
    assert res.confidence < 0.1


def _cylinder(n: int, rng: np.random.Generator, turn: tuple[float, float], height: tuple[float, float]) -> np.ndarray:
    theta, z = rng.uniform(*np.radians(turn), n), rng.uniform(*height, n)
    return np.column_stack([0.1 * np.cos(theta), 0.1 * np.sin(theta), z]) + rng.normal(scale=0.0005, size=(n, 3))


def test_a_featureless_cylinder_that_can_slide_along_its_axis_is_ambiguous():
    """A 200-degree arc of a plain cylinder (z 0-0.4) against a 270-degree arc of it (z 0.1-0.6): any
    slide along the axis fits as well, and the search's best one (the source pushed inside the target)
    came back ok at confidence 1, 18 degrees and a quarter of the target off. A confident answer whose
    contact leaves a direction free is slid along it too (``verdict.slide_free_ratio``), finds the
    equally good rival and is refused."""
    rng = np.random.default_rng(11)
    src = _cylinder(20000, rng, (0.0, 200.0), (0.0, 0.4))
    tgt = _cylinder(8000, rng, (-40.0, 230.0), (0.1, 0.6))
    move = np.eye(4)
    move[:3, :3] = 1.7 * Rotation.random(random_state=5).as_matrix()
    move[:3, 3] = [0.3, -0.2, 0.5]
    res = register(src @ move[:3, :3].T + move[:3, 3], tgt, cfg_default(), seed=6)  # seed 6 settled at 1.0
    assert res.status == "failed", (res.confidence, res.message)
    assert res.message.startswith("ambiguous"), res.message
    assert res.confidence < 0.1


def _box(n: int, rng: np.random.Generator, size=(0.2, 0.12, 0.08)) -> np.ndarray:
    """Points on the six faces of a closed box (faces drawn uniformly, not by area)."""
    half = 0.5 * np.asarray(size)
    face = rng.integers(0, 6, n)
    points = rng.uniform(-1.0, 1.0, (n, 3)) * half
    axis = face // 2
    points[np.arange(n), axis] = np.where(face % 2 == 0, -1.0, 1.0) * half[axis]
    return points


def _tube(n: int, rng: np.random.Generator) -> np.ndarray:
    theta = rng.uniform(0.0, 2.0 * np.pi, n)
    return np.column_stack([0.05 * np.cos(theta), 0.05 * np.sin(theta), rng.uniform(-0.15, 0.15, n)])


@pytest.mark.parametrize("shape, seed, turn", [("box", 1, 1.0), ("tube", 2, 1.3)])
def test_a_symmetric_shape_against_a_turned_copy_is_ambiguous(shape, seed, turn):
    """A closed box and an open tube, each against a copy sampled apart and moved: a half-turn about an
    axis of either fits as well as the truth. The search proposed only one of them, which came back ok
    at confidence 1 (the box 180 degrees off, the tube 104); the answer turned half a turn about each
    principal axis of both clouds (``verdict.turned_finalists``) is the rival that says so."""
    rng = np.random.default_rng(seed)
    make = _box if shape == "box" else _tube
    src, tgt = make(20000 if shape == "box" else 6000, rng), make(8000 if shape == "box" else 3000, rng)
    R = turn * (Rotation.from_euler("xyz", (30, -50, 80), degrees=True).as_matrix() if shape == "box"
                else Rotation.random(random_state=seed).as_matrix())
    tgt = tgt @ R.T + ([0.4, -1.2, 2.0] if shape == "box" else [0.2, -0.1, 0.3])
    tgt += rng.normal(scale=0.0005, size=tgt.shape)
    without = register(src, tgt, EngineConfig(verdict={"turned_finalists": 0}), seed=0)
    assert without.status == "ok" and without.confidence == 1.0  # what the turns are for
    res = register(src, tgt, cfg_default(), seed=0)
    assert res.status == "failed" and res.message.startswith("ambiguous"), (res.confidence, res.message)


def test_the_half_turn_starts_are_distinct_poses():
    """A box laid on a copy of itself: the half-turns about the source's and the target's principal axes
    are the same three poses (0.01 apart), and the turns refined as rivals must be distinct ones, so that
    ``verdict.turned_finalists`` = 2 tries two of the three, not one of them twice."""
    from gctr_cli.engine.decide import likely_turns
    from gctr_cli.engine.prepare import RefinementCloud

    rng = np.random.default_rng(0)
    cfg = EngineConfig.model_validate({"refine": {"voxel_ratio": 0.01}})
    src, tgt = _box(6000, rng, size=(1.0, 0.6, 0.4)), _box(6000, rng, size=(1.0, 0.6, 0.4))
    src_ref = RefinementCloud.build(src, cfg, np.random.default_rng(1))
    tgt_ref = RefinementCloud.build(tgt, cfg, np.random.default_rng(2))
    turns = likely_turns(np.eye(4), src_ref, tgt_ref, cfg, 6, src[:500])
    assert len(turns) == 3  # six axes, three poses
    gaps = [displacement(a, b, src[:500]) for i, a in enumerate(turns) for b in turns[i + 1:]]
    assert min(gaps) > 0.5  # each pair of turns moves the box by half its length or more
    assert all(displacement(T, np.eye(4), src[:500]) > 0.5 for T in turns)
    two = likely_turns(np.eye(4), src_ref, tgt_ref, cfg, 2, src[:500])  # the default count: two poses
    assert len(two) == 2 and displacement(two[0], two[1], src[:500]) > 0.5


def test_threshold_is_a_config_key():
    """A pair that passes at the default threshold is refused at a strict one, with the
    low-confidence message naming the threshold; the failed result still carries the best transform.
    (``full_margin = 1`` keeps the confidence below 1: it is then the plain lead over the rival.)"""
    pair, _ = make_part_pair(_model("bunny"), np.random.default_rng([7, 0]), True, n_source=8000)
    strict = EngineConfig(min_confidence=0.99, verdict={"full_margin": 1.0})
    res = register(pair.source, pair.target, strict, seed=0)
    assert res.status == "failed"
    assert res.message.startswith("low confidence") and "threshold 0.99" in res.message, res.message
    assert res.refusal == "low_confidence"
    assert 0.0 < res.confidence < 0.99
    err = _errors(res.transform, pair.T_gt, pair.source, pair.target)
    assert err.rot_err_deg < 2.0  # refused, but the best transform found is still reported


def test_refusal_message_states_the_share_explained_and_the_lead():
    from gctr_cli.engine.decide import refusal_message
    from gctr_cli.engine.verdict import Verdict

    cfg = EngineConfig()

    def message(score: float, rival: float) -> str:
        v = Verdict(confidence=confidence(score, rival, cfg.verdict.full_margin), score=score, rival_score=rival,
                    agreement=Agreement(score, score), support=1.0)
        return refusal_message(v, cfg)

    assert "lays 13% of the two surfaces on each other (at the verdict's tight tolerance, finer than fitness's) " \
           "and scores only 1 point more than" in message(0.13, 0.12)
    assert "scores only 4 points more than" in message(0.10, 0.06)
    assert message(0.10, 0.11).startswith("low confidence 0.00") and "no more than a distinct" in message(0.10, 0.11)
    # the share explained is the plain agreement; the score also counts the points landing beside
    a = Agreement(0.3, 0.2, 0.7, 0.7, 0.25)  # score 0.25 - 0.175 = 0.075
    v = Verdict(confidence=confidence(a.score, 0.07, 0.25), score=a.score, rival_score=0.07, support=1.0, agreement=a)
    # ambiguous: the rival reaches 0.8 x 0.075 on a pair 25% explained, though the score is only 0.075
    assert refusal_message(v, cfg).startswith("ambiguous") and "(score 0.08 vs 0.07;" in refusal_message(v, cfg)
    # a score of 0 or less: the answer lays as much of the clouds beside each other as on each other
    a = Agreement(0.2, 0.1, 0.8, 0.6, 0.25)  # score 0.15 - 0.175 = -0.025
    v = Verdict(confidence=confidence(a.score, -0.1, 0.25), score=a.score, rival_score=-0.1, support=1.0, agreement=a)
    assert v.confidence == 0.0
    assert refusal_message(v, cfg).startswith("low confidence 0.00 (threshold 0.15): the best alignment lays 15%")
    off = "as much of them or more near each other but off the surface (score -0.02 vs -0.10)"
    assert off in refusal_message(v, cfg)
    # too little explained to call it ambiguous, however close the rival
    a = Agreement(0.1, 0.1)
    v = Verdict(confidence=0.0, score=a.score, rival_score=0.1, support=1.0, agreement=a)
    assert refusal_message(v, cfg).startswith("low confidence")
    # the relief is named only when it gave the confidence (the larger of the two leads)
    a = Agreement(0.5, 0.5)
    from_relief = Verdict(confidence=0.12, score=0.5, rival_score=0.48, support=1.0, agreement=a,
                          relief_confidence=0.12)
    plain = Verdict(confidence=0.14, score=0.5, rival_score=0.465, support=1.0, agreement=a, relief_confidence=0.07)
    assert "; that confidence comes from the relief (the heights above" in refusal_message(from_relief, cfg)
    assert "relief" not in refusal_message(plain, cfg)
    # the confidence is truncated, never rounded up to the threshold it missed
    a = Agreement(0.5, 0.5)
    v = Verdict(confidence=0.1496, score=0.5, rival_score=0.4626, support=1.0, agreement=a)
    assert "confidence 0.14, threshold 0.15" in refusal_message(v, cfg)
    assert message(0.50, 0.48).startswith("ambiguous: two distinct alignments")
    # a rival above the answer is an unrefined transform of the pool (refined finalists are ranked): said so
    assert "(score 0.10 vs 0.11, the alternative found by the search and not refined)" in message(0.10, 0.11)
    a = Agreement(0.3, 0.2, 0.6, 0.6, 0.25)  # score 0.25 - 0.15 = 0.10, 25% explained: ambiguous
    v = Verdict(confidence=0.0, score=a.score, rival_score=0.14, support=1.0, agreement=a)
    assert refusal_message(v, cfg).startswith("ambiguous: two distinct alignments explain the data almost equally "
                                              "well (score 0.10 vs 0.14, the alternative found by the search and "
                                              "not refined; confidence 0.00")
    assert "did not refine" not in message(0.50, 0.48)


def test_a_sparse_verdict_needs_a_larger_lead():
    """The score's noise grows like 1/sqrt(n): below ``full_margin_points`` sample points the confidence is
    scaled by sqrt(n / full_margin_points), and a refusal says so."""
    from gctr_cli.engine.decide import refusal_message
    from gctr_cli.engine.verdict import Verdict

    assert sample_weight(800, 800) == 1.0 and sample_weight(5000, 800) == 1.0 and sample_weight(100, 0) == 1.0
    assert sample_weight(200, 800) == pytest.approx(0.5) and sample_weight(50, 800) == pytest.approx(0.25)
    cfg = EngineConfig()
    a = Agreement(0.4, 0.4)
    v = Verdict(confidence=0.5 * confidence(0.4, 0.35, 0.25), score=0.4, rival_score=0.35, agreement=a, support=1.0,
                sample_points=200, sample_weight=0.5)
    assert refusal_message(v, cfg).endswith("; the clouds are sparse: the verdict compared only 200 points a cloud, "
                                            "so its confidence counts sqrt(200/800) = 0.50 of the lead "
                                            "(verdict.full_margin_points)")
    assert "sparse" not in refusal_message(Verdict(confidence=0.1, score=0.4, rival_score=0.35, agreement=a,
                                                   support=1.0, sample_points=900), cfg)


@functools.cache
def _dragon_points() -> np.ndarray:
    return np.asarray(load_point_cloud(MODELS / "dragon.ply"), dtype=np.float64)


def test_a_sparse_half_turn_is_refused():
    """Two random 500-point subsets of the dragon (``data_scripts/probe_pairs.py``, tuning offset 0): the
    search ends half-turned (163°), and its lead over the rival, 0.19 of the full margin on a 118-point
    sample, was accepted before the sample-size weight; now it is refused, saying the clouds are sparse."""
    source, target, T_gt = sparse_pair(_dragon_points(), 500, 0.0, 500_001)
    res = register(source, target, EngineConfig(), seed=1)
    assert _errors(res.transform, T_gt, source, target).rot_err_deg > 150
    assert res.status == "failed" and res.confidence < 0.1
    assert "the clouds are sparse: the verdict compared only 118 points a cloud" in res.message
    # with the weight off it comes back ok: the wrong answer the weight exists for
    off = EngineConfig().model_copy(update={"verdict": EngineConfig().verdict.model_copy(
        update={"full_margin_points": 0})})
    assert register(source, target, off, seed=1).status == "ok"


def test_a_clear_sparse_answer_is_still_accepted():
    """800-point subsets of the dragon: right, and accepted at a confidence capped by the sample size."""
    source, target, T_gt = sparse_pair(_dragon_points(), 800, 0.0, 800_000)
    res = register(source, target, EngineConfig(), seed=0)
    assert res.ok, res.message
    assert _errors(res.transform, T_gt, source, target).rot_err_deg < 1.0
    assert 0.15 < res.confidence <= np.sqrt(353 / 800) + 1e-9


def _probe(kind: str, models: str, n: int, noise: float, rep: int, offset: int, reverse_below: float = 0.3,
           **verdict: float | bool) -> dict:
    """One pair of ``data_scripts/probe_pairs.py`` registered with ``verdict.reverse_below`` and any other
    ``verdict`` keys set."""
    from data_scripts.probe_pairs import run_one
    from gctr_cli.config import Config

    config = Config().model_dump(mode="json")
    config["engine"]["verdict"].update(reverse_below=reverse_below, **verdict)
    return run_one((kind, models, n, noise, rep, offset, config))


def test_a_mirrored_cloud_is_refused():
    """A dragon crop reflected through a plane (a cloud with a flipped axis, ``probe_pairs --kind mirrored``,
    tuning offset 0): the best rotation lays it on the dragon at confidence 0.55, a silent wrong answer
    without the mirror check; the mirror image fits far better (score 0.52 against 0.14), so it is refused."""
    row = _probe("mirrored", "dragon", 2000, 0.002, 0, 0, reflection_check=False)  # the full check alone
    assert row["status"] == "failed" and row["confidence"] == pytest.approx(0.5543, abs=2e-3)
    assert row["refusal"] == "mirrored"
    assert row["score"] == pytest.approx(0.139, abs=2e-3) and row["mirror_score"] == pytest.approx(0.519, abs=2e-3)
    assert row["message"] == ("mirrored: the source reflected (x -> -x) fits the target better than any rotation of "
                              "it (score 0.52 against 0.14); either one of the clouds has a flipped axis (a "
                              "left-handed coordinate system? flip it and register again), or the clouds share too "
                              "little of a nearly mirror-symmetric shape to be registered (a flipped copy would fit "
                              "and be just as wrong)")
    assert _probe("mirrored", "dragon", 2000, 0.002, 0, 0, mirror_below=0.0,
                  reflection_check=False)["outcome"] == "silent wrong"


def test_a_mirror_image_that_fits_well_is_refused_by_the_reflection_check():
    """A bunny crop of 8,000 points reflected through a plane (``probe_pairs --kind mirrored``, tuning offset
    0): the bunny is nearly mirror-symmetric, so the best rotation fits it well (score 0.40) and it was
    accepted at confidence 1, a fit too good for the full mirror check (verdict.mirror_below 0.3). The
    answer reflected through a principal plane of a cloud and refined fits much better: refused."""
    row = _probe("mirrored", "bunny", 8000, 0.002, 0, 0)
    assert row["status"] == "failed" and row["refusal"] == "mirrored" and row["confidence"] == 1.0
    assert row["message"].startswith("mirrored: the source reflected fits the target better than any rotation of "
                                     "it (score 0.7")
    assert row["message"].endswith(" against 0.40, the answer reflected through a principal plane of a cloud and "
                                   "refined); either one of the clouds has a flipped axis (a left-handed coordinate "
                                   "system? flip it and register again), or the clouds share too little of a nearly "
                                   "mirror-symmetric shape to be registered (a flipped copy would fit and be just as "
                                   "wrong)")
    unchecked = _probe("mirrored", "bunny", 8000, 0.002, 0, 0, reflection_check=False)
    assert unchecked["outcome"] == "silent wrong" and unchecked["confidence"] == 1.0


def test_the_mirror_check_keeps_a_right_answer_of_a_nearly_symmetric_shape():
    """The bunny is nearly mirror-symmetric: a right answer on a low-overlap bunny pair is checked (with
    mirror_below 0.5, the setting for clouds of unknown axis conventions), and its mirror image scores
    below it or within mirror_margin, so it stays ok."""
    pair = make_lowoverlap_pair(_model("bunny"), np.random.default_rng([7, 7]), n_source=8000)
    cfg = EngineConfig()
    cfg = cfg.model_copy(update={"verdict": cfg.verdict.model_copy(update={"mirror_below": 0.5})})
    res = register(pair.source, pair.target, cfg, seed=0)
    _assert_correct(res, pair.T_gt, pair.source, pair.target)
    assert res.evidence["score"] < 0.5 and "mirror_score" in res.evidence
    assert res.evidence["mirror_score"] - res.evidence["score"] < cfg.verdict.mirror_margin
    # the reflection check passes it (NaN: its reflection was not even worth refining)
    assert not res.evidence["reflection_lead"] >= cfg.verdict.mirror_margin


def test_a_reflected_refinement_cloud_queries_the_original_tree_through_the_mirror():
    """The reflection check's mirrored source builds no tree: its queries go to the original cloud's tree
    through the mirror (``prepare.MirroredTree``). On the shipped bunny, the neighbours and distances, the
    surface agreements and the refinement are the same, bit for bit, as with a tree built on the reflected
    points."""
    from dataclasses import replace

    from gctr_cli.engine.decide import MIRROR, icp, reflection_starts, similarity_scale, tight_agreement, tight_test
    from gctr_cli.engine.gctr import _normalised, _prepared_pair
    from gctr_cli.engine.prepare import MirroredTree, RefinementCloud, StageTimer
    from gctr_cli.engine.scipy_parts import cKDTree

    cfg = EngineConfig()
    rng = np.random.default_rng(3)
    pts = _model("bunny")[::2]
    T_gt = np.eye(4)
    T_gt[:3, :3] = 0.8 * Rotation.from_euler("xyz", [30, -20, 110], degrees=True).as_matrix()
    T_gt[:3, 3] = [0.1, -0.2, 0.3]
    target = apply(T_gt, pts[rng.permutation(len(pts))[: len(pts) // 2]]) + rng.normal(0, 1e-4, (len(pts) // 2, 3))
    ns, nt, src, tgt, _, _ = _prepared_pair(pts, target, cfg, 0, StageTimer({}))
    src_ref, tgt_ref = RefinementCloud.of(src, ns.points, cfg, rng), RefinementCloud.of(tgt, nt.points, cfg, rng)
    mirrored = src_ref.reflected(MIRROR, cfg)
    assert isinstance(mirrored.tree, MirroredTree)
    built_tree = cKDTree(mirrored.points)
    built = replace(mirrored, tree=built_tree, surface=replace(mirrored.surface, tree=built_tree))
    queries = mirrored.points[::5] + rng.normal(0, 0.01, (len(mirrored.points[::5]), 3))
    for bound in (0.02, np.inf):
        d, j = mirrored.tree.query(queries, distance_upper_bound=bound)
        d_built, j_built = built_tree.query(queries, distance_upper_bound=bound)
        np.testing.assert_array_equal(d, d_built)
        np.testing.assert_array_equal(j, j_built)
    # the reflection check's starts: the answer reflected through the clouds' principal planes, which are
    # proper similarities of the mirrored source (the bunny is nearly mirror-symmetric: some fit well)
    T_n = _normalised(T_gt, ns, nt)
    test = tight_test(mirrored, tgt_ref, similarity_scale(T_n), cfg)
    starts = reflection_starts(T_n, src_ref, tgt_ref)
    scores = []
    for T in starts:
        tight = tight_agreement(T, mirrored, tgt_ref, test)
        assert tight == tight_agreement(T, built, tgt_ref, test)
        assert surface_agreement(T, mirrored.surface, tgt_ref.surface, 0.03) == surface_agreement(
            T, built.surface, tgt_ref.surface, 0.03)
        scores.append(tight.score)
    assert max(scores) > 0.05  # not all trivially 0
    best = starts[int(np.argmax(scores))]
    np.testing.assert_array_equal(icp(best, mirrored, tgt_ref, cfg, (0.01, 100.0)),
                                  icp(best, built, tgt_ref, cfg, (0.01, 100.0)))


def test_the_mirror_search_reuses_the_forward_tensors_a_reflection_leaves_unchanged():
    """The mirror check searches the forward run's prepared source reflected, with the forward search's
    tensors: every hypothesis' tensor built on the reflected clouds is the forward one entry for entry (the
    triangle descriptors are lengths and angles), and the generator ends in the same state."""
    from gctr_cli.engine.gctr import MIRROR, mirror_config, mirrored_run, run_search
    from gctr_cli.engine.prepare import StageTimer
    from gctr_cli.engine.search import hypothesis_tensor, oriented, search_plan

    pair, _ = make_part_pair(_model("bunny"), np.random.default_rng([7, 3]), True, n_source=4000)
    cfg = EngineConfig()
    run = run_search(pair.source, pair.target, cfg, 0, StageTimer({}))
    searched = {key[0].name for key in run.tensors}
    assert run.tensors and searched <= {h.name for h in search_plan(cfg)}
    reflected = run.source.reflected(MIRROR, cfg)
    np.testing.assert_allclose(reflected.salient, run.source.salient * MIRROR)
    for hypothesis in search_plan(cfg):
        prior = hypothesis.scale_prior(run.bounds_n)
        a, b, h, p, _ = oriented(run.source, run.target, hypothesis, prior)
        am, bm, _, _, _ = oriented(reflected, run.target, hypothesis, prior)
        rng, rng_m = np.random.default_rng(5), np.random.default_rng(5)
        H, Hm = hypothesis_tensor(a, b, h, p, cfg, rng), hypothesis_tensor(am, bm, h, p, cfg, rng_m)
        for field in ("a", "b", "c"):
            np.testing.assert_array_equal(getattr(H, field), getattr(Hm, field))
        np.testing.assert_allclose(H.values, Hm.values, rtol=1e-12)
        assert rng.random() == rng_m.random()
    # the mirror search takes the tensor of the hypothesis it runs from the forward search
    overlap = next(h.overlap for h in search_plan(cfg) if h.name in searched)
    timer, kept = StageTimer({}), len(run.tensors)
    mirrored = mirrored_run(run, mirror_config(cfg, overlap), 0, timer)
    assert mirrored.tensors is run.tensors and len(run.tensors) == kept and timer.timings["tensor"] < 0.01
    # a search with other tensor settings builds its own tensor instead of taking the forward one
    other = mirror_config(cfg.model_copy(update={"tensor": cfg.tensor.model_copy(update={"knn": 9})}), overlap)
    mirrored_run(run, other, 0, StageTimer({}))
    assert len(run.tensors) == kept + 1
    np.testing.assert_allclose(mirrored.source.points, run.source.points * MIRROR)
    np.testing.assert_allclose(mirrored.norm_source.centre, run.norm_source.centre * MIRROR)


def test_an_unconfirmed_low_confidence_answer_is_refused():
    """A bunny subset against a dragon (a manifest pairing the wrong files; bench/UNRELATED.md): the search
    lays one on the other at confidence 0.28, which passed the threshold; registered the other way round
    the pair ends elsewhere, so the answer is refused."""
    row = _probe("unrelated", "bunny>dragon", 1000, 0.002, 3, 50000, 0.3)
    assert row["status"] == "failed" and row["confidence"] == pytest.approx(0.2785, abs=1e-3)
    assert row["refusal"] == "not_confirmed"
    assert row["message"].startswith("not confirmed: registered the other way round (target onto source), the "
                                     "pair ends at another alignment (")
    assert "at confidence 0.27, below verdict.reverse_below 0.30, an answer needs that confirmation" in row["message"]
    assert _probe("unrelated", "bunny>dragon", 1000, 0.002, 3, 50000, 0.0)["outcome"] == "silent wrong"


@pytest.mark.parametrize("bounds", [(0.1, 10.0), (1.2, 3.0), (1.0, float("inf"))])
def test_the_reverse_run_inverts_the_scale_bounds(bounds):
    """scale_bounds hold the source->target scale; the reverse run (target onto source) must get them
    inverted, or a right answer at scale 1.5 within [1.2, 3] is held at 1.2 backwards and 'not confirmed'."""
    from gctr_cli.engine.gctr import _normalised, _prepared_pair, reverse_displacement
    from gctr_cli.engine.prepare import StageTimer

    rng = np.random.default_rng(0)
    pts = np.asarray(load_point_cloud(MODELS / "bunny.ply"), dtype=np.float64)
    src = pts[rng.choice(len(pts), 4000, replace=False)]
    T = np.eye(4)
    T[:3, :3] = 1.5 * Rotation.from_euler("xyz", [20, 40, 60], degrees=True).as_matrix()
    T[:3, 3] = [0.1, 0.2, 0.3]
    tgt = apply(T, pts[rng.choice(len(pts), 4000, replace=False)])
    cfg = EngineConfig().model_copy(update={"scale_bounds": bounds})
    res = register(src, tgt, cfg, seed=0)
    assert res.ok and abs(res.scale - 1.5) < 0.005
    ns, nt, *_ = _prepared_pair(src, tgt, cfg, 0, StageTimer({}))
    moved = reverse_displacement(src, tgt, cfg, 0, _normalised(res.transform, ns, nt), ns, nt, ns.points[::20])
    assert moved < 0.01  # the same alignment from the other side (0.54-0.65 with the bounds as given)


def test_a_right_low_confidence_answer_is_confirmed():
    """A sparse dragon pair (500 points each) right at confidence 0.18: the reverse run ends at the same
    alignment, so it stays ok."""
    row = _probe("sparse", "dragon", 500, 0.0, 0, 0, 0.3)
    assert row["status"] == "ok" and row["outcome"] == "right" and 0.15 < row["confidence"] < 0.3
    assert row["rot_err_deg"] < 5


@pytest.mark.parametrize("first_confidence, min_confidence, halves_below, support, searched",
                         [(0.37, 0.4, 0.35, 1.0, True),   # would be refused: the halves run though 0.37 > 0.35
                          (0.37, 0.2, 0.35, 1.0, False),  # accepted and above source_halves_below
                          (0.30, 0.2, 0.35, 1.0, True),   # below source_halves_below
                          (0.30, 0.4, 0.0, 1.0, False),   # source_halves_below 0 = never
                          (0.90, 0.2, 0.35, 0.0, True),   # confident, but no search run ended at the answer
                          (0.90, 0.2, 0.35, 0.05, False),  # confident and supported
                          (0.90, 0.2, 0.0, 0.0, False)])  # 0 = never, support or not
def test_an_answer_is_not_refused_without_the_search_from_the_halves(monkeypatch, first_confidence, min_confidence,
                                                                     halves_below, support, searched):
    """The second search (from each half of the source) runs below ``source_halves_below`` and below
    ``min_confidence``: an answer the threshold would refuse always gets it (0 turns it off). It also
    runs for a confident answer that no search run ended at (support 0): on a fresh generator seed
    such an answer was a half-turned part-in-whole pair at confidence 0.71, which the halves found."""
    from gctr_cli.engine import gctr
    from gctr_cli.engine.verdict import Verdict

    calls: list[int] = []

    def fake_decide(pool, *args, **kwargs):
        return pool[0].transform, Verdict(confidence=first_confidence, score=0.3, rival_score=0.2,
                                          agreement=Agreement(0.3, 0.3), support=support)

    def fake_halves(*args, **kwargs):
        calls.append(1)
        return []

    monkeypatch.setattr(gctr, "decide", fake_decide)
    monkeypatch.setattr(gctr, "half_candidates", fake_halves)
    pair, _ = make_part_pair(_model("bunny"), np.random.default_rng(0), patch_is_source=True, n_source=4000)
    cfg = EngineConfig(min_confidence=min_confidence, source_halves_below=halves_below)
    res = gctr.register(pair.source, pair.target, cfg, seed=0)
    assert bool(calls) == searched
    assert res.confidence == first_confidence
    if first_confidence < min_confidence:
        assert res.status == "failed" and f"threshold {min_confidence:.2f}" in res.message, res.message


def test_an_answer_is_slid_along_the_direction_its_contact_leaves_free():
    """A floor (z = 0) and a wall (x = 0) pin z and x; the answer is slid both ways along y only,
    by each configured step times the smaller cloud's size, and the contact says y is free (ratio 0);
    a third wall (y = 0) pins y as well."""
    from types import SimpleNamespace

    from scipy.spatial import cKDTree

    from gctr_cli.engine.decide import contact_freedom, slid_transforms

    g = np.linspace(0.0, 1.0, 21)
    a, b = (m.ravel() for m in np.meshgrid(g, g))
    floor = np.column_stack([a, b, np.zeros_like(a)])
    wall = np.column_stack([np.zeros_like(a), a, b])
    points = np.vstack([floor, wall])
    normals = np.vstack([np.tile([0.0, 0.0, 1.0], (len(floor), 1)), np.tile([1.0, 0.0, 0.0], (len(wall), 1))])
    cloud = SimpleNamespace(points=points, normals=normals, tree=cKDTree(points))
    T = np.diag([0.5, 0.5, 0.5, 1.0])  # scale 0.5: the smaller cloud's size is 0.5
    T[:3, 3] = [0.1, 0.2, 0.0]
    moved_back = SimpleNamespace(points=(points - T[:3, 3]) / 0.5)  # the source lands exactly on the target
    free = contact_freedom(T, moved_back, cloud, 0.01)
    assert free is not None
    direction, ratio = free
    assert abs(direction @ [0.0, 1.0, 0.0]) == pytest.approx(1.0) and ratio == pytest.approx(0.0, abs=1e-12)
    shifted = slid_transforms(T, direction, (0.1, 0.2))
    steps = sorted(float((S[:3, 3] - T[:3, 3]) @ [0.0, 1.0, 0.0]) for S in shifted)
    assert steps == pytest.approx([-0.1, -0.05, 0.05, 0.1])
    for S in shifted:
        assert np.allclose(S[:3, :3], T[:3, :3])
        assert abs(S[0, 3] - T[0, 3]) < 1e-9 and abs(S[2, 3] - T[2, 3]) < 1e-9
    assert contact_freedom(T, SimpleNamespace(points=points + 5.0), cloud, 0.01) is None
    back_wall = np.column_stack([a, np.zeros_like(a), b])
    corner = np.vstack([points, back_wall])
    corner_normals = np.vstack([normals, np.tile([0.0, 1.0, 0.0], (len(back_wall), 1))])
    room = SimpleNamespace(points=corner, normals=corner_normals, tree=cKDTree(corner))
    free = contact_freedom(T, SimpleNamespace(points=(corner - T[:3, 3]) / 0.5), room, 0.01)
    assert free is not None and free[1] > 0.99  # three walls: no direction is freer
