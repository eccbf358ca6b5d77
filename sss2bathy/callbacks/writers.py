"""Callbacks that write a run's results into its folder.

* :class:`CNNTableWriter`: after testing, the Table-2-style CNN table with constant rows and
  the bias files (:mod:`sss2bathy.eval.cnn_table`);
* :class:`SirenMapExport`: at the end of a SIREN's training, the final map (``map.tif``,
  ``map.npz``, ``metrics.json``, PNGs; :func:`sss2bathy.eval.maps.save_map_outputs`); its
  metrics are the module's ``final_metrics``, which :class:`~sss2bathy.callbacks.RunHparams`
  logs with the hparams. ``map.tif`` carries its provenance as GDAL metadata
  (:func:`map_provenance`: units, vertical reference, method, CNN checkpoint SHA-256,
  version, command line).
"""

from __future__ import annotations

import logging
import math
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import pytorch_lightning as pl
import torch

from sss2bathy.callbacks.hparams import RunHparams
from sss2bathy.eval.cnn_table import (
    SIDES,
    constant_metric_keys,
    table_rows_from_metrics,
    write_cnn_bias,
    write_cnn_table,
)
from sss2bathy.eval.maps import save_map_outputs
from sss2bathy.io.export import add_geotiff_tags, provenance_tags
from sss2bathy.metrics.normal import LineSideBias, NormalMetrics, masked_mean
from sss2bathy.utils.atomic import atomic_write_text

log = logging.getLogger(__name__)


