"""XTF (eXtended Triton Format) sidescan in and out, through pyxtf's ctypes structures.

Reading walks the packets itself (so a bad packet can be named by its ping index and a
truncated tail can be skipped) and parses each packet with pyxtf's own classes
(``XTFFileHeader``, ``XTFPingHeader``, ``XTFAttitudeData``). Writing builds the same
structures and serialises them with their ``to_bytes``; ``pyxtf.xtf_read`` reads the result.

The import (:func:`read_xtf`, its settings one :class:`XTFReadOptions`) runs as named stages,
each a function whose docstring says what it checks (refuses) and what it may repair (a
WARNING): packets -> pings (:mod:`sss2bathy.io.xtf_packets`), sensor, channels and samples,
navigation and attitude (:mod:`sss2bathy.io.xtf_nav`), waterfall and no-hit pings, altitude
from the altimeter cross-checked against the first bottom return
(:mod:`sss2bathy.io.xtf_altitude`), then the :class:`SidescanLine` and its stats.

Memory: the parsed pings keep where their samples lie in the file, not the samples; those
are read and resampled a few MB at a time into the float32 waterfall, and the parser hands
back the pages of the file it has mapped as it goes. A line of any size imports in memory
that grows with its pings x ``n_bins`` (the waterfall returned), not with the file.

Fields read, per sonar ping (``XTFPingHeader``, header type 0):

* time: ``Year Month Day Hour Minute Second HSeconds`` (UTC, 10 ms resolution);
* position: ``SensorXcoordinate`` / ``SensorYcoordinate`` (longitude / latitude when the file
  header's ``NavUnits`` is 3, easting / northing in metres when it is 0; any other unit is
  refused). Where the sensor position is empty, ``ShipX/Ycoordinate`` moved back by
  ``Layback`` along the heading;
* ``SensorDepth`` (m, down) -> z = -depth; ``SensorPrimaryAltitude`` (m; 0 = missing);
* attitude: ``SensorHeading`` / ``SensorPitch`` / ``SensorRoll`` (degrees; heading clockwise
  from North, pitch bow up, roll starboard down), or the attitude packets (type 3)
  interpolated to the ping times when the file has them;
* ``SoundVelocity`` (m/s; Isis writes half the sound speed, e.g. 750: values below
  1000 m/s are doubled);
* per channel (``XTFPingChanHeader``): ``SlantRange`` (m, far end of the recording),
  ``TimeDelay`` (s, start of the recording), ``TimeDuration``, ``NumSamples``, ``Weight``
  (samples are multiplied by 2^-Weight) and the samples. Integer samples are scaled by
  ``ChanInfo.VoltScale / max code`` when VoltScale is set.
* file header ``ChanInfo``: channel types (1 port, 2 starboard), ``TiltAngle``,
  ``BeamWidth`` (degrees), ``Frequency`` (kHz), ``OffsetX/Y/Z`` (m; starboard, forward,
  down) of the transducers (the mean of the port and starboard offsets is applied as a lever
  arm through the attitude).

Sample order: pyxtf (``concatenate_channel`` pads port pings on the left, and its examples
show ``hstack(port, starboard)`` as a waterfall) stores the port channel outward-to-nadir
(first sample farthest) and starboard nadir-outward. The reader flips port so that bin 0 is
nearest the sonar on both sides; ``port_far_first=False`` reads files that store port in
time order.
"""

from __future__ import annotations

import ctypes
import datetime as _dt
import logging
import math
from collections.abc import Mapping
from dataclasses import dataclass, fields
from pathlib import Path
from typing import Any

import numpy as np
from pyxtf import XTFChannelType, XTFFileHeader, XTFPingChanHeader, XTFPingHeader

from sss2bathy.geometry import rotation_to_attitude
from sss2bathy.io.bottom import bad_pings
from sss2bathy.io.jsf import read_jsf_sensor
from sss2bathy.io.xtf_altitude import altitude_from_sonar, report_beam
from sss2bathy.io.xtf_checks import beam_vs_data
from sss2bathy.io.xtf_nav import (
    NAV_UNITS_LATLON,
    NAV_UNITS_METRES,
    Navigation,
    attitude_from_packets,
    frame_origin,
    navigate,
    orient,
    ping_times,
    transformer,
    utm_crs_for,
)
from sss2bathy.io.xtf_packets import (
    FILE_HEADER_BYTES,
    MAGIC,
    Channel,
    ParsedFile,
    parse_packets,
    ping_channel,
    resample_side,
    sidescan_channels,
)
from sss2bathy.survey import SensorParams, SidescanLine, SurveyFormatError
from sss2bathy.survey.model import (
    ALTITUDE_DETECTED,
    ALTITUDE_INTERPOLATED,
    ALTITUDE_MISSING,
)
from sss2bathy.utils.atomic import atomic_path
from sss2bathy.utils.checks import (
    SETTING,
    check_number,
    require,
    require_bool,
    require_choice,
    setting,
)

log = logging.getLogger(__name__)

__all__ = [
    "ALTITUDE_OFFSET",
    "MISSING_ATTITUDE",
    "NAV_UNITS",
    "NAV_UNITS_LATLON",
    "NAV_UNITS_METRES",
    "read_xtf",
    "read_xtf_sensor",
    "utm_crs_for",
    "write_xtf",
]

