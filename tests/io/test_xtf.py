"""XTF in and out: round trips through pyxtf, projection, resampling and every bad-input case."""

from __future__ import annotations

import logging
import math

import numpy as np
import pytest
import pyxtf
from scipy.integrate import quad

from sss2bathy.geometry import rotation_to_attitude
from sss2bathy.io.xtf import (
    XTFReadOptions,
    read_xtf,
    read_xtf_sensor,
    utm_crs_for,
    write_xtf,
)
from sss2bathy.survey import SurveyFormatError

# WGS 84 ellipsoid (published defining constants) and the UTM scale factor.
WGS84_A, WGS84_F, UTM_K0 = 6378137.0, 1 / 298.257223563, 0.9996


def meridian_arc(lat_deg: float) -> float:
    """Distance (m) along the WGS 84 meridian from the equator, by numerical integration."""
    e2 = WGS84_F * (2 - WGS84_F)

    def dm(phi: float) -> float:
        return WGS84_A * (1 - e2) / (1 - e2 * math.sin(phi) ** 2) ** 1.5

    return quad(dm, 0.0, math.radians(lat_deg), epsabs=1e-7, epsrel=1e-14)[0]


def written(tmp_path, line, origin, name="L0.xtf", **kw):
    path = tmp_path / name
    write_xtf(line, path, origin, **kw)
    return path


# ----------------------------------------------------------------------------- round trips
def test_round_trip_synthetic_line(tmp_path, line, origin):
    path = tmp_path / "L0.xtf"
    wstats = write_xtf(line, path, origin)
    back, stats = read_xtf(path, origin=origin)

    assert back.name == "L0" and back.n_pings == line.n_pings and back.n_bins == line.n_bins
    # Intensities within one uint16 step of the channel's scale (VoltScale / 65535).
    lsb = np.array(wstats["volt_scale"])[None, :, None] / 65535
    assert np.all(np.abs(back.intensity - line.intensity) <= lsb * 0.51 + 1e-7)
    # Positions survive UTM -> lon/lat (file) -> UTM within a millimetre.
    assert np.abs(back.position - line.position).max() < 1e-3
    np.testing.assert_allclose(back.range_m, line.range_m, atol=1e-4)
    np.testing.assert_allclose(back.altitude_m, line.altitude_m, atol=1e-5)
    got_att, want_att = rotation_to_attitude(back.rotation), rotation_to_attitude(line.rotation)
    for got, want in zip(got_att, want_att, strict=True):
        d = np.angle(np.exp(1j * (np.asarray(got) - np.asarray(want))))
        assert np.abs(d).max() < 1e-6  # float32 degrees in the file
    # Times: 10 ms resolution, relative times put after 2000-01-01.
    assert stats["nav_units"] == "latlon" and wstats["epoch_s"] == 946684800.0
    assert np.abs(back.time_s - wstats["epoch_s"] - line.time_s).max() <= 0.005 + 1e-9
    assert back.sensor.tilt_rad == pytest.approx(line.sensor.tilt_rad, abs=1e-6)
    assert back.sensor.beam_width_rad == pytest.approx(line.sensor.beam_width_rad, abs=1e-6)
    assert back.sensor.frequency_hz == pytest.approx(line.sensor.frequency_hz, rel=1e-6)
    assert back.sensor.sound_speed_mps == pytest.approx(1500.0)
    assert stats["altitude_detected"] == 0 and stats["nav_interpolated"] == 0
    assert np.all(back.altitude_source == 0)
    # The detector agrees with the altimeter on these simulated pings (within 2 bins).
    dr = float(line.range_m[1] - line.range_m[0])
    assert np.abs(back.extras["first_return_m"] - line.altitude_m).max() <= 2 * dr


