"""The comparison benchmark (data_scripts/bench_compare.py): statistics, goals, report and plots from a
hand-made run, and a tiny real end-to-end run (2 methods, 1 level, 1 small pair)."""

from __future__ import annotations

import csv
import json
import math
import os
from pathlib import Path

import pytest
from conftest import REPO, read_csv

from data_scripts import bench_compare as bc
from gctr_cli.batch import ERRORS_COLUMNS, TRANSFORMS_COLUMNS

PNG_MAGIC = b"\x89PNG\r\n\x1a\n"


def _write(path: Path, header, rows) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    with open(path, "w", newline="") as fh:
        w = csv.writer(fh, lineterminator="\n")
        w.writerow(header)
        w.writerows(rows)


# errors of each (method, level): list of (rot_err_deg, trans_err_rel, scale_err, runtime_s) or None = failed
FAKE = {
    ("gctr", "easy"): [(0.1, 0.001, 0.002, 1.0), (0.2, 0.002, 0.001, 1.2)],
    ("gctr", "cross"): [(0.3, 0.004, 0.01, 1.5), (40.0, 0.3, 0.2, 1.6)],
    ("fgr", "easy"): [(0.2, 0.002, 0.003, 0.5), (0.1, 0.001, 0.002, 0.7)],
    ("fgr", "cross"): [(90.0, 0.5, 0.4, 0.8), None],
}


def make_fake_run(work: Path) -> list[bc.BatchRun]:
    data = work / "data"
    runs = []
    for level in ("easy", "cross"):
        _write(data / level / "pairs.csv", ["pair_id", "source", "target", "gt", "model", "level", "scale_gt",
                                            "overlap_src", "overlap_tgt"],
               [[f"{level}_{k}", "s.ply", "t.ply", "g.txt", "bunny", level, "1.5", "0.8", "0.7"] for k in range(2)])
    for (method, level), pairs in FAKE.items():
        out = work / "results" / method / level
        trows, erows = [], []
        for k, e in enumerate(pairs):
            pid = f"{level}_{k}"
            if e is None:
                trows.append([pid, "s.ply", "t.ply", "failed", "too weak evidence", "", *[""] * 16,
                              "", "", "", "2.0", "1"])
                continue
            rot, tr, sc, t = e
            trows.append([pid, "s.ply", "t.ply", "ok", "", "1.5"] + ["0"] * 16 + ["0.9", "", "0.01", repr(t), "1"])
            ok = rot < 5 and tr < 0.05 and sc < 0.05
            erows.append([pid, repr(rot), repr(tr * 10), repr(tr), repr(sc), repr(rot / 10), "true" if ok else "false"])
        _write(out / "transforms.csv", TRANSFORMS_COLUMNS, trows)
        _write(out / "tm_errors.csv", ERRORS_COLUMNS, erows)
        runs.append(bc.BatchRun(method=method, level=level, n_pairs=2, command=["gctr", "batch"], exit_code=0,
                                wall_s=5.0, cpu_s=4.0, peak_rss_mb=123.0 if method == "gctr" else 270.0))
    return runs


def fake_meta(work: Path, methods=("gctr", "fgr"), levels=("easy", "cross")) -> dict:
    settings = bc.Settings(mode="quick", pairs_per_model=1, seed=0, workers=1, methods=methods, levels=levels,
                           profile_pairs=0)
    from dataclasses import asdict

    return {
        "command": "python -m data_scripts.bench_compare --quick",
        "date": "2026-01-01 00:00 UTC",
        "settings": {**asdict(settings), "methods": list(methods), "levels": list(levels)},
        "machine": bc.machine_info(),
        "load_samples": [0.5, 0.7],
        "generate_command": "python -m data_scripts.make_benchmark generate ...",
        "success_thresholds": {"rotation_deg": 5.0, "translation_rel": 0.05, "scale": 0.05},
        "baseline_rss_mb": {"gctr": 100.0, "open3d": 250.0},
        "code_state": "commit abc",
        "total_wall_s": 60.0,
        "work_rel": str(work),
    }