SAMPLE_FORMAT_UINT16 = 3
# Times written before this epoch (2000-01-01T00:00:00Z) are taken as relative to it.
DEFAULT_EPOCH_S = 946684800.0
SENSOR_KEYS = ("tilt_deg", "beam_width_deg", "frequency_hz", "sound_speed_mps")
# pings without attitude: refuse them, or take the heading from the track (pitch = roll = 0)
MISSING_ATTITUDE = ("error", "track")
# the altimeter - first return offset: stored in the stats, or applied to the altimeter
ALTITUDE_OFFSET = ("record", "apply")
# the unit of the navigation: the file header's NavUnits, or an override
NAV_UNITS = ("file", "latlon", "metres")


# ----------------------------------------------------------------------------- sensor
def read_xtf_sensor(path: str | Path, channel_pair: int = 0) -> dict[str, float | None]:
    """Sensor parameters stated in an XTF file header (``None`` where the file leaves them 0).

    Returns ``{"tilt_deg", "beam_width_deg", "frequency_hz"}`` from the port channel's
    ``ChanInfo`` (starboard where port leaves a value 0).
    """
    path = Path(path)
    if not path.is_file():
        raise SurveyFormatError(path, "file", "an existing XTF file", "missing file")
    if path.suffix.lower() == ".jsf":
        return read_jsf_sensor(path, channel_pair)
    with open(path, "rb") as f:
        raw = f.read(FILE_HEADER_BYTES)
    if len(raw) < FILE_HEADER_BYTES:
        raise SurveyFormatError(path, "file header", f"{FILE_HEADER_BYTES} bytes", len(raw))
    header = XTFFileHeader.create_from_buffer(raw)
    port, stbd = sidescan_channels(header, path, channel_pair)
    out: dict[str, float | None] = {}
    for key, field, factor in (
        ("tilt_deg", "TiltAngle", 1.0),
        ("beam_width_deg", "BeamWidth", 1.0),
        ("frequency_hz", "Frequency", 1e3),
    ):
        vals = [float(getattr(header.ChanInfo[i], field)) for i in (port, stbd)]
        good = [v for v in vals if math.isfinite(v) and v > 0]
        out[key] = good[0] * factor if good else None
    return out


def _resolve_sensor(
    path: Path,
    file_sensor: Mapping[str, float | None],
    overrides: Mapping[str, float | None],
    file_sound_speed: float | None,
) -> SensorParams:
    """The line's :class:`SensorParams`: each of :data:`SENSOR_KEYS` from ``overrides``
    where not None, else from the file. Checks: every value present in one of them and
    plausible (:class:`SensorParams`'s own checks, naming the file). Repairs nothing."""
    values: dict[str, float] = {}
    merged = dict(file_sensor, sound_speed_mps=file_sound_speed)
    for key in SENSOR_KEYS:
        v = overrides.get(key)
        if v is None:
            v = merged.get(key)
        if v is None:
            raise SurveyFormatError(
                path,
                key,
                f"a value in the file or in the config (set data.survey.{key})",
                "missing in both",
            )
        values[key] = float(v)
    try:
        return SensorParams(
            tilt_rad=math.radians(values["tilt_deg"]),
            beam_width_rad=math.radians(values["beam_width_deg"]),
            frequency_hz=values["frequency_hz"],
            sound_speed_mps=values["sound_speed_mps"],
        )
    except SurveyFormatError as err:
        raise SurveyFormatError(path, err.field, err.expected, err.found) from None


def _file_sound_speed(pings: list[XTFPingHeader]) -> tuple[np.ndarray, float | None]:
    """``(per-ping sound speed (NaN where implausible), their median or None)``. Repairs
    (silently, a unit convention, not damage): Isis's half (one-way) speeds below 1000 m/s are
    doubled; values outside 1300..1800 m/s are not used. Pure."""
    sv = np.array([p.SoundVelocity for p in pings], dtype=np.float64)
    sv = np.where((sv > 0) & (sv < 1000.0), 2.0 * sv, sv)  # Isis: one-way (half) speed
    ok = np.isfinite(sv) & (sv >= 1300.0) & (sv <= 1800.0)
    return np.where(ok, sv, np.nan), (float(np.median(sv[ok])) if ok.any() else None)


