"""``sss2bathy-map-blend``: the tile maps of a tiled ``sss2bathy-map`` run -> one map.

sss2bathy-map-blend OUT            # OUT/tile_<k>/map.tif ... -> OUT/map.tif, OUT/map.png
sss2bathy-map-blend OUT --out DIR

Reads every ``OUT/*/tile.json`` (written by a tile job, ``sss2bathy-map tile.index=K``,
:mod:`sss2bathy.cli.map_tiles`), checks that the jobs share one plan and that every tile of
it is there, and blends their ``map.tif`` with the partition-of-unity weights of
:func:`sss2bathy.survey.tiles.blend` (cos^2 / sin^2 across each shared band): ``map.tif``
(a cloud-optimised GeoTIFF on the tiles' common cell lattice, no-data where no tile has
data, the tiles' provenance tags plus ``SSS2BATHY_TILES``), ``map.png`` and, where every
tile has one, ``uncertainty.tif`` + ``.png`` (the same weighted mean of the tiles' 1-sigma
layers) and ``blend.json``.
"""

from __future__ import annotations

import argparse
import json
import logging
import sys
from collections.abc import Sequence
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np

from sss2bathy.cli.map_tiles import TILE_JSON
from sss2bathy.survey.tiles import Tile, blend, tile_from_dict

log = logging.getLogger("sss2bathy.map")


def read_tile_runs(folder: Path) -> tuple[dict[str, Any], dict[int, Path]]:
    """``(plan, {index: run folder})`` of the tile jobs under ``folder`` (its subfolders'
    ``tile.json``); ``ValueError`` (one line) when there are none, the jobs' plans differ,
    two jobs fitted one tile, or tiles of the plan are missing."""
    folder = Path(folder)
    if not folder.is_dir():
        raise ValueError(f"{folder}: expected the folder of a tiled sss2bathy-map run, found none")
    records = sorted(folder.glob(f"*/{TILE_JSON}"))
    if not records:
        raise ValueError(
            f"{folder}: expected tile runs (sub-folders with {TILE_JSON}, written by "
            "sss2bathy-map tile.index=K), found none"
        )
    plan: dict[str, Any] | None = None
    runs: dict[int, Path] = {}
    for path in records:
        record = json.loads(path.read_text())
        key = {k: record[k] for k in ("tiles", "survey", "origin")}
        if plan is None:
            plan, first = {**key, "size_m": record.get("size_m")}, path
        elif key != {k: plan[k] for k in key}:
            raise ValueError(
                f"{path}: expected the plan of {first} (tiles, survey, origin), found another "
                "(tile runs of different tile.size_m / tile.overlap_m or surveys in one folder)"
            )
        index = int(record["index"])
        if index in runs:
            raise ValueError(f"{path}: tile {index} is also fitted in {runs[index]}")
        runs[index] = path.parent
    assert plan is not None
    missing = [k for k in range(len(plan["tiles"])) if k not in runs]
    if missing:
        raise ValueError(
            f"{folder}: expected the {len(plan['tiles'])} tiles of the plan, found tiles "
            f"{', '.join(map(str, missing))} missing (run sss2bathy-map ... "
            f"tile.index={missing[0]} into {folder}/tile_{missing[0]})"
        )
    return plan, runs


def open_edges(tile: Tile) -> Tile:
    """The tile with its survey-edge sides (no neighbour) moved to infinity: its weight
    stays 1 beyond the plan's bounds (a cell centre just outside them keeps its value)."""
    w, e, s, n = tile.edges
    x0, x1, y0, y1 = tile.bounds
    inf = float("inf")
    return replace(
        tile, bounds=(-inf if w else x0, inf if e else x1, -inf if s else y0, inf if n else y1)
    )


def _read(path: Path) -> tuple[np.ndarray, Any, Any, dict[str, str]]:
    """A raster's band (NaN where no-data), transform, CRS and tags."""
    import rasterio

    with rasterio.open(path) as src:
        z = src.read(1, masked=True).astype(np.float64).filled(np.nan)
        return z, src.transform, src.crs, src.tags()


