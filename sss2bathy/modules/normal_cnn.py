"""LightningModule training the normal CNN (its images and table writer are callbacks in
:mod:`sss2bathy.callbacks`).

Batches are dicts (see ``sss2bathy.data`` windows): ``intensity [B,1,H,W] float32``,
``n_lat [B,1,H,W] float32``, ``mask [B,1,H,W] bool`` (True = valid), optionally ``inputs
[B,C,H,W] float32`` (the network's input channels; absent: the intensity alone) plus ``line,
side, ping_start, bin_start [B] long`` and ``flipped [B] bool`` (unused here).

Logged keys: ``{stage}/loss`` and each loss term (``{stage}/loss_na``, ``{stage}/loss_tv``),
``{stage}/nlat_{mae,rel,rmse,delta1,delta2,delta3}`` (n_lat, unitless; deltas in percent) for
``train`` and ``val``; test metrics are ``test/{name}/nlat_...`` (losses ``test/{name}/loss``)
with one ``name`` per test dataloader (``datamodule.test_set_names``).
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Mapping, Sequence
from typing import Any

import pytorch_lightning as pl
import torch
from torch import nn

from sss2bathy.callbacks import NormalImageLogger
from sss2bathy.callbacks.hparams import flatten
from sss2bathy.data.sonar_envelope import CHECKPOINT_KEY as SONAR_ENVELOPE_KEY
from sss2bathy.eval.cnn_table import NLAT_PREFIX
from sss2bathy.losses.normal import NormalLoss, lowpass_loss
from sss2bathy.metrics.normal import NormalMetrics
from sss2bathy.modules.cnn_parts import (
    COMPILED_PREFIX,
    build_net,
    check_batch,
    describe_factory,
    init_from_model,
    input_channel_names,
    net_config,
    sonar_mask_mismatch,
)
from sss2bathy.utils.checks import require_bool

log = logging.getLogger(__name__)

#: the box of the logged low-pass n_lat error ``{stage}/nlat_lp_mae`` (pings x bins, within
#: each window: :func:`~sss2bathy.losses.normal.lowpass_loss`)
LOWPASS_BOX = (16, 32)


def window_lowpass_mae(pred: torch.Tensor, batch: Mapping[str, torch.Tensor]) -> torch.Tensor:
    """MAE of the :data:`LOWPASS_BOX`-averaged n_lat in each window (the error a map feels)."""
    pings = min(LOWPASS_BOX[0], pred.shape[-2])
    bins = min(LOWPASS_BOX[1], pred.shape[-1])
    return lowpass_loss(pred.detach(), batch["n_lat"], batch["mask"], pings, bins)


class NormalCNNModule(pl.LightningModule):
    """Trains a normal-estimation network on sidescan windows.

    Args:
        net: maps ``[B, 1, H, W]`` intensity to ``[B, 1, H, W]`` n_lat (``NormalResNet``).
        loss: a :class:`~sss2bathy.losses.NormalLoss` or a mapping of its arguments.
        optimizer: factory ``optimizer(params=...)`` (Hydra ``_partial_: true``), e.g. Adam
            lr 2e-4, betas (0.9, 0.999) as in the paper.
        scheduler: factory ``scheduler(optimizer=...)`` stepped every epoch, or None (the
            paper's linear decay: ``LinearLR(start_factor=1, end_factor=0,
            total_iters=max_epochs)``).
        image_every_n_epochs: log validation images every N epochs (0: never); the images
            come from :class:`NormalImageLogger`, added by :meth:`configure_callbacks`.
        n_images: number of fixed validation windows shown.
        compile: ``torch.compile`` the network for fitting.
        input_channels: names of the network's input channels
            (:data:`sss2bathy.data.masks.CHANNELS`; ``None``: ``[intensity]``), stored in the
            checkpoint so prediction builds the same inputs. ``net`` may be a factory
            ``net(in_channels=...)`` (Hydra ``_partial_: true``), built with one input per
            channel; a built network must have ``in_channels`` equal to their number.
        channels_last: run the network in ``torch.channels_last`` memory format.
        init: start from a trained CNN's weights (fine-tuning): ``"pretrained"`` (the CNN
            shipped in the package), a ``.ckpt`` of a CNN run or an exported
            ``.safetensors``; None: random weights. Its input channels and network must be
            this run's (:func:`~sss2bathy.modules.cnn_parts.init_from_model`: one line
            otherwise); what was loaded is kept in the hparams (``init``), and a data
            ``sonar_mask`` other than the weights' is a WARNING at the start of the fit.

    The checkpoint's hyper-parameters hold plain values only (``net_config``: the network's
    class path and arguments), so ``torch.load(weights_only=True)`` can read it and
    :func:`sss2bathy.modules.predict.predict_normals` can rebuild the network. The training
    lines' sonar (the datamodule's ``sonar_envelope``, a plain dict) is stored under the
    checkpoint's ``sonar_envelope`` key, so the CNN's normals for a survey recorded with
    another sonar come with a warning (:mod:`sss2bathy.data.sonar_envelope`).
    """

    def __init__(
        self,
        net: nn.Module,
        loss: NormalLoss | Mapping[str, Any],
        optimizer: Callable[..., torch.optim.Optimizer],
        scheduler: Callable[..., Any] | None = None,
        image_every_n_epochs: int = 5,
        n_images: int = 4,
        compile: bool = False,
        input_channels: Sequence[str] | None = None,
        channels_last: bool = False,
        init: str | None = None,
    ) -> None:
        super().__init__()
        channels = input_channel_names(input_channels)
        net = build_net(net, channels)
        init_record = None if init is None else init_from_model(net, init, channels)
        if not callable(optimizer):
            raise ValueError(
                f"optimizer: expected a factory optimizer(params=...), found {optimizer!r}"
            )
        if scheduler is not None and not callable(scheduler):
            raise ValueError(f"scheduler: expected a factory or None, found {scheduler!r}")
        for name, value in (("image_every_n_epochs", image_every_n_epochs), ("n_images", n_images)):
            if not isinstance(value, int) or isinstance(value, bool) or value < 0:
                raise ValueError(f"{name}: expected an integer >= 0, found {value!r}")
        self.net = net
        self.loss_fn = NormalLoss.from_config(loss)
        self.optimizer_factory = optimizer
        self.scheduler_factory = scheduler
        self.save_hyperparameters(
            {
                "net_config": net_config(net),
                "loss": self.loss_fn.config(),
                "optimizer": describe_factory(optimizer),
                "scheduler": describe_factory(scheduler),
                "image_every_n_epochs": image_every_n_epochs,
                "n_images": n_images,
                "compile": require_bool("compile", compile),
                "input_channels": list(channels),
                "channels_last": bool(channels_last),
                "init": init_record,
            },
            logger=False,
        )
        self.train_metrics = NormalMetrics(prefix=f"train/{NLAT_PREFIX}")
        self.val_metrics = NormalMetrics(prefix=f"val/{NLAT_PREFIX}")
        self.test_metrics = nn.ModuleDict()
        self.final_metrics: dict[str, float] = {}
        self.sonar_envelope: dict[str, Any] | None = None

    # ----------------------------------------------------------------- model
    def forward(self, inputs: torch.Tensor) -> torch.Tensor:
        """``inputs [B, C, H, W]`` (C input channels) -> n_lat ``[B, 1, H, W]``."""
        if self.hparams.get("channels_last", False):
            inputs = inputs.contiguous(memory_format=torch.channels_last)
        return self.net(inputs)

    @staticmethod
    def batch_inputs(batch: Mapping[str, torch.Tensor]) -> torch.Tensor:
        """The network input of a batch: ``inputs`` when present, else ``intensity``."""
        return batch["inputs"] if "inputs" in batch else batch["intensity"]

    def setup(self, stage: str) -> None:
        if self.hparams.get("channels_last", False):
            self.net = self.net.to(memory_format=torch.channels_last)
        already_compiled = hasattr(self.net, COMPILED_PREFIX.rstrip("."))
        if self.hparams.compile and stage == "fit" and not already_compiled:
            self.net = torch.compile(self.net)

    def model_step(
        self, batch: Mapping[str, torch.Tensor]
    ) -> tuple[dict[str, torch.Tensor], torch.Tensor]:
        """Forward + loss, shared by all stages: ``(loss terms dict, prediction [B,1,H,W])``."""
        check_batch(batch, len(self.hparams.get("input_channels") or [1]))
        pred = self(self.batch_inputs(batch))
        return self.loss_fn(pred, batch["n_lat"], batch["mask"]), pred

    def _log_losses(
        self, stage: str, losses: Mapping[str, torch.Tensor], batch_size: int, **kw
    ) -> None:
        for key, value in losses.items():
            self.log(f"{stage}/{key}", value, batch_size=batch_size, **kw)

    # ----------------------------------------------------------------- stages
    def training_step(self, batch: Mapping[str, torch.Tensor], batch_idx: int) -> torch.Tensor:
        losses, pred = self.model_step(batch)
        n = int(batch["intensity"].shape[0])
        self._log_losses("train", losses, n, on_step=True, on_epoch=True, prog_bar=False)
        self.train_metrics.update(pred, batch["n_lat"], batch["mask"])
        self.log_dict(self.train_metrics, on_step=False, on_epoch=True, batch_size=n)
        return losses["loss"]

    def validation_step(self, batch: Mapping[str, torch.Tensor], batch_idx: int) -> None:
        losses, pred = self.model_step(batch)
        n = int(batch["intensity"].shape[0])
        self._log_losses("val", losses, n, on_step=False, on_epoch=True, sync_dist=True)
        self.val_metrics.update(pred, batch["n_lat"], batch["mask"])
        self.log_dict(self.val_metrics, on_step=False, on_epoch=True, batch_size=n, prog_bar=True)
        lp = window_lowpass_mae(pred, batch)
        self.log(f"val/{NLAT_PREFIX}lp_mae", lp, on_step=False, on_epoch=True, batch_size=n)

    def test_set_name(self, dataloader_idx: int) -> str | None:
        """Name of a test dataloader: ``datamodule.test_set_names[idx]`` when the datamodule
        names each loader; else None for a single loader, ``dataloader_{idx}``."""
        dm = getattr(self.trainer, "datamodule", None)
        names = getattr(dm, "test_set_names", None)
        n_loaders = len(self.trainer.num_test_batches or [0])
        if names is not None and len(names) == n_loaders:
            return str(names[dataloader_idx])
        return None if n_loaders == 1 else f"dataloader_{dataloader_idx}"

    def on_test_start(self) -> None:
        # one metric collection per test dataloader, named by this run's datamodule
        self.test_metrics = nn.ModuleDict()

    def test_step(
        self, batch: Mapping[str, torch.Tensor], batch_idx: int, dataloader_idx: int = 0
    ) -> dict[str, torch.Tensor]:
        losses, pred = self.model_step(batch)
        n = int(batch["intensity"].shape[0])
        name = self.test_set_name(dataloader_idx)
        prefix = "test/" if name is None else f"test/{name}/"
        key = f"dataloader_{dataloader_idx}"
        if key not in self.test_metrics:
            self.test_metrics[key] = NormalMetrics(prefix=prefix).to(self.device)
        metrics = self.test_metrics[key]
        for term, value in losses.items():
            self.log(
                f"{prefix}{term}", value, batch_size=n, add_dataloader_idx=False, sync_dist=True
            )
        metrics.update(pred, batch["n_lat"], batch["mask"])
        self.log(
            f"{prefix}{NLAT_PREFIX}lp_mae", window_lowpass_mae(pred, batch), batch_size=n,
            add_dataloader_idx=False, sync_dist=True,
        )  # fmt: skip
        # created after Lightning indexed the module's metrics: name their attribute path
        for base, metric in metrics.items(keep_base=True, copy_state=False):
            self.log(
                f"{prefix}{NLAT_PREFIX}{base}",
                metric,
                on_step=False,
                on_epoch=True,
                batch_size=n,
                add_dataloader_idx=False,
                metric_attribute=f"test_metrics.{key}.{base}",
            )
        # the predictions, for callbacks (CNNTableWriter's bias files)
        return {"pred": pred.detach()}

    # ----------------------------------------------------------------- optim
    def configure_optimizers(self) -> Any:
        optimizer = self.optimizer_factory(params=self.parameters())
        if self.scheduler_factory is None:
            return optimizer
        scheduler = self.scheduler_factory(optimizer=optimizer)
        return {
            "optimizer": optimizer,
            "lr_scheduler": {"scheduler": scheduler, "interval": "epoch"},
        }

    def configure_callbacks(self) -> list[pl.Callback]:
        if self.hparams.image_every_n_epochs and self.hparams.n_images:
            return [NormalImageLogger(self.hparams.image_every_n_epochs, self.hparams.n_images)]
        return []

    # ----------------------------------------------------------------- results
    def record_final_metrics(self) -> None:
        """Keep the ``val/*`` and ``test/*`` callback metrics in :attr:`final_metrics` (a test
        replaces ``trainer.callback_metrics``: the fit's validation values stay)."""
        for key, value in self.trainer.callback_metrics.items():
            if key.startswith(("val/", "test/")):
                self.final_metrics[key] = float(value)

    def hparams_for_log(self) -> dict[str, Any]:
        """The module's and the datamodule's hyper-parameters, flattened (``model/...``,
        ``data/...``), for :class:`~sss2bathy.callbacks.RunHparams`."""
        params: dict[str, Any] = {"model": dict(self.hparams)}
        dm = getattr(self.trainer, "datamodule", None)
        if dm is not None and getattr(dm, "hparams", None):
            params["data"] = dict(dm.hparams)
        return flatten(params)

    def on_fit_start(self) -> None:
        self.final_metrics = {}
        dm = getattr(self.trainer, "datamodule", None)
        envelope = getattr(dm, "sonar_envelope", None)
        if envelope is not None:
            self.sonar_envelope = envelope
        data_mask = (getattr(dm, "hparams", None) or {}).get("sonar_mask")
        mismatch = sonar_mask_mismatch(self.hparams.get("init"), data_mask)
        if mismatch is not None:
            log.warning("%s", mismatch)

    def on_save_checkpoint(self, checkpoint: dict[str, Any]) -> None:
        """Store the training sonar (the datamodule's, else the one of the checkpoint this
        module was loaded from) as plain values."""
        trainer = self._trainer
        envelope = getattr(getattr(trainer, "datamodule", None), "sonar_envelope", None)
        envelope = envelope if envelope is not None else self.sonar_envelope
        if envelope is not None:
            checkpoint[SONAR_ENVELOPE_KEY] = envelope

    def on_load_checkpoint(self, checkpoint: dict[str, Any]) -> None:
        self.sonar_envelope = checkpoint.get(SONAR_ENVELOPE_KEY)

    def on_fit_end(self) -> None:
        self.record_final_metrics()

    def on_test_end(self) -> None:
        self.record_final_metrics()


__all__ = ["NormalCNNModule"]
