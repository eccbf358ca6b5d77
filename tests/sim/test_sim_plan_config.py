"""Config validation (named errors), Hydra composition of the presets, survey planning."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hydra import compose, initialize_config_dir
from omegaconf import OmegaConf
from sim_helpers import CONF, preset

from sss2bathy.sim.config import SyntheticSurveyConfig
from sss2bathy.sim.plan import SwathOutsideTerrainError, plan_survey, validate_swath
from sss2bathy.sim.terrain import Terrain


def flat_terrain(cfg: SyntheticSurveyConfig) -> Terrain:
    t = cfg.terrain
    nx = int(round(t.size_m[0] / t.cell_m)) + 1
    ny = int(round(t.size_m[1] / t.cell_m)) + 1
    return Terrain(
        np.full((ny, nx), -t.mean_depth_m), t.cell_m, np.zeros((ny, nx), np.uint8),
        cfg.materials.names, np.ones((2, 2), np.float32), 1.0, np.zeros((0, 4)),
    )  # fmt: skip


@pytest.mark.parametrize(
    "key, value, match",
    [
        (
            "plan__line_spacing_m",
            -3.0,
            r"data\.survey\.plan\.line_spacing_m: expected a number > 0",
        ),
        ("sonar__beam_width_deg", 0.0, r"data\.survey\.sonar\.beam_width_deg: expected"),
        ("sonar__beam_width_deg", 180.0, r"data\.survey\.sonar\.beam_width_deg: expected"),
        ("sonar__max_range_m", 0.5, r"data\.survey\.sonar\.max_range_m"),
        ("terrain__cell_m", "fine", r"data\.survey\.terrain\.cell_m: expected a finite number"),
        ("terrain__boulders__diameter_m", [3.0, 0.3], r"diameter_m: expected low <= high"),
        (
            "terrain__ridges__wiggle",
            1.0,
            r"data\.survey\.terrain\.ridges: unknown key\(s\) \['wiggle'\]",
        ),
        ("plan__mount", "towfish", r"data\.survey\.plan\.mount: expected one of \['hull', 'auv'\]"),
        ("plan__motion__yaw", 1.0, r"data\.survey\.plan\.motion: unknown key"),
        ("materials__classes__mud__fraction", 0.9, r"fractions summing to 1"),
        ("materials__classes__sand__exponent", 0.5, r"sand\.exponent: expected a number >= 1"),
        ("materials__reference_material", "clay", r"reference_material: expected one of"),
        ("name", "../escape", r"data\.survey\.name"),
        ("kind", "xtf", r"data\.survey\.kind"),
    ],
)
def test_bad_configs_raise_named_errors(key, value, match):
    with pytest.raises(ValueError, match=match):
        SyntheticSurveyConfig.from_mapping(preset("synthetic_d1", "tiny", **{key: value}))


def test_degrees_in_config_radians_inside_and_hash():
    cfg = SyntheticSurveyConfig.from_mapping(preset("synthetic_d1", "demo"))
    assert cfg.sonar.tilt_rad == pytest.approx(math.radians(30.0))
    assert cfg.sonar.beam_width_rad == pytest.approx(math.radians(60.0))
    assert cfg.plan.roll_rad == pytest.approx(math.radians(1.0))
    same = SyntheticSurveyConfig.from_mapping(preset("synthetic_d1", "demo", workers=2))
    other = SyntheticSurveyConfig.from_mapping(preset("synthetic_d1", "demo", seed=7))
    assert cfg.hash() == same.hash() != other.hash()  # workers do not change the data
    with pytest.warns(UserWarning, match="ignoring keys"):
        SyntheticSurveyConfig.from_mapping(preset("synthetic_d1", "demo", stray_key=1))


@pytest.mark.parametrize("survey", ["synthetic_d1", "synthetic_d2", "synthetic_d3"])
@pytest.mark.parametrize("scale", ["tiny", "demo", "paper"])
def test_presets_compose_and_plan(survey, scale):
    with initialize_config_dir(config_dir=str(CONF), version_base="1.3"):
        composed = compose(
            config_name="prepare", overrides=[f"data/survey={survey}", f"scale={scale}"]
        )
    plain = OmegaConf.to_container(composed.data.survey, resolve=True)
    assert plain["name"] == f"{survey}_{scale}"
    cfg = SyntheticSurveyConfig.from_mapping(plain)
    lines = plan_survey(cfg.plan, cfg.sonar, flat_terrain(cfg), np.random.default_rng(0))
    n_test = [ln for ln in lines if ln.split == "test"]
    n_train = [ln for ln in lines if ln.split == "train"]
    expected = {
        ("synthetic_d1", "paper"): (45, 12, 2000, 512),
        ("synthetic_d1", "demo"): (32, 4, 300, 256),
        ("synthetic_d1", "tiny"): (2, 2, 60, 64),
        ("synthetic_d2", "paper"): (0, 36, 2000, 512),
        ("synthetic_d2", "demo"): (0, 6, 300, 256),
        ("synthetic_d2", "tiny"): (0, 4, 60, 64),
        ("synthetic_d3", "paper"): (0, 36, 2000, 512),
        ("synthetic_d3", "demo"): (0, 6, 300, 256),
        ("synthetic_d3", "tiny"): (0, 4, 60, 64),
    }[(survey, scale)]
    assert (len(n_train), len(n_test)) == expected[:2]
    pings = np.array([len(ln.time_s) for ln in lines])
    assert np.all(pings > 0.6 * expected[2]) and np.all(pings < 1.4 * expected[2])
    assert cfg.sonar.n_bins == expected[3]
    # test lines: half of them perpendicular to the other half
    sets = [ln.line_set for ln in n_test]
    assert abs(sets.count("main") - sets.count("cross")) <= 1
    assert {round(math.degrees(ln.heading_rad)) % 180 for ln in n_test} == {0, 90}


def _composed_survey(survey: str, scale: str) -> dict:
    with initialize_config_dir(config_dir=str(CONF), version_base="1.3"):
        composed = compose(
            config_name="prepare", overrides=[f"data/survey={survey}", f"scale={scale}"]
        )
    return OmegaConf.to_container(composed.data.survey, resolve=True)


@pytest.mark.parametrize("scale", ["tiny", "demo", "paper"])
def test_d2_keeps_d1_instrument_and_d3_does_not(scale):
    """The paper's Dataset II used Dataset I's ship and sonar: synthetic_d2's sonar block
    (after its scale preset) equals synthetic_d1's except for the water; synthetic_d3 is
    the different-sonar stress site. Both read as plain files (bench, tests) and composed."""
    d1, d2, d3 = (
        _composed_survey(s, scale) for s in ("synthetic_d1", "synthetic_d2", "synthetic_d3")
    )
    for survey, plain in (("synthetic_d1", d1), ("synthetic_d2", d2)):
        assert preset(survey, scale)["sonar"] == plain["sonar"]  # plain files, no defaults list
    son1, son2, son3 = ({k: v for k, v in d["sonar"].items() if k != "water"} for d in (d1, d2, d3))
    assert son2 == son1
    assert d2["plan"]["sonar_depth_m"] == d1["plan"]["sonar_depth_m"]  # same hull mount
    assert d2["plan"]["mount"] == d1["plan"]["mount"] == "hull"
    assert d2["sonar"]["water"]["salinity_ppt"] < 1.0 < d1["sonar"]["water"]["salinity_ppt"]
    differs = {k for k in son1 if son3[k] != son1[k]}
    assert {"tilt_deg", "beam_width_deg", "beam_rolloff", "tvg"} <= differs
    # the geometry of the swath is the scale's, shared by all three sites
    for key in ("max_range_m", "n_bins", "min_range_m"):
        assert son3[key] == son1[key]
    names = {d["name"] for d in (d1, d2, d3)}
    seeds = {d["seed"] for d in (d1, d2, d3)}
    origins = {(d["origin"]["easting"], d["origin"]["northing"]) for d in (d1, d2, d3)}
    assert len(names) == len(seeds) == len(origins) == 3


def _planned_altitudes(survey: str, scale: str) -> np.ndarray:
    from sss2bathy.sim.generate import altitude_summary
    from sss2bathy.sim.terrain import generate_terrain

    cfg = SyntheticSurveyConfig.from_mapping(preset(survey, scale))
    terrain = generate_terrain(cfg.terrain, cfg.materials, np.random.default_rng([cfg.seed, 0]))
    lines = plan_survey(cfg.plan, cfg.sonar, terrain, np.random.default_rng([cfg.seed, 1]))
    a = np.concatenate([ln.altitude_m for ln in lines])
    summary = altitude_summary(lines)["all"]
    assert summary["min"] == pytest.approx(a.min(), abs=1e-3)
    assert summary["median"] == pytest.approx(np.median(a), abs=1e-3)
    return a


def test_demo_sites_fly_at_realistic_comparable_altitudes():
    """The paper's depths: 9.03-25.07 m (Dataset I), 10.45-13.66 m (II); the demo sonar
    reaches 30 m. Both demo sites' median altitudes lie in the paper's range, within 3 m of
    each other; synthetic_d1's relief and slope give the wider spread."""
    a1, a2 = _planned_altitudes("synthetic_d1", "demo"), _planned_altitudes("synthetic_d2", "demo")
    m1, m2 = float(np.median(a1)), float(np.median(a2))
    assert 10.0 <= m1 <= 16.0 and 10.0 <= m2 <= 14.0
    assert abs(m1 - m2) <= 3.0
    assert a1.min() > 8.0 and a1.max() < 20.0 and a2.min() > 9.0 and a2.max() < 15.0
    assert np.ptp(a1) > 5.0 and np.ptp(a1) > 2 * np.ptp(a2)


