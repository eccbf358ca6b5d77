"""Paper-scale CPU study (studies.paper_cpu_study): table, commands, a tiny run."""

from __future__ import annotations

import csv
import io
import math

import numpy as np
import pytest

from studies.paper_cpu_study import (
    DEFAULT_METHODS,
    DEFAULT_SCHEDULES,
    check_preset,
    fit_command,
    mae_at,
    main,
    parse_reference,
    prepare_commands,
    run_study,
    survey_status,
    time_to_quality,
    to_csv,
    to_markdown,
)


def _curve(wall, mae):
    return {
        "wall_s": np.asarray(wall, float),
        "val/map_mae_m": np.asarray(mae, float),
        "step": np.arange(1, len(wall) + 1, dtype=float) * 10,
    }


def test_mae_at_is_the_latest_evaluation_and_nan_beyond_the_budget():
    c = _curve([60, 120, 300], [1.0, 0.5, 0.2])
    assert math.isnan(mae_at(c, 30, budget_s=600))  # no evaluation yet
    assert mae_at(c, 120, budget_s=600) == 0.5
    assert mae_at(c, 299, budget_s=600) == 0.5
    assert mae_at(c, 600, budget_s=600) == 0.2  # finished early: holds its last map
    assert math.isnan(mae_at(c, 601, budget_s=600))
    late = _curve([60, 302], [1.0, 0.4])  # the final evaluation lands after the time limit
    assert mae_at(late, 300, budget_s=300) == 0.4 and mae_at(late, 299, budget_s=300) == 1.0


def test_time_to_quality_uses_the_methods_best_over_its_runs():
    curves = {
        ("siren_gt_n2d", "paper"): _curve([100, 200, 400], [0.5, 0.3, 0.2]),
        ("siren_gt_n2d", "fast"): _curve([50, 150], [0.25, 0.21]),
        ("siren_lambert", "fast"): _curve([60, 120], [0.9, 0.8]),
    }
    rows = {(r["method"], r["schedule"]): r for r in time_to_quality(curves, 600, 0.10, (1, 5))}
    paper, fast = rows[("siren_gt_n2d", "paper")], rows[("siren_gt_n2d", "fast")]
    assert paper["method_best_mae"] == fast["method_best_mae"] == 0.2
    assert paper["t_within_s"] == 400  # 0.2 <= 0.22; 0.3 is not
    assert fast["t_within_s"] == 150  # 0.21 <= 0.22; 0.25 is not
    assert math.isnan(paper["mae_1min"]) and paper["mae_5min"] == 0.3  # first eval at 100 s
    assert fast["mae_1min"] == 0.25
    lam = rows[("siren_lambert", "fast")]
    assert lam["method_best_mae"] == 0.8 and lam["t_within_s"] == 120  # 0.8 is its own best
    assert lam["evaluations"] == 2 and lam["steps"] == 20 and lam["final_mae"] == 0.8


def test_time_to_quality_refuses_bad_arguments():
    with pytest.raises(ValueError, match="within: expected a fraction"):
        time_to_quality({("siren_gt_n2d", "fast"): _curve([1], [1])}, 60, within=1.5)
    with pytest.raises(ValueError, match="expected at least one evaluation"):
        time_to_quality({("siren_gt_n2d", "fast"): _curve([], [])}, 60)


