"""The truth-score tool (data_scripts/truth_score.py) and the engine function it calls
(gctr_cli.engine.gctr.verdict_agreement): the verdict's judgement of a given transform."""

from __future__ import annotations

import csv
from pathlib import Path

import numpy as np
import pytest
from conftest import BROKEN_TARGET

from data_scripts import truth_score as ts


def _clouds(data: Path) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    from gctr_cli.io import load_point_cloud, read_matrix

    folder = data / "easy"
    return (load_point_cloud(folder / "easy_bunny_0_src.ply"), load_point_cloud(folder / "easy_bunny_0_tgt.ply"),
            read_matrix(folder / "easy_bunny_0_gt.txt"))


def test_the_truth_scores_what_the_engines_right_answer_scores_and_a_turned_pose_far_less(easy_bunny_pair):
    """On a clean pair the truth and the engine's (right) answer get about the same verdict score, clearly
    positive; the truth turned by 90 degrees about the source's centre lays the clouds beside each other."""
    from gctr_cli.config import EngineConfig
    from gctr_cli.engine.gctr import register, verdict_agreement
    from gctr_cli.geometry import to_matrix

    source, target, T_gt = _clouds(easy_bunny_pair)
    cfg = EngineConfig()
    truth = verdict_agreement(source, target, T_gt, cfg, seed=3)
    result = register(source, target, cfg, seed=3)
    assert result.status == "ok"
    assert truth.score > 0.3
    assert abs(truth.score - result.evidence["score"]) < 0.05
    # the engine's own answer, re-scored: the same clouds and (same scale here) the same tolerances as its verdict
    answer = verdict_agreement(source, target, result.transform, cfg, seed=3)
    assert answer.score == pytest.approx(result.evidence["score"], abs=1e-6)
    assert answer.source == pytest.approx(result.evidence["source_agreement"], abs=1e-6)
    c = source.mean(axis=0)
    quarter_turn = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
    turn = to_matrix(1.0, quarter_turn, c - quarter_turn @ c)  # about the source's centre
    turned = verdict_agreement(source, target, T_gt @ turn, cfg, seed=3)
    assert turned.score < truth.score - 0.2
    assert turned.conflict_source + turned.conflict_target > truth.conflict_source + truth.conflict_target


def test_the_tool_reports_the_truths_score_and_whether_it_reaches_the_threshold(easy_bunny_pair, tmp_path):
    out, table = tmp_path / "truth.md", tmp_path / "truth.csv"
    assert ts.main(["--data", str(easy_bunny_pair), "--levels", "easy", "--out", str(out), "--csv", str(table)]) == 0
    with open(table, encoding="utf-8") as fh:
        rows = list(csv.DictReader(fh))
    assert [r["pair_id"] for r in rows] == ["easy_bunny_0"]
    row = rows[0]
    assert row["error"] == "" and row["acceptable"] == "True"
    assert float(row["best_confidence"]) == pytest.approx(min(1.0, float(row["score"]) / 0.25))
    report = out.read_text(encoding="utf-8")
    assert "| easy | bunny | 1 |" in report and "Pairs whose truth cannot reach the threshold: 0" in report
    # a stricter threshold than the truth can reach lists the pair
    strict = tmp_path / "strict.md"
    assert ts.main(["--data", str(easy_bunny_pair), "--levels", "easy", "--out", str(strict),
                    "--set", "engine.verdict.full_margin=1", "--set", "engine.min_confidence=0.9"]) == 0
    assert "Pairs whose truth cannot reach the threshold: 1" in strict.read_text(encoding="utf-8")
    assert "| easy_bunny_0 |" in strict.read_text(encoding="utf-8")


def test_a_filter_that_matches_nothing_is_an_error_naming_the_manifest(easy_bunny_pair, capsys):
    assert ts.main(["--data", str(easy_bunny_pair), "--levels", "easy", "--match", "nclt"]) == 2
    err = capsys.readouterr().err
    assert "pairs.csv" in err and "nclt" in err


def test_a_broken_cloud_is_an_error_row_naming_the_file_and_empty_levels_are_refused(easy_bunny_pair_broken,
                                                                                    tmp_path, capsys):
    data = easy_bunny_pair_broken
    table = tmp_path / "t.csv"
    assert ts.main(["--data", str(data), "--levels", "easy", "--csv", str(table)]) == 0
    captured = capsys.readouterr()
    assert "Pairs that could not be scored:" in captured.out and BROKEN_TARGET in captured.out
    assert "truth_score: error: " in captured.err and BROKEN_TARGET in captured.err
    with open(table, encoding="utf-8") as fh:
        row = next(csv.DictReader(fh))
    assert row["score"] == "" and BROKEN_TARGET in row["error"]
    assert ts.main(["--data", str(data), "--levels", ","]) == 2
    assert "names no level" in capsys.readouterr().err
