"""The ``gctr`` command line: help, config, manifest, register and batch (exit codes 0/1/2/3).

Batch and register tests swap in the deterministic fake engine (``data_scripts/fake_engine.py``) through
monkeypatch, so the production command path is exercised with everything but the algorithm.
Tests marked ``engine`` run the real GCTR engine end to end.
"""

from __future__ import annotations

import functools
import os
import subprocess
import textwrap
from pathlib import Path

import numpy as np
import pytest
import yaml
from click.testing import CliRunner
from conftest import (
    PYTHON,
    REPO,
    bumpy_surface,
    read_csv,
    rotation,
    row_matrix,
    write_cloud,
    write_manifest_rows,
)

from data_scripts import fake_engine
from gctr_cli import batch, cli
from gctr_cli.batch import ERRORS_COLUMNS, TRANSFORMS_COLUMNS
from gctr_cli.config import Config, config_from_dict
from gctr_cli.geometry import apply, to_matrix
from gctr_cli.io import load_point_cloud, read_matrix, write_matrix
from gctr_cli.metrics import transform_errors


@pytest.fixture
def runner():
    return CliRunner()


@pytest.fixture
def fake_batch(monkeypatch):
    """``gctr batch`` runs the fake engine in its workers."""
    monkeypatch.setattr(batch, "run_batch", functools.partial(batch.run_batch, register_fn=fake_engine.register))


@pytest.fixture
def fake_register(monkeypatch):
    """``gctr register`` (in-process) uses the fake engine."""
    import gctr_cli.engine

    monkeypatch.setattr(gctr_cli.engine, "register", fake_engine.register)


def invoke(runner, *args):
    return runner.invoke(cli.main, [str(a) for a in args], catch_exceptions=False)


def gctr(*args, env=None, cwd=None, timeout=300):
    return subprocess.run([PYTHON, "-m", "gctr_cli", *map(str, args)], capture_output=True, text=True,
                          env=env, cwd=cwd, timeout=timeout)


# ----------------------------------------------------------------------------------------------------
# help and config
# ----------------------------------------------------------------------------------------------------


def test_help_is_lazy_and_documents_exit_codes():
    code = textwrap.dedent(
        """
        import sys
        from gctr_cli.cli import main
        for args in (["--help"], ["batch", "--help"], ["register", "--help"], ["config", "--help"]):
            try:
                main(args)
            except SystemExit as e:
                assert e.code == 0, e.code
        heavy = [m for m in ("open3d", "numpy", "scipy", "pydantic", "gctr_cli.engine") if m in sys.modules]
        print("HEAVY:", heavy)
        """
    )
    out = subprocess.run([PYTHON, "-c", code], capture_output=True, text=True, timeout=60)
    assert out.returncode == 0, out.stderr
    assert "HEAVY: []" in out.stdout
    assert "Exit codes:" in out.stdout and "--min-success" in out.stdout
    for line in ("0  every pair registered", "1  at least one pair failed", "2  usage, manifest, config",
                 "3  --min-success given"):
        assert line in out.stdout
    top_help, batch_help = out.stdout.split("Usage: ")[1:3]
    register_help = out.stdout.split("Usage: ")[3]
    for text in (top_help, batch_help, register_help):  # the signals' codes, SIGHUP's too (as in the README)
        assert "130/143" in text and "129: SIGHUP" in text


def test_cli_thread_variables_match_the_batch_workers():
    assert cli.THREAD_ENV_VARS == batch.THREAD_ENV_VARS


def test_python_m_gctr_cli(tmp_path):
    out = gctr("--version")
    assert out.returncode == 0 and "gctr" in out.stdout
    out = gctr("batch", "--help")
    assert out.returncode == 0 and "Exit codes:" in out.stdout
    out = gctr("frobnicate")
    assert out.returncode == 2 and "No such command" in out.stderr


def test_config_show_is_commented_yaml_of_the_defaults(runner):
    res = invoke(runner, "config", "show")
    assert res.exit_code == 0
    assert "# base seed" in res.output and "# working size of each cloud" in res.output
    assert "one of: auto, edge_ratio, umeyama" in res.output
    data = yaml.safe_load(res.output)
    assert data == Config().model_dump(mode="json")
    assert config_from_dict(data) == Config()


def test_config_show_file_and_check(runner, tmp_path):
    good = tmp_path / "good.yaml"
    good.write_text("seed: 42\nengine:\n  refine:\n    enabled: false\nbatch:\n  workers: 3\n")
    res = invoke(runner, "config", "show", good)
    assert res.exit_code == 0
    assert yaml.safe_load(res.output)["seed"] == 42
    assert yaml.safe_load(res.output)["engine"]["refine"]["enabled"] is False
    res = invoke(runner, "config", "check", good)
    assert (res.exit_code, res.output.strip()) == (0, f"ok: {good}")


@pytest.mark.parametrize(
    "text, expected",
    [
        ("engine:\n  tensor:\n    knn: 40\n    foo: 1\n", ["engine.tensor.foo: unknown key"]),
        ("batch:\n  workers: many\n", ["batch.workers", "integer"]),
        ("success:\n  rotation_deg: -1\n", ["success.rotation_deg", "greater than 0"]),
        ("seed: [1, 2\n", ["not valid YAML"]),
        # a key without ':' on the last line: PyYAML notices at the end, "line 5" of a 4-line file
        ("engine:\n  tensor:\n    knn: 5\n  bad_indent\n",
         ["not valid YAML (line 4, column 3): while scanning a simple key, could not find expected ':'"]),
        ("- just\n- a list\n", ["top level must be a mapping"]),
        # a control character: PyYAML gives a character offset and a second line, not a line and column
        ("engine:\n  seed: 3\n\x00\n", ["not valid YAML (line 3, column 1): control character 0x00 is not allowed"]),
        ("seed: \x01\n", ["not valid YAML (line 1, column 7): control character 0x01 is not allowed"]),
        # a byte-order mark (Windows editors) is not a column of line 1
        ("\ufeffseed: \x01\n", ["not valid YAML (line 1, column 7): control character 0x01 is not allowed"]),
        ("\ufeffseed: [1, 2\n", ["not valid YAML (line 1, column 7): while parsing a flow sequence"]),
        ("engine:\n  seed: 1\nengine:\n  seed: 2\n", ["(line 3, column 1): key 'engine' is given twice"]),
        ("engine:\n  refine:\n    end_ratio: 0.9\n", ["engine.refine.end_ratio must not exceed"]),
        ("engine:\n  refine:\n    iterations: on\n", ["engine.refine.iterations", "expected a number, got a boolean"]),
        ("engine:\n  scale_bounds: [true, 5]\n", ["engine.scale_bounds", "expected a number, got a boolean"]),
        ("engine:\n  scale_bounds: [1, 1.0001]\n", ["engine.scale_bounds", "narrower than 0.2%", "[0.99, 1.01]"]),
        ("baselines: {kiss_matcher: {solver_noise_bound_gain: 2}}\n",
         ["baselines.kiss_matcher: solver_noise_bound_gain must not exceed robin_noise_bound_gain"]),
    ],
)
def test_config_errors_exit_2_naming_the_key(runner, tmp_path, text, expected):
    bad = tmp_path / "bad.yaml"
    bad.write_text(text)
    res = invoke(runner, "config", "check", bad)
    assert res.exit_code == 2
    for piece in expected:
        assert piece in res.stderr
    assert "(got {" not in res.stderr  # a check across keys names them, not the whole section
    # the same error stops a batch before anything runs
    (tmp_path / "pairs.csv").write_text("pair_id,source,target\na,a.ply,b.ply\n")
    res = invoke(runner, "batch", tmp_path / "pairs.csv", "-c", bad, "-o", tmp_path / "out")
    assert res.exit_code == 2 and expected[0] in res.stderr
    assert not (tmp_path / "out").exists()


