"""Overlap self-consistency: does the map predict what another line measures off-track?

The K-fold verdict (:mod:`sss2bathy.eval.verdict`) holds out altimeter blocks: points
under the vehicle, where a fit to the altimeter alone is strong by construction and the
sidescan adds little. What the sidescan adds lies off-track. Where swaths overlap, another
line's altimeter measures the seabed there, and that is an observation a fit without that
line never saw.

**Leave one line out.** For each line ``L`` of a survey, its *overlap points* are its
altimeter points that lie inside the sonar footprint of the bins of the *other* lines
(:func:`sss2bathy.eval.maps.swath_footprint_mask`) and not in a cell holding one of the
other lines' altimeter points: seabed the others saw with their sidescan only, off their
tracks. The map is fitted from the other lines alone (their sidescan and their altimeter)
and scored at ``L``'s overlap points against ``L``'s altimeter heights (MAE, m). Beside it,
on the same points: the same fit with no sidescan (``siren_heights_only``) and the
least-squares plane through the other lines' altimeter points (:func:`plane_heights`). A
map that does not beat heights-only there has learnt nothing off-track from the sidescan.

Each held-out line with at least ``min_points`` overlap points is one fold;
:func:`overlap_verdict` compares the methods with the verdict's paired comparison (per-fold
differences, 95 % t interval, "inconclusive" when it contains 0). A single line has no
overlap (its port and starboard swaths meet only across the nadir gap, which neither
images): :func:`overlap_unavailable` says so. :func:`offtrack_counts` decides before any
fit which lines can be held out (an upper bound: every bin beyond the altitude counts as
used). All functions here are pure.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from sss2bathy.eval.maps import altimeter_cells, grid_over_bounds, swath_footprint_mask
from sss2bathy.eval.verdict import HEIGHTS_ONLY, PLANE, KFoldVerdict, kfold_verdict
from sss2bathy.survey import BathyGrid
from sss2bathy.survey.model import SidescanLine

#: what an overlap fold holds out (the verdict sentence's words)
HELD_OUT_LINES = "held-out lines' altimeter off the other lines' tracks"


def _cell_index(grid: BathyGrid, xy: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Column, row and inside-the-grid flag of the cell holding each point ``xy (N, 2)``
    (the cells of :func:`sss2bathy.eval.maps.altimeter_cells`)."""
    ix = np.floor((xy[:, 0] - grid.x0) / grid.cell_size + 0.5).astype(np.int64)
    iy = np.floor((xy[:, 1] - grid.y0) / grid.cell_size + 0.5).astype(np.int64)
    ny, nx = grid.shape
    ok = (ix >= 0) & (ix < nx) & (iy >= 0) & (iy < ny)
    return np.clip(ix, 0, nx - 1), np.clip(iy, 0, ny - 1), ok


def _points(name: str, xyz: np.ndarray) -> np.ndarray:
    pts = np.asarray(xyz, np.float64)
    if pts.ndim != 2 or pts.shape[1] != 3:
        raise ValueError(f"{name}: expected an (N, 3) array of points (m), found {pts.shape}")
    return pts[np.isfinite(pts).all(1)]


def overlap_mask(
    grid: BathyGrid, imaged: np.ndarray, fitted_xyz: np.ndarray, held_xyz: np.ndarray
) -> np.ndarray:
    """``(N,)`` bool: which held-out points ``held_xyz (N, 3)`` are overlap points: their
    cell of ``grid`` is ``imaged`` (``(ny, nx)`` bool, the other lines' footprint) and holds
    none of the fitted altimeter points ``fitted_xyz (M, 3)`` (off their tracks)."""
    imaged = np.asarray(imaged, bool)
    if imaged.shape != grid.shape:
        raise ValueError(f"imaged: expected the grid's shape {grid.shape}, found {imaged.shape}")
    held = np.asarray(held_xyz, np.float64)
    if held.ndim != 2 or held.shape[1] != 3:
        raise ValueError(f"held_xyz: expected an (N, 3) array of points (m), found {held.shape}")
    fitted = _points("fitted_xyz", fitted_xyz)
    off_track = imaged & ~altimeter_cells(grid, fitted[:, :2])
    ix, iy, ok = _cell_index(grid, held[:, :2])
    return ok & off_track[iy, ix] & np.isfinite(held).all(1)


