"""The shipped configs: valid, and configs/default.yaml is exactly the built-in defaults."""

from pathlib import Path

import pytest

from gctr_cli.config import Config, ConfigError, config_from_dict, load_config

CONFIGS = Path(__file__).resolve().parents[1] / "configs"


def test_default_yaml_matches_the_built_in_defaults():
    assert load_config(CONFIGS / "default.yaml") == Config()


@pytest.mark.parametrize("name", ["default.yaml", "fast.yaml", "accurate.yaml", "scene.yaml", "rigid.yaml"])
def test_shipped_config_is_valid(name):
    cfg = load_config(CONFIGS / name)
    assert cfg.method == "gctr"


def test_fast_is_lighter_and_accurate_heavier_than_default():
    d, f, a = (load_config(CONFIGS / n).engine for n in ("default.yaml", "fast.yaml", "accurate.yaml"))
    assert f.triplets.n_target < d.triplets.n_target < a.triplets.n_target
    assert f.ransac.iterations < d.ransac.iterations < a.ransac.iterations


def test_scene_config_only_raises_the_threshold_and_polishes():
    """configs/scene.yaml is the defaults with the threshold measured for sensor-like scene noise and the
    answer's polish (stage 5b) on."""
    scene = load_config(CONFIGS / "scene.yaml")
    assert scene.engine.min_confidence == 0.45 > Config().engine.min_confidence
    default = Config()
    assert scene.engine.polish.enabled and not default.engine.polish.enabled
    same = scene.engine.model_copy(update={"min_confidence": default.engine.min_confidence,
                                           "polish": default.engine.polish})
    assert scene.model_copy(update={"engine": same}) == default


def test_rigid_config_only_holds_the_scale_near_one():
    """configs/rigid.yaml is the defaults with scale_bounds [0.99, 1.01] (docs/config.md's advice for a
    pair known to be rigid) and the answer's polish."""
    rigid = load_config(CONFIGS / "rigid.yaml")
    assert rigid.engine.scale_bounds == (0.99, 1.01)
    default = Config()
    assert rigid.engine.polish.enabled  # and the answer's polish (stage 5b), for scans with little noise
    wide = rigid.engine.model_copy(update={"scale_bounds": default.engine.scale_bounds,
                                           "polish": default.engine.polish})
    assert rigid.model_copy(update={"engine": wide}) == default


def test_slide_steps_must_be_shares_of_the_smaller_cloud():
    assert config_from_dict({"engine": {"verdict": {"slide_steps": []}}}).engine.verdict.slide_steps == ()
    entry = r"engine\.verdict\.slide_steps\.\d: Input should be (greater than 0|less than 1)"
    for bad in ([0.0], [-0.1], [0.1, 1.5]):
        with pytest.raises(ConfigError, match=entry):
            config_from_dict({"engine": {"verdict": {"slide_steps": bad}}})


@pytest.mark.parametrize("section, key", [("tensor", "knn_eps"), ("tensor", "normal_weight"),
                                          ("supervoxel", "spatial_weight"), ("refine", "start_ratio")])
@pytest.mark.parametrize("value", [float("inf"), float("-inf"), float("nan")])
def test_numbers_must_be_finite(section, key, value):
    """YAML's .inf / .nan are refused for every number, with the key named: before, an infinite
    knn_eps passed `gctr config check` and then failed each pair with an IndexError."""
    with pytest.raises(ConfigError, match=rf"engine\.{section}\.{key}: Input should be a finite number"):
        config_from_dict({"engine": {section: {key: value}}})


def test_a_config_path_is_named_the_same_way_in_every_message(tmp_path, monkeypatch):
    """A read error and a validation error of one file name it alike (`./x.yaml` is `x.yaml` in both), and a
    folder is not a file that "does not exist" (found by a review)."""
    monkeypatch.chdir(tmp_path)
    Path("unknown.yaml").write_text("engine:\n  no_such_key: 1\n")
    Path("broken.yaml").write_text("engine: [1\n")
    Path("folder.yaml").mkdir()
    with pytest.raises(ConfigError, match=r"^invalid config unknown\.yaml:"):
        load_config("./unknown.yaml")
    with pytest.raises(ConfigError, match=r"^config file broken\.yaml is not valid YAML"):
        load_config("./broken.yaml")
    with pytest.raises(ConfigError, match=r"^config file folder\.yaml is not a regular file"):
        load_config("folder.yaml")
    with pytest.raises(ConfigError, match=r"^config file missing\.yaml does not exist"):
        load_config("missing.yaml")
