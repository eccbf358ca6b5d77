"""``python -m sss2bathy.cli.pipeline``: --help runs nothing; arguments; what runs when a CNN
exists or not; the stage times; the Makefile's help."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import time
from pathlib import Path

import pytest

from sss2bathy.cli.pipeline import (
    Args,
    Stage,
    default_jobs,
    dependencies,
    parse_args,
    plan_stages,
    record_time,
    record_wall,
    run_plan,
    schedule,
    select,
    stage_threads,
)
from sss2bathy.utils.experiments import pipeline_experiments

ROOT = Path(__file__).resolve().parents[2]
STAGE_NAMES = [s.name for s in plan_stages(pipeline_experiments(ROOT / "conf"))]


@pytest.mark.parametrize("flag", ["--help", "-h"])
def test_help_prints_usage_and_runs_nothing(tmp_path, flag):
    (tmp_path / "conf").symlink_to(ROOT / "conf")
    env = dict(os.environ, SSS2BATHY_ROOT=str(tmp_path), OMP_NUM_THREADS="1")
    proc = subprocess.run(
        [sys.executable, "-m", "sss2bathy.cli.pipeline", flag, "scale=tiny"],
        cwd=tmp_path,
        env=env,
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout.startswith("usage: python -m sss2bathy.cli.pipeline")
    assert "stages, in order: " + ", ".join(STAGE_NAMES) in proc.stdout
    assert "===" not in proc.stdout  # no stage started
    assert sorted(p.name for p in tmp_path.iterdir()) == ["conf"]  # nothing written


def test_a_bad_pipeline_key_is_one_line_and_exit_2(tmp_path):
    (tmp_path / "conf").mkdir()
    shutil.copytree(ROOT / "conf" / "experiment", tmp_path / "conf" / "experiment")
    bad = tmp_path / "conf" / "experiment" / "siren_lambert.yaml"
    bad.write_text(bad.read_text().replace("  order: 70", "  order: seventy"))
    env = dict(os.environ, SSS2BATHY_ROOT=str(tmp_path), OMP_NUM_THREADS="1")
    proc = subprocess.run(
        [sys.executable, "-m", "sss2bathy.cli.pipeline", "--help"],
        cwd=tmp_path,
        env=env,
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert proc.returncode == 2 and proc.stdout == ""
    assert proc.stderr.strip().count("\n") == 0, proc.stderr
    assert "siren_lambert.yaml: pipeline.order: expected an integer >= 0, found 'seventy'" in (
        proc.stderr
    )


def test_parse_args_splits_scale_stages_and_overrides():
    args = parse_args(["scale=tiny", "stages=[cnn, report]", "seed=2", "make=d2", "needs=[cnn]"])
    assert args == Args("tiny", ["cnn", "report"], "d2", ["cnn"], ["seed=2"])
    with pytest.raises(SystemExit, match="unknown stage"):
        select(parse_args(["stages=[cnn,nope]"]), Path("/nonexistent"))
    with pytest.raises(SystemExit, match="make: expected one of"):
        select(parse_args(["make=nope"]), Path("/nonexistent"))


def _cnn_run(outputs: Path, scale: str) -> None:
    run = outputs / "runs" / "cnn" / "2026-01-01_00-00-00"
    (run / "checkpoints").mkdir(parents=True)
    (run / "checkpoints" / "last.ckpt").write_bytes(b"")
    (run / ".hydra").mkdir()
    (run / ".hydra" / "config.yaml").write_text(f"scale:\n  name: {scale}\n")


def _names(argv: list[str], outputs: Path) -> list[str]:
    return [s.name for s in select(parse_args(argv), outputs)]


def test_a_cnn_is_trained_first_only_when_none_of_this_scale_exists(tmp_path):
    prepare = ["prepare_d1", "prepare_d2", "prepare_d3", "prepare_d1_site2"]
    assert _names(["scale=demo", "make=siren-cnn-n2d"], tmp_path) == [
        *prepare,
        "cnn",
        "siren_cnn_n2d",
    ]
    assert _names(["scale=demo", "make=d3"], tmp_path) == [
        *prepare,
        "cnn",
        "d3_siren_cnn_n2d",
        "d3_siren_cnn_n2d_pretrained",
        "d3_siren_lambert",
    ]
    _cnn_run(tmp_path, "tiny")  # a run of another scale does not count
    assert "cnn" in _names(["scale=demo", "needs=[cnn]"], tmp_path)
    _cnn_run(tmp_path / "demo", "demo")
    outputs = tmp_path / "demo"
    assert _names(["scale=demo", "make=siren-cnn-n2d"], outputs) == ["siren_cnn_n2d"]
    assert _names(["scale=demo", "make=d3"], outputs) == [
        "prepare_d3",
        "d3_siren_cnn_n2d",
        "d3_siren_cnn_n2d_pretrained",
        "d3_siren_lambert",
    ]
    assert _names(["scale=demo", "needs=[cnn]"], outputs) == []
    # chosen explicitly, it runs anyway; the whole pipeline runs every stage
    assert "cnn" in _names(["scale=demo", "stages=[cnn]"], outputs)
    assert _names(["scale=demo"], outputs) == STAGE_NAMES


def test_stage_times_keep_the_latest_time_of_each_stage(tmp_path):
    path = tmp_path / "stage_times.json"
    record_time(path, "demo", "cnn", 100.04)
    record_time(path, "demo", "siren_gt_n2d", 20.0)
    record_time(path, "demo", "cnn", 90.0)
    assert json.loads(path.read_text()) == {
        "scale": "demo",
        "seconds": {"cnn": 90.0, "siren_gt_n2d": 20.0, "total": 110.0},
    }
    record_time(path, "tiny", "cnn", 5.0)  # another scale starts afresh
    assert json.loads(path.read_text())["seconds"] == {"cnn": 5.0, "total": 5.0}


@pytest.mark.skipif(shutil.which("make") is None, reason="make is not installed")
def test_make_help_has_no_colour_codes_in_a_pipe_and_lists_every_experiment():
    proc = subprocess.run(
        ["make", "--no-print-directory", "help"],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert proc.returncode == 0, proc.stderr
    assert "\033[" not in proc.stdout
    targets = {line.split()[0] for line in proc.stdout.splitlines() if line.strip()}
    assert {"siren-heights-only", "siren-gt-n2d", "sweep-siren", "report", "demo"} <= targets


def test_stages_wait_for_the_surveys_and_their_needs_and_the_report_for_all():
    plan = plan_stages(pipeline_experiments(ROOT / "conf"))
    deps = dependencies(plan)
    prepares = {s.name for s in plan if s.name.startswith("prepare_")}
    assert all(deps[p] == set() for p in prepares)
    assert deps["cnn"] == prepares
    assert deps["siren_cnn_n2d"] == prepares | {"cnn"}
    assert deps["siren_gt_n2d"] == prepares  # does not wait for the CNN
    assert deps["report"] == {s.name for s in plan} - {"report"}


def test_two_jobs_overlap_the_cnn_with_the_fits_that_do_not_read_it():
    plan = plan_stages(pipeline_experiments(ROOT / "conf"))
    durations = {s.name: 10.0 for s in plan} | {"cnn": 100.0}
    one = schedule(plan, 1, durations)
    assert one == sum(durations.values())
    two = schedule(plan, 2, durations)
    # the prepares in two lanes (20), the CNN beside the 6 fits that need no CNN (100), the
    # 3 CNN-N2d fits in two lanes (20), the report (10)
    assert two == 20 + 100 + 20 + 10
    bad = [Stage("a", "sss2bathy.cli.train", ("experiment=a",)), Stage("report", "x", ())]
    deps_on_missing = {"a": 1.0, "report": 1.0}
    assert schedule(bad, 2, deps_on_missing) == 2.0


def test_jobs_follow_the_cores_and_the_stage_threads(tmp_path):
    assert default_jobs(1, 2) == 2 and default_jobs(2, 2) == 1 and default_jobs(None, 16) == 1
    assert default_jobs(4, 2) == 1
    assert stage_threads(parse_args(["scale=demo"]), ROOT / "conf") == 1
    assert stage_threads(parse_args(["scale=paper"]), ROOT / "conf") is None
    assert stage_threads(parse_args(["scale=demo", "torch_threads=3"]), ROOT / "conf") == 3
    assert stage_threads(parse_args(["scale=demo", "torch_threads=null"]), ROOT / "conf") is None
    with pytest.raises(ValueError, match="torch_threads: expected an integer >= 1 or null"):
        stage_threads(parse_args(["torch_threads=two"]), ROOT / "conf")
    assert parse_args(["jobs=3"]).jobs == 3
    with pytest.raises(ValueError, match="jobs: expected an integer >= 1, found '0'"):
        parse_args(["jobs=0"])


def _script_plan(tmp_path: Path) -> tuple[list[Stage], callable]:
    """Four stages of small Python scripts: two prepares, a fit that needs one, a report."""
    plan = [
        Stage("prepare_a", "sss2bathy.cli.prepare", ()),
        Stage("prepare_b", "sss2bathy.cli.prepare", ()),
        Stage("fit", "sss2bathy.cli.train", (), ("other",)),
        Stage("report", "sss2bathy.cli.report", ()),
    ]
    marks = tmp_path / "marks"
    marks.mkdir()

    def command(stage: Stage) -> list[str]:
        code = (
            "import sys, time, pathlib;"
            f"m = pathlib.Path({str(marks)!r});"
            f"(m / '{stage.name}.start').write_text(str(time.time()));"
            f"print('hello from {stage.name}');"
            "time.sleep(0.5);"
            f"(m / '{stage.name}.end').write_text(str(time.time()));"
            f"sys.exit(3 if (m / 'fail_{stage.name}').exists() else 0)"
        )
        return [sys.executable, "-c", code]

    return plan, command


def test_run_plan_runs_independent_stages_side_by_side_and_keeps_each_log(tmp_path, capfd):
    plan, command = _script_plan(tmp_path)
    marks = tmp_path / "marks"
    finished: list[str] = []
    code = run_plan(
        plan, 2, command, tmp_path, tmp_path / "logs", lambda s, t: finished.append(s.name)
    )
    assert code == 0
    assert finished[-1] == "report" and sorted(finished) == sorted(s.name for s in plan)

    def t(name: str, what: str) -> float:
        return float((marks / f"{name}.{what}").read_text())

    assert t("prepare_b", "start") < t("prepare_a", "end")  # side by side
    assert t("fit", "start") >= max(t("prepare_a", "end"), t("prepare_b", "end"))
    assert t("report", "start") >= t("fit", "end")
    out = capfd.readouterr().out
    assert "[fit] hello from fit" in out and "=== [3/4] fit: done in" in out
    assert (tmp_path / "logs" / "fit.log").read_text() == "hello from fit\n"


def test_run_plan_starts_nothing_after_a_failure_and_returns_its_status(tmp_path, capfd):
    plan, command = _script_plan(tmp_path)
    (tmp_path / "marks" / "fail_prepare_a").write_text("")
    finished: list[str] = []
    code = run_plan(
        plan, 2, command, tmp_path, tmp_path / "logs", lambda s, t: finished.append(s.name)
    )
    assert code == 3
    assert finished == ["prepare_b"]  # prepare_b was already running; nothing started after
    assert not (tmp_path / "marks" / "fit.start").exists()
    captured = capfd.readouterr()
    assert "stage 'prepare_a' failed (exit 3); stopping." in captured.err


def test_the_wall_time_sits_beside_the_stage_times_until_a_new_run_starts(tmp_path):
    path = tmp_path / "stage_times.json"
    record_time(path, "demo", "cnn", 100.0)
    record_time(path, "demo", "siren_gt_n2d", 20.0)
    record_wall(path, 100.5, 2)
    record_time(path, "demo", "report", 5.0)  # the report stage keeps them
    data = json.loads(path.read_text())
    assert data["wall_seconds"] == 100.5 and data["jobs"] == 2
    assert data["seconds"]["total"] == 125.0
    record_wall(path, None, None)
    assert "wall_seconds" not in json.loads(path.read_text())


def test_a_worker_left_holding_a_stages_output_does_not_hold_the_pipeline(tmp_path, monkeypatch):
    import sss2bathy.cli.pipeline as pipeline

    monkeypatch.setattr(pipeline, "READER_GRACE_S", 0.5)
    leaves_a_worker = (
        "import subprocess, sys; "
        "subprocess.Popen([sys.executable, '-c', 'import time; time.sleep(20)']); print('bye')"
    )
    plan = [Stage("prepare_a", "sss2bathy.cli.prepare", ())]
    t0 = time.perf_counter()
    code = run_plan(
        plan, 2, lambda s: [sys.executable, "-c", leaves_a_worker], tmp_path, tmp_path / "logs",
        lambda s, t: None,
    )  # fmt: skip
    assert code == 0 and time.perf_counter() - t0 < 10


def test_a_stage_waiting_for_one_that_never_runs_is_an_error_not_a_silent_success(
    tmp_path, capfd, monkeypatch
):
    import sss2bathy.cli.pipeline as pipeline

    plan = [Stage("fit", "sss2bathy.cli.train", ()), Stage("report", "x", ())]
    # the fit waits for itself: never ready (a checked plan cannot do this)
    monkeypatch.setattr(pipeline, "dependencies", lambda plan: {"fit": {"fit"}, "report": {"fit"}})
    code = run_plan(plan, 2, lambda s: [sys.executable, "-c", ""], tmp_path, None, print)
    assert code == 1
    assert "wait for stages that never ran" in capfd.readouterr().err
