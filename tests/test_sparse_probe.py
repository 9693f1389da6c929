"""data_scripts.sparse_probe: sparse pairs drawn reproducibly from the shipped models, outcomes counted."""

from __future__ import annotations

import csv

import numpy as np
import pytest
from scipy.spatial import cKDTree

from data_scripts.sparse_probe import main, sparse_pair
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
