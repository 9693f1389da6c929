"""Tests of the shipped data and of the benchmark generator (data_scripts/make_benchmark.py)."""

from __future__ import annotations

import csv
import dataclasses
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial import cKDTree

from data_scripts import make_benchmark as mb
from data_scripts.common import bbox_diagonal, read_pose_file, write_points
from gctr_cli.geometry import apply, invert, split
from gctr_cli.io import load_point_cloud, read_matrix

DATA = Path(__file__).resolve().parents[1] / "data"


@pytest.fixture(scope="module")
def bunny() -> np.ndarray:
    return load_point_cloud(DATA / "models" / "bunny.ply")


def _clean(level: mb.Level) -> mb.Level:
    """The level's similarity range, but no noise, no outliers, no crop, same density."""
    return dataclasses.replace(level, density=1.0, noise=0.0, outliers=0.0, crop_lo=1.0, crop_hi=1.0)


# ------------------------------------------------------------------------------------------ generator
@pytest.mark.parametrize("level_name", list(mb.LEVELS))
def test_clean_pair_satisfies_ground_truth(bunny, level_name):
    level = mb.LEVELS[level_name]
    for k in range(3):
        pair = mb.make_pair(bunny, _clean(level), mb.pair_rng(0, level_name, "bunny", k), n_source=5000)
        assert len(pair.source) == len(pair.target) == 5000
        mapped = apply(pair.T_gt, pair.source)
        d_model = cKDTree(bunny).query(mapped)[0]
        assert d_model.max() < 1e-9 * bbox_diagonal(bunny)  # T_gt @ source lies exactly on the model
        # ... and the source itself is far from it (it really was moved)
        assert np.median(cKDTree(bunny).query(pair.source)[0]) > 0.01 * bbox_diagonal(bunny)
        assert level.s_lo <= pair.scale <= level.s_hi
        A = pair.T_gt[:3, :3] / pair.scale
        np.testing.assert_allclose(A @ A.T, np.eye(3), atol=1e-12)
        assert np.linalg.det(A) > 0
        np.testing.assert_array_equal(pair.T_gt[3], [0, 0, 0, 1])
        assert np.linalg.norm(pair.T_gt[:3, 3]) <= level.t_radius * bbox_diagonal(bunny)


