"""make gpu-check: one line and exit 0 without CUDA; its commands, stop rule and summaries;
the whole check on a CPU at the tiny scale (slow tier)."""

from __future__ import annotations

import json
import math
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from sss2bathy.utils.progress import progress_line
from studies import gpu_check
from studies.gpu_check import (
    BEST_KNOWN_MAE_M,
    DONE_LINE,
    cnn_command,
    parse_duration,
    siren_command,
    siren_summary,
    target_stop,
)

ROOT = Path(__file__).resolve().parents[2]


def test_without_cuda_it_says_so_in_one_line_and_exits_0(monkeypatch, capsys):
    monkeypatch.setattr(gpu_check, "cuda_device", lambda: None)
    monkeypatch.setattr(gpu_check, "nvidia_present", lambda: False)
    assert gpu_check.main([]) == 0
    out = capsys.readouterr().out
    assert out.count("\n") == 1 and out.startswith("gpu-check: no CUDA GPU on this machine")
    # a GPU that this torch cannot use is no "CPU-only machine": one line, status 2
    monkeypatch.setattr(gpu_check, "nvidia_present", lambda: True)
    assert gpu_check.main([]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "an NVIDIA GPU is present but torch" in err


@pytest.mark.skipif(
    torch.cuda.is_available() or gpu_check.nvidia_present(),
    reason="a GPU is present: the check would run (or refuse a CPU torch)",
)
def test_the_command_on_a_cpu_only_machine():
    env = {**os.environ, "SSS2BATHY_ROOT": str(ROOT), "OMP_NUM_THREADS": "1"}
    done = subprocess.run(
        [sys.executable, "-m", "studies.gpu_check"], cwd=ROOT, env=env,
        capture_output=True, text=True, timeout=300,
    )  # fmt: skip
    assert done.returncode == 0, done.stderr
    assert done.stdout.strip().splitlines() == [gpu_check.no_gpu_line()]


def test_fit_commands_and_the_stop_rule(tmp_path):
    target = 1.1 * BEST_KNOWN_MAE_M
    cmd = siren_command("paper", tmp_path, tmp_path / "runs" / "s", 240, "cuda", target)
    assert "experiment=siren_gt_n2d" in cmd and "siren_schedule=fast" in cmd
    assert "trainer.accelerator=gpu" in cmd and "scale.siren.fast_steps_per_epoch=2000" in cmd
    assert "++trainer.max_time={seconds:240}" in cmd
    assert any("stopping_threshold:0.08426" in a for a in cmd)
    assert "callbacks.progress.when=always" in cmd  # the log shows progress
    cmd = siren_command("tiny", tmp_path, tmp_path / "s", 30, "cpu", None)
    assert "trainer.accelerator=cpu" in cmd and not any("stopping_threshold" in a for a in cmd)
    cmd = cnn_command("paper", tmp_path, tmp_path / "runs" / "c", 150, "cuda")
    assert "experiment=cnn" in cmd and "trainer.max_epochs=1" in cmd and "test=false" in cmd
    assert "data.test_surveys=[]" in cmd and "++trainer.max_time={seconds:150}" in cmd
    with pytest.raises(ValueError, match="target_mae: expected a positive MAE"):
        target_stop(0.0)
    with pytest.raises(ValueError, match="cnn budget: expected a positive number"):
        cnn_command("paper", tmp_path, tmp_path, 0, "cuda")


def test_the_cnn_epoch_is_read_from_its_closing_progress_line():
    line = progress_line("train done: epoch 1/1", 93, 120, 754.0, "steps")
    m = DONE_LINE.search("[...][sss2bathy.progress][INFO] - " + line)
    assert m and (int(m["done"]), int(m["total"])) == (93, 120)
    assert parse_duration(m["elapsed"]) == 754.0  # "12 min 34 s"
    assert float(m["rate"]) == pytest.approx(93 / 754.0, rel=1e-2)
    assert parse_duration("1 h 02 min") == 3720.0
    with pytest.raises(ValueError, match="duration: expected"):
        parse_duration("soon")


def test_siren_summary_times_to_its_own_best_and_to_the_target():
    curve = {
        "val/map_mae_m": np.array([0.30, 0.12, 0.090, 0.082, 0.080]),
        "wall_s": np.array([10.0, 60.0, 120.0, 180.0, 240.0]),
        "step": np.array([100, 600, 1200, 1800, 2400]),
    }
    s = siren_summary(curve, 0.0843, 250.0)
    assert s["best_mae_m"] == 0.080 and s["steps"] == 2400
    assert s["t_within_own_best_s"] == 180.0  # 0.082 <= 1.1 x 0.080
    assert s["t_target_s"] == 180.0 and s["steps_per_s"] == 10.0
    assert siren_summary(curve, 0.05, 250.0)["t_target_s"] is None
    assert math.isnan(
        siren_summary({**curve, "wall_s": curve["wall_s"] * 0}, None, 1)["steps_per_s"]
    )


@pytest.mark.slow
def test_the_whole_check_runs_on_a_cpu_at_the_tiny_scale(tmp_path):
    env = {**os.environ, "SSS2BATHY_ROOT": str(ROOT), "OMP_NUM_THREADS": "1"}
    out = tmp_path / "gpu_check"
    cmd = [sys.executable, "-m", "studies.gpu_check", "--device", "cpu", "--scale", "tiny"]
    cmd += ["--out", str(out), "--data-dir", str(tmp_path / "data"), "--siren-budget-s", "60"]
    cmd += ["--cnn-budget-s", "60", "--sim-workers", "1", "--extra", "torch_threads=1"]
    done = subprocess.run(cmd, cwd=ROOT, env=env, capture_output=True, text=True, timeout=900)
    assert done.returncode == 0, done.stderr[-3000:]
    result = json.loads((out / "gpu_check.json").read_text())
    assert result["gpu"] is None and result["scale"] == "tiny"
    assert result["siren"]["steps"] > 0 and result["siren"]["best_mae_m"] > 0
    assert result["cnn"]["steps"] > 0 and result["cnn"]["steps_per_s"] > 0
    assert "gpu-check on CPU" in done.stdout and "SIREN-GT-N2d: best map MAE" in done.stdout
