"""Reconstructed bathymetry maps: sampling a SIREN on a grid, scoring, rendering, export.

* :func:`siren_to_grid` — the SIREN's heights at the cell centres of a grid (aligned with
  the MBES grid, so GeoTIFFs overlay exactly in QGIS).
* :func:`track_region_mask` — the *surveyed area* that maps are scored on: cells within
  ``radius_m`` (the swath's horizontal half-width) of any sonar position of the lines used.
* :func:`map_metrics` — MAE, STD and gradient cosine similarity
  (:mod:`sss2bathy.metrics.bathy`) over that region.
* :func:`gradient_hsv` — the paper's gradient picture: hue = direction
  ``arctan2(dz/dx, dz/dy)`` (the paper's ``arctan(dx/dy)`` over the full circle),
  saturation 1, value = gradient norm (scaled by ``vmax``).
* :func:`swath_footprint_mask` — the cells the sonar's used bins imaged (per ping and
  side, the flat-seabed ground between the first and the last usable bin: no nadir gap,
  nothing before or after the line); with the altimeter cells it is what a fit's
  ``map.tif`` holds data in (:func:`coverage_stats`: imaged area, extrapolated share).
* :func:`coverage_mask` — the older, wider coverage: the track region plus the cells
  holding an altimeter point, grown by a cell (``map.tif``'s when no footprint is given).
* :func:`render_map`, :func:`save_map_outputs` — PNGs and the files of a finished fit. With
  the survey origin the GeoTIFF is in true projected coordinates and the survey's CRS
  (:func:`sss2bathy.io.export.write_geotiff`) and the PNG axes are easting/northing; without
  it the PNGs say "local coordinates".
"""

from __future__ import annotations

import json
import math
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import torch

from sss2bathy.metrics.bathy import bathy_metrics, map_gradient, signed_error
from sss2bathy.survey import BathyGrid
from sss2bathy.utils.atomic import atomic_path, atomic_write_text, save_figure


def grid_over_bounds(
    bounds: Sequence[float],
    cell_size: float,
    crs: str | None = None,
    origin: Mapping[str, Any] | None = None,
) -> BathyGrid:
    """An all-NaN grid whose cell centres cover ``(xmin, ymin, xmax, ymax)`` (m, local
    frame) with ``cell_size`` cells (for surveys without an MBES grid).

    Its cell edges fall on multiples of ``cell_size`` in true projected coordinates (local
    plus the survey ``origin``'s easting / northing; without ``origin``, in the coordinates
    given: the same for an XTF import, whose origin is a multiple of 100 m), so the
    GeoTIFF's corner is a round number and maps of one area line up cell for cell."""
    xmin, ymin, xmax, ymax = (float(b) for b in bounds)
    if not (cell_size > 0 and xmax > xmin and ymax > ymin):
        raise ValueError(
            f"bounds, cell_size: expected xmin < xmax, ymin < ymax and a positive cell, "
            f"found {tuple(bounds)}, {cell_size}"
        )
    shift = [float((origin or {}).get(k) or 0.0) for k in ("easting", "northing")]
    # the first centre: the cell centre (an odd multiple of half a cell, in true
    # coordinates) at or below the bound
    x0, y0 = (
        (math.floor((lo + off) / cell_size - 0.5 + 1e-9) + 0.5) * cell_size - off
        for lo, off in ((xmin, shift[0]), (ymin, shift[1]))
    )
    nx = max(2, int(math.ceil((xmax - x0) / cell_size - 1e-9)) + 1)
    ny = max(2, int(math.ceil((ymax - y0) / cell_size - 1e-9)) + 1)
    return BathyGrid(np.full((ny, nx), np.nan, np.float32), x0, y0, cell_size, crs)


@torch.no_grad()
def siren_to_grid(siren: Any, like: BathyGrid, chunk: int = 65536) -> BathyGrid:
    """Heights of ``siren`` at every cell centre of ``like`` (same geometry and CRS).

    Args:
        siren: a model with ``height(xy (N, 2)) -> (N,)`` (m).
        like: the grid to align with (its heights are not read).
        chunk: points per evaluation.
    """
    if not isinstance(like, BathyGrid):
        raise ValueError(f"like: expected a BathyGrid, found {type(like).__name__}")
    if chunk < 1:
        raise ValueError(f"chunk: expected a positive number of points, found {chunk}")
    param = next(iter(siren.parameters()), None)
    device = param.device if param is not None else torch.device("cpu")
    xx, yy = np.meshgrid(like.x, like.y)
    xy = torch.from_numpy(np.stack([xx.ravel(), yy.ravel()], 1).astype(np.float32)).to(device)
    z = torch.cat([siren.height(part) for part in xy.split(chunk)])
    heights = z.float().cpu().numpy().reshape(like.shape)
    return BathyGrid(heights, like.x0, like.y0, like.cell_size, like.crs)


