"""The settle-margin tool (data_scripts/settle_margin.py): every overlap hypothesis' candidate of a pair,
scored against the ground truth, and the report built from them."""

from __future__ import annotations

from pathlib import Path

import numpy as np
from conftest import BROKEN_TARGET

from data_scripts import bench_engine as be
from data_scripts import settle_margin as sm


def test_every_hypothesis_runs_and_the_first_candidate_is_the_engines_answer(easy_bunny_pair):
    """With settling off, every hypothesis of the plan yields a candidate; on a clean pair the first one is
    right and reaches ``settle_alone``, so a normal run stops there and answers from it."""
    from gctr_cli.config import EngineConfig
    from gctr_cli.engine.search import search_plan

    config, config_dict = be.resolve_config(None, sm.NEVER_SETTLE)
    task = be.load_tasks(easy_bunny_pair / "pairs.csv", ["easy"], False, config, config_dict)[0]
    rows = sm.candidates_of(task)
    assert [r["order"] for r in rows] == list(range(len(search_plan(EngineConfig()))))
    first = rows[0]
    assert first["right"] and first["rot_err_deg"] < 5.0  # unrefined (the verdict's ICP polishes it)
    assert first["agreement"] >= EngineConfig().outer.settle_alone  # so a normal run stops after it
    assert first["overlap"] == 1.0
    # a normal run (settling on) stops after this first hypothesis and answers from it
    _, normal_dict = be.resolve_config(None, [])
    result = be.run_one({**task, "config": normal_dict, "diagnose": False})
    assert result["overlap"] == 1.0 and result["outcome"] == "success"
    assert all(np.isfinite(r["agreement"]) and 0.0 <= r["agreement"] <= 1.0 for r in rows)


def test_kinds_and_report_counts():
    def row(pid, order, agreement, right, rot):
        return {"pair_id": pid, "level": "hard", "order": order, "overlap": 1.0, "agreement": agreement,
                "right": right, "rot_err_deg": rot}

    rows = [row("a", 0, 0.70, True, 0.5), row("a", 1, 0.48, False, 170.0),
            row("b", 0, 0.53, False, 3.0), row("b", 1, 0.20, False, 90.0),
            row("c", 0, 0.45, False, 120.0)]  # exactly at a threshold: counts
    assert [sm.kind(r) for r in rows] == ["right", "wrong basin", "imprecise", "wrong basin", "wrong basin"]
    report = sm.render(rows, ["hard"], Path("data"), 3, alone=0.52)
    hard = next(line for line in report.splitlines() if line.startswith("| hard |"))
    assert "| 3 | 5 | 1 |" in hard  # pairs, candidates, right
    assert "0.480 (a, hypothesis 2, 170.0°)" in hard and "0.530 (b, hypothesis 1, 3.0°)" in hard
    assert "0.700 (a, hypothesis 1, 0.5°)" in hard
    lines = {line.split("|")[1].strip(): [c.strip() for c in line.strip("|").split("|")]
             for line in report.splitlines() if line.startswith("| 0.")}
    # t: wrong-basin, imprecise candidates >= t; where the search stops: right, imprecise, wrong basin
    assert lines["0.4"][1:] == ["2", "1", "1", "1", "1: c (0.450, hypothesis 1, 120.0°)"]
    assert lines["0.45"][1:] == ["2", "1", "1", "1", "1: c (0.450, hypothesis 1, 120.0°)"]
    assert lines["0.5"][1:] == ["0", "1", "1", "1", "0"]
    assert lines["0.55"][1:] == ["0", "0", "1", "0", "0"]
    # the best candidate so far decides: pair a stops at its right first candidate, never at its wrong second
    assert sm.settling_candidate(rows[:2], 0.45) is rows[0]
    assert sm.settling_candidate(rows[2:4], 0.6) is None


def test_settle_full_applies_only_to_the_full_overlap_candidate():
    """``settle_full`` stops the search at the full-overlap hypothesis' candidate (as the engine's
    ``settled``); a later hypothesis' candidate still needs ``settle_alone``."""
    def row(pid, order, overlap, agreement, right, rot):
        return {"pair_id": pid, "level": "scene", "order": order, "overlap": overlap, "agreement": agreement,
                "right": right, "rot_err_deg": rot}

    a = [row("a", 0, 1.0, 0.46, True, 1.0), row("a", 1, 0.75, 0.60, True, 0.5)]
    b = [row("b", 0, 1.0, 0.30, False, 150.0), row("b", 1, 0.75, 0.47, False, 170.0),
         row("b", 2, 0.5, 0.55, True, 0.8)]
    assert sm.settling_candidate(a, 0.52, full=0.45) is a[0]  # full overlap at 0.46 >= 0.45
    assert sm.settling_candidate(a, 0.52, full=0.47) is a[1]  # not at 0.47: on to the next hypothesis
    assert sm.settling_candidate(a, 0.52, full=0.46) is a[0]  # at the threshold itself
    assert sm.settling_candidate(b, 0.52, full=0.45) is b[2]  # 0.47 is not full overlap: settle_alone holds
    def full_table(rows: list[dict], n_pairs: int) -> dict[str, list[str]]:
        report = sm.render(rows, ["scene"], Path("data"), n_pairs, alone=0.52)
        return {line.split("|")[1].strip(): [cell.strip() for cell in line.strip("|").split("|")]
                for line in report.splitlines() if line.startswith("| full ")}

    # full-overlap candidates >= t (wrong basin, imprecise); stops at right, imprecise, wrong basin
    full = full_table(a + b, 2)
    assert full["full 0.45"][1:] == ["0", "0", "2", "0", "0"]
    assert full["full 0.5"][1:] == ["0", "0", "2", "0", "0"]  # a stops later, at its 0.60 candidate
    assert full["full 0.35"][1:] == ["0", "0", "2", "0", "0"]
    wrong = [row("c", 0, 1.0, 0.41, False, 140.0), row("c", 1, 0.75, 0.2, False, 60.0)]
    full = full_table(wrong, 1)
    assert full["full 0.4"][1:] == ["1", "0", "0", "0", "1: c (0.410, hypothesis 1, 140.0°)"]
    assert full["full 0.42"][1:] == ["0", "0", "0", "0", "0"]