def test_report_from_a_hand_made_run(tmp_path):
    work = tmp_path / "work"
    runs = make_fake_run(work)
    out = tmp_path / "report" / "RESULTS.md"
    result = bc.write_report(fake_meta(work), runs, work, work / "data", out, profile={})

    stats = result["stats"]
    assert stats[("gctr", "easy")]["success"] == 2 and stats[("gctr", "cross")]["success"] == 1
    assert stats[("fgr", "cross")]["success"] == 0 and stats[("fgr", "cross")]["ok"] == 1
    # medians over all pairs, a failed pair counting as an infinite error
    assert stats[("fgr", "cross")]["rot"] == math.inf
    assert stats[("gctr", "cross")]["rot"] == pytest.approx(20.15)
    assert stats[("gctr", "easy")]["time_med"] == pytest.approx(1.1)
    assert stats[("gctr", "all")]["pairs"] == 4
    assert stats[("gctr", "easy")]["ln_tm"] == pytest.approx((math.log(0.01) + math.log(0.02)) / 2)  # median of ln

    goals = {g["goal"].split(":")[0]: g for g in result["goals"]}
    assert goals["`easy`"]["met"] is True  # 2/2 vs 2/2: ≥ holds
    assert goals["`cross`"]["met"] is True  # 1/2 vs 0/2: strictly higher
    time_goal = next(g for g in result["goals"] if "median time" in g["goal"])
    assert time_goal["met"] is False and time_goal["fastest"] == "fgr"  # 1.35 s vs 0.7 s

    text = out.read_text()
    assert "Command: `python -m data_scripts.bench_compare --quick`" in text
    assert "cores" in text and "Load average" in text
    assert "| **gctr** | easy | 2 | 2/2 (100%) |" in text
    assert "| fgr | cross | 2 | 0/2 (0%) | ∞ |" in text
    assert "| 123 |" in text and "| 270 |" in text  # peak memory column
    assert "**1 of 3 goals are not met.**" in text
    assert "Not met — gctr median time" in text
    assert "## gctr's unsuccessful pairs" in text and "cross_1" in text
    assert "GCTR (paper)" in text  # Table 1 beside ours
    for png in (bc.CDF_PNG, bc.TIME_PNG):
        assert f"]({png})" in text
        assert (out.parent / png).read_bytes()[:8] == PNG_MAGIC
    rows = read_csv(work / "rows.csv")[1]
    assert len(rows) == 8 and {r["method"] for r in rows} == {"gctr", "fgr"}


@pytest.mark.slow  # ~15 s
def test_tiny_end_to_end_run_and_report_only(tmp_path):
    """The real pipeline: generator -> gctr batch per method and level (measured) -> report."""
    work, out = tmp_path / "work", tmp_path / "out" / "RESULTS.md"
    argv = ["--quick", "--methods", "gctr,icp", "--levels", "easy", "--models", str(REPO / "data/models/bunny.ply"),
            "--pairs-per-model", "1", "--n-source", "2000", "-j", "1", "--profile-pairs", "1",
            "--work", str(work), "--out", str(out)]
    assert bc.main(argv) == 0
    text = out.read_text()
    assert "| **gctr** | easy | 1 |" in text and "| icp | easy | 1 |" in text
    assert "--levels easy" in text and "--n-source 2000" in text  # the generator command
    assert "## Where the time goes" in text and "**gctr** (total" in text
    for png in (bc.CDF_PNG, bc.TIME_PNG):
        assert (out.parent / png).read_bytes()[:8] == PNG_MAGIC
    for method in ("gctr", "icp"):
        (_,) = read_csv(work / "results" / method / "easy" / "transforms.csv")[1]
        assert (work / "configs" / f"{method}.yaml").read_text().startswith(f"method: {method}")
    saved = json.loads((work / "run.json").read_text())
    assert [(r["method"], r["level"]) for r in saved["runs"]] == [("gctr", "easy"), ("icp", "easy")]
    assert all(r["peak_rss_mb"] > 30 and r["exit_code"] in (0, 1) for r in saved["runs"])
    # the report can be re-rendered from the saved run, identically
    out.unlink()
    assert bc.main([*argv, "--report-only"]) == 0
    assert out.read_text() == text


# ------------------------------------------------------------------------------------------ issue 9 verdicts
from data_scripts import common  # noqa: E402

NAN = float("nan")
# (status, success, confidence, would_succeed, runtime)
VERDICT_ROWS = [("ok", True, 0.9, True, 1.0), ("ok", True, 0.2, True, 2.0), ("ok", False, 0.15, False, 3.0),
                ("ok", False, 0.6, False, 4.0), ("failed", False, 0.05, True, 5.0), ("failed", False, NAN, None, 6.0)]