def track_region_mask(grid: BathyGrid, track_xy: np.ndarray, radius_m: float) -> np.ndarray:
    """``(ny, nx)`` bool: cells whose centre lies within ``radius_m`` of a track point.

    Args:
        grid: the map grid.
        track_xy: ``(M, 2)`` sonar positions (m) of the lines used.
        radius_m: swath half-width on the ground (m).
    """
    from scipy.spatial import cKDTree

    track_xy = np.asarray(track_xy, dtype=np.float64)
    if track_xy.ndim != 2 or track_xy.shape[1] != 2 or track_xy.shape[0] == 0:
        raise ValueError(f"track_xy: expected a non-empty (M, 2) array, found {track_xy.shape}")
    if not radius_m > 0:
        raise ValueError(f"radius_m: expected a positive radius (m), found {radius_m}")
    xx, yy = np.meshgrid(grid.x, grid.y)
    dist, _ = cKDTree(track_xy).query(
        np.stack([xx.ravel(), yy.ravel()], 1), distance_upper_bound=radius_m * (1 + 1e-9)
    )
    return (dist <= radius_m).reshape(grid.shape)


def altimeter_cells(grid: BathyGrid, xy: np.ndarray) -> np.ndarray:
    """``(ny, nx)`` bool: the cells whose area holds at least one of the points ``xy (N, 2)``."""
    xy = np.asarray(xy, dtype=np.float64).reshape(-1, 2)
    out = np.zeros(grid.shape, dtype=bool)
    ix = np.floor((xy[:, 0] - grid.x0) / grid.cell_size + 0.5).astype(np.int64)
    iy = np.floor((xy[:, 1] - grid.y0) / grid.cell_size + 0.5).astype(np.int64)
    ok = (ix >= 0) & (ix < grid.shape[1]) & (iy >= 0) & (iy < grid.shape[0])
    out[iy[ok], ix[ok]] = True
    return out


def coverage_mask(
    grid: BathyGrid,
    region: np.ndarray,
    altimeter_xy: np.ndarray | None = None,
    margin_cells: int = 1,
) -> np.ndarray:
    """Cells some measurement constrains: ``region`` (the sidescan swaths,
    :func:`track_region_mask`) plus the cells holding an altimeter point, grown by
    ``margin_cells`` (default 1: the central-difference stencil, so the slope of every
    covered cell can still be computed from the written map)."""
    region = np.asarray(region, dtype=bool)
    if region.shape != grid.shape:
        raise ValueError(f"region: expected the grid's shape {grid.shape}, found {region.shape}")
    if int(margin_cells) != margin_cells or margin_cells < 0:
        raise ValueError(f"margin_cells: expected a count >= 0, found {margin_cells}")
    covered = region.copy()
    if altimeter_xy is not None and len(altimeter_xy):
        covered |= altimeter_cells(grid, altimeter_xy)
    if margin_cells and covered.any():
        from scipy.ndimage import binary_dilation

        covered = binary_dilation(covered, np.ones((3, 3), bool), iterations=int(margin_cells))
    return covered


