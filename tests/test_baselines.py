"""Comparison methods (gctr_cli.baselines): each recovers a known similarity on an easy pair built from
the shipped bunny, degenerate inputs give failed results, config/dispatch, and the batch CLI with
``method: fpfh_ransac`` (normal rows, reproducible across processes)."""

from __future__ import annotations

import numpy as np
import pytest
import yaml
from click.testing import CliRunner
from conftest import REPO, read_csv, rotation, row_matrix, write_cloud, write_manifest_rows

from gctr_cli import cli
from gctr_cli.baselines import REGISTER_FUNCTIONS, register_fpfh_ransac
from gctr_cli.baselines.common import box_normalise
from gctr_cli.baselines.cpd import cpd_rigid
from gctr_cli.config import BaselineConfig, Config, ConfigError, config_from_dict
from gctr_cli.engine.preprocess import denormalise
from gctr_cli.geometry import apply, invert, split, to_matrix
from gctr_cli.io import load_point_cloud
from gctr_cli.methods import BASELINES, METHODS, get_register_fn, method_config
from gctr_cli.metrics import is_similarity, transform_errors

BUNNY = REPO / "data" / "models" / "bunny.ply"


def _similarity(scale: float, angle_deg: float, axis, translation) -> np.ndarray:
    """Scale, rotation of ``angle_deg`` about ``axis``, translation."""
    return to_matrix(scale, rotation(axis, angle_deg), translation)


@pytest.fixture(scope="module")
def bunny() -> np.ndarray:
    return load_point_cloud(BUNNY)


def easy_pair(bunny: np.ndarray, T_gt: np.ndarray, seed: int = 0):
    """Source: 8000 bunny points moved by inv(T_gt); target: 4000 *other* bunny points (1/2 density)
    with Gaussian noise of 0.2% of the diagonal, in the bunny frame. ``target ~ T_gt @ source``."""
    rng = np.random.default_rng(seed)
    idx = rng.permutation(len(bunny))
    diag = float(np.linalg.norm(bunny.max(0) - bunny.min(0)))
    source = apply(invert(T_gt), bunny[idx[:8000]])
    target = bunny[idx[8000:12000]] + rng.normal(scale=0.002 * diag, size=(4000, 3))
    return source, target


def _check(result, T_gt, source, target, rot_deg=1.5, scale=0.01, centroid_rel=0.01, trans_rel=0.02):
    assert result.status == "ok", result.message
    ok, reason = is_similarity(result.transform)
    assert ok, reason
    diag = float(np.linalg.norm(target.max(0) - target.min(0)))
    err = transform_errors(result.transform, T_gt, diag)
    # where the source lands (independent of the coordinate origin): its centroid
    c = source.mean(axis=0)
    centroid_err = np.linalg.norm(apply(result.transform, c[None])[0] - apply(T_gt, c[None])[0]) / diag
    assert err.rot_err_deg < rot_deg, err
    assert err.scale_err < scale, err
    assert err.trans_err_rel < trans_rel, err
    assert centroid_err < centroid_rel, centroid_err
    # the record is self-consistent
    s, R, t = split(result.transform)
    assert result.scale == pytest.approx(s, rel=1e-9)
    np.testing.assert_allclose(result.rotation, R, atol=1e-9)
    np.testing.assert_allclose(result.translation, t, atol=1e-12)
    assert 0.5 < result.fitness <= 1.0 and result.n_inliers > 0 and np.isfinite(result.inlier_rmse)
    assert result.runtime_s > 0 and result.timings


# ------------------------------------------------------------------------------------------ accuracy
def test_icp_recovers_a_moderate_similarity(bunny):
    # ICP is local: a rotation of 15 degrees (its basin), scale 1.7 and a shift of about half the model
    T_gt = _similarity(1.7, 15.0, [1, 2, -1], [0.05, -0.03, 0.08])
    source, target = easy_pair(bunny, T_gt)
    _check(get_register_fn("icp")(source, target, BaselineConfig(), seed=1), T_gt, source, target)


