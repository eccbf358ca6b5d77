"""The SIREN's settings chosen from a survey's scale (sss2bathy.cli.map_settings)."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
from hydra import compose, initialize_config_dir
from omegaconf import OmegaConf, open_dict

from sss2bathy.cli.map_settings import (
    DETAIL_W,
    MAX_OMEGA0,
    SURVEY_W_SHADOW,
    SurveyScale,
    apply_map_settings,
    choose_map_settings,
    scale_of_survey,
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


def test_detail_puts_the_finer_omega0_in_a_detail_network_beside_the_scales():
    s = choose_map_settings(scale(), 10.0, None, 80, 16, detail=True)
    one = choose_map_settings(scale(), 10.0, None, 80, 16)
    # the scale's steps (more cost the base its held-out altimeter error)
    assert s.detail and s.omega0 == one.omega0 and s.steps_per_epoch is None
    assert s.overrides() == {
        "model.siren._target_": "sss2bathy.models.siren.TwoScaleSiren",
        "model.siren.detail_omega0": round(one.omega0, 3),  # the base keeps the scale's
        "model.w_shadow": SURVEY_W_SHADOW,
        "model.w_detail": DETAIL_W,
        "model.detail_nadir": True,
        "model.heights_on_base": True,
        "model.shadow_on_detail": True,
    }
    # no finer than the scale's: no detail network, the scale's own settings
    coarse = choose_map_settings(scale(range_m=300.0, half=(300.0, 300.0)), 30.0, None, 80, 16,
                                 detail=True)  # fmt: skip
    assert not coarse.detail and coarse.overrides() == {"model.siren.omega0": 30.0}


def test_apply_detail_builds_a_two_scale_siren_for_sidescan_fits_only():
    import hydra

    from sss2bathy.models.siren import TwoScaleSiren

    cfg = _map_train_cfg()
    with open_dict(cfg):
        applied = apply_map_settings(cfg, scale(pings=320), [], mode="detail")
    assert cfg.model.siren.omega0 == cfg.scale.siren.omega0  # the base: the scale's
    assert applied["model.siren.detail_omega0"] > cfg.model.siren.omega0
    assert cfg.model.w_detail == DETAIL_W and cfg.model.detail_nadir and cfg.model.heights_on_base
    model = hydra.utils.instantiate(cfg.model)
    assert isinstance(model.siren, TwoScaleSiren)
    assert model.siren.detail.omega0 == pytest.approx(applied["model.siren.detail_omega0"])
    # heights only: a detail network would see no data; the verdict's baseline stays the scale's
    cfg = _map_train_cfg(experiment="siren_heights_only")
    with open_dict(cfg):
        assert apply_map_settings(cfg, scale(pings=320), [], mode="detail") == {}
    assert "Siren" in cfg.model.siren._target_ and "detail_omega0" not in cfg.model.siren
    # the user's own SIREN class wins; the user's omega0 is the base's, the detail still comes
    cfg = _map_train_cfg("model.siren._target_=sss2bathy.models.siren.Siren")
    with open_dict(cfg):
        user = ["model.siren._target_=sss2bathy.models.siren.Siren"]
        assert apply_map_settings(cfg, scale(pings=320), user, mode="detail") == {}
    cfg = _map_train_cfg("model.siren.omega0=7")
    with open_dict(cfg):
        applied = apply_map_settings(cfg, scale(pings=320), ["model.siren.omega0=7"], "detail")
    assert cfg.model.siren.omega0 == 7 and applied["model.w_shadow"] == SURVEY_W_SHADOW
    # the scale's settings set nothing; an unknown mode is refused with the map's key
    assert apply_map_settings(_map_train_cfg(), scale(), [], mode="scale") == {}
    with pytest.raises(ValueError, match="map_settings: expected one of scale, survey, detail"):
        apply_map_settings(_map_train_cfg(), scale(), [], mode="fine")


def _xtf_survey_cfg(files, **keys):
    """A map route's ``survey`` config (conf/data/survey/xtf.yaml) of ``files``."""
    cfg = OmegaConf.load(CONF / "data" / "survey" / "xtf.yaml")
    cfg.files = str(files)
    cfg.name = "lines"
    for key, value in keys.items():
        cfg[key] = value
    return cfg


@pytest.mark.skipif(
    not REAL_LINE.is_file(), reason=f"{REAL_LINE} absent (set SSS2BATHY_REALDATA=FOLDER)"
)
def test_the_real_iver2_line(tmp_path):
    from sss2bathy.data.sources import survey_folder

    cfg = _xtf_survey_cfg(REAL_LINE, n_bins=512, tilt_deg=20.0, beam_width_deg=50.0)
    s = scale_of_survey(survey_folder(cfg, tmp_path / "data"))
    assert s.range_m == pytest.approx(30.0, abs=0.1) and s.bin_m == pytest.approx(
        30 / 512, rel=0.02
    )
    assert 40.0 < s.track_m < 80.0 and s.n_pings == 460
    chosen = choose_map_settings(s, 10.0, None, 80, 16)
    assert 30.0 < chosen.omega0 < 80.0 and chosen.steps_per_epoch == 80


def test_the_scale_of_an_imported_survey_reads_its_lines_and_leaves_the_warnings_to_the_import(
    tmp_path, caplog
):
    import importlib.util
    import logging

    from sss2bathy.data.sources import survey_folder
    from sss2bathy.io.xtf import write_xtf
    from sss2bathy.survey import Survey

    spec = importlib.util.spec_from_file_location("io_fixtures", ROOT / "tests/io/conftest.py")
    fixtures = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(fixtures)
    path = tmp_path / "L0.xtf"
    write_xtf(fixtures.synthetic_line(n_pings=30, n_bins=64), path, fixtures.ORIGIN)
    # 64 samples read as 32 bins: the reader warns (the import's WARNING, not this check's)
    cfg = _xtf_survey_cfg(path, n_bins=32, tilt_deg=30.0, beam_width_deg=60.0)
    folder = survey_folder(cfg, tmp_path / "data")
    caplog.clear()
    with caplog.at_level(logging.INFO):
        first = scale_of_survey(folder)
        again = scale_of_survey(folder)  # a fold fit's config: the same survey
    lines = Survey.load(folder).lines
    assert (
        first == again == survey_scale([ln.position for ln in lines], [ln.range_m for ln in lines])
    )
    assert first.n_pings == sum(ln.n_pings for ln in lines)
    assert first.range_m == pytest.approx(40.0, rel=0.05)
    assert not [r for r in caplog.records if r.name.startswith("sss2bathy.io")]