def test_pyxtf_reads_what_we_write(tmp_path, line, origin):
    path = written(tmp_path, line, origin)
    header, packets = pyxtf.xtf_read(str(path))
    pings = packets[pyxtf.XTFHeaderType.sonar]
    assert len(pings) == line.n_pings and header.NavUnits == 3
    assert [int(header.ChanInfo[i].TypeOfChannel) for i in (0, 1)] == [1, 2]
    port = pyxtf.concatenate_channel(pings, header, 0)
    stbd = pyxtf.concatenate_channel(pings, header, 1)
    assert port.dtype == np.uint16 and port.shape == (line.n_pings, line.n_bins)
    # concatenate_channel stacks pings newest first; port is stored outward-to-nadir.
    scale = [header.ChanInfo[i].VoltScale / 65535 for i in (0, 1)]
    np.testing.assert_allclose(port[::-1, ::-1] * scale[0], line.port, atol=scale[0] * 0.51 + 1e-7)
    np.testing.assert_allclose(stbd[::-1] * scale[1], line.starboard, atol=scale[1] * 0.51 + 1e-7)
    lon, lat = pings[0].SensorXcoordinate, pings[0].SensorYcoordinate
    assert 14.0 < lon < 16.0 and 58.0 < lat < 59.0  # UTM 33N, 6500 km north


def test_metres_navigation_round_trip(tmp_path, line):
    origin = {"crs": None, "easting": 300000.0, "northing": 4000000.0}
    path = written(tmp_path, line, origin)
    back, stats = read_xtf(path, origin=origin)
    assert stats["nav_units"] == "metres"
    assert np.abs(back.position - line.position).max() < 1e-6


def test_default_origin_is_utm_zone_of_first_fix(tmp_path, line, origin):
    path = written(tmp_path, line, origin)
    back, stats = read_xtf(path)
    assert stats["origin"]["crs"] == "EPSG:32633"
    assert stats["origin"]["easting"] % 100 == 0 and stats["origin"]["northing"] % 100 == 0
    shift = np.array(
        [
            stats["origin"]["easting"] - origin["easting"],
            stats["origin"]["northing"] - origin["northing"],
            0.0,
        ]
    )
    assert np.abs(back.position + shift - line.position).max() < 1e-3


def test_resampling_to_fewer_bins_averages(tmp_path, line, origin):
    wstats = write_xtf(line, tmp_path / "L0.xtf", origin)
    back, stats = read_xtf(tmp_path / "L0.xtf", n_bins=32, origin=origin)
    assert back.intensity.shape == (line.n_pings, 2, 32) and stats["samples_per_side"] == 128
    coarse = line.intensity.reshape(line.n_pings, 2, 32, 4).mean(axis=-1)
    lsb = max(wstats["volt_scale"]) / 65535
    np.testing.assert_allclose(back.intensity, coarse, atol=0.51 * lsb + 1e-6)
    np.testing.assert_allclose(back.range_m, line.range_m.reshape(32, 4).mean(-1), atol=1e-4)


# ----------------------------------------------------------------------------- projection
@pytest.mark.parametrize(
    ("lon", "lat", "crs", "easting", "northing"),
    [
        (15.0, 0.0, "EPSG:32633", 500000.0, 0.0),  # zone 33 central meridian, equator
        (-123.0, 0.0, "EPSG:32610", 500000.0, 0.0),  # zone 10 central meridian
        (15.0, 45.0, "EPSG:32633", 500000.0, UTM_K0 * meridian_arc(45.0)),
        (27.0, -30.0, "EPSG:32735", 500000.0, 10_000_000.0 - UTM_K0 * meridian_arc(30.0)),
    ],
)
def test_projection_of_reference_points(tmp_path, line, lon, lat, crs, easting, northing):
    # On the central meridian UTM northing is k0 times the meridian arc (false northing
    # 10 000 km south): an independent reference, not pyproj checking itself.
    assert utm_crs_for(lon, lat) == crs
    origin = {"crs": crs, "easting": easting, "northing": northing}
    line.position[:] = line.position - line.position[:1] * [1, 1, 0]  # first fix at the point
    path = written(tmp_path, line, origin)
    header, packets = pyxtf.xtf_read(str(path), types=[pyxtf.XTFHeaderType.sonar])
    first = packets[pyxtf.XTFHeaderType.sonar][0]
    assert first.SensorXcoordinate == pytest.approx(lon, abs=1e-8)  # ~1 mm
    assert first.SensorYcoordinate == pytest.approx(lat, abs=1e-8)


