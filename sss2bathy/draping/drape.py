"""Georeferencing of sidescan bins on a surface by ray casting in each head's plane.

For every ping and head a fan of rays is cast in the head's plane (directions
``R [0, sigma cos theta, -sin theta]``, the isotemporal-arc directions of paper eq. 10),
one first-hit query for all rays of a chunk of pings. Along the fan the first-hit range
``rho(theta)`` describes the seabed as the sonar sees it. Bin ``i`` (slant range ``r_i``)
is matched where ``rho`` crosses ``r_i`` between two neighbouring rays, and its hit is
then made exact by intersecting the range arc with the plane of a bracketing ray's hit
face (in float64, in closed form), so hit points on a piecewise-planar surface are exact
to rounding. Fan angles and first-hit ranges only choose rays and brackets, so they are
float32 (the ranges are embree's own hit distances).

Bins without a crossing are classified: ``r_i`` below the nearest first hit of the fan ->
WATER_COLUMN; inside the range gap of an occlusion (a jump of ``rho`` between two rays,
confirmed by a ray cast between them) -> SHADOW; otherwise -> NO_HIT (the fan left the
mesh, or a no-data hole). A crossing outside the vertical beam gives OUT_OF_BEAM (point
and normal kept). Where several crossings share a bin (layover), the in-beam one with the
largest angular extent per metre of range (the strongest echo) wins.

The only Python loop is over ping chunks, whose size (``pings_per_chunk``) trades speed
against memory and does not change results. The chunks run on a thread pool of
``cfg.threads`` threads (``auto``: the usable cores, at most 4 and at most torch's
thread count): each chunk reads the line, the fan and the surface and writes only its
own pings of the outputs, the compiled kernels are ``nogil`` and embree's queries on the
committed scene are thread-safe (:meth:`DrapeSurface.prepare_threads` commits it and
finds the direct call's handle before the threads start; embreex's own call also runs
without the GIL), so the result is the same bits for any thread count. ~93 % of a
chunk's time is in GIL-free kernels; on two cores two threads drape the benchmark line
1.8x faster than one (the same rays split over two threads with the bare call: 1.86x).
Per chunk the fans are built (float32 steps in a numba kernel, numpy's ``arccos``,
``cos``, ``sin``, sort and matmul) and cast with embree: ``rtcIntersect1`` called from a
compiled loop on embreex's own scene (faces and hit distances at the cost of embreex's
ids-only call; embreex's full-output call where that scene handle cannot be found,
:data:`sss2bathy.draping.surface.DIRECT_EMBREE`). The bookkeeping after the cast
(brackets, occlusion checks, exact roots, layover, normals, grazing angles, masks) runs
in compiled numba kernels (:mod:`sss2bathy.draping.kernels`, ``BOOKKEEPING = "numba"``,
one loop over fans, pairs and bins) that give the same bits as the vectorised numpy
version kept as their reference (``BOOKKEEPING = "numpy"``, also the fallback without
numba). On the draping benchmark (one core, 1000 pings) embree takes ~79 % of draping's
time (~0.72 s); of the rest about 55 % is :func:`~sss2bathy.draping.kernels.drape_fans`
(~0.11 s: root finding per bin, then per matched bin the gradient, ``hypot`` and
``acos``) and the remainder numpy's fan set-up (``cos``/``sin``, sort, ``arccos``, the
direction matmul; ~0.04 s), the occlusion checks (~0.01 s) and
:meth:`DrapedLine.validate` (a compiled pass, ~3 ms)."""

from __future__ import annotations

import logging
import math
from concurrent.futures import ThreadPoolExecutor
from typing import Any

import numpy as np

from sss2bathy.draping.config import DrapeConfig
from sss2bathy.draping.draped import DrapedLine
from sss2bathy.draping.surface import DrapeSurface
from sss2bathy.geometry import arc_basis, head_plane_unit
from sss2bathy.survey import (
    MASK_NO_HIT,
    MASK_OUT_OF_BEAM,
    MASK_SHADOW,
    MASK_WATER_COLUMN,
    BathyGrid,
    SensorParams,
    SidescanLine,
    mask_reason_counts,
)

log = logging.getLogger(__name__)

_SIDES = np.array([0, 1])

# Bump when draping's numbers change (part of the draping cache key). 2: fan angles and
# first-hit ranges in float32 (exact hits still from the face planes), one fan size per
# line (results independent of pings_per_chunk).
DRAPE_ALGORITHM_VERSION = 2