@pytest.mark.parametrize("method", ["fpfh_ransac", "fgr"])
def test_global_feature_methods_recover_an_arbitrary_similarity(bunny, method):
    T_gt = _similarity(0.6, 150.0, [-0.3, 1.0, 0.4], [0.2, 0.1, -0.15])
    source, target = easy_pair(bunny, T_gt, seed=2)
    _check(get_register_fn(method)(source, target, BaselineConfig(), seed=5), T_gt, source, target)


@pytest.mark.slow  # ~7 s
def test_cpd_recovers_a_similarity(bunny):
    # CPD is local too (wider basin than ICP): 50 degrees, scale 2.5
    T_gt = _similarity(2.5, 50.0, [0.2, -1.0, 0.5], [-0.1, 0.3, 0.05])
    source, target = easy_pair(bunny, T_gt, seed=3)
    result = get_register_fn("cpd")(source, target, BaselineConfig(), seed=7)
    _check(result, T_gt, source, target)
    assert 1 < result.iterations <= BaselineConfig().cpd.max_iterations


def test_kiss_matcher_recovers_an_arbitrary_similarity(bunny):
    pytest.importorskip("kiss_matcher")
    # a large rotation and a scale of 0.6: the global matcher finds the pose, scaled ICP the scale
    T_gt = _similarity(0.6, 150.0, [-0.3, 1.0, 0.4], [0.2, 0.1, -0.15])
    source, target = easy_pair(bunny, T_gt, seed=2)
    result = get_register_fn("kiss_matcher")(source, target, BaselineConfig(), seed=5)
    _check(result, T_gt, source, target)
    err = transform_errors(result.transform, T_gt, float(np.linalg.norm(target.max(0) - target.min(0))))
    # measured with kiss-matcher 1.0.2: 0.25 deg, scale error 0.27 %, translation 0.3 % of the diagonal
    assert err.rot_err_deg < 0.6 and err.scale_err < 0.006 and err.trans_err_rel < 0.006, err
    assert {"kiss_matcher", "refine"} <= set(result.timings)
    # KISS-Matcher itself takes well under a second on these 8000/4000 points
    assert result.timings["kiss_matcher"] < 2.0


def test_kiss_matcher_failures_are_failed_results():
    pytest.importorskip("kiss_matcher")
    from gctr_cli.baselines.kiss import register_kiss_matcher

    rng = np.random.default_rng(0)
    good = rng.normal(size=(3000, 3))
    cfg = config_from_dict({"baselines": {"outlier_removal": "none"}}).baselines
    # 20 scattered points: no point has a Faster-PFH descriptor (kiss-matcher 1.0.2 would segfault)
    r = register_kiss_matcher(rng.normal(size=(20, 3)), good, cfg)
    assert r.status == "failed" and r.message.startswith("source: only 0 points with a Faster-PFH descriptor"), r
    # a sphere (every descriptor alike) against a Gaussian blob: KISS-Matcher runs and finds no solution
    sphere = rng.normal(size=(3000, 3))
    sphere /= np.linalg.norm(sphere, axis=1, keepdims=True)
    r = register_kiss_matcher(sphere, good, cfg)
    assert r.status == "failed" and r.message == "KISS-Matcher found no valid solution (0 inliers)", r
    assert r.transform.shape == (4, 4)


def test_kiss_matcher_without_the_package_fails_with_a_message(monkeypatch):
    import sys

    from gctr_cli.baselines.kiss import register_kiss_matcher

    monkeypatch.setitem(sys.modules, "kiss_matcher", None)  # import kiss_matcher -> ImportError
    rng = np.random.default_rng(0)
    r = register_kiss_matcher(rng.normal(size=(500, 3)), rng.normal(size=(500, 3)), BaselineConfig())
    assert r.status == "failed" and "pip install kiss-matcher" in r.message and "GPL" in r.message


def test_kiss_matcher_config_limits():
    cfg = config_from_dict({"method": "kiss_matcher", "baselines": {"kiss_matcher": {"metric_diagonal": 50}}})
    assert cfg.baselines.kiss_matcher.metric_diagonal == 50.0
    with pytest.raises(ConfigError, match="5 mm"):
        config_from_dict({"baselines": {"kiss_matcher": {"metric_diagonal": 0.1}}})
    with pytest.raises(ConfigError, match="solver_noise_bound_gain"):
        config_from_dict({"baselines": {"kiss_matcher": {"solver_noise_bound_gain": 2.0}}})


