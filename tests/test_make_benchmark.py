"""Tests of the shipped data and of the benchmark generator (data_scripts/make_benchmark.py)."""

from __future__ import annotations

import csv
import dataclasses
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial import cKDTree

from data_scripts import make_benchmark as mb
from data_scripts.common import bbox_diagonal, read_matrix, read_points, read_pose_file, transform, write_points

DATA = Path(__file__).resolve().parents[1] / "data"


@pytest.fixture(scope="module")
def bunny() -> np.ndarray:
    return read_points(DATA / "models" / "bunny.ply")


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
        mapped = transform(pair.T_gt, pair.source)
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
    d_src = tree.query(transform(pair.T_gt, pair.source[~pair.src_outlier]))[0]
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
    np.testing.assert_array_equal(read_points(tmp_path / f"c.{fmt}"), pts)


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
        src, tgt, T = read_points(out / r["source"]), read_points(out / r["target"]), read_matrix(out / r["gt"])
        assert np.cbrt(np.linalg.det(T[:3, :3])) == pytest.approx(float(r["scale_gt"]), rel=1e-12)
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
    b000, b045 = read_points(DATA / "scans/bun000.ply"), read_points(DATA / "scans/bun045.ply")
    T = np.linalg.inv(poses["bun000"]) @ poses["bun045"]  # target_from_source
    tree = cKDTree(b000)
    assert np.median(tree.query(transform(T, b045))[0]) < 1e-3  # < 1 mm
    assert np.median(tree.query(b045)[0]) > 1e-2  # identity: > 1 cm
    assert np.median(tree.query(transform(np.linalg.inv(T), b045))[0]) > 1e-2  # the inverse is wrong

    # the cross-source real pair: random similarity on the source, T_gt still maps it onto the target
    pair = mb.make_real_pair(b045, b000, poses["bun045"], poses["bun000"], np.random.default_rng(0), n_source=6000)
    assert len(pair.source) == 6000 and len(pair.target) == 1500
    assert 0.5 <= pair.scale <= 2.0
    assert np.median(tree.query(transform(pair.T_gt, pair.source))[0]) < 1e-3
    assert np.median(tree.query(pair.source)[0]) > 1e-2
