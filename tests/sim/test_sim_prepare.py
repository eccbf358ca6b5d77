"""Whole tiny surveys: determinism, survey contents, the cache, pictures and the CLI."""

from __future__ import annotations

import numpy as np
import pytest
from PIL import Image
from sim_helpers import preset

import sss2bathy.sim.generate as generate_module
from sss2bathy.cli.render import main as render_main
from sss2bathy.sim.config import SyntheticSurveyConfig
from sss2bathy.sim.generate import generate_survey
from sss2bathy.sim.prepare import prepare_synthetic
from sss2bathy.sim.render import render_terrain, render_waterfall, waterfall_image
from sss2bathy.survey import MASK_VALID, MASK_WATER_COLUMN, Survey


@pytest.fixture(scope="module")
def tiny_d1():
    return generate_survey(SyntheticSurveyConfig.from_mapping(preset("synthetic_d1", "tiny")))


def test_same_seed_gives_identical_arrays(tiny_d1):
    survey, _ = tiny_d1
    again, _ = generate_survey(SyntheticSurveyConfig.from_mapping(preset("synthetic_d1", "tiny")))
    for a, b in zip(survey.lines, again.lines, strict=True):
        np.testing.assert_array_equal(a.intensity, b.intensity)
        np.testing.assert_array_equal(a.position, b.position)
        for key in a.extras:
            np.testing.assert_array_equal(a.extras[key], b.extras[key])
    np.testing.assert_array_equal(survey.grid.heights, again.grid.heights)


def test_tiny_survey_contents(tiny_d1):
    survey, terrain = tiny_d1
    assert len(survey.splits["train"]) == 2
    assert len(survey.splits["test"]) == 2
    assert survey.origin["crs"] == "EPSG:32633" and survey.origin["easting"] > 1e5
    assert survey.grid.cell_size == 0.5 and survey.grid.crs == "EPSG:32633"
    noise = survey.grid.heights - terrain.heights
    assert 0.005 < noise.std() < 0.05  # MBES-like noise, small
    for line in survey.lines:
        P, B = line.n_pings, line.n_bins
        assert B == 64 and 30 <= P <= 80
        assert line.extras["true_n_lat"].shape == (P, 2, B)
        assert line.extras["true_n_lat"].dtype == np.float32
        assert line.extras["true_points"].shape == (P, 2, B, 3)
        assert line.extras["true_mask"].dtype == np.uint8
        assert np.all(np.isfinite(line.altitude_m))
        # altitude = sonar height above the true seafloor directly below
        below = terrain.sample_heights(line.position[:, 0], line.position[:, 1])
        np.testing.assert_allclose(line.position[:, 2] - line.altitude_m, below, atol=1e-4)
        mask = line.extras["true_mask"]
        valid = mask == MASK_VALID
        assert valid.mean() > 0.2
        assert np.all(np.isfinite(line.extras["true_n_lat"][valid]))
        # true points lie on the seabed at their bin's slant range
        pts = line.extras["true_points"][valid]
        z = terrain.sample_heights(pts[:, 0], pts[:, 1])
        assert np.median(np.abs(pts[:, 2] - z)) < 0.02
        rng = np.linalg.norm(pts - line.position[np.nonzero(valid)[0]], axis=1)
        bins = np.broadcast_to(line.range_m, valid.shape)[valid]
        assert np.all(np.abs(rng - bins) <= (line.range_m[1] - line.range_m[0]))
        # the water column holds only noise: far darker than the seabed
        water = mask == MASK_WATER_COLUMN
        assert line.intensity[water].mean() < 0.1 * line.intensity[valid].mean()
    meta = survey.metadata
    assert (
        meta["config_hash"]
        == SyntheticSurveyConfig.from_mapping(preset("synthetic_d1", "tiny")).hash()
    )
    assert meta["n_lat_valid_bins"]["frac_below_0.2"] > 0.8


@pytest.mark.parametrize("survey", ["synthetic_d2", "synthetic_d3"])
def test_lake_sites_are_all_test_lines(survey):
    cfg = SyntheticSurveyConfig.from_mapping(preset(survey, "tiny"))
    survey, _ = generate_survey(cfg)
    assert survey.splits["train"] == []
    assert sorted(survey.splits["test"]) == sorted(ln.name for ln in survey.lines)
    assert len(survey.lines) == 4
    assert survey.metadata["physics"]["absorption_db_per_m"] < 0.27  # fresh water
    alt = survey.metadata["altitude_m"]
    assert set(alt) == {"all", "test"}  # no training lines
    pings = np.concatenate([ln.altitude_m for ln in survey.lines])
    assert alt["all"]["min"] <= alt["all"]["median"] <= alt["all"]["max"]
    assert alt["all"]["median"] == pytest.approx(float(np.median(pings)), abs=1e-3)


