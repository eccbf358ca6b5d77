"""Metric-versus-time curve of a run: ``metric_curve.csv`` in the run folder.

Every evaluation appends one row: epoch, optimizer step, wall seconds since the fit
started, *training* seconds (wall minus the time spent in validation, so runs that
evaluate at different rates stay comparable), the learning rate and every ``val/*``
metric of that evaluation. This is what the schedule study
(``python -m studies.schedule_study``) compares: how soon a schedule reaches a map error.

A module with periodic map evaluations (:class:`~sss2bathy.modules.siren.SirenModule`, every
``eval_every_n_epochs`` epochs) exposes the latest as ``latest_evaluation`` (its ``epoch``
and ``metrics``); a row is written only for an evaluation made in the current epoch. Other
modules' ``val/*`` metrics are read from the trainer's callback metrics after each
validation loop. A resumed run
appends to the rows already in the file and continues their clocks.
"""

from __future__ import annotations

import math
import time
from pathlib import Path
from typing import Any

import pytorch_lightning as pl
from pytorch_lightning.callbacks import Callback

# the file's format (also what the schedule study reads) lives in eval/
from sss2bathy.eval.metric_curve import BASE_COLUMNS, read_curve, write_curve


class MetricCurve(Callback):
    """Writes ``filename`` (CSV) with a row per evaluation (module docstring).

    Args:
        dirpath: folder of the CSV; ``None`` = the trainer's ``default_root_dir``.
        filename: CSV file name.
    """

    def __init__(self, dirpath: str | Path | None = None, filename: str = "metric_curve.csv"):
        super().__init__()
        if not isinstance(filename, str) or not filename.endswith(".csv"):
            raise ValueError(f"filename: expected a '*.csv' file name, found {filename!r}")
        self.dirpath = Path(dirpath) if dirpath is not None else None
        self.filename = filename
        self.rows: list[dict[str, Any]] = []
        self._start = 0.0
        self._offset_wall = 0.0
        self._offset_train = 0.0
        self._val_seconds = 0.0
        self._val_start: float | None = None

    @property
    def path(self) -> Path:
        if self.dirpath is None:
            raise RuntimeError("MetricCurve: no folder yet (set at fit start)")
        return self.dirpath / self.filename

    def on_fit_start(self, trainer: pl.Trainer, pl_module: pl.LightningModule) -> None:
        if self.dirpath is None:
            self.dirpath = Path(trainer.default_root_dir)
        self.rows = []
        if trainer.global_step > 0 or trainer.ckpt_path:
            self.rows = read_curve(self.path) if self.path.is_file() else []
            self.rows = [r for r in self.rows if int(r["step"]) <= trainer.global_step]
        last = self.rows[-1] if self.rows else None
        self._offset_wall = float(last["wall_s"]) if last else 0.0
        self._offset_train = float(last["train_s"]) if last else 0.0
        self._val_seconds = 0.0
        self._start = time.perf_counter()

    def on_validation_start(self, trainer: pl.Trainer, pl_module: pl.LightningModule) -> None:
        self._val_start = time.perf_counter()

    def on_validation_end(self, trainer: pl.Trainer, pl_module: pl.LightningModule) -> None:
        now = time.perf_counter()
        if self._val_start is not None:
            self._val_seconds += now - self._val_start
            self._val_start = None
        if trainer.sanity_checking or not trainer.is_global_zero:
            return
        metrics = evaluation_metrics(trainer, pl_module)
        if not metrics:
            return
        wall = now - self._start
        opt = trainer.optimizers[0] if trainer.optimizers else None
        lr = float(opt.param_groups[0]["lr"]) if opt is not None else math.nan
        row = {
            "epoch": int(trainer.current_epoch),
            "step": int(trainer.global_step),
            "wall_s": round(self._offset_wall + wall, 4),
            "train_s": round(self._offset_train + wall - self._val_seconds, 4),
            "lr": lr,
            **metrics,
        }
        self.rows.append(row)
        write_curve(self.path, self.rows)


def evaluation_metrics(trainer: pl.Trainer, pl_module: pl.LightningModule) -> dict[str, float]:
    """The ``val/*`` metrics of the current epoch's evaluation (module docstring); empty
    when a module with ``latest_evaluation`` did not evaluate this epoch."""
    if hasattr(pl_module, "latest_evaluation"):
        ev = pl_module.latest_evaluation
        if ev is None or ev.epoch != trainer.current_epoch:
            return {}
        items = ev.tags("val/")
    else:
        items = {k: v for k, v in trainer.callback_metrics.items() if k.startswith("val/")}
    out = {}
    for key, value in items.items():
        try:
            out[key] = float(value)
        except (TypeError, ValueError):
            continue
    return out


__all__ = ["BASE_COLUMNS", "MetricCurve", "evaluation_metrics", "read_curve", "write_curve"]