def _verdict_rows(method="gctr", level="part"):
    return [{"method": method, "level": level, "pair_id": f"{level}_{i}", "status": st, "success": su,
             "confidence": c, "would_succeed": ws, "runtime_s": t}
            for i, (st, su, c, ws, t) in enumerate(VERDICT_ROWS)]


def test_outcomes_and_outcome_table():
    rows = _verdict_rows()
    assert [common.outcome(r) for r in rows] == ["success", "success", "silent_wrong", "silent_wrong", "failed",
                                                 "failed"]
    assert common.outcome({"status": "timeout", "success": False}) == "failed"
    assert common.outcome_counts(rows) == {"success": 2, "silent_wrong": 2, "failed": 2, "pairs": 6}
    table = common.outcome_table([("gctr", "part", rows)], "runtime_s")
    assert table[2] == "| gctr | part | 6 | 2 (33.3%) | 2 (33.3%) | 2 (33.3%) | 3.50 | 5.50 |"


def test_confidence_sweep_counts():
    sweep = {round(c["threshold"], 1): c for c in common.confidence_sweep(_verdict_rows())}
    assert list(sweep) == [0.0, 0.1, 0.2, 0.3, 0.4, 0.5, 0.6, 0.7, 0.8, 0.9]

    def get(t):
        c = sweep[t]
        return c["success"], c["silent_wrong"], c["correct_refused"], c["refused"]

    assert get(0.0) == (3, 2, 0, 1)  # the failed pair with a good transform is accepted at t = 0
    assert get(0.1) == (2, 2, 1, 2)
    assert get(0.2) == (2, 1, 1, 3)  # conf 0.2 >= 0.2 accepted; the wrong one at 0.15 refused
    assert get(0.3) == (1, 1, 2, 4)
    assert get(0.6) == (1, 1, 2, 4)  # conf 0.6 still accepted
    assert get(0.7) == (1, 0, 2, 5)
    assert get(0.9) == (1, 0, 2, 5)
    # a method without confidence never refuses a usable transform
    nan_rows = [{**r, "confidence": NAN} for r in _verdict_rows()]
    assert {(c["silent_wrong"], c["correct_refused"]) for c in common.confidence_sweep(nan_rows)} == {(2, 0)}


@pytest.mark.parametrize("refusal", ["not_confirmed", "mirrored", "scale_held", "weak_evidence"])
def test_confidence_sweep_counts_a_refusal_no_threshold_lifts_as_refused_at_every_threshold(refusal):
    """A right answer at confidence 0.21 refused for another reason than its confidence (here: not confirmed
    the other way round, mirrored, held at a scale bound, too weak evidence) was refused: the configured row
    must say so, and so must every lower threshold."""
    rows = [{"would_succeed": True, "confidence": 0.21, "status": "failed", "refusal": refusal},
            {"would_succeed": True, "confidence": 0.21, "status": "ok", "refusal": ""}]
    for c in common.confidence_sweep(rows, (0.0, 0.15, 0.3)):
        assert c["correct_refused"] == (1 if c["threshold"] < 0.21 else 2)


def test_confidence_sweep_accepts_a_low_confidence_refusal_from_the_thresholds_it_reaches():
    rows = [{"would_succeed": True, "confidence": 0.12, "status": "failed", "refusal": "low_confidence"}]
    assert [c["success"] for c in common.confidence_sweep(rows, (0.0, 0.1, 0.15))] == [1, 1, 0]


def test_sweep_table_marks_configured_threshold():
    sweeps = {"gctr": common.confidence_sweep(_verdict_rows()),
              "icp": common.confidence_sweep([{**r, "confidence": NAN} for r in _verdict_rows()])}
    table = common.sweep_table(sweeps, configured=0.3)
    assert table[0] == ("| threshold | gctr: silent wrong | gctr: correct refused | icp: silent wrong "
                        "| icp: correct refused |")
    assert table[2] == "| 0.00 | 2 (33.3%) | 0 (0.0%) | 2 (33.3%) | 0 (0.0%) |"
    assert table[5] == "| 0.30 (configured) | 1 (16.7%) | 2 (33.3%) | 2 (33.3%) | 0 (0.0%) |"
    assert len(table) == 12


