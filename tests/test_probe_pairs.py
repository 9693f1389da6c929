"""data_scripts.probe_pairs: sparse, unrelated and mirrored pairs drawn reproducibly from the shipped models."""

from __future__ import annotations

import csv

import numpy as np
import pytest
from scipy.spatial import cKDTree

from data_scripts.probe_pairs import _cropped_subset, main, mirrored_pair, sparse_pair, unrelated_pair
from gctr_cli.geometry import apply

pytestmark = pytest.mark.engine


def test_sparse_pair_is_two_subsets_related_by_the_true_similarity():
    model = np.random.default_rng(0).normal(size=(5000, 3))
    source, target, T = sparse_pair(model, 300, 0.0, 7)
    assert source.shape == target.shape == (300, 3)
    moved = apply(T, source)  # the true similarity takes the source back onto model points
    assert cKDTree(model).query(moved)[0].max() < 1e-9
    assert cKDTree(model).query(target)[0].max() == 0.0
    again = sparse_pair(model, 300, 0.0, 7)
    assert np.array_equal(again[0], source) and np.array_equal(again[2], T)


def test_probe_counts_outcomes_per_size(tmp_path):
    out, rows_csv = tmp_path / "sparse.md", tmp_path / "rows.csv"
    assert main(["--offset", "0", "--sizes", "800", "--reps", "1", "--noise", "0", "--out", str(out),
                 "--csv", str(rows_csv)]) == 0
    with open(rows_csv) as fh:
        rows = list(csv.DictReader(fh))
    assert [r["model"] for r in rows] == ["bunny", "dragon", "redkitchen"]
    dragon = rows[1]  # the pair of tests/test_engine_verdict.py::test_a_clear_sparse_answer_is_still_accepted
    assert dragon["outcome"] == "right" and float(dragon["rot_err_deg"]) < 1.0
    text = out.read_text()
    counts = [sum(r["outcome"] == k for r in rows) for k in ("right", "silent wrong", "refused right", "refused wrong")]
    assert f"| 800 | 3 | {' | '.join(map(str, counts))} |" in text


def test_unrelated_pair_crops_one_model_and_subsamples_the_other():
    rng = np.random.default_rng(1)
    a, b = rng.normal(size=(4000, 3)), rng.normal(size=(3000, 3)) + 10.0
    source, target, T = unrelated_pair(a, b, 1000, 0.0, 5)
    assert 500 <= len(source) <= 1000 and target.shape == (1000, 3)
    assert cKDTree(a).query(apply(np.linalg.inv(T), source))[0].max() < 1e-9  # from the first model, moved
    assert cKDTree(b).query(target)[0].max() == 0.0


def test_unrelated_probe_counts_every_ok_as_silent_wrong(tmp_path):
    rows_csv = tmp_path / "rows.csv"
    assert main(["--kind", "unrelated", "--offset", "0", "--sizes", "1000", "--reps", "1", "--csv",
                 str(rows_csv), "--out", str(tmp_path / "u.md")]) == 0
    with open(rows_csv) as fh:
        rows = list(csv.DictReader(fh))
    assert len(rows) == 6 and {r["model"] for r in rows} >= {"bunny>dragon", "redkitchen>bunny"}
    assert all(r["outcome"] == ("silent wrong" if r["status"] == "ok" else "refused wrong") for r in rows)
    assert "| 1000 | 6 |" in (tmp_path / "u.md").read_text()


def test_mirrored_pair_is_a_reflection_of_a_crop_of_the_model():
    """Moved back by the similarity, the source is its crop of the model reflected through a plane: the linear
    map between the two is orthogonal with determinant -1 (no rotation aligns them)."""
    rng = np.random.default_rng(2)
    model = rng.normal(size=(4000, 3)) * [3.0, 2.0, 1.0]
    source, target, T = mirrored_pair(model, 2000, 0.0, 9)
    assert 1000 <= len(source) <= 2000 and target.shape == (2000, 3)
    assert cKDTree(model).query(target)[0].max() == 0.0
    crop = _cropped_subset(np.random.default_rng(9), model, 2000)  # the crop, drawn first from the pair's seed
    back = apply(np.linalg.inv(T), source)
    M, *_ = np.linalg.lstsq(crop - crop.mean(0), back - back.mean(0), rcond=None)
    assert np.allclose(M.T @ M, np.eye(3), atol=1e-9) and np.linalg.det(M) == pytest.approx(-1.0)
    assert np.allclose(back, (crop - crop.mean(0)) @ M + back.mean(0), atol=1e-9)


@pytest.mark.parametrize("args", [["--sizes", "abc"], ["--reps", "-1"], ["--noise", "x"]])
def test_bad_sizes_reps_or_noise_are_usage_errors(args, capsys):
    """--sizes abc ended in a traceback and --reps -1 wrote an empty report (found by an audit)."""
    with pytest.raises(SystemExit) as ei:
        main(["--kind", "sparse", "--offset", "7", *args])
    assert ei.value.code == 2 and "error: --" in capsys.readouterr().err
