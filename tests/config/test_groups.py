"""Every option of every config group composes into ``train.yaml`` (at scale=tiny) and what
it configures instantiates: datamodule (constructor only, no data made), model, callbacks,
loggers and trainer through sss2bathy-train's own start-up (``instantiate_run``); Hydra's
launcher and sweeper targets are located. Catches "Error locating target" and options that
no longer fit the rest of the config (as lightning-hydra-template's test_configs.py)."""

from __future__ import annotations

import importlib.util
from pathlib import Path

import pytest
import torch
from hydra import compose, initialize_config_dir
from hydra.core.hydra_config import HydraConfig
from hydra.utils import get_class
from omegaconf import OmegaConf, open_dict

from sss2bathy.cli.train import instantiate_run
from sss2bathy.config_validation import validate_config
from tests.conftest import skip_unless_survey_files

CONF = Path(__file__).resolve().parents[2] / "conf"
GROUPS = sorted(
    str(d.relative_to(CONF)) for d in CONF.rglob("*") if d.is_dir() and any(d.glob("*.yaml"))
)
# MLflow's import and store set-up take ~10 s: the default tier leaves those two to the slow
# one (tests/cli/test_loggers.py writes with every logger option)
SLOW = {("logger", "mlflow"), ("logger", "many")}
CASES = [
    pytest.param(
        g, p.stem, id=f"{g}={p.stem}", marks=[pytest.mark.slow] if (g, p.stem) in SLOW else []
    )
    for g in GROUPS
    for p in sorted((CONF / g).glob("*.yaml"))
]

# groups placed at another package than their folder
OVERRIDE_KEY = {"loss": "loss@model.loss"}
# what an option needs beside it to make sense (by group, or by (group, option))
BASE = {
    "loss": ["experiment=cnn"],
    "data/normals": ["experiment=siren_gt_n2d"],
    ("callbacks", "lambert_curves"): ["experiment=siren_lambert"],
    ("hparams_search", "cnn_optuna"): ["experiment=cnn"],
    ("hparams_search", "siren_optuna"): ["experiment=siren_lambert"],
    ("data/survey", "xtf"): ["data.survey.files=/nowhere", "data.test_surveys=null"],
}
# options that only configure Hydra itself (nothing of the run to instantiate)
HYDRA_ONLY = {"hydra", "hydra/launcher", "hparams_search"}


def _overrides(group: str, option: str, run_dir: Path) -> list[str]:
    base = BASE.get((group, option), BASE.get(group, []))
    return [
        "scale=tiny",
        f"paths.output_dir={run_dir}",
        f"paths.data_dir={run_dir / 'data'}",
        *base,
        f"{OVERRIDE_KEY.get(group, group)}={option}",
    ]


def _loggers_importable(cfg) -> None:
    for name, node in (cfg.get("logger") or {}).items():
        target = str(node.get("_target_", "")) if node else ""
        needs = {"MLFlowLogger": "mlflow", "WandbLogger": "wandb"}.get(target.rsplit(".", 1)[-1])
        if needs and importlib.util.find_spec(needs) is None:
            pytest.skip(f"logger {name} needs the optional package {needs}")


@pytest.mark.parametrize("group, option", CASES)
def test_every_option_composes_and_instantiates(group, option, tmp_path, monkeypatch):
    monkeypatch.setenv("SSS2BATHY_RUN_DIR", str(tmp_path))
    if (group, option) == ("trainer", "slurm"):  # Lightning's SLURMEnvironment reads these
        for var, value in {
            "SLURM_NTASKS": "2",
            "SLURM_NTASKS_PER_NODE": "2",
            "SLURM_NODEID": "0",
            "SLURM_PROCID": "0",
            "SLURM_LOCALID": "0",
            "SLURM_JOB_ID": "1",
            "SLURM_JOB_NAME": "test",
        }.items():
            monkeypatch.setenv(var, value)
    with initialize_config_dir(str(CONF), version_base="1.3"):
        cfg = compose(
            "train", overrides=_overrides(group, option, tmp_path), return_hydra_config=True
        )
    with open_dict(cfg):
        cfg.hydra.runtime.output_dir = str(tmp_path)
        if not torch.cuda.is_available() and cfg.trainer.get("accelerator") == "gpu":
            cfg.trainer.accelerator = "cpu"  # trainer=gpu on a machine without one
    HydraConfig.instance().set_config(cfg)
    if group in HYDRA_ONLY:
        for node in (cfg.hydra.launcher, cfg.hydra.sweeper):
            if node.get("_target_"):
                if (
                    node._target_.startswith("hydra_plugins.")
                    and importlib.util.find_spec(node._target_.rsplit(".", 2)[0]) is None
                ):
                    pytest.skip(f"{node._target_}: Hydra plugin not installed")
                get_class(node._target_)
        for key in cfg.hydra.sweeper.get("params") or {}:
            assert OmegaConf.select(cfg, key) is not None, f"{group}={option}: no key {key}"
        return
    # every value resolves (no dangling interpolation), then the run's own start-up
    for key in cfg:
        value = cfg[key]  # a leaf resolves on access
        if key != "hydra" and OmegaConf.is_config(value):
            OmegaConf.to_container(value, resolve=True)
    skip_unless_survey_files(cfg)
    validate_config(cfg)
    _loggers_importable(cfg)
    run = instantiate_run(cfg, tmp_path)
    assert run.datamodule is not None and run.model is not None and run.trainer is not None