def test_utm_zone_rejects_non_geographic():
    assert utm_crs_for(15.5, 10.0) == "EPSG:32633" and utm_crs_for(180.0, 1.0) == "EPSG:32660"
    with pytest.raises(ValueError, match="lon/lat"):
        utm_crs_for(500000.0, 10.0)


# ----------------------------------------------------------------------------- altitude
def test_missing_altitude_comes_from_the_detector(tmp_path, line, origin):
    line.altitude_m[10:20] = np.nan
    path = written(tmp_path, line, origin)
    back, stats = read_xtf(path, origin=origin)
    true = 9.0 + 2.0 * np.sin(0.25 * line.time_s)
    dr = float(line.range_m[1] - line.range_m[0])
    assert stats["altitude_detected"] == 10
    assert np.all(back.altitude_source[10:20] == 1) and np.all(back.altitude_source[:10] == 0)
    assert np.all(np.isfinite(back.altitude_m))
    assert np.abs(back.altitude_m[10:20] - true[10:20]).max() <= 2 * dr
    np.testing.assert_allclose(back.altitude_m[:10], line.altitude_m[:10], atol=1e-5)


# ----------------------------------------------------------------------------- bad input
def test_truncated_tail_is_skipped_and_counted(tmp_path, line, origin, caplog):
    path = written(tmp_path, line, origin)
    raw = path.read_bytes()
    path.write_bytes(raw[: len(raw) - 300])  # the last ping is cut short
    with caplog.at_level(logging.WARNING):
        back, stats = read_xtf(path, origin=origin)
    assert back.n_pings == line.n_pings - 1 and stats["packets_truncated"] == 1
    assert "truncated" in caplog.text and path.name in caplog.text


def test_truncated_file_header(tmp_path, line, origin):
    path = written(tmp_path, line, origin)
    path.write_bytes(path.read_bytes()[:500])
    with pytest.raises(SurveyFormatError, match=r"L0\.xtf.*file header.*500 bytes"):
        read_xtf(path)


def test_destroyed_magic_is_skipped_by_resynchronising(tmp_path, line, origin, xtf_patch, caplog):
    _, _, offsets = xtf_patch
    path = written(tmp_path, line, origin)
    offs = offsets(path)
    raw = bytearray(path.read_bytes())
    raw[offs[7] : offs[7] + 2] = b"\x00\x00"  # destroy the 0xFACE magic number of ping 7
    path.write_bytes(bytes(raw))
    with caplog.at_level(logging.WARNING):
        back, stats = read_xtf(path, origin=origin)
    assert back.n_pings == line.n_pings - 1 and stats["packets_truncated"] == 0
    np.testing.assert_allclose(back.time_s[7] - back.time_s[6], 0.4, atol=0.006)
    msg = next(r.getMessage() for r in caplog.records if "damaged packets" in r.getMessage())
    assert f"bytes {offs[7]}-{offs[8]} (after sonar ping 6)" in msg and "1 sonar pings lost" in msg


def test_corrupt_sample_count_names_ping(tmp_path, line, origin, xtf_patch):
    _, _, offsets = xtf_patch
    path = written(tmp_path, line, origin)
    # NumSamples of ping 3's first channel header
    off = offsets(path)[3] + 256 + pyxtf.XTFPingChanHeader.NumSamples.offset
    raw = bytearray(path.read_bytes())
    raw[off : off + 4] = (10**6).to_bytes(4, "little")
    path.write_bytes(bytes(raw))
    with pytest.raises(SurveyFormatError, match=r"L0\.xtf.*ping 3"):
        read_xtf(path)


def test_no_sidescan_channels(tmp_path, line, origin, xtf_patch):
    _, patch_header, _ = xtf_patch
    path = written(tmp_path, line, origin)

    def subbottom_only(h):
        h.ChanInfo[0].TypeOfChannel = 0
        h.ChanInfo[1].TypeOfChannel = 0

    patch_header(path, subbottom_only)
    with pytest.raises(SurveyFormatError, match=r"L0\.xtf.*port .* and a starboard"):
        read_xtf(path)