def test_a_longer_reference_sets_the_best_and_keeps_its_own_budget():
    curves = {
        ("siren_gt_n2d", "fast"): _curve([300, 600, 1200], [0.20, 0.12, 0.10]),
        ("siren_gt_n2d", "fast x2"): _curve([600, 1200, 2400, 3600], [0.15, 0.11, 0.095, 0.092]),
    }
    rows = time_to_quality(
        curves, 1200, marks_min=(20, 60), budgets={("siren_gt_n2d", "fast x2"): 3600}
    )
    fast, ref = rows
    assert fast["method_best_mae"] == ref["method_best_mae"] == 0.092  # the reference's best
    assert fast["t_within_s"] == 1200  # 0.10 <= 1.1 * 0.092; 0.12 is not
    assert fast["mae_20min"] == 0.10 and math.isnan(fast["mae_60min"])  # beyond its budget
    assert ref["mae_20min"] == 0.11 and ref["mae_60min"] == 0.092
    assert ref["t_within_s"] == 2400
    with pytest.raises(ValueError, match=r"budgets\[\('siren_gt_n2d', 'fast x2'\)\]"):
        time_to_quality(curves, 1200, budgets={("siren_gt_n2d", "fast x2"): 0})


def _write_run(run_dir, wall, mae):
    run_dir.mkdir(parents=True)
    lines = ["epoch,step,wall_s,train_s,lr,val/map_mae_m"]
    lines += [
        f"{i},{10 * (i + 1)},{w},{w},1e-4,{m}"
        for i, (w, m) in enumerate(zip(wall, mae, strict=True))
    ]
    (run_dir / "metric_curve.csv").write_text("\n".join(lines) + "\n")


def test_tabulate_only_reads_existing_runs_and_references(tmp_path):
    out = tmp_path / "out"
    _write_run(out / "runs" / "siren_gt_n2d_fast", [300, 600, 1200], [0.2, 0.12, 0.10])
    _write_run(tmp_path / "ref", [600, 3600], [0.15, 0.09])
    key, ref_dir = parse_reference(f"siren_gt_n2d:fast x2={tmp_path / 'ref'}")
    assert key == ("siren_gt_n2d", "fast x2")
    rows = run_study(
        out, scale="tiny", budget_min=20, data_dir=tmp_path / "data", marks_min=(20,),
        references={key: ref_dir}, tabulate_only=True,
    )  # fmt: skip
    # nothing was prepared or fitted: only the run that exists and the reference
    assert [(r["schedule"], r["method_best_mae"]) for r in rows] == [
        ("fast", 0.09),
        ("fast x2", 0.09),
    ]
    assert rows[0]["run"] == "runs/siren_gt_n2d_fast" and rows[1]["run"] == str(ref_dir)
    assert not (tmp_path / "data").exists()
    assert "fast x2" in (out / "paper_cpu_study.md").read_text()
    # every run in out/runs is tabulated, whichever method and schedule made it
    _write_run(out / "runs" / "siren_heights_only_budget", [300, 600], [0.8, 0.9])
    rows = run_study(
        out, scale="tiny", budget_min=20, data_dir=tmp_path / "data", marks_min=(20,),
        tabulate_only=True,
    )  # fmt: skip
    assert [(r["method"], r["schedule"]) for r in rows] == [
        ("siren_gt_n2d", "fast"),
        ("siren_heights_only", "budget"),
    ]
    for bad, match in (
        ("siren_gt_n2d=x", "METHOD:LABEL=RUN_DIR"),
        ("nope:x=" + str(tmp_path), "expected a method"),
        (f"siren_gt_n2d:x={tmp_path / 'missing'}", "found no folder"),
    ):
        with pytest.raises(ValueError, match=match):
            parse_reference(bad)
    twice = ["--reference", f"siren_gt_n2d:x={tmp_path / 'ref'}"] * 2
    with pytest.raises(SystemExit) as err:
        main(["--tabulate", "--out", str(out), *twice])
    assert err.value.code == 2


