"""One damaged XTF per kind: repaired (values near the undamaged line, a WARNING) or refused
(one line naming file, field, expected and found)."""

from __future__ import annotations

import ctypes
import logging
import re

import numpy as np
import pytest
import pyxtf

from sss2bathy.io.xtf import read_xtf, write_xtf
from sss2bathy.survey import SurveyFormatError


def written(tmp_path, line, origin, name="L0.xtf"):
    path = tmp_path / name
    write_xtf(line, path, origin)
    return path


def sonar_pings(path):
    _, packets = pyxtf.xtf_read(str(path), types=[pyxtf.XTFHeaderType.sonar])
    return packets[pyxtf.XTFHeaderType.sonar]


def warnings_of(caplog, text):
    return [
        r.getMessage()
        for r in caplog.records
        if r.levelno == logging.WARNING and text in r.getMessage()
    ]


# ----------------------------------------------------------------------------- altitude
def test_absurd_altitudes_are_replaced_by_the_detector(tmp_path, line, origin, xtf_patch, caplog):
    patch, _, _ = xtf_patch
    path = written(tmp_path, line, origin)
    for k in (10, 11, 40):
        patch(path, k, SensorPrimaryAltitude=9999.0)
    with caplog.at_level(logging.WARNING):
        back, stats = read_xtf(path, origin=origin)
    dr = float(line.range_m[1] - line.range_m[0])
    assert stats["altimeter_rejected_beyond_range"] == 3
    assert np.all(back.altitude_source[[10, 11, 40]] == 1)
    assert np.abs(back.altitude_m[[10, 11, 40]] - line.altitude_m[[10, 11, 40]]).max() <= 2 * dr
    (msg,) = warnings_of(caplog, "altitude/sample repairs")
    assert "3 altimeter values beyond the slant range rejected" in msg
    assert "3 filled from the detector" in msg and "median |error|" in msg


def test_a_run_of_altimeter_values_3m_off_is_replaced(
    tmp_path, make_line, origin, xtf_patch, caplog
):
    patch, _, _ = xtf_patch
    line = make_line(n_pings=120)
    path = written(tmp_path, line, origin)
    for k in range(50, 70):
        patch(path, k, SensorPrimaryAltitude=float(line.altitude_m[k] + 3.0))
    with caplog.at_level(logging.WARNING):
        back, stats = read_xtf(path, origin=origin)
    dr = float(line.range_m[1] - line.range_m[0])
    assert stats["altimeter_rejected_jumps"] == 20 and stats["altitude_offset_model"] == "offset"
    assert np.abs(back.altitude_m - line.altitude_m).max() <= 2 * dr
    (msg,) = warnings_of(caplog, "altitude/sample repairs")
    assert "20 altimeter jumps" in msg and "20 filled from the detector" in msg
    med, worst = stats["altitude_fill_error_m"]
    assert med <= dr and worst <= 2 * dr and f"median |error| {med:.2f} m" in msg


def test_no_altimeter_at_all_says_the_fill_accuracy_is_unchecked(tmp_path, line, origin, caplog):
    true = line.altitude_m.copy()
    line.altitude_m[:] = np.nan  # written as 0 on every ping
    path = written(tmp_path, line, origin)
    with caplog.at_level(logging.WARNING):
        back, stats = read_xtf(path, origin=origin)
    dr = float(line.range_m[1] - line.range_m[0])
    assert (
        stats["altitude_detected"] == line.n_pings
        and stats["altimeter_minus_first_return_m"] is None
    )
    assert np.abs(back.altitude_m - true).max() <= 2 * dr
    (msg,) = warnings_of(caplog, "altitude/sample repairs")
    assert f"{line.n_pings} filled from the detector" in msg
    assert "no altimeter value to check the detector against" in msg
    assert f"one bin ({dr:.3f} m)" in msg and "absolute offset unknown" in msg


# ----------------------------------------------------------------------------- navigation
def test_heading_reversed_against_the_course_is_refused(tmp_path, line, origin, xtf_patch):
    patch, _, _ = xtf_patch
    path = written(tmp_path, line, origin)
    for k, p in enumerate(sonar_pings(path)):
        if 20 <= k <= 35:
            patch(path, k, SensorHeading=float((p.SensorHeading + 180.0) % 360.0))
    with pytest.raises(SurveyFormatError) as err:
        read_xtf(path, origin=origin)
    msg = str(err.value)
    assert "\n" not in msg and "L0.xtf" in msg and "pings 20-35: SensorHeading" in msg
    assert "within 135 deg of the course over ground" in msg
    assert re.search(r"found 1[78]\d deg off the course on 16 pings", msg)


