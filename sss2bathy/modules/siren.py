"""SIREN bathymetry fit (paper "Training SIREN"), and SIREN-Direct-Fit.

One training step (``direct_fit=False``):

1. the batch's bins (ping x side x bin) that the sensor model can use (``bin_mask``);
2. under ``no_grad``, the depression angle where each bin's isotemporal arc crosses the
   SIREN (:func:`~sss2bathy.models.intersection.find_intersections`), warm-started from
   the bin's previous solution (``theta_cache (n_pings, 2, n_bins)``, NaN = none yet,
   +inf = no crossing last time);
3. at the valid crossings, the SIREN's height gradient with a graph
   (:meth:`~sss2bathy.models.siren.Siren.height_and_gradient`), the head-plane normal
   (eq. 1-3) and an :class:`~sss2bathy.models.sensors.ArcGeometry`;
4. ``loss = sensor.loss(geo, target) + w_height * height_loss(altimeter)`` (eq. 7-9).

Without a sensor model (``sensor=None``) the loss is the altimeter height loss alone: the
heights-only baseline. ``direct_fit=True`` (SIREN-Direct-Fit, the paper's capacity check)
replaces all that by
``mean |Phi(x, y) - z_MBES|`` over ``direct_fit_points`` random MBES cells of the scored
region per step.

The SIREN's frame (input bounds, output height range) comes from the datamodule in
:meth:`SirenModule.setup` (``set_frame``; sonar tracks and altimeter heights only, never
the MBES grid). The SIREN itself is built in ``__init__`` (so checkpoints load into an
identically shaped model) and its frame is a persistent buffer (so a loaded checkpoint
keeps the frame it was trained with).

Evaluation: every ``eval_every_n_epochs`` epochs (validation loop, one dummy batch) and
at the end of the fit the SIREN is sampled on the MBES grid (or, without one, on a grid of
``eval_cell_m`` over the bounds) and scored over the *surveyed area*: cells within the
swath half-width (``sqrt(r_max^2 - median altitude^2)``, or ``region_radius_m``) of any
sonar position of the lines used. Logged: ``val/mae``, ``val/std``, ``val/grad_cs``
(:mod:`sss2bathy.metrics.bathy`); with held-out altimeter points (``data.holdout``, with or
without MBES) ``val/holdout_alt_mae``, ``val/holdout_interp_mae`` (the along-track
interpolation baseline, constant over the run) and ``val/holdout_ratio``
(:mod:`sss2bathy.data.holdout`); images by :class:`SirenMapImages` (TensorBoard only).
At the end of the fit ``map.tif``, ``map.npz``, ``metrics.json`` and PNGs go to
``output_dir`` (default: the logger's ``save_dir``, i.e. the Hydra run folder, else the
trainer's ``default_root_dir``), and the hyper-parameters are logged with the final
metrics.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any

import numpy as np
import pytorch_lightning as pl
import torch
from pytorch_lightning.callbacks import Callback

from sss2bathy.eval.maps import (
    colorize,
    error_map,
    gradient_hsv,
    grid_over_bounds,
    map_metrics,
    save_map_outputs,
    siren_to_grid,
    track_region_mask,
)
from sss2bathy.geometry import arc_point, head_plane_normal_from_gradient
from sss2bathy.losses.siren import height_loss, total_loss
from sss2bathy.metrics.bathy import map_gradient
from sss2bathy.models.intersection import SOLVERS, find_intersections
from sss2bathy.models.sensors import ArcGeometry, SensorModel
from sss2bathy.models.siren import Siren, autocast_disabled
from sss2bathy.survey import BathyGrid

log = logging.getLogger(__name__)

# metrics ``select_best`` may choose the final map by (lower is better; no MBES needed)
SELECT_BEST = ("holdout_alt_mae",)

FINDER_DEFAULTS: dict[str, Any] = {
    "solver": "secant",
    "max_iter": None,
    "tol_m": 1e-3,
    "gd_step": 0.01,
    "warm_start": True,
    "n_scan": 16,
    "scan_max_slope": 1.0,
    "warm_bracket_deg": 0.5,
    "chunk": 8192,
}


def _finder_config(finder: Mapping[str, Any] | None) -> dict[str, Any]:
    cfg = dict(FINDER_DEFAULTS)
    given = dict(finder or {})
    unknown = sorted(set(given) - set(cfg))
    if unknown:
        raise ValueError(f"finder: expected keys among {sorted(cfg)}, found unknown {unknown}")
    cfg.update(given)
    if cfg["solver"] not in SOLVERS:
        raise ValueError(f"finder.solver: expected one of {SOLVERS}, found {cfg['solver']!r}")
    return cfg


def arc_geometry(
    siren: Siren,
    batch: dict[str, torch.Tensor],
    use: torch.Tensor,
    theta_limits: tuple[float, float],
    finder: Mapping[str, Any],
    theta_cache: torch.Tensor | None = None,
) -> tuple[ArcGeometry, dict[str, torch.Tensor]]:
    """Crossings of a batch's bins with the SIREN, and the SIREN's normals there.

    Args:
        siren: the bathymetry.
        batch: ping batch (``position``, ``rotation``, ``range_m``, ``line``, ``index``).
        use: ``(P, 2, B)`` bool, the bins to use (the sensor model's ``bin_mask``).
        theta_limits: beam limits (rad).
        finder: finder settings (:data:`FINDER_DEFAULTS` keys).
        theta_cache: ``(n_pings, 2, B)`` per-bin warm-start angles indexed by the batch's
            ``index`` (NaN = none yet, +inf = no crossing last time), updated in place;
            ``None`` = cold solves.

    Returns:
        ``(geo, stats)``: the valid bins' :class:`ArcGeometry` (gradient and normals with
        graph; ``geo.ping`` indexes the batch) and finder statistics (``valid_fraction``,
        ``finder_iters`` = mean solver evaluations per bin).
    """
    finder = _finder_config(finder)
    pi, si, bi = use.nonzero(as_tuple=True)
    sonar, rot = batch["position"][pi], batch["rotation"][pi]
    range_m = batch["range_m"][bi]
    warm = finder["warm_start"] and theta_cache is not None
    cache_idx = (batch["index"][pi], si, bi)
    # Geometry in float32 even under an enclosing autocast (bf16 would move crossings and
    # normals by centimetres); the SIREN picks its own precision (Siren.precision).
    with autocast_disabled(sonar.device):
        theta, valid, n_iter = find_intersections(
            siren,
            sonar,
            rot,
            range_m,
            si,
            theta_limits,
            solver=finder["solver"],
            theta0=theta_cache[cache_idx] if warm else None,
            max_iter=finder["max_iter"],
            tol_m=finder["tol_m"],
            gd_step=finder["gd_step"],
            n_scan=finder["n_scan"],
            scan_max_slope=finder["scan_max_slope"],
            warm_bracket_rad=math.radians(finder["warm_bracket_deg"]),
            chunk=finder["chunk"],
        )
        if warm:
            # +inf marks "no crossing": next time only the beam's ends are checked
            theta_cache[cache_idx] = torch.where(valid, theta, torch.inf).to(theta_cache.dtype)
        v = valid.nonzero().squeeze(-1)
        pi, si, bi = pi[v], si[v], bi[v]
        sonar, rot, range_m, theta = sonar[v], rot[v], range_m[v], theta[v]
        points = arc_point(sonar, rot, range_m, theta, si)
    # the SIREN blocks its points itself (Siren.chunk: cache-sized on CPU)
    grad = siren.height_and_gradient(points[:, :2])[1]
    with autocast_disabled(sonar.device):
        n_lat, n_up = head_plane_normal_from_gradient(grad[:, 0], grad[:, 1], rot, si)
    geo = ArcGeometry(
        points=points,
        theta=theta,
        range_m=range_m,
        side=si,
        sonar=sonar,
        rotation=rot,
        grad=grad,
        n_lat=n_lat,
        n_up=n_up,
        ping=pi,
        bin=bi,
        line=batch["line"][pi],
    )
    n_bins = max(int(valid.numel()), 1)
    stats = {"valid_fraction": valid.sum() / n_bins, "finder_iters": n_iter.sum() / n_bins}
    return geo, stats


class SirenModule(pl.LightningModule):
    """Fits a :class:`~sss2bathy.models.siren.Siren` to sidescan + altimeter data.

    Args:
        siren: a ``Siren`` or a callable returning one (a Hydra ``_partial_``).
        sensor: the sensor model (normals or Lambertian); ``None``: altimeter heights
            alone (the baseline the sidescan must improve on), or with ``direct_fit``.
        w_height: ``w_H`` of eq. 7.
        optimizer: partial ``torch.optim`` optimizer (called with the parameters).
        scheduler: partial LR scheduler (called with the optimizer), stepped per epoch.
        finder: intersection-finder settings, keys of :data:`FINDER_DEFAULTS`
            (``warm_bracket_deg`` in degrees).
        eval_every_n_epochs: epochs between map evaluations (also at the end of the fit).
        eval_cell_m: map cell (m) when the survey has no MBES grid.
        direct_fit: fit the MBES grid directly (SIREN-Direct-Fit).
        direct_fit_points: MBES cells per direct-fit step.
        region_radius_m: scored area's radius around the tracks (m); default the swath
            half-width from the datamodule.
        output_dir: where the final map files go (default: see the module docstring).
        log_images: add the :class:`SirenMapImages` callback.
        encoding_lr: learning rate of the SIREN's input encoding's parameters (a hash grid's
            tables train best at ~1e-2); ``None`` = the optimizer's.
        sensor_lr: learning rate of the sensor model's own parameters (the Lambertian
            beam pattern, gain and scale); ``None`` = the optimizer's.
    """

    def __init__(
        self,
        siren: Siren | Callable[[], Siren],
        sensor: SensorModel | None = None,
        w_height: float = 1.0,
        optimizer: Callable[..., torch.optim.Optimizer] | None = None,
        scheduler: Callable[..., Any] | None = None,
        finder: Mapping[str, Any] | None = None,
        eval_every_n_epochs: int = 50,
        eval_cell_m: float = 0.5,
        direct_fit: bool = False,
        direct_fit_points: int = 16384,
        region_radius_m: float | None = None,
        output_dir: str | None = None,
        log_images: bool = True,
        sensor_lr: float | None = None,
        encoding_lr: float | None = None,
        select_best: str | None = None,
    ) -> None:
        super().__init__()
        self.save_hyperparameters(
            ignore=["siren", "sensor", "optimizer", "scheduler"], logger=False
        )
        self.siren = siren if isinstance(siren, Siren) else siren()
        if not isinstance(self.siren, Siren):
            raise ValueError(f"siren: expected a Siren or a factory of one, found {type(siren)}")
        if sensor is not None and not isinstance(sensor, SensorModel):
            raise ValueError(f"sensor: expected a SensorModel, found {type(sensor).__name__}")
        if w_height < 0:
            raise ValueError(f"w_height: expected a non-negative weight, found {w_height}")
        if int(eval_every_n_epochs) < 1:
            raise ValueError(f"eval_every_n_epochs: expected >= 1, found {eval_every_n_epochs}")
        self.sensor = sensor
        self.w_height = float(w_height)
        self.optimizer_factory = optimizer or (lambda params: torch.optim.Adam(params, lr=2e-4))
        self.scheduler_factory = scheduler
        self.finder = _finder_config(finder)
        self.eval_every_n_epochs = int(eval_every_n_epochs)
        self.eval_cell_m = float(eval_cell_m)
        self.direct_fit = bool(direct_fit)
        self.direct_fit_points = int(direct_fit_points)
        self.region_radius_m = region_radius_m
        self.output_dir = output_dir
        self.log_images = bool(log_images)
        if sensor_lr is not None and not sensor_lr > 0:
            raise ValueError(
                f"sensor_lr: expected a positive learning rate or None, found {sensor_lr}"
            )
        self.sensor_lr = None if sensor_lr is None else float(sensor_lr)
        if encoding_lr is not None and not encoding_lr > 0:
            raise ValueError(
                f"encoding_lr: expected a positive learning rate or None, found {encoding_lr}"
            )
        self.encoding_lr = None if encoding_lr is None else float(encoding_lr)
        if select_best is not None and select_best not in SELECT_BEST:
            raise ValueError(
                f"select_best: expected one of {SELECT_BEST} or None, found {select_best!r}"
            )
        # the map written at the end: the SIREN of the evaluation with the lowest
        # ``select_best`` metric (a signal without MBES: held-out altimeter points), or the last
        self.select_best = select_best
        self.best_eval: dict[str, Any] | None = None
        self.register_buffer("framed", torch.tensor(False))
        self.register_buffer("theta_cache", torch.zeros(0, 2, 0), persistent=False)
        self.register_buffer("fit_cells", torch.zeros(0, 3), persistent=False)
        # held-out altimeter points (x, y, z) of the datamodule's holdout split
        self.register_buffer("holdout_points", torch.zeros(0, 3), persistent=False)
        self.holdout_interp_mae: float | None = None
        self.final_metrics: dict[str, float] = {}
        self.theta_limits: tuple[float, float] | None = None
        self.eval_like: BathyGrid | None = None
        self.true_grid: BathyGrid | None = None
        self.region: np.ndarray | None = None
        self.last_eval: dict[str, Any] | None = None

    # ------------------------------------------------------------------ set-up
    def setup(self, stage: str) -> None:
        dm = self.trainer.datamodule if self.trainer is not None else None
        if dm is None or getattr(dm, "bounds", None) is None:
            raise ValueError(
                "datamodule: expected a set-up PingAltimeterDataModule (bounds, z_range, "
                "sensor, grid) passed to the trainer, found none"
            )
        if not bool(self.framed):
            self.siren.set_frame(dm.bounds, dm.z_range)
            self.framed.fill_(True)
        self.theta_limits = dm.sensor.beam_limits_rad
        if self.sensor is not None:
            self.sensor.setup_from_data(dm.sensor, dm.table.range_m)
        self.theta_cache = torch.full((dm.n_pings, 2, dm.table.n_bins), torch.nan)
        self.true_grid = dm.grid
        self.eval_like = (
            dm.grid if dm.grid is not None else grid_over_bounds(dm.bounds, self.eval_cell_m)
        )
        radius = self.region_radius_m or dm.swath_half_width_m
        self.region = track_region_mask(self.eval_like, dm.track_xy, radius)
        self._setup_holdout(getattr(dm, "holdout_split", None))
        if self.direct_fit:
            if dm.grid is None:
                raise ValueError("direct_fit: expected a survey with an MBES grid, found none")
            ok = self.region & np.isfinite(dm.grid.heights)
            xx, yy = np.meshgrid(dm.grid.x, dm.grid.y)
            cells = np.stack([xx[ok], yy[ok], dm.grid.heights[ok]], 1).astype(np.float32)
            if cells.shape[0] == 0:
                raise ValueError(
                    "direct_fit: the MBES grid has no finite cell in the survey region"
                )
            self.fit_cells = torch.from_numpy(cells)

    def on_save_checkpoint(self, checkpoint: dict[str, Any]) -> None:
        # the warm-start angles steer the intersection finder, so a resumed fit needs them
        # to continue exactly (kept out of the state dict: they are sized by the survey)
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
        encoding = self.siren.encoding
        enc_params = list(encoding.parameters()) if encoding is not None else []
        enc_ids = {id(p) for p in enc_params}
        groups: list[dict[str, Any]] = [
            {"params": [p for p in self.siren.parameters() if id(p) not in enc_ids]}
        ]
        if enc_params:
            group_enc: dict[str, Any] = {"params": enc_params}
            if self.encoding_lr is not None:
                group_enc["lr"] = self.encoding_lr
            groups.append(group_enc)
        # a sensor may split its parameters (e.g. the Lambertian reflectivity field's own lr);
        # groups without "lr" take sensor_lr
        sensor_groups = (
            self.sensor.parameter_groups()
            if hasattr(self.sensor, "parameter_groups")
            else [{"params": list(self.sensor.parameters())}]
            if self.sensor is not None
            else []
        )
        for group in sensor_groups:
            if not group["params"]:
                continue
            if self.sensor_lr is not None and "lr" not in group:
                group = {**group, "lr": self.sensor_lr}
            groups.append(group)
        opt = self.optimizer_factory(params=groups)
        if self.scheduler_factory is None:
            return {"optimizer": opt}
        sched = self.scheduler_factory(optimizer=opt)
        return {"optimizer": opt, "lr_scheduler": {"scheduler": sched, "interval": "epoch"}}

    def configure_callbacks(self) -> list[Callback]:
        return [SirenMapImages()] if self.log_images else []

    # ------------------------------------------------------------------ steps
    def sidescan_geometry(
        self, batch: dict[str, torch.Tensor]
    ) -> tuple[ArcGeometry, torch.Tensor, dict[str, torch.Tensor]]:
        """:func:`arc_geometry` of the bins the sensor can use, and their targets."""
        geo, stats = arc_geometry(
            self.siren,
            batch,
            self.sensor.bin_mask(batch),
            self.theta_limits,
            self.finder,
            self.theta_cache if self.theta_cache.numel() else None,
        )
        return geo, batch[self.sensor.target_key][geo.ping, geo.side, geo.bin], stats

    def model_step(self, batch: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
        """Loss terms and statistics of one batch (module docstring)."""
        alt = batch["altimeter"]
        loss_height = height_loss(self.siren.height(alt[:, :2]), alt[:, 2])
        if self.direct_fit:
            pick = torch.randint(
                self.fit_cells.shape[0], (self.direct_fit_points,), device=self.fit_cells.device
            )
            cells = self.fit_cells[pick]
            loss = height_loss(self.siren.height(cells[:, :2]), cells[:, 2])
            return {"loss": loss, "loss_direct": loss.detach(), "loss_height": loss_height.detach()}
        if self.sensor is None:
            return {"loss": loss_height, "loss_height": loss_height.detach()}
        geo, target, stats = self.sidescan_geometry(batch)
        loss_sensor, sensor_logs = self.sensor.loss(geo, target)
        loss = total_loss(loss_sensor, loss_height, self.w_height)
        out = {
            "loss": loss,
            "loss_sensor": loss_sensor.detach(),
            "loss_height": loss_height.detach(),
            **stats,
        }
        out.update({f"sensor/{k}": torch.as_tensor(v).detach() for k, v in sensor_logs.items()})
        return out

    def training_step(self, batch: dict[str, torch.Tensor], batch_idx: int) -> torch.Tensor:
        out = self.model_step(batch)
        n = int(batch["position"].shape[0])
        for key, value in out.items():
            self.log(
                f"train/{key}",
                value.detach() if key == "loss" else value,
                on_step=key == "loss",
                on_epoch=True,
                prog_bar=key == "loss",
                batch_size=n,
            )
        return out["loss"]

    # -------------------------------------------------------------- evaluation
    def _setup_holdout(self, split: Any) -> None:
        """Held-out altimeter points (:class:`~sss2bathy.data.holdout.AltimeterSplit`, or
        ``None``) for :meth:`holdout_metrics`; the interpolation baseline is fixed here."""
        if split is None or split.n_held == 0:
            self.holdout_points = torch.zeros(0, 3, device=self.holdout_points.device)
            self.holdout_interp_mae = None
            return
        pts = torch.from_numpy(np.asarray(split.held, np.float32))
        self.holdout_points = pts.to(self.holdout_points.device)
        self.holdout_interp_mae = float(split.interp_mae)

    def holdout_metrics(self) -> dict[str, float]:
        """``holdout_alt_mae`` (the SIREN at the held-out altimeter points, m),
        ``holdout_interp_mae`` (along-track interpolation of the kept points there, m),
        ``holdout_ratio`` (their ratio; < 1: the fit beats interpolation) and
        ``holdout_n``; empty without held-out points."""
        if not self.holdout_points.numel() or self.holdout_interp_mae is None:
            return {}
        from sss2bathy.data.holdout import holdout_mae

        pts = self.holdout_points
        with torch.no_grad():
            z = torch.cat([self.siren.height(part) for part in pts[:, :2].split(65536)])
        alt_mae = holdout_mae(z.float().cpu().numpy(), pts[:, 2].cpu().numpy())
        interp = self.holdout_interp_mae
        return {
            "holdout_alt_mae": alt_mae,
            "holdout_interp_mae": interp,
            "holdout_ratio": alt_mae / interp if interp > 0 else float("nan"),
            "holdout_n": int(pts.shape[0]),
        }

    def evaluate_map(self) -> tuple[BathyGrid, dict[str, float]]:
        """The SIREN on the evaluation grid, its metrics against the MBES grid (if any) and
        on the held-out altimeter points (if any). The latest evaluation's numbers are also
        kept as :attr:`final_metrics` (``final/<name>``; after a fit: the final map's)."""
        pred = siren_to_grid(self.siren, self.eval_like)
        metrics = map_metrics(pred, self.true_grid, self.region) if self.true_grid else {}
        metrics.update(self.holdout_metrics())
        self.final_metrics = {
            f"final/{k}": float(v)
            for k, v in metrics.items()
            if isinstance(v, int | float) and math.isfinite(v)
        }
        return pred, metrics

    def _eval_due(self) -> bool:
        """Every ``eval_every_n_epochs`` epochs, and at the last epoch of ``max_epochs``
        (so a short run still logs its ``val/*`` metrics once)."""
        epoch = self.current_epoch + 1
        max_epochs = self.trainer.max_epochs
        last = max_epochs is not None and max_epochs > 0 and epoch >= max_epochs
        return epoch % self.eval_every_n_epochs == 0 or last

    def validation_step(self, batch: Any, batch_idx: int) -> None:
        if self.trainer.sanity_checking or not self._eval_due():
            return
        pred, metrics = self.evaluate_map()
        self.last_eval = {"pred": pred, "metrics": metrics, "epoch": self.current_epoch}
        keys = ("mae", "std", "grad_cs", "holdout_alt_mae", "holdout_interp_mae", "holdout_ratio")
        for key in keys:
            if key in metrics and math.isfinite(metrics[key]):
                self.log(f"val/{key}", metrics[key], batch_size=1)
        self._track_best(metrics)

    def _track_best(self, metrics: Mapping[str, float]) -> None:
        """Keep a copy of the SIREN at the evaluation with the lowest ``select_best``."""
        if self.select_best is None:
            return
        value = metrics.get(self.select_best)
        if value is None or not math.isfinite(value):
            return
        if self.best_eval is None or value < self.best_eval["value"]:
            state = {k: v.detach().clone() for k, v in self.siren.state_dict().items()}
            self.best_eval = {"value": float(value), "epoch": self.current_epoch, "state": state}

    def _restore_best(self, metrics: Mapping[str, float]) -> int | None:
        """Load the best evaluation's SIREN when it beats the final one; its epoch, else None."""
        if self.select_best is None or self.best_eval is None:
            return None
        value = metrics.get(self.select_best)
        if value is not None and math.isfinite(value) and value <= self.best_eval["value"]:
            return None
        self.siren.load_state_dict(self.best_eval["state"])
        return int(self.best_eval["epoch"])

    def on_fit_end(self) -> None:
        if not self.trainer.is_global_zero:
            return
        pred, metrics = self.evaluate_map()
        best_epoch = self._restore_best(metrics)
        if best_epoch is not None:
            log.info(
                "final map: the SIREN of epoch %d (lowest %s %.4g; last epoch %.4g)",
                best_epoch,
                self.select_best,
                self.best_eval["value"],
                metrics.get(self.select_best, float("nan")),
            )
            pred, metrics = self.evaluate_map()
        self.last_eval = {"pred": pred, "metrics": metrics, "epoch": self.current_epoch}
        out_dir = self._output_dir()
        summary = {"final/" + k: v for k, v in metrics.items() if isinstance(v, int | float)}
        summary["epochs"] = int(self.current_epoch)
        summary["final/map_epoch"] = int(self.current_epoch) if best_epoch is None else best_epoch
        self.final_metrics["final/map_epoch"] = float(summary["final/map_epoch"])
        if self.direct_fit:
            title = "SIREN-Direct-Fit"
        else:
            title = type(self.sensor).__name__ if self.sensor is not None else "heights only"
        dm = getattr(self.trainer, "datamodule", None)  # survey origin: georeferenced map.tif
        alt = getattr(dm, "altimeter", None)
        paths = save_map_outputs(
            out_dir,
            pred,
            self.true_grid,
            self.region,
            summary,
            title,
            origin=getattr(dm, "origin", None),
            altimeter_xy=None if alt is None else alt[:, :2].cpu().numpy(),
        )
        log.info("SIREN map written to %s (%s)", paths["map_tif"], metrics)
        for logger in self.loggers:
            logger.log_hyperparams(self._hparams_for_log(), metrics=summary)

    def _output_dir(self) -> Path:
        if self.output_dir:
            return Path(self.output_dir)
        if self.logger is not None and getattr(self.logger, "save_dir", None):
            return Path(self.logger.save_dir)
        return Path(self.trainer.default_root_dir)

    def _hparams_for_log(self) -> dict[str, Any]:
        flat: dict[str, Any] = {
            "siren/hidden": self.siren.hidden,
            "siren/n_layers": self.siren.n_layers,
            "siren/omega0": self.siren.omega0,
            "siren/precision": self.siren.precision,
            "siren/encoding": type(self.siren.encoding).__name__
            if self.siren.encoding is not None
            else "none",
            "sensor": type(self.sensor).__name__ if self.sensor is not None else "none",
            "w_height": self.w_height,
            "direct_fit": self.direct_fit,
        }
        flat.update({f"finder/{k}": str(v) if v is None else v for k, v in self.finder.items()})
        opt = self.trainer.optimizers[0] if self.trainer.optimizers else None
        if opt is not None:
            flat["lr"] = opt.defaults.get("lr")
        return flat


class SirenMapImages(Callback):
    """Logs the last evaluated map to TensorBoard: bathymetry, gradient HSV, signed error.

    Does nothing with other loggers (or none); the module's ``last_eval`` is produced by
    its validation step every ``eval_every_n_epochs`` epochs.
    """

    def on_validation_epoch_end(self, trainer: pl.Trainer, pl_module: pl.LightningModule) -> None:
        from pytorch_lightning.loggers import TensorBoardLogger

        ev = getattr(pl_module, "last_eval", None)
        if trainer.sanity_checking or not trainer.is_global_zero or ev is None:
            return
        if ev.get("logged"):
            return
        ev["logged"] = True
        pred: BathyGrid = ev["pred"]
        region = pl_module.region
        shown = np.where(region, pred.heights, np.nan) if region is not None else pred.heights
        images = {
            "map/bathymetry": colorize(shown),
            "map/gradient_hsv": gradient_hsv(*map_gradient(shown, pred.cell_size)),
        }
        if pl_module.true_grid is not None:
            err = error_map(pred, pl_module.true_grid, region)
            images["map/signed_error"] = colorize(err, "RdBu_r", symmetric=True)
        for logger in trainer.loggers:
            if isinstance(logger, TensorBoardLogger):
                for tag, rgb in images.items():
                    logger.experiment.add_image(
                        tag, np.ascontiguousarray(rgb[::-1]), trainer.global_step, dataformats="HWC"
                    )