# ----------------------------------------------------------------------------- options
@dataclass(frozen=True)
class XTFReadOptions:
    """Every setting of :func:`read_xtf` (its Args say what each does), with its default and
    bounds declared once (:func:`~sss2bathy.utils.checks.setting`) and checked when the
    options are made (``ValueError``: ``<name>: expected ..., found ...``)."""

    n_bins: int | None = setting(None, kind="integer", ge=2, optional=True)
    origin: Mapping[str, Any] | None = None
    crs: str | None = None
    sensor: Mapping[str, float | None] | None = None
    name: str | None = None
    channel_pair: int = setting(0, kind="integer", ge=0)
    port_far_first: bool = setting(True, kind="boolean")
    max_jump_m: float = setting(200.0, gt=0)
    max_speed_mps: float = setting(10.0, gt=0)
    max_nav_gap_s: float = setting(30.0, gt=0)
    missing_attitude: str = setting("error", kind="choice", choices=MISSING_ATTITUDE)
    min_first_return_m: float = setting(0.0, ge=0)
    blanking_m: float = setting(0.0, ge=0)
    auto_blanking: bool = setting(True, kind="boolean")
    altitude_tolerance_m: float | None = setting(1.0, kind="optional_number", gt=0)
    altitude_offset: str = setting("record", kind="choice", choices=ALTITUDE_OFFSET)
    nav_units: str = setting("file", kind="choice", choices=NAV_UNITS)

    def __post_init__(self) -> None:
        for f in fields(self):
            spec = f.metadata.get(SETTING)
            if spec is not None:
                _check_setting(f.name, getattr(self, f.name), spec)
        unknown = set(self.sensor or {}) - set(SENSOR_KEYS)
        if unknown:
            raise ValueError(f"sensor: expected keys among {SENSOR_KEYS}, found {sorted(unknown)}")


def _check_setting(name: str, value: Any, spec: Mapping[str, Any]) -> None:
    """``value`` checked against its :func:`~sss2bathy.utils.checks.setting` (the checks of
    :mod:`sss2bathy.utils.checks`; integers may be numpy integers)."""
    kind = spec["kind"]
    if kind == "integer":
        ge = spec["ge"]
        integer = isinstance(value, int | np.integer) and not isinstance(value, bool)
        expected = f"an integer >= {ge}"
        if spec.get("optional"):
            if value is None:
                return
            expected = f"None or {expected}"
        require(name, value, integer and value >= ge, expected)
    elif kind == "boolean":
        require_bool(name, value)
    elif kind == "choice":
        require_choice(name, value, spec["choices"])
    elif kind == "optional_number":
        if value is not None:
            check_number(name, value, **{k: v for k, v in spec.items() if k in _BOUNDS})
    else:
        check_number(name, value, **{k: v for k, v in spec.items() if k in _BOUNDS})


_BOUNDS = ("gt", "ge", "lt", "le")
_D = XTFReadOptions  # the defaults of read_xtf's keywords (class attributes of the fields)


# ----------------------------------------------------------------------------- reader
def read_xtf(
    path: str | Path,
    n_bins: int | None = _D.n_bins,
    *,
    origin: Mapping[str, Any] | None = None,
    crs: str | None = None,
    sensor: Mapping[str, float | None] | None = None,
    name: str | None = None,
    channel_pair: int = _D.channel_pair,
    port_far_first: bool = _D.port_far_first,
    max_jump_m: float = _D.max_jump_m,
    max_speed_mps: float = _D.max_speed_mps,
    max_nav_gap_s: float = _D.max_nav_gap_s,
    missing_attitude: str = _D.missing_attitude,
    min_first_return_m: float = _D.min_first_return_m,
    blanking_m: float = _D.blanking_m,
    auto_blanking: bool = _D.auto_blanking,
    altitude_tolerance_m: float | None = _D.altitude_tolerance_m,
    altitude_offset: str = _D.altitude_offset,
    nav_units: str = _D.nav_units,
) -> tuple[SidescanLine, dict[str, Any]]:
    """Read one XTF file into a :class:`SidescanLine` in the survey's local ENU frame.

    Args:
        path: the ``.xtf`` file.
        n_bins: bins per side of the returned waterfall (area-weighted resampling of the
            recorded samples over the line's common slant-range window); ``None`` keeps the
            recorded sample count.
        origin: ``{"crs", "easting", "northing"}`` of the survey frame; positions are projected
            to ``origin["crs"]`` and shifted by (easting, northing). ``None``: the CRS is ``crs``
            (or, for geographic navigation, the UTM zone of the first valid position) and the
            origin is the first valid position rounded to 100 m (returned in ``stats``).
        crs: CRS of the survey frame when ``origin`` is not given. For files in metres
            (``NavUnits`` 0) also the CRS their coordinates are in (default: the origin's);
            they are transformed when it differs from the origin's CRS.
        sensor: ``{tilt_deg, beam_width_deg, frequency_hz, sound_speed_mps}``; a value that is
            not ``None`` overrides the file, ``None`` or a missing key takes the file's value
            (channel info; sound speed = median of the pings' sound velocity).
        name: line name (default: the file stem).
        channel_pair: which port/starboard pair to read (0 = the first of each type).
        port_far_first: the file stores port samples outward-to-nadir (the XTF convention).
        max_jump_m, max_speed_mps: a fix farther than ``max_jump_m`` from the running median
            of its neighbours is an outlier (interpolated, counted); a remaining step between
            consecutive fixes longer than ``max_jump_m + max_speed_mps * dt`` is refused.
        max_nav_gap_s: longest navigation gap interpolated; longer gaps are refused.
        missing_attitude: ``"error"`` refuses pings without attitude (non-finite values, or no
            attitude at all: heading, pitch and roll all exactly 0 on every ping);
            ``"track"`` takes the heading from the course made good and zero pitch and roll.
        min_first_return_m: the bottom detector ignores returns nearer than this.
        blanking_m, auto_blanking: the transducer ring-down zone the detector never searches,
            and whether to also estimate it from the near-field decay
            (:func:`sss2bathy.io.bottom.detect_first_return`).
        altitude_tolerance_m: refuse the file when the disagreement between the altimeter and
            the first bottom return is not one offset (or the beam-edge scale): its spread or
            drift over the line exceeds this (m) (:func:`~sss2bathy.io.xtf_checks.check_altimeter`;
            ``None``: no refusal). Also the least jump (m) of an altimeter value rejected as
            implausible.
        altitude_offset: ``"record"`` keeps the altimeter and stores the offset (median of
            altimeter - first return) in ``stats``; ``"apply"`` shifts the altimeter by it
            onto the sonar's first return (a lever arm between altimeter and transducers).
        nav_units: ``"file"`` (the header's ``NavUnits``), ``"latlon"`` or ``"metres"`` (the
            header is wrong). Coordinates that do not look like the unit used are refused.

    Pings whose samples on a side are constant, saturated or NaN get NaN intensities there
    (no-hit). Where the altimeter is 0/NaN, beyond the slant range or an implausible jump
    (:func:`~sss2bathy.io.xtf_checks.implausible_altitude`) the altitude comes from the first
    bottom return calibrated to the nearby altimeter (or short-gap interpolation between
    returns), else stays NaN; ``line.altitude_source`` records which, and one WARNING per file
    counts every repair with its cross-validated accuracy. Every repair that changes data is a
    WARNING; so are a sonar setting the data contradict (:func:`~sss2bathy.io.xtf_checks.
    beam_vs_data`) and resampling to ``n_bins``.

    The keywords are the fields of :class:`XTFReadOptions` (defaults and bounds declared
    there); :func:`read_xtf_with` takes them as one and runs the import's stages.

    Returns:
        ``(line, stats)``: ``stats`` holds the origin, CRS, counts of everything interpolated,
        detected or skipped, and the recorded sample geometry.

    Raises:
        SurveyFormatError: one line naming the file (and the ping where there is one).
        ValueError: on bad arguments.
    """
    options = XTFReadOptions(
        n_bins=n_bins,
        origin=origin,
        crs=crs,
        sensor=sensor,
        name=name,
        channel_pair=channel_pair,
        port_far_first=port_far_first,
        max_jump_m=max_jump_m,
        max_speed_mps=max_speed_mps,
        max_nav_gap_s=max_nav_gap_s,
        missing_attitude=missing_attitude,
        min_first_return_m=min_first_return_m,
        blanking_m=blanking_m,
        auto_blanking=auto_blanking,
        altitude_tolerance_m=altitude_tolerance_m,
        altitude_offset=altitude_offset,
        nav_units=nav_units,
    )
    return read_xtf_with(path, options)


