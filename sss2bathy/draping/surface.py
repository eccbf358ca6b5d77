"""The surface bins are draped onto: a triangle mesh, its ray intersector and its normals."""

from __future__ import annotations

import ctypes
import gc
import logging
import os
import platform
import sys
import threading
from pathlib import Path
from typing import Any

import numpy as np

from sss2bathy.survey import BathyGrid

log = logging.getLogger(__name__)

# Cast rays that need distances with embree's rtcIntersect1 called from a compiled loop
# (:func:`sss2bathy.draping.kernels.embree_first_hits`) on embreex's own scene, where its
# handle can be found and checked (:func:`_embree_scene_pointer`); else through
# embreex's full-output call. Same faces and distances to the bit, at the cost of
# embreex's ids-only call (no per-call arrays of u, v, normals and geometry ids).
DIRECT_EMBREE = True


class _EmbreeScene:
    """An embreex scene of the mesh in a shifted and scaled float32 frame.

    Embree works in float32: vertices and ray origins are shifted by the mesh's lower
    bounding-box corner and scaled to a box of about 100 units (as trimesh does), so
    survey-sized coordinates keep their precision. Built here rather than through
    trimesh's wrapper, which converts, normalises and rescales every ray batch in float64
    on each call; callers pass float32 rays and get face indices (and, on request,
    embree's float32 hit distances).
    """

    def __init__(self, mesh: Any) -> None:
        from embreex import rtcore_scene
        from embreex.mesh_construction import TriangleMesh

        verts = np.asarray(mesh.vertices, dtype=np.float64)
        self.origin = verts.min(axis=0)
        extent = float(np.linalg.norm(verts.max(axis=0) - self.origin))
        self.scale = 100.0 / extent if extent > 0 else 1.0
        self.scene = rtcore_scene.EmbreeScene()
        TriangleMesh(
            scene=self.scene,
            vertices=((verts - self.origin) * self.scale).astype(np.float32),
            indices=np.asarray(mesh.faces, dtype=np.int32),
        )
        self._handle: int | None = None  # the RTCScene address, 0 = not available
        self._handle_lock = threading.Lock()

    def prepare(self) -> None:
        """Build the BVH (embreex commits on its first query) and look up the direct
        call's scene handle now, so that threads casting at once only read the scene
        (embree: queries on a committed scene are thread-safe)."""
        if self.scene.is_committed == 0:
            self.scene.run(np.zeros((1, 3), np.float32), np.array([[0.0, 0.0, 1.0]], np.float32))
        if DIRECT_EMBREE:
            self._direct_handle()

    def _direct_handle(self) -> int:
        """The checked ``RTCScene`` address (0 = unusable), looked up once under a lock."""
        if self._handle is None:
            with self._handle_lock:
                if self._handle is None:
                    self._handle = _embree_scene_pointer(self)
        return self._handle

    def origins(self, origins: np.ndarray) -> np.ndarray:
        """``(N, 3)`` float32 ray origins in the scene's frame from world ``(N, 3)``."""
        return ((np.asarray(origins, dtype=np.float64) - self.origin) * self.scale).astype(
            np.float32
        )

    def run(self, origins32: np.ndarray, directions32: np.ndarray, distances: bool = False) -> Any:
        """First-hit face index ``(N,) int32`` (-1 = miss) of rays already in the frame.

        With ``distances``: also the float32 hit distance in world units of the direction's
        length (NaN = miss), from embree's ``tfar`` (float32 scene precision).
        """
        if not distances:
            return self.scene.run(origins32, directions32)
        res = self.scene.run(origins32, directions32, output=1)
        tri = res["primID"]
        dist = res["tfar"]
        dist *= np.float32(1.0 / self.scale)
        dist[tri < 0] = np.nan
        return tri, dist

    def first_hits_direct(
        self, origins32: np.ndarray, directions32: np.ndarray, repeat: int
    ) -> tuple[np.ndarray, np.ndarray] | None:
        """:meth:`run` with ``distances`` of rays ``directions32 (K * repeat, 3)`` from
        ``origins32 (K, 3)`` (not repeated), both float32 in the frame, by the compiled
        ``rtcIntersect1`` loop; ``None`` where that is off or unavailable."""
        if not DIRECT_EMBREE:
            return None
        handle = self._direct_handle()
        if not handle:
            return None
        from sss2bathy.draping import kernels

        n = len(directions32)
        tri, dist = np.empty(n, np.int32), np.empty(n, np.float32)
        kernels.embree_first_hits(
            handle,
            origins32,
            int(repeat),
            directions32,
            np.float32(1.0 / self.scale),
            tri,
            dist,
        )
        return tri, dist


