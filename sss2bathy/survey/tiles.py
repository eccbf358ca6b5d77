"""Overlapping tiles of a survey and their seamless blend (pure functions).

A survey larger than one SIREN can represent at the detail needed is fitted as overlapping
tiles, each an independent job, and the tile maps are blended into one map. The layout
splits the survey's bounds into ``nx x ny`` equal *core* cells; a tile is its core cell
widened by half the overlap on every side that has a neighbour, so two neighbours share a
band ``overlap_m`` wide centred on their common core border. Across that band the weight of
one tile falls from 1 to 0 as ``cos^2`` while its neighbour's rises as ``sin^2``; along x
and y the weights multiply. The weights are a partition of unity: at every point of the
survey they sum to 1, so a blend of maps that agree is that map, and where they disagree
the blend moves smoothly from one to the other over the band (no step).

Coordinates are the survey's local frame (m); bounds are ``(x_min, x_max, y_min, y_max)``.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import asdict, dataclass, replace
from typing import Any

import numpy as np

from sss2bathy.survey.model import SidescanLine

__all__ = [
    "Tile",
    "blend",
    "border_bands",
    "cut_lines",
    "footprint_bounds",
    "nadir_in",
    "runs_of",
    "taper",
    "tile_from_dict",
    "tile_layout",
    "tile_to_dict",
    "tile_weights",
]

Bounds = tuple[float, float, float, float]


@dataclass(frozen=True)
class Tile:
    """One tile of a :func:`tile_layout`.

    Attributes:
        index: ``(column, row)`` in the layout (column along x).
        core: the core cell ``(x_min, x_max, y_min, y_max)``: the tiles' cores partition
            the survey's bounds.
        bounds: the tile (the core widened by ``overlap / 2`` toward each neighbour): what
            its fit must cover.
        overlap_m: the width of the band shared with each neighbour.
        edges: which sides are the survey's edge (no neighbour, no taper):
            ``(west, east, south, north)``.
    """

    index: tuple[int, int]
    core: Bounds
    bounds: Bounds
    overlap_m: float
    edges: tuple[bool, bool, bool, bool]


def _check_bounds(bounds: Sequence[float], key: str = "bounds") -> Bounds:
    if len(bounds) != 4:
        raise ValueError(f"{key}: expected (x_min, x_max, y_min, y_max), found {bounds!r}")
    b = tuple(float(v) for v in bounds)
    if not all(math.isfinite(v) for v in b) or not (b[1] > b[0] and b[3] > b[2]):
        raise ValueError(f"{key}: expected finite x_min < x_max and y_min < y_max, found {b}")
    return b  # type: ignore[return-value]


def _largest_tile(extent: float, n: int, overlap_m: float) -> float:
    """The widest of ``n`` tiles over ``extent``: a core, plus half the overlap per
    neighbour."""
    return extent / n + overlap_m * min(n - 1, 2) / 2


def _count(extent: float, size: float, overlap_m: float) -> int:
    n = max(1, math.ceil(extent / size - 1e-9))
    while _largest_tile(extent, n, overlap_m) > size + 1e-9:
        n += 1
    return n


def tile_layout(
    bounds: Sequence[float], tile_m: float | Sequence[float], overlap_m: float
) -> list[Tile]:
    """The fewest equal core cells covering ``bounds`` whose tiles (a core widened by half
    the overlap toward each neighbour) are at most ``tile_m`` per side, and those tiles.

    Args:
        bounds: the survey's ``(x_min, x_max, y_min, y_max)``.
        tile_m: the largest tile side (m), one value or ``(along x, along y)``.
        overlap_m: the width of the band two neighbours share (m), ``0 <= overlap_m <
            tile_m``; 0 = tiles that only touch (a hard cut).

    Returns:
        The tiles, row by row from the south-west.

    Raises:
        ValueError: bad bounds, sizes or overlap (one line naming the argument).
    """
    x0, x1, y0, y1 = _check_bounds(bounds)
    sizes = (tile_m, tile_m) if np.ndim(tile_m) == 0 else tuple(tile_m)  # type: ignore[arg-type]
    if len(sizes) != 2 or not all(math.isfinite(s) and s > 0 for s in sizes):
        raise ValueError(f"tile_m: expected a positive size or two, found {tile_m!r}")
    if not (math.isfinite(overlap_m) and 0 <= overlap_m < min(sizes)):
        raise ValueError(
            f"overlap_m: expected 0 <= overlap_m < tile_m ({min(sizes)} m), found {overlap_m}"
        )
    counts = [
        _count(extent, size, overlap_m)
        for extent, size in ((x1 - x0, sizes[0]), (y1 - y0, sizes[1]))
    ]
    xs = np.linspace(x0, x1, counts[0] + 1)
    ys = np.linspace(y0, y1, counts[1] + 1)
    half = overlap_m / 2
    cores_x = [(float(a), float(b)) for a, b in zip(xs[:-1], xs[1:], strict=True)]
    cores_y = [(float(a), float(b)) for a, b in zip(ys[:-1], ys[1:], strict=True)]
    if any(b - a < overlap_m for a, b in cores_x + cores_y):
        raise ValueError(
            f"overlap_m: expected at most the core cell ({min(b - a for a, b in cores_x + cores_y):.1f} m) "
            f"so that only neighbours overlap, found {overlap_m}"
        )
    tiles = []
    for j, (cy0, cy1) in enumerate(cores_y):
        for i, (cx0, cx1) in enumerate(cores_x):
            edges = (i == 0, i == counts[0] - 1, j == 0, j == counts[1] - 1)
            tiles.append(
                Tile(
                    index=(i, j),
                    core=(cx0, cx1, cy0, cy1),
                    bounds=(
                        cx0 if edges[0] else cx0 - half,
                        cx1 if edges[1] else cx1 + half,
                        cy0 if edges[2] else cy0 - half,
                        cy1 if edges[3] else cy1 + half,
                    ),
                    overlap_m=float(overlap_m),
                    edges=edges,
                )
            )
    return tiles


def taper(u: np.ndarray, lo: float, hi: float, overlap_m: float, lo_edge: bool, hi_edge: bool):
    """1-D weight of a tile spanning ``[lo, hi]`` at coordinates ``u``: 0 outside, 1 inside
    except over the ``overlap_m``-wide bands at its ends that are not survey edges, where it
    rises as ``sin^2`` (``cos^2`` falling at the far end); a neighbour's ramp over the same
    band is the complement, so the two sum to 1."""
    u = np.asarray(u, dtype=np.float64)
    w = ((u >= lo) & (u <= hi)).astype(np.float64)
    if overlap_m > 0:
        if not lo_edge:
            t = np.clip((u - lo) / overlap_m, 0.0, 1.0)
            w *= np.sin(0.5 * np.pi * t) ** 2
        if not hi_edge:
            t = np.clip((hi - u) / overlap_m, 0.0, 1.0)
            w *= np.sin(0.5 * np.pi * t) ** 2
    else:  # touching tiles: each point belongs to one of them (the west / south one at a border)
        if not lo_edge:
            w *= u > lo
    return w


def tile_weights(tile: Tile, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """The tile's blend weight at the points ``(x, y)`` (arrays of one shape): the product of
    its :func:`taper` along x and along y."""
    x, y = np.broadcast_arrays(np.asarray(x, np.float64), np.asarray(y, np.float64))
    w, e, s, n = tile.edges
    bx0, bx1, by0, by1 = tile.bounds
    return taper(x, bx0, bx1, tile.overlap_m, w, e) * taper(y, by0, by1, tile.overlap_m, s, n)


def blend(
    tiles: Sequence[Tile], maps: Sequence[np.ndarray], x: np.ndarray, y: np.ndarray
) -> np.ndarray:
    """The tiles' maps blended into one: ``sum_i w_i z_i / sum_i w_i`` over the tiles with
    a finite value at each point (the weights sum to 1 where every tile has one; where a
    tile has no value its neighbours' weights are renormalised), NaN where none has one.

    Args:
        tiles: the layout.
        maps: per tile, its heights at the points ``(x, y)`` (NaN outside its bounds or where
            it has none).
        x, y: the points (arrays of the maps' shape).
    """
    if len(tiles) != len(maps):
        raise ValueError(f"maps: expected one per tile ({len(tiles)}), found {len(maps)}")
    x, y = np.broadcast_arrays(np.asarray(x, np.float64), np.asarray(y, np.float64))
    total = np.zeros(x.shape)
    weight = np.zeros(x.shape)
    for i, (tile, z) in enumerate(zip(tiles, maps, strict=True)):
        z = np.asarray(z, np.float64)
        if z.shape != x.shape:
            raise ValueError(f"maps[{i}]: expected shape {x.shape}, found {z.shape}")
        w = np.where(np.isfinite(z), tile_weights(tile, x, y), 0.0)
        total += w * np.nan_to_num(z)
        weight += w
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(weight > 0, total / np.where(weight > 0, weight, 1.0), np.nan)


def border_bands(tiles: Sequence[Tile], x: np.ndarray, y: np.ndarray, width_m: float):
    """Points within ``width_m / 2`` of a border between two tiles' cores (where a blend
    changes from one tile to another): a bool array of the points' shape."""
    x, y = np.broadcast_arrays(np.asarray(x, np.float64), np.asarray(y, np.float64))
    half = width_m / 2
    near = np.zeros(x.shape, dtype=bool)
    for t in tiles:
        cx0, cx1, cy0, cy1 = t.core
        inside_y = (y >= cy0 - half) & (y <= cy1 + half)
        inside_x = (x >= cx0 - half) & (x <= cx1 + half)
        if not t.edges[1]:  # the east border, shared with the next column
            near |= (np.abs(x - cx1) <= half) & inside_y
        if not t.edges[3]:  # the north border
            near |= (np.abs(y - cy1) <= half) & inside_x
    return near


def tile_to_dict(tile: Tile) -> dict[str, Any]:
    """A tile as plain JSON-able values (:func:`tile_from_dict` reads it back)."""
    return {k: list(v) if isinstance(v, tuple) else v for k, v in asdict(tile).items()}


def tile_from_dict(d: Any) -> Tile:
    """The :class:`Tile` of :func:`tile_to_dict`."""
    return Tile(
        index=tuple(int(v) for v in d["index"]),  # type: ignore[arg-type]
        core=tuple(float(v) for v in d["core"]),  # type: ignore[arg-type]
        bounds=tuple(float(v) for v in d["bounds"]),  # type: ignore[arg-type]
        overlap_m=float(d["overlap_m"]),
        edges=tuple(bool(v) for v in d["edges"]),  # type: ignore[arg-type]
    )


# ----------------------------------------------------------------------------- the pings
def nadir_in(position: np.ndarray, bounds: Sequence[float], margin_m: float) -> np.ndarray:
    """``(P,)`` bool: pings whose nadir ``position[:, :2]`` lies within ``bounds``
    ``(x_min, x_max, y_min, y_max)`` widened by ``margin_m``."""
    x0, x1, y0, y1 = bounds
    x, y = position[:, 0], position[:, 1]
    return (x >= x0 - margin_m) & (x <= x1 + margin_m) & (y >= y0 - margin_m) & (y <= y1 + margin_m)


def runs_of(keep: np.ndarray, min_pings: int) -> list[slice]:
    """The runs of consecutive True in ``keep`` at least ``min_pings`` long."""
    k = np.concatenate([[False], np.asarray(keep, bool), [False]])
    starts = np.flatnonzero(k[1:] & ~k[:-1])
    ends = np.flatnonzero(~k[1:] & k[:-1])
    return [slice(int(a), int(b)) for a, b in zip(starts, ends, strict=True) if b - a >= min_pings]


def footprint_bounds(lines: Sequence[SidescanLine]) -> Bounds:
    """``(x_min, x_max, y_min, y_max)`` of the lines' nadirs widened by the longest slant
    range: every cell a bin can image (what a fit's map grid spans), the area a tile plan
    covers."""
    if not lines:
        raise ValueError("lines: expected at least one line, found none")
    xy = np.concatenate([ln.position[:, :2] for ln in lines])
    reach = max(float(ln.range_m.max()) for ln in lines)
    lo, hi = xy.min(0) - reach, xy.max(0) + reach
    return (float(lo[0]), float(hi[0]), float(lo[1]), float(hi[1]))


def _ping_slice(line: SidescanLine, sl: slice, name: str) -> SidescanLine:
    n = line.n_pings
    extras = {k: v[sl] if np.ndim(v) and np.shape(v)[0] == n else v for k, v in line.extras.items()}
    source = None if line.altitude_source is None else line.altitude_source[sl]
    return replace(
        line,
        name=name,
        time_s=line.time_s[sl],
        position=line.position[sl],
        rotation=line.rotation[sl],
        altitude_m=line.altitude_m[sl],
        intensity=line.intensity[sl],
        extras=extras,
        altitude_source=source,
    )


def cut_lines(
    lines: Sequence[SidescanLine], bounds: Sequence[float], margin_m: float, min_pings: int
) -> tuple[list[SidescanLine], int]:
    """The runs of each line's pings whose nadir lies in ``bounds`` widened by ``margin_m``
    (:func:`nadir_in`), at least ``min_pings`` long, as lines (a line that leaves and
    re-enters gives one line per run: ``<name>_<k>``; a line kept whole keeps its name), and
    the number of in-bounds pings left out in runs shorter than ``min_pings``."""
    out, dropped = [], 0
    for line in lines:
        keep = nadir_in(line.position, bounds, margin_m)
        runs = runs_of(keep, min_pings)
        dropped += int(keep.sum()) - sum(r.stop - r.start for r in runs)
        for k, sl in enumerate(runs):
            whole = len(runs) == 1 and sl.start == 0 and sl.stop == line.n_pings
            out.append(line if whole else _ping_slice(line, sl, f"{line.name}_{k}"))
    return out, dropped
