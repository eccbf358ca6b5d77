"""Maps out: reconstructed bathymetry as GeoTIFF (in the survey's CRS) and as a PLY mesh.

:func:`write_geotiff` (from :mod:`sss2bathy.survey.georef`, re-exported here) is the one
georeferencing path of every raster the project writes (run maps, survey grids, simulator
truth): the local ENU grid is shifted by the survey origin to true projected coordinates and
labelled with the survey's CRS; :func:`read_geotiff` brings such files back into the local
frame. :func:`write_ply` writes a mesh.
"""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np

from sss2bathy.survey import BathyGrid
from sss2bathy.survey.georef import FRAME_TAG, read_geotiff, to_local, to_projected, write_geotiff
from sss2bathy.utils.atomic import atomic_path

__all__ = ["FRAME_TAG", "read_geotiff", "to_local", "to_projected", "write_geotiff", "write_ply"]


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
