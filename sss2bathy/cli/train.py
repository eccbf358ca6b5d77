"""``sss2bathy-train``: fit (and test) the model a config composes.

sss2bathy-train experiment=cnn scale=demo
sss2bathy-train -m experiment=siren_gt_n2d model.w_height=0.1,1,10 seed=1,2
"""

from __future__ import annotations

import contextlib
import logging
import math
import os
import shutil
import sys
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import hydra
from omegaconf import DictConfig, OmegaConf

from sss2bathy.cli._common import (
    apply_extras,
    hydra_entry,
    log_config,
    one_line,
    setup_environment,
    write_run_record,
)

log = logging.getLogger("sss2bathy.train")

# what a run without MBES is scored by when its optimized_metric was not logged
HOLDOUT_METRIC = "val/holdout_alt_mae_m"


@dataclass
class FitResult:
    """What :func:`fit` returns: the final metrics and whether the data had an MBES grid."""

    metrics: dict[str, Any]
    has_mbes: bool


def optimized_value(
    name: str | None, metrics: Mapping[str, Any], has_mbes: bool
) -> tuple[str | None, float | None]:
    """``(metric name, value)`` to return to a sweeper for ``optimized_metric=name``.

    The configured metric when it was logged. A run without MBES (the sidescan-only route:
    no ``val/map_mae_m``) falls back to the held-out altimeter MAE (:data:`HOLDOUT_METRIC`) with a
    WARNING, or to ``(None, None)`` with a WARNING when that was not logged either (no
    held-out points). A run with MBES that did not log its metric is a configuration error.
    """
    if not name:
        return None, None
    if name in metrics:
        return name, float(metrics[name])
    if has_mbes:
        raise KeyError(f"optimized_metric '{name}' was not logged; logged: {sorted(metrics)}")
    fallback = metrics.get(HOLDOUT_METRIC)
    if fallback is not None and math.isfinite(float(fallback)):
        log.warning(
            "optimized_metric '%s' was not logged (no MBES grid); returning %s = %.4f instead",
            name,
            HOLDOUT_METRIC,
            float(fallback),
        )
        return HOLDOUT_METRIC, float(fallback)
    log.warning(
        "optimized_metric '%s' was not logged (no MBES grid) and neither was %s "
        "(no held-out altimeter points: data.holdout); returning none",
        name,
        HOLDOUT_METRIC,
    )
    return None, None


def train(cfg: DictConfig, run_dir: Path | None = None) -> dict[str, Any]:
    """Instantiate datamodule, model, callbacks, loggers and trainer from ``cfg``; fit; test.

    Returns the final metrics (``trainer.callback_metrics`` after fit and test).
    """
    return fit(cfg, run_dir).metrics


@dataclass
class Run:
    """What :func:`instantiate_run` builds from a composed config."""

    datamodule: Any
    model: Any
    callbacks: list
    loggers: list
    trainer: Any


def _resolved(cfg: DictConfig, key: str) -> Any:
    """``cfg[key]`` with every interpolation resolved into plain containers, still under
    ``key`` (so constructor errors name the full config key); None stays None.

    OmegaConf cannot resolve *in place* an interpolation to a survey preset whose keys fall
    back to list literals (``${oc.select:key,[a, b]}``): the CNN's ``data.test_surveys``
    entries at ``scale=paper`` (and the run hyper-parameters that copy them) failed with
    "Value 'list' is not a supported primitive type". ``to_container(resolve=True)`` has no
    such limit.
    """
    node = cfg.get(key)
    if node is None:
        return None
    return OmegaConf.create({key: OmegaConf.to_container(node, resolve=True)})[key]


