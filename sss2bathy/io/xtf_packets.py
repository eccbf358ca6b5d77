"""XTF packets: walking the file's packets, parsing the sonar pings and attitude packets, and
resampling each side's samples onto the import's range bins (the first stages of
:func:`sss2bathy.io.xtf.read_xtf`).

Checks: the file header (``FileFormat`` 0x7B, at most 6 channels, a port and a starboard
channel), every packet's 0xFACE magic and record size, every ping's channel sample counts and
time fields. Repairs (each a WARNING): a truncated final packet is skipped; damaged packets
are skipped by re-synchronising on the next valid packet header (refused when most of the
file is damaged).
"""

from __future__ import annotations

import calendar
import ctypes
import datetime as _dt
import logging
import math
import mmap
import os
from dataclasses import dataclass
from pathlib import Path

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

from sss2bathy.io.jsf import jsf_as_xtf
from sss2bathy.survey import SurveyFormatError

# the import's messages come from one logger, whichever stage writes them
log = logging.getLogger("sss2bathy.io.xtf")

FILE_HEADER_BYTES = 1024
MAGIC = 0xFACE


# ----------------------------------------------------------------------------- parsing
@dataclass(frozen=True)
class FileSamples:
    """Where one channel's samples lie in the file (read when resampled, not when parsed)."""

    offset: int
    dtype: np.dtype
    size: int

    @property
    def nbytes(self) -> int:
        return self.size * self.dtype.itemsize


@dataclass
class Channel:
    """One side of one ping: its samples as stored (an array, or where they lie in the file)
    and what turns them into intensities (:meth:`load`)."""

    data: np.ndarray | FileSamples
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
        if isinstance(data, FileSamples):
            raw = os.pread(fd, data.nbytes, data.offset)
            data = np.frombuffer(raw, dtype=data.dtype, count=data.size)
        samples = data.astype(np.float64) * self.scale
        return samples[::-1] if self.flip else samples


@dataclass
class ParsedFile:
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
RELEASE_BYTES = 64 << 20
# samples resampled at a time (bytes of float64 samples): bounds the memory of the resampling
RESAMPLE_BYTES = 32 << 20


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


def parse_packets(path: Path, channel_pair: int) -> ParsedFile:
    if path.suffix.lower() == ".jsf":  # Edgetech JSF, as the XTF packets it converts to
        return ParsedFile(*jsf_as_xtf(path, channel_pair), damaged=[])
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
        sidescan_channels(header, path, channel_pair)  # refuse before parsing any ping
        pos = FILE_HEADER_BYTES
        released = 0  # the pages of the map before this offset are handed back
        while pos < size:
            if pos - released >= RELEASE_BYTES:
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
    return ParsedFile(header, pings, attitude, truncated, other, damaged)


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
    :class:`FileSamples` (where each channel's samples lie), so that the pings of a line
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
        where.append(FileSamples(offset, data.dtype, int(data.size)))
        offset += data.nbytes
    ping.data = where
    return ping


def ping_time(p: XTFPingHeader, path: Path, index: int) -> float:
    try:
        t = calendar.timegm(
            _dt.datetime(p.Year, p.Month, p.Day, p.Hour, p.Minute, p.Second).timetuple()
        )
    except ValueError as exc:
        raise SurveyFormatError(path, f"ping {index}: time", "a valid date and time", exc) from None
    if p.HSeconds > 99:
        raise SurveyFormatError(path, f"ping {index}: HSeconds", "0..99", p.HSeconds)
    return float(t) + p.HSeconds / 100.0


def attitude_time(a: XTFAttitudeData) -> float:
    if a.SourceEpoch:
        return float(a.SourceEpoch) + a.EpochMicroseconds * 1e-6
    t = calendar.timegm(
        _dt.datetime(a.Year, a.Month, a.Day, a.Hour, a.Minute, a.Second).timetuple()
    )
    return float(t) + a.Millisecond * 1e-3


def sidescan_channels(header: XTFFileHeader, path: Path, channel_pair: int) -> tuple[int, int]:
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


def ping_channel(
    ping: XTFPingHeader, chan_no: int, header: XTFFileHeader, c: float, flip: bool
) -> Channel | None:
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
            return Channel(data, scale, flip, r_start, math.nan)
        return Channel(data, scale, flip, r_start, r_end)
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


def resample_side(chans: list[Channel], edges: np.ndarray, out: np.ndarray, fd: int | None) -> int:
    """Resample every ping's samples onto the output bin edges into ``out`` ``(P, M)``, a few
    megabytes of samples at a time (read from the file ``fd`` where they are not in memory);
    returns the count of range settings (groups of pings on the same recording window)."""
    keys = [(c.r_start, c.r_end, c.size) for c in chans]
    groups: dict[tuple, list[int]] = {}
    for i, k in enumerate(keys):
        groups.setdefault(k, []).append(i)
    for (r0, r1, n), idx in groups.items():
        step = max(1, RESAMPLE_BYTES // (8 * max(n, 1)))
        for a in range(0, len(idx), step):
            part = idx[a : a + step]
            block = np.stack([chans[i].load(fd) for i in part])
            out[part] = _resample_group(block, r0, r1, edges)
    return len(groups)
