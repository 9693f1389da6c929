"""data_scripts/bench_process.py: argument parsing and report formatting only (no process is timed here)."""

from __future__ import annotations

import argparse
from pathlib import Path
from types import SimpleNamespace

import pytest

from data_scripts import bench_process as bp
from gctr_cli.methods import BASELINES


def test_methods_default_to_every_comparison_method_of_the_registry():
    args = bp.build_parser().parse_args([])
    assert args.methods == list(BASELINES)
    assert {"icp", "fpfh_ransac", "fgr", "cpd", "kiss_matcher"} <= set(args.methods)
    assert "gctr" not in args.methods  # the engine has its own row (`gctr register`, no config)


def test_methods_option_picks_validates_and_allows_none(capsys):
    parse = bp.build_parser().parse_args
    assert parse(["--methods", "cpd, icp,cpd"]).methods == ["cpd", "icp"]  # given order, duplicates dropped
    assert parse(["--methods", ""]).methods == []
    with pytest.raises(SystemExit):
        parse(["--methods", "icp,nope"])
    assert "unknown comparison method(s) nope" in capsys.readouterr().err
    with pytest.raises(argparse.ArgumentTypeError, match="gctr"):
        bp.parse_methods("gctr")


def test_table_row_runtime_overhead_and_ratio():
    row = bp.table_row("gctr register, method icp", [3.0, 2.0, 4.0], 2.0, 1.25, None, [1.0, 2.0, 1.5])
    cells = [c.strip() for c in row.strip("|").split("|")]
    # median wall 3.0, min 2.0, 3.0 / 2.0, imports, -X importtime not measured, runtime 1.5, overhead 3.0 - 1.5
    assert cells == ["`gctr register, method icp`", "3.000", "2.000", "1.50", "1.250", "–", "1.500", "1.500"]
    assert len(cells) == len(bp.TABLE_HEADER[0].strip("|").split("|"))
    ref = bp.table_row("Open3D script", [2.0], 2.0, 1.1, 1.0, None)
    assert ref.endswith("| 1.00 | 1.100 | 1.000 | – | – |")


def test_accuracy_line_ok_wrong_and_failed():
    thresholds = SimpleNamespace(rotation_deg=5.0, translation_rel=0.05, scale=0.05)
    good = SimpleNamespace(rot_err_deg=0.5, trans_err_rel=0.002, scale_err=0.001)
    wrong = SimpleNamespace(rot_err_deg=43.1, trans_err_rel=0.09, scale_err=0.3)
    assert bp.accuracy_line("gctr register", "ok", good, success=thresholds) == \
        "| gctr register | ok | 0.5 | 0.002 | 0.001 | yes |"
    assert bp.accuracy_line("icp", "ok", wrong, success=thresholds).endswith("| 43.1 | 0.09 | 0.3 | **no** |")
    assert bp.accuracy_line("cpd", "failed", None, "too few | points") == \
        "| cpd | failed (too few / points) | – | – | – | no |"
    for line in (bp.accuracy_line("x", "ok", good), bp.accuracy_line("y", "failed")):
        assert line.count("|") == bp.ACCURACY_HEADER[0].count("|")


def test_command_lines_are_exact_and_list_the_method_configs(tmp_path, monkeypatch):
    monkeypatch.setattr(bp.shutil, "which", lambda name: "/usr/bin/taskset")
    cfg = tmp_path / "method-icp.yaml"
    cfg.write_text("method: icp\n")
    commands = {"gctr register, method icp": ["/v/bin/gctr", "register", "-c", str(cfg), "a b.ply", "t.ply"],
                "python -c pass": ["/v/bin/python", "-c", "pass"]}
    text = "\n".join(bp.command_lines(commands, 1, {"gctr register, method icp": cfg}))
    assert f"- `gctr register, method icp`: `taskset -c 1 /v/bin/gctr register -c {cfg} 'a b.ply' t.ply`" in text
    assert "- `python -c pass`: `taskset -c 1 /v/bin/python -c pass`" in text
    assert "OMP_NUM_THREADS=1" in text
    assert f"`{bp._rel(Path(cfg))}` = `method: icp`" in text


def _kdamond(root, state, action="pageout", aggr_us=5_000_000, min_age=12):
    ctx = root / "0" / "contexts" / "0"
    (ctx / "monitoring_attrs" / "intervals").mkdir(parents=True)
    (ctx / "schemes" / "0" / "access_pattern" / "age").mkdir(parents=True)
    (root / "0" / "state").write_text(state + "\n")
    (ctx / "monitoring_attrs" / "intervals" / "aggr_us").write_text(f"{aggr_us}\n")
    (ctx / "schemes" / "0" / "access_pattern" / "age" / "min").write_text(f"{min_age}\n")
    (ctx / "schemes" / "0" / "action").write_text(action + "\n")


def test_damon_state_reports_the_idle_age_after_which_pages_go(tmp_path):
    _kdamond(tmp_path, "on")
    assert bp.damon_state(tmp_path) == "on (pageout after 60 s idle)"
    off = tmp_path / "off"
    _kdamond(off, "off")
    assert bp.damon_state(off) == "off or not available"
    assert bp.damon_state(tmp_path / "missing") == "off or not available"


def test_every_timed_run_is_warmed_unless_told_otherwise():
    assert bp.build_parser().parse_args([]).warm is True
    assert bp.build_parser().parse_args(["--no-warm"]).warm is False
