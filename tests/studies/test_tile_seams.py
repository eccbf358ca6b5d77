"""Tile seams study: ping selection, hard cut, neighbour disagreement, border steps, scores."""

from __future__ import annotations

import math

import numpy as np
import pytest

from sss2bathy.survey import BathyGrid
from sss2bathy.survey.tiles import tile_layout
from studies.tile_seams import (
    border_step,
    hard_cut,
    nadir_in,
    neighbour_disagreement,
    runs_of,
    seam_scores,
)


def _grid(nx: int = 81, ny: int = 21, cell: float = 1.0) -> BathyGrid:
    x = np.arange(nx) * cell
    return BathyGrid(np.tile(-10.0 + 0.01 * x, (ny, 1)), 0.0, 0.0, cell)


def test_nadir_in_and_runs_of():
    pos = np.stack([np.arange(10.0) * 10, np.zeros(10), np.zeros(10)], axis=1)
    keep = nadir_in(pos, (15.0, 55.0, -1.0, 1.0), margin_m=5.0)
    assert np.flatnonzero(keep).tolist() == [1, 2, 3, 4, 5, 6]
    assert runs_of(np.array([1, 1, 0, 1, 1, 1, 0, 1], bool), 2) == [slice(0, 2), slice(3, 6)]
    assert runs_of(np.zeros(4, bool), 1) == []


def test_scores_of_agreeing_tiles_show_no_seam_and_offset_tiles_do():
    g = _grid()
    tiles = tile_layout((-0.5, 80.5, -0.5, 20.5), 50.0, 16.0)
    assert len(tiles) == 2
    xx, yy = np.meshgrid(g.x, g.y)
    truth = np.asarray(g.heights, np.float64)

    def inside(t):
        b = t.bounds
        return (xx >= b[0]) & (xx <= b[1]) & (yy >= b[2]) & (yy <= b[3])

    same = [np.where(inside(t), truth, np.nan) for t in tiles]
    s = seam_scores(g, truth, same, tiles, np.ones(g.shape, bool))
    assert s["mae_tiled"] == pytest.approx(0.0, abs=1e-12)
    assert s["neighbour_disagreement"] == pytest.approx(0.0, abs=1e-12)
    assert s["step_tiled"] == pytest.approx(s["step_truth"]) == pytest.approx(0.01, abs=1e-5)
    # the east tile 0.4 m too high: a hard cut steps by 0.4 m, the blend spreads it over
    # the 16 m band (steps of ~0.4 * pi / 2 / 16 per metre at most)
    off = [same[0], same[1] + 0.4]
    s = seam_scores(g, truth, off, tiles, np.ones(g.shape, bool))
    assert s["neighbour_disagreement"] == pytest.approx(0.4, abs=1e-6)
    assert s["step_hard_cut"] == pytest.approx(0.41, abs=1e-5)
    assert s["step_tiled"] < 0.01 + 0.4 * math.pi / 2 / 16 + 1e-9
    assert s["band_mae_tiled"] < s["band_mae_hard_cut"] + 1e-12
    assert s["tiled_vs_single_away"] == pytest.approx(
        np.abs(hard_cut(tiles, off, xx, yy) - truth)[~(np.abs(xx - 40.0) <= 8)].mean()
    )


def test_neighbour_disagreement_and_border_step_are_nan_without_cells():
    g = _grid()
    tiles = tile_layout((-0.5, 80.5, -0.5, 20.5), 50.0, 16.0)
    xx, yy = np.meshgrid(g.x, g.y)
    empty = [np.full(g.shape, np.nan)] * 2
    assert math.isnan(neighbour_disagreement(tiles, empty, xx, yy))
    assert math.isnan(border_step(np.zeros(g.shape), tiles, g, np.zeros(g.shape, bool)))
