"""The engine benchmark driver (data_scripts/bench_engine.py) on a tiny generated set.

One end-to-end run of the command line on two small bunny pairs (levels easy and cross, 3000-point
sources), plus an ``--append`` run of a second variant; the rest are in-process unit checks.
"""

from __future__ import annotations

import csv
import re
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from data_scripts import bench_engine as be
from data_scripts import make_benchmark as mb

REPO = Path(__file__).resolve().parents[1]
TIMING_COLUMNS = {"time_s", "cpu_s", "load_s", "rss_baseline_mb", "peak_rss_mb", "rss_increment_mb",
                  "ru_maxrss_mb", "load_avg_1m"}


@pytest.fixture(scope="module")
def tiny_data(tmp_path_factory) -> Path:
    """``pairs.csv`` with one easy and one cross bunny pair (3000-point sources), as the generator writes it."""
    from gctr_cli.io import load_point_cloud

    out = tmp_path_factory.mktemp("bench") / "data"
    bunny = load_point_cloud(mb.DATA_DIR / "models" / "bunny.ply")
    rows = []
    for level in ("easy", "cross"):
        pair = mb.make_pair(bunny, mb.LEVELS[level], mb.pair_rng(0, level, "bunny", 0), n_source=3000)
        row = mb.write_pair(out / level, f"{level}_bunny_0", pair, "ply")
        rows.append({**row, **{c: f"{level}/{row[c]}" for c in ("source", "target", "gt")},
                     "model": "bunny", "level": level})
    mb.write_manifest(out / "pairs.csv", rows)
    return out


def read_rows(path: Path) -> tuple[list[str], list[dict[str, str]]]:
    with open(path, newline="") as fh:
        reader = csv.DictReader(fh)
        return list(reader.fieldnames or []), list(reader)


def run_cli(*args: str) -> subprocess.CompletedProcess:
    cmd = [sys.executable, "-m", "data_scripts.bench_engine", "-q", *args]
    return subprocess.run(cmd, cwd=REPO, capture_output=True, text=True, timeout=120)


def level_row(report: str, level: str) -> list[str]:
    """Cells of the per-level accuracy table row of ``level`` (first table of the section)."""
    for line in report.splitlines():
        if line.startswith(f"| {level} |"):
            return [c.strip() for c in line.strip("|").split("|")]
    raise AssertionError(f"no table row for level {level}")


