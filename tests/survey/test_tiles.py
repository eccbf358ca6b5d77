"""Tile layout and blend: a partition of unity over the survey, overlaps as asked."""

from __future__ import annotations

import numpy as np
import pytest

from sss2bathy.survey.tiles import blend, border_bands, taper, tile_layout, tile_weights

BOUNDS = (-10.0, 230.0, 5.0, 185.0)


def _points(step: float = 0.7):
    x, y = np.meshgrid(np.arange(-10.0, 230.0 + 1e-9, step), np.arange(5.0, 185.0 + 1e-9, step))
    return x, y


@pytest.mark.parametrize("overlap", [0.0, 10.0, 30.0])
def test_layout_covers_the_bounds_with_tiles_no_larger_than_asked(overlap):
    tiles = tile_layout(BOUNDS, (100.0, 80.0), overlap)
    for t in tiles:
        bx0, bx1, by0, by1 = t.bounds
        assert bx1 - bx0 <= 100.0 + 1e-9 and by1 - by0 <= 80.0 + 1e-9
    # the fewest: one column (row) fewer would need a tile larger than asked
    nx = 1 + max(t.index[0] for t in tiles)
    ny = 1 + max(t.index[1] for t in tiles)
    assert len(tiles) == nx * ny
    assert 240.0 / (nx - 1) + overlap * min(nx - 2, 2) / 2 > 100.0
    assert 180.0 / (ny - 1) + overlap * min(ny - 2, 2) / 2 > 80.0
    # the cores partition the bounds: their areas add up and they lie inside
    area = sum((t.core[1] - t.core[0]) * (t.core[3] - t.core[2]) for t in tiles)
    assert area == pytest.approx((BOUNDS[1] - BOUNDS[0]) * (BOUNDS[3] - BOUNDS[2]))
    assert min(t.bounds[0] for t in tiles) == BOUNDS[0]
    assert max(t.bounds[3] for t in tiles) == BOUNDS[3]


@pytest.mark.parametrize("overlap", [0.0, 12.0])
def test_weights_sum_to_one_everywhere(overlap):
    tiles = tile_layout(BOUNDS, 100.0, overlap)
    x, y = _points()
    total = sum(tile_weights(t, x, y) for t in tiles)
    np.testing.assert_allclose(total, 1.0, atol=1e-12)


def test_blend_of_a_constant_is_the_constant_and_of_agreeing_maps_the_map():
    tiles = tile_layout(BOUNDS, 90.0, 20.0)
    x, y = _points()
    inside = [
        (x >= t.bounds[0]) & (x <= t.bounds[1]) & (y >= t.bounds[2]) & (y <= t.bounds[3])
        for t in tiles
    ]
    const = blend(tiles, [np.where(m, -13.5, np.nan) for m in inside], x, y)
    np.testing.assert_allclose(const, -13.5, atol=1e-12)
    z = 0.01 * x - 0.02 * y + np.sin(x / 7.0)
    np.testing.assert_allclose(blend(tiles, [np.where(m, z, np.nan) for m in inside], x, y), z)


def test_overlap_width_is_respected_and_the_blend_has_no_step():
    tiles = tile_layout((0.0, 200.0, 0.0, 50.0), 110.0, 20.0)
    assert [t.index for t in tiles] == [(0, 0), (1, 0)]
    west, east = tiles
    assert west.bounds[1] - east.bounds[0] == pytest.approx(20.0)  # the shared band
    assert west.core[1] == pytest.approx(100.0)
    u = np.linspace(0.0, 200.0, 2001)
    w = tile_weights(west, u, np.full_like(u, 25.0))
    ramp = (w > 0) & (w < 1)
    assert u[ramp].min() >= 90.0 - 1e-9 and u[ramp].max() <= 110.0 + 1e-9
    assert np.all(w[u < 90.0] == 1.0) and np.all(w[u > 110.0] == 0.0)
    # two maps 1 m apart blend smoothly: steps between neighbouring points stay small
    z = blend(tiles, [np.where(u <= 110, 0.0, np.nan), np.where(u >= 90, 1.0, np.nan)], u, 0 * u)
    assert z[0] == 0.0 and z[-1] == 1.0
    assert np.abs(np.diff(z)).max() < 0.02
    # a hard cut (no overlap) is one step of the full difference
    hard = tile_layout((0.0, 200.0, 0.0, 50.0), 100.0, 0.0)
    zh = blend(hard, [np.where(u <= 100, 0.0, np.nan), np.where(u >= 100, 1.0, np.nan)], u, 0 * u)
    assert np.abs(np.diff(zh)).max() == 1.0


def test_a_tile_without_data_leaves_its_neighbours_weight_and_nan_where_none():
    tiles = tile_layout((0.0, 200.0, 0.0, 50.0), 110.0, 20.0)
    u = np.linspace(0.0, 200.0, 401)
    z = blend(tiles, [np.full_like(u, 2.0), np.full_like(u, np.nan)], u, 0 * u)
    assert np.all(z[u < 110] == 2.0) and np.all(np.isnan(z[u >= 110]))


def test_border_bands_mark_the_core_borders_only():
    tiles = tile_layout((0.0, 200.0, 0.0, 50.0), 110.0, 20.0)
    u = np.linspace(0.0, 200.0, 401)
    near = border_bands(tiles, u, np.full_like(u, 25.0), 20.0)
    assert np.array_equal(near, np.abs(u - 100.0) <= 10.0)


@pytest.mark.parametrize(
    ("bounds", "tile", "overlap", "match"),
    [
        ((0, 1, 0), 10.0, 0.0, "bounds"),
        ((0, 10, 5, 5), 10.0, 0.0, "bounds"),
        ((0, 10, 0, 10), -1.0, 0.0, "tile_m"),
        ((0, 10, 0, 10), 10.0, 10.0, "overlap_m"),
        ((0, 100, 0, 10), 30.0, 25.0, "overlap_m"),
    ],
)
def test_bad_arguments_are_one_line_errors(bounds, tile, overlap, match):
    with pytest.raises(ValueError, match=match):
        tile_layout(bounds, tile, overlap)


def test_taper_is_one_inside_and_zero_outside_without_neighbours():
    u = np.array([-1.0, 0.0, 5.0, 10.0, 11.0])
    assert taper(u, 0.0, 10.0, 4.0, True, True).tolist() == [0.0, 1.0, 1.0, 1.0, 0.0]