def test_fixes_moved_50m_are_interpolated_with_their_speed(
    tmp_path, line, origin, xtf_patch, caplog
):
    patch, _, _ = xtf_patch
    path = written(tmp_path, line, origin)
    pings = sonar_pings(path)
    for k in (15, 16, 44):  # ~50 m north: 250 m/s at 0.2 s per ping
        patch(path, k, SensorYcoordinate=pings[k].SensorYcoordinate + 50.0 / 111_000.0)
    with caplog.at_level(logging.WARNING):
        back, stats = read_xtf(path, origin=origin)
    assert stats["nav_outliers"] == 3 and stats["nav_interpolated"] == 3
    assert np.abs(back.position - line.position)[:, :2].max() < 0.05
    (msg,) = warnings_of(caplog, "navigation/ping repairs")
    assert "fixes rejected as outliers: 3 (implied speeds up to 2" in msg


def test_too_many_fast_fixes_are_refused(tmp_path, line, origin, xtf_patch):
    patch, _, _ = xtf_patch
    path = written(tmp_path, line, origin)
    pings = sonar_pings(path)
    for k in range(5, 55, 5):  # 10 of 60 fixes
        patch(path, k, SensorYcoordinate=pings[k].SensorYcoordinate + 50.0 / 111_000.0)
    with pytest.raises(SurveyFormatError, match=r"L0\.xtf.*'position'.*at most 10%.*10 of 60"):
        read_xtf(path, origin=origin)


def test_fixes_from_the_ship_are_a_warning(tmp_path, line, origin, xtf_patch, caplog):
    patch, _, _ = xtf_patch
    path = written(tmp_path, line, origin)
    for k in (3, 4):
        patch(path, k, SensorXcoordinate=float("nan"), SensorYcoordinate=float("nan"))
    with caplog.at_level(logging.WARNING):
        back, stats = read_xtf(path, origin=origin)
    assert stats["positions_from_ship"] == 2
    assert np.abs(back.position - line.position)[:, :2].max() < 1e-3  # ship = sensor here
    (msg,) = warnings_of(caplog, "navigation/ping repairs")
    assert "sensor fixes taken from the ship position" in msg and "layback: 2" in msg


def test_degrees_labelled_as_metres_are_refused(tmp_path, line, origin, xtf_patch):
    _, patch_header, _ = xtf_patch
    path = written(tmp_path, line, origin)  # lon/lat
    patch_header(path, lambda h: setattr(h, "NavUnits", 0))  # ... labelled metres
    with pytest.raises(SurveyFormatError) as err:
        read_xtf(path, crs="EPSG:32633")
    msg = str(err.value)
    assert "\n" not in msg and "L0.xtf" in msg and "'NavUnits'" in msg
    assert "metres (0) as NavUnits states" in msg and "look like degrees" in msg
    assert "data.survey.nav_units" in msg
    back, stats = read_xtf(path, origin=origin, nav_units="latlon")  # the override reads it
    assert stats["nav_units"] == "latlon"
    assert np.abs(back.position - line.position).max() < 1e-3


# ----------------------------------------------------------------------------- packets
def test_corrupt_packet_size_is_resynchronised_not_truncated(
    tmp_path, line, origin, xtf_patch, caplog
):
    _, _, offsets = xtf_patch
    path = written(tmp_path, line, origin)
    offs = offsets(path)
    raw = bytearray(path.read_bytes())
    at = offs[20] + pyxtf.XTFPacketStart.NumBytesThisRecord.offset
    raw[at : at + 4] = (0xFFFFFFFF).to_bytes(4, "little")
    path.write_bytes(bytes(raw))
    with caplog.at_level(logging.WARNING):
        back, stats = read_xtf(path, origin=origin)
    assert stats["packets_truncated"] == 0 and "truncated" not in caplog.text
    assert back.n_pings == line.n_pings - 1
    np.testing.assert_allclose(
        back.intensity[20:], line.intensity[21:], atol=1e-3 * line.intensity.max()
    )
    (msg,) = warnings_of(caplog, "damaged packets")
    assert f"bytes {offs[20]}-{offs[21]} (after sonar ping 19)" in msg
    assert "about 1 sonar pings lost, 59 read" in msg


def test_mostly_damaged_file_is_refused(tmp_path, line, origin, xtf_patch):
    _, _, offsets = xtf_patch
    path = written(tmp_path, line, origin)
    offs = offsets(path)
    raw = bytearray(path.read_bytes())
    size = ctypes.sizeof(pyxtf.XTFPacketStart)
    for k in range(10, 50):  # 40 of 60 packets lose their magic number
        raw[offs[k] : offs[k] + 2] = b"\x00\x00"
    assert size == 14
    path.write_bytes(bytes(raw))
    with pytest.raises(SurveyFormatError, match=r"L0\.xtf.*'packets'.*at most half.*damaged"):
        read_xtf(path, origin=origin)