def swath_footprint_mask(
    grid: BathyGrid,
    position: np.ndarray,
    rotation: np.ndarray,
    altitude_m: np.ndarray,
    range_m: np.ndarray,
    usable: np.ndarray,
    line: np.ndarray | None = None,
    max_step_m: float | None = None,
) -> np.ndarray:
    """``(ny, nx)`` bool: cells whose centre the sonar's used bins imaged (flat seabed).

    Per ping and side, the ground between the first and the last usable bin: slant range
    ``r`` lies ``sqrt(r^2 - h^2)`` across track on a flat seabed ``h = altitude`` below
    the sonar, along the horizontal part of the side's across-track axis ``sigma R e_y``
    (sigma = +1 port, -1 starboard; docs/architecture.md). The water column, the nadir
    gap and the ranges beyond the last usable bin are outside. Consecutive pings of one
    line (``line``) are joined by the quadrilateral between their near and far ground
    points (two triangles, cells whose centre lies inside or on an edge), so the strips
    leave no holes; each ping's own near-far segment is drawn too (sampled every half
    cell), so a lone ping still counts. Two pings more than ``max_step_m`` apart (default
    ``max(4 x the line's median non-zero step, 2 cells)``: a gap in the navigation) are
    not joined.

    Args:
        grid: the map grid.
        position: ``(P, 3)`` sonar positions (m), pings of a line in order.
        rotation: ``(P, 3, 3)`` vehicle -> world rotations.
        altitude_m: ``(P,)`` altitude above the seabed (m), NaN = none (the ping images
            nothing).
        range_m: ``(B,)`` slant range of each bin (m).
        usable: ``(P, 2, B)`` bool, the bins the fit uses (e.g. ``mask == 0``).
        line: ``(P,)`` line index of each ping (None: one line).
        max_step_m: see above.
    """
    pos = np.asarray(position, np.float64)
    rot = np.asarray(rotation, np.float64)
    alt = np.asarray(altitude_m, np.float64)
    rng = np.asarray(range_m, np.float64)
    use = np.asarray(usable, bool)
    n = pos.shape[0] if pos.ndim == 2 else -1
    if pos.shape != (n, 3) or rot.shape != (n, 3, 3) or alt.shape != (n,):
        raise ValueError(
            f"position, rotation, altitude_m: expected (P, 3), (P, 3, 3), (P,), found "
            f"{pos.shape}, {rot.shape}, {alt.shape}"
        )
    if rng.ndim != 1 or use.shape != (n, 2, rng.shape[0]):
        raise ValueError(
            f"usable: expected shape ({n}, 2, {rng.shape[0] if rng.ndim == 1 else '?'}), "
            f"found {use.shape}"
        )
    line = np.zeros(n, np.int64) if line is None else np.asarray(line).astype(np.int64)
    if line.shape != (n,):
        raise ValueError(f"line: expected shape ({n},), found {line.shape}")
    out = np.zeros(grid.shape, bool)
    if n == 0:
        return out
    use = use & np.isfinite(alt)[:, None, None]
    has = use.any(-1)  # (P, 2)
    first = np.argmax(use, -1)
    last = rng.shape[0] - 1 - np.argmax(use[..., ::-1], -1)
    h2 = np.where(np.isfinite(alt), alt, 0.0)[:, None] ** 2
    ground = lambda r: np.sqrt(np.maximum(r**2 - h2, 0.0))  # noqa: E731
    near, far = ground(rng[first]), ground(rng[last])  # (P, 2)
    across = rot[:, :2, 1]  # the vehicle's port axis, horizontal part
    norm = np.linalg.norm(across, axis=1, keepdims=True)
    across = np.divide(across, norm, out=np.zeros_like(across), where=norm > 1e-9)
    sigma = np.array([1.0, -1.0])
    direction = sigma[None, :, None] * across[:, None, :]  # (P, 2, 2)
    xy = pos[:, None, :2]
    p_near, p_far = xy + near[..., None] * direction, xy + far[..., None] * direction
    step = np.hypot(*np.diff(pos[:, :2], axis=0).T)
    joined = line[1:] == line[:-1]
    if max_step_m is None:
        limit = np.full(n - 1, 2.0 * grid.cell_size)
        for ln in np.unique(line):
            idx = np.flatnonzero((line[:-1] == ln) & joined)
            moving = step[idx][step[idx] > 1e-6]
            if moving.size:
                limit[idx] = max(4.0 * float(np.median(moving)), 2.0 * grid.cell_size)
    else:
        limit = np.full(n - 1, float(max_step_m))
    joined &= step <= limit
    tris = []
    for side in (0, 1):
        pair = joined & has[:-1, side] & has[1:, side]
        a0, a1 = p_near[:-1, side][pair], p_far[:-1, side][pair]
        b0, b1 = p_near[1:, side][pair], p_far[1:, side][pair]
        tris += [np.stack([a0, a1, b1], 1), np.stack([a0, b1, b0], 1)]
    _fill_triangles(out, grid, np.concatenate(tris) if tris else np.zeros((0, 3, 2)))
    # every ping's own near-far segment, sampled every half cell
    seg_near, seg_far = p_near[has], p_far[has]
    length = np.linalg.norm(seg_far - seg_near, axis=1)
    steps = np.ceil(length / (0.5 * grid.cell_size)).astype(np.int64) + 1
    if steps.size:
        which = np.repeat(np.arange(steps.size), steps)
        t = (np.arange(which.size) - np.repeat(np.cumsum(steps) - steps, steps)) / np.maximum(
            np.repeat(steps, steps) - 1, 1
        )
        pts = seg_near[which] + t[:, None] * (seg_far[which] - seg_near[which])
        out |= altimeter_cells(grid, pts)
    return out


def _fill_triangles(out: np.ndarray, grid: BathyGrid, tri: np.ndarray) -> None:
    """Set the cells of ``out`` whose centre lies in (or on an edge of) one of the
    triangles ``tri (T, 3, 2)`` (world m); degenerate triangles are skipped."""
    if tri.shape[0] == 0:
        return
    c = grid.cell_size
    # triangle vertices in cell units (cell centres at integers)
    v = np.stack([(tri[..., 0] - grid.x0) / c, (tri[..., 1] - grid.y0) / c], -1)
    e1, e2 = v[:, 1] - v[:, 0], v[:, 2] - v[:, 0]
    area = e1[:, 0] * e2[:, 1] - e1[:, 1] * e2[:, 0]
    v = v[np.abs(area) > 1e-9]
    if not v.shape[0]:
        return
    ny, nx = grid.shape
    lo = np.clip(np.ceil(v.min(1) - 1e-9), 0, [nx, ny]).astype(np.int64)
    hi = np.clip(np.floor(v.max(1) + 1e-9), -1, [nx - 1, ny - 1]).astype(np.int64)
    size = np.maximum(hi - lo + 1, 0)
    keep = (size > 0).all(1)
    v, lo, size = v[keep], lo[keep], size[keep]
    order = np.argsort(size[:, 0] * size[:, 1])
    v, lo, size = v[order], lo[order], size[order]
    start = 0
    while start < v.shape[0]:  # chunks of triangles with bounding boxes of similar size
        w, h = size[start]
        stop = start + 1
        while stop < v.shape[0]:
            nw, nh = max(w, size[stop, 0]), max(h, size[stop, 1])
            if (stop - start + 1) * nw * nh > 2_000_000:
                break
            w, h, stop = nw, nh, stop + 1
        ox, oy = np.meshgrid(np.arange(w), np.arange(h))
        px = lo[start:stop, 0, None] + ox.ravel()[None]  # (T, w*h)
        py = lo[start:stop, 1, None] + oy.ravel()[None]
        tv = v[start:stop]
        sides = []
        for i in range(3):
            a, b = tv[:, i], tv[:, (i + 1) % 3]
            sides.append(
                (b[:, 0, None] - a[:, 0, None]) * (py - a[:, 1, None])
                - (b[:, 1, None] - a[:, 1, None]) * (px - a[:, 0, None])
            )
        d = np.stack(sides)
        eps = 1e-9
        inside = ((d >= -eps).all(0) | (d <= eps).all(0)) & (px < nx) & (py < ny)
        out[py[inside], px[inside]] = True
        start = stop


