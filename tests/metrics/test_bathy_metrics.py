"""Bathymetry map metrics (MAE, STD, gradient CS) and the map tools of eval/maps.py."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
import torch

from sss2bathy.eval.maps import (
    colorize,
    gradient_hsv,
    grid_over_bounds,
    map_metrics,
    render_map,
    save_map_outputs,
    siren_to_grid,
    track_region_mask,
)
from sss2bathy.metrics.bathy import (
    bathy_metrics,
    gradient_cosine_similarity,
    height_error_std,
    height_mae,
    map_gradient,
)
from sss2bathy.models.siren import Siren
from sss2bathy.survey import BathyGrid


def _plane_grid(gx: float, gy: float, n: int = 20, cell: float = 0.5) -> BathyGrid:
    x = np.arange(n) * cell
    xx, yy = np.meshgrid(x, x)
    return BathyGrid(-10.0 + gx * xx + gy * yy, 0.0, 0.0, cell)


def test_mae_and_std_golden():
    true = np.zeros((4, 5))
    pred = true.copy()
    pred[:2] = 0.2  # 10 cells +0.2
    pred[2:] = -0.1  # 10 cells -0.1
    assert height_mae(pred, true) == pytest.approx(0.15)
    assert height_error_std(pred, true) == pytest.approx(0.15)  # signed error +0.2/-0.1
    region = np.zeros((4, 5), bool)
    region[:2] = True
    assert height_mae(pred, true, region) == pytest.approx(0.2)
    assert height_error_std(pred, true, region) == pytest.approx(0.0)
    pred[0, 0] = np.nan  # no-data cells are not scored
    assert bathy_metrics(pred, true, 1.0, region)["n_cells"] == 9
    with pytest.raises(ValueError, match="region"):
        height_mae(pred, true, region.astype(int))
    with pytest.raises(ValueError, match="pred, true"):
        height_mae(pred, true[:2])


def test_gradient_cosine_similarity():
    east, north = _plane_grid(0.1, 0.0), _plane_grid(0.0, 0.2)
    g_east = map_gradient(east.heights, east.cell_size)
    assert np.allclose(g_east[0], 0.1) and np.allclose(g_east[1], 0.0)
    assert gradient_cosine_similarity(g_east, g_east) == pytest.approx(1.0)
    west = map_gradient(-east.heights, east.cell_size)
    assert gradient_cosine_similarity(g_east, west) == pytest.approx(-1.0)
    g_north = map_gradient(north.heights, north.cell_size)
    assert gradient_cosine_similarity(g_east, g_north) == pytest.approx(0.0, abs=1e-12)
    # direction only: a steeper slope the same way is still 1; flat cells are not scored
    steep = map_gradient(3 * east.heights, east.cell_size)
    assert gradient_cosine_similarity(g_east, steep) == pytest.approx(1.0)
    flat = (np.zeros((20, 20)), np.zeros((20, 20)))
    assert math.isnan(gradient_cosine_similarity(flat, g_east))
    # half the region agrees, half is opposite -> 0
    mixed = (
        np.where(np.arange(20)[None, :] < 10, 0.1, -0.1) * np.ones((20, 1)),
        np.zeros((20, 20)),
    )
    assert gradient_cosine_similarity(g_east, mixed) == pytest.approx(0.0)
    region = np.zeros((20, 20), bool)
    region[:, :10] = True
    assert gradient_cosine_similarity(g_east, mixed, region) == pytest.approx(1.0)


def test_map_metrics_requires_aligned_grids():
    true = _plane_grid(0.05, -0.02)
    pred = BathyGrid(true.heights + 0.1, true.x0, true.y0, true.cell_size)
    m = map_metrics(pred, true)
    assert m["mae"] == pytest.approx(0.1, abs=1e-6) and m["std"] == pytest.approx(0.0, abs=1e-6)
    assert m["grad_cs"] == pytest.approx(1.0) and m["n_cells"] == 400
    shifted = BathyGrid(true.heights, true.x0 + 0.25, true.y0, true.cell_size)
    with pytest.raises(ValueError, match="pred_grid"):
        map_metrics(shifted, true)


def test_gradient_hsv_colours():
    dzdx = np.array([[1.0, 0.0, -1.0, np.nan]])
    dzdy = np.array([[0.0, 1.0, 0.0, 0.0]])
    rgb = gradient_hsv(dzdx, dzdy, vmax=1.0)
    assert rgb.shape == (1, 4, 3) and rgb.dtype == np.float32
    # north-facing slope (dz/dy > 0): hue 0 = red; east: hue 0.25; west: hue 0.75
    assert np.allclose(rgb[0, 1], [1.0, 0.0, 0.0])
    assert np.allclose(rgb[0, 0], [0.5, 1.0, 0.0])
    assert np.allclose(rgb[0, 2], [0.5, 0.0, 1.0])
    assert np.allclose(rgb[0, 3], 0.0)  # NaN black
    half = gradient_hsv(np.array([[0.5]]), np.array([[0.0]]), vmax=1.0)
    assert half.max() == pytest.approx(0.5)  # value = norm / vmax
    assert colorize(np.array([[0.0, 1.0], [np.nan, 0.5]])).shape == (2, 2, 3)


def test_siren_to_grid_is_aligned_with_the_grid():
    torch.manual_seed(0)
    like = grid_over_bounds((10.0, 20.0, 30.0, 35.0), 1.0, crs="EPSG:32633")
    # cell edges on whole metres: centres from 9.5 (at or below 10) to 30.5 (at or above 30)
    assert like.shape == (17, 22) and like.bounds == (9.5, 19.5, 30.5, 35.5)
    siren = Siren(hidden=16, n_layers=3, bounds=(0, 0, 50, 50), z_range=(-20, -10))
    grid = siren_to_grid(siren, like, chunk=50)
    assert grid.crs == "EPSG:32633" and grid.shape == like.shape
    xy = torch.tensor([[like.x[3], like.y[7]], [like.x[20], like.y[0]]], dtype=torch.float32)
    with torch.no_grad():
        z = siren.height(xy)
    assert grid.heights[7, 3] == pytest.approx(z[0].item(), abs=1e-5)
    assert grid.heights[0, 20] == pytest.approx(z[1].item(), abs=1e-5)


def test_track_region_mask_selects_cells_near_tracks():
    grid = BathyGrid(np.full((11, 11), np.nan), 0.0, 0.0, 1.0)  # centres 0 .. 10
    track = np.array([[5.0, y] for y in np.linspace(0, 10, 41)])
    region = track_region_mask(grid, track, 2.0)
    assert region[:, 3:8].all() and not region[:, :3].any() and not region[:, 8:].any()
    with pytest.raises(ValueError, match="radius_m"):
        track_region_mask(grid, track, 0.0)


def test_save_map_outputs_writes_aligned_geotiff_and_figures(tmp_path):
    true = _plane_grid(0.05, -0.02)
    true.crs = "EPSG:32633"
    pred = BathyGrid(true.heights + 0.05, true.x0, true.y0, true.cell_size, true.crs)
    region = np.ones(true.shape, bool)
    metrics = map_metrics(pred, true, region)
    paths = save_map_outputs(tmp_path, pred, true, region, metrics, "test")
    for name in ("map.tif", "map.npz", "metrics.json", "map.png", "gradient_hsv.png", "error.png"):
        assert (tmp_path / name).stat().st_size > 0
    back = BathyGrid.load_geotiff(paths["map_tif"])
    assert np.allclose(back.heights, pred.heights) and (back.x0, back.y0) == (true.x0, true.y0)
    assert json.loads((tmp_path / "metrics.json").read_text())["mae"] == pytest.approx(
        0.05, abs=1e-6
    )
    assert np.load(tmp_path / "map.npz")["heights"].shape == true.shape
    assert render_map(np.zeros((3, 4, 3)), tmp_path / "rgb.png", "rgb").is_file()
