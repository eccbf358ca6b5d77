"""A STAC Item (``item.json``) that describes a map run's rasters, through ``pystac``.

:func:`map_item` builds it from the run's GeoTIFFs: the geometry is the convex hull of the
map's valid cells (:func:`valid_footprint`, corners of every cell with data) in WGS84 and
the bbox that hull's; ``datetime`` / ``start_datetime`` / ``end_datetime`` are the first and
last ping; the projection extension gives the map grid's EPSG code, shape and transform
(item level) and each raster asset's own (a mosaic has its own grid); the raster extension
gives each raster band's data type, no-data and unit; assets carry roles and media types
(COG, JSON, PNG). The **processing** record (the `processing` STAC extension's fields:
``processing:software`` and ``processing:lineage``) names the software and version and the
command line; ``sss2bathy:method`` and, for a CNN's normals,
``sss2bathy:cnn_checkpoint_sha256`` say how the map was made. Asset paths are relative to
``item.json`` (the run folder travels as a whole).

:func:`check_item` is a structural check of the fields STAC 1.x and the extensions
require, for where ``pystac.Item.validate`` cannot run (it needs ``jsonschema`` and the
schemas from the network).
"""

from __future__ import annotations

import datetime as dt
import json
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

import sss2bathy
from sss2bathy.utils.atomic import atomic_write_text

PROCESSING_SCHEMA = "https://stac-extensions.github.io/processing/v1.2.0/schema.json"
#: a COG's media type (``pystac.MediaType.COG``)
COG_TYPE = "image/tiff; application=geotiff; profile=cloud-optimized"


@dataclass(frozen=True)
class AssetSpec:
    """One file of the run: its path, title, roles and (optional) description."""

    path: Path
    title: str
    roles: tuple[str, ...]
    description: str | None = None
    extra: Mapping[str, Any] = field(default_factory=dict)


def valid_footprint(path: str | Path, max_points: int = 200_000) -> list[tuple[float, float]]:
    """The convex hull (closed ring, counter-clockwise, in the raster's CRS) of the corners
    of the cells of a GeoTIFF that hold data (not no-data / NaN); the raster's extent when
    none does. ``max_points`` caps the corners handed to the hull (a regular subsample)."""
    import rasterio
    from scipy.spatial import ConvexHull

    with rasterio.open(path) as src:
        band = src.read(1, masked=True)
        t = src.transform
        valid = ~np.ma.getmaskarray(band)
        if np.issubdtype(band.dtype, np.floating):
            valid &= np.isfinite(np.ma.getdata(band))
        width, height = src.width, src.height
    rows, cols = np.nonzero(valid)
    if rows.size == 0:
        corners = np.array([[0, 0], [width, 0], [width, height], [0, height]], np.float64)
    else:
        step = max(1, int(math.ceil(4 * rows.size / max_points)))
        r, c = rows[::step], cols[::step]
        corners = np.concatenate(
            [np.stack([c + dc, r + dr], 1) for dc in (0, 1) for dr in (0, 1)]
        ).astype(np.float64)
    col, row = corners[:, 0], corners[:, 1]
    pts = np.stack([t.a * col + t.b * row + t.c, t.d * col + t.e * row + t.f], 1)
    hull = ConvexHull(pts)
    ring = [(float(x), float(y)) for x, y in pts[hull.vertices]]  # counter-clockwise
    return [*ring, ring[0]]


def _densify(ring: Sequence[tuple[float, float]], step: float) -> list[tuple[float, float]]:
    """``ring`` with points added every ``step`` (its units) along each edge."""
    out: list[tuple[float, float]] = []
    for (x0, y0), (x1, y1) in zip(ring[:-1], ring[1:], strict=True):
        n = max(1, int(math.ceil(math.hypot(x1 - x0, y1 - y0) / step)))
        out += [(x0 + (x1 - x0) * i / n, y0 + (y1 - y0) * i / n) for i in range(n)]
    return [*out, out[0]]


def to_wgs84(ring: Sequence[tuple[float, float]], crs: str) -> list[tuple[float, float]]:
    """A ring in ``crs`` as (longitude, latitude) in WGS84, densified every 100 m first."""
    from pyproj import Transformer

    dense = _densify(ring, 100.0)
    tf = Transformer.from_crs(crs, "EPSG:4326", always_xy=True)
    lon, lat = tf.transform([p[0] for p in dense], [p[1] for p in dense])
    return [(round(float(a), 9), round(float(b), 9)) for a, b in zip(lon, lat, strict=True)]


