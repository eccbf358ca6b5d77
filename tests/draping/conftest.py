"""Analytic surfaces and straight survey lines for the draping tests."""

from __future__ import annotations

import math
from collections.abc import Callable

import numpy as np
import pytest

from sss2bathy.geometry import attitude_to_rotation
from sss2bathy.survey import BathyGrid, SensorParams, SidescanLine


def plane_grid(
    a: float = 0.0,
    b: float = 0.0,
    c: float = -20.0,
    x_range: tuple[float, float] = (-60.0, 60.0),
    y_range: tuple[float, float] = (-10.0, 60.0),
    cell: float = 0.5,
) -> BathyGrid:
    """Grid of the plane ``z = a x + b y + c``."""
    x = np.arange(x_range[0], x_range[1] + cell / 2, cell)
    y = np.arange(y_range[0], y_range[1] + cell / 2, cell)
    X, Y = np.meshgrid(x, y)
    return BathyGrid(a * X + b * Y + c, float(x[0]), float(y[0]), cell)


def straight_line(
    n_pings: int = 12,
    n_bins: int = 200,
    max_range: float = 40.0,
    depth: float = -10.0,
    heading_deg: float = 0.0,
    pitch_deg: float = 0.0,
    roll_deg: float = 0.0,
    start: tuple[float, float] = (0.0, 0.0),
    length: float = 40.0,
    name: str = "line",
    sensor: SensorParams | None = None,
    altitude: float = 10.0,
) -> SidescanLine:
    """A line at constant depth along ``heading_deg``; bins uniform in (0, max_range]."""
    hd = math.radians(heading_deg)
    t = np.linspace(0.0, length, n_pings)
    pos = np.stack(
        [start[0] + t * math.sin(hd), start[1] + t * math.cos(hd), np.full(n_pings, depth)], 1
    )
    R = attitude_to_rotation(
        np.full(n_pings, hd),
        np.full(n_pings, math.radians(pitch_deg)),
        np.full(n_pings, math.radians(roll_deg)),
    )
    rng = np.linspace(max_range / n_bins, max_range, n_bins)
    return SidescanLine(
        name=name,
        time_s=np.arange(n_pings) * 0.2,
        position=pos,
        rotation=R,
        altitude_m=np.full(n_pings, altitude, np.float32),
        intensity=np.ones((n_pings, 2, n_bins), np.float32),
        range_m=rng,
        sensor=sensor or SensorParams(),
    )


@pytest.fixture
def make_plane() -> Callable[..., BathyGrid]:
    return plane_grid


@pytest.fixture
def make_line() -> Callable[..., SidescanLine]:
    return straight_line