# The bookkeeping after the fans' cast: "numba" (compiled kernels, :mod:`.kernels`; the
# default where numba imports) or "numpy" (the vectorised reference, same results).
BOOKKEEPING = "numba"
_numba_ok: bool | None = None


def _use_numba() -> bool:
    """Whether to run the compiled bookkeeping (``BOOKKEEPING``, and numba importable)."""
    global _numba_ok
    if BOOKKEEPING == "numpy":
        return False
    if BOOKKEEPING != "numba":
        raise ValueError(f"BOOKKEEPING: expected 'numba' or 'numpy', found {BOOKKEEPING!r}")
    if _numba_ok is None:
        try:
            from sss2bathy.draping import kernels  # noqa: F401
        except ImportError as exc:  # numba missing or broken: the numpy reference
            log.warning("draping without numba (%s): numpy bookkeeping, slower", exc)
            _numba_ok = False
        else:
            _numba_ok = True
    return _numba_ok


def as_surface(surface: Any, engine: str = "auto") -> DrapeSurface:
    """A :class:`DrapeSurface` from a ``BathyGrid``, a ``trimesh.Trimesh`` or itself."""
    if isinstance(surface, DrapeSurface):
        return surface
    if isinstance(surface, BathyGrid):
        return DrapeSurface.from_grid(surface, engine=engine)
    import trimesh

    if isinstance(surface, trimesh.Trimesh):
        return DrapeSurface.from_mesh(surface, engine=engine)
    raise ValueError(
        "surface: expected a BathyGrid, a trimesh.Trimesh or a DrapeSurface, "
        f"found {type(surface).__name__}"
    )


def drape_line(line: SidescanLine, surface: Any, cfg: DrapeConfig | Any = None) -> DrapedLine:
    """Georeference every bin of ``line`` on ``surface``.

    Args:
        line: the sidescan line (positions, rotations and slant ranges are used).
        surface: a ``BathyGrid`` (normals from its bilinear gradient at the hit, eq. 1-3),
            a ``trimesh.Trimesh`` (normals from the hit face) or a prepared
            :class:`DrapeSurface` (reuse one across lines).
        cfg: :class:`DrapeConfig`, a plain mapping of its fields, or ``None``.

    Returns:
        The :class:`DrapedLine` with ``(P, 2, B)`` arrays. The result does not depend on
        ``cfg.pings_per_chunk`` or ``cfg.threads`` (chunks of pings draped on that many
        threads at once; one with the ``triangle`` engine).
    """
    if not isinstance(line, SidescanLine):
        raise ValueError(f"line: expected a SidescanLine, found {type(line).__name__}")
    cfg = DrapeConfig.coerce(cfg)
    surf = as_surface(surface, cfg.engine)
    P, B = line.n_pings, line.n_bins
    range_m = line.range_m.astype(np.float64)
    bin_step = float(np.median(np.diff(range_m))) if B > 1 else float(range_m[0])
    fan = _Fan(line, surf, range_m, bin_step, cfg)
    bin_index = _BinIndex(range_m)
    points = np.full((P, 2, B, 3), np.nan, np.float32)
    n_lat = np.full((P, 2, B), np.nan, np.float32)
    grazing = np.full((P, 2, B), np.nan, np.float32)
    mask = np.zeros((P, 2, B), np.uint8)
    n_threads = _thread_count(surf, cfg)
    chunks = _chunks(P, cfg.pings_per_chunk, n_threads)

    def drape(sl: slice) -> None:
        out = (points[sl], n_lat[sl], grazing[sl], mask[sl])
        _drape_chunk(surf, fan, sl, range_m, bin_step, bin_index, line.sensor, cfg, out)

    n_threads = min(n_threads, len(chunks))
    if n_threads <= 1:
        for sl in chunks:
            drape(sl)
    else:
        surf.prepare_threads()
        with ThreadPoolExecutor(n_threads, thread_name_prefix="drape") as pool:
            # chunks write disjoint pings of the outputs; result() re-raises an error,
            # after which the chunks not started yet are dropped
            jobs = [pool.submit(drape, sl) for sl in chunks]
            try:
                for job in jobs:
                    job.result()
            except BaseException:
                for job in jobs:
                    job.cancel()
                raise
    if log.isEnabledFor(logging.DEBUG):
        log.debug("draped line '%s': %s", line.name, mask_reason_counts(mask))
    return DrapedLine(points=points, n_lat=n_lat, grazing_rad=grazing, mask=mask)


