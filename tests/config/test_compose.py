"""Every config composes, every experiment resolves, and validation names the bad key."""

from pathlib import Path

import pytest
from hydra import compose, initialize_config_dir
from omegaconf import OmegaConf

from sss2bathy.config_validation import ConfigError, validate_config

CONF = Path(__file__).resolve().parents[2] / "conf"
EXPERIMENTS = sorted(p.stem for p in (CONF / "experiment").glob("*.yaml"))
SCALES = ("tiny", "demo", "paper")


def _compose(config_name="train", overrides=()):
    with initialize_config_dir(str(CONF), version_base="1.3"):
        return compose(config_name, overrides=list(overrides), return_hydra_config=False)


def _resolve(cfg):
    # hydra:runtime.* interpolations only exist inside a Hydra run
    c = OmegaConf.to_container(cfg, resolve=False)
    for group in ("logger", "callbacks"):
        c.pop(group, None)
    return OmegaConf.to_container(OmegaConf.create(c), resolve=True)


def test_paper_experiments_exist():
    expected = {
        "cnn",
        "siren_direct_fit",
        "siren_gt_n2d",
        "siren_cnn_n2d",
        "siren_lambert",
        "siren_lambert_all",
        "d2_siren_cnn_n2d",
        "d2_siren_lambert",
    }
    assert expected <= set(EXPERIMENTS)


@pytest.mark.parametrize("scale", SCALES)
@pytest.mark.parametrize("experiment", EXPERIMENTS)
def test_experiment_composes_and_validates(experiment, scale):
    cfg = _compose(overrides=[f"experiment={experiment}", f"scale={scale}"])
    resolved = _resolve(cfg)
    assert resolved["task_name"] == experiment
    assert "_target_" in resolved["data"] and "_target_" in resolved["model"]
    assert resolved["trainer"]["max_epochs"] >= 1
    validate_config(cfg)


@pytest.mark.parametrize("config_name", ["prepare", "eval", "predict"])
def test_other_entry_configs_compose(config_name):
    cfg = _compose(config_name, ["scale=tiny"])
    assert _resolve(cfg)["data"]["survey"]["kind"] == "synthetic"


@pytest.mark.parametrize(
    "override, key",
    [
        ("model.w_height=-1", "model.w_height"),
        ("data.survey.sonar.beam_width_deg=0", "data.survey.sonar.beam_width_deg"),
        ("data.survey.sonar.beam_width_deg=180", "data.survey.sonar.beam_width_deg"),
        ("data.survey.terrain.cell_m=0", "data.survey.terrain.cell_m"),
        ("data.batch_pings=0", "data.batch_pings"),
        ("trainer.max_epochs=0", "trainer.max_epochs"),
        ("seed=-3", "seed"),
    ],
)
def test_validation_names_key_and_value(override, key):
    cfg = _compose(overrides=["experiment=siren_gt_n2d", "scale=tiny", override])
    with pytest.raises(ConfigError) as err:
        validate_config(cfg)
    assert f"'{key}'" in str(err.value)
    assert override.split("=")[1] in str(err.value)


def test_window_larger_than_waterfall_rejected():
    cfg = _compose(overrides=["experiment=cnn", "scale=tiny", "data.window_bins=4096"])
    with pytest.raises(ConfigError, match="data.window_bins"):
        validate_config(cfg)
