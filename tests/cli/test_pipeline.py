"""``python -m sss2bathy.cli.pipeline``: --help runs nothing; arguments; what runs when a CNN
exists or not; the stage times; the Makefile's help."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from sss2bathy.cli.pipeline import Args, parse_args, plan_stages, record_time, select
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
