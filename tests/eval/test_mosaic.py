"""Sidescan mosaics: placement on a flat seabed and on a grid, gridding, overlap rules,
no-data, the GeoTIFF's georeferencing and the entry point's one-line errors."""

from __future__ import annotations

import math
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import rasterio

from sss2bathy.cli._common import USER_ERROR_EXIT
from sss2bathy.eval.mosaic import (
    MosaicConfig,
    build_mosaic,
    flat_seabed_points,
    place_line,
    placement_errors,
    write_mosaic,
    write_run_mosaic,
)
from sss2bathy.geometry import attitude_to_rotation
from sss2bathy.survey import BathyGrid, SensorParams, SidescanLine, Survey

ROOT = Path(__file__).resolve().parents[2]
ORIGIN = {"crs": "EPSG:32619", "easting": 512700.0, "northing": 5365800.0}
SEABED_Z, SONAR_Z = -20.0, -10.0  # flat seabed 10 m below the sonar
N_BINS, MAX_RANGE = 400, 40.0  # 0.1 m bins
SENSOR = SensorParams(tilt_rad=math.radians(30.0), beam_width_rad=math.radians(60.0))


def north_line(
    x: float = 0.0, n_pings: int = 41, length: float = 20.0, name: str = "L", value=None
) -> SidescanLine:
    """A level line heading North at ``x``, 10 m above the flat seabed; intensities
    ``value`` (default seeded uniform in [0.5, 1.5])."""
    y = np.linspace(0.0, length, n_pings)
    pos = np.stack([np.full(n_pings, x), y, np.full(n_pings, SONAR_Z)], 1)
    zeros = np.zeros(n_pings)
    rng = np.linspace(MAX_RANGE / N_BINS, MAX_RANGE, N_BINS)
    if value is None:
        value = np.random.default_rng(3).uniform(0.5, 1.5, (n_pings, 2, N_BINS))
    intensity = np.broadcast_to(np.asarray(value, np.float32), (n_pings, 2, N_BINS)).copy()
    return SidescanLine(
        name=name,
        time_s=np.arange(n_pings) * 0.25,
        position=pos,
        rotation=attitude_to_rotation(zeros, zeros, zeros),
        altitude_m=np.full(n_pings, SONAR_Z - SEABED_Z, np.float32),
        intensity=intensity,
        range_m=rng,
        sensor=SENSOR,
    )


def plane(a: float = 0.0, c: float = SEABED_Z, cell: float = 0.5) -> BathyGrid:
    """Grid of ``z = a x + c`` over the lines' area."""
    x = np.arange(-50.0, 80.0 + cell / 2, cell)
    y = np.arange(-10.0, 35.0 + cell / 2, cell)
    X, _ = np.meshgrid(x, y)
    return BathyGrid(a * X + c, float(x[0]), float(y[0]), cell)


def analytic_flat(line: SidescanLine) -> np.ndarray:
    """``(P, 2, B, 3)``: port (left of North = West) at ``x - g``, starboard at ``x + g``,
    ``g = sqrt(r^2 - h^2)``; NaN before the first return."""
    h = SONAR_Z - SEABED_Z
    with np.errstate(invalid="ignore"):
        g = np.sqrt(line.range_m.astype(np.float64) ** 2 - h**2)
    P = line.n_pings
    out = np.empty((P, 2, line.n_bins, 3))
    for side, sign in ((0, -1.0), (1, 1.0)):
        out[:, side, :, 0] = line.position[:, None, 0] + sign * g[None, :]
        out[:, side, :, 1] = line.position[:, None, 1]
        out[:, side, :, 2] = SEABED_Z
    out[:, :, ~np.isfinite(g)] = np.nan
    return out


def survey_of(*lines: SidescanLine, grid: BathyGrid | None = None) -> Survey:
    return Survey(name="flat", lines=list(lines), grid=grid, origin=dict(ORIGIN))


