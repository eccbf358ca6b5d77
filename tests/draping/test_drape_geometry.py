"""Draping on analytic surfaces: exact n_lat and points, and every mask reason."""

from __future__ import annotations

import math

import numpy as np
import pytest
import trimesh

from sss2bathy.draping import DrapeConfig, DrapedLine, DrapeSurface, drape_line
from sss2bathy.geometry import head_plane_normal_from_gradient
from sss2bathy.survey import (
    MASK_NO_HIT,
    MASK_OUT_OF_BEAM,
    MASK_SHADOW,
    MASK_VALID,
    MASK_WATER_COLUMN,
    BathyGrid,
    SurveyFormatError,
)

H = 10.0  # sonar height above the flat floor in most tests
MM = 2e-3


def test_flat_floor_points_normals_and_masks(make_plane, make_line):
    line = make_line(n_pings=6, n_bins=200, max_range=40.0)
    d = drape_line(line, make_plane())
    r = line.range_m.astype(np.float64)
    step = r[1] - r[0]
    edge_oob = H / math.sin(math.radians(60.0))  # beam's steep edge: theta_max = 60 deg
    for side, sigma in ((0, 1.0), (1, -1.0)):
        m = d.mask[:, side]
        assert np.all(m[:, r < H - step] == MASK_WATER_COLUMN)
        assert np.all(m[:, (r > H + step) & (r < edge_oob - step)] == MASK_OUT_OF_BEAM)
        far = r > edge_oob + step
        assert np.all(m[:, far] == MASK_VALID)
        p = d.points[:, side][:, far].astype(np.float64)
        ground = np.sqrt(r[far] ** 2 - H**2)
        # heading 0: forward = North, port = West (-x)
        np.testing.assert_allclose(
            p[..., 0], np.broadcast_to(-sigma * ground, p.shape[:2]), atol=MM
        )
        np.testing.assert_allclose(
            p[..., 1], np.broadcast_to(line.position[:, 1:2], p.shape[:2]), atol=MM
        )
        np.testing.assert_allclose(p[..., 2], -20.0, atol=MM)
        np.testing.assert_allclose(d.n_lat[:, side][:, far], 0.0, atol=1e-6)
        np.testing.assert_allclose(
            d.grazing_rad[:, side][:, far],
            np.broadcast_to(np.arcsin(H / r[far]), p.shape[:2]),
            atol=1e-5,
        )
    assert np.all(np.isnan(d.points[d.mask == MASK_WATER_COLUMN]))


@pytest.mark.parametrize(
    "gradient,attitude",
    [((0.15, -0.1), (30.0, 3.0, -4.0)), ((-0.2, 0.05), (200.0, -2.0, 6.0))],
)
def test_tilted_plane_exact(make_plane, make_line, gradient, attitude):
    a, b = gradient
    heading, pitch, roll = attitude
    grid = make_plane(a=a, b=b, c=-25.0, x_range=(-50, 50), y_range=(-50, 50), cell=1.0)
    line = make_line(
        n_pings=8,
        n_bins=160,
        max_range=35.0,
        depth=-12.0,
        heading_deg=heading,
        pitch_deg=pitch,
        roll_deg=roll,
        start=(0.0, -10.0),
        length=20.0,
    )
    d = drape_line(line, grid)
    valid = d.mask == MASK_VALID
    assert valid.mean() > 0.5
    R = line.rotation
    expected, _ = head_plane_normal_from_gradient(
        np.full((8, 2), a), np.full((8, 2), b), R[:, None], np.array([[0, 1]])
    )
    err = np.abs(d.n_lat - expected[:, :, None].astype(np.float32))
    assert err[valid].max() < 1e-5
    p = d.points.astype(np.float64)
    s = line.position[:, None, None, :]
    assert np.abs(p[..., 2] - (a * p[..., 0] + b * p[..., 1] - 25.0))[valid].max() < MM
    rng = np.linalg.norm(p - s, axis=-1)
    assert np.abs(rng - line.range_m[None, None, :])[valid].max() < MM
    along = np.einsum("pk,psbk->psb", R[:, :, 0], p - s)
    assert np.abs(along)[valid].max() < MM
    lateral = np.einsum("pk,psbk->psb", R[:, :, 1], p - s) * np.array([1.0, -1.0])[None, :, None]
    assert lateral[valid].min() > 0
    # the grazing angle is the angle between the ray and the plane
    n = np.array([-a, -b, 1.0]) / math.sqrt(a * a + b * b + 1)
    ray = (p - s) / rng[..., None]
    np.testing.assert_allclose(d.grazing_rad[valid], np.arcsin(-(ray @ n))[valid], atol=1e-5)


