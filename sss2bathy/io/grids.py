"""Bathymetry grids and meshes in: GeoTIFF / ESRI ASCII (rasterio), BAG (h5py), XYZ points, meshes.

Every reader returns a :class:`~sss2bathy.survey.BathyGrid` (row 0 = south, ``x0, y0`` = centre
of the SW cell, square cells). CRS handling, in one place (:func:`read_grid`):

* the grid's CRS comes from the file (GeoTIFF/ASCII header, BAG ISO metadata) or, for files
  without one (XYZ, meshes), from ``source_crs``;
* the wanted CRS is ``target_crs``, or the survey origin's CRS when ``origin`` is given;
* equivalent CRSs (a point moves < 1 mm between them) are relabelled, different ones are
  reprojected (rasters: ``rasterio.warp.reproject``, bilinear; points and meshes: pyproj)
  or, with ``on_crs_mismatch="error"``, refused with a message naming both CRSs;
* a geographic grid (degrees) without a projected target is refused;
* with ``origin`` the grid is shifted into the survey's local frame (x - easting,
  y - northing).

Damaged files are refused in one line naming the file (:class:`SurveyFormatError`): not a
raster of the suffix's format (a PNG named ``.tif``), no georeferencing, truncated or
unreadable, no valid cell. Repairs are WARNINGs with counts, made at the file's own
resolution before any reprojection: cells holding an untagged no-data value (beyond
+-11 km, or a -9999-style sentinel far from every other height) become no-data,
non-square cells are resampled to square ones, and with ``spikes`` (a
:class:`SpikeFilter`) isolated outliers become no-data. ``z_positive="down"`` reads
depths (positive down) as heights for every format.

BAG (Bathymetric Attributed Grid, HDF5): ``BAG_root/elevation`` (no-data 1e6), row 0 is the
**south** row; georeferenced from the SW corner point of the ISO metadata
(``BAG_root/metadata``, ``gmd:cornerPoints``; the corner is a cell centre) and the
``gmd:resolution`` of the row/column dimensions, never from the NE corner (one cell off in
some producers' files); the CRS is the horizontal ``gmd:referenceSystemInfo`` code (WKT or
EPSG).
"""

from __future__ import annotations

import logging
import math
import re
import warnings
import xml.etree.ElementTree as ET
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from sss2bathy.survey import BathyGrid, SurveyFormatError

log = logging.getLogger(__name__)

__all__ = [
    "CRS_MISMATCH",
    "MESH_SUFFIXES",
    "RASTER_SUFFIXES",
    "STATISTICS",
    "XYZ_SUFFIXES",
    "SpikeFilter",
    "Z_POSITIVE",
    "crs_equivalent",
    "grid_points",
    "read_bag",
    "read_grid",
    "read_mesh",
    "read_raster",
    "read_xyz",
    "shift_grid",
    "spike_mask",
]

RASTER_SUFFIXES = (".tif", ".tiff", ".gtiff", ".asc")
BAG_SUFFIXES = (".bag",)
XYZ_SUFFIXES = (".xyz", ".txt", ".csv", ".pts")
MESH_SUFFIXES = (".ply", ".obj", ".stl", ".off", ".glb", ".gltf")
BAG_NODATA = 1.0e6
CRS_MISMATCH = ("reproject", "error")
Z_POSITIVE = ("up", "down")  # heights (negative below the datum) or depths
STATISTICS = ("mean", "median")  # height per cell of gridded points
#: GDAL drivers a raster suffix must be read with (a PNG renamed ``.tif`` is not a grid)
RASTER_DRIVERS = {
    ".tif": ("GTiff", "COG"),
    ".tiff": ("GTiff", "COG"),
    ".gtiff": ("GTiff", "COG"),
    ".asc": ("AAIGrid",),
}
#: no seabed is this far from any datum (the deepest ocean is ~10.9 km): such values are
#: untagged no-data (3.4e38 float maxima, 1e6 fills)
HEIGHT_LIMIT_M = 11_000.0
#: common no-data values, taken as such when untagged and far from every other height
SENTINELS = (-9999.0, -99999.0, -32767.0, -32768.0, 9999.0, 99999.0)
SENTINEL_GAP_M = 1_000.0
_MAGIC = (
    (b"\x89PNG\r\n\x1a\n", "a PNG image"),
    (b"\xff\xd8\xff", "a JPEG image"),
    (b"GIF8", "a GIF image"),
    (b"BM", "a BMP image"),
    (b"\x89HDF\r\n\x1a\n", "an HDF5 file"),
    (b"II*\x00", "a TIFF"),
    (b"MM\x00*", "a TIFF"),
    (b"II+\x00", "a BigTIFF"),
    (b"MM\x00+", "a BigTIFF"),
    (b"PK\x03\x04", "a ZIP archive"),
    (b"%PDF", "a PDF document"),
    (b"\x1f\x8b", "a gzip file"),
    (b"CDF", "a netCDF file"),
)


@dataclass(frozen=True)
class SpikeFilter:
    """Spikes: valid cells more than ``threshold_m`` from the median of their
    ``window_cells`` x ``window_cells`` neighbourhood and, with ``spread_factor``, also more
    than ``threshold_m`` and ``spread_factor`` robust standard deviations (1.4826 x the
    median absolute deviation) from the local plane through the neighbourhood's other cells
    (their spread about it): a spike on a steep slope is found, the crests of steep or rough
    terrain are kept. ``key`` names the threshold's setting in the warning."""

    threshold_m: float
    window_cells: int = 5
    spread_factor: float | None = None
    key: str = "spike_threshold_m"

    def __post_init__(self) -> None:
        if not self.threshold_m > 0:
            raise ValueError(f"{self.key}: expected > 0 (m), found {self.threshold_m}")
        w = self.window_cells
        if not isinstance(w, (int, np.integer)) or w < 3 or w % 2 == 0:
            raise ValueError(f"window_cells: expected an odd integer >= 3, found {w!r}")
        if self.spread_factor is not None and not self.spread_factor > 0:
            raise ValueError(f"spread_factor: expected > 0 or None, found {self.spread_factor}")


