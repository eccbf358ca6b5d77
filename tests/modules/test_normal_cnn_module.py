"""NormalCNNModule through Hydra's compose API and Lightning; image logger, hparams, table."""

import math
from functools import partial
from pathlib import Path

import numpy as np
import pytest
import pytorch_lightning as pl
import torch
from hydra import compose, initialize_config_dir
from hydra.utils import instantiate
from pytorch_lightning.loggers import TensorBoardLogger
from tensorboard.plugins.hparams import metadata as hp_meta
from torch.utils.data import DataLoader, Dataset

from sss2bathy.callbacks import CNNTableWriter, RunHparams, render_window_panel
from sss2bathy.cli._common import config_dir
from sss2bathy.eval.cnn_table import table_rows_from_metrics, write_cnn_table
from sss2bathy.eval.paper_numbers import PAPER_LABEL
from sss2bathy.losses import NormalLoss
from sss2bathy.models.normal_cnn import NormalResNet
from sss2bathy.modules.normal_cnn import NormalCNNModule

H, W = 8, 16
TEST_NAMES = ["synthetic_d1_demo", "synthetic_d2_demo"]


class RandomWindows(Dataset):
    """Seeded random windows with the windows DataModule's batch keys."""

    def __init__(self, n: int, seed: int) -> None:
        g = torch.Generator().manual_seed(seed)
        self.n_lat = 0.3 * torch.tanh(torch.randn(n, 1, H, W, generator=g))
        self.intensity = 1.0 - self.n_lat + 0.05 * torch.randn(n, 1, H, W, generator=g)
        self.mask = torch.rand(n, 1, H, W, generator=g) > 0.2

    def __len__(self) -> int:
        return len(self.n_lat)

    def __getitem__(self, i: int) -> dict[str, torch.Tensor]:
        return {
            "intensity": self.intensity[i],
            "n_lat": self.n_lat[i],
            "mask": self.mask[i],
            "line": torch.tensor(i % 3),
            "side": torch.tensor(i % 2),
            "ping_start": torch.tensor(4 * i),
            "bin_start": torch.tensor(0),
            "flipped": torch.tensor(False),
        }


class TinyWindows(pl.LightningDataModule):
    test_set_names = TEST_NAMES

    def train_dataloader(self):
        return DataLoader(RandomWindows(8, 0), batch_size=4, shuffle=True)

    def val_dataloader(self):
        return DataLoader(RandomWindows(6, 1), batch_size=3)

    def test_dataloader(self):
        return [DataLoader(RandomWindows(4, 2 + i), batch_size=4) for i in range(2)]


def tiny_module(**kw) -> NormalCNNModule:
    args = {
        "net": NormalResNet(base_width=4, n_blocks=1),
        "loss": NormalLoss("normal_aware", tv_across_track=1e-3, tv_along_track=1e-3),
        "optimizer": partial(torch.optim.Adam, lr=1e-3, betas=(0.9, 0.999)),
        "scheduler": None,
        "image_every_n_epochs": 0,
    }
    args.update(kw)
    return NormalCNNModule(**args)


