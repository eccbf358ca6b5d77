"""The surface bins are draped onto: a triangle mesh, its ray intersector and its normals."""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Any

import numpy as np

from sss2bathy.survey import BathyGrid

log = logging.getLogger(__name__)


def _make_intersector(mesh: Any, engine: str) -> tuple[Any, str]:
    """``(intersector, engine name)``: embreex through trimesh, else trimesh's own."""
    if engine in ("auto", "embree"):
        try:
            from trimesh.ray.ray_pyembree import RayMeshIntersector

            return RayMeshIntersector(mesh), "embree"
        except ImportError as exc:
            if engine == "embree":
                raise ImportError(
                    f"drape.engine='embree' needs the embreex package ({exc})"
                ) from exc
            log.warning(
                "embreex is not available (%s); draping with trimesh's ray_triangle "
                "intersector, which is much slower",
                exc,
            )
    try:
        import rtree  # noqa: F401  (trimesh's ray_triangle needs it)
    except ImportError as exc:
        raise ImportError(
            "no ray intersector: install embreex (fast) or rtree (for trimesh's ray_triangle)"
        ) from exc
    from trimesh.ray.ray_triangle import RayMeshIntersector as TriangleIntersector

    return TriangleIntersector(mesh), "triangle"


class DrapeSurface:
    """A triangle mesh prepared for draping.

    Holds the mesh, a first-hit ray intersector, per-face planes (float64, for exact hit
    distances and arc/plane intersections) and, for an MBES grid, the grid's gradient
    fields so normals come from the bilinear gradient at the hit (paper eq. 1).

    Build with :meth:`from_grid`, :meth:`from_mesh` or :meth:`from_file`.
    """

    def __init__(self, mesh: Any, grid: BathyGrid | None = None, engine: str = "auto") -> None:
        import trimesh

        if not isinstance(mesh, trimesh.Trimesh):
            raise ValueError(f"mesh: expected a trimesh.Trimesh, found {type(mesh).__name__}")
        if len(mesh.faces) == 0:
            raise ValueError("mesh: expected at least one triangle, found an empty mesh")
        self.mesh = mesh
        self.grid = grid
        tris = np.asarray(mesh.triangles, dtype=np.float64)
        normals = np.cross(tris[:, 1] - tris[:, 0], tris[:, 2] - tris[:, 0])
        norm = np.linalg.norm(normals, axis=1, keepdims=True)
        # Degenerate faces keep a zero normal: hits on them are treated as misses.
        self.face_normals = np.divide(normals, norm, out=np.zeros_like(normals), where=norm > 0)
        self.face_offsets = np.einsum("fk,fk->f", self.face_normals, tris[:, 0])
        self.intersector, self.engine = _make_intersector(mesh, engine)
        self._grad: tuple[BathyGrid, BathyGrid] | None = None
        if grid is not None:
            gx, gy = grid.gradient()
            self._grad = (
                BathyGrid(gx, grid.x0, grid.y0, grid.cell_size),
                BathyGrid(gy, grid.x0, grid.y0, grid.cell_size),
            )

    @classmethod
    def from_grid(cls, grid: BathyGrid, engine: str = "auto") -> DrapeSurface:
        """Triangulate the grid's valid cells; normals from its bilinear gradient."""
        if not isinstance(grid, BathyGrid):
            raise ValueError(f"grid: expected a BathyGrid, found {type(grid).__name__}")
        mesh = grid.to_mesh()
        if len(mesh.faces) == 0:
            raise ValueError(
                f"grid: expected at least one 2x2 block of valid heights, found none "
                f"({int(np.isfinite(grid.heights).sum())} finite of {grid.heights.size} cells)"
            )
        return cls(mesh, grid=grid, engine=engine)

    @classmethod
    def from_mesh(cls, mesh: Any, engine: str = "auto") -> DrapeSurface:
        """Any trimesh triangle mesh; normals from the hit face (oriented to the sonar)."""
        return cls(mesh, grid=None, engine=engine)

    @classmethod
    def from_file(cls, path: str | Path, engine: str = "auto") -> DrapeSurface:
        """A mesh file trimesh reads (PLY, OBJ, STL, ...), merged into one mesh."""
        import trimesh

        path = Path(path)
        if not path.is_file():
            raise ValueError(f"mesh_path: expected an existing mesh file, found none at {path}")
        try:
            mesh = trimesh.load(path, force="mesh", process=False)
        except Exception as exc:  # trimesh raises many error types for bad files
            raise ValueError(f"mesh_path: could not read {path} as a mesh ({exc})") from exc
        return cls.from_mesh(mesh, engine=engine)

    def first_hits(
        self, origins: np.ndarray, directions: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray]:
        """First hit of each ray.

        Args:
            origins: ``(N, 3)`` ray origins (m, world).
            directions: ``(N, 3)`` unit ray directions.

        Returns:
            ``tri (N,) int64`` face index (-1 = miss) and ``dist (N,) float64`` distance
            along the ray (NaN = miss), computed in float64 from the face's plane.
        """
        if len(origins) == 0:
            return np.zeros(0, np.int64), np.zeros(0, np.float64)
        tri = np.asarray(self.intersector.intersects_first(origins, directions), dtype=np.int64)
        hit = tri >= 0
        dist = np.full(len(tri), np.nan)
        n = self.face_normals[tri[hit]]
        denom = np.einsum("nk,nk->n", n, directions[hit])
        num = self.face_offsets[tri[hit]] - np.einsum("nk,nk->n", n, origins[hit])
        with np.errstate(divide="ignore", invalid="ignore"):
            t = num / denom
        ok = np.isfinite(t) & (t >= 0) & (np.abs(denom) > 1e-12)
        dist[hit] = np.where(ok, t, np.nan)
        tri[hit] = np.where(ok, tri[hit], -1)
        return tri, dist

    def normals_at(self, points: np.ndarray, tri: np.ndarray, sonar: np.ndarray) -> np.ndarray:
        """World normals ``(N, 3)`` at surface points (NaN where unknown).

        A grid surface gives the unnormalised ``[-dz/dx, -dz/dy, 1]`` from the bilinear
        gradient at ``(x, y)`` (eq. 1); a mesh gives the unit normal of face ``tri``
        oriented towards ``sonar`` (the hit face is seen from the sonar).
        """
        if self._grad is not None:
            gx = self._grad[0].sample(points[:, 0], points[:, 1])
            gy = self._grad[1].sample(points[:, 0], points[:, 1])
            return np.stack([-gx, -gy, np.ones_like(gx)], axis=-1)
        n = self.face_normals[tri].copy()
        facing = np.einsum("nk,nk->n", n, sonar - points)
        n[facing < 0] *= -1.0
        n[np.linalg.norm(n, axis=1) == 0] = np.nan
        return n
