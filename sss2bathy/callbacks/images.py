"""TensorBoard images of the fits (Lightning callbacks).

* :class:`NormalImageLogger`: the normal CNN's fixed validation windows (input, ground truth,
  prediction, error; :func:`render_window_panel`), added by
  :meth:`~sss2bathy.modules.normal_cnn.NormalCNNModule.configure_callbacks`;
* :class:`SirenMapImages`: a SIREN fit's latest map evaluation (bathymetry, gradient HSV,
  signed error), added by :meth:`~sss2bathy.modules.siren.SirenModule.configure_callbacks`.

Both do nothing without a ``TensorBoardLogger``.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import numpy as np
import pytorch_lightning as pl
import torch
from pytorch_lightning.loggers import TensorBoardLogger

from sss2bathy.eval.maps import ERROR_LABEL, error_map, gradient_hsv, map_figure
from sss2bathy.metrics.bathy import map_gradient


def tensorboard_logger(trainer: pl.Trainer) -> TensorBoardLogger | None:
    """The trainer's first TensorBoard logger, or None."""
    return next((lg for lg in trainer.loggers if isinstance(lg, TensorBoardLogger)), None)


def render_window_panel(
    intensity: np.ndarray,
    n_lat_gt: np.ndarray,
    n_lat_pred: np.ndarray,
    mask: np.ndarray,
    normal_limit: float,
    gap: int = 2,
) -> np.ndarray:
    """The paper's CNN figure for one window: rows input / ground truth / prediction / |error|.

    Args:
        intensity, n_lat_gt, n_lat_pred: ``(H, W)`` float arrays.
        mask: ``(H, W)`` bool, True = valid; invalid pixels are black in every row.
        normal_limit: n_lat colour range ``[-normal_limit, normal_limit]`` (``RdBu_r``);
            the error row spans ``[0, normal_limit]`` (``magma``).
        gap: white rows between panels.

    Returns:
        ``(4 H + 3 gap, W, 3)`` uint8 RGB image.
    """
    from matplotlib import colormaps

    shape = np.shape(intensity)
    for name, arr in (("n_lat_gt", n_lat_gt), ("n_lat_pred", n_lat_pred), ("mask", mask)):
        if np.shape(arr) != shape or len(shape) != 2:
            raise ValueError(f"{name}: expected a 2D array of shape {shape}, found {np.shape(arr)}")
    if not normal_limit > 0:
        raise ValueError(f"normal_limit: expected a positive number, found {normal_limit!r}")
    mask = np.asarray(mask, dtype=bool)
    inten = np.asarray(intensity, dtype=np.float64)
    valid_i = inten[mask & np.isfinite(inten)]
    lo, hi = np.percentile(valid_i, [1, 99]) if valid_i.size else (0.0, 1.0)
    gray = np.clip((inten - lo) / max(hi - lo, 1e-12), 0, 1)
    rows = [
        colormaps["gray"](gray)[..., :3],
        colormaps["RdBu_r"]((np.asarray(n_lat_gt) + normal_limit) / (2 * normal_limit))[..., :3],
        colormaps["RdBu_r"]((np.asarray(n_lat_pred) + normal_limit) / (2 * normal_limit))[..., :3],
        colormaps["magma"](np.abs(np.asarray(n_lat_pred) - n_lat_gt) / normal_limit)[..., :3],
    ]
    spacer = np.ones((gap, shape[1], 3))
    parts = []
    for i, rgb in enumerate(rows):
        rgb = np.where(mask[..., None], np.nan_to_num(rgb), 0.0)
        parts += [rgb] if i == 0 else [spacer, rgb]
    return (np.concatenate(parts, axis=0) * 255).round().astype(np.uint8)


