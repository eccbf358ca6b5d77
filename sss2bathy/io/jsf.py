"""Edgetech JSF sidescan in (and out, for test fixtures), imported through the XTF pipeline.

A JSF file is a sequence of messages, each a 16-byte message header followed by
``size`` bytes (little-endian throughout):

* message header: start marker ``0x1601`` (bytes 0-1), protocol version (2), session (3),
  message type (4-5), command type (6), subsystem (7), channel (8), sequence (9),
  reserved (10-11), size of the message that follows (12-15, int32);
* message type 80, sonar data: one channel of one ping, a 240-byte header and the samples.
  Subsystems 20 / 21 / 22 are the low / high / very-high frequency sidescan, channel 0 is
  port and 1 starboard; both channels are stored in time order (sample 0 nearest);
* message type 2020, pitch/roll data (44 bytes), used where the pings carry no attitude.
  Every other message (NMEA 2002, pressure 2060, DVL 2080, system information 182, ...) is
  counted and skipped.

Fields read from the 240-byte sonar data header (byte offsets from the Edgetech *JSF Data
File Description*; the layout is :data:`SONAR_HEADER`):

* time: ``0-3`` seconds since 1970 plus the milliseconds of ``200-203`` (milliseconds
  today); files written before protocol version 8 (``0-3`` zero) use the year / day of
  ``156-159`` with the milliseconds today;
* ``30-31`` validity flags: bit 0 position, 3 heading, 5 pitch/roll, 6 altitude, 9 depth,
  14 sound speed. A value whose bit is clear is missing (NaN, or 0 for the altitude, as XTF
  has it). A file whose pings set no validity bit at all (old recorders) takes its non-zero
  values as valid, with a WARNING;
* position ``80-87`` (X / longitude, Y / latitude, int32) in the coordinate units of
  ``88-89``: 2 = minutes of arc x 10000 (about 0.19 m of latitude per unit), 1 = mm,
  3 = dm, 4 = cm. The position is taken as the sonar's; ``228-231`` layback is reported,
  never applied (the file does not say whether its positions already include it);
* ``136-139`` depth (mm; 0 = not filled), ``144-147`` altitude (mm; 0 = not filled),
  ``148-151`` sound speed (m/s, float);
* ``172-173`` compass heading (0.01 deg), ``174-175`` pitch and ``176-177`` roll
  (x 180 / 32768 deg; bow up and port up positive, the same rotation as XTF's roll
  starboard-down positive);
* samples: count ``114-115`` with bits 8-11 of ``16-17`` as its 4 high bits, interval
  ``116-119`` (ns; the sub-nanosecond fraction of ``18-19`` is not read: under 1e-4 of a
  sonar's interval), window offset ``4-7`` (samples), weighting factor ``168-169`` (every
  sample x 2^-N), data format ``34-35``: 0 = envelope (uint16), 1 = analytic signal
  (int16 real, imaginary: the magnitude is read); other formats are refused;
* frequency: mean of the transmit start / end frequencies ``126-129`` (daHz, with bits 0-3
  / 4-7 of ``16-17`` as their high bits).

Tilt and beam width are not in a JSF file: ``data.survey.tilt_deg`` / ``beam_width_deg``
give them (the import refuses without them, as for an XTF file that lacks them).

The import (:func:`sss2bathy.io.xtf.read_xtf` on a ``.jsf`` path, and so
``prepare_xtf_survey``) hands the parsed pings to the XTF pipeline as the XTF packets the
line would convert to (:func:`jsf_as_xtf`: pyxtf structures, port samples outward-to-nadir
as XTF stores them): projection, navigation checks, resampling, the bottom detector and
the altitude checks are the XTF ones. What the conversion costs: ping times are rounded to
10 ms (XTF's ping time resolution; JSF has 1 ms), and error messages from those stages name
the XTF fields (``SensorHeading``, ``SensorPrimaryAltitude``, ``SensorDepth``). ``channel_pair``
selects the sidescan subsystem (0 = the lowest present, e.g. 20 on a dual-frequency
sonar, 1 = the next). ``port_far_first`` describes XTF files: leave it true for JSF.
"""

from __future__ import annotations

import calendar
import datetime as _dt
import logging
import math
import mmap
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from pyxtf import (
    XTFAttitudeData,
    XTFChannelType,
    XTFFileHeader,
    XTFPingChanHeader,
    XTFPingHeader,
)

from sss2bathy.geometry import rotation_to_attitude
from sss2bathy.survey import SidescanLine, SurveyFormatError
from sss2bathy.utils.atomic import atomic_path

log = logging.getLogger(__name__)

__all__ = [
    "MESSAGE_HEADER",
    "PITCH_ROLL",
    "SIDESCAN_SUBSYSTEMS",
    "SONAR_HEADER",
    "JsfChannel",
    "JsfLine",
    "jsf_as_xtf",
    "read_jsf",
    "read_jsf_sensor",
    "write_jsf",
]

START_MARKER = 0x1601
_MARKER_BYTES = START_MARKER.to_bytes(2, "little")
SONAR_DATA = 80
PITCH_ROLL_DATA = 2020
SIDESCAN_SUBSYSTEMS = (20, 21, 22)
PORT, STARBOARD = 0, 1
# Times written before this epoch (2000-01-01T00:00:00Z) are taken as relative to it.
DEFAULT_EPOCH_S = 946684800.0

#: the 16-byte message header
MESSAGE_HEADER = np.dtype(
    [
        ("marker", "<u2"),
        ("version", "u1"),
        ("session", "u1"),
        ("type", "<u2"),
        ("command", "u1"),
        ("subsystem", "u1"),
        ("channel", "u1"),
        ("sequence", "u1"),
        ("reserved", "<u2"),
        ("size", "<i4"),
    ]
)
assert MESSAGE_HEADER.itemsize == 16