def _chunks(n_pings: int, pings_per_chunk: int, threads: int) -> list[slice]:
    """Consecutive slices of at most ``pings_per_chunk`` pings covering ``n_pings``: as
    few as that allows, rounded up to a multiple of ``threads`` where there are at least
    that many, their sizes differing by at most one ping, so that threads get equal
    shares (1000 pings at 32: 32 chunks of 31-32 pings, not 31 of 32 and one of 8; on
    two threads a 100-ping line drapes ~7 % faster in 4 chunks of 25 than in 32, 32, 32
    and 4). Results do not depend on the chunks."""
    if n_pings <= 0:
        return []
    n = -(-n_pings // pings_per_chunk)
    if threads > 1 and n >= threads:
        n = -(-n // threads) * threads
    n = min(n, n_pings)
    edges = [(i * n_pings) // n for i in range(n + 1)]
    return [slice(a, b) for a, b in zip(edges[:-1], edges[1:], strict=True)]


def _thread_count(surf: DrapeSurface, cfg: DrapeConfig) -> int:
    """Threads draping a line's chunks: ``cfg.threads``, but one with the ``triangle``
    engine (trimesh's intersector and its caches are not meant for concurrent calls)."""
    return cfg.n_threads() if surf.engine == "embree" else 1


def _reference_altitude(line: SidescanLine, surf: DrapeSurface) -> np.ndarray:
    """``(P,)`` height of the sonar above the surface straight below it (m).

    Only used to space the range-uniform rays; from a world-down ray, else the recorded
    altitude, else the line's median, else the first bin's range.
    """
    down = np.broadcast_to(np.array([0.0, 0.0, -1.0]), line.position.shape)
    _, dist = surf.first_hits(line.position, np.ascontiguousarray(down))
    h = np.where(np.isfinite(dist), dist, line.altitude_m.astype(np.float64))
    if not np.isfinite(h).any():
        h = np.full(line.n_pings, float(line.range_m[0]))
    h = np.where(np.isfinite(h), h, np.nanmedian(h))
    return np.maximum(h, 1e-3)


class _Fan:
    """The fan of ray angles of every ping and head of a line.

    Per ping and head the fan is the sorted union of ``n_uniform`` angles uniform over
    ``[th_lo, th_hi]`` and ``n_range`` angles uniform in the range a flat floor ``h_ref``
    below would give (see :class:`DrapeConfig`). ``n_uniform`` is fixed for the whole
    line so that the result does not depend on how pings are chunked.
    """

    def __init__(
        self,
        line: SidescanLine,
        surf: DrapeSurface,
        range_m: np.ndarray,
        bin_step: float,
        cfg: DrapeConfig,
    ) -> None:
        R = line.rotation.astype(np.float64)
        self.sonar = line.position.astype(np.float64)
        # (P, 2, 3) head-plane axes (eq. 10): u = sigma R e_y (outward), v = -R e_z (down)
        self.u, w = arc_basis(R[:, None], _SIDES)
        self.v = np.ascontiguousarray(-w)
        th_min, th_max = line.sensor.beam_limits_rad
        a, b = self.u[..., 2], self.v[..., 2]  # world z of the two in-plane axes
        self.theta_down = np.arctan2(-b, -a)  # the in-plane direction pointing most downward
        c = np.maximum(np.hypot(a, b), 1e-6)
        self.th_lo = min(th_min, 0.0) - math.radians(cfg.beam_margin_deg)
        self.th_hi = np.maximum(
            th_max + math.radians(cfg.beam_margin_deg),
            self.theta_down + math.radians(cfg.nadir_margin_deg),
        )
        span = float(self.th_hi.max()) - self.th_lo
        self.n_uniform = int(math.ceil(span / math.radians(cfg.fan_step_deg))) + 1
        # Rays uniform in the range a flat floor h_ref below would give:
        # rho = hc / cos(theta_down - theta).
        self.n_range = max(2, int(math.ceil(cfg.rays_per_bin * len(range_m))))
        h_ref = _reference_altitude(line, surf)
        self.hc = h_ref[:, None] / c
        off = np.minimum(self.theta_down - self.th_lo, math.pi / 2 - 1e-6)
        rho_edge = np.where(
            self.theta_down - self.th_lo < math.pi / 2 - 1e-6, self.hc / np.cos(off), np.inf
        )
        self.rho_hi = np.maximum(np.minimum(range_m[-1] + bin_step, rho_edge), self.hc)
        self.n_rays = self.n_uniform + self.n_range
        self._ramps = (
            np.linspace(0.0, 1.0, self.n_uniform, dtype=np.float32),
            np.linspace(0.0, 1.0, self.n_range, dtype=np.float32),
        )

    def angles(self, sl: slice) -> np.ndarray:
        """``(n, 2, M)`` sorted depression angles (rad, float32) of pings ``sl``.

        float32 is plenty for choosing rays (1e-7 rad); every later step uses the angles
        as stored, so the fan is consistent with itself.
        """
        f32 = np.float32
        th_hi, hc = self.th_hi[sl].astype(f32), self.hc[sl].astype(f32)
        theta_down, rho_hi = self.theta_down[sl].astype(f32), self.rho_hi[sl].astype(f32)
        th_lo = f32(self.th_lo)
        out = np.empty((*th_hi.shape, self.n_rays), f32)
        tail = out[..., self.n_uniform :]
        if _use_numba():  # the same float32 steps in one compiled pass
            from sss2bathy.draping import kernels

            kernels.fan_ramps(th_lo, th_hi, hc, rho_hi, *self._ramps, out)
        else:
            np.multiply((th_hi - th_lo)[..., None], self._ramps[0], out=out[..., : self.n_uniform])
            out[..., : self.n_uniform] += th_lo
            np.multiply((rho_hi - hc)[..., None], self._ramps[1], out=tail)
            tail += hc[..., None]  # range-uniform ranges ...
            np.divide(hc[..., None], tail, out=tail)
            np.clip(tail, -1.0, 1.0, out=tail)
        np.arccos(tail, out=tail)
        np.subtract(theta_down[..., None], tail, out=tail)  # ... and their angles
        out.sort(axis=-1)
        return out


class _BinIndex:
    """Bin index of slant ranges: ``k(x)`` = the number of bins with range below ``x``.

    ``searchsorted(range_m, x)``; for uniform bins (deviating from a uniform spacing
    by under 1e-3 of a step, e.g. float32 ranges) by arithmetic, ``ceil((x - r0) /
    step)``, which may count a bin within rounding (or 1e-3 step) of ``x`` on either side.
    Draping only uses ``k`` to bracket bins between rays and the exact angle is solved
    afterwards, with a slack of several percent of a bracket, so either count is right.
    """

    def __init__(self, range_m: np.ndarray) -> None:
        self.range_m = range_m
        B = len(range_m)
        self.uniform = False
        if B > 1:
            self.r0 = float(range_m[0])
            self.step = float(range_m[-1] - range_m[0]) / (B - 1)
            ideal = self.r0 + self.step * np.arange(B)
            self.uniform = self.step > 0 and bool(
                np.max(np.abs(range_m - ideal)) <= 1e-3 * self.step
            )

    def __call__(self, x: np.ndarray) -> np.ndarray:
        """``int32`` counts in ``[0, B]``, same shape as ``x``; 0 where ``x`` is NaN."""
        B = len(self.range_m)
        if not self.uniform:
            k = np.searchsorted(self.range_m, x, side="left")
            k[np.isnan(x)] = 0
            return k.astype(np.int32)
        k = np.subtract(x, x.dtype.type(self.r0))
        k *= x.dtype.type(1.0 / self.step)
        np.ceil(k, out=k)
        np.fmax(k, 0.0, out=k)  # NaN -> 0
        np.fmin(k, float(B), out=k)
        return k.astype(np.int32)


def _drape_chunk(
    surf: DrapeSurface,
    fan: _Fan,
    sl: slice,
    range_m: np.ndarray,
    bin_step: float,
    bin_index: _BinIndex,
    sensor: SensorParams,
    cfg: DrapeConfig,
    out: tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray],
) -> None:
    """Drape pings ``sl`` into ``out`` = views (points ``(n,2,B,3)``, n_lat, grazing, mask).

    ``out`` must arrive NaN-filled (floats) and zero (mask). Fans (ping, head) are
    flattened into one axis of length ``K = 2 n``; rays into a flat axis of ``K M``.
    """
    theta = fan.angles(sl)
    n, M = theta.shape[0], theta.shape[-1]
    K = 2 * n
    theta = theta.reshape(K, M)
    u, v = fan.u[sl].reshape(K, 3), fan.v[sl].reshape(K, 3)
    s = np.repeat(fan.sonar[sl], 2, axis=0)  # (K, 3)

    # --- cast the fans (float32 directions); first-hit ranges from the intersector
    cs = np.empty((K, M, 2), np.float32)
    np.cos(theta, out=cs[..., 0])
    np.sin(theta, out=cs[..., 1])
    dirs = np.matmul(cs, np.stack([u, v], axis=1).astype(np.float32))  # (K, M, 3)
    tri, rho = surf.cast(s, dirs.reshape(-1, 3), repeat=M, distances=True)
    tri, rho = tri.reshape(K, M), rho.reshape(K, M)
    # The ranges (float32) only bracket bins between rays and detect occlusions; each
    # bin's hit is then solved exactly on a face plane, in float64.
    # (the kernels are compiled for embree's float32 ranges and int32 faces; the slow
    # triangle reference engine's float64 plane distances keep the numpy bookkeeping)
    compiled = rho.dtype == np.float32 and tri.dtype == np.int32 and _use_numba()
    post = _post_cast_numba if compiled else _post_cast_numpy
    post(surf, theta, cs, tri, rho, u, v, s, range_m, bin_step, bin_index, sensor, cfg, out)


def _post_cast_numba(
    surf: DrapeSurface,
    theta: np.ndarray,
    cs: np.ndarray,
    tri: np.ndarray,
    rho: np.ndarray,
    u: np.ndarray,
    v: np.ndarray,
    s: np.ndarray,
    range_m: np.ndarray,
    bin_step: float,
    bin_index: _BinIndex,
    sensor: SensorParams,
    cfg: DrapeConfig,
    out: tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray],
) -> None:
    """The bookkeeping after the fans' cast in compiled kernels (:mod:`.kernels`), one
    loop over fans, pairs and bins; the middle rays are cast here, with embree."""
    from sss2bathy.draping import kernels

    K, M = rho.shape
    B = len(range_m)
    real = np.float32  # embree's ranges: the numpy reference compares in float32
    uniform = bin_index.uniform
    r0 = real(bin_index.r0) if uniform else real(0.0)
    inv_step = real(1.0 / bin_index.step) if uniform else real(0.0)
    kbin, k_c, j_c, t_check = kernels.fan_brackets(
        theta, tri, rho, range_m, uniform, r0, inv_step, real(cfg.jump_check_bins * bin_step)
    )
    s_mid, d_mid = kernels.mid_rays(np.cos(t_check), np.sin(t_check), k_c, u, v, s)
    _, rho_mid = surf.cast(s_mid, d_mid, distances=True)
    grad = surf._grad if surf.grid is not None else None
    if grad is None:
        grad, x0, y0, cell = np.zeros((0, 0, 2), np.float32), 0.0, 0.0, 1.0
    else:
        x0, y0, cell = float(surf.grid.x0), float(surf.grid.y0), float(surf.grid.cell_size)
    th_min, th_max = sensor.beam_limits_rad
    # the kernel writes into the caller's chunk views: reshape them without copying
    pts_out, nlat_out, graz_out, mask_out = (
        _reshaped_view(a, shape)
        for a, shape in zip(out, ((K, B, 3), (K, B), (K, B), (K, B)), strict=True)
    )
    kernels.drape_fans(
        theta,
        tri,
        rho,
        kbin,
        k_c,
        j_c,
        rho_mid.astype(np.float32, copy=False),
        u,
        v,
        s,
        range_m,
        real(cfg.jump_tolerance),
        surf.face_planes,
        cs,
        float(th_min),
        float(th_max),
        grad,
        x0,
        y0,
        cell,
        surf.face_normals,
        grad.size > 0,
        pts_out,
        nlat_out,
        graz_out,
        mask_out,
        MASK_NO_HIT,
        MASK_WATER_COLUMN,
        MASK_SHADOW,
        MASK_OUT_OF_BEAM,
    )


def _reshaped_view(a: np.ndarray, shape: tuple[int, ...]) -> np.ndarray:
    """``a`` reshaped as a view (writes reach ``a``); raises where that needs a copy."""
    out = a.reshape(shape)
    if a.size and not np.may_share_memory(out, a):
        raise RuntimeError(f"draping: expected a contiguous output chunk, found {a.strides}")
    return out


def _post_cast_numpy(
    surf: DrapeSurface,
    theta: np.ndarray,
    cs: np.ndarray,
    tri: np.ndarray,
    rho: np.ndarray,
    u: np.ndarray,
    v: np.ndarray,
    s: np.ndarray,
    range_m: np.ndarray,
    bin_step: float,
    bin_index: _BinIndex,
    sensor: SensorParams,
    cfg: DrapeConfig,
    out: tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray],
) -> None:
    """The bookkeeping after the fans' cast, vectorised with numpy (the reference of the
    compiled kernels; ``BOOKKEEPING = "numpy"``)."""
    K, M = rho.shape
    B = len(range_m)
    kbin = bin_index(rho)  # (K, M) number of bins nearer than each first hit

    # --- segments between neighbouring rays; occlusion jumps checked with a middle ray
    dr = np.abs(rho[:, 1:] - rho[:, :-1])  # NaN unless both rays hit
    with np.errstate(invalid="ignore"):
        k_c, j_c = np.nonzero(dr > cfg.jump_check_bins * bin_step)
    keep = tri[k_c, j_c] != tri[k_c, j_c + 1]
    k_c, j_c = k_c[keep], j_c[keep]
    t_check = 0.5 * (theta[k_c, j_c] + theta[k_c, j_c + 1])
    d_mid = np.cos(t_check)[:, None] * u[k_c] + np.sin(t_check)[:, None] * v[k_c]
    _, rho_mid = surf.cast(s[k_c], d_mid.astype(np.float32), distances=True)
    lin_mid = 0.5 * (rho[k_c, j_c] + rho[k_c, j_c + 1])
    is_jump = ~np.isfinite(rho_mid) | (
        np.abs(rho_mid - lin_mid) > cfg.jump_tolerance * dr[k_c, j_c]
    )
    k_j, j_j = k_c[is_jump], j_c[is_jump]

    # --- (segment, bin) pairs: bins whose range lies in [min rho, max rho) of a segment
    crosses = kbin[:, 1:] != kbin[:, :-1]
    crosses &= dr == dr  # both rays hit
    crosses[k_j, j_j] = False
    seg = np.flatnonzero(crosses)
    ph = seg // (M - 1)  # the segment's fan
    qa = seg + ph  # flat index of the segment's first ray
    kflat = kbin.reshape(-1)
    k_a, k_b = np.take(kflat, qa), np.take(kflat, qa + 1)
    lo = np.minimum(k_a, k_b)
    seg_count = np.abs(k_b - k_a)
    bins = lo
    multi = np.flatnonzero(seg_count > 1)
    if len(multi):  # segments spanning several bins: append their further bins
        extra = seg_count[multi] - 1
        rep = np.repeat(multi, extra)
        step = np.arange(len(rep)) - np.repeat(np.cumsum(extra) - extra, extra) + 1
        bins = np.concatenate([lo, np.take(lo, rep) + step])
        qa = np.concatenate([qa, np.take(qa, rep)])
        ph = np.concatenate([ph, np.take(ph, rep)])
    qb = qa + 1
    rho_f, theta_f = rho.reshape(-1), theta.reshape(-1)
    ra = np.take(rho_f, qa).astype(np.float64)
    rb = np.take(rho_f, qb).astype(np.float64)
    ta = np.take(theta_f, qa).astype(np.float64)
    tb = np.take(theta_f, qb).astype(np.float64)
    r = np.take(range_m, bins)
    theta_lin = ta + (r - ra) / (rb - ra) * (tb - ta)

    # --- exact hit: where the range arc s + r (cos t u + sin t v) meets the plane of a
    # bracket face; the root nearest theta_lin within the bracket [ta, tb] (widened by
    # 5 % each side: t_mid +- t_half) wins, trying face a's two roots, then face b's.
    t_mid = 0.5 * (ta + tb)
    t_half = 0.55 * np.abs(tb - ta) + 1e-12
    # per pair its fan's rows G = [[u, 0], [v, 0], [-s, 1]]: G @ [n, offset] = [A, B, C]
    G = np.zeros((K, 3, 4))
    G[:, 0, :3], G[:, 1, :3], G[:, 2, :3], G[:, 2, 3] = u, v, -s, 1.0
    G = np.take(G.reshape(K, 12), ph, axis=0).reshape(-1, 3, 4)
    u_p, v_p, s_neg = G[:, 0, :3], G[:, 1, :3], G[:, 2, :3]
    tri_f = tri.reshape(-1)
    tri_a = np.take(tri_f, qa).astype(np.int64)
    tri_b = np.take(tri_f, qb).astype(np.int64)
    best = _Roots(len(r))
    best.update(_arc_coefficients(surf, tri_a, G), r, theta_lin, t_mid, t_half)
    other = np.flatnonzero(tri_a != tri_b)
    from_b = np.zeros(len(r), bool)
    if len(other):
        sub = best.take(other)
        abc_b = _arc_coefficients(surf, np.take(tri_b, other), np.take(G, other, axis=0))
        sub.update(
            abc_b,
            np.take(r, other),
            np.take(theta_lin, other),
            np.take(t_mid, other),
            np.take(t_half, other),
        )
        from_b[other] = sub.d < np.take(best.d, other)
        best.put(other, sub)
    refined = best.d < np.inf
    theta_hit = np.where(refined, best.t, theta_lin)
    # in-plane coordinates (r cos t, r sin t) of the hit
    y_hit, z_hit = best.y, best.z
    lin = np.flatnonzero(~refined)  # no root in the bracket: the interpolated angle
    y_hit[lin] = r[lin] * np.cos(theta_lin[lin])
    z_hit[lin] = r[lin] * np.sin(theta_lin[lin])

    # --- one crossing per bin: prefer in-beam, then the largest |dtheta/drho|
    th_min, th_max = sensor.beam_limits_rad
    in_beam = (theta_hit >= th_min) & (theta_hit <= th_max)
    key = ph * B + bins
    dup = np.bincount(key, minlength=K * B)[key] > 1
    rewrite = None
    if dup.any():
        # layover: several crossings of one bin; the last by (key, in_beam, strength,
        # position in the fan) wins, resolving only the duplicated keys
        idx = np.flatnonzero(dup)
        strength = np.abs(tb[idx] - ta[idx]) / np.abs(rb[idx] - ra[idx])
        order = np.lexsort((qa[idx], strength, in_beam[idx], key[idx]))
        sk = key[idx][order]
        last = np.ones(len(order), bool)
        last[:-1] = sk[1:] != sk[:-1]
        rewrite = idx[order[last]]  # the winners of duplicated keys
        in_beam[idx[order[~last]]] = True  # losers never mark a bin out of beam

    # --- points, normals (eq. 1-3), grazing angles
    p_hit = np.empty((len(r), 3))
    for k in range(3):  # s + y u + z v, per coordinate
        np.multiply(y_hit, u_p[:, k], out=p_hit[:, k])
        p_hit[:, k] += z_hit * v_p[:, k]
        p_hit[:, k] -= s_neg[:, k]
    if surf.grid is not None:
        grad = surf.grid_gradient_at(p_hit[:, 0], p_hit[:, 1])  # normal [-gx, -gy, 1]
        gx, gy = grad[:, 0], grad[:, 1]
        un = u_p[:, 2] - u_p[:, 0] * gx - u_p[:, 1] * gy
        vn = v_p[:, 2] - v_p[:, 0] * gx - v_p[:, 1] * gy
        normal_len = np.sqrt(1.0 + gx * gx + gy * gy)
    else:
        # the face of the refining root, else the face of the nearer ray
        nearer_b = np.abs(ra - r) > np.abs(rb - r)
        tri_hit = tri_f[np.where(np.where(refined, from_b, nearer_b), qb, qa)]
        normal = surf.normals_at(p_hit, tri_hit, -s_neg)
        un = np.einsum("qk,qk->q", u_p, normal)
        vn = np.einsum("qk,qk->q", v_p, normal)
        normal_len = np.sqrt(np.einsum("qk,qk->q", normal, normal))
    # eq. 2-3: sigma N_v,y = u . N and N_v,z = -(v . N)
    nlat_hit = head_plane_unit(un, -vn)[0]
    # incidence cosine N.(s - p) / (|N| |s - p|) (geometry.incidence_cosine) in the head
    # plane's coordinates: s - p = -(y u + z v), so N.(s - p) = -(y N.u + z N.v) and
    # |s - p| = sqrt(y^2 + z^2) (u, v orthonormal), without forming (N, 3) vectors
    with np.errstate(invalid="ignore"):
        cos_inc = -(y_hit * un + z_hit * vn) / np.maximum(
            normal_len * np.hypot(y_hit, z_hit), 1e-12
        )
    graz_hit = np.pi / 2 - np.arccos(np.clip(cos_inc, -1.0, 1.0))
    has_normal = np.isfinite(nlat_hit)
    if not has_normal.all():  # (outside the grid) no normal: drop, losers included
        keep = has_normal
        if rewrite is not None:
            keep = np.zeros(len(key), bool)
            keep[np.flatnonzero(~dup)] = True
            keep[rewrite] = True
            keep &= has_normal
            rewrite = None
        key, p_hit, nlat_hit, graz_hit, in_beam = (
            a[keep] for a in (key, p_hit, nlat_hit, graz_hit, in_beam)
        )

    # --- write the chunk; the winners of duplicated keys are written again, last
    pts_out, nlat_out, graz_out, mask_out = out
    pts_f, nlat_f, graz_f = pts_out.reshape(-1, 3), nlat_out.reshape(-1), graz_out.reshape(-1)
    for sel in [slice(None)] if rewrite is None else [slice(None), rewrite]:
        k = key[sel]
        pts_f[k], nlat_f[k], graz_f[k] = p_hit[sel], nlat_hit[sel], graz_hit[sel]
    matched = np.zeros(K * B, bool)
    matched[key] = True
    matched = matched.reshape(K, B)

    with np.errstate(invalid="ignore"):
        nearest = np.fmin.reduce(rho, axis=1)  # NaN where the fan hits nothing
        water = ~matched & (range_m[None, :] < nearest[:, None])
    mask = mask_out.reshape(K, B)
    mask[~matched] = MASK_NO_HIT
    mask[water] = MASK_WATER_COLUMN
    if len(k_j):
        cover = np.zeros((K, B + 1), np.int32)
        k0, k1 = kbin[k_j, j_j], kbin[k_j, j_j + 1]
        np.add.at(cover, (k_j, np.minimum(k0, k1)), 1)
        np.add.at(cover, (k_j, np.maximum(k0, k1)), -1)
        shadow = ~matched & ~water & (np.cumsum(cover[:, :B], axis=1) > 0)
        mask[shadow] = MASK_SHADOW
    mask.reshape(-1)[key[~in_beam]] = MASK_OUT_OF_BEAM