@pytest.mark.slow
def test_cli_writes_csv_and_report_consistent_with_it(tiny_data, tmp_path):
    out, pairs_csv = tmp_path / "ENGINE.md", tmp_path / "t_pairs.csv"
    proc = run_cli("--data", str(tiny_data), "--levels", "easy,cross", "--variant", "t", "--out", str(out),
                   "--csv", str(pairs_csv))
    assert proc.returncode == 0, proc.stderr

    columns, rows = read_rows(pairs_csv)
    for col in ("pair_id", "level", "model", "n_source", "n_target", "status", "rot_err_deg", "trans_err_rel",
                "scale_err", "tm_err", "log_tm", "success", "time_s", "cpu_s", "load_s", "overlap", "peak_rss_mb",
                "rss_baseline_mb", "rss_increment_mb", "t_preprocess", "t_tensor", "t_power_iteration", "t_ransac",
                "t_refine", "t_other", "message"):
        assert col in columns, col
    assert [r["pair_id"] for r in rows] == ["easy_bunny_0", "cross_bunny_0"]
    for r in rows:
        assert r["status"] in ("ok", "failed")
        assert int(r["n_source"]) == 3000 and int(r["n_target"]) > 0
        assert float(r["time_s"]) > 0 and float(r["cpu_s"]) > 0
        assert 0 < float(r["rss_baseline_mb"]) < float(r["peak_rss_mb"]) < 1024
        stage_sum = sum(float(r[c]) for c in columns if c.startswith("t_"))
        assert stage_sum == pytest.approx(float(r["time_s"]), rel=0.02, abs=1e-3)

    report = out.read_text()
    assert report.startswith("# GCTR engine benchmark")
    assert "python -m data_scripts.bench_engine -q --data " in report  # the exact command line
    assert f"--levels easy,cross --variant t --out {out}" in report
    for header in ("| level | pairs | models |", "success", "median rot err (°)", "median log(TM)",
                   "median time (s)", "p90 time (s)", "max peak mem (MB)", "### Time per stage", "| stage |",
                   "### Failed pairs", "<!-- bench-section: t -->"):
        assert header in report, header
    for level in ("easy", "cross"):
        n_ok = sum(r["success"] == "true" for r in rows if r["level"] == level)
        cells = level_row(report, level)
        assert cells[1] == "1" and cells[2] == "1"  # pairs, models
        assert cells[4] == f"{n_ok}/1 ({100.0 * n_ok:.1f}%)"
    n_ok = sum(r["success"] == "true" for r in rows)
    assert level_row(report, "all")[4] == f"{n_ok}/2 ({50.0 * n_ok:.1f}%)"

    # --append adds a second variant's section and keeps the first; re-running it replaces it in place
    for _ in range(2):
        proc = run_cli("--data", str(tiny_data), "--levels", "cross", "--variant", "no-refine", "--set",
                       "engine.refine.enabled=false", "--out", str(out), "--csv", str(tmp_path / "n.csv"), "--append")
        assert proc.returncode == 0, proc.stderr
    report2 = out.read_text()
    assert report2.startswith(report.rstrip("\n"))
    assert report2.count("<!-- bench-section: no-refine -->") == 1
    assert report2.count("# GCTR engine benchmark") == 1
    assert "overrides: `engine.refine.enabled=false`" in report2
    _, rows2 = read_rows(tmp_path / "n.csv")
    assert [r["pair_id"] for r in rows2] == ["cross_bunny_0"] and float(rows2[0]["t_refine"]) == 0.0


@pytest.mark.slow
def test_an_unreadable_cloud_is_named_in_one_line_and_the_other_rows_kept(tiny_data, tmp_path):
    """A cloud that exists but does not read was counted as the engine's failure, with a traceback and exit 0
    (found by an audit): now one line naming the pair and the file, exit 2, the good pair's row in the CSV and
    no report that would count the bad data as a refusal."""
    data = tmp_path / "data"
    shutil.copytree(tiny_data, data)
    bad = data / "cross" / "cross_bunny_0_src.ply"
    bad.write_text("ply\nformat ascii 1.0\nelement vertex 10\nproperty float x\nend_header\n1\n")
    out, pairs_csv = tmp_path / "ENGINE.md", tmp_path / "t_pairs.csv"
    proc = run_cli("--data", str(data), "--levels", "easy,cross", "--no-diagnose", "--out", str(out),
                   "--csv", str(pairs_csv))
    assert proc.returncode == 2 and "Traceback" not in proc.stderr, proc.stderr
    assert f"error: {data / 'pairs.csv'}: pair cross_bunny_0: {bad}: PLY vertex element has no y/z fields" \
        in proc.stderr
    _, rows = read_rows(pairs_csv)
    assert [(r["pair_id"], r["status"]) for r in rows] == [("easy_bunny_0", "ok"), ("cross_bunny_0", "bad_data")]
    assert float(rows[0]["rot_err_deg"]) < 1.0 and not out.exists()


def test_run_one_is_deterministic_apart_from_timings(tiny_data):
    config, config_dict = be.resolve_config(None, [])
    task = be.load_tasks(tiny_data / "pairs.csv", ["cross"], False, config, config_dict)[0]
    a, b = be.run_one(task), be.run_one(task)
    stages = be.stage_names([a, b])
    fa, fb = be.flat_row(a, stages), be.flat_row(b, stages)
    stable = [c for c in be.csv_columns(stages) if c not in TIMING_COLUMNS and not c.startswith("t_")]
    assert {c: be._fmt(fa.get(c)) for c in stable} == {c: be._fmt(fb.get(c)) for c in stable}