def test_markdown_and_csv_tables():
    curves = {("siren_gt_n2d", "paper"): _curve([100, 200], [0.5, 0.3])}
    rows = time_to_quality(curves, 300, marks_min=(5,))
    rows[0].update(process_wall_s=330.0, run="runs/siren_gt_n2d_paper")
    prep = {"simulation": {"wall_s": 12.0, "inner_s": 8.0, "note": "generated"}, "draping": {}}
    meta = {"scale": "paper", "survey": "synthetic_d1_paper", "command": "x",
            "budget_s": 300, "evals_per_epoch": 4, "threads": 2}  # fmt: skip
    md = to_markdown(rows, prep, meta)
    assert "| SIREN-GT-N2d | paper | 0.3000 | 3.33 | 0.3000 | 0.3000 | - | 2 | 20 | 3.33 |" in md
    assert "| simulation | 12.0 | 8.0 | generated |" in md
    parsed = list(csv.DictReader(io.StringIO(to_csv(rows))))
    assert parsed[0]["method"] == "siren_gt_n2d" and float(parsed[0]["mae_5min"]) == 0.3
    assert parsed[0]["run"] == "runs/siren_gt_n2d_paper"


def test_commands(tmp_path):
    cmd = fit_command("siren_lambert", "fast", "paper", tmp_path, tmp_path / "r", 1200, 4, 2)
    assert "experiment=siren_lambert" in cmd and "siren_schedule=fast" in cmd
    assert "++trainer.max_time={seconds:1200}" in cmd
    assert "++trainer.val_check_interval=0.25" in cmd and "torch_threads=2" in cmd
    assert "++trainer.min_epochs=0" in cmd  # else the time limit waits for the epoch's end
    assert not any(c.startswith("scale.siren.budget_s=") for c in cmd)
    # the budget schedule decays its rate over the same seconds the fit may take
    budget = fit_command("siren_gt_n2d", "budget", "paper", tmp_path, tmp_path / "r", 1200)
    assert "siren_schedule=budget" in budget and "scale.siren.budget_s=1200" in budget
    assert "++trainer.max_time={seconds:1200}" in budget
    assert DEFAULT_SCHEDULES == ("paper", "budget")
    with pytest.raises(ValueError, match="schedule: expected one of"):
        fit_command("siren_gt_n2d", "slow", "paper", tmp_path, tmp_path, 60)
    with pytest.raises(ValueError, match="method: expected one of"):
        fit_command("cnn", "fast", "paper", tmp_path, tmp_path, 60)
    # the altimeter-only baseline can be asked for; the default study runs GT-N2d and Lambert
    base = fit_command("siren_heights_only", "fast", "paper", tmp_path, tmp_path, 60)
    assert "experiment=siren_heights_only" in base
    assert DEFAULT_METHODS == ("siren_gt_n2d", "siren_lambert")
    assert not any("EarlyStopping" in c for c in cmd)  # the stop lever is off by default
    stop = fit_command("siren_gt_n2d", "fast", "paper", tmp_path, tmp_path, 60, holdout_stop=3)
    assert "model.select_best=holdout_alt_mae" in stop
    early = [c for c in stop if "EarlyStopping" in c]
    assert len(early) == 1 and "monitor:val/holdout_alt_mae" in early[0]
    assert "patience:3" in early[0]
    with pytest.raises(ValueError, match="holdout_stop: expected an integer >= 0"):
        fit_command("siren_gt_n2d", "fast", "paper", tmp_path, tmp_path, 60, holdout_stop=-1)
    prep = prepare_commands("tiny", tmp_path, tmp_path)
    assert "drape=false" in prep["simulation"] and "drape=true" in prep["draping"]
    assert not any("workers" in c for c in prep["simulation"])
    prep2 = prepare_commands("tiny", tmp_path, tmp_path, sim_workers=2)
    assert "data.survey.workers=2" in prep2["simulation"]
    with pytest.raises(ValueError, match="sim_workers: expected an integer >= 1"):
        prepare_commands("tiny", tmp_path, tmp_path, sim_workers=0)


