"""Synthetic sidescan lines and XTF-damaging helpers for the io tests (no checked-in binaries)."""

from __future__ import annotations

import ctypes
import math
from pathlib import Path

import numpy as np
import pytest
from pyxtf import XTFFileHeader, XTFPingHeader

from sss2bathy.geometry import attitude_to_rotation
from sss2bathy.survey import SensorParams, SidescanLine
from tests.conftest import REALDATA  # the shared real files, or $SSS2BATHY_REALDATA

ORIGIN = {"crs": "EPSG:32633", "easting": 500000.0, "northing": 6500000.0}


def simulated_pings(
    altitude: np.ndarray, range_m: np.ndarray, seed: int = 0, noise: float = 0.02
) -> np.ndarray:
    """``(P, 2, B)`` waterfalls: water-column noise, then a bottom return at slant range =
    altitude whose level falls off as (altitude / r)^2, with exponential speckle."""
    rng = np.random.default_rng(seed)
    P, B = altitude.size, range_m.size
    r = range_m[None, None, :]
    a = altitude[:, None, None]
    bottom = np.where(r >= a, (a / r) ** 2, 0.0) * rng.exponential(1.0, (P, 2, B))
    water = noise * rng.exponential(1.0, (P, 2, B))
    return (bottom + water).astype(np.float32)


def synthetic_line(
    name: str = "L0",
    n_pings: int = 60,
    n_bins: int = 128,
    max_range: float = 40.0,
    heading_deg: float = 75.0,
    speed: float = 2.0,
    ping_period: float = 0.2,
    seed: int = 0,
    sensor: SensorParams | None = None,
) -> SidescanLine:
    """A gently turning, rolling and pitching line with altitude 7-11 m and matching pings."""
    t = np.arange(n_pings) * ping_period
    heading = np.radians(heading_deg + 5.0 * np.sin(0.2 * t))
    pitch = np.radians(2.0 * np.cos(0.5 * t))
    roll = np.radians(-3.0 * np.sin(0.7 * t))
    x = np.cumsum(speed * ping_period * np.sin(heading))
    y = np.cumsum(speed * ping_period * np.cos(heading))
    z = -15.0 - 0.5 * np.sin(0.3 * t)
    altitude = 9.0 + 2.0 * np.sin(0.25 * t)
    dr = max_range / n_bins
    range_m = (np.arange(n_bins) + 0.5) * dr
    return SidescanLine(
        name=name,
        time_s=t,
        position=np.stack([x + 120.0, y - 40.0, z], axis=1),
        rotation=attitude_to_rotation(heading, pitch, roll),
        altitude_m=altitude,
        intensity=simulated_pings(altitude, range_m, seed=seed),
        range_m=range_m,
        sensor=sensor
        or SensorParams(
            tilt_rad=math.radians(20.0),
            beam_width_rad=math.radians(50.0),
            frequency_hz=400e3,
            sound_speed_mps=1500.0,
        ),
    )


def ping_offsets(path: Path) -> list[int]:
    """Byte offsets of the sonar pings of a file written by ``write_xtf`` (fixed record size)."""
    raw = path.read_bytes()
    first = XTFPingHeader.from_buffer_copy(raw[1024 : 1024 + ctypes.sizeof(XTFPingHeader)])
    size = first.NumBytesThisRecord
    return list(range(1024, len(raw) - size + 1, size))


def patch_ping(path: Path, index: int, **fields: float) -> None:
    """Overwrite ping-header fields of ping ``index`` in place."""
    off = ping_offsets(path)[index]
    n = ctypes.sizeof(XTFPingHeader)
    with open(path, "r+b") as f:
        f.seek(off)
        hdr = XTFPingHeader.from_buffer_copy(f.read(n))
        for key, value in fields.items():
            setattr(hdr, key, value)
        f.seek(off)
        f.write(bytes(hdr))


def patch_file_header(path: Path, fn) -> None:
    """Apply ``fn(header)`` to the file header in place."""
    with open(path, "r+b") as f:
        hdr = XTFFileHeader.from_buffer_copy(f.read(1024))
        fn(hdr)
        f.seek(0)
        f.write(bytes(hdr))


@pytest.fixture
def line() -> SidescanLine:
    return synthetic_line()


@pytest.fixture
def make_line():
    return synthetic_line


@pytest.fixture
def make_pings():
    return simulated_pings


@pytest.fixture
def xtf_patch():
    """``(patch_ping, patch_file_header, ping_offsets)`` to damage written files."""
    return patch_ping, patch_file_header, ping_offsets


@pytest.fixture
def origin() -> dict:
    return dict(ORIGIN)


@pytest.fixture
def realdata() -> Path:
    if not REALDATA.is_dir():
        pytest.skip(f"real bathymetry files not available at {REALDATA}")
    return REALDATA
