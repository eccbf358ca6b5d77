"""The compiled draping bookkeeping (numba, ``draping/kernels.py``) against the numpy
reference (``BOOKKEEPING = "numpy"``): the same results to the last bit on rough terrain
with occlusions, layover, holes, water column, out-of-beam bins and fans leaving the grid."""

from __future__ import annotations

import math

import numpy as np
import pytest

import sss2bathy.draping.drape as drape_mod
from sss2bathy.draping import DrapeConfig, DrapeSurface, drape_line, kernels
from sss2bathy.geometry import attitude_to_rotation
from sss2bathy.survey import (
    MASK_NO_HIT,
    MASK_OUT_OF_BEAM,
    MASK_SHADOW,
    MASK_VALID,
    MASK_WATER_COLUMN,
    BathyGrid,
    SidescanLine,
)


def _holey_rough_grid(size: float = 70.0, cell: float = 0.5, seed: int = 11) -> BathyGrid:
    """Hills, boulders (occlusions, layover) and no-data holes (no-hit bins, and hits
    next to a hole whose bilinear gradient is NaN: crossings without a normal)."""
    rs = np.random.default_rng(seed)
    ax = np.arange(-size / 2, size / 2 + cell / 2, cell)
    X, Y = np.meshgrid(ax, ax)
    z = -20.0 + 1.5 * np.sin(X / 4.0) * np.cos(Y / 6.0)
    for (cx, cy), r in zip(rs.uniform(-25, 25, (14, 2)), rs.uniform(1, 2.5, 14), strict=True):
        d2 = (X - cx) ** 2 + (Y - cy) ** 2
        z = np.where(d2 < r * r, z + 1.5 * np.sqrt(np.maximum(r * r - d2, 0.0)), z)
    for cx, cy in rs.uniform(-25, 25, (10, 2)):
        z[(np.abs(X - cx) < 1.2) & (np.abs(Y - cy) < 0.8)] = np.nan
    return BathyGrid(z, float(ax[0]), float(ax[0]), cell)


def _line(n_pings: int = 17, n_bins: int = 150, max_range: float = 45.0) -> SidescanLine:
    """A wobbling line whose far bins leave the 70 m grid (no hit)."""
    rs = np.random.default_rng(4)
    pos = np.stack(
        [rs.normal(0, 0.5, n_pings), np.linspace(-20, 20, n_pings), np.full(n_pings, -11.0)], 1
    )
    R = attitude_to_rotation(
        rs.normal(0, 0.3, n_pings), rs.normal(0, 0.05, n_pings), rs.normal(0, 0.2, n_pings)
    )
    return SidescanLine(
        name="rough",
        time_s=np.arange(n_pings) * 0.1,
        position=pos,
        rotation=R,
        altitude_m=np.full(n_pings, np.nan, np.float32),
        intensity=np.zeros((n_pings, 2, n_bins), np.float32),
        range_m=np.linspace(max_range / n_bins, max_range, n_bins),
    )


def _both(monkeypatch, line, surface, cfg=None):
    monkeypatch.setattr(drape_mod, "BOOKKEEPING", "numpy")
    ref = drape_line(line, surface, cfg)
    monkeypatch.setattr(drape_mod, "BOOKKEEPING", "numba")
    return ref, drape_line(line, surface, cfg)


def _assert_identical(ref, got):
    """Masks equal; floats equal up to 2 float32 ulp (a libm or summation-order ulp in
    float64 may round a float32 the other way on another machine; here they are equal
    to the bit)."""
    np.testing.assert_array_equal(got.mask, ref.mask, "mask")
    for name in ("points", "n_lat", "grazing_rad"):
        np.testing.assert_allclose(
            getattr(got, name), getattr(ref, name), rtol=2.5e-7, atol=1e-12, err_msg=name
        )


def test_numba_matches_numpy_on_rough_grid_with_holes(monkeypatch):
    surface = DrapeSurface.from_grid(_holey_rough_grid())
    line = _line()
    # the reference must meet crossings without a normal (next to the holes)
    seen_nan = []
    unit = drape_mod.head_plane_unit

    def spy(lat, up):
        out = unit(lat, up)
        seen_nan.append(bool(np.isnan(out[0]).any()))
        return out

    monkeypatch.setattr(drape_mod, "head_plane_unit", spy)
    ref, got = _both(monkeypatch, line, surface)
    assert any(seen_nan)
    reasons = set(np.unique(ref.mask))
    assert {MASK_VALID, MASK_WATER_COLUMN, MASK_SHADOW, MASK_NO_HIT, MASK_OUT_OF_BEAM} <= reasons
    assert (ref.mask == MASK_SHADOW).sum() > 50
    _assert_identical(ref, got)
    # and chunking still does not matter
    other = drape_line(line, surface, DrapeConfig(pings_per_chunk=3))
    _assert_identical(ref, other)