def test_mesh_file_matches_grid(tmp_path, make_plane, make_line):
    grid = make_plane(a=0.1, b=0.05, x_range=(-45, 45), y_range=(-10, 50), cell=1.0)
    path = tmp_path / "plane.ply"
    grid.to_mesh().export(path)
    mesh = trimesh.load(path, force="mesh", process=False)
    line = make_line(n_pings=5, n_bins=150, max_range=38.0, heading_deg=10.0, roll_deg=3.0)
    from_grid, from_mesh = drape_line(line, grid), drape_line(line, mesh)
    assert (from_grid.mask == from_mesh.mask).mean() > 0.99
    both = (from_grid.mask == MASK_VALID) & (from_mesh.mask == MASK_VALID)
    assert both.mean() > 0.5
    np.testing.assert_allclose(from_mesh.n_lat[both], from_grid.n_lat[both], atol=1e-5)
    np.testing.assert_allclose(from_mesh.points[both], from_grid.points[both], atol=MM)


def test_box_casts_shadow_of_geometric_length(make_line):
    cell = 0.1
    x = np.arange(-40.0, 1.0 + cell / 2, cell)
    y = np.arange(-5.0, 5.0 + cell / 2, cell)
    X, Y = np.meshgrid(x, y)
    heights = np.full(X.shape, -20.0)
    heights[(X >= -22.0) & (X <= -20.0) & (np.abs(Y) < 3.0)] = -18.0  # 2 m high box, port
    grid = BathyGrid(heights, float(x[0]), float(y[0]), cell)
    line = make_line(n_pings=3, n_bins=400, max_range=40.0, start=(0.0, -1.0), length=2.0)
    d = drape_line(line, grid)
    r = line.range_m.astype(np.float64)
    step = r[1] - r[0]
    top_edge = math.hypot(22.0, H - 2.0)  # far top edge of the box
    shadow_end = math.hypot(22.0 * H / (H - 2.0), H)  # where the grazing ray meets the floor
    m = d.mask[:, 0]
    inside = (r > top_edge + step) & (r < shadow_end - step)
    assert inside.sum() > 40
    assert np.all(m[:, inside] == MASK_SHADOW)
    outside = (r < top_edge - 2 * step) | (r > shadow_end + 2 * step)
    assert not np.any(m[:, outside] == MASK_SHADOW)
    # starboard has no box: no shadow
    assert not np.any(d.mask[:, 1] == MASK_SHADOW)


def test_no_hit_beyond_mesh_and_in_nan_hole(make_plane, make_line):
    grid = make_plane(x_range=(-25, 25), y_range=(-10, 50), cell=0.5)
    heights = grid.heights.copy()
    xs = grid.x
    heights[:, (xs >= 18.0) & (xs <= 22.0)] = np.nan  # starboard (east) no-data strip
    grid = BathyGrid(heights, grid.x0, grid.y0, grid.cell_size)
    line = make_line(n_pings=4, n_bins=200, max_range=40.0)
    d = drape_line(line, grid)
    r = line.range_m.astype(np.float64)
    ground = np.sqrt(np.maximum(r**2 - H**2, 0.0))
    port, stbd = d.mask[:, 0], d.mask[:, 1]
    assert np.all(port[:, ground > 25.0 + 0.5] == MASK_NO_HIT)
    assert np.all(port[:, (ground > 7.0) & (ground < 24.0)] == MASK_VALID)
    assert np.all(stbd[:, (ground > 18.6) & (ground < 21.4)] == MASK_NO_HIT)
    assert np.all(stbd[:, (ground > 7.0) & (ground < 16.5)] == MASK_VALID)
    assert np.all(np.isfinite(d.n_lat[d.mask == MASK_VALID]))


