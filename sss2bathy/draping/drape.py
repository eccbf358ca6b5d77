"""Georeferencing of sidescan bins on a surface by ray casting in each head's plane.

For every ping and head a fan of rays is cast in the head's plane (directions
``R [0, sigma cos theta, -sin theta]``, the isotemporal-arc directions of paper eq. 10),
one first-hit query for all rays of a chunk of pings. Along the fan the first-hit range
``rho(theta)`` describes the seabed as the sonar sees it. Bin ``i`` (slant range ``r_i``)
is matched where ``rho`` crosses ``r_i`` between two neighbouring rays: the depression
angle is interpolated there and then made exact by intersecting the range arc with the
plane of the hit face, so hit points on a piecewise-planar surface are exact to rounding.

Bins without a crossing are classified: ``r_i`` below the nearest first hit of the fan ->
WATER_COLUMN; inside the range gap of an occlusion (a jump of ``rho`` between two rays,
confirmed by a ray cast between them) -> SHADOW; otherwise -> NO_HIT (the fan left the
mesh, or a no-data hole). A crossing outside the vertical beam gives OUT_OF_BEAM (point
and normal kept). Where several crossings share a bin (layover), the in-beam one with the
largest angular extent per metre of range (the strongest echo) wins.

Vectorised over pings, heads, rays and bins; the only Python loop is over ping chunks.
"""

from __future__ import annotations

import logging
import math
from typing import Any

import numpy as np

from sss2bathy.draping.config import DrapeConfig
from sss2bathy.draping.draped import DrapedLine
from sss2bathy.draping.surface import DrapeSurface
from sss2bathy.geometry import grazing_angle, head_plane_normal, vehicle_normal
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

