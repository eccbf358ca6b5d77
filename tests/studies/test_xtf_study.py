"""The XTF study: overlap, repair errors, dropout, table; one tiny end-to-end run (slow)."""

from __future__ import annotations

import csv
import io
import json
import math

import numpy as np
import pytest

from sss2bathy.survey.model import (
    ALTITUDE_DETECTED,
    ALTITUDE_INTERPOLATED,
    ALTITUDE_MISSING,
    ALTITUDE_RECORDED,
)
from studies.xtf_study import (
    StudySurvey,
    dropout_pings,
    failed_row,
    ground_half_width,
    map_command,
    repair_errors,
    run_study,
    study_row,
    summarise,
    swath_overlap,
    to_csv,
    to_markdown,
)


def _track(y: float, n: int = 401) -> np.ndarray:
    return np.stack([np.linspace(0.0, 100.0, n), np.full(n, y)], axis=1)


def test_swath_overlap_two_parallel_lines_matches_the_geometry():
    # strips y in [-10, 10] and [0, 20] with half-disc end caps (r = 10, centres 10 m apart)
    r, d = 10.0, 10.0
    lens = 2 * r * r * math.acos(d / (2 * r)) - d / 2 * math.sqrt(4 * r * r - d * d)
    cap_union = 2 * (math.pi * r * r / 2) - lens / 2
    union = 100 * 30 + 2 * cap_union
    both = 100 * 10 + 2 * (lens / 2)
    hw = np.full(401, r)
    out = swath_overlap([_track(0.0), _track(10.0)], [hw, hw], cell_m=0.25)
    assert out["covered_m2"] == pytest.approx(union, rel=0.01)
    assert out["overlap"] == pytest.approx(both / union, abs=0.005)
    assert out["overlap3"] == 0.0


def test_swath_overlap_disjoint_lines_and_nan_widths():
    hw = np.full(401, 5.0)
    out = swath_overlap([_track(0.0), _track(50.0)], [hw, hw], cell_m=0.5)
    assert out["overlap"] == 0.0
    # a line whose pings see nothing covers nothing
    none = swath_overlap([_track(0.0)], [np.full(401, np.nan)])
    assert none["covered_m2"] == 0.0 and math.isnan(none["overlap"])


def test_swath_overlap_refuses_mismatched_shapes():
    with pytest.raises(ValueError, match=r"half_widths\[0\]: expected shape \(401,\)"):
        swath_overlap([_track(0.0)], [np.ones(3)])
    with pytest.raises(ValueError, match="one array per track"):
        swath_overlap([_track(0.0)], [])


def test_ground_half_width():
    hw = ground_half_width(30.0, np.array([10.0, np.nan, 31.0, 0.0]))
    assert hw[0] == pytest.approx(math.sqrt(800.0))
    assert np.isnan(hw[1]) and np.isnan(hw[2])
    assert hw[3] == pytest.approx(30.0)


def test_repair_errors_counts_only_repaired_pings():
    truth = np.array([10.0, 10.0, 10.0, 10.0, 10.0])
    alt = np.array([12.0, 10.1, 9.7, np.nan, 10.0])
    src = np.array(
        [ALTITUDE_RECORDED, ALTITUDE_DETECTED, ALTITUDE_INTERPOLATED, ALTITUDE_MISSING,
         ALTITUDE_RECORDED]
    )  # fmt: skip
    out = repair_errors(alt, src, truth)
    assert out["n"] == 2 and out["detected"] == 1 and out["interpolated"] == 1
    assert out["missing"] == 1
    assert out["max"] == pytest.approx(0.3)
    assert out["median"] == pytest.approx(0.2)
    none = repair_errors(alt[:1], src[:1], truth[:1])
    assert none["n"] == 0 and math.isnan(none["max"])
    with pytest.raises(ValueError, match="equal 1-D shapes"):
        repair_errors(alt, src[:2], truth)


def test_dropout_pings_seeded_runs_inside_the_line():
    a = dropout_pings(100, 2, 3, seed=5)
    assert a.sum() == 6 and not a[:3].any() and not a[-3:].any()
    starts = np.flatnonzero(a & ~np.r_[False, a[:-1]])
    assert len(starts) == 2  # two separate runs
    assert np.array_equal(a, dropout_pings(100, 2, 3, seed=5))
    assert not dropout_pings(100, 0, 3, seed=5).any()
    with pytest.raises(ValueError, match="room for 5 runs of 10 pings"):
        dropout_pings(40, 5, 10, seed=0)


def _row(method, variant, seed, fit, interp):
    return {
        "method": method, "variant": variant, "seed": seed, "holdout_mae": fit,
        "interp_mae": interp, "ratio": fit / interp, "holdout_n": 200, "overlap": 0.57,
        "repair_n": 24, "repair_max_m": 0.14, "repair_median_m": 0.09, "wall_s": 47.0,
        "run": f"runs/s{seed}/{method}_{variant}",
    }  # fmt: skip


