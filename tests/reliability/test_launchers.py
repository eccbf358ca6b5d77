"""Cluster plumbing composes and instantiates: the submitit SLURM and joblib launchers, and
trainer=slurm (Lightning's SLURM auto-requeue)."""

from __future__ import annotations

import warnings

import hydra
import pytest
from hydra import compose, initialize_config_dir
from hydra.core.hydra_config import HydraConfig
from omegaconf import OmegaConf
from reliability_helpers import CONF, compose_run


def _compose(overrides):
    with warnings.catch_warnings():
        # our launcher files extend the plugins' schemas of the same name (Hydra warns)
        warnings.simplefilter("ignore", UserWarning)
        with initialize_config_dir(str(CONF), version_base="1.3"):
            cfg = compose("train", overrides=overrides, return_hydra_config=True)
    HydraConfig.instance().set_config(cfg)
    return cfg


def test_submitit_slurm_launcher_composes_and_builds_sbatch_parameters(tmp_path, monkeypatch):
    submitit = pytest.importorskip("submitit")
    from submitit.slurm.slurm import SlurmExecutor

    # no SLURM here: pretend srun exists so the executor can be built and its sbatch text made
    monkeypatch.setattr(SlurmExecutor, "affinity", classmethod(lambda cls: 1))
    from hydra_plugins.hydra_submitit_launcher.config import BaseQueueConf

    cfg = _compose(
        [
            "hydra/launcher=submitit_slurm",
            "scale=tiny",
            "hydra.launcher.partition=gpu",
            f"hydra.sweep.dir={tmp_path}",
        ]
    )
    assert cfg.hydra.runtime.choices["hydra/launcher"] == "submitit_slurm"
    launcher = hydra.utils.instantiate(cfg.hydra.launcher)
    # (Hydra's plugin discovery imports the plugin module under its own name)
    assert type(launcher).__qualname__ == "SlurmLauncher"
    params = launcher.params
    assert params["partition"] == "gpu" and params["max_num_timeout"] == 3
    assert params["submitit_folder"] == f"{tmp_path}/.submitit/%j"
    # the launcher's own translation into submitit parameters, then sbatch's text
    executor = submitit.AutoExecutor(
        cluster="slurm", folder=tmp_path, slurm_max_num_timeout=params["max_num_timeout"]
    )
    base = set(OmegaConf.structured(BaseQueueConf).keys())
    executor.update_parameters(
        **{
            (k if k in base else f"slurm_{k}"): v
            for k, v in params.items()
            if k not in ("submitit_folder", "max_num_timeout", "_target_")
        }
    )
    text = executor._executor._make_submission_file_text("python -c pass", "uid")
    for line in ("--signal=USR2@120", "--time=720", "--partition=gpu", "--gpus-per-node=1"):
        assert line in text, text


def test_joblib_launcher_composes_and_instantiates():
    cfg = _compose(["hydra/launcher=joblib", "scale=tiny", "hydra.launcher.n_jobs=3"])
    assert cfg.hydra.launcher.n_jobs == 3
    assert type(hydra.utils.instantiate(cfg.hydra.launcher)).__qualname__ == "JoblibLauncher"
    assert _compose(["hydra/launcher=joblib"]).hydra.launcher.n_jobs == 2


def test_slurm_trainer_enables_lightning_auto_requeue(tmp_path):
    from pytorch_lightning.plugins.environments import SLURMEnvironment

    cfg = compose_run(["trainer=slurm", "scale=tiny"], tmp_path)
    assert cfg.trainer.strategy == "ddp" and cfg.trainer.default_root_dir == str(tmp_path)
    (env,) = hydra.utils.instantiate(cfg.trainer.plugins)
    assert isinstance(env, SLURMEnvironment) and env.auto_requeue
    assert _compose(["trainer=ddp"]).trainer.plugins is None