def raster_info(path: str | Path) -> dict[str, Any]:
    """EPSG code, shape, transform and band (data type, no-data, unit) of a GeoTIFF."""
    import rasterio

    with rasterio.open(path) as src:
        epsg = src.crs.to_epsg() if src.crs is not None else None
        nodata = src.nodata
        return {
            "epsg": epsg,
            "crs": src.crs.to_string() if src.crs is not None else None,
            "shape": [int(src.height), int(src.width)],
            "transform": [float(v) for v in list(src.transform)[:6]],
            "dtype": str(src.dtypes[0]),
            "nodata": "nan" if nodata is not None and math.isnan(nodata) else nodata,
            "unit": (src.units or (None,))[0] or None,
            "description": (src.descriptions or (None,))[0],
        }


def _utc(seconds: float) -> dt.datetime:
    return dt.datetime.fromtimestamp(float(seconds), tz=dt.UTC)


def map_item(
    item_id: str,
    map_tif: str | Path,
    start_s: float,
    end_s: float,
    assets: Mapping[str, AssetSpec],
    item_dir: str | Path,
    method: str | None = None,
    command: Sequence[str] | None = None,
    cnn_checkpoint_sha256: str | None = None,
    properties: Mapping[str, Any] | None = None,
) -> Any:
    """The ``pystac.Item`` of a map run (module docstring).

    Args:
        item_id: the item's id (e.g. the survey and run folder names).
        map_tif: the map GeoTIFF: geometry (its valid cells), bbox and item projection.
        start_s, end_s: first and last ping (UNIX seconds, UTC).
        assets: key -> :class:`AssetSpec`; ``.tif`` assets get their own projection and
            raster-band fields.
        item_dir: the folder ``item.json`` goes to (asset hrefs relative to it).
        method, command, cnn_checkpoint_sha256: the processing record.
        properties: further properties (e.g. ``sss2bathy:*`` numbers).

    Raises:
        ValueError: the map has no CRS, or ``end_s < start_s``.
    """
    import pystac
    from pystac.extensions.projection import ProjectionExtension
    from pystac.extensions.raster import RasterBand, RasterExtension

    info = raster_info(map_tif)
    if info["crs"] is None:
        raise ValueError(
            f"{map_tif}: expected a GeoTIFF with a CRS for a STAC item (survey.crs), found none"
        )
    if not (math.isfinite(start_s) and math.isfinite(end_s) and end_s >= start_s):
        raise ValueError(
            f"start_s, end_s: expected finite ping times with start <= end, found "
            f"{start_s}, {end_s}"
        )
    ring = to_wgs84(valid_footprint(map_tif), info["crs"])
    lons, lats = [p[0] for p in ring], [p[1] for p in ring]
    geometry = {"type": "Polygon", "coordinates": [[list(p) for p in ring]]}
    bbox = [min(lons), min(lats), max(lons), max(lats)]
    start, end = _utc(start_s), _utc(end_s)
    props: dict[str, Any] = {
        "start_datetime": pystac.utils.datetime_to_str(start),
        "end_datetime": pystac.utils.datetime_to_str(end),
        "processing:software": {"sss2bathy": str(sss2bathy.__version__)},
        "processing:level": "L3",
    }
    if command:
        import shlex

        props["processing:lineage"] = shlex.join(str(a) for a in command)
    if method:
        props["sss2bathy:method"] = str(method)
    if cnn_checkpoint_sha256:
        props["sss2bathy:cnn_checkpoint_sha256"] = str(cnn_checkpoint_sha256)
    props.update(properties or {})
    item = pystac.Item(
        id=str(item_id), geometry=geometry, bbox=bbox, datetime=start, properties=props
    )
    item.stac_extensions.append(PROCESSING_SCHEMA)
    proj = ProjectionExtension.ext(item, add_if_missing=True)
    _set_projection(proj, info)
    RasterExtension.add_to(item)
    folder = Path(item_dir)
    for key, spec in assets.items():
        path = Path(spec.path)
        suffix = path.suffix.lower()
        media = {
            ".tif": COG_TYPE,
            ".tiff": COG_TYPE,
            ".json": pystac.MediaType.JSON,
            ".png": pystac.MediaType.PNG,
            ".html": pystac.MediaType.HTML,
        }.get(suffix)
        asset = pystac.Asset(
            href=_relative(path, folder),
            title=spec.title,
            description=spec.description,
            media_type=media,
            roles=list(spec.roles),
            extra_fields=dict(spec.extra),
        )
        item.add_asset(key, asset)
        if suffix in (".tif", ".tiff") and path.is_file():
            tif = raster_info(path)
            _set_projection(ProjectionExtension.ext(asset), tif)
            band = RasterBand.create(
                nodata=tif["nodata"], data_type=tif["dtype"], unit=tif["unit"] or None
            )
            RasterExtension.ext(asset).bands = [band]
    return item


