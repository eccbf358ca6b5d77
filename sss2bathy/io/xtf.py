"""XTF (eXtended Triton Format) sidescan in and out, through pyxtf's ctypes structures.

Reading walks the packets itself (so a bad packet can be named by its ping index and a
truncated tail can be skipped) and parses each packet with pyxtf's own classes
(``XTFFileHeader``, ``XTFPingHeader``, ``XTFAttitudeData``). Writing builds the same
structures and serialises them with their ``to_bytes``; ``pyxtf.xtf_read`` reads the result.

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

import calendar
import ctypes
import datetime as _dt
import logging
import math
import mmap
import os
import warnings
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from pyxtf import (
    XTFAttitudeData,
    XTFChannelType,
    XTFFileHeader,
    XTFHeaderType,
    XTFPacketStart,
    XTFPingChanHeader,
    XTFPingHeader,
)
from scipy.ndimage import median_filter

from sss2bathy.geometry import attitude_to_rotation, rotation_to_attitude
from sss2bathy.io.bottom import (
    bad_pings,
    calibrate_to_altimeter,
    detect_first_return,
    detector_accuracy,
)
from sss2bathy.io.jsf import jsf_as_xtf, read_jsf_sensor
from sss2bathy.io.xtf_checks import (
    AltimeterCheck,
    beam_vs_data,
    check_altimeter,
    implausible_altitude,
    max_beam_edge_scale,
    nav_units_mismatch,
    reversed_heading_runs,
    speed_outliers,
)
from sss2bathy.survey import SensorParams, SidescanLine, SurveyFormatError
from sss2bathy.survey.model import (
    ALTITUDE_DETECTED,
    ALTITUDE_INTERPOLATED,
    ALTITUDE_MISSING,
    ALTITUDE_RECORDED,
)
from sss2bathy.utils.atomic import atomic_path

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

NAV_UNITS_METRES = 0
NAV_UNITS_LATLON = 3
FILE_HEADER_BYTES = 1024
MAGIC = 0xFACE
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


# ----------------------------------------------------------------------------- projection
def utm_crs_for(lon: float, lat: float) -> str:
    """``EPSG:326zz`` (north) / ``EPSG:327zz`` (south): the WGS 84 UTM zone holding (lon, lat).

    Zones are the regular 6-degree bands (the Norway/Svalbard exceptions are not applied).
    """
    if not (math.isfinite(lon) and math.isfinite(lat) and abs(lat) <= 90 and abs(lon) <= 180):
        raise ValueError(f"lon/lat: expected a geographic position, found ({lon}, {lat})")
    zone = min(int(math.floor((lon + 180.0) / 6.0)) + 1, 60)
    return f"EPSG:{32600 + zone if lat >= 0 else 32700 + zone}"


def _transformer(src: str, dst: str):
    from pyproj import Transformer

    return Transformer.from_crs(src, dst, always_xy=True)


def _same_crs(a: Any, b: Any) -> bool:
    from pyproj import CRS

    return CRS.from_user_input(a) == CRS.from_user_input(b)


def _crs_string(crs: Any) -> str | None:
    """A compact, round-trippable CRS string (``EPSG:nnnn`` where possible, else WKT)."""
    if crs is None:
        return None
    from pyproj import CRS

    c = CRS.from_user_input(crs)
    epsg = c.to_epsg(min_confidence=90)
    return f"EPSG:{epsg}" if epsg else c.to_wkt()


# ----------------------------------------------------------------------------- parsing
@dataclass(frozen=True)
class _FileSamples:
    """Where one channel's samples lie in the file (read when resampled, not when parsed)."""

    offset: int
    dtype: np.dtype
    size: int

    @property
    def nbytes(self) -> int:
        return self.size * self.dtype.itemsize


@dataclass
class _Channel:
    """One side of one ping: its samples as stored (an array, or where they lie in the file)
    and what turns them into intensities (:meth:`load`)."""

    data: np.ndarray | _FileSamples
    scale: float
    flip: bool
    r_start: float
    r_end: float

    @property
    def size(self) -> int:
        return int(self.data.size)

    def load(self, fd: int | None) -> np.ndarray:
        """float64 samples scaled by ``scale``, bin 0 nearest the sonar (``fd``: the file,
        for samples not in memory)."""
        data = self.data
        if isinstance(data, _FileSamples):
            raw = os.pread(fd, data.nbytes, data.offset)
            data = np.frombuffer(raw, dtype=data.dtype, count=data.size)
        samples = data.astype(np.float64) * self.scale
        return samples[::-1] if self.flip else samples


@dataclass
class _Parsed:
    header: XTFFileHeader
    pings: list[XTFPingHeader]
    attitude: list[XTFAttitudeData]
    truncated: int
    other_packets: dict[str, int]
    # damaged byte ranges [start, end) skipped by re-synchronising, with the count of sonar
    # pings read before each
    damaged: list[tuple[int, int, int]]


_MAGIC_BYTES = MAGIC.to_bytes(2, "little")
# parsing hands back the pages of the file it has read past every this many bytes
_RELEASE_BYTES = 64 << 20
# samples resampled at a time (bytes of float64 samples): bounds the memory of the resampling
_RESAMPLE_BYTES = 32 << 20


def _packet_size(raw, pos: int, size: int, n_start: int, chained: bool = True) -> int | None:
    """Record size of a plausible packet at ``pos``: magic 0xFACE, a size that fits the file
    and (``chained``) is followed by the next packet's magic or the end of the file; else
    None."""
    if size - pos < n_start or raw[pos : pos + 2] != _MAGIC_BYTES:
        return None
    n_bytes = int.from_bytes(raw[pos + 10 : pos + 14], "little")
    end = pos + n_bytes
    if n_bytes < n_start or end > size:
        return None
    if not chained or end == size or size - end < n_start or raw[end : end + 2] == _MAGIC_BYTES:
        return n_bytes
    return None


def _next_packet(raw, start: int, size: int, n_start: int) -> int | None:
    """Offset of the next plausible packet at or after ``start`` (re-synchronisation)."""
    q = raw.find(_MAGIC_BYTES, start)
    while q != -1:
        if _packet_size(raw, q, size, n_start) is not None:
            return q
        q = raw.find(_MAGIC_BYTES, q + 1)
    return None