def test_yaml_merge_keys_may_be_overridden(runner, tmp_path):
    cfg = tmp_path / "merge.yaml"
    cfg.write_text("engine:\n  power_iteration:\n    <<: {iterations: 10}\n"
                   "    iterations: 12\n")
    res = invoke(runner, "config", "show", cfg)
    assert res.exit_code == 0, res.stderr
    assert yaml.safe_load(res.output)["engine"]["power_iteration"]["iterations"] == 12


def test_a_config_that_is_not_text_exits_2_without_a_traceback(tmp_path):
    latin = tmp_path / "latin.yaml"
    latin.write_bytes("seed: 3  # caf\u00e9\n".encode("latin-1"))
    out = gctr("config", "check", latin)
    assert out.returncode == 2
    assert out.stderr.strip() == (f"gctr: error: config file {latin} is not UTF-8 text (bad byte at offset 14); "
                                  "is it a YAML file?")
    bom = tmp_path / "bom.yaml"  # the offset counts the byte-order mark: it is the file's byte
    bom.write_bytes(b"\xef\xbb\xbfseed: 1\n\xff\n")
    out = gctr("config", "check", bom)
    assert out.returncode == 2 and "(bad byte at offset 11)" in out.stderr, out.stderr


def test_a_method_that_is_not_installed_is_a_config_error(runner, tmp_path, monkeypatch):
    import gctr_cli.methods

    monkeypatch.setattr(gctr_cli.methods, "is_available", lambda method: method != "kiss_matcher")
    cfg = tmp_path / "kiss.yaml"
    cfg.write_text("method: kiss_matcher\n")
    res = invoke(runner, "config", "check", cfg)
    assert res.exit_code == 2
    assert f"{cfg}: method 'kiss_matcher' needs the optional package 'kiss_matcher'" in res.stderr
    (tmp_path / "pairs.csv").write_text("pair_id,source,target\na,a.ply,b.ply\n")
    res = invoke(runner, "batch", tmp_path / "pairs.csv", "-c", cfg, "-o", tmp_path / "out")
    assert res.exit_code == 2 and not (tmp_path / "out").exists()
    assert invoke(runner, "config", "show", cfg).exit_code == 0  # showing it is fine


def test_usage_errors_are_one_line_like_every_other_error(tmp_path):
    out = gctr("register", tmp_path / "a.ply")
    assert out.returncode == 2
    assert out.stderr.strip() == "gctr: error: Missing argument 'TARGET'. (see 'gctr register --help')"
    assert gctr("--version").returncode == 0


def test_printing_commands_on_a_full_stdout_say_so_in_one_line(tmp_path):
    """`gctr config show > /dev/full` (or --help, --version, config check, manifest) ended in an OSError
    traceback and exit 1. Where the printed text is the result (the YAML, the help) it is exit 2 with one
    line; where a file or the exit code is the result, a warning and the command's own exit code."""
    def full(*args):
        with open("/dev/full", "w") as dev_full:
            return subprocess.run([PYTHON, "-m", "gctr_cli", *map(str, args)], stdout=dev_full,
                                  stderr=subprocess.PIPE, text=True, timeout=120)

    for args, problem in ((("config", "show"), "cannot print the configuration"),
                          (("--help",), "cannot print to standard output"),
                          (("--version",), "cannot print to standard output"),
                          (("config", "--help"), "cannot print to standard output")):
        done = full(*args)
        assert (done.returncode, done.stderr) == (2, f"gctr: error: {problem} (No space left on device)\n"), args
    good = tmp_path / "good.yaml"
    good.write_text("seed: 3\n")
    done = full("config", "check", good)
    assert done.returncode == 0
    assert done.stderr == f"gctr: WARNING: cannot print 'ok: {good}' (No space left on device)\n"
    rng = np.random.default_rng(0)
    write_cloud(tmp_path / "a" / "s.ply", bumpy_surface(rng, 50))
    write_cloud(tmp_path / "b" / "s.ply", bumpy_surface(rng, 50))
    done = full("manifest", tmp_path / "a", tmp_path / "b", "-o", tmp_path / "pairs.csv")
    assert done.returncode == 0 and "Traceback" not in done.stderr, done.stderr
    assert "cannot print the summary line (No space left on device)" in done.stderr
    assert (tmp_path / "pairs.csv").read_text().startswith("pair_id,source,target\n")
    # a reader that quits early is not an error at all
    piped = subprocess.run(f"{PYTHON} -m gctr_cli --help | head -1", shell=True, capture_output=True, text=True,
                           timeout=120)
    assert piped.stdout.startswith("Usage: gctr") and piped.stderr == ""


def test_config_check_missing_file_via_subprocess(tmp_path):
    out = gctr("config", "check", tmp_path / "nope.yaml")
    assert out.returncode == 2 and "does not exist" in out.stderr


# ----------------------------------------------------------------------------------------------------
# manifest
# ----------------------------------------------------------------------------------------------------


def test_manifest_command(runner, tmp_path):
    rng = np.random.default_rng(0)
    for stem, se, te in (("a", ".ply", ".pcd"), ("b", ".xyz", ".ply"), ("c", ".pcd", ".xyz")):
        write_cloud(tmp_path / "lidar" / f"{stem}{se}", bumpy_surface(rng, 50))
        write_cloud(tmp_path / "photo" / f"{stem}{te}", bumpy_surface(rng, 50))
    write_cloud(tmp_path / "photo" / "only_here.ply", bumpy_surface(rng, 50))
    write_matrix(tmp_path / "gt" / "a.txt", np.eye(4))
    res = invoke(runner, "manifest", tmp_path / "lidar", tmp_path / "photo", "--gt-dir", tmp_path / "gt",
                 "-o", tmp_path / "pairs.csv")
    assert res.exit_code == 0, res.output
    assert "wrote 3 pairs (1 with ground truth)" in res.stdout
    from gctr_cli.manifest import read_manifest

    pairs = read_manifest(tmp_path / "pairs.csv")
    assert [p.pair_id for p in pairs] == ["a", "b", "c"]
    assert pairs[0].source == (tmp_path / "lidar" / "a.ply").resolve()
    assert pairs[0].gt == (tmp_path / "gt" / "a.txt").resolve() and pairs[1].gt is None

    # the manifest must not replace a file it lists, nor another input of the folders (it did, silently)
    before = {f: f.read_bytes() for f in (tmp_path / "lidar" / "a.ply", tmp_path / "gt" / "a.txt",
                                          tmp_path / "photo" / "only_here.ply")}
    for out, says in ((tmp_path / "lidar" / "a.ply", "is also the source cloud of pair a"),
                      (tmp_path / "gt" / "a.txt", "is also the ground truth of pair a"),
                      (tmp_path / "photo" / "only_here.ply", "is an input file in TARGET_DIR")):
        res = invoke(runner, "manifest", tmp_path / "lidar", tmp_path / "photo", "--gt-dir", tmp_path / "gt",
                     "-o", out)
        assert res.exit_code == 2 and f"gctr: error: {out}: {says}" in res.stderr, res.stderr
    assert all(f.read_bytes() == data for f, data in before.items())

    res = invoke(runner, "manifest", tmp_path / "lidar", tmp_path / "nope", "-o", tmp_path / "p2.csv")
    assert res.exit_code == 2 and "does not exist" in res.stderr
    assert not (tmp_path / "p2.csv").exists()


