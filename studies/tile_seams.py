"""Tiled vs single SIREN fit: the seams of a blended tile map and its error against the MBES.

A generated AUV XTF survey with its simulated MBES grid (:func:`studies.xtf_study.make_survey`:
``synthetic_d1`` at a scale, one split's lines) is mapped twice with ``sss2bathy-map``, one
fit at a time on one thread:

* **single**: one fit over every ping;
* **tiled**: the survey's extent split into overlapping tiles
  (:func:`sss2bathy.survey.tiles.tile_layout`); per tile, the pings whose nadir lies within
  the tile widened by ``--data-margin-m`` are cut out of every line into XTF files
  (:func:`cut_lines`) and fitted as an independent job; the tile maps are blended with the
  partition-of-unity taper (:func:`sss2bathy.survey.tiles.blend`). The same tiles cut hard
  at their core borders (no blend) are scored beside it.

Both routes read the same re-written lines (the single fit's files pass through the same
read/write as the tiles'). Scores, on the MBES cells every map covers: the MAE against the
MBES of each map, overall and in the seam bands (within ``overlap / 2`` of a core border);
the mean |tiled - single| there and away from the borders; the mean |a - b| of two neighbour
tiles over their shared band (the step a hard cut would leave); and the mean cell-to-cell
step across the border line of each map against the MBES's own.

    python -m studies.tile_seams --out outputs/tile_seams --seeds 1
    make tile-seams
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from collections.abc import Mapping, Sequence
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np

from sss2bathy.io.xtf import read_xtf, write_xtf
from sss2bathy.survey import BathyGrid, Survey
from sss2bathy.survey.tiles import (
    Tile,
    blend,
    border_bands,
    nadir_in,
    runs_of,
    tile_layout,
    tile_weights,
)
from sss2bathy.utils.atomic import atomic_write_text
from studies.tables import fmt_cell, markdown_table, to_csv, write_tables
from studies.xtf_study import (
    StudySurvey,
    make_survey,
    map_command,
    map_on_grid,
    mask_on_grid,
    run_map,
    truth_grid,
)

MAP_ARGS = (
    "holdout.fraction=0",
    "mosaic.placement=none",
    "verdict.overlap.enabled=false",
)


# ----------------------------------------------------------------------------- pure parts
def hard_cut(tiles: Sequence[Tile], maps: Sequence[np.ndarray], x: np.ndarray, y: np.ndarray):
    """Each point from the one tile whose core holds it (no blend): what tiles without an
    overlap give."""
    out = np.full(np.shape(x), np.nan)
    for t, z in zip(tiles, maps, strict=True):
        cx0, cx1, cy0, cy1 = t.core
        inside = (x >= cx0) & (x < cx1 if not t.edges[1] else x <= cx1)
        inside &= (y >= cy0) & (y < cy1 if not t.edges[3] else y <= cy1)
        out = np.where(inside, z, out)
    return out


def neighbour_disagreement(
    tiles: Sequence[Tile], maps: Sequence[np.ndarray], x: np.ndarray, y: np.ndarray
) -> float:
    """Mean |z_a - z_b| over the points where two tiles both have a weight in (0, 1) (their
    shared bands) and both a value: the step a hard cut could leave. NaN without such
    points."""
    diffs = []
    for i, (ta, za) in enumerate(zip(tiles, maps, strict=True)):
        wa = tile_weights(ta, x, y)
        for tb, zb in list(zip(tiles, maps, strict=True))[i + 1 :]:
            wb = tile_weights(tb, x, y)
            shared = (wa > 0) & (wb > 0) & np.isfinite(za) & np.isfinite(zb)
            diffs.append(np.abs(za - zb)[shared])
    d = np.concatenate(diffs) if diffs else np.array([])
    return float(d.mean()) if d.size else math.nan


def border_step(z: np.ndarray, tiles: Sequence[Tile], grid: BathyGrid, valid: np.ndarray) -> float:
    """Mean |z| step between the two cells on either side of each core border (east and
    north borders), over the rows / columns where both are ``valid``; NaN without any."""
    steps = []
    x, y = grid.x, grid.y
    for t in tiles:
        if not t.edges[1]:
            j = int(np.searchsorted(x, t.core[1]))  # first column east of the border
            if 0 < j < x.size:
                rows = (y >= t.core[2]) & (y <= t.core[3])
                ok = rows & valid[:, j] & valid[:, j - 1]
                steps.append(np.abs(z[ok, j] - z[ok, j - 1]))
        if not t.edges[3]:
            i = int(np.searchsorted(y, t.core[3]))
            if 0 < i < y.size:
                cols = (x >= t.core[0]) & (x <= t.core[1])
                ok = cols & valid[i] & valid[i - 1]
                steps.append(np.abs(z[i, ok] - z[i - 1, ok]))
    s = np.concatenate(steps) if steps else np.array([])
    return float(s.mean()) if s.size else math.nan


def seam_scores(
    truth: BathyGrid,
    single: np.ndarray,
    tile_maps: Sequence[np.ndarray],
    tiles: Sequence[Tile],
    cells: np.ndarray,
) -> dict[str, float]:
    """The study's scores on ``truth``'s grid (``cells``: the cells to score)."""
    xx, yy = np.meshgrid(truth.x, truth.y)
    tiled = blend(tiles, tile_maps, xx, yy)
    cut = hard_cut(tiles, tile_maps, xx, yy)
    h = np.asarray(truth.heights, np.float64)
    ok = cells & np.isfinite(h) & np.isfinite(single) & np.isfinite(tiled) & np.isfinite(cut)
    band = border_bands(tiles, xx, yy, tiles[0].overlap_m) & ok
    away = ok & ~band

    def mae(z: np.ndarray, m: np.ndarray) -> float:
        return float(np.abs(z - h)[m].mean()) if m.any() else math.nan

    def diff(m: np.ndarray) -> float:
        return float(np.abs(tiled - single)[m].mean()) if m.any() else math.nan

    return {
        "cells": int(ok.sum()),
        "band_cells": int(band.sum()),
        "mae_single": mae(single, ok),
        "mae_tiled": mae(tiled, ok),
        "mae_hard_cut": mae(cut, ok),
        "band_mae_single": mae(single, band),
        "band_mae_tiled": mae(tiled, band),
        "band_mae_hard_cut": mae(cut, band),
        "tiled_vs_single_band": diff(band),
        "tiled_vs_single_away": diff(away),
        "neighbour_disagreement": neighbour_disagreement(tiles, tile_maps, xx, yy),
        "step_truth": border_step(h, tiles, truth, ok),
        "step_single": border_step(single, tiles, truth, ok),
        "step_tiled": border_step(tiled, tiles, truth, ok),
        "step_hard_cut": border_step(cut, tiles, truth, ok),
    }


# ----------------------------------------------------------------------------- runs
def cut_lines(
    lines: Sequence[Any],
    origin: Mapping[str, Any],
    out_dir: Path,
    bounds: Sequence[float] | None,
    margin_m: float,
    min_pings: int = 20,
) -> int:
    """Write the runs of each line's pings with nadir in ``bounds`` (+ ``margin_m``; None =
    every ping) to ``out_dir/<line>_<k>.xtf``; returns the pings written."""
    out_dir.mkdir(parents=True, exist_ok=True)
    written = 0
    for line in lines:
        keep = (
            np.ones(line.n_pings, bool)
            if bounds is None
            else nadir_in(line.position, bounds, margin_m)
        )
        for k, sl in enumerate(runs_of(keep, min_pings)):
            part = replace(
                line,
                time_s=line.time_s[sl],
                position=line.position[sl],
                rotation=line.rotation[sl],
                altitude_m=line.altitude_m[sl],
                intensity=line.intensity[sl],
                extras={},
                altitude_source=None,
            )
            write_xtf(part, out_dir / f"{line.name}_{k}.xtf", origin)
            written += sl.stop - sl.start
    return written


def load_map(run_dir: Path, data_dir: Path, name: str, truth: BathyGrid, origin: Mapping):
    """A run's ``map.npz`` on ``truth``'s cells (NaN outside what it covers)."""
    with np.load(run_dir / "map.npz", allow_pickle=False) as d:
        m = {k: d[k] for k in d.files}
    imported = Survey.load(data_dir / name).origin
    shift = (
        float(origin["easting"]) - float(imported.get("easting") or 0.0),
        float(origin["northing"]) - float(imported.get("northing") or 0.0),
    )
    geom = (float(m["x0"]), float(m["y0"]), float(m["cell_size"]))
    z = map_on_grid(m["heights"], *geom, truth, shift).heights.astype(np.float64)
    covered = mask_on_grid(m["coverage"], *geom, truth, shift)
    return np.where(covered, z, np.nan), covered


def run_seed(
    out: Path,
    seed: int,
    scale: str,
    split: str,
    tile_m: Sequence[float],
    overlap_m: float,
    margin_m: float,
) -> dict[str, Any]:
    survey = make_survey(out / f"survey_s{seed}", seed, scale=scale, split=split)
    truth, (easting, northing) = truth_grid(survey)
    origin = {"crs": survey.crs, "easting": easting, "northing": northing}
    files = sorted(p for p in survey.xtf_dir.glob("*.xtf"))
    lines = [read_xtf(p, None, origin=origin)[0] for p in files]
    bounds = (
        truth.x0 - truth.cell_size / 2,
        truth.x0 + (truth.shape[1] - 0.5) * truth.cell_size,
        truth.y0 - truth.cell_size / 2,
        truth.y0 + (truth.shape[0] - 0.5) * truth.cell_size,
    )
    tiles = tile_layout(bounds, tuple(tile_m), overlap_m)
    data_dir = out / "data"
    jobs = {"single": (None, out / f"s{seed}" / "single")}
    for t in tiles:
        jobs[f"tile_{t.index[0]}_{t.index[1]}"] = (
            t,
            out / f"s{seed}" / f"tile_{t.index[0]}_{t.index[1]}",
        )
    maps, walls, pings = {}, {}, {}
    for key, (tile, folder) in jobs.items():
        xtf_dir = folder / "xtf"
        if not xtf_dir.is_dir():
            pings[key] = cut_lines(
                lines, origin, xtf_dir, None if tile is None else tile.bounds, margin_m
            )
        else:
            pings[key] = None
        name = f"tile_seams_s{seed}_{key}"
        run_dir = folder / "run"
        if not (run_dir / "map.npz").is_file():
            job = StudySurvey(xtf_dir, name, survey.crs)
            cmd = map_command(
                job, "siren_lambert", "demo", seed, run_dir, data_dir, scale, map_args=MAP_ARGS
            )
            run_map(cmd, run_dir)
        walls[key] = float((run_dir / "study_wall_s.txt").read_text())  # written by run_map
        print(f"seed {seed} {key}: {walls[key]:.0f} s", flush=True)
        z, _ = load_map(run_dir, data_dir, name, truth, origin)
        if tile is not None:
            xx, yy = np.meshgrid(truth.x, truth.y)
            bx0, bx1, by0, by1 = tile.bounds
            z = np.where((xx >= bx0) & (xx <= bx1) & (yy >= by0) & (yy <= by1), z, np.nan)
        maps[key] = z
    single = maps.pop("single")
    scores = seam_scores(truth, single, list(maps.values()), tiles, np.isfinite(single))
    row = {"seed": seed, "tiles": len(tiles), "overlap_m": overlap_m, **scores}
    row["wall_single_s"] = walls["single"]
    row["wall_tiles_s"] = sum(v for k, v in walls.items() if k != "single")
    _figure(truth, single, maps, tiles, out / f"s{seed}" / "tile_seams.png")
    return row


def _figure(truth: BathyGrid, single, maps, tiles, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    xx, yy = np.meshgrid(truth.x, truth.y)
    tiled = blend(tiles, list(maps.values()), xx, yy)
    cut = hard_cut(tiles, list(maps.values()), xx, yy)
    h = truth.heights
    ext = (truth.x[0], truth.x[-1], truth.y[0], truth.y[-1])
    fig, axes = plt.subplots(1, 4, figsize=(16, 4))
    for ax, (title, z) in zip(
        axes,
        (
            ("single - MBES", single - h),
            ("tiled (blended) - MBES", tiled - h),
            ("hard cut - MBES", cut - h),
            ("tiled - single", tiled - single),
        ),
        strict=True,
    ):
        im = ax.imshow(z, origin="lower", extent=ext, cmap="RdBu_r", vmin=-1, vmax=1)
        for t in tiles:
            cx0, cx1, cy0, cy1 = t.core
            ax.plot([cx0, cx1, cx1, cx0, cx0], [cy0, cy0, cy1, cy1, cy0], "k--", lw=0.6)
        ax.set_title(title)
        ax.set_xlabel("x (m)")
    axes[0].set_ylabel("y (m)")
    fig.colorbar(im, ax=axes, shrink=0.8, label="m")
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=100)
    plt.close(fig)


COLUMNS = (
    "seed",
    "tiles",
    "overlap_m",
    "cells",
    "mae_single",
    "mae_tiled",
    "mae_hard_cut",
    "band_mae_single",
    "band_mae_tiled",
    "band_mae_hard_cut",
    "tiled_vs_single_band",
    "tiled_vs_single_away",
    "neighbour_disagreement",
    "step_truth",
    "step_single",
    "step_tiled",
    "step_hard_cut",
    "wall_single_s",
    "wall_tiles_s",
)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--out", type=Path, default=Path("outputs/tile_seams"))
    parser.add_argument("--seeds", type=int, nargs="+", default=[1])
    parser.add_argument("--scale", default="demo")
    parser.add_argument("--split", default="test")
    parser.add_argument("--tile-m", type=float, nargs=2, default=[80.0, 120.0])
    parser.add_argument("--overlap-m", type=float, default=30.0)
    parser.add_argument("--data-margin-m", type=float, default=10.0)
    args = parser.parse_args(argv)
    rows = []
    for seed in args.seeds:
        try:
            rows.append(
                run_seed(
                    args.out,
                    seed,
                    args.scale,
                    args.split,
                    args.tile_m,
                    args.overlap_m,
                    args.data_margin_m,
                )
            )
        except (RuntimeError, ValueError) as err:
            print(f"error: seed {seed}: {err}", file=sys.stderr)
            return 1
    md = "\n".join(
        markdown_table(COLUMNS, [[fmt_cell(r.get(c, math.nan)) for c in COLUMNS] for r in rows])
    )
    write_tables(args.out, "tile_seams", md + "\n", to_csv(rows, COLUMNS, ignore_extra=True))
    atomic_write_text(args.out / "tile_seams.json", json.dumps(rows, indent=1))
    print(md)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
