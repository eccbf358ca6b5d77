"""First-bottom-return detector: within 2 bins of the true altitude on simulated pings."""

import numpy as np
import pytest

from sss2bathy.io.bottom import detect_first_return


@pytest.mark.parametrize(
    ("alt_lo", "alt_hi", "noise", "seed"),
    [(8.0, 12.0, 0.02, 0), (3.0, 5.0, 0.02, 1), (15.0, 25.0, 0.05, 2), (6.0, 9.0, 0.1, 3)],
)
def test_detector_within_two_bins(make_pings, alt_lo, alt_hi, noise, seed):
    P, B, max_range = 200, 256, 50.0
    range_m = (np.arange(B) + 0.5) * max_range / B
    t = np.linspace(0, 1, P)
    altitude = alt_lo + (alt_hi - alt_lo) * (0.5 + 0.5 * np.sin(6 * t))
    pings = make_pings(altitude, range_m, seed=seed, noise=noise).mean(axis=1)
    est = detect_first_return(pings, range_m)
    bin_m = max_range / B
    err_bins = np.abs(est - altitude) / bin_m
    assert est.shape == (P,) and np.all(np.isfinite(est))
    assert err_bins.max() <= 2.0, err_bins.max()
    assert np.median(err_bins) <= 1.0


def test_detector_rejects_noise_bursts_and_fills_empty_pings(make_pings):
    P, B, max_range = 120, 200, 40.0
    range_m = (np.arange(B) + 0.5) * max_range / B
    altitude = np.full(P, 10.0)
    pings = make_pings(altitude, range_m, seed=5).mean(axis=1)
    rng = np.random.default_rng(0)
    burst = rng.choice(P, 6, replace=False)
    pings[burst, 20:24] += 5.0  # a fish / noise burst at ~4 m in a few pings
    pings[50] = 0.02  # a dead ping: no contrast at all
    est = detect_first_return(pings, range_m)
    assert np.all(np.abs(est - 10.0) <= 2 * max_range / B)


def test_detector_min_range_skips_surface_echo(make_pings):
    P, B, max_range = 50, 200, 40.0
    range_m = (np.arange(B) + 0.5) * max_range / B
    altitude = np.full(P, 12.0)
    pings = make_pings(altitude, range_m, seed=7).mean(axis=1)
    pings[:, 25:30] += 3.0  # surface echo at ~5 m (towfish 5 m deep)
    assert np.all(detect_first_return(pings, range_m) < 7.0)
    est = detect_first_return(pings, range_m, min_range_m=7.0)
    assert np.all(np.abs(est - 12.0) <= 2 * max_range / B)


def test_detector_validates_inputs():
    r = np.linspace(1, 10, 8)
    with pytest.raises(ValueError, match="waterfall"):
        detect_first_return(np.zeros(8), r)
    with pytest.raises(ValueError, match="range_m"):
        detect_first_return(np.zeros((3, 8)), r[::-1])
    with pytest.raises(ValueError, match="waterfall.*NaN"):
        detect_first_return(np.full((3, 8), np.nan), r)
    with pytest.raises(ValueError, match="no first bottom return"):
        detect_first_return(np.ones((3, 8)), r)
    with pytest.raises(ValueError, match="median_pings"):
        detect_first_return(np.ones((3, 8)), r, median_pings=4)