def test_set_overrides_are_yaml_scalars_and_validated():
    config, d = be.resolve_config(None, ["engine.refine.enabled=false", "engine.scale_method=umeyama",
                                         "engine.tensor.knn=20", "success.rotation_deg=2.5"])
    assert config.engine.refine.enabled is False and config.engine.scale_method == "umeyama"
    assert config.engine.tensor.knn == 20 and config.success.rotation_deg == 2.5
    assert d["engine"]["tensor"]["knn"] == 20
    with pytest.raises(be.BenchError, match="unknown key"):
        be.resolve_config(None, ["engine.no_such_key=1"])
    with pytest.raises(be.BenchError, match="KEY=VALUE"):
        be.resolve_config(None, ["engine.refine.enabled"])


def test_a_config_file_is_read_by_gctrs_own_reader(tmp_path):
    """The benchmark reads a config file as `gctr` does (it had its own reader, without line and column, that let a
    key given twice pass): the same one-line messages, and --set applied on top of the file."""
    good = tmp_path / "good.yaml"
    good.write_text("\ufeffengine:\n  tensor:\n    knn: 12\n")
    config, d = be.resolve_config(good, ["engine.refine.enabled=false"])
    assert config.engine.tensor.knn == 12 and config.engine.refine.enabled is False
    assert d["engine"]["tensor"]["knn"] == 12
    cases = {
        "twice.yaml": ("engine:\n  seed: 1\nengine:\n  seed: 2\n",
                       "is not valid YAML (line 3, column 1): key 'engine' is given twice"),
        "bad.yaml": ("engine:\n  tensor: [1, 2\n", "is not valid YAML (line 2,"),
        "list.yaml": ("- 1\n- 2\n", "top level must be a mapping, got list"),
        "latin.yaml": ("engine: caf\xe9\n".encode("latin-1"), "is not UTF-8 text (bad byte at offset 11)"),
    }
    for name, (text, message) in cases.items():
        path = tmp_path / name
        path.write_bytes(text if isinstance(text, bytes) else text.encode())
        with pytest.raises(be.BenchError) as err:
            be.resolve_config(path, [])
        assert str(path) in str(err.value) and message in str(err.value), str(err.value)
    with pytest.raises(be.BenchError, match="does not exist"):
        be.resolve_config(tmp_path / "missing.yaml", [])


def test_quick_keeps_first_three_pairs_per_model_and_level(tmp_path):
    rows = []
    for level in ("cross", "hard"):
        for model in ("a", "b"):
            for k in range(5):
                pid = f"{level}_{model}_{k}"
                rows.append({"pair_id": pid, "source": f"{pid}_s.ply", "target": f"{pid}_t.ply", "gt": f"{pid}.txt",
                             "model": model, "level": level, "scale_gt": "", "overlap_src": "", "overlap_tgt": ""})
                (tmp_path / f"{pid}_s.ply").touch()  # (load_tasks checks that the files are there)
                (tmp_path / f"{pid}_t.ply").touch()
                (tmp_path / f"{pid}.txt").write_text("1 0 0 0\n0 1 0 0\n0 0 1 0\n0 0 0 1\n")
    mb.write_manifest(tmp_path / "pairs.csv", rows)
    config, d = be.resolve_config(None, [])
    tasks = be.load_tasks(tmp_path / "pairs.csv", ["hard", "cross"], True, config, d)
    assert [t["pair_id"] for t in tasks] == [f"{lv}_{m}_{k}" for lv in ("hard", "cross") for m in "ab"
                                             for k in range(3)]
    assert len({t["seed"] for t in tasks}) == len(tasks)
    assert len(be.load_tasks(tmp_path / "pairs.csv", ["cross"], False, config, d)) == 10
    with pytest.raises(be.BenchError, match="no pairs for level"):
        be.load_tasks(tmp_path / "pairs.csv", ["easy"], False, config, d)
    # bad benchmark data is named before anything runs, not counted as the engine's refusal or dropped
    # (a missing cloud and a corrupt ground truth ran as "honest failures"; a damaged row vanished: an audit)
    good = list(rows)
    (tmp_path / "bad.txt").write_text("not a matrix\n")
    (tmp_path / "folder.ply").mkdir()
    for change, message in ((lambda r: r.update(source="gone.ply"), "its source .*gone.ply does not exist"),
                            (lambda r: r.update(target="folder.ply"), "its target .*folder.ply is not a regular file"),
                            (lambda r: r.update(gt="bad.txt"), "ground truth .*bad.txt"),
                            (lambda r: r.update(level="eazy"), "unknown level 'eazy'"),
                            (lambda r: r.update(level=""), "no level")):
        rows = [dict(r) for r in good]
        change(rows[-1])
        mb.write_manifest(tmp_path / "pairs.csv", rows)
        with pytest.raises(be.BenchError, match=message):
            be.load_tasks(tmp_path / "pairs.csv", ["hard", "cross"], False, config, d)