def test_prepare_reuses_the_cache_and_regenerates_on_change(tmp_path, monkeypatch):
    cfg = preset("synthetic_d1", "tiny")
    folder = prepare_synthetic(cfg, tmp_path)
    assert folder == tmp_path / "synthetic_d1_tiny"
    survey = Survey.load(folder)
    key = survey.metadata["config_hash"]
    assert (folder / "truth" / "heights.tif").is_file()
    stamp = (folder / "survey.yaml").stat().st_mtime_ns

    def refuse(*args, **kwargs):
        raise AssertionError("regenerated although the cache matches")

    with monkeypatch.context() as m:
        m.setattr(generate_module, "generate_survey", refuse)
        assert prepare_synthetic(cfg, tmp_path) == folder
        with pytest.raises(AssertionError, match="regenerated"):
            prepare_synthetic(cfg, tmp_path, force=True)
    assert (folder / "survey.yaml").stat().st_mtime_ns == stamp

    changed = preset("synthetic_d1", "tiny", seed=5)
    assert prepare_synthetic(changed, tmp_path) == folder
    assert Survey.load(folder).metadata["config_hash"] != key
    # an incomplete folder (a line file lost) is regenerated, not trusted
    (folder / "lines" / "line_000.npz").unlink()
    prepare_synthetic(changed, tmp_path)
    assert (folder / "lines" / "line_000.npz").is_file()
    assert not [p for p in tmp_path.iterdir() if ".tmp-" in p.name or ".old-" in p.name]


def test_renders_and_cli(tmp_path, tiny_d1):
    survey, _ = tiny_d1
    line = survey.lines[0]
    img = waterfall_image(line)
    np.testing.assert_array_equal(
        img[:, : line.n_bins], line.intensity[:, 0, ::-1]
    )  # port mirrored
    np.testing.assert_array_equal(img[:, line.n_bins :], line.intensity[:, 1])
    wf = render_waterfall(line, tmp_path / "wf.png")
    terrain = render_terrain(survey, tmp_path / "terrain.png")
    for path in (wf, terrain):
        with Image.open(path) as im:
            assert im.size[0] > 300 and im.size[1] > 200
    with pytest.raises(ValueError, match="pings"):
        render_waterfall(line, tmp_path / "x.png", pings=(5, 2))
    folder = survey.save(tmp_path / "survey")
    render_main(
        [
            "waterfall",
            "--survey",
            str(folder),
            "--line",
            line.name,
            "--out",
            str(tmp_path / "c.png"),
        ]
    )
    render_main(["terrain", "--survey", str(folder), "--out", str(tmp_path / "t.png")])
    assert (tmp_path / "c.png").stat().st_size > 1000 and (tmp_path / "t.png").stat().st_size > 1000
    with pytest.raises(SystemExit):
        render_main(["waterfall", "--survey", str(folder), "--line", "nope", "--out", "x.png"])


def test_parallel_workers_give_the_same_survey(tiny_d1):
    survey, _ = tiny_d1
    parallel, _ = generate_survey(
        SyntheticSurveyConfig.from_mapping(preset("synthetic_d1", "tiny", workers=2))
    )
    assert parallel.metadata["timing_s"]["workers"] == 2
    for a, b in zip(survey.lines, parallel.lines, strict=True):
        np.testing.assert_array_equal(a.intensity, b.intensity)
        np.testing.assert_array_equal(a.extras["true_n_lat"], b.extras["true_n_lat"])


def _randomized(**overrides):
    return preset("synthetic_d1", "tiny", randomize__enabled=True, **overrides)


def test_randomize_off_keeps_data_and_cache_key():
    plain = SyntheticSurveyConfig.from_mapping(preset("synthetic_d1", "tiny"))
    assert plain.randomize is None
    without = preset("synthetic_d1", "tiny")
    without.pop("randomize")
    assert SyntheticSurveyConfig.from_mapping(without).hash() == plain.hash()
    on = SyntheticSurveyConfig.from_mapping(_randomized())
    assert on.randomize is not None and on.randomize.splits == ("train",)
    assert on.hash() != plain.hash()


