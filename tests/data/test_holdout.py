"""Held-out altimeter evaluation: the block split, the interpolation baseline, the datamodule."""

from __future__ import annotations

import importlib.util
from pathlib import Path

import numpy as np
import pytest

from sss2bathy.data.holdout import (
    along_track_blocks,
    along_track_distance,
    default_block_m,
    fold_blocks,
    holdout_blocks,
    holdout_mae,
    interpolate_along_track,
    split_altimeter,
    split_altimeter_fold,
)
from sss2bathy.data.pings import PingAltimeterDataModule, holdout_config

ROOT = Path(__file__).resolve().parents[2]


def _runs(mask: np.ndarray) -> list[tuple[int, int]]:
    """``(start, stop)`` of the runs of True in a bool array."""
    edges = np.diff(np.concatenate([[0], mask.astype(int), [0]]))
    return list(zip(np.flatnonzero(edges == 1), np.flatnonzero(edges == -1), strict=True))


# ------------------------------------------------------------------ the split
@pytest.mark.parametrize("fraction", [0.1, 0.2, 0.5])
def test_blocks_hold_out_the_fraction_in_whole_aligned_blocks(fraction):
    n_pings = [500, 300, 200]  # 10 + 6 + 4 = 20 blocks of 50
    held = holdout_blocks(n_pings, fraction, 50, seed=3)
    assert [h.shape for h in held] == [(n,) for n in n_pings]
    n_held = sum(int(h.sum()) for h in held)
    assert n_held == round(fraction * 20) * 50  # whole blocks, the requested share of them
    for h in held:
        for start, stop in _runs(h):  # contiguous runs made of aligned blocks
            assert start % 50 == 0 and (stop - start) % 50 == 0
        assert not h[:50].any() and not h[-50:].any()  # a line's ends are always kept


def test_blocks_are_seeded_and_zero_fraction_holds_out_nothing():
    a = holdout_blocks([400, 400], 0.25, 40, seed=7)
    b = holdout_blocks([400, 400], 0.25, 40, seed=7)
    c = holdout_blocks([400, 400], 0.25, 40, seed=8)
    assert all(np.array_equal(x, y) for x, y in zip(a, b, strict=True))
    assert not all(np.array_equal(x, y) for x, y in zip(a, c, strict=True))
    assert not any(h.any() for h in holdout_blocks([400, 400], 0.0, 40, seed=7))
    with pytest.raises(ValueError, match=r"holdout.fraction: expected a number in \[0, 1\)"):
        holdout_blocks([10], 1.0, 5, seed=0)
    with pytest.raises(ValueError, match="holdout.block_pings: expected a positive count"):
        holdout_blocks([10], 0.2, 0, seed=0)


def test_a_line_never_loses_its_last_altimeter_points():
    # two short lines of one block each: holding out either would leave no baseline
    held = holdout_blocks([30, 30], 0.5, 50, seed=0)
    assert not any(h.any() for h in held)
    # a line whose only valid points are in its middle block keeps that block
    valid = [np.r_[np.zeros(50, bool), np.ones(50, bool), np.zeros(50, bool)], np.ones(150, bool)]
    for seed in range(10):
        held = holdout_blocks([150, 150], 0.5, 50, seed, valid=valid)
        assert not held[0].any()
        assert held[1].sum() == 50 and held[1][50:100].all()


def _line(n: int, heading: tuple[float, float], start: tuple[float, float]):
    k = np.arange(n, dtype=float)
    x, y = start[0] + heading[0] * k, start[1] + heading[1] * k
    seabed = -20.0 + 0.5 * np.sin(0.05 * (x + y))
    z = np.full(n, -10.0)
    altitude = z - seabed
    return np.stack([x, y, z], 1), altitude, seabed