def test_stage_table_and_failed_list_render():
    rows = [
        {"pair_id": "p1", "level": "cross", "model": "m", "status": "ok", "success": True, "rot_err_deg": 0.1,
         "trans_err_rel": 0.001, "scale_err": 0.001, "tm_err": 0.01, "time_s": 1.0, "cpu_s": 0.9, "load_s": 0.01,
         "n_source": 20000, "n_target": 5000, "peak_rss_mb": 120.0, "rss_baseline_mb": 80.0,
         "rss_increment_mb": 40.0, "load_avg_1m": 1.0, "timings": {"tensor": 0.6, "ransac": 0.3}},
        {"pair_id": "p2", "level": "cross", "model": "n", "status": "failed", "success": False, "rot_err_deg": 90.0,
         "trans_err_rel": 1.0, "scale_err": 0.5, "tm_err": 3.0, "time_s": 3.0, "cpu_s": 2.9, "load_s": 0.01,
         "n_source": 20000, "n_target": 5000, "peak_rss_mb": 130.0, "rss_baseline_mb": 80.0,
         "rss_increment_mb": 50.0, "load_avg_1m": 3.0, "message": "too weak | evidence",
         "timings": {"tensor": 1.0, "ransac": 1.5}},
    ]
    info = {"variant": "v", "date": "d", "command": "python -m data_scripts.bench_engine", "load_before": 1.0,
            "load_after": 1.0, "machine": {"cores": "2", "cpu": "x", "python": "3", "numpy": "2", "scipy": "1"},
            "config_source": "built-in defaults", "overrides": [], "config_hash": "h", "seed": 0,
            "success": {"rotation_deg": 5.0, "translation_rel": 0.05, "scale": 0.05}, "data": "d", "csv": "c",
            "quick": False, "jobs": 1, "wall_s": 4.0, "code": "git `x`"}
    text = be.render_section(rows, ["cross"], info)
    assert "| cross | 2 | 2 | 20000 / 5000 | 1/2 (50.0%) |" in text
    assert "| tensor | 0.800 (40%) |" in text and "| ransac | 0.900 (45%) |" in text
    assert "| other | 0.300 (15%) |" in text and "| **total** | 2.000 (100%) |" in text
    assert "| refine |" not in text  # a stage that never ran is left out
    assert re.search(r"\| p2 \| cross \| failed \| 90 \| 1 \| 0\.5 \| 3\.00 \| too weak \\\| evidence \|", text)
    assert ("other processes were running, but the pairs were not starved of CPU "
            "(median wall/CPU time ratio 1.07)") in text
    rows[1]["time_s"] = 6.0  # wall twice the CPU time: contention
    assert "they took CPU from the benchmark" in be.render_section(rows, ["cross"], info)
    assert "Machine reference" not in text  # a report rendered without the reference has no such line
    with_reference = be.render_section(rows, ["cross"], {**info, "reference_s": (0.0551, 0.0562)})
    assert "- Machine reference: 0.055 s before, 0.056 s after the run" in with_reference


