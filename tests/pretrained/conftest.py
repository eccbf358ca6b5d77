"""A tiny trained CNN in a Hydra-like run folder, shared by the pretrained-model tests."""

from __future__ import annotations

import json
from functools import partial
from pathlib import Path

import numpy as np
import pytest
import pytorch_lightning as pl
import torch
import yaml

from sss2bathy.data.windows import SidescanWindowDataModule
from sss2bathy.losses import NormalLoss
from sss2bathy.models.normal_cnn import NormalResNet
from sss2bathy.modules.normal_cnn import NormalCNNModule
from sss2bathy.survey import BathyGrid, SensorParams, SidescanLine, Survey


def hills_survey(folder: Path) -> Path:
    """Four 850 kHz training lines (64 bins over 25 m, 10 m altitude) over seeded hills and
    a test line, saved under ``folder/hills``."""
    x = np.arange(-40.0, 40.25, 0.5)
    y = np.arange(-10.0, 60.25, 0.5)
    X, Y = np.meshgrid(x, y)
    grid = BathyGrid(-12.0 + 1.5 * np.sin(X / 4.0) * np.cos(Y / 5.0), x[0], y[0], 0.5)
    lines = []
    rng = np.random.default_rng(0)
    for i, name in enumerate(["t0", "t1", "t2", "t3", "test0"]):
        n = 40
        lines.append(
            SidescanLine(
                name=name,
                time_s=np.arange(n, dtype=np.float64),
                position=np.stack(
                    [np.full(n, -12.0 + 6.0 * i), np.linspace(0, 45, n), np.full(n, -2.0)], 1
                ),
                rotation=np.repeat(np.eye(3)[None], n, axis=0),
                altitude_m=np.full(n, 10.0, np.float32),
                intensity=rng.random((n, 2, 64)).astype(np.float32),
                range_m=np.linspace(25.0 / 64, 25.0, 64),
                sensor=SensorParams(),
            )
        )
    splits = {"train": ["t0", "t1", "t2", "t3"], "test": ["test0"]}
    return Survey("hills", lines, grid, splits).save(folder / "hills")


def fit_tiny_cnn(tmp: Path, survey_dir: Path, run: Path, seed: int = 0) -> Path:
    """One optimiser step of a width-2 CNN on the hills survey, saved as
    ``run/checkpoints/last.ckpt`` beside a Hydra-like record of the run."""
    dm = SidescanWindowDataModule(
        survey={"kind": "folder", "path": str(survey_dir)},
        data_dir=str(tmp),
        window_pings=16,
        window_bins=32,
        val_fraction=0.25,
        batch_size=8,
        seed=1,
    )
    torch.manual_seed(seed)
    module = NormalCNNModule(
        net=partial(NormalResNet, base_width=2, n_blocks=1),
        loss=NormalLoss(),
        optimizer=partial(torch.optim.Adam, lr=1e-3),
        image_every_n_epochs=0,
    )
    trainer = pl.Trainer(
        accelerator="cpu",
        logger=False,
        enable_checkpointing=False,
        enable_progress_bar=False,
        enable_model_summary=False,
        max_steps=1,
        limit_val_batches=1,
        num_sanity_val_steps=0,
    )
    trainer.fit(module, datamodule=dm)
    (run / "checkpoints").mkdir(parents=True)
    (run / ".hydra").mkdir()
    path = run / "checkpoints" / "last.ckpt"
    trainer.save_checkpoint(path)
    overrides = ["experiment=cnn", "scale=tiny", "paths.output_dir=/somewhere/local"]
    (run / ".hydra" / "overrides.yaml").write_text(yaml.safe_dump(overrides))
    config = {
        "task_name": "cnn",
        "seed": 42,
        "scale": {"name": "tiny", "cnn": {"max_epochs": 1}},
        "trainer": {
            "max_epochs": "${scale.cnn.max_epochs}",
            "default_root_dir": "${paths.output_dir}",
        },
        "callbacks": {"dir": "${hydra:runtime.output_dir}"},
        "paths": {"output_dir": "/somewhere/local"},
    }
    (run / ".hydra" / "config.yaml").write_text(yaml.safe_dump(config))
    (run / "run_info.json").write_text(json.dumps({"experiment": "cnn", "scale": "tiny"}))
    metrics = {
        "val/nlat_mae": 0.2,
        "test/hills:test/nlat_mae": 0.3,
        "test/hills:test/constant/nlat_mae": 0.25,
        "train/loss": 1.0,
        "test/hills:test/nlat_delta1": float("nan"),
    }
    (run / "metrics.json").write_text(json.dumps(metrics))
    return path


@pytest.fixture(scope="session")
def tiny_run(tmp_path_factory) -> tuple[Path, Path]:
    """``(checkpoint, survey folder)`` of a tiny CNN run (see :func:`fit_tiny_cnn`)."""
    tmp = tmp_path_factory.mktemp("pretrained_run")
    survey_dir = hills_survey(tmp)
    return fit_tiny_cnn(tmp, survey_dir, tmp / "run"), survey_dir


@pytest.fixture(scope="session")
def exported(tiny_run, tmp_path_factory) -> Path:
    """The tiny run exported as ``tiny.safetensors`` + ``tiny.json``."""
    from sss2bathy.pretrained import export_checkpoint

    out = tmp_path_factory.mktemp("exported")
    weights, _ = export_checkpoint(tiny_run[0], out, "tiny")
    return weights