def _embree_scene_pointer(scene: _EmbreeScene) -> int:
    """The ``RTCScene`` address inside embreex's ``EmbreeScene``, checked; 0 if unusable.

    embreex keeps it in a private C field (after the object header: the scene, the
    ``is_committed`` flag, the device object). Used only when the object has that size,
    the flag and device object sit where expected, embree reports that device for the
    scene, and a test fan of rays gives embreex's own faces and distances to the bit.
    Also makes the embree library embreex loaded visible to numba's compiled code.
    """
    try:
        import llvmlite.binding as llvm

        from sss2bathy.draping import kernels  # noqa: F401  (numba)
    except ImportError:
        return 0
    es = scene.scene
    try:
        if es.is_committed == 0:  # embreex builds the BVH on its first query
            es.run(np.zeros((1, 3), np.float32), np.array([[0.0, 0.0, 1.0]], np.float32))
        word = ctypes.sizeof(ctypes.c_void_p)
        devices = [r for r in gc.get_referents(es) if type(r).__name__ == "EmbreeDevice"]
        base = id(es)
        if not (
            sys.implementation.name == "cpython"
            and word == 8
            # the kernel passes pointers as 64-bit integers: same registers on these
            and platform.machine().lower() in ("x86_64", "amd64", "aarch64", "arm64")
            and type(es).__basicsize__ == 40
            and len(devices) == 1
            and type(devices[0]).__basicsize__ == 24
            and es.is_committed == 1
            and ctypes.c_int.from_address(base + 24).value == 1
            and ctypes.c_void_p.from_address(base + 32).value == id(devices[0])
        ):
            return 0
        handle = ctypes.c_void_p.from_address(base + 16).value or 0
        device = ctypes.c_void_p.from_address(id(devices[0]) + 16).value
        path = _loaded_library("libembree4")
        if not handle or not device or path is None:
            return 0
        lib = ctypes.CDLL(path, mode=os.RTLD_NOLOAD | os.RTLD_NOW)  # the loaded one only
        lib.rtcGetSceneDevice.restype = ctypes.c_void_p
        lib.rtcGetSceneDevice.argtypes = [ctypes.c_void_p]
        lib.rtcReleaseDevice.argtypes = [ctypes.c_void_p]
        got = lib.rtcGetSceneDevice(handle)
        if got:
            lib.rtcReleaseDevice(got)  # rtcGetSceneDevice took a reference
        if got != device:
            return 0
        llvm.load_library_permanently(path)
        if not _direct_agrees(scene, handle):
            log.warning("draping: embree's direct first-hit call disagrees with embreex; unused")
            return 0
    except (OSError, AttributeError, ValueError, TypeError) as exc:
        log.info("draping: embree's direct first-hit call unavailable (%s)", exc)
        return 0
    return int(handle)


def _loaded_library(stem: str) -> str | None:
    """Path of an already loaded shared library whose file name starts with ``stem``."""
    try:
        with open("/proc/self/maps") as f:
            paths = {line.split()[-1] for line in f if stem in line}
    except OSError:
        return None
    paths = {p for p in paths if os.path.basename(p).startswith(stem)}
    return paths.pop() if len(paths) == 1 else None