def test_sweep_includes_a_configured_threshold_off_the_grid():
    assert common.sweep_thresholds(0.35) == (0.0, 0.1, 0.2, 0.3, 0.35, 0.4, 0.5, 0.6, 0.7, 0.8, 0.9)
    assert common.sweep_thresholds(0.3) == common.CONFIDENCE_THRESHOLDS
    assert common.sweep_thresholds(None) == common.CONFIDENCE_THRESHOLDS
    assert common.sweep_thresholds(True) == common.CONFIDENCE_THRESHOLDS  # not a threshold
    assert 0.1234567 in common.sweep_thresholds(0.1234567)  # kept exactly, so its row is marked
    sweeps = {"gctr": common.confidence_sweep(_verdict_rows(), common.sweep_thresholds(0.35))}
    table = common.sweep_table(sweeps, configured=0.35)
    assert len(table) == 13 and table[6].startswith("| 0.35 (configured) |")


def test_diagnose_and_diagnosis_table():
    assert common.diagnose(0.80, 0.50) == "search missed"
    assert common.diagnose(0.50, 0.80) == "objective can't tell"
    assert common.diagnose(0.50, 0.515) == "precision"
    assert common.diagnose(0.50, 0.525) == "objective can't tell"
    assert common.diagnose(NAN, 0.5) == ""
    rows = [{"level": "hard", "status": "ok", "success": False, "diagnosis": "search missed"},
            {"level": "hard", "status": "ok", "success": False, "diagnosis": "precision"},
            {"level": "hard", "status": "ok", "success": True},
            {"level": "part", "status": "failed", "success": False, "diagnosis": ""},
            {"level": "part", "status": "ok", "success": False, "diagnosis": "objective can't tell"}]
    table = common.diagnosis_table(rows, ["hard", "part"])
    assert table[2] == "| hard | 2 | 1 | 0 | 1 | 0 |"
    assert table[3] == "| part | 2 | 0 | 1 | 0 | 1 |"
    assert table[4] == "| **all** | 4 | 1 | 1 | 1 | 1 |"


def test_usable_transform():
    import numpy as np

    T = np.eye(4)
    T[:3, 3] = 1.0
    assert common.usable_transform(T) and not common.usable_transform(np.eye(4))
    assert not common.usable_transform(np.zeros((4, 4))) and not common.usable_transform(None)
    T[0, 0] = NAN
    assert not common.usable_transform(T)


def test_compare_render_verdicts_and_plot(tmp_path):
    rows = _verdict_rows("gctr") + [{**r, "confidence": NAN} for r in _verdict_rows("icp")]
    rows[2]["diagnosis"] = "search missed"
    text = "\n".join(bc.render_verdicts(rows, ("gctr", "icp"), ("part",), 0.3))
    assert "| gctr | part | 6 | 2 (33.3%) | 2 (33.3%) | 2 (33.3%) | 3.50 | 5.50 |" in text
    assert "Silent wrong over all levels: gctr 2 of 6 pairs (33.3%); icp 2 of 6 pairs (33.3%)." in text
    assert "| 0.30 (configured) | 1 (16.7%) | 2 (33.3%) | 2 (33.3%) | 0 (0.0%) |" in text
    assert "never refusing: icp" in text
    assert "2 failed rows have no matrix" in text  # one per method
    assert "| part | 4 | 1 | 0 | 0 | 3 |" in text  # gctr's 4 unsuccessful pairs, one diagnosed
    png = tmp_path / "t.png"
    common.plot_confidence_tradeoff({m: common.confidence_sweep([r for r in rows if r["method"] == m])
                                     for m in ("gctr", "icp")}, png, 0.3)
    assert png.read_bytes()[:8] == PNG_MAGIC


