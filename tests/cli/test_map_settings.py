"""The SIREN's settings chosen from a survey's scale (sss2bathy.cli.map_settings)."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
from hydra import compose, initialize_config_dir
from omegaconf import OmegaConf, open_dict

from sss2bathy.cli.map_settings import (
    MAX_OMEGA0,
    SURVEY_W_SHADOW,
    SurveyScale,
    apply_map_settings,
    choose_map_settings,
    scale_of_xtf_files,
    survey_scale,
)
from tests.conftest import REALDATA

ROOT = Path(__file__).resolve().parents[2]
CONF = ROOT / "conf"
REAL_LINE = REALDATA / "scotsman-iver2.xtf"


def scale(range_m=30.0, half=(75.0, 75.0), pings=720) -> SurveyScale:
    return SurveyScale(range_m, range_m / 256, 270.0, half, pings)


def test_survey_scale_measures_range_bins_track_and_the_sirens_box():
    rng = np.random.default_rng(0)
    x = np.linspace(0.0, 90.0, 241)
    lines = [np.stack([x, np.full_like(x, 38.0), rng.normal(-17, 0.1, x.size)], 1),
             np.stack([np.full_like(x, 50.0), x, rng.normal(-17, 0.1, x.size)], 1)]  # fmt: skip
    ranges = [np.linspace(0.1, 30.0, 256)] * 2
    s = survey_scale(lines, ranges)
    assert s.range_m == pytest.approx(30.0) and s.bin_m == pytest.approx(29.9 / 255)
    assert s.track_m == pytest.approx(180.0) and s.n_pings == 482
    # the box of data.pings: the tracks' box grown by the range
    assert s.half_extent_m == pytest.approx((45.0 + 30.0, 45.0 + 30.0))


def test_omega0_puts_the_first_layers_finest_wavelength_at_half_the_range():
    s = choose_map_settings(scale(), base_omega0=10.0, base_steps_per_epoch=None,
                            fast_steps_per_epoch=80, batch_pings=16)  # fmt: skip
    assert s.omega0 == pytest.approx(4 * math.pi * 75.0 / 15.0)
    assert s.wavelength_m == pytest.approx(15.0)
    # a finer SIREN gets the fast schedule's steps: 720 pings / 16 = 45 < 80
    assert s.steps_per_epoch == 80
    assert s.overrides() == {
        "model.siren.omega0": round(s.omega0, 3),
        "data.steps_per_epoch": 80,
        "model.w_shadow": SURVEY_W_SHADOW,  # a SIREN fine enough for objects: their shadows
    }
    # the extent enters through its larger half-width; a longer range means coarser detail
    wide = choose_map_settings(scale(half=(75.0, 150.0)), 10.0, None, 80, 16)
    assert wide.omega0 == pytest.approx(2 * s.omega0)
    far = choose_map_settings(scale(range_m=60.0), 10.0, None, 80, 16)
    assert far.omega0 == pytest.approx(s.omega0 / 2)


def test_never_coarser_than_the_scale_and_capped():
    big = choose_map_settings(scale(range_m=300.0, half=(300.0, 300.0)), 30.0, None, 80, 16)
    assert big.omega0 == 30.0 and big.steps_per_epoch is None  # the scale's own: unchanged
    assert big.w_shadow == 0.0 and "model.w_shadow" not in big.overrides()
    tiny_range = choose_map_settings(scale(range_m=2.0), 10.0, None, 80, 16)
    assert tiny_range.omega0 == MAX_OMEGA0
    # steps already at least the fast count stay
    many = choose_map_settings(scale(pings=4000), 10.0, None, 80, 16)
    assert many.steps_per_epoch is None
    with pytest.raises(ValueError, match="base_omega0: expected a positive number"):
        choose_map_settings(scale(), 0.0, None, 80, 16)
    with pytest.raises(ValueError, match="range_m: expected a positive number"):
        SurveyScale(0.0, 0.1, 1.0, (1.0, 1.0), 1)


def _map_train_cfg(*overrides: str, experiment: str = "siren_lambert"):
    with initialize_config_dir(str(CONF), version_base="1.3"):
        cfg = compose("train", overrides=[f"experiment={experiment}", "scale=tiny",
                                          "data/survey=xtf", "data.survey.files=/nowhere",
                                          *overrides])  # fmt: skip
    return cfg


def test_apply_leaves_what_the_user_set():
    cfg = _map_train_cfg()
    with open_dict(cfg):
        applied = apply_map_settings(cfg, scale(pings=320), [])
    assert cfg.model.siren.omega0 == applied["model.siren.omega0"] > 5.0
    assert cfg.data.steps_per_epoch == 40  # scale=tiny's fast count (320 / 16 = 20 before)
    assert cfg.model.w_shadow == SURVEY_W_SHADOW == applied["model.w_shadow"]
    # heights only has no sidescan sensor model: no occlusion term
    cfg = _map_train_cfg(experiment="siren_heights_only")
    with open_dict(cfg):
        applied = apply_map_settings(cfg, scale(pings=320), [])
    assert "model.w_shadow" not in applied and cfg.model.w_shadow == 0.0
    user = ["model.siren.omega0=7", "+data.steps_per_epoch=12"]
    cfg = _map_train_cfg("model.siren.omega0=7", "data.steps_per_epoch=12")
    with open_dict(cfg):
        applied = apply_map_settings(cfg, scale(pings=320), user)
    assert applied == {} and cfg.model.siren.omega0 == 7 and cfg.data.steps_per_epoch == 12
    # the scale's own key stands for the model's
    cfg = _map_train_cfg("scale.siren.omega0=9")
    with open_dict(cfg):
        applied = apply_map_settings(cfg, scale(), ["scale.siren.omega0=9"])
    assert "model.siren.omega0" not in applied and OmegaConf.select(cfg, "model.siren.omega0") == 9


@pytest.mark.skipif(
    not REAL_LINE.is_file(), reason=f"{REAL_LINE} absent (set SSS2BATHY_REALDATA=FOLDER)"
)
def test_the_real_iver2_line():
    s = scale_of_xtf_files(
        {"files": str(REAL_LINE), "n_bins": 512, "tilt_deg": 20.0, "beam_width_deg": 50.0}
    )
    assert s.range_m == pytest.approx(30.0, abs=0.1) and s.bin_m == pytest.approx(
        30 / 512, rel=0.02
    )
    assert 40.0 < s.track_m < 80.0 and s.n_pings == 460
    chosen = choose_map_settings(s, 10.0, None, 80, 16)
    assert 30.0 < chosen.omega0 < 80.0 and chosen.steps_per_epoch == 80