def _two_candidates(first_agreement: float) -> list[dict]:
    """One `cross` pair: a right full-overlap candidate, then a wrong overlap-0.75 one."""
    return [{"pair_id": "a", "level": "cross", "order": 0, "overlap": 1.0, "agreement": first_agreement,
             "right": True, "rot_err_deg": 0.4},
            {"pair_id": "a", "level": "cross", "order": 1, "overlap": 0.75, "agreement": 0.3, "right": False,
             "rot_err_deg": 90.0}]


def _write_candidates(path: Path, rows: list[dict]) -> Path:
    """``rows`` as a ``--csv`` file of settle_margin."""
    import csv

    with open(path, "w", newline="") as fh:
        writer = csv.DictWriter(fh, fieldnames=list(rows[0]))
        writer.writeheader()
        writer.writerows(rows)
    return path


def test_report_renders_again_from_the_csv(tmp_path):
    rows = _two_candidates(0.61)
    assert sm.read_rows(_write_candidates(tmp_path / "c.csv", rows)) == rows


def test_main_reports_settle_full_with_the_configs_settle_alone(tmp_path):
    """--from-csv renders without the engine; the settle_full table uses the config's settle_alone (with
    ``--set`` applied), not the 1.0 that every-hypothesis runs use."""
    path = _write_candidates(tmp_path / "c.csv", _two_candidates(0.49))
    (tmp_path / "pairs.csv").write_text("pair_id,source,target,gt,model,level\na,s.ply,t.ply,gt.txt,bunny,cross\n",
                                        encoding="utf-8")
    out = tmp_path / "r.md"
    for override, alone, stops in ((None, 0.52, "0"), ("engine.outer.settle_alone=0.48", 0.48, "1")):
        args = ["--data", str(tmp_path), "--from-csv", str(path), "--out", str(out), "--levels", "cross"]
        assert sm.main([*args, *(["--set", override] if override else [])]) == 0
        report = out.read_text(encoding="utf-8")
        assert f"`settle_alone` = {alone})" in report
        full = next(line for line in report.splitlines() if line.startswith("| full 0.5 |"))
        # the full-overlap row t = 0.5 stops at min(0.5, settle_alone): the right 0.49 candidate only at 0.48
        assert full.split("|")[4].strip() == stops


def test_a_pair_the_engine_rejects_has_no_candidates(tmp_path):
    """A planar source (``register`` fails it before any search) gives no candidate rows instead of an
    exception that would stop the whole run."""
    from gctr_cli.geometry import to_matrix
    from gctr_cli.io import save_point_cloud, write_matrix

    rng = np.random.default_rng(3)
    plane = np.column_stack([rng.uniform(-1, 1, size=(2000, 2)), np.zeros(2000)])
    save_point_cloud(tmp_path / "s.ply", plane)
    save_point_cloud(tmp_path / "t.ply", rng.normal(size=(2000, 3)))
    write_matrix(tmp_path / "gt.txt", to_matrix(1.0, np.eye(3), [0.0, 0.0, 0.0]))
    _, config_dict = be.resolve_config(None, sm.NEVER_SETTLE)
    task = {"pair_id": "planar", "level": "easy", "model": "none", "seed": 0, "config": config_dict,
            "source": str(tmp_path / "s.ply"), "target": str(tmp_path / "t.ply"), "gt": str(tmp_path / "gt.txt")}
    assert sm.candidates_of(task) == []


def test_a_broken_cloud_is_reported_by_name_and_does_not_stop_the_run(easy_bunny_pair_broken, capsys):
    """A pair whose cloud cannot be read gets a line naming the file in the report (and on stderr) instead
    of an exception that would stop the whole run."""
    assert sm.main(["--data", str(easy_bunny_pair_broken), "--levels", "easy"]) == 0
    captured = capsys.readouterr()
    assert "Pairs that could not be read:" in captured.out and BROKEN_TARGET in captured.out
    assert "easy_bunny_0" in captured.err and BROKEN_TARGET in captured.err