def test_numba_matches_numpy_on_a_mesh_with_non_uniform_bins(monkeypatch):
    grid = _holey_rough_grid(seed=12)
    surface = DrapeSurface.from_mesh(grid.to_mesh())  # normals from the hit faces
    line = _line(n_pings=9)
    ref, got = _both(monkeypatch, line, surface)
    assert (ref.mask == MASK_SHADOW).any() and (ref.mask == MASK_VALID).mean() > 0.3
    _assert_identical(ref, got)
    line.range_m = 45.0 * np.linspace(0.05, 1.0, line.n_bins) ** 1.4  # growing bins
    ref, got = _both(monkeypatch, line, DrapeSurface.from_grid(grid))
    assert (ref.mask == MASK_VALID).mean() > 0.3
    _assert_identical(ref, got)


def test_numba_matches_numpy_on_layover(monkeypatch, make_line):
    # a wall facing the sonar between a floor and a plateau: three crossings per bin
    cell = 0.05
    x = np.arange(-30.0, 2.0 + cell / 2, cell)
    y = np.arange(-4.0, 4.0 + cell / 2, cell)
    X, _ = np.meshgrid(x, y)
    z = np.full(X.shape, -20.0)
    z = np.where((X >= -16.0) & (X <= -15.0), -20.0 + 4.0 * (-15.0 - X), z)
    z = np.where((X >= -22.0) & (X < -16.0), -16.0, z)
    grid = BathyGrid(z, float(x[0]), float(y[0]), cell)
    line = make_line(n_pings=3, n_bins=700, max_range=24.0, start=(0.0, -1.0), length=2.0)
    ref, got = _both(monkeypatch, line, grid)
    lo, hi = math.hypot(16.0, 6.0), math.hypot(15.0, 10.0)
    band = (line.range_m > lo + 0.05) & (line.range_m < hi - 0.05)
    assert np.all(ref.n_lat[:, 0][:, band] < -0.8)  # the wall won the layover bins
    _assert_identical(ref, got)


def test_fast_root_angles_are_within_their_margin():
    # the approximate angle decides only where it is _EPS_T from a threshold: its error
    # must be far below that, with the first ray's direction in float32 as in draping
    rs = np.random.default_rng(1)
    ta = rs.uniform(-1.0, 2.0, 20000).astype(np.float32)
    t = ta.astype(np.float64) + rs.uniform(-0.1, 0.1, ta.size)
    r = rs.uniform(1.0, 80.0, ta.size)
    y, z = r * np.cos(t), r * np.sin(t)
    cs = np.stack([np.cos(ta), np.sin(ta)], 1)  # float32, numpy's own cos and sin
    worst, n_fast = 0.0, 0
    for i in range(ta.size):
        got, exact = kernels._root_angle(y[i], z[i], float(cs[i, 0]), float(cs[i, 1]), float(ta[i]))
        want = math.atan2(z[i], y[i])
        assert exact or abs(got - want) < 1e-6
        if not exact:
            n_fast += 1
            worst = max(worst, abs(got - want))
    assert n_fast > 0.9 * ta.size and worst < 1e-6


def test_far_root_bound_is_above_tan():
    # drape_fans skips roots with |cross| > far * dot, far = phi / (1 - phi^2 / 2.4) (times
    # 1.0001), phi <= 1.05 + 2e-5 rad: far must not be below tan(phi) anywhere there
    phi = np.linspace(0.0, 1.06, 1_000_001)
    assert np.all(phi / (1.0 - phi * phi / 2.4) >= np.tan(phi))


def test_bookkeeping_switch_is_checked(monkeypatch, make_plane, make_line):
    monkeypatch.setattr(drape_mod, "BOOKKEEPING", "fortran")
    with pytest.raises(ValueError, match="BOOKKEEPING: expected 'numba' or 'numpy'"):
        drape_line(make_line(n_pings=2, n_bins=20), make_plane())