def instantiate_run(cfg: DictConfig, run_dir: Path | None = None) -> Run:
    """Datamodule, model, callbacks, loggers and trainer of ``cfg``, before any heavy work.

    The data modules make and load their data in ``prepare_data`` / ``setup``, so this runs
    every constructor's own argument checks before any data is made; a constructor's
    ``ValueError`` (``<argument>: expected ..., found ...``) becomes a
    :class:`~sss2bathy.config_validation.ConfigError` naming the config key
    (:func:`~sss2bathy.config_validation.instantiate_group`).
    """
    import pytorch_lightning as pl

    from sss2bathy.cli.instantiate import instantiate_callbacks, instantiate_loggers
    from sss2bathy.config_validation import instantiate_group

    # deterministic=true: torch.use_deterministic_algorithms(True, warn_only=True) through
    # Lightning (which also sets cuDNN and cuBLAS up for it)
    determinism = {"deterministic": "warn"} if cfg.get("deterministic") else {}
    datamodule = instantiate_group(
        "data", lambda: hydra.utils.instantiate(_resolved(cfg, "data"), _recursive_=False), cfg
    )
    model = instantiate_group(
        "model",
        lambda: hydra.utils.instantiate(cfg.model, _recursive_=True, _convert_="partial"),
        cfg,
    )
    callbacks = instantiate_group(
        "callbacks", lambda: instantiate_callbacks(_resolved(cfg, "callbacks")), cfg
    )
    loggers = instantiate_group("logger", lambda: instantiate_loggers(cfg.get("logger")), cfg)
    from sss2bathy.callbacks import MetricCurve

    for c in callbacks:
        if isinstance(c, MetricCurve) and c.dirpath is None and run_dir is not None:
            c.dirpath = Path(run_dir)  # metric_curve.csv next to the run's other outputs
    if not loggers:
        # a learning-rate monitor has nothing to write to without a logger (and Lightning
        # refuses the combination): drop it rather than fail `logger=none` runs
        callbacks = [c for c in callbacks if not isinstance(c, pl.callbacks.LearningRateMonitor)]
    trainer = instantiate_group(
        "trainer",
        lambda: hydra.utils.instantiate(
            cfg.trainer,
            callbacks=callbacks,
            logger=loggers or False,
            _convert_="partial",
            **determinism,
        ),
        cfg,
    )
    # every checkpoint to a temporary name, then renamed: never a truncated last.ckpt
    from sss2bathy.callbacks import use_atomic_checkpoints

    use_atomic_checkpoints(trainer)
    return Run(datamodule, model, callbacks, loggers, trainer)


def module_kind(model: Any) -> str | None:
    """The :func:`~sss2bathy.utils.checkpoints.checkpoint_kind` the checkpoints of
    ``model`` have (None for another module)."""
    from sss2bathy.models.lambertian import LambertianSensorModel
    from sss2bathy.modules.normal_cnn import NormalCNNModule
    from sss2bathy.modules.siren import SirenModule
    from sss2bathy.utils.checkpoints import KIND_CNN, KIND_LAMBERT, KIND_SIREN

    if isinstance(model, NormalCNNModule):
        return KIND_CNN
    if isinstance(model, SirenModule):
        lambert = isinstance(getattr(model, "sensor", None), LambertianSensorModel)
        return KIND_LAMBERT if lambert else KIND_SIREN
    return None


def check_checkpoints(cfg: DictConfig, model: Any, ckpt_path: str | None) -> None:
    """Read the checkpoints a run will load before any data is made: ``ckpt_path`` must be
    a checkpoint of the module being trained, ``data.normals.checkpoint`` (a file) a CNN's.
    Each problem is one line naming the key, the file and what it holds; a resume logs
    where it starts ("resuming from <path> at epoch k (step s)")."""
    from sss2bathy.utils.checkpoints import expect_kind, read_checkpoint, resume_position

    cnn = OmegaConf.select(cfg, "data.normals.checkpoint")
    if OmegaConf.select(cfg, "data.normals.source") == "cnn" and cnn not in (None, "", "latest"):
        from sss2bathy.data.cnn_normals import check_cnn_model  # .ckpt, .safetensors, pretrained

        check_cnn_model(cnn, "data.normals.checkpoint")
    if ckpt_path is None:
        return
    ckpt = read_checkpoint(ckpt_path, "ckpt_path")
    kind = module_kind(model)
    if kind is not None:
        expect_kind(ckpt, ckpt_path, "ckpt_path", kind)
    if cfg.get("train", True):
        epoch, step = resume_position(ckpt)
        log.info("resuming from %s at epoch %d (step %d)", ckpt_path, epoch, step)
    else:
        log.info("testing the checkpoint %s (epoch %d)", ckpt_path, int(ckpt.get("epoch", 0)))