# ------------------------------------------------------------------------------------------ issue 9 verdicts
def test_render_verdicts_and_targets():
    nan = float("nan")
    rows = []
    for i, (st, su, conf, ws, diag) in enumerate([
            ("ok", True, 0.9, True, None), ("ok", False, 0.6, False, "search missed"),
            ("ok", False, 0.15, False, "precision"), ("failed", False, 0.05, True, "objective can't tell")]):
        rows.append({"pair_id": f"p{i}", "level": "part" if i < 2 else "scene", "model": f"m{i}", "status": st,
                     "success": su, "confidence": conf, "would_succeed": ws, "time_s": float(i + 1),
                     "cpu_s": float(i + 1), "n_source": 20000, "n_target": 5000, "peak_rss_mb": 300.0,
                     "rss_increment_mb": 200.0, "rss_baseline_mb": 100.0, "load_s": 0.01,
                     **({"diagnosis": diag} if diag else {})})
    info = {"min_confidence": 0.1, "plot": "confidence_tradeoff.png", "jobs": 1}
    text = "\n".join(be.render_verdicts(rows, ["part", "scene"], info))
    assert "| gctr | part | 2 | 1 (50.0%) | 1 (50.0%) | 0 (0.0%) | 1.50 | 1.90 |" in text
    assert "| gctr | scene | 2 | 0 (0.0%) | 1 (50.0%) | 1 (50.0%) | 3.50 | 3.90 |" in text
    assert "Silent wrong over all levels: **2 of 4 pairs (50.0%)**." in text
    assert "| 0.00 | 2 (50.0%) | 0 (0.0%) |" in text  # t = 0: the refused-but-right pair is accepted
    assert "| 0.10 (configured) | 2 (50.0%) | 1 (25.0%) |" in text
    assert "| 0.20 | 1 (25.0%) | 1 (25.0%) |" in text
    assert "| 0.70 | 0 (0.0%) | 1 (25.0%) |" in text
    assert "![confidence trade-off](confidence_tradeoff.png)" in text
    assert "| part | 1 | 1 | 0 | 0 | 0 |" in text and "| scene | 2 | 0 | 1 | 1 | 0 |" in text
    assert "returned no confidence" not in text
    assert "returned no confidence" in "\n".join(
        be.render_verdicts([{**r, "confidence": nan} for r in rows], ["part", "scene"], info))

    stats = {lv: be._level_stats([r for r in rows if r["level"] == lv]) for lv in ("part", "scene")}
    targets = {t[0].split(":")[0]: (t[1], t[2]) for t in be._targets(stats, rows, info)}
    assert targets["`part`"] == ("1/2 (50.0%), 2 models/scenes", False)
    assert targets["silent wrong ≤ 1% of all pairs over all levels"] == ("2/4 (50.0%)", False)
    time_target = [t for t in be._targets(stats, rows, {**info, "reference_s": (0.5, 0.6)}) if "median time" in t[0]]
    assert time_target[0][1].endswith("; 5.0× the machine reference")  # median 2.5 s / 0.5 s
    assert be.SUCCESS_TARGETS["scene"] == 0.80 and be.SUCCESS_TARGETS["sfm"] == 0.95