# ----------------------------------------------------------------------------- placement
def test_flat_placement_is_the_slant_range_correction():
    line = north_line()
    got, want = flat_seabed_points(line), analytic_flat(line)
    assert np.array_equal(np.isnan(got[..., 0]), np.isnan(want[..., 0]))
    ok = np.isfinite(want[..., 0])
    assert ok.sum() > 0.7 * ok.size  # bins 0-98 are nearer than the seabed
    assert np.abs(got[ok] - want[ok]).max() < 1e-9


def test_flat_placement_follows_roll_and_heading():
    """A rolled vehicle heading East: the flat placement is still on the seabed plane, at the
    slant range from the sonar, across the heading (the arc conventions, not sqrt alone)."""
    n = 5
    R = attitude_to_rotation(np.full(n, math.pi / 2), np.zeros(n), np.full(n, math.radians(8.0)))
    line = north_line(n_pings=n)
    line = SidescanLine(
        "rolled", line.time_s, line.position, R, line.altitude_m, line.intensity, line.range_m
    )
    pts = flat_seabed_points(line)
    ok = np.isfinite(pts[..., 0])
    assert np.allclose(pts[..., 2][ok], SEABED_Z)
    dist = np.linalg.norm(pts - line.position[:, None, None, :], axis=-1)
    assert np.allclose(dist[ok], np.broadcast_to(line.range_m, ok.shape)[ok], atol=1e-5)
    # heading East: port (left) is North, starboard South; the ping's y does not move
    dy = pts[..., 1] - line.position[:, None, None, 1]
    assert np.all(dy[:, 0][ok[:, 0]] > -1e-9) and np.all(dy[:, 1][ok[:, 1]] < 1e-9)
    assert dy[:, 0][ok[:, 0]].max() > 30.0 and dy[:, 1][ok[:, 1]].min() < -30.0
    assert np.allclose(
        pts[..., 0][ok], np.broadcast_to(line.position[:, None, None, 0], ok.shape)[ok]
    )


def test_draped_on_the_true_flat_grid_matches_the_flat_placement():
    line = north_line()
    placed = place_line(line, "grid", plane())
    want = analytic_flat(line)
    ok = placed.mask == 0
    assert ok.sum() > 0.5 * ok.size
    # the draping is exact on a planar surface up to its float32 points
    assert np.abs(placed.points[ok] - want[ok]).max() < 1e-3
    assert np.allclose(placed.ground_range[ok], np.abs(want[..., 0][ok]), atol=1e-3)


def test_placement_errors_on_a_slope_show_what_flat_placement_misses():
    """Across a 5 % slope the flat seabed misplaces bins by decimetres; draped on the true
    grid they are where the truth draping puts them."""
    line = north_line()
    truth = plane(a=0.05, c=SEABED_Z)
    err = placement_errors(line, truth, surface=truth)
    assert err["flat"]["n"] > 1000 and err["grid"]["n"] > 1000
    assert err["grid"]["p95"] < 1e-6
    assert 0.1 < err["flat"]["median"] < err["flat"]["p95"] < 5.0


# ----------------------------------------------------------------------------- gridding
@pytest.mark.parametrize("axis", ["across", "along"])
def test_every_cell_holds_a_bin_within_half_a_cell_of_it(axis):
    """Each bin carries its own true coordinate as its value (the ground range across, the
    ping's northing along): a cell's value is that coordinate at the cell, within half a
    cell plus half the spacing of the bins (their footprints)."""
    cell = 0.25
    line = north_line()
    truth = analytic_flat(line)
    if axis == "across":
        value = np.nan_to_num(np.abs(truth[..., 0]), nan=1.0) + 1.0
    else:
        value = np.broadcast_to(line.position[:, None, None, 1] + 1.0, truth.shape[:3])
    line.intensity = np.asarray(value, np.float32)
    mosaic = build_mosaic(survey_of(line), {"resolution": cell, "normalise": "raw"})
    g = mosaic.grid
    X, Y = np.meshgrid(g.x, g.y)
    has = np.isfinite(g.heights)
    assert has.mean() > 0.5
    want = (np.abs(X) if axis == "across" else Y) + 1.0
    err = np.abs(g.heights[has] - want[has])
    # bins 0.1 m apart in slant range (<= 0.2 m on the ground here), pings 0.5 m apart
    spacing = 0.2 if axis == "across" else 0.5
    assert np.median(err) <= cell / 2 + 1e-9
    assert err.max() <= cell / 2 * math.sqrt(2) + spacing / 2 + 1e-6