def plane_heights(fitted_xyz: np.ndarray, xy: np.ndarray, min_spread: float = 0.1) -> np.ndarray:
    """The least-squares plane ``z = a + b x + c y`` through ``fitted_xyz (M, 3)`` at
    ``xy (N, 2)``. A horizontal direction along which the points spread less than
    ``min_spread`` x their spread along the main one (points on one straight line: the
    across-track direction, whose spread is only the track's wobble) leaves the slope along
    it undetermined: the plane is level along it (a level extension of the line's profile)."""
    fitted = _points("fitted_xyz", fitted_xyz)
    xy = np.asarray(xy, np.float64).reshape(-1, 2)
    if fitted.shape[0] == 0:
        raise ValueError("fitted_xyz: expected at least one altimeter point, found none")
    centre = fitted[:, :2].mean(0)
    local = fitted[:, :2] - centre
    _, spread, axes = np.linalg.svd(local, full_matrices=False)
    keep = axes[spread > max(float(min_spread) * spread[0], 1e-9)] if spread.size else axes[:0]
    design = np.column_stack([np.ones(len(fitted)), local @ keep.T])
    coef, *_ = np.linalg.lstsq(design, fitted[:, 2], rcond=None)
    return coef[0] + ((xy - centre) @ keep.T) @ coef[1:]


@dataclass(frozen=True)
class OverlapFold:
    """One held-out line's scores.

    Attributes:
        line: the held-out line's name.
        n_points: its overlap points (:func:`overlap_mask`).
        mae: method -> MAE (m) of the map fitted without the line at its overlap points
            (NaN: no point, or the map has none of them).
        offtrack_m: median horizontal distance (m) from the overlap points to the nearest
            fitted altimeter point (how far off the other lines' tracks they lie).
    """

    line: str
    n_points: int
    mae: Mapping[str, float]
    offtrack_m: float


def score_overlap_fold(
    line: str,
    held_xyz: np.ndarray,
    fitted_xyz: np.ndarray,
    imaged: np.ndarray,
    maps: Mapping[str, BathyGrid],
    footprint_grid: BathyGrid,
    min_points: int = 1,
) -> OverlapFold:
    """Score the maps fitted without ``line`` at its overlap points.

    Args:
        line: the held-out line's name.
        held_xyz: ``(N, 3)`` its altimeter points (seabed below the sonar, m).
        fitted_xyz: ``(M, 3)`` the altimeter points the maps were fitted to.
        imaged: ``(ny, nx)`` bool on ``footprint_grid``: the footprint of the bins the
            sidescan fit used (the other lines').
        maps: method -> fitted map (any grid; sampled bilinearly). :data:`PLANE` is added
            (:func:`plane_heights` of ``fitted_xyz``).
        footprint_grid: the grid of ``imaged``.
        min_points: under this many overlap points every MAE is NaN (the fold is skipped).
    """
    if int(min_points) < 1:
        raise ValueError(f"min_points: expected a count >= 1, found {min_points}")
    held = np.asarray(held_xyz, np.float64)
    fitted = _points("fitted_xyz", fitted_xyz)
    inside = overlap_mask(footprint_grid, imaged, fitted, held)
    pts = held[inside]
    names = [*maps, PLANE]
    if pts.shape[0] < int(min_points):
        return OverlapFold(line, int(pts.shape[0]), dict.fromkeys(names, math.nan), math.nan)
    preds = {name: grid.sample(pts[:, 0], pts[:, 1]) for name, grid in maps.items()}
    preds[PLANE] = plane_heights(fitted, pts[:, :2])
    mae = {}
    for name, z in preds.items():
        err = np.abs(np.asarray(z, np.float64) - pts[:, 2])
        err = err[np.isfinite(err)]
        mae[name] = float(err.mean()) if err.size else math.nan
    from scipy.spatial import cKDTree

    dist, _ = cKDTree(fitted[:, :2]).query(pts[:, :2])
    return OverlapFold(line, int(pts.shape[0]), mae, float(np.median(dist)))


