"""First-bottom-return detector: within 2 bins of the true altitude on simulated pings."""

import numpy as np
import pytest

from sss2bathy.io.bottom import bad_pings, detect_first_return


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
    est = detect_first_return(pings, range_m).altitude_m
    bin_m = max_range / B
    err_bins = np.abs(est - altitude) / bin_m
    assert est.shape == (P,) and np.all(np.isfinite(est))
    assert err_bins.max() <= 2.0, err_bins.max()
    assert np.median(err_bins) <= 1.0


def test_detector_rejects_noise_bursts_and_flags_dead_pings(make_pings):
    P, B, max_range = 120, 200, 40.0
    range_m = (np.arange(B) + 0.5) * max_range / B
    altitude = np.full(P, 10.0)
    pings = make_pings(altitude, range_m, seed=5).mean(axis=1)
    rng = np.random.default_rng(0)
    burst = rng.choice(P, 6, replace=False)
    pings[burst, 20:24] += 5.0  # a fish / noise burst at ~4 m in a few pings
    pings[50] = 0.02  # a dead ping: no contrast at all -> flagged, no pick
    pings[70, 100:110] = 0.0  # a few dropped samples: still detected, then filled
    res = detect_first_return(pings, range_m)
    est = res.altitude_m
    assert res.bad[50] and res.bad.sum() == 1 and np.isnan(est[50])
    ok = np.arange(P) != 50
    assert np.all(np.abs(est[ok] - 10.0) <= 2 * max_range / B)


def test_detector_min_range_skips_surface_echo(make_pings):
    P, B, max_range = 50, 200, 40.0
    range_m = (np.arange(B) + 0.5) * max_range / B
    altitude = np.full(P, 12.0)
    pings = make_pings(altitude, range_m, seed=7).mean(axis=1)
    pings[:, 25:30] += 3.0  # surface echo at ~5 m (towfish 5 m deep)
    assert np.all(detect_first_return(pings, range_m).altitude_m < 7.0)
    est = detect_first_return(pings, range_m, min_range_m=7.0).altitude_m
    assert np.all(np.abs(est - 12.0) <= 2 * max_range / B)


def test_detector_validates_inputs():
    r = np.linspace(1, 10, 8)
    with pytest.raises(ValueError, match="waterfall"):
        detect_first_return(np.zeros(8), r)
    with pytest.raises(ValueError, match="range_m"):
        detect_first_return(np.zeros((3, 8)), r[::-1])
    with pytest.raises(ValueError, match="blanking_m"):
        detect_first_return(np.ones((3, 8)), r, blanking_m=-1.0)
    with pytest.raises(ValueError, match="median_pings"):
        detect_first_return(np.ones((3, 8)), r, median_pings=4)


def ringdown(range_m, length_m=1.5, level=10.0):
    """Transducer ring-down: ``level`` at range 0 decaying to the noise by ``length_m``."""
    return level * np.exp(-range_m / (length_m / 6.0))


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_detector_skips_saturated_ringdown_within_20cm(make_pings, seed):
    # AUV-like pings: 512 bins over 40 m (7.8 cm), altitude 3.8-6.8 m, a 1.5 m ring-down
    # clipped at the receiver's maximum (saturated near field).
    P, B, max_range = 200, 512, 40.0
    range_m = (np.arange(B) + 0.5) * max_range / B
    t = np.linspace(0, 1, P)
    altitude = 3.8 + 3.0 * (0.5 + 0.5 * np.sin(6 * t + seed))
    pings = make_pings(altitude, range_m, seed=seed).mean(axis=1)
    pings = np.minimum(pings + ringdown(range_m)[None, :], 8.0)
    res = detect_first_return(pings, range_m)
    assert 1.0 <= res.blanking_m <= 2.5
    assert res.picked.all() and not res.bad.any()
    assert np.abs(res.altitude_m - altitude).max() <= 0.2


def test_detector_without_blanking_rejects_instead_of_zero(make_pings):
    P, B, max_range = 60, 512, 40.0
    range_m = (np.arange(B) + 0.5) * max_range / B
    pings = make_pings(np.full(P, 5.0), range_m, seed=3).mean(axis=1)
    pings = pings + ringdown(range_m)[None, :]
    res = detect_first_return(pings, range_m, auto_blanking=False)
    # The ring-down rises at bin 0: the edge is unknown, so no altitude (never 0 m).
    assert res.rejected.all() and np.isnan(res.altitude_m).all()
    fixed = detect_first_return(pings, range_m, auto_blanking=False, blanking_m=2.0)
    assert np.abs(fixed.altitude_m - 5.0).max() <= 0.2


def test_detector_rejects_a_bottom_inside_the_ringdown(make_pings):
    # Altitude 1 m inside a 1.5 m ring-down: no supported pick, NaN rather than a guess.
    P, B, max_range = 40, 512, 40.0
    range_m = (np.arange(B) + 0.5) * max_range / B
    pings = make_pings(np.full(P, 1.0), range_m, seed=4).mean(axis=1)
    pings = pings + ringdown(range_m, length_m=1.5, level=2.0)[None, :]
    res = detect_first_return(pings, range_m, blanking_m=1.5)
    assert not res.picked.any() and np.isnan(res.altitude_m).all()


def test_bad_pings_are_flagged_by_kind():
    rng = np.random.default_rng(0)
    w = rng.exponential(1.0, (5, 50))
    w[1] = 3.0
    w[2, :40] = w.max()
    w[3, 7] = np.nan
    flags = bad_pings(w)
    assert flags["constant"].tolist() == [False, True, False, False, False]
    assert flags["saturated"].tolist() == [False, False, True, False, False]
    assert flags["nonfinite"].tolist() == [False, False, False, True, False]


def test_calibrate_to_altimeter_removes_the_local_detector_error():
    from sss2bathy.io.bottom import calibrate_to_altimeter

    P = 120
    truth = 10.0 + 0.01 * np.arange(P)
    # the detector reads 1.2 m late over pings 20-59 (nadir echo missed), 0.3 m early after
    fr = truth + np.where((np.arange(P) >= 20) & (np.arange(P) < 60), 1.2, -0.3)
    alt = truth.copy()
    gap = np.r_[35:38, 90:93]
    alt[gap] = np.nan
    out, offset = calibrate_to_altimeter(fr, alt, n_ref=6)
    assert np.abs(out[gap] - truth[gap]).max() < 1e-9
    assert np.allclose(offset[gap[:3]], -1.2) and np.allclose(offset[gap[3:]], 0.3)
    keep = np.setdiff1d(np.arange(P), gap)
    assert np.array_equal(out[keep], fr[keep]) and not offset[keep].any()
    # no ping with both values: the raw picks; a shift to <= 0 m is not applied
    raw, off0 = calibrate_to_altimeter(fr, np.full(P, np.nan))
    assert np.array_equal(raw, fr) and not off0.any()
    low, off1 = calibrate_to_altimeter(np.array([0.5, 3.0]), np.array([np.nan, 1.0]))
    assert low[0] == 0.5 and off1[0] == 0.0
    with pytest.raises(ValueError, match="equal 1-D shapes"):
        calibrate_to_altimeter(fr, alt[:3])
