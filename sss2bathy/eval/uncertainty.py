"""Per-cell height uncertainty of a map from the K-fold verdict's fits, and its calibration.

**The estimate.** ``sss2bathy-map`` with ``verdict.folds = K`` (>= 2) fits the map's method
K times, fold ``k`` without the altimeter points of its blocks (all the sidescan is kept;
:mod:`sss2bathy.data.holdout`), then once on every point (the written map). The K fold maps
are delete-a-group jackknife replicates of the final map, so the **jackknife standard
error** of each cell's height

    sigma_J = sqrt((K - 1) / K x sum_k (h_k - mean_k h_k)^2)

(:func:`jackknife_sigma`) estimates how much the map would move with other altimeter data
over the same sidescan; it costs no fit beyond the verdict's (reading K maps). Its limits:
the fold fits share the seed and every sidescan ping, so what they share is not seen — the
forward model's error (a Lambertian seabed that is not one, a wrong tilt) moves every fold
alike. ``sigma_J`` is therefore too small as an error bar, and a **scale factor** ``c``
calibrated against MBES truth on synthetic surveys (:func:`calibrate_scale`: the
``level`` quantile of ``|error| / sigma_J``, so that ``level`` of the cells lie within
``+-c sigma_J``) makes ``sigma = c x sigma_J`` (:func:`scaled_sigma`). The calibration and
its numbers: ``studies/uncertainty_calibration.py``,
``docs/studies/uncertainty_calibration.md``.

**Scoring it** (:func:`calibration_stats`): the share of cells whose true height lies
within +-1 sigma and +-2 sigma (a Gaussian error: 68.3 % and 95.4 %) and the Spearman rank
correlation of sigma with the absolute error (does a larger sigma mark a worse cell?).

:func:`fold_members` reads the fold maps of a run folder and :func:`write_run_uncertainty`
writes a run's ``uncertainty.tif`` (float32 m, ``map.tif``'s grid and no-data) and
``uncertainty.png``. Everything else here is pure.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from sss2bathy.survey import BathyGrid

#: the share of a Gaussian within +-1 sigma and +-2 sigma
GAUSS_1SIGMA = math.erf(1 / math.sqrt(2))
GAUSS_2SIGMA = math.erf(2 / math.sqrt(2))


def jackknife_sigma(members: np.ndarray | Sequence[np.ndarray]) -> np.ndarray:
    """Delete-a-group jackknife standard error per cell of ``K`` replicate maps.

    Args:
        members: ``(K, ny, nx)`` heights (m), replicate ``k`` fitted without group ``k``.

    Returns:
        ``(ny, nx)`` float32 ``sqrt((K - 1) / K x sum_k (h_k - mean h)^2)`` (m); NaN where
        any member is NaN.
    """
    stack = np.asarray(members, dtype=np.float64)
    if stack.ndim != 3 or stack.shape[0] < 2:
        raise ValueError(
            f"members: expected (K, ny, nx) heights of K >= 2 fold maps, found shape {stack.shape}"
        )
    k = stack.shape[0]
    dev = stack - stack.mean(axis=0)
    return np.sqrt((k - 1) / k * (dev**2).sum(axis=0)).astype(np.float32)


def scaled_sigma(sigma_j: np.ndarray, scale: float) -> np.ndarray:
    """``scale x sigma_j`` (float32), the calibrated sigma; ``scale`` must be positive."""
    if not (isinstance(scale, int | float) and math.isfinite(scale) and scale > 0):
        raise ValueError(f"uncertainty.scale: expected a positive finite factor, found {scale!r}")
    return (np.asarray(sigma_j, np.float32) * np.float32(scale)).astype(np.float32)


def _pairs(abs_err: np.ndarray, sigma: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The finite pairs of ``abs_err`` and ``sigma`` (same shape), flattened."""
    e = np.abs(np.asarray(abs_err, np.float64))
    s = np.asarray(sigma, np.float64)
    if e.shape != s.shape:
        raise ValueError(f"sigma: expected the errors' shape {e.shape}, found {s.shape}")
    ok = np.isfinite(e) & np.isfinite(s)
    return e[ok], s[ok]


def coverage(abs_err: np.ndarray, sigma: np.ndarray, k: float = 1.0) -> float:
    """Share of the finite cells with ``|error| <= k x sigma`` (NaN without cells)."""
    e, s = _pairs(abs_err, sigma)
    return float(np.mean(e <= k * s)) if e.size else math.nan


