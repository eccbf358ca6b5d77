"""Shared set-up of the reliability tests: tiny surveys built by the data tests' builders,
and ``train()`` runs composed from the real configs (CPU, one thread, no logger)."""

from __future__ import annotations

import importlib.util
from pathlib import Path

import pytest
from hydra import compose, initialize_config_dir
from hydra.core.hydra_config import HydraConfig
from omegaconf import DictConfig, open_dict

ROOT = Path(__file__).resolve().parents[2]
CONF = ROOT / "conf"


def _load_test_module(name: str, rel: str):
    spec = importlib.util.spec_from_file_location(name, ROOT / rel)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


@pytest.fixture(scope="session")
def plane_survey(tmp_path_factory) -> Path:
    """A tilted plane with two crossing 40-ping lines (tests/data/test_pings.py)."""
    builder = _load_test_module("_reliability_pings", "tests/data/test_pings.py").make_tiny_survey
    return builder(tmp_path_factory.mktemp("plane") / "tiny_plane")


@pytest.fixture(scope="session")
def hills_survey(tmp_path_factory) -> Path:
    """A hilly grid with 4 training lines and one test line (tests/data/test_windows.py)."""
    module = _load_test_module("_reliability_windows", "tests/data/test_windows.py")
    return module._save_survey(tmp_path_factory.mktemp("hills"))


COMMON = [
    "scale=tiny",
    "logger=none",
    "~callbacks.lr_monitor",
    "torch_threads=1",
    "trainer.accelerator=cpu",
    "trainer.enable_progress_bar=false",
    "+trainer.enable_model_summary=false",
]


def siren_overrides(survey: Path, tmp: Path) -> list[str]:
    """A SIREN-GT-N2d fit of the plane survey: 5 steps per epoch, map scored every epoch."""
    return [
        "experiment=siren_gt_n2d",
        "data/survey=xtf",
        "data.survey.kind=folder",
        f"+data.survey.path={survey}",
        f"paths.data_dir={tmp}",
        f"paths.output_dir={tmp / 'outputs'}",
        "model.siren.hidden=16",
        "model.siren.n_layers=3",
        "data.batch_pings=16",
        "data.altimeter_points=100",
        "model.eval_cell_m=2.0",
        "model.log_images=false",
        "+trainer.num_sanity_val_steps=0",
        *COMMON,
    ]


def cnn_overrides(survey: Path, tmp: Path) -> list[str]:
    """The CNN experiment on the hills survey: a tiny net, 16-ping windows, no test surveys."""
    return [
        "experiment=cnn",
        "data/survey=xtf",
        "data.survey.kind=folder",
        f"+data.survey.path={survey}",
        "data.test_surveys=null",
        f"paths.data_dir={tmp}",
        f"paths.output_dir={tmp / 'outputs'}",
        "data.window_pings=16",
        "data.batch_size=4",
        "model.net.base_width=4",
        "model.net.n_blocks=1",
        "model.image_every_n_epochs=0",
        "~callbacks.cnn_table",
        *COMMON,
    ]


def compose_run(overrides: list[str], run_dir: Path) -> DictConfig:
    """The composed ``train`` config with ``hydra.runtime.output_dir = run_dir``, as inside a
    Hydra run (the callbacks' ``${hydra:runtime.output_dir}`` resolve there)."""
    with initialize_config_dir(str(CONF), version_base="1.3"):
        cfg = compose("train", overrides=overrides, return_hydra_config=True)
    with open_dict(cfg):
        cfg.hydra.runtime.output_dir = str(run_dir)
    HydraConfig.instance().set_config(cfg)
    return cfg
