"""``hparams_search=siren_optuna``: a SIREN search that needs no MBES (objective: the held-out
altimeter MAE), its keys exist in every SIREN model config, and a 2-trial tiny sweep runs."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest
import yaml
from hydra import compose, initialize_config_dir
from omegaconf import OmegaConf

from sss2bathy.cli.train import HOLDOUT_METRIC

ROOT = Path(__file__).resolve().parents[2]
CONF = ROOT / "conf"
SIREN_EXPERIMENTS = ["siren_gt_n2d", "siren_cnn_n2d", "siren_lambert", "siren_heights_only"]


def _compose(overrides: list[str]):
    with initialize_config_dir(str(CONF), version_base="1.3"):
        return compose("train", overrides=overrides, return_hydra_config=True)


@pytest.mark.parametrize("experiment", SIREN_EXPERIMENTS)
def test_siren_optuna_searches_keys_the_siren_configs_have(experiment):
    cfg = _compose([f"experiment={experiment}", "hparams_search=siren_optuna", "scale=tiny"])
    # the experiment's val/map_mae_m (needs MBES) is replaced by the held-out altimeter MAE
    assert cfg.optimized_metric == HOLDOUT_METRIC
    assert cfg.hydra.sweeper.direction == "minimize"
    assert cfg.data.holdout.fraction > 0  # there is a held-out score to minimise
    params = OmegaConf.to_container(cfg.hydra.sweeper.params)
    assert set(params) == {
        "model.w_height",
        "model.optimizer.lr",
        "model.siren.omega0",
        "model.scheduler.gamma",
    }
    for key in params:
        assert OmegaConf.select(cfg, key, throw_on_missing=True) is not None, key


def test_map_mae_objective_is_one_override():
    cfg = _compose(
        ["experiment=siren_gt_n2d", "hparams_search=siren_optuna", "optimized_metric=val/map_mae_m"]
    )
    assert cfg.optimized_metric == "val/map_mae_m"


@pytest.mark.slow
def test_a_two_trial_siren_sweep_on_the_tiny_survey(tmp_path):
    (tmp_path / "conf").symlink_to(CONF)
    env = dict(os.environ, SSS2BATHY_ROOT=str(tmp_path), OMP_NUM_THREADS="1", MKL_NUM_THREADS="1")
    env.pop("SSS2BATHY_RUN_DIR", None)
    cmd = [sys.executable, "-m", "sss2bathy.cli.train", "-m", "experiment=siren_gt_n2d"]
    cmd += ["hparams_search=siren_optuna", "hydra.sweeper.n_trials=2", "scale=tiny"]
    # the tiny lines are 57 pings long: blocks of 10 pings, so some altimeter is held out
    cmd += ["data.holdout.block_pings=10", "logger=none", "callbacks=none", "torch_threads=1"]
    cmd += ["trainer.enable_progress_bar=false", "model.log_images=false"]
    proc = subprocess.run(cmd, cwd=tmp_path, env=env, capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, proc.stderr[-3000:]
    (sweep,) = (tmp_path / "outputs" / "multiruns" / "siren_gt_n2d").iterdir()
    result = yaml.safe_load((sweep / "optimization_results.yaml").read_text())
    assert set(result["best_params"]) == {
        "model.w_height",
        "model.optimizer.lr",
        "model.siren.omega0",
        "model.scheduler.gamma",
    }
    assert 0 < result["best_value"] < 5  # a held-out altimeter MAE in metres
    assert sorted(p.name for p in sweep.iterdir() if p.is_dir()) == ["0", "1"]