def _layout(fields: tuple[tuple[str, int, str], ...], size: int) -> np.dtype:
    names, offsets, formats = zip(*fields, strict=True)
    return np.dtype(
        {"names": list(names), "offsets": list(offsets), "formats": list(formats), "itemsize": size}
    )


#: the fields read (and written) of the 240-byte sonar data header: (name, byte offset, type)
SONAR_HEADER = _layout(
    (
        ("ping_time_s", 0, "<i4"),
        ("starting_depth", 4, "<u4"),
        ("ping_number", 8, "<u4"),
        ("msb", 16, "<u2"),
        ("id_code", 28, "<i2"),
        ("validity", 30, "<u2"),
        ("data_format", 34, "<i2"),
        ("x", 80, "<i4"),
        ("y", 84, "<i4"),
        ("coordinate_units", 88, "<i2"),
        ("samples", 114, "<u2"),
        ("sample_interval_ns", 116, "<u4"),
        ("start_frequency_dahz", 126, "<u2"),
        ("end_frequency_dahz", 128, "<u2"),
        ("depth_mm", 136, "<i4"),
        ("altitude_mm", 144, "<i4"),
        ("sound_speed_mps", 148, "<f4"),
        ("year", 156, "<i2"),
        ("day", 158, "<i2"),
        ("hour", 160, "<i2"),
        ("minute", 162, "<i2"),
        ("second", 164, "<i2"),
        ("time_basis", 166, "<i2"),
        ("weighting", 168, "<i2"),
        ("heading_cdeg", 172, "<u2"),
        ("pitch", 174, "<i2"),
        ("roll", 176, "<i2"),
        ("ms_today", 200, "<u4"),
        ("packet_number", 220, "<u2"),
        ("layback_m", 228, "<f4"),
    ),
    240,
)

#: the fields read (and written) of the 44-byte pitch/roll message
PITCH_ROLL = _layout(
    (
        ("time_s", 0, "<i4"),
        ("ms", 4, "<i4"),
        ("pitch", 24, "<i2"),
        ("roll", 26, "<i2"),
        ("heading_cdeg", 34, "<u2"),
        ("validity", 36, "<i4"),
    ),
    44,
)

# sonar data validity bits
BIT_POSITION, BIT_HEADING, BIT_PITCH_ROLL, BIT_ALTITUDE, BIT_DEPTH, BIT_SOUND_SPEED = (
    0,
    3,
    5,
    6,
    9,
    14,
)
# pitch/roll message validity bits
PR_BIT_PITCH, PR_BIT_ROLL, PR_BIT_HEADING = 6, 7, 9
ANGLE_SCALE = 180.0 / 32768.0
# coordinate units -> metres per unit (2 = minutes of arc x 10000: degrees per unit)
METRES_PER_UNIT = {1: 1e-3, 3: 0.1, 4: 0.01}
DEGREES_PER_UNIT = 1.0 / 600000.0
UNITS_LATLON = 2
# data format -> (sample dtype, values per sample)
DATA_FORMATS = {0: ("<u2", 1), 1: ("<i2", 2)}
SOUND_SPEED_RANGE = (1300.0, 1800.0)
MESSAGE_NAMES = {
    80: "sonar_data",
    182: "system_information",
    181: "navigation_offsets",
    2002: "nmea",
    2020: "pitch_roll",
    2060: "pressure",
    2080: "dvl",
    2090: "situation",
    2091: "situation_comprehensive",
}


# ----------------------------------------------------------------------------- containers
@dataclass
class JsfChannel:
    """One side of one ping as stored (weighting applied, analytic data as magnitude)."""

    samples: np.ndarray  # float64, sample 0 nearest the sonar
    start_s: float  # two-way time of sample 0's start (window offset)
    interval_s: float  # two-way time per sample


@dataclass
class JsfLine:
    """The sidescan pings of one subsystem of a JSF file, in file order (``P`` pings).

    Missing values are NaN (the altitude too); positions are longitude / latitude in
    degrees (``units == "latlon"``) or metres (``"metres"``, CRS unknown).
    """

    subsystem: int
    ping_number: np.ndarray  # (P,) int64
    time_s: np.ndarray  # (P,) UNIX seconds, 1 ms resolution
    x: np.ndarray  # (P,) longitude (deg) or easting (m)
    y: np.ndarray  # (P,) latitude (deg) or northing (m)
    units: str
    heading_deg: np.ndarray
    pitch_deg: np.ndarray
    roll_deg: np.ndarray
    altitude_m: np.ndarray
    depth_m: np.ndarray
    sound_speed_mps: np.ndarray
    frequency_hz: np.ndarray
    layback_m: np.ndarray
    port: list[JsfChannel | None]
    starboard: list[JsfChannel | None]
    # pitch/roll messages with valid pitch, roll and heading: time_s, heading, pitch, roll
    attitude: dict[str, np.ndarray] = field(default_factory=dict)
    other_messages: dict[str, int] = field(default_factory=dict)
    truncated: int = 0
    damaged_bytes: int = 0
    # pings lost whole in damaged messages (ping-number gaps), and pings left with one side
    pings_lost: int = 0
    pings_one_side: int = 0
    validity_flags: bool = True

    @property
    def n_pings(self) -> int:
        return int(self.time_s.size)


# ----------------------------------------------------------------------------- scanning
@dataclass
class _Scan:
    """Message index of a file: ``(offset, type, subsystem, channel, size)`` per message."""

    messages: list[tuple[int, int, int, int, int]]
    size: int
    truncated: tuple[int, int, int, int] | None  # (offset, type, subsystem, channel)
    damaged: list[tuple[int, int]]  # byte ranges skipped by re-synchronising