def test_cpd_core_exact_on_noise_free_correspondences():
    rng = np.random.default_rng(0)
    Y = rng.normal(size=(300, 3)) * [1.0, 0.6, 0.3]
    T = _similarity(1.3, 30.0, [1, 1, 0], [0.2, -0.1, 0.3])
    X = apply(T, Y)
    r = cpd_rigid(X, Y, w=0.0, max_iterations=200, tol=1e-10)
    assert r.scale == pytest.approx(1.3, rel=1e-4)
    np.testing.assert_allclose(r.scale * r.rotation, T[:3, :3], atol=1e-4)
    np.testing.assert_allclose(r.translation, T[:3, 3], atol=1e-4)


def test_normalisation_is_composed_back():
    rng = np.random.default_rng(1)
    a, b = rng.normal(size=(50, 3)) * 3 + 10, rng.normal(size=(60, 3)) * 0.2 - 4
    na, nb = box_normalise(a), box_normalise(b)
    assert np.linalg.norm(na.points.max(0) - na.points.min(0)) == pytest.approx(1.0)
    T_n = _similarity(1.1, 20.0, [0, 0, 1], [0.01, 0.02, 0.0])
    T = denormalise(T_n, na, nb)
    # T maps original source points exactly where T_n maps the normalised ones (in target units)
    np.testing.assert_allclose(apply(T, a), apply(T_n, na.points) * nb.size + nb.centre, atol=1e-9)


# ------------------------------------------------------------------------------------------ robustness
@pytest.mark.parametrize("method", BASELINES)
@pytest.mark.parametrize("case", ["too_few", "planar", "nan", "collinear"])
def test_degenerate_inputs_give_failed_results_not_exceptions(method, case):
    rng = np.random.default_rng(0)
    good = rng.normal(size=(500, 3))
    bad = {
        "too_few": good[:5],
        "planar": np.column_stack([rng.normal(size=(500, 2)), np.zeros(500)]),
        "nan": np.full((50, 3), np.nan),
        "collinear": np.outer(np.linspace(0, 1, 100), [1.0, 2.0, 3.0]),
    }[case]
    result = get_register_fn(method)(bad, good, BaselineConfig(), seed=0)
    assert result.status == "failed"
    assert "source" in result.message
    assert result.transform.shape == (4, 4)


def test_fpfh_ransac_is_deterministic(bunny):
    T_gt = _similarity(1.4, 100.0, [1, 0, 1], [0.1, 0.0, 0.1])
    source, target = easy_pair(bunny, T_gt, seed=4)
    a = register_fpfh_ransac(source, target, BaselineConfig(), seed=11)
    b = register_fpfh_ransac(source, target, BaselineConfig(), seed=11)
    assert a.status == b.status == "ok"
    np.testing.assert_array_equal(a.transform, b.transform)
    assert a.fitness == b.fitness


# ------------------------------------------------------------------------------------------ config
def test_method_dispatch_and_config_section():
    assert METHODS == ("gctr", "icp", "fpfh_ransac", "fgr", "cpd", "kiss_matcher")
    assert set(REGISTER_FUNCTIONS) == set(BASELINES)
    for name, fn in REGISTER_FUNCTIONS.items():
        assert get_register_fn(name) is fn
        cfg = Config(method=name)
        assert method_config(cfg) is cfg.baselines
    cfg = Config()
    assert method_config(cfg) is cfg.engine
    with pytest.raises(ValueError, match="unknown method"):
        get_register_fn("go_icp")


def test_the_registry_is_the_only_list_of_methods():
    """Config, baselines package and benchmark all derive their method lists from gctr_cli.methods.REGISTRY."""
    import typing

    from data_scripts import bench_compare
    from gctr_cli.config import Config as ConfigModel
    from gctr_cli.methods import REGISTRY

    assert typing.get_args(ConfigModel.model_fields["method"].annotation) == METHODS == tuple(REGISTRY)
    assert bench_compare.METHODS == METHODS
    assert set(bench_compare.METHOD_DESCRIPTIONS) == set(METHODS)
    for name in METHODS:
        fn = get_register_fn(name)
        assert fn.__name__ == REGISTRY[name].function and callable(fn)
    with pytest.raises(ConfigError, match=r"Input should be 'gctr', .* or 'kiss_matcher'"):
        config_from_dict({"method": "go_icp"})


