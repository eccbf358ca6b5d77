"""Cloud-optimised GeoTIFFs (the layout read back from the TIFF structure) and the STAC Item
of a map run (pystac; a structural check where pystac's schema validation cannot run)."""

from __future__ import annotations

import datetime as dt
import json
import math

import numpy as np
import pytest
import rasterio

from sss2bathy.io.export import add_geotiff_tags, cog_layout, write_geotiff
from sss2bathy.io.stac import AssetSpec, check_item, map_item, valid_footprint, write_item
from sss2bathy.survey import BathyGrid

ORIGIN = {"crs": "EPSG:32630", "easting": 451200.0, "northing": 6123400.0}


def _grid(shape, seed=0):
    h = np.random.default_rng(seed).normal(-30, 1, shape).astype(np.float32)
    return BathyGrid(h, 0.25, 0.25, 0.5)


def test_a_large_raster_is_a_cog_tiles_overviews_directories_first(tmp_path):
    path = write_geotiff(_grid((600, 1100)), tmp_path / "big.tif", origin=ORIGIN, tags={"A": "1"})
    layout = cog_layout(path)
    assert layout.images == ((1100, 600), (550, 300), (275, 150))  # overviews 2, 4
    assert layout.tile == (256, 256) and layout.compression == 8  # DEFLATE
    assert layout.ifds_before_data and layout.overviews_decreasing and layout.overview_data_first
    assert "LAYOUT=IFDS_BEFORE_DATA" in layout.ghost_layout
    assert "KNOWN_INCOMPATIBLE_EDITION=NO" in layout.ghost_layout
    assert layout.problems() == []
    with rasterio.open(path) as src:
        assert src.tags(ns="IMAGE_STRUCTURE")["LAYOUT"] == "COG"  # GDAL agrees
        assert src.overviews(1) == [2, 4] and src.block_shapes[0] == (256, 256)


def test_tags_added_later_keep_the_cog_layout_and_the_provenance(tmp_path):
    path = write_geotiff(_grid((300, 700)), tmp_path / "m.tif", origin=ORIGIN)
    before = rasterio.open(path).read(1)
    add_geotiff_tags(path, {"SSS2BATHY_METHOD": "x"}, unit="", description="intensity")
    assert cog_layout(path).problems() == []
    with rasterio.open(path) as src:
        tags = src.tags()
        np.testing.assert_array_equal(src.read(1), before)
        assert src.descriptions == ("intensity",) and src.overviews(1) == [2]
        assert src.crs.to_epsg() == 32630 and math.isnan(src.nodata)
    assert tags["SSS2BATHY_METHOD"] == "x" and tags["SSS2BATHY_FRAME"] == "projected"
    assert tags["SSS2BATHY_UNITS"] == "m" and "SSS2BATHY_VERSION" in tags


def test_the_layout_check_fails_a_cog_edited_in_place_and_a_stripped_tiff(tmp_path):
    path = write_geotiff(_grid((300, 600)), tmp_path / "e.tif", origin=ORIGIN)
    with rasterio.open(path, "r+", IGNORE_COG_LAYOUT_BREAK="YES") as dst:
        dst.update_tags(EDITED="yes")
    problems = cog_layout(path).problems()
    assert "an image directory after pixel data" in problems
    assert any("edited after" in p for p in problems)
    plain = tmp_path / "plain.tif"
    with rasterio.open(
        plain, "w", driver="GTiff", width=600, height=300, count=1, dtype="float32"
    ) as dst:
        dst.write(np.zeros((300, 600), np.float32), 1)
    problems = cog_layout(plain).problems()
    assert {"not tiled (strips)", "not compressed"} <= set(problems)
    (tmp_path / "x.tif").write_bytes(b"PK\x03\x04 not a tiff")
    with pytest.raises(ValueError, match="x.tif: expected a TIFF file"):
        cog_layout(tmp_path / "x.tif")


def test_a_small_raster_is_one_tile_without_overviews(tmp_path):
    layout = cog_layout(write_geotiff(_grid((30, 40)), tmp_path / "s.tif", origin=ORIGIN))
    assert layout.overviews == 0 and layout.tile == (256, 256) and layout.problems() == []


# ------------------------------------------------------------------ STAC


@pytest.fixture()
def run_dir(tmp_path):
    """A run folder: map.tif with data in a diagonal band only, uncertainty.tif, a mosaic on
    its own finer grid, metrics.json and a PNG."""
    run = tmp_path / "run"
    run.mkdir()
    grid = _grid((80, 120))
    yy, xx = np.mgrid[0:80, 0:120]
    band = np.abs(yy - 0.5 * xx - 10) < 8
    write_geotiff(grid, run / "map.tif", origin=ORIGIN, mask=band)
    sigma = BathyGrid(np.full((80, 120), 0.2, np.float32), 0.25, 0.25, 0.5)
    write_geotiff(sigma, run / "uncertainty.tif", origin=ORIGIN, mask=band)
    write_geotiff(_grid((200, 300)), run / "mosaic.tif", origin=ORIGIN, unit="", description="i")
    (run / "metrics.json").write_text(json.dumps({"final/written_area_m2": 1.0}))
    (run / "map.png").write_bytes(b"\x89PNG\r\n\x1a\n")
    return run, band


START = dt.datetime(2013, 9, 10, 21, 14, 7, tzinfo=dt.UTC).timestamp()