def _one_line(exc: BaseException) -> str:
    return " ".join(str(exc).split()) or type(exc).__name__


def _sniff(path: Path) -> str:
    """What a file holds, in words, from its size and first bytes."""
    try:
        size = path.stat().st_size
        with open(path, "rb") as f:
            head = f.read(64)
    except OSError as exc:
        return f"an unreadable file ({_one_line(exc)})"
    if size == 0:
        return "an empty file (0 bytes)"
    for magic, what in _MAGIC:
        if head.startswith(magic):
            return f"{what} of {size} bytes"
    try:
        text = head.decode("ascii")
        if text.isprintable() or all(c.isprintable() or c in "\r\n\t" for c in text):
            return f"text of {size} bytes starting {text[:24]!r}"
    except UnicodeDecodeError:
        pass
    return f"{size} bytes starting {head[:8].hex(' ')}"


# ----------------------------------------------------------------------------- CRS helpers
def _crs(value: Any):
    from pyproj import CRS

    return CRS.from_user_input(value)


def _crs_string(value: Any) -> str | None:
    if value is None:
        return None
    c = _crs(value)
    epsg = c.to_epsg(min_confidence=90)
    return f"EPSG:{epsg}" if epsg else c.to_wkt()


def _crs_name(value: Any) -> str:
    return "none" if value is None else f"'{_crs(value).name}'"


def crs_equivalent(a: Any, b: Any, x: float, y: float, tol_m: float = 1e-3) -> bool:
    """True when CRSs ``a`` and ``b`` agree: equal, or the point ``(x, y)`` of ``a`` moves
    less than ``tol_m`` when transformed to ``b`` (e.g. an EPSG code and its WKT with a null
    ``TOWGS84``)."""
    ca, cb = _crs(a), _crs(b)
    if ca == cb:
        return True
    if ca.is_geographic != cb.is_geographic:
        return False
    from pyproj import Transformer

    tx, ty = Transformer.from_crs(ca, cb, always_xy=True).transform(x, y)
    if ca.is_geographic:
        return abs(tx - x) * 111_000 < tol_m and abs(ty - y) * 111_000 < tol_m
    return bool(math.hypot(tx - x, ty - y) < tol_m)


def shift_grid(grid: BathyGrid, origin: Mapping[str, Any]) -> BathyGrid:
    """The grid in the survey's local frame: ``x - easting, y - northing``, CRS = origin's."""
    return BathyGrid(
        grid.heights,
        grid.x0 - float(origin.get("easting", 0.0)),
        grid.y0 - float(origin.get("northing", 0.0)),
        grid.cell_size,
        origin.get("crs", grid.crs),
    )


# ----------------------------------------------------------------------------- rasters
def _north_up_to_grid(
    data: np.ndarray, transform, crs: Any, path: Any, cell_size: float | None
) -> BathyGrid:
    """North-up raster + affine (square, unrotated) -> BathyGrid (row 0 south)."""
    if transform.b != 0 or transform.d != 0:
        raise SurveyFormatError(
            path,
            "transform",
            "an unrotated grid (or a CRS, in the file or target_crs, to resample it in)",
            f"a rotated geotransform (a, b, c, d, e, f) = {tuple(round(v, 6) for v in transform[:6])}",
        )
    ny = data.shape[0]
    cell = abs(transform.a)
    if transform.e < 0:
        heights = data[::-1]
        y0 = transform.f + transform.e * (ny - 0.5)
    else:
        heights = data
        y0 = transform.f + transform.e * 0.5
    if transform.a < 0:
        heights = heights[:, ::-1]
        x0 = transform.c + transform.a * (data.shape[1] - 0.5)
    else:
        x0 = transform.c + transform.a * 0.5
    return BathyGrid(np.ascontiguousarray(heights), x0, y0, cell, _crs_string(crs))


def _warp(
    data: np.ndarray,
    transform,
    src_crs: Any,
    dst_crs: Any,
    cell_size: float | None,
) -> tuple[np.ndarray, Any]:
    """Reproject / resample a float raster (NaN no-data; rotated too) to a north-up one of
    square ``cell_size`` cells."""
    from rasterio.warp import Resampling, calculate_default_transform, reproject

    h, w = data.shape
    xs, ys = zip(*(transform @ corner for corner in ((0, 0), (w, 0), (0, h), (w, h))), strict=True)
    west, east, south, north = min(xs), max(xs), min(ys), max(ys)
    # keep the source cell size unless told otherwise
    res = cell_size or math.hypot(transform.a, transform.d)
    dst_transform, dw, dh = calculate_default_transform(
        src_crs, dst_crs, w, h, west, south, east, north, resolution=res
    )
    out = np.full((dh, dw), np.nan, dtype=np.float32)
    reproject(
        source=data.astype(np.float32),
        destination=out,
        src_transform=transform,
        src_crs=src_crs,
        src_nodata=np.nan,
        dst_transform=dst_transform,
        dst_crs=dst_crs,
        dst_nodata=np.nan,
        resampling=Resampling.bilinear,
    )
    return out, dst_transform