def test_compare_load_rows_confidence_and_would_succeed(tmp_path):
    data = tmp_path / "data"
    _write(data / "part" / "pairs.csv", ["pair_id", "source", "target", "gt", "model", "level"],
           [["p0", "s.ply", "t.ply", "g.txt", "bunny", "part"], ["p1", "s.ply", "t.ply", "g.txt", "bunny", "part"],
            ["p2", "s.ply", "t.ply", "g.txt", "bunny", "part"]])
    out = tmp_path / "results" / "gctr" / "part"
    shifted = ["1", "0", "0", "1", "0", "1", "0", "0", "0", "0", "1", "0", "0", "0", "0", "1"]
    cols = [*TRANSFORMS_COLUMNS, "confidence"] if "confidence" not in TRANSFORMS_COLUMNS else list(TRANSFORMS_COLUMNS)
    ci = cols.index("confidence")

    def trow(pid, status, cells, conf):
        row = [pid, "s.ply", "t.ply", status, "", "1"] + cells + ["0.9", "0.01", "1.0", "1"]
        row += [""] * (len(cols) - len(row))
        row[ci] = conf
        return row

    _write(out / "transforms.csv", cols, [trow("p0", "ok", shifted, "0.8"), trow("p1", "failed", shifted, "0.1"),
                                          trow("p2", "failed", [""] * 16, "")])
    _write(out / "tm_errors.csv", ERRORS_COLUMNS, [["p0", "1.0", "0.1", "0.001", "0.01", "0.1", "true"],
                                                   ["p1", "2.0", "0.1", "0.001", "0.01", "0.1", "false"]])
    th = {"rotation_deg": 5.0, "translation_rel": 0.05, "scale": 0.05}
    rows = {r["pair_id"]: r for r in bc.load_rows(tmp_path, data, ("gctr",), ("part",), th)}
    assert rows["p0"]["confidence"] == 0.8 and rows["p0"]["would_succeed"] is True and rows["p0"]["success"]
    assert rows["p1"]["confidence"] == 0.1 and rows["p1"]["would_succeed"] is True and not rows["p1"]["success"]
    assert math.isnan(rows["p2"]["confidence"]) and rows["p2"]["would_succeed"] is None


def test_process_times_reads_the_process_report(tmp_path):
    from data_scripts.bench_compare import process_times

    report = tmp_path / "PROCESS.md"
    report.write_text(
        "| command | wall median (s) | wall min (s) |\n|---|---:|---:|\n"
        "| `gctr register` | 1.846 | 1.580 |\n"
        "| `gctr register, method kiss_matcher` | 2.795 | 2.262 |\n"
        "| `Open3D script` | 2.411 | 2.019 |\n| `gctr --help` | 0.170 | 0.111 |\n", encoding="utf-8")
    assert process_times(report) == {"gctr": 1.846, "kiss_matcher": 2.795, "open3d_script": 2.411}
    assert process_times(tmp_path / "missing.md") == {}


@pytest.mark.skipif(not hasattr(os, "sched_setaffinity"), reason="no CPU affinity on this OS")
def test_one_core_pins_the_run_and_restores_the_affinity():
    """A full run (one worker per batch) is pinned to one CPU, so multi-threaded methods get one core like
    the others; the affinity before the run comes back afterwards (tests call main() in-process)."""
    before = os.sched_getaffinity(0)
    with bc.one_core(True) as cpu:
        assert cpu == max(before) and os.sched_getaffinity(0) == {cpu}
    assert os.sched_getaffinity(0) == before
    with bc.one_core(False) as cpu:
        assert cpu is None and os.sched_getaffinity(0) == before


def test_median_ratio_spread_exact_and_on_a_gap():
    """The firmness of the median-time comparison: exact when one method is always twice as slow; a wide
    interval when the first method's median sits on the gap between a fast and a slow group of pairs."""

    def rows(times_a, times_b):
        return ([{"method": "a", "pair_id": f"p{i}", "runtime_s": t} for i, t in enumerate(times_a)]
                + [{"method": "b", "pair_id": f"p{i}", "runtime_s": t} for i, t in enumerate(times_b)])

    b = [0.5 + 0.01 * i for i in range(40)]
    sp = bc.median_ratio_spread(rows([2 * t for t in b], b), "a", "b", resamples=500)
    assert sp["pairs"] == 40
    assert sp["ratio"] == pytest.approx(2.0) and sp["mean_ratio"] == pytest.approx(2.0)
    assert sp["low"] == pytest.approx(2.0) and sp["high"] == pytest.approx(2.0)
    assert sp["faster_share"] == 0.0
    # 21 fast pairs at 0.6 s and 20 slow ones at 2 s against a steady 0.62 s: a is faster at the median
    # (ratio 0.97), but a resample with a few fast pairs fewer puts its median among the slow ones.
    gap = rows([0.6] * 21 + [2.0] * 20, [0.62] * 41)
    sp = bc.median_ratio_spread(gap + [{"method": "a", "pair_id": "only_a", "runtime_s": 9.0}], "a", "b")
    assert sp["pairs"] == 41 and sp["ratio"] == pytest.approx(0.6 / 0.62)
    assert sp["low"] == pytest.approx(0.6 / 0.62) and sp["high"] == pytest.approx(2.0 / 0.62)
    assert sp["faster_share"] == pytest.approx(21 / 41)
    assert sp["mean_ratio"] == pytest.approx((21 * 0.6 + 20 * 2.0) / 41 / 0.62)
    assert bc.median_ratio_spread(gap, "a", "missing") == {}