class CNNTableWriter(pl.Callback):
    """After testing, writes the Table-2-style CNN table (Markdown + CSV, the paper's numbers
    beside ours) into ``out_dir`` from the ``test/{name}/...`` metrics, with a
    constant-prediction row per test set and the per-line, per-side bias files.

    * **Constant prediction**: the mean n_lat over the valid bins of the datamodule's
      *training* lines (``datamodule.train_set.lines``, never test data), scored with the
      same metrics on every test batch's valid bins. Its metrics go to the table and, as
      ``test/{name}/constant/{metric}`` (plus ``.../value``), into the module's
      ``final_metrics`` (hence the run's ``metrics.json``); ``data/n_train_lines`` and
      ``data/n_val_lines`` are recorded too. A datamodule without training lines gets no
      constant row (a warning says so).
    * **Bias**: ``cnn_bias.csv``, ``cnn_bias_range.csv`` and ``cnn_bias.png``
      (:func:`sss2bathy.eval.cnn_table.write_cnn_bias`) from the test predictions, which
      ``test_step`` returns as ``{"pred": ...}``.

    Args:
        out_dir: the run folder.
        n_range_bins: groups of bins across track in the bias-against-range panel.

    Under DDP each rank scores its share; the constant metrics are reduced across ranks,
    the bias files hold rank 0's share.
    """

    def __init__(self, out_dir: str | Path, n_range_bins: int = 16) -> None:
        if not isinstance(n_range_bins, int) or isinstance(n_range_bins, bool) or n_range_bins < 1:
            raise ValueError(f"n_range_bins: expected an integer >= 1, found {n_range_bins!r}")
        self.out_dir = Path(out_dir)
        self.n_range_bins = n_range_bins
        self.paths: tuple[Path, Path] | None = None
        self.bias_paths: tuple[Path, Path, Path] | None = None
        self.constant: float | None = None
        self._const_metrics: dict[int, Any] = {}
        self._bias: dict[int, Any] = {}

    @staticmethod
    def training_lines(trainer: pl.Trainer) -> list[Any] | None:
        """The datamodule's training lines (``train_set.lines``, set up for ``fit`` if the
        run only tests), or None when the datamodule has none."""
        dm = getattr(trainer, "datamodule", None)
        if dm is None or not hasattr(dm, "train_set"):
            return None
        if dm.train_set is None:
            log.info("CNN table: setting the training lines up for the constant prediction")
            dm.setup("fit")
        lines = getattr(dm.train_set, "lines", None)
        return list(lines) if lines else None

    def on_test_start(self, trainer: pl.Trainer, pl_module: pl.LightningModule) -> None:
        self._const_metrics, self._bias = {}, {}
        lines = self.training_lines(trainer)
        if lines is None:
            self.constant = None
            log.warning(
                "CNN table: the datamodule has no training lines (train_set.lines); "
                "no constant-prediction row"
            )
            return
        self.constant = masked_mean([ln.n_lat for ln in lines], [ln.valid for ln in lines])
        log.info("CNN table: constant prediction = training mean n_lat %+.5f", self.constant)

    def on_test_batch_end(
        self,
        trainer: pl.Trainer,
        pl_module: pl.LightningModule,
        outputs: Any,
        batch: Mapping[str, torch.Tensor],
        batch_idx: int,
        dataloader_idx: int = 0,
    ) -> None:
        if self.constant is not None:
            if dataloader_idx not in self._const_metrics:
                self._const_metrics[dataloader_idx] = NormalMetrics().to(pl_module.device)
            target = batch["n_lat"]
            const = torch.full_like(target, self.constant)
            self._const_metrics[dataloader_idx].update(const, target, batch["mask"])
        if not isinstance(outputs, Mapping) or "pred" not in outputs:
            raise ValueError(
                "test_step outputs: expected a dict with the predictions under 'pred' "
                f"(for the bias files), found {type(outputs).__name__}"
            )
        for key in ("line", "side", "bin_start"):
            if key not in batch:
                raise ValueError(f"batch: missing key '{key}' (for the bias files)")
        acc = self._bias.setdefault(dataloader_idx, LineSideBias())
        acc.update(
            outputs["pred"], batch["n_lat"], batch["mask"],
            batch["line"], batch["side"], batch["bin_start"],
        )  # fmt: skip

    def _line_names(self, trainer: pl.Trainer, idx: int) -> list[str] | None:
        sets = getattr(getattr(trainer, "datamodule", None), "test_sets", None)
        if sets is not None and idx < len(sets):
            names = getattr(sets[idx], "line_names", None)
            return list(names) if names is not None else None
        return None

    def _bias_rows(self, pl_module: pl.LightningModule) -> tuple[list, list]:
        line_rows, range_rows = [], []
        for idx in sorted(self._bias):
            name = pl_module.test_set_name(idx) or "test"
            names = self._line_names(pl_module.trainer, idx)
            acc = self._bias[idx]
            for r in acc.line_side_rows():
                line = names[r["line"]] if names else f"line_{r['line']}"
                line_rows.append({**r, "dataset": name, "line": line, "side": SIDES[r["side"]]})
            for r in acc.range_rows(self.n_range_bins):
                range_rows.append({**r, "dataset": name, "side": SIDES[r["side"]]})
        return line_rows, range_rows

    def on_test_end(self, trainer: pl.Trainer, pl_module: pl.LightningModule) -> None:
        # computed on every rank: the metrics' compute() reduces across DDP processes
        constant_rows = {}
        for idx in sorted(self._const_metrics):
            name = pl_module.test_set_name(idx) or "test"
            row = {k: float(v) for k, v in self._const_metrics[idx].compute().items()}
            constant_rows[name] = {**row, "value": float(self.constant)}
        if not trainer.is_global_zero:
            return
        final = getattr(pl_module, "final_metrics", None)
        if isinstance(final, dict):
            for name, row in constant_rows.items():
                final.update(constant_metric_keys(name, row))
            dm = getattr(trainer, "datamodule", None)
            for key in ("train_lines", "val_lines"):
                if getattr(dm, key, None):
                    final[f"data/n_{key}"] = float(len(getattr(dm, key)))
        rows = table_rows_from_metrics(trainer.callback_metrics)
        if not rows:
            log.warning("CNN table: no complete test/<name>/<metric> set was logged; not written")
            return
        if any(not math.isfinite(v) for row in rows.values() for v in row.values()):
            log.warning("CNN table: some test metrics are not finite (no valid pixel?)")
        constant_rows = {k: v for k, v in constant_rows.items() if k in rows}
        self.paths = write_cnn_table(rows, self.out_dir, constant_rows or None)
        log.info("CNN table written to %s", self.paths[0])
        line_rows, range_rows = self._bias_rows(pl_module)
        if line_rows:
            self.bias_paths = write_cnn_bias(line_rows, range_rows, self.out_dir)
            log.info("CNN bias per line and side written to %s", self.bias_paths[0])