def read_xtf_with(path: str | Path, o: XTFReadOptions) -> tuple[SidescanLine, dict[str, Any]]:
    """:func:`read_xtf` with its settings as one :class:`XTFReadOptions`: the import's stages
    in order, each checking (refusing) and repairing (a WARNING) what its docstring says."""
    path = Path(path)
    if not path.is_file():
        raise SurveyFormatError(path, "file", "an existing XTF file", "missing file")

    # 1. packets -> pings and attitude packets (damaged / truncated packets skipped)
    parsed = parse_packets(path, o.channel_pair)
    port_no, stbd_no = sidescan_channels(parsed.header, path, o.channel_pair)
    if not parsed.pings:
        raise SurveyFormatError(path, "sonar pings", "at least 2 sonar pings (type 0)", 0)
    nav_units_code = _nav_units_code(path, parsed.header, o.nav_units)

    # 2. sensor: the config's values over the file's
    sv_ping, sv_file = _file_sound_speed(parsed.pings)
    file_sensor = read_xtf_sensor(path, o.channel_pair)
    sensor_params = _resolve_sensor(path, file_sensor, dict(o.sensor or {}), sv_file)

    # 3. channels and samples of each ping (pings lacking a side skipped)
    c_default = sv_file if sv_file is not None else sensor_params.sound_speed_mps
    keep, ports, stbds = _ping_channels(
        path, parsed, (port_no, stbd_no), sv_ping, c_default, o.port_far_first
    )
    pings = [parsed.pings[k] for k in keep]
    ping_ids = np.asarray(keep)
    t = ping_times(path, pings, ping_ids)

    def field(name_: str) -> np.ndarray:
        return np.array([getattr(p, name_) for p in pings], dtype=np.float64)

    # 4. navigation (checked, repaired) and attitude
    heading, pitch, roll, attitude_source = attitude_from_packets(
        parsed.attitude, t, field("SensorHeading"), field("SensorPitch"), field("SensorRoll")
    )
    nav = navigate(
        path,
        t,
        ping_ids,
        field,
        heading,
        nav_units_code,
        o.nav_units,
        o.crs,
        o.origin,
        o.max_jump_m,
        o.max_speed_mps,
        o.max_nav_gap_s,
    )
    sl = nav.keep
    t, ping_ids, altimeter = t[sl], ping_ids[sl], field("SensorPrimaryAltitude")[sl]
    ports, stbds = ports[sl], stbds[sl]
    R, track_heading_pings = orient(
        path,
        t,
        nav.xy,
        (heading[sl], pitch[sl], roll[sl]),
        attitude_source,
        o.missing_attitude,
        ping_ids,
    )
    origin_ = frame_origin(o.origin, nav.frame_crs, nav.xy)
    position = _position(nav, origin_, R, _lever_arm(parsed.header, (port_no, stbd_no)))

    # 5. waterfall on a common slant-range window; unusable pings -> no-hit (NaN)
    wf = _waterfall(path, ports, stbds, o.n_bins)
    ping_flags = _mask_no_hit(path, wf.intensity)

    # 6. altitude: altimeter cross-checked against the first bottom return, repaired from it
    picks, alt = altitude_from_sonar(
        path,
        wf.intensity,
        wf.range_m,
        wf.r1,
        altimeter,
        t,
        sensor_params,
        ping_flags,
        min_first_return_m=o.min_first_return_m,
        blanking_m=o.blanking_m,
        auto_blanking=o.auto_blanking,
        tolerance_m=o.altitude_tolerance_m,
        offset_mode=o.altitude_offset,
    )
    sonar_vs_data = beam_vs_data(
        wf.intensity,
        wf.range_m,
        alt.altitude,
        R,
        sensor_params.beam_limits_rad,
        blanking_m=picks.blanking_m,
    )
    report_beam(path, sonar_vs_data, sensor_params, wf.r1)

    # 7. the line and what the import did
    line = SidescanLine(
        name=o.name or path.stem,
        time_s=t,
        position=position,
        rotation=R,
        altitude_m=alt.altitude,
        intensity=wf.intensity,
        range_m=wf.range_m,
        sensor=sensor_params,
        extras={"first_return_m": picks.altitude_m.astype(np.float32)},
        altitude_source=alt.source,
    )
    source, chk = alt.source, alt.check
    stats: dict[str, Any] = {
        "file": str(path),
        "origin": origin_,
        "crs": origin_["crs"],
        "nav_units": "latlon" if nav_units_code == NAV_UNITS_LATLON else "metres",
        "pings_in_file": len(parsed.pings),
        "pings": line.n_pings,
        "pings_missing_channel": len(parsed.pings) - len(keep),
        "pings_dropped_nav": nav.dropped,
        "packets_truncated": parsed.truncated,
        "other_packets": dict(parsed.other_packets),
        "nav_interpolated": nav.interpolated,
        "nav_outliers": nav.outliers,
        "positions_from_ship": nav.from_ship,
        "depth_interpolated": nav.depth_interpolated,
        "attitude_source": attitude_source,
        "attitude_from_track": track_heading_pings,
        "altitude_detected": int((source == ALTITUDE_DETECTED).sum()),
        "altitude_interpolated": int((source == ALTITUDE_INTERPOLATED).sum()),
        "altitude_missing": int((source == ALTITUDE_MISSING).sum()),
        "first_return_rejected": int(picks.rejected.sum()),
        "blanking_m": picks.blanking_m,
        "pings_constant": ping_flags["constant"],
        "pings_saturated": ping_flags["saturated"],
        "pings_nonfinite": ping_flags["nonfinite"],
        "altimeter_rejected_beyond_range": alt.beyond_range,
        "altimeter_rejected_jumps": alt.jumps,
        # altimeter - first return over the pings having both (the offset later stages read)
        "altimeter_minus_first_return_m": None if chk is None else chk.offset_m,
        "altimeter_vs_first_return_abs_m": alt.abs_diff_m,
        "altitude_offset_sigma_m": None if chk is None else chk.sigma_m,
        "altitude_offset_drift_m": None if chk is None else chk.drift_m,
        "altitude_offset_drift_per_100_pings_m": None if chk is None else chk.drift_per_100_m,
        "altitude_offset_pings": 0 if chk is None else chk.n,
        "altitude_offset_model": None if chk is None else chk.model,
        "first_return_scale": None if chk is None else chk.scale,
        "first_return_intercept_m": None if chk is None else chk.intercept_m,
        "altitude_offset_applied_m": alt.shift_m,
        "altitude_fill_error_m": alt.accuracy,
        "sonar_vs_data": sonar_vs_data,
        "file_frequency_hz": file_sensor["frequency_hz"],
        "samples_per_side": wf.native,
        "n_bins": wf.n_bins,
        "range_window_m": [wf.r0, wf.r1],
        "range_settings": wf.range_settings,
        "channels_off_window": wf.off_window,
        "sound_speed_mps": sensor_params.sound_speed_mps,
    }
    _report_nav_repairs(path, stats, nav)
    return line, stats