def test_outcomes_by_shared_share_split_the_scene_windows_by_sensor():
    nan = float("nan")

    def row(level: str, model: str, share: float, status: str, success: bool, would: bool | None) -> dict:
        return {"pair_id": f"{level}_{model}_{share}", "level": level, "model": model, "overlap_src": share,
                "status": status, "success": success, "would_succeed": would}

    rows = [row("scene", "nclt", 0.28, "failed", False, False), row("scene", "nclt", 0.30, "ok", False, False),
            row("scene", "nclt", 0.57, "failed", False, True), row("scene", "nclt", 0.56, "ok", True, True),
            row("scene", "redkitchen0", 0.40, "ok", True, True), row("scene", "redkitchen0>4", nan, "ok", True, True),
            row("lowoverlap", "bunny", 0.45, "ok", True, True), row("easy", "bunny", 0.95, "ok", True, True)]
    text = "\n".join(be.render_by_overlap(rows, ["easy", "lowoverlap", "scene"]))
    assert "| level | < 35% | 35%–45% | 45%–55% | 55%–100% |" in text
    # pairs / success / silent wrong / refused / refused although right
    assert "| scene, NCLT LiDAR windows | 2 / 0 / **1** / 1 / 0 | – | – | 2 / 1 / **0** / 1 / 1 |" in text
    assert "| scene, redkitchen windows | – | 1 / 1 / **0** / 0 / 0 | – | – |" in text  # the real pair has no share
    assert "| lowoverlap | – | – | 1 / 1 / **0** / 0 / 0 | – |" in text
    assert "easy" not in text
    assert be.render_by_overlap([row("easy", "bunny", 0.9, "ok", True, True)], ["easy"]) == []
    assert be.float_or_nan(" 0.4617 ") == 0.4617  # a manifest cell
    assert be.float_or_nan("") != be.float_or_nan(None)  # both NaN


# ------------------------------------------------------------------------------------------ issue 10 stages before
def test_reference_workload_is_a_positive_time_and_takes_the_fastest_repeat(monkeypatch):
    from data_scripts import common

    clock = iter([0.0, 0.3, 1.0, 1.1, 2.0, 2.5])  # repeats of 0.3, 0.1 and 0.5 s
    monkeypatch.setattr(common.time, "perf_counter", lambda: next(clock))
    assert common.reference_workload_seconds(repeats=3) == pytest.approx(0.1)
    monkeypatch.undo()
    assert 0 < common.reference_workload_seconds(repeats=1) < 30


def test_read_stage_table_of_the_committed_before_file():
    path = REPO / "bench" / "stages-before-speed.md"
    before = be.read_stage_table(path.read_text(), str(path))
    assert before["levels"] == ["easy", "cross", "hard", "real", "part", "lowoverlap", "sfm", "scene"]
    assert before["means"]["tensor"] == 0.662 and before["means"]["verdict"] == 0.257
    assert before["means"]["other"] == 0.017 and before["means"]["total"] == 2.551
    assert list(before["means"])[:2] == ["preprocess", "supervoxels"]
    assert before["lines"][0].startswith("| stage | easy |") and before["lines"][-1].startswith("| **total** |")
    assert "\n".join(before["lines"]) in path.read_text()  # verbatim


def test_read_stage_table_rejects_what_it_cannot_read():
    with pytest.raises(be.BenchError, match="no table"):
        be.read_stage_table("# nothing here\n")
    with pytest.raises(be.BenchError, match="no 'all' column"):
        be.read_stage_table("| stage | cross |\n|---|---:|\n| tensor | 0.5 (50%) |\n")
    with pytest.raises(be.BenchError, match="cannot read the 'all' cell of stage 'tensor'"):
        be.read_stage_table("| stage | all |\n|---|---:|\n| tensor | fast |\n")