def test_config_method_and_baselines_section():
    cfg = config_from_dict({"method": "cpd", "baselines": {"cpd": {"w": 0.3, "max_points": 500}}})
    assert cfg.method == "cpd" and cfg.baselines.cpd.w == 0.3 and cfg.baselines.cpd.max_points == 500
    with pytest.raises(ConfigError, match="method"):
        config_from_dict({"method": "super4pcs"})
    with pytest.raises(ConfigError, match=r"baselines\.ransac\.iters: unknown key"):
        config_from_dict({"baselines": {"ransac": {"iters": 5}}})
    with pytest.raises(ConfigError, match=r"baselines\.cpd\.w"):
        config_from_dict({"baselines": {"cpd": {"w": 1.0}}})


def test_config_show_documents_the_baselines_section():
    out = CliRunner().invoke(cli.main, ["config", "show"], catch_exceptions=False).output
    assert "baselines:" in out and "voxel_ratio: 0.02  # voxel size / bbox diagonal" in out
    assert "one of: gctr, icp, fpfh_ransac, fgr, cpd, kiss_matcher" in out
    assert "kiss_matcher:\n    metric_diagonal: 20.0" in out
    yaml.safe_load(out)


# ------------------------------------------------------------------------------------------ batch
@pytest.mark.slow  # ~7-8 s
def test_gctr_batch_with_method_fpfh_ransac(bunny, tmp_path):
    """The user-facing path: a manifest, a config with ``method: fpfh_ransac``, ``gctr batch``."""
    from gctr_cli.batch import ERRORS_COLUMNS, TRANSFORMS_COLUMNS, derive_seed
    from gctr_cli.io import write_matrix

    data = tmp_path / "data"
    rows, truths = [], {}
    for k, (angle, scale) in enumerate([(120.0, 0.7), (40.0, 1.8)]):
        T_gt = _similarity(scale, angle, [1, -1, 2], [0.1 * k, 0.05, -0.1])
        source, target = easy_pair(bunny, T_gt, seed=10 + k)
        pid = f"bunny_{k}"
        write_cloud(data / f"{pid}_src.ply", source)
        write_cloud(data / f"{pid}_tgt.ply", target)
        write_matrix(data / f"{pid}_gt.txt", T_gt)
        rows.append({"pair_id": pid, "source": f"{pid}_src.ply", "target": f"{pid}_tgt.ply", "gt": f"{pid}_gt.txt"})
        truths[pid] = T_gt
    manifest = write_manifest_rows(data / "pairs.csv", rows)
    config = tmp_path / "fpfh.yaml"
    config.write_text("method: fpfh_ransac\nseed: 3\n")
    out = tmp_path / "out"
    res = CliRunner().invoke(cli.main, ["batch", str(manifest), "-c", str(config), "-o", str(out), "-j", "2", "-q"],
                             catch_exceptions=False)
    assert res.exit_code == 0, res.output
    header, trows = read_csv(out / "transforms.csv")
    assert tuple(header) == TRANSFORMS_COLUMNS
    eheader, erows = read_csv(out / "tm_errors.csv")
    assert tuple(eheader) == ERRORS_COLUMNS
    assert {r["pair_id"] for r in trows} == set(truths)
    assert all(r["status"] == "ok" and r["message"] == "" for r in trows), trows
    assert {r["pair_id"] for r in erows} == set(truths) and all(r["success"] == "true" for r in erows), erows
    assert yaml.safe_load((out / "config.yaml").read_text())["method"] == "fpfh_ransac"
    # the batch row is exactly what the function gives in this process with the pair's seed
    for r in trows:
        src = load_point_cloud(data / f"{r['pair_id']}_src.ply")
        tgt = load_point_cloud(data / f"{r['pair_id']}_tgt.ply")
        seed = derive_seed(3, r["pair_id"])
        assert int(r["seed"]) == seed
        again = register_fpfh_ransac(src, tgt, BaselineConfig(), seed=seed)
        np.testing.assert_array_equal(row_matrix(r), again.transform)
