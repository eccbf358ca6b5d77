"""Resume: a fit stopped mid-epoch (or at an epoch end) and resumed from last.ckpt ends
exactly as the uninterrupted fit: weights, optimizer and metrics equal bit for bit."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import pytorch_lightning as pl
import torch
from reliability_helpers import ROOT, cnn_overrides, compose_run, siren_overrides

import sss2bathy.cli.instantiate as instantiate_module
from sss2bathy.cli.instantiate import resolve_ckpt_path
from sss2bathy.cli.train import train
from sss2bathy.data.pings import PingBatchSampler
from sss2bathy.data.windows import FlipShuffleSampler, ResumableDataLoader

# measured: 0 (bitwise equal) for both modules; the bound allows for BLAS differences only
TOLERANCE = 1e-6


class Interrupt(pl.Callback):
    """Stops the fit right after optimizer step ``at`` (as a kill would, minus the kill)."""

    def __init__(self, at: int) -> None:
        self.at = at

    def on_train_batch_end(self, trainer, pl_module, outputs, batch, batch_idx):
        if trainer.global_step == self.at:
            raise KeyboardInterrupt(f"interrupted at step {self.at}")


def _run(overrides, run_dir: Path, monkeypatch=None, interrupt_at=None) -> dict:
    cfg = compose_run(overrides, run_dir)
    if interrupt_at is not None:
        original = instantiate_module.instantiate_callbacks
        monkeypatch.setattr(
            instantiate_module,
            "instantiate_callbacks",
            lambda c: original(c) + [Interrupt(interrupt_at)],
        )
        with pytest.raises(SystemExit):  # Lightning's graceful shutdown of the interrupt
            train(cfg, run_dir)
        monkeypatch.undo()
        return {}
    return {k: float(v) for k, v in train(cfg, run_dir).items()}


def _weights(ckpt: Path) -> dict[str, torch.Tensor]:
    return torch.load(ckpt, map_location="cpu", weights_only=True)["state_dict"]


def _assert_same_run(a: Path, b: Path, metrics_a: dict, metrics_b: dict) -> float:
    """Largest difference of final weights, Adam moments and val metrics of two runs."""
    ca = torch.load(a / "checkpoints" / "last.ckpt", weights_only=True)
    cb = torch.load(b / "checkpoints" / "last.ckpt", weights_only=True)
    assert ca["global_step"] == cb["global_step"] and ca["epoch"] == cb["epoch"]
    diff = 0.0
    for key, value in ca["state_dict"].items():
        diff = max(diff, float((value.float() - cb["state_dict"][key].float()).abs().max()))
    for sa, sb in zip(
        ca["optimizer_states"][0]["state"].values(),
        cb["optimizer_states"][0]["state"].values(),
        strict=True,
    ):
        diff = max(diff, float((sa["exp_avg"] - sb["exp_avg"]).abs().max()))
    assert ca["lr_schedulers"] == cb["lr_schedulers"]
    for key, value in metrics_a.items():
        if key.startswith("val/"):
            diff = max(diff, abs(value - metrics_b[key]))
    assert diff <= TOLERANCE, diff
    return diff


# ------------------------------------------------------------------ data order
@pytest.mark.parametrize("kind", ["windows", "pings"])
def test_resumable_loader_serves_the_rest_of_the_epoch(kind):
    if kind == "windows":
        make = lambda: ResumableDataLoader(  # noqa: E731
            list(range(20)), batch_size=3, sampler=FlipShuffleSampler(10, seed=5)
        )
    else:
        make = lambda: ResumableDataLoader(  # noqa: E731
            {(e, k): (e, k) for e in range(5) for k in range(6)},
            batch_size=None,
            sampler=PingBatchSampler(6),
        )
    first = make()
    first.sampler.set_epoch(2)
    full = list(first)
    it = iter(first)
    first.sampler.set_epoch(2)
    served = [next(it), next(it)]
    state = first.state_dict()
    assert state == {"epoch": 2, "batches": 2}
    resumed = make()
    resumed.load_state_dict(state)
    resumed.sampler.set_epoch(2)
    rest = list(resumed)
    assert [torch.as_tensor(b).tolist() for b in served + rest] == [
        torch.as_tensor(b).tolist() for b in full
    ]
    # another epoch than the saved one is served whole, from its own seed
    other = make()
    other.load_state_dict(state)
    other.sampler.set_epoch(3)
    assert len(list(other)) == len(full)


def test_resolve_ckpt_path(tmp_path, caplog):
    run = tmp_path / "run"
    assert resolve_ckpt_path(None, run) is None
    assert resolve_ckpt_path("last", run) is None and "starting fresh" in caplog.text
    last = run / "checkpoints" / "last.ckpt"
    last.parent.mkdir(parents=True)
    last.write_bytes(b"x")
    assert resolve_ckpt_path("last", run) == str(last)
    assert resolve_ckpt_path(str(run), tmp_path / "new") == str(last)
    hpc = run / "hpc_ckpt_1.ckpt"
    hpc.write_bytes(b"x")
    os.utime(hpc, (time.time() + 10, time.time() + 10))
    assert resolve_ckpt_path("last", run) == str(hpc)  # the newer: Lightning's SLURM save
    assert resolve_ckpt_path(str(last), None) == str(last)
    with pytest.raises(FileNotFoundError, match="ckpt_path"):
        resolve_ckpt_path(str(tmp_path / "nope.ckpt"), run)
    with pytest.raises(FileNotFoundError, match="ckpt_path"):
        resolve_ckpt_path(str(tmp_path), run)  # a folder without checkpoints


# ------------------------------------------------------------------ whole fits
def test_siren_fit_interrupted_mid_epoch_resumes_exactly(tmp_path, plane_survey, monkeypatch):
    # 5 steps per epoch, 3 epochs; last.ckpt every 2 steps: interrupted at step 7, the fit
    # resumes from step 6 (epoch 1, batch 1), warm-start cache and data order included
    base = siren_overrides(plane_survey, tmp_path) + [
        "trainer.max_epochs=3",
        "callbacks.step_checkpoint.every_n_train_steps=2",
    ]
    full, part = tmp_path / "full", tmp_path / "part"
    m_full = _run(base + [f"model.output_dir={full / 'map'}"], full)
    _run(base + [f"model.output_dir={part / 'map'}"], part, monkeypatch, interrupt_at=7)
    assert torch.load(part / "checkpoints" / "last.ckpt", weights_only=True)["global_step"] == 6
    m_part = _run(base + [f"model.output_dir={part / 'map'}", "ckpt_path=last"], part)
    _assert_same_run(full, part, m_full, m_part)
    final = [
        json.loads((d / "map" / "metrics.json").read_text())["final/mae"] for d in (full, part)
    ]
    assert final[0] == final[1] and np.isfinite(final[0])


def test_cnn_fit_with_dropout_resumes_exactly_from_another_run_folder(
    tmp_path, hills_survey, monkeypatch
):
    # dropout draws from the global RNG: GlobalRNGState carries it through the checkpoint
    base = cnn_overrides(hills_survey, tmp_path) + [
        "trainer.max_epochs=3",
        "model.net.use_dropout=true",
        "callbacks.step_checkpoint.every_n_train_steps=3",
    ]
    full, part, cont = tmp_path / "full", tmp_path / "part", tmp_path / "cont"
    m_full = _run(base, full)
    _run(base, part, monkeypatch, interrupt_at=17)
    assert torch.load(part / "checkpoints" / "last.ckpt", weights_only=True)["global_step"] == 15
    # ckpt_path=<run folder>: that run's last.ckpt, continued in a new folder
    m_cont = _run(base + [f"ckpt_path={part}"], cont)
    _assert_same_run(full, cont, m_full, m_cont)
    assert m_full["test/hills:test/nlat_mae"] == m_cont["test/hills:test/nlat_mae"]


# ------------------------------------------------------------------ real signals
def _cli(args: list[str], env: dict) -> subprocess.Popen:
    return subprocess.Popen(
        [sys.executable, "-m", "sss2bathy.cli.train", *args],
        cwd=ROOT,
        env=env,
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
    )


@pytest.mark.slow
@pytest.mark.parametrize("sig", [signal.SIGKILL, signal.SIGTERM])
def test_cli_killed_and_resumed_in_its_run_folder(tmp_path, plane_survey, sig):
    """``sss2bathy-train ... ckpt_path=last hydra.run.dir=<the killed run's folder>``."""
    env = {**os.environ, "SSS2BATHY_ROOT": str(ROOT), "OMP_NUM_THREADS": "1"}
    base = siren_overrides(plane_survey, tmp_path) + [
        "trainer.max_epochs=40",
        "callbacks.step_checkpoint.every_n_train_steps=3",
    ]
    full, part = tmp_path / "full", tmp_path / "part"
    proc = _cli(base + [f"hydra.run.dir={full}", f"model.output_dir={full / 'map'}"], env)
    assert proc.wait(timeout=300) == 0, proc.stdout.read()
    proc = _cli(base + [f"hydra.run.dir={part}", f"model.output_dir={part / 'map'}"], env)
    last = part / "checkpoints" / "last.ckpt"
    deadline = time.time() + 120
    while time.time() < deadline and proc.poll() is None:
        if last.is_file() and torch.load(last, weights_only=True)["global_step"] >= 20:
            break
        time.sleep(0.05)
    assert proc.poll() is None, "the run ended before it could be killed"
    proc.send_signal(sig)
    proc.wait(timeout=120)
    assert torch.load(last, weights_only=True)["epoch"] < 39
    args = base + [f"hydra.run.dir={part}", f"model.output_dir={part / 'map'}", "ckpt_path=last"]
    proc = _cli(args, env)
    out = proc.communicate(timeout=300)[0]
    assert proc.returncode == 0 and "Restored all states" in out, out
    metrics = [json.loads((d / "map" / "metrics.json").read_text()) for d in (full, part)]
    assert metrics[0]["final/mae"] == metrics[1]["final/mae"]
    maps = [np.load(d / "map" / "map.npz", allow_pickle=False)["heights"] for d in (full, part)]
    np.testing.assert_array_equal(maps[0], maps[1])