def _message_size(raw, pos: int, size: int, chained: bool) -> int | None:
    """Size of the message body at ``pos`` when a plausible header starts there: the start
    marker, a size that fits the file and (``chained``) is followed by the next message's
    marker or the end of the file; else None."""
    if size - pos < 16 or raw[pos : pos + 2] != _MARKER_BYTES:
        return None
    n = int.from_bytes(raw[pos + 12 : pos + 16], "little", signed=True)
    end = pos + 16 + n
    if n < 0 or end > size:
        return None
    if not chained or end == size or size - end < 2 or raw[end : end + 2] == _MARKER_BYTES:
        return n
    return None


def _next_message(raw, start: int, size: int) -> int | None:
    q = raw.find(_MARKER_BYTES, start)
    while q != -1:
        if _message_size(raw, q, size, chained=True) is not None:
            return q
        q = raw.find(_MARKER_BYTES, q + 1)
    return None


def _scan(raw, size: int, path: Path) -> _Scan:
    if size < 16 or raw[:2] != _MARKER_BYTES:
        found = raw[:2].hex() if size >= 2 else f"{size} bytes"
        raise SurveyFormatError(
            path, "message header", "a JSF file (start marker 0x1601 at byte 0)", found
        )
    messages: list[tuple[int, int, int, int, int]] = []
    damaged: list[tuple[int, int]] = []
    truncated = None
    pos = 0
    while pos < size:
        n = _message_size(raw, pos, size, chained=True)
        if n is None:
            own = _message_size(raw, pos, size, chained=False)
            nxt = _next_message(raw, pos + 1, size)
            if own is not None and (nxt is None or nxt >= pos + 16 + own):
                n = own  # whole; whatever follows is looked at next
            elif nxt is None:
                if raw[pos : pos + 2] == _MARKER_BYTES:
                    head = np.frombuffer(raw[pos : pos + 16].ljust(16, b"\0"), MESSAGE_HEADER)[0]
                    whole = size - pos >= 16
                    truncated = (
                        pos,
                        int(head["type"]) if whole else -1,
                        int(head["subsystem"]) if whole else -1,
                        int(head["channel"]) if whole else -1,
                    )
                else:
                    damaged.append((pos, size))
                break
            else:
                damaged.append((pos, nxt))
                pos = nxt
                continue
        head = np.frombuffer(raw[pos : pos + 16], MESSAGE_HEADER)[0]
        messages.append(
            (pos, int(head["type"]), int(head["subsystem"]), int(head["channel"]), int(n))
        )
        pos += 16 + n
    return _Scan(messages, size, truncated, damaged)


def _choose_subsystem(scan: _Scan, path: Path, channel_pair: int) -> int:
    sidescan = sorted(
        {s for _, t, s, c, _ in scan.messages if t == SONAR_DATA and s in SIDESCAN_SUBSYSTEMS}
    )
    if not sidescan:
        kinds: dict[str, int] = {}
        for _, t, s, _c, _ in scan.messages:
            name = (
                f"sonar data of subsystem {s}"
                if t == SONAR_DATA
                else MESSAGE_NAMES.get(t, f"type {t}")
            )
            kinds[name] = kinds.get(name, 0) + 1
        found = ", ".join(f"{v} x {k}" for k, v in sorted(kinds.items())) or "no whole message"
        raise SurveyFormatError(
            path,
            "sonar data messages (type 80)",
            f"sidescan messages (subsystem {', '.join(map(str, SIDESCAN_SUBSYSTEMS))})",
            f"none ({found})",
        )
    if not 0 <= channel_pair < len(sidescan):
        raise SurveyFormatError(
            path,
            "channel_pair",
            f"an index below {len(sidescan)} (sidescan subsystems {sidescan})",
            channel_pair,
        )
    return sidescan[channel_pair]


# ----------------------------------------------------------------------------- reading
def _sonar_header(raw, pos: int, n: int, path: Path, where: str) -> np.void:
    if n < SONAR_HEADER.itemsize:
        raise SurveyFormatError(
            path, f"{where}: message size", "a 240-byte sonar data header at least", f"{n} bytes"
        )
    return np.frombuffer(raw[pos + 16 : pos + 16 + SONAR_HEADER.itemsize], SONAR_HEADER)[0]


def _n_samples(h: np.void) -> int:
    return int(h["samples"]) + (((int(h["msb"]) >> 8) & 0xF) << 16)


def _frequency_hz(h: np.void) -> float:
    msb = int(h["msb"])
    start = int(h["start_frequency_dahz"]) + ((msb & 0xF) << 16)
    end = int(h["end_frequency_dahz"]) + (((msb >> 4) & 0xF) << 16)
    good = [f for f in (start, end) if f > 0]
    return 10.0 * sum(good) / len(good) if good else math.nan


def _ping_time(h: np.void, path: Path, where: str) -> tuple[float, bool]:
    """UNIX time of a ping (1 ms resolution) and whether its two time stamps disagree."""
    ms = int(h["ms_today"])
    if ms >= 86_400_000:
        raise SurveyFormatError(
            path, f"{where}: milliseconds today (bytes 200-203)", "0..86399999", ms
        )
    t1970 = int(h["ping_time_s"])
    if t1970 > 0:
        # the two stamps name the same second of the day (one second of slack at its edge)
        off = (t1970 % 86400) - ms // 1000
        return t1970 + (ms % 1000) / 1000.0, min(abs(off), 86400 - abs(off)) > 1
    year, day = int(h["year"]), int(h["day"])
    if not (1970 <= year <= 2100 and 1 <= day <= 366):
        raise SurveyFormatError(
            path,
            f"{where}: time",
            "seconds since 1970 (bytes 0-3) or a year and day (bytes 156-159)",
            f"0 s, year {year}, day {day}",
        )
    start = calendar.timegm((year, 1, 1, 0, 0, 0, 0, 0, 0)) + (day - 1) * 86400
    return start + ms / 1000.0, False