def calibrate_scale(abs_err: np.ndarray, sigma: np.ndarray, level: float = GAUSS_1SIGMA) -> float:
    """The factor ``c`` with ``level`` of the cells inside ``+-c x sigma``: the ``level``
    quantile of ``|error| / sigma`` over the cells where both are finite and sigma > 0.

    Raises:
        ValueError: ``level`` outside (0, 1), or no such cell.
    """
    if not 0.0 < level < 1.0:
        raise ValueError(f"level: expected a share in (0, 1), found {level}")
    e, s = _pairs(abs_err, sigma)
    ok = s > 0
    if not ok.any():
        raise ValueError("sigma: expected cells with a finite positive sigma, found none")
    return float(np.quantile(e[ok] / s[ok], level))


def spearman(a: np.ndarray, b: np.ndarray) -> float:
    """Spearman's rank correlation of the finite pairs of ``a`` and ``b`` (NaN under 3)."""
    from scipy.stats import spearmanr

    x, y = np.asarray(a, np.float64).ravel(), np.asarray(b, np.float64).ravel()
    ok = np.isfinite(x) & np.isfinite(y)
    if ok.sum() < 3:
        return math.nan
    return float(spearmanr(x[ok], y[ok]).statistic)


def calibration_stats(error: np.ndarray, sigma: np.ndarray) -> dict[str, float]:
    """How well ``sigma`` describes ``error`` (map - truth, m) over their finite cells:
    ``n``, ``mae``, ``median_sigma``, ``within_1sigma``, ``within_2sigma`` (ideal 0.683,
    0.954), ``spearman`` (of sigma with |error|) and ``scale_1sigma`` (the factor that would
    put 68.3 % inside +-1 sigma, :func:`calibrate_scale`)."""
    e, s = _pairs(error, sigma)
    if not e.size:
        raise ValueError("error, sigma: expected cells where both are finite, found none")
    return {
        "n": float(e.size),
        "mae": float(e.mean()),
        "median_sigma": float(np.median(s)),
        "within_1sigma": float(np.mean(e <= s)),
        "within_2sigma": float(np.mean(e <= 2 * s)),
        "spearman": spearman(s, e),
        "scale_1sigma": calibrate_scale(e, s) if (s > 0).any() else math.nan,
    }


@dataclass(frozen=True)
class FoldMaps:
    """The fold maps of a map run (:func:`fold_members`): ``heights (K, ny, nx)`` on the
    final map's grid, and the files they came from."""

    heights: np.ndarray
    paths: tuple[Path, ...]

    @property
    def k(self) -> int:
        return int(self.heights.shape[0])


def fold_members(run_dir: str | Path, method: str, like: BathyGrid) -> FoldMaps:
    """The heights of ``run_dir/verdict/<method>/fold<k>/map.npz`` (what ``sss2bathy-map``'s
    K-fold verdict writes), each checked to lie on ``like``'s grid (shape, SW centre, cell).

    Raises:
        ValueError: fewer than 2 fold maps, or one on another grid (names the file).
    """
    folder = Path(run_dir) / "verdict" / str(method)
    paths = sorted(folder.glob("fold*/map.npz"), key=lambda p: int(p.parent.name[4:] or -1))
    if len(paths) < 2:
        raise ValueError(
            f"{folder}: expected the map.npz of >= 2 fold fits (verdict.folds >= 2), found "
            f"{len(paths)}"
        )
    heights = []
    for path in paths:
        with np.load(path, allow_pickle=False) as saved:
            geom = (float(saved["x0"]), float(saved["y0"]), float(saved["cell_size"]))
            h = np.asarray(saved["heights"], np.float32)
        want = (like.x0, like.y0, like.cell_size)
        if h.shape != like.shape or not np.allclose(geom, want, rtol=0, atol=1e-6):
            raise ValueError(
                f"{path}: expected a fold map on the final map's grid {like.shape} at "
                f"{want}, found {h.shape} at {geom}"
            )
        heights.append(h)
    return FoldMaps(np.stack(heights), tuple(paths))


def describe_sigma(sigma: np.ndarray, mask: np.ndarray | None = None) -> dict[str, Any]:
    """Summary numbers of a sigma layer over ``mask`` (default: its finite cells):
    ``median``, ``p95``, ``max`` (m), ``cells``."""
    s = np.asarray(sigma, np.float64)
    keep = np.isfinite(s) if mask is None else (np.asarray(mask, bool) & np.isfinite(s))
    v = s[keep]
    if not v.size:
        return {"cells": 0, "median": math.nan, "p95": math.nan, "max": math.nan}
    return {
        "cells": int(v.size),
        "median": float(np.median(v)),
        "p95": float(np.percentile(v, 95)),
        "max": float(v.max()),
    }


