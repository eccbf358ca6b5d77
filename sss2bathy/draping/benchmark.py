"""Draping throughput: rays per second and seconds per 1000 pings, vs raw ray casting.

``python -m sss2bathy.draping.benchmark [--pings 1000] [--bins 512] [--engine auto]``

Builds a seeded rough seabed (hills and boulders, 0.5 m cells) and one straight line,
drapes it while recording every ray the draping casts, then casts exactly those rays
again with the bare intersector (embreex's first-hit call on float32 rays already in
the scene's frame, no bookkeeping) — the limit draping could reach. Prints one JSON
line.
"""

from __future__ import annotations

import argparse
import json
import time
from collections.abc import Callable

import numpy as np

from sss2bathy.draping.config import DrapeConfig
from sss2bathy.draping.drape import drape_line
from sss2bathy.draping.surface import DrapeSurface
from sss2bathy.geometry import attitude_to_rotation
from sss2bathy.survey import BathyGrid, SidescanLine, mask_reason_counts


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


class _Recorder(DrapeSurface):
    """A surface that remembers every ray batch it casts (all casting goes through
    :meth:`DrapeSurface.cast`, also :meth:`DrapeSurface.first_hits`)."""

    def __init__(self, base: DrapeSurface) -> None:
        self.__dict__.update(base.__dict__)
        self.batches: list[tuple[np.ndarray, np.ndarray, int]] = []

    def cast(self, origins, directions, repeat=1, distances=False):  # type: ignore[override]
        self.batches.append((np.array(origins, np.float64), np.array(directions), int(repeat)))
        return super().cast(origins, directions, repeat, distances)


def record_rays(
    line: SidescanLine, surface: DrapeSurface, cfg: DrapeConfig
) -> list[tuple[np.ndarray, np.ndarray, int]]:
    """Drape ``line`` once and return every ray batch ``(origins, directions, repeat)``."""
    rec = _Recorder(surface)
    drape_line(line, rec, cfg)
    return rec.batches


def count_rays(batches: list[tuple[np.ndarray, np.ndarray, int]]) -> int:
    """Number of rays in recorded batches."""
    return sum(len(d) for _, d, _ in batches)


def raw_cast(
    surface: DrapeSurface, batches: list[tuple[np.ndarray, np.ndarray, int]]
) -> Callable[[], None]:
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


def trimesh_cast(
    surface: DrapeSurface, batches: list[tuple[np.ndarray, np.ndarray, int]]
) -> Callable[[], None] | None:
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


def run(n_pings: int = 1000, n_bins: int = 512, engine: str = "auto") -> dict:
    grid = bench_terrain()
    line = bench_line(n_pings, n_bins)
    t0 = time.perf_counter()
    surface = DrapeSurface.from_grid(grid, engine=engine)
    surface.first_hits(line.position[:1], np.array([[0.0, 0.0, -1.0]]))  # builds the BVH
    t_build = time.perf_counter() - t0
    cfg = DrapeConfig(engine=engine)
    t0 = time.perf_counter()
    draped = drape_line(line, surface, cfg)
    t_drape = time.perf_counter() - t0
    batches = record_rays(line, surface, cfg)
    n_rays = count_rays(batches)
    raw = raw_cast(surface, batches)
    t0 = time.perf_counter()
    raw()
    t_raw = time.perf_counter() - t0
    return {
        "engine": surface.engine,
        "pings": n_pings,
        "bins": n_bins,
        "faces": int(len(surface.mesh.faces)),
        "surface_build_s": round(t_build, 3),
        "rays": n_rays,
        "rays_per_ping_head": round(n_rays / (2 * n_pings), 1),
        "drape_s": round(t_drape, 3),
        "drape_rays_per_s": round(n_rays / t_drape),
        "drape_s_per_1000_pings": round(1000 * t_drape / n_pings, 3),
        "raw_cast_s": round(t_raw, 3),
        "raw_rays_per_s": round(n_rays / t_raw),
        "drape_over_raw_time": round(t_drape / t_raw, 2),
        "mask": mask_reason_counts(draped.mask),
    }


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--pings", type=int, default=1000)
    parser.add_argument("--bins", type=int, default=512)
    parser.add_argument("--engine", default="auto")
    args = parser.parse_args(argv)
    print(json.dumps(run(args.pings, args.bins, args.engine)))


if __name__ == "__main__":
    main()