def test_stages_before_section_follows_the_stage_table_with_before_now_ratio():
    before_text = ("### Time per stage\n\nsome words\n\n| stage | cross | all |\n|---|---:|---:|\n"
                   "| tensor | 1.000 (50%) | 1.000 (50%) |\n| verdict | 0.500 (25%) | 0.500 (25%) |\n"
                   "| other | 0.500 (25%) | 0.500 (25%) |\n| **total** | 2.000 (100%) | 2.000 (100%) |\n\nmore\n")
    before = be.read_stage_table(before_text)
    assert before["means"] == {"tensor": 1.0, "verdict": 0.5, "other": 0.5, "total": 2.0}
    rows = [{"pair_id": f"p{i}", "level": "cross", "model": "m", "status": "ok", "success": True, "time_s": t,
             "cpu_s": t, "load_s": 0.01, "n_source": 100, "n_target": 100, "peak_rss_mb": 1.0,
             "rss_baseline_mb": 1.0, "rss_increment_mb": 0.0, "timings": {"tensor": tt, "ransac": 0.1}}
            for i, (t, tt) in enumerate([(0.8, 0.4), (1.2, 0.6)])]
    means = be.stage_means(rows, be.stage_names(rows))
    assert means["tensor"] == pytest.approx(0.5) and means["total"] == pytest.approx(1.0)
    assert means["other"] == pytest.approx(0.4)
    info = {"variant": "v", "date": "d", "command": "c", "load_before": 1.0, "load_after": 1.0,
            "machine": {"cores": "2", "cpu": "x", "python": "3", "numpy": "2", "scipy": "1"},
            "config_source": "built-in defaults", "overrides": [], "config_hash": "h", "seed": 0,
            "success": {"rotation_deg": 5.0, "translation_rel": 0.05, "scale": 0.05}, "data": "d", "csv": "c",
            "quick": False, "jobs": 1, "wall_s": 2.0, "code": "git `x`",
            "stages_before": {**before, "path": "bench/stages-before-speed.md", "note": be.STAGES_BEFORE_NOTE}}
    text = be.render_section(rows, ["cross"], info)
    stage_table = text.index("### Time per stage\n")
    section = text.index("### Time per stage before the speed work (issue 10)")
    assert stage_table < section < text.index("### Failed pairs")
    assert "| **total** | 1.000 (100%) |" in text[stage_table:section]  # the current table comes first
    assert f"From `bench/stages-before-speed.md`: {be.STAGES_BEFORE_NOTE}." in text[section:]
    assert "another machine" in be.STAGES_BEFORE_NOTE  # the seconds of two CPUs are not comparable
    assert "\n".join(before["lines"]) in text[section:]
    lines = text[section:].splitlines()
    comparison = lines[lines.index("| stage | before (s) | now (s) | now / before |"):]
    assert comparison[2:8] == ["| tensor | 1.000 | 0.500 | 0.50 |", "| verdict | 0.500 | – | – |",
                               "| ransac | – | 0.100 | – |", "| other | 0.500 | 0.400 | 0.80 |",
                               "| **total** | 2.000 | 1.000 | 0.50 |", ""]
    assert "Not like for like" not in text
    assert "the levels differ" in be.render_section(rows, ["cross"], {**info, "stages_before": {
        **info["stages_before"], "levels": ["cross", "hard"]}})
    assert "### Time per stage before" not in be.render_section(rows, ["cross"], {**info, "stages_before": None})


def test_stages_before_option_fails_early_on_a_bad_file(tmp_path, capsys):
    bad = tmp_path / "before.md"
    bad.write_text("no table\n")
    assert be.main(["--data", str(tmp_path / "nodata"), "--stages-before", str(bad)]) == 2
    assert "no table" in capsys.readouterr().err


def test_a_failed_generation_is_a_clear_error_not_a_traceback(monkeypatch, tmp_path):
    """Without the shared data beside the repository the generator stops with its own usage message; the
    benchmark then says which folder it could not generate and how to do it by hand (exit status 2)."""
    monkeypatch.setattr(be.subprocess, "run", lambda *a, **k: subprocess.CompletedProcess(a, 2))
    with pytest.raises(be.BenchError, match=r"generating .*d7 failed \(exit status 2\).*--data DIR"):
        be.ensure_data(tmp_path / "d7", 7)
    assert be.main(["--seed", "7", "--data", str(tmp_path / "d7"), "--no-diagnose", "-q",
                    "--out", str(tmp_path / "x.md")]) == 2


def test_the_report_header_names_the_pairs_this_run_used():
    """It said "the report set … --seed 0" for any run, then "(`--seed 1` here)" (found by an audit)."""
    from data_scripts.bench_engine import report_header

    text = report_header("d/pairs.csv", ["easy", "part"], 9)
    assert "Pairs:\n`d/pairs.csv`, levels easy,part, generator seed 9 — a set other than the report and tuning" in text
    assert "the report set (" in report_header("d/pairs.csv", ["easy"], 0)
