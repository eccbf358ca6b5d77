"""The verdict study of ``studies.xtf_study``: the verdict's calls, the MBES's call,
their agreement and table, and resampling a map onto the MBES grid."""

from __future__ import annotations

import csv
import io
import math

import numpy as np
import pytest

from sss2bathy.survey.grid import BathyGrid
from studies.xtf_study import (
    StudySurvey,
    map_command,
    map_on_grid,
    mask_on_grid,
    run_verdict_study,
    truth_call,
    truth_grid,
    verdict_agreement,
    verdict_call,
    verdict_row,
    verdict_to_csv,
    verdict_to_markdown,
)


def _verdict(heights_winner, interp_winner, outcome="inconclusive"):
    def comp(b, winner, diff):
        return {"a": "siren_lambert", "b": b, "n": 5, "mean_diff": diff, "se": 0.01,
                "half_width_95": 0.03, "winner": winner}  # fmt: skip

    return {
        "subject": "siren_lambert",
        "folds": 5,
        "block_m": 12.0,
        "outcome": outcome,
        "comparisons": [
            comp("siren_heights_only", heights_winner, -0.05),
            comp("interpolation", interp_winner, 0.08),
        ],
    }


def _scores(side, heights):
    return {
        "sidescan": {"mae": side, "region_mae": side + 0.1, "bias": 0.01, "n_cells": 900},
        "heights": {"mae": heights, "region_mae": heights + 0.1, "bias": -0.02, "n_cells": 900},
    }


def test_verdict_call_reads_each_comparison():
    v = _verdict("siren_lambert", "interpolation", "did not help")
    assert verdict_call(v, "siren_heights_only") == {"call": "better", "diff": -0.05, "half": 0.03}
    assert verdict_call(v, "interpolation")["call"] == "worse"
    assert verdict_call(_verdict(None, None), "siren_heights_only")["call"] == "inconclusive"
    with pytest.raises(ValueError, match="expected a comparison of 'siren_lambert' with 'x'"):
        verdict_call(v, "x")


def test_truth_call():
    assert truth_call(0.2, 0.3) == "better"
    assert truth_call(0.3, 0.2) == "worse"
    assert truth_call(0.3, 0.3) == "worse"  # a tie is no help
    assert truth_call(math.nan, 0.2) == "unknown"


def test_agreement_counts_only_conclusive_calls_and_the_table_says_so():
    rows = [
        verdict_row(1, _verdict("siren_lambert", None), _scores(0.2, 0.3)),  # agrees
        verdict_row(2, _verdict("siren_heights_only", None), _scores(0.2, 0.3)),  # disagrees
        verdict_row(3, _verdict(None, "interpolation"), _scores(0.4, 0.3)),  # inconclusive
        verdict_row(4, _verdict("siren_heights_only", None), _scores(0.5, 0.3)),  # agrees
    ]
    assert [r["agrees"] for r in rows] == [True, False, None, True]
    assert [r["truth"] for r in rows] == ["better", "better", "worse", "worse"]
    assert rows[2]["vs_interp"] == "worse" and rows[0]["vs_interp"] == "inconclusive"
    assert verdict_agreement(rows) == {"n": 4, "conclusive": 3, "agree": 2, "inconclusive": 1}
    md = verdict_to_markdown(rows)
    assert "2 of 3 conclusive cases agree" in md and "(1 of 4 inconclusive)" in md
    assert "| 2 | worse | -0.050 +- 0.030 | inconclusive |" in md and "| NO |" in md
    parsed = list(csv.DictReader(io.StringIO(verdict_to_csv(rows))))
    assert len(parsed) == 4 and parsed[0]["map_mae_sidescan"] == "0.2"
    assert parsed[2]["agrees"] == "" and parsed[3]["region_mae_heights"] == "0.4"


def test_map_on_grid_samples_a_plane_across_frames():
    # a plane z = 2x + y on a 1 m map; the MBES grid (0.5 m cells) is in a frame shifted by
    # (+3, -2) m from the map's: its point p is p + (3, -2) in the map's frame
    xs, ys = np.arange(0.0, 20.0), np.arange(0.0, 15.0)
    xx, yy = np.meshgrid(xs, ys)
    like = BathyGrid(np.zeros((8, 10), np.float32), 1.0, 4.0, 0.5)
    out = map_on_grid(2 * xx + yy, 0.0, 0.0, 1.0, like, (3.0, -2.0))
    lx, ly = np.meshgrid(like.x + 3.0, like.y - 2.0)
    assert out.shape == like.shape and (out.x0, out.cell_size) == (1.0, 0.5)
    np.testing.assert_allclose(out.heights, 2 * lx + ly, atol=1e-4)
    far = map_on_grid(2 * xx + yy, 0.0, 0.0, 1.0, like, (100.0, 0.0))
    assert np.isnan(far.heights).all()
    mask = np.zeros((15, 20), bool)
    mask[:, :6] = True  # map cells x <= 5 (edges at 5.5)
    got = mask_on_grid(mask, 0.0, 0.0, 1.0, like, (3.0, -2.0))
    np.testing.assert_array_equal(got, np.broadcast_to(lx < 5.5, like.shape))
    assert not mask_on_grid(mask, 0.0, 0.0, 1.0, like, (0.0, 100.0)).any()


def test_map_command_verdict_folds(tmp_path):
    survey = StudySurvey(tmp_path / "xtf", "xtf_study_tiny_s1", "EPSG:32633")
    args = (survey, "siren_lambert", "demo", 1, tmp_path / "r", tmp_path / "d")
    assert "verdict.folds=0" in map_command(*args)
    assert "verdict.folds=5" in map_command(*args, verdict_folds=5)


def test_truth_grid_needs_the_mbes_and_folds(tmp_path):
    survey = StudySurvey(tmp_path, "s", "EPSG:32633")
    np.savez(survey.truth_path, **{"line_001/altitude": np.zeros(3)})
    with pytest.raises(ValueError, match="truth.npz: expected the MBES grid"):
        truth_grid(survey)
    np.savez(
        survey.truth_path,
        **{"mbes/heights": np.ones((3, 4)), "mbes/geometry": np.array([1.0, 2.0, 0.5, 7.0, 8.0])},
    )
    grid, origin = truth_grid(survey)
    assert grid.shape == (3, 4) and (grid.x0, grid.y0, grid.cell_size) == (1.0, 2.0, 0.5)
    assert origin == (7.0, 8.0) and grid.crs == "EPSG:32633"
    with pytest.raises(ValueError, match="--verdict-folds: expected 2 or more folds, found 1"):
        run_verdict_study(tmp_path, [1], folds=1)
