"""Schedule study: goal from the reference's final MAE, first time each run reaches it."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from sss2bathy.eval.metric_curve import write_curve
from studies.schedule_study import load_run_curve, main, study, time_to_reach


def _run(tmp_path, name, maes, dt):
    rows = [
        {
            "epoch": i,
            "step": 10 * (i + 1),
            "wall_s": dt * (i + 1) + 0.5,
            "train_s": dt * (i + 1),
            "lr": 1e-3,
            "val/map_mae_m": m,
        }
        for i, m in enumerate(maes)
    ]
    d = tmp_path / name
    d.mkdir()
    write_curve(d / "metric_curve.csv", rows)
    return d


def test_time_to_reach_first_crossing_and_never():
    curve = {"train_s": np.array([1.0, 2.0, 3.0]), "val/map_mae_m": np.array([0.5, 0.3, 0.2])}
    assert time_to_reach(curve, 0.3) == 2.0
    assert time_to_reach(curve, 0.6) == 1.0
    assert math.isnan(time_to_reach(curve, 0.1))


def test_study_compares_against_the_reference_final(tmp_path):
    ref = _run(tmp_path, "paper", [0.6, 0.5, 0.45, 0.40], dt=100.0)
    fast = _run(tmp_path, "fast", [0.5, 0.41, 0.39, 0.38], dt=5.0)
    slow = _run(tmp_path, "slow", [0.7, 0.6], dt=5.0)
    res = study({"paper": ref, "fast": fast, "slow": slow}, "paper", reference_epochs=4)
    assert res["goal"] == pytest.approx(0.40)
    assert res["reference_complete"]
    assert res["runs"]["fast"]["time_to_goal_s"] == pytest.approx(15.0)
    assert res["runs"]["fast"]["fraction_of_reference_time"] == pytest.approx(15.0 / 400.0)
    assert math.isnan(res["runs"]["slow"]["time_to_goal_s"])
    assert res["runs"]["fast"]["time_to_best_goal_s"] == pytest.approx(15.0)
    assert res["runs"]["paper"]["fraction_of_reference_time"] == pytest.approx(1.0)
    stopped = study({"paper": ref, "fast": fast}, "paper", reference_epochs=1500)
    assert not stopped["reference_complete"]
    with pytest.raises(ValueError, match="reference: expected one of"):
        study({"fast": fast}, "paper")


def test_cli_writes_md_json_png(tmp_path, capsys):
    ref = _run(tmp_path, "paper", [0.6, 0.4], dt=100.0)
    fast = _run(tmp_path, "fast", [0.39], dt=5.0)
    out = tmp_path / "out"
    assert (
        main(
            [
                "--run",
                f"paper={ref}",
                "--run",
                f"fast={fast}",
                "--reference",
                "paper",
                "--out",
                str(out),
            ]
        )
        == 0
    )
    doc = json.loads((out / "schedule_study.json").read_text())
    assert doc["runs"]["fast"]["time_to_goal_s"] == pytest.approx(5.0)
    assert (out / "schedule_study.png").read_bytes()[:4] == b"\x89PNG"
    assert "| fast | 1 | 0.3900" in (out / "schedule_study.md").read_text()


def test_missing_run_is_named(tmp_path):
    with pytest.raises(FileNotFoundError, match="metric_curve.csv or tensorboard"):
        load_run_curve(tmp_path)
