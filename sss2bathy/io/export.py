"""Maps out: reconstructed bathymetry as GeoTIFF (in the survey's CRS) and as a PLY mesh.

:func:`write_geotiff` is the one georeferencing path of every raster the project writes (run
maps, simulator truth): the local ENU grid is shifted by the survey origin to true projected
coordinates and labelled with the survey's CRS (:func:`sss2bathy.survey.georef.write_geotiff`,
which a survey's own ``grid.tif`` takes directly), and the file carries its provenance as
GDAL metadata (:func:`provenance_tags`: units, vertical reference, software version, the
command line, and for a run's map its method and CNN checkpoint's SHA-256); the band's unit
is ``m``. :func:`read_geotiff` brings such files back into the local frame. :func:`write_ply`
writes a mesh.

Every GeoTIFF written here is a **cloud-optimised GeoTIFF** (:func:`write_cog`: GDAL's
``COG`` driver, :data:`COG_OPTIONS`: 256 px tiles, DEFLATE with the floating-point
predictor, the image directories before the data, overviews of a raster larger than a tile
first); tags added later (:func:`add_geotiff_tags`) rewrite the file as a COG again, so an
edit never leaves a file whose layout claims more than it holds. :func:`cog_layout` reads
the TIFF structure back (tiles, overviews, directory and data order) to check it.
"""

from __future__ import annotations

import contextlib
import logging
import shlex
import struct
import sys
import uuid
from collections.abc import Iterator, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

import sss2bathy
from sss2bathy.survey import BathyGrid
from sss2bathy.survey.georef import FRAME_TAG, read_geotiff, to_local, to_projected
from sss2bathy.survey.georef import write_geotiff as _georef_write_geotiff
from sss2bathy.survey.grid import GEOTIFF_TILE
from sss2bathy.utils.atomic import atomic_path, file_sha256