def _rank_zero_process() -> bool:
    """Not a rank > 0 of a distributed launch (torchrun, srun, Lightning's DDP launcher),
    which shares rank 0's run folder."""
    return all(
        os.environ.get(var, "0") in ("", "0")
        for var in ("RANK", "LOCAL_RANK", "NODE_RANK", "GROUP_RANK", "SLURM_PROCID")
    )


def run_folder_lock(run_dir: Path | None) -> contextlib.AbstractContextManager:
    """The run folder's lock (:func:`~sss2bathy.utils.atomic.folder_lock`): a second fit
    into a folder another live fit is writing refuses at once (one line)."""
    from sss2bathy.utils.atomic import folder_lock

    if run_dir is None or not _rank_zero_process():
        return contextlib.nullcontext()
    return folder_lock(run_dir)


def _state_dict_mismatch(err: RuntimeError, ckpt_path: str | None) -> ValueError | None:
    """A one-line error for a checkpoint whose weights do not fit the model, else None."""
    text = str(err)
    if ckpt_path is None or not text.startswith("Error(s) in loading state_dict"):
        return None
    detail = one_line(text.split(":", 1)[1] if ":" in text else text)
    if len(detail) > 200:
        detail = detail[:200] + " ..."
    return ValueError(
        f"ckpt_path: {ckpt_path} holds weights of another model configuration ({detail}); "
        "resume it with the experiment and model settings it was trained with"
    )


def report_interruption(trainer: Any, run_dir: Path | None) -> SystemExit:
    """Print the one stderr line of a fit stopped by SIGTERM / SIGINT (what was saved and
    how to resume) and return the ``SystemExit`` with the signal's shell status (143 /
    130)."""
    from sss2bathy.callbacks import interruption

    what = interruption(trainer)
    where = f"epoch {what.epoch}, step {what.step}"
    if what.checkpoint is None:
        saved = "no checkpoint was written"
    elif what.saved_now:
        saved = f"saved {what.checkpoint}"
    else:
        saved = f"the newest save {what.checkpoint} resumes it"
    folder = run_dir if run_dir is not None else "<run folder>"
    entry = _hydra_config_name()
    if what.checkpoint is None:
        how = "rerun the same command to start over"
    elif entry in (None, "train"):
        how = f"resume with the same command and ckpt_path=last hydra.run.dir={folder}"
    else:  # sss2bathy-map composes its fit's config itself and takes no ckpt_path
        how = f"sss2bathy-{entry} does not resume a fit: rerun it to start over"
    print(f"interrupted by {what.signal} at {where}: {saved}; {how}", file=sys.stderr, flush=True)
    return SystemExit(what.exit_code)


def _hydra_config_name() -> str | None:
    """The primary config of the running Hydra job (``train``, ``map``), None outside one."""
    try:
        from hydra.core.hydra_config import HydraConfig

        return str(HydraConfig.get().job.config_name)
    except (ValueError, ImportError, AttributeError):
        return None


def _fresh_tensorboard_dirs(loggers: list) -> list[Path]:
    """The ``log_dir`` of each TensorBoard logger that does not exist yet: this run's own,
    safe to remove (a resumed run's earlier event files are not)."""
    from pytorch_lightning.loggers import TensorBoardLogger

    dirs = [Path(lg.log_dir) for lg in loggers if isinstance(lg, TensorBoardLogger)]
    return [d for d in dirs if not d.exists()]


def fit(
    cfg: DictConfig, run_dir: Path | None = None, on_checked: Callable[[], None] | None = None
) -> FitResult:
    """:func:`train`, also saying whether the datamodule had an MBES grid (``grid``; data
    modules without that attribute, the CNN's, always train on MBES). ``on_checked`` runs
    once every start-up check passed (the run instantiated), before any data is made."""
    # the cross-key rules, then every constructor's own checks: all before any data is made
    from sss2bathy.config_validation import validate_config

    validate_config(cfg)
    with run_folder_lock(run_dir):
        return _fit(cfg, run_dir, on_checked)