# ----------------------------------------------------------------------------- stages
def _nav_units_code(path: Path, header: XTFFileHeader, nav_units: str) -> int:
    """The navigation unit (:data:`NAV_UNITS_METRES` / :data:`NAV_UNITS_LATLON`): the
    header's ``NavUnits``, or ``nav_units`` where it overrides the header. Checks: a header
    unit of 0 or 3 when it is used. Repairs nothing."""
    file_units = int(header.NavUnits)
    if nav_units != "file":
        return NAV_UNITS_LATLON if nav_units == "latlon" else NAV_UNITS_METRES
    if file_units not in (NAV_UNITS_METRES, NAV_UNITS_LATLON):
        raise SurveyFormatError(
            path,
            "NavUnits",
            "0 (metres) or 3 (latitude/longitude) (or set data.survey.nav_units)",
            file_units,
        )
    return file_units


def _ping_channels(
    path: Path,
    parsed: ParsedFile,
    channels: tuple[int, int],
    sv_ping: np.ndarray,
    c_default: float,
    port_far_first: bool,
) -> tuple[list[int], list[Channel], list[Channel]]:
    """``(kept ping indices, port channels, starboard channels)``: the sidescan pair of every
    ping having both sides (the others are skipped and counted by the caller), ranges from the
    ping's sound speed (``c_default`` where it has none). Checks: a slant range (or
    TimeDuration) on every kept channel, and at least 2 kept pings. Repairs nothing."""
    keep, ports, stbds = [], [], []
    for k, p in enumerate(parsed.pings):
        c = float(sv_ping[k]) if np.isfinite(sv_ping[k]) else c_default
        pc = ping_channel(p, channels[0], parsed.header, c, flip=port_far_first)
        sc = ping_channel(p, channels[1], parsed.header, c, flip=False)
        if pc is None or sc is None:
            continue
        for side, ch in (("port", pc), ("starboard", sc)):
            if not math.isfinite(ch.r_end):
                raise SurveyFormatError(
                    path,
                    f"ping {k} {side} channel",
                    "SlantRange > 0 (or TimeDuration > 0)",
                    "no slant range",
                )
        keep.append(k)
        ports.append(pc)
        stbds.append(sc)
    if len(keep) < 2:
        raise SurveyFormatError(
            path, "sonar pings", "at least 2 pings with both sidescan channels", len(keep)
        )
    return keep, ports, stbds