def _finish_raster(
    data: np.ndarray,
    transform,
    crs: Any,
    path: Path,
    cell_size: float | None,
    target_crs: Any,
    on_crs_mismatch: str,
    info: dict | None = None,
) -> BathyGrid:
    """Common tail of raster readers: CRS check, reprojection/resampling, grid."""
    from rasterio.transform import array_bounds

    h, w = data.shape
    cx, cy = transform.c + transform.a * w / 2, transform.f + transform.e * h / 2
    if info is not None:
        x_a, y_a, x_b, y_b = array_bounds(h, w, transform)
        info["file_crs"] = _crs_string(crs) if crs is not None else None
        info["file_bounds"] = [min(x_a, x_b), min(y_a, y_b), max(x_a, x_b), max(y_a, y_b)]
    dst = crs
    if target_crs is not None:
        if crs is None:
            log.warning("%s: no CRS in the file; assuming the survey's %s", path, target_crs)
            crs = target_crs
        elif not crs_equivalent(crs, target_crs, cx, cy):
            if on_crs_mismatch == "error":
                raise SurveyFormatError(
                    path,
                    "crs",
                    f"the survey's CRS {_crs_name(target_crs)} (or on_crs_mismatch: reproject)",
                    _crs_name(crs),
                )
            log.info("%s: reprojecting from %s to %s", path, _crs_name(crs), _crs_name(target_crs))
        else:
            crs = target_crs
        dst = target_crs
    if dst is not None and _crs(dst).is_geographic:
        raise SurveyFormatError(
            path, "crs", "a projected CRS in metres (give target_crs)", _crs_name(dst)
        )
    size_x, size_y = math.hypot(transform.a, transform.d), math.hypot(transform.b, transform.e)
    square = math.isclose(size_x, size_y, rel_tol=1e-6)
    rotated = transform.b != 0 or transform.d != 0
    if not square:
        cell_size = cell_size or min(size_x, size_y)
        if crs is not None:
            log.warning(
                "%s: cells of %g m (x) by %g m (y) are not square; resampled bilinearly to "
                "square %g m cells (%d x %d cells -> about %d x %d)",
                path,
                size_x,
                size_y,
                cell_size,
                h,
                w,
                round(h * size_y / cell_size),
                round(w * size_x / cell_size),
            )
    if rotated and crs is not None:
        log.warning(
            "%s: the grid is rotated by %.2f degrees; resampled bilinearly to a north-up grid "
            "(%d x %d cells)",
            path,
            math.degrees(math.atan2(transform.d, transform.a)),
            h,
            w,
        )
    same_cell = cell_size is None or math.isclose(abs(transform.a), cell_size, rel_tol=1e-9)
    if (
        crs is not None
        and dst is not None
        and (not crs_equivalent(crs, dst, cx, cy) or not square or not same_cell or rotated)
    ):
        data, transform = _warp(data, transform, crs, dst, cell_size)
    elif not (square and same_cell) and not rotated:
        if crs is None:
            raise SurveyFormatError(
                path,
                "transform",
                "square cells (or a CRS to resample them in)",
                f"cells of {size_x:g} m by {size_y:g} m (wanted {cell_size:g} m square) and no CRS",
            )
        data, transform = _warp(data, transform, crs, crs, cell_size)
    return _north_up_to_grid(data, transform, dst, path, cell_size)


def _untagged_nodata(z: np.ndarray, path: Path, info: dict | None, what: str = "cells") -> None:
    """Set untagged no-data values of ``z`` to NaN in place (a WARNING with their count):
    infinities, values beyond +-:data:`HEIGHT_LIMIT_M`, and :data:`SENTINELS` lying more
    than :data:`SENTINEL_GAP_M` from every other height."""
    finite = np.isfinite(z)
    bad = np.isinf(z)
    with np.errstate(invalid="ignore"):
        bad |= finite & (np.abs(z) >= HEIGHT_LIMIT_M)
    rest = finite & ~bad
    for value in SENTINELS:
        hit = rest & (z == value)
        if not hit.any():
            continue
        others = z[rest & ~hit]
        if others.size == 0 or np.abs(others - value).min() > SENTINEL_GAP_M:
            bad |= hit
            rest &= ~hit
    n = int(bad.sum())
    if info is not None:
        info["untagged_nodata"] = n
    if n:
        values, counts = np.unique(z[bad], return_counts=True)
        order = np.argsort(-counts, kind="stable")[:3]
        shown = ", ".join(f"{values[i]:g} ({counts[i]})" for i in order)
        shown += ", ..." if values.size > 3 else ""
        log.warning(
            "%s: %d %s (%.1f %% of those with values) hold %s, not tagged as no-data: "
            "treated as no-data",
            path,
            n,
            what,
            100.0 * n / max(int(finite.sum() + np.isinf(z).sum()), 1),
            shown,
        )
        z[bad] = np.nan


def _window_median(h: np.ndarray, window_cells: int) -> np.ndarray:
    """Median of each cell's ``window_cells`` square of valid cells (NaN: none valid)."""
    half = window_cells // 2
    padded = np.pad(h, half, constant_values=np.nan)
    windows = np.lib.stride_tricks.sliding_window_view(padded, (window_cells, window_cells))
    median = np.full(h.shape, np.nan)
    rows = max(1, 2_000_000 // (h.shape[1] * window_cells**2))  # bounded memory per chunk
    for r0 in range(0, h.shape[0], rows):
        block = windows[r0 : r0 + rows].reshape(-1, h.shape[1], window_cells**2)
        with np.errstate(invalid="ignore"), warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)  # all-NaN windows: NaN median
            median[r0 : r0 + rows] = np.nanmedian(block, axis=-1)
    return median


