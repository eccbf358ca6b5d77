"""The XTF import's cross-checks: altimeter vs first return, sonar settings vs data."""

from __future__ import annotations

import logging
import math

import numpy as np
import pytest

from sss2bathy.io.xtf import read_xtf, write_xtf
from sss2bathy.io.xtf_checks import (
    beam_vs_data,
    check_altimeter,
    implausible_altitude,
    nav_units_mismatch,
    reversed_heading_runs,
    speed_outliers,
)
from sss2bathy.survey import SurveyFormatError

P = 120


def truth_of(line) -> np.ndarray:
    return 9.0 + 2.0 * np.sin(0.25 * line.time_s)


def line_with_altimeter(tmp_path, make_line, origin, altimeter):
    """A 120-ping line whose pings show the true altitude and whose altimeter reads
    ``altimeter(truth)``."""
    line = make_line(n_pings=P)
    line.altitude_m = np.asarray(altimeter(truth_of(line)), np.float64)
    path = tmp_path / "L0.xtf"
    write_xtf(line, path, origin)
    return path, line


def test_constant_offset_is_accepted_and_reported(tmp_path, make_line, origin, caplog):
    path, line = line_with_altimeter(tmp_path, make_line, origin, lambda h: h - 1.5)
    with caplog.at_level(logging.INFO, logger="sss2bathy.io.xtf"):
        back, stats = read_xtf(path, origin=origin)
    assert stats["altimeter_minus_first_return_m"] == pytest.approx(-1.5, abs=0.1)
    assert stats["altitude_offset_model"] == "offset" and stats["altitude_offset_sigma_m"] < 0.3
    assert abs(stats["altitude_offset_drift_m"]) < 0.3 and stats["altitude_offset_applied_m"] == 0
    np.testing.assert_allclose(back.altitude_m, line.altitude_m, atol=1e-5)  # kept as recorded
    msg = next(r for r in caplog.records if "altimeter - first bottom return" in r.getMessage())
    assert msg.levelno == logging.WARNING and "-1.5" in msg.getMessage()
    assert "lever arm" in msg.getMessage() and "altitude_offset: record" in msg.getMessage()


@pytest.mark.parametrize(
    ("kind", "altimeter"),
    [
        ("drift", lambda h: h + np.linspace(0.0, 4.0, P)),
        ("random", lambda h: h + np.random.default_rng(3).normal(0.0, 1.5, P)),
    ],
)
def test_disagreement_that_is_not_one_offset_is_refused(
    tmp_path, make_line, origin, kind, altimeter
):
    path, _ = line_with_altimeter(tmp_path, make_line, origin, altimeter)
    with pytest.raises(SurveyFormatError) as err:
        read_xtf(path, origin=origin)
    msg = str(err.value)
    assert "\n" not in msg and "L0.xtf" in msg and "SensorPrimaryAltitude" in msg
    assert "data.survey.altitude_tolerance_m = 1.0 m; null skips the check" in msg
    assert "drift" in msg and "spread" in msg
    back, _ = read_xtf(path, origin=origin, altitude_tolerance_m=None)  # null: no refusal
    assert back.n_pings == P


def test_check_altimeter_numbers():
    rng = np.random.default_rng(0)
    t = np.arange(300) * 0.1
    alt = 6.0 + 3.0 * np.sin(t / 5.0)
    fr = alt + 1.6 + rng.normal(0, 0.05, t.size)
    c = check_altimeter(alt, fr, t, 1.0, 1.77)
    assert c.model == "offset" and c.offset_m == pytest.approx(-1.6, abs=0.02)
    assert c.sigma_m == pytest.approx(0.05, abs=0.02) and abs(c.drift_m) < 0.05
    # a beam-edge first return: 1.4 x the altitude, not one offset but one scale
    c = check_altimeter(alt, 1.4 * alt + rng.normal(0, 0.05, t.size), t, 1.0, 1.77)
    assert c.model == "beam_edge" and c.scale == pytest.approx(1.4, abs=0.02)
    assert c.sigma_m > 1.0 and c.scale_sigma_m < 0.1
    # a scale the beam cannot explain (an altimeter in feet) is refused
    assert check_altimeter(alt * 3.28, alt, t, 1.0, 1.77).model is None
    assert check_altimeter(alt[:5], fr[:5], t[:5], 1.0, 1.77) is None  # too few pings


