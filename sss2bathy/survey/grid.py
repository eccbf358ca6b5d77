"""Regular bathymetry grid in the survey's local ENU frame."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from sss2bathy.survey.errors import SurveyFormatError

GEOTIFF_TILE = 256
"""Tile edge (px) of tiled GeoTIFFs, and the smallest overview kept."""


def overview_factors(ny: int, nx: int, smallest: int = GEOTIFF_TILE) -> list[int]:
    """Overview decimation factors 2, 4, 8, ... while ``max(ny, nx) / factor >= smallest``."""
    factors, f = [], 2
    while max(ny, nx) / f >= smallest:
        factors.append(f)
        f *= 2
    return factors


@dataclass
class BathyGrid:
    """Heights on a regular grid.

    Attributes:
        heights: ``(ny, nx)`` float heights z (m, negative below the datum); NaN = no data.
            Row 0 is the **south** row (y increases with the row index).
        x0, y0: world coordinates (m) of the centre of cell ``[0, 0]`` (the SW cell).
        cell_size: cell edge (m), the same along x and y.
        crs: optional CRS (WKT or ``EPSG:nnnn``) of the projected frame the local ENU
            frame is shifted from (see ``Survey.origin``).
    """

    heights: np.ndarray
    x0: float
    y0: float
    cell_size: float
    crs: str | None = None

    def __post_init__(self) -> None:
        self.heights = np.asarray(self.heights, dtype=np.float32)
        if self.heights.ndim != 2 or min(self.heights.shape) < 2:
            raise SurveyFormatError(
                "grid", "heights", "a 2D array of at least 2x2", self.heights.shape
            )
        if not (np.isfinite(self.cell_size) and self.cell_size > 0):
            raise SurveyFormatError("grid", "cell_size", "a positive number", self.cell_size)
        if not (np.isfinite(self.x0) and np.isfinite(self.y0)):
            raise SurveyFormatError("grid", "x0/y0", "finite numbers", (self.x0, self.y0))
        self.x0, self.y0, self.cell_size = float(self.x0), float(self.y0), float(self.cell_size)

    @property
    def shape(self) -> tuple[int, int]:
        return self.heights.shape  # type: ignore[return-value]

    @property
    def x(self) -> np.ndarray:
        """``(nx,)`` cell-centre x coordinates."""
        return self.x0 + self.cell_size * np.arange(self.shape[1])

    @property
    def y(self) -> np.ndarray:
        """``(ny,)`` cell-centre y coordinates (south to north)."""
        return self.y0 + self.cell_size * np.arange(self.shape[0])

    @property
    def bounds(self) -> tuple[float, float, float, float]:
        """``(xmin, ymin, xmax, ymax)`` of the cell centres."""
        ny, nx = self.shape
        return (
            self.x0,
            self.y0,
            self.x0 + (nx - 1) * self.cell_size,
            self.y0 + (ny - 1) * self.cell_size,
        )

    def sample(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        """Bilinear heights at world ``(x, y)``; NaN outside the grid or next to no-data."""
        x, y = np.asarray(x, dtype=np.float64), np.asarray(y, dtype=np.float64)
        fx = (x - self.x0) / self.cell_size
        fy = (y - self.y0) / self.cell_size
        ny, nx = self.shape
        inside = (fx >= 0) & (fx <= nx - 1) & (fy >= 0) & (fy <= ny - 1)
        ix = np.clip(np.floor(fx).astype(np.int64), 0, nx - 2)
        iy = np.clip(np.floor(fy).astype(np.int64), 0, ny - 2)
        tx, ty = fx - ix, fy - iy
        h = self.heights
        z = (
            h[iy, ix] * (1 - tx) * (1 - ty)
            + h[iy, ix + 1] * tx * (1 - ty)
            + h[iy + 1, ix] * (1 - tx) * ty
            + h[iy + 1, ix + 1] * tx * ty
        )
        return np.where(inside, z, np.nan)

    def gradient(self) -> tuple[np.ndarray, np.ndarray]:
        """``(dz/dx, dz/dy)`` per cell by central differences (one-sided at the edges)."""
        dzdy, dzdx = np.gradient(self.heights.astype(np.float64), self.cell_size)
        return dzdx, dzdy

    def sample_gradient(self, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Bilinearly interpolated ``(dz/dx, dz/dy)`` at world ``(x, y)``."""
        gx, gy = self.gradient()
        return (
            BathyGrid(gx, self.x0, self.y0, self.cell_size).sample(x, y),
            BathyGrid(gy, self.x0, self.y0, self.cell_size).sample(x, y),
        )

    def to_mesh(self):  # -> trimesh.Trimesh
        """Triangulated surface of the valid cells (two triangles per fully valid quad)."""
        import trimesh

        ny, nx = self.shape
        xx, yy = np.meshgrid(self.x, self.y)
        verts = np.stack([xx, yy, self.heights], axis=-1).reshape(-1, 3)
        idx = np.arange(ny * nx).reshape(ny, nx)
        a, b = idx[:-1, :-1].ravel(), idx[:-1, 1:].ravel()
        c, d = idx[1:, :-1].ravel(), idx[1:, 1:].ravel()
        valid = np.isfinite(self.heights)
        quad_ok = (valid[:-1, :-1] & valid[:-1, 1:] & valid[1:, :-1] & valid[1:, 1:]).ravel()
        faces = np.concatenate(
            [np.stack([a, b, d], 1)[quad_ok], np.stack([a, d, c], 1)[quad_ok]], axis=0
        )
        verts = np.where(np.isfinite(verts), verts, 0.0)
        return trimesh.Trimesh(vertices=verts, faces=faces, process=False)

    # ------------------------------------------------------------------ GeoTIFF
    def save_geotiff(self, path: str | Path, tags: dict[str, str] | None = None) -> None:
        """Write the grid **in its own coordinates** as a north-up float32 GeoTIFF, atomically.

        NaN is the no-data value (the nodata tag is set). Maps larger than
        :data:`GEOTIFF_TILE` px are tiled, with internal overviews (averages) at factors
        2, 4, 8, ... while the overview stays at least :data:`GEOTIFF_TILE` px, so GIS tools
        open them fast. ``tags`` are written as GeoTIFF metadata. To place a local-frame grid
        on the map use :func:`sss2bathy.survey.georef.write_geotiff` (it shifts by the survey
        origin and labels the CRS).
        """
        import rasterio
        from affine import Affine
        from rasterio.enums import Resampling

        from sss2bathy.utils.atomic import atomic_path

        ny, nx = self.shape
        west = self.x0 - self.cell_size / 2
        north = self.y0 + (ny - 0.5) * self.cell_size
        transform = Affine(self.cell_size, 0.0, west, 0.0, -self.cell_size, north)
        profile: dict = {"compress": "deflate", "predictor": 3}
        factors = overview_factors(ny, nx)
        if max(ny, nx) > GEOTIFF_TILE:
            profile.update(tiled=True, blockxsize=GEOTIFF_TILE, blockysize=GEOTIFF_TILE)
        with atomic_path(path) as tmp:
            with rasterio.open(
                tmp,
                "w",
                driver="GTiff",
                height=ny,
                width=nx,
                count=1,
                dtype="float32",
                crs=self.crs,
                transform=transform,
                nodata=np.nan,
                **profile,
            ) as dst:
                dst.write(self.heights[::-1].astype(np.float32), 1)
                if tags:
                    dst.update_tags(**{k: str(v) for k, v in tags.items()})
                if factors:
                    dst.build_overviews(factors, Resampling.average)
                    dst.update_tags(ns="rio_overview", resampling="average")

    @classmethod
    def load_geotiff(cls, path: str | Path, band: int = 1) -> BathyGrid:
        """Read a north-up GeoTIFF into a grid (row 0 south). Square, unrotated pixels only."""
        import rasterio

        path = Path(path)
        if not path.is_file():
            raise SurveyFormatError(path, "file", "an existing GeoTIFF", "missing file")
        try:
            src_ctx = rasterio.open(path)
        except Exception as exc:  # rasterio raises its own error types
            raise SurveyFormatError(path, "file", "a readable GeoTIFF", exc) from exc
        with src_ctx as src:
            t = src.transform
            if t.b != 0 or t.d != 0:
                raise SurveyFormatError(path, "transform", "an unrotated grid", t)
            if not np.isclose(abs(t.a), abs(t.e), rtol=1e-6):
                raise SurveyFormatError(path, "transform", "square pixels", (t.a, t.e))
            data = src.read(band).astype(np.float32)
            if src.nodata is not None and np.isfinite(src.nodata):
                data[data == src.nodata] = np.nan
            cell = abs(t.a)
            if t.e < 0:  # north-up: flip so row 0 is south
                data = data[::-1]
                y0 = t.f + t.e * (src.height - 0.5)
            else:
                y0 = t.f + t.e * 0.5
            x0 = t.c + t.a * 0.5
            crs = src.crs.to_string() if src.crs else None
        return cls(np.ascontiguousarray(data), x0, y0, cell, crs)
