"""Georeferenced rasters: projected coordinates + the survey's CRS, nodata outside the
coverage, overviews, no invented CRS, and the survey grid.tif round trip."""

import logging
import math

import numpy as np
import pytest
import rasterio
import yaml

from sss2bathy.eval.maps import (
    altimeter_cells,
    axis_labels,
    coverage_mask,
    save_map_outputs,
    track_region_mask,
)
from sss2bathy.geometry import attitude_to_rotation
from sss2bathy.io.export import read_geotiff, write_geotiff
from sss2bathy.survey import BathyGrid, SensorParams, SidescanLine, Survey, SurveyFormatError

ORIGIN = {"crs": "EPSG:32633", "easting": 680000.0, "northing": 6580000.0}


def _line(name: str, x0: float, y: float, n: int = 40, seed: int = 0) -> SidescanLine:
    """A straight east-going line of ``n`` pings 1 m apart at local ``y`` (2 m depth)."""
    rng = np.random.default_rng(seed)
    heading = np.full(n, math.pi / 2)  # east
    return SidescanLine(
        name=name,
        time_s=np.arange(n) * 0.1,
        position=np.c_[x0 + np.arange(n, dtype=float), np.full(n, y), np.full(n, -2.0)],
        rotation=attitude_to_rotation(heading, np.zeros(n), np.zeros(n)),
        altitude_m=np.full(n, 8.0),
        intensity=rng.random((n, 2, 16)),
        range_m=np.linspace(1.0, 15.0, 16),
        sensor=SensorParams(),
    )


def _local_map(shape=(60, 90), cell=1.0, x0=-20.3, y0=-30.2) -> BathyGrid:
    """A map whose every cell has a different height (so a cell is identified by value)."""
    ny, nx = shape
    iy, ix = np.mgrid[0:ny, 0:nx]
    heights = -20.0 - 0.01 * ix - 1.0 * iy
    return BathyGrid(heights, x0, y0, cell, ORIGIN["crs"])


def test_run_map_places_a_navigation_fix_in_its_cell(tmp_path):
    pred = _local_map()
    line = _line("L0", x0=-5.0, y=-2.0)
    region = track_region_mask(pred, line.position[:, :2], radius_m=6.0)
    alt_xy = line.altimeter_points()[:, :2]
    save_map_outputs(tmp_path, pred, None, region, {}, "test", origin=ORIGIN, altimeter_xy=alt_xy)
    with rasterio.open(tmp_path / "map.tif") as src:
        assert src.crs.to_epsg() == 32633
        assert src.nodata is not None and math.isnan(src.nodata)
        data = src.read(1)
        # ping 17: local ENU + origin = its projected position
        px, py = line.position[17, :2]
        row, col = src.index(px + ORIGIN["easting"], py + ORIGIN["northing"])
        lx = int(round((px - pred.x0) / pred.cell_size))
        ly = int(round((py - pred.y0) / pred.cell_size))
        assert (row, col) == (pred.shape[0] - 1 - ly, lx)
        assert data[row, col] == pytest.approx(pred.heights[ly, lx])
        # a cell far (> 20 m) from any track is no-data, the track's cells are not
        far_row, far_col = src.index(
            pred.x0 + 80.0 + ORIGIN["easting"], py + 25 + ORIGIN["northing"]
        )
        assert math.isnan(data[far_row, far_col])
        covered = np.isfinite(data[::-1])
        np.testing.assert_array_equal(covered, coverage_mask(pred, region, alt_xy))
        assert 0.05 < covered.mean() < 0.5
        assert src.tags()["SSS2BATHY_FRAME"] == "projected"
    # map.npz keeps every cell and the region; reading map.tif back with the origin gives
    # the local geometry again
    with np.load(tmp_path / "map.npz") as d:
        assert np.isfinite(d["heights"]).all() and d["region"].sum() == region.sum()
    back = read_geotiff(tmp_path / "map.tif", origin=ORIGIN)
    assert back.shape == pred.shape and back.crs == "EPSG:32633"
    assert back.x0 == pytest.approx(pred.x0, abs=1e-9)
    assert back.y0 == pytest.approx(pred.y0, abs=1e-9)
    np.testing.assert_array_equal(np.isfinite(back.heights), covered)