def coverage_stats(
    grid: BathyGrid, written: np.ndarray, imaged: np.ndarray, altimeter: np.ndarray | None = None
) -> dict[str, float]:
    """Coverage of a written map: ``imaged_area_m2`` (the sonar footprint,
    :func:`swath_footprint_mask`), ``measured_area_m2`` (footprint plus altimeter cells),
    ``written_area_m2`` (the map's cells with data) and ``extrapolated_share`` (the share of
    those that no measurement constrains: neither imaged nor holding an altimeter point).

    Args:
        grid: the map grid.
        written, imaged: ``(ny, nx)`` bool, the map's cells with data and the footprint.
        altimeter: ``(ny, nx)`` bool cells holding an altimeter point (:func:`altimeter_cells`).
    """
    written, imaged = np.asarray(written, bool), np.asarray(imaged, bool)
    for name, arr in (("written", written), ("imaged", imaged)):
        if arr.shape != grid.shape:
            raise ValueError(f"{name}: expected the grid's shape {grid.shape}, found {arr.shape}")
    measured = imaged | (np.zeros_like(imaged) if altimeter is None else np.asarray(altimeter))
    cell_area = float(grid.cell_size) ** 2
    n_written = int(written.sum())
    return {
        "imaged_area_m2": float(imaged.sum()) * cell_area,
        "measured_area_m2": float(measured.sum()) * cell_area,
        "written_area_m2": float(n_written) * cell_area,
        "extrapolated_share": float((written & ~measured).sum()) / n_written if n_written else 0.0,
    }


def map_metrics(
    pred_grid: BathyGrid, true_grid: BathyGrid, region_mask: np.ndarray | None = None
) -> dict[str, float]:
    """``mae``, ``std``, ``grad_cs``, ``n_cells`` of a map against the MBES grid.

    Both grids must share geometry (use :func:`siren_to_grid` with ``like=true_grid``).
    """
    same = pred_grid.shape == true_grid.shape and np.allclose(
        [pred_grid.x0, pred_grid.y0, pred_grid.cell_size],
        [true_grid.x0, true_grid.y0, true_grid.cell_size],
    )
    if not same:
        raise ValueError(
            "pred_grid: expected the geometry of true_grid "
            f"{true_grid.shape, true_grid.x0, true_grid.y0, true_grid.cell_size}, found "
            f"{pred_grid.shape, pred_grid.x0, pred_grid.y0, pred_grid.cell_size}"
        )
    return bathy_metrics(pred_grid.heights, true_grid.heights, true_grid.cell_size, region_mask)


def gradient_hsv(dzdx: np.ndarray, dzdy: np.ndarray, vmax: float | None = None) -> np.ndarray:
    """``(ny, nx, 3)`` float RGB in ``[0, 1]`` of a gradient map (the paper's HSV picture).

    Hue = ``arctan2(dz/dx, dz/dy)`` mapped to ``[0, 1)``, saturation 1, value =
    ``min(|grad| / vmax, 1)``; ``vmax`` defaults to the 99th percentile of the finite norms
    (pass the MBES map's value to compare maps on one scale). NaN cells are black.
    """
    from matplotlib.colors import hsv_to_rgb

    dzdx, dzdy = np.asarray(dzdx, dtype=np.float64), np.asarray(dzdy, dtype=np.float64)
    if dzdx.ndim != 2 or dzdx.shape != dzdy.shape:
        raise ValueError(
            f"dzdx, dzdy: expected two 2D maps of one shape, found {dzdx.shape}, {dzdy.shape}"
        )
    norm = np.hypot(dzdx, dzdy)
    finite = np.isfinite(norm)
    if vmax is None:
        vmax = float(np.percentile(norm[finite], 99)) if finite.any() else 1.0
    vmax = vmax if vmax > 0 else 1.0
    hue = np.mod(np.arctan2(dzdx, dzdy) / (2 * np.pi), 1.0)
    hsv = np.stack(
        [
            np.where(finite, hue, 0.0),
            np.ones_like(norm),
            np.where(finite, np.clip(norm / vmax, 0.0, 1.0), 0.0),
        ],
        axis=-1,
    )
    return hsv_to_rgb(hsv).astype(np.float32)