def _samples(raw, pos: int, n: int, h: np.void, path: Path, where: str) -> JsfChannel:
    fmt = int(h["data_format"])
    if fmt not in DATA_FORMATS:
        raise SurveyFormatError(
            path,
            f"{where}: data format (bytes 34-35)",
            "0 (envelope) or 1 (analytic signal, real/imaginary)",
            f"{fmt}{' (compressed, proprietary)' if fmt > 255 else ''}",
        )
    if int(h["packet_number"]) > 1:
        raise SurveyFormatError(
            path,
            f"{where}: packet number (bytes 220-221)",
            "one packet per ping (1)",
            int(h["packet_number"]),
        )
    count = _n_samples(h)
    dtype, per = DATA_FORMATS[fmt]
    need = count * per * 2
    have = n - SONAR_HEADER.itemsize
    if need > have or count < 1:
        raise SurveyFormatError(
            path,
            f"{where}: samples (bytes 114-115)",
            f"at least 1 sample and {have} bytes of samples for them",
            f"{count} samples of format {fmt} ({need} bytes)",
        )
    interval = int(h["sample_interval_ns"])
    if interval <= 0:
        raise SurveyFormatError(
            path, f"{where}: sample interval (bytes 116-119)", "> 0 ns", interval
        )
    start = pos + 16 + SONAR_HEADER.itemsize
    data = np.frombuffer(raw[start : start + need], dtype).astype(np.float64)
    if per == 2:
        data = np.hypot(data[0::2], data[1::2])
    data *= 2.0 ** (-int(h["weighting"]))
    return JsfChannel(data, int(h["starting_depth"]) * interval * 1e-9, interval * 1e-9)


def _lost_in_damage(scan: _Scan, numbers: list[tuple[int, int]], median_bytes: float) -> int:
    """Pings lost in the damaged byte ranges: the ping-number gap across each, else an
    estimate from its length. ``numbers``: (offset, ping number) of the read pings."""
    lost = 0
    offsets = [o for o, _ in numbers]
    for a, b in scan.damaged:
        k = int(np.searchsorted(offsets, a))
        estimate = math.ceil((b - a) / median_bytes) if median_bytes else 0
        gap = None
        if 0 < k < len(numbers):
            gap = numbers[k][1] - numbers[k - 1][1] - 1
        lost += gap if gap is not None and 0 <= gap <= 2 * estimate + 1 else estimate
    return lost