def test_unknown_nav_unit(tmp_path, line, origin, xtf_patch):
    _, patch_header, _ = xtf_patch
    path = written(tmp_path, line, origin)
    patch_header(path, lambda h: setattr(h, "NavUnits", 7))
    with pytest.raises(SurveyFormatError, match=r"L0\.xtf.*NavUnits.*found 7"):
        read_xtf(path)


def test_zero_and_nan_positions_are_interpolated(tmp_path, line, origin, xtf_patch):
    patch, _, _ = xtf_patch
    path = written(tmp_path, line, origin)
    for k in (5, 6, 7):
        patch(
            path,
            k,
            SensorXcoordinate=0.0,
            SensorYcoordinate=0.0,
            ShipXcoordinate=0.0,
            ShipYcoordinate=0.0,
        )
    patch(path, 20, SensorXcoordinate=float("nan"), ShipXcoordinate=float("nan"))
    back, stats = read_xtf(path, origin=origin)
    assert stats["nav_interpolated"] == 4 and back.n_pings == line.n_pings
    assert np.all(np.isfinite(back.position))
    # Linear interpolation over a gently curving track stays within centimetres.
    assert np.abs(back.position - line.position)[:, :2].max() < 0.05


def test_position_from_ship_with_layback(tmp_path, line, origin, xtf_patch):
    patch, _, _ = xtf_patch
    path = written(tmp_path, line, origin)
    header, packets = pyxtf.xtf_read(str(path), types=[pyxtf.XTFHeaderType.sonar])
    p = packets[pyxtf.XTFHeaderType.sonar][9]
    # Ship 30 m ahead of the fish along the heading; fish position left empty.
    from pyproj import Transformer

    fwd = np.radians(p.SensorHeading)
    to_utm = Transformer.from_crs("EPSG:4326", origin["crs"], always_xy=True)
    e, n = to_utm.transform(p.SensorXcoordinate, p.SensorYcoordinate)
    lon, lat = to_utm.transform(e + 30 * np.sin(fwd), n + 30 * np.cos(fwd), direction="INVERSE")
    patch(
        path,
        9,
        SensorXcoordinate=0.0,
        SensorYcoordinate=0.0,
        ShipXcoordinate=lon,
        ShipYcoordinate=lat,
        Layback=30.0,
    )
    back, stats = read_xtf(path, origin=origin)
    assert stats["positions_from_ship"] == 1
    assert np.abs(back.position[9] - line.position[9]).max() < 2e-3


def test_leading_positions_without_fix_are_dropped(tmp_path, line, origin, xtf_patch):
    patch, _, _ = xtf_patch
    path = written(tmp_path, line, origin)
    for k in (0, 1):
        patch(
            path,
            k,
            SensorXcoordinate=0.0,
            SensorYcoordinate=0.0,
            ShipXcoordinate=0.0,
            ShipYcoordinate=0.0,
        )
    back, stats = read_xtf(path, origin=origin)
    assert stats["pings_dropped_nav"] == 2 and back.n_pings == line.n_pings - 2
    np.testing.assert_allclose(back.position, line.position[2:], atol=1e-3)


def test_no_valid_position(tmp_path, line, origin, xtf_patch):
    patch, _, _ = xtf_patch
    path = written(tmp_path, line, origin)
    for k in range(line.n_pings):
        patch(
            path,
            k,
            SensorXcoordinate=0.0,
            SensorYcoordinate=0.0,
            ShipXcoordinate=0.0,
            ShipYcoordinate=0.0,
        )
    with pytest.raises(SurveyFormatError, match=r"L0\.xtf.*position.*none"):
        read_xtf(path)