def test_line_off_the_mesh_is_all_no_hit(make_plane, make_line):
    line = make_line(n_pings=3, n_bins=50, start=(5000.0, 0.0))
    d = drape_line(line, make_plane(x_range=(-20, 20), y_range=(-5, 45)))
    assert np.all(d.mask == MASK_NO_HIT)


def test_denser_fan_changes_nothing_on_a_plane(make_plane, make_line):
    grid = make_plane(a=0.05, b=-0.1, cell=1.0)
    line = make_line(n_pings=3, n_bins=100, heading_deg=45.0)
    coarse = drape_line(line, grid, {"rays_per_bin": 1.0, "fan_step_deg": 1.0})
    fine = drape_line(line, grid, DrapeConfig(rays_per_bin=4.0, fan_step_deg=0.1))
    assert (coarse.mask == fine.mask).mean() > 0.98
    both = (coarse.mask == MASK_VALID) & (fine.mask == MASK_VALID)
    np.testing.assert_allclose(coarse.points[both], fine.points[both], atol=MM)


def test_bad_inputs(make_plane, make_line):
    line = make_line(n_pings=2, n_bins=10)
    with pytest.raises(ValueError, match="line: expected a SidescanLine"):
        drape_line("line", make_plane())
    with pytest.raises(ValueError, match="surface: expected a BathyGrid"):
        drape_line(line, np.zeros((3, 3)))
    with pytest.raises(ValueError, match="drape.rays_per_bin"):
        DrapeConfig(rays_per_bin=0)
    with pytest.raises(ValueError, match="drape.engine"):
        DrapeConfig(engine="optix")
    with pytest.raises(ValueError, match="unknown keys"):
        DrapeConfig.coerce({"rays": 3})
    all_nan = BathyGrid(np.full((4, 4), np.nan), 0.0, 0.0, 1.0)
    with pytest.raises(ValueError, match="grid: expected at least one 2x2 block"):
        DrapeSurface.from_grid(all_nan)


def test_triangle_engine_fallback(make_plane, make_line):
    grid = make_plane(x_range=(-20, 20), y_range=(-5, 30), cell=1.0)
    line = make_line(n_pings=2, n_bins=60, max_range=20.0, length=5.0)
    slow, fast = drape_line(line, grid, {"engine": "triangle"}), drape_line(line, grid)
    assert (slow.mask == fast.mask).mean() > 0.98


def test_draped_line_roundtrip_and_validation(tmp_path, make_plane, make_line):
    d = drape_line(make_line(n_pings=3, n_bins=40), make_plane())
    d.meta = {"line": "x"}
    d.save(tmp_path / "d.npz")
    back = DrapedLine.load(tmp_path / "d.npz")
    assert back.meta == {"line": "x"}
    np.testing.assert_array_equal(back.mask, d.mask)
    np.testing.assert_array_equal(back.n_lat, d.n_lat)
    with pytest.raises(SurveyFormatError, match="points"):
        DrapedLine(d.points[:, :, :5], d.n_lat, d.grazing_rad, d.mask)
    bad = d.mask.copy()
    bad[0, 0, 0] = 64
    with pytest.raises(SurveyFormatError, match="mask"):
        DrapedLine(d.points, d.n_lat, d.grazing_rad, bad)
    arrays = dict(np.load(tmp_path / "d.npz"))
    arrays["n_lat"] = arrays["n_lat"].astype(np.float64)
    np.savez(tmp_path / "e.npz", **arrays)
    with pytest.raises(SurveyFormatError, match="n_lat"):
        DrapedLine.load(tmp_path / "e.npz")
    (tmp_path / "f.npz").write_bytes(b"not a zip")
    with pytest.raises(SurveyFormatError, match="readable"):
        DrapedLine.load(tmp_path / "f.npz")
