"""The written map's coverage: the sonar's footprint of the bins used (no nadir gap, nothing
beyond the line's ends, no holes between pings) and its coverage statistics."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from sss2bathy.data.masks import sonar_mask
from sss2bathy.eval.maps import (
    altimeter_cells,
    coverage_mask,
    coverage_stats,
    grid_over_bounds,
    swath_footprint_mask,
    track_region_mask,
)
from sss2bathy.geometry import attitude_to_rotation

CELL = 0.5
ALTITUDE = 5.0
TILT, BEAM = math.radians(30.0), math.radians(60.0)  # beam: depression 0..60 deg


def _line(heading_deg: float, n: int = 120, step: float = 0.4, seed: int = 0) -> dict:
    """A straight line (position, rotation, altitude, ranges, sonar-only usable bins)."""
    rng = np.random.default_rng(seed)
    heading = math.radians(heading_deg)
    forward = np.array([math.sin(heading), math.cos(heading)])
    xy = np.arange(n)[:, None] * step * forward[None]
    position = np.concatenate([xy, np.full((n, 1), -2.0)], 1)
    rotation = attitude_to_rotation(
        torch.full((n,), heading), torch.zeros(n), torch.zeros(n)
    ).numpy()
    range_m = np.linspace(0.1, 20.0, 128)
    altitude = np.full(n, ALTITUDE)
    intensity = rng.uniform(0.5, 1.5, (n, 2, 128)).astype(np.float32)
    mask = sonar_mask(
        intensity, range_m, altitude, rotation, (TILT - BEAM / 2, TILT + BEAM / 2),
        {"shadow_threshold": 0.0},
    )  # fmt: skip
    return {
        "position": position,
        "rotation": rotation,
        "altitude_m": altitude,
        "range_m": range_m,
        "usable": mask == 0,
    }


def _grid_for(line: dict) -> object:
    xy = line["position"][:, :2]
    reach = float(line["range_m"].max()) + 2.0
    lo, hi = xy.min(0) - reach, xy.max(0) + reach
    return grid_over_bounds((lo[0], lo[1], hi[0], hi[1]), CELL)


def test_a_straight_lines_footprint_has_no_cells_beyond_its_ends_nor_in_the_nadir_gap():
    line = _line(heading_deg=90.0)  # eastward along y = 0
    grid = _grid_for(line)
    fp = swath_footprint_mask(grid, **line)
    xx, yy = np.meshgrid(grid.x, grid.y)
    x_first, x_last = line["position"][0, 0], line["position"][-1, 0]
    # nothing before the first ping or after the last (beyond the cell the ends fall in)
    assert not fp[(xx < x_first - CELL) | (xx > x_last + CELL)].any()
    # the nadir gap: bins nearer than the beam's 60 deg depression are not used
    r = line["range_m"]
    first = r[line["usable"][0, 0]].min()
    near_ground = math.sqrt(first**2 - ALTITUDE**2)
    assert near_ground > 2.5  # a real gap of several cells
    assert not fp[np.abs(yy) < near_ground - CELL].any()
    far_ground = math.sqrt(r.max() ** 2 - ALTITUDE**2)
    assert not fp[np.abs(yy) > far_ground + CELL].any()
    # no holes: every cell centre inside the swept swath (either side) is covered
    inside = (
        (xx >= x_first) & (xx <= x_last) & (np.abs(yy) >= near_ground) & (np.abs(yy) <= far_ground)
    )
    assert fp[inside].all()
    # the disc of swath radius it replaces reaches far beyond the ends and fills the gap
    old = track_region_mask(grid, line["position"][:, :2], far_ground)
    gap = (np.abs(yy) < 1.0) & (xx >= x_first) & (xx <= x_last)
    assert old[(xx < x_first - 5.0)].any() and old[gap].all()


def test_the_footprint_follows_heading_and_side_sign():
    line = _line(heading_deg=0.0, n=60)  # northward: port is West (-x), starboard East
    grid = _grid_for(line)
    xx, _ = np.meshgrid(grid.x, grid.y)
    port_only = dict(line, usable=line["usable"] & np.array([True, False])[None, :, None])
    fp = swath_footprint_mask(grid, **port_only)
    assert fp.any() and not fp[xx > 0].any()
    star_only = dict(line, usable=line["usable"] & np.array([False, True])[None, :, None])
    fp = swath_footprint_mask(grid, **star_only)
    assert fp.any() and not fp[xx < 0].any()


def test_no_holes_between_pings_on_a_turn_and_lines_are_not_joined():
    n = 90
    heading = np.linspace(0.0, math.pi / 2, n)  # a quarter turn of radius ~20 m
    radius = 20.0
    xy = np.stack([radius * (1 - np.cos(heading)), radius * np.sin(heading)], 1)
    rotation = attitude_to_rotation(
        torch.from_numpy(heading), torch.zeros(n, dtype=torch.float64),
        torch.zeros(n, dtype=torch.float64),
    ).numpy()  # fmt: skip
    range_m = np.linspace(0.1, 12.0, 64)
    usable = np.broadcast_to(range_m > ALTITUDE + 0.5, (n, 2, 64)).copy()
    position = np.concatenate([xy, np.full((n, 1), -2.0)], 1)
    grid = grid_over_bounds((-15, -15, 35, 35), CELL)
    fp = swath_footprint_mask(grid, position, rotation, np.full(n, ALTITUDE), range_m, usable)
    # every cell centre between near and far ground range of the arc is covered
    xx, yy = np.meshgrid(grid.x, grid.y)
    dist = np.hypot(xx - radius, yy)  # distance to the turn's centre (20, 0)
    angle = np.arctan2(yy, radius - xx)
    near = math.sqrt((ALTITUDE + 0.5 + range_m[1] - range_m[0]) ** 2 - ALTITUDE**2)
    far = math.sqrt(12.0**2 - ALTITUDE**2)
    band = (np.abs(dist - radius) >= near + CELL) & (np.abs(dist - radius) <= far - CELL)
    band &= (angle >= 0.05) & (angle <= math.pi / 2 - 0.05)
    assert band.sum() > 500 and fp[band].all()
    # the same pings as two lines: the strip between the last ping of one and the first of
    # the next is not drawn
    line = np.repeat([0, 1], [n // 2, n - n // 2])
    split = swath_footprint_mask(
        grid, position, rotation, np.full(n, ALTITUDE), range_m, usable, line=line
    )
    assert split.sum() < fp.sum() and not (split & ~fp).any()


def test_no_usable_bin_images_nothing_and_the_stats_count_the_altimeter():
    line = _line(heading_deg=90.0, n=40)
    grid = _grid_for(line)
    empty = swath_footprint_mask(grid, **dict(line, usable=np.zeros_like(line["usable"])))
    assert not empty.any()
    alt = altimeter_cells(grid, line["position"][:, :2])
    stats = coverage_stats(grid, alt, empty, alt)
    assert stats["imaged_area_m2"] == 0.0 and stats["extrapolated_share"] == 0.0
    assert stats["measured_area_m2"] == pytest.approx(alt.sum() * CELL**2)
    fp = swath_footprint_mask(grid, **line)
    old = coverage_mask(grid, track_region_mask(grid, line["position"][:, :2], 19.0), None)
    before = coverage_stats(grid, old, fp, alt)
    after = coverage_stats(grid, fp | alt, fp, alt)
    assert after["extrapolated_share"] == 0.0 and before["extrapolated_share"] > 0.3
    assert after["imaged_area_m2"] == pytest.approx(fp.sum() * CELL**2)
    with pytest.raises(ValueError, match="usable: expected shape"):
        swath_footprint_mask(grid, **dict(line, usable=line["usable"][:, :, :5]))
