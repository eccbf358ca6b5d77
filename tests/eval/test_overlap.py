"""The off-track overlap score: overlap points, the plane baseline, the pre-fit overlap
count, per-fold scores and the verdict over held-out lines (sss2bathy.eval.overlap), and its
config and summary in sss2bathy-map."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
from omegaconf import OmegaConf

from sss2bathy.eval.overlap import (
    HELD_OUT_LINES,
    PLANE,
    OverlapFold,
    offtrack_counts,
    overlap_mask,
    overlap_unavailable,
    overlap_verdict,
    plane_heights,
    score_overlap_fold,
    unscored_reason,
)
from sss2bathy.eval.verdict import HEIGHTS_ONLY
from sss2bathy.survey import BathyGrid
from sss2bathy.survey.model import SidescanLine

CONF = Path(__file__).resolve().parents[2] / "conf"
EAST = np.eye(3)  # heading east: the vehicle's port axis (y) points north
NORTH = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])  # port points west


def _line(name: str, start, step, rotation, n: int = 80, altitude: float = 5.0) -> SidescanLine:
    """A straight line of ``n`` pings from ``start`` by ``step`` (m), 20 m range, flat
    seabed ``altitude`` below."""
    start, step = np.asarray(start, float), np.asarray(step, float)
    pos = start[None, :] + np.arange(n)[:, None] * step[None, :]
    rng = np.linspace(0.5, 20.0, 40)
    return SidescanLine(
        name=name,
        time_s=np.arange(n, dtype=float),
        position=np.c_[pos, np.zeros(n)],
        rotation=np.repeat(rotation[None], n, 0),
        altitude_m=np.full(n, altitude),
        intensity=np.ones((n, 2, rng.size)),
        range_m=rng,
    )


def _grid(fill: float = 0.0, cell: float = 0.5) -> BathyGrid:
    return BathyGrid(np.full((81, 81), fill, np.float32), 0.0, 0.0, cell)


def test_plane_recovers_a_plane_and_stays_level_across_a_single_line():
    rng = np.random.default_rng(0)
    xy = rng.uniform(0, 40, (300, 2))
    z = -10.0 + 0.05 * xy[:, 0] - 0.02 * xy[:, 1]
    at = np.array([[5.0, 35.0], [30.0, 2.0]])
    assert plane_heights(np.c_[xy, z], at) == pytest.approx(-10 + 0.05 * at[:, 0] - 0.02 * at[:, 1])
    # one straight line with 0.3 m of wobble: the across-track slope is not determined,
    # so 20 m off the track the plane is the line's own profile (no blow-up)
    x = np.linspace(0, 100, 200)
    wobble = 0.3 * rng.standard_normal(200)
    line = np.c_[x, 5 + wobble, -10 + 0.05 * x + 0.2 * wobble]
    off = plane_heights(line, np.array([[50.0, 25.0], [50.0, -15.0]]))
    assert off == pytest.approx([-7.5, -7.5], abs=0.05)
    with pytest.raises(ValueError, match="fitted_xyz: expected at least one"):
        plane_heights(np.zeros((0, 3)), at)


def test_overlap_points_are_imaged_and_off_the_fitted_tracks():
    grid = _grid()
    imaged = np.zeros(grid.shape, bool)
    imaged[:, 20:] = True  # x >= 10 m imaged
    fitted = np.array([[20.0, 5.0, -5.0]])  # a fitted altimeter point in an imaged cell
    held = np.array(
        [
            [5.0, 5.0, -5.0],  # not imaged
            [15.0, 5.0, -5.0],  # imaged, off-track: an overlap point
            [20.1, 5.1, -5.0],  # in the fitted point's cell: on its track
            [99.0, 5.0, -5.0],  # outside the grid
            [15.0, 6.0, np.nan],  # no height
        ]
    )
    assert overlap_mask(grid, imaged, fitted, held).tolist() == [False, True, False, False, False]
    with pytest.raises(ValueError, match="imaged: expected the grid's shape"):
        overlap_mask(grid, imaged[1:], fitted, held)


def test_offtrack_counts_see_crossing_lines_not_distant_or_single_ones():
    east = _line("east", (0.0, 20.0), (0.5, 0.0), EAST)  # y = 20, x 0 .. 40
    north = _line("north", (20.0, 0.0), (0.0, 0.5), NORTH)  # x = 20, y 0 .. 40
    counts = offtrack_counts([east, north], 0.5)
    # each track crosses the other's swath: ground from sqrt(5.5^2 - 5^2) = 2.3 m (the first
    # bin beyond the altitude) to sqrt(20^2 - 5^2) = 19.4 m on both sides: 2 x 17.1 m of
    # track, 0.5 m per ping (~68 points)
    assert counts.shape == (2,) and all(66 <= c <= 72 for c in counts), counts
    far = _line("far", (0.0, 80.0), (0.5, 0.0), EAST)  # 60 m away: beyond the 19.4 m reach
    assert offtrack_counts([east, far], 0.5).tolist() == [0, 0]
    assert offtrack_counts([east], 0.5).tolist() == [0]
    # a parallel neighbour 10 m away: its whole track lies in the other's swath
    near = _line("near", (0.0, 30.0), (0.5, 0.0), EAST)
    assert offtrack_counts([east, near], 0.5).tolist() == [80, 80]


def test_a_fold_scores_the_maps_at_the_overlap_points_only():
    grid = _grid()  # true seabed: z = -5 + 0.1 x (a slope across the fitted line)
    true = BathyGrid(-5.0 + 0.1 * np.repeat(grid.x[None], grid.shape[0], 0), 0.0, 0.0, 0.5)
    biased = BathyGrid(true.heights + 0.3, 0.0, 0.0, 0.5)
    imaged = np.zeros(grid.shape, bool)
    imaged[:, :] = True
    # fitted along x = 10 (a north-going line), held out along y = 20 (crossing it)
    fy = np.linspace(0, 40, 81)
    fitted = np.c_[np.full(81, 10.0), fy, np.full(81, -4.0)]
    hx = np.linspace(0, 40, 81)
    held = np.c_[hx, np.full(81, 20.0), -5.0 + 0.1 * hx]
    fold = score_overlap_fold(
        "h", held, fitted, imaged, {"sidescan": true, "heights": biased}, grid
    )
    assert fold.n_points == 80  # the held-out point in the fitted line's cell is on its track
    assert fold.mae["sidescan"] == pytest.approx(0.0, abs=1e-5)
    assert fold.mae["heights"] == pytest.approx(0.3, abs=1e-5)
    # the plane through one line is level across it: |0.1 (x - 10)| on average
    on = ~np.isclose(hx, 10.0)
    assert fold.mae[PLANE] == pytest.approx(np.mean(np.abs(0.1 * (hx[on] - 10))), abs=1e-3)
    assert fold.offtrack_m == pytest.approx(np.median(np.abs(hx[on] - 10)), abs=0.3)
    # too few overlap points: every score NaN, the fold counts none
    few = score_overlap_fold("h", held, fitted, imaged, {"sidescan": true}, grid, min_points=81)
    assert few.n_points == 80 and math.isnan(few.mae["sidescan"]) and math.isnan(few.offtrack_m)
    assert "most: 80 of line h" in unscored_reason([few], 81)
    assert unscored_reason([fold], 10) is None


def _fold(line: str, lam: float, heights: float, plane: float, n: int = 50) -> OverlapFold:
    return OverlapFold(line, n, {"siren_lambert": lam, HEIGHTS_ONLY: heights, PLANE: plane}, 4.0)


def test_the_overlap_verdict_names_what_was_held_out():
    folds = [
        _fold("a", 0.20, 0.50, 0.90),
        _fold("b", 0.31, 0.60, 1.10),
        _fold("c", 0.25, 0.52, 0.80),
        _fold("d", 0.28, 0.58, 1.00),
    ]
    result = overlap_verdict(folds, "siren_lambert", seconds=12.0)
    assert result.verdict.outcome == "helped"
    assert HELD_OUT_LINES in result.verdict.sentence()
    assert result.n_points == 200
    assert result.pooled_mae()["siren_lambert"] == pytest.approx(0.26)
    data = result.to_dict()
    assert data["computable"] and data["held_out"] == HELD_OUT_LINES
    assert [ln["line"] for ln in data["lines"]] == ["a", "b", "c", "d"]
    metrics = result.metrics("verdict/overlap/")
    assert metrics["verdict/overlap/siren_lambert/mae_mean"] == pytest.approx(0.26)
    assert metrics["verdict/overlap/n_points"] == 200.0
    assert any("held-out lines: a (50 points, 4.0 m off-track)" in row for row in result.lines())
    # heights-only better on every line: the sidescan did not help off-track
    worse = overlap_verdict(
        [_fold(f.line, f.mae[HEIGHTS_ONLY] + 0.1, f.mae[HEIGHTS_ONLY], 2.0) for f in folds],
        "siren_lambert",
    )
    assert worse.verdict.outcome == "did not help"
    with pytest.raises(ValueError, match="subject: expected one of the scored methods"):
        overlap_verdict(folds, "siren_cnn_n2d")
    with pytest.raises(ValueError, match="folds: expected at least one held-out line"):
        overlap_verdict([], "siren_lambert")


def test_why_there_is_no_overlap_score():
    one = overlap_unavailable(["line"], [0], 10)
    assert one.startswith("not computable: the survey has one line") and "nadir gap" in one
    apart = overlap_unavailable(["a", "b"], [3, 0], 10)
    assert "min_points" in apart and "most: 3 of line a" in apart
    assert overlap_unavailable(["a", "b"], [12, 0], 10) is None
    with pytest.raises(ValueError, match="counts: expected one per line"):
        overlap_unavailable(["a", "b"], [1], 10)


def test_map_config_checks_the_overlap_block_and_prints_the_score():
    from sss2bathy.cli.map import MapResult, check_map_config, overlap_settings

    cfg = OmegaConf.load(CONF / "map.yaml")
    # on with the K-fold verdict (the default), off with one held-out draw unless asked for
    assert overlap_settings(cfg) == {"enabled": True, "min_points": 10}
    cfg.verdict.folds = 0
    assert overlap_settings(cfg)["enabled"] is False
    cfg.verdict.overlap.enabled = True
    assert overlap_settings(cfg)["enabled"] is True
    for key, bad, expected in (
        ("enabled", "yes", "verdict.overlap.enabled: expected true, false or null"),
        ("min_points", 0, "verdict.overlap.min_points: expected a count >= 1"),
    ):
        broken = cfg.copy()
        broken.verdict.overlap[key] = bad
        with pytest.raises(ValueError, match=expected):
            check_map_config(broken)
    result = overlap_verdict(
        [_fold("a", 0.2, 0.5, 0.9), _fold("b", 0.3, 0.6, 1.0)], "siren_lambert"
    )
    printed = MapResult(Path("."), "siren_lambert", "s", {}, False, overlap=result).summary()
    assert any(line.startswith("  OVERLAP VERDICT:") for line in printed)
    assert any("off-track overlap score (each fold: one line held out" in ln for ln in printed)
    note = overlap_unavailable(["line"], [0], 10)
    printed = MapResult(Path("."), "siren_lambert", "s", {}, False, overlap_note=note).summary()
    assert f"  off-track overlap score: {note}" in printed


# ------------------------------------------------------------------ end to end (slow)
@pytest.mark.slow
def test_sss2bathy_map_scores_overlapping_lines_and_says_why_not_for_one(tmp_path):
    """Two crossing tiny lines: each held out in turn (2 x 2 fits), overlap.json, metrics
    and the printed verdict; one of them alone: one line saying the score is not computable."""
    import json
    import os
    import subprocess
    import sys

    from sss2bathy.io.xtf import write_xtf
    from sss2bathy.sim import config as sim_config
    from sss2bathy.sim import generate
    from sss2bathy.utils.config import survey_preset

    cfg = OmegaConf.create(survey_preset("synthetic_d1", "tiny", CONF))
    cfg.name = "sim_tiny"
    survey, _ = generate.generate_survey(
        sim_config.SyntheticSurveyConfig.from_mapping(OmegaConf.to_container(cfg))
    )
    folder = tmp_path / "lines"
    lines = survey.split_lines("test")
    assert len(lines) == 2
    for line in lines:
        write_xtf(line, folder / f"{line.name}.xtf", survey.origin)
    env = dict(os.environ, OMP_NUM_THREADS="1", HYDRA_FULL_ERROR="1")

    def run(files: Path, run_dir: Path) -> subprocess.CompletedProcess:
        args = [
            f"files={files}", f"survey.crs={survey.origin['crs']}", "survey.n_bins=null",
            "verdict.folds=0", "holdout.fraction=0", "verdict.overlap.enabled=true",
            "verdict.overlap.min_points=3", "mosaic.placement=none", "scale=tiny",
            "logger=none", "torch_threads=1", f"paths.data_dir={tmp_path / 'data'}",
            f"paths.output_dir={tmp_path / 'outputs'}", f"hydra.run.dir={run_dir}",
            'overrides=["callbacks=none","trainer.enable_progress_bar=false"]',
        ]  # fmt: skip
        return subprocess.run(
            [sys.executable, "-m", "sss2bathy.cli.map", *args],
            cwd=tmp_path, env=env, capture_output=True, text=True, timeout=900,
        )  # fmt: skip

    proc = run(folder, tmp_path / "both")
    assert proc.returncode == 0, proc.stderr[-3000:]
    scored = json.loads((tmp_path / "both" / "overlap.json").read_text())
    assert scored["computable"] and scored["held_out"] == HELD_OUT_LINES
    assert {ln["line"] for ln in scored["lines"]} == {ln.name for ln in lines}
    assert set(scored["methods"]) == {"siren_lambert", HEIGHTS_ONLY, PLANE}
    assert scored["n_points"] >= 3 and scored["outcome"] in (
        "helped",
        "did not help",
        "inconclusive",
    )
    metrics = json.loads((tmp_path / "both" / "metrics.json").read_text())
    assert metrics["verdict/overlap/siren_lambert/mae_mean"] == pytest.approx(
        scored["methods"]["siren_lambert"]["mean"]
    )
    assert "OVERLAP VERDICT:" in proc.stdout and "held-out lines: line_" in proc.stdout
    one = tmp_path / "one"
    proc = run(folder / f"{lines[0].name}.xtf", one)
    assert proc.returncode == 0, proc.stderr[-3000:]
    note = json.loads((one / "overlap.json").read_text())
    assert note["computable"] is False and "one line" in note["reason"]
    assert "off-track overlap score: not computable: the survey has one line" in proc.stdout
    assert not (one / "overlap").exists()  # no fit was made for it