def _lattice(transforms: Sequence[Any], shapes: Sequence[tuple[int, int]], name: str):
    """The union grid of north-up rasters on one cell lattice: its transform, shape and
    each raster's ``(row, col)`` offset in it."""
    from rasterio.transform import Affine

    cell = transforms[0].a
    for t in transforms:
        if not (np.isclose(t.a, cell) and np.isclose(t.e, -cell) and t.b == 0 and t.d == 0):
            raise ValueError(
                f"{name}: expected north-up rasters of one cell size ({cell:g} m), found {t}"
            )
    left = min(t.c for t in transforms)
    top = max(t.f for t in transforms)
    offsets = []
    for t in transforms:
        col, row = (t.c - left) / cell, (top - t.f) / cell
        if not (np.isclose(col, round(col), atol=1e-3) and np.isclose(row, round(row), atol=1e-3)):
            raise ValueError(
                f"{name}: expected rasters on one cell lattice, found an offset of "
                f"({col:.3f}, {row:.3f}) cells"
            )
        offsets.append((round(row), round(col)))
    ny = max(r + s[0] for (r, _), s in zip(offsets, shapes, strict=True))
    nx = max(c + s[1] for (_, c), s in zip(offsets, shapes, strict=True))
    return Affine(cell, 0.0, left, 0.0, -cell, top), (ny, nx), offsets


def blend_layer(
    tiles: Sequence[Tile], paths: Sequence[Path], origin: dict[str, Any], name: str
) -> tuple[np.ndarray, Any, Any, list[dict[str, str]]]:
    """The tiles' rasters ``paths`` (one per tile) placed on their union grid and blended:
    ``(values north-up, NaN where none, transform, crs, each raster's tags)``."""
    read = [_read(p) for p in paths]
    transform, shape, offsets = _lattice([r[1] for r in read], [r[0].shape for r in read], name)
    cell = transform.a
    xs = transform.c + cell * (np.arange(shape[1]) + 0.5) - float(origin.get("easting") or 0.0)
    ys = transform.f - cell * (np.arange(shape[0]) + 0.5) - float(origin.get("northing") or 0.0)
    xx, yy = np.meshgrid(xs, ys)
    maps = []
    for (z, *_), (r, c) in zip(read, offsets, strict=True):
        full = np.full(shape, np.nan)
        full[r : r + z.shape[0], c : c + z.shape[1]] = z
        maps.append(full)
    return (
        blend([open_edges(t) for t in tiles], maps, xx, yy),
        transform,
        read[0][2],
        [r[3] for r in read],
    )


def _write(
    values: np.ndarray, transform: Any, origin: dict[str, Any], path: Path, tags: dict, **kw
) -> Path:
    """A north-up layer on ``transform`` written by :func:`sss2bathy.io.export.write_geotiff`
    (a COG in the survey's CRS, no-data where NaN) with ``tags``."""
    from sss2bathy.io.export import write_geotiff

    grid = _local_grid(values, transform, origin)
    mask = np.isfinite(grid.heights)
    return write_geotiff(grid, path, origin=origin, mask=mask, tags=tags, **kw)


def _local_grid(values: np.ndarray, transform: Any, origin: dict[str, Any]):
    """The north-up ``values`` on ``transform`` as a :class:`BathyGrid` in the survey's
    local frame (rows from the south)."""
    from sss2bathy.survey import BathyGrid

    cell = transform.a
    x0 = transform.c + cell / 2 - float(origin.get("easting") or 0.0)
    y0 = transform.f - cell * (values.shape[0] - 0.5) - float(origin.get("northing") or 0.0)
    return BathyGrid(values[::-1].astype(np.float32), x0, y0, cell)