def test_fast_dev_run_from_composed_config_logs_every_key():
    with initialize_config_dir(config_dir=config_dir(), version_base="1.3"):
        cfg = compose(
            config_name="model/normal_cnn",
            overrides=["+trainer.max_epochs=3", "model.net.base_width=4", "model.net.n_blocks=1"],
        )
    model = instantiate(cfg.model, _recursive_=True, _convert_="partial")
    assert model.loss_fn.kind == "normal_aware"
    assert model.hparams["optimizer"]["lr"] == pytest.approx(2e-4)
    trainer = pl.Trainer(
        fast_dev_run=True,
        accelerator="cpu",
        logger=False,
        enable_checkpointing=False,
        enable_progress_bar=False,
        enable_model_summary=False,
    )
    dm = TinyWindows()
    trainer.fit(model, datamodule=dm)
    metrics = trainer.callback_metrics
    for key in ["train/loss", "train/loss_na", "train/loss_tv", "train/nlat_mae"]:
        assert key in metrics and math.isfinite(float(metrics[key])), key
    for name in ["nlat_mae", "nlat_rel", "nlat_rmse", "nlat_delta1", "nlat_delta2", "loss"]:
        assert f"val/{name}" in metrics, name
    assert float(metrics["train/loss_tv"]) > 0
    trainer.test(model, datamodule=dm)
    for test_set in TEST_NAMES:
        for name in ["nlat_mae", "nlat_rel", "nlat_rmse", "nlat_delta3", "loss"]:
            assert f"test/{test_set}/{name}" in trainer.callback_metrics
    # the two test sets hold different windows: their metrics must differ
    assert float(trainer.callback_metrics[f"test/{TEST_NAMES[0]}/nlat_mae"]) != float(
        trainer.callback_metrics[f"test/{TEST_NAMES[1]}/nlat_mae"]
    )
    assert set(table_rows_from_metrics(trainer.callback_metrics)) == set(TEST_NAMES)
    assert f"test/{TEST_NAMES[1]}/nlat_delta1" in model.final_metrics


def test_images_hparams_scheduler_checkpoint_and_table(tmp_path):
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    torch.manual_seed(0)
    model = tiny_module(
        scheduler=partial(
            torch.optim.lr_scheduler.LinearLR, start_factor=1.0, end_factor=0.0, total_iters=2
        ),
        image_every_n_epochs=1,
        n_images=2,
    )
    logger = TensorBoardLogger(tmp_path, name="tb", version="", default_hp_metric=False)
    table = CNNTableWriter(tmp_path / "run")
    record = RunHparams(run={"experiment": "cnn", "seed": 0}, overrides=["seed=0"])
    trainer = pl.Trainer(
        max_epochs=2,
        accelerator="cpu",
        logger=logger,
        callbacks=[table, record],
        enable_checkpointing=False,
        enable_progress_bar=False,
        enable_model_summary=False,
        log_every_n_steps=1,
        num_sanity_val_steps=0,
    )
    dm = TinyWindows()
    trainer.fit(model, datamodule=dm)
    # linear decay: epoch 0 at lr, epoch 1 at lr / 2, then 0
    assert trainer.optimizers[0].param_groups[0]["lr"] == pytest.approx(0.0)
    trainer.test(model, datamodule=dm)

    events = EventAccumulator(str(tmp_path / "tb"), size_guidance={"images": 0}).Reload()
    images = events.Tags()["images"]
    assert images == ["val_images/window_0", "val_images/window_1"]
    assert len(events.Images("val_images/window_0")) == 2  # every epoch
    assert any(tag == "train/loss_na_epoch" for tag in events.Tags()["scalars"])

    # one hparams session, no experiment summary (HPARAMS builds its columns from all runs)
    content = events.PluginTagToContent(hp_meta.PLUGIN_NAME)
    assert hp_meta.EXPERIMENT_TAG not in content
    start = hp_meta.parse_session_start_info_plugin_data(content[hp_meta.SESSION_START_INFO_TAG])
    assert start.hparams["model/net_config/base_width"].number_value == 4
    assert start.hparams["model/loss/kind"].string_value == "normal_aware"
    assert start.hparams["run/experiment"].string_value == "cnn"
    assert start.hparams["run/overrides"].string_value == "seed=0"
    assert start.hparams["run/module"].string_value == "NormalCNNModule"
    scalars = events.Tags()["scalars"]
    assert "val/nlat_mae" in scalars and f"test/{TEST_NAMES[0]}/nlat_mae" in scalars

    ckpt_path = tmp_path / "model.ckpt"
    trainer.save_checkpoint(ckpt_path)
    ckpt = torch.load(ckpt_path, weights_only=True)
    assert ckpt["hyper_parameters"]["net_config"] == model.net.config()

    md_path, csv_path = table.paths
    text = md_path.read_text()
    assert PAPER_LABEL in text and "0.0221" in text and TEST_NAMES[1] in text
    mae = float(trainer.callback_metrics[f"test/{TEST_NAMES[0]}/nlat_mae"])
    assert f"{mae:.4f}" in text
    assert len(csv_path.read_text().strip().splitlines()) == 1 + 2 + 2


