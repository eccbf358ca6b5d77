"""TensorBoard figures of a Lambertian SIREN fit (a Lightning callback,
``callbacks=lambert_curves``).

Outside :mod:`sss2bathy.models` (which knows nothing of Lightning); the model it draws is
:class:`~sss2bathy.models.lambertian.LambertianSensorModel`. With any other sensor model
it does nothing, so it can sit in every SIREN run's callbacks.
"""

from __future__ import annotations

import logging
import math
from typing import Any

import numpy as np
import pytorch_lightning as pl
import torch

from sss2bathy.models.lambertian import LambertianSensorModel, waterfall_image

log = logging.getLogger(__name__)


def _tensorboard_writer(trainer: Any) -> Any | None:
    """The ``SummaryWriter`` of the trainer's first TensorBoard logger, or None."""
    from pytorch_lightning.loggers import TensorBoardLogger

    for logger in getattr(trainer, "loggers", None) or []:
        if isinstance(logger, TensorBoardLogger):
            return logger.experiment
    return None


class LambertCurvesLogger(pl.Callback):
    """TensorBoard figures of a Lambertian SIREN fit, every ``every_n_epochs`` epochs.

    * ``lambert/beam_pattern``: learned ``B(theta)`` over the beam (deg), knots marked;
    * ``lambert/range_gain``: learned ``G(r)`` over its span (m), knots marked;
    * ``lambert/waterfall``: measured vs predicted intensity of line ``waterfall_line``
      (index in the datamodule's lines; ``waterfall_max_pings`` pings spread along it), via
      the SIREN module's ``sidescan_geometry`` and the datamodule's ping ``table``.

    Does nothing (debug log) when the module's ``sensor`` is not a
    :class:`LambertianSensorModel` or no TensorBoard logger is attached; no waterfall when
    the module or datamodule lacks what it needs.
    """

    def __init__(
        self,
        every_n_epochs: int = 10,
        n_points: int = 200,
        waterfall_line: int = 0,
        waterfall_max_pings: int = 256,
    ) -> None:
        super().__init__()
        if every_n_epochs < 1:
            raise ValueError(f"every_n_epochs: expected >= 1, found {every_n_epochs}")
        if n_points < 2:
            raise ValueError(f"n_points: expected >= 2, found {n_points}")
        if waterfall_max_pings < 1:
            raise ValueError(f"waterfall_max_pings: expected >= 1, found {waterfall_max_pings}")
        self.every_n_epochs = int(every_n_epochs)
        self.n_points = int(n_points)
        self.waterfall_line = int(waterfall_line)
        self.waterfall_max_pings = int(waterfall_max_pings)

    def on_train_epoch_end(self, trainer: pl.Trainer, pl_module: pl.LightningModule) -> None:
        epoch = trainer.current_epoch + 1
        last = trainer.max_epochs is not None and epoch >= trainer.max_epochs
        if not trainer.is_global_zero or (epoch % self.every_n_epochs and not last):
            return
        sensor = getattr(pl_module, "sensor", None)
        if not isinstance(sensor, LambertianSensorModel):
            log.debug("LambertCurvesLogger: module has no LambertianSensorModel; skipped")
            return
        writer = _tensorboard_writer(trainer)
        if writer is None:
            log.debug("LambertCurvesLogger: no TensorBoard logger; skipped")
            return
        step = trainer.global_step
        for tag, figure in self.curve_figures(sensor).items():
            writer.add_figure(tag, figure, global_step=step)
        figure = self.waterfall_figure(trainer, pl_module)
        if figure is not None:
            writer.add_figure("lambert/waterfall", figure, global_step=step)

    def curve_figures(self, sensor: LambertianSensorModel) -> dict[str, Any]:
        """``{tag: matplotlib Figure}`` of the learned beam pattern and range gain."""
        import matplotlib

        matplotlib.use("Agg", force=False)
        import matplotlib.pyplot as plt

        figures = {}
        theta, beam = sensor.beam_pattern_curve(self.n_points)
        r, gain = sensor.gain_curve(self.n_points)
        curves = (
            (
                "lambert/beam_pattern",
                np.degrees(theta.cpu().numpy()),
                beam,
                np.degrees(sensor.beam_knots_rad.cpu().numpy()),
                sensor.beam_values(),
                "depression angle (deg)",
                "B",
            ),
            (
                "lambert/range_gain",
                r.cpu().numpy(),
                gain,
                sensor.gain_knots_m.cpu().numpy(),
                sensor.gain_values(),
                "slant range (m)",
                "G",
            ),
        )
        for tag, x, y, kx, ky, xlabel, ylabel in curves:
            fig, ax = plt.subplots(figsize=(5, 3.2))
            ax.plot(x, y.cpu().numpy(), "-")
            ax.plot(kx, ky.detach().cpu().numpy(), "o")
            ax.set_xlabel(xlabel)
            ax.set_ylabel(f"{ylabel} (K = {float(sensor.scale):.3g})")
            ax.grid(True, alpha=0.3)
            fig.tight_layout()
            figures[tag] = fig
        return figures

    def line_batch(self, datamodule: Any) -> dict[str, torch.Tensor] | None:
        """Ping batch of ``waterfall_line``: at most ``waterfall_max_pings`` pings spread
        evenly along it, from the datamodule's ping table (``table.line``, ``table.gather``)."""
        table = getattr(datamodule, "table", None)
        if table is None or getattr(table, "intensity", None) is None:
            return None
        index = (table.line == self.waterfall_line).nonzero().squeeze(-1)
        if index.numel() == 0:
            return None
        stride = math.ceil(index.numel() / self.waterfall_max_pings)
        return table.gather(index[::stride])

    def waterfall_figure(self, trainer: Any, pl_module: Any) -> Any | None:
        """Measured | predicted waterfall figure of the fixed line, or None when unavailable.

        Uses the module's ``sidescan_geometry(batch) -> (ArcGeometry, target, stats)`` (the
        crossings of the bins its sensor uses) on :meth:`line_batch`; the measured panel
        shows every bin, the predicted one the bins with a crossing.
        """
        geometry = getattr(pl_module, "sidescan_geometry", None)
        batch = self.line_batch(getattr(trainer, "datamodule", None))
        if geometry is None or batch is None:
            log.debug("LambertCurvesLogger: no sidescan_geometry() or intensity table; skipped")
            return None
        with torch.no_grad():
            geo, _, _ = geometry(batch)
            pred = pl_module.sensor.predict(geo)
        import matplotlib

        matplotlib.use("Agg", force=False)
        import matplotlib.pyplot as plt

        measured = batch["intensity"].cpu().numpy()
        n_pings, n_bins = measured.shape[0], measured.shape[-1]
        idx = [t.cpu().numpy() for t in (geo.ping, geo.side, geo.bin)]
        images = [
            np.concatenate([measured[:, 0, ::-1], measured[:, 1]], axis=1),
            waterfall_image(*idx, pred.cpu().numpy(), n_pings, n_bins),
        ]
        vmax = float(np.nanpercentile(images[0], 99)) if np.isfinite(images[0]).any() else 1.0
        cmap = plt.get_cmap("copper").with_extremes(bad="black")
        fig, axes = plt.subplots(1, 2, figsize=(10, 4), sharey=True)
        for ax, image, title in zip(axes, images, ("measured", "predicted"), strict=True):
            ax.imshow(image, cmap=cmap, vmin=0.0, vmax=vmax, aspect="auto", interpolation="nearest")
            ax.set_title(f"line {self.waterfall_line}: {title}")
            ax.set_xlabel("port  <- bin ->  starboard")
        axes[0].set_ylabel("ping (subsampled)")
        fig.tight_layout()
        return fig
