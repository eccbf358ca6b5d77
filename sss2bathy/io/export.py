"""Maps out: reconstructed bathymetry as GeoTIFF (in the survey's CRS) and as a PLY mesh."""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np

from sss2bathy.survey import BathyGrid
from sss2bathy.utils.atomic import atomic_path

__all__ = ["to_projected", "write_geotiff", "write_ply"]


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


def write_geotiff(
    grid: BathyGrid,
    path: str | Path,
    crs: str | None = None,
    origin: Mapping[str, Any] | None = None,
) -> Path:
    """Write a north-up float32 GeoTIFF (NaN no-data), atomically.

    With ``origin`` the local grid is shifted back to the survey's projected CRS, so GIS tools
    place it on the map; ``crs`` labels a grid that is already projected.
    """
    out = to_projected(grid, origin, crs)
    path = Path(path)
    out.save_geotiff(path)
    return path


def write_ply(grid: BathyGrid, path: str | Path, origin: Mapping[str, Any] | None = None) -> Path:
    """Write the valid cells of a grid as a binary PLY triangle mesh (float64 vertices).

    Vertices are the cell centres (two triangles per fully valid quad, as
    :meth:`BathyGrid.to_mesh`); unreferenced vertices (no-data cells) are dropped. With
    ``origin`` the vertices are in projected coordinates (float64 keeps millimetres there),
    otherwise in the local frame. The CRS and origin are written as PLY comments.
    """
    mesh = grid.to_mesh()
    faces = np.asarray(mesh.faces, dtype=np.int64)
    used = np.unique(faces)
    remap = np.full(len(mesh.vertices), -1, dtype=np.int64)
    remap[used] = np.arange(used.size)
    verts = np.asarray(mesh.vertices, dtype=np.float64)[used]
    faces = remap[faces]
    comments = ["sss2bathy bathymetry: z up (m), negative below the datum"]
    if origin is not None:
        out = to_projected(grid, origin)
        verts[:, 0] += out.x0 - grid.x0
        verts[:, 1] += out.y0 - grid.y0
        comments.append(f"crs {out.crs}")
    else:
        comments.append(f"local frame; crs {grid.crs}" if grid.crs else "local frame (no CRS)")
    header = (
        "ply\nformat binary_little_endian 1.0\n"
        + "".join(f"comment {' '.join(c.split())}\n" for c in comments)
        + f"element vertex {len(verts)}\n"
        + "property double x\nproperty double y\nproperty double z\n"
        + f"element face {len(faces)}\n"
        + "property list uchar int vertex_indices\nend_header\n"
    )
    face_rec = np.zeros(len(faces), dtype=[("n", "u1"), ("v", "<i4", (3,))])
    face_rec["n"] = 3
    face_rec["v"] = faces
    path = Path(path)
    with atomic_path(path) as tmp, open(tmp, "wb") as f:
        f.write(header.encode("ascii"))
        f.write(verts.astype("<f8").tobytes())
        f.write(face_rec.tobytes())
    return path
