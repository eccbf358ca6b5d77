"""MetricCurve: one CSV row per evaluation, training clock excludes validation."""

from __future__ import annotations

import math
import time

import pytest
import pytorch_lightning as pl
import torch
from torch.utils.data import DataLoader, TensorDataset

from sss2bathy.callbacks.curve import MetricCurve, read_curve, write_curve


class _Toy(pl.LightningModule):
    def __init__(self, val_sleep: float = 0.0) -> None:
        super().__init__()
        self.w = torch.nn.Parameter(torch.tensor(3.0))
        self.val_sleep = val_sleep

    def training_step(self, batch, batch_idx):
        return (self.w - 1.0) ** 2

    def validation_step(self, batch, batch_idx):
        time.sleep(self.val_sleep)
        self.log("val/err", (self.w.detach() - 1.0).abs())

    def configure_optimizers(self):
        return torch.optim.SGD(self.parameters(), lr=0.1)


def _loader():
    return DataLoader(TensorDataset(torch.zeros(4, 1)), batch_size=1)


def _fit(tmp_path, callback, module, epochs=3):
    trainer = pl.Trainer(
        max_epochs=epochs,
        callbacks=[callback],
        logger=False,
        enable_checkpointing=False,
        enable_progress_bar=False,
        enable_model_summary=False,
        num_sanity_val_steps=0,
        default_root_dir=tmp_path,
    )
    trainer.fit(module, _loader(), _loader())
    return trainer


def test_one_row_per_evaluation_and_the_error_falls(tmp_path):
    curve = MetricCurve(dirpath=tmp_path)
    _fit(tmp_path, curve, _Toy())
    rows = read_curve(tmp_path / "metric_curve.csv")
    assert [int(r["epoch"]) for r in rows] == [0, 1, 2]
    assert [int(r["step"]) for r in rows] == [4, 8, 12]
    errs = [r["val/err"] for r in rows]
    assert errs[0] > errs[1] > errs[2] > 0
    assert all(r["lr"] == pytest.approx(0.1) for r in rows)
    walls = [r["wall_s"] for r in rows]
    assert walls == sorted(walls) and walls[0] > 0


def test_training_clock_excludes_validation(tmp_path):
    curve = MetricCurve(dirpath=tmp_path)
    _fit(tmp_path, curve, _Toy(val_sleep=0.05), epochs=2)
    rows = read_curve(tmp_path / "metric_curve.csv")
    # 4 validation batches x 50 ms per epoch are in wall_s, not in train_s
    gap = rows[-1]["wall_s"] - rows[-1]["train_s"]
    assert gap >= 2 * 4 * 0.05 * 0.9


def test_round_trip_and_bad_files(tmp_path):
    rows = [
        {"epoch": 0, "step": 5, "wall_s": 1.5, "train_s": 1.0, "lr": 1e-3, "val/map_mae_m": 0.2}
    ]
    rows.append({**rows[0], "epoch": 1, "val/cs": 0.9})
    write_curve(tmp_path / "c.csv", rows)
    back = read_curve(tmp_path / "c.csv")
    assert back[1]["val/cs"] == 0.9 and math.isnan(back[0]["val/cs"])
    (tmp_path / "bad.csv").write_text("epoch,step\n0,1\n")
    with pytest.raises(ValueError, match="missing \\['wall_s', 'train_s', 'lr'\\]"):
        read_curve(tmp_path / "bad.csv")
    (tmp_path / "nan.csv").write_text("epoch,step,wall_s,train_s,lr\n0,1,x,1,1\n")
    with pytest.raises(ValueError, match="line 2, column 'wall_s'"):
        read_curve(tmp_path / "nan.csv")
    with pytest.raises(ValueError, match="filename"):
        MetricCurve(filename="curve.txt")
