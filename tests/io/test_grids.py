"""Grids in (BAG, GeoTIFF, XYZ, meshes) and maps out (GeoTIFF, PLY), with CRS checks."""

from __future__ import annotations

import numpy as np
import pytest
import rasterio
import trimesh
from pyproj import Transformer

from sss2bathy.io.export import write_geotiff, write_ply
from sss2bathy.io.grids import crs_equivalent, grid_points, read_grid
from sss2bathy.survey import BathyGrid, SurveyFormatError


def surface(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """A smooth seabed: a slope and a mound (heights, m)."""
    return -30.0 + 0.02 * x - 0.01 * y + 3.0 * np.exp(-((x - 40) ** 2 + (y - 20) ** 2) / 400.0)


def analytic_grid(x0=500000.0, y0=6500000.0, cell=1.0, shape=(60, 80), crs="EPSG:32633"):
    ny, nx = shape
    xx, yy = np.meshgrid(np.arange(nx) * cell, np.arange(ny) * cell)
    return BathyGrid(surface(xx, yy), x0, y0, cell, crs)


# ----------------------------------------------------------------------------- real files
def test_bag_and_geotiff_of_the_same_survey_agree(realdata):
    bag = read_grid(realdata / "F00788_SR_8m.bag")
    tif = read_grid(realdata / "F00788_SR_8m.tif")
    assert bag.shape == tif.shape == (179, 179) and bag.cell_size == tif.cell_size == 8.0
    assert crs_equivalent(bag.crs, "EPSG:26910", bag.x0, bag.y0) and tif.crs == "EPSG:26910"
    xx, yy = np.meshgrid(tif.x, tif.y)
    valid = np.isfinite(tif.heights)
    assert 0.15 < valid.mean() < 0.25  # ~20 % valid
    # The BAG cell holding each TIFF cell centre (bilinear sampling would mix in no-data).
    ix = np.round((xx[valid] - bag.x0) / bag.cell_size).astype(int)
    iy = np.round((yy[valid] - bag.y0) / bag.cell_size).astype(int)
    assert ix.min() >= 0 and iy.min() >= 0 and ix.max() < 179 and iy.max() < 179
    z_bag = bag.heights[iy, ix]
    assert np.all(np.isfinite(z_bag))
    assert np.abs(z_bag - tif.heights[valid]).max() < 1e-3
    assert np.nanmin(bag.heights) == pytest.approx(-68.443, abs=1e-3)
    assert np.nanmax(bag.heights) == pytest.approx(-36.185, abs=1e-3)
    # Row 0 is south in both: the SW cell centre is the BAG's SW corner point.
    assert bag.x0 == pytest.approx(523816.2806, abs=1e-3)
    assert bag.y0 == pytest.approx(5332689.7195, abs=1e-3)
    # The BAG's WKT CRS and the TIFF's EPSG code are the same frame: no reprojection.
    same = read_grid(realdata / "F00788_SR_8m.bag", target_crs="EPSG:26910")
    np.testing.assert_array_equal(same.heights, bag.heights)


@pytest.mark.parametrize(
    ("name", "shape", "valid", "z_range", "sw"),
    [
        ("bdb_01.bag", (12, 16), 0.47, (-4.6, -2.7), (580104.0, 4495100.0)),
        ("bdb_02.bag", (15, 26), 0.82, (-16.8, -0.8), (614136.0, 4494756.0)),
    ],
)
def test_small_bags_load_plausibly(realdata, name, shape, valid, z_range, sw):
    g = read_grid(realdata / name)
    assert g.shape == shape and g.cell_size == 4.0 and (g.x0, g.y0) == sw
    assert np.isfinite(g.heights).mean() == pytest.approx(valid, abs=0.01)
    assert z_range[0] <= np.nanmin(g.heights) < np.nanmax(g.heights) <= z_range[1]
    assert "UTM" in g.crs and "18N" in g.crs


def test_crs_mismatch_refused_or_reprojected(realdata):
    path = realdata / "F00788_SR_8m.bag"
    with pytest.raises(
        SurveyFormatError, match=r"F00788.*crs.*UTM zone 11N.*found 'NAD83 / UTM zone 10N'"
    ):
        read_grid(path, target_crs="EPSG:32611", on_crs_mismatch="error")
    src = read_grid(path)
    out = read_grid(path, target_crs="EPSG:32611")
    assert out.crs == "EPSG:32611" and out.cell_size == 8.0
    xx, yy = np.meshgrid(src.x, src.y)
    ok = np.isfinite(src.heights)
    tx, ty = Transformer.from_crs("EPSG:26910", "EPSG:32611", always_xy=True).transform(
        xx[ok], yy[ok]
    )
    d = out.sample(tx, ty) - src.heights[ok]
    assert np.isfinite(d).mean() > 0.9  # edges of no-data blur away under bilinear warping
    assert np.nanmedian(np.abs(d)) < 0.1


def test_geographic_grid_needs_a_projected_target(tmp_path):
    g = BathyGrid(np.full((4, 5), -10.0), 15.0, 58.0, 0.001, "EPSG:4326")
    g.save_geotiff(tmp_path / "geo.tif")
    with pytest.raises(SurveyFormatError, match="projected CRS in metres"):
        read_grid(tmp_path / "geo.tif")
    out = read_grid(tmp_path / "geo.tif", target_crs="EPSG:32633", cell_size=20.0)
    assert out.crs == "EPSG:32633" and out.cell_size == 20.0
    assert np.nanmax(np.abs(out.heights + 10.0)) < 1e-4


# ----------------------------------------------------------------------------- GeoTIFF out/in
def test_geotiff_round_trip_with_origin(tmp_path):
    origin = {"crs": "EPSG:32633", "easting": 500000.0, "northing": 6500000.0}
    local = analytic_grid(x0=12.5, y0=-7.5, crs="EPSG:32633")
    write_geotiff(local, tmp_path / "map.tif", origin=origin)
    with rasterio.open(tmp_path / "map.tif") as src:
        assert src.crs.to_epsg() == 32633
        assert src.transform.c == pytest.approx(500012.0)  # west edge of the SW cell
        np.testing.assert_allclose(src.read(1)[::-1], local.heights)
    back = read_grid(tmp_path / "map.tif", origin=origin)
    assert (back.x0, back.y0, back.cell_size) == (12.5, -7.5, 1.0)
    np.testing.assert_array_equal(back.heights, local.heights)
    resampled = read_grid(tmp_path / "map.tif", origin=origin, cell_size=2.0)
    assert resampled.cell_size == 2.0
    xs, ys = resampled.x[2:-2], resampled.y[2:-2]
    xx, yy = np.meshgrid(xs, ys)
    assert np.abs(resampled.sample(xx, yy) - local.sample(xx, yy)).max() < 0.05
    with pytest.raises(ValueError, match="target_crs.*origin"):
        read_grid(tmp_path / "map.tif", target_crs="EPSG:32632", origin=origin)


# ----------------------------------------------------------------------------- XYZ
def test_xyz_points_gridded_to_cell_size(tmp_path):
    rng = np.random.default_rng(0)
    x = 500000.0 + rng.uniform(0, 50, 20000)
    y = 6500000.0 + rng.uniform(0, 30, 20000)
    z = surface(x - 500000.0, y - 6500000.0)
    text = "easting,northing,depth\n" + "\n".join(
        f"{a:.3f},{b:.3f},{-c:.4f}" for a, b, c in zip(x, y, z, strict=True)
    )
    (tmp_path / "mbes.csv").write_text(text)
    g = read_grid(tmp_path / "mbes.csv", cell_size=2.0, source_crs="EPSG:32633", z_positive="down")
    assert g.cell_size == 2.0 and g.crs == "EPSG:32633"
    assert g.x0 % 2.0 == 0 and g.y0 % 2.0 == 0  # cells centred on multiples of the size
    assert g.shape == (16, 26)
    xx, yy = np.meshgrid(g.x, g.y)
    ok = np.isfinite(g.heights)
    assert ok.mean() > 0.95
    # A cell's mean of points spread over 2 m: the surface at the centre within its curvature;
    # border cells hold points on their inner half only.
    err = np.abs(g.heights - surface(xx - 500000.0, yy - 6500000.0))
    assert np.nanmax(err[1:-1, 1:-1]) < 0.05 and np.nanmax(err) < 0.15
    med = read_grid(tmp_path / "mbes.csv", cell_size=2.0, statistic="median", z_positive="down")
    assert np.nanmax(np.abs(med.heights - g.heights)) < 0.05


def test_grid_points_mean_median_and_empty_cells():
    pts = np.array([[0.1, 0.0, -1.0], [0.2, 0.1, -3.0], [-0.3, 0.2, -8.0], [2.0, 1.0, -5.0]])
    mean = grid_points(pts, 1.0)
    assert mean.shape == (2, 3) and (mean.x0, mean.y0) == (0.0, 0.0)
    np.testing.assert_allclose(mean.heights, [[-4.0, np.nan, np.nan], [np.nan, np.nan, -5.0]])
    med = grid_points(pts, 1.0, statistic="median")
    assert med.heights[0, 0] == -3.0
    with pytest.raises(ValueError, match="cell_size"):
        grid_points(pts, 0.0)
    with pytest.raises(ValueError, match="statistic"):
        grid_points(pts, 1.0, statistic="mode")


def test_xyz_in_another_crs_is_reprojected_or_refused(tmp_path):
    to_32632 = Transformer.from_crs("EPSG:32633", "EPSG:32632", always_xy=True)
    xs, ys = np.meshgrid(500000.0 + np.arange(0, 20.0, 0.5), 6500000.0 + np.arange(0, 20.0, 0.5))
    ex, ny = to_32632.transform(xs.ravel(), ys.ravel())
    z = surface(xs.ravel() - 500000.0, ys.ravel() - 6500000.0)
    np.savetxt(tmp_path / "pts.xyz", np.c_[ex, ny, z], fmt="%.4f")
    with pytest.raises(SurveyFormatError, match=r"pts\.xyz.*crs.*UTM zone 33N.*UTM zone 32N"):
        read_grid(
            tmp_path / "pts.xyz",
            1.0,
            "EPSG:32633",
            source_crs="EPSG:32632",
            on_crs_mismatch="error",
        )
    g = read_grid(tmp_path / "pts.xyz", 1.0, "EPSG:32633", source_crs="EPSG:32632")
    xx, yy = np.meshgrid(g.x, g.y)
    ok = np.isfinite(g.heights)
    assert ok.mean() > 0.9
    err = np.abs(g.heights - surface(xx - 500000.0, yy - 6500000.0))
    assert np.nanmax(err[1:-1, 1:-1]) < 0.05 and np.nanmax(err) < 0.15
    with pytest.raises(ValueError, match="cell_size"):
        read_grid(tmp_path / "pts.xyz")


# ----------------------------------------------------------------------------- meshes
def test_ply_out_and_mesh_in(tmp_path):
    origin = {"crs": "EPSG:32633", "easting": 500000.0, "northing": 6500000.0}
    local = analytic_grid(x0=0.0, y0=0.0, cell=1.0)
    local.heights[:5, :7] = np.nan  # a no-data corner
    write_ply(local, tmp_path / "map.ply", origin=origin)
    mesh = trimesh.load(tmp_path / "map.ply", process=False)
    assert mesh.vertices.dtype == np.float64
    assert mesh.vertices[:, 0].min() == pytest.approx(500000.0, abs=1e-9)
    assert b"crs EPSG:32633" in (tmp_path / "map.ply").read_bytes()[:400]
    assert len(mesh.vertices) == np.isfinite(local.heights).sum()
    # Read back onto the same lattice by casting rays down: the vertices' heights.
    back = read_grid(tmp_path / "map.ply", cell_size=1.0, origin=origin, source_crs="EPSG:32633")
    assert (back.x0, back.y0) == (0.0, 0.0) and back.shape == local.shape
    both = np.isfinite(back.heights) & np.isfinite(local.heights)
    assert both.sum() > 0.9 * np.isfinite(local.heights).sum()
    assert np.abs(back.heights[both] - local.heights[both]).max() < 1e-3
    assert np.isnan(back.heights[:4, :6]).all()
    # Between vertices the rays hit the triangles: bilinear-like interpolation.
    half = read_grid(tmp_path / "map.ply", cell_size=0.5, origin=origin)
    xx, yy = np.meshgrid(half.x, half.y)
    ok = np.isfinite(half.heights)
    assert np.abs(half.heights[ok] - surface(xx[ok], yy[ok])).max() < 0.05


def test_local_ply_and_bad_suffix(tmp_path):
    g = analytic_grid(x0=0.0, y0=0.0, shape=(4, 5), crs=None)
    write_ply(g, tmp_path / "m.ply")
    mesh = trimesh.load(tmp_path / "m.ply", process=False)
    assert (
        len(mesh.faces) == 2 * 3 * 4 and b"local frame" in (tmp_path / "m.ply").read_bytes()[:200]
    )
    (tmp_path / "grid.nc").write_text("x")
    with pytest.raises(SurveyFormatError, match=r"grid\.nc.*suffix"):
        read_grid(tmp_path / "grid.nc")
    with pytest.raises(SurveyFormatError, match="missing file"):
        read_grid(tmp_path / "none.tif")


def test_esri_ascii_grid_is_south_first(tmp_path):
    rows = ["-1 -2 -3", "-4 -9999 -6"]  # north row first, as the format stores it
    header = "ncols 3\nnrows 2\nxllcorner 1000\nyllcorner 2000\ncellsize 2\nNODATA_value -9999\n"
    (tmp_path / "g.asc").write_text(header + "\n".join(rows) + "\n")
    g = read_grid(tmp_path / "g.asc")
    assert (g.x0, g.y0, g.cell_size) == (1001.0, 2001.0, 2.0)
    np.testing.assert_array_equal(g.heights, [[-4, np.nan, -6], [-1, -2, -3]])
