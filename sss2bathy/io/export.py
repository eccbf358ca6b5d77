"""Maps out: reconstructed bathymetry as GeoTIFF (in the survey's CRS) and as a PLY mesh.

:func:`write_geotiff` is the one georeferencing path of every raster the project writes (run
maps, simulator truth): the local ENU grid is shifted by the survey origin to true projected
coordinates and labelled with the survey's CRS (:func:`sss2bathy.survey.georef.write_geotiff`,
which a survey's own ``grid.tif`` takes directly), and the file carries its provenance as
GDAL metadata (:func:`provenance_tags`: units, vertical reference, software version, the
command line, and for a run's map its method and CNN checkpoint's SHA-256); the band's unit
is ``m``. :func:`read_geotiff` brings such files back into the local frame. :func:`write_ply`
writes a mesh.
"""

from __future__ import annotations

import shlex
import sys
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np

import sss2bathy
from sss2bathy.survey import BathyGrid
from sss2bathy.survey.georef import FRAME_TAG, read_geotiff, to_local, to_projected
from sss2bathy.survey.georef import write_geotiff as _georef_write_geotiff
from sss2bathy.utils.atomic import atomic_path, file_sha256

__all__ = [
    "FRAME_TAG",
    "add_geotiff_tags",
    "VERTICAL_REFERENCE",
    "provenance_tags",
    "read_geotiff",
    "to_local",
    "to_projected",
    "write_geotiff",
    "write_ply",
]

#: what the heights of a map are, by survey kind (docs/architecture.md, Conventions: z up,
#: seafloor heights negative; an XTF import sets the vehicle's z = -SensorDepth)
VERTICAL_REFERENCE = {
    "xtf": (
        "height of the seafloor (m, up, negative below) relative to the sea surface through "
        "the vehicle depth: the vehicle at z = -SensorDepth of the XTF pings, the altimeter's "
        "seabed at that z minus the altitude; no tide or datum correction"
    ),
    None: "height of the seafloor (m, up, negative below the survey's vertical datum z = 0)",
}

#: GDAL metadata keys of :func:`provenance_tags`
TAG_PREFIX = "SSS2BATHY_"


def provenance_tags(
    method: str | None = None,
    cnn_checkpoint: str | Path | None = None,
    survey_kind: str | None = None,
    vertical_reference: str | None = None,
    command: list[str] | None = None,
) -> dict[str, str]:
    """GDAL metadata tags that say what a GeoTIFF holds and how it was made.

    ``SSS2BATHY_UNITS`` (``m``), ``SSS2BATHY_VERTICAL_REFERENCE`` (``vertical_reference``,
    else :data:`VERTICAL_REFERENCE` of ``survey_kind``), ``SSS2BATHY_VERSION``
    (``sss2bathy.__version__``), ``SSS2BATHY_COMMAND`` (``command``, default
    ``sys.argv``, shell-quoted) and ``TIFFTAG_SOFTWARE``; with ``method``
    ``SSS2BATHY_METHOD``; with ``cnn_checkpoint`` ``SSS2BATHY_CNN_CHECKPOINT`` (its path) and
    ``SSS2BATHY_CNN_CHECKPOINT_SHA256`` (of the file's bytes).
    """
    reference = vertical_reference or VERTICAL_REFERENCE.get(survey_kind, VERTICAL_REFERENCE[None])
    argv = list(sys.argv if command is None else command)
    tags = {
        f"{TAG_PREFIX}UNITS": "m",
        f"{TAG_PREFIX}VERTICAL_REFERENCE": reference,
        f"{TAG_PREFIX}VERSION": str(sss2bathy.__version__),
        f"{TAG_PREFIX}COMMAND": shlex.join(str(a) for a in argv),
        "TIFFTAG_SOFTWARE": f"sss2bathy {sss2bathy.__version__}",
    }
    if method:
        tags[f"{TAG_PREFIX}METHOD"] = str(method)
    if cnn_checkpoint:
        path = Path(cnn_checkpoint)
        tags[f"{TAG_PREFIX}CNN_CHECKPOINT"] = str(path)
        tags[f"{TAG_PREFIX}CNN_CHECKPOINT_SHA256"] = file_sha256(path, length=64)
    return tags


def write_geotiff(
    grid: BathyGrid,
    path: str | Path,
    crs: str | None = None,
    origin: Mapping[str, Any] | None = None,
    mask: np.ndarray | None = None,
    tags: Mapping[str, Any] | None = None,
) -> Path:
    """:func:`sss2bathy.survey.georef.write_geotiff` (a north-up float32 GeoTIFF in
    projected coordinates, written atomically) with provenance: the band's unit ``m`` and
    description, and the GDAL metadata of :func:`provenance_tags` (defaults), updated by
    ``tags`` (e.g. ``provenance_tags(method=..., cnn_checkpoint=...)`` of a run's map).

    The provenance is added in place once the raster is written (GDAL rewrites the TIFF
    directory only), so the georeferencing's messages name ``path`` itself.
    """
    path = _georef_write_geotiff(grid, path, crs=crs, origin=origin, mask=mask)
    return add_geotiff_tags(path, {**provenance_tags(), **(tags or {})})


def add_geotiff_tags(path: str | Path, tags: Mapping[str, Any]) -> Path:
    """Set ``tags`` (GDAL metadata, values as strings) on an existing GeoTIFF, in place, and
    its band's unit (``m``) and description; e.g. a run's map, once its provenance is
    known (:func:`provenance_tags`)."""
    import rasterio

    with rasterio.open(path, "r+") as dst:
        dst.update_tags(**{str(k): str(v) for k, v in tags.items()})
        dst.set_band_unit(1, "m")
        dst.set_band_description(1, "height (m, up)")
    return Path(path)


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