def test_altimeter_points_outside_the_swaths_count_as_coverage():
    grid = _local_map(shape=(10, 10), x0=0.0, y0=0.0)
    region = np.zeros(grid.shape, bool)
    cells = altimeter_cells(grid, np.array([[3.2, 6.7], [-50.0, 0.0]]))  # 2nd: off the grid
    assert cells.sum() == 1 and cells[7, 3]
    assert coverage_mask(grid, region, np.array([[3.2, 6.7]]), margin_cells=0).sum() == 1
    grown = coverage_mask(grid, region, np.array([[3.2, 6.7]]))  # + the gradient stencil
    assert grown.sum() == 9 and grown[6:9, 2:5].all()
    assert not coverage_mask(grid, region).any()
    with pytest.raises(ValueError, match="region: expected the grid's shape"):
        coverage_mask(grid, np.zeros((3, 3), bool))


def test_survey_without_crs_writes_no_crs_and_says_so(tmp_path, caplog):
    origin = {"crs": None, "easting": 1000.0, "northing": 2000.0}
    local = BathyGrid(np.full((4, 5), -7.0), 10.0, 20.0, 2.0)
    with caplog.at_level(logging.WARNING):
        write_geotiff(local, tmp_path / "g.tif", origin=origin)
    assert "without a CRS" in caplog.text and "no CRS was invented" in caplog.text
    with rasterio.open(tmp_path / "g.tif") as src:
        assert src.crs is None
        assert src.transform.c == pytest.approx(1000.0 + 10.0 - 1.0)
        assert src.transform.f == pytest.approx(2000.0 + 20.0 + 3.5 * 2.0)
        assert src.tags()["SSS2BATHY_CRS"] == "none"
    back = read_geotiff(tmp_path / "g.tif", origin=origin)
    assert (back.x0, back.y0, back.crs) == (10.0, 20.0, None)
    # the survey names a CRS the file lacks: named, not guessed
    with pytest.raises(SurveyFormatError, match="'crs': expected the survey origin's CRS EPSG"):
        read_geotiff(tmp_path / "g.tif", origin=ORIGIN)


def test_run_map_without_origin_is_local_and_carries_no_crs(tmp_path, caplog):
    pred = _local_map(shape=(8, 9))
    with caplog.at_level(logging.WARNING):
        save_map_outputs(tmp_path, pred, None, None, None, "local")
    assert "without a survey origin" in caplog.text
    with rasterio.open(tmp_path / "map.tif") as src:
        assert src.crs is None and src.tags()["SSS2BATHY_FRAME"] == "unreferenced"
        assert src.transform.c == pytest.approx(pred.x0 - 0.5)


def test_mask_must_match_the_grid(tmp_path):
    with pytest.raises(ValueError, match="mask: expected a bool array"):
        write_geotiff(_local_map(), tmp_path / "m.tif", origin=ORIGIN, mask=np.ones((2, 2), bool))


def test_large_maps_are_tiled_with_overviews(tmp_path):
    big = BathyGrid(np.random.default_rng(0).normal(-30, 1, (600, 1100)), 0.0, 0.0, 0.5)
    write_geotiff(big, tmp_path / "big.tif", origin=ORIGIN)
    with rasterio.open(tmp_path / "big.tif") as src:
        assert src.overviews(1) == [2, 4]  # 1100 / 8 < 256
        assert src.profile["tiled"] and src.block_shapes[0] == (256, 256)
    small = _local_map(shape=(30, 40))
    write_geotiff(small, tmp_path / "small.tif", origin=ORIGIN)
    with rasterio.open(tmp_path / "small.tif") as src:
        assert src.overviews(1) == []


def test_figure_axes_say_projected_or_local():
    assert axis_labels(ORIGIN) == ("easting (m), EPSG:32633", "northing (m), EPSG:32633")
    assert "local" in axis_labels(None)[0]
    assert "no CRS" in axis_labels({"crs": None, "easting": 5.0, "northing": 6.0})[0]


# ------------------------------------------------------------------------ survey grid.tif
def _survey(origin=ORIGIN) -> Survey:
    heights = -10.0 - 0.1 * np.arange(12.0)[:, None] + 0.01 * np.arange(14.0)[None, :]
    grid = BathyGrid(heights, -3.25, -4.75, 1.5, origin["crs"])
    return Survey("s", [_line("A", 0.0, 0.0)], grid=grid, splits={"test": ["A"]}, origin=origin)