def _parse_packets(path: Path, channel_pair: int) -> _Parsed:
    if path.suffix.lower() == ".jsf":  # Edgetech JSF, as the XTF packets it converts to
        return _Parsed(*jsf_as_xtf(path, channel_pair), damaged=[])
    size = path.stat().st_size
    if size < FILE_HEADER_BYTES:
        raise SurveyFormatError(
            path, "file header", f"at least {FILE_HEADER_BYTES} bytes", f"{size} bytes (truncated)"
        )
    pings: list[XTFPingHeader] = []
    attitude: list[XTFAttitudeData] = []
    other: dict[str, int] = {}
    damaged: list[tuple[int, int, int]] = []
    truncated = 0
    n_start = ctypes.sizeof(XTFPacketStart)
    with open(path, "rb") as f, mmap.mmap(f.fileno(), 0, access=mmap.ACCESS_READ) as raw:
        header = XTFFileHeader.create_from_buffer(f)
        if header.FileFormat != 0x7B:
            raise SurveyFormatError(
                path, "FileFormat", "0x7B (an XTF file)", hex(header.FileFormat)
            )
        if header.channel_count() > 6:
            raise SurveyFormatError(
                path, "file header", "at most 6 channels (pyxtf)", header.channel_count()
            )
        _sidescan_channels(header, path, channel_pair)  # refuse before parsing any ping
        pos = FILE_HEADER_BYTES
        released = 0  # the pages of the map before this offset are handed back
        while pos < size:
            if pos - released >= _RELEASE_BYTES:
                # the map's pages read so far count in the process's memory until released
                raw.madvise(mmap.MADV_DONTNEED, released, pos - pos % mmap.PAGESIZE - released)
                released = pos - pos % mmap.PAGESIZE
            n_bytes = _packet_size(raw, pos, size, n_start)
            resume = nxt = None
            if n_bytes is None:
                # A damaged packet (bad magic or size) or a cut final one: re-synchronise on
                # the next plausible packet header; none left means the file ends here.
                nxt = _next_packet(raw, pos + 1, size, n_start)
                own = _packet_size(raw, pos, size, n_start, chained=False)
                if own is not None and (nxt is None or nxt >= pos + own):
                    # this packet is whole; the damage starts after it
                    n_bytes, resume = own, size if nxt is None else nxt
            if n_bytes is None:
                if nxt is None:
                    stated = int.from_bytes(raw[pos + 10 : pos + 14], "little")
                    cut = raw[pos : pos + 2] == _MAGIC_BYTES and (
                        size - pos < n_start or pos + stated > size
                    )
                    if cut or size - pos < n_start:
                        truncated += 1
                    else:
                        damaged.append((pos, size, len(pings)))
                    break
                damaged.append((pos, nxt, len(pings)))
                pos = nxt
                continue
            f.seek(pos)
            start = XTFPacketStart.from_buffer_copy(raw[pos : pos + n_start])
            if start.HeaderType == XTFHeaderType.sonar:
                pings.append(_parse_ping(f, header, path, len(pings)))
            elif start.HeaderType == XTFHeaderType.attitude and n_bytes >= ctypes.sizeof(
                XTFAttitudeData
            ):
                attitude.append(XTFAttitudeData.create_from_buffer(f))
            else:
                try:
                    name = XTFHeaderType(start.HeaderType).name
                except ValueError:
                    name = f"type_{start.HeaderType}"
                other[name] = other.get(name, 0) + 1
            if resume is not None:
                damaged.append((pos + n_bytes, resume, len(pings)))
            pos = pos + n_bytes if resume is None else resume
    if truncated:
        log.warning("%s: skipped a truncated final packet (file cut short)", path)
    if damaged:
        _report_damage(path, size, pings, damaged)
    return _Parsed(header, pings, attitude, truncated, other, damaged)


def _report_damage(
    path: Path, size: int, pings: list[XTFPingHeader], damaged: list[tuple[int, int, int]]
) -> None:
    """One WARNING naming the damaged byte ranges and the pings lost; refuse when most of the
    file is damaged."""
    lost_bytes = sum(b - a for a, b, _ in damaged)
    ranges = ", ".join(
        f"bytes {a}-{b} ({f'after sonar ping {k - 1}' if k else 'before the first ping'})"
        for a, b, k in damaged[:3]
    ) + (f" and {len(damaged) - 3} more" if len(damaged) > 3 else "")
    if lost_bytes > 0.5 * (size - FILE_HEADER_BYTES):
        raise SurveyFormatError(
            path,
            "packets",
            "a readable file (at most half of its packets damaged)",
            f"{lost_bytes} of {size - FILE_HEADER_BYTES} bytes damaged ({ranges})",
        )
    record = int(np.median([p.NumBytesThisRecord for p in pings])) if pings else 0
    lost = 0
    for a, b, k in damaged:
        gap = None
        if 0 < k < len(pings):  # ping numbers on both sides of the damage
            gap = int(pings[k].PingNumber) - int(pings[k - 1].PingNumber) - 1
        estimate = math.ceil((b - a) / record) if record else 0
        lost += gap if gap is not None and 0 <= gap <= 2 * estimate + 1 else estimate
    log.warning(
        "%s: damaged packets (bad 0xFACE magic or record size): %s; re-synchronised on the "
        "next valid packet header, about %d sonar pings lost, %d read",
        path.name,
        ranges,
        lost,
        len(pings),
    )


def _parse_ping(f, header: XTFFileHeader, path: Path, index: int) -> XTFPingHeader:
    """The sonar ping at ``f``'s position, parsed and checked by pyxtf; its ``data`` are
    :class:`_FileSamples` (where each channel's samples lie), so that the pings of a line
    hold no samples and a file of any size is parsed in bounded memory."""
    pos = f.tell()
    try:
        ping = XTFPingHeader.create_from_buffer(f, file_header=header)
    except (RuntimeError, ValueError, IndexError, KeyError) as exc:
        raise SurveyFormatError(path, f"ping {index}", "a readable sonar ping", exc) from None
    offset = pos + ctypes.sizeof(XTFPingHeader)
    where = []
    for chan, data in zip(ping.ping_chan_headers, ping.data, strict=True):
        if chan.NumSamples and data.size != chan.NumSamples:
            raise SurveyFormatError(
                path,
                f"ping {index} channel {chan.ChannelNumber}",
                f"{chan.NumSamples} samples",
                f"{data.size} (corrupt or truncated record)",
            )
        offset += ctypes.sizeof(XTFPingChanHeader)
        where.append(_FileSamples(offset, data.dtype, int(data.size)))
        offset += data.nbytes
    ping.data = where
    return ping


