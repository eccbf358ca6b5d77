"""NonFiniteGuard: a non-finite loss or gradient skips the step (weights and Adam state
unchanged), is counted and logged, and N in a row abort the run with a clear message."""

from __future__ import annotations

import math

import numpy as np
import pytest
import pytorch_lightning as pl
import torch
from reliability_helpers import cnn_overrides, compose_run, siren_overrides
from torch import nn
from torch.utils.data import DataLoader

from sss2bathy.callbacks.guard import NonFiniteGuard, NonFiniteTrainingError
from sss2bathy.cli.train import train
from sss2bathy.data.pings import PingBatches
from sss2bathy.data.windows import SidescanWindowDataset


class Line(pl.LightningModule):
    """``y = w x + b`` fitted to zero; chosen steps get a NaN loss or a NaN gradient."""

    def __init__(self, nan_loss=(), nan_grad=()) -> None:
        super().__init__()
        self.lin = nn.Linear(3, 1)
        self.nan_loss, self.nan_grad = set(nan_loss), set(nan_grad)

    def training_step(self, batch, batch_idx):
        loss = self.lin(batch).pow(2).mean()
        if self.global_step in self.nan_loss:
            loss = loss * math.nan
        if self.global_step in self.nan_grad:
            # finite value, NaN gradient (the sqrt branch is not taken but differentiated)
            loss = torch.where(torch.tensor(True), loss, torch.sqrt(-loss - 1.0))
        return loss

    def configure_optimizers(self):
        return torch.optim.Adam(self.parameters(), lr=0.1)


class Recorder(pl.Callback):
    """Weights and Adam state before and after every step."""

    def __init__(self) -> None:
        self.steps: list[tuple[dict, dict, dict, dict]] = []

    @staticmethod
    def _snap(pl_module, trainer):
        weights = {k: v.detach().clone() for k, v in pl_module.state_dict().items()}
        opt = trainer.optimizers[0].state_dict()["state"]
        moments = {k: {n: t.clone() for n, t in s.items()} for k, s in opt.items()}
        return weights, moments

    def on_train_batch_start(self, trainer, pl_module, batch, batch_idx):
        self._before = self._snap(pl_module, trainer)

    def on_train_batch_end(self, trainer, pl_module, outputs, batch, batch_idx):
        self.steps.append((*self._before, *self._snap(pl_module, trainer)))


def _fit(module, guard, n_batches=6):
    recorder = Recorder()
    data = DataLoader(torch.randn(n_batches * 4, 3, generator=torch.Generator().manual_seed(0)), 4)
    trainer = pl.Trainer(
        max_epochs=1,
        accelerator="cpu",
        logger=False,
        enable_checkpointing=False,
        enable_progress_bar=False,
        enable_model_summary=False,
        callbacks=[guard, recorder],
    )
    trainer.fit(module, data)
    return trainer, recorder


def _same(a: dict, b: dict) -> bool:
    return a.keys() == b.keys() and all(torch.equal(a[k], b[k]) for k in a)


def test_nonfinite_steps_are_skipped_counted_and_logged(caplog):
    guard = NonFiniteGuard(max_consecutive=3)
    trainer, rec = _fit(Line(nan_loss={1, 2}, nan_grad={4}), guard)
    assert guard.skipped == 3 and guard.consecutive == 0
    assert float(trainer.callback_metrics["train/skipped_nonfinite"]) == 3.0
    for step, (w0, m0, w1, m1) in enumerate(rec.steps):
        assert all(torch.isfinite(v).all() for v in w1.values())
        if step in (1, 2, 4):
            # no update at all: weights, Adam moments and step counts as before
            assert _same(w0, w1)
            assert all(_same(m0[k], m1[k]) for k in m0)
        else:
            assert not _same(w0, w1)
    assert "non-finite loss nan" in caplog.text and "gradient of 'lin." in caplog.text


def test_consecutive_nonfinite_steps_abort_with_the_key_named():
    guard = NonFiniteGuard(max_consecutive=3)
    with pytest.raises(NonFiniteTrainingError, match=r"3 consecutive .*max_consecutive_nonfinite"):
        _fit(Line(nan_loss={2, 3, 4, 5}), guard)
    assert guard.skipped == 3
    with pytest.raises(ValueError, match="max_consecutive"):
        NonFiniteGuard(max_consecutive=0)


def test_guard_counters_survive_a_checkpoint():
    guard = NonFiniteGuard(max_consecutive=5)
    guard.skipped, guard.consecutive = 4, 2
    again = NonFiniteGuard(max_consecutive=5)
    again.load_state_dict(guard.state_dict())
    assert (again.skipped, again.consecutive) == (4, 2)


def test_cnn_batch_with_nan_intensities_is_skipped(tmp_path, hills_survey, monkeypatch):
    original = SidescanWindowDataset.__getitem__

    def poisoned(self, item):
        out = original(self, item)
        if self.flip_augment and item % 7 == 3:  # some training windows
            out["intensity"] = torch.full_like(out["intensity"], math.nan)
            if "inputs" in out:  # the network's input channels (intensity first)
                out["inputs"] = torch.full_like(out["inputs"], math.nan)
        return out

    monkeypatch.setattr(SidescanWindowDataset, "__getitem__", poisoned)
    run = tmp_path / "run"
    metrics = train(compose_run(cnn_overrides(hills_survey, tmp_path), run), run)
    assert metrics["train/skipped_nonfinite"] >= 1
    state = torch.load(run / "checkpoints" / "last.ckpt", weights_only=True)["state_dict"]
    assert all(torch.isfinite(v).all() for v in state.values())
    assert np.isfinite(metrics["val/nlat_mae"])


def test_siren_with_nan_altimeter_aborts_after_n_steps(tmp_path, plane_survey, monkeypatch):
    original = PingBatches.__getitem__

    def poisoned(self, key):
        batch = original(self, key)
        batch["altimeter"] = torch.full_like(batch["altimeter"], math.nan)
        return batch

    monkeypatch.setattr(PingBatches, "__getitem__", poisoned)
    overrides = siren_overrides(plane_survey, tmp_path) + [
        "guard.max_consecutive_nonfinite=3",
        f"model.output_dir={tmp_path / 'map'}",
    ]
    run = tmp_path / "run"
    cfg = compose_run(overrides, run)
    assert cfg.callbacks.nonfinite_guard.max_consecutive == 3
    with pytest.raises(NonFiniteTrainingError, match="guard.max_consecutive_nonfinite=3"):
        train(cfg, run)