def _direct_agrees(scene: _EmbreeScene, handle: int) -> bool:
    """Whether a fan of test rays down through the scene's box gives embreex's faces and
    distances to the bit with the compiled loop."""
    from sss2bathy.draping import kernels

    lo, hi = np.zeros(3), np.full(3, 100.0)  # the scene's frame spans about [0, 100]
    rs = np.random.default_rng(0)
    o = np.column_stack(
        [rs.uniform(lo[0], hi[0], 64), rs.uniform(lo[1], hi[1], 64), np.full(64, 150.0)]
    ).astype(np.float32)
    d = np.column_stack([rs.normal(0, 0.3, 64), rs.normal(0, 0.3, 64), -np.ones(64)]).astype(
        np.float32
    )
    want_tri, want = scene.run(o, d, distances=True)
    tri, dist = np.empty(64, np.int32), np.empty(64, np.float32)
    kernels.embree_first_hits(handle, o, 1, d, np.float32(1.0 / scene.scale), tri, dist)
    return bool(
        np.array_equal(tri, want_tri) and np.array_equal(dist.view(np.int32), want.view(np.int32))
    )


def _make_intersector(mesh: Any, engine: str) -> tuple[Any, str]:
    """``(intersector, engine name)``: an embreex scene, or trimesh's ``ray_triangle``
    intersector (``engine="triangle"``, much slower; a reference)."""
    if engine in ("auto", "embree"):
        return _EmbreeScene(mesh), "embree"
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
        # (F + 1, 4) planes [n, offset]; the last row is NaN so index -1 (a miss) gives NaN.
        self.face_planes = np.concatenate(
            [
                np.concatenate([self.face_normals, self.face_offsets[:, None]], axis=1),
                np.full((1, 4), np.nan),
            ]
        )
        self.intersector, self.engine = _make_intersector(mesh, engine)
        # For an MBES grid: dz/dx and dz/dy stacked (ny, nx, 2), float32 like BathyGrid.
        self._grad: np.ndarray | None = None
        if grid is not None:
            gx, gy = grid.gradient()
            self._grad = np.ascontiguousarray(np.stack([gx, gy], axis=-1), dtype=np.float32)

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

    def prepare_threads(self) -> None:
        """Make the intersector ready for :meth:`cast` from several threads at once (the
        embree scene committed, the direct call's handle found; casts then only read)."""
        if isinstance(self.intersector, _EmbreeScene):
            self.intersector.prepare()

    def cast(
        self,
        origins: np.ndarray,
        directions: np.ndarray,
        repeat: int = 1,
        distances: bool = False,
    ) -> Any:
        """First face each ray hits: the bare intersector call (embree in float32).

        Args:
            origins: ``(K, 3)`` ray origins (m, world, float64).
            directions: ``(K * repeat, 3)`` ray directions (float32 is passed to embree as
                is); rays ``k * repeat ... (k + 1) * repeat - 1`` start at ``origins[k]``.
            repeat: rays per origin (a fan of rays from one point).
            distances: also return the hit distances.

        Returns:
            ``(K * repeat,)`` face index, -1 where the ray misses; with ``distances`` also
            the distance to the hit in units of the direction's length (m for unit
            directions; NaN = miss), by embree's ``rtcIntersect1`` from compiled code
            where available (``DIRECT_EMBREE``), else embreex's full-output call (same
            bits). Embree's distances are float32 and carry the scene's
            float32 precision (about 1e-7 of the mesh extent): exact hits come from
            :meth:`first_hits` or from the face planes.
        """
        origins = np.asarray(origins, dtype=np.float64)
        if len(directions) != len(origins) * repeat:
            raise ValueError(
                f"directions: expected {len(origins) * repeat} rays "
                f"({len(origins)} origins x repeat {repeat}), found {len(directions)}"
            )
        if len(directions) == 0:
            tri = np.zeros(0, np.int64)
            return (tri, np.zeros(0, np.float32)) if distances else tri
        if isinstance(self.intersector, _EmbreeScene):
            o32 = self.intersector.origins(origins)
            if distances:
                d32 = np.ascontiguousarray(directions, dtype=np.float32)
                direct = self.intersector.first_hits_direct(o32, d32, repeat)
                if direct is not None:
                    return direct
            if repeat > 1:
                o32 = np.repeat(o32, repeat, axis=0)
            d32 = np.ascontiguousarray(directions, dtype=np.float32)
            return self.intersector.run(o32, d32, distances)
        if repeat > 1:
            origins = np.repeat(origins, repeat, axis=0)
        directions = np.asarray(directions, np.float64)
        tri = np.asarray(self.intersector.intersects_first(origins, directions), np.int64)
        if not distances:
            return tri
        return tri, self._plane_distances(tri, origins, directions)

    def _plane_distances(
        self, tri: np.ndarray, origins: np.ndarray, directions: np.ndarray
    ) -> np.ndarray:
        """Float64 distance along each ray to the plane of its face ``tri`` (NaN = miss).

        Updates ``tri`` in place to -1 where the distance is not usable (ray parallel
        to the face, face behind the origin, degenerate face).
        """
        plane = np.take(self.face_planes, tri, axis=0)  # tri -1 -> the NaN row
        denom = np.einsum("nk,nk->n", plane[:, :3], directions)
        num = plane[:, 3] - np.einsum("nk,nk->n", plane[:, :3], origins)
        dist = np.full(len(tri), np.nan)
        with np.errstate(invalid="ignore"):
            np.divide(num, denom, out=dist, where=np.abs(denom) > 1e-12)
            dist[dist < 0] = np.nan
        tri[np.isnan(dist)] = -1
        return dist

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
        origins = np.asarray(origins, dtype=np.float64)
        directions = np.asarray(directions, dtype=np.float64)
        if len(origins) == 0:
            return np.zeros(0, np.int64), np.zeros(0, np.float64)
        tri = np.asarray(self.cast(origins, directions), dtype=np.int64)
        dist = self._plane_distances(tri, origins, directions)
        return tri, dist

    def grid_gradient_at(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        """``(N, 2)`` bilinear ``(dz/dx, dz/dy)`` of the grid at world ``(x, y)``.

        ``BathyGrid.sample`` of each gradient field (to rounding; NaN outside the grid),
        with one index and weight computation for both. Grid surfaces only.
        """
        if self._grad is None or self.grid is None:
            raise ValueError("surface: expected a surface built from a BathyGrid, found a mesh")
        g, grid = self._grad, self.grid
        fx = (np.asarray(x, dtype=np.float64) - grid.x0) / grid.cell_size
        fy = (np.asarray(y, dtype=np.float64) - grid.y0) / grid.cell_size
        ny, nx = g.shape[:2]
        inside = (fx >= 0) & (fx <= nx - 1) & (fy >= 0) & (fy <= ny - 1)
        with np.errstate(invalid="ignore"):
            cx = np.clip(np.floor(fx), 0, nx - 2)
            cy = np.clip(np.floor(fy), 0, ny - 2)
        cx[~inside], cy[~inside] = 0.0, 0.0  # NaN coordinates
        tx, ty = (fx - cx)[:, None], (fy - cy)[:, None]
        i00 = cy.astype(np.int64) * nx + cx.astype(np.int64)
        corners = np.stack([i00, i00 + 1, i00 + nx, i00 + nx + 1])  # (4, N)
        flat = g.reshape(-1, 2).view(np.int64).reshape(-1)  # (dz/dx, dz/dy) as one item
        h = np.take(flat, corners).view(np.float32).reshape(4, -1, 2).astype(np.float64)
        z = h[1] - h[0]
        z *= tx
        z += h[0]  # along x on the lower row ...
        upper = h[3] - h[2]
        upper *= tx
        upper += h[2]  # ... and the upper row
        upper -= z
        upper *= ty
        z += upper
        z[~inside] = np.nan
        return z

    def normals_at(self, points: np.ndarray, tri: np.ndarray, sonar: np.ndarray) -> np.ndarray:
        """World normals ``(N, 3)`` at surface points (NaN where unknown).

        A grid surface gives the unnormalised ``[-dz/dx, -dz/dy, 1]`` from the bilinear
        gradient at ``(x, y)`` (eq. 1); a mesh gives the unit normal of face ``tri``
        oriented towards ``sonar`` (the hit face is seen from the sonar).
        """
        if self._grad is not None:
            g = self.grid_gradient_at(points[:, 0], points[:, 1])
            return np.stack([-g[:, 0], -g[:, 1], np.ones(len(g))], axis=-1)
        n = self.face_normals[tri].copy()
        facing = np.einsum("nk,nk->n", n, sonar - points)
        n[facing < 0] *= -1.0
        n[np.linalg.norm(n, axis=1) == 0] = np.nan
        return n