# ----------------------------------------------------------------------------------------------------
# register
# ----------------------------------------------------------------------------------------------------


def test_register_command(runner, fake_register, four_pairs, tmp_path):
    row = four_pairs.rows[1]  # .pcd -> .xyz
    src, tgt, gt = (four_pairs.root / row[k] for k in ("source", "target", "gt"))
    out_matrix = tmp_path / "est.txt"
    res = invoke(runner, "register", src, tgt, "-o", out_matrix, "--gt", gt, "--seed", 11)
    assert res.exit_code == 0, res.output
    lines = res.stdout.splitlines()
    assert lines[0] == "status: ok"
    i = lines.index("matrix (source -> target):")
    printed = np.array([[float(v) for v in lines[i + k].split()] for k in range(1, 5)])
    assert np.array_equal(printed, read_matrix(out_matrix))  # printed at full precision
    np.testing.assert_allclose(printed, four_pairs.gt["pcd_xyz"], atol=1e-6)
    assert "seed: 11" in lines and "success: true" in lines and "fitness: 0.875" in lines
    assert lines[-1] == f"matrix_file: {out_matrix}"  # the write is confirmed, as --aligned's is
    for key in ("scale: ", "inlier_rmse: ", "runtime_s: ", "rot_err_deg: ", "trans_err_rel: ", "scale_err: ",
                "tm_err: "):
        assert any(line.startswith(key) for line in lines), key
    # the seed changes the (fake) result; default seed = config seed
    res2 = invoke(runner, "register", src, tgt)
    assert res2.exit_code == 0 and "seed: 0" in res2.stdout.splitlines()
    assert "matrix_file" not in res2.stdout


@pytest.mark.parametrize("flags", [("-v", "register"), ("register", "-v"), ("-v", "register", "-v"),
                                   ("-vv", "register", "-v")])
def test_verbose_before_or_after_the_command(runner, fake_register, four_pairs, tmp_path, flags):
    """-v works on either side of the command name, and the two sides count together."""
    row = four_pairs.rows[1]
    src, tgt = (four_pairs.root / row[k] for k in ("source", "target"))
    out_matrix = tmp_path / "est.txt"
    before, after = flags[: flags.index("register")], flags[flags.index("register") + 1:]
    try:
        res = invoke(runner, *before, "register", src, tgt, "-o", out_matrix, *after)
        assert res.exit_code == 0, res.output
        assert f"gctr: INFO: wrote {out_matrix}" in res.stderr
        assert cli.logger.getEffectiveLevel() == (10 if "".join(flags).count("v") >= 2 else 20)
    finally:
        cli._setup_logging(0)
    quiet = invoke(runner, "register", src, tgt, "-o", out_matrix)
    assert quiet.exit_code == 0 and "INFO" not in quiet.stderr


def test_verbose_on_the_config_group_and_its_commands(runner):
    for args in (("config", "-v", "show"), ("config", "show", "-v"), ("-v", "config", "-v", "show")):
        res = invoke(runner, *args)
        assert res.exit_code == 0 and res.stdout.startswith("# gctr configuration"), args
    cli._setup_logging(0)


def test_register_exit_codes(runner, fake_register, dataset, tmp_path):
    dataset.add_pair("fails", n=fake_engine.FAIL_N)
    row = dataset.rows[0]
    src, tgt = dataset.root / row["source"], dataset.root / row["target"]
    res = invoke(runner, "register", src, tgt, "-o", tmp_path / "m.txt")
    assert res.exit_code == 1
    assert "status: failed" in res.stdout and "message: too few inliers (3 < 6)" in res.stdout
    assert not (tmp_path / "m.txt").exists()

    res = invoke(runner, "register", tmp_path / "missing.ply", tgt)
    assert res.exit_code == 2 and f"{tmp_path}/missing.ply: file does not exist" in res.stderr
    (tmp_path / "bad_gt.txt").write_text("1 2 3\n")
    res = invoke(runner, "register", src, tgt, "--gt", tmp_path / "bad_gt.txt")
    expected = f"ground truth {tmp_path}/bad_gt.txt: line 1 has 3 values, expected 4 numbers"
    assert res.exit_code == 2 and expected in res.stderr
    (tmp_path / "bad.yaml").write_text("engine: {nope: 1}\n")
    res = invoke(runner, "register", src, tgt, "-c", tmp_path / "bad.yaml")
    assert res.exit_code == 2 and "engine.nope: unknown key" in res.stderr


def test_register_failures_say_what_is_there(runner, fake_register, dataset, tmp_path):
    """A folder named as an input gets the batch's message (click said "Invalid value for 'TARGET': File …
    is a directory"); a failed pair whose -o file exists from before says that the file is an older one."""
    dataset.add_pair("fails", n=fake_engine.FAIL_N)
    row = dataset.rows[0]
    src, tgt = dataset.root / row["source"], dataset.root / row["target"]
    (tmp_path / "dir.ply").mkdir()
    for args, what in (((src, tmp_path / "dir.ply"), ""), ((tmp_path / "dir.ply", tgt), ""),
                       ((src, tgt, "--gt", tmp_path / "dir.ply"), "ground truth "),
                       (("apply", tmp_path / "dir.ply", src, "-o", tmp_path / "x.ply"), "matrix ")):
        res = invoke(runner, *(args if args[0] == "apply" else ("register", *args)))
        expected = f"gctr: error: {what}{tmp_path}/dir.ply: is a folder, not a regular file\n"
        assert res.exit_code == 2 and res.stderr == expected
    (tmp_path / "m.txt").write_text("an earlier matrix\n")
    res = invoke(runner, "register", src, tgt, "-o", tmp_path / "m.txt")
    assert res.exit_code == 1 and (tmp_path / "m.txt").read_text() == "an earlier matrix\n"
    assert (f"gctr: no matrix written to {tmp_path}/m.txt (registration failed; the {tmp_path}/m.txt there is an "
            "older file, left as it was)") in res.stderr


