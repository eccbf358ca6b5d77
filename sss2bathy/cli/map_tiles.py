"""``sss2bathy-map`` over overlapping tiles: the plan, one tile's job and its survey.

A survey larger than one SIREN can represent at the detail needed is mapped as overlapping
tiles (:mod:`sss2bathy.survey.tiles`), each an independent ``sss2bathy-map`` run, and
blended into one map by ``sss2bathy-map-blend`` (:mod:`sss2bathy.cli.map_blend`):

    sss2bathy-map files=/data/lines tile.size_m=200 tile.overlap_m=30
        -> imports the survey, prints the plan (N tiles) and the two commands below
    sss2bathy-map -m files=/data/lines tile.size_m=200 tile.overlap_m=30 \\
        'tile.index=range(0,N)' hydra.sweep.dir=OUT [hydra/launcher=joblib torch_threads=1]
        -> OUT/tile_<k>/: each tile's map.tif, map.npz, tile.json, ...
    sss2bathy-map-blend OUT
        -> OUT/map.tif (+ map.png, uncertainty.tif where the tiles have one)

The plan covers the survey's footprint (the nadirs widened by the longest slant range:
:func:`sss2bathy.survey.tiles.footprint_bounds`). Tile ``k``'s job fits the runs of pings
whose nadir lies within its tile widened by ``tile.margin_m`` (null: the longest slant
range, so every ping that can image the tile), written as a survey folder
``paths.data_dir/<survey>_tile<k>/`` (reused while the import and the plan are unchanged).
A plan of one tile is the untiled route (the job fits the whole survey).
"""

from __future__ import annotations

import json
import logging
import math
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

from omegaconf import OmegaConf

from sss2bathy.survey.tiles import Tile, tile_layout, tile_to_dict
from sss2bathy.utils.atomic import atomic_write_text, stable_hash

log = logging.getLogger("sss2bathy.map")

#: the file each tile job writes into its run folder (the blend reads it)
TILE_JSON = "tile.json"
#: the plan a planning run writes into its run folder
PLAN_JSON = "tiles.json"
#: Hydra's resolver of ``hydra.sweep.subdir`` in ``conf/map.yaml``
SUBDIR_RESOLVER = "sss2bathy_tile_subdir"


def tile_subdir(index: Any, job_num: Any) -> str:
    """A multirun job's folder: ``tile_<index>`` for a tile job, else the job number."""
    return str(job_num) if index is None else f"tile_{index}"


def register_resolver() -> None:
    """Register :func:`tile_subdir` for ``conf/map.yaml``'s ``hydra.sweep.subdir``."""
    if not OmegaConf.has_resolver(SUBDIR_RESOLVER):
        OmegaConf.register_new_resolver(SUBDIR_RESOLVER, tile_subdir)


def tile_settings(cfg: Mapping[str, Any]) -> dict[str, Any] | None:
    """``tile`` checked: None when off (``size_m`` null), else ``size_m`` (two sides),
    ``overlap_m``, ``index`` (None = plan only), ``margin_m`` (None = the longest slant
    range) and ``min_pings``. One-line ``ValueError`` naming the key otherwise."""
    node = cfg.get("tile") or {}
    size = node.get("size_m")
    if size is None:
        return None

    def number(v: Any) -> bool:
        return not isinstance(v, bool) and isinstance(v, int | float) and math.isfinite(v)

    sizes = list(size) if isinstance(size, Sequence) and not isinstance(size, str) else [size]
    sizes = sizes * 2 if len(sizes) == 1 else sizes
    if len(sizes) != 2 or not all(number(s) and s > 0 for s in sizes):
        raise ValueError(
            f"tile.size_m: expected a positive tile side (m) or [along x, along y], found {size!r}"
        )
    overlap = node.get("overlap_m", 0)
    if not number(overlap) or not 0 <= overlap < min(sizes):
        raise ValueError(
            f"tile.overlap_m: expected 0 <= overlap < tile.size_m ({min(sizes):g} m), "
            f"found {overlap!r}"
        )
    index = node.get("index")
    if index is not None and (isinstance(index, bool) or not isinstance(index, int) or index < 0):
        raise ValueError(
            f"tile.index: expected a tile number >= 0 (or null: print the plan), found {index!r}"
        )
    margin = node.get("margin_m")
    if margin is not None and not (number(margin) and margin >= 0):
        raise ValueError(
            f"tile.margin_m: expected a distance >= 0 (m) or null (the longest slant range), "
            f"found {margin!r}"
        )
    min_pings = node.get("min_pings", 20)
    if isinstance(min_pings, bool) or not isinstance(min_pings, int) or min_pings < 2:
        raise ValueError(f"tile.min_pings: expected a count >= 2, found {min_pings!r}")
    return {
        "size_m": [float(s) for s in sizes],
        "overlap_m": float(overlap),
        "index": index,
        "margin_m": None if margin is None else float(margin),
        "min_pings": int(min_pings),
    }


