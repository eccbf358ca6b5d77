"""Per-cell height uncertainty: the delete-a-fold jackknife of the verdict's fold maps, its
calibration factor and scores, and the run's uncertainty.tif on map.tif's grid."""

from __future__ import annotations

import math

import numpy as np
import pytest
import rasterio

from sss2bathy.eval.uncertainty import (
    GAUSS_1SIGMA,
    GAUSS_2SIGMA,
    calibrate_scale,
    calibration_stats,
    coverage,
    fold_members,
    jackknife_sigma,
    scaled_sigma,
    spearman,
    write_run_uncertainty,
)
from sss2bathy.io.export import cog_layout, write_geotiff
from sss2bathy.survey import BathyGrid

ORIGIN = {"crs": "EPSG:32633", "easting": 512300.0, "northing": 6402100.0}


def test_jackknife_sigma_is_the_delete_a_group_standard_error():
    rng = np.random.default_rng(0)
    members = rng.normal(-20.0, 0.3, (5, 4, 6))
    k = members.shape[0]
    want = np.sqrt((k - 1) / k * ((members - members.mean(0)) ** 2).sum(0))
    got = jackknife_sigma(members)
    assert got.dtype == np.float32 and got.shape == (4, 6)
    np.testing.assert_allclose(got, want, rtol=1e-5)
    # sqrt(K - 1) x the members' own standard deviation (ddof 1) / sqrt(K) * sqrt(K - 1)
    np.testing.assert_allclose(got, (k - 1) / math.sqrt(k) * members.std(0, ddof=1), rtol=1e-5)
    # identical replicates: zero; a NaN member: NaN in that cell only
    assert np.all(jackknife_sigma(np.repeat(members[:1], 3, axis=0)) == 0)
    members[2, 1, 1] = np.nan
    out = jackknife_sigma(members)
    assert np.isnan(out[1, 1]) and np.isfinite(out).sum() == out.size - 1


@pytest.mark.parametrize("shape", [(1, 3, 3), (3, 3)])
def test_jackknife_needs_two_or_more_maps(shape):
    with pytest.raises(ValueError, match="members: expected"):
        jackknife_sigma(np.zeros(shape))


def test_scale_factor_is_checked():
    assert scaled_sigma(np.array([0.5, 1.0]), 2.0).tolist() == [1.0, 2.0]
    for bad in (0, -1.0, math.nan, "2"):
        with pytest.raises(ValueError, match="uncertainty.scale"):
            scaled_sigma(np.ones(2), bad)


def test_a_calibrated_narrow_sigma_covers_a_gaussian_error_as_a_gaussian_should():
    """Errors N(0, s) per cell, a raw sigma 3x too narrow but of the right shape: the
    factor comes out near 3 and, calibrated on half the cells, the other half's coverage is
    Gaussian (tolerance: 2 points at 10,000 cells)."""
    rng = np.random.default_rng(1)
    s = rng.uniform(0.05, 0.5, 20_000)
    err = rng.normal(0.0, s)
    raw = s / 3.0
    c = calibrate_scale(np.abs(err[::2]), raw[::2])
    assert c == pytest.approx(3.0, rel=0.05)
    sigma = c * raw[1::2]
    assert coverage(err[1::2], sigma, 1) == pytest.approx(GAUSS_1SIGMA, abs=0.02)
    assert coverage(err[1::2], sigma, 2) == pytest.approx(GAUSS_2SIGMA, abs=0.02)
    stats = calibration_stats(err[1::2], sigma)
    assert stats["within_1sigma"] == pytest.approx(GAUSS_1SIGMA, abs=0.02)
    assert stats["scale_1sigma"] == pytest.approx(1.0, abs=0.05)
    assert stats["spearman"] > 0.3  # a larger sigma marks larger errors
    # an uninformative sigma: coverage can be right on average, the rank correlation is not
    flat = np.full_like(sigma, float(np.median(sigma)))
    assert (
        abs(calibration_stats(err[1::2], flat * rng.uniform(0.5, 1.5, flat.size))["spearman"])
        < 0.05
    )
    # and a sigma 3x too narrow covers far too little
    assert calibration_stats(err, raw)["within_1sigma"] < 0.35


def test_calibration_inputs_are_checked():
    with pytest.raises(ValueError, match="level"):
        calibrate_scale(np.ones(3), np.ones(3), level=1.0)
    with pytest.raises(ValueError, match="sigma: expected cells"):
        calibrate_scale(np.ones(3), np.zeros(3))
    with pytest.raises(ValueError, match="sigma: expected the errors' shape"):
        coverage(np.ones(3), np.ones(4))
    assert math.isnan(spearman(np.ones(2), np.ones(2)))
    # non-finite cells are left out, not counted as misses
    assert coverage(np.array([0.1, np.nan, 5.0]), np.array([1.0, 1.0, np.nan])) == 1.0