def test_outputs_that_cannot_be_written_are_refused_before_any_work(runner, fake_register, four_pairs, tmp_path,
                                                                     monkeypatch):
    import gctr_cli.engine

    def must_not_run(*args, **kwargs):
        raise AssertionError("registered although the output cannot be written")

    monkeypatch.setattr(gctr_cli.engine, "register", must_not_run)
    row = four_pairs.rows[0]
    src, tgt = four_pairs.root / row["source"], four_pairs.root / row["target"]
    (tmp_path / "afile").write_text("")
    under_file = f"cannot write file ({tmp_path}/afile is a file, not a folder)"
    for args in (("-o", tmp_path / "afile" / "m.txt"), ("--aligned", tmp_path / "afile" / "a.ply")):
        res = invoke(runner, "register", src, tgt, *args)
        assert res.exit_code == 2 and f"{args[1]}: {under_file}" in res.stderr, args
        assert "status" not in res.stdout
    res = invoke(runner, "apply", tmp_path / "nope.txt", src, "-o", tmp_path / "afile" / "out.ply")
    assert res.exit_code == 2 and under_file in res.stderr
    res = invoke(runner, "show", src, tgt, "-o", tmp_path / "afile" / "v.png")
    assert res.exit_code == 2 and under_file in res.stderr
    res = invoke(runner, "show", src, tgt, "-o", tmp_path / "v.jpg")
    assert res.exit_code == 2 and "the picture is written as PNG" in res.stderr
    res = invoke(runner, "manifest", four_pairs.root, four_pairs.root, "-o", tmp_path / "afile" / "p.csv")
    assert res.exit_code == 2 and under_file in res.stderr


def test_apply_with_its_arguments_swapped_names_the_cloud_as_the_matrix(runner, four_pairs, tmp_path):
    src = four_pairs.root / four_pairs.rows[0]["source"]
    (tmp_path / "m.txt").write_text("1 0 0 0\n0 1 0 0\n0 0 1 0\n0 0 0 1\n")
    res = invoke(runner, "apply", src, tmp_path / "m.txt", "-o", tmp_path / "out.ply")
    assert res.exit_code == 2 and res.stderr.startswith(f"gctr: error: matrix {src}: "), res.stderr
    assert not (tmp_path / "out.ply").exists()


# ----------------------------------------------------------------------------------------------------
# batch
# ----------------------------------------------------------------------------------------------------


def test_batch_all_ok_exit_0_and_resume(runner, fake_batch, four_pairs, tmp_path):
    manifest = four_pairs.manifest()
    cfg = tmp_path / "cfg.yaml"
    cfg.write_text("seed: 3\nbatch:\n  workers: 2\n")
    out = tmp_path / "out"
    res = invoke(runner, "batch", manifest, "-c", cfg, "-o", out, "--min-success", 1.0)
    assert res.exit_code == 0, res.output
    assert "pairs: 5 (5 ok, 0 failed)" in res.stdout
    assert "success: 4/4 pairs with ground truth (100.0%)" in res.stdout
    assert "median errors: rotation" in res.stdout and "wall time:" in res.stdout
    header, rows = read_csv(out / "transforms.csv")
    assert header == list(TRANSFORMS_COLUMNS) and len(rows) == 5
    assert read_csv(out / "tm_errors.csv")[0] == list(ERRORS_COLUMNS)
    for r in rows:
        assert np.array_equal(row_matrix(r), read_matrix(out / "matrices" / f"{r['pair_id']}.txt"))
        assert int(r["seed"]) == batch.derive_seed(3, r["pair_id"])
    assert yaml.safe_load((out / "config.yaml").read_text())["batch"]["workers"] == 2
    assert res.stderr == ""  # no progress bar when stderr is not a terminal

    # a rerun without --resume refuses to touch the folder
    res = invoke(runner, "batch", manifest, "-c", cfg, "-o", out)
    assert res.exit_code == 2 and "--resume" in res.stderr
    # with --resume there is nothing left to do
    res = invoke(runner, "batch", manifest, "-c", cfg, "-o", out, "--resume", "-j", 1)
    assert res.exit_code == 0
    assert "pairs: 5 (5 ok, 0 failed) (5 done by an earlier run)" in res.stdout
    assert len(read_csv(out / "transforms.csv")[1]) == 5


def test_batch_names_the_pairs_that_are_ok_but_wrong(runner, fake_batch, four_pairs, tmp_path):
    """A CI log showed "success: 3/4" and exit 3 but named only refused pairs: which pair regressed, and by
    how much, took tm_errors.csv. The wrong answers are listed with the errors over their limits."""
    four_pairs.rows[0]["gt"] = four_pairs.rows[1]["gt"]  # ply_ply judged against another pair's ground truth
    errs = transform_errors(four_pairs.gt["ply_ply"], four_pairs.gt["pcd_xyz"], 1.0)
    res = invoke(runner, "batch", four_pairs.manifest(), "-o", tmp_path / "out", "-j", 1, "--min-success", 0.9)
    assert res.exit_code == 3, res.output
    assert "success: 3/4 pairs with ground truth (75.0%)" in res.stdout
    lines = res.stdout.splitlines()
    at = lines.index("ok but wrong by their ground truth:")
    assert lines[at + 1].startswith(f"  ply_ply: rotation {errs.rot_err_deg:.4g} deg (limit 5 deg)")
    assert len(lines) == at + 2 or not lines[at + 2].startswith("  ")  # only that pair


def test_batch_retry_failed_needs_resume(runner, fake_batch, four_pairs, tmp_path):
    res = invoke(runner, "batch", four_pairs.manifest(), "-o", tmp_path / "out", "--retry-failed")
    assert res.exit_code == 2
    assert res.stderr == ("gctr: error: --retry-failed needs --resume (it runs again the failed pairs of an earlier "
                          "run in OUTDIR)\n")
    assert not (tmp_path / "out").exists()


def test_batch_write_aligned(runner, fake_batch, four_pairs, tmp_path):
    out = tmp_path / "out"
    res = invoke(runner, "batch", four_pairs.manifest(), "-o", out, "-j", 1, "--write-aligned")
    assert res.exit_code == 0, res.output
    assert "matrices/, config.yaml, aligned/" in res.stdout
    specs = {s.pair_id: s for s in four_pairs.specs()}
    _, rows = read_csv(out / "transforms.csv")
    for r in rows:
        aligned = out / "aligned" / f"{r['pair_id']}{specs[r['pair_id']].source.suffix}"
        src = np.asarray(load_point_cloud(specs[r["pair_id"]].source))
        T = row_matrix(r)
        moved = np.asarray(load_point_cloud(aligned))
        np.testing.assert_allclose(moved, src @ T[:3, :3].T + T[:3, 3], rtol=1e-6,
                                   atol=1e-6 * np.abs(moved).max())


@pytest.mark.slow
def test_batch_exit_1_and_3(runner, fake_batch, four_pairs, tmp_path):
    ds = four_pairs
    (ds.root / "empty.pcd").write_bytes(b"")
    ds.add_raw("broken", "empty.pcd", ds.rows[0]["target"], ds.rows[0]["gt"])
    ds.add_pair("sigkill", n=fake_engine.KILL_N, with_gt=False)
    manifest = ds.manifest()
    # 4 of 5 pairs with gt succeed (80 %); two pairs failed
    res = invoke(runner, "batch", manifest, "-o", tmp_path / "o1", "-j", 2)
    assert res.exit_code == 1
    assert "pairs: 7 (5 ok, 2 failed)" in res.stdout
    assert "success: 4/5 pairs with ground truth (80.0%)" in res.stdout
    assert f"broken: {ds.root}/empty.pcd: file is empty" in res.stdout
    assert "sigkill: worker died (signal 9)" in res.stdout

    res = invoke(runner, "batch", manifest, "-o", tmp_path / "o2", "-j", 2, "--min-success", 0.8)
    assert res.exit_code == 1  # rate reached, but pairs failed
    # a gate that passes says so: a CI log shows that it was on
    assert "min-success 0.8: passed, success rate 0.8 (4 of 5 pairs with ground truth)" in res.stdout
    res = invoke(runner, "batch", manifest, "-o", tmp_path / "o3", "-j", 2, "--min-success", 0.80000001, "-q")
    assert res.exit_code == 3  # takes precedence over 1
    # both as given: "80.0% is below 80.0%" read as a contradiction
    assert "success rate 0.8 (4 of 5 pairs with ground truth) is below --min-success 0.80000001" in res.stderr