def test_overlap_nearest_to_nadir_max_and_mean():
    """Two lines 30 m apart, values 1 and 2: between them the nearer line's bin wins."""
    a = north_line(0.0, name="A", value=1.0)
    b = north_line(30.0, name="B", value=2.0)
    survey = survey_of(a, b)

    def at(mosaic, x, y=10.0):
        g = mosaic.grid
        return g.heights[int(round((y - g.y0) / g.cell_size)), int(round((x - g.x0) / g.cell_size))]

    base = {"resolution": 0.5, "normalise": "raw"}
    nadir = build_mosaic(survey, {**base, "overlap": "nadir"})
    assert at(nadir, 10.0) == 1.0 and at(nadir, 12.0) == 1.0  # 10-12 m from A, 18-20 from B
    assert at(nadir, 20.0) == 2.0 and at(nadir, 18.0) == 2.0
    assert at(nadir, -20.0) == 1.0 and at(nadir, 50.0) == 2.0  # one line only
    biggest = build_mosaic(survey, {**base, "overlap": "max"})
    assert at(biggest, 10.0) == 2.0 and at(biggest, -20.0) == 1.0
    mean = build_mosaic(survey, {**base, "overlap": "mean"})
    assert 1.0 < at(mean, 10.0) < 2.0 and 1.0 < at(mean, 20.0) < 2.0
    assert at(mean, -20.0) == pytest.approx(1.0)
    # a tie (the middle): the first line of the survey
    assert at(nadir, 15.0) == 1.0


def test_masked_bins_are_nodata():
    line = north_line()
    line.intensity[:, 1, 250:271] = np.nan  # starboard, ground range ~22.9-25.1 m
    survey = survey_of(line)
    g = build_mosaic(survey, {"resolution": 0.25, "normalise": "raw"}).grid
    X, _ = np.meshgrid(g.x, g.y)
    inside_y = (g.y > 1.0)[:, None] & (g.y < 19.0)[:, None]
    h = 10.0
    g_first = math.sqrt(26.0**2 - h**2) - 0.3, math.sqrt(26.0**2 - h**2) + 0.3
    hole = inside_y & (X > g_first[0]) & (X < g_first[1])
    assert np.isnan(g.heights[hole]).all()
    assert np.isfinite(g.heights[inside_y & (X < -g_first[0]) & (X > -g_first[1])]).all()
    # near nadir: out of the 0-60 deg beam on a flat seabed (ground range < h / tan 60)
    near = inside_y & (np.abs(X) < h / math.tan(math.radians(60.0)) - 0.3)
    assert np.isnan(g.heights[near]).all()
    kept = build_mosaic(survey, {"resolution": 0.25, "normalise": "raw", "blank": []}).grid
    assert np.isfinite(kept.heights[near & (np.abs(X) > 1.5)]).mean() > 0.95


def test_normalised_values_and_bad_settings():
    line = north_line(value=np.linspace(10.0, 50.0, N_BINS))  # a range ramp
    survey = survey_of(line)
    rel = build_mosaic(survey, {"resolution": 0.5, "normalise": True}).grid.heights
    assert np.nanmedian(rel) == pytest.approx(1.0, abs=0.05)  # the ramp divides out
    assert np.nanstd(rel) < 0.05
    raw = build_mosaic(survey, {"resolution": 0.5, "normalise": False}).grid.heights
    assert np.nanmax(raw) > 40.0
    for bad, text in (
        ({"overlap": "min"}, "overlap: expected one of"),
        ({"resolution": 0}, "resolution: expected a cell size"),
        ({"blank": ["shade"]}, "blank: expected names of"),
        ({"placement": "mesh"}, "placement: expected one of"),
        ({"colour": 1}, "unknown keys ['colour']"),
    ):
        with pytest.raises(ValueError, match=text.replace("[", r"\[").replace("]", r"\]")):
            MosaicConfig.coerce(bad)
    with pytest.raises(ValueError, match="placement=grid needs a height grid"):
        build_mosaic(survey, {"placement": "grid"})