HEIGHT_LABEL = "seabed height z (m, up; z = -depth)"
ERROR_LABEL = "signed error map - MBES (m)"


def map_figure(
    grid_or_array: BathyGrid | np.ndarray,
    title: str,
    cmap: str = "viridis",
    symmetric: bool = False,
    label: str = HEIGHT_LABEL,
    extent: Sequence[float] | None = None,
    origin: Mapping[str, Any] | None = None,
    vmax: float | None = None,
    figsize: tuple[float, float] = (7.5, 5.5),
) -> Any:
    """A map as a matplotlib ``Figure`` a surveyor reads without help (north up).

    A scalar map gets a colour bar labelled ``label`` (its unit); an RGB gradient picture
    (:func:`gradient_hsv`) gets the HSV colour-wheel key beside it. Axes are projected
    easting/northing when ``origin`` is known (the CRS named), else local metres; a north
    arrow and "North up" sit on the map. Save it with
    :func:`sss2bathy.utils.atomic.save_figure`, log it with TensorBoard's ``add_figure`` or
    turn it into pixels with :func:`figure_to_rgb`.

    Args:
        grid_or_array: a :class:`BathyGrid`, a ``(ny, nx)`` array (row 0 south) or an
            ``(ny, nx, 3)`` RGB gradient image.
        title: the figure title; name the experiment and survey (e.g.
            ``"SIREN-GT-N2d on synthetic_d1: bathymetry"``).
        cmap, symmetric, label: colour map, ``+-max|value|`` limits (signed errors) and
            colour-bar label of scalar maps.
        extent: ``(xmin, xmax, ymin, ymax)`` in local metres (taken from a grid).
        origin: the survey origin ``{"crs", "easting", "northing"}``.
        vmax: gradient norm (m/m) at full brightness of an RGB gradient image, for its key.
        figsize: inches.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    if isinstance(grid_or_array, BathyGrid):
        data, extent = grid_or_array.heights, _extent(grid_or_array)
    else:
        data = np.asarray(grid_or_array)
    if data.ndim not in (2, 3) or (data.ndim == 3 and data.shape[-1] != 3):
        raise ValueError(f"grid_or_array: expected (ny, nx) or (ny, nx, 3), found {data.shape}")
    if extent is not None and origin is not None:
        e, n = float(origin.get("easting", 0.0)), float(origin.get("northing", 0.0))
        x0, x1, y0, y1 = extent
        extent = (x0 + e, x1 + e, y0 + n, y1 + n)
    if data.ndim == 2:
        fig, ax = plt.subplots(figsize=figsize)
    else:  # the colour-wheel key in a column of its own
        fig, (ax, key) = plt.subplots(
            1, 2, figsize=figsize, gridspec_kw={"width_ratios": [4.0, 1.4]}
        )
    kw: dict[str, Any] = {"origin": "lower", "extent": extent, "interpolation": "nearest"}
    if data.ndim == 2:
        finite = data[np.isfinite(data)]
        if symmetric and finite.size:
            lim = float(np.percentile(np.abs(finite), 99.5)) or 1.0
            kw.update(vmin=-lim, vmax=lim)
        im = ax.imshow(np.ma.masked_invalid(data), cmap=cmap, **kw)
        fig.colorbar(im, ax=ax, label=label, shrink=0.9)
    else:
        ax.imshow(data, **kw)
        hsv_wheel_key(key, vmax)
    ax.set_title(title, fontsize=10)
    if extent is None:
        ax.set_xlabel("column (east)")
        ax.set_ylabel("row (north)")
    else:
        xlabel, ylabel = axis_labels(origin)
        ax.set_xlabel(xlabel, fontsize=8)
        ax.set_ylabel(ylabel, fontsize=8)
        _plain_ticks(ax)
    north_arrow(ax)
    fig.tight_layout()
    return fig


def render_map(
    grid_or_array: BathyGrid | np.ndarray,
    path: str | Path,
    title: str,
    cmap: str = "viridis",
    symmetric: bool = False,
    label: str = HEIGHT_LABEL,
    extent: Sequence[float] | None = None,
    origin: Mapping[str, Any] | None = None,
    vmax: float | None = None,
) -> Path:
    """Write :func:`map_figure` of a map as a PNG at ``path`` (same arguments)."""
    fig = map_figure(grid_or_array, title, cmap, symmetric, label, extent, origin, vmax)
    return save_figure(fig, path, dpi=110)


def hsv_wheel_key(ax: Any, vmax: float | None = None, n: int = 129) -> None:
    """Draw the key of :func:`gradient_hsv` pictures into ``ax``: a colour wheel whose hue is
    the upslope direction (the compass point the seabed rises towards; north up) and whose
    brightness is the slope ``|grad z|``, from black (flat) at the centre to full at the rim
    (``vmax`` m/m, said under the wheel when given)."""
    g = np.linspace(-1.0, 1.0, n)
    gx, gy = np.meshgrid(g, g)  # gx: dz/dx (east), gy: dz/dy (north)
    rgb = gradient_hsv(np.where(np.hypot(gx, gy) <= 1, gx, np.nan), gy, vmax=1.0)
    outside = np.hypot(gx, gy) > 1
    rgba = np.concatenate([rgb, (~outside)[..., None].astype(np.float32)], axis=-1)
    ax.imshow(rgba, origin="lower", extent=(-1, 1, -1, 1), interpolation="bilinear")
    for text, (x, y) in {"N": (0, 1.22), "E": (1.22, 0), "S": (0, -1.22), "W": (-1.22, 0)}.items():
        ax.text(x, y, text, ha="center", va="center", fontsize=7, fontweight="bold")
    ax.set_xlim(-1.45, 1.45)
    ax.set_ylim(-1.45, 1.45)
    ax.set_aspect("equal")
    ax.axis("off")
    rim = f"rim: |grad z| >= {vmax:.3g} m/m" if vmax is not None else "rim: the steepest 1 %"
    ax.set_title("gradient key\nhue: upslope direction", fontsize=7)
    ax.text(
        0, -1.75, f"brightness: slope\n(centre: flat; {rim})", ha="center", va="top", fontsize=6
    )


def north_arrow(ax: Any) -> None:
    """A north arrow and "North up" on a map's axes (top right; readable on dark and light)."""
    from matplotlib import patheffects

    halo = [patheffects.withStroke(linewidth=3, foreground="white")]
    ax.annotate(
        "",
        xy=(0.95, 0.97),
        xytext=(0.95, 0.85),
        xycoords="axes fraction",
        arrowprops={"arrowstyle": "-|>", "color": "k", "lw": 1.5, "path_effects": halo},
    )
    ax.text(
        0.95,
        0.81,
        "N",
        transform=ax.transAxes,
        ha="center",
        va="center",
        fontsize=9,
        fontweight="bold",
        path_effects=halo,
    )
    ax.text(
        0.02,
        0.02,
        "North up",
        transform=ax.transAxes,
        fontsize=6,
        bbox={"boxstyle": "round,pad=0.15", "fc": "white", "ec": "none", "alpha": 0.8},
    )


