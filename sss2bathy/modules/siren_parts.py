"""Plain parts of the SIREN fit's module (no Lightning): map evaluation, the final-map
choice, the optimiser's parameter groups and the hparams description.

* :class:`MapScorer` fixes, once the survey is known, the evaluation grid (the MBES grid,
  or ``eval_cell_m`` cells over the bounds), the *surveyed area* scored against the MBES
  (cells within the swath half-width of a sonar position of the lines used: the published
  tables' region), the *coverage* of the written map (the cells the used bins imaged,
  :func:`~sss2bathy.eval.maps.swath_footprint_mask`, plus the fitted altimeter points'
  cells) and the held-out altimeter points; its :meth:`~MapScorer.evaluate` returns a
  :class:`MapEvaluation`.
* :class:`BestSnapshot` keeps a copy of the SIREN at the evaluation with the lowest
  ``select_best`` metric, for the final map.
* :func:`param_groups`: the SIREN's, its input encoding's and the sensor model's
  parameters with their learning rates; :func:`describe_fit`: flat hparams.

Metrics: ``mae``, ``std``, ``grad_cs``, ``n_cells`` against the MBES grid
(:func:`sss2bathy.eval.maps.map_metrics`); with held-out altimeter points,
``holdout_alt_mae``, ``holdout_interp_mae``, ``holdout_ratio``, ``holdout_n`` and the
split's ``holdout_blocks``, ``holdout_block_pings`` (mean pings per block) and, for a
K-fold split, ``holdout_block_m``, ``holdout_folds``, ``holdout_fold``
(:mod:`sss2bathy.data.holdout`); with the sonar's footprint,
:func:`~sss2bathy.eval.maps.coverage_stats` of the written map (``imaged_area_m2``,
``measured_area_m2``, ``written_area_m2``, ``extrapolated_share``) and
``track_region_extrapolated_share`` (the share of the older track-region coverage,
:func:`~sss2bathy.eval.maps.coverage_mask`, that nothing measured) and, with held-out
points, ``holdout_imaged_share`` (the share of them inside the sonar footprint: on a single
line 0, its own nadir gap).
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import torch

from sss2bathy.data.holdout import AltimeterSplit, holdout_mae
from sss2bathy.eval.maps import (
    altimeter_cells,
    coverage_mask,
    coverage_stats,
    grid_over_bounds,
    map_metrics,
    siren_to_grid,
    swath_footprint_mask,
    track_region_mask,
)
from sss2bathy.metrics.bathy import MAP_TAGS
from sss2bathy.survey import BathyGrid

# metrics ``select_best`` may choose the final map by (lower is better; no MBES needed)
SELECT_BEST = ("holdout_alt_mae",)


@dataclass(frozen=True)
class MapEvaluation:
    """One evaluation of the SIREN's map (read by the map callbacks, never changed).

    Attributes:
        pred: the SIREN on the evaluation grid.
        metrics: its scores (module docstring).
        epoch: the epoch it was made at (0-based).
        truth: the MBES grid, or None.
        region: ``(ny, nx)`` bool, the scored area.
        map_epoch: the epoch of the SIREN the map shows (the final map with ``select_best``
            may show an earlier one).
        coverage: ``(ny, nx)`` bool, the cells the written map holds data in (None: the
            export's :func:`~sss2bathy.eval.maps.coverage_mask`).
    """

    pred: BathyGrid
    metrics: Mapping[str, float]
    epoch: int
    truth: BathyGrid | None
    region: np.ndarray | None
    map_epoch: int | None = None
    coverage: np.ndarray | None = None

    def tags(self, prefix: str = "val/") -> dict[str, float]:
        """The metrics under their logged names (:data:`MAP_TAGS`), e.g. ``val/map_mae_m``."""
        return {f"{prefix}{MAP_TAGS.get(k, k)}": v for k, v in self.metrics.items()}


@dataclass
class MapScorer:
    """Evaluation grid, scored area and held-out points of one survey (module docstring)."""

    like: BathyGrid
    truth: BathyGrid | None
    region: np.ndarray
    holdout_points: torch.Tensor = field(default_factory=lambda: torch.zeros(0, 3))
    holdout_interp_mae: float | None = None
    holdout_info: dict[str, float] = field(default_factory=dict)
    coverage: np.ndarray | None = None
    coverage_metrics: dict[str, float] = field(default_factory=dict)

    @classmethod
    def for_survey(
        cls,
        bounds: tuple[float, float, float, float],
        grid: BathyGrid | None,
        track_xy: np.ndarray,
        radius_m: float,
        eval_cell_m: float,
        holdout: AltimeterSplit | None = None,
        swath: Mapping[str, np.ndarray] | None = None,
        altimeter_xy: np.ndarray | None = None,
        origin: Mapping[str, Any] | None = None,
    ) -> MapScorer:
        """Args (besides the fields): ``swath``, the :func:`swath_footprint_mask` arguments
        of the pings used (:func:`swath_inputs`; None: no footprint, the export's older
        coverage); ``altimeter_xy`` ``(M, 2)``, the fitted altimeter points; ``origin``, the
        survey origin (a grid without MBES has its cell edges on multiples of the cell in
        true coordinates, :func:`grid_over_bounds`)."""
        like = grid if grid is not None else grid_over_bounds(bounds, eval_cell_m, origin=origin)
        scorer = cls(like, grid, track_region_mask(like, track_xy, radius_m))
        if holdout is not None and holdout.n_held > 0:
            scorer.holdout_points = torch.from_numpy(np.asarray(holdout.held, np.float32))
            scorer.holdout_interp_mae = float(holdout.interp_mae)
            info = {
                "holdout_blocks": holdout.n_blocks,
                "holdout_block_pings": holdout.block_pings,
                "holdout_block_m": holdout.block_m,
                "holdout_folds": holdout.folds or None,
                "holdout_fold": holdout.fold,
            }
            scorer.holdout_info = {k: float(v) for k, v in info.items() if v is not None}
        if swath is not None:
            imaged = swath_footprint_mask(like, **swath)
            alt = (
                altimeter_cells(like, altimeter_xy)
                if altimeter_xy is not None
                else np.zeros(like.shape, bool)
            )
            scorer.coverage = imaged | alt
            stats = coverage_stats(like, scorer.coverage, imaged, alt)
            old = coverage_mask(like, scorer.region, altimeter_xy)
            stats["track_region_extrapolated_share"] = coverage_stats(like, old, imaged, alt)[
                "extrapolated_share"
            ]
            if scorer.holdout_points.numel():
                # held-out nadir points the sidescan imaged (other lines' swaths; a line's
                # own nadir gap never is): 0 = the sidescan reaches them only through the
                # map's continuity
                held = altimeter_cells_index(like, scorer.holdout_points[:, :2].numpy())
                inside = imaged[held[:, 1], held[:, 0]] if held.size else np.zeros(0, bool)
                stats["holdout_imaged_share"] = float(inside.mean()) if inside.size else 0.0
            scorer.coverage_metrics = stats
        return scorer

    def holdout_metrics(self, siren: torch.nn.Module) -> dict[str, float]:
        """``holdout_alt_mae`` (the SIREN at the held-out altimeter points, m),
        ``holdout_interp_mae`` (along-track interpolation of the kept points there, m),
        ``holdout_ratio`` (their ratio; < 1: the fit beats interpolation) and
        ``holdout_n``; empty without held-out points."""
        if not self.holdout_points.numel() or self.holdout_interp_mae is None:
            return {}
        device = next(iter(siren.parameters())).device
        pts = self.holdout_points.to(device)
        with torch.no_grad():
            z = torch.cat([siren.height(part) for part in pts[:, :2].split(65536)])
        alt_mae = holdout_mae(z.float().cpu().numpy(), pts[:, 2].cpu().numpy())
        interp = self.holdout_interp_mae
        return {
            "holdout_alt_mae": alt_mae,
            "holdout_interp_mae": interp,
            "holdout_ratio": alt_mae / interp if interp > 0 else float("nan"),
            "holdout_n": int(pts.shape[0]),
            **self.holdout_info,
        }

    def evaluate(self, siren: torch.nn.Module, epoch: int) -> MapEvaluation:
        """The SIREN on the evaluation grid and its metrics."""
        pred = siren_to_grid(siren, self.like)
        metrics = map_metrics(pred, self.truth, self.region) if self.truth else {}
        metrics.update(self.holdout_metrics(siren))
        metrics.update(self.coverage_metrics)
        return MapEvaluation(
            pred, metrics, int(epoch), self.truth, self.region, coverage=self.coverage
        )


def altimeter_cells_index(grid: BathyGrid, xy: np.ndarray) -> np.ndarray:
    """``(N, 2)`` column and row of the cell of each point ``xy (N, 2)`` clipped to the
    grid (the cells of :func:`~sss2bathy.eval.maps.altimeter_cells`)."""
    xy = np.asarray(xy, np.float64).reshape(-1, 2)
    ix = np.floor((xy[:, 0] - grid.x0) / grid.cell_size + 0.5).astype(np.int64)
    iy = np.floor((xy[:, 1] - grid.y0) / grid.cell_size + 0.5).astype(np.int64)
    ny, nx = grid.shape
    return np.stack([np.clip(ix, 0, nx - 1), np.clip(iy, 0, ny - 1)], 1)


def swath_inputs(datamodule: Any, uses_sidescan: bool = True) -> dict[str, np.ndarray] | None:
    """The :func:`~sss2bathy.eval.maps.swath_footprint_mask` arguments of a set-up
    ``PingAltimeterDataModule``'s ping table (its valid bins, ``mask == 0``, and the pings'
    altitudes ``ping_altitude_m``); ``uses_sidescan=False`` (a heights-only fit): no bin is
    used, the footprint is empty. None when the datamodule lacks them."""
    table = getattr(datamodule, "table", None)
    altitude = getattr(datamodule, "ping_altitude_m", None)
    if table is None or altitude is None or len(altitude) != table.n_pings:
        return None
    mask = table.mask.cpu().numpy()
    return {
        "position": table.position.cpu().numpy(),
        "rotation": table.rotation.cpu().numpy(),
        "altitude_m": np.asarray(altitude, np.float64),
        "range_m": table.range_m.cpu().numpy(),
        "usable": (mask == 0) if uses_sidescan else np.zeros(mask.shape, bool),
        "line": table.line.cpu().numpy(),
    }


def finite_metrics(metrics: Mapping[str, Any], prefix: str = "final/") -> dict[str, float]:
    """The finite numeric entries of ``metrics`` as floats, keys prefixed."""
    return {
        f"{prefix}{k}": float(v)
        for k, v in metrics.items()
        if isinstance(v, int | float) and math.isfinite(v)
    }


class BestSnapshot:
    """A copy of the SIREN at the evaluation with the lowest ``metric`` (``None``: off)."""

    def __init__(self, metric: str | None) -> None:
        if metric is not None and metric not in SELECT_BEST:
            raise ValueError(
                f"select_best: expected one of {SELECT_BEST} or None, found {metric!r}"
            )
        self.metric = metric
        self.best: dict[str, Any] | None = None

    def track(self, siren: torch.nn.Module, metrics: Mapping[str, float], epoch: int) -> None:
        """Keep a copy of ``siren`` if this evaluation's metric is the lowest so far."""
        if self.metric is None:
            return
        value = metrics.get(self.metric)
        if value is None or not math.isfinite(value):
            return
        if self.best is None or value < self.best["value"]:
            state = {k: v.detach().clone() for k, v in siren.state_dict().items()}
            self.best = {"value": float(value), "epoch": int(epoch), "state": state}

    def restore(self, siren: torch.nn.Module, metrics: Mapping[str, float]) -> int | None:
        """Load the best copy into ``siren`` when it beats ``metrics`` (the final
        evaluation's); its epoch, else None."""
        if self.metric is None or self.best is None:
            return None
        value = metrics.get(self.metric)
        if value is not None and math.isfinite(value) and value <= self.best["value"]:
            return None
        siren.load_state_dict(self.best["state"])
        return int(self.best["epoch"])


