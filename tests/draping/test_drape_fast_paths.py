"""The fast paths of draping: chunk-independent results, the bare ray cast with embree's
distances, the fused gradient sampler, non-uniform bins, layover and the benchmark's
ray recording."""

from __future__ import annotations

import math

import numpy as np
import pytest

import sss2bathy.draping.cache as cache_mod
from benchmarks.draping import count_rays, raw_cast, record_rays
from sss2bathy.draping import DrapeConfig, DrapeSurface, drape_key, drape_line
from sss2bathy.geometry import attitude_to_rotation
from sss2bathy.survey import MASK_VALID, BathyGrid, SidescanLine, Survey

MM = 2e-3


def _rough_grid(size: float = 80.0, cell: float = 0.5, seed: int = 3) -> BathyGrid:
    """Hills and a few boulders, about 20 m deep (occlusions, layover, shadows)."""
    rs = np.random.default_rng(seed)
    ax = np.arange(-size / 2, size / 2 + cell / 2, cell)
    X, Y = np.meshgrid(ax, ax)
    z = -20.0 + 1.5 * np.sin(X / 5.0) * np.cos(Y / 7.0)
    centres = rs.uniform(-30, 30, (12, 2))
    for (cx, cy), r in zip(centres, rs.uniform(1, 2.5, 12), strict=True):
        d2 = (X - cx) ** 2 + (Y - cy) ** 2
        z = np.where(d2 < r * r, z + np.sqrt(np.maximum(r * r - d2, 0.0)), z)
    return BathyGrid(z, float(ax[0]), float(ax[0]), cell)


def _wobbly_line(n_pings: int = 23, n_bins: int = 120, seed: int = 5) -> SidescanLine:
    """A line whose attitude changes from ping to ping (the fan differs per ping)."""
    rs = np.random.default_rng(seed)
    y = np.linspace(-15.0, 15.0, n_pings)
    pos = np.stack([rs.normal(0, 0.3, n_pings), y, np.full(n_pings, -10.0)], 1)
    R = attitude_to_rotation(
        rs.normal(0, 0.2, n_pings), rs.normal(0, 0.05, n_pings), rs.normal(0, 0.15, n_pings)
    )
    return SidescanLine(
        name="wobbly",
        time_s=np.arange(n_pings) * 0.1,
        position=pos,
        rotation=R,
        altitude_m=np.full(n_pings, np.nan, np.float32),
        intensity=np.zeros((n_pings, 2, n_bins), np.float32),
        range_m=np.linspace(30.0 / n_bins, 30.0, n_bins),
    )


def test_results_do_not_depend_on_the_chunk_size():
    surface = DrapeSurface.from_grid(_rough_grid())
    line = _wobbly_line()
    ref = drape_line(line, surface)
    assert (ref.mask == MASK_VALID).mean() > 0.4
    assert len(set(np.unique(ref.mask))) >= 3  # valid, water column and shadow at least
    for chunk in (1, 5, 64):
        other = drape_line(line, surface, DrapeConfig(pings_per_chunk=chunk))
        for name in ("points", "n_lat", "grazing_rad", "mask"):
            np.testing.assert_array_equal(getattr(other, name), getattr(ref, name), name)


def test_cast_distances_repeat_and_validation():
    surface = DrapeSurface.from_grid(_rough_grid())
    rs = np.random.default_rng(0)
    K, M = 7, 50
    origins = np.stack([rs.uniform(-20, 20, K), rs.uniform(-20, 20, K), np.full(K, -8.0)], 1)
    d = rs.normal(size=(K * M, 3))
    d[:, 2] = -np.abs(d[:, 2]) - 0.7
    d[::9, 2] = 0.3  # upwards: misses
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    d32 = d.astype(np.float32)
    tri, dist = surface.cast(origins, d32, repeat=M, distances=True)
    tri_rep = surface.cast(np.repeat(origins, M, axis=0), d32)
    np.testing.assert_array_equal(tri, tri_rep)
    tri64, dist64 = surface.first_hits(np.repeat(origins, M, axis=0), d32.astype(np.float64))
    hit = tri64 >= 0
    assert 0.5 < hit.mean() < 1.0
    np.testing.assert_array_equal(tri >= 0, hit)
    np.testing.assert_array_equal(np.isnan(dist), ~hit)
    # embree's float32 distances against the exact float64 plane distances
    assert np.abs(dist[hit] - dist64[hit]).max() < 1e-4
    with pytest.raises(ValueError, match="directions: expected 350 rays"):
        surface.cast(origins, d32[:-1], repeat=M)
    empty_tri, empty_dist = surface.cast(origins[:0], d32[:0], distances=True)
    assert empty_tri.shape == empty_dist.shape == (0,)