__all__ = [
    "COG_OPTIONS",
    "FRAME_TAG",
    "CogLayout",
    "add_geotiff_tags",
    "cog_layout",
    "VERTICAL_REFERENCE",
    "provenance_tags",
    "read_geotiff",
    "to_local",
    "to_projected",
    "write_cog",
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


#: the band labels of a height raster
HEIGHT_UNIT = "m"
HEIGHT_DESCRIPTION = "height (m, up)"

#: creation options of GDAL's COG driver for every raster written here: tiles of
#: :data:`GEOTIFF_TILE` px, DEFLATE with the predictor of the data type (3: floating point),
#: overviews by averaging (those the source already has, else GDAL's own for a raster
#: larger than one tile), BigTIFF only when the file may pass 4 GiB
COG_OPTIONS: dict[str, Any] = {
    "compress": "DEFLATE",
    "predictor": "YES",
    "blocksize": GEOTIFF_TILE,
    "overview_resampling": "AVERAGE",
    "bigtiff": "IF_SAFER",
}


def write_geotiff(
    grid: BathyGrid,
    path: str | Path,
    crs: str | None = None,
    origin: Mapping[str, Any] | None = None,
    mask: np.ndarray | None = None,
    tags: Mapping[str, Any] | None = None,
    unit: str = HEIGHT_UNIT,
    description: str = HEIGHT_DESCRIPTION,
) -> Path:
    """:func:`sss2bathy.survey.georef.write_geotiff` (a north-up float32 GeoTIFF in
    projected coordinates, written atomically) with provenance, as a cloud-optimised
    GeoTIFF: the band's ``unit`` and ``description`` (default: a height in m) and the GDAL
    metadata of :func:`provenance_tags` (defaults), updated by ``tags`` (e.g.
    ``provenance_tags(method=..., cnn_checkpoint=...)`` of a run's map).

    The provenance is added once the raster is written (:func:`add_geotiff_tags`, which
    rewrites it as a COG), so the georeferencing's messages name ``path`` itself.
    """
    path = _georef_write_geotiff(grid, path, crs=crs, origin=origin, mask=mask)
    return add_geotiff_tags(
        path, {**provenance_tags(), **(tags or {})}, unit=unit, description=description
    )


def add_geotiff_tags(
    path: str | Path,
    tags: Mapping[str, Any],
    unit: str = HEIGHT_UNIT,
    description: str = HEIGHT_DESCRIPTION,
) -> Path:
    """Set ``tags`` (GDAL metadata, values as strings) on an existing GeoTIFF and its
    band's ``unit`` and ``description`` (default: a height in m), e.g. a run's map once its
    provenance is known (:func:`provenance_tags`); the file is rewritten as a COG
    (:func:`write_cog`) with everything else it held (data, georeferencing, no-data,
    earlier tags, overviews)."""
    import rasterio
    from rasterio.shutil import copy as rio_copy

    path = Path(path)
    # edit an in-memory copy: editing a COG in place would break its layout
    mem = f"/vsimem/sss2bathy_{uuid.uuid4().hex}.tif"
    with _quiet_layout_notes():
        try:
            rio_copy(path, mem, driver="GTiff", copy_src_overviews=True)
            with rasterio.open(mem, "r+", IGNORE_COG_LAYOUT_BREAK="YES") as dst:
                dst.update_tags(**{str(k): str(v) for k, v in tags.items()})
                dst.set_band_unit(1, unit)
                dst.set_band_description(1, description)
            write_cog(mem, path)
        finally:
            _vsimem_unlink(mem)
    return path


def write_cog(src: str | Path, dst: str | Path | None = None) -> Path:
    """Write the GeoTIFF ``src`` as a cloud-optimised GeoTIFF ``dst`` (default: ``src``
    itself, replaced), atomically, with :data:`COG_OPTIONS`. Data, georeferencing,
    no-data, GDAL metadata, band unit and description and existing overviews are kept."""
    from rasterio.shutil import copy as rio_copy

    out = Path(src if dst is None else dst)
    with atomic_path(out) as tmp:
        rio_copy(str(src), tmp, driver="COG", **COG_OPTIONS)
    return out


class _LayoutNoteFilter(logging.Filter):
    """Drops GDAL's notes that an edit broke a COG layout (the edited copy in memory is
    written out as a new COG right after)."""

    def filter(self, record: logging.LogRecord) -> bool:
        text = record.getMessage()
        return not ("COG layout" in text or "optimizations in its layout" in text)


@contextlib.contextmanager
def _quiet_layout_notes() -> Iterator[None]:
    logger = logging.getLogger("rasterio._env")
    note = _LayoutNoteFilter()
    logger.addFilter(note)
    try:
        yield
    finally:
        logger.removeFilter(note)


def _vsimem_unlink(name: str) -> None:
    from rasterio.shutil import delete

    try:
        delete(name)
    except Exception:  # noqa: BLE001 - nothing was written there
        pass


@dataclass(frozen=True)
class CogLayout:
    """The TIFF structure of a GeoTIFF (:func:`cog_layout`).

    Attributes:
        images: ``(width, height)`` of each image directory in file order (the full
            resolution first, then overviews, masks excluded).
        tile: ``(width, height)`` of the tiles, or None (stripped).
        compression: the TIFF compression code of the full image (1 = none, 8 = DEFLATE).
        ifds_before_data: every image directory lies before the first byte of pixel data.
        overviews_decreasing: each overview smaller than the image before it.
        overview_data_first: each smaller image's pixel data lies before the larger's (the
            full resolution last: a reader of an overview reads the head of the file).
        ghost_layout: GDAL's layout note at the file's head (``LAYOUT=IFDS_BEFORE_DATA``
            and ``KNOWN_INCOMPATIBLE_EDITION=NO`` of a COG the COG driver wrote), or ``""``.
    """

    images: tuple[tuple[int, int], ...]
    tile: tuple[int, int] | None
    compression: int
    ifds_before_data: bool
    overviews_decreasing: bool
    overview_data_first: bool
    ghost_layout: str

    @property
    def overviews(self) -> int:
        return len(self.images) - 1

    def problems(self) -> list[str]:
        """What keeps the file from being a cloud-optimised GeoTIFF (empty: none): tiled,
        compressed, directories before the data, overviews smaller and smaller with the
        smallest's data first, and overviews when the image is larger than a tile."""
        out = []
        if self.tile is None:
            out.append("not tiled (strips)")
        if self.compression == 1:
            out.append("not compressed")
        if not self.ifds_before_data:
            out.append("an image directory after pixel data")
        if not self.overviews_decreasing:
            out.append("overviews not in decreasing size")
        if not self.overview_data_first:
            out.append("pixel data not ordered smallest overview first")
        if self.tile is not None and self.overviews == 0:
            width, height = self.images[0]
            if max(width, height) > 2 * max(self.tile):
                out.append(f"no overviews on a {width} x {height} image")
        if "KNOWN_INCOMPATIBLE_EDITION=YES" in self.ghost_layout:
            out.append("edited after it was written as a COG (GDAL's layout note)")
        return out


# TIFF field types -> struct codes
_TIFF_TYPES = {1: "B", 3: "H", 4: "I", 6: "b", 8: "h", 9: "i", 16: "Q", 17: "q"}


def cog_layout(path: str | Path) -> CogLayout:
    """Read the image directories of a (Big)TIFF file and describe its layout
    (:class:`CogLayout`): what a COG validator checks, without GDAL.

    Raises:
        ValueError: not a TIFF file (names the file and what its head holds).
    """
    data = Path(path).read_bytes()
    order = {b"II": "<", b"MM": ">"}.get(data[:2])
    if order is None:
        raise ValueError(f"{path}: expected a TIFF file (II or MM), found {data[:4]!r}")
    (magic,) = struct.unpack(order + "H", data[2:4])
    if magic == 42:
        (offset,) = struct.unpack(order + "I", data[4:8])
        count_fmt, entry_fmt, next_fmt, inline = "H", "HHII", "I", 4
    elif magic == 43:
        (offset,) = struct.unpack(order + "Q", data[8:16])
        count_fmt, entry_fmt, next_fmt, inline = "Q", "HHQQ", "Q", 8
    else:
        raise ValueError(f"{path}: expected TIFF magic 42 or 43, found {magic}")
    entry_size = struct.calcsize(order + entry_fmt)
    ifds: list[tuple[int, dict[int, tuple[int, ...]]]] = []
    seen: set[int] = set()
    while offset and offset not in seen:
        seen.add(offset)
        (n,) = struct.unpack_from(order + count_fmt, data, offset)
        pos = offset + struct.calcsize(order + count_fmt)
        fields: dict[int, tuple[int, ...]] = {}
        for i in range(n):
            tag, typ, count, value = struct.unpack_from(
                order + entry_fmt, data, pos + i * entry_size
            )
            code = _TIFF_TYPES.get(typ)
            if code is None:
                continue
            size = struct.calcsize(order + code) * count
            at = pos + i * entry_size + struct.calcsize(order + "HH" + entry_fmt[2])
            at = at if size <= inline else value
            fields[tag] = struct.unpack_from(f"{order}{count}{code}", data, at)
        ifds.append((offset, fields))
        (offset,) = struct.unpack_from(order + next_fmt, data, pos + n * entry_size)
    images = [(o, f) for o, f in ifds if not (f.get(254, (0,))[0] & 4)]  # not masks
    spans = []
    for _, f in images:
        offsets = f.get(324, f.get(273, ()))
        used = [o for o, c in zip(offsets, f.get(325, f.get(279, ())), strict=False) if c]
        spans.append((min(used), max(used)) if used else (len(data), len(data)))
    first_data = min((lo for lo, _ in spans), default=len(data))
    sizes = [(f[256][0], f[257][0]) for _, f in images]
    main = images[0][1] if images else {}
    tile = (main[322][0], main[323][0]) if 322 in main and 323 in main else None
    ghost = ""
    start = data.find(b"GDAL_STRUCTURAL_METADATA_SIZE=", 0, 64)
    if start >= 0:
        end = data.find(b"\n", start)
        digits = data[start:end].split(b"=")[1].split()[0]
        ghost = data[end + 1 : end + 1 + int(digits)].decode("ascii", "replace").strip()
    return CogLayout(
        images=tuple(sizes),
        tile=tile,
        compression=int(main.get(259, (1,))[0]),
        ifds_before_data=all(o < first_data for o, _ in ifds),
        overviews_decreasing=all(
            b[0] < a[0] and b[1] < a[1] for a, b in zip(sizes, sizes[1:], strict=False)
        ),
        overview_data_first=all(
            small[1] < big[0] for big, small in zip(spans, spans[1:], strict=False)
        ),
        ghost_layout=ghost,
    )


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