def test_split_has_no_overlap_with_the_fitted_points_and_interpolates_the_gaps():
    (p0, a0, s0), (p1, a1, s1) = _line(400, (1.0, 0.0), (0, 0)), _line(300, (0.0, 1.5), (5, 5))
    a0[17] = np.nan  # a missing altimeter reading is in neither set
    split = split_altimeter([p0, p1], [a0, a1], 0.2, 25, seed=1)
    assert split.n_held == split.held.shape[0] == split.interp.shape[0] > 0
    assert split.fit.shape[0] + split.n_held == 699
    assert split.fraction == pytest.approx(split.n_held / 699)
    fitted = {tuple(p) for p in np.round(split.fit[:, :2], 6)}
    held = {tuple(p) for p in np.round(split.held[:, :2], 6)}
    assert not fitted & held
    # held-out points are the seabed below their pings
    for line, (pos, seabed) in enumerate(((p0, s0), (p1, s1))):
        pick = split.held_line == line
        ping = split.held_ping[pick]
        np.testing.assert_allclose(split.held[pick, :2], pos[ping, :2])
        np.testing.assert_allclose(split.held[pick, 2], seabed[ping])
    # smooth seabed: interpolating across 25-ping gaps is close, not exact
    assert 0 < split.interp_mae < 0.2
    assert split.interp_mae == pytest.approx(holdout_mae(split.interp, split.held[:, 2]))


# ------------------------------------------------------------------ the baseline
def test_interpolation_is_linear_along_track_and_flat_beyond_the_ends():
    # a dog-leg track: distance along it, not x or y, is the interpolation variable
    xy = np.array([[0, 0], [3, 4], [6, 8], [6, 18], [6, 28]], float)
    s = along_track_distance(xy)
    np.testing.assert_allclose(s, [0, 5, 10, 20, 30])
    profile = -20.0 + 0.1 * s  # a known linear profile along the track
    keep = np.array([True, False, True, False, True])
    np.testing.assert_allclose(
        interpolate_along_track(s[keep], profile[keep], s[~keep]), [-19.5, -18.0]
    )
    np.testing.assert_allclose(
        interpolate_along_track(
            np.array([5.0, 10.0]), np.array([1.0, 2.0]), np.array([0, 7.5, 30])
        ),
        [1.0, 1.5, 2.0],
    )
    assert np.isnan(interpolate_along_track(np.zeros(0), np.zeros(0), np.array([1.0]))).all()
    with pytest.raises(ValueError, match="non-decreasing"):
        interpolate_along_track(np.array([2.0, 1.0]), np.array([0.0, 0.0]), np.array([1.5]))


def test_known_profile_interpolation_error():
    # seabed z = -20 + 0.01 s^2 sampled every metre: linear interpolation across a gap of
    # 2h metres misses the parabola by 0.01 * (h^2 - t^2) at t from the gap's centre
    s = np.arange(101, dtype=float)
    z = -20.0 + 0.01 * s**2
    keep = np.ones(101, bool)
    keep[40:61] = False  # a 21-ping gap between s = 39 and s = 61
    pred = interpolate_along_track(s[keep], z[keep], s[~keep])
    t = s[~keep] - 50.0
    np.testing.assert_allclose(pred - z[~keep], 0.01 * (11.0**2 - t**2), atol=1e-9)


