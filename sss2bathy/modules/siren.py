"""SIREN bathymetry fit (paper "Training SIREN"): wiring only.

One training step: ``loss = sensor.loss(geo, target) + w_height * height_loss(altimeter)``
(eq. 7-9), with ``geo`` the crossings of the batch's usable bins with the SIREN and its
normals there (:func:`sss2bathy.models.arc_fit.arc_geometry`, eq. 10-12 then 1-3),
warm-started from each bin's last crossing (``theta_cache (n_pings, 2, n_bins)``). The
``sensor`` chooses the fit:

* a :class:`~sss2bathy.models.sensors.SensorModel` (normals, Lambertian): the above;
* ``None``: the altimeter height loss alone (the heights-only baseline);
* :class:`~sss2bathy.models.direct_fit.MBESCellFit`: SIREN-Direct-Fit, MBES cells in place
  of the sidescan (``conf/model/siren_direct_fit.yaml``).

The SIREN's frame and the survey come from the datamodule as one
:class:`~sss2bathy.data.siren_inputs.SirenInputs` in :meth:`SirenModule.setup`. The SIREN
is built in ``__init__`` (checkpoints load into an identically shaped model) and its frame
is a persistent buffer (a loaded checkpoint keeps the frame it was trained with).

Evaluation every ``eval_every_n_epochs`` epochs and at the last epoch
(:class:`~sss2bathy.modules.siren_parts.MapScorer`): logged as ``val/map_mae_m``,
``val/map_std_m``, ``val/map_grad_cs`` and the held-out altimeter scores
(``val/holdout_alt_mae_m``, ``val/holdout_interp_mae_m``, ``val/holdout_ratio``;
:data:`sss2bathy.metrics.bathy.MAP_TAGS`); the latest is :attr:`latest_evaluation` (a
frozen :class:`~sss2bathy.modules.siren_parts.MapEvaluation`, read by the callbacks).
:meth:`configure_callbacks` adds the map export (``map.tif``, ``map.npz``,
``metrics.json``, PNGs into ``output_dir``; :class:`~sss2bathy.callbacks.SirenMapExport`)
and, with ``log_images``, the TensorBoard map images.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Callable, Mapping
from typing import Any

import numpy as np
import pytorch_lightning as pl
import torch
from pytorch_lightning.callbacks import Callback

from sss2bathy.callbacks import SirenMapExport, SirenMapImages
from sss2bathy.data.siren_inputs import SirenInputs
from sss2bathy.losses.shadow import (
    depression_angle,
    extended_shadow,
    occlusion_loss,
    shadow_run_bins,
)
from sss2bathy.losses.siren import height_loss, total_loss
from sss2bathy.models.arc_fit import arc_geometry
from sss2bathy.models.direct_fit import MBESCellFit
from sss2bathy.models.intersection import FinderSettings
from sss2bathy.models.normal_sensor import NormalSensorModel
from sss2bathy.models.sensors import ArcGeometry, SensorModel
from sss2bathy.models.siren import Siren, TwoScaleSiren
from sss2bathy.modules.siren_parts import (
    SELECT_BEST,
    BestSnapshot,
    MapEvaluation,
    MapScorer,
    describe_fit,
    finite_metrics,
    param_groups,
    swath_inputs,
)
from sss2bathy.survey.masks import MASK_SHADOW
from sss2bathy.utils.checks import require_number

log = logging.getLogger(__name__)

# logged every evaluation (metrics.bathy.MAP_TAGS: what and in which unit)
VAL_TAGS = (
    "map_mae_m", "map_std_m", "map_grad_cs",
    "holdout_alt_mae_m", "holdout_interp_mae_m", "holdout_ratio",
)  # fmt: skip


def _positive_or_none(name: str, value: float | None) -> float | None:
    if value is not None and not value > 0:
        raise ValueError(f"{name}: expected a positive learning rate or None, found {value}")
    return None if value is None else float(value)


def _two_scale_switch(name: str, value: Any, siren: Siren, what: str) -> bool:
    """``value`` checked as a switch that only a :class:`TwoScaleSiren` may turn on."""
    if not isinstance(value, bool):
        raise ValueError(f"{name}: expected true or false, found {value!r}")
    if value and not isinstance(siren, TwoScaleSiren):
        raise ValueError(f"{name}: expected false for a one-scale SIREN ({what}), found {value}")
    return value


class SirenModule(pl.LightningModule):
    """Fits a :class:`~sss2bathy.models.siren.Siren` to sidescan + altimeter data.

    Args:
        siren: a ``Siren`` or a callable returning one (a Hydra ``_partial_``).
        sensor: a ``SensorModel``, an ``MBESCellFit`` or ``None`` (module docstring).
        w_height: ``w_H`` of eq. 7.
        optimizer, scheduler: partial ``torch.optim`` optimizer (called with the parameter
            groups) and LR scheduler (called with the optimizer, stepped per epoch).
        finder: intersection-finder settings, fields of
            :class:`~sss2bathy.models.intersection.FinderSettings` (the one source of their
            defaults).
        eval_every_n_epochs: epochs between map evaluations (also at the end of the fit).
        eval_cell_m: map cell (m) when the survey has no MBES grid.
        region_radius_m: scored area's radius around the tracks (m); default the swath
            half-width from the datamodule.
        output_dir: folder of the final map files (default: the logger's ``save_dir``, else
            the trainer's ``default_root_dir``).
        log_images: add the TensorBoard map images.
        sensor_lr, encoding_lr: learning rates of the sensor model's and the SIREN input
            encoding's parameters; ``None`` = the optimizer's.
        select_best: the final map is the SIREN of the evaluation with the lowest such
            metric (:data:`~sss2bathy.modules.siren_parts.SELECT_BEST`), or the last (None).
        title: names the run in its map figures (e.g. ``"siren_gt_n2d on synthetic_d1_demo"``);
            None = the sensor model's title.
        line_offset: learn one ``n_lat`` offset per (line, side) of the target normals (a
            self-calibration of the CNN's bias, :mod:`sss2bathy.models.normal_sensor`); only
            with a :class:`~sss2bathy.models.normal_sensor.NormalSensorModel`.
        line_offset_weight: weight of the offsets' mean square in the loss (>= 0).
        w_shadow: weight of the occlusion term (:mod:`sss2bathy.losses.shadow`, radians):
            the bins the data mask as shadow (``MASK_SHADOW`` alone) must be hidden from the
            sonar by what is closer along their ping, and the bins the sensor model uses
            must be seen; 0 = off (the paper). With a sidescan sensor model only.
        shadow_min_m: a shadow counts only where it runs at least this far along range (m;
            a morphological opening of the mask: dark speckle at far range is no shadow).
        w_detail: weight of a :class:`~sss2bathy.models.siren.TwoScaleSiren`'s detail
            penalty (its mean squared detail height, m^2, over ``detail_points`` points drawn
            uniformly in the bounds each step): the detail network rises only where the
            data ask for it; 0 = off (and required for a one-scale SIREN).
        shadow_on_detail: with a ``TwoScaleSiren``, the occlusion term moves the detail
            network only (the base's height enters it detached), so what a shadow asks for
            is relief, not a tilt of the whole map.
        heights_on_base: with a ``TwoScaleSiren``, the altimeter heights move the base only
            (the detail's height enters their loss detached): the detail cannot bend to fit
            the altimeter's points, which it would not carry across a gap.
        detail_nadir: with ``w_detail``, the penalty adds the detail's mean square under the
            batch's pings (their nadir, which no sidescan bin images), so the depths along
            the track, the altimeter's, are the base's alone.
    """

    def __init__(
        self,
        siren: Siren | Callable[[], Siren],
        sensor: SensorModel | MBESCellFit | None = None,
        w_height: float = 1.0,
        optimizer: Callable[..., torch.optim.Optimizer] | None = None,
        scheduler: Callable[..., Any] | None = None,
        finder: FinderSettings | Mapping[str, Any] | None = None,
        eval_every_n_epochs: int = 50,
        eval_cell_m: float = 0.5,
        region_radius_m: float | None = None,
        output_dir: str | None = None,
        log_images: bool = True,
        sensor_lr: float | None = None,
        encoding_lr: float | None = None,
        select_best: str | None = None,
        title: str | None = None,
        line_offset: bool = False,
        line_offset_weight: float = 1.0,
        w_shadow: float = 0.0,
        shadow_min_m: float = 0.25,
        w_detail: float = 0.0,
        detail_points: int = 4096,
        shadow_on_detail: bool = False,
        heights_on_base: bool = False,
        detail_nadir: bool = False,
    ) -> None:
        super().__init__()
        self.save_hyperparameters(
            ignore=["siren", "sensor", "optimizer", "scheduler"], logger=False
        )
        self.siren = siren if isinstance(siren, Siren) else siren()
        if not isinstance(self.siren, Siren):
            raise ValueError(f"siren: expected a Siren or a factory of one, found {type(siren)}")
        if sensor is not None and not isinstance(sensor, SensorModel | MBESCellFit):
            raise ValueError(
                f"sensor: expected a SensorModel, an MBESCellFit or None, found "
                f"{type(sensor).__name__}"
            )
        if w_height < 0:
            raise ValueError(f"w_height: expected a non-negative weight, found {w_height}")
        if int(eval_every_n_epochs) < 1:
            raise ValueError(f"eval_every_n_epochs: expected >= 1, found {eval_every_n_epochs}")
        if not isinstance(line_offset, bool):
            raise ValueError(f"line_offset: expected true or false, found {line_offset!r}")
        if line_offset:
            if not isinstance(sensor, NormalSensorModel):
                raise ValueError(
                    "line_offset: expected the normal sensor model (SIREN-GT-N2d / CNN-N2d) "
                    f"with line_offset=true, found sensor {type(sensor).__name__}"
                )
            sensor.enable_line_offset(line_offset_weight)
        self.sensor = sensor
        self.w_height = float(w_height)
        self.w_shadow = float(
            require_number("w_shadow", w_shadow, lambda v: v >= 0, "a weight >= 0 (0 = off)")
        )
        self.shadow_min_m = float(
            require_number("shadow_min_m", shadow_min_m, lambda v: v >= 0, "a length >= 0 (m)")
        )
        self._shadow_min_bins: int | None = None  # shadow_min_m in bins, from the first batch
        self.w_detail = float(
            require_number("w_detail", w_detail, lambda v: v >= 0, "a weight >= 0 (0 = off)")
        )
        self.detail_points = int(
            require_number("detail_points", detail_points, lambda v: v >= 1, "a count >= 1")
        )
        self.shadow_on_detail = _two_scale_switch(
            "shadow_on_detail", shadow_on_detail, self.siren,
            "it moves a TwoScaleSiren's detail network only",
        )  # fmt: skip
        self.heights_on_base = _two_scale_switch(
            "heights_on_base", heights_on_base, self.siren,
            "the altimeter then fits a TwoScaleSiren's base only",
        )  # fmt: skip
        self.detail_nadir = _two_scale_switch(
            "detail_nadir", detail_nadir, self.siren,
            "the detail penalty then also holds the detail at zero under each ping",
        )  # fmt: skip
        if self.w_detail > 0 and not isinstance(self.siren, TwoScaleSiren):
            raise ValueError(
                f"w_detail: expected 0 for a one-scale SIREN (model.siren._target_ "
                f"{type(self.siren).__name__}; the penalty is on a TwoScaleSiren's detail), "
                f"found {w_detail}"
            )
        if self.w_shadow > 0 and not isinstance(sensor, SensorModel):
            raise ValueError(
                f"w_shadow: expected 0 without a sidescan sensor model (found sensor "
                f"{type(sensor).__name__}), found {w_shadow}"
            )
        self.optimizer_factory = optimizer or (lambda params: torch.optim.Adam(params, lr=2e-4))
        self.scheduler_factory = scheduler
        self.finder = FinderSettings.from_mapping(finder)
        self.eval_every_n_epochs = int(eval_every_n_epochs)
        self.eval_cell_m = float(
            require_number("eval_cell_m", eval_cell_m, lambda v: v > 0, "a positive number (m)")
        )
        self.region_radius_m = require_number(
            "region_radius_m",
            region_radius_m,
            lambda v: v > 0,
            "a positive number (m) or null",
            optional=True,
        )
        self.output_dir = output_dir
        self.log_images = bool(log_images)
        self.sensor_lr = _positive_or_none("sensor_lr", sensor_lr)
        self.encoding_lr = _positive_or_none("encoding_lr", encoding_lr)
        self.best = BestSnapshot(select_best)
        self.title = None if title is None else str(title)
        self.register_buffer("framed", torch.tensor(False))
        self.register_buffer("theta_cache", torch.zeros(0, 2, 0), persistent=False)
        self.final_metrics: dict[str, float] = {}
        self.theta_limits: tuple[float, float] | None = None
        self.inputs: SirenInputs | None = None
        self.scorer: MapScorer | None = None
        self.latest_evaluation: MapEvaluation | None = None
        # per-epoch sums of the training step's terms and statistics (training_step)
        self._train_sums: dict[str, tuple[torch.Tensor, int]] = {}

    # ------------------------------------------------------------------ set-up
    def setup(self, stage: str) -> None:
        inputs = self.inputs = SirenInputs.of(getattr(self.trainer, "datamodule", None))
        if not bool(self.framed):
            self.siren.set_frame(inputs.bounds, inputs.z_range)
            self.framed.fill_(True)
        self.theta_limits = inputs.sensor.beam_limits_rad
        self.theta_cache = torch.full((inputs.n_pings, 2, inputs.n_bins), torch.nan)
        radius = self.region_radius_m or inputs.swath_half_width_m
        # the written map's coverage: the bins the fit uses (none for heights only) and the
        # fitted altimeter points; the MBES scores keep the track region (``radius``)
        swath = swath_inputs(
            getattr(self.trainer, "datamodule", None), uses_sidescan=self.sensor is not None
        )
        alt = inputs.altimeter
        self.scorer = MapScorer.for_survey(
            inputs.bounds, inputs.grid, inputs.track_xy, radius, self.eval_cell_m,
            inputs.holdout, swath=swath,
            altimeter_xy=None if alt is None else alt[:, :2].cpu().numpy().astype(np.float64),
            origin=inputs.origin,
        )  # fmt: skip
        if isinstance(self.sensor, MBESCellFit):
            grid = inputs.grid
            self.sensor.set_cells_from_grid(
                *((grid.x, grid.y, grid.heights) if grid is not None else (None, None, None)),
                self.scorer.region,
            )
        elif self.sensor is not None:
            self.sensor.setup_from_data(inputs.sensor, inputs.range_m)
            if hasattr(self.sensor, "setup_lines"):
                self.sensor.setup_lines(inputs.n_lines)

    def on_save_checkpoint(self, checkpoint: dict[str, Any]) -> None:
        # the warm-start angles steer the finder, so a resumed fit needs them to continue
        # exactly (kept out of the state dict: they are sized by the survey)
        if self.theta_cache.numel():
            checkpoint["theta_cache"] = self.theta_cache.detach().cpu()

    def on_load_checkpoint(self, checkpoint: dict[str, Any]) -> None:
        cache = checkpoint.get("theta_cache")
        if cache is None or not self.theta_cache.numel():
            return  # not set up (a plain load of the weights) or an older checkpoint
        if tuple(cache.shape) != tuple(self.theta_cache.shape):
            log.warning(
                "checkpoint warm-start cache %s does not match this survey's %s; solving cold",
                tuple(cache.shape),
                tuple(self.theta_cache.shape),
            )
            return
        self.theta_cache.copy_(cache)

    def configure_optimizers(self) -> dict[str, Any]:
        groups = param_groups(self.siren, self.sensor, self.encoding_lr, self.sensor_lr)
        opt = self.optimizer_factory(params=groups)
        if self.scheduler_factory is None:
            return {"optimizer": opt}
        sched = self.scheduler_factory(optimizer=opt)
        # per epoch (torch's schedulers), unless the scheduler says otherwise (the wall-clock
        # decay of siren_schedule=budget steps every optimiser step)
        interval = getattr(sched, "interval", "epoch")
        return {"optimizer": opt, "lr_scheduler": {"scheduler": sched, "interval": interval}}

    def configure_callbacks(self) -> list[Callback]:
        export = SirenMapExport(self.output_dir)
        return [export, SirenMapImages()] if self.log_images else [export]

    # ------------------------------------------------------------------ steps
    def sidescan_geometry(
        self, batch: dict[str, torch.Tensor]
    ) -> tuple[ArcGeometry, torch.Tensor, dict[str, torch.Tensor]]:
        """:func:`~sss2bathy.models.arc_fit.arc_geometry` of the bins the sensor can use,
        and their targets."""
        geo, stats, _ = self._crossings(batch, with_shadow=False)
        return geo, batch[self.sensor.target_key][geo.ping, geo.side, geo.bin], stats

    def _crossings(
        self, batch: dict[str, torch.Tensor], with_shadow: bool
    ) -> tuple[ArcGeometry, dict[str, torch.Tensor], torch.Tensor | None]:
        """The crossings of the sensor's bins and, ``with_shadow``, also of the bins the data
        mask as shadow: ``(geometry, finder statistics, (N,) bool shadow or None)``."""
        cache = self.theta_cache if self.theta_cache.numel() else None
        use = self.sensor.bin_mask(batch)
        shadow_bins = None
        if with_shadow:
            if self._shadow_min_bins is None:  # the bins' ranges never change: read them once
                self._shadow_min_bins = shadow_run_bins(self.shadow_min_m, batch["range_m"])
            shadow_bins = extended_shadow(batch["mask"] == MASK_SHADOW, self._shadow_min_bins)
            use = use | shadow_bins
        if "keep" in batch:  # the bins drawn for this step (data.bin_fraction < 1)
            use = use & batch["keep"]
        geo, stats = arc_geometry(self.siren, batch, use, self.theta_limits, self.finder, cache)
        shadow = None if shadow_bins is None else shadow_bins[geo.ping, geo.side, geo.bin]
        return geo, stats, shadow

    def model_step(self, batch: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
        """Loss terms and statistics of one batch (module docstring)."""
        alt = batch["altimeter"]
        if self.heights_on_base:  # the altimeter fits the base; the detail enters detached
            xy = alt[:, :2]
            z = self.siren.base_height(xy) + self.siren.detail.height(xy).detach()
        else:
            z = self.siren.height(alt[:, :2])
        loss_height = height_loss(z, alt[:, 2])
        if isinstance(self.sensor, MBESCellFit):
            loss, logs = self.sensor.loss(self.siren)
            return {"loss": loss, **logs, "loss_height": loss_height.detach()}
        if self.sensor is None:
            return {"loss": loss_height, "loss_height": loss_height.detach()}
        every, stats, shadow = self._crossings(batch, with_shadow=self.w_shadow > 0)
        geo = every if shadow is None else every.select(~shadow)
        target = batch[self.sensor.target_key][geo.ping, geo.side, geo.bin]
        loss_sensor, sensor_logs = self.sensor.loss(geo, target)
        loss = total_loss(loss_sensor, loss_height, self.w_height)
        out = {}
        if shadow is not None:
            height = every.height
            if self.shadow_on_detail:  # the base's height enters detached: the detail moves
                # (one pass of the small detail network, not of the base)
                detail = self.siren.detail.height(every.points[:, :2])
                height = (height - detail).detach() + detail
            angle = depression_angle(every.points, height, every.sonar)
            shape = (int(batch["mask"].shape[0]), 2, int(batch["mask"].shape[-1]))
            loss_shadow, shadow_logs = occlusion_loss(
                angle, every.ping, every.side, every.bin, shadow, shape
            )
            loss = loss + self.w_shadow * loss_shadow
            out["loss_shadow"] = loss_shadow.detach()
            out.update({f"shadow/{k}": v for k, v in shadow_logs.items()})
        out = {
            "loss": loss,
            "loss_sensor": loss_sensor.detach(),
            "loss_height": loss_height.detach(),
            **stats,
            **out,
        }
        out.update({f"sensor/{k}": torch.as_tensor(v).detach() for k, v in sensor_logs.items()})
        return out

    def training_step(self, batch: dict[str, torch.Tensor], batch_idx: int) -> torch.Tensor:
        out = self.model_step(batch)
        if self.w_detail > 0:
            penalty = self.siren.detail_penalty(self.detail_points)
            if self.detail_nadir:  # under each ping: the nadir gap, which no bin images
                penalty = (
                    penalty + self.siren.detail.height(batch["position"][:, :2]).square().mean()
                )
            out["loss"] = out["loss"] + self.w_detail * penalty
            out["loss_detail"] = penalty.detach()
        n = int(batch["position"].shape[0])
        self.log("train/loss", out["loss"].detach(), on_step=True, on_epoch=True,
                 prog_bar=True, batch_size=n)  # fmt: skip
        # The other terms and statistics: epoch means weighted by the batch's pings, as
        # Lightning's on_epoch logging makes them, summed here and logged once an epoch
        # (each self.log call costs Python work per step; a small step made 7-8 of them)
        for key, value in out.items():
            if key != "loss":
                total, weight = self._train_sums.get(key, (0.0, 0))
                self._train_sums[key] = (total + value.detach().float() * n, weight + n)
        return out["loss"]

    def on_train_epoch_start(self) -> None:
        self._train_sums = {}

    def on_train_epoch_end(self) -> None:
        for key, (total, weight) in self._train_sums.items():
            self.log(f"train/{key}", total / weight, on_step=False, on_epoch=True)

    # -------------------------------------------------------------- evaluation
    def evaluate_map(self) -> MapEvaluation:
        """The SIREN on the evaluation grid and its metrics; also kept as
        :attr:`final_metrics` (``final/<name>``)."""
        evaluation = self.scorer.evaluate(self.siren, self.current_epoch)
        self.final_metrics = finite_metrics(evaluation.metrics)
        return evaluation

    def validation_step(self, batch: Any, batch_idx: int) -> None:
        epoch, max_epochs = self.current_epoch + 1, self.trainer.max_epochs
        last = max_epochs is not None and max_epochs > 0 and epoch >= max_epochs
        if self.trainer.sanity_checking or not (epoch % self.eval_every_n_epochs == 0 or last):
            return
        self.latest_evaluation = evaluation = self.evaluate_map()
        for tag, value in evaluation.tags("val/").items():
            if tag.split("/", 1)[1] in VAL_TAGS and math.isfinite(value):
                self.log(tag, value, batch_size=1)
        self.best.track(self.siren, evaluation.metrics, self.current_epoch)

    def final_map(self) -> MapEvaluation:
        """The final map: the last SIREN's, or the ``select_best`` one's when that beats it
        (its SIREN is loaded back); ``map_epoch`` says which epoch the map shows."""
        evaluation = self.evaluate_map()
        best_epoch = self.best.restore(self.siren, evaluation.metrics)
        if best_epoch is not None:
            log.info(
                "final map: the SIREN of epoch %d (lowest %s %.4g; last epoch %.4g)",
                best_epoch, self.best.metric, self.best.best["value"],
                evaluation.metrics.get(self.best.metric, float("nan")),
            )  # fmt: skip
            evaluation = self.evaluate_map()
        map_epoch = int(self.current_epoch) if best_epoch is None else best_epoch
        self.final_metrics["final/map_epoch"] = float(map_epoch)
        self.latest_evaluation = MapEvaluation(
            evaluation.pred, evaluation.metrics, int(self.current_epoch),
            evaluation.truth, evaluation.region, map_epoch, evaluation.coverage,
        )  # fmt: skip
        return self.latest_evaluation

    def map_title(self) -> str:
        if self.title:
            return self.title
        if self.sensor is None:
            return "heights only"
        return getattr(self.sensor, "title", type(self.sensor).__name__)

    def hparams_for_log(self) -> dict[str, Any]:
        """Flat hyper-parameters for the loggers' HPARAMS (:func:`describe_fit`, the lr)."""
        flat = describe_fit(self.siren, self.sensor, self.w_height, self.finder)
        opt = self.trainer.optimizers[0] if self.trainer.optimizers else None
        if opt is not None:
            flat["lr"] = opt.defaults.get("lr")
        return flat


__all__ = ["SELECT_BEST", "SirenModule", "arc_geometry"]
