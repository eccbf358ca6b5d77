"""The overlap study's pure parts: a row from the verdict study's row and an overlap.json,
agreement counts (conclusive calls and signs) and the Markdown table."""

from __future__ import annotations

import math

import pytest

from sss2bathy.eval.overlap import OverlapFold, overlap_verdict
from sss2bathy.eval.verdict import HEIGHTS_ONLY, PLANE
from studies.overlap_study import agreement, overlap_row, to_markdown


def _nadir(seed: int, call: str, diff: float, truth: str) -> dict:
    """A verdict-study row (studies.xtf_study.verdict_row) with the keys the study reads."""
    return {
        "seed": seed,
        "vs_heights": call,
        "diff_heights_m": diff,
        "half_heights_m": 0.1,
        "map_mae_sidescan": 0.3 if truth == "better" else 0.6,
        "map_mae_heights": 0.5,
        "truth": truth,
    }


def _overlap(lam: list[float], heights: list[float]) -> dict:
    folds = [
        OverlapFold(f"line_{i}", 40, {"siren_lambert": a, HEIGHTS_ONLY: b, PLANE: 1.0}, 5.0)
        for i, (a, b) in enumerate(zip(lam, heights, strict=True))
    ]
    return overlap_verdict(folds, "siren_lambert").to_dict()


def test_a_row_sets_both_verdicts_against_the_truth():
    better = _overlap([0.20, 0.22, 0.25, 0.21], [0.40, 0.45, 0.50, 0.42])
    row = overlap_row(_nadir(1, "inconclusive", -0.04, "better"), better, "run", 12.0)
    assert row["overlap_call"] == "better" and row["overlap_agrees"] is True
    assert row["nadir_agrees"] is None and row["nadir_sign_agrees"] is True
    assert row["overlap_sign_agrees"] is True and row["overlap_vs_plane"] == "better"
    assert row["overlap_lines"] == 4 and row["overlap_points"] == 160
    assert row["overlap_mae_sidescan"] == pytest.approx(0.22)
    assert row["overlap_mae_plane"] == pytest.approx(1.0)
    # the same overlap call on a survey where the MBES says the sidescan map is worse
    wrong = overlap_row(_nadir(2, "worse", +0.05, "worse"), better)
    assert wrong["overlap_agrees"] is False and wrong["overlap_sign_agrees"] is False
    assert wrong["nadir_agrees"] is True and math.isnan(wrong["wall_s"])
    with pytest.raises(ValueError, match="expected an overlap score, found one line"):
        overlap_row(_nadir(3, "worse", 0.1, "worse"), {"computable": False, "reason": "one line"})


def test_agreement_counts_and_the_table():
    better = _overlap([0.20, 0.22, 0.25, 0.21], [0.40, 0.45, 0.50, 0.42])
    mixed = _overlap([0.20, 0.60, 0.25, 0.70], [0.40, 0.45, 0.50, 0.42])
    rows = [
        overlap_row(_nadir(1, "inconclusive", -0.04, "better"), better),
        overlap_row(_nadir(2, "inconclusive", +0.02, "better"), mixed),
    ]
    assert rows[1]["overlap_call"] == "inconclusive"
    assert agreement(rows, "overlap_agrees") == (1, 1)
    assert agreement(rows, "nadir_agrees") == (0, 0)
    assert agreement(rows, "nadir_sign_agrees") == (1, 2)
    text = to_markdown(rows, "python -m studies.overlap_study --scale tiny")
    assert "    python -m studies.overlap_study --scale tiny" in text
    assert "overlap score (conclusive calls) 1 of 1" in text and "nadir sign 1 of 2" in text
    table = [ln for ln in text.splitlines() if ln.startswith("| ")]
    assert len(table) == 3 and table[1].split(" | ")[3] == "better"