UNCERTAINTY_DESCRIPTION = "height uncertainty: 1 sigma (m)"


@dataclass(frozen=True)
class RunUncertainty:
    """What :func:`write_run_uncertainty` wrote: the files, the fold count, the scale and
    the sigma's summary over the written cells (:func:`describe_sigma`)."""

    tif: Path
    png: Path
    folds: int
    scale: float
    summary: dict[str, Any]

    def to_metrics(self, prefix: str = "uncertainty/") -> dict[str, float]:
        """Flat numbers for ``metrics.json``."""
        out = {f"{prefix}folds": float(self.folds), f"{prefix}scale": float(self.scale)}
        for key in ("median", "p95", "max"):
            value = self.summary.get(key)
            if value is not None and math.isfinite(value):
                out[f"{prefix}sigma_{key}_m"] = float(value)
        return out


def write_run_uncertainty(
    run_dir: str | Path,
    method: str,
    scale: float,
    origin: Any = None,
    title: str = "map",
) -> RunUncertainty:
    """``run_dir/uncertainty.tif`` and ``.png`` of a finished ``sss2bathy-map`` run:
    ``scale x`` :func:`jackknife_sigma` of the fold maps of ``method``
    (:func:`fold_members`), on the final map's grid (``map.npz``), no-data outside the
    cells ``map.tif`` holds (its ``coverage``), in the same frame (``origin``: the survey
    origin, as the map was written; None: local coordinates without a CRS).

    Raises:
        ValueError: no ``map.npz``, fewer than 2 fold maps, or a fold on another grid.
    """
    from sss2bathy.eval.maps import render_map
    from sss2bathy.io.export import provenance_tags, write_geotiff

    run_dir = Path(run_dir)
    path = run_dir / "map.npz"
    if not path.is_file():
        raise ValueError(f"{path}: expected the run's final map, found no file")
    with np.load(path, allow_pickle=False) as saved:
        final = BathyGrid(
            np.asarray(saved["heights"], np.float32),
            float(saved["x0"]),
            float(saved["y0"]),
            float(saved["cell_size"]),
        )
        covered = np.asarray(saved["coverage"], bool) if "coverage" in saved else None
    folds = fold_members(run_dir, method, final)
    sigma = scaled_sigma(jackknife_sigma(folds.heights), scale)
    if covered is not None:
        sigma = np.where(covered, sigma, np.nan).astype(np.float32)
    sigma = np.where(np.isfinite(final.heights), sigma, np.nan).astype(np.float32)
    crs = None if origin is None else origin.get("crs")
    grid = BathyGrid(sigma, final.x0, final.y0, final.cell_size, crs)
    tags = {
        **provenance_tags(method=method),
        "SSS2BATHY_UNITS": "m",
        "SSS2BATHY_VERTICAL_REFERENCE": "none (a standard deviation of the map's heights)",
        "SSS2BATHY_UNCERTAINTY": (
            f"{scale:g} x the delete-a-fold jackknife standard error of {folds.k} fold fits "
            f"of {method} (each without one fold of altimeter blocks), "
            "sss2bathy.eval.uncertainty"
        ),
        "SSS2BATHY_UNCERTAINTY_SCALE": f"{scale:g}",
        "SSS2BATHY_UNCERTAINTY_FOLDS": str(folds.k),
    }
    tif = write_geotiff(
        grid,
        run_dir / "uncertainty.tif",
        origin=origin,
        tags=tags,
        unit="m",
        description=UNCERTAINTY_DESCRIPTION,
    )
    png = render_map(
        grid,
        run_dir / "uncertainty.png",
        f"{title}: height uncertainty (1 sigma, {folds.k}-fold jackknife x {scale:g})",
        cmap="magma",
        label="1 sigma (m)",
        origin=origin,
    )
    return RunUncertainty(tif, png, folds.k, float(scale), describe_sigma(sigma))


__all__ = [
    "GAUSS_1SIGMA",
    "GAUSS_2SIGMA",
    "FoldMaps",
    "RunUncertainty",
    "calibrate_scale",
    "calibration_stats",
    "coverage",
    "describe_sigma",
    "fold_members",
    "jackknife_sigma",
    "scaled_sigma",
    "spearman",
    "write_run_uncertainty",
]