def waterfall_figure(
    intensity: np.ndarray,
    n_lat: np.ndarray,
    n_lat_true: np.ndarray | None = None,
    mask: np.ndarray | None = None,
    title: str = "",
    normal_limit: float | None = None,
    figsize: tuple[float, float] | None = None,
) -> Any:
    """A sidescan waterfall with its lateral normal component ``n_lat`` beside it (and the
    ground truth's with ``n_lat_true``): a matplotlib ``Figure``, pings upward, colour bars
    labelled.

    Args:
        intensity: ``(pings, bins)`` sidescan intensity (any scale; shown 1-99 % stretched).
        n_lat: ``(pings, bins)`` estimated n_lat (unitless, the normal's across-track
            component in the head plane; ``RdBu_r`` over ``+-normal_limit``).
        n_lat_true: the same from the MBES (draped), or None.
        mask: ``(pings, bins)`` bool, True = valid bin; invalid bins are grey.
        title: names the run and line (e.g. ``"CNN on synthetic_d1, line T03"``).
        normal_limit: n_lat colour range; default the 98th percentile of ``|n_lat|``.
        figsize: inches; default scales with the number of panels.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    inten = np.asarray(intensity, dtype=np.float64)
    if inten.ndim != 2:
        raise ValueError(f"intensity: expected a (pings, bins) array, found {inten.shape}")
    panels = [("n_lat (estimated)", np.asarray(n_lat, dtype=np.float64))]
    if n_lat_true is not None:
        panels.append(("n_lat (MBES, draped)", np.asarray(n_lat_true, dtype=np.float64)))
    for name, arr in [("n_lat", panels[0][1])] + (
        [("n_lat_true", panels[1][1])] if n_lat_true is not None else []
    ):
        if arr.shape != inten.shape:
            raise ValueError(
                f"{name}: expected the shape of intensity {inten.shape}, found {arr.shape}"
            )
    valid = np.ones(inten.shape, bool) if mask is None else np.asarray(mask, dtype=bool)
    if valid.shape != inten.shape:
        raise ValueError(
            f"mask: expected the shape of intensity {inten.shape}, found {valid.shape}"
        )
    if normal_limit is None:
        ref = np.abs(panels[-1][1][valid & np.isfinite(panels[-1][1])])
        normal_limit = max(0.05, float(np.percentile(ref, 98))) if ref.size else 0.5
    shown = inten[valid & np.isfinite(inten)]
    lo, hi = np.percentile(shown, [1, 99]) if shown.size else (0.0, 1.0)
    ncol = 1 + len(panels)
    fig, axes = plt.subplots(1, ncol, figsize=figsize or (3.6 * ncol, 5.0), squeeze=False)
    axes = axes[0]
    kw: dict[str, Any] = {"origin": "lower", "aspect": "auto", "interpolation": "nearest"}
    cmap_gray = matplotlib.colormaps["gray"].with_extremes(bad="0.6")
    im = axes[0].imshow(np.ma.masked_where(~valid, inten), cmap=cmap_gray, vmin=lo, vmax=hi, **kw)
    fig.colorbar(im, ax=axes[0], label="intensity (1-99 % stretch)", shrink=0.85)
    axes[0].set_title("sidescan waterfall", fontsize=9)
    cmap_n = matplotlib.colormaps["RdBu_r"].with_extremes(bad="0.6")
    for ax, (name, arr) in zip(axes[1:], panels, strict=True):
        im = ax.imshow(
            np.ma.masked_where(~valid, arr),
            cmap=cmap_n,
            vmin=-normal_limit,
            vmax=normal_limit,
            **kw,
        )
        fig.colorbar(im, ax=ax, label="n_lat (unitless)", shrink=0.85)
        ax.set_title(name, fontsize=9)
    for ax in axes:
        ax.set_xlabel("bin (port | starboard)", fontsize=8)
        ax.tick_params(labelsize=7)
    axes[0].set_ylabel("ping (time upward)", fontsize=8)
    if title:
        fig.suptitle(title, fontsize=10)
    fig.tight_layout()
    return fig


def figure_to_rgb(fig: Any, close: bool = True) -> np.ndarray:
    """``(H, W, 3)`` uint8 pixels of a matplotlib figure (for image loggers); closes it."""
    import matplotlib.pyplot as plt

    fig.canvas.draw()
    rgb = np.asarray(fig.canvas.buffer_rgba())[..., :3].copy()
    if close:
        plt.close(fig)
    return rgb


def axis_labels(origin: Mapping[str, Any] | None) -> tuple[str, str]:
    """Axis labels of a map figure: projected easting/northing (with the CRS) when the survey
    origin is known, else local coordinates (and the origin when it is known but unnamed)."""
    if origin is None:
        return "x east (m), local coordinates", "y north (m), local coordinates"
    crs = origin.get("crs")
    if crs:
        return f"easting (m), {_crs_label(crs)}", f"northing (m), {_crs_label(crs)}"
    e, n = float(origin.get("easting", 0.0)), float(origin.get("northing", 0.0))
    return f"easting (m), no CRS (origin E {e:.1f})", f"northing (m), no CRS (origin N {n:.1f})"


def _crs_label(crs: str) -> str:
    try:
        from pyproj import CRS

        c = CRS.from_user_input(crs)
        epsg = c.to_epsg()
        return f"EPSG:{epsg}" if epsg else c.name
    except Exception:  # an unparsable label is still shown as given
        return str(crs)[:40]


def _plain_ticks(ax: Any) -> None:
    from matplotlib.ticker import ScalarFormatter

    for axis in (ax.xaxis, ax.yaxis):
        fmt = ScalarFormatter(useOffset=False)
        fmt.set_scientific(False)
        axis.set_major_formatter(fmt)
    ax.tick_params(labelsize=7)


def colorize(data: np.ndarray, cmap: str = "viridis", symmetric: bool = False) -> np.ndarray:
    """``(ny, nx, 3)`` float RGB of a scalar map (NaN black), for image loggers.

    Limits: the 0.5/99.5 percentiles, or ``+-`` the 99.5 percentile of ``|data|`` with
    ``symmetric``. Row 0 stays row 0 (flip vertically to show north up).
    """
    import matplotlib

    data = np.asarray(data, dtype=np.float64)
    if data.ndim != 2:
        raise ValueError(f"data: expected a 2D map, found shape {data.shape}")
    finite = np.isfinite(data)
    if not finite.any():
        return np.zeros((*data.shape, 3), np.float32)
    if symmetric:
        hi = float(np.percentile(np.abs(data[finite]), 99.5)) or 1.0
        lo = -hi
    else:
        lo, hi = (float(v) for v in np.percentile(data[finite], [0.5, 99.5]))
        hi = hi if hi > lo else lo + 1.0
    rgb = matplotlib.colormaps[cmap](np.clip((data - lo) / (hi - lo), 0.0, 1.0))[..., :3]
    return np.where(finite[..., None], rgb, 0.0).astype(np.float32)


def error_map(pred: BathyGrid, true: BathyGrid, region: np.ndarray | None) -> np.ndarray:
    """``(ny, nx)`` signed error ``pred - true`` (m), NaN outside ``region``."""
    err = signed_error(pred.heights, true.heights)
    return np.where(region, err, np.nan) if region is not None else err


def save_map_outputs(
    out_dir: str | Path,
    pred: BathyGrid,
    true: BathyGrid | None = None,
    region: np.ndarray | None = None,
    metrics: dict[str, Any] | None = None,
    title: str = "SIREN",
    origin: Mapping[str, Any] | None = None,
    altimeter_xy: np.ndarray | None = None,
    coverage: np.ndarray | None = None,
) -> dict[str, Path]:
    """Write a finished map: ``map.tif`` (GeoTIFF), ``map.npz``, ``metrics.json`` and PNGs
    (``map.png``, ``gradient_hsv.png``, with an MBES grid also ``error.png``,
    ``gt_gradient_hsv.png``). Returns the written paths by name.

    Args:
        out_dir, pred, true, region, metrics, title: the run folder, the map (local frame),
            the MBES grid, the scored region (:func:`track_region_mask`), the metrics and the
            figure title.
        origin: the survey origin: ``map.tif`` in projected coordinates and the survey's CRS
            (none when the survey has none), PNG axes in easting/northing. Without it the
            GeoTIFF is in local coordinates **without a CRS** (a WARNING says so).
        altimeter_xy: ``(N, 2)`` altimeter points used: their cells count as covered.
        coverage: ``(ny, nx)`` bool, the cells the written map holds data in: what the
            measurements constrain (the sonar's footprint, :func:`swath_footprint_mask`,
            plus the altimeter cells). None: :func:`coverage_mask` of ``region`` and
            ``altimeter_xy`` (when ``region`` is given), else every cell.

    ``map.tif`` and ``map.png`` (and ``gradient_hsv.png``) are no-data outside the coverage;
    ``map.npz`` keeps every cell, the region and the coverage. ``error.png`` shows the
    scored ``region``.
    """
    from sss2bathy.io.export import write_geotiff

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    paths = {"map_tif": out / "map.tif", "map_npz": out / "map.npz"}
    if coverage is not None:
        covered = np.asarray(coverage, bool)
        if covered.shape != pred.shape:
            raise ValueError(
                f"coverage: expected the map's shape {pred.shape}, found {covered.shape}"
            )
    else:
        covered = coverage_mask(pred, region, altimeter_xy) if region is not None else None
    if origin is None:  # local coordinates: a CRS label would put the map in the wrong place
        local = BathyGrid(pred.heights, pred.x0, pred.y0, pred.cell_size)
        write_geotiff(local, paths["map_tif"], mask=covered)
    else:
        write_geotiff(pred, paths["map_tif"], origin=origin, mask=covered)
    arrays: dict[str, np.ndarray] = {
        "heights": pred.heights,
        "x0": np.float64(pred.x0),
        "y0": np.float64(pred.y0),
        "cell_size": np.float64(pred.cell_size),
    }
    if region is not None:
        arrays["region"] = region
    if covered is not None:
        arrays["coverage"] = covered
    with atomic_path(paths["map_npz"]) as tmp:
        with open(tmp, "wb") as f:
            np.savez_compressed(f, **arrays)
    shown = BathyGrid(
        np.where(covered, pred.heights, np.nan) if covered is not None else pred.heights,
        pred.x0,
        pred.y0,
        pred.cell_size,
    )
    paths["map_png"] = render_map(shown, out / "map.png", f"{title}: bathymetry", origin=origin)
    vmax = None
    if true is not None:
        tx, ty = map_gradient(true.heights, true.cell_size)
        vmax = _gradient_vmax(tx, ty)
        paths["gt_gradient_png"] = render_map(
            gradient_hsv(tx, ty, vmax),
            out / "gt_gradient_hsv.png",
            f"MBES (ground truth) beside {title}: gradient (HSV)",
            extent=_extent(true),
            origin=origin,
            vmax=vmax,
        )
        paths["error_png"] = render_map(
            error_map(pred, true, region),
            out / "error.png",
            f"{title}: signed error against the MBES",
            cmap="RdBu_r",
            symmetric=True,
            label=ERROR_LABEL,
            extent=_extent(true),
            origin=origin,
        )
    px, py = map_gradient(shown.heights, pred.cell_size)
    vmax = vmax if vmax is not None else _gradient_vmax(px, py)
    paths["gradient_png"] = render_map(
        gradient_hsv(px, py, vmax),
        out / "gradient_hsv.png",
        f"{title}: gradient (HSV)",
        extent=_extent(pred),
        origin=origin,
        vmax=vmax,
    )
    if metrics is not None:
        paths["metrics"] = out / "metrics.json"
        atomic_write_text(paths["metrics"], json.dumps(metrics, indent=2, sort_keys=True))
    return paths


def _gradient_vmax(dzdx: np.ndarray, dzdy: np.ndarray) -> float | None:
    """The slope (m/m) of full brightness in :func:`gradient_hsv`: the 99th percentile."""
    norm = np.hypot(dzdx, dzdy)
    return float(np.nanpercentile(norm, 99)) if np.isfinite(norm).any() else None


def _extent(g: BathyGrid) -> tuple[float, float, float, float]:
    h = g.cell_size / 2
    return (g.x[0] - h, g.x[-1] + h, g.y[0] - h, g.y[-1] + h)