def _fit(cfg: DictConfig, run_dir: Path | None, on_checked: Callable[[], None] | None) -> FitResult:
    import pytorch_lightning as pl
    from pytorch_lightning.utilities.exceptions import SIGTERMException
    from pytorch_lightning.utilities.model_helpers import is_overridden

    from sss2bathy.cli.instantiate import resolve_ckpt_path

    if cfg.get("torch_threads"):  # the entry point's start applied the policy's default
        from sss2bathy.utils.threads import apply_thread_policy

        apply_thread_policy(int(cfg.torch_threads), announce=False)
    # seeds torch, numpy, Python and (via PL_SEED_WORKERS) data-loader workers; the data
    # modules draw batches from their own generators seeded by data.seed (= seed)
    pl.seed_everything(cfg.seed, workers=True)
    run = instantiate_run(cfg, run_dir)
    datamodule, model, trainer = run.datamodule, run.model, run.trainer
    ckpt_path = resolve_ckpt_path(cfg.get("ckpt_path"), run_dir)
    check_checkpoints(cfg, model, ckpt_path)
    if on_checked is not None:
        on_checked()
    metrics: dict[str, Any] = {}
    fresh_dirs = _fresh_tensorboard_dirs(run.loggers)
    try:
        if cfg.get("train", True):
            # checkpoints hold tensors and plain values only: no pickled code runs on resume
            trainer.fit(model=model, datamodule=datamodule, ckpt_path=ckpt_path, weights_only=True)
            metrics.update(trainer.callback_metrics)
        if cfg.get("test", True) and is_overridden("test_step", model):
            # after a fit: the weights it ended with; without one (train=false): the checkpoint's
            test_ckpt = None if cfg.get("train", True) else ckpt_path
            trainer.test(
                model=model,
                datamodule=datamodule,
                ckpt_path=test_ckpt,
                weights_only=True,
                verbose=False,  # callbacks.writers.MetricsTableLogger prints full names
            )
            metrics.update(trainer.callback_metrics)
    except BaseException as err:
        if trainer.global_step == 0:
            # failed before its first step (e.g. in the data module's setup): TensorBoard
            # would list an empty run; the run folder keeps its log
            for folder in fresh_dirs:
                shutil.rmtree(folder, ignore_errors=True)
        if isinstance(err, SIGTERMException):
            # Lightning's graceful stop on SIGTERM (or LastCheckpoint's on SIGINT) ends
            # with SystemExit(None), status 0: say what was saved, exit 143 / 130
            raise report_interruption(trainer, run_dir) from None
        if isinstance(err, RuntimeError):
            mismatch = _state_dict_mismatch(err, ckpt_path)
            if mismatch is not None:
                raise mismatch from None
        raise
    final = getattr(model, "final_metrics", None)
    if isinstance(final, dict):
        metrics.update(final)
    if run_dir is not None and trainer.is_global_zero:
        write_run_record(run_dir, cfg, metrics)
    has_mbes = getattr(datamodule, "grid", True) is not None
    return FitResult(metrics, has_mbes)


setup_environment()


@hydra_entry("train")
def main(cfg: DictConfig) -> float | None:
    from hydra.core.hydra_config import HydraConfig

    # the config dump waits for the constructors' checks: a bad value is one line before it;
    # fit validates the config (once)
    apply_extras(cfg, print_config=False, validate=False)
    run_dir = Path(HydraConfig.get().runtime.output_dir)
    result = fit(cfg, run_dir, on_checked=lambda: log_config(cfg))
    # evaluation-only runs (train=false) have no optimised metric to return
    if not cfg.get("train", True):
        return None
    return optimized_value(cfg.get("optimized_metric"), result.metrics, result.has_mbes)[1]


if __name__ == "__main__":
    main()