def _ping_time(p: XTFPingHeader, path: Path, index: int) -> float:
    try:
        t = calendar.timegm(
            _dt.datetime(p.Year, p.Month, p.Day, p.Hour, p.Minute, p.Second).timetuple()
        )
    except ValueError as exc:
        raise SurveyFormatError(path, f"ping {index}: time", "a valid date and time", exc) from None
    if p.HSeconds > 99:
        raise SurveyFormatError(path, f"ping {index}: HSeconds", "0..99", p.HSeconds)
    return float(t) + p.HSeconds / 100.0


def _attitude_time(a: XTFAttitudeData) -> float:
    if a.SourceEpoch:
        return float(a.SourceEpoch) + a.EpochMicroseconds * 1e-6
    t = calendar.timegm(
        _dt.datetime(a.Year, a.Month, a.Day, a.Hour, a.Minute, a.Second).timetuple()
    )
    return float(t) + a.Millisecond * 1e-3


def _sidescan_channels(header: XTFFileHeader, path: Path, channel_pair: int) -> tuple[int, int]:
    n = int(header.NumberOfSonarChannels)
    types = [int(header.ChanInfo[i].TypeOfChannel) for i in range(min(n, 6))]
    ports = [i for i, t in enumerate(types) if t == XTFChannelType.port]
    stbds = [i for i, t in enumerate(types) if t == XTFChannelType.stbd]
    if not ports or not stbds:
        raise SurveyFormatError(
            path,
            "ChanInfo",
            "a port (type 1) and a starboard (type 2) sidescan channel",
            f"{n} sonar channels of types {types}",
        )
    if channel_pair >= min(len(ports), len(stbds)) or channel_pair < 0:
        raise SurveyFormatError(
            path,
            "channel_pair",
            f"a pair index below {min(len(ports), len(stbds))}",
            channel_pair,
        )
    return ports[channel_pair], stbds[channel_pair]


def _sample_scale(info, dtype: np.dtype) -> float:
    if np.issubdtype(dtype, np.integer) and info.VoltScale > 0:
        return float(info.VoltScale) / float(np.iinfo(dtype).max)
    return 1.0


def _channel(
    ping: XTFPingHeader, chan_no: int, header: XTFFileHeader, c: float, flip: bool
) -> _Channel | None:
    for ch, data in zip(ping.ping_chan_headers, ping.data, strict=True):
        if ch.ChannelNumber != chan_no:
            continue
        n = data.size
        if n < 1:
            return None
        scale = _sample_scale(header.ChanInfo[chan_no], data.dtype) * 2.0 ** (-ch.Weight)
        r_start = max(float(ch.TimeDelay), 0.0) * c / 2.0
        r_end = float(ch.SlantRange)
        if not (math.isfinite(r_end) and r_end > r_start):
            r_end = (max(float(ch.TimeDelay), 0.0) + float(ch.TimeDuration)) * c / 2.0
        if not (math.isfinite(r_end) and r_end > r_start):
            return _Channel(data, scale, flip, r_start, math.nan)
        return _Channel(data, scale, flip, r_start, r_end)
    return None


# ----------------------------------------------------------------------------- resampling
def _resample_group(
    samples: np.ndarray, r_start: float, r_end: float, edges: np.ndarray
) -> np.ndarray:
    """Area-weighted resampling of ``(K, N)`` samples on ``[r_start, r_end]`` onto ``edges``.

    Each sample is the mean over its range cell; an output bin is the mean over the part of
    it the recording covers (0 where it covers nothing).
    """
    K, N = samples.shape
    u = (edges - r_start) / (r_end - r_start) * N  # output edges in sample units
    u = np.where(np.abs(u - np.round(u)) < 1e-9, np.round(u), u)
    u = np.clip(u, 0.0, N)
    cum = np.concatenate([np.zeros((K, 1)), np.cumsum(samples, axis=1)], axis=1)
    i0 = np.minimum(np.floor(u).astype(np.int64), N - 1)
    w = u - i0
    at = cum[:, i0] * (1.0 - w) + cum[:, i0 + 1] * w  # (K, M + 1)
    cover = np.diff(u)
    out = np.diff(at, axis=1)
    return np.where(cover > 0, out / np.where(cover > 0, cover, 1.0), 0.0)