def test_position_jump_of_kilometres_names_ping(tmp_path, line, origin, xtf_patch):
    patch, _, _ = xtf_patch
    path = written(tmp_path, line, origin)
    header, packets = pyxtf.xtf_read(str(path), types=[pyxtf.XTFHeaderType.sonar])
    pings = packets[pyxtf.XTFHeaderType.sonar]
    for k in range(30, line.n_pings):  # the second half of the line 0.05 deg (~5 km) north
        patch(
            path,
            k,
            SensorYcoordinate=pings[k].SensorYcoordinate + 0.05,
            ShipYcoordinate=pings[k].ShipYcoordinate + 0.05,
        )
    with pytest.raises(SurveyFormatError, match=r"L0\.xtf.*ping 30: position.*jump of \d{4} m"):
        read_xtf(path)


def test_single_fix_spike_is_an_outlier(tmp_path, line, origin, xtf_patch):
    patch, _, _ = xtf_patch
    path = written(tmp_path, line, origin)
    header, packets = pyxtf.xtf_read(str(path), types=[pyxtf.XTFHeaderType.sonar])
    p = packets[pyxtf.XTFHeaderType.sonar][25]
    patch(path, 25, SensorYcoordinate=p.SensorYcoordinate + 0.03)  # one fix 3 km off
    back, stats = read_xtf(path, origin=origin)
    assert stats["nav_outliers"] == 1 and stats["nav_interpolated"] == 1
    assert np.abs(back.position - line.position)[:, :2].max() < 0.05


def test_long_navigation_gap_is_refused(tmp_path, make_line, origin, xtf_patch):
    patch, _, _ = xtf_patch
    line = make_line(n_pings=40, ping_period=1.0, speed=0.5)
    path = written(tmp_path, line, origin)
    for k in range(5, 38):
        patch(
            path,
            k,
            SensorXcoordinate=0.0,
            SensorYcoordinate=0.0,
            ShipXcoordinate=0.0,
            ShipYcoordinate=0.0,
        )
    with pytest.raises(SurveyFormatError, match=r"L0\.xtf.*ping 38: position.*gap of 34\.0 s"):
        read_xtf(path)


def test_non_increasing_time_names_ping(tmp_path, line, origin, xtf_patch):
    patch, _, _ = xtf_patch
    path = written(tmp_path, line, origin)
    header, packets = pyxtf.xtf_read(str(path), types=[pyxtf.XTFHeaderType.sonar])
    p11 = packets[pyxtf.XTFHeaderType.sonar][11]
    patch(path, 12, Second=p11.Second, HSeconds=p11.HSeconds, Minute=p11.Minute)
    with pytest.raises(SurveyFormatError, match=r"L0\.xtf.*ping 12: time.*strictly increasing"):
        read_xtf(path)


def test_invalid_date_names_ping(tmp_path, line, origin, xtf_patch):
    patch, _, _ = xtf_patch
    path = written(tmp_path, line, origin)
    patch(path, 4, Month=13)
    with pytest.raises(SurveyFormatError, match=r"L0\.xtf.*ping 4: time"):
        read_xtf(path)


def test_missing_attitude_names_ping(tmp_path, line, origin, xtf_patch):
    patch, _, _ = xtf_patch
    path = written(tmp_path, line, origin)
    patch(path, 17, SensorRoll=float("nan"))
    with pytest.raises(SurveyFormatError, match=r"L0\.xtf.*ping 17: attitude.*missing"):
        read_xtf(path)
    back, stats = read_xtf(path, origin=origin, missing_attitude="track")
    assert stats["attitude_from_track"] == 1
    h_back = np.degrees(rotation_to_attitude(back.rotation)[0][17])
    h_true = np.degrees(rotation_to_attitude(line.rotation)[0][17])
    assert abs((h_back - h_true + 180) % 360 - 180) < 5.0  # course made good ~ heading


def test_all_zero_attitude_is_missing(tmp_path, line, origin, xtf_patch):
    patch, _, _ = xtf_patch
    path = written(tmp_path, line, origin)  # the line heads ~75 deg: zeros are not a heading
    for k in range(line.n_pings):
        patch(path, k, SensorHeading=0.0, SensorPitch=0.0, SensorRoll=0.0)
    with pytest.raises(SurveyFormatError, match=r"L0\.xtf.*attitude.*all 0 while the track"):
        read_xtf(path)
    back, stats = read_xtf(path, origin=origin, missing_attitude="track")
    assert stats["attitude_from_track"] == line.n_pings