# ------------------------------------------------------------------ the datamodule
def _tiny_survey(folder: Path) -> Path:
    spec = importlib.util.spec_from_file_location("_pings_tests", ROOT / "tests/data/test_pings.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module.make_tiny_survey(folder)


def test_datamodule_fits_on_the_kept_points_and_keeps_all_pings(tmp_path):
    survey = _tiny_survey(tmp_path / "tiny_plane")
    cfg = {"kind": "folder", "path": str(survey)}
    common = dict(normals="none", batch_pings=16, altimeter_points=50, seed=4)
    full = PingAltimeterDataModule(cfg, str(tmp_path), **common)
    full.setup("fit")
    dm = PingAltimeterDataModule(
        cfg, str(tmp_path), holdout={"fraction": 0.25, "block_pings": 10}, **common
    )
    dm.setup("fit")
    assert full.holdout_split is None
    split = dm.holdout_split
    assert dm.holdout == {  # seed = data.seed; the K-fold split off
        "fraction": 0.25,
        "block_pings": 10,
        "seed": 4,
        "folds": 0,
        "fold": 0,
        "block_m": None,
    }
    # 8 blocks of 10 pings, 2 held out (19 points if one holds the missing reading)
    assert split is not None and split.n_held in (19, 20)
    assert dm.table.n_pings == full.table.n_pings  # all the sidescan is still used
    assert dm.altimeter.shape[0] + split.n_held == full.altimeter.shape[0]
    fitted = {tuple(p) for p in np.round(dm.altimeter.numpy()[:, :2].astype(float), 3)}
    held = {tuple(p) for p in np.round(split.held[:, :2], 3)}
    assert fitted & held <= {(60.0, 60.0)}  # only where the two lines cross
    # plane seabed, straight lines: the interpolation baseline is exact
    assert split.interp_mae < 1e-5
    with pytest.raises(ValueError, match="data.holdout: expected keys among"):
        PingAltimeterDataModule(cfg, str(tmp_path), holdout={"fractoin": 0.2})
    with pytest.raises(ValueError, match=r"data.holdout.fraction: expected a number in \[0, 1\)"):
        holdout_config({"fraction": 1.5}, 0)
    with pytest.raises(ValueError, match="data.holdout.block_pings: expected a positive integer"):
        holdout_config({"fraction": 0.2, "block_pings": 2.5}, 0)


# ------------------------------------------------------------------ K folds in metres
def _fold_lines(seed: int = 0) -> list[np.ndarray]:
    """Along-track distances of three lines with uneven ping spacing (and standstills)."""
    rng = np.random.default_rng(seed)
    lines = []
    for n in (400, 250, 120):
        step = rng.choice([0.0, 0.2, 0.25, 0.4], n - 1)
        lines.append(np.concatenate([[0.0], np.cumsum(step)]))
    return lines


@pytest.mark.parametrize("folds", [2, 5])
def test_every_eligible_block_is_held_out_in_exactly_one_fold(folds):
    distances = _fold_lines()
    block_m = 6.0
    assignment = fold_blocks(distances, block_m, folds, seed=11)
    eligible = 0
    for s, fold in zip(distances, assignment, strict=True):
        blocks = along_track_blocks(s, block_m)
        assert fold.shape == s.shape and set(np.unique(fold)) <= {-1, *range(folds)}
        for b in np.unique(blocks):
            f = np.unique(fold[blocks == b])
            assert f.size == 1  # a block is held out whole, in one fold
            if b * block_m < block_m or (b + 1) * block_m > s[-1] - block_m:
                assert f[0] == -1  # a whole block at either end of a line is always kept
            else:
                assert f[0] >= 0
                eligible += 1
                span = s[blocks == b]
                assert span.max() - span.min() <= block_m  # the length in metres
    per_fold = [sum(int(len(np.unique(along_track_blocks(s, block_m)[f == k])))
                    for s, f in zip(distances, assignment, strict=True)) for k in range(folds)]  # fmt: skip
    assert sum(per_fold) == eligible and max(per_fold) - min(per_fold) <= 1  # dealt evenly
    again = fold_blocks(distances, block_m, folds, seed=11)
    assert all(np.array_equal(a, b) for a, b in zip(assignment, again, strict=True))


def test_fold_blocks_skip_blocks_without_altimeter_and_refuse_too_few():
    s = np.arange(100) * 0.5  # 49.5 m: blocks of 5 m, 10 blocks
    valid = np.ones(100, bool)
    valid[:20] = False  # blocks 0-1 without altimeter: block 2 is the line's first kept
    fold = fold_blocks([s], 5.0, 2, seed=0, valid=[valid])[0]
    blocks = along_track_blocks(s, 5.0)
    # kept: up to 5 m past the first altimeter point (10 m) and from 5 m before the last
    # (49.5 m): block 8 ends at 45 m > 44.5 m
    assert (fold[blocks <= 2] == -1).all() and (fold[blocks >= 8] == -1).all()
    assert (fold[(blocks > 2) & (blocks < 8)] >= 0).all()
    with pytest.raises(ValueError, match=r"data.holdout.block_m: expected blocks short enough"):
        fold_blocks([s], 20.0, 5, seed=0)
    with pytest.raises(ValueError, match=r"verdict.folds: expected an integer >= 2"):
        fold_blocks([s], 5.0, 1, seed=0)
    with pytest.raises(ValueError, match=r"holdout.block_m: expected a positive length"):
        along_track_blocks(s, 0.0)


def test_default_block_is_twice_the_swath_unless_the_survey_is_short():
    assert default_block_m([2000.0, 1500.0], swath_width_m=60.0, folds=5) == 120.0
    short = default_block_m([55.7], swath_width_m=59.0, folds=5)
    assert short == pytest.approx(55.7 / 8)
    s = np.linspace(0.0, 55.7, 460)
    fold_blocks([s], short, 5, seed=0)  # the default length always gives every fold a block


def test_fold_splits_partition_the_eligible_points_and_interpolate_them():
    rng = np.random.default_rng(2)
    positions, altitudes = [], []
    for n in (300, 200):
        xy = np.stack([np.arange(n) * 0.3, rng.normal(0, 0.01, n)], 1)
        positions.append(np.concatenate([xy, np.full((n, 1), -5.0)], 1))
        alt = 3.0 + 0.01 * np.arange(n)  # a uniform slope: interpolation is exact
        alt[rng.random(n) < 0.05] = np.nan
        altitudes.append(alt)
    folds = 4
    splits = [
        split_altimeter_fold(positions, altitudes, folds, k, 6.0, seed=5) for k in range(folds)
    ]
    held = [
        (int(line), int(p))
        for sp in splits
        for line, p in zip(sp.held_line, sp.held_ping, strict=True)
    ]
    assert len(held) == len(set(held))  # no point held out twice
    n_valid = sum(int(np.isfinite(a).sum()) for a in altitudes)
    for sp in splits:
        assert sp.n_held > 0 and sp.n_held + sp.fit.shape[0] == n_valid
        assert sp.block_m == 6.0 and sp.folds == folds and sp.n_blocks >= 1
        assert sp.block_pings == pytest.approx(20.0, abs=1.0)  # 6 m of 0.3 m steps
        assert np.isfinite(sp.interp).all() and sp.interp_mae < 1e-3
    with pytest.raises(ValueError, match=r"data.holdout.fold: expected an integer in \[0, 4\)"):
        split_altimeter_fold(positions, altitudes, folds, 4, 6.0, seed=5)
    # block_m=None: the default length from the swath width
    auto = split_altimeter_fold(positions, altitudes, 3, 0, None, seed=5, swath_width_m=4.0)
    assert auto.block_m == pytest.approx(8.0)


def test_holdout_config_takes_the_k_fold_keys():
    cfg = holdout_config({"folds": 5, "fold": 4, "block_m": 7.5}, 3)
    assert cfg["folds"] == 5 and cfg["fold"] == 4 and cfg["block_m"] == 7.5 and cfg["seed"] == 3
    with pytest.raises(ValueError, match=r"data.holdout.folds: expected 0 \(off\)"):
        holdout_config({"folds": 1}, 0)
    with pytest.raises(ValueError, match=r"data.holdout.fold: expected an integer in \[0, 5\)"):
        holdout_config({"folds": 5, "fold": 5}, 0)
    with pytest.raises(ValueError, match=r"data.holdout.block_m"):
        holdout_config({"folds": 5, "block_m": -1.0}, 0)
