"""Values that only the data can check are rejected in the data modules' set-up, naming
the config key; everything else fails in train() before any data is touched."""

from __future__ import annotations

import hydra
import pytest
from reliability_helpers import compose_run, siren_overrides

import sss2bathy.data.pings as pings
from sss2bathy.cli.train import train
from sss2bathy.config_validation import ConfigError


@pytest.mark.parametrize(
    "override, key, found",
    [
        ("data.sidescan_split=nope", "data.sidescan_split", "'nope'"),
        ("data.altimeter_split=survey", "data.altimeter_split", "'survey'"),
        ("data.altimeter_split=train", "data.altimeter_split", "'train'"),  # no lines
    ],
)
def test_split_names_are_checked_against_the_survey(tmp_path, plane_survey, override, key, found):
    cfg = compose_run(siren_overrides(plane_survey, tmp_path) + [override], tmp_path / "r")
    dm = hydra.utils.instantiate(cfg.data, _recursive_=False)
    with pytest.raises(ValueError) as err:
        dm.setup("fit")
    assert str(err.value).startswith(f"{key}: expected") and found in str(err.value)


def test_bad_config_fails_before_any_data_is_loaded(tmp_path, plane_survey, monkeypatch):
    def refuse(*args, **kwargs):
        raise AssertionError("data loaded before the config was validated")

    monkeypatch.setattr(pings, "survey_folder", refuse)
    monkeypatch.setattr(pings, "load_survey", refuse)
    cfg = compose_run(siren_overrides(plane_survey, tmp_path) + ["model.w_height=-1"], tmp_path)
    with pytest.raises(ConfigError, match=r"'model.w_height'.*-1"):
        train(cfg, tmp_path / "r")


@pytest.mark.parametrize(
    "key, bad, expected",
    [
        ("tilt_deg", 95.0, "a value in [-90, 90] degrees or null"),
        ("max_jump_m", 0, "a positive distance (m)"),
        ("max_jump_m", None, "a positive distance (m)"),
        ("min_first_return_m", -0.5, "a distance >= 0 (m)"),
        ("altitude_tolerance_m", "1", "a positive distance (m) or null"),
        ("mbes_z_positive", "sideways", "one of ['up', 'down']"),
        ("missing_attitude", "zero", "one of ['error', 'track']"),
        ("auto_blanking", 1, "true or false"),
        ("channel_pair", -1, "an integer >= 0"),
    ],
)
def test_xtf_survey_checks_name_the_key(key, bad, expected):
    """The importer's own checks are the start-up checks of an xtf survey (no RULES copy)."""
    from sss2bathy.io.xtf_survey import DEFAULTS, validate_xtf_config

    validate_xtf_config(DEFAULTS)
    with pytest.raises(ValueError) as err:
        validate_xtf_config({**DEFAULTS, key: bad})
    assert str(err.value) == f"data.survey.{key}: expected {expected}, found {bad!r}"


def test_the_table_holds_no_key_a_constructor_checks():
    """Data-module, survey, loss and sensor keys are their constructors' (one system)."""
    from sss2bathy.config_validation import RULES

    owned = ("data.", "model.loss.", "model.sensor.", "model.net.", "model.finder.")
    assert [key for key, *_ in RULES if key.startswith(owned)] == []