def blend_tile_runs(folder: Path, out: Path | None = None) -> dict[str, Path]:
    """Blend the tile runs under ``folder`` (:func:`read_tile_runs`) into ``out`` (default
    ``folder``): ``map.tif``, ``map.png``, with every tile's uncertainty ``uncertainty.tif``
    + ``.png``, and ``blend.json``. Returns the written paths by name."""
    import shlex

    from sss2bathy.eval.maps import render_map
    from sss2bathy.io.export import TAG_PREFIX

    folder = Path(folder)
    out = folder if out is None else Path(out)
    plan, runs = read_tile_runs(folder)
    tiles = [tile_from_dict(t) for t in plan["tiles"]]
    origin = dict(plan["origin"])
    order = [runs[k] for k in range(len(tiles))]
    for run in order:
        if not (run / "map.tif").is_file():
            raise ValueError(f"{run}: expected the tile's map.tif, found none (did its job fail?)")
    z, transform, _, tags = blend_layer(tiles, [r / "map.tif" for r in order], origin, str(folder))
    methods = {t.get(f"{TAG_PREFIX}METHOD") for t in tags}
    if len(methods) > 1:
        raise ValueError(
            f"{folder}: expected tiles fitted by one method, found {sorted(map(str, methods))}"
        )
    keep = {k: v for k, v in tags[0].items() if k.startswith(TAG_PREFIX) or k == "TIFFTAG_SOFTWARE"}
    keep.pop(f"{TAG_PREFIX}TILE", None)
    keep[f"{TAG_PREFIX}TILE_COMMAND"] = keep.pop(f"{TAG_PREFIX}COMMAND", "")
    keep[f"{TAG_PREFIX}COMMAND"] = shlex.join(sys.argv)
    size = plan_size(plan)
    keep[f"{TAG_PREFIX}TILES"] = (
        f"{len(tiles)} tiles of at most {size} m, {tiles[0].overlap_m:g} m overlap, blended "
        f"cos^2/sin^2 across each shared band: {', '.join(str(r) for r in order)}"
    )
    out.mkdir(parents=True, exist_ok=True)
    paths = {"map_tif": _write(z, transform, origin, out / "map.tif", keep)}
    cell = transform.a
    grid = _local_grid(z, transform, origin)
    method = keep.get(f"{TAG_PREFIX}METHOD", "SIREN")
    paths["map_png"] = render_map(
        grid, out / "map.png", f"{method}, {len(tiles)} tiles blended: bathymetry", origin=origin
    )
    summary = {
        "tiles": len(tiles),
        "runs": [str(r) for r in order],
        "cells": int(np.isfinite(z).sum()),
        "written_area_m2": float(np.isfinite(z).sum() * cell**2),
    }
    sigma_paths = [r / "uncertainty.tif" for r in order]
    if all(p.is_file() for p in sigma_paths):
        from sss2bathy.eval.uncertainty import UNCERTAINTY_DESCRIPTION

        s, s_transform, _, s_tags = blend_layer(tiles, sigma_paths, origin, str(folder))
        s_keep = {k: v for k, v in s_tags[0].items() if k.startswith(TAG_PREFIX)}
        s_keep[f"{TAG_PREFIX}COMMAND"] = shlex.join(sys.argv)
        s_keep[f"{TAG_PREFIX}TILES"] = keep[f"{TAG_PREFIX}TILES"]
        paths["uncertainty_tif"] = _write(
            s, s_transform, origin, out / "uncertainty.tif", s_keep,
            description=UNCERTAINTY_DESCRIPTION,
        )  # fmt: skip
        paths["uncertainty_png"] = render_map(
            _local_grid(s, s_transform, origin),
            out / "uncertainty.png",
            f"{method}, {len(tiles)} tiles blended: 1-sigma uncertainty",
            cmap="magma",
            label="1 sigma (m)",
            origin=origin,
        )
        summary["sigma_median_m"] = float(np.nanmedian(s))
    elif any(p.is_file() for p in sigma_paths):
        log.warning(
            "uncertainty.tif not blended: tiles %s have none",
            ", ".join(str(k) for k, p in enumerate(sigma_paths) if not p.is_file()),
        )
    from sss2bathy.utils.atomic import atomic_write_text

    paths["blend_json"] = out / "blend.json"
    atomic_write_text(paths["blend_json"], json.dumps(summary, indent=1))
    return paths


def plan_size(plan: dict[str, Any]) -> str:
    size = plan.get("size_m") or []
    return " x ".join(f"{float(s):g}" for s in size) if size else "?"


def main(argv: list[str] | None = None) -> None:
    from sss2bathy.cli._common import setup_environment

    setup_environment()
    parser = argparse.ArgumentParser(
        prog="sss2bathy-map-blend",
        description="Blend the tile maps of a tiled sss2bathy-map run (OUT/tile_<k>/) into "
        "one map: OUT/map.tif (+ map.png, uncertainty.tif where the tiles have one).",
    )
    parser.add_argument("folder", help="the multirun folder of the tile jobs (hydra.sweep.dir)")
    parser.add_argument("--out", default=None, help="where the blended map goes (default FOLDER)")
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(levelname)s %(name)s: %(message)s")
    try:
        paths = blend_tile_runs(Path(args.folder), None if args.out is None else Path(args.out))
    except ValueError as err:
        print(f"sss2bathy-map-blend: {err}", file=sys.stderr)
        raise SystemExit(2) from None
    for name, path in paths.items():
        print(f"  {name}: {path}")


if __name__ == "__main__":
    main()