def _plane_residuals(
    h: np.ndarray, iy: np.ndarray, ix: np.ndarray, window_cells: int
) -> tuple[np.ndarray, np.ndarray]:
    """For the cells ``(iy, ix)``: ``(residual, mad)``, the cell's height above the plane
    through the other valid cells of its window (least squares, refitted once without the
    cells beyond 3 robust standard deviations: other spikes), taken from the median of
    their residuals, and the median absolute deviation of those residuals. Windows with
    fewer than 6 other valid cells use a flat plane at their median."""
    w, half, k = window_cells, window_cells // 2, window_cells * window_cells
    padded = np.pad(h, half, constant_values=np.nan)
    win = np.lib.stride_tricks.sliding_window_view(padded, (w, w))[iy, ix].reshape(iy.size, k)
    win = win.astype(np.float64)  # a copy: the centre is taken out below
    centre = win[:, k // 2].copy()
    win[:, k // 2] = np.nan
    dy, dx = np.mgrid[-half : half + 1, -half : half + 1]
    design = np.stack([np.ones(k), dx.ravel(), dy.ravel()], axis=1)  # (k, 3)
    valid = np.isfinite(win).astype(np.float64)
    weights = valid
    z0 = np.where(valid > 0, win, 0.0)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # all-NaN rows: NaN statistics
        for refit in (False, True):
            ata = np.einsum("nk,ki,kj->nij", weights, design, design)
            atz = np.einsum("nk,ki,nk->ni", weights, design, z0)
            coef = np.zeros((iy.size, 3))
            coef[:, 0] = np.nanmedian(np.where(weights > 0, win, np.nan), axis=1)
            ok = (weights.sum(1) >= 6) & (np.abs(np.linalg.det(ata)) > 1e-9)
            if ok.any():
                coef[ok] = np.linalg.solve(ata[ok], atz[ok][..., None])[..., 0]
            res = np.where(valid > 0, win - coef @ design.T, np.nan)
            med = np.nanmedian(res, axis=1)
            mad = np.nanmedian(np.abs(res - med[:, None]), axis=1)
            if not refit:
                weights = valid * (np.abs(res - med[:, None]) <= 3 * 1.4826 * mad[:, None] + 1e-6)
    return centre - coef[:, 0] - med, mad


def _spikes(
    h: np.ndarray, threshold_m: float, window_cells: int, spread_factor: float | None
) -> tuple[np.ndarray, np.ndarray]:
    """``(mask, deviation)``: the spike cells and every cell's distance to its window median."""
    median = _window_median(h, window_cells)
    with np.errstate(invalid="ignore"):
        deviation = np.abs(h - median)
        mask = np.isfinite(h) & (deviation > threshold_m)
    if spread_factor is not None and mask.any():
        iy, ix = np.nonzero(mask)  # only the candidates: few cells
        residual, mad = _plane_residuals(h, iy, ix, window_cells)
        with np.errstate(invalid="ignore"):
            spike = (np.abs(residual) > threshold_m) & (
                np.abs(residual) > spread_factor * 1.4826 * mad
            )
        mask[iy[~spike], ix[~spike]] = False
    return mask, deviation


def spike_mask(
    heights: np.ndarray,
    threshold_m: float,
    window_cells: int = 5,
    spread_factor: float | None = None,
) -> np.ndarray:
    """``(ny, nx)`` bool: valid cells more than ``threshold_m`` from the median of their
    ``window_cells`` x ``window_cells`` neighbourhood (valid cells only; the grid's edge
    and no-data do not count). Real grids carry such outliers (fliers, injected spikes).
    With ``spread_factor`` a cell must also lie that many robust standard deviations
    (1.4826 x MAD) from its neighbourhood's local plane (see :class:`SpikeFilter`).

    >>> h = np.zeros((7, 7)); h[3, 3] = 5.0
    >>> np.argwhere(spike_mask(h, 1.0)).tolist()
    [[3, 3]]
    """
    h = np.asarray(heights, dtype=np.float64)
    if h.ndim != 2:
        raise ValueError(f"heights: expected a (ny, nx) grid, found shape {h.shape}")
    if not threshold_m > 0:
        raise ValueError(f"threshold_m: expected > 0, found {threshold_m}")
    if window_cells < 3 or window_cells % 2 == 0:
        raise ValueError(f"window_cells: expected an odd integer >= 3, found {window_cells}")
    return _spikes(h, threshold_m, window_cells, spread_factor)[0]


def _despike(h: np.ndarray, path: Path, spikes: SpikeFilter | None, info: dict | None) -> None:
    """Set the spikes of grid ``h`` to NaN in place, with a WARNING (count, largest)."""
    if spikes is None:
        return
    mask, deviation = _spikes(
        np.asarray(h, dtype=np.float64),
        spikes.threshold_m,
        spikes.window_cells,
        spikes.spread_factor,
    )
    n = int(mask.sum())
    largest = float(deviation[mask].max()) if n else 0.0
    if info is not None:
        info["spikes_removed"] = n
        info["spike_max_deviation_m"] = largest
    if not n:
        return
    valid = int(np.isfinite(h).sum())
    share = 100.0 * n / max(valid, 1)
    rule = f"more than {spikes.threshold_m:g} m from the median of their {spikes.window_cells}"
    rule += f"x{spikes.window_cells} cells"
    if spikes.spread_factor is not None:
        rule += f" and {spikes.spread_factor:g} robust SDs from their local plane"
    log.warning(
        "%s: %d spike cells (%.2f %% of %d valid) set to no-data: %s; largest deviation "
        "%.2f m, median %.2f m (%s: null keeps them)%s",
        path,
        n,
        share,
        valid,
        rule,
        largest,
        float(np.median(deviation[mask])),
        spikes.key,
        "; that many suggests rough or steep terrain rather than spikes: raise the threshold"
        if share > 1.0
        else "",
    )
    h[mask] = np.nan


def _prepare_heights(
    z: np.ndarray,
    path: Path,
    z_positive: str,
    spikes: SpikeFilter | None,
    info: dict | None,
) -> np.ndarray:
    """A grid's heights at its own resolution: untagged no-data, sign, spikes."""
    _untagged_nodata(z, path, info)
    if z_positive == "down":
        z = -z
    _despike(z, path, spikes, info)
    return z


def read_raster(
    path: str | Path,
    cell_size: float | None = None,
    target_crs: Any = None,
    *,
    band: int = 1,
    on_crs_mismatch: str = "reproject",
    z_positive: str = "up",
    spikes: SpikeFilter | None = None,
    info: dict | None = None,
) -> BathyGrid:
    """A GeoTIFF or ESRI ASCII grid band as a grid (heights, m; ``z_positive="down"``:
    depths). The file must be of its suffix's format (:data:`RASTER_DRIVERS`),
    georeferenced and readable to the end; untagged no-data and ``spikes`` are repaired at
    the file's resolution (WARNINGs), before any reprojection. ``info`` (a dict) receives
    the file's CRS and bounds and the repairs' counts."""
    import rasterio
    from rasterio.enums import ColorInterp
    from rasterio.errors import NotGeoreferencedWarning

    path = Path(path)
    drivers = RASTER_DRIVERS.get(path.suffix.lower(), ())
    what = "an ESRI ASCII grid" if drivers == ("AAIGrid",) else "a GeoTIFF"
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", NotGeoreferencedWarning)
            src_ctx = rasterio.open(path)
    except Exception as exc:  # rasterio raises its own error types
        raise SurveyFormatError(
            path, "file", f"{what} (a readable raster)", f"{_sniff(path)}: {_one_line(exc)}"
        ) from exc
    with src_ctx as src:
        if drivers and src.driver not in drivers:
            raise SurveyFormatError(
                path,
                "file",
                f"{what} (GDAL driver {drivers[0]})",
                f"{_sniff(path)}, read by GDAL's {src.driver} driver",
            )
        if src.transform.is_identity and src.crs is None and not src.gcps[0]:
            raise SurveyFormatError(
                path,
                "georeferencing",
                "a georeferenced grid (a geotransform: origin and cell size)",
                f"none: a {src.width} x {src.height} {src.dtypes[0]} image",
            )
        if not 1 <= band <= src.count:
            raise SurveyFormatError(path, "band", f"a band in 1..{src.count}", band)
        colours = {ColorInterp.red, ColorInterp.green, ColorInterp.blue, ColorInterp.palette}
        if colours & set(src.colorinterp):
            raise SurveyFormatError(
                path,
                "bands",
                "a grid of heights (one value band)",
                f"a colour image ({src.count} bands {', '.join(c.name for c in src.colorinterp)})",
            )
        try:
            data = src.read(band).astype(np.float32)
        except Exception as exc:  # rasterio.errors.RasterioIOError on a damaged file
            cause = exc.__cause__ or exc.__context__ or exc
            raise SurveyFormatError(
                path,
                f"band {band}",
                f"all {src.width} x {src.height} cells readable",
                f"a read error in {_sniff(path)} (truncated or corrupt?): {_one_line(cause)}",
            ) from exc
        if src.nodata is not None and np.isfinite(src.nodata):
            data[data == np.float32(src.nodata)] = np.nan
        transform = src.transform
        crs = src.crs.to_wkt() if src.crs else None
    data = _prepare_heights(data, path, z_positive, spikes, info)
    return _finish_raster(data, transform, crs, path, cell_size, target_crs, on_crs_mismatch, info)


# ----------------------------------------------------------------------------- BAG
def _local(tag: str) -> str:
    return tag.rsplit("}", 1)[-1]


def _iter_local(root: ET.Element, name: str):
    return (el for el in root.iter() if _local(el.tag) == name)


def _text_of(root: ET.Element, name: str) -> str | None:
    for el in _iter_local(root, name):
        text = "".join(el.itertext()).strip()
        if text:
            return text
    return None


def _bag_metadata(path: Path, xml_bytes: bytes) -> tuple[float, float, float, float, Any]:
    """``(sw_x, sw_y, res_x, res_y, crs)`` from the BAG ISO 19115/19139 metadata."""
    try:
        root = ET.fromstring(xml_bytes.rstrip(b"\x00"))
    except ET.ParseError as exc:
        raise SurveyFormatError(path, "BAG_root/metadata", "ISO XML metadata", exc) from exc
    res: dict[str, float] = {}
    for dim in _iter_local(root, "MD_Dimension"):
        name = _text_of(dim, "MD_DimensionNameTypeCode")
        value = _text_of(dim, "Measure")
        if name and value:
            res[name.lower()] = float(value)
    if "row" not in res or "column" not in res:
        raise SurveyFormatError(
            path, "metadata resolution", "row and column gmd:resolution", sorted(res)
        )
    corners = None
    for cp in _iter_local(root, "cornerPoints"):
        text = _text_of(cp, "coordinates")
        if text:
            corners = [tuple(float(v) for v in pair.split(",")) for pair in text.split()]
        else:
            pos = [el.text for el in _iter_local(cp, "pos") if el.text]
            corners = [tuple(float(v) for v in p.split()) for p in pos]
        break
    if not corners or len(corners[0]) < 2:
        raise SurveyFormatError(path, "metadata cornerPoints", "a SW corner point", corners)
    crs = None
    for rs in _iter_local(root, "referenceSystemInfo"):
        code = _text_of(rs, "code")
        space = (_text_of(rs, "codeSpace") or "").upper()
        if not code:
            continue
        candidate = f"EPSG:{code}" if space == "EPSG" and code.isdigit() else code
        try:
            c = _crs(candidate)
        except Exception:  # pyproj.exceptions.CRSError and friends: not a CRS string
            continue
        if not c.is_vertical:
            op = c.coordinate_operation if c.is_bound else None
            if op is not None and not any(p.value for p in op.params):
                c = c.source_crs  # a null TOWGS84 adds nothing
            crs = _crs_string(c)
            break
    return corners[0][0], corners[0][1], res["column"], res["row"], crs


def read_bag(
    path: str | Path,
    cell_size: float | None = None,
    target_crs: Any = None,
    *,
    on_crs_mismatch: str = "reproject",
    z_positive: str = "up",
    spikes: SpikeFilter | None = None,
    info: dict | None = None,
) -> BathyGrid:
    """A BAG's elevation layer as a grid (see the module docstring for the conventions;
    ``z_positive``, ``spikes`` and ``info`` as in :func:`read_raster`)."""
    import h5py
    from rasterio.transform import from_origin

    path = Path(path)
    try:
        with h5py.File(path, "r") as f:
            if "BAG_root/elevation" not in f or "BAG_root/metadata" not in f:
                raise SurveyFormatError(
                    path, "BAG_root", "elevation and metadata datasets", sorted(f.keys())
                )
            elev = np.asarray(f["BAG_root/elevation"][()], dtype=np.float32)
            xml = np.asarray(f["BAG_root/metadata"][()]).tobytes()
    except SurveyFormatError:
        raise
    except Exception as exc:  # h5py: OSError, KeyError, RuntimeError on damaged files
        raise SurveyFormatError(
            path, "file", "a readable BAG (HDF5)", f"{_sniff(path)}: {_one_line(exc)}"
        ) from exc
    if elev.ndim != 2 or min(elev.shape) < 1:
        raise SurveyFormatError(path, "BAG_root/elevation", "a 2D array", elev.shape)
    try:
        sw_x, sw_y, res_x, res_y, crs = _bag_metadata(path, xml)
    except SurveyFormatError:
        raise
    except (ValueError, IndexError) as exc:
        raise SurveyFormatError(
            path,
            "BAG_root/metadata",
            "ISO XML with numeric corner points and resolution",
            _one_line(exc),
        ) from exc
    if not (res_x > 0 and res_y > 0):
        raise SurveyFormatError(
            path, "metadata resolution", "positive row and column sizes", (res_y, res_x)
        )
    elev[~np.isfinite(elev) | (np.abs(elev) >= 0.5 * BAG_NODATA)] = np.nan
    ny, nx = elev.shape
    north_up = _prepare_heights(elev[::-1].copy(), path, z_positive, spikes, info)  # row 0 south
    transform = from_origin(sw_x - res_x / 2, sw_y + (ny - 0.5) * res_y, res_x, res_y)
    return _finish_raster(
        north_up, transform, crs, path, cell_size, target_crs, on_crs_mismatch, info
    )


# ----------------------------------------------------------------------------- points
def grid_points(
    xyz: np.ndarray, cell_size: float, statistic: str = "mean", crs: Any = None
) -> BathyGrid:
    """Grid ``(N, 3)`` points: cells centred on multiples of ``cell_size``; each cell holds the
    mean (or median) height of its points, NaN where it has none."""
    xyz = np.asarray(xyz, dtype=np.float64)
    if xyz.ndim != 2 or xyz.shape[1] < 3 or xyz.shape[0] < 1:
        raise ValueError(f"xyz: expected an (N, 3) array of points, found shape {xyz.shape}")
    if not (cell_size and cell_size > 0):
        raise ValueError(f"cell_size: expected a positive cell size (m), found {cell_size}")
    if statistic not in STATISTICS:
        raise ValueError(f"statistic: expected 'mean' or 'median', found {statistic!r}")
    xyz = xyz[np.all(np.isfinite(xyz[:, :3]), axis=1)]
    if xyz.shape[0] == 0:
        raise ValueError("xyz: expected finite points, found none")
    ix = np.round(xyz[:, 0] / cell_size).astype(np.int64)
    iy = np.round(xyz[:, 1] / cell_size).astype(np.int64)
    ix0, iy0 = ix.min(), iy.min()
    nx, ny = max(int(ix.max() - ix0) + 1, 2), max(int(iy.max() - iy0) + 1, 2)
    flat = (iy - iy0) * nx + (ix - ix0)
    if statistic == "mean":
        total = np.bincount(flat, weights=xyz[:, 2], minlength=nx * ny)
        count = np.bincount(flat, minlength=nx * ny)
        heights = np.where(count > 0, total / np.maximum(count, 1), np.nan)
    else:
        order = np.lexsort((xyz[:, 2], flat))
        f_sorted, z_sorted = flat[order], xyz[order, 2]
        starts = np.flatnonzero(np.r_[True, np.diff(f_sorted) != 0])
        counts = np.diff(np.r_[starts, f_sorted.size])
        lo = z_sorted[starts + (counts - 1) // 2]
        hi = z_sorted[starts + counts // 2]
        heights = np.full(nx * ny, np.nan)
        heights[f_sorted[starts]] = 0.5 * (lo + hi)
    return BathyGrid(
        heights.reshape(ny, nx), ix0 * cell_size, iy0 * cell_size, cell_size, _crs_string(crs)
    )


def _transform_xy(xy: np.ndarray, src: Any, dst: Any) -> np.ndarray:
    from pyproj import Transformer

    tx, ty = Transformer.from_crs(_crs(src), _crs(dst), always_xy=True).transform(
        xy[:, 0], xy[:, 1]
    )
    return np.stack([np.asarray(tx), np.asarray(ty)], axis=1)


def _points_crs(
    path: Path, xy: np.ndarray, source_crs: Any, target_crs: Any, on_crs_mismatch: str
) -> tuple[np.ndarray, Any]:
    """Move point coordinates into the target CRS (or refuse); returns (xy, crs)."""
    if target_crs is None:
        crs = source_crs
    elif source_crs is None:
        log.warning("%s: no CRS given for the file; assuming the survey's %s", path, target_crs)
        crs = target_crs
    else:
        cx, cy = np.median(xy[:, 0]), np.median(xy[:, 1])
        if not crs_equivalent(source_crs, target_crs, cx, cy):
            if on_crs_mismatch == "error":
                raise SurveyFormatError(
                    path,
                    "crs",
                    f"the survey's CRS {_crs_name(target_crs)} (or on_crs_mismatch: reproject)",
                    _crs_name(source_crs),
                )
            xy = _transform_xy(xy, source_crs, target_crs)
        crs = target_crs
    if crs is not None and _crs(crs).is_geographic:
        raise SurveyFormatError(
            path, "crs", "a projected CRS in metres (give target_crs)", _crs_name(crs)
        )
    return xy, crs


def _numeric_header_lines(path: Path, delimiter: str | None, limit: int = 50) -> int:
    with open(path, errors="replace") as f:
        for i, text in enumerate(f):
            if i >= limit:
                break
            tokens = [t for t in re.split(delimiter or r"\s+", text.strip()) if t]
            if not tokens or text.lstrip().startswith("#"):
                continue
            try:
                [float(t) for t in tokens[:3]]
                return i
            except ValueError:
                continue
    return 0


def read_xyz(
    path: str | Path,
    cell_size: float | None,
    target_crs: Any = None,
    *,
    source_crs: Any = None,
    z_positive: str = "up",
    statistic: str = "mean",
    on_crs_mismatch: str = "reproject",
    spikes: SpikeFilter | None = None,
    info: dict | None = None,
) -> BathyGrid:
    """An ASCII point file (``x y z`` per line; whitespace, comma or semicolon separated; header
    lines and ``#`` comments skipped) gridded to ``cell_size``.

    ``z_positive="down"`` reads depths (positive down) as heights ``-z``. Untagged no-data
    points are dropped and ``spikes`` removed from the gridded cells (WARNINGs).
    """
    path = Path(path)
    if cell_size is None:
        raise ValueError(f"cell_size: expected a cell size (m) to grid the points of {path}")
    if z_positive not in Z_POSITIVE:
        raise ValueError(f"z_positive: expected 'up' or 'down', found {z_positive!r}")
    with open(path, errors="replace") as f:
        sample = "".join(f.readline() for _ in range(50))
    delimiter = ";" if ";" in sample else ("," if "," in sample else None)
    skip = _numeric_header_lines(path, delimiter)
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", UserWarning)  # "input contained no data"
            pts = np.loadtxt(
                path, delimiter=delimiter, comments="#", skiprows=skip, usecols=(0, 1, 2), ndmin=2
            )
    except (ValueError, IndexError) as exc:
        raise SurveyFormatError(
            path, "file", "numeric 'x y z' rows", f"{_sniff(path)}: {_one_line(exc)}"
        ) from exc
    _untagged_nodata(pts[:, 2], path, info, what="points")
    pts = pts[np.all(np.isfinite(pts), axis=1)]
    if pts.shape[0] == 0:
        raise SurveyFormatError(path, "file", "numeric 'x y z' rows", f"none in {_sniff(path)}")
    if z_positive == "down":
        pts[:, 2] = -pts[:, 2]
    if info is not None:
        info["file_crs"] = _crs_string(source_crs) if source_crs is not None else None
        info["file_bounds"] = [*pts[:, :2].min(0).tolist(), *pts[:, :2].max(0).tolist()]
    xy, crs = _points_crs(path, pts[:, :2], source_crs, target_crs, on_crs_mismatch)
    grid = grid_points(np.column_stack([xy, pts[:, 2]]), cell_size, statistic, crs)
    _despike(grid.heights, path, spikes, info)
    return grid


# ----------------------------------------------------------------------------- meshes
def read_mesh(
    path: str | Path,
    cell_size: float | None = None,
    target_crs: Any = None,
    *,
    source_crs: Any = None,
    z_positive: str = "up",
    on_crs_mismatch: str = "reproject",
    spikes: SpikeFilter | None = None,
    info: dict | None = None,
) -> BathyGrid:
    """A triangle mesh (PLY/OBJ/STL/...) sampled on a grid by casting rays straight down at
    the cell centres (the highest surface hit); NaN where a ray misses; ``spikes`` removed
    from the sampled cells.

    ``cell_size`` defaults to the median edge length. Rays are cast in coordinates centred on
    the mesh (float32 ray tracers lose millimetres at UTM magnitudes).
    """
    import trimesh

    path = Path(path)
    if z_positive not in Z_POSITIVE:
        raise ValueError(f"z_positive: expected 'up' or 'down', found {z_positive!r}")
    try:
        mesh = trimesh.load(path, force="mesh", process=False)
    except Exception as exc:  # trimesh raises many types for unreadable files
        raise SurveyFormatError(
            path, "file", "a readable triangle mesh", f"{_sniff(path)}: {_one_line(exc)}"
        ) from exc
    if len(getattr(mesh, "faces", ())) == 0:
        raise SurveyFormatError(path, "faces", "a mesh with triangles", f"none in {_sniff(path)}")
    verts = np.asarray(mesh.vertices, dtype=np.float64).copy()
    if not np.isfinite(verts).all():
        raise SurveyFormatError(
            path,
            "vertices",
            "finite coordinates",
            f"{int((~np.isfinite(verts)).any(1).sum())} vertices with NaN or infinite coordinates",
        )
    if z_positive == "down":
        verts[:, 2] = -verts[:, 2]
    if info is not None:
        info["file_crs"] = _crs_string(source_crs) if source_crs is not None else None
        info["file_bounds"] = [*verts[:, :2].min(0).tolist(), *verts[:, :2].max(0).tolist()]
    verts[:, :2], crs = _points_crs(path, verts[:, :2], source_crs, target_crs, on_crs_mismatch)
    if cell_size is None:
        edges = np.linalg.norm(
            verts[mesh.edges_unique[:, 0], :2] - verts[mesh.edges_unique[:, 1], :2], axis=1
        )
        cell_size = float(np.median(edges[edges > 0]))
    if not cell_size > 0:
        raise ValueError(f"cell_size: expected a positive cell size (m), found {cell_size}")
    centre = np.r_[0.5 * (verts[:, :2].min(0) + verts[:, :2].max(0)), 0.0]
    local = trimesh.Trimesh(vertices=verts - centre, faces=mesh.faces, process=False)
    lo, hi = verts[:, :2].min(0), verts[:, :2].max(0)
    ix0, iy0 = np.ceil(lo / cell_size).astype(np.int64)
    ix1, iy1 = np.floor(hi / cell_size).astype(np.int64)
    nx, ny = int(ix1 - ix0) + 1, int(iy1 - iy0) + 1
    if nx < 2 or ny < 2:
        raise SurveyFormatError(path, "extent", f"at least 2x2 cells of {cell_size} m", (ny, nx))
    gx = (ix0 + np.arange(nx)) * cell_size
    gy = (iy0 + np.arange(ny)) * cell_size
    xx, yy = np.meshgrid(gx - centre[0], gy - centre[1])
    top = verts[:, 2].max() - centre[2] + 1.0
    origins = np.stack([xx.ravel(), yy.ravel(), np.full(xx.size, top)], axis=1)
    dirs = np.tile([0.0, 0.0, -1.0], (origins.shape[0], 1))
    locs, ray_idx, _ = local.ray.intersects_location(origins, dirs, multiple_hits=True)
    heights = np.full(origins.shape[0], -np.inf)
    np.maximum.at(heights, ray_idx, locs[:, 2])
    heights = np.where(np.isfinite(heights), heights + centre[2], np.nan).reshape(ny, nx)
    _despike(heights, path, spikes, info)
    return BathyGrid(heights, ix0 * cell_size, iy0 * cell_size, cell_size, _crs_string(crs))


# ----------------------------------------------------------------------------- dispatch
def read_grid(
    path: str | Path,
    cell_size: float | None = None,
    target_crs: Any = None,
    *,
    origin: Mapping[str, Any] | None = None,
    source_crs: Any = None,
    on_crs_mismatch: str = "reproject",
    band: int = 1,
    z_positive: str = "up",
    statistic: str = "mean",
    spikes: SpikeFilter | None = None,
    info: dict | None = None,
) -> BathyGrid:
    """Read a bathymetry grid or mesh, dispatching on the file suffix.

    Args:
        path: ``.tif/.tiff/.asc`` (raster), ``.bag``, ``.xyz/.txt/.csv/.pts`` (points),
            ``.ply/.obj/.stl/.off/.glb`` (mesh).
        cell_size: output cell size (m); rasters are resampled when it differs from theirs;
            required for points; meshes default to their median edge length.
        target_crs: CRS of the output; default the origin's CRS, else the file's.
        origin: survey origin ``{"crs", "easting", "northing"}``: the grid is checked against
            (and brought into) its CRS, then shifted into the survey's local frame.
        source_crs: CRS of point/mesh coordinates (files without a CRS of their own).
        on_crs_mismatch: ``"reproject"`` or ``"error"`` (refuse a grid in another CRS).
        band: raster band (GeoTIFF).
        z_positive: ``"up"`` heights or ``"down"`` depths (every format).
        statistic: ``"mean"`` or ``"median"`` height per cell (points).
        spikes: remove isolated outliers (:class:`SpikeFilter`; rasters and BAGs at their
            own resolution, before any reprojection); None: keep every cell.
        info: a dict that receives what the file held and what was repaired:
            ``file_crs`` (the file's own CRS, before reprojection), ``file_bounds``
            (west, south, east, north in that CRS), ``untagged_nodata``,
            ``spikes_removed``, ``spike_max_deviation_m``.

    Returns:
        :class:`BathyGrid`; in the survey's local frame when ``origin`` is given.
    """
    path = Path(path)
    if on_crs_mismatch not in CRS_MISMATCH:
        raise ValueError(
            f"on_crs_mismatch: expected one of {CRS_MISMATCH}, found {on_crs_mismatch!r}"
        )
    if cell_size is not None and not cell_size > 0:
        raise ValueError(f"cell_size: expected None or a positive size (m), found {cell_size}")
    if z_positive not in Z_POSITIVE:
        raise ValueError(f"z_positive: expected 'up' or 'down', found {z_positive!r}")
    if origin is not None:
        ocrs = origin.get("crs")
        if target_crs is not None and ocrs is not None:
            if not crs_equivalent(
                target_crs, ocrs, origin.get("easting", 0.0), origin.get("northing", 0.0)
            ):
                raise ValueError(
                    f"target_crs: expected the survey origin's CRS {_crs_name(ocrs)}, "
                    f"found {_crs_name(target_crs)}"
                )
        target_crs = ocrs if ocrs is not None else target_crs
    if not path.is_file():
        raise SurveyFormatError(path, "file", "an existing grid or mesh file", "missing file")
    suffix = path.suffix.lower()
    common = {"z_positive": z_positive, "spikes": spikes, "info": info}
    if suffix in RASTER_SUFFIXES:
        grid = read_raster(
            path, cell_size, target_crs, band=band, on_crs_mismatch=on_crs_mismatch, **common
        )
    elif suffix in BAG_SUFFIXES:
        grid = read_bag(path, cell_size, target_crs, on_crs_mismatch=on_crs_mismatch, **common)
    elif suffix in XYZ_SUFFIXES:
        grid = read_xyz(
            path,
            cell_size,
            target_crs,
            source_crs=source_crs,
            statistic=statistic,
            on_crs_mismatch=on_crs_mismatch,
            **common,
        )
    elif suffix in MESH_SUFFIXES:
        grid = read_mesh(
            path,
            cell_size,
            target_crs,
            source_crs=source_crs,
            on_crs_mismatch=on_crs_mismatch,
            **common,
        )
    else:
        raise SurveyFormatError(
            path,
            "suffix",
            f"one of {RASTER_SUFFIXES + BAG_SUFFIXES + XYZ_SUFFIXES + MESH_SUFFIXES}",
            suffix,
        )
    if not np.isfinite(grid.heights).any():
        raise SurveyFormatError(
            path,
            "heights",
            "at least one valid cell",
            f"all {grid.heights.size} cells no-data ({grid.shape[0]} x {grid.shape[1]})",
        )
    if origin is not None:
        grid = shift_grid(grid, origin)
    return grid


def footprint_coverage(grid: BathyGrid, lines: list) -> dict[str, float]:
    """Where the lines' swaths fall on ``grid``: ``inside`` — fraction of footprint points
    (each ping's nadir and its port/starboard swath at the farthest horizontal range, sampled
    every range step) within the grid's extent; ``holes`` — fraction of those inside points
    on NaN cells; ``grid_nan`` — fraction of the grid's cells that are NaN."""
    pts = []
    for ln in lines:
        xy = ln.position[:, :2]
        right = ln.rotation[:, :2, 1]  # vehicle +y (left, FLU) in world
        norm = np.linalg.norm(right, axis=1, keepdims=True)
        right = right / np.where(norm > 0, norm, 1.0)
        r = np.asarray(ln.range_m, dtype=np.float64)
        alt = np.where(np.isfinite(ln.altitude_m), ln.altitude_m, 0.0)[:, None]
        ground = np.sqrt(np.maximum(r[None, :] ** 2 - alt**2, 0.0))  # (P, B)
        step = max(1, r.size // 16)
        g = ground[:, ::step]
        for sign in (1.0, -1.0):
            pts.append((xy[:, None, :] + sign * g[..., None] * right[:, None, :]).reshape(-1, 2))
        pts.append(xy)
    xy = np.concatenate(pts)
    west, south, east, north = _bounds(grid)
    inside = (xy[:, 0] >= west) & (xy[:, 0] <= east) & (xy[:, 1] >= south) & (xy[:, 1] <= north)
    holes = 0.0
    if inside.any():
        holes = float((~np.isfinite(grid.sample(xy[inside, 0], xy[inside, 1]))).mean())
    return {
        "inside": float(inside.mean()),
        "holes": holes,
        "grid_nan": float((~np.isfinite(grid.heights)).mean()),
    }


def _bounds(grid: BathyGrid) -> tuple[float, float, float, float]:
    ny, nx = grid.shape
    h = grid.cell_size / 2
    return (
        grid.x0 - h,
        grid.y0 - h,
        grid.x0 + (nx - 1) * grid.cell_size + h,
        grid.y0 + (ny - 1) * grid.cell_size + h,
    )