def _resample_side(
    chans: list[_Channel], edges: np.ndarray, out: np.ndarray, fd: int | None
) -> int:
    """Resample every ping's samples onto the output bin edges into ``out`` ``(P, M)``, a few
    megabytes of samples at a time (read from the file ``fd`` where they are not in memory);
    returns the count of range settings (groups of pings on the same recording window)."""
    keys = [(c.r_start, c.r_end, c.size) for c in chans]
    groups: dict[tuple, list[int]] = {}
    for i, k in enumerate(keys):
        groups.setdefault(k, []).append(i)
    for (r0, r1, n), idx in groups.items():
        step = max(1, _RESAMPLE_BYTES // (8 * max(n, 1)))
        for a in range(0, len(idx), step):
            part = idx[a : a + step]
            block = np.stack([chans[i].load(fd) for i in part])
            out[part] = _resample_group(block, r0, r1, edges)
    return len(groups)


# ----------------------------------------------------------------------------- navigation
def _interp_gaps(t: np.ndarray, values: np.ndarray, valid: np.ndarray) -> np.ndarray:
    """Linear-in-time interpolation of ``(P, K)`` values where ``valid`` is False."""
    out = values.copy()
    for k in range(values.shape[1]):
        out[~valid, k] = np.interp(t[~valid], t[valid], values[valid, k])
    return out


def _check_nav(
    path: Path,
    t: np.ndarray,
    xy: np.ndarray,
    valid: np.ndarray,
    max_jump_m: float,
    max_speed_mps: float,
    ping_ids: np.ndarray,
) -> tuple[np.ndarray, int, float]:
    """Drop outlier fixes (-> gaps), refuse jumps and too many outliers.

    Outliers: fixes farther than ``max_jump_m`` from the running median of their neighbours,
    and fixes that left the track faster than ``max_speed_mps``
    (:func:`~sss2bathy.io.xtf_checks.speed_outliers`). Returns the updated validity mask, the
    outlier count and their largest implied speed (m/s; 0 without outliers).
    """
    idx = np.flatnonzero(valid)
    outliers = np.zeros_like(valid)
    if idx.size >= 3:
        win = min(9, idx.size if idx.size % 2 else idx.size - 1)
        med = np.stack([median_filter(xy[idx, k], size=win, mode="nearest") for k in (0, 1)], 1)
        dev = np.linalg.norm(xy[idx] - med, axis=1)
        outliers[idx[dev > max_jump_m]] = True
    fast, speed = speed_outliers(t, xy, valid, max_speed_mps)
    outliers |= fast
    n_valid = int(valid.sum())
    if outliers.sum() > max(0.1 * n_valid, 1):
        j = int(np.argmax(outliers))
        raise SurveyFormatError(
            path,
            "position",
            "at most 10% of the fixes off the track (outliers are interpolated; "
            f"data.survey.max_speed_mps = {max_speed_mps} m/s, data.survey.max_jump_m = "
            f"{max_jump_m} m)",
            f"{int(outliers.sum())} of {n_valid} fixes, the first at ping {ping_ids[j]} "
            f"(implied speeds up to {np.nanmax(np.where(outliers, speed, np.nan)):.0f} m/s)",
        )
    top_speed = float(np.nanmax(np.where(outliers, speed, np.nan))) if outliers.any() else 0.0
    valid = valid & ~outliers
    idx = np.flatnonzero(valid)
    if idx.size >= 2:
        step = np.linalg.norm(np.diff(xy[idx], axis=0), axis=1)
        allowed = max_jump_m + max_speed_mps * np.diff(t[idx])
        bad = np.flatnonzero(step > allowed)
        if bad.size:
            j = idx[bad[0] + 1]
            raise SurveyFormatError(
                path,
                f"ping {ping_ids[j]}: position",
                f"a step below {allowed[bad[0]]:.0f} m (data.survey.max_jump_m + "
                "data.survey.max_speed_mps * dt)",
                f"a jump of {step[bad[0]]:.0f} m in {t[j] - t[idx[bad[0]]]:.2f} s",
            )
    return valid, int(outliers.sum()), top_speed


def _unwrap_deg(a: np.ndarray) -> np.ndarray:
    return np.degrees(np.unwrap(np.radians(a)))


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
    port, stbd = _sidescan_channels(header, path, channel_pair)
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
    sv = np.array([p.SoundVelocity for p in pings], dtype=np.float64)
    sv = np.where((sv > 0) & (sv < 1000.0), 2.0 * sv, sv)  # Isis: one-way (half) speed
    ok = np.isfinite(sv) & (sv >= 1300.0) & (sv <= 1800.0)
    return np.where(ok, sv, np.nan), (float(np.median(sv[ok])) if ok.any() else None)


# ----------------------------------------------------------------------------- altitude
@dataclass
class _Altitude:
    """The altitude of a line and how it was made (:func:`_resolve_altitude`)."""

    altitude: np.ndarray  # (P,) m, NaN = none
    source: np.ndarray  # (P,) ALTITUDE_* codes
    check: AltimeterCheck | None  # altimeter vs first return (None: too few pings with both)
    beyond_range: int  # altimeter values above the slant range, rejected
    jumps: int  # altimeter jumps off their neighbours and the first return, rejected
    shifted: int  # filled pings shifted by the nearby altimeter - first return offset
    shift_m: float  # applied to every altimeter value (altitude_offset: apply)
    accuracy: list[float] | None  # [median, max] |error| (m) of the fills, cross-validated
    abs_diff_m: float | None  # median |altimeter - first return|


def _resolve_altitude(
    path: Path,
    altitude: np.ndarray,
    picks: Any,
    t: np.ndarray,
    max_range_m: float,
    sensor: SensorParams,
    tolerance_m: float | None,
    offset_mode: str,
) -> _Altitude:
    """Altimeter where plausible, the calibrated first bottom return elsewhere; refuses an
    altimeter whose disagreement with the first return is not one offset (or beam-edge scale).
    """
    fr = picks.altitude_m
    fr_picked = np.where(picks.picked, fr, np.nan)
    ok = np.isfinite(altitude) & (altitude > 0)
    max_scale = max_beam_edge_scale(sensor.tilt_rad, sensor.beam_width_rad)
    floor = tolerance_m if tolerance_m is not None else 1.0

    def cross_check(valid: np.ndarray) -> AltimeterCheck | None:
        return check_altimeter(
            np.where(valid, altitude, np.nan), fr_picked, t, tolerance_m, max_scale
        )

    check = cross_check(ok)
    bad = implausible_altitude(altitude, ok, fr_picked, check, max_range_m, floor)
    rejected = bad["beyond_range"] | bad["jump"]
    if rejected.any():
        ok &= ~rejected
        check = cross_check(ok)
    if check is not None and check.model is None:
        raise SurveyFormatError(
            path,
            "SensorPrimaryAltitude",
            "an altimeter that agrees with the first bottom return up to one offset (spread "
            f"and drift within data.survey.altitude_tolerance_m = {tolerance_m} m; null skips "
            "the check)",
            f"altimeter - first return {check.offset_m:+.2f} m median on {check.n} pings with "
            f"spread {check.sigma_m:.2f} m and drift {check.drift_m:+.2f} m over the line (nor "
            f"a beam-edge first return: {check.scale:.2f} x altimeter {check.intercept_m:+.2f} m "
            f"leaves spread {check.scale_sigma_m:.2f} m, drift {check.scale_drift_m:+.2f} m)",
        )
    shift = -check.offset_m if offset_mode == "apply" and check is not None else 0.0
    if check is not None:
        _report_altimeter(path, check, sensor, offset_mode)
    altimeter = np.where(ok, altitude + shift, np.nan)
    # fills carry the detector's local error against the altimeter (nearest pings with both)
    repaired, offset = calibrate_to_altimeter(fr, altimeter)
    out = np.where(ok, altimeter, repaired)
    source = np.full(len(out), ALTITUDE_MISSING, dtype=np.uint8)
    source[ok] = ALTITUDE_RECORDED
    source[~ok & picks.picked] = ALTITUDE_DETECTED
    source[~ok & picks.interpolated & np.isfinite(fr)] = ALTITUDE_INTERPOLATED
    accuracy = detector_accuracy(fr_picked, altimeter) if (~ok).any() else None
    both = ok & picks.picked
    return _Altitude(
        altitude=out,
        source=source,
        check=check,
        beyond_range=int(bad["beyond_range"].sum()),
        jumps=int(bad["jump"].sum()),
        shifted=int((~ok & (offset != 0)).sum()),
        shift_m=float(shift),
        accuracy=None if accuracy is None else [accuracy[0], accuracy[1]],
        abs_diff_m=float(np.median(np.abs(altimeter[both] - fr[both]))) if both.any() else None,
    )


def _report_altimeter(
    path: Path, check: AltimeterCheck, sensor: SensorParams, offset_mode: str
) -> None:
    """One line: the altimeter - first return offset, its spread and drift, and its cause."""
    tilt, beam = math.degrees(sensor.tilt_rad), math.degrees(sensor.beam_width_rad)
    if check.model == "beam_edge":
        cause = (
            f"not one offset: first return = {check.scale:.2f} x altimeter "
            f"{check.intercept_m:+.2f} m (residual spread {check.scale_sigma_m:.2f} m) - the "
            "detector picks the edge of the vertical beam rather than nadir (tilt "
            f"{tilt:.0f} deg + beam {beam:.0f} deg / 2 below 90 deg puts it up to "
            f"{check.max_scale / 1.25:.2f}x the altitude away)"
        )
    else:
        cause = (
            "one constant offset: the lever arm between the altimeter and the transducers, "
            "or the detector picking a later edge than the altimeter"
        )
    action = (
        f"altimeter shifted by {-check.offset_m:+.2f} m onto the first return "
        "(data.survey.altitude_offset: apply)"
        if offset_mode == "apply"
        else "altimeter kept, offset stored in the line's import stats "
        "(data.survey.altitude_offset: record)"
    )
    loud = check.model == "beam_edge" or offset_mode == "apply" or abs(check.offset_m) > 0.5
    log.log(
        logging.WARNING if loud else logging.INFO,
        "%s: altimeter - first bottom return %+.2f m (median of %d pings; spread %.2f m, drift "
        "%+.2f m per 100 pings, %+.2f m over the line): %s; %s",
        path.name,
        check.offset_m,
        check.n,
        check.sigma_m,
        check.drift_per_100_m,
        check.drift_m,
        cause,
        action,
    )


def _fill_accuracy(alt: _Altitude, range_m: np.ndarray, sensor: SensorParams) -> str:
    """How accurate the detector fills are, in words (for the repairs WARNING)."""
    if alt.accuracy is not None:
        return (
            "detector fills against the altimeter (cross-validated on pings having both): "
            f"median |error| {alt.accuracy[0]:.2f} m, max {alt.accuracy[1]:.2f} m"
        )
    if alt.check is None and (alt.source == ALTITUDE_RECORDED).sum() == 0:
        bin_m = float(range_m[1] - range_m[0]) if range_m.size > 1 else float("nan")
        top = math.degrees(sensor.tilt_rad + sensor.beam_width_rad / 2)
        edge = f"up to {1 / math.sin(math.radians(top)):.2f}x" if top < 90 else "about 1x"
        return (
            "no altimeter value to check the detector against: expect about one bin "
            f"({bin_m:.3f} m) on flat seabed, absolute offset unknown (where nadir is "
            f"outside the beam the first return is its edge, {edge} the altitude)"
        )
    return "no ping with both altimeter and first return to check the fills against"


def _report_beam(
    path: Path, sides: list[dict[str, Any]], sensor: SensorParams, max_range_m: float
) -> None:
    """One WARNING where the beam limits of the configured tilt / beam width cut bright seabed
    or keep bins without seabed return (:func:`~sss2bathy.io.xtf_checks.beam_vs_data`)."""
    tilt, beam = math.degrees(sensor.tilt_rad), math.degrees(sensor.beam_width_rad)
    parts = []
    for name, side in zip(("port", "starboard"), sides, strict=True):
        if side.get("masked_bright"):
            a, b, k = side["masked_bright"]
            parts.append(
                f"the beam limits mask {a:.2f}x-{b:.2f}x altitude on {name} where the median "
                f"intensity is {k:.1f} times the noise floor"
            )
        if side.get("kept_dark"):
            a, b, k = side["kept_dark"]
            parts.append(
                f"they keep {a:.2f}x-{b:.2f}x altitude on {name} where the median intensity is "
                f"only {k:.1f} times the noise floor (water column / no seabed)"
            )
    if not parts:
        return
    seen = "; ".join(
        f"{name} seabed return from {s['seabed_from']:.2f}x altitude to "
        + (
            f"{s['seabed_to']:.2f}x"
            if s["seabed_to"] is not None
            else f"the {max_range_m:.0f} m range"
        )
        for name, s in zip(("port", "starboard"), sides, strict=True)
        if s.get("seabed_from") is not None
    )
    log.warning(
        "%s: sonar settings vs data: with tilt %.0f deg and beam width %.0f deg (depression "
        "%.0f..%.0f deg) on a flat seabed %s; %s; check data.survey.tilt_deg / "
        "data.survey.beam_width_deg",
        path.name,
        tilt,
        beam,
        tilt - beam / 2,
        tilt + beam / 2,
        ", ".join(parts),
        seen or "no clear seabed return",
    )


# ----------------------------------------------------------------------------- reader
def read_xtf(
    path: str | Path,
    n_bins: int | None = None,
    *,
    origin: Mapping[str, Any] | None = None,
    crs: str | None = None,
    sensor: Mapping[str, float | None] | None = None,
    name: str | None = None,
    channel_pair: int = 0,
    port_far_first: bool = True,
    max_jump_m: float = 200.0,
    max_speed_mps: float = 10.0,
    max_nav_gap_s: float = 30.0,
    missing_attitude: str = "error",
    min_first_return_m: float = 0.0,
    blanking_m: float = 0.0,
    auto_blanking: bool = True,
    altitude_tolerance_m: float | None = 1.0,
    altitude_offset: str = "record",
    nav_units: str = "file",
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

    Returns:
        ``(line, stats)``: ``stats`` holds the origin, CRS, counts of everything interpolated,
        detected or skipped, and the recorded sample geometry.

    Raises:
        SurveyFormatError: one line naming the file (and the ping where there is one).
        ValueError: on bad arguments.
    """
    path = Path(path)
    if n_bins is not None and (not isinstance(n_bins, (int, np.integer)) or n_bins < 2):
        raise ValueError(f"n_bins: expected None or an integer >= 2, found {n_bins!r}")
    if missing_attitude not in MISSING_ATTITUDE:
        raise ValueError(
            f"missing_attitude: expected 'error' or 'track', found {missing_attitude!r}"
        )
    if not isinstance(channel_pair, (int, np.integer)) or channel_pair < 0:
        raise ValueError(f"channel_pair: expected an integer >= 0, found {channel_pair!r}")
    for arg, val in (
        ("max_jump_m", max_jump_m),
        ("max_speed_mps", max_speed_mps),
        ("max_nav_gap_s", max_nav_gap_s),
    ):
        if not val > 0:
            raise ValueError(f"{arg}: expected > 0, found {val}")
    if altitude_tolerance_m is not None and not altitude_tolerance_m > 0:
        raise ValueError(
            f"altitude_tolerance_m: expected null or > 0 (m), found {altitude_tolerance_m}"
        )
    if not (math.isfinite(blanking_m) and blanking_m >= 0):
        raise ValueError(f"blanking_m: expected a distance >= 0 (m), found {blanking_m}")
    if altitude_offset not in ALTITUDE_OFFSET:
        raise ValueError(
            f"altitude_offset: expected one of {ALTITUDE_OFFSET}, found {altitude_offset!r}"
        )
    if nav_units not in NAV_UNITS:
        raise ValueError(f"nav_units: expected one of {NAV_UNITS}, found {nav_units!r}")
    if not path.is_file():
        raise SurveyFormatError(path, "file", "an existing XTF file", "missing file")

    parsed = _parse_packets(path, channel_pair)
    header = parsed.header
    port_no, stbd_no = _sidescan_channels(header, path, channel_pair)
    if not parsed.pings:
        raise SurveyFormatError(path, "sonar pings", "at least 2 sonar pings (type 0)", 0)

    file_units = int(header.NavUnits)
    if nav_units != "file":
        file_units = NAV_UNITS_LATLON if nav_units == "latlon" else NAV_UNITS_METRES
    elif file_units not in (NAV_UNITS_METRES, NAV_UNITS_LATLON):
        raise SurveyFormatError(
            path,
            "NavUnits",
            "0 (metres) or 3 (latitude/longitude) (or set data.survey.nav_units)",
            file_units,
        )
    nav_units_code = file_units

    sv_ping, sv_file = _file_sound_speed(parsed.pings)
    overrides = dict(sensor or {})
    unknown = set(overrides) - set(SENSOR_KEYS)
    if unknown:
        raise ValueError(f"sensor: expected keys among {SENSOR_KEYS}, found {sorted(unknown)}")
    file_sensor = read_xtf_sensor(path, channel_pair)
    sensor_params = _resolve_sensor(path, file_sensor, overrides, sv_file)
    c_default = sv_file if sv_file is not None else sensor_params.sound_speed_mps

    # ---- per-ping fields; pings lacking one of the two sides are skipped
    keep, ports, stbds = [], [], []
    for k, p in enumerate(parsed.pings):
        c = float(sv_ping[k]) if np.isfinite(sv_ping[k]) else c_default
        pc = _channel(p, port_no, header, c, flip=port_far_first)
        sc = _channel(p, stbd_no, header, c, flip=False)
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
    missing_channel = len(parsed.pings) - len(keep)
    if len(keep) < 2:
        raise SurveyFormatError(
            path, "sonar pings", "at least 2 pings with both sidescan channels", len(keep)
        )
    pings = [parsed.pings[k] for k in keep]
    ping_ids = np.asarray(keep)

    t = np.array([_ping_time(p, path, k) for p, k in zip(pings, keep, strict=True)])
    dt = np.diff(t)
    if np.any(dt <= 0):
        j = int(np.argmax(dt <= 0)) + 1
        raise SurveyFormatError(
            path,
            f"ping {ping_ids[j]}: time",
            "strictly increasing ping times",
            f"{t[j] - t[j - 1]:+.2f} s after ping {ping_ids[j - 1]}",
        )

    def field(name_: str) -> np.ndarray:
        return np.array([getattr(p, name_) for p in pings], dtype=np.float64)

    sx, sy = field("SensorXcoordinate"), field("SensorYcoordinate")
    shx, shy = field("ShipXcoordinate"), field("ShipYcoordinate")
    layback = np.nan_to_num(field("Layback"), nan=0.0)
    depth = field("SensorDepth")
    altitude = field("SensorPrimaryAltitude")
    heading, pitch, roll = field("SensorHeading"), field("SensorPitch"), field("SensorRoll")

    # ---- attitude
    attitude_source = "ping_header"
    track_heading_pings = 0
    att = parsed.attitude
    if len(att) >= 2:
        ta = np.array([_attitude_time(a) for a in att])
        order = np.argsort(ta, kind="stable")
        ta = ta[order]
        if ta[0] <= t[0] and ta[-1] >= t[-1] and np.all(np.diff(ta) > 0):
            ah = _unwrap_deg(np.array([att[i].Heading for i in order], dtype=np.float64))
            heading = np.mod(np.interp(t, ta, ah), 360.0)
            pitch = np.interp(t, ta, np.array([att[i].Pitch for i in order], dtype=np.float64))
            roll = np.interp(t, ta, np.array([att[i].Roll for i in order], dtype=np.float64))
            attitude_source = "attitude_packets"
    att_ok = np.isfinite(heading) & np.isfinite(pitch) & np.isfinite(roll)

    # ---- navigation: raw coordinates -> projected -> local
    def plausible(x: np.ndarray, y: np.ndarray) -> np.ndarray:
        ok = np.isfinite(x) & np.isfinite(y) & ~((x == 0) & (y == 0))
        if nav_units_code == NAV_UNITS_LATLON:
            ok &= (np.abs(x) <= 180) & (np.abs(y) <= 90)
        return ok

    has_sensor = np.isfinite(sx) & np.isfinite(sy) & ~((sx == 0) & (sy == 0))
    units_problem = nav_units_mismatch(
        np.where(has_sensor, sx, shx),
        np.where(has_sensor, sy, shy),
        t,
        has_sensor | (np.isfinite(shx) & np.isfinite(shy) & ~((shx == 0) & (shy == 0))),
        latlon=nav_units_code == NAV_UNITS_LATLON,
    )
    if units_problem is not None:
        stated = "latitude/longitude (3)" if nav_units_code == NAV_UNITS_LATLON else "metres (0)"
        source = "NavUnits" if nav_units == "file" else "data.survey.nav_units"
        raise SurveyFormatError(
            path,
            "NavUnits",
            f"coordinates in {stated} as {source} states (set data.survey.nav_units: latlon or "
            "metres when the header is wrong)",
            units_problem,
        )
    sensor_ok = plausible(sx, sy)
    ship_ok = plausible(shx, shy) & ~sensor_ok
    depth_ok = np.isfinite(depth)
    if not (sensor_ok | ship_ok).any():
        raise SurveyFormatError(
            path, "position", "at least one valid sensor or ship position", "none (all 0 or NaN)"
        )

    raw_x, raw_y = np.where(sensor_ok, sx, shx), np.where(sensor_ok, sy, shy)
    if nav_units_code == NAV_UNITS_LATLON:
        source_crs = "EPSG:4326"
        j = int(np.argmax(sensor_ok | ship_ok))
        default_crs = crs or utm_crs_for(float(raw_x[j]), float(raw_y[j]))
    else:
        source_crs = crs if crs is not None else (origin or {}).get("crs")
        default_crs = source_crs
    frame_crs = origin.get("crs") if origin is not None else default_crs
    if nav_units_code == NAV_UNITS_LATLON and frame_crs is None:
        raise SurveyFormatError(
            path, "origin.crs", "a projected CRS for geographic navigation", None
        )
    if source_crs is not None and frame_crs is not None and not _same_crs(source_crs, frame_crs):
        ex, ny_ = _transformer(source_crs, frame_crs).transform(raw_x, raw_y)
        ex, ny_ = np.asarray(ex, dtype=np.float64), np.asarray(ny_, dtype=np.float64)
    else:
        ex, ny_ = raw_x, raw_y
    nav_ok = sensor_ok | ship_ok
    ex, ny_ = np.where(nav_ok, ex, 0.0), np.where(nav_ok, ny_, 0.0)
    if ship_ok.any():
        h = np.radians(np.where(np.isfinite(heading), heading, 0.0))
        ex = np.where(ship_ok, ex - layback * np.sin(h), ex)
        ny_ = np.where(ship_ok, ny_ - layback * np.cos(h), ny_)
    xy = np.stack([ex, ny_], axis=1)
    nav_ok, outliers, outlier_speed = _check_nav(
        path, t, xy, nav_ok, max_jump_m, max_speed_mps, ping_ids
    )
    if nav_ok.sum() < 2:
        raise SurveyFormatError(path, "position", "at least 2 valid fixes", int(nav_ok.sum()))

    # Pings before the first / after the last valid fix cannot be interpolated: skipped.
    first, last = np.flatnonzero(nav_ok)[[0, -1]]
    sl = slice(first, last + 1)
    dropped_nav = len(t) - (last + 1 - first)
    t, xy, nav_ok, depth, depth_ok = t[sl], xy[sl], nav_ok[sl], depth[sl], depth_ok[sl]
    altitude, heading, pitch, roll = altitude[sl], heading[sl], pitch[sl], roll[sl]
    att_ok, ping_ids = att_ok[sl], ping_ids[sl]
    ports, stbds = ports[first : last + 1], stbds[first : last + 1]
    good_t = t[nav_ok]
    gaps = np.diff(good_t)
    if gaps.size and gaps.max() > max_nav_gap_s:
        j = int(np.argmax(gaps))
        after = int(np.flatnonzero(t == good_t[j + 1])[0])
        raise SurveyFormatError(
            path,
            f"ping {ping_ids[after]}: position",
            f"navigation gaps up to data.survey.max_nav_gap_s = {max_nav_gap_s} s",
            f"a gap of {gaps[j]:.1f} s",
        )
    nav_interp = int((~nav_ok).sum())
    if nav_interp:
        xy = _interp_gaps(t, xy, nav_ok)
    depth_interp = int((~depth_ok).sum())
    if depth_interp:
        if not depth_ok.any():
            raise SurveyFormatError(path, "SensorDepth", "finite sensor depths", "all NaN")
        depth = _interp_gaps(t, depth[:, None], depth_ok)[:, 0]

    course = np.mod(
        np.degrees(np.arctan2(np.gradient(xy[:, 0], t), np.gradient(xy[:, 1], t))), 360.0
    )
    why = "missing (NaN)"
    if attitude_source == "ping_header" and np.all((heading == 0) & (pitch == 0) & (roll == 0)):
        # Every attitude field exactly 0: unrecorded, unless the vehicle really heads North.
        off_north = np.abs((course + 180.0) % 360.0 - 180.0)
        if np.median(off_north) > 45.0:
            att_ok[:] = False
            why = f"missing (all 0 while the track heads {float(np.median(course)):.0f} deg)"
    if not att_ok.all():
        if missing_attitude == "error":
            j = int(np.argmax(~att_ok))
            raise SurveyFormatError(
                path,
                f"ping {ping_ids[j]}: attitude",
                "finite SensorHeading/Pitch/Roll or attitude packets (or "
                "data.survey.missing_attitude: track)",
                why,
            )
        track_heading_pings = int((~att_ok).sum())
        heading = np.where(att_ok, heading, course)
        pitch = np.where(att_ok, pitch, 0.0)
        roll = np.where(att_ok, roll, 0.0)
    reversed_runs = reversed_heading_runs(t, xy, np.where(att_ok, heading, np.nan))
    if reversed_runs:
        a, b, angle = reversed_runs[0]
        n_rev = sum(e - f + 1 for f, e, _ in reversed_runs)
        raise SurveyFormatError(
            path,
            f"pings {ping_ids[a]}-{ping_ids[b]}: SensorHeading",
            "a heading within 135 deg of the course over ground (else port and starboard swap)",
            f"{angle:.0f} deg off the course on {n_rev} pings in {len(reversed_runs)} run(s): "
            "a heading reversed by 180 deg (fix the heading, or read those pings apart)",
        )
    R = attitude_to_rotation(np.radians(heading), np.radians(pitch), np.radians(roll))

    # Lever arm of the transducers (XTF: X starboard, Y forward, Z down) -> FLU.
    offs = np.array(
        [
            [header.ChanInfo[i].OffsetY, -header.ChanInfo[i].OffsetX, -header.ChanInfo[i].OffsetZ]
            for i in (port_no, stbd_no)
        ],
        dtype=np.float64,
    ).mean(axis=0)
    lever = R @ offs if np.any(offs != 0) else np.zeros((len(t), 3))

    if origin is None:
        easting = float(np.round(xy[0, 0] / 100.0) * 100.0)
        northing = float(np.round(xy[0, 1] / 100.0) * 100.0)
        frame_origin = {"crs": _crs_string(frame_crs), "easting": easting, "northing": northing}
    else:
        frame_origin = {
            "crs": origin.get("crs"),
            "easting": float(origin.get("easting", 0.0)),
            "northing": float(origin.get("northing", 0.0)),
        }
    position = (
        np.stack(
            [
                xy[:, 0] - frame_origin["easting"],
                xy[:, 1] - frame_origin["northing"],
                -depth,
            ],
            axis=1,
        )
        + lever
    )

    # ---- waterfall on a common slant-range window
    r0 = float(np.median([c.r_start for c in ports + stbds]))
    r1 = float(np.median([c.r_end for c in ports + stbds]))
    native = int(np.median([c.size for c in ports + stbds]))
    B = int(n_bins) if n_bins is not None else native
    edges = np.linspace(r0, r1, B + 1)
    intensity = np.empty((len(ports), 2, B), dtype=np.float32)
    with open(path, "rb") as f:  # the samples are read from the file as they are resampled
        groups_p = _resample_side(ports, edges, intensity[:, 0], f.fileno())
        groups_s = _resample_side(stbds, edges, intensity[:, 1], f.fileno())
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

    # ---- unusable pings (constant, saturated or NaN over a whole side): no-hit (NaN)
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

    # ---- altitude: altimeter where plausible, calibrated first bottom return elsewhere
    with np.errstate(invalid="ignore"), warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # both sides NaN -> NaN: a bad ping
        mean_wf = np.nanmean(intensity.astype(np.float64), axis=1)
    picks = detect_first_return(
        mean_wf,
        range_m,
        min_range_m=min_first_return_m,
        blanking_m=blanking_m,
        auto_blanking=auto_blanking,
    )
    first_return = picks.altitude_m
    alt = _resolve_altitude(
        path, altitude, picks, t, r1, sensor_params, altitude_tolerance_m, altitude_offset
    )
    altitude, source = alt.altitude, alt.source
    if not np.isfinite(altitude).any():
        raise SurveyFormatError(
            path,
            "altitude",
            "an altimeter value or a visible first bottom return on some ping",
            f"neither on any of {len(altitude)} pings",
        )
    repairs = {
        "altimeter values beyond the slant range rejected": alt.beyond_range,
        "altimeter jumps (off their neighbours and the first return) rejected": alt.jumps,
        "filled from the detector": int((source == ALTITUDE_DETECTED).sum()),
        "interpolated between detected pings": int((source == ALTITUDE_INTERPOLATED).sum()),
        "of those shifted by the nearest pings' altimeter - first return offset": alt.shifted,
        "left missing (NaN, no altimeter point)": int((source == ALTITUDE_MISSING).sum()),
        "first returns rejected (edge in the blanking zone)": int(picks.rejected.sum()),
        "pings masked as no-hit (constant)": ping_flags["constant"],
        "pings masked as no-hit (saturated)": ping_flags["saturated"],
        "pings masked as no-hit (NaN samples)": ping_flags["nonfinite"],
    }
    if any(repairs.values()):
        log.warning(
            "%s: altitude/sample repairs: %s; blanking %.2f m; %s",
            path.name,
            ", ".join(f"{v} {k}" for k, v in repairs.items() if v),
            picks.blanking_m,
            _fill_accuracy(alt, range_m, sensor_params),
        )
    sonar_vs_data = beam_vs_data(
        intensity,
        range_m,
        altitude,
        R,
        sensor_params.beam_limits_rad,
        blanking_m=picks.blanking_m,
    )
    _report_beam(path, sonar_vs_data, sensor_params, r1)

    line = SidescanLine(
        name=name or path.stem,
        time_s=t,
        position=position,
        rotation=R,
        altitude_m=altitude,
        intensity=intensity,
        range_m=range_m,
        sensor=sensor_params,
        extras={"first_return_m": first_return.astype(np.float32)},
        altitude_source=source,
    )
    chk = alt.check
    stats: dict[str, Any] = {
        "file": str(path),
        "origin": frame_origin,
        "crs": frame_origin["crs"],
        "nav_units": "latlon" if nav_units_code == NAV_UNITS_LATLON else "metres",
        "pings_in_file": len(parsed.pings),
        "pings": line.n_pings,
        "pings_missing_channel": missing_channel,
        "pings_dropped_nav": int(dropped_nav),
        "packets_truncated": parsed.truncated,
        "other_packets": dict(parsed.other_packets),
        "nav_interpolated": nav_interp,
        "nav_outliers": outliers,
        "positions_from_ship": int(ship_ok[sl].sum()),
        "depth_interpolated": depth_interp,
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
        "samples_per_side": native,
        "n_bins": B,
        "range_window_m": [r0, r1],
        "range_settings": max(groups_p, groups_s),
        "channels_off_window": off_window,
        "sound_speed_mps": sensor_params.sound_speed_mps,
    }
    counts = {k: v for k, v in stats.items() if k in _LOGGED and v}
    if outlier_speed:
        counts["nav_outliers"] = f"{outliers} (implied speeds up to {outlier_speed:.0f} m/s)"
    if counts:
        # every one of these changed or dropped data: a WARNING, never INFO
        log.warning(
            "%s: navigation/ping repairs: %s",
            path.name,
            ", ".join(f"{_LOGGED[k]} {v}" for k, v in counts.items()),
        )
    return line, stats


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
        lon, lat = _transformer(crs, "EPSG:4326").transform(x, y)
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