def read_jsf(path: str | Path, channel_pair: int = 0) -> JsfLine:
    """The sidescan pings of one subsystem of a JSF file (see the module docstring).

    Args:
        path: the ``.jsf`` file.
        channel_pair: which sidescan subsystem (0 = the lowest-numbered present).

    A file cut short loses its final message (a WARNING names it and the pings lost); damaged
    messages (bad start marker or size) are skipped by re-synchronising on the next message
    (a WARNING with the byte ranges and the pings lost; more than half the file damaged is
    refused). A ping with one side only is kept with the other side ``None``.

    Raises:
        SurveyFormatError: one line naming the file, the field (and message or ping), what
            was expected and what was found; also when the file has no sidescan messages.
    """
    path = Path(path)
    if not path.is_file():
        raise SurveyFormatError(path, "file", "an existing JSF file", "missing file")
    size = path.stat().st_size
    if size == 0:
        raise SurveyFormatError(path, "message header", "a JSF file", "an empty file")
    with open(path, "rb") as f, mmap.mmap(f.fileno(), 0, access=mmap.ACCESS_READ) as raw:
        scan = _scan(raw, size, path)
        subsystem = _choose_subsystem(scan, path, channel_pair)
        pings: dict[int, dict[str, Any]] = {}
        order: list[int] = []
        other: dict[str, int] = {}
        attitude: list[np.void] = []
        numbers: list[tuple[int, int]] = []
        ping_bytes: list[int] = []
        for pos, mtype, subsys, chan, n in scan.messages:
            if mtype == SONAR_DATA and subsys == subsystem and chan in (PORT, STARBOARD):
                where = f"message at byte {pos} (subsystem {subsys}, channel {chan})"
                h = _sonar_header(raw, pos, n, path, where)
                number = int(h["ping_number"])
                where = f"ping {number} {'port' if chan == PORT else 'starboard'}"
                side = "port" if chan == PORT else "starboard"
                entry = pings.get(number)
                if entry is None:
                    entry = pings[number] = {"header": h, "where": where}
                    order.append(number)
                    numbers.append((pos, number))
                elif side in entry:
                    raise SurveyFormatError(
                        path,
                        f"{where}: ping number (bytes 8-11)",
                        "one message per ping and channel",
                        f"a second one at byte {pos}",
                    )
                entry[side] = _samples(raw, pos, n, h, path, where)
                ping_bytes.append(16 + n)
            elif mtype == PITCH_ROLL_DATA and n >= PITCH_ROLL.itemsize:
                attitude.append(
                    np.frombuffer(raw[pos + 16 : pos + 16 + PITCH_ROLL.itemsize], PITCH_ROLL)[0]
                )
            else:
                name = MESSAGE_NAMES.get(mtype, f"type_{mtype}")
                if mtype == SONAR_DATA:
                    name = f"sonar_data_subsystem_{subsys}_channel_{chan}"
                other[name] = other.get(name, 0) + 1

    damaged_bytes = sum(b - a for a, b in scan.damaged)
    if damaged_bytes > 0.5 * size:
        raise SurveyFormatError(
            path,
            "messages",
            "a readable file (at most half of it damaged)",
            f"{damaged_bytes} of {size} bytes damaged (bad start marker or message size)",
        )
    if not order:
        raise SurveyFormatError(
            path, "sonar data messages (type 80)", "sidescan pings", "none readable"
        )
    median_bytes = 2 * float(np.median(ping_bytes)) if ping_bytes else 0.0
    lost = _lost_in_damage(scan, numbers, median_bytes) if scan.damaged else 0
    one_side = sum(("port" in pings[k]) != ("starboard" in pings[k]) for k in order)

    headers = [pings[k]["header"] for k in order]
    validity = np.array([int(h["validity"]) for h in headers], dtype=np.int64)
    flags = bool(validity.any())

    def valid(bit: int, values: np.ndarray) -> np.ndarray:
        if flags:
            return (validity >> bit) & 1 == 1
        return values != 0

    def column(name: str) -> np.ndarray:
        return np.array([h[name] for h in headers], dtype=np.float64)

    times, clash = zip(
        *(_ping_time(pings[k]["header"], path, pings[k]["where"]) for k in order), strict=True
    )
    t = np.asarray(times, dtype=np.float64)

    xr, yr = column("x"), column("y")
    units_raw = np.array([int(h["coordinate_units"]) for h in headers])
    pos_ok = valid(BIT_POSITION, np.abs(xr) + np.abs(yr)) & ~((xr == 0) & (yr == 0))
    used_units = sorted(set(units_raw[pos_ok].tolist()))
    if len(used_units) > 1:
        raise SurveyFormatError(
            path,
            "coordinate units (bytes 88-89)",
            "one unit over the line",
            f"units {used_units}",
        )
    unit = used_units[0] if used_units else UNITS_LATLON
    if unit == UNITS_LATLON:
        scale, units = DEGREES_PER_UNIT, "latlon"
    elif unit in METRES_PER_UNIT:
        scale, units = METRES_PER_UNIT[unit], "metres"
    else:
        k = int(np.argmax(pos_ok))
        raise SurveyFormatError(
            path,
            f"{pings[order[k]]['where']}: coordinate units (bytes 88-89)",
            "1 (mm), 2 (minutes of arc x 10000), 3 (dm) or 4 (cm)",
            unit,
        )
    x = np.where(pos_ok, xr * scale, np.nan)
    y = np.where(pos_ok, yr * scale, np.nan)

    heading_raw, pitch_raw, roll_raw = column("heading_cdeg"), column("pitch"), column("roll")
    head_ok = valid(BIT_HEADING, heading_raw)
    att_ok = valid(BIT_PITCH_ROLL, np.abs(pitch_raw) + np.abs(roll_raw))
    heading = np.where(head_ok, np.mod(heading_raw / 100.0, 360.0), np.nan)
    pitch = np.where(att_ok, pitch_raw * ANGLE_SCALE, np.nan)
    roll = np.where(att_ok, roll_raw * ANGLE_SCALE, np.nan)
    alt_raw, depth_raw = column("altitude_mm"), column("depth_mm")
    altitude = np.where(valid(BIT_ALTITUDE, alt_raw) & (alt_raw > 0), alt_raw / 1000.0, np.nan)
    depth = np.where(valid(BIT_DEPTH, depth_raw) & (depth_raw != 0), depth_raw / 1000.0, np.nan)
    sv_raw = column("sound_speed_mps")
    lo, hi = SOUND_SPEED_RANGE
    sv_ok = valid(BIT_SOUND_SPEED, sv_raw) & np.isfinite(sv_raw) & (sv_raw >= lo) & (sv_raw <= hi)
    sound_speed = np.where(sv_ok, sv_raw, np.nan)

    att: dict[str, np.ndarray] = {}
    if attitude:
        a = np.array(attitude, dtype=PITCH_ROLL)
        bits = a["validity"].astype(np.int64)
        ok = np.ones(a.size, dtype=bool)
        for bit in (PR_BIT_PITCH, PR_BIT_ROLL, PR_BIT_HEADING):
            ok &= (bits >> bit) & 1 == 1
        ms_ok = (a["ms"] >= 0) & (a["ms"] < 1000) & (a["time_s"] > 0)
        ok &= ms_ok
        if ok.any():
            att = {
                "time_s": a["time_s"][ok] + a["ms"][ok] / 1000.0,
                "heading": np.mod(a["heading_cdeg"][ok] / 100.0, 360.0),
                "pitch": a["pitch"][ok] * ANGLE_SCALE,
                "roll": a["roll"][ok] * ANGLE_SCALE,
            }
        if (~ok).any():
            other["pitch_roll_without_valid_attitude"] = int((~ok).sum())

    line = JsfLine(
        subsystem=subsystem,
        ping_number=np.asarray(order, dtype=np.int64),
        time_s=t,
        x=x,
        y=y,
        units=units,
        heading_deg=heading,
        pitch_deg=pitch,
        roll_deg=roll,
        altitude_m=altitude,
        depth_m=depth,
        sound_speed_mps=sound_speed,
        frequency_hz=np.array([_frequency_hz(h) for h in headers]),
        layback_m=np.nan_to_num(column("layback_m"), nan=0.0),
        port=[pings[k].get("port") for k in order],
        starboard=[pings[k].get("starboard") for k in order],
        attitude=att,
        other_messages=other,
        truncated=int(scan.truncated is not None),
        damaged_bytes=damaged_bytes,
        pings_lost=lost,
        pings_one_side=one_side,
        validity_flags=flags,
    )
    _report(path, scan, line, sum(clash))
    return line


