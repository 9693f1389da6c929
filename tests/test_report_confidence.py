"""report.html: the confidence column and the confidence-threshold trade-off plot (issue 9, batch side)."""

from __future__ import annotations

import csv

import pytest
from conftest import read_csv

from data_scripts import fake_engine
from gctr_cli.batch import run_batch
from gctr_cli.config import Config, config_to_yaml
from gctr_cli.outcome import ERRORS_COLUMNS, TRANSFORMS_COLUMNS
from gctr_cli.report import COLUMNS, confidence_tradeoff, render_report

#: (pair_id, status, confidence, success or None without gt)
ROWS = [
    ("a", "ok", "0.92", True), ("b", "ok", "0.83", True), ("c", "ok", "0.62", False), ("d", "ok", "0.97", False),
    ("e", "ok", "0.41", True), ("f", "ok", "0.74", True),
    ("g", "ok", "", True),  # a method without confidence: not in the plot
    ("h", "ok", "0.5", None),  # no ground truth: not in the plot
    ("i", "failed", "0.1", None),  # refused by the run: no matrix, no errors
]


def write_folder(out, min_confidence=0.3):
    out.mkdir()
    with open(out / "transforms.csv", "w", newline="") as fh:
        w = csv.writer(fh, lineterminator="\n")
        w.writerow(TRANSFORMS_COLUMNS)
        for pid, status, conf, _ in ROWS:
            m = [str(int(i % 5 == 0)) for i in range(16)] if status == "ok" else [""] * 16  # the identity
            w.writerow([pid, "s.ply", "t.ply", status, "", "1.0" if status == "ok" else "", *m, "0.8", conf, "0.01",
                        "0.1", "1"])
    with open(out / "tm_errors.csv", "w", newline="") as fh:
        w = csv.writer(fh, lineterminator="\n")
        w.writerow(ERRORS_COLUMNS)
        for pid, status, _, success in ROWS:
            if success is not None and status == "ok":
                w.writerow([pid, "1", "0.1", "0.01", "0.001", "0.1", "true" if success else "false"])
    config = Config.model_validate({"engine": {"min_confidence": min_confidence}})
    (out / "config.yaml").write_text(config_to_yaml(config))


def test_tradeoff_counts(tmp_path):
    write_folder(tmp_path / "out")
    rows = read_csv(tmp_path / "out" / "transforms.csv")[1]
    errs = {r["pair_id"]: r for r in read_csv(tmp_path / "out" / "tm_errors.csv")[1]}
    ts, wrong, refused, n = confidence_tradeoff(rows, errs, 0.3, n_steps=8)
    assert n == 6 and ts[0] == 0.3 and ts[-1] == 1.0 and len(ts) == 8
    assert ts[2] == pytest.approx(0.5) and ts[4] == pytest.approx(0.7) and ts[6] == pytest.approx(0.9)
    pairs = list(zip(wrong, refused))
    assert pairs[0] == (2, 0)  # t = 0.3 (the run's): c and d are ok but wrong, nothing refused
    assert pairs[2] == (2, 1)  # t = 0.5: e (0.41) refused
    assert pairs[4] == (1, 1)  # t = 0.7: c (0.62) caught; f (0.74) still kept
    assert pairs[6] == (1, 3)  # t = 0.9: b (0.83) and f refused too; d (0.97) still slips through
    assert pairs[-1] == (0, 4)  # t = 1: nothing silently wrong, every correct pair refused


def test_report_shows_confidence_and_the_tradeoff_plot(tmp_path):
    write_folder(tmp_path / "out", min_confidence=0.3)
    page = render_report(tmp_path / "out")
    assert [c[0] for c in COLUMNS].index("confidence") == [c[0] for c in COLUMNS].index("fitness") + 1
    assert 'data-key="confidence"' in page and 'data-v="0.97"' in page
    assert 'id="tradeoff-plot"' in page and "run: min_confidence 0.3" in page
    assert "At the run's threshold 0.3: 2 silently wrong, 0 refused" in page
    assert "thresholds below the run's <code>engine.min_confidence</code> cannot be evaluated" in page


def test_no_tradeoff_plot_without_confidences(four_pairs, fast_config, tmp_path, monkeypatch):
    # a method that reports no confidence (NaN): empty cells, no plot
    out = tmp_path / "out"
    run_batch(four_pairs.specs(), fast_config, out, workers=1, register_fn=fake_engine.register_without_confidence)
    rows = read_csv(out / "transforms.csv")[1]
    assert rows and all(r["confidence"] == "" for r in rows)
    page = render_report(out)
    assert 'id="tradeoff-plot"' not in page and 'data-key="confidence"' in page
