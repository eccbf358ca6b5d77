"""A run's HPARAMS record: who the run is, what it was fitted with, how it ended.

:class:`RunHparams` (``conf/callbacks/default.yaml``) logs, once the fit (and the test) is
over, to every logger:

* ``run/*``: the run's identity from the config (experiment/task name, seed, scale,
  survey(s), normals source, ...) and ``run/overrides`` (the command line's overrides:
  what a sweep varies), ``run/module`` (the LightningModule class);
* the module's parameters: its ``hparams_for_log()`` when it has one (the SIREN fit: SIREN
  shape, sensor model, ``w_height``, finder, lr), else its saved hyper-parameters, flattened;
* its ``final_metrics`` (finite numbers) as scalars at the last step.

TensorBoard: the parameters go in as an hparams *session* (start and end info) without an
*experiment* summary. TensorBoard's HPARAMS tab then builds its columns from every run in
the log dir (the hparams of all sessions, the scalar tags of all of them), so CNN and SIREN
runs side by side each show their own metrics; a per-run experiment summary (what
``TensorBoardLogger.log_hyperparams(params, metrics)`` writes) would make it show one run's
columns only. Other loggers get ``log_hyperparams(params)`` and ``log_metrics(metrics)``.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from typing import Any

import pytorch_lightning as pl
from hydra.core.hydra_config import HydraConfig
from pytorch_lightning.loggers import TensorBoardLogger


def flatten(params: Mapping[str, Any], prefix: str = "") -> dict[str, Any]:
    """Nested mappings as ``a/b/c`` keys; values kept as they are."""
    out: dict[str, Any] = {}
    for key, value in params.items():
        name = f"{prefix}{key}"
        if isinstance(value, Mapping):
            out.update(flatten(value, f"{name}/"))
        else:
            out[name] = value
    return out


def plain(value: Any) -> bool | int | float | str:
    """A value TensorBoard's hparams accept: bool, int, float or str (others as ``str``)."""
    if isinstance(value, bool | int | float | str):
        return value
    if hasattr(value, "item") and getattr(value, "ndim", 1) == 0:
        return value.item()
    return str(value)


def final_scalars(metrics: Mapping[str, Any]) -> dict[str, float]:
    """The finite numeric entries of ``metrics`` as floats."""
    out = {}
    for key, value in metrics.items():
        try:
            number = float(value)
        except (TypeError, ValueError):
            continue
        if math.isfinite(number):
            out[str(key)] = number
    return out


class RunHparams(pl.Callback):
    """Logs the run's identity, the module's parameters and its final metrics (module
    docstring) at the end of the fit and of the test (rank 0).

    Args:
        run: the run's identity, e.g. ``{experiment: ${task_name}, seed: ${seed}, ...}``
            (``None`` values are logged as ``"none"``).
        overrides: the command line's overrides; ``None`` = those of the running Hydra job
            (``hydra.overrides.task``), none outside Hydra (a config composed in code).
    """

    def __init__(
        self, run: Mapping[str, Any] | None = None, overrides: Sequence[str] | None = None
    ) -> None:
        if run is not None and not isinstance(run, Mapping):
            raise ValueError(f"run: expected a mapping of names to values, found {run!r}")
        if isinstance(overrides, str):
            raise ValueError(f"overrides: expected a list of overrides, found {overrides!r}")
        self.run = dict(run or {})
        if overrides is None:
            overrides = _hydra_task_overrides()
        self.overrides = [str(o) for o in overrides or []]
        self._sessions: set[int] = set()

    def params(self, pl_module: pl.LightningModule) -> dict[str, bool | int | float | str]:
        """Everything logged as hparams (module docstring), plain values."""
        out: dict[str, Any] = {f"run/{k}": "none" if v is None else v for k, v in self.run.items()}
        out["run/overrides"] = " ".join(self.overrides) if self.overrides else "none"
        out["run/module"] = type(pl_module).__name__
        describe = getattr(pl_module, "hparams_for_log", None)
        out.update(describe() if callable(describe) else flatten(dict(pl_module.hparams)))
        return {k: plain(v) for k, v in out.items() if v is not None}

    def teardown(self, trainer: pl.Trainer, pl_module: pl.LightningModule, stage: str) -> None:
        if not trainer.is_global_zero or not trainer.loggers or stage not in ("fit", "test"):
            return
        params = self.params(pl_module)
        metrics = final_scalars(getattr(pl_module, "final_metrics", None) or {})
        for logger in trainer.loggers:
            if isinstance(logger, TensorBoardLogger):
                self._tensorboard_session(logger, params, metrics)
            else:
                logger.log_hyperparams(params)
            if metrics:
                logger.log_metrics(metrics, step=trainer.global_step)

    def _tensorboard_session(
        self, logger: TensorBoardLogger, params: dict[str, Any], metrics: dict[str, float]
    ) -> None:
        """hparams session start/end info in the run's event file, once per logger (the
        first session start info of a run is the one TensorBoard reads)."""
        from torch.utils.tensorboard.summary import hparams

        logger.hparams.update(params)  # hparams.yaml beside the event files
        if id(logger) in self._sessions:
            return
        self._sessions.add(id(logger))
        _, start, end = hparams(params, dict(metrics))
        writer = logger.experiment._get_file_writer()
        writer.add_summary(start)
        writer.add_summary(end)


def _hydra_task_overrides() -> list[str]:
    """The running Hydra job's command-line overrides, or none outside a Hydra job."""
    if not HydraConfig.initialized():
        return []
    return list(HydraConfig.get().overrides.task)


__all__ = ["RunHparams", "final_scalars", "flatten", "plain"]