def plan_tiles(
    cfg: Mapping[str, Any], survey_cfg: Mapping[str, Any]
) -> tuple[list[Tile], Any, dict[str, Any]] | None:
    """``(tiles, full survey, settings)`` of a map config with ``tile.size_m`` set, else
    None; ``survey_cfg``: its XTF import (``data/survey=xtf`` with the survey's name:
    :func:`sss2bathy.cli.map.map_survey_config`), imported or reused."""
    settings = tile_settings(cfg)
    if settings is None:
        return None
    from sss2bathy.data.sources import load_survey
    from sss2bathy.survey.tiles import footprint_bounds

    survey, _ = load_survey(survey_cfg, str(cfg["paths"]["data_dir"]))
    bounds = footprint_bounds(survey.lines)
    try:
        tiles = tile_layout(bounds, settings["size_m"], settings["overlap_m"])
    except ValueError as err:
        raise ValueError("tile." + str(err).replace("tile_m", "size_m")) from None
    index = settings["index"]
    if index is not None and index >= len(tiles):
        raise ValueError(
            f"tile.index: expected 0..{len(tiles) - 1} (the plan's {len(tiles)} tiles over "
            f"{bounds[1] - bounds[0]:.0f} m x {bounds[3] - bounds[2]:.0f} m of survey "
            f"'{survey.name}'), found {index}"
        )
    return tiles, survey, settings


def _margin(settings: Mapping[str, Any], survey: Any) -> float:
    if settings["margin_m"] is not None:
        return float(settings["margin_m"])
    return max(float(ln.range_m.max()) for ln in survey.lines)


def tile_survey_config(
    cfg: Mapping[str, Any], survey_cfg: Mapping[str, Any]
) -> dict[str, Any] | None:
    """The ``data.survey`` of a tile job (``tile.index`` set, a plan of two tiles or more):
    a survey folder of the runs of pings whose nadir lies within the tile widened by the
    margin (written once, reused while the import and the plan are unchanged); None
    otherwise (no tiles, the plan only, or one tile: the whole survey)."""
    planned = plan_tiles(cfg, survey_cfg)
    if planned is None:
        return None
    tiles, survey, settings = planned
    index = settings["index"]
    if index is None or len(tiles) == 1:
        return None
    from sss2bathy.survey import Survey
    from sss2bathy.survey.tiles import cut_lines

    tile = tiles[index]
    margin = _margin(settings, survey)
    folder = Path(str(cfg["paths"]["data_dir"])) / f"{survey.name}_tile{index}"
    key = stable_hash(
        {
            "source": (survey.metadata or {}).get("source_hash"),
            "survey": survey.name,
            "tile": tile_to_dict(tile),
            "margin_m": margin,
            "min_pings": settings["min_pings"],
        }
    )
    manifest = folder / "survey.yaml"
    if (
        manifest.is_file()
        and (Survey.read_manifest(folder).get("metadata") or {}).get("tile_key") == key
    ):
        log.info("tile %d: reusing its survey %s", index, folder)
    else:
        lines, dropped, cut = [], 0, {}
        for line in survey.lines:
            runs, left_out = cut_lines([line], tile.bounds, margin, settings["min_pings"])
            lines += runs
            dropped += left_out
            cut[line.name] = [ln.name for ln in runs]
        if not lines:
            raise ValueError(
                f"tile.index: tile {index} ({_describe(tile)}) holds no run of "
                f"{settings['min_pings']} or more pings of survey '{survey.name}' within "
                f"{margin:g} m; nothing to fit (a larger tile.size_m or tile.margin_m)"
            )
        if dropped:
            log.warning(
                "tile %d: %d pings inside the tile (+ %g m) left out in runs shorter than "
                "tile.min_pings=%d",
                index, dropped, margin, settings["min_pings"],
            )  # fmt: skip
        splits = {
            split: [n for old in members for n in cut.get(old, [])]
            for split, members in survey.splits.items()
        }
        Survey(
            name=folder.name,
            lines=lines,
            grid=survey.grid,
            splits={k: v for k, v in splits.items() if v},
            origin=dict(survey.origin),
            metadata={"tile_key": key, "tile": tile_to_dict(tile), "parent": survey.name},
        ).save(folder)
        n = sum(ln.n_pings for ln in lines)
        log.info(
            "tile %d of %d (%s): %d of %d pings (nadir within the tile + %g m), %d lines, in %s",
            index, len(tiles), _describe(tile), n, sum(ln.n_pings for ln in survey.lines),
            margin, len(lines), folder,
        )  # fmt: skip
    return {"kind": "folder", "path": str(folder), "name": folder.name}