def _item(run):
    assets = {
        "map": AssetSpec(run / "map.tif", "bathymetry", ("data",)),
        "uncertainty": AssetSpec(run / "uncertainty.tif", "1 sigma", ("data",)),
        "mosaic": AssetSpec(run / "mosaic.tif", "mosaic", ("data",)),
        "metrics": AssetSpec(run / "metrics.json", "metrics", ("metadata",)),
        "map_png": AssetSpec(run / "map.png", "quicklook", ("overview",)),
    }
    return map_item(
        "survey_run",
        run / "map.tif",
        START,
        START + 920.5,
        assets,
        run,
        method="siren_cnn_n2d",
        command=["sss2bathy-map", "files=/d/a b.xtf"],
        cnn_checkpoint_sha256="ab" * 32,
        properties={"sss2bathy:verdict": "inconclusive"},
    )


def test_the_stac_item_describes_the_run(run_dir):
    from pyproj import Transformer

    run, band = run_dir
    item = _item(run)
    path = write_item(item, run / "item.json")
    data = json.loads(path.read_text())
    assert check_item(data) == []
    props = data["properties"]
    assert props["datetime"] == props["start_datetime"] == "2013-09-10T21:14:07Z"
    assert props["end_datetime"] == "2013-09-10T21:29:27.500000Z"
    assert props["proj:code"] == "EPSG:32630" and props["proj:shape"] == [80, 120]
    with rasterio.open(run / "map.tif") as src:
        assert props["proj:transform"] == pytest.approx(list(src.transform)[:6])
    assert props["processing:software"]["sss2bathy"]
    assert props["processing:lineage"] == "sss2bathy-map 'files=/d/a b.xtf'"
    assert props["sss2bathy:method"] == "siren_cnn_n2d"
    assert props["sss2bathy:cnn_checkpoint_sha256"] == "ab" * 32
    # assets: relative hrefs that exist, COG media type, the mosaic's own grid
    for key, asset in data["assets"].items():
        assert asset["href"].startswith("./") and (run / asset["href"]).is_file(), key
    assert (
        data["assets"]["map"]["type"] == "image/tiff; application=geotiff; profile=cloud-optimized"
    )
    assert data["assets"]["metrics"]["type"] == "application/json"
    assert data["assets"]["mosaic"]["proj:shape"] == [200, 300]
    assert data["assets"]["uncertainty"]["raster:bands"][0]["unit"] == "m"
    assert data["assets"]["map"]["raster:bands"][0]["nodata"] == "nan"
    # the footprint: the band of valid cells, not the raster's whole extent
    ring = data["geometry"]["coordinates"][0]
    tf = Transformer.from_crs("EPSG:4326", ORIGIN["crs"], always_xy=True)
    xs, ys = tf.transform([p[0] for p in ring], [p[1] for p in ring])
    e, n = np.asarray(xs) - ORIGIN["easting"], np.asarray(ys) - ORIGIN["northing"]
    rows, cols = np.nonzero(band)
    assert e.min() == pytest.approx(cols.min() * 0.5, abs=0.05)
    assert e.max() == pytest.approx((cols.max() + 1) * 0.5, abs=0.05)
    assert n.min() == pytest.approx(rows.min() * 0.5, abs=0.05)
    hull_area = 0.5 * abs(np.dot(e[:-1], n[1:]) - np.dot(n[:-1], e[1:]))
    assert hull_area < 0.6 * (120 * 0.5) * (80 * 0.5)  # a diagonal band's hull
    # pystac reads it back
    import pystac

    again = pystac.Item.from_dict(data)
    assert again.id == "survey_run" and set(again.assets) == set(data["assets"])


def test_pystac_schema_validation_where_it_can_run(run_dir):
    pytest.importorskip(
        "jsonschema",
        reason="pystac's validate() needs jsonschema (not installed; check_item covers it)",
    )
    item = _item(run_dir[0])
    try:
        item.validate()
    except Exception as err:  # noqa: BLE001 - offline: the schemas are fetched over the network
        if "URLError" in type(err).__name__ or "urlopen" in str(err) or "resolve" in str(err):
            pytest.skip(f"STAC schemas not reachable offline: {err}")
        raise


def test_check_item_finds_what_a_stac_item_lacks(run_dir):
    data = _item(run_dir[0]).to_dict(include_self_link=False, transform_hrefs=False)
    broken = json.loads(json.dumps(data))
    broken["properties"].pop("datetime")
    broken["properties"].pop("start_datetime")
    broken["geometry"]["coordinates"][0].pop()  # ring no longer closed
    broken["stac_extensions"] = []
    broken["assets"]["map"].pop("type")
    problems = check_item(broken)
    assert any("datetime" in p for p in problems)
    assert any("closed ring" in p for p in problems)
    assert any("projection schema" in p for p in problems)
    assert "assets.map: expected type" in problems
    assert check_item({"type": "Feature"})[0] == "missing field 'stac_version'"


def test_an_empty_map_footprint_is_the_raster_extent_and_no_crs_is_refused(tmp_path):
    grid = _grid((10, 20))
    path = write_geotiff(grid, tmp_path / "e.tif", origin=ORIGIN, mask=np.zeros((10, 20), bool))
    ring = valid_footprint(path)
    xs, ys = zip(*ring, strict=True)
    assert min(xs) == pytest.approx(ORIGIN["easting"]) and max(ys) == pytest.approx(
        ORIGIN["northing"] + 5.0
    )
    local = write_geotiff(grid, tmp_path / "local.tif")  # no CRS, no origin
    with pytest.raises(ValueError, match="expected a GeoTIFF with a CRS"):
        map_item("x", local, START, START, {}, tmp_path)
    with pytest.raises(ValueError, match="start <= end"):
        map_item("x", path, START, START - 1, {}, tmp_path)