def test_north_heading_line_with_zero_attitude_is_accepted(tmp_path, make_line, origin):
    from sss2bathy.geometry import attitude_to_rotation

    line = make_line(heading_deg=0.0)
    line.rotation = attitude_to_rotation(
        np.zeros(line.n_pings), np.zeros(line.n_pings), np.zeros(line.n_pings)
    )
    path = written(tmp_path, line, origin)
    back, stats = read_xtf(path, origin=origin)
    np.testing.assert_allclose(back.rotation, line.rotation, atol=1e-7)


def test_pings_missing_a_channel_are_skipped(tmp_path, line, origin, xtf_patch):
    _, _, offsets = xtf_patch
    path = written(tmp_path, line, origin)
    off = offsets(path)[8] + 256 + 64 + 2 * line.n_bins  # ping 8's second channel header
    raw = bytearray(path.read_bytes())
    raw[off : off + 2] = (5).to_bytes(2, "little")  # ChannelNumber 5: not a sidescan channel
    path.write_bytes(bytes(raw))
    back, stats = read_xtf(path, origin=origin)
    assert stats["pings_missing_channel"] == 1 and back.n_pings == line.n_pings - 1


def test_sensor_from_file_and_overrides(tmp_path, line, origin, xtf_patch):
    _, patch_header, _ = xtf_patch
    path = written(tmp_path, line, origin)
    assert read_xtf_sensor(path)["tilt_deg"] == pytest.approx(20.0)
    back, _ = read_xtf(path, origin=origin, sensor={"tilt_deg": 12.0, "beam_width_deg": None})
    assert back.sensor.tilt_rad == pytest.approx(math.radians(12.0))
    assert back.sensor.beam_width_rad == pytest.approx(math.radians(50.0), abs=1e-6)

    def no_tilt(h):
        h.ChanInfo[0].TiltAngle = 0.0
        h.ChanInfo[1].TiltAngle = 0.0

    patch_header(path, no_tilt)
    with pytest.raises(SurveyFormatError, match=r"L0\.xtf.*tilt_deg.*data\.survey\.tilt_deg"):
        read_xtf(path)
    with pytest.raises(ValueError, match="sensor: expected keys"):
        read_xtf(path, sensor={"tilt": 3.0})


def test_bad_arguments(tmp_path, line, origin):
    path = written(tmp_path, line, origin)
    with pytest.raises(ValueError, match="n_bins"):
        read_xtf(path, n_bins=1)
    with pytest.raises(ValueError, match="missing_attitude"):
        read_xtf(path, missing_attitude="guess")
    with pytest.raises(SurveyFormatError, match="missing file"):
        read_xtf(tmp_path / "nope.xtf")


@pytest.mark.parametrize(
    ("key", "value", "expected"),
    [
        ("n_bins", 1.5, "None or an integer >= 2"),
        ("channel_pair", -1, "an integer >= 0"),
        ("port_far_first", "yes", "true or false"),
        ("max_jump_m", 0.0, "a number > 0"),
        ("max_speed_mps", float("inf"), "a finite number"),
        ("max_nav_gap_s", float("nan"), "a finite number"),
        ("min_first_return_m", -1.0, "a number >= 0"),
        ("blanking_m", -0.5, "a number >= 0"),
        ("altitude_tolerance_m", 0.0, "a number > 0"),
        ("altitude_offset", "shift", "one of ['record', 'apply']"),
        ("nav_units", "feet", "one of ['file', 'latlon', 'metres']"),
    ],
)
def test_read_options_refuse_a_bad_setting_naming_it(key, value, expected):
    """Every setting of read_xtf is checked once, in XTFReadOptions, before any file is
    opened: one line naming it, what it expects and what it found."""
    with pytest.raises(ValueError, match=rf"^{key}: expected ") as err:
        XTFReadOptions(**{key: value})
    assert expected in str(err.value)
    # the default passes its own check
    assert XTFReadOptions(**{key: getattr(XTFReadOptions, key)}) == XTFReadOptions()