def _arc_coefficients(surf: DrapeSurface, tri: np.ndarray, G: np.ndarray) -> np.ndarray:
    """``(Q, 3) [A, B, C] = [n.u, n.v, offset - n.s]`` of faces ``tri`` in float64.

    ``G (Q, 3, 4)`` holds each pair's fan ``[[u, 0], [v, 0], [-s, 1]]``. The arc
    ``s + r (cos t u + sin t v)`` meets the face's plane ``n.x = offset`` where
    ``A cos t + B sin t = C / r`` (NaN rows for ``tri = -1``).
    """
    plane = np.take(surf.face_planes, tri, axis=0)
    return np.einsum("qi,qji->qj", plane, G)


class _Roots:
    """Per pair, the best arc/plane root so far: angle ``t``, ``d = |t - theta_lin|``
    (inf = none yet) and in-plane coordinates ``y = r cos t``, ``z = r sin t``."""

    def __init__(self, n: int) -> None:
        self.t, self.y, self.z = np.zeros(n), np.zeros(n), np.zeros(n)
        self.d = np.full(n, np.inf)

    def take(self, idx: np.ndarray) -> _Roots:
        out = _Roots(0)
        out.t, out.d, out.y, out.z = (np.take(a, idx) for a in (self.t, self.d, self.y, self.z))
        return out

    def put(self, idx: np.ndarray, other: _Roots) -> None:
        self.t[idx], self.d[idx], self.y[idx], self.z[idx] = other.t, other.d, other.y, other.z

    def update(
        self,
        abc: np.ndarray,
        r: np.ndarray,
        theta_ref: np.ndarray,
        t_mid: np.ndarray,
        t_half: np.ndarray,
    ) -> None:
        """Offer a face's two roots; one replaces the best if it lies in the bracket
        ``t_mid +- t_half`` and is strictly nearer ``theta_ref``.

        In the head plane, with ``y = r cos t`` and ``z = r sin t``, the face's plane is
        the line ``A y + B z = C`` (``abc = (Q, 3) [A, B, C]``); it meets the circle of
        radius ``r`` at ``(y, z) = (C (A, B) -+ sqrt(r^2 K^2 - C^2) (B, -A)) / K^2`` with
        ``K^2 = A^2 + B^2``: exact, with one square root and an arctan2 per root.
        """
        A, Bc, C = abc[:, 0], abc[:, 1], abc[:, 2]
        k2 = A * A + Bc * Bc
        with np.errstate(invalid="ignore", divide="ignore"):
            # no root (NaN from here on) where r^2 K^2 < C^2, K = 0 or the face is a miss
            w = np.sqrt(r * r * k2 - C * C)
            inv = 1.0 / k2
            ca, cb, wa, wb = C * A, C * Bc, w * A, w * Bc
            for sign in (1.0, -1.0):
                y = (ca - wb if sign > 0 else ca + wb) * inv
                z = (cb + wa if sign > 0 else cb - wa) * inv
                t = np.arctan2(z, y)
                d = np.abs(t - theta_ref)
                better = d < self.d
                better &= np.abs(t - t_mid) <= t_half
                for dst, src in ((self.t, t), (self.d, d), (self.y, y), (self.z, z)):
                    np.copyto(dst, src, where=better)