class NormalImageLogger(pl.Callback):
    """Every ``every_n_epochs`` validation epochs, logs input / GT / prediction / error images
    of ``n_images`` fixed validation windows to TensorBoard (``val_images/window_{i}``).

    The windows are the ones with the most valid pixels in the first validation batch (taken
    once, so the same windows are shown every time). Nothing happens without a
    ``TensorBoardLogger``.
    """

    def __init__(self, every_n_epochs: int = 5, n_images: int = 4) -> None:
        if not isinstance(every_n_epochs, int) or every_n_epochs < 1:
            raise ValueError(f"every_n_epochs: expected an integer >= 1, found {every_n_epochs!r}")
        if not isinstance(n_images, int) or n_images < 1:
            raise ValueError(f"n_images: expected an integer >= 1, found {n_images!r}")
        self.every_n_epochs = every_n_epochs
        self.n_images = n_images
        self.windows: dict[str, torch.Tensor] | None = None
        self.normal_limit = 0.5

    def on_validation_batch_end(
        self,
        trainer: pl.Trainer,
        pl_module: pl.LightningModule,
        outputs: Any,
        batch: Mapping[str, torch.Tensor],
        batch_idx: int,
        dataloader_idx: int = 0,
    ) -> None:
        if self.windows is not None or tensorboard_logger(trainer) is None:
            return
        valid = batch["mask"].flatten(1).sum(1)
        pick = torch.argsort(valid, descending=True, stable=True)[: self.n_images]
        keys = ["intensity", "n_lat", "mask", *(["inputs"] if "inputs" in batch else [])]
        self.windows = {k: batch[k][pick].detach().cpu().clone() for k in keys}
        gt = self.windows["n_lat"][self.windows["mask"]].abs()
        if gt.numel():
            # colour range from the shown windows' ground truth (n_lat is mostly near 0)
            self.normal_limit = max(0.05, float(torch.quantile(gt.float(), 0.98)))

    def on_validation_epoch_end(self, trainer: pl.Trainer, pl_module: pl.LightningModule) -> None:
        tb = tensorboard_logger(trainer)
        if tb is None or self.windows is None or trainer.sanity_checking:
            return
        if trainer.current_epoch % self.every_n_epochs:
            return
        with torch.no_grad():
            inputs = pl_module.batch_inputs(self.windows)
            pred = pl_module(inputs.to(pl_module.device)).float().cpu()
        for i in range(pred.shape[0]):
            panel = render_window_panel(
                self.windows["intensity"][i, 0].numpy(),
                self.windows["n_lat"][i, 0].numpy(),
                pred[i, 0].numpy(),
                self.windows["mask"][i, 0].numpy(),
                self.normal_limit,
            )
            tb.experiment.add_image(
                f"val_images/window_{i}", panel, trainer.global_step, dataformats="HWC"
            )


class SirenMapImages(pl.Callback):
    """Logs a SIREN fit's latest map evaluation to TensorBoard once: bathymetry, gradient
    HSV and (with an MBES grid) the signed error.

    Reads the module's ``latest_evaluation`` (a frozen
    :class:`~sss2bathy.modules.siren_parts.MapEvaluation`, made every
    ``eval_every_n_epochs`` epochs) after each validation epoch; an evaluation already
    logged is not logged again.
    """

    def __init__(self) -> None:
        self._logged: Any = None

    def on_validation_epoch_end(self, trainer: pl.Trainer, pl_module: pl.LightningModule) -> None:
        ev = getattr(pl_module, "latest_evaluation", None)
        if trainer.sanity_checking or not trainer.is_global_zero or ev is None:
            return
        if ev is self._logged:
            return
        self._logged = ev
        pred, region = ev.pred, ev.region
        loggers = [lg for lg in trainer.loggers if isinstance(lg, TensorBoardLogger)]
        if not loggers:
            return
        shown = np.where(region, pred.heights, np.nan) if region is not None else pred.heights
        title = pl_module.map_title() if hasattr(pl_module, "map_title") else "SIREN"
        inputs = getattr(pl_module, "inputs", None)
        origin = getattr(inputs, "origin", None)
        extent = (
            float(pred.x[0] - pred.cell_size / 2),
            float(pred.x[-1] + pred.cell_size / 2),
            float(pred.y[0] - pred.cell_size / 2),
            float(pred.y[-1] + pred.cell_size / 2),
        )
        dzdx, dzdy = map_gradient(shown, pred.cell_size)
        norm = np.hypot(dzdx, dzdy)
        vmax = float(np.nanpercentile(norm, 99)) if np.isfinite(norm).any() else None
        figures = {
            "map/bathymetry": lambda: map_figure(
                shown, f"{title}: bathymetry", extent=extent, origin=origin
            ),
            "map/gradient_hsv": lambda: map_figure(
                gradient_hsv(dzdx, dzdy, vmax),
                f"{title}: gradient (hue: upslope direction)",
                extent=extent,
                origin=origin,
                vmax=vmax,
            ),
        }
        if ev.truth is not None:
            err = error_map(pred, ev.truth, region)
            figures["map/signed_error"] = lambda: map_figure(
                err,
                f"{title}: map - MBES",
                cmap="RdBu_r",
                symmetric=True,
                label=ERROR_LABEL,
                extent=extent,
                origin=origin,
            )
        for tag, make in figures.items():
            for logger in loggers:  # a labelled figure (colour bar, axes, north), not raw pixels
                logger.experiment.add_figure(tag, make(), trainer.global_step, close=True)


__all__ = ["NormalImageLogger", "SirenMapImages", "render_window_panel", "tensorboard_logger"]