def _describe(tile: Tile) -> str:
    x0, x1, y0, y1 = tile.bounds
    return f"x {x0:.0f}..{x1:.0f} m, y {y0:.0f}..{y1:.0f} m"


def is_tile_job(cfg: Mapping[str, Any]) -> bool:
    """Whether a map config fits one tile of a plan (``tile.size_m`` and ``tile.index``)."""
    settings = tile_settings(cfg)
    return settings is not None and settings["index"] is not None


def _plan_record(tiles: Sequence[Tile], survey: Any, settings: Mapping[str, Any]) -> dict:
    """The plan as ``tiles.json`` / ``tile.json`` hold it."""
    return {
        "n_tiles": len(tiles),
        "tiles": [tile_to_dict(t) for t in tiles],
        "survey": survey.name,
        "origin": dict(survey.origin),
        "size_m": settings["size_m"],
        "overlap_m": settings["overlap_m"],
        "margin_m": _margin(settings, survey),
    }


def write_tile_record(cfg: Mapping[str, Any], survey_cfg: Mapping[str, Any], run_dir: Path) -> Path:
    """A tile job's ``tile.json`` (the plan, its index, the survey origin) and its
    ``map.tif``'s tags: the vertical reference of the XTF import (the tile's survey is a
    folder cut from it) and ``SSS2BATHY_TILE``."""
    from sss2bathy.io.export import TAG_PREFIX, VERTICAL_REFERENCE, add_geotiff_tags

    tiles, survey, settings = plan_tiles(cfg, survey_cfg)  # type: ignore[misc]
    index = settings["index"]
    record = {"index": index, **_plan_record(tiles, survey, settings)}
    path = Path(run_dir) / TILE_JSON
    atomic_write_text(path, json.dumps(record, indent=1))
    tif = Path(run_dir) / "map.tif"
    if tif.is_file():
        add_geotiff_tags(
            tif,
            {
                f"{TAG_PREFIX}VERTICAL_REFERENCE": VERTICAL_REFERENCE["xtf"],
                f"{TAG_PREFIX}TILE": f"{index} of {len(tiles)} ({_describe(tiles[index])})",
            },
        )
    return path


def _user_overrides() -> list[str]:
    """The command line's overrides (Hydra's), less ``tile.index`` and ``hydra.*``."""
    try:
        from hydra.core.hydra_config import HydraConfig

        given = list(HydraConfig.get().overrides.task)
    except ValueError:
        return []
    return [
        o for o in given if not o.split("=", 1)[0].lstrip("+~").startswith(("tile.index", "hydra"))
    ]


def run_tile_plan(
    cfg: Mapping[str, Any], survey_cfg: Mapping[str, Any], run_dir: Path
) -> list[str]:
    """The plan of a map config with ``tile.size_m`` and no ``tile.index``: ``tiles.json``
    in ``run_dir``, and the lines to print (the tiles, the multirun and blend commands)."""
    import shlex

    tiles, survey, settings = plan_tiles(cfg, survey_cfg)  # type: ignore[misc]
    margin = _margin(settings, survey)
    record = _plan_record(tiles, survey, settings)
    atomic_write_text(Path(run_dir) / PLAN_JSON, json.dumps(record, indent=1))
    from sss2bathy.survey.tiles import nadir_in

    lines = [
        f"sss2bathy-map: tile plan of survey '{survey.name}': {len(tiles)} tiles of at most "
        f"{settings['size_m'][0]:g} x {settings['size_m'][1]:g} m, {settings['overlap_m']:g} m "
        f"overlap; each fits the pings whose nadir lies within its tile + {margin:g} m "
        f"(plan: {Path(run_dir) / PLAN_JSON})"
    ]
    for k, t in enumerate(tiles):
        n = sum(int(nadir_in(ln.position, t.bounds, margin).sum()) for ln in survey.lines)
        lines.append(
            f"  tile {k} (column {t.index[0]}, row {t.index[1]}): {_describe(t)}, {n} pings"
        )
    out = Path(run_dir) / "tiles"
    args = " ".join(shlex.quote(o) for o in _user_overrides())
    lines += [
        "fit every tile (one job each; add hydra/launcher=joblib torch_threads=1 for parallel "
        "jobs here, hydra/launcher=submitit_slurm on a cluster):",
        f"  sss2bathy-map -m {args} 'tile.index=range(0,{len(tiles)})' hydra.sweep.dir={out}",
        "then blend them into one map:",
        f"  sss2bathy-map-blend {out}",
    ]
    return lines