def test_plan_geometry_and_navigation():
    cfg = SyntheticSurveyConfig.from_mapping(
        preset("synthetic_d1", "demo", plan__nav_noise__position_m=0.3)
    )
    terrain = flat_terrain(cfg)
    lines = plan_survey(cfg.plan, cfg.sonar, terrain, np.random.default_rng(0))
    t_prev = -np.inf
    for ln in lines:
        assert np.all(np.diff(ln.time_s) > 0) and ln.time_s[0] > t_prev
        t_prev = ln.time_s[-1]
        np.testing.assert_allclose(ln.position[:, 2], -cfg.plan.sonar_depth_m)  # hull-mounted
        np.testing.assert_allclose(ln.altitude_m, cfg.terrain.mean_depth_m - cfg.plan.sonar_depth_m)
        step = np.linalg.norm(np.diff(ln.position[:, :2], axis=0), axis=1)
        np.testing.assert_allclose(step, cfg.plan.speed_mps / cfg.plan.ping_rate_hz)
        offset = np.linalg.norm(ln.nav_position - ln.position, axis=1)
        assert 0.05 < offset.mean() < 1.5  # recorded navigation carries the noise
    main = [ln for ln in lines if ln.line_set == "main"]
    # lawnmower: consecutive lines of a set alternate direction
    headings = [round(math.degrees(ln.heading_rad)) for ln in main]
    assert all(a != b for a, b in zip(headings, headings[1:], strict=False))


