"""The K-fold verdict: paired per-fold differences, "inconclusive" when their 95 % interval
contains 0, the winner named otherwise."""

from __future__ import annotations

import math

import numpy as np
import pytest

from sss2bathy.eval.verdict import (
    HEIGHTS_ONLY,
    INTERPOLATION,
    MethodScores,
    kfold_verdict,
    paired_comparison,
)


def _folds(seed: int, k: int = 5) -> np.ndarray:
    """Per-fold MAEs that differ a lot between folds (rough and smooth seabed)."""
    return np.random.default_rng(seed).uniform(0.05, 0.6, k)


def test_heights_only_equal_to_interpolation_is_inconclusive():
    base = _folds(0)
    noise = np.array([0.01, -0.012, 0.008, -0.009, 0.002])  # no systematic difference
    scores = {HEIGHTS_ONLY: base + noise, INTERPOLATION: base}
    verdict = kfold_verdict(scores, HEIGHTS_ONLY)
    (comparison,) = verdict.comparisons
    assert comparison.inconclusive and comparison.winner is None
    assert abs(comparison.mean_diff) < comparison.half_width
    assert verdict.outcome == "inconclusive" and "inconclusive" in verdict.sentence()
    # exactly equal scores: a tie, not a win
    tie = kfold_verdict({HEIGHTS_ONLY: base, INTERPOLATION: base}, HEIGHTS_ONLY)
    assert tie.outcome == "inconclusive" and tie.comparisons[0].mean_diff == 0.0


def test_a_method_clearly_better_in_every_fold_is_named():
    base = _folds(1)
    better = base - np.array([0.05, 0.06, 0.04, 0.055, 0.05])  # better in every fold
    scores = {"siren_lambert": better, HEIGHTS_ONLY: base, INTERPOLATION: base + 0.1}
    verdict = kfold_verdict(scores, "siren_lambert", block_m=7.0, block_pings=57.0)
    assert [c.winner for c in verdict.comparisons] == ["siren_lambert", "siren_lambert"]
    assert verdict.outcome == "helped" and verdict.best == "siren_lambert"
    assert "the sidescan helped" in verdict.sentence()
    # the same numbers with the roles swapped: the baseline wins, the sidescan did not help
    worse = kfold_verdict(
        {"siren_lambert": base + 0.05, HEIGHTS_ONLY: base, INTERPOLATION: base + 0.2},
        "siren_lambert",
    )
    assert worse.comparisons[0].winner == HEIGHTS_ONLY
    assert worse.outcome == "did not help"
    assert "heights only" in worse.sentence() and "did NOT help" in worse.sentence()
    mixed = kfold_verdict(
        {"siren_lambert": base, HEIGHTS_ONLY: base + 0.1, INTERPOLATION: base - 0.05},
        "siren_lambert",
    )
    assert mixed.outcome == "did not help"
    assert mixed.sentence().endswith(
        "did NOT help (though it beats heights only (SIREN, no sidescan))."
    )


def test_the_spread_between_folds_does_not_hide_a_paired_difference():
    """Fold MAEs spread from 0.05 to 0.6 m; a constant 0.03 m difference still wins, since
    the comparison pairs the folds."""
    base = _folds(2)
    a = MethodScores("a", tuple(base - 0.03 + np.array([0.002, -0.001, 0.0, 0.001, -0.002])))
    b = MethodScores("b", tuple(base))
    assert a.std > 0.1  # the spreads overlap by far
    c = paired_comparison(a, b)
    assert c.winner == "a" and c.mean_diff == pytest.approx(-0.03)
    # t(0.975, 4) = 2.776 standard errors
    assert c.half_width == pytest.approx(2.776 * c.se, rel=1e-3)


def test_table_and_records_carry_every_method_and_fold():
    scores = {"siren_lambert": [0.2, 0.1, math.nan, 0.3], HEIGHTS_ONLY: [0.25, 0.1, 0.2, 0.4]}
    verdict = kfold_verdict(scores, "siren_lambert", 7.0, 57.0, seconds=12.0)
    assert verdict.folds == 4 and verdict.scores[0].n == 3  # a NaN fold is left out
    assert verdict.comparisons[0].n == 3
    rows = verdict.table()
    assert len(rows) == 3 and "mean +- std" in rows[0] and rows[1].endswith("3")
    record = verdict.to_dict()
    assert record["methods"][HEIGHTS_ONLY]["mae_per_fold"] == [0.25, 0.1, 0.2, 0.4]
    flat = verdict.metrics()
    assert flat["verdict/folds"] == 4.0 and flat["verdict/block_m"] == 7.0
    assert flat["verdict/siren_heights_only/mae_mean"] == pytest.approx(0.2375)
    with pytest.raises(ValueError, match="subject: expected one of the scored methods"):
        kfold_verdict(scores, "siren_cnn_n2d")
    with pytest.raises(ValueError, match="the same number of folds"):
        kfold_verdict({"a": [0.1, 0.2], "b": [0.1]}, "a")