def test_render_window_panel_masks_invalid_pixels_black():
    rng = np.random.default_rng(0)
    gt = rng.uniform(-0.3, 0.3, (H, W))
    mask = rng.random((H, W)) > 0.3
    panel = render_window_panel(rng.random((H, W)), gt, gt + 0.05, mask, 0.3, gap=2)
    assert panel.shape == (4 * H + 3 * 2, W, 3) and panel.dtype == np.uint8
    for row in range(4):
        block = panel[row * (H + 2) : row * (H + 2) + H]
        assert (block[~mask] == 0).all()
        assert block[mask].max() > 0
    assert (panel[H : H + 2] == 255).all()  # white gap
    with pytest.raises(ValueError, match="mask"):
        render_window_panel(gt, gt, gt, mask[:2], 0.3)


def test_bad_batches_and_arguments_are_named():
    model = tiny_module()
    batch = RandomWindows(2, 0)[0]
    batch = {k: v[None] if v.ndim == 3 else v for k, v in batch.items()}
    del batch["mask"]
    with pytest.raises(ValueError, match="'mask'"):
        model.model_step(batch)
    batch["mask"] = torch.ones(1, 1, H, W)
    with pytest.raises(ValueError, match=r"batch\['mask'\].*bool"):
        model.model_step(batch)
    with pytest.raises(ValueError, match="kind.*'huber'"):
        tiny_module(loss={"kind": "huber"})
    with pytest.raises(ValueError, match="n_images"):
        tiny_module(n_images=-1)


def test_write_cnn_table_validates_rows(tmp_path):
    row = {"mae": 0.03, "rel": 0.031, "rmse": 0.04, "delta1": 88.0, "delta2": 95.0, "delta3": 98.5}
    md_path, csv_path = write_cnn_table({"synthetic_d1 test": row}, tmp_path)
    lines = md_path.read_text().splitlines()
    ours = next(ln for ln in lines if "synthetic_d1 test" in ln)
    assert "0.0300" in ours and "88.00" in ours
    assert csv_path.read_text().splitlines()[1].startswith("ours")
    with pytest.raises(ValueError, match="delta3"):
        write_cnn_table({"x": {k: v for k, v in row.items() if k != "delta3"}}, tmp_path)


@pytest.mark.parametrize("loss", ["normal_aware", "l1"])
def test_cnn_experiment_composes_with_loss_override(loss):
    conf = config_dir()
    needed = [f"{conf}/data/survey/{s}.yaml" for s in ("synthetic_d1", "synthetic_d2")]
    if not all(Path(p).is_file() for p in needed + [f"{conf}/data/windows.yaml"]):
        pytest.skip("survey / windows configs not present")
    with initialize_config_dir(config_dir=conf, version_base="1.3"):
        cfg = compose(
            config_name="train",
            overrides=["experiment=cnn", "scale=tiny", "debug=fast", f"loss@model.loss={loss}"],
        )
    assert cfg.task_name == "cnn" and cfg.model.loss.kind == loss
    assert cfg.model.net.base_width == cfg.scale.cnn.base_width
    assert cfg.trainer.max_epochs == cfg.model.scheduler.total_iters == 1
    assert (
        [s.name for s in cfg.data.test_surveys]
        == [
            cfg.cnn_test_surveys.synthetic_d2.name,
            cfg.cnn_test_surveys.synthetic_d3.name,
            cfg.cnn_test_surveys.synthetic_d1_site2.name,
        ]
        == ["synthetic_d2_tiny", "synthetic_d3_tiny", "synthetic_d1_site2_tiny"]
    )
    assert cfg.data.survey.name not in {s.name for s in cfg.data.test_surveys}
    model = instantiate(cfg.model, _recursive_=True, _convert_="partial")
    assert model.loss_fn.kind == loss and model.net.base_width == cfg.model.net.base_width
