"""Damaged MBES grids: each kind of damage is refused in one line naming the file, the field,
what was expected and what was found, or repaired with a WARNING that counts the repair."""

from __future__ import annotations

import logging
from pathlib import Path

import h5py
import numpy as np
import pytest
import rasterio
from omegaconf import OmegaConf
from rasterio.transform import from_origin

from sss2bathy.io.grids import SpikeFilter, read_grid, spike_mask
from sss2bathy.io.xtf import write_xtf
from sss2bathy.io.xtf_survey import prepare_xtf_survey
from sss2bathy.survey import BathyGrid, Survey, SurveyFormatError

CONF = Path(__file__).resolve().parents[2] / "conf" / "data" / "survey" / "xtf.yaml"
CRS = "EPSG:32633"
#: the xtf import's default spike filter (conf/data/survey/xtf.yaml)
IMPORT_SPIKES = SpikeFilter(1.0, 5, 5.0, key="data.survey.mbes_spike_threshold_m")


def seabed(shape=(80, 100), cell=1.0, seed=0) -> np.ndarray:
    """Gentle relief (a slope, a mound, 5 cm noise), heights ~ -30 m, north row first."""
    rng = np.random.default_rng(seed)
    ny, nx = shape
    yy, xx = np.mgrid[0:ny, 0:nx] * cell
    mound = 2.0 * np.exp(-((xx - 0.4 * nx * cell) ** 2 + (yy - 0.5 * ny * cell) ** 2) / 300.0)
    return (-30.0 + 0.01 * xx - 0.02 * yy + mound + rng.normal(0, 0.05, shape)).astype(np.float32)


def write_tif(path: Path, data: np.ndarray, *, crs=CRS, nodata=None, cell=(1.0, 1.0), **kw):
    """A north-up single-band GeoTIFF (row 0 = north) with its SW corner at (500000, 6500000)."""
    ny, nx = data.shape
    profile = {"driver": "GTiff", "height": ny, "width": nx, "count": 1, "dtype": data.dtype.name}
    profile.update(crs=crs, nodata=nodata, **kw)
    profile.setdefault(
        "transform", from_origin(500000.0, 6500000.0 + ny * cell[1], cell[0], cell[1])
    )
    with rasterio.open(path, "w", **profile) as dst:
        dst.write(data, 1)
    return path


def bag_xml(sw: tuple[float, float], res: float, epsg: int) -> bytes:
    gmd = "http://www.isotc211.org/2005/gmd"
    gco = "http://www.isotc211.org/2005/gco"
    gml = "http://www.opengis.net/gml/3.2"
    dims = "".join(
        f"<gmd:axisDimensionProperties><gmd:MD_Dimension><gmd:dimensionName>"
        f"<gmd:MD_DimensionNameTypeCode>{name}</gmd:MD_DimensionNameTypeCode>"
        f"</gmd:dimensionName><gmd:resolution><gco:Measure uom='m'>{res}</gco:Measure>"
        f"</gmd:resolution></gmd:MD_Dimension></gmd:axisDimensionProperties>"
        for name in ("row", "column")
    )
    return (
        f"<gmi:MI_Metadata xmlns:gmi='http://www.isotc211.org/2005/gmi' xmlns:gmd='{gmd}' "
        f"xmlns:gco='{gco}' xmlns:gml='{gml}'><gmd:referenceSystemInfo><gmd:MD_ReferenceSystem>"
        f"<gmd:referenceSystemIdentifier><gmd:RS_Identifier><gmd:code><gco:CharacterString>"
        f"{epsg}</gco:CharacterString></gmd:code><gmd:codeSpace><gco:CharacterString>EPSG"
        f"</gco:CharacterString></gmd:codeSpace></gmd:RS_Identifier>"
        f"</gmd:referenceSystemIdentifier></gmd:MD_ReferenceSystem></gmd:referenceSystemInfo>"
        f"<gmd:spatialRepresentationInfo><gmd:MD_Georectified>{dims}<gmd:cornerPoints>"
        f"<gml:Point><gml:coordinates>{sw[0]},{sw[1]} {sw[0] + 50 * res},{sw[1] + 50 * res}"
        f"</gml:coordinates></gml:Point></gmd:cornerPoints></gmd:MD_Georectified>"
        f"</gmd:spatialRepresentationInfo></gmi:MI_Metadata>"
    ).encode()