def test_writer_refuses_what_xtf_cannot_hold(tmp_path, line, origin):
    line.range_m = np.sqrt(line.range_m * line.range_m[-1])  # non-uniform bins
    with pytest.raises(ValueError, match="range_m.*uniformly spaced"):
        write_xtf(line, tmp_path / "a.xtf", origin)


def test_writer_rejects_pings_closer_than_10ms(tmp_path, make_line, origin):
    line = make_line(ping_period=0.004)
    with pytest.raises(ValueError, match="10 ms"):
        write_xtf(line, tmp_path / "a.xtf", origin)


def test_writer_clips_negative_intensity_and_geographic_needs_crs(tmp_path, line):
    line.intensity[0, 0, :5] = -1.0
    stats = write_xtf(line, tmp_path / "a.xtf", {"crs": None})
    assert stats["clipped_samples"] == 5 and stats["nav_units"] == "metres"
    with pytest.raises(ValueError, match="origin.*crs"):
        write_xtf(line, tmp_path / "b.xtf", {"crs": None}, nav_units="latlon")


def test_no_usable_sidescan_is_refused(tmp_path, line, origin):
    line.intensity[:] = 0.01  # no contrast anywhere: every ping constant
    path = written(tmp_path, line, origin)
    with pytest.raises(SurveyFormatError, match=r"L0\.xtf.*sidescan samples.*constant"):
        read_xtf(path, origin=origin)


def test_dead_pings_are_no_hit_and_their_missing_altitude_stays_nan(tmp_path, line, origin, caplog):
    line.intensity[5:8] = 0.01  # three dead pings (both sides constant)
    line.intensity[20, 1, 10:] = line.intensity.max()  # starboard saturated on one ping
    line.altitude_m[5:7] = np.nan
    path = written(tmp_path, line, origin)
    with caplog.at_level(logging.WARNING):
        back, stats = read_xtf(path, origin=origin)
    assert np.isnan(back.intensity[5:8]).all() and np.isnan(back.intensity[20, 1]).all()
    assert np.isfinite(back.intensity[20, 0]).all()
    assert stats["pings_constant"] == 3 and stats["pings_saturated"] == 1
    assert np.isnan(back.altitude_m[5:7]).all() and np.all(back.altitude_source[5:7] == 3)
    assert back.altitude_m[7] == pytest.approx(line.altitude_m[7], abs=1e-5)
    assert stats["altitude_missing"] == 2
    warning = [
        r.getMessage()
        for r in caplog.records
        if r.levelno == logging.WARNING and "altitude/sample repairs" in r.getMessage()
    ]
    assert len(warning) == 1 and "L0.xtf" in warning[0]
    assert "2 left missing" in warning[0] and "3 pings masked as no-hit (constant)" in warning[0]


def ringdown_line(make_line, make_pings, seed=0):
    """An AUV-like line: 512 bins over 40 m, altitude 3.8-6.8 m, a saturated 1.5 m ring-down."""
    ln = make_line(n_pings=80, n_bins=512, seed=seed)
    truth = 5.3 + 1.5 * np.sin(0.4 * ln.time_s)
    ln.altitude_m = truth.astype(np.float32)
    ln.intensity = make_pings(truth, ln.range_m.astype(np.float64), seed=seed)
    ring = 10.0 * np.exp(-ln.range_m / 0.25)
    ln.intensity = np.minimum(ln.intensity + ring[None, None, :], 8.0).astype(np.float32)
    return ln, truth


