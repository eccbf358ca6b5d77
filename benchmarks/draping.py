"""Section ``drape``: draping throughput against casting the same rays with the bare intersector.

Builds a seeded rough seabed (hills and boulders, 0.5 m cells) and one straight line
(:func:`bench_terrain`, :func:`bench_line`), drapes it while recording every ray the
draping casts (:func:`record_rays`), then casts exactly those rays again with the bare
intersector (embreex's first-hit call on float32 rays already in the scene's frame, no
bookkeeping; :func:`raw_cast`) — the limit draping could reach —, through draping's own
cast (:func:`direct_cast`: embree's ``rtcIntersect1`` called from numba, faces and
distances; about the cost of the bare ids-only call) and through trimesh's embree
wrapper (:func:`trimesh_cast`, the previous baseline): rays/s of each and ratios. All of
these on one thread; then draping on a thread pool (``DrapeConfig.threads``, the
benchmark's thread count, by default ``torch.get_num_threads()``) against one-thread
draping (its speed-up) and against the same rays split evenly over the same number of
threads with the bare call and with draping's own cast (:func:`split_cast`), so that
"% of bare embree" compares like with like at every thread count.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import replace
from typing import Any

import numpy as np
import torch

from benchmarks.timing import figure, rates, time_in_turns
from sss2bathy.draping.config import DrapeConfig
from sss2bathy.draping.drape import drape_line
from sss2bathy.draping.surface import DrapeSurface
from sss2bathy.geometry import attitude_to_rotation
from sss2bathy.survey import BathyGrid, SidescanLine

TITLE = "Draping"
RayBatches = list[tuple[np.ndarray, np.ndarray, int]]


def bench_terrain(size_m: float = 300.0, cell: float = 0.5, seed: int = 0) -> BathyGrid:
    """Seeded hills plus boulders, ``size_m`` square, about 20 m deep."""
    rs = np.random.default_rng(seed)
    ax = np.arange(-size_m / 2, size_m / 2 + cell / 2, cell)
    X, Y = np.meshgrid(ax, ax)
    z = -20.0 + 2.0 * np.sin(X / 9.0) * np.cos(Y / 13.0) + 0.02 * X
    for cx, cy, r in zip(
        rs.uniform(-size_m / 2, size_m / 2, 400),
        rs.uniform(-size_m / 2, size_m / 2, 400),
        rs.uniform(0.3, 2.0, 400),
        strict=True,
    ):
        d2 = (X - cx) ** 2 + (Y - cy) ** 2
        z = np.where(d2 < r * r, np.maximum(z, z + np.sqrt(np.maximum(r * r - d2, 0.0))), z)
    return BathyGrid(z, float(ax[0]), float(ax[0]), cell)


def bench_line(n_pings: int, n_bins: int, max_range: float = 50.0) -> SidescanLine:
    """One straight line along North at 8 m depth, ``n_bins`` bins to ``max_range`` (m)."""
    y = np.linspace(-0.4, 0.4, n_pings) * 300.0
    pos = np.stack([np.zeros(n_pings), y, np.full(n_pings, -8.0)], 1)
    att = np.zeros(n_pings)
    return SidescanLine(
        name="bench",
        time_s=np.arange(n_pings) * 0.1,
        position=pos,
        rotation=attitude_to_rotation(att, att + 0.01, att + 0.02),
        altitude_m=np.full(n_pings, np.nan, np.float32),
        intensity=np.zeros((n_pings, 2, n_bins), np.float32),
        range_m=np.linspace(max_range / n_bins, max_range, n_bins),
    )


class RecordingSurface(DrapeSurface):
    """A :class:`DrapeSurface` that remembers every ray batch it casts (all casting goes
    through :meth:`DrapeSurface.cast`, also :meth:`DrapeSurface.first_hits`)."""

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        self.batches: RayBatches = []

    def cast(self, origins, directions, repeat=1, distances=False):  # type: ignore[override]
        self.batches.append((np.array(origins, np.float64), np.array(directions), int(repeat)))
        return super().cast(origins, directions, repeat, distances)


def record_rays(line: SidescanLine, surface: DrapeSurface, cfg: DrapeConfig) -> RayBatches:
    """Drape ``line`` once on a recording copy of ``surface`` (same mesh, grid and engine)
    and return every ray batch ``(origins, directions, repeat)`` it cast, in draping's
    one-thread order (``cfg.threads`` is set to 1 here)."""
    rec = RecordingSurface(surface.mesh, grid=surface.grid, engine=surface.engine)
    drape_line(line, rec, replace(cfg, threads=1))
    return rec.batches


def count_rays(batches: RayBatches) -> int:
    """Number of rays in recorded batches."""
    return sum(len(d) for _, d, _ in batches)


def raw_cast(surface: DrapeSurface, batches: RayBatches) -> Callable[[], None]:
    """A function casting the recorded rays with the bare intersector, nothing else.

    Embree: the scene's first-hit call on float32 origins and directions already in
    its frame (prepared here, outside the timing); the triangle fallback: trimesh's
    ``intersects_first``.
    """
    scene = surface.intersector
    if surface.engine == "embree":
        ready = [
            (np.repeat(scene.origins(o), r, axis=0), np.ascontiguousarray(d, np.float32))
            for o, d, r in batches
        ]

        def cast() -> None:
            for o32, d32 in ready:
                scene.run(o32, d32)

        return cast
    world = [(np.repeat(o, r, axis=0), np.asarray(d, np.float64)) for o, d, r in batches]

    def cast_triangle() -> None:
        for o, d in world:
            scene.intersects_first(o, d)

    return cast_triangle


def direct_cast(surface: DrapeSurface, batches: RayBatches) -> Callable[[], None] | None:
    """The recorded rays through draping's own cast: embree's ``rtcIntersect1`` called from
    compiled code on embreex's scene, faces and distances (rays prepared outside the
    timing, as for :func:`raw_cast`); ``None`` where draping does not use it."""
    scene = surface.intersector
    if surface.engine != "embree":
        return None
    ready = [(scene.origins(o), np.ascontiguousarray(d, np.float32), r) for o, d, r in batches]
    if scene.first_hits_direct(*ready[0]) is None:
        return None

    def cast() -> None:
        for o32, d32, r in ready:
            scene.first_hits_direct(o32, d32, r)

    return cast


def split_cast(
    surface: DrapeSurface, batches: RayBatches, threads: int, direct: bool = False
) -> tuple[Callable[[], None], Callable[[], None]] | None:
    """``(cast, close)``: the recorded rays cast on ``threads`` threads at once, split into
    ``threads`` contiguous runs of equal length (the best balance draping's chunks could
    have), with the bare first-hit call (embreex's ids-only call) or, with ``direct``,
    draping's own cast (``rtcIntersect1`` from numba, faces and distances). Rays are
    prepared and the pool started outside the timing; ``close`` stops the pool. ``None``
    without embree, or without the direct call where ``direct`` asks for it. Both calls
    run without the GIL and embree's queries on a committed scene are thread-safe."""
    scene = surface.intersector
    if surface.engine != "embree":
        return None
    surface.prepare_threads()
    o32 = np.concatenate([np.repeat(scene.origins(o), r, axis=0) for o, _, r in batches])
    d32 = np.concatenate([np.ascontiguousarray(d, np.float32) for _, d, _ in batches])
    edges = np.linspace(0, len(d32), int(threads) + 1).astype(int)
    parts = [(o32[a:b], d32[a:b]) for a, b in zip(edges[:-1], edges[1:], strict=True)]
    if direct:
        if scene.first_hits_direct(parts[0][0][:1], parts[0][1][:1], 1) is None:
            return None

        def one(part: tuple[np.ndarray, np.ndarray]) -> Any:
            return scene.first_hits_direct(part[0], part[1], 1)

    else:

        def one(part: tuple[np.ndarray, np.ndarray]) -> Any:
            return scene.run(part[0], part[1])

    pool = ThreadPoolExecutor(int(threads), thread_name_prefix="bench-cast")

    def cast() -> None:
        for _ in pool.map(one, parts):
            pass

    return cast, pool.shutdown


def trimesh_cast(surface: DrapeSurface, batches: RayBatches) -> Callable[[], None] | None:
    """The recorded rays through trimesh's embree wrapper (``intersects_first``, float64
    world inputs; it converts, normalises and scales per call); ``None`` without embree."""
    if surface.engine != "embree":
        return None
    from trimesh.ray.ray_pyembree import RayMeshIntersector

    wrapper = RayMeshIntersector(surface.mesh)
    world = [(np.repeat(o, r, axis=0), np.asarray(d, np.float64)) for o, d, r in batches]
    wrapper.intersects_first(world[0][0][:1], world[0][1][:1])  # builds its BVH

    def cast() -> None:
        for o, d in world:
            wrapper.intersects_first(o, d)

    return cast


def bench_drape(
    *,
    n_pings: int = 1000,
    n_bins: int = 512,
    size_m: float = 300.0,
    cell_m: float = 0.5,
    engine: str = "auto",
    warmup: int = 1,
    repeats: int = 3,
    threads: int | None = None,
) -> dict:
    """Draping rays/s against casting the same rays with the bare intersector.

    "Raw" is embreex's first-hit call on the recorded rays, already float32 in the scene's
    frame (no conversion, no bookkeeping), one thread like the one-thread draping;
    trimesh's embree wrapper (``intersects_first``, the previous baseline, which converts
    and normalises per call) is reported too. With ``threads`` > 1 (default
    ``torch.get_num_threads()``) also draping with ``DrapeConfig(threads=threads)``, its
    speed-up over one thread, and the same rays split over as many threads, bare and
    through draping's own cast (:func:`split_cast`). All variants run interleaved (in
    turns); ratios are per repeat.
    """
    n_threads = int(threads) if threads is not None else torch.get_num_threads()
    if n_threads < 1:
        raise ValueError(f"threads: expected >= 1, found {threads!r}")
    grid = bench_terrain(size_m=size_m, cell=cell_m)
    line = bench_line(int(n_pings), int(n_bins))
    t0 = time.perf_counter()
    surface = DrapeSurface.from_grid(grid, engine=engine)
    surface.first_hits(line.position[:1], np.array([[0.0, 0.0, -1.0]]))  # builds the BVH
    t_build = time.perf_counter() - t0
    cfg = DrapeConfig(engine=engine, threads=1)
    cfg_mt = DrapeConfig(engine=engine, threads=n_threads)
    batches = record_rays(line, surface, cfg)
    n_rays = count_rays(batches)
    fns: dict[str, Callable[[], Any]] = {
        "drape": lambda: drape_line(line, surface, cfg),
        "raw": raw_cast(surface, batches),
    }
    direct = direct_cast(surface, batches)
    if direct is not None:
        fns["direct"] = direct
    wrapped = trimesh_cast(surface, batches)
    if wrapped is not None:
        fns["trimesh"] = wrapped
    closers: list[Callable[[], None]] = []
    if n_threads > 1:
        fns["drape_mt"] = lambda: drape_line(line, surface, cfg_mt)
        for key, use_direct in (("raw_mt", False), ("direct_mt", True)):
            split = split_cast(surface, batches, n_threads, direct=use_direct)
            if split is not None:
                fns[key], close = split
                closers.append(close)
    try:
        times, _ = time_in_turns(fns, dict.fromkeys(fns, repeats), warmup, torch.device("cpu"))
    finally:
        for close in closers:
            close()
    t_drape, t_raw = times["drape"], times["raw"]
    figures = [
        figure("draping rays/s", "rays/s", rates(n_rays, t_drape)),
        figure(
            "raw embree rays/s",
            "rays/s",
            rates(n_rays, t_raw),
            "same rays, bare first-hit call, 1 thread",
        ),
        figure(
            "draping / raw throughput",
            "%",
            [100 * r / d for r, d in zip(t_raw, t_drape, strict=True)],
            "target >= 80 % (issue #20)",
        ),
    ]
    if "direct" in times:
        t_direct = times["direct"]
        figures += [
            figure(
                "direct embree rays/s",
                "rays/s",
                rates(n_rays, t_direct),
                "same rays, draping's own cast (rtcIntersect1 from numba; faces and distances)",
            ),
            figure(
                "draping / direct embree",
                "%",
                [100 * c / d for c, d in zip(t_direct, t_drape, strict=True)],
            ),
        ]
    if "trimesh" in times:
        t_wrap = times["trimesh"]
        figures += [
            figure(
                "trimesh intersects_first rays/s",
                "rays/s",
                rates(n_rays, t_wrap),
                "same rays via trimesh's embree wrapper (previous baseline)",
            ),
            figure(
                "draping / trimesh intersects_first",
                "%",
                [100 * w / d for w, d in zip(t_wrap, t_drape, strict=True)],
            ),
        ]
    figures.append(
        figure("draping time per 1000 pings", "s", [1000 * t / n_pings for t in t_drape])
    )
    if "drape_mt" in times:
        figures += _thread_figures(times, n_threads, n_rays, n_pings)
    return {
        "title": TITLE,
        "params": {
            "engine": surface.engine,
            "n_pings": int(n_pings),
            "n_bins": int(n_bins),
            "faces": int(len(surface.mesh.faces)),
            "rays": int(n_rays),
            "pings_per_chunk": int(cfg.pings_per_chunk),
            "threads": n_threads,
        },
        "figures": figures,
        "info": {"surface_build_s": round(t_build, 3)},
        "notes": (
            f"drape_line of a {n_pings}-ping line ({n_bins} bins per side) on the draping "
            f"benchmark's {size_m:g} m seabed ({len(surface.mesh.faces)} faces, "
            f"{surface.engine}), {n_rays / (2 * n_pings):.0f} rays per ping and head; "
            f"one thread, and {n_threads} threads where > 1 (draping's chunks on a pool, "
            "the bare casts' rays split evenly); every variant interleaved."
        ),
    }


def _thread_figures(
    times: dict[str, list[float]], n_threads: int, n_rays: int, n_pings: int
) -> list[dict]:
    """The figures of draping on ``n_threads`` threads (``times["drape_mt"]``): rays/s,
    speed-up over one thread, and ratios to the bare and direct casts split over as many
    threads."""
    t_mt, t_one = times["drape_mt"], times["drape"]
    tag = f"{n_threads} threads"
    figures = [
        figure(f"draping rays/s, {tag}", "rays/s", rates(n_rays, t_mt)),
        figure(
            f"draping speed-up, {tag} / 1 thread",
            "x",
            [a / b for a, b in zip(t_one, t_mt, strict=True)],
            "DrapeConfig.threads; same bits as one thread",
        ),
        figure(f"draping time per 1000 pings, {tag}", "s", [1000 * t / n_pings for t in t_mt]),
    ]
    for key, label, note in (
        ("raw_mt", "raw embree", "same rays split evenly, bare first-hit call on each thread"),
        ("direct_mt", "direct embree", "same rays split evenly, draping's own cast"),
    ):
        if key not in times:
            continue
        t_cast = times[key]
        figures += [
            figure(f"{label} rays/s, {tag}", "rays/s", rates(n_rays, t_cast), note),
            figure(
                f"{label} speed-up, {tag} / 1 thread",
                "x",
                [a / b for a, b in zip(times[key.removesuffix("_mt")], t_cast, strict=True)],
            ),
            figure(
                f"draping / {label}, {tag}",
                "%",
                [100 * c / d for c, d in zip(t_cast, t_mt, strict=True)],
                "target >= 80 % (issue #20) at this thread count" if key == "raw_mt" else "",
            ),
        ]
    return figures