def test_grid_gradient_sampler_matches_bathygrid():
    grid = _rough_grid(size=30.0, cell=1.0)
    surface = DrapeSurface.from_grid(grid)
    rs = np.random.default_rng(1)
    x = np.concatenate([rs.uniform(-16, 16, 500), [15.0, -15.0]])
    y = np.concatenate([rs.uniform(-16, 16, 500), [15.0, -15.0]])
    assert np.isnan(surface.grid_gradient_at(np.array([np.nan]), np.array([0.0]))).all()
    got = surface.grid_gradient_at(x, y)
    gx, gy = grid.sample_gradient(x, y)
    np.testing.assert_array_equal(np.isnan(got), np.isnan(np.stack([gx, gy], 1)))
    ok = ~np.isnan(gx)
    assert 0.5 < ok.mean() < 1.0  # some points lie outside the grid
    np.testing.assert_allclose(got[ok], np.stack([gx, gy], 1)[ok], rtol=0, atol=1e-12)
    mesh_surface = DrapeSurface.from_mesh(grid.to_mesh())
    with pytest.raises(ValueError, match="surface: expected a surface built from a BathyGrid"):
        mesh_surface.grid_gradient_at(x, y)


def test_non_uniform_bins_are_exact_on_a_plane(make_plane, make_line):
    grid = make_plane(a=0.1, b=-0.05, c=-22.0, x_range=(-50, 50), y_range=(-10, 50), cell=1.0)
    line = make_line(n_pings=4, n_bins=150, max_range=38.0, heading_deg=20.0, roll_deg=2.0)
    line.range_m = 38.0 * np.linspace(0.05, 1.0, 150) ** 1.5  # growing bin size
    d = drape_line(line, grid)
    valid = d.mask == MASK_VALID
    assert valid.mean() > 0.4
    p = d.points.astype(np.float64)
    rng = np.linalg.norm(p - line.position[:, None, None, :], axis=-1)
    assert np.abs(rng - line.range_m[None, None, :])[valid].max() < MM
    assert np.abs(p[..., 2] - (0.1 * p[..., 0] - 0.05 * p[..., 1] - 22.0))[valid].max() < MM


def test_layover_bins_go_to_the_steepest_crossing(make_line):
    # port: flat floor 10 m below the sonar, a wall rising 4 m between x = -15 and -16
    # (facing the sonar), a plateau to x = -22. Ranges 17.1 - 18.0 m cross the floor,
    # the wall and the plateau; the wall, with by far the largest angle per metre of
    # range (the strongest echo), must win.
    cell = 0.05
    x = np.arange(-30.0, 2.0 + cell / 2, cell)
    y = np.arange(-4.0, 4.0 + cell / 2, cell)
    X, _ = np.meshgrid(x, y)
    z = np.full(X.shape, -20.0)
    z = np.where((X >= -16.0) & (X <= -15.0), -20.0 + 4.0 * (-15.0 - X), z)
    z = np.where((X >= -22.0) & (X < -16.0), -16.0, z)
    grid = BathyGrid(z, float(x[0]), float(y[0]), cell)
    line = make_line(n_pings=3, n_bins=1000, max_range=24.0, start=(0.0, -1.0), length=2.0)
    d = drape_line(line, grid)
    r = line.range_m.astype(np.float64)
    lo, hi = math.hypot(16.0, 6.0), math.hypot(15.0, 10.0)  # wall top and foot ranges
    band = (r > lo + 0.05) & (r < hi - 0.05)
    assert band.sum() > 30
    m, p = d.mask[:, 0][:, band], d.points[:, 0][:, band].astype(np.float64)
    assert np.all(m == MASK_VALID)
    assert np.all((p[..., 0] > -16.0 - MM) & (p[..., 0] < -15.0 + MM))  # on the wall
    rng = np.linalg.norm(p - line.position[:, None, :], axis=-1)
    assert np.abs(rng - r[band]).max() < MM
    # the wall tilts towards the sonar: strongly negative n_lat
    assert np.all(d.n_lat[:, 0][:, band] < -0.8)


def test_benchmark_records_every_ray_and_draping_key_has_a_version(
    tmp_path, make_plane, make_line, monkeypatch
):
    grid = make_plane(a=0.05, b=0.02, x_range=(-40, 40), y_range=(-10, 40), cell=1.0)
    line = make_line(n_pings=5, n_bins=60, max_range=30.0, length=10.0, name="l0")
    surface = DrapeSurface.from_grid(grid)
    batches = record_rays(line, surface, DrapeConfig(pings_per_chunk=2))
    n_rays = count_rays(batches)
    # the reference-altitude rays, then one fan per chunk (and middle rays if any)
    assert len(batches) >= 4 and batches[0][0].shape == (5, 3)
    assert n_rays == sum(len(d) for _, d, _ in batches) > 5 * 2 * 60
    raw_cast(surface, batches)()  # the bare casts run on the recorded rays
    survey = Survey("tiny", [line], grid, splits={"train": ["l0"]})
    folder = survey.save(tmp_path / "tiny")
    survey = Survey.load(folder)
    key = drape_key(survey, folder)
    monkeypatch.setattr(cache_mod, "DRAPE_ALGORITHM_VERSION", 999)
    assert drape_key(survey, folder) != key
