"""Resume: a fit stopped mid-epoch (or at an epoch end) and resumed from last.ckpt ends
exactly as the uninterrupted fit: weights, optimizer and metrics equal bit for bit.

The default callbacks (``conf/callbacks/default.yaml``: last.ckpt every epoch and every 500
steps, no test-only intervals) are what a killed run resumes from; SIGTERM saves last.ckpt
at the next batch end and exits 143 with the resume command on stderr."""

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


class KillAtEpoch(pl.Callback):
    """Stops the fit as SIGKILL would at the start of epoch ``at``: nothing is saved on
    the way out (only what the periodic saves wrote before stands)."""

    def __init__(self, at: int) -> None:
        self.at = at

    def on_train_epoch_start(self, trainer, pl_module):
        if trainer.current_epoch == self.at:
            raise KeyboardInterrupt(f"killed at epoch {self.at}")


class Interrupt(pl.Callback):
    """Stops the fit right after optimizer step ``at`` (as a kill would, minus the kill)."""

    def __init__(self, at: int) -> None:
        self.at = at

    def on_train_batch_end(self, trainer, pl_module, outputs, batch, batch_idx):
        if trainer.global_step == self.at:
            raise KeyboardInterrupt(f"interrupted at step {self.at}")


def _run(overrides, run_dir: Path, monkeypatch=None, interrupt_at=None, kill_at_epoch=None):
    cfg = compose_run(overrides, run_dir)
    if interrupt_at is not None or kill_at_epoch is not None:
        stop = Interrupt(interrupt_at) if interrupt_at is not None else KillAtEpoch(kill_at_epoch)
        original = instantiate_module.instantiate_callbacks
        monkeypatch.setattr(
            instantiate_module, "instantiate_callbacks", lambda c: original(c) + [stop]
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
    # a folder without last.ckpt (a run killed before it had one, e.g. with only the CNN's
    # best-epoch save): its newest checkpoint
    other = tmp_path / "other"
    (other / "checkpoints").mkdir(parents=True)
    for i, name in enumerate(["epoch_0000.ckpt", "epoch_0001.ckpt"]):
        (other / "checkpoints" / name).write_bytes(b"x")
        os.utime(other / "checkpoints" / name, (time.time() + i, time.time() + i))
    assert resolve_ckpt_path("last", other) == str(other / "checkpoints" / "epoch_0001.ckpt")
    with pytest.raises(FileNotFoundError, match="ckpt_path"):
        resolve_ckpt_path(str(tmp_path / "nope.ckpt"), run)
    with pytest.raises(FileNotFoundError, match="ckpt_path"):
        resolve_ckpt_path(str(tmp_path), run)  # a folder without checkpoints


# ------------------------------------------------------------------ whole fits
def _task_overrides(task: str, plane_survey: Path, hills_survey: Path, tmp: Path) -> list[str]:
    """A tiny fit of ``task`` with the DEFAULT checkpoint callbacks (nothing test-only)."""
    if task == "cnn":
        return cnn_overrides(hills_survey, tmp)
    overrides = siren_overrides(plane_survey, tmp)
    if task == "lambert":
        overrides[0] = "experiment=siren_lambert"
    return overrides


@pytest.mark.parametrize("task", ["siren", "cnn", "lambert"])
def test_fit_killed_after_an_epoch_resumes_from_that_epoch_with_the_default_callbacks(
    tmp_path, plane_survey, hills_survey, monkeypatch, caplog, task
):
    # killed (nothing saved on the way out) at the start of epoch 2 of 3: the epoch-end save
    # of epoch 1 is there whatever save_top_k, and the resumed fit starts at epoch 2
    base = _task_overrides(task, plane_survey, hills_survey, tmp_path)
    base.append("trainer.max_epochs=3")
    full, part = tmp_path / "full", tmp_path / "part"
    maps = {d: [f"model.output_dir={d / 'map'}"] if task != "cnn" else [] for d in (full, part)}
    m_full = _run(base + maps[full], full)
    _run(base + maps[part], part, monkeypatch, kill_at_epoch=2)
    last = part / "checkpoints" / "last.ckpt"
    assert torch.load(last, weights_only=True)["epoch"] == 1
    caplog.clear()
    with caplog.at_level("INFO", logger="sss2bathy.train"):
        m_part = _run(base + maps[part] + ["ckpt_path=last"], part)
    assert f"resuming from {last} at epoch 2 (step " in caplog.text
    _assert_same_run(full, part, m_full, m_part)
    if task != "cnn":
        final = [json.loads((d / "map" / "metrics.json").read_text()) for d in (full, part)]
        assert final[0] == final[1]


@pytest.mark.slow
def test_cnn_folder_with_only_its_best_epoch_checkpoint_resumes_from_it(
    tmp_path, hills_survey, monkeypatch, caplog
):
    """A CNN run folder from before last.ckpt was written every epoch: ``ckpt_path=last``
    takes ``epoch_NNNN.ckpt`` (the best-epoch save) and goes on after that epoch."""
    base = cnn_overrides(hills_survey, tmp_path) + ["trainer.max_epochs=3"]
    full, part = tmp_path / "full", tmp_path / "part"
    m_full = _run(base, full)
    _run(base, part, monkeypatch, kill_at_epoch=2)
    (part / "checkpoints" / "last.ckpt").unlink()
    (best,) = (part / "checkpoints").glob("epoch_*.ckpt")
    epoch = torch.load(best, weights_only=True)["epoch"]  # saved at that epoch's end
    with caplog.at_level("INFO", logger="sss2bathy.train"):
        m_part = _run(base + ["ckpt_path=last"], part)
    assert f"resuming from {best} at epoch {epoch + 1}" in caplog.text
    _assert_same_run(full, part, m_full, m_part)


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
class SignalAt(pl.Callback):
    """Sends this process ``sig`` after optimizer step ``at`` (mid-epoch), as a scheduler or
    Ctrl+C would."""

    def __init__(self, at: int, sig: signal.Signals) -> None:
        self.at, self.sig = at, sig

    def on_train_batch_end(self, trainer, pl_module, outputs, batch, batch_idx):
        if trainer.global_step == self.at:
            os.kill(os.getpid(), self.sig)


@pytest.mark.parametrize(
    "task, sig", [("siren", signal.SIGTERM), ("siren", signal.SIGINT), ("cnn", signal.SIGTERM)]
)
def test_signal_mid_epoch_saves_exits_with_the_signal_status_and_resumes_exactly(
    tmp_path, plane_survey, hills_survey, monkeypatch, capsys, caplog, task, sig
):
    # the signal after the second step of epoch 1 (SIREN: 5 steps an epoch, CNN: 11):
    # last.ckpt is saved at that batch end (the default callbacks alone would have only
    # epoch 0's), the fit ends with 128 + the signal's number and one stderr line saying
    # how to resume
    base = _task_overrides(task, plane_survey, hills_survey, tmp_path) + ["trainer.max_epochs=3"]
    at = 7 if task == "siren" else 13
    full, part = tmp_path / "full", tmp_path / "part"
    maps = {d: [f"model.output_dir={d / 'map'}"] if task != "cnn" else [] for d in (full, part)}
    m_full = _run(base + maps[full], full)
    original = instantiate_module.instantiate_callbacks
    monkeypatch.setattr(
        instantiate_module, "instantiate_callbacks", lambda c: original(c) + [SignalAt(at, sig)]
    )
    previous = signal.getsignal(signal.SIGINT)
    capsys.readouterr()
    with pytest.raises(SystemExit) as stop:
        train(compose_run(base + maps[part], part), part)
    monkeypatch.undo()
    assert stop.value.code == 128 + sig
    assert signal.getsignal(signal.SIGINT) is previous  # the SIGINT handler is given back
    last = part / "checkpoints" / "last.ckpt"
    (line,) = [ln for ln in capsys.readouterr().err.splitlines() if ln.strip()]
    assert line == (
        f"interrupted by {sig.name} at epoch 1, step {at}: saved {last}; resume with the same "
        f"command and ckpt_path=last hydra.run.dir={part}"
    )
    assert torch.load(last, weights_only=True)["global_step"] == at
    assert not (part / "run.lock").exists()
    with caplog.at_level("INFO", logger="sss2bathy.train"):
        m_part = _run(base + maps[part] + ["ckpt_path=last"], part)
    assert f"resuming from {last} at epoch 1 (step {at})" in caplog.text
    _assert_same_run(full, part, m_full, m_part)


def _cli(args: list[str], env: dict) -> subprocess.Popen:
    return subprocess.Popen(
        [sys.executable, "-m", "sss2bathy.cli.train", *args],
        cwd=ROOT,
        env=env,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )


def _cli_overrides(task: str, plane_survey: Path, hills_survey: Path, tmp: Path) -> list[str]:
    """Long enough to be stopped while it runs (tiny epochs take well under a second)."""
    if task == "siren":
        return siren_overrides(plane_survey, tmp) + ["trainer.max_epochs=40"]
    return cnn_overrides(hills_survey, tmp) + ["trainer.max_epochs=12"]


def _outputs(task: str, run: Path) -> list[str]:
    return [f"hydra.run.dir={run}"] + (
        [f"model.output_dir={run / 'map'}"] if task == "siren" else []
    )


@pytest.mark.slow
@pytest.mark.parametrize("task", ["siren", "cnn"])
@pytest.mark.parametrize("sig", [signal.SIGKILL, signal.SIGTERM])
def test_cli_killed_and_resumed_in_its_run_folder(tmp_path, plane_survey, hills_survey, task, sig):
    """``sss2bathy-train ... ckpt_path=last hydra.run.dir=<the killed run's folder>`` with the
    default callbacks: SIGKILL after epoch 2 resumes at epoch >= 3; SIGTERM mid-fit exits
    143 with the resume command on stderr; both end as the uninterrupted run."""
    env = {**os.environ, "SSS2BATHY_ROOT": str(ROOT), "OMP_NUM_THREADS": "1"}
    env.pop("HYDRA_FULL_ERROR", None)
    base = _cli_overrides(task, plane_survey, hills_survey, tmp_path)
    full, part = tmp_path / "full", tmp_path / "part"
    proc = _cli(base + _outputs(task, full), env)
    assert proc.wait(timeout=600) == 0, proc.stderr.read()
    proc = _cli(base + _outputs(task, part), env)
    last = part / "checkpoints" / "last.ckpt"
    deadline = time.time() + 300
    while time.time() < deadline and proc.poll() is None:
        # atomic saves: last.ckpt is always whole, never read half-written
        if last.is_file() and torch.load(last, weights_only=True)["epoch"] >= 2:
            break
        time.sleep(0.02)
    assert proc.poll() is None, "the run ended before it could be killed"
    proc.send_signal(sig)
    err = proc.communicate(timeout=300)[1]
    ckpt = torch.load(last, weights_only=True)
    progress = ckpt["loops"]["fit_loop"]["epoch_progress"]["current"]["processed"]
    assert progress >= 3 if sig == signal.SIGKILL else progress >= 2
    if sig == signal.SIGKILL:
        assert proc.returncode == -signal.SIGKILL and (part / "run.lock").is_file()
    else:
        assert proc.returncode == 143, err
        (line,) = [ln for ln in err.splitlines() if ln.startswith("interrupted")]
        assert line.startswith("interrupted by SIGTERM at epoch ") and line.endswith(
            f"ckpt_path=last hydra.run.dir={part}"
        )
        assert "Traceback" not in err and not (part / "run.lock").exists()
    proc = _cli(base + _outputs(task, part) + ["ckpt_path=last"], env)
    out, err = proc.communicate(timeout=600)
    assert proc.returncode == 0, err
    assert f"resuming from {last} at epoch {progress} (step {ckpt['global_step']})" in out, out
    if sig == signal.SIGKILL:  # the killed run's lock is stale: taken over with a warning
        assert "taking over the stale lock of pid" in out
    metrics = [json.loads((d / "metrics.json").read_text()) for d in (full, part)]
    assert metrics[0] == metrics[1] and metrics[0]
    if task == "siren":
        maps = [np.load(d / "map" / "map.npz", allow_pickle=False)["heights"] for d in (full, part)]
        np.testing.assert_array_equal(maps[0], maps[1])