def test_workers_with_a_scheduler_are_said_to_have_no_effect(runner, monkeypatch, four_pairs, tmp_path):
    """-j with --scheduler was accepted without a word: the cluster's workers decide how many pairs run."""
    seen = {}

    def stop(*a, **k):
        seen.update(k)
        raise batch.BatchError("stopped by the test")

    monkeypatch.setattr(batch, "run_batch", stop)
    res = invoke(runner, "batch", four_pairs.manifest(), "-o", tmp_path / "out", "-j", 5, "--scheduler",
                 "tcp://127.0.0.1:1")
    assert res.exit_code == 2 and seen.get("scheduler") == "tcp://127.0.0.1:1"
    assert "-j 5 has no effect with --scheduler" in res.stderr


def test_batch_exit_2_nothing_run(runner, monkeypatch, four_pairs, tmp_path):
    def must_not_run(*a, **k):  # pragma: no cover
        raise AssertionError("run_batch called")

    monkeypatch.setattr(batch, "run_batch", must_not_run)
    out = tmp_path / "out"
    rows = four_pairs.rows
    cases = {
        "dup.csv": (rows[:2] + [dict(rows[0], source=rows[2]["source"])], "duplicate pair_id 'ply_ply'"),
        "nogt.csv": ([dict(r, gt="") for r in rows], "--min-success needs pairs with ground truth"),
    }
    for name, (mrows, msg) in cases.items():
        manifest = write_manifest_rows(four_pairs.root / name, mrows)
        res = invoke(runner, "batch", manifest, "-o", out, "--min-success", 0.5)
        assert res.exit_code == 2, (name, res.output)
        assert msg in res.stderr
    (four_pairs.root / "nocol.csv").write_text("pair_id,source\na,b.ply\n")
    res = invoke(runner, "batch", four_pairs.root / "nocol.csv", "-o", out)
    assert res.exit_code == 2 and "missing required column 'target'" in res.stderr
    res = invoke(runner, "batch", tmp_path / "nope.csv", "-o", out)
    assert res.exit_code == 2 and "manifest does not exist" in res.stderr
    res = invoke(runner, "batch", four_pairs.manifest(), "-o", out, "--min-success", 1.5)
    assert res.exit_code == 2 and "--min-success" in res.stderr
    # NaN passed click's range check, and then every gate (a CI template's "$THRESH" left as nan)
    for nan in ("nan", "NaN"):
        res = invoke(runner, "batch", four_pairs.manifest(), "-o", out, "--min-success", nan)
        assert res.exit_code == 2 and f"'{nan}' is not a number in the range 0.0<=x<=1.0" in res.stderr
    res = invoke(runner, "batch", four_pairs.manifest())
    assert res.exit_code == 2 and "Missing option '-o'" in res.stderr
    assert not out.exists()


def test_batch_manifest_error_via_subprocess(four_pairs, tmp_path):
    rows = four_pairs.rows
    manifest = write_manifest_rows(four_pairs.root / "dup.csv", rows + [rows[1]])
    out = gctr("batch", manifest, "-o", tmp_path / "out")
    assert out.returncode == 2
    assert "duplicate pair_id 'pcd_xyz'" in out.stderr
    assert not (tmp_path / "out").exists()


def test_batch_lock_refusal_via_cli(runner, fake_batch, four_pairs, tmp_path):
    import subprocess as sp

    out = tmp_path / "out"
    out.mkdir()
    sleeper = sp.Popen([PYTHON, "-c", "import time; time.sleep(60)"])
    try:
        (out / batch.LOCK_NAME).write_text(f"{sleeper.pid}\n")
        res = invoke(runner, "batch", four_pairs.manifest(), "-o", out)
        assert res.exit_code == 2
        assert f"another gctr batch (pid {sleeper.pid}) is writing to {out}" in res.stderr
        assert not (out / "transforms.csv").exists()
    finally:
        sleeper.kill()
        sleeper.wait()


CLI_DRIVER = textwrap.dedent(
    """
    import functools, sys
    from data_scripts import fake_engine
    from gctr_cli import batch, cli

    if __name__ == "__main__":
        batch.run_batch = functools.partial(batch.run_batch, register_fn=fake_engine.slow_register)
        cli.main(sys.argv[1:], prog_name="gctr")
    """
)


@pytest.mark.parametrize("stdout", ["closed", "full"])
def test_batch_whose_stdout_is_closed_or_full_registers_every_pair(four_pairs, tmp_path, subprocess_env, stdout):
    """Cron runs commands with stdout closed (>&-) or redirected anywhere: the workers must not die on
    it (they did: every pair 'worker died'), and a summary that cannot be printed is a warning, not a
    traceback and exit 1."""
    driver = tmp_path / "gctr_driver.py"
    driver.write_text(CLI_DRIVER.replace("fake_engine.slow_register", "fake_engine.register"))
    out = tmp_path / "out"
    cmd = [PYTHON, str(driver), "batch", str(four_pairs.manifest()), "-o", str(out), "-j", "2", "-q"]
    if stdout == "closed":
        done = subprocess.run(cmd, env=subprocess_env, stderr=subprocess.PIPE, text=True, timeout=300,
                              preexec_fn=lambda: os.close(1))
    else:
        with open("/dev/full", "w") as full:
            done = subprocess.run(cmd, env=subprocess_env, stdout=full, stderr=subprocess.PIPE, text=True,
                                  timeout=300)
    assert done.returncode == 0 and "Traceback" not in done.stderr, done.stderr
    rows = read_csv(out / "transforms.csv")[1]
    assert len(rows) == len(four_pairs.rows) and {r["status"] for r in rows} == {"ok"}
    if stdout == "full":
        assert f"cannot print the summary (No space left on device); the results are in {out}" in done.stderr


def _signal_when(proc: subprocess.Popen, ready, sig: int, timeout: float = 60) -> str:
    """Send ``sig`` to ``proc`` once ``ready()`` holds (the process must still run until then) and
    return its stderr; the process is killed if anything goes wrong."""
    import time

    try:
        deadline = time.monotonic() + timeout
        while not ready() and time.monotonic() < deadline:
            assert proc.poll() is None, proc.communicate()
            time.sleep(0.02)
        proc.send_signal(sig)
        return proc.communicate(timeout=30)[1]
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()


def _default_sighup() -> None:
    import signal

    signal.signal(signal.SIGHUP, signal.SIG_DFL)  # a test run under nohup would hand its child an ignored one