def test_survey_grid_tif_is_projected_and_round_trips(tmp_path):
    survey = _survey()
    survey.save(tmp_path / "s")
    manifest = yaml.safe_load((tmp_path / "s" / "survey.yaml").read_text())
    assert manifest["grid_frame"] == "projected"
    with rasterio.open(tmp_path / "s" / "grid.tif") as src:
        assert src.crs.to_epsg() == 32633
        west, south, east, north = src.bounds
        assert west == pytest.approx(680000.0 - 3.25 - 0.75)
        assert south == pytest.approx(6580000.0 - 4.75 - 0.75)
    back = Survey.load(tmp_path / "s")
    assert back.grid.shape == survey.grid.shape
    assert back.grid.x0 == pytest.approx(-3.25, abs=1e-9)
    assert back.grid.y0 == pytest.approx(-4.75, abs=1e-9)
    np.testing.assert_array_equal(back.grid.heights, survey.grid.heights)
    assert Survey.load_grid(tmp_path / "s").x0 == back.grid.x0


def test_old_survey_folder_with_local_grid_still_loads(tmp_path):
    survey = _survey()
    folder = survey.save(tmp_path / "s")
    survey.grid.save_geotiff(folder / "grid.tif")  # as before grid_frame existed: local
    manifest = yaml.safe_load((folder / "survey.yaml").read_text())
    del manifest["grid_frame"]
    (folder / "survey.yaml").write_text(yaml.safe_dump(manifest))
    back = Survey.load(folder)
    assert (back.grid.x0, back.grid.y0) == (-3.25, -4.75)
    manifest["grid_frame"] = "utm"
    (folder / "survey.yaml").write_text(yaml.safe_dump(manifest))
    with pytest.raises(SurveyFormatError, match="'grid_frame': expected one of"):
        Survey.load(folder)


def test_survey_grid_in_another_crs_is_refused(tmp_path):
    folder = _survey().save(tmp_path / "s")
    manifest = yaml.safe_load((folder / "survey.yaml").read_text())
    manifest["origin"]["crs"] = "EPSG:32634"
    (folder / "survey.yaml").write_text(yaml.safe_dump(manifest))
    with pytest.raises(
        SurveyFormatError, match="'crs': expected the survey origin's CRS EPSG:32634"
    ):
        Survey.load(folder)


def test_survey_without_crs_saves_its_grid_without_one(tmp_path, caplog):
    origin = {"crs": None, "easting": 100.0, "northing": 200.0}
    with caplog.at_level(logging.WARNING):
        folder = _survey(origin).save(tmp_path / "s")
    assert "without a CRS" in caplog.text
    with rasterio.open(folder / "grid.tif") as src:
        assert src.crs is None
    assert Survey.load(folder).grid.x0 == pytest.approx(-3.25, abs=1e-9)
    # a grid with its own CRS label in a survey whose origin names none keeps its label
    labelled = _survey(origin)
    labelled.grid.crs = "EPSG:32633"
    back = Survey.load(labelled.save(tmp_path / "t"))
    assert back.grid.crs == "EPSG:32633" and back.grid.x0 == pytest.approx(-3.25, abs=1e-9)
    # a grid in another CRS than the origin's is refused at saving
    other = _survey()
    other.grid.crs = "EPSG:32634"
    with pytest.raises(ValueError, match="crs: expected the survey origin's CRS"):
        other.save(tmp_path / "u")


def test_report_reads_the_projected_survey_grid_back_local(tmp_path):
    from sss2bathy.eval.report import RunRecord, _origin_note, _panels, mbes_grid

    _survey().save(tmp_path / "data" / "s")
    run = RunRecord(tmp_path, {"survey_name": "s", "data_dir": str(tmp_path / "data")}, {})
    truth = mbes_grid(run)
    assert truth.x0 == pytest.approx(-3.25, abs=1e-9) and truth.crs == "EPSG:32633"
    note = _origin_note(run)
    assert "local coordinates" in note and "E 680000.0" in note and "EPSG:32633" in note
    region = np.ones(truth.shape, bool)
    assert _panels(truth, [], region, tmp_path / "maps.png", axes_note=note).is_file()