def flat_seabed_usable(altitude_m: np.ndarray, range_m: np.ndarray) -> np.ndarray:
    """``(P, 2, B)`` bool: the bins whose slant range exceeds the ping's altitude (a flat
    seabed gives them ground; NaN altitude: none), on both sides."""
    alt = np.asarray(altitude_m, np.float64)[:, None]
    rng = np.asarray(range_m, np.float64)[None, :]
    beyond = np.isfinite(alt) & (rng > np.where(np.isfinite(alt), alt, np.inf))
    return np.repeat(beyond[:, None, :], 2, axis=1)


def offtrack_counts(lines: Sequence[SidescanLine], cell_m: float) -> np.ndarray:
    """``(L,)`` per line, its altimeter points inside the flat-seabed footprint of the other
    lines (every bin beyond the altitude counted, :func:`flat_seabed_usable`: an upper bound
    of what a fit's masked bins image) and off their altimeter cells, on a grid of
    ``cell_m`` cells. A single line gives ``[0]``."""
    if not cell_m > 0:
        raise ValueError(f"cell_m: expected a positive cell size (m), found {cell_m}")
    if len(lines) < 2:
        return np.zeros(len(lines), np.int64)
    reach = max(float(np.max(ln.range_m)) for ln in lines)
    xy = np.concatenate([ln.position[:, :2] for ln in lines])
    lo, hi = xy.min(0) - reach, xy.max(0) + reach
    grid = grid_over_bounds((lo[0], lo[1], hi[0], hi[1]), float(cell_m))
    footprints = [
        swath_footprint_mask(
            grid,
            ln.position,
            ln.rotation,
            ln.altitude_m,
            ln.range_m,
            flat_seabed_usable(ln.altitude_m, ln.range_m),
        )
        for ln in lines
    ]
    counts = []
    for i, line in enumerate(lines):
        others = [j for j in range(len(lines)) if j != i]
        imaged = np.logical_or.reduce([footprints[j] for j in others])
        fitted = np.concatenate([lines[j].altimeter_points() for j in others])
        held = line.altimeter_points()
        counts.append(int(overlap_mask(grid, imaged, fitted, held).sum()))
    return np.asarray(counts, np.int64)


def overlap_unavailable(names: Sequence[str], counts: Sequence[int], min_points: int) -> str | None:
    """Why no overlap score can be computed (one sentence), or None when some line has at
    least ``min_points`` overlap points (``counts``, :func:`offtrack_counts`)."""
    if len(names) != len(counts):
        raise ValueError(f"counts: expected one per line ({len(names)}), found {len(counts)}")
    if len(names) < 2:
        return (
            "not computable: the survey has one line, so no seabed is seen from two lines "
            "(its port and starboard swaths meet only across the nadir gap, which neither "
            "images) and no altimeter can check the map off-track; it needs 2 or more "
            "overlapping lines"
        )
    if max(counts) < int(min_points):
        best = int(np.argmax(counts))
        return (
            f"not computable: no line's altimeter track runs through another line's swath "
            f"footprint at {int(min_points)} or more points (verdict.overlap.min_points; most: "
            f"{int(counts[best])} of line {names[best]}): the lines do not overlap"
        )
    return None