def _lever_arm(header: XTFFileHeader, channels: tuple[int, int]) -> np.ndarray:
    """The mean transducer offset of the pair in the body frame (FLU, m), from the XTF
    ``OffsetX/Y/Z`` (X starboard, Y forward, Z down). Pure."""
    return np.array(
        [
            [header.ChanInfo[i].OffsetY, -header.ChanInfo[i].OffsetX, -header.ChanInfo[i].OffsetZ]
            for i in channels
        ],
        dtype=np.float64,
    ).mean(axis=0)


def _position(
    nav: Navigation, origin: Mapping[str, Any], R: np.ndarray, offs: np.ndarray
) -> np.ndarray:
    """``(P, 3)`` transducer positions in the local ENU frame: the fixes minus the origin,
    z = -depth, plus the lever arm ``offs`` rotated by the attitude ``R``. Pure."""
    lever = R @ offs if np.any(offs != 0) else np.zeros((len(nav.xy), 3))
    return (
        np.stack(
            [
                nav.xy[:, 0] - origin["easting"],
                nav.xy[:, 1] - origin["northing"],
                -nav.depth,
            ],
            axis=1,
        )
        + lever
    )


@dataclass
class _Waterfall:
    """Both sides resampled onto the line's common range bins (:func:`_waterfall`)."""

    intensity: np.ndarray  # (P, 2, B) float32
    range_m: np.ndarray  # (B,) bin centres
    r0: float  # the common range window (m)
    r1: float
    native: int  # recorded samples per side (median)
    n_bins: int
    range_settings: int  # recording windows met (the larger count of the two sides)
    off_window: int  # channels recorded on another window than the common one


def _waterfall(
    path: Path, ports: list[Channel], stbds: list[Channel], n_bins: int | None
) -> _Waterfall:
    """The float32 waterfall: every channel's samples read from the file and resampled
    (area-weighted) onto ``n_bins`` bins (the recorded count when None) of the median range
    window. Checks: positive slant ranges. Repairs (WARNING): resampling to another bin
    count than recorded; channels on another window are resampled onto the common one
    (counted in the navigation/ping WARNING)."""
    r0 = float(np.median([c.r_start for c in ports + stbds]))
    r1 = float(np.median([c.r_end for c in ports + stbds]))
    native = int(np.median([c.size for c in ports + stbds]))
    B = int(n_bins) if n_bins is not None else native
    edges = np.linspace(r0, r1, B + 1)
    intensity = np.empty((len(ports), 2, B), dtype=np.float32)
    with open(path, "rb") as f:  # the samples are read from the file as they are resampled
        groups_p = resample_side(ports, edges, intensity[:, 0], f.fileno())
        groups_s = resample_side(stbds, edges, intensity[:, 1], f.fileno())
    range_m = 0.5 * (edges[:-1] + edges[1:])
    if range_m[0] <= 0:
        raise SurveyFormatError(path, "TimeDelay/SlantRange", "positive slant ranges", r0)
    off_window = sum(
        1 for c in ports + stbds if abs(c.r_start - r0) > 1e-6 or abs(c.r_end - r1) > 1e-6
    )
    if B != native:
        log.warning(
            "%s: %d samples per side (%.3f m each) resampled to %d bins (%.3f m each; "
            "data.survey.n_bins, null keeps the recorded samples)",
            path.name,
            native,
            (r1 - r0) / native,
            B,
            (r1 - r0) / B,
        )
    return _Waterfall(intensity, range_m, r0, r1, native, B, max(groups_p, groups_s), off_window)