def _run_folder(tmp_path, k=4, shape=(30, 40), cell=0.5, seed=0):
    """A map run folder: map.npz (coverage: a band of rows) and K fold maps whose spread
    grows towards the east."""
    rng = np.random.default_rng(seed)
    ny, nx = shape
    x = np.arange(nx) / nx
    final = -25.0 + rng.normal(0, 0.05, shape)
    coverage_ = np.zeros(shape, bool)
    coverage_[5:25, :] = True
    run = tmp_path / "run"
    run.mkdir()
    geom = {"x0": np.float64(1.25), "y0": np.float64(-3.25), "cell_size": np.float64(cell)}
    np.savez(run / "map.npz", heights=final.astype(np.float32), coverage=coverage_, **geom)
    folds = []
    for fold in range(k):
        h = final + rng.normal(0, 1, shape) * (0.02 + 0.3 * x)[None, :]
        (run / "verdict" / "siren_lambert" / f"fold{fold}").mkdir(parents=True)
        np.savez(run / "verdict" / "siren_lambert" / f"fold{fold}" / "map.npz", heights=h, **geom)
        folds.append(h)
    grid = BathyGrid(final.astype(np.float32), 1.25, -3.25, cell, ORIGIN["crs"])
    return run, grid, coverage_, np.stack(folds)


def test_fold_members_reads_the_verdicts_fold_maps_on_the_final_grid(tmp_path):
    run, grid, _, folds = _run_folder(tmp_path, k=3)
    got = fold_members(run, "siren_lambert", grid)
    assert got.k == 3 and [p.parent.name for p in got.paths] == ["fold0", "fold1", "fold2"]
    np.testing.assert_allclose(got.heights, folds.astype(np.float32))
    with pytest.raises(ValueError, match=r"expected the map.npz of >= 2 fold fits"):
        fold_members(run, "siren_cnn_n2d", grid)
    # a fold on another grid is named
    bad = run / "verdict" / "siren_lambert" / "fold1" / "map.npz"
    np.savez(bad, heights=folds[1], x0=1.75, y0=-3.25, cell_size=0.5)
    with pytest.raises(ValueError, match="fold1/map.npz: expected a fold map on the final"):
        fold_members(run, "siren_lambert", grid)


def test_run_uncertainty_lies_on_map_tifs_grid_with_its_no_data(tmp_path):
    run, grid, covered, folds = _run_folder(tmp_path)
    write_geotiff(grid, run / "map.tif", origin=ORIGIN, mask=covered)
    out = write_run_uncertainty(run, "siren_lambert", 2.5, ORIGIN, "SIREN-Lambert")
    assert out.tif == run / "uncertainty.tif" and out.png.is_file() and out.folds == 4
    with rasterio.open(run / "map.tif") as m, rasterio.open(out.tif) as u:
        assert (u.crs, u.transform, u.shape, u.dtypes) == (m.crs, m.transform, m.shape, m.dtypes)
        assert math.isnan(u.nodata) and math.isnan(m.nodata)
        sigma, heights = u.read(1), m.read(1)
        assert u.units == ("m",) and "sigma" in u.descriptions[0]
        tags = u.tags()
    np.testing.assert_array_equal(np.isfinite(sigma), np.isfinite(heights))  # same no-data
    want = 2.5 * jackknife_sigma(folds.astype(np.float32))[::-1]  # row 0 of the file is north
    np.testing.assert_allclose(sigma[np.isfinite(sigma)], want[np.isfinite(sigma)], rtol=1e-5)
    assert (
        tags["SSS2BATHY_UNCERTAINTY_SCALE"] == "2.5" and tags["SSS2BATHY_UNCERTAINTY_FOLDS"] == "4"
    )
    assert (
        tags["SSS2BATHY_METHOD"] == "siren_lambert" and "jackknife" in tags["SSS2BATHY_UNCERTAINTY"]
    )
    # sigma grows where the folds disagree (east)
    west, east = sigma[:, :10], sigma[:, -10:]
    assert np.nanmedian(east) > 3 * np.nanmedian(west)
    assert not cog_layout(out.tif).problems()
    metrics = out.to_metrics()
    assert metrics["uncertainty/scale"] == 2.5 and metrics["uncertainty/folds"] == 4
    assert metrics["uncertainty/sigma_median_m"] == pytest.approx(np.nanmedian(sigma), rel=1e-5)


def test_run_uncertainty_needs_the_final_map(tmp_path):
    with pytest.raises(ValueError, match="map.npz: expected the run's final map"):
        write_run_uncertainty(tmp_path, "siren_lambert", 1.0, ORIGIN)