def _report(path: Path, scan: _Scan, line: JsfLine, clashes: int) -> None:
    """WARNINGs for what the reader skipped or could not check."""
    if scan.truncated is not None or scan.damaged:
        where = []
        if scan.truncated is not None:
            pos, mtype, subsys, chan = scan.truncated
            kind = (
                "a message header"
                if mtype < 0
                else f"a sonar data message (subsystem {subsys}, channel {chan})"
                if mtype == SONAR_DATA
                else f"a message of type {mtype}"
            )
            where.append(f"file cut short at byte {pos} of {scan.size} in {kind}")
        if scan.damaged:
            ranges = ", ".join(f"bytes {a}-{b}" for a, b in scan.damaged[:3]) + (
                f" and {len(scan.damaged) - 3} more" if len(scan.damaged) > 3 else ""
            )
            where.append(
                f"damaged messages (bad 0x1601 start marker or message size) at {ranges}, "
                "re-synchronised on the next valid message"
            )
        log.warning(
            "%s: %s; skipped: %d pings lost whole, %d pings left with one side (dropped by the "
            "import), %d pings read",
            path.name,
            "; ".join(where),
            line.pings_lost,
            line.pings_one_side,
            line.n_pings,
        )
    if not line.validity_flags:
        log.warning(
            "%s: no ping sets a validity flag (bytes 30-31; an old recorder): non-zero "
            "position, heading, attitude, altitude, depth and sound speed taken as valid",
            path.name,
        )
    if clashes:
        log.warning(
            "%s: %d pings whose seconds since 1970 (bytes 0-3) and milliseconds today "
            "(bytes 200-203) name different seconds; the seconds since 1970 were used",
            path.name,
            clashes,
        )
    if np.any(line.layback_m > 0):
        log.warning(
            "%s: layback up to %.1f m recorded; positions taken as the sonar's (not moved: the "
            "file does not say whether they already include it)",
            path.name,
            float(np.max(line.layback_m)),
        )


def read_jsf_sensor(path: str | Path, channel_pair: int = 0) -> dict[str, float | None]:
    """Sensor parameters a JSF file states: ``{"tilt_deg": None, "beam_width_deg": None,
    "frequency_hz"}`` (the median transmit frequency of the subsystem's pings; JSF has no
    tilt or beam width)."""
    path = Path(path)
    if not path.is_file():
        raise SurveyFormatError(path, "file", "an existing JSF file", "missing file")
    size = path.stat().st_size
    if size == 0:
        raise SurveyFormatError(path, "message header", "a JSF file", "an empty file")
    freqs = []
    with open(path, "rb") as f, mmap.mmap(f.fileno(), 0, access=mmap.ACCESS_READ) as raw:
        scan = _scan(raw, size, path)
        subsystem = _choose_subsystem(scan, path, channel_pair)
        for pos, mtype, subsys, chan, n in scan.messages:
            if mtype == SONAR_DATA and subsys == subsystem and chan in (PORT, STARBOARD):
                h = _sonar_header(raw, pos, n, path, f"message at byte {pos}")
                freqs.append(_frequency_hz(h))
    good = [v for v in freqs if math.isfinite(v) and v > 0]
    return {
        "tilt_deg": None,
        "beam_width_deg": None,
        "frequency_hz": float(np.median(good)) if good else None,
    }


# ----------------------------------------------------------------------------- XTF view
def jsf_as_xtf(
    path: str | Path, channel_pair: int = 0
) -> tuple[XTFFileHeader, list[XTFPingHeader], list[XTFAttitudeData], int, dict[str, int]]:
    """A JSF line as the XTF packets it converts to, for the XTF import's stages.

    Returns ``(file_header, pings, attitude, truncated, other_messages)``: the file header
    has two channels (0 port, 1 starboard; the median transmit frequency; no tilt or beam
    width), NavUnits 3 (lon/lat) or 0 (metres); each ping carries the sonar position,
    depth, altitude (0 = missing), heading / pitch / roll (NaN = missing), sound speed
    (0 = missing), the time rounded to 10 ms, and the samples (port outward-to-nadir, as XTF
    stores it; ``TimeDelay`` / ``TimeDuration`` from the window offset and sample interval,
    ``SlantRange`` 0 so that the import's sound speed sets the range). The pitch/roll
    messages become attitude packets only when some ping lacks a valid heading or
    pitch/roll (the import then interpolates them to every ping time).
    """
    path = Path(path)
    line = read_jsf(path, channel_pair)
    header = XTFFileHeader()
    header.RecordingProgramName = b"jsf"
    header.SonarName = f"JSF subsystem {line.subsystem}".encode()[:16]
    header.NavUnits = 3 if line.units == "latlon" else 0
    header.NumberOfSonarChannels = 2
    header.ThisFileName = path.name.encode()[:64]
    freq = line.frequency_hz[np.isfinite(line.frequency_hz)]
    for i, ctype in enumerate((XTFChannelType.port, XTFChannelType.stbd)):
        info = header.ChanInfo[i]
        info.TypeOfChannel = int(ctype)
        info.SubChannelNumber = i
        info.Frequency = float(np.median(freq)) / 1e3 if freq.size else 0.0

    centis = np.round(line.time_s * 100.0).astype(np.int64)
    pings: list[XTFPingHeader] = []
    for k in range(line.n_pings):
        secs, hsec = divmod(int(centis[k]), 100)
        when = _dt.datetime.fromtimestamp(secs, tz=_dt.timezone.utc)
        p = XTFPingHeader()
        p.NumChansToFollow = 2
        p.Year, p.Month, p.Day = when.year, when.month, when.day
        p.Hour, p.Minute, p.Second, p.HSeconds = when.hour, when.minute, when.second, hsec
        p.JulianDay = when.timetuple().tm_yday
        p.PingNumber = int(line.ping_number[k]) & 0xFFFFFFFF
        sv = line.sound_speed_mps[k]
        p.SoundVelocity = float(sv) if np.isfinite(sv) else 0.0
        p.SensorXcoordinate = float(line.x[k])
        p.SensorYcoordinate = float(line.y[k])
        p.SensorDepth = float(line.depth_m[k])
        alt = line.altitude_m[k]
        p.SensorPrimaryAltitude = float(alt) if np.isfinite(alt) else 0.0
        p.SensorHeading = float(line.heading_deg[k])
        p.SensorPitch, p.SensorRoll = float(line.pitch_deg[k]), float(line.roll_deg[k])
        p.ping_chan_headers, p.data = [], []
        for number, chan in ((0, line.port[k]), (1, line.starboard[k])):
            if chan is None:
                continue
            ch = XTFPingChanHeader()
            ch.ChannelNumber = number
            ch.TimeDelay = chan.start_s
            ch.TimeDuration = chan.samples.size * chan.interval_s
            ch.NumSamples = chan.samples.size
            ch.Frequency = min(int(round(info.Frequency)), 65535)
            p.ping_chan_headers.append(ch)
            p.data.append(chan.samples[::-1] if number == 0 else chan.samples)
        pings.append(p)

    attitude: list[XTFAttitudeData] = []
    missing = ~(
        np.isfinite(line.heading_deg) & np.isfinite(line.pitch_deg) & np.isfinite(line.roll_deg)
    )
    if missing.any() and line.attitude:
        a = line.attitude
        for ti, hd, pt, rl in zip(a["time_s"], a["heading"], a["pitch"], a["roll"], strict=True):
            secs = int(math.floor(ti))
            rec = XTFAttitudeData()
            rec.SourceEpoch = secs
            rec.EpochMicroseconds = int(round((ti - secs) * 1e6))
            rec.Heading, rec.Pitch, rec.Roll = float(hd), float(pt), float(rl)
            attitude.append(rec)
    other = dict(line.other_messages)
    if line.attitude and not attitude:
        other["pitch_roll_unused"] = int(line.attitude["time_s"].size)
    return header, pings, attitude, line.truncated, other