_SIDE_SIGNS = np.array([1.0, -1.0])


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
        The :class:`DrapedLine` with ``(P, 2, B)`` arrays.
    """
    if not isinstance(line, SidescanLine):
        raise ValueError(f"line: expected a SidescanLine, found {type(line).__name__}")
    cfg = DrapeConfig.coerce(cfg)
    surf = as_surface(surface, cfg.engine)
    P, B = line.n_pings, line.n_bins
    h_ref = _reference_altitude(line, surf)
    points = np.full((P, 2, B, 3), np.nan, np.float32)
    n_lat = np.full((P, 2, B), np.nan, np.float32)
    grazing = np.full((P, 2, B), np.nan, np.float32)
    mask = np.zeros((P, 2, B), np.uint8)
    range_m = line.range_m.astype(np.float64)
    for start in range(0, P, cfg.pings_per_chunk):
        sl = slice(start, min(P, start + cfg.pings_per_chunk))
        points[sl], n_lat[sl], grazing[sl], mask[sl] = _drape_chunk(
            surf, line.position[sl], line.rotation[sl], h_ref[sl], range_m, line.sensor, cfg
        )
    log.debug("draped line '%s': %s", line.name, mask_reason_counts(mask))
    return DrapedLine(points=points, n_lat=n_lat, grazing_rad=grazing, mask=mask)


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


def _fan_angles(
    u: np.ndarray,
    v: np.ndarray,
    h_ref: np.ndarray,
    range_m: np.ndarray,
    bin_step: float,
    sensor: SensorParams,
    cfg: DrapeConfig,
) -> np.ndarray:
    """``(n, 2, M)`` sorted depression angles of the fan of each ping and head."""
    th_min, th_max = sensor.beam_limits_rad
    a, b = u[..., 2], v[..., 2]  # world z of the two in-plane axes
    theta_down = np.arctan2(-b, -a)  # the in-plane direction pointing most downward
    c = np.maximum(np.hypot(a, b), 1e-6)
    th_lo = min(th_min, 0.0) - math.radians(cfg.beam_margin_deg)
    th_hi = np.maximum(
        th_max + math.radians(cfg.beam_margin_deg),
        theta_down + math.radians(cfg.nadir_margin_deg),
    )
    n_uniform = int(math.ceil((float(th_hi.max()) - th_lo) / math.radians(cfg.fan_step_deg))) + 1
    theta_u = th_lo + (th_hi - th_lo)[..., None] * np.linspace(0.0, 1.0, n_uniform)
    # Rays uniform in the range a flat floor h_ref below would give: rho = hc / cos(theta_down - theta).
    n_range = max(2, int(math.ceil(cfg.rays_per_bin * len(range_m))))
    hc = h_ref[:, None] / c
    off = np.minimum(theta_down - th_lo, math.pi / 2 - 1e-6)
    rho_edge = np.where(theta_down - th_lo < math.pi / 2 - 1e-6, hc / np.cos(off), np.inf)
    rho_hi = np.maximum(np.minimum(range_m[-1] + bin_step, rho_edge), hc)
    rho = hc[..., None] + (rho_hi - hc)[..., None] * np.linspace(0.0, 1.0, n_range)
    theta_r = theta_down[..., None] - np.arccos(np.clip(hc[..., None] / rho, -1.0, 1.0))
    return np.sort(np.concatenate([theta_u, theta_r], axis=-1), axis=-1)


def _arc_planes(
    surf: DrapeSurface,
    tri: np.ndarray,
    sonar: np.ndarray,
    u: np.ndarray,
    v: np.ndarray,
    r: np.ndarray,
    theta_ref: np.ndarray,
) -> tuple[np.ndarray, np.ndarray]:
    """Angles where the range arc ``s + r (cos t u + sin t v)`` meets each face's plane.

    Solves ``A cos t + B sin t = C / r``; returns the two roots ``(Q, 2)`` wrapped next
    to ``theta_ref`` and whether they exist ``(Q, 2)``.
    """
    n = surf.face_normals[tri]
    A = np.einsum("qk,qk->q", n, u)
    Bc = np.einsum("qk,qk->q", n, v)
    C = surf.face_offsets[tri] - np.einsum("qk,qk->q", n, sonar)
    K = np.hypot(A, Bc)
    with np.errstate(divide="ignore", invalid="ignore"):
        ratio = C / (r * K)
    exists = np.isfinite(ratio) & (np.abs(ratio) <= 1.0) & (tri >= 0)
    phi = np.arctan2(Bc, A)
    half = np.arccos(np.clip(np.nan_to_num(ratio), -1.0, 1.0))
    roots = phi[:, None] + np.stack([half, -half], axis=1)
    roots = theta_ref[:, None] + np.remainder(roots - theta_ref[:, None] + np.pi, 2 * np.pi) - np.pi
    return roots, np.stack([exists, exists], axis=1)


def _drape_chunk(
    surf: DrapeSurface,
    sonar: np.ndarray,
    R: np.ndarray,
    h_ref: np.ndarray,
    range_m: np.ndarray,
    sensor: SensorParams,
    cfg: DrapeConfig,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Drape ``n`` pings: returns points ``(n,2,B,3)``, n_lat, grazing, mask ``(n,2,B)``."""
    n, B = len(sonar), len(range_m)
    bin_step = float(np.median(np.diff(range_m))) if B > 1 else float(range_m[0])
    u = _SIDE_SIGNS[None, :, None] * R[:, None, :, 1]  # (n, 2, 3): sigma * vehicle y in world
    v = np.broadcast_to(-R[:, None, :, 2], u.shape)  # (n, 2, 3): vehicle down in world
    theta = _fan_angles(u, v, h_ref, range_m, bin_step, sensor, cfg)
    M = theta.shape[-1]
    dirs = np.cos(theta)[..., None] * u[:, :, None] + np.sin(theta)[..., None] * v[:, :, None]
    origins = np.broadcast_to(sonar[:, None, None, :], dirs.shape)
    tri, rho = surf.first_hits(
        np.ascontiguousarray(origins.reshape(-1, 3)), np.ascontiguousarray(dirs.reshape(-1, 3))
    )
    # Flatten (ping, head) into one axis "ph" of length 2n; s/R/u/v indexed by ph.
    tri, rho, theta = tri.reshape(2 * n, M), rho.reshape(2 * n, M), theta.reshape(2 * n, M)
    u_ph, v_ph = u.reshape(-1, 3), np.ascontiguousarray(v).reshape(-1, 3)
    s_ph = np.repeat(sonar, 2, axis=0)

    # --- segments between neighbouring rays; find occlusion jumps
    r0, r1, t0, t1 = rho[:, :-1], rho[:, 1:], theta[:, :-1], theta[:, 1:]
    both = np.isfinite(r0) & np.isfinite(r1)
    dr = np.abs(r1 - r0)
    check = both & (tri[:, :-1] != tri[:, 1:]) & (dr > cfg.jump_check_bins * bin_step)
    ph_c, j_c = np.nonzero(check)
    t_mid = 0.5 * (t0[ph_c, j_c] + t1[ph_c, j_c])
    d_mid = np.cos(t_mid)[:, None] * u_ph[ph_c] + np.sin(t_mid)[:, None] * v_ph[ph_c]
    _, rho_mid = surf.first_hits(s_ph[ph_c], d_mid)
    lin_mid = 0.5 * (r0[ph_c, j_c] + r1[ph_c, j_c])
    jump = np.zeros_like(check)
    jump[ph_c, j_c] = ~np.isfinite(rho_mid) | (
        np.abs(rho_mid - lin_mid) > cfg.jump_tolerance * dr[ph_c, j_c]
    )
    seg_ok = both & ~jump

    # --- (segment, bin) pairs: bins whose range lies in [min rho, max rho) of a segment
    ph_s, j_s = np.nonzero(seg_ok)
    ra, rb = r0[ph_s, j_s], r1[ph_s, j_s]
    i_lo = np.searchsorted(range_m, np.minimum(ra, rb), side="left")
    i_hi = np.searchsorted(range_m, np.maximum(ra, rb), side="left")
    count = i_hi - i_lo
    pair = np.repeat(np.arange(len(count)), count)
    first = np.repeat(np.cumsum(count) - count, count)
    bins = i_lo[pair] + (np.arange(len(pair)) - first)
    ph, j = ph_s[pair], j_s[pair]
    ra, rb, r = ra[pair], rb[pair], range_m[bins]
    ta, tb = t0[ph, j], t1[ph, j]
    tri_a, tri_b = tri[ph, j], tri[ph, j + 1]
    theta_lin = ta + (r - ra) / (rb - ra) * (tb - ta)

    # --- exact angle: intersect the range arc with the planes of both bracket faces
    roots_a, ok_a = _arc_planes(surf, tri_a, s_ph[ph], u_ph[ph], v_ph[ph], r, theta_lin)
    roots_b, ok_b = _arc_planes(surf, tri_b, s_ph[ph], u_ph[ph], v_ph[ph], r, theta_lin)
    roots = np.concatenate([roots_a, roots_b], axis=1)
    tol = 0.05 * np.abs(tb - ta) + 1e-12
    lo_t, hi_t = np.minimum(ta, tb) - tol, np.maximum(ta, tb) + tol
    ok = np.concatenate([ok_a, ok_b], axis=1) & (roots >= lo_t[:, None]) & (roots <= hi_t[:, None])
    dist = np.where(ok, np.abs(roots - theta_lin[:, None]), np.inf)
    best = np.argmin(dist, axis=1)
    refined = np.isfinite(dist[np.arange(len(best)), best])
    nearer = np.where(np.abs(ra - r) <= np.abs(rb - r), tri_a, tri_b)
    theta_hit = np.where(refined, roots[np.arange(len(best)), best], theta_lin)
    tri_hit = np.where(refined, np.where(best < 2, tri_a, tri_b), nearer)

    # --- one crossing per bin: prefer in-beam, then the largest |dtheta/drho|
    th_min, th_max = sensor.beam_limits_rad
    in_beam = (theta_hit >= th_min) & (theta_hit <= th_max)
    strength = np.abs(tb - ta) / np.abs(rb - ra)
    key = ph * B + bins
    order = np.lexsort((strength, in_beam, key))
    last = np.ones(len(order), bool)
    last[:-1] = key[order][1:] != key[order][:-1]
    pick = order[last]
    key, ph, r = key[pick], ph[pick], r[pick]
    theta_hit, tri_hit, in_beam = theta_hit[pick], tri_hit[pick], in_beam[pick]

    # --- points, normals (eq. 1-3), grazing angles
    s_hit = s_ph[ph]
    d_hit = np.cos(theta_hit)[:, None] * u_ph[ph] + np.sin(theta_hit)[:, None] * v_ph[ph]
    p_hit = s_hit + r[:, None] * d_hit
    normal = surf.normals_at(p_hit, tri_hit, s_hit)
    R_hit = R[ph // 2]
    side = (ph % 2).astype(np.int64)
    nlat_hit, _ = head_plane_normal(vehicle_normal(normal, R_hit), side)
    graz_hit = grazing_angle(normal, p_hit, s_hit)
    has_normal = np.isfinite(nlat_hit)

    # --- masks
    points = np.full((2 * n * B, 3), np.nan, np.float32)
    n_lat = np.full(2 * n * B, np.nan, np.float32)
    grazing = np.full(2 * n * B, np.nan, np.float32)
    matched = np.zeros(2 * n * B, bool)
    good = key[has_normal]
    matched[good] = True
    points[good] = p_hit[has_normal]
    n_lat[good] = nlat_hit[has_normal]
    grazing[good] = graz_hit[has_normal]
    matched = matched.reshape(2 * n, B)

    nearest = np.where(np.isfinite(rho), rho, np.inf).min(axis=1)
    water = ~matched & (range_m[None, :] < nearest[:, None]) & np.isfinite(nearest)[:, None]
    ph_j, j_j = np.nonzero(jump)
    cover = np.zeros((2 * n, B + 1), np.int32)
    jlo = np.searchsorted(range_m, np.minimum(r0[ph_j, j_j], r1[ph_j, j_j]), side="left")
    jhi = np.searchsorted(range_m, np.maximum(r0[ph_j, j_j], r1[ph_j, j_j]), side="left")
    np.add.at(cover, (ph_j, jlo), 1)
    np.add.at(cover, (ph_j, jhi), -1)
    shadow = ~matched & ~water & (np.cumsum(cover[:, :B], axis=1) > 0)

    mask = np.zeros((2 * n, B), np.uint8)
    mask[water] = MASK_WATER_COLUMN
    mask[shadow] = MASK_SHADOW
    mask[~matched & ~water & ~shadow] = MASK_NO_HIT
    oob = key[has_normal & ~in_beam]
    mask.reshape(-1)[oob] = MASK_OUT_OF_BEAM
    return (
        points.reshape(n, 2, B, 3),
        n_lat.reshape(n, 2, B),
        grazing.reshape(n, 2, B),
        mask.reshape(n, 2, B),
    )