def unscored_reason(folds: Sequence[OverlapFold], min_points: int) -> str | None:
    """Why fitted folds gave no score (one sentence), or None when some fold has
    ``min_points`` or more overlap points inside the fits' own footprint (masked bins make
    it smaller than :func:`offtrack_counts` assumes)."""
    if any(f.n_points >= int(min_points) for f in folds):
        return None
    most = max(folds, key=lambda f: f.n_points) if folds else None
    found = f"most: {most.n_points} of line {most.line}" if most else "no held-out line"
    return (
        f"not computable: the fits' swath footprints (their usable bins) hold fewer than "
        f"{int(min_points)} of any held-out line's altimeter points "
        f"(verdict.overlap.min_points; {found})"
    )


@dataclass(frozen=True)
class OverlapResult:
    """The folds of a leave-one-line-out overlap score and their verdict."""

    folds: tuple[OverlapFold, ...]
    verdict: KFoldVerdict

    @property
    def n_points(self) -> int:
        return sum(f.n_points for f in self.folds)

    def pooled_mae(self) -> dict[str, float]:
        """Method -> MAE over every overlap point of every scored fold (m)."""
        out = {}
        for s in self.verdict.scores:
            pairs = [
                (f.mae.get(s.name, math.nan), f.n_points)
                for f in self.folds
                if math.isfinite(f.mae.get(s.name, math.nan))
            ]
            n = sum(w for _, w in pairs)
            out[s.name] = sum(v * w for v, w in pairs) / n if n else math.nan
        return out

    def lines(self) -> list[str]:
        """The table (fold = a held-out line), one row per line, and the verdict."""
        rows = [f"    {row}" for row in self.verdict.table()]
        rows += [f"    {c.describe()}" for c in self.verdict.comparisons]
        rows.append(
            "    held-out lines: "
            + ", ".join(
                f"{f.line} ({f.n_points} points, {f.offtrack_m:.1f} m off-track)"
                if math.isfinite(f.offtrack_m)
                else f"{f.line} (skipped: {f.n_points} points)"
                for f in self.folds
            )
        )
        return rows

    def to_dict(self) -> dict[str, Any]:
        """Plain values for ``overlap.json``."""
        return {
            "computable": True,
            **self.verdict.to_dict(),
            "pooled_mae": self.pooled_mae(),
            "n_points": self.n_points,
            "lines": [
                {
                    "line": f.line,
                    "n_points": f.n_points,
                    "offtrack_m": f.offtrack_m,
                    "mae": {k: float(v) for k, v in f.mae.items()},
                }
                for f in self.folds
            ],
        }

    def metrics(self, prefix: str = "overlap/") -> dict[str, float]:
        """Flat numbers for ``metrics.json`` (:meth:`KFoldVerdict.metrics` plus
        ``n_points``)."""
        out = self.verdict.metrics(prefix)
        out[f"{prefix}n_points"] = float(self.n_points)
        return out


def overlap_verdict(
    folds: Sequence[OverlapFold], subject: str, seconds: float | None = None
) -> OverlapResult:
    """The verdict on ``subject`` against heights-only and the plane (every other method
    of the folds) over the held-out lines (module docstring)."""
    if not folds:
        raise ValueError("folds: expected at least one held-out line, found none")
    names = list(folds[0].mae)
    if subject not in names:
        raise ValueError(f"subject: expected one of the scored methods {names}, found {subject!r}")
    for f in folds:
        if list(f.mae) != names:
            raise ValueError(
                f"folds: expected the methods {names} in every fold, found {list(f.mae)} "
                f"for line {f.line}"
            )
    scores = {name: [f.mae[name] for f in folds] for name in names}
    verdict = kfold_verdict(scores, subject, seconds=seconds, held_out=HELD_OUT_LINES)
    return OverlapResult(tuple(folds), verdict)


__all__ = [
    "HEIGHTS_ONLY",
    "HELD_OUT_LINES",
    "PLANE",
    "OverlapFold",
    "OverlapResult",
    "flat_seabed_usable",
    "offtrack_counts",
    "overlap_mask",
    "overlap_unavailable",
    "overlap_verdict",
    "plane_heights",
    "score_overlap_fold",
    "unscored_reason",
]