def test_auv_mount_keeps_constant_altitude():
    cfg = SyntheticSurveyConfig.from_mapping(
        preset("synthetic_d1", "tiny", plan__mount="auv", plan__altitude_m=5.0)
    )
    lines = plan_survey(cfg.plan, cfg.sonar, flat_terrain(cfg), np.random.default_rng(0))
    np.testing.assert_allclose(lines[0].altitude_m, 5.0)


def test_lines_outside_the_terrain_fail_with_a_named_error():
    cfg = SyntheticSurveyConfig.from_mapping(preset("synthetic_d1", "tiny"))
    terrain = flat_terrain(cfg)
    line = plan_survey(cfg.plan, cfg.sonar, terrain, np.random.default_rng(0))[0]
    shifted = line.position + [0.0, 20.0, 0.0]  # swath now reaches past the north edge
    with pytest.raises(SwathOutsideTerrainError, match=r"line 'line_000'.*swath of ping 0"):
        validate_swath("line_000", shifted, line.rotation, cfg.sonar, terrain)
    with pytest.raises(SwathOutsideTerrainError, match="outside the terrain"):
        validate_swath("line_000", line.position + [0, 100, 0], line.rotation, cfg.sonar, terrain)
    too_wide = SyntheticSurveyConfig.from_mapping(
        preset("synthetic_d1", "tiny", plan__line_spacing_m=30.0)
    )
    with pytest.raises(ValueError, match=r"data\.survey\.plan\.line_spacing_m: expected <="):
        plan_survey(too_wide.plan, too_wide.sonar, terrain, np.random.default_rng(0))
    small = SyntheticSurveyConfig.from_mapping(
        preset("synthetic_d1", "tiny", terrain__size_m=[20, 20])
    )
    with pytest.raises(SwathOutsideTerrainError, match=r"terrain\.size_m"):
        plan_survey(small.plan, small.sonar, flat_terrain(small), np.random.default_rng(0))
    shallow = SyntheticSurveyConfig.from_mapping(
        preset("synthetic_d1", "tiny", plan__sonar_depth_m=7.0)
    )
    with pytest.raises(ValueError, match=r"plan\.min_altitude_m"):
        plan_survey(shallow.plan, shallow.sonar, flat_terrain(shallow), np.random.default_rng(0))
