"""Map and waterfall figures a surveyor reads without help: colour bars with units,
projected axes, north up, the HSV colour-wheel key, titles that name the run."""

from __future__ import annotations

import matplotlib

matplotlib.use("Agg")

import matplotlib.pyplot as plt
import numpy as np
import pytest

from sss2bathy.eval.maps import (
    figure_to_rgb,
    gradient_hsv,
    hsv_wheel_key,
    map_figure,
    waterfall_figure,
)
from sss2bathy.survey import BathyGrid

ORIGIN = {"crs": "EPSG:32633", "easting": 500000.0, "northing": 6500000.0}


def _grid() -> BathyGrid:
    y, x = np.mgrid[0:21, 0:31] * 0.5
    return BathyGrid((-8 + 0.05 * x + 0.02 * y).astype(np.float32), 0.0, 0.0, 0.5, ORIGIN["crs"])


def _texts(fig) -> list[str]:
    return [t.get_text() for t in fig.findobj(matplotlib.text.Text)]


def test_height_map_has_a_colour_bar_in_metres_projected_axes_and_north_up():
    fig = map_figure(_grid(), "SIREN-GT-N2d on synthetic_d1: bathymetry", origin=ORIGIN)
    ax, cbar = fig.axes
    assert "(m" in cbar.get_ylabel() and "height" in cbar.get_ylabel()
    assert ax.get_xlabel() == "easting (m), EPSG:32633"
    assert ax.get_ylabel() == "northing (m), EPSG:32633"
    assert ax.get_xlim()[0] == pytest.approx(500000.0 - 0.25)  # projected, not local
    assert ax.get_title() == "SIREN-GT-N2d on synthetic_d1: bathymetry"
    texts = _texts(fig)
    assert "North up" in texts and "N" in texts
    plt.close(fig)


def test_local_axes_say_so():
    fig = map_figure(_grid(), "local")
    assert "local coordinates" in fig.axes[0].get_xlabel()
    plt.close(fig)


def test_gradient_map_has_the_hsv_colour_wheel_key():
    g = _grid()
    gx, gy = np.gradient(g.heights, g.cell_size)
    fig = map_figure(gradient_hsv(gx, gy, 0.1), "g", extent=(0, 15, 0, 10), vmax=0.1)
    ax, key = fig.axes
    texts = _texts(fig)
    assert {"N", "E", "S", "W"} <= set(texts)
    assert any("upslope" in t for t in texts)
    assert any("0.1 m/m" in t for t in texts)  # what full brightness means
    assert not fig.axes[1].axison
    plt.close(fig)


def test_the_wheel_key_is_red_to_the_north_and_black_at_the_centre():
    fig, ax = plt.subplots()
    hsv_wheel_key(ax, 0.2, n=65)
    rgba = ax.get_images()[0].get_array()
    assert np.allclose(rgba[32, 32, :3], 0.0, atol=0.05)  # flat: black
    assert np.allclose(rgba[63, 32, :3], [1.0, 0.0, 0.0], atol=0.1)  # upslope north: red
    assert rgba[0, 0, 3] == 0  # outside the wheel: transparent
    plt.close(fig)


def test_waterfall_figure_shows_n_lat_beside_the_sidescan_with_labelled_colour_bars():
    rng = np.random.default_rng(0)
    inten = rng.random((40, 64))
    n_lat = np.tile(np.linspace(-0.3, 0.3, 64), (40, 1))
    fig = waterfall_figure(inten, n_lat, n_lat * 0.9, inten > 0.05, "CNN on synthetic_d1, line T01")
    images = [ax for ax in fig.axes if ax.get_images()]
    assert [ax.get_title() for ax in images] == [
        "sidescan waterfall",
        "n_lat (estimated)",
        "n_lat (MBES, draped)",
    ]
    bars = [ax.get_ylabel() for ax in fig.axes if not ax.get_images()]
    assert bars == ["intensity (1-99 % stretch)", "n_lat (unitless)", "n_lat (unitless)"]
    assert fig._suptitle.get_text() == "CNN on synthetic_d1, line T01"
    rgb = figure_to_rgb(fig)
    assert rgb.dtype == np.uint8 and rgb.ndim == 3 and rgb.shape[2] == 3
    assert rgb.shape[0] >= 400 and rgb.shape[1] >= 800  # readable, not a 40x64 stack
    with pytest.raises(ValueError, match="n_lat: expected the shape of intensity"):
        waterfall_figure(inten, n_lat[:, :10])