def test_cross_pair_counts_noise_and_outliers(bunny):
    level = mb.LEVELS["cross"]
    pair = mb.make_pair(bunny, level, mb.pair_rng(0, "cross", "bunny", 0), n_source=20000)
    n_src, n_tgt = len(pair.source), len(pair.target)
    assert n_src == 20000
    assert abs(n_tgt / n_src - level.density) < 1e-3
    assert abs(pair.src_outlier.mean() - level.outliers) < 1e-3
    assert abs(pair.tgt_outlier.mean() - level.outliers) < 1e-3
    # outliers are shuffled in, not appended at the end
    assert 0 < pair.src_outlier[: n_src // 2].sum() < pair.src_outlier.sum()
    # inliers: on the model up to the noise (sigma = 0.5 % of the model diagonal, 3D -> ~1.6 sigma typical)
    sigma = level.noise * bbox_diagonal(bunny)
    tree = cKDTree(bunny)
    d_src = tree.query(apply(pair.T_gt, pair.source[~pair.src_outlier]))[0]
    d_tgt = tree.query(pair.target[~pair.tgt_outlier])[0]
    assert np.median(d_src) < 2 * sigma and np.median(d_tgt) < 2 * sigma
    assert np.median(tree.query(pair.target[pair.tgt_outlier])[0]) > 3 * sigma
    # outliers inside the cloud's bbox enlarged by 10 %
    inl = pair.target[~pair.tgt_outlier]
    lo, hi = inl.min(0), inl.max(0)
    assert np.all(pair.target >= lo - 0.05 * (hi - lo) - 1e-12) and np.all(pair.target <= hi + 0.05 * (hi - lo) + 1e-12)
    # partial overlap: crops keep 70-90 %, so each cloud covers only part of the other
    assert 0.3 < pair.overlap_src < 1.0 and 0.3 < pair.overlap_tgt < 1.0


def test_crop_by_plane_keeps_fraction(bunny):
    rng = np.random.default_rng(1)
    for keep in (0.5, 0.7, 0.9):
        mask = mb.crop_by_plane(bunny, keep, rng)
        assert abs(mask.mean() - keep) < 1e-3
    assert mb.crop_by_plane(bunny, 1.0, rng).all()


def test_random_similarity_ranges():
    rng = np.random.default_rng(2)
    scales = []
    for _ in range(200):
        T = mb.random_similarity(rng, 0.25, 4.0, 3.0)
        s = np.cbrt(np.linalg.det(T[:3, :3]))
        scales.append(s)
        assert 0.25 <= s <= 4.0 and np.linalg.norm(T[:3, 3]) <= 3.0
    assert min(scales) < 0.5 and max(scales) > 2.0  # log-uniform: both ends are reached


def test_determinism(bunny):
    level = mb.LEVELS["hard"]
    a = mb.make_pair(bunny, level, mb.pair_rng(7, "hard", "bunny", 3), n_source=3000)
    b = mb.make_pair(bunny, level, mb.pair_rng(7, "hard", "bunny", 3), n_source=3000)
    c = mb.make_pair(bunny, level, mb.pair_rng(7, "hard", "bunny", 4), n_source=3000)
    np.testing.assert_array_equal(a.source, b.source)
    np.testing.assert_array_equal(a.target, b.target)
    np.testing.assert_array_equal(a.T_gt, b.T_gt)
    assert not np.array_equal(a.T_gt, c.T_gt)
    assert not np.array_equal(a.target[:100], c.target[:100])


@pytest.mark.parametrize("fmt", ["ply", "pcd", "xyz"])
def test_written_clouds_are_exact(tmp_path, fmt):
    pts = np.random.default_rng(3).normal(size=(500, 3)) * 1e3
    write_points(tmp_path / f"c.{fmt}", pts)
    np.testing.assert_array_equal(load_point_cloud(tmp_path / f"c.{fmt}"), pts)


def test_generate_layout_and_byte_identical(tmp_path, bunny):
    models = {"bunny": bunny, "tiny": bunny[::7]}
    outs = []
    for run in ("a", "b"):
        out = tmp_path / run
        rows = mb.generate_synthetic(models, ["easy", "cross"], 2, 0, out, ["ply", "pcd", "xyz"], n_source=2000)
        mb.write_manifest(out / "pairs.csv", rows)
        outs.append(out)
    files = sorted(p.relative_to(outs[0]) for p in outs[0].rglob("*") if p.is_file())
    assert len(files) == 2 * (4 * 3 + 1) + 1
    for rel in files:
        assert (outs[0] / rel).read_bytes() == (outs[1] / rel).read_bytes(), rel

    out = outs[0]
    with open(out / "pairs.csv", newline="") as fh:
        rows = list(csv.DictReader(fh))
    assert list(rows[0])[:4] == ["pair_id", "source", "target", "gt"]
    assert len({r["pair_id"] for r in rows}) == len(rows) == 8
    assert [Path(r["source"]).suffix for r in rows[:4]] == [".ply", ".pcd", ".xyz", ".ply"]
    for r in rows:
        src, tgt = load_point_cloud(out / r["source"]), load_point_cloud(out / r["target"])
        T = read_matrix(out / r["gt"])
        assert split(T)[0] == pytest.approx(float(r["scale_gt"]), rel=1e-12)
        assert len(tgt) < len(src)
    with open(out / "cross" / "pairs.csv", newline="") as fh:
        level_rows = list(csv.DictReader(fh))
    assert len(level_rows) == 4 and all((out / "cross" / r["source"]).is_file() for r in level_rows)


def test_demo_command(tmp_path):
    from click.testing import CliRunner

    res = CliRunner().invoke(mb.cli, ["demo", "--out", str(tmp_path / "demo")])
    assert res.exit_code == 0, res.output
    with open(tmp_path / "demo" / "pairs.csv", newline="") as fh:
        rows = list(csv.DictReader(fh))
    assert len(rows) == 8 and {r["level"] for r in rows} == {"cross", "real"}
    assert {Path(r["source"]).suffix for r in rows} == {".ply", ".pcd", ".xyz"}


# ------------------------------------------------------------------------------------------ shipped data
EXPECTED = {
    "models/bunny.ply": (35947, 35947),
    "models/dragon.ply": (30000, 40000),
    "models/redkitchen.ply": (30000, 40000),
    **{f"scans/{n}.ply": (8000, 10000) for n in mb.SHIP_SCANS},
}


def test_shipped_files_load_with_open3d():
    import open3d as o3d

    for rel, (lo, hi) in EXPECTED.items():
        pcd = o3d.io.read_point_cloud(str(DATA / rel))
        pts = np.asarray(pcd.points)
        assert lo <= len(pts) <= hi, rel
        assert np.isfinite(pts).all()
        assert b"property float x" in (DATA / rel).read_bytes()[:600]  # float32 xyz
    assert (DATA / "ATTRIBUTION.md").is_file()
    total = sum(p.stat().st_size for p in DATA.rglob("*") if p.is_file() and "demo" not in p.relative_to(DATA).parts)
    assert total < 3_000_000


def test_shipped_poses_and_real_ground_truth():
    poses = read_pose_file(DATA / "scans" / "poses.txt")
    assert set(poses) == set(mb.SHIP_SCANS)
    np.testing.assert_array_equal(poses["bun000"], np.eye(4))
    b000, b045 = load_point_cloud(DATA / "scans/bun000.ply"), load_point_cloud(DATA / "scans/bun045.ply")
    T = invert(poses["bun000"]) @ poses["bun045"]  # target_from_source
    tree = cKDTree(b000)
    assert np.median(tree.query(apply(T, b045))[0]) < 1e-3  # < 1 mm
    assert np.median(tree.query(b045)[0]) > 1e-2  # identity: > 1 cm
    assert np.median(tree.query(apply(invert(T), b045))[0]) > 1e-2  # the inverse is wrong

    # the cross-source real pair: random similarity on the source, T_gt still maps it onto the target
    pair = mb.make_real_pair(b045, b000, poses["bun045"], poses["bun000"], np.random.default_rng(0), n_source=6000)
    assert len(pair.source) == 6000 and len(pair.target) == 1500
    assert 0.5 <= pair.scale <= 2.0
    assert np.median(tree.query(apply(pair.T_gt, pair.source))[0]) < 1e-3
    assert np.median(tree.query(pair.source)[0]) > 1e-2


# ------------------------------------------------------------------------------------------ issue 9 levels
def _on_model(model: np.ndarray, pts: np.ndarray) -> np.ndarray:
    """Distance of each point to the nearest model point."""
    return cKDTree(model).query(pts)[0]


def test_part_level_patch_fraction_and_direction(tmp_path, bunny):
    diag = bbox_diagonal(bunny)
    sigma = mb.PART["noise"] * diag
    rows = mb.generate_special({"bunny": bunny}, ["part"], 4, 0, tmp_path, ["ply"], n_source=20000)
    assert [r["patch"] for r in rows] == ["source", "target", "source", "target"]  # direction alternates with k
    for k, r in enumerate(rows):
        fraction = float(r["patch_fraction"])
        assert 0.15 <= fraction <= 0.40
        pair, frac2 = mb.make_part_pair(bunny, mb.pair_rng(0, "part", "bunny", k), patch_is_source=(k % 2 == 0))
        assert frac2 == pytest.approx(fraction, abs=1e-4)
        patch, whole = (pair.source, pair.target) if k % 2 == 0 else (pair.target, pair.source)
        p_out, w_out = (pair.src_outlier, pair.tgt_outlier) if k % 2 == 0 else (pair.tgt_outlier, pair.src_outlier)
        if k % 2 == 0:
            patch = apply(pair.T_gt, patch)
        else:
            whole = apply(pair.T_gt, whole)
        assert abs(p_out.mean() - 0.10) < 2e-3 and abs(w_out.mean() - 0.10) < 2e-3
        inl_p, inl_w = patch[~p_out], whole[~w_out]
        assert np.median(_on_model(bunny, inl_p)) < 2 * sigma and np.median(_on_model(bunny, inl_w)) < 2 * sigma
        # the patch is compact and covers `fraction` of the model; the whole covers all of it
        d = np.linalg.norm(bunny - inl_p.mean(axis=0), axis=1)
        covered = cKDTree(inl_p).query(bunny)[0] < 3 * sigma
        assert fraction - 0.05 < covered.mean() < fraction + 0.08
        assert d[covered].max() < 1.3 * np.quantile(d, fraction + 0.08)  # one blob, not scattered
        assert (cKDTree(inl_w).query(bunny)[0] < 3 * sigma).mean() > 0.95
        # whole at 1/4 of the patch's density (the patch keeps all its model points here)
        assert len(inl_w) == pytest.approx(len(bunny) / 4, rel=0.01)
        assert len(inl_p) == pytest.approx(fraction * len(bunny), rel=0.01)
        ov_patch, ov_whole = ((pair.overlap_src, pair.overlap_tgt) if k % 2 == 0
                              else (pair.overlap_tgt, pair.overlap_src))
        assert ov_patch == 1.0 and ov_whole == pytest.approx(fraction, abs=0.03)
        assert 0.5 <= pair.scale <= 2.0


def test_lowoverlap_level_overlap_in_range(bunny):
    diag = bbox_diagonal(bunny)
    for k in range(4):
        pair = mb.make_lowoverlap_pair(bunny, mb.pair_rng(0, "lowoverlap", "bunny", k), n_source=8000)
        assert 0.23 <= pair.overlap_src <= 0.52 and 0.23 <= pair.overlap_tgt <= 0.52
        assert 0.05 - 2e-3 <= pair.src_outlier.mean() <= 0.10 + 2e-3
        assert len(pair.target) / len(pair.source) == pytest.approx(0.25, abs=2e-3)
        # geometric check of the overlap: source inliers (mapped) near the target's crop of the model
        src = apply(pair.T_gt, pair.source[~pair.src_outlier])
        tgt = pair.target[~pair.tgt_outlier]
        assert np.median(_on_model(bunny, src)) < 2 * mb.LOWOVERLAP["noise"] * diag
        near = cKDTree(tgt).query(src)[0] < 0.02 * diag
        assert pair.overlap_src - 0.1 < near.mean() < pair.overlap_src + 0.15


def test_sfm_level_density_holes_noise_and_floaters(bunny):
    diag = bbox_diagonal(bunny)
    rng_uniform = np.random.default_rng(5)
    for k in range(2):
        pair = mb.make_sfm_pair(bunny, mb.pair_rng(0, "sfm", "bunny", k), n_source=20000)
        assert 0.5 <= pair.scale <= 2.0
        assert 0.05 - 2e-3 <= pair.tgt_outlier.mean() <= 0.10 + 2e-3 and not pair.src_outlier.any()
        tgt, floaters = pair.target[~pair.tgt_outlier], pair.target[pair.tgt_outlier]
        # density across the surface: target inliers per model point in balls of 4 % of the diagonal
        r = 0.04 * diag
        n_model = np.array([len(x) for x in cKDTree(bunny).query_ball_point(bunny[::20], r)])
        n_tgt = np.array([len(x) for x in cKDTree(tgt).query_ball_point(bunny[::20], r)])
        ratio = n_tgt[n_model >= 50] / n_model[n_model >= 50]
        assert np.quantile(ratio[ratio > 0], 0.95) / np.quantile(ratio[ratio > 0], 0.05) >= 10
        assert (ratio == 0).mean() > 0.01  # holes: regions of the model with no target point
        # clustered floaters: much closer to each other than as many uniform points in the same box
        lo, hi = pair.target.min(0), pair.target.max(0)
        uniform = rng_uniform.uniform(lo, hi, size=floaters.shape)
        nn_f = cKDTree(floaters).query(floaters, k=2)[0][:, 1]
        nn_u = cKDTree(uniform).query(uniform, k=2)[0][:, 1]
        assert np.median(nn_f) < 0.4 * np.median(nn_u)
        assert np.median(_on_model(bunny, floaters)) < 0.08 * diag  # near the surface
        # source: clean-ish scan-like crop of 70-100 % of the model
        src = apply(pair.T_gt, pair.source)
        assert len(src) == 20000 and np.median(_on_model(bunny, src)) < 2 * mb.SFM["src_noise"] * diag


def test_anisotropic_noise():
    camera = np.array([0.6, 0.0, 0.8])
    noise = mb.anisotropic_noise(50000, camera, 0.01, 0.002, np.random.default_rng(0))
    w, v = np.linalg.eigh(np.cov(noise.T))
    assert np.sqrt(w[-1]) == pytest.approx(0.01, rel=0.03) and np.sqrt(w[:2]) == pytest.approx([0.002] * 2, rel=0.03)
    assert abs(v[:, -1] @ camera) > 0.999


def test_slab_pair_overlap_and_horizontal_windows(bunny):
    for overlap in (0.25, 0.5):
        a, b = mb.slab_pair(bunny, overlap, 0.9, np.random.default_rng(1))
        assert (a & b).sum() / a.sum() == pytest.approx(overlap, abs=0.01)
        assert (a & b).sum() / b.sum() == pytest.approx(overlap, abs=0.01)
    # with a plane normal the windows slide perpendicular to it: moving points along it changes nothing
    up = np.array([0.0, 0.0, 1.0])
    lifted = bunny + np.outer(np.random.default_rng(2).normal(size=len(bunny)), up)
    m1 = mb.slab_pair(bunny, 0.4, 0.9, np.random.default_rng(3), up)
    m2 = mb.slab_pair(lifted, 0.4, 0.9, np.random.default_rng(3), up)
    np.testing.assert_array_equal(m1[0], m2[0])
    np.testing.assert_array_equal(m1[1], m2[1])


SHARED = mb.default_shared()
needs_shared = pytest.mark.skipif(
    SHARED is None or not all((SHARED / rel).is_file() for rel in [*mb.SCENE_FILES.values(), mb.KITCHEN_GT_LOG]),
    reason="shared data folder (../shared/data) with the scene files not available")


@pytest.fixture(scope="module")
def scenes():
    return mb.load_scenes(SHARED)


@needs_shared
def test_scene_window_pairs_ground_truth(scenes):
    clouds, _ = scenes
    for name in ("nclt", "redkitchen0"):
        scene = clouds[name]
        for k in range(2):
            pair = mb.make_scene_window_pair(scene, mb.pair_rng(0, "scene", name, k), n_source=6000,
                                             up=mb.SCENE_UP.get(name))
            assert 0.23 <= pair.overlap_src <= 0.62 and 0.23 <= pair.overlap_tgt <= 0.62
            assert 0.5 <= pair.scale <= 2.0
            assert abs(pair.src_outlier.mean() - 0.05) < 2e-3
            assert 1 / 4 - 0.01 <= len(pair.target) / len(pair.source) <= 1 / 2 + 0.01
            src = apply(pair.T_gt, pair.source[~pair.src_outlier])
            sigma_max = mb.SCENE["noise_hi"] * bbox_diagonal(scene)
            assert np.median(_on_model(scene, src)) < 2 * sigma_max  # the truth maps the source onto the scene
            assert np.median(_on_model(scene, pair.source)) > 5 * sigma_max  # and the source was moved


@needs_shared
def test_scene_real_kitchen_pair(tmp_path, scenes):
    clouds, T_4to0 = scenes
    frag4 = cKDTree(clouds["redkitchen4"])
    rows = mb.generate_scene({"redkitchen0": clouds["redkitchen0"], "redkitchen4": clouds["redkitchen4"]}, T_4to0,
                             0, tmp_path, ["ply"], n_source=4000, windows_per_scene=0, real_pairs=2)
    assert [r["model"] for r in rows] == ["redkitchen0>4"] * 2
    for r in rows:
        src, tgt = load_point_cloud(tmp_path / r["source"]), load_point_cloud(tmp_path / r["target"])
        T = read_matrix(tmp_path / r["gt"])
        assert len(src) == 4000 and 1000 <= len(tgt) <= 2000
        assert (frag4.query(apply(T, src))[0] < 0.03).mean() > 0.3  # ~half of fragment 0 overlaps 4
        assert (frag4.query(src)[0] < 0.03).mean() < 0.05


@needs_shared
def test_scene_noise_option_sets_the_windows_noise(tmp_path, scenes):
    """--scene-noise replaces the windows' 0.3-0.5 % noise (here by LiDAR-like 0.02-0.03 %); the same seed
    draws the same windows, so only the noise differs."""
    clouds, T_4to0 = scenes
    nclt = {"nclt": clouds["nclt"]}
    quiet = mb.generate_scene(nclt, T_4to0, 5, tmp_path / "q", ["ply"], n_source=3000, windows_per_scene=1,
                              real_pairs=0, noise=(0.0002, 0.0003))
    loud = mb.generate_scene(nclt, T_4to0, 5, tmp_path / "l", ["ply"], n_source=3000, windows_per_scene=1,
                             real_pairs=0)
    diag = bbox_diagonal(clouds["nclt"])
    residual = {}
    for name, rows in (("quiet", quiet), ("loud", loud)):
        folder = tmp_path / ("q" if name == "quiet" else "l")
        src = load_point_cloud(folder / rows[0]["source"])
        T = read_matrix(folder / rows[0]["gt"])
        residual[name] = float(np.median(_on_model(clouds["nclt"], apply(T, src))))
    assert quiet[0]["overlap_src"] == loud[0]["overlap_src"]  # the same windows
    assert residual["quiet"] < 2 * 0.0003 * diag < residual["loud"]


@pytest.mark.parametrize("value", ["0.005,0.003", "x", "0.1,0.2", "-0.001,0.002"])
def test_scene_noise_option_rejects_bad_values(tmp_path, value):
    from click.testing import CliRunner

    res = CliRunner().invoke(mb.cli, ["generate", "--levels", "scene", f"--scene-noise={value}", "--out",
                                      str(tmp_path)])
    assert res.exit_code == 2 and "--scene-noise" in res.output
    assert not (tmp_path / "pairs.csv").exists()


def test_scene_noise_without_the_scene_level_is_a_usage_error(tmp_path):
    from click.testing import CliRunner

    res = CliRunner().invoke(mb.cli, ["generate", "--levels", "easy", "--scene-noise", "0.0002,0.0003", "--out",
                                      str(tmp_path)])
    assert res.exit_code == 2 and "--scene-noise only applies to level 'scene'" in res.output
    assert not (tmp_path / "pairs.csv").exists()


def test_a_bad_models_file_or_an_out_under_a_file_is_one_line(tmp_path):
    """They ended in a 30-line traceback (found by an audit)."""
    from click.testing import CliRunner

    (tmp_path / "afile").write_text("x")
    for args, expected in ((["--models", str(tmp_path / "none.ply"), "--out", str(tmp_path / "d")],
                            "Invalid value for --models: " + str(tmp_path / "none.ply") + ": file does not exist"),
                           (["--out", str(tmp_path / "afile" / "sub")],
                            f"Invalid value for --out: {tmp_path / 'afile' / 'sub'}: {tmp_path / 'afile'} is a file")):
        res = CliRunner().invoke(mb.cli, ["generate", "--levels", "easy", "--pairs-per-model", "1", *args])
        assert res.exit_code == 2 and expected in res.output, res.output
        assert res.exception is None or isinstance(res.exception, SystemExit)


def test_nothing_to_generate_is_a_usage_error(tmp_path):
    """``--levels ''`` or 0 pairs per model wrote an empty pairs.csv and exited 0 (found by an audit)."""
    from click.testing import CliRunner

    for args, expected in ((["--levels", " , "], "Invalid value for --levels: no level given"),
                           (["--levels", "easy", "--pairs-per-model", "0"],
                            "Invalid value for --pairs-per-model: 0 pairs per model and no level with real pairs"),
                           (["--levels", "easy", "--models", " , "], "Invalid value for --models: no model given")):
        res = CliRunner().invoke(mb.cli, ["generate", *args, "--out", str(tmp_path / "d")])
        assert res.exit_code == 2 and expected in res.output, res.output
        assert not (tmp_path / "d").exists()


def test_scene_missing_shared_file_is_named(tmp_path):
    (tmp_path / "real" / "nclt_lidar").mkdir(parents=True)
    with pytest.raises(Exception, match=r"cloud_bin_0\.ply"):
        mb.load_scenes(tmp_path)


def test_new_levels_deterministic_and_independent(tmp_path, bunny):
    small = {"bunny": bunny[::4]}
    a = mb.generate_special(small, ["part", "lowoverlap", "sfm"], 2, 3, tmp_path / "a", ["ply", "xyz"], n_source=1500)
    b = mb.generate_special(small, ["sfm"], 2, 3, tmp_path / "b", ["ply", "xyz"], n_source=1500)
    assert len(a) == 6 and len(b) == 2
    for rel in ("sfm/sfm_bunny_0_src.ply", "sfm/sfm_bunny_1_tgt.xyz", "sfm/sfm_bunny_1_gt.txt", "sfm/pairs.csv"):
        assert (tmp_path / "a" / rel).read_bytes() == (tmp_path / "b" / rel).read_bytes(), rel
    c = mb.generate_special(small, ["sfm"], 2, 4, tmp_path / "c", ["ply", "xyz"], n_source=1500)  # another seed
    gt_name = "sfm/sfm_bunny_0_gt.txt"
    assert (tmp_path / "c" / gt_name).read_bytes() != (tmp_path / "b" / gt_name).read_bytes()
    assert len(c) == 2


@pytest.mark.skipif(SHARED is None or not (SHARED / mb.DRAGON_SCANS / mb.DRAGON_POSES).is_file(),
                    reason="shared dragon scans not available")
def test_real_level_three_groups_and_ground_truth(tmp_path):
    scans, poses = mb.load_scans()
    dragon, dposes = mb.load_dragon_scans(SHARED)
    recon = load_point_cloud(DATA / "models" / "bunny.ply")
    assert len(mb.REAL_PAIRS) * mb.REAL_DRAWS + len(mb.REAL_DRAGON_PAIRS) * mb.REAL_DRAWS_DRAGON + 6 >= 30
    rows = mb.generate_real_all(scans, poses, dragon, dposes, recon, 0, tmp_path, ["ply"], n_source=1500,
                                draws=2, dragon_draws=1)
    assert len(rows) == 12 + 6 + 6 and len({r["pair_id"] for r in rows}) == len(rows)
    assert {r["model"] for r in rows} == {"bunny_scans", "dragon_scans", "bunny_scan2recon"}
    by_id = {r["pair_id"]: r for r in rows}
    # draws of the same scan pair differ (another similarity)
    assert read_matrix(tmp_path / by_id["real_bun045_to_bun000"]["gt"]).tolist() != \
        read_matrix(tmp_path / by_id["real_bun045_to_bun000_d1"]["gt"]).tolist()
    for r in rows[::3]:
        src, tgt, T = (load_point_cloud(tmp_path / r["source"]), load_point_cloud(tmp_path / r["target"]),
                       read_matrix(tmp_path / r["gt"]))
        d = cKDTree(tgt).query(apply(T, src))[0]
        # the overlapping part lands on the (sparse: 1/4 of 1500 points) target within a few mm; unmoved it does not
        assert np.quantile(d, 0.3) < 0.006, r["pair_id"]
        assert np.quantile(cKDTree(tgt).query(src)[0], 0.3) > 3 * np.quantile(d, 0.3)