def write_bag(path: Path, heights_south_first: np.ndarray) -> Path:
    with h5py.File(path, "w") as f:
        root = f.create_group("BAG_root")
        root.create_dataset("elevation", data=heights_south_first, chunks=(10, 10))
        xml = bag_xml((500000.5, 6500000.5), 1.0, 32633)
        root.create_dataset("metadata", data=np.frombuffer(xml, dtype="S1"))
    return path


def refused(path, **kw) -> SurveyFormatError:
    with pytest.raises(SurveyFormatError) as err:
        read_grid(path, **kw)
    message = str(err.value)
    assert "\n" not in message and message.startswith(str(path))
    return err.value


# ----------------------------------------------------------------------------- unreadable
def test_truncated_geotiff_is_one_line(tmp_path):
    good = write_tif(tmp_path / "good.tif", seabed((200, 200)))
    cut = tmp_path / "cut.tif"
    cut.write_bytes(good.read_bytes()[: good.stat().st_size // 2])
    err = refused(cut)
    assert err.field == "band 1" and err.expected == "all 200 x 200 cells readable"
    assert "truncated or corrupt" in str(err.found) and "TIFF of" in str(err.found)


def test_truncated_and_empty_bag_are_one_line(tmp_path):
    heights = seabed((50, 50))[::-1]
    good = write_bag(tmp_path / "good.bag", heights)
    g = read_grid(good)  # the fixture itself is a readable BAG
    assert g.crs == "EPSG:32633" and (g.x0, g.y0) == (500000.5, 6500000.5)
    np.testing.assert_array_equal(g.heights, heights)
    cut = tmp_path / "cut.bag"
    cut.write_bytes(good.read_bytes()[: good.stat().st_size // 2])
    err = refused(cut)
    assert err.field == "file" and err.expected == "a readable BAG (HDF5)"
    assert str(err.found).startswith("an HDF5 file of") and "truncated" in str(err.found)
    (tmp_path / "empty.bag").write_bytes(b"")
    err = refused(tmp_path / "empty.bag")
    assert str(err.found).startswith("an empty file (0 bytes)")


@pytest.mark.parametrize("name", ["empty.tif", "empty.asc", "empty.xyz"])
def test_empty_files_are_one_line(tmp_path, name):
    (tmp_path / name).write_bytes(b"")
    err = refused(tmp_path / name, cell_size=1.0)
    assert err.field == "file" and "empty file (0 bytes)" in str(err.found)


def test_png_named_tif_is_not_a_grid(tmp_path):
    rng = np.random.default_rng(3)
    png = tmp_path / "photo.tif"
    img = rng.integers(0, 255, (40, 60), dtype=np.uint8)
    with rasterio.open(png, "w", driver="PNG", height=40, width=60, count=1, dtype="uint8") as d:
        d.write(img, 1)
    err = refused(png, target_crs=CRS)
    assert err.field == "file" and err.expected == "a GeoTIFF (GDAL driver GTiff)"
    assert str(err.found).startswith("a PNG image of") and "PNG driver" in str(err.found)
    # Bytes that no driver reads: what they are is named.
    junk = tmp_path / "junk.tif"
    junk.write_bytes(b"\x89PNG\r\n\x1a\n" + bytes(rng.integers(0, 255, 300, dtype=np.uint8)))
    assert str(refused(junk).found).startswith("a PNG image of 308 bytes")


def test_plain_and_colour_images_are_not_grids(tmp_path):
    rng = np.random.default_rng(4)
    plain = tmp_path / "scan.tif"
    with rasterio.open(
        plain, "w", driver="GTiff", height=30, width=20, count=1, dtype="uint8"
    ) as d:
        d.write(rng.integers(0, 255, (30, 20), dtype=np.uint8), 1)
    err = refused(plain, target_crs=CRS)
    assert err.field == "georeferencing" and str(err.found) == "none: a 20 x 30 uint8 image"
    rgb = tmp_path / "chart.tif"
    with rasterio.open(
        rgb,
        "w",
        driver="GTiff",
        height=30,
        width=20,
        count=3,
        dtype="uint8",
        crs=CRS,
        transform=from_origin(500000, 6500030, 1, 1),
        photometric="RGB",
    ) as d:
        d.write(rng.integers(0, 255, (3, 30, 20), dtype=np.uint8))
    err = refused(rgb)
    assert err.field == "bands" and "colour image (3 bands red, green, blue)" in str(err.found)


# ----------------------------------------------------------------------------- no-data
def test_all_nodata_grid_is_refused(tmp_path):
    path = write_tif(tmp_path / "blank.tif", np.full((30, 40), -9999.0, np.float32), nodata=-9999)
    err = refused(path)
    assert err.field == "heights" and err.expected == "at least one valid cell"
    assert str(err.found) == "all 1200 cells no-data (30 x 40)"


def test_untagged_float_max_nodata_is_repaired_with_a_warning(tmp_path, caplog):
    clean = seabed()
    damaged = clean.copy()
    damaged[:, :30] = np.float32(3.4028235e38)  # the ggoutlier file's fill, no nodata tag
    damaged[50:55, 60:70] = -np.inf
    path = write_tif(tmp_path / "untagged.tif", damaged)
    info: dict = {}
    with caplog.at_level(logging.WARNING, logger="sss2bathy.io.grids"):
        g = read_grid(path, info=info)
    n_bad = 80 * 30 + 5 * 10
    assert info["untagged_nodata"] == n_bad
    assert (
        f"untagged.tif: {n_bad} cells" in caplog.text
        and "hold 3.40282e+38 (2400), -inf (50)" in caplog.text
    )
    assert "not tagged as no-data" in caplog.text
    south_first = clean[::-1]
    bad = ~np.isfinite(g.heights)
    assert bad.sum() == n_bad
    np.testing.assert_array_equal(g.heights[~bad], south_first[~bad])


def test_untagged_sentinel_only_when_far_from_the_heights(tmp_path, caplog):
    shallow = seabed()
    shallow[10:20, 10:20] = -9999.0
    with caplog.at_level(logging.WARNING, logger="sss2bathy.io.grids"):
        g = read_grid(write_tif(tmp_path / "sentinel.tif", shallow))
    assert (
        np.isnan(g.heights).sum() == 100
        and "100 cells" in caplog.text
        and "hold -9999 (100)" in caplog.text
    )
    deep = seabed() - 9970.0  # an abyssal grid: -9999 m is a depth there, not a fill
    deep[10:20, 10:20] = -9999.0
    caplog.clear()
    with caplog.at_level(logging.WARNING, logger="sss2bathy.io.grids"):
        g = read_grid(write_tif(tmp_path / "abyss.tif", deep))
    assert np.isfinite(g.heights).all() and "not tagged" not in caplog.text


# ----------------------------------------------------------------------------- geometry
def test_non_square_cells_are_resampled_with_a_warning(tmp_path, caplog):
    ny, nx = 40, 60
    yy, xx = np.mgrid[0:ny, 0:nx]
    plane = (-30.0 + 0.02 * xx * 1.0 - 0.01 * (ny - 1 - yy) * 2.0).astype(np.float32)
    path = write_tif(tmp_path / "rect.tif", plane, cell=(1.0, 2.0))
    with caplog.at_level(logging.WARNING, logger="sss2bathy.io.grids"):
        g = read_grid(path)
    assert "cells of 1 m (x) by 2 m (y) are not square" in caplog.text
    assert "square 1 m cells (40 x 60 cells -> about 80 x 60)" in caplog.text
    assert g.cell_size == 1.0 and g.shape == (80, 60)
    # Bilinear resampling reproduces a plane inside the grid (its edge half-cells aside).
    inner = g.heights[2:-2, 2:-2]
    xs, ys = np.meshgrid(g.x[2:-2] - 500000.0, g.y[2:-2] - 6500000.0)
    want = -30.0 + 0.02 * (xs - 0.5) - 0.01 * (ys - 1.0)
    assert np.nanmax(np.abs(inner - want)) < 1e-4
    # Without a CRS there is nothing to resample in: refused.
    nocrs = write_tif(tmp_path / "rect_local.tif", plane, crs=None, cell=(1.0, 2.0))
    err = refused(nocrs)
    assert err.field == "transform" and "cells of 1 m by 2 m" in str(err.found)


def test_rotated_grid_is_resampled_north_up_or_refused_without_crs(tmp_path, caplog):
    from affine import Affine

    ny, nx = 30, 40
    yy, xx = np.mgrid[0:ny, 0:nx] + 0.5
    angle = np.radians(20.0)
    c, s = np.cos(angle), np.sin(angle)
    rot = Affine(c, -s, 500000.0, -s, -c, 6500000.0)  # rows run south-east, columns east-north
    ex, nn = rot.c + rot.a * xx + rot.b * yy, rot.f + rot.d * xx + rot.e * yy
    plane = (-30.0 + 0.01 * (ex - 500000.0) + 0.02 * (nn - 6500000.0)).astype(np.float32)
    path = write_tif(tmp_path / "rotated.tif", plane, transform=rot)
    with caplog.at_level(logging.WARNING, logger="sss2bathy.io.grids"):
        g = read_grid(path)
    assert "rotated by -20.00 degrees; resampled bilinearly to a north-up grid" in caplog.text
    assert g.cell_size == pytest.approx(1.0)
    # The area is kept (within a cell row around the edge) and the plane is reproduced.
    assert abs(np.isfinite(g.heights).sum() - ny * nx) < 2 * (ny + nx)
    gx, gy = np.meshgrid(g.x, g.y)
    want = -30.0 + 0.01 * (gx - 500000.0) + 0.02 * (gy - 6500000.0)
    ok = np.isfinite(g.heights)
    assert np.median(np.abs(g.heights[ok] - want[ok])) < 1e-3
    path = write_tif(tmp_path / "rotated_local.tif", plane, transform=rot, crs=None)
    err = refused(path)
    assert err.field == "transform" and str(err.found).startswith("a rotated geotransform")
    assert read_grid(path, target_crs=CRS).shape == g.shape  # a target CRS to resample in


def test_truncated_ascii_grid_is_one_line(tmp_path):
    header = "ncols 3\nnrows 4\nxllcorner 1000\nyllcorner 2000\ncellsize 2\nNODATA_value -9999\n"
    (tmp_path / "short.asc").write_text(header + "-1 -2 -3\n-4 -5\n")
    err = refused(tmp_path / "short.asc")
    assert err.field == "band 1" and err.expected == "all 3 x 4 cells readable"
    assert "text of" in str(err.found) and "File short" in str(err.found)


def test_depths_read_as_heights_for_rasters_with_z_positive_down(tmp_path):
    clean = seabed()
    path = write_tif(tmp_path / "depths.tif", -clean)
    g = read_grid(path, z_positive="down")
    np.testing.assert_array_equal(g.heights, clean[::-1])
    with pytest.raises(ValueError, match="z_positive: expected 'up' or 'down', found 'sideways'"):
        read_grid(path, z_positive="sideways")


# ----------------------------------------------------------------------------- spikes
def spiked(clean: np.ndarray, n: int, height: float, seed: int) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    ny, nx = clean.shape
    where = np.zeros(clean.shape, bool)
    # Spread out (one per 4 x 4 block at most) so no window holds two.
    blocks = rng.choice((ny // 4) * (nx // 4), n, replace=False)
    where[4 * (blocks // (nx // 4)) + 2, 4 * (blocks % (nx // 4)) + 2] = True
    out = clean.copy()
    out[where] += np.float32(height)
    return out, where


def test_spike_filter_restores_the_clean_grid_and_counts(tmp_path, caplog):
    clean = seabed(seed=5)
    damaged, where = spiked(clean, 12, 20.0, seed=6)
    path = write_tif(tmp_path / "spiky.tif", damaged)
    info: dict = {}
    with caplog.at_level(logging.WARNING, logger="sss2bathy.io.grids"):
        g = read_grid(path, spikes=IMPORT_SPIKES, info=info)
    assert info["spikes_removed"] == 12 and 19.8 < info["spike_max_deviation_m"] < 20.2
    assert "spiky.tif: 12 spike cells" in caplog.text and "largest deviation 20." in caplog.text
    assert "data.survey.mbes_spike_threshold_m: null keeps them" in caplog.text
    removed = np.isnan(g.heights)
    np.testing.assert_array_equal(removed, where[::-1])  # exactly the spikes, nothing else
    # Tolerance: every kept cell equals the clean grid (0 m); the removed ones are no-data.
    assert np.abs(g.heights[~removed] - clean[::-1][~removed]).max() == 0.0
    # Off: the spikes stay.
    assert np.nanmax(read_grid(path).heights) > np.nanmax(clean) + 15.0


def test_spikes_removed_before_reprojection(tmp_path):
    clean = seabed(seed=7)
    damaged, where = spiked(clean, 8, 20.0, seed=8)
    path = write_tif(tmp_path / "spiky.tif", damaged)
    g = read_grid(path, target_crs="EPSG:32632", spikes=IMPORT_SPIKES)
    ref = read_grid(write_tif(tmp_path / "clean.tif", clean), target_crs="EPSG:32632")
    both = np.isfinite(g.heights) & np.isfinite(ref.heights)
    # Bilinear warping never smears a spike: kept cells stay within 5 cm of the clean warp.
    assert both.sum() > 0.9 * np.isfinite(ref.heights).sum()
    assert np.abs(g.heights[both] - ref.heights[both]).max() < 0.05


def test_spread_factor_keeps_steep_crests_and_finds_spikes_on_slopes():
    rng = np.random.default_rng(9)
    yy, xx = np.mgrid[0:60, 0:80] * 8.0  # 8 m cells
    ridge = -50.0 - np.tan(np.radians(30.0)) * np.abs(xx - 320.0) + rng.normal(0, 0.05, xx.shape)
    plain = spike_mask(ridge, 1.0, 5)
    guarded = spike_mask(ridge, 1.0, 5, spread_factor=5.0)
    assert plain.sum() > 100 and guarded.sum() == 0  # the crest and the edges are terrain
    damaged, where = spiked(ridge, 20, 20.0, seed=10)
    np.testing.assert_array_equal(spike_mask(damaged, 1.0, 5, spread_factor=5.0), where)
    with pytest.raises(ValueError, match="spread_factor"):
        SpikeFilter(1.0, 5, 0.0)
    with pytest.raises(ValueError, match="window_cells: expected an odd integer >= 3, found 4"):
        SpikeFilter(1.0, 4)


def test_spikes_in_bag_and_xyz(tmp_path, caplog):
    clean = seabed((50, 50), seed=11)
    damaged, where = spiked(clean, 5, -20.0, seed=12)  # downward fliers too
    with caplog.at_level(logging.WARNING, logger="sss2bathy.io.grids"):
        g = read_grid(write_bag(tmp_path / "fliers.bag", damaged), spikes=IMPORT_SPIKES)
    np.testing.assert_array_equal(np.isnan(g.heights), where)
    assert "fliers.bag: 5 spike cells" in caplog.text
    yy, xx = np.mgrid[0:50, 0:50]
    pts = np.c_[500000.0 + xx.ravel(), 6500000.0 + yy.ravel(), damaged.ravel()]
    np.savetxt(tmp_path / "fliers.xyz", pts, fmt="%.3f")
    g = read_grid(tmp_path / "fliers.xyz", 1.0, source_crs=CRS, spikes=IMPORT_SPIKES)
    assert np.isnan(g.heights).sum() == 5


# ----------------------------------------------------------------------------- the xtf import
ORIGIN_19N = {"crs": "EPSG:32619", "easting": 500000.0, "northing": 4800000.0}


@pytest.fixture
def lines_19n(tmp_path, make_line):
    folder = tmp_path / "raw"
    lines = [make_line(f"L{i}", n_pings=40, n_bins=64, seed=i) for i in range(2)]
    for ln in lines:
        write_xtf(ln, folder / f"{ln.name}.xtf", ORIGIN_19N)
    return folder, lines


def survey_grid(path: Path, heights: np.ndarray | None = None, crs: str = "EPSG:32619") -> Path:
    """A 1 m grid under the lines (absolute 32619 numbers, whatever ``crs`` labels it)."""
    h = seabed((120, 200), seed=13) - 4.0 if heights is None else heights
    g = BathyGrid(h[::-1], ORIGIN_19N["easting"] + 40.5, ORIGIN_19N["northing"] - 99.5, 1.0, crs)
    g.save_geotiff(path)
    return path


def config(folder: Path, grid: Path, **over):
    cfg = OmegaConf.load(CONF)
    cfg.files, cfg.mbes_grid, cfg.n_bins = str(folder), str(grid), 16
    for k, v in over.items():
        cfg[k] = v
    return cfg


def test_import_removes_spikes_and_records_them(tmp_path, lines_19n, caplog):
    folder, _ = lines_19n
    clean = seabed((120, 200), seed=13) - 4.0
    damaged, where = spiked(clean, 15, 20.0, seed=14)
    grid = survey_grid(tmp_path / "mbes.tif", damaged)
    with caplog.at_level(logging.WARNING):
        out = prepare_xtf_survey(config(folder, grid, name="spiky"), tmp_path / "data")
    assert "mbes.tif: 15 spike cells" in caplog.text
    survey = Survey.load(out)
    stats = survey.metadata["import_stats"]["_mbes_grid"]
    assert stats["spikes_removed"] == 15 and stats["file_crs"] == "EPSG:32619"
    assert np.nanmax(survey.grid.heights) < np.nanmax(clean) + 1e-3
    assert np.isnan(survey.grid.heights).sum() == 15
    off = prepare_xtf_survey(
        config(folder, grid, name="kept", mbes_spike_threshold_m=None), tmp_path / "data"
    )
    assert np.nanmax(Survey.load(off).grid.heights) > np.nanmax(clean) + 15.0


def test_import_grid_with_a_wrong_crs_label_names_both_and_the_file(tmp_path, lines_19n):
    folder, _ = lines_19n
    grid = survey_grid(tmp_path / "mbes_20n.tif", crs="EPSG:32620")
    with pytest.raises(SurveyFormatError) as err:
        prepare_xtf_survey(config(folder, grid), tmp_path / "data")
    message = str(err.value)
    assert message.startswith(str(grid)) and "\n" not in message
    assert err.value.field == "extent" and "lines in CRS EPSG:32619" in err.value.expected
    assert "CRS EPSG:32620, reprojected to EPSG:32619" in str(err.value.found)
    assert "is its CRS label EPSG:32620 wrong" in str(err.value.found)
    refuse = config(folder, grid, mbes_crs_mismatch="error")
    with pytest.raises(SurveyFormatError, match=r"mbes_20n\.tif.*crs.*UTM zone 19N.*20N"):
        prepare_xtf_survey(refuse, tmp_path / "data")


def test_import_grid_of_depths_is_recognised(tmp_path, lines_19n):
    folder, _ = lines_19n
    depths = 4.0 - seabed((120, 200), seed=13)  # 30-36 m, positive down
    grid = survey_grid(tmp_path / "depths.tif", depths)
    with pytest.raises(SurveyFormatError) as err:
        prepare_xtf_survey(config(folder, grid), tmp_path / "data")
    assert str(err.value).startswith(str(grid)) and err.value.field == "heights"
    assert "all 24000 valid cells above 0 m" in str(err.value.found)
    assert "set data.survey.mbes_z_positive=down" in str(err.value.found)
    out = prepare_xtf_survey(config(folder, grid, mbes_z_positive="down"), tmp_path / "data")
    np.testing.assert_array_equal(Survey.load(out).grid.heights, -depths[::-1])


def test_import_grid_above_the_vehicle_is_refused(tmp_path, lines_19n):
    folder, _ = lines_19n
    lifted = seabed((120, 200), seed=13) + 20.0  # -10 m: above the vehicle at -15 m
    grid = survey_grid(tmp_path / "datum.tif", lifted)
    with pytest.raises(SurveyFormatError) as err:
        prepare_xtf_survey(config(folder, grid), tmp_path / "data")
    assert err.value.field == "heights" and "the grid above it at 100% of 80 pings" in str(
        err.value.found
    )


@pytest.mark.parametrize(
    ("name", "damage", "field"),
    [
        ("cut.tif", lambda p: p.write_bytes(p.read_bytes()[: p.stat().st_size // 3]), None),
        ("empty.tif", lambda p: p.write_bytes(b""), "file"),
        ("photo.tif", lambda p: p.write_bytes(b"\x89PNG\r\n\x1a\n" + bytes(100)), "file"),
    ],
)
def test_import_of_unreadable_grids_is_one_line(tmp_path, lines_19n, name, damage, field):
    folder, _ = lines_19n
    grid = survey_grid(tmp_path / name)
    damage(grid)
    with pytest.raises(SurveyFormatError) as err:
        prepare_xtf_survey(config(folder, grid), tmp_path / "data")
    assert str(err.value).startswith(str(grid)) and "\n" not in str(err.value)
    assert field is None or err.value.field == field


def test_import_config_checks_the_spike_keys(tmp_path, lines_19n):
    folder, _ = lines_19n
    grid = survey_grid(tmp_path / "mbes.tif")
    for key, bad, expected in [
        ("mbes_spike_threshold_m", -1.0, "a positive height (m) or null"),
        ("mbes_spike_window_cells", 4, "an odd integer >= 3"),
        ("mbes_spike_spread_factor", 0, "a positive factor or null"),
    ]:
        with pytest.raises(ValueError) as err:
            prepare_xtf_survey(config(folder, grid, **{key: bad}), tmp_path / "data")
        assert str(err.value) == f"data.survey.{key}: expected {expected}, found {bad!r}"


# ----------------------------------------------------------------------------- real grids
def test_real_grids_through_the_import_spike_filter(realdata, caplog):
    info: dict = {}
    with caplog.at_level(logging.WARNING, logger="sss2bathy.io.grids"):
        g = read_grid(realdata / "ggoutlier_DepthSurface_1m.tif", spikes=IMPORT_SPIKES, info=info)
    # ~48 injected spike cells ("GG" and dots, up to z -25 m): 45 found, the surface left
    # within the README's real range.
    assert info["spikes_removed"] == 45 and info["untagged_nodata"] == 0
    assert 18.0 < info["spike_max_deviation_m"] < 19.5
    assert -48.1 < np.nanmin(g.heights) and np.nanmax(g.heights) < -41.5
    # A clean NOAA survey at 8 m: its steep slopes are not spikes (the threshold alone
    # would take 132 cells).
    info = {}
    read_grid(realdata / "F00788_SR_8m.bag", spikes=IMPORT_SPIKES, info=info)
    assert info["spikes_removed"] <= 1