@pytest.mark.parametrize(
    "key, value, match",
    [
        ("randomize__enabled", "yes", r"data\.survey\.randomize\.enabled: expected true or false"),
        ("randomize__splits", ["val"], r"data\.survey\.randomize\.splits: expected"),
        ("randomize__sonar__tilt_deg", [35.0, 20.0], r"randomize\.sonar\.tilt_deg: expected low"),
        ("randomize__materials__mu_scale", [0.0, 1.0], r"randomize\.materials\.mu_scale\[0\]"),
        ("randomize__sonar__gain", [0, 1], r"randomize\.sonar: unknown key\(s\) \['gain'\]"),
    ],
)
def test_randomize_bad_values_are_named(key, value, match):
    with pytest.raises(ValueError, match=match):  # checked even while disabled
        SyntheticSurveyConfig.from_mapping(preset("synthetic_d1", "tiny", **{key: value}))


def test_randomized_training_lines_draw_their_own_sensor_and_altitude(tiny_d1, tmp_path):
    base, _ = tiny_d1
    cfg = SyntheticSurveyConfig.from_mapping(_randomized())
    survey, terrain = generate_survey(cfg)
    r = cfg.randomize
    meta = survey.metadata["lines"]
    drawn = [meta[name]["randomized"] for name in survey.splits["train"]]
    assert len(drawn) == 2 and drawn[0] != drawn[1]
    for d in drawn:
        assert r.tilt_rad[0] <= np.radians(d["tilt_deg"]) <= r.tilt_rad[1]
        assert r.altitude_offset_m[0] <= d["altitude_offset_m"] <= r.altitude_offset_m[1]
        assert all(r.mu_scale[0] <= f <= r.mu_scale[1] for f in d["mu_factor"])
    for plain, line in zip(base.lines, survey.lines, strict=True):
        if line.name in survey.splits["test"]:  # test lines: bit-identical to the plain survey
            assert "randomized" not in meta[line.name]
            np.testing.assert_array_equal(line.intensity, plain.intensity)
            assert line.sensor == plain.sensor
            continue
        d = meta[line.name]["randomized"]
        assert line.sensor == plain.sensor  # one nominal sensor record per survey
        np.testing.assert_allclose(
            line.altitude_m, plain.altitude_m + d["altitude_offset_m"], atol=2e-3
        )
        below = terrain.sample_heights(line.position[:, 0], line.position[:, 1])
        np.testing.assert_allclose(line.position[:, 2] - line.altitude_m, below, atol=1e-3)
        assert not np.array_equal(line.intensity, plain.intensity)
        valid = line.extras["true_mask"] == MASK_VALID
        assert valid.mean() > 0.02 and 0.01 < line.intensity[valid].mean() < 0.9  # 14 m range
    assert Survey.load(survey.save(tmp_path / "rand")).splits == survey.splits  # one sensor
    # the drawn values are a pure function of the config
    again, _ = generate_survey(cfg)
    np.testing.assert_array_equal(again.lines[0].intensity, survey.lines[0].intensity)


def test_randomized_altitude_below_the_minimum_is_named():
    cfg = SyntheticSurveyConfig.from_mapping(_randomized(randomize__altitude_offset_m=[-9.0, -8.0]))
    with pytest.raises(ValueError, match=r"randomize\.altitude_offset_m: expected values"):
        generate_survey(cfg)


def test_randomized_terrain_following_altitude_is_independent_of_the_seabed(tiny_d1):
    """``randomize.altitude_m``: each training line flies at its own drawn altitude, following
    the seabed (its altitude varies only within the smoothing length), so altitude and the
    slopes below are decorrelated; test lines stay the hull-mounted ones."""
    base, _ = tiny_d1
    cfg = SyntheticSurveyConfig.from_mapping(
        _randomized(
            randomize__altitude_offset_m=None,
            randomize__altitude_m=[6.0, 9.0],
            randomize__altitude_smoothing_m=15.0,
        )
    )
    survey, terrain = generate_survey(cfg)
    meta = survey.metadata["lines"]
    for plain, line in zip(base.lines, survey.lines, strict=True):
        if line.name in survey.splits["test"]:
            np.testing.assert_array_equal(line.altitude_m, plain.altitude_m)
            continue
        target = meta[line.name]["randomized"]["altitude_m"]
        assert 6.0 <= target <= 9.0
        # the smoothed altitude is the drawn one; what is left is the seabed's short relief
        assert abs(float(np.median(line.altitude_m)) - target) < 0.5
        assert np.std(line.altitude_m) < np.std(plain.altitude_m) + 1e-9
        below = terrain.sample_heights(line.position[:, 0], line.position[:, 1])
        np.testing.assert_allclose(line.position[:, 2] - line.altitude_m, below, atol=1e-3)
    with pytest.raises(ValueError, match=r"randomize\.altitude_m\[0\]: expected a number > 0"):
        SyntheticSurveyConfig.from_mapping(_randomized(randomize__altitude_m=[-1.0, 2.0]))