def _set_projection(proj: Any, info: Mapping[str, Any]) -> None:
    if info["epsg"] is not None:
        proj.epsg = int(info["epsg"])
    else:
        proj.code = None
        proj.wkt2 = _wkt(info["crs"])
    proj.shape = list(info["shape"])
    proj.transform = list(info["transform"])


def _wkt(crs: str) -> str:
    from pyproj import CRS

    return CRS.from_user_input(crs).to_wkt()


def _relative(path: Path, folder: Path) -> str:
    try:
        return "./" + Path(path).resolve().relative_to(folder.resolve()).as_posix()
    except ValueError:
        return Path(path).resolve().as_uri()


def write_item(item: Any, path: str | Path) -> Path:
    """``item`` as JSON at ``path`` (atomically), asset hrefs as they are (relative)."""
    path = Path(path)
    data = item.to_dict(include_self_link=False, transform_hrefs=False)
    atomic_write_text(path, json.dumps(data, indent=2, sort_keys=False) + "\n")
    return path


#: fields every STAC 1.x Item has (core spec)
ITEM_REQUIRED = ("type", "stac_version", "id", "geometry", "bbox", "properties", "links", "assets")


def check_item(data: Mapping[str, Any]) -> list[str]:
    """Problems of an Item's JSON (empty: none) against what STAC 1.x, the projection
    extension and this project's record require: the core fields, ``type == "Feature"``,
    a closed Polygon ring in WGS84 ranges inside the bbox, ``datetime`` (or
    start/end), every extension's schema URI, ``proj:code``/``proj:shape``/
    ``proj:transform``, assets with an href, type and roles, and the processing record."""
    problems = [f"missing field {k!r}" for k in ITEM_REQUIRED if k not in data]
    if problems:
        return problems
    if data["type"] != "Feature":
        problems.append(f"type: expected 'Feature', found {data['type']!r}")
    props = data["properties"]
    if props.get("datetime") is None and not (
        props.get("start_datetime") and props.get("end_datetime")
    ):
        problems.append("properties: expected datetime or start_datetime and end_datetime")
    for key in ("start_datetime", "end_datetime", "datetime"):
        if props.get(key):
            try:
                dt.datetime.fromisoformat(str(props[key]).replace("Z", "+00:00"))
            except ValueError:
                problems.append(
                    f"properties.{key}: expected an RFC 3339 time, found {props[key]!r}"
                )
    geom = data["geometry"]
    bbox = data["bbox"]
    if not (isinstance(bbox, list) and len(bbox) == 4):
        problems.append(f"bbox: expected [west, south, east, north], found {bbox!r}")
        return problems
    if geom.get("type") != "Polygon" or not geom.get("coordinates"):
        problems.append(f"geometry: expected a Polygon, found {geom.get('type')!r}")
    else:
        ring = geom["coordinates"][0]
        if len(ring) < 4 or ring[0] != ring[-1]:
            problems.append("geometry: expected a closed ring of >= 4 positions")
        for lon, lat in ring:
            if not (-180 <= lon <= 180 and -90 <= lat <= 90):
                problems.append(f"geometry: position ({lon}, {lat}) outside WGS84 ranges")
                break
            if not (
                bbox[0] - 1e-9 <= lon <= bbox[2] + 1e-9 and bbox[1] - 1e-9 <= lat <= bbox[3] + 1e-9
            ):
                problems.append(f"geometry: position ({lon}, {lat}) outside the bbox")
                break
    exts = data.get("stac_extensions") or []
    for prefix, name in (
        ("proj:", "projection"),
        ("raster:", "raster"),
        ("processing:", "processing"),
    ):
        used = any(k.startswith(prefix) for k in props) or any(
            any(k.startswith(prefix) for k in a) for a in data["assets"].values()
        )
        if used and not any(f"/{name}/" in e for e in exts):
            problems.append(f"stac_extensions: {prefix}* fields used without the {name} schema")
    for key in ("proj:code", "proj:shape", "proj:transform"):
        if key not in props:
            problems.append(f"properties: expected {key}")
    if "processing:software" not in props:
        problems.append("properties: expected processing:software")
    for name, asset in data["assets"].items():
        for key in ("href", "type", "roles"):
            if not asset.get(key):
                problems.append(f"assets.{name}: expected {key}")
    return problems


__all__ = [
    "COG_TYPE",
    "AssetSpec",
    "check_item",
    "map_item",
    "raster_info",
    "to_wgs84",
    "valid_footprint",
    "write_item",
]