class SirenMapExport(pl.Callback):
    """At the end of a SIREN's training (rank 0, ``on_train_end``: before every callback's
    ``on_fit_end``): the module's final map
    (:meth:`~sss2bathy.modules.siren.SirenModule.final_map`) written by
    :func:`~sss2bathy.eval.maps.save_map_outputs` into ``out_dir``.

    Args:
        out_dir: the folder; ``None`` = the first logger's ``save_dir`` (the Hydra run
            folder), else the trainer's ``default_root_dir``.
    """

    def __init__(self, out_dir: str | Path | None = None) -> None:
        self.out_dir = Path(out_dir) if out_dir else None
        self.paths: dict[str, Path] | None = None

    def folder(self, trainer: pl.Trainer) -> Path:
        if self.out_dir is not None:
            return self.out_dir
        logger = trainer.logger
        if logger is not None and getattr(logger, "save_dir", None):
            return Path(logger.save_dir)
        return Path(trainer.default_root_dir)

    def on_train_end(self, trainer: pl.Trainer, pl_module: pl.LightningModule) -> None:
        if not trainer.is_global_zero:
            return
        final = pl_module.final_map()
        summary = {"final/" + k: v for k, v in final.metrics.items() if isinstance(v, int | float)}
        summary["epochs"] = int(trainer.current_epoch)
        summary["final/map_epoch"] = final.map_epoch
        offsets = _line_offsets(pl_module)
        if offsets is not None:
            rms = float(np.sqrt(np.mean(offsets**2)))
            summary["final/line_offset_rms"] = rms
            pl_module.final_metrics["final/line_offset_rms"] = rms
        inputs = pl_module.inputs
        alt = inputs.altimeter
        self.paths = save_map_outputs(
            self.folder(trainer),
            final.pred,
            final.truth,
            final.region,
            summary,
            pl_module.map_title(),
            origin=inputs.origin,
            altimeter_xy=None if alt is None else alt[:, :2].cpu().numpy(),
            coverage=final.coverage,
        )
        add_geotiff_tags(self.paths["map_tif"], map_provenance(trainer))
        if offsets is not None:
            names = list(getattr(trainer.datamodule, "line_names", None) or [])
            self.paths["line_offsets"] = write_line_offsets(offsets, names, self.folder(trainer))
        log.info("SIREN map written to %s (%s)", self.paths["map_tif"], dict(final.metrics))


def run_experiment(trainer: pl.Trainer) -> str | None:
    """The fit's experiment (method) name: the ``run.experiment`` of its
    :class:`~sss2bathy.callbacks.RunHparams` (the config's ``task_name``), else the Hydra
    job's ``experiment`` choice, else None."""
    for callback in getattr(trainer, "callbacks", None) or []:
        if isinstance(callback, RunHparams) and callback.run.get("experiment"):
            return str(callback.run["experiment"])
    try:
        from hydra.core.hydra_config import HydraConfig

        choice = HydraConfig.get().runtime.choices.get("experiment")
        return str(choice) if choice else None
    except ValueError:  # not under a Hydra job
        return None


def cnn_checkpoint_of(datamodule: Any) -> Path | None:
    """The CNN checkpoint a datamodule's normals come from (``data.normals`` with source
    ``cnn``; ``latest`` and ``pretrained`` resolved as it resolves them), else None."""
    from sss2bathy.data.normal_source import NormalSource

    normals = getattr(datamodule, "normals", None)
    if not isinstance(normals, NormalSource) or normals.source != "cnn":
        return None
    return Path(normals.resolve().checkpoint)