def test_the_study_runs_on_another_synthetic_survey(tmp_path):
    # the default is d1; the validation site is where settings may be chosen
    assert "data/survey=synthetic_d1" in fit_command(
        "siren_gt_n2d", "budget", "paper", tmp_path, tmp_path / "r", 60
    )
    cmd = fit_command(
        "siren_gt_n2d", "budget", "paper", tmp_path, tmp_path / "r", 60,
        preset="synthetic_d1_valsite",
    )  # fmt: skip
    assert "data/survey=synthetic_d1_valsite" in cmd
    prep = prepare_commands("tiny", tmp_path, tmp_path, "synthetic_d1_valsite")
    assert "data/survey=synthetic_d1_valsite" in prep["simulation"]
    status = survey_status("tiny", tmp_path, "synthetic_d1_valsite")
    assert status["name"] == "synthetic_d1_valsite_tiny"
    assert check_preset("synthetic_d1_valsite") == "synthetic_d1_valsite"
    with pytest.raises(
        ValueError, match=r"survey: expected a synthetic survey preset, one of .*found 'xtf'"
    ):
        check_preset("xtf")
    with pytest.raises(SystemExit):
        main(["--survey", "nope", "--dry-run"])


def test_survey_status_is_a_dry_compose(tmp_path):
    status = survey_status("tiny", tmp_path)
    assert status["name"] == "synthetic_d1_tiny" and len(status["config_hash"]) == 16
    assert status["problem"] is not None  # nothing there; nothing was made either
    assert not any(tmp_path.iterdir())


@pytest.mark.slow
def test_tiny_study_end_to_end(tmp_path):
    rows = run_study(
        tmp_path / "out", scale="tiny", budget_min=0.1, data_dir=tmp_path / "data",
        methods=["siren_gt_n2d"], schedules=["fast"], threads=1, marks_min=(0.05,),
    )  # fmt: skip
    assert len(rows) == 1
    row = rows[0]
    assert 0 < row["best_mae"] < 2 and row["evaluations"] >= 2
    assert math.isfinite(row["t_within_s"]) and row["t_within_s"] <= row["fit_wall_s"]
    out = tmp_path / "out"
    for name in ("paper_cpu_study.md", "paper_cpu_study.csv", "paper_cpu_study.png"):
        assert (out / name).is_file()
    assert (out / "runs" / "siren_gt_n2d_fast" / "metric_curve.csv").is_file()
    assert "| simulation |" in (out / "paper_cpu_study.md").read_text()
    assert row["map_mae"] == pytest.approx(row["final_mae"], rel=0.05)  # no select_best


@pytest.mark.slow
def test_budget_stops_a_fit_inside_its_first_epoch(tmp_path):
    rows = run_study(
        tmp_path / "out", scale="tiny", budget_min=0.1, data_dir=tmp_path / "data",
        methods=["siren_gt_n2d"], schedules=["fast"], threads=1, marks_min=(0.05,),
        evals_per_epoch=100, extra=["scale.siren.fast_steps_per_epoch=5000"],
    )  # fmt: skip
    # an epoch of 5000 steps takes minutes; the 6 s budget ends the fit well inside it
    assert len(rows) == 1 and 0 < rows[0]["steps"] < 2500
    assert rows[0]["fit_wall_s"] < 60


@pytest.mark.slow
def test_tiny_holdout_stop_ends_the_fit_early(tmp_path):
    rows = run_study(
        tmp_path / "out", scale="tiny", budget_min=2.0, data_dir=tmp_path / "data",
        methods=["siren_gt_n2d"], schedules=["fast"], threads=1, marks_min=(0.05,),
        evals_per_epoch=4, holdout_stop=1,
        extra=["data.holdout.block_pings=10"],  # tiny lines are shorter than 50-ping blocks
    )  # fmt: skip
    # the fast schedule's 10 epochs x 40 steps (4 evaluations each) would give 40 or more
    assert len(rows) == 1 and rows[0]["steps"] < 400 and rows[0]["evaluations"] < 40
    assert "stopped after 1 evaluations" in (tmp_path / "out" / "paper_cpu_study.md").read_text()
    assert rows[0]["map_mae"] <= rows[0]["final_mae"]  # the held-out best SIREN is mapped