# ----------------------------------------------------------------------------- writer
def _transformer(src: str, dst: str):
    from pyproj import Transformer

    return Transformer.from_crs(src, dst, always_xy=True)


def _message(mtype: int, subsystem: int, channel: int, body: bytes) -> bytes:
    head = np.zeros(1, MESSAGE_HEADER)
    head["marker"], head["version"], head["type"] = START_MARKER, 16, mtype
    head["command"], head["subsystem"], head["channel"] = 2, subsystem, channel
    head["size"] = len(body)
    return head.tobytes() + body


def write_jsf(
    line: SidescanLine,
    path: str | Path,
    origin: Mapping[str, Any] | None = None,
    *,
    nav_units: str = "auto",
    epoch_s: float | None = None,
    subsystem: int = 21,
    ping_attitude: bool = True,
    attitude_messages: bool = False,
    data_format: int = 0,
) -> dict[str, Any]:
    """Write a survey line as a JSF file (one sonar data message per ping and side),
    atomically. For test fixtures: only the fields :func:`read_jsf` reads are filled.

    Args:
        line: any line; ``range_m`` uniformly spaced, starting a whole number of bins from 0.
        path: output ``.jsf``.
        origin: ``{"crs", "easting", "northing"}`` of the line's local frame.
        nav_units: ``"latlon"`` (minutes of arc x 10000, needs ``origin["crs"]``),
            ``"metres"`` (mm where they fit an int32, else cm) or ``"auto"`` (latlon when the
            origin has a CRS).
        epoch_s: UNIX time added to ``line.time_s``; default 2000-01-01T00:00:00Z when the
            line's times are earlier than that, else 0.
        subsystem: the sonar data subsystem (20, 21, 22 sidescan; 0 sub-bottom).
        ping_attitude: write heading, pitch and roll in the pings (else their validity bits
            are clear).
        attitude_messages: also write a pitch/roll message (2020) at every ping time and half
            a ping period after the last.
        data_format: 0 (envelope, uint16) or 1 (analytic signal: int16 real and imaginary
            parts of the intensity at a phase advancing 0.7 rad per sample).

    Stored: per ping and side the largest weighting factor N that fits the largest sample
    in uint16 (int16 parts for the analytic format), samples ``round(I * 2^N)`` (so each is
    within ``max / 65535`` of ``I``; ``max / 32767`` for the analytic format's magnitude;
    negative / non-finite intensities are written as 0 and counted); the sample interval in
    whole nanoseconds; NaN altitude as 0 with its validity bit clear; times to 1 ms.

    Returns:
        ``{"epoch_s", "nav_units", "sample_interval_ns", "clipped_samples", "pings"}``.
    """
    path = Path(path)
    if nav_units not in ("auto", "latlon", "metres"):
        raise ValueError(f"nav_units: expected 'auto', 'latlon' or 'metres', found {nav_units!r}")
    if data_format not in DATA_FORMATS:
        raise ValueError(
            f"data_format: expected one of {sorted(DATA_FORMATS)}, found {data_format}"
        )
    if not 0 <= subsystem <= 255:
        raise ValueError(f"subsystem: expected 0..255, found {subsystem}")
    origin = dict(origin or {})
    crs = origin.get("crs")
    easting, northing = float(origin.get("easting", 0.0)), float(origin.get("northing", 0.0))
    units = ("latlon" if crs else "metres") if nav_units == "auto" else nav_units
    if units == "latlon" and not crs:
        raise ValueError("origin: expected a 'crs' to write geographic positions, found none")
    r = np.asarray(line.range_m, dtype=np.float64)
    dr = float((r[-1] - r[0]) / (r.size - 1)) if r.size > 1 else 0.0
    if r.size < 2 or np.max(np.abs(np.diff(r) - dr)) > 1e-4 * dr + 1e-6:
        raise ValueError(
            "line.range_m: expected >= 2 uniformly spaced bins (JSF has a sample interval)"
        )
    first = (r[0] - dr / 2) / dr
    if abs(first - round(first)) > 1e-3:
        raise ValueError(
            f"line.range_m: expected bins starting a whole number of bins from 0, found "
            f"{r[0] - dr / 2:.4f} m = {first:.3f} bins"
        )
    c = float(line.sensor.sound_speed_mps)
    interval_ns = int(round(2.0 * dr / c * 1e9))
    if interval_ns < 1:
        raise ValueError(f"line.range_m: expected bins of at least 1 ns, found {dr} m")

    if epoch_s is None:
        epoch_s = DEFAULT_EPOCH_S if line.time_s[0] < DEFAULT_EPOCH_S else 0.0
    ms = np.round((line.time_s + epoch_s) * 1000.0).astype(np.int64)
    if np.any(np.diff(ms) <= 0) or ms[0] < 0:
        raise ValueError("line.time_s: expected pings after 1970, at least 1 ms apart")

    x = line.position[:, 0] + easting
    y = line.position[:, 1] + northing
    if units == "latlon":
        lon, lat = _transformer(crs, "EPSG:4326").transform(x, y)
        code, xs = UNITS_LATLON, np.round(np.asarray(lon) * 600000.0)
        ys = np.round(np.asarray(lat) * 600000.0)
    else:
        fits = max(np.abs(x).max(), np.abs(y).max()) * 1000.0 < 2**31 - 1
        code = 1 if fits else 4
        xs = np.round(x / METRES_PER_UNIT[code])
        ys = np.round(y / METRES_PER_UNIT[code])
    heading, pitch, roll = (np.degrees(np.asarray(a)) for a in rotation_to_attitude(line.rotation))
    heading = np.mod(heading, 360.0)

    intensity = np.asarray(line.intensity, dtype=np.float64)
    bad = ~np.isfinite(intensity) | (intensity < 0)
    clipped = int(bad.sum())
    if clipped:
        log.warning("%s: %d negative/non-finite intensities written as 0", path.name, clipped)
    intensity = np.where(bad, 0.0, intensity)

    freq_dahz = int(round(line.sensor.frequency_hz / 10.0))
    if not 0 < freq_dahz < 2**20:
        raise ValueError(
            f"line.sensor.frequency_hz: expected 10 Hz..10.4 GHz, found {freq_dahz * 10}"
        )
    P, B = line.n_pings, line.n_bins
    validity = (1 << BIT_POSITION) | (1 << BIT_DEPTH) | (1 << BIT_SOUND_SPEED)
    if ping_attitude:
        validity |= (1 << BIT_HEADING) | (1 << BIT_PITCH_ROLL)
    full = 65535.0 if data_format == 0 else 32767.0
    with atomic_path(path) as tmp, open(tmp, "wb") as f:
        for k in range(P):
            secs = int(ms[k] // 1000)
            when = _dt.datetime.fromtimestamp(secs, tz=_dt.timezone.utc)
            h = np.zeros(1, SONAR_HEADER)
            h["ping_time_s"] = secs
            h["starting_depth"] = int(round(first))
            h["ping_number"] = k + 1
            h["msb"] = (freq_dahz >> 16) | ((freq_dahz >> 16) << 4) | ((B >> 16) << 8)
            h["id_code"] = 1
            h["data_format"] = data_format
            h["x"], h["y"], h["coordinate_units"] = int(xs[k]), int(ys[k]), code
            h["samples"] = B & 0xFFFF
            h["sample_interval_ns"] = interval_ns
            h["start_frequency_dahz"] = h["end_frequency_dahz"] = freq_dahz & 0xFFFF
            h["depth_mm"] = int(round(-line.position[k, 2] * 1000.0))
            alt = float(line.altitude_m[k])
            v = validity
            if math.isfinite(alt) and alt > 0:
                h["altitude_mm"] = int(round(alt * 1000.0))
                v |= 1 << BIT_ALTITUDE
            h["validity"] = v
            h["sound_speed_mps"] = c
            h["year"], h["day"] = when.year, when.timetuple().tm_yday
            h["hour"], h["minute"], h["second"] = when.hour, when.minute, when.second
            h["time_basis"] = 3
            if ping_attitude:
                h["heading_cdeg"] = int(round(heading[k] * 100.0)) % 36000
                h["pitch"] = int(round(pitch[k] / ANGLE_SCALE))
                h["roll"] = int(round(roll[k] / ANGLE_SCALE))
            h["ms_today"] = int(ms[k] % 86_400_000)
            h["packet_number"] = 1
            for side in (PORT, STARBOARD):
                vals = intensity[k, side]
                top = float(vals.max())
                n_w = int(math.floor(math.log2(full / top))) if top > 0 else 0
                n_w = max(min(n_w, 32767), -32768)
                if data_format == 0:
                    codes = np.clip(np.round(vals * 2.0**n_w), 0, full).astype("<u2")
                else:
                    parts = vals * 2.0**n_w * np.exp(0.7j * np.arange(B))
                    pairs = np.stack([parts.real, parts.imag], axis=1)
                    codes = np.clip(np.round(pairs), -full, full).astype("<i2")
                h["weighting"] = n_w
                f.write(_message(SONAR_DATA, subsystem, side, h.tobytes() + codes.tobytes()))
        if attitude_messages:
            period = float(np.median(np.diff(ms))) if P > 1 else 100.0
            stamps = np.concatenate([ms, [ms[-1] + max(int(period // 2), 1)]])
            att = np.concatenate(
                [np.stack([heading, pitch, roll], 1), [[heading[-1], pitch[-1], roll[-1]]]]
            )
            for stamp, (hd, pt, rl) in zip(stamps, att, strict=True):
                a = np.zeros(1, PITCH_ROLL)
                a["time_s"], a["ms"] = int(stamp // 1000), int(stamp % 1000)
                a["pitch"] = int(round(pt / ANGLE_SCALE))
                a["roll"] = int(round(rl / ANGLE_SCALE))
                a["heading_cdeg"] = int(round(hd * 100.0)) % 36000
                a["validity"] = (1 << PR_BIT_PITCH) | (1 << PR_BIT_ROLL) | (1 << PR_BIT_HEADING)
                f.write(_message(PITCH_ROLL_DATA, 0, 0, a.tobytes()))
    return {
        "epoch_s": float(epoch_s),
        "nav_units": units,
        "sample_interval_ns": interval_ns,
        "clipped_samples": clipped,
        "pings": P,
    }