@pytest.mark.parametrize("seed", [0, 1])
def test_zero_and_nan_altitude_repaired_within_20cm_despite_ringdown(
    tmp_path, make_line, make_pings, origin, xtf_patch, seed, caplog
):
    ln, truth = ringdown_line(make_line, make_pings, seed)
    ln.altitude_m[10:30] = np.nan  # written as 0 (missing)
    path = written(tmp_path, ln, origin)
    patch_ping, _, _ = xtf_patch
    for k in range(40, 50):
        patch_ping(path, k, SensorPrimaryAltitude=float("nan"))
    with caplog.at_level(logging.WARNING):
        back, stats = read_xtf(path, origin=origin)
    repaired = np.r_[10:30, 40:50]
    assert np.all(back.altitude_source[repaired] == 1)
    assert np.abs(back.altitude_m[repaired] - truth[repaired]).max() <= 0.2
    assert np.all(back.altitude_m > 0)
    assert 1.0 <= stats["blanking_m"] <= 2.5 and stats["altitude_detected"] == 30
    assert stats["altimeter_vs_first_return_abs_m"] <= 0.1
    assert "30 filled from the detector" in caplog.text and "median |error|" in caplog.text


def test_altimeter_with_a_constant_3m_offset_is_kept_or_shifted(
    tmp_path, make_line, make_pings, origin
):
    ln, truth = ringdown_line(make_line, make_pings)
    ln.altitude_m = (truth + 3.0).astype(np.float32)  # altimeter 3 m longer on every ping
    path = written(tmp_path, ln, origin)
    back, stats = read_xtf(path, origin=origin)  # one offset explains it: recorded, kept
    assert stats["altimeter_minus_first_return_m"] == pytest.approx(3.0, abs=0.1)
    assert stats["altitude_offset_model"] == "offset" and np.all(back.altitude_source == 0)
    np.testing.assert_allclose(back.altitude_m, ln.altitude_m, atol=1e-5)
    shifted, stats = read_xtf(path, origin=origin, altitude_offset="apply")
    assert stats["altitude_offset_applied_m"] == pytest.approx(-3.0, abs=0.1)
    assert np.abs(shifted.altitude_m - truth).max() <= 0.15


def test_attitude_packets_replace_missing_ping_attitude(tmp_path, line, origin, xtf_patch):
    patch, _, _ = xtf_patch
    path = written(tmp_path, line, origin)
    heading, pitch, roll = (np.degrees(a) for a in rotation_to_attitude(line.rotation))
    for k in range(line.n_pings):  # the ping headers lose their attitude ...
        patch(
            path, k, SensorHeading=float("nan"), SensorPitch=float("nan"), SensorRoll=float("nan")
        )
    # ... and separate attitude packets (type 3) carry it, at the ping times +- 50 ms.
    packets = []
    times = 946684800.0 + line.time_s
    for k, t0 in enumerate(times):
        for dt in (-0.05, 0.05):
            a = pyxtf.XTFAttitudeData()
            a.NumBytesThisRecord = 64
            sec = math.floor(t0 + dt)
            a.SourceEpoch, a.EpochMicroseconds = sec, round((t0 + dt - sec) * 1e6)
            # The same value on both sides of a ping: the interpolation lands on it.
            a.Heading, a.Pitch, a.Roll = heading[k], pitch[k], roll[k]
            packets.append(bytes(a))
    with open(path, "ab") as f:
        f.write(b"".join(packets))
    back, stats = read_xtf(path, origin=origin)
    assert stats["attitude_source"] == "attitude_packets" and back.n_pings == line.n_pings
    np.testing.assert_allclose(back.rotation, line.rotation, atol=2e-5)


def test_transducer_offsets_are_a_lever_arm(tmp_path, line, origin, xtf_patch):
    _, patch_header, _ = xtf_patch
    path = written(tmp_path, line, origin)

    def offsets(h):  # transducers 1.5 m forward, 0.4 m to starboard, 0.2 m down
        for i in (0, 1):
            h.ChanInfo[i].OffsetY, h.ChanInfo[i].OffsetX, h.ChanInfo[i].OffsetZ = 1.5, 0.4, 0.2

    patch_header(path, offsets)
    back, _ = read_xtf(path, origin=origin)
    lever = line.rotation @ np.array([1.5, -0.4, -0.2])  # FLU
    np.testing.assert_allclose(back.position - line.position, lever, atol=1e-3)