def test_miss_breakdown_separates_refused_from_wrong_answers():
    """A refused pair has no matrix (infinite errors): it is counted as refused, never as a wrong coarse match."""
    th = {"rotation_deg": 5.0, "translation_rel": 0.05, "scale": 0.05}
    inf = math.inf
    refused = {"status": "failed", "rot_err_deg": inf, "trans_err_rel": inf, "scale_err": inf}
    coarse = {"status": "ok", "rot_err_deg": 40.0, "trans_err_rel": 0.3, "scale_err": 0.01}
    near = {"status": "ok", "rot_err_deg": 5.5, "trans_err_rel": 0.01, "scale_err": 0.06}
    assert bc.miss_breakdown([refused, refused], th) == "2 refused, none answered wrongly"
    assert bc.miss_breakdown([refused, coarse, near], th) == (
        "1 refused, 2 answered wrongly: over the threshold in rotation 2, translation 1, scale 1; 1 with a "
        "rotation error ≥ 10°, i.e. a wrong coarse match, the others near misses")


def test_batch_order_runs_level_by_level_alternating_the_methods():
    """Every method on a level before the next level, the methods' order reversed on every second
    level: methods compared on a level meet the same state of a drifting machine, none always first."""
    order = bc.batch_order(["gctr", "kiss_matcher", "icp"], ["easy", "hard", "part"])
    assert order == [("gctr", "easy"), ("kiss_matcher", "easy"), ("icp", "easy"),
                     ("icp", "hard"), ("kiss_matcher", "hard"), ("gctr", "hard"),
                     ("gctr", "part"), ("kiss_matcher", "part"), ("icp", "part")]
    assert sorted(order) == sorted((m, lv) for m in ["gctr", "kiss_matcher", "icp"] for lv in ["easy", "hard", "part"])


def test_limits_state_how_firm_a_met_time_goal_is():
    """A met time goal is stated with its bootstrap firmness whether its margin is thin or clear."""
    rows = ([{"method": "gctr", "pair_id": f"p{i}", "runtime_s": t} for i, t in enumerate([0.2] * 30 + [0.9] * 20)]
            + [{"method": "kiss", "pair_id": f"p{i}", "runtime_s": 0.3} for i in range(50)])
    goals = [{"goal": "gctr median time per pair ≤ the fastest global baseline's", "met": True, "fastest": "kiss"}]
    for gctr_median, thin in ((0.2, False), (0.29, True)):
        stats = {("gctr", "all"): {"time_med": gctr_median}, ("kiss", "all"): {"time_med": 0.3}}
        text = "\n".join(bc.limits_text(rows, stats, goals, ["gctr", "kiss"], [], {}, {}))
        assert ("thin margin" in text) is thin
        assert ("The time goal holds (gctr 0.20 s vs kiss 0.30 s)" in text) is not thin
        assert "How firm the median comparison is: ratio 0.67" in text


def test_a_failed_generation_is_a_clear_error_not_a_traceback(monkeypatch, tmp_path):
    """The generator's own message (e.g. no shared data beside the repository) is followed by one line naming
    the folder, not a traceback."""
    import subprocess

    monkeypatch.setattr(bc.subprocess, "run", lambda *a, **k: subprocess.CompletedProcess(a, 2))
    settings = bc.Settings(mode="quick", pairs_per_model=1, seed=0, workers=1, methods=("gctr",),
                           levels=("easy",), profile_pairs=0)
    with pytest.raises(bc.BenchError, match=r"generating the pairs into .*data failed \(exit status 2\)"):
        bc.ensure_data(settings, tmp_path / "w" / "data")
