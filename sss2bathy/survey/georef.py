"""Georeferenced GeoTIFFs of grids: the one path every raster the project writes takes.

The local ENU grid is shifted by the survey origin to true projected coordinates and labelled
with the survey's CRS (:func:`write_geotiff`); a survey without a CRS gets a raster without
one (and a warning), never an invented CRS. The files carry the tags
``SSS2BATHY_FRAME=projected`` and the origin, and :func:`read_geotiff` brings them back into
the local frame. It lives with the survey containers because a survey's ``grid.tif`` is part
of its on-disk format; :mod:`sss2bathy.io.export` re-exports it for maps out.
"""

from __future__ import annotations

import logging
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np

from sss2bathy.survey.errors import SurveyFormatError
from sss2bathy.survey.grid import BathyGrid

__all__ = ["FRAME_TAG", "read_geotiff", "to_local", "to_projected", "write_geotiff"]

log = logging.getLogger(__name__)

FRAME_TAG = "SSS2BATHY_FRAME"
"""GeoTIFF tag naming the frame of the file's coordinates (``projected``)."""


def to_projected(
    grid: BathyGrid, origin: Mapping[str, Any] | None = None, crs: str | None = None
) -> BathyGrid:
    """The grid in projected coordinates: local ENU shifted back by the survey origin.

    Args:
        grid: a grid in the survey's local frame (or already projected when ``origin`` is None).
        origin: ``{"crs", "easting", "northing"}``; its CRS labels the result.
        crs: CRS label when ``origin`` has none (or no origin is given); must agree with the
            origin's CRS when both are given.
    """
    if not isinstance(grid, BathyGrid):
        raise ValueError(f"grid: expected a BathyGrid, found {type(grid).__name__}")
    if origin is None:
        return BathyGrid(grid.heights, grid.x0, grid.y0, grid.cell_size, crs or grid.crs)
    ocrs = origin.get("crs")
    if crs is not None and ocrs is not None:
        from pyproj import CRS

        if CRS.from_user_input(crs) != CRS.from_user_input(ocrs):
            raise ValueError(f"crs: expected the survey origin's CRS {ocrs!r}, found {crs!r}")
    return BathyGrid(
        grid.heights,
        grid.x0 + float(origin.get("easting", 0.0)),
        grid.y0 + float(origin.get("northing", 0.0)),
        grid.cell_size,
        ocrs or crs,
    )


def to_local(grid: BathyGrid, origin: Mapping[str, Any]) -> BathyGrid:
    """Inverse of :func:`to_projected`: a projected grid shifted into the survey's local frame."""
    return BathyGrid(
        grid.heights,
        grid.x0 - float(origin.get("easting", 0.0)),
        grid.y0 - float(origin.get("northing", 0.0)),
        grid.cell_size,
        origin.get("crs"),
    )


def write_geotiff(
    grid: BathyGrid,
    path: str | Path,
    crs: str | None = None,
    origin: Mapping[str, Any] | None = None,
    mask: np.ndarray | None = None,
) -> Path:
    """Write a north-up float32 GeoTIFF (NaN no-data, tiled with overviews when large),
    atomically.

    Args:
        grid: the raster; in the survey's local frame when ``origin`` is given, else already
            in projected coordinates.
        path: output ``.tif``.
        crs: CRS label of an already projected grid; with ``origin`` it must agree with the
            origin's CRS. Default: the grid's own CRS.
        origin: the survey origin ``{"crs", "easting", "northing"}``: the grid is shifted back
            to projected coordinates and labelled with the origin's CRS.
        mask: ``(ny, nx)`` bool, cells to keep; the others are written as no-data (cells no
            measurement constrains).

    A raster without a CRS (the survey has none) is written without one and a WARNING says
    so; its coordinates are still the projected ones the origin gives.
    """
    out = to_projected(grid, origin, crs or grid.crs)
    path = Path(path)
    if mask is not None:
        mask = np.asarray(mask)
        if mask.shape != grid.shape or mask.dtype != np.bool_:
            raise ValueError(
                f"mask: expected a bool array of the grid's shape {grid.shape}, "
                f"found {mask.dtype} {mask.shape}"
            )
        out = BathyGrid(np.where(mask, out.heights, np.nan), out.x0, out.y0, out.cell_size, out.crs)
    referenced = origin is not None or out.crs is not None
    tags = {FRAME_TAG: "projected" if referenced else "unreferenced"}
    if origin is not None:
        tags["SSS2BATHY_ORIGIN_EASTING"] = repr(float(origin.get("easting", 0.0)))
        tags["SSS2BATHY_ORIGIN_NORTHING"] = repr(float(origin.get("northing", 0.0)))
    if out.crs is None:
        tags["SSS2BATHY_CRS"] = "none"
        if origin is not None:
            log.warning(
                "%s: written without a CRS: the survey has none (origin easting %.3f, "
                "northing %.3f, no CRS named); no CRS was invented",
                path,
                float(origin.get("easting", 0.0)),
                float(origin.get("northing", 0.0)),
            )
        else:
            log.warning(
                "%s: written without a CRS and without a survey origin: coordinates as "
                "given (local frame, SW cell centre at %.3f, %.3f)",
                path,
                out.x0,
                out.y0,
            )
    out.save_geotiff(path, tags=tags)
    return path


def read_geotiff(
    path: str | Path, origin: Mapping[str, Any] | None = None, band: int = 1
) -> BathyGrid:
    """Read a GeoTIFF (e.g. one :func:`write_geotiff` wrote); with ``origin``, into the
    survey's local frame.

    With ``origin`` a georeferenced file (tag ``SSS2BATHY_FRAME=projected``, or any GeoTIFF
    without the tag) is shifted back by the origin; when the origin names a CRS the file's
    must be the same, else :class:`SurveyFormatError` names the two (an origin without a CRS
    keeps whatever label the file has). A file
    tagged ``unreferenced`` (written without origin or CRS) is returned as it is. Without
    ``origin`` the grid keeps the file's coordinates.
    """
    import rasterio

    grid = BathyGrid.load_geotiff(path, band=band)
    if origin is None:
        return grid
    with rasterio.open(path) as src:
        frame = src.tags().get(FRAME_TAG, "projected")
    if frame == "unreferenced":
        return grid
    if frame != "projected":
        raise SurveyFormatError(path, FRAME_TAG, "'projected' or 'unreferenced'", frame)
    ocrs = origin.get("crs")
    if ocrs is not None and (grid.crs is None or not _same_crs(grid.crs, ocrs)):
        raise SurveyFormatError(
            path, "crs", f"the survey origin's CRS {ocrs}", grid.crs or "no CRS"
        )
    local = to_local(grid, origin)
    local.crs = ocrs or grid.crs  # an origin without a CRS keeps the file's label
    return local


def _same_crs(a: str, b: str) -> bool:
    from pyproj import CRS

    return CRS.from_user_input(a) == CRS.from_user_input(b)
