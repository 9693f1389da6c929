"""The tensor diagnostic (data_scripts/tensor_diagnostics.py) counts true triangle matches against ground truth."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner
from scipy.spatial.transform import Rotation

from data_scripts.tensor_diagnostics import main, pair_signal
from gctr_cli.config import config_from_dict
from gctr_cli.geometry import apply, to_matrix
from gctr_cli.io import load_point_cloud

MODELS = Path(__file__).resolve().parent.parent / "data" / "models"
CFG = config_from_dict({"engine": {"triplets": {"n_target": 8000}}}).engine  # smaller, faster tensors


def _pair() -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    rng = np.random.default_rng(11)
    bunny = np.asarray(load_point_cloud(MODELS / "bunny.ply"), dtype=float)
    source = bunny[rng.choice(len(bunny), 6000, replace=False)]
    T = to_matrix(1.6, Rotation.from_euler("xyz", [20, -35, 50], degrees=True).as_matrix(), np.array([0.3, -1, 2]))
    target = apply(T, bunny[rng.choice(len(bunny), 4000, replace=False)])
    return source, target, T


@pytest.mark.slow  # ~7 s
def test_true_matches_are_found_under_the_truth_and_not_under_a_wrong_pose():
    source, target, T = _pair()
    truth = {s.name: s for s in pair_signal(source, target, T, CFG)}
    full = truth["overlap 1.00"]
    assert full.inside > 300 and full.sampled > 50 and full.in_knn > 5 and full.true_entries > 5
    assert full.in_knn <= full.sampled <= full.inside <= full.source_triangles
    assert full.true_entries <= full.entries
    wrong = T.copy()
    wrong[:3, :3] = wrong[:3, :3] @ Rotation.from_euler("z", 90, degrees=True).as_matrix()
    off = {s.name: s for s in pair_signal(source, target, wrong, CFG)}["overlap 1.00"]
    assert off.true_entries < full.true_entries / 5 and off.in_knn < full.in_knn / 5


def test_cli_prints_a_table_per_pair_and_rejects_unknown_pairs(tmp_path):
    source, target, T = _pair()
    np.savetxt(tmp_path / "s.xyz", source)
    np.savetxt(tmp_path / "t.xyz", target)
    np.savetxt(tmp_path / "gt.txt", T)
    (tmp_path / "pairs.csv").write_text("pair_id,source,target,gt\np0,s.xyz,t.xyz,gt.txt\n")
    args = ["--data", str(tmp_path), "--set", '{"triplets": {"n_target": 8000}, "part_regions": [0.5]}']
    out = CliRunner().invoke(main, [*args, "--pair", "p0"])
    assert out.exit_code == 0, out.output
    assert "### p0" in out.output and "target inside source (0.50)" in out.output
    assert "total over 1 pairs" in out.output
    bad = CliRunner().invoke(main, [*args, "--pair", "nope"])
    assert bad.exit_code != 0 and "'nope' is not in" in bad.output


def test_a_bad_config_or_override_is_one_line_not_a_traceback(tmp_path):
    """A config file that is not YAML, or an override naming no key, ended in a traceback (found by a review)."""
    (tmp_path / "pairs.csv").write_text("pair_id,source,target,gt\n")
    (tmp_path / "bad.yaml").write_text("engine:\n  tensor: [1, 2\n")
    bad_file = CliRunner().invoke(main, ["--data", str(tmp_path), "--pair", "p0", "--config",
                                         str(tmp_path / "bad.yaml")])
    assert bad_file.exit_code == 2 and isinstance(bad_file.exception, SystemExit), bad_file.output
    assert f"config file {tmp_path / 'bad.yaml'} is not valid YAML (line 2, column 11)" in bad_file.output
    bad_key = CliRunner().invoke(main, ["--data", str(tmp_path), "--pair", "p0", "--set", '{"no_such_key": 1}'])
    assert bad_key.exit_code == 2 and isinstance(bad_key.exception, SystemExit), bad_key.output
    assert "Invalid value for --set" in bad_key.output
    assert "engine.no_such_key: unknown key" in bad_key.output
