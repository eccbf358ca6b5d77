"""Edgetech JSF in and out: round trips within the format's precision, the import through the
XTF pipeline and prepare_xtf_survey, and damaged / wrong files."""

from __future__ import annotations

import logging
import math
from pathlib import Path

import numpy as np
import pytest
from pyproj import Transformer

from sss2bathy.geometry import rotation_to_attitude
from sss2bathy.io.jsf import (
    ANGLE_SCALE,
    MESSAGE_HEADER,
    SONAR_HEADER,
    read_jsf,
    read_jsf_sensor,
    write_jsf,
)
from sss2bathy.io.xtf import read_xtf, write_xtf
from sss2bathy.io.xtf_survey import prepare_xtf_survey, resolve_files
from sss2bathy.survey import Survey, SurveyFormatError

SENSOR = {"tilt_deg": 20.0, "beam_width_deg": 50.0}  # JSF has neither


def messages(path: Path) -> list[tuple[int, int, int, int]]:
    """``(offset, type, subsystem, channel)`` of every message of an intact file."""
    raw = path.read_bytes()
    out, pos = [], 0
    while pos < len(raw):
        h = np.frombuffer(raw[pos : pos + 16], MESSAGE_HEADER)[0]
        out.append((pos, int(h["type"]), int(h["subsystem"]), int(h["channel"])))
        pos += 16 + int(h["size"])
    return out


def sonar_offsets(path: Path) -> list[int]:
    return [o for o, t, _, _ in messages(path) if t == 80]


def patch_sonar(path: Path, index: int, **fields: int) -> None:
    """Overwrite fields of the sonar data header of sonar message ``index`` in place."""
    off = sonar_offsets(path)[index] + 16
    with open(path, "r+b") as f:
        f.seek(off)
        h = np.frombuffer(f.read(SONAR_HEADER.itemsize), SONAR_HEADER).copy()
        for key, value in fields.items():
            h[key] = value
        f.seek(off)
        f.write(h.tobytes())