@pytest.mark.slow
@pytest.mark.parametrize("signame", ["SIGTERM", "SIGHUP"])
def test_sigterm_stops_the_batch_cleanly_and_resume_finishes(dataset, tmp_path, subprocess_env, signame):
    """SIGHUP (a closed ssh session) killed the batch as SIGKILL would: no message, no report, a stale lock."""
    import signal

    sig = getattr(signal, signame)
    for i in range(6):
        dataset.add_pair(f"p{i}", exts=((".ply", ".pcd"), (".xyz", ".ply"))[i % 2])
    manifest = dataset.manifest()
    driver = tmp_path / "gctr_driver.py"
    driver.write_text(CLI_DRIVER)
    out = tmp_path / "out"
    cmd = [PYTHON, str(driver), "batch", str(manifest), "-o", str(out), "-j", "2"]
    proc = subprocess.Popen(cmd, env=subprocess_env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            preexec_fn=_default_sighup)
    transforms = out / "transforms.csv"
    stderr = _signal_when(proc, lambda: transforms.exists() and transforms.read_bytes().count(b"\n") >= 2, sig)
    assert proc.returncode == 128 + sig, stderr
    assert "interrupted" in stderr and "--resume" in stderr
    assert not (out / batch.LOCK_NAME).exists()  # released on the way out
    assert (out / "report.html").exists()
    n_before = len(read_csv(out / "transforms.csv")[1])
    assert 1 <= n_before < 6

    done = subprocess.run(cmd + ["--resume"], env=subprocess_env, capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr
    assert f"pairs: 6 (6 ok, 0 failed) ({n_before} done by an earlier run)" in done.stdout
    ids = sorted(r["pair_id"] for r in read_csv(out / "transforms.csv")[1])
    assert ids == [f"p{i}" for i in range(6)]


# ----------------------------------------------------------------------------------------------------
# end to end with the real engine
# ----------------------------------------------------------------------------------------------------


def _real_pairs(root: Path) -> tuple[Path, dict[str, np.ndarray]]:
    """Four cross-source-like pairs in mixed formats: different samplings, noise, partial overlap.

    Built from the shipped bunny model when present, otherwise from a synthetic bumpy surface.
    """
    rng = np.random.default_rng(2024)
    bunny = REPO / "data" / "models" / "bunny.ply"
    base = load_point_cloud(bunny) if bunny.exists() else bumpy_surface(rng, 30000)
    base = base - base.mean(0)
    diag = float(np.linalg.norm(base.max(0) - base.min(0)))
    specs = [
        ("p_ply_pcd", ".ply", ".pcd", 1.0, 25.0),
        ("p_pcd_xyz", ".pcd", ".xyz", 2.5, 60.0),
        ("p_xyz_ply", ".xyz", ".ply", 0.4, 100.0),
        ("p_ply_ply_utm", ".ply", ".ply", 1.7, 45.0),
    ]
    rows, gts = [], {}
    for pid, se, te, scale, angle in specs:
        idx_s = rng.choice(len(base), size=min(6000, len(base)), replace=False)
        idx_t = rng.choice(len(base), size=min(9000, len(base)), replace=False)
        src = base[idx_s] + rng.normal(scale=0.002 * diag, size=(len(idx_s), 3))
        tgt_model = base[idx_t]
        # partial overlap: the target misses a slab of the model
        axis = rng.normal(size=3)
        axis /= np.linalg.norm(axis)
        proj = tgt_model @ axis
        tgt_model = tgt_model[proj < np.quantile(proj, 0.85)]
        t = rng.uniform(-1, 1, 3) * diag
        if pid.endswith("utm"):
            t = t + np.array([4.6e5, 5.2e6, 300.0])
        T = to_matrix(scale, rotation(rng.normal(size=3), angle), t)
        tgt = apply(T, tgt_model) + rng.normal(scale=0.003 * diag * scale, size=(len(tgt_model), 3))
        s_path = write_cloud(root / "src" / f"{pid}{se}", src)
        t_path = write_cloud(root / "tgt" / f"{pid}{te}", tgt)
        write_matrix(root / "gt" / f"{pid}.txt", T)
        gts[pid] = T
        rows.append({"pair_id": pid, "source": s_path.relative_to(root).as_posix(),
                     "target": t_path.relative_to(root).as_posix(), "gt": f"gt/{pid}.txt"})
    return write_manifest_rows(root / "pairs.csv", rows), gts


@pytest.mark.engine
def test_real_engine_batch_end_to_end(tmp_path, subprocess_env):
    manifest, _gts = _real_pairs(tmp_path / "data")
    out2 = gctr("batch", manifest, "-o", tmp_path / "j2", "-j", 2, "--min-success", 0.75, env=subprocess_env)
    assert out2.returncode == 0, out2.stdout + out2.stderr
    assert "pairs: 4 (4 ok, 0 failed)" in out2.stdout
    header, rows = read_csv(tmp_path / "j2" / "transforms.csv")
    assert header == list(TRANSFORMS_COLUMNS)
    eheader, erows = read_csv(tmp_path / "j2" / "tm_errors.csv")
    assert eheader == list(ERRORS_COLUMNS) and len(erows) == 4
    cfg = Config().success
    for r in rows:
        T = read_matrix(tmp_path / "j2" / "matrices" / f"{r['pair_id']}.txt")
        assert np.array_equal(row_matrix(r), T)
        assert 0 < float(r["fitness"]) <= 1
    n_success = 0
    for e in erows:
        n_success += e["success"] == "true"
        if e["success"] == "true":
            assert float(e["rot_err_deg"]) < cfg.rotation_deg
            assert float(e["trans_err_rel"]) < cfg.translation_rel
            assert float(e["scale_err"]) < cfg.scale
    assert n_success >= 3

    out1 = gctr("batch", manifest, "-o", tmp_path / "j1", "-j", 1, "-q", env=subprocess_env)
    assert out1.returncode == 0, out1.stderr
    r1 = {r["pair_id"]: r for r in read_csv(tmp_path / "j1" / "transforms.csv")[1]}
    for r in rows:
        assert [r[c] for c in batch.MATRIX_COLUMNS + ("scale", "seed")] == [
            r1[r["pair_id"]][c] for c in batch.MATRIX_COLUMNS + ("scale", "seed")
        ], r["pair_id"]

    # `gctr register --seed <seed column>` reproduces a batch row exactly
    root = tmp_path / "data"
    row = next(r for r in rows if r["pair_id"] == "p_pcd_xyz")
    reg = gctr("register", root / "src" / "p_pcd_xyz.pcd", root / "tgt" / "p_pcd_xyz.xyz", "--gt",
               root / "gt" / "p_pcd_xyz.txt", "--seed", row["seed"], "-o", tmp_path / "m.txt", env=subprocess_env)
    assert reg.returncode == 0, reg.stderr
    assert "status: ok" in reg.stdout and f"seed: {row['seed']}" in reg.stdout
    e = {r["pair_id"]: r for r in erows}["p_pcd_xyz"]
    assert f"success: {e['success']}" in reg.stdout
    assert (tmp_path / "m.txt").read_bytes() == (tmp_path / "j2" / "matrices" / "p_pcd_xyz.txt").read_bytes()


def test_register_and_apply_as_processes_write_everything_before_the_fast_exit(tmp_path, subprocess_env):
    """``gctr register``/``apply`` end with ``os._exit`` (no interpreter teardown): outputs, stdout and
    exit codes must be complete anyway."""
    manifest, gts = _real_pairs(tmp_path / "data")
    _, rows = read_csv(manifest)
    row = rows[0]
    src, tgt = tmp_path / "data" / row["source"], tmp_path / "data" / row["target"]
    out = gctr("register", src, tgt, "-o", tmp_path / "m.txt", "--gt", tmp_path / "data" / row["gt"],
               env=subprocess_env)
    assert out.returncode == 0, out.stdout + out.stderr
    assert "status: ok" in out.stdout
    assert out.stdout.rstrip().endswith(f"success: true\nmatrix_file: {tmp_path / 'm.txt'}")
    T = read_matrix(tmp_path / "m.txt")
    e = transform_errors(T, gts[row["pair_id"]], 1.0, load_point_cloud(src).mean(axis=0))
    assert e.rot_err_deg < 2.0 and e.scale_err < 0.02
    moved = gctr("apply", tmp_path / "m.txt", src, "-o", tmp_path / "moved.ply", env=subprocess_env)
    assert moved.returncode == 0, moved.stderr
    np.testing.assert_allclose(load_point_cloud(tmp_path / "moved.ply"), apply(T, load_point_cloud(src)),
                               rtol=0, atol=1e-9 * float(np.abs(load_point_cloud(tgt)).max()))
    missing = gctr("register", tmp_path / "nope.ply", tgt, env=subprocess_env)
    assert missing.returncode == 2 and "nope.ply" in missing.stderr


REGISTER_DRIVER = textwrap.dedent(
    """
    import sys, time
    from pathlib import Path
    import gctr_cli.engine
    from gctr_cli import cli

    started = Path(sys.argv.pop())

    def stuck(*args, **kwargs):
        started.touch()  # running: the signal handlers are in place
        time.sleep(60)

    gctr_cli.engine.register = stuck
    cli.run()
    """
)


def test_register_stopped_by_sigterm_says_so_and_exits_143(tmp_path, subprocess_env):
    import signal

    manifest, _ = _real_pairs(tmp_path / "data")
    row = read_csv(manifest)[1][0]
    driver, started = tmp_path / "driver.py", tmp_path / "started"
    driver.write_text(REGISTER_DRIVER)
    proc = subprocess.Popen([PYTHON, str(driver), "register", str(tmp_path / "data" / row["source"]),
                             str(tmp_path / "data" / row["target"]), str(started)],
                            env=subprocess_env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    stderr = _signal_when(proc, started.exists, signal.SIGTERM)
    assert proc.returncode == 128 + signal.SIGTERM and stderr.strip().endswith("gctr: terminated"), stderr


def test_register_whose_reader_stops_early_keeps_its_exit_code(tmp_path, subprocess_env):
    """``gctr register … | head -1``: the closed pipe drops the rest of the report, silently; the exit
    code stays the registration's (0), the matrix file is written."""
    manifest, _ = _real_pairs(tmp_path / "data")
    row = read_csv(manifest)[1][0]
    proc = subprocess.Popen([PYTHON, "-m", "gctr_cli", "register", str(tmp_path / "data" / row["source"]),
                             str(tmp_path / "data" / row["target"]), "-o", str(tmp_path / "m.txt")],
                            env=subprocess_env, stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    assert proc.stdout is not None and proc.stderr is not None
    proc.stdout.close()  # the reader is gone before the report is printed
    stderr = proc.stderr.read().decode()
    assert proc.wait(timeout=300) == 0, stderr
    assert stderr == "" and read_matrix(tmp_path / "m.txt").shape == (4, 4)


@pytest.mark.parametrize("stdout", ["closed", "full"])
def test_register_and_apply_with_stdout_closed_or_full_write_their_files(tmp_path, subprocess_env, stdout):
    """Cron may close stdout or point it at a full disk: the files are written, the exit code is the
    command's, and a summary that cannot be printed is one warning (no traceback)."""
    manifest, _ = _real_pairs(tmp_path / "data")
    row = read_csv(manifest)[1][0]
    src, tgt = tmp_path / "data" / row["source"], tmp_path / "data" / row["target"]

    def run(*args):
        cmd = [PYTHON, "-m", "gctr_cli", *map(str, args)]
        if stdout == "closed":
            return subprocess.run(cmd, env=subprocess_env, stderr=subprocess.PIPE, text=True, timeout=300,
                                  preexec_fn=lambda: os.close(1))
        with open("/dev/full", "w") as full:
            return subprocess.run(cmd, env=subprocess_env, stdout=full, stderr=subprocess.PIPE, text=True,
                                  timeout=300)

    for args, out in ((("register", src, tgt, "-o", tmp_path / "m.txt"), tmp_path / "m.txt"),
                      (("apply", tmp_path / "m.txt", src, "-o", tmp_path / "moved.ply"), tmp_path / "moved.ply")):
        done = run(*args)
        assert done.returncode == 0 and "Traceback" not in done.stderr, done.stderr
        assert out.is_file()
        warned = "cannot print the result (No space left on device)" in done.stderr
        assert warned == (stdout == "full"), done.stderr
    # without -o the printed matrix is the only result: losing it is an error, not a success
    done = run("register", src, tgt)
    problem = "stdout is closed" if stdout == "closed" else "No space left on device"
    assert done.returncode == 2 and "Traceback" not in done.stderr, done.stderr
    assert done.stderr.strip().endswith(
        f"gctr: error: cannot print the result ({problem}), and without -o FILE the printed matrix is its only "
        "copy: pass -o FILE to write it to a file"), done.stderr


def test_register_sets_up_the_allocator(runner, fake_register, four_pairs, monkeypatch):
    import gctr_cli.allocator

    calls = []
    monkeypatch.setattr(gctr_cli.allocator, "keep_freed_memory", lambda: calls.append(1) or True)
    row = four_pairs.rows[0]
    res = invoke(runner, "register", four_pairs.root / row["source"], four_pairs.root / row["target"])
    assert res.exit_code == 0, res.output
    assert calls == [1]


def test_register_writes_its_files_even_when_the_reader_of_its_output_stops_early(tmp_path, subprocess_env):
    """`gctr register … -o M --aligned A | head -1`: the pipe closes before the summary is printed, and
    the matrix and the aligned cloud must still be written (they are written before anything is printed)."""
    rng = np.random.default_rng(3)
    base = load_point_cloud(REPO / "data" / "models" / "bunny.ply")
    src = base[rng.choice(len(base), 3000, replace=False)]
    T = to_matrix(1.3, rotation([1.0, 2.0, 0.5], 35.0), np.array([0.1, -0.2, 0.05]))
    write_cloud(tmp_path / "src.ply", src)
    write_cloud(tmp_path / "tgt.ply", apply(T, base[rng.choice(len(base), 4000, replace=False)]))
    cmd = [PYTHON, "-m", "gctr_cli", "register", str(tmp_path / "src.ply"), str(tmp_path / "tgt.ply"),
           "-o", str(tmp_path / "m.txt"), "--aligned", str(tmp_path / "al.ply")]
    proc = subprocess.Popen(cmd, env=subprocess_env, stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    assert proc.stdout is not None
    proc.stdout.close()  # the reader is gone before the first line
    _, err = proc.communicate(timeout=120)
    assert proc.returncode in (0, 1), err  # 1: click's exit code for a closed stdout
    M = read_matrix(tmp_path / "m.txt")
    assert transform_errors(M, T, 1.0).rot_err_deg < 1.0
    np.testing.assert_allclose(load_point_cloud(tmp_path / "al.ply"), apply(M, src), atol=1e-9)


def test_batch_lost_scheduler_says_whether_anything_was_saved(runner, monkeypatch, four_pairs, tmp_path):
    """The dask executor cannot know what the batch recorded; the message said "the finished pairs
    are saved" even when none had finished and the run had removed its output folder."""
    out = tmp_path / "out"

    def lost(pairs, config, outdir, **kwargs):
        if kwargs.get("resume"):  # a run that had recorded one pair before the scheduler went away
            (Path(outdir) / batch.TRANSFORMS_FILE).write_text("pair_id\nply_ply\n")
        raise batch.ExecutorLost("lost the connection to the dask scheduler at tcp://h:8786 (2 pairs sent to it "
                                 "unfinished)")

    monkeypatch.setattr(batch, "run_batch", lost)
    res = invoke(runner, "batch", four_pairs.manifest(), "-o", out, "--executor", "dask", "-q")
    assert res.exit_code == 2
    assert res.stderr == ("gctr: error: lost the connection to the dask scheduler at tcp://h:8786 (2 pairs sent to "
                          "it unfinished); no pair had finished, nothing was written\n")
    out.mkdir()
    res = invoke(runner, "batch", four_pairs.manifest(), "-o", out, "--executor", "dask", "-q", "--resume")
    assert res.exit_code == 2
    assert res.stderr.endswith(f"(2 pairs sent to it unfinished); the finished pairs are saved in {out}: rerun "
                               "with --resume against a running scheduler to finish\n")


@pytest.mark.engine
def test_a_mirrored_real_scan_is_refused_and_registers_once_flipped_back(runner, tmp_path):
    """A real range scan of the bunny (data/scans/bun045.ply) with one axis flipped, as a left-handed export
    gives it, against the bunny model: the best rotation fits it at confidence 1 (score 0.37), too well for
    the full mirror check at its default (``verdict.mirror_below`` 0.3). The reflection check finds the
    mirror image (the answer reflected through the model's plane of near-symmetry and refined) fitting far
    better, so ``gctr register`` refuses it (exit 1) and says to flip it; with the full check for clouds
    of unknown axis conventions (``mirror_below: 0.5``) and without the reflection check it is refused too;
    flipped back with ``gctr apply`` it registers, right against the shipped pose."""
    config = tmp_path / "mixed.yaml"
    config.write_text("engine:\n  verdict:\n    mirror_below: 0.5\n    reflection_check: false\n")
    flip = tmp_path / "flip.txt"
    write_matrix(flip, np.diag([-1.0, 1.0, 1.0, 1.0]))
    scan, model = REPO / "data" / "scans" / "bun045.ply", REPO / "data" / "models" / "bunny.ply"
    flipped, back = tmp_path / "flipped.ply", tmp_path / "back.ply"
    assert invoke(runner, "apply", flip, scan, "-o", flipped).exit_code == 0
    res = invoke(runner, "register", flipped, model)
    assert res.exit_code == 1
    assert ("message: mirrored: the source reflected fits the target better than any rotation of it (score 0.59 "
            "against 0.37, the answer reflected through a principal plane of a cloud and refined); either one of "
            "the clouds has a flipped axis") in res.output
    res = invoke(runner, "register", flipped, model, "-c", config)
    assert res.exit_code == 1
    assert ("message: mirrored: the source reflected (x -> -x) fits the target better than any rotation of it "
            "(score 0.59 against 0.37); either one of the clouds has a flipped axis") in res.output
    assert invoke(runner, "apply", flip, flipped, "-o", back).exit_code == 0
    lines = (REPO / "data" / "scans" / "poses.txt").read_text().splitlines()
    i = lines.index("bun045.ply")
    gt = tmp_path / "gt.txt"
    write_matrix(gt, np.array([[float(v) for v in line.split()] for line in lines[i + 1:i + 5]]))
    res = invoke(runner, "register", back, model, "--gt", gt)
    assert res.exit_code == 0 and "status: ok" in res.output and "success: true" in res.output.lower()


@pytest.mark.parametrize("command", ["batch", "register", "apply", "manifest", "show"])
def test_an_empty_path_is_a_usage_error_not_the_current_folder(runner, four_pairs, tmp_path, monkeypatch, command):
    """``-o "$out"`` with ``out`` unset: an empty path meant the current folder, so a batch wrote its files
    wherever the cron job happened to run. Every path option and argument now refuses it (exit 2)."""
    monkeypatch.chdir(tmp_path)
    src, tgt = (four_pairs.root / four_pairs.rows[0][k] for k in ("source", "target"))
    args = {"batch": ["batch", four_pairs.manifest(), "-o", ""],
            "register": ["register", src, tgt, "-o", ""],
            "apply": ["apply", "", src, "-o", tmp_path / "moved.ply"],
            "manifest": ["manifest", four_pairs.root, "", "-o", tmp_path / "pairs.csv"],
            "show": ["show", src, tgt, "-o", ""]}[command]
    before = set(os.listdir(tmp_path))
    result = invoke(runner, *args)
    assert result.exit_code == 2, result.output
    assert "is empty (an unset shell variable?)" in result.output
    assert set(os.listdir(tmp_path)) == before


@pytest.mark.parametrize("case", ["apply onto its input", "apply through a link", "register -o onto the source",
                                  "register --aligned onto the target", "register -o and --aligned the same"])
def test_an_output_that_is_an_input_is_refused_before_anything_runs(runner, four_pairs, tmp_path, case):
    """``gctr apply m.txt scan.pcd -o scan.pcd`` replaced the scan with the moved cloud (a read-only file in
    a shared data folder, as root): an output that is one of the command's inputs is an error (exit 2)."""
    src, tgt = (four_pairs.root / four_pairs.rows[0][k] for k in ("source", "target"))
    matrix = tmp_path / "m.txt"
    matrix.write_text("1 0 0 0\n0 1 0 0\n0 0 1 0\n0 0 0 1\n")
    link = tmp_path / f"link{src.suffix}"
    link.symlink_to(src)
    args, role = {
        "apply onto its input": (["apply", matrix, src, "-o", src], "the INPUT cloud"),
        "apply through a link": (["apply", matrix, src, "-o", link], "the INPUT cloud"),
        "register -o onto the source": (["register", src, tgt, "-o", src], "the SOURCE cloud"),
        "register --aligned onto the target": (["register", src, tgt, "--aligned", tgt], "the TARGET cloud"),
        "register -o and --aligned the same": (["register", src, tgt, "-o", tmp_path / "x.ply", "--aligned",
                                                tmp_path / "x.ply"], None),
    }[case]
    before = src.read_bytes(), tgt.read_bytes()
    result = invoke(runner, *args)
    assert result.exit_code == 2, result.output
    if role is None:
        assert "given as both -o and --aligned: choose two files" in result.output
    else:
        assert f"is also {role}; writing there would replace it: choose another output file" in result.output
    assert (src.read_bytes(), tgt.read_bytes()) == before