def test_implausible_altitude_needs_a_jump_and_a_disagreement():
    t = np.arange(200) * 0.1
    true = 8.0 + 1.5 * np.sin(t / 5.0)
    fr = true + 0.8  # detector 0.8 m long everywhere
    alt = true.copy()
    alt[50:70] += 3.0  # 20 pings 3 m off
    alt[120] = 9999.0
    fr[150:160] -= 2.5  # the detector, not the altimeter, jumps here
    c = check_altimeter(alt, fr, t, 1.0, 1.77)
    bad = implausible_altitude(alt, np.ones(200, bool), fr, c, 30.0)
    assert np.flatnonzero(bad["beyond_range"]).tolist() == [120]
    assert np.flatnonzero(bad["jump"]).tolist() == list(range(50, 70))


def test_navigation_checks_on_arrays():
    t = np.arange(100) * 0.1
    xy = np.stack([1.5 * t, 0.5 * t], 1)
    moved = xy.copy()
    moved[[30, 31, 70]] += [50.0, 0.0]
    out, speed = speed_outliers(t, moved, np.ones(100, bool), 10.0)
    assert np.flatnonzero(out).tolist() == [30, 31, 70] and speed[70] == pytest.approx(
        500, rel=0.01
    )
    heading = np.full(100, np.degrees(np.arctan2(1.5, 0.5)))
    assert reversed_heading_runs(t * 10, xy * 10, heading) == []
    heading[40:60] += 180.0
    (run,) = reversed_heading_runs(t * 10, xy * 10, heading)
    assert run[:2] == (40, 59) and run[2] == pytest.approx(180.0, abs=1.0)
    lon, lat = -66.2 + xy[:, 0] * 1e-4, 48.4 + xy[:, 1] * 1e-4  # ~1 m/s in degrees
    assert "look like degrees" in nav_units_mismatch(lon, lat, t * 10, np.ones(100, bool), False)
    assert nav_units_mismatch(xy[:, 0] + 5e5, xy[:, 1], t, np.ones(100, bool), False) is None


def test_beam_limits_against_the_seabed_return(line):
    # the simulated seabed returns from nadir (slant range = altitude) outwards
    rot = line.rotation
    tilt20 = (math.radians(20 - 25), math.radians(20 + 25))
    port, stbd = beam_vs_data(line.intensity, line.range_m, line.altitude_m, rot, tilt20)
    for side in (port, stbd):
        a, b, ratio = side["masked_bright"]  # nadir is outside a 20 +- 25 deg beam
        assert a == pytest.approx(1.0) and 1.3 <= b <= 1.55 and ratio > 4
        assert side["seabed_from"] == pytest.approx(1.0) and side["kept_dark"] is None
    nadir_in = (math.radians(45 - 45), math.radians(45 + 45))
    port, _ = beam_vs_data(line.intensity, line.range_m, line.altitude_m, rot, nadir_in)
    assert port["masked_bright"] is None


def test_sonar_settings_and_resampling_are_warned(tmp_path, line, origin, caplog):
    path = tmp_path / "L0.xtf"
    write_xtf(line, path, origin)
    with caplog.at_level(logging.WARNING):
        back, stats = read_xtf(path, n_bins=32, origin=origin)
    assert "128 samples per side (0.312 m each) resampled to 32 bins" in caplog.text
    assert "data.survey.n_bins" in caplog.text
    beam = next(
        r.getMessage() for r in caplog.records if "sonar settings vs data" in r.getMessage()
    )
    assert "tilt 20 deg and beam width 50 deg" in beam and "on port where the median" in beam
    assert "data.survey.tilt_deg" in beam
    assert stats["sonar_vs_data"][0]["masked_bright"] is not None


def test_real_iver2_line_imports_with_its_offset_recorded(realdata, caplog):
    path = realdata / "scotsman-iver2.xtf"
    if not path.is_file():
        pytest.skip(f"real XTF line not available at {path}")
    with caplog.at_level(logging.INFO, logger="sss2bathy.io.xtf"):
        line, stats = read_xtf(path, 512, sensor={"tilt_deg": 20.0, "beam_width_deg": 50.0})
    assert line.n_pings == 460 and np.all(line.altitude_source == 0)
    # altimeter minus first return, the altimeter kept as recorded
    assert stats["altimeter_minus_first_return_m"] == pytest.approx(-1.6, abs=0.15)
    assert stats["altitude_offset_applied_m"] == 0.0
    # not one constant offset: the first return is the beam's edge, ~1.5x the altitude
    assert stats["altitude_offset_model"] == "beam_edge"
    assert 1.3 <= stats["first_return_scale"] <= 1.7
    assert "altimeter - first bottom return -1.6" in caplog.text