def angle_error_deg(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return np.degrees(np.abs(np.angle(np.exp(1j * (np.asarray(a) - np.asarray(b))))))


@pytest.fixture
def jsf(tmp_path, line, origin):
    path = tmp_path / "L0.jsf"
    stats = write_jsf(line, path, origin)
    return path, stats


# ----------------------------------------------------------------------------- round trips
def test_round_trip_within_the_formats_precision(jsf, line, origin):
    path, wstats = jsf
    got = read_jsf(path)

    assert got.n_pings == line.n_pings and got.units == "latlon" and got.subsystem == 21
    np.testing.assert_array_equal(got.ping_number, np.arange(1, line.n_pings + 1))
    assert np.abs(got.time_s - wstats["epoch_s"] - line.time_s).max() <= 0.0005 + 1e-6
    # positions: 1e-4 minutes of arc per unit
    lon, lat = Transformer.from_crs(origin["crs"], "EPSG:4326", always_xy=True).transform(
        line.position[:, 0] + origin["easting"], line.position[:, 1] + origin["northing"]
    )
    assert np.abs(got.x - lon).max() <= 0.5 / 600000 + 1e-12
    assert np.abs(got.y - lat).max() <= 0.5 / 600000 + 1e-12
    # heading 0.01 deg, pitch / roll 180/32768 deg, altitude and depth 1 mm
    heading, pitch, roll = (np.degrees(a) for a in rotation_to_attitude(line.rotation))
    assert angle_error_deg(np.radians(got.heading_deg), np.radians(heading)).max() <= 0.005 + 1e-9
    assert np.abs(got.pitch_deg - pitch).max() <= ANGLE_SCALE / 2 + 1e-9
    assert np.abs(got.roll_deg - roll).max() <= ANGLE_SCALE / 2 + 1e-9
    assert np.abs(got.altitude_m - line.altitude_m).max() <= 0.0005 + 1e-6
    assert np.abs(got.depth_m + line.position[:, 2]).max() <= 0.0005 + 1e-9
    np.testing.assert_allclose(got.sound_speed_mps, 1500.0)
    np.testing.assert_allclose(got.frequency_hz, 400e3)
    # intensities: within max / 65535 of each ping's side (the weighting factor's LSB)
    for side, chans in ((0, got.port), (1, got.starboard)):
        for k, ch in enumerate(chans):
            want = line.intensity[k, side].astype(np.float64)
            assert np.abs(ch.samples - want).max() <= want.max() / 65535 + 1e-12
            assert ch.start_s == 0.0
            assert ch.interval_s == pytest.approx(wstats["sample_interval_ns"] * 1e-9)
    assert got.truncated == 0 and got.pings_lost == 0 and got.other_messages == {}


def test_import_gives_the_xtf_line(jsf, line, origin):
    path, wstats = jsf
    back, stats = read_xtf(path, origin=origin, sensor=SENSOR)

    assert back.name == "L0" and back.n_pings == line.n_pings and back.n_bins == line.n_bins
    # lon/lat units of 1e-4 minutes of arc: <= 0.093 m north, less east
    d = np.abs(back.position - line.position)
    assert d[:, 0].max() < 0.06 and d[:, 1].max() < 0.095 and d[:, 2].max() <= 0.0005 + 1e-6
    assert np.abs(back.altitude_m - line.altitude_m).max() <= 0.0005 + 1e-6
    for got, want, tol in zip(
        rotation_to_attitude(back.rotation),
        rotation_to_attitude(line.rotation),
        (0.005, ANGLE_SCALE / 2, ANGLE_SCALE / 2),
        strict=True,
    ):
        assert angle_error_deg(got, want).max() <= tol + 1e-6
    top = line.intensity.max(axis=2, keepdims=True)
    assert np.all(np.abs(back.intensity - line.intensity) <= top / 65535 + 1e-6)
    # the sample interval in whole ns: range within 1e-5 of the written one
    np.testing.assert_allclose(back.range_m, line.range_m, rtol=1e-5)
    # times at XTF's 10 ms (the conversion's resolution)
    assert np.abs(back.time_s - wstats["epoch_s"] - line.time_s).max() <= 0.005 + 1e-6
    assert back.sensor.frequency_hz == pytest.approx(400e3)
    assert back.sensor.sound_speed_mps == pytest.approx(1500.0)
    assert math.degrees(back.sensor.tilt_rad) == pytest.approx(20.0)
    assert stats["nav_units"] == "latlon" and stats["attitude_source"] == "ping_header"
    assert stats["packets_truncated"] == 0 and stats["pings_missing_channel"] == 0
    assert read_jsf_sensor(path) == {
        "tilt_deg": None,
        "beam_width_deg": None,
        "frequency_hz": pytest.approx(400e3),
    }


def test_analytic_signal_is_read_as_its_magnitude(tmp_path, line, origin):
    path = tmp_path / "C.jsf"
    write_jsf(line, path, origin, data_format=1)
    got = read_jsf(path)
    for side, chans in ((0, got.port), (1, got.starboard)):
        for k, ch in enumerate(chans):
            want = line.intensity[k, side].astype(np.float64)
            # each part rounded: the magnitude within 0.71 of the int16 part's LSB
            assert np.abs(ch.samples - want).max() <= 0.71 * want.max() / 32767 * 2


def test_metres_navigation_round_trip(tmp_path, line):
    path = tmp_path / "M.jsf"
    stats = write_jsf(line, path, {"crs": None})
    assert stats["nav_units"] == "metres"
    got = read_jsf(path)
    assert got.units == "metres"
    assert np.abs(got.x - line.position[:, 0]).max() <= 0.0005 + 1e-9
    back, st = read_xtf(path, crs="EPSG:32633", sensor=SENSOR)
    origin = st["origin"]
    x = back.position[:, 0] + origin["easting"]
    assert np.abs(x - line.position[:, 0]).max() <= 0.0005 + 1e-6
    assert st["nav_units"] == "metres"


def test_attitude_from_pitch_roll_messages(tmp_path, line, origin):
    path = tmp_path / "A.jsf"
    write_jsf(line, path, origin, ping_attitude=False, attitude_messages=True)
    back, stats = read_xtf(path, origin=origin, sensor=SENSOR)
    assert stats["attitude_source"] == "attitude_packets"
    # the messages sit at the ping times; interpolated at times rounded to 10 ms
    for got, want in zip(
        rotation_to_attitude(back.rotation), rotation_to_attitude(line.rotation), strict=True
    ):
        assert angle_error_deg(got, want).max() < 0.02

    bare = tmp_path / "B.jsf"
    write_jsf(line, bare, origin, ping_attitude=False)
    with pytest.raises(SurveyFormatError, match=r"B\.jsf: field 'ping 0: attitude'"):
        read_xtf(bare, origin=origin, sensor=SENSOR)


def test_pitch_roll_messages_unused_when_pings_have_attitude(tmp_path, line, origin):
    path = tmp_path / "A.jsf"
    write_jsf(line, path, origin, attitude_messages=True)
    _, stats = read_xtf(path, origin=origin, sensor=SENSOR)
    assert stats["attitude_source"] == "ping_header"
    assert stats["other_packets"] == {"pitch_roll_unused": line.n_pings + 1}


def test_choosing_the_subsystem(tmp_path, make_line, origin):
    """Dual frequency: channel_pair 0 reads subsystem 20, 1 reads 21."""
    low, high = make_line(seed=1), make_line(seed=2)
    a, b = tmp_path / "lo.jsf", tmp_path / "hi.jsf"
    write_jsf(low, a, origin, subsystem=20)
    write_jsf(high, b, origin, subsystem=21)
    both = tmp_path / "dual.jsf"
    both.write_bytes(a.read_bytes() + b.read_bytes())
    first, second = read_jsf(both, 0), read_jsf(both, 1)
    assert (first.subsystem, second.subsystem) == (20, 21)
    assert first.other_messages == {
        "sonar_data_subsystem_21_channel_0": 60,
        "sonar_data_subsystem_21_channel_1": 60,
    }
    assert np.abs(second.port[3].samples - high.intensity[3, 0]).max() < 1e-3
    with pytest.raises(SurveyFormatError, match=r"channel_pair'.*below 2.*\[20, 21\]"):
        read_jsf(both, 2)


# ----------------------------------------------------------------------------- damage
def test_truncated_file_loses_the_last_ping_with_a_warning(jsf, line, origin, caplog):
    path, _ = jsf
    raw = path.read_bytes()
    last = sonar_offsets(path)[-1]  # the starboard message of the last ping
    path.write_bytes(raw[: last + 300])
    with caplog.at_level(logging.WARNING):
        back, stats = read_xtf(path, origin=origin, sensor=SENSOR)
    assert back.n_pings == line.n_pings - 1
    assert stats["packets_truncated"] == 1 and stats["pings_missing_channel"] == 1
    text = caplog.text
    assert f"file cut short at byte {last} of {last + 300}" in text
    assert "sonar data message (subsystem 21, channel 1)" in text
    assert "1 pings left with one side" in text and f"{line.n_pings} pings read" in text


def test_file_cut_inside_a_message_header(jsf, line, caplog):
    path, _ = jsf
    raw = path.read_bytes()
    path.write_bytes(raw + raw[:9])  # a next message begun, 9 of its 16 header bytes
    with caplog.at_level(logging.WARNING):
        got = read_jsf(path)
    assert got.n_pings == line.n_pings and got.truncated == 1 and got.pings_one_side == 0
    assert "in a message header" in caplog.text


def test_damaged_message_is_skipped_by_resynchronising(jsf, line, origin, caplog):
    path, _ = jsf
    offs = sonar_offsets(path)
    raw = bytearray(path.read_bytes())
    for k in (20, 21, 22):  # ping 11's both sides and ping 12's port: marker destroyed
        raw[offs[k] : offs[k] + 2] = b"\0\0"
    path.write_bytes(bytes(raw))
    with caplog.at_level(logging.WARNING):
        back, stats = read_xtf(path, origin=origin, sensor=SENSOR)
    assert back.n_pings == line.n_pings - 2
    assert stats["pings_missing_channel"] == 1
    assert f"bytes {offs[20]}-{offs[23]}" in caplog.text
    assert "1 pings lost whole, 1 pings left with one side" in caplog.text


def test_mostly_damaged_file_is_refused(jsf):
    path, _ = jsf
    offs = sonar_offsets(path)
    raw = bytearray(path.read_bytes())
    for o in offs[1:]:
        raw[o : o + 2] = b"\0\0"
    path.write_bytes(bytes(raw))
    with pytest.raises(SurveyFormatError, match=r"field 'messages'.*bytes damaged"):
        read_jsf(path)


@pytest.mark.parametrize("subsystem", [0, 40])
def test_file_without_sidescan_is_refused(tmp_path, line, origin, subsystem):
    path = tmp_path / "sbp.jsf"
    write_jsf(line, path, origin, subsystem=subsystem, attitude_messages=True)
    with pytest.raises(SurveyFormatError) as err:
        read_xtf(path, origin=origin, sensor=SENSOR)
    msg = str(err.value)
    assert "\n" not in msg and "sbp.jsf: field 'sonar data messages (type 80)'" in msg
    assert "expected sidescan messages (subsystem 20, 21, 22)" in msg
    assert f"120 x sonar data of subsystem {subsystem}" in msg and "61 x pitch_roll" in msg


@pytest.mark.parametrize(
    ("content", "found"),
    [(b"", "an empty file"), (b"\xce\xfa" + bytes(2000), "cefa"), (b"\x01", "1 bytes")],
)
def test_not_a_jsf_file(tmp_path, content, found):
    path = tmp_path / "x.jsf"
    path.write_bytes(content)
    with pytest.raises(SurveyFormatError, match=f"x.jsf: field 'message header'.*found {found}"):
        read_jsf(path)


def test_xtf_file_named_jsf_is_refused(tmp_path, line, origin):
    path = tmp_path / "x.jsf"
    write_xtf(line, tmp_path / "x.xtf", origin)
    path.write_bytes((tmp_path / "x.xtf").read_bytes())
    with pytest.raises(SurveyFormatError, match=r"start marker 0x1601 at byte 0\), found 7b"):
        read_xtf(path, origin=origin, sensor=SENSOR)


@pytest.mark.parametrize(
    ("fields", "match"),
    [
        ({"data_format": 2}, r"ping 4 port: data format \(bytes 34-35\)'.*found 2$"),
        ({"data_format": 300}, r"found 300 \(compressed, proprietary\)$"),
        ({"samples": 5000}, r"ping 4 port: samples \(bytes 114-115\)'.*found 5000 samples"),
        ({"sample_interval_ns": 0}, r"sample interval \(bytes 116-119\)'.*> 0 ns, found 0"),
        ({"packet_number": 2}, r"packet number \(bytes 220-221\)'.*found 2"),
        ({"ms_today": 86_400_000}, r"milliseconds today \(bytes 200-203\)'.*found 86400000"),
        ({"coordinate_units": 7}, r"coordinate units \(bytes 88-89\)'.*units \[2, 7\]"),
        ({"ping_number": 3}, r"ping 3 port: ping number \(bytes 8-11\)'.*second one at byte"),
    ],
)
def test_bad_fields_name_the_ping(jsf, fields, match):
    path, _ = jsf
    patch_sonar(path, 6, **fields)  # ping 4's port message
    with pytest.raises(SurveyFormatError, match=match) as err:
        read_jsf(path)
    assert "\n" not in str(err.value) and str(err.value).startswith(str(path))


def test_unknown_coordinate_units_on_every_ping(jsf):
    path, _ = jsf
    for k in range(len(sonar_offsets(path))):
        patch_sonar(path, k, coordinate_units=0)
    with pytest.raises(SurveyFormatError, match=r"ping 1 port: coordinate units.*found 0"):
        read_jsf(path)


def test_missing_values_follow_the_validity_flags(jsf, line, origin, caplog):
    path, _ = jsf
    # ping 6: altitude and depth flagged invalid; ping 8: position flagged invalid
    for k in (10, 11):
        patch_sonar(path, k, validity=(1 << 0) | (1 << 3) | (1 << 5) | (1 << 14))
    for k in (14, 15):
        patch_sonar(path, k, validity=(1 << 3) | (1 << 5) | (1 << 6) | (1 << 9) | (1 << 14))
    got = read_jsf(path)
    assert np.isnan(got.altitude_m[5]) and np.isnan(got.depth_m[5])
    assert np.isnan(got.x[7]) and np.isfinite(got.x[[6, 8]]).all()
    with caplog.at_level(logging.WARNING):
        back, stats = read_xtf(path, origin=origin, sensor=SENSOR)
    assert stats["nav_interpolated"] == 1 and stats["depth_interpolated"] == 1
    assert back.altitude_source[5] != 0  # filled from the first bottom return
    assert abs(back.altitude_m[5] - line.altitude_m[5]) < 0.5


def test_files_without_validity_flags_take_non_zero_values(jsf, line, caplog):
    path, _ = jsf
    for k in range(len(sonar_offsets(path))):
        patch_sonar(path, k, validity=0)
    with caplog.at_level(logging.WARNING):
        got = read_jsf(path)
    assert not got.validity_flags and "no ping sets a validity flag" in caplog.text
    assert np.abs(got.altitude_m - line.altitude_m).max() < 1e-3
    assert np.isfinite(got.heading_deg).all() and np.isfinite(got.sound_speed_mps).all()


def test_clashing_time_stamps_and_layback_are_warned(jsf, line, caplog):
    path, wstats = jsf
    off = sonar_offsets(path)[4] + 16  # ping 3's port message
    h = np.frombuffer(path.read_bytes()[off : off + 240], SONAR_HEADER)[0]
    patch_sonar(path, 4, ms_today=int(h["ms_today"]) + 5000, layback_m=12.0)
    with caplog.at_level(logging.WARNING):
        got = read_jsf(path)
    assert "1 pings whose seconds since 1970 (bytes 0-3) and milliseconds today" in caplog.text
    assert "layback up to 12.0 m recorded; positions taken as the sonar's" in caplog.text
    # the seconds since 1970 are kept; the milliseconds of the second still come from 200-203
    assert np.abs(got.time_s - wstats["epoch_s"] - line.time_s).max() <= 0.0005 + 1e-6
    assert got.layback_m[2] == 12.0


def test_time_from_year_and_day_before_protocol_8(jsf, line):
    path, wstats = jsf
    for k in range(len(sonar_offsets(path))):
        patch_sonar(path, k, ping_time_s=0)
    got = read_jsf(path)
    assert np.abs(got.time_s - wstats["epoch_s"] - line.time_s).max() <= 0.0005 + 1e-6


def test_writer_refuses_what_jsf_cannot_hold(tmp_path, line, make_line, origin):
    with pytest.raises(ValueError, match="origin: expected a 'crs'"):
        write_jsf(line, tmp_path / "a.jsf", {"crs": None}, nav_units="latlon")
    from dataclasses import replace

    shifted = replace(line, range_m=line.range_m + 0.1)
    with pytest.raises(ValueError, match="whole number of bins from 0"):
        write_jsf(shifted, tmp_path / "a.jsf", origin)
    close = make_line(ping_period=0.0004)
    with pytest.raises(ValueError, match="at least 1 ms apart"):
        write_jsf(close, tmp_path / "a.jsf", origin)
    assert not (tmp_path / "a.jsf").exists()


# ----------------------------------------------------------------------------- survey import
def test_prepare_survey_from_a_jsf_folder(tmp_path, make_line, origin):
    folder = tmp_path / "jsf"
    for i in range(2):
        write_jsf(make_line(name=f"L{i}", seed=i), folder / f"L{i}.jsf", origin)
    (folder / "notes.txt").write_text("not a sonar file")
    assert [p.name for p in resolve_files(folder)] == ["L0.jsf", "L1.jsf"]
    cfg = {"kind": "xtf", "name": "jsf_survey", "files": str(folder), "n_bins": 64, **SENSOR}
    out = prepare_xtf_survey(cfg, tmp_path / "data")
    survey = Survey.load(out)
    assert [ln.name for ln in survey.lines] == ["L0", "L1"]
    assert all(ln.n_bins == 64 and ln.n_pings == 60 for ln in survey.lines)
    assert survey.origin["crs"] == "EPSG:32633"
    stats = survey.metadata["import_stats"]
    assert stats["L0"]["file_frequency_hz"] == pytest.approx(400e3)
    # unchanged inputs: the folder is reused
    assert prepare_xtf_survey(cfg, tmp_path / "data") == out


def test_real_xtf_line_through_jsf(tmp_path, realdata):
    """The real Iver2 line, imported, written as JSF and imported again: the same line within
    JSF's precision (the lines' intensities are float32: compared to each ping's maximum)."""
    sensor = {"tilt_deg": 20.0, "beam_width_deg": 50.0}
    line, stats = read_xtf(realdata / "scotsman-iver2.xtf", sensor=sensor)
    path = tmp_path / "scotsman.jsf"
    write_jsf(line, path, stats["origin"])
    back, st = read_xtf(path, origin=stats["origin"], sensor=sensor)
    assert back.n_pings == line.n_pings == stats["pings"] and back.n_bins == line.n_bins
    d = np.abs(back.position - line.position)
    assert d[:, :2].max() < 0.1 and d[:, 2].max() <= 0.0005 + 1e-6
    assert np.abs(back.altitude_m - line.altitude_m).max() <= 0.0005 + 1e-6
    top = line.intensity.max(axis=2, keepdims=True)
    assert np.all(np.abs(back.intensity - line.intensity) <= top / 65535 + 1e-6)
    np.testing.assert_allclose(back.range_m, line.range_m, rtol=2e-5)
    assert st["altimeter_minus_first_return_m"] == pytest.approx(
        stats["altimeter_minus_first_return_m"], abs=0.05
    )
