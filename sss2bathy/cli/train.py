"""``sss2bathy-train``: fit (and test) the model a config composes.

sss2bathy-train experiment=cnn scale=demo
sss2bathy-train -m experiment=siren_gt_n2d model.w_height=0.1,1,10 seed=1,2
"""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Any

import hydra
from omegaconf import DictConfig

from sss2bathy.cli._common import apply_extras, config_dir, setup_environment, write_run_record

log = logging.getLogger("sss2bathy.train")


def train(cfg: DictConfig, run_dir: Path | None = None) -> dict[str, Any]:
    """Instantiate datamodule, model, callbacks, loggers and trainer from ``cfg``; fit; test.

    Returns the final metrics (``trainer.callback_metrics`` after fit and test).
    """
    import pytorch_lightning as pl
    from pytorch_lightning.utilities.model_helpers import is_overridden

    from sss2bathy.cli.instantiate import (
        instantiate_callbacks,
        instantiate_loggers,
        resolve_ckpt_path,
    )
    from sss2bathy.config_validation import validate_config

    validate_config(cfg)
    if cfg.get("torch_threads"):
        import torch

        torch.set_num_threads(int(cfg.torch_threads))
    # seeds torch, numpy, Python and (via PL_SEED_WORKERS) data-loader workers; the data
    # modules draw batches from their own generators seeded by data.seed (= seed)
    pl.seed_everything(cfg.seed, workers=True)
    # deterministic=true: torch.use_deterministic_algorithms(True, warn_only=True) through
    # Lightning (which also sets cuDNN and cuBLAS up for it)
    determinism = {"deterministic": "warn"} if cfg.get("deterministic") else {}
    datamodule = hydra.utils.instantiate(cfg.data, _recursive_=False)
    model = hydra.utils.instantiate(cfg.model, _recursive_=True, _convert_="partial")
    callbacks = instantiate_callbacks(cfg.get("callbacks"))
    loggers = instantiate_loggers(cfg.get("logger"))
    from sss2bathy.modules.curve import MetricCurve

    for c in callbacks:
        if isinstance(c, MetricCurve) and c.dirpath is None and run_dir is not None:
            c.dirpath = Path(run_dir)  # metric_curve.csv next to the run's other outputs
    if not loggers:
        # a learning-rate monitor has nothing to write to without a logger (and Lightning
        # refuses the combination): drop it rather than fail `logger=none` runs
        callbacks = [c for c in callbacks if not isinstance(c, pl.callbacks.LearningRateMonitor)]
    trainer = hydra.utils.instantiate(
        cfg.trainer,
        callbacks=callbacks,
        logger=loggers or False,
        _convert_="partial",
        **determinism,
    )
    ckpt_path = resolve_ckpt_path(cfg.get("ckpt_path"), run_dir)
    metrics: dict[str, Any] = {}
    if cfg.get("train", True):
        # checkpoints hold tensors and plain values only: no pickled code runs on resume
        trainer.fit(model=model, datamodule=datamodule, ckpt_path=ckpt_path, weights_only=True)
        metrics.update(trainer.callback_metrics)
    if cfg.get("test", True) and is_overridden("test_step", model):
        # after a fit: the weights it ended with; without one (train=false): the checkpoint's
        test_ckpt = None if cfg.get("train", True) else ckpt_path
        trainer.test(model=model, datamodule=datamodule, ckpt_path=test_ckpt, weights_only=True)
        metrics.update(trainer.callback_metrics)
    final = getattr(model, "final_metrics", None)
    if isinstance(final, dict):
        metrics.update(final)
    if run_dir is not None and trainer.is_global_zero:
        write_run_record(run_dir, cfg, metrics)
    return metrics


setup_environment()


@hydra.main(version_base="1.3", config_path=config_dir(), config_name="train")
def main(cfg: DictConfig) -> float | None:
    from hydra.core.hydra_config import HydraConfig

    apply_extras(cfg)
    run_dir = Path(HydraConfig.get().runtime.output_dir)
    metrics = train(cfg, run_dir)
    name = cfg.get("optimized_metric")
    # evaluation-only runs (train=false) have no optimised metric to return
    if name and cfg.get("train", True):
        if name not in metrics:
            raise KeyError(f"optimized_metric '{name}' was not logged; logged: {sorted(metrics)}")
        return float(metrics[name])
    return None


if __name__ == "__main__":
    main()