def map_provenance(trainer: pl.Trainer) -> dict[str, str]:
    """``map.tif``'s provenance tags (:func:`sss2bathy.io.export.provenance_tags`): the
    method (:func:`run_experiment`), the CNN checkpoint and its SHA-256 when the normals came
    from one, and the vertical reference of the survey's kind (``xtf``: the sea surface
    through the vehicle depth)."""
    datamodule = getattr(trainer, "datamodule", None)
    survey = getattr(datamodule, "survey_cfg", None) or {}
    kind = survey.get("kind") if isinstance(survey, Mapping) else None
    ckpt = cnn_checkpoint_of(datamodule)
    return provenance_tags(
        method=run_experiment(trainer),
        cnn_checkpoint=ckpt if ckpt is not None and ckpt.is_file() else None,
        survey_kind=None if kind is None else str(kind),
    )


def _line_offsets(pl_module: pl.LightningModule) -> np.ndarray | None:
    """``(n_lines, 2)`` learned n_lat offsets of a fit's normal sensor, or None (off)."""
    sensor = getattr(pl_module, "sensor", None)
    if not getattr(sensor, "use_line_offset", False):
        return None
    return sensor.offsets().cpu().numpy().astype(np.float64)


def write_line_offsets(offsets: np.ndarray, line_names: Sequence[str], out_dir: Path) -> Path:
    """``line_offsets.csv``: the n_lat offset a SIREN-N2d fit learned for each line and side
    (``line_offset=true``; what it subtracted from the target normals)."""
    if len(line_names) != offsets.shape[0]:
        log.warning(
            "line_offsets.csv: expected %d line names (the datamodule's line_names), found %d; "
            "lines are labelled by their index",
            offsets.shape[0],
            len(line_names),
        )
        line_names = [str(i) for i in range(offsets.shape[0])]
    rows = ["line,side,offset"]
    for name, pair in zip(line_names, offsets, strict=True):
        rows += [f"{name},port,{pair[0]:.6f}", f"{name},starboard,{pair[1]:.6f}"]
    path = Path(out_dir) / "line_offsets.csv"
    atomic_write_text(path, "\n".join(rows) + "\n")
    return path


def metrics_table(metrics: Mapping[str, Any], prefix: str = "test/") -> str:
    """A plain-text table of the ``prefix`` metrics, full names (no truncation), grouped
    by test set: one row per ``<set>`` (``test/<set>/<metric>``), one column per metric."""
    rows: dict[str, dict[str, float]] = {}
    for key, value in metrics.items():
        key = str(key)
        if not key.startswith(prefix):
            continue
        head, _, metric = key[len(prefix) :].rpartition("/")
        rows.setdefault(head or "-", {})[metric] = float(value)
    if not rows:
        return ""
    columns = sorted({c for row in rows.values() for c in row})
    names = sorted(rows)
    width = max(len("test set"), *(len(n) for n in names))
    cells = {c: max(len(c), 10) for c in columns}
    lines = ["  ".join(["test set".ljust(width), *(c.rjust(cells[c]) for c in columns)])]
    for name in names:
        values = [
            (f"{rows[name][c]:.4f}" if c in rows[name] else "").rjust(cells[c]) for c in columns
        ]
        lines.append("  ".join([name.ljust(width), *values]))
    return "\n".join(lines)


class MetricsTableLogger(pl.Callback):
    """After testing (rank 0), logs every ``test/...`` metric in one table, test sets by row
    with their full names (Lightning's own table truncates long names such as
    ``test/synthetic_d1_tiny:test/...``; the CLI runs ``trainer.test(verbose=False)`` beside
    this one)."""

    def on_test_end(self, trainer: pl.Trainer, pl_module: pl.LightningModule) -> None:
        if not trainer.is_global_zero:
            return
        table = metrics_table(trainer.callback_metrics)
        if table:
            log.info("test metrics:\n%s", table)


__all__ = ["CNNTableWriter", "SirenMapExport", "MetricsTableLogger", "metrics_table"]