def param_groups(
    siren: torch.nn.Module,
    sensor: torch.nn.Module | None,
    encoding_lr: float | None = None,
    sensor_lr: float | None = None,
) -> list[dict[str, Any]]:
    """Optimiser parameter groups: the SIREN without its encoding; the encoding's
    parameters (at ``encoding_lr``, None = the optimiser's); the sensor's groups (its
    ``parameter_groups()`` when it splits them, e.g. the reflectivity field's own lr; groups
    without ``lr`` take ``sensor_lr``). Empty groups are left out."""
    enc = getattr(siren, "encoding", None)
    enc_params = list(enc.parameters()) if enc is not None else []
    enc_ids = {id(p) for p in enc_params}
    groups = [{"params": [p for p in siren.parameters() if id(p) not in enc_ids]}]
    if enc_params:
        groups.append(
            {"params": enc_params, **({} if encoding_lr is None else {"lr": encoding_lr})}
        )
    if sensor is None:
        return groups
    split = getattr(sensor, "parameter_groups", None)
    for group in split() if split else [{"params": list(sensor.parameters())}]:
        if not group["params"]:
            continue
        if sensor_lr is not None and "lr" not in group:
            group = {**group, "lr": sensor_lr}
        groups.append(group)
    return groups


def describe_fit(
    siren: Any, sensor: torch.nn.Module | None, w_height: float, finder: Any
) -> dict[str, Any]:
    """Flat hyper-parameters of a SIREN fit for the loggers' HPARAMS."""
    enc = siren.encoding
    flat: dict[str, Any] = {
        "siren/hidden": siren.hidden,
        "siren/n_layers": siren.n_layers,
        "siren/omega0": siren.omega0,
        "siren/precision": siren.precision,
        "siren/encoding": type(enc).__name__ if enc is not None else "none",
        "sensor": type(sensor).__name__ if sensor is not None else "none",
        "w_height": w_height,
    }
    if getattr(sensor, "use_line_offset", False):  # the normal sensor's learned line offsets
        flat["sensor/line_offset_weight"] = float(sensor.offset_weight)
    settings = dataclasses.asdict(finder) if dataclasses.is_dataclass(finder) else dict(finder)
    flat.update({f"finder/{k}": str(v) if v is None else v for k, v in settings.items()})
    return flat


__all__ = [
    "SELECT_BEST",
    "BestSnapshot",
    "MapEvaluation",
    "MapScorer",
    "describe_fit",
    "finite_metrics",
    "param_groups",
    "swath_inputs",
]