# ----------------------------------------------------------------------------- files
def test_geotiff_is_projected_around_the_track(tmp_path):
    line = north_line()
    survey = survey_of(line)
    mosaic = build_mosaic(survey, {"resolution": 0.5})
    tif, png = write_mosaic(mosaic, tmp_path / "m.tif", survey.origin, track=[line.position])
    assert png.suffix == ".png" and png.stat().st_size > 1000
    with rasterio.open(tif) as src:
        assert src.crs.to_epsg() == 32619
        b = src.bounds
        tags = src.tags()
        assert src.descriptions[0].startswith("sidescan intensity relative")
    east = line.position[:, 0] + ORIGIN["easting"]
    north = line.position[:, 1] + ORIGIN["northing"]
    reach = math.sqrt(MAX_RANGE**2 - 10.0**2)
    assert b.left == pytest.approx(east.min() - reach, abs=1.0)
    assert b.right == pytest.approx(east.max() + reach, abs=1.0)
    assert b.bottom <= north.min() and b.top >= north.max()
    assert b.top - b.bottom <= north.max() - north.min() + 4 * 0.5
    assert tags["SSS2BATHY_MOSAIC_OVERLAP"] == "nadir"
    assert tags["SSS2BATHY_FRAME"] == "projected"


def test_write_run_mosaic_drapes_on_a_given_grid(tmp_path):
    survey = survey_of(north_line())
    flat = write_run_mosaic(tmp_path / "flat", survey)
    draped = write_run_mosaic(tmp_path / "grid", survey, grid=plane(), cfg={"resolution": 0.5})
    assert [p.name for p in flat] == ["mosaic.tif", "mosaic.png"]
    with rasterio.open(flat[0]) as a, rasterio.open(draped[0]) as b:
        assert a.tags()["SSS2BATHY_METHOD"].endswith("placement=flat")
        assert b.tags()["SSS2BATHY_METHOD"].endswith("placement=grid")
        assert b.res == (0.5, 0.5)


def run_cli(args: list[str], tmp_path: Path) -> subprocess.CompletedProcess:
    env = {**os.environ, "SSS2BATHY_ROOT": str(ROOT), "OMP_NUM_THREADS": "1"}
    env.pop("HYDRA_FULL_ERROR", None)
    return subprocess.run(
        [sys.executable, "-m", "sss2bathy.cli.mosaic", *args, f"hydra.run.dir={tmp_path / 'o'}"],
        cwd=tmp_path,
        env=env,
        capture_output=True,
        text=True,
        timeout=120,
    )


def test_cli_missing_survey_folder_is_one_line(tmp_path):
    missing = tmp_path / "no_survey"
    proc = run_cli([f"survey={missing}", f"out={tmp_path / 'm.tif'}"], tmp_path)
    lines = [ln for ln in proc.stderr.splitlines() if ln.strip()]
    assert proc.returncode == USER_ERROR_EXIT, proc.stderr
    assert len(lines) == 1, proc.stderr
    assert lines[0].startswith("error: survey: expected a survey folder holding survey.yaml")
    assert str(missing) in lines[0] and "no such folder" in lines[0]
    assert not (tmp_path / "o").exists()  # refused before the run folder


@pytest.mark.slow  # a fresh interpreter importing torch and Hydra: ~20 s on a busy CPU
def test_cli_writes_the_mosaic(tmp_path):
    folder = survey_of(north_line(n_pings=21)).save(tmp_path / "survey")
    out = tmp_path / "out" / "m.tif"
    proc = run_cli([f"survey={folder}", f"out={out}", "resolution=0.5", "overlap=max"], tmp_path)
    assert proc.returncode == 0, proc.stderr
    assert out.is_file() and out.with_suffix(".png").is_file()
    with rasterio.open(out) as src:
        assert src.crs.to_epsg() == 32619 and src.res == (0.5, 0.5)
        assert src.tags()["SSS2BATHY_MOSAIC_OVERLAP"] == "max"