def _mask_no_hit(path: Path, intensity: np.ndarray) -> dict[str, int]:
    """Pings constant, saturated or NaN over a whole side become NaN there (no-hit), in place;
    returns the counts per cause (reported in the altitude/sample WARNING). Checks: some ping
    keeps usable samples."""
    flags = [bad_pings(intensity[:, side]) for side in (0, 1)]
    ping_flags = {k: int((flags[0][k] | flags[1][k]).sum()) for k in flags[0]}
    for side in (0, 1):
        dead = flags[side]["nonfinite"] | flags[side]["constant"] | flags[side]["saturated"]
        intensity[dead, side] = np.nan
    if np.isnan(intensity).all(axis=(1, 2)).all():
        raise SurveyFormatError(
            path,
            "sidescan samples",
            "pings with usable samples",
            f"every ping constant, saturated or NaN ({ping_flags})",
        )
    return ping_flags


def _report_nav_repairs(path: Path, stats: Mapping[str, Any], nav: Navigation) -> None:
    """One WARNING counting every navigation/ping repair of the import (:data:`_LOGGED`)."""
    counts = {k: v for k, v in stats.items() if k in _LOGGED and v}
    if nav.outlier_speed:
        counts["nav_outliers"] = (
            f"{nav.outliers} (implied speeds up to {nav.outlier_speed:.0f} m/s)"
        )
    if counts:
        # every one of these changed or dropped data: a WARNING, never INFO
        log.warning(
            "%s: navigation/ping repairs: %s",
            path.name,
            ", ".join(f"{_LOGGED[k]} {v}" for k, v in counts.items()),
        )


#: stats counted in the repairs WARNING, with their wording
_LOGGED = {
    "pings_missing_channel": "pings skipped for a missing sidescan channel:",
    "pings_dropped_nav": "pings dropped before the first / after the last fix:",
    "packets_truncated": "truncated final packets skipped:",
    "nav_interpolated": "fixes interpolated (missing or outliers):",
    "nav_outliers": "fixes rejected as outliers:",
    "positions_from_ship": "sensor fixes taken from the ship position moved back by the layback:",
    "depth_interpolated": "depths interpolated:",
    "attitude_from_track": "headings taken from the course made good:",
    "channels_off_window": "channels resampled onto the common range window:",
}


# ----------------------------------------------------------------------------- writer
def _uniform_range(range_m: np.ndarray) -> tuple[float, float]:
    r = np.asarray(range_m, dtype=np.float64)
    if r.size < 2:
        raise ValueError(f"line.range_m: expected >= 2 bins, found {r.size}")
    dr = (r[-1] - r[0]) / (r.size - 1)
    if np.max(np.abs(np.diff(r) - dr)) > 1e-4 * dr + 1e-6:
        raise ValueError(
            "line.range_m: expected uniformly spaced bins (XTF stores a sample period)"
        )
    return float(r[0] - dr / 2), float(r[-1] + dr / 2)