def test_table_summary_markdown_and_csv():
    rows = [
        _row("siren_lambert", "demo", 1, 0.3, 0.4),
        _row("siren_lambert", "demo", 2, 0.6, 0.4),
        _row("siren_lambert", "fast_best", 1, 0.2, 0.4),
    ]
    summary = summarise(rows)
    assert [(s["method"], s["variant"], s["seeds"]) for s in summary] == [
        ("siren_lambert", "demo", 2),
        ("siren_lambert", "fast_best", 1),
    ]
    assert summary[0]["ratio_mean"] == pytest.approx(1.125)
    assert summary[0]["ratio_max"] == pytest.approx(1.5)
    assert summary[0]["beats"] == 1
    md = to_markdown(rows)
    assert "| SIREN-Lambert | demo | 1 | 0.300 | 0.400 | 0.75 | 200 | 57 % | 24 | 0.140 |" in md
    assert "| SIREN-Lambert | fast_best* | 1 |" in md  # selected on the held-out points
    assert "| SIREN-Lambert | demo | 2 | 0.450 | 0.400 | 1.12 | 1.50 | 1/2 |" in md
    parsed = list(csv.DictReader(io.StringIO(to_csv(rows))))
    assert len(parsed) == 3 and float(parsed[1]["ratio"]) == pytest.approx(1.5)


def test_failed_run_is_a_row_saying_so():
    rows = [_row("siren_lambert", "fast", 1, 0.3, 0.4), failed_row("siren_cnn_n2d", "fast", 1, "x")]
    md = to_markdown(rows)
    assert "| SIREN-CNN-N2d | fast | 1 | - | - | - | - | - | 0 | - | - | failed |" in md
    assert "| SIREN-CNN-N2d | fast | 1 | - | - | - | - | 0/1 |" in md
    assert "FAILED: x" in to_csv(rows)


def test_study_row_reads_final_metrics(tmp_path):
    run = tmp_path / "run"
    run.mkdir()
    (run / "metrics.json").write_text(
        json.dumps(
            {
                "val/holdout_alt_mae_m": 9.0,
                "final/holdout_alt_mae": 0.25,
                "final/holdout_interp_mae": 0.5,
                "final/holdout_n": 120.0,
            }
        )  # fmt: skip
    )
    (run / "study_wall_s.txt").write_text("12.5\n")
    scores = {"overlap": {"overlap": 0.7}, "repair": {"n": 6, "max": 0.1, "median": 0.05}}
    row = study_row("siren_lambert", "fast", 3, run, scores)
    assert row["holdout_mae"] == 0.25 and row["ratio"] == pytest.approx(0.5)
    assert row["holdout_n"] == 120 and row["wall_s"] == 12.5 and row["repair_n"] == 6
    with pytest.raises(FileNotFoundError, match="metrics.json: expected a finished run"):
        study_row("siren_lambert", "fast", 3, tmp_path / "missing", scores)


def test_map_command_variants(tmp_path):
    survey = StudySurvey(tmp_path / "xtf", "xtf_study_demo_s1", "EPSG:32633")
    cmd = map_command(survey, "siren_lambert", "fast_best", 1, tmp_path / "r", tmp_path / "d")
    assert "siren_schedule=fast" in cmd and "torch_threads=1" in cmd
    over = [c for c in cmd if c.startswith("overrides=")][0]
    assert "'model.select_best=holdout_alt_mae'" in over
    assert "'model.eval_every_n_epochs=1'" in over
    demo = map_command(survey, "siren_lambert", "demo", 1, tmp_path / "r", tmp_path / "d")
    assert not any(c.startswith("siren_schedule=") for c in demo)
    # the study's tables are of the scale's SIREN settings unless the map args name others
    assert "map_settings=scale" in demo
    detail = map_command(survey, "siren_lambert", "demo", 1, tmp_path / "r", tmp_path / "d",
                         map_args=["map_settings=detail"])  # fmt: skip
    assert [c for c in detail if c.startswith("map_settings=")] == ["map_settings=detail"]
    ckpt = map_command(
        survey, "siren_cnn_n2d", "fast", 1, tmp_path / "r", tmp_path / "d", cnn_checkpoint="c"
    )
    assert "cnn_checkpoint=c" in ckpt
    with pytest.raises(ValueError, match="variant: expected one of"):
        map_command(survey, "siren_lambert", "slow", 1, tmp_path / "r", tmp_path / "d")


def test_run_study_refuses_cnn_without_checkpoint(tmp_path):
    with pytest.raises(ValueError, match="siren_cnn_n2d needs --cnn-checkpoint"):
        run_study(tmp_path, [0], ["siren_cnn_n2d"], ["demo"], scale="tiny")


@pytest.mark.slow
def test_tiny_study_end_to_end(tmp_path):
    rows = run_study(
        tmp_path, [0], ["siren_heights_only"], ["demo"], scale="tiny",
        map_args=["holdout.block_pings=10"],
    )  # fmt: skip
    assert len(rows) == 1
    row = rows[0]
    assert math.isfinite(row["holdout_mae"]) and math.isfinite(row["interp_mae"])
    assert row["holdout_n"] > 0
    assert 0.0 < row["overlap"] <= 1.0
    # 2 test lines x 2 runs x 3 pings had their altitude removed; the detector repairs them
    assert row["repair_n"] == 12
    assert row["repair_max_m"] < 1.0
    assert (tmp_path / "xtf_study.md").is_file() and (tmp_path / "xtf_study.csv").is_file()
    assert (tmp_path / "runs" / "s0" / "siren_heights_only_demo" / "map.tif").is_file()
