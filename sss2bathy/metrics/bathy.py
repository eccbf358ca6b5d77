"""Bathymetric map metrics (paper Table "Quantitative Results For SIREN"), pure numpy.

All functions take ``(ny, nx)`` height maps on one grid and a boolean ``region`` of the
cells to score; cells where either map is NaN are left out.

* MAE: ``mean |z_pred - z_true|`` (m).
* STD: population standard deviation of the signed error ``z_pred - z_true`` (m).
* Gradient CS: both maps' gradients ``(dz/dx, dz/dy)`` by the same central differences
  (``numpy.gradient``, one-sided at edges, NaN next to no-data); per cell the cosine of
  the angle between the two 2D gradient vectors, ``g_p . g_t / (|g_p| |g_t|)``; the mean
  over the region's cells where both gradients are finite and longer than ``eps``
  (direction is undefined on an exactly flat cell). Ranges in ``[-1, 1]``; 1 = every
  slope points the same way.
"""

from __future__ import annotations

import numpy as np

GRADIENT_EPS = 1e-6

# logged names (``val/<tag>``) of a SIREN fit's map metrics (these and the held-out altimeter
# scores of sss2bathy.data.holdout): what they measure and in which unit, so a map metric in
# metres never shares a tag with the normal CNN's n_lat metrics (``val/nlat_*``). The
# ``final/<name>`` keys of a run's metrics.json keep the plain names.
MAP_TAGS = {
    "mae": "map_mae_m",
    "std": "map_std_m",
    "grad_cs": "map_grad_cs",
    "n_cells": "map_n_cells",
    "holdout_alt_mae": "holdout_alt_mae_m",
    "holdout_interp_mae": "holdout_interp_mae_m",
    "holdout_ratio": "holdout_ratio",
    "holdout_n": "holdout_n",
}


def _check(pred: np.ndarray, true: np.ndarray, region: np.ndarray | None) -> np.ndarray:
    pred, true = np.asarray(pred), np.asarray(true)
    if pred.ndim != 2 or pred.shape != true.shape:
        raise ValueError(
            f"pred, true: expected two 2D maps of one shape, found {pred.shape} and {true.shape}"
        )
    if region is None:
        region = np.ones(pred.shape, dtype=bool)
    region = np.asarray(region)
    if region.shape != pred.shape or region.dtype != np.bool_:
        raise ValueError(
            f"region: expected a bool map of shape {pred.shape}, "
            f"found {region.dtype} {region.shape}"
        )
    return region & np.isfinite(pred) & np.isfinite(true)


def signed_error(pred: np.ndarray, true: np.ndarray) -> np.ndarray:
    """``(ny, nx)`` ``pred - true`` (m); positive where the map is too shallow."""
    return np.asarray(pred, dtype=np.float64) - np.asarray(true, dtype=np.float64)


def height_mae(pred: np.ndarray, true: np.ndarray, region: np.ndarray | None = None) -> float:
    """Mean absolute height error (m) over the scored cells; NaN if there are none."""
    ok = _check(pred, true, region)
    return float(np.abs(signed_error(pred, true)[ok]).mean()) if ok.any() else float("nan")


def height_error_std(pred: np.ndarray, true: np.ndarray, region: np.ndarray | None = None) -> float:
    """Standard deviation (m, ddof 0) of the signed error over the scored cells."""
    ok = _check(pred, true, region)
    return float(signed_error(pred, true)[ok].std()) if ok.any() else float("nan")


def map_gradient(heights: np.ndarray, cell_size: float) -> tuple[np.ndarray, np.ndarray]:
    """``(dz/dx, dz/dy)`` of a map with row 0 south (central differences)."""
    if not cell_size > 0:
        raise ValueError(f"cell_size: expected a positive cell size (m), found {cell_size}")
    dzdy, dzdx = np.gradient(np.asarray(heights, dtype=np.float64), float(cell_size))
    return dzdx, dzdy


def gradient_cosine_similarity(
    pred_grad: tuple[np.ndarray, np.ndarray],
    true_grad: tuple[np.ndarray, np.ndarray],
    region: np.ndarray | None = None,
    eps: float = GRADIENT_EPS,
) -> float:
    """Mean per-cell cosine similarity of two gradient maps (module docstring)."""
    px, py = (np.asarray(a, dtype=np.float64) for a in pred_grad)
    tx, ty = (np.asarray(a, dtype=np.float64) for a in true_grad)
    ok = _check(px, tx, region) & np.isfinite(py) & np.isfinite(ty)
    pn, tn = np.hypot(px, py), np.hypot(tx, ty)
    ok &= (pn > eps) & (tn > eps)
    if not ok.any():
        return float("nan")
    cos = (px[ok] * tx[ok] + py[ok] * ty[ok]) / (pn[ok] * tn[ok])
    return float(np.clip(cos, -1.0, 1.0).mean())


def bathy_metrics(
    pred: np.ndarray, true: np.ndarray, cell_size: float, region: np.ndarray | None = None
) -> dict[str, float]:
    """``mae``, ``std``, ``grad_cs`` (module docstring) and ``n_cells`` scored."""
    ok = _check(pred, true, region)
    return {
        "mae": height_mae(pred, true, ok),
        "std": height_error_std(pred, true, ok),
        "grad_cs": gradient_cosine_similarity(
            map_gradient(pred, cell_size), map_gradient(true, cell_size), ok
        ),
        "n_cells": int(ok.sum()),
    }