def write_xtf(
    line: SidescanLine,
    path: str | Path,
    origin: Mapping[str, Any] | None = None,
    *,
    nav_units: str = "auto",
    epoch_s: float | None = None,
    sonar_name: str = "sss2bathy",
) -> dict[str, Any]:
    """Write a survey line to an XTF file (2 sidescan channels, uint16 samples), atomically.

    Args:
        line: any line (synthetic too). ``range_m`` must be uniformly spaced.
        path: output ``.xtf``.
        origin: ``{"crs", "easting", "northing"}`` of the line's local frame (default: no CRS,
            zero offsets).
        nav_units: ``"latlon"`` (geographic positions, needs ``origin["crs"]``), ``"metres"``
            (projected easting/northing) or ``"auto"`` (latlon when the origin has a CRS).
        epoch_s: UNIX time added to ``line.time_s``; default 2000-01-01T00:00:00Z when the
            line's times are earlier than that (relative times), else 0.
        sonar_name: written to the file header.

    Stored: per channel ``round(I / VoltScale * 65535)`` with ``VoltScale`` = the channel's
    maximum intensity (negative / non-finite intensities are written as 0 and counted), port
    samples outward-to-nadir; NaN altitude is written as 0 (missing); times are rounded to
    10 ms (XTF's resolution); sound velocity as half the sound speed (Isis convention).

    Returns:
        Stats: ``{"epoch_s", "nav_units", "volt_scale", "clipped_samples", "pings"}``.
    """
    path = Path(path)
    if nav_units not in ("auto", "latlon", "metres"):
        raise ValueError(f"nav_units: expected 'auto', 'latlon' or 'metres', found {nav_units!r}")
    origin = dict(origin or {})
    crs = origin.get("crs")
    easting, northing = float(origin.get("easting", 0.0)), float(origin.get("northing", 0.0))
    units = ("latlon" if crs else "metres") if nav_units == "auto" else nav_units
    if units == "latlon" and not crs:
        raise ValueError("origin: expected a 'crs' to write geographic positions, found none")
    r_start, r_end = _uniform_range(line.range_m)
    P, B = line.n_pings, line.n_bins
    c = float(line.sensor.sound_speed_mps)

    if epoch_s is None:
        epoch_s = DEFAULT_EPOCH_S if line.time_s[0] < DEFAULT_EPOCH_S else 0.0
    centis = np.round((line.time_s + epoch_s) * 100.0).astype(np.int64)
    if np.any(np.diff(centis) <= 0):
        raise ValueError(
            "line.time_s: expected pings at least 10 ms apart (XTF time resolution), "
            f"found {int(np.sum(np.diff(centis) <= 0))} collisions"
        )
    if centis[0] < 0:
        raise ValueError(
            f"line.time_s + epoch_s: expected times after 1970, found {centis[0] / 100}"
        )

    x = line.position[:, 0] + easting
    y = line.position[:, 1] + northing
    if units == "latlon":
        lon, lat = transformer(crs, "EPSG:4326").transform(x, y)
        nx_, ny_ = np.asarray(lon, dtype=np.float64), np.asarray(lat, dtype=np.float64)
    else:
        nx_, ny_ = x, y
    heading, pitch, roll = (np.degrees(np.asarray(a)) for a in rotation_to_attitude(line.rotation))

    intensity = np.asarray(line.intensity, dtype=np.float64)
    bad = ~np.isfinite(intensity) | (intensity < 0)
    clipped = int(bad.sum())
    if clipped:
        log.warning("%s: %d negative/non-finite intensities written as 0", path.name, clipped)
    intensity = np.where(bad, 0.0, intensity)
    vmax = intensity.max(axis=(0, 2))
    volt = np.where(vmax > 0, vmax, 1.0).astype(np.float32)
    codes = np.clip(np.round(intensity / volt[None, :, None].astype(np.float64) * 65535), 0, 65535)
    codes = codes.astype(np.uint16)

    header = XTFFileHeader()
    header.RecordingProgramName = b"sss2bthy"
    header.SonarName = sonar_name.encode()[:16]
    header.NavUnits = NAV_UNITS_LATLON if units == "latlon" else NAV_UNITS_METRES
    header.NumberOfSonarChannels = 2
    header.ThisFileName = path.name.encode()[:64]
    for i, (ctype, cname) in enumerate(
        ((XTFChannelType.port, b"port"), (XTFChannelType.stbd, b"starboard"))
    ):
        info = header.ChanInfo[i]
        info.TypeOfChannel = int(ctype)
        info.SubChannelNumber = i
        info.BytesPerSample = 2
        info.SampleFormat = SAMPLE_FORMAT_UINT16
        info.Reserved = B
        info.ChannelName = cname
        info.VoltScale = float(volt[i])
        info.Frequency = line.sensor.frequency_hz / 1e3
        info.TiltAngle = math.degrees(line.sensor.tilt_rad)
        info.BeamWidth = math.degrees(line.sensor.beam_width_rad)

    n_record = ctypes.sizeof(XTFPingHeader) + 2 * (ctypes.sizeof(XTFPingChanHeader) + 2 * B)
    padded = ((n_record + 63) // 64) * 64
    period = float(np.median(np.diff(line.time_s))) if P > 1 else 0.0
    altitude = np.where(np.isfinite(line.altitude_m), line.altitude_m, 0.0)
    with atomic_path(path) as tmp, open(tmp, "wb") as f:
        f.write(header.to_bytes())
        for k in range(P):
            secs, hsec = divmod(int(centis[k]), 100)
            when = _dt.datetime.fromtimestamp(secs, tz=_dt.timezone.utc)
            p = XTFPingHeader()
            p.MagicNumber = MAGIC
            p.NumChansToFollow = 2
            p.NumBytesThisRecord = padded
            p.Year, p.Month, p.Day = when.year, when.month, when.day
            p.Hour, p.Minute, p.Second, p.HSeconds = when.hour, when.minute, when.second, hsec
            p.JulianDay = when.timetuple().tm_yday
            p.PingNumber = k + 1
            p.SoundVelocity = c / 2.0
            p.SensorXcoordinate = p.ShipXcoordinate = float(nx_[k])
            p.SensorYcoordinate = p.ShipYcoordinate = float(ny_[k])
            p.SensorDepth = float(-line.position[k, 2])
            p.SensorPrimaryAltitude = float(altitude[k])
            p.SensorHeading = p.ShipGyro = float(heading[k])
            p.SensorPitch, p.SensorRoll = float(pitch[k]), float(roll[k])
            p.ping_chan_headers, p.data = [], []
            for side in (0, 1):
                ch = XTFPingChanHeader()
                ch.ChannelNumber = side
                ch.SlantRange = r_end
                ch.TimeDelay = 2.0 * r_start / c
                ch.TimeDuration = 2.0 * (r_end - r_start) / c
                ch.SecondsPerPing = period
                ch.Frequency = min(int(round(line.sensor.frequency_hz / 1e3)), 65535)
                ch.NumSamples = B
                samples = codes[k, side]
                p.ping_chan_headers.append(ch)
                p.data.append(np.ascontiguousarray(samples[::-1] if side == 0 else samples))
            record = p.to_bytes()
            f.write(record + bytes(padded - len(record)))
    return {
        "epoch_s": float(epoch_s),
        "nav_units": units,
        "volt_scale": [float(v) for v in volt],
        "clipped_samples": clipped,
        "pings": P,
    }
