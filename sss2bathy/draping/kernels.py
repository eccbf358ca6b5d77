"""Compiled (numba) parts of draping: fan angles, embree's first-hit call, bookkeeping.

Per chunk of pings :func:`sss2bathy.draping.drape._drape_chunk` builds the fans
(:meth:`~sss2bathy.draping.drape._Fan.angles`: :func:`fan_ramps` does numpy's float32
steps in one pass; ``arccos``, ``cos``, ``sin`` and the sort stay numpy's), casts them
(:meth:`~sss2bathy.draping.surface.DrapeSurface.cast`, which runs
:func:`embree_first_hits`: embree's ``rtcIntersect1`` per ray on embreex's own scene,
faces and distances without embreex's per-call output arrays), then calls
:func:`fan_brackets` (bin counts of the first hits and the ray pairs to check for an
occlusion), casts the middle rays of those pairs (:func:`mid_rays`) and calls
:func:`drape_fans`, which loops over fans (ping, head), their ray pairs and bins and
writes points, ``n_lat``, grazing angles and masks (per fan: the pairs that cross a bin
listed first; roots provably outside a pair's bracket skipped, the others' angles from a
fast arctangent wherever that decides, else ``atan2``; ``hypot`` and ``acos`` in loops of
their own). No large temporaries: per fan a few arrays of one fan's rays or bins, reused.
:func:`draped_values_ok` runs
``DrapedLine.validate``'s value checks in one pass.

The arithmetic repeats the numpy reference (``_post_cast_numpy`` and the numpy fan
set-up in ``drape.py``) operation by operation, in the same precision (float32 where it
is float32 there, the same summation order as ``np.einsum``'s; LLVM does not fuse
multiply-adds without fastmath), so results agree to the last bit up to the libm
functions (``cos``, ``sin``, ``atan2``, ``hypot``, ``acos``) numpy and LLVM call.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit, types

# IEEE semantics: x / 0 -> inf / NaN like numpy, no ZeroDivisionError
_JIT = {"cache": True, "error_model": "numpy", "nogil": True}


@njit(**_JIT)
def _bin_count(x, range_m, uniform, r0, inv_step):  # pragma: no cover - compiled
    """``_BinIndex`` of one float32 range: bins with range below ``x`` (0 for NaN)."""
    B = range_m.shape[0]
    if x != x:
        return 0
    if uniform:
        k = (x - r0) * inv_step  # in x's precision (r0, inv_step of x's dtype), as numpy
        k = np.ceil(k)
        if k < 0:
            return 0
        if k > B:
            return B
        return int(k)
    xd = np.float64(x)
    lo, hi = 0, B  # first index with range_m >= x (searchsorted, side="left")
    while lo < hi:
        mid = (lo + hi) >> 1
        if range_m[mid] < xd:
            lo = mid + 1
        else:
            hi = mid
    return lo


@njit(**_JIT)
def fan_ramps(th_lo, th_hi, hc, rho_hi, ramp_u, ramp_r, out):  # pragma: no cover - compiled
    """The two parts of ``_Fan.angles`` before ``arccos``, in float32 as numpy does them.

    Args:
        th_lo: float32 lower fan edge; th_hi, hc, rho_hi: ``(n, 2)`` float32 upper edge,
            flat-floor height over ``c`` and range limit per fan.
        ramp_u, ramp_r: float32 ramps ``[0, 1]`` of the uniform and range-uniform parts.
        out: ``(n, 2, len(ramp_u) + len(ramp_r))`` float32: the uniform angles
            ``(th_hi - th_lo) ramp + th_lo``, then the clipped cosines
            ``hc / ((rho_hi - hc) ramp + hc)`` of the range-uniform rays.
    """
    n_u = ramp_u.shape[0]
    n_r = ramp_r.shape[0]
    for p in range(out.shape[0]):
        for h in range(out.shape[1]):
            span = th_hi[p, h] - th_lo
            for i in range(n_u):
                out[p, h, i] = span * ramp_u[i] + th_lo
            c, extent = hc[p, h], rho_hi[p, h] - hc[p, h]
            for i in range(n_r):
                x = c / (extent * ramp_r[i] + c)
                if x < -1.0:
                    x = np.float32(-1.0)
                elif x > 1.0:
                    x = np.float32(1.0)
                out[p, h, n_u + i] = x


@njit(**_JIT)
def fan_brackets(theta, tri, rho, range_m, uniform, r0, inv_step, jump_thr):  # pragma: no cover
    """Bin counts of the first hits and the ray pairs to check for an occlusion.

    Args:
        theta, tri, rho: ``(K, M)`` fan angles (float32), first-hit faces and ranges
            (float32, NaN = miss).
        range_m: ``(B,)`` bin ranges; ``uniform``, ``r0``, ``inv_step`` (float32): the
            arithmetic bin index of ``_BinIndex`` where bins are uniform.
        jump_thr: float32 range jump above which a pair of rays hitting different faces
            is checked with a middle ray (``rho``'s dtype, like ``r0`` and ``inv_step``).

    Returns:
        ``kbin (K, M) int32``; the checked pairs' fan ``k_c`` and first ray ``j_c``
        (int64, in fan then ray order) and their middle angle ``t_check`` (float32).
    """
    K, M = rho.shape
    kbin = np.empty((K, M), np.int32)
    n_max = K * (M - 1)
    k_c = np.empty(n_max, np.int64)
    j_c = np.empty(n_max, np.int64)
    t_check = np.empty(n_max, np.float32)
    half = np.float32(0.5)
    n = 0
    for k in range(K):
        for j in range(M):
            kbin[k, j] = _bin_count(rho[k, j], range_m, uniform, r0, inv_step)
        for j in range(M - 1):
            dr = abs(rho[k, j + 1] - rho[k, j])
            if dr > jump_thr and tri[k, j] != tri[k, j + 1]:
                k_c[n] = k
                j_c[n] = j
                t_check[n] = half * (theta[k, j] + theta[k, j + 1])
                n += 1
    return kbin, k_c[:n], j_c[:n], t_check[:n]


@njit(**_JIT)
def mid_rays(cos_t, sin_t, k_c, u, v, s):  # pragma: no cover - compiled
    """Origins ``s[k_c]`` and float32 directions ``cos_t u[k_c] + sin_t v[k_c]`` of the
    checked pairs' middle rays, as numpy forms them (``cos_t``, ``sin_t``: numpy's float32
    cosine and sine, products and sum in float64, then rounded to float32)."""
    n = k_c.shape[0]
    origins = np.empty((n, 3))
    dirs = np.empty((n, 3), np.float32)
    for i in range(n):
        k = k_c[i]
        c, sn = np.float64(cos_t[i]), np.float64(sin_t[i])
        for j in range(3):
            origins[i, j] = s[k, j]
            dirs[i, j] = np.float32(c * u[k, j] + sn * v[k, j])
    return origins, dirs


# Embree's single-ray first-hit query ``rtcIntersect1(scene, rayhit, args)``, bound by
# name: :func:`sss2bathy.draping.surface._embree_scene_pointer` makes the library that
# embreex loaded visible to LLVM before the first call (pointers passed as integers,
# which the x86-64 and AArch64 calling conventions pass like pointers).
_rtc_intersect1 = types.ExternalFunction(
    "rtcIntersect1", types.void(types.uintp, types.uintp, types.uintp)
)
_INVALID_ID = np.uint32(0xFFFFFFFF)


@njit(**_JIT)
def embree_first_hits(scene, origins, repeat, directions, inv_scale, tri, dist):  # pragma: no cover
    """First hits of rays with embree's ``rtcIntersect1``, the call embreex makes per ray.

    Args:
        scene: the ``RTCScene`` handle (an address) of a committed embreex scene.
        origins: ``(K, 3)`` float32 ray origins in the scene's frame; ray ``i`` starts at
            ``origins[i // repeat]``.
        repeat: rays per origin.
        directions: ``(K * repeat, 3)`` float32 directions in the scene's frame.
        inv_scale: float32 world units per scene unit.
        tri, dist: ``(K * repeat,)`` outputs: the hit face (int32, -1 = miss) and
            embree's ``tfar`` times ``inv_scale`` in float32 (NaN = miss), as
            ``_EmbreeScene.run`` makes them from embreex's full output.
    """
    # one RTCRayHit (80 bytes, 96 with instance arrays), 16-byte aligned in the buffer:
    # ray org, tnear, dir, time, tfar, mask, id, flags; hit Ng, u, v, primID, geomID,
    # instID (, instPrimID)
    buf = np.zeros(40, np.float32)
    start = ((16 - buf.ctypes.data % 16) % 16) // 4
    ray = buf[start : start + 32]
    bits = ray.view(np.uint32)
    addr = ray.ctypes.data
    for i in range(directions.shape[0]):
        o = i // repeat
        ray[0], ray[1], ray[2], ray[3] = origins[o, 0], origins[o, 1], origins[o, 2], 0.0
        ray[4], ray[5], ray[6], ray[7] = directions[i, 0], directions[i, 1], directions[i, 2], 0.0
        ray[8] = np.inf
        bits[9], bits[10], bits[11] = _INVALID_ID, 0, 0  # mask: every geometry
        bits[17], bits[18], bits[19], bits[20] = _INVALID_ID, _INVALID_ID, _INVALID_ID, _INVALID_ID
        _rtc_intersect1(scene, addr, 0)
        face = bits[17]
        if face == _INVALID_ID:
            tri[i] = -1
            dist[i] = np.nan
        else:
            tri[i] = np.int32(face)
            dist[i] = ray[8] * inv_scale


# Roots whose angle the fast path below only approximates (error < 1e-6 rad: the first
# ray's float32 direction, < 4e-7 rad, and a 9th-order arctangent) decide only where
# they are this far from every threshold; nearer, the exact ``atan2`` decides. So the
# outputs are those of ``atan2`` everywhere, whatever the rounding of the series (whose
# last coefficient is a product by 1 / 9, not a division: one division less per root).
_EPS_T = 1e-5
_INLINE = {**_JIT, "inline": "always"}


@njit(**_INLINE)
def _root_angle(y, z, ca0, sa0, ta):  # pragma: no cover - compiled
    """``(t, exact)``: the angle of ``(y, z)``, within ``_EPS_T`` of ``atan2(z, y)``
    (``exact`` False), from ``ta`` + the arctangent of its small angle to the first
    ray's direction ``(ca0, sa0)``; exactly (``atan2``) where that angle is not small."""
    dot = y * ca0 + z * sa0
    cross = ca0 * z - sa0 * y
    if dot > 0.0 and abs(cross) <= 0.1 * dot and abs(ta) < 3.0:
        x = cross / dot
        x2 = x * x
        t = ta + x * (1.0 - x2 * (1.0 / 3.0 - x2 * (0.2 - x2 * (1.0 / 7.0 - x2 * (1.0 / 9.0)))))
        return t, False
    return math.atan2(z, y), True


@njit(**_INLINE)
def _arc_abc(face_planes, f, u, v, s):  # pragma: no cover - compiled
    """``[A, B, C]`` of ``_arc_coefficients`` for face ``f`` (plane ``[n, offset]``):
    ``np.einsum("qi,qji->qj")`` with rows ``[u, 0], [v, 0], [-s, 1]``, summed in
    einsum's order ``(x0 + x2) + (x1 + x3)``."""
    n0, n1, n2, off = face_planes[f, 0], face_planes[f, 1], face_planes[f, 2], face_planes[f, 3]
    A = (n0 * u[0] + n2 * u[2]) + (n1 * u[1] + off * 0.0)
    Bc = (n0 * v[0] + n2 * v[2]) + (n1 * v[1] + off * 0.0)
    C = (n0 * -s[0] + n2 * -s[2]) + (n1 * -s[1] + off * 1.0)
    return A, Bc, C


@njit(**_JIT)
def _bilinear(grad, iy, ix, q, tx, ty):  # pragma: no cover - compiled
    """Component ``q`` of the gradient at cell ``(iy, ix)``, weights ``(tx, ty)``, in
    ``DrapeSurface.grid_gradient_at``'s order of operations (float64)."""
    h0 = np.float64(grad[iy, ix, q])
    h1 = np.float64(grad[iy, ix + 1, q])
    h2 = np.float64(grad[iy + 1, ix, q])
    h3 = np.float64(grad[iy + 1, ix + 1, q])
    lower = (h1 - h0) * tx + h0
    upper = (h3 - h2) * tx + h2
    return lower + (upper - lower) * ty


@njit(**_JIT)
def _nan_last_ge(a, b):  # pragma: no cover - compiled
    """``a >= b`` in numpy's sort order (NaN largest)."""
    if a != a:
        return True
    if b != b:
        return False
    return a >= b


@njit(**_JIT)
def drape_fans(
    theta,
    tri,
    rho,
    kbin,
    k_c,
    j_c,
    rho_mid,
    u,
    v,
    s,
    range_m,
    jump_tol,
    face_planes,
    cs,
    th_min,
    th_max,
    grad,
    grid_x0,
    grid_y0,
    cell,
    face_normals,
    use_grid,
    pts_out,
    nlat_out,
    graz_out,
    mask_out,
    mask_no_hit,
    mask_water,
    mask_shadow,
    mask_oob,
):  # pragma: no cover - compiled
    """Match bins to ray pairs, solve exact hits, resolve layover, write the outputs.

    Args:
        theta, tri, rho, kbin: ``(K, M)`` fans from the cast and :func:`fan_brackets`.
        k_c, j_c, rho_mid: the checked pairs and their middle ray's range (NaN = miss).
        u, v, s: ``(K, 3)`` head-plane axes and sonar position of each fan (float64).
        range_m: ``(B,)`` bin ranges (float64). jump_tol: float32 jump tolerance.
        face_planes: ``(F + 1, 4)`` planes (last row NaN). cs: ``(K, M, 2)`` cos and
            sin of ``theta`` (float32, as cast). th_min, th_max: the beam.
        grad, grid_x0, grid_y0, cell: the grid's ``(ny, nx, 2)`` float32 gradient and
            geometry (``use_grid``), else ``face_normals (F, 3)`` give the normals.
        pts_out, nlat_out, graz_out, mask_out: ``(K, B, 3)``, ``(K, B)`` outputs, NaN
            (floats) and zero (mask) on entry.
    """
    K, M = rho.shape
    B = range_m.shape[0]
    ny, nx = grad.shape[0], grad.shape[1]
    half = np.float32(0.5)
    fc = np.empty((2, 7))  # per face of a pair: A, B, A^2 + B^2, C^2, 1 / k2, C A, C B
    jump = np.zeros(M, np.bool_)
    crossing = np.empty(M, np.int64)
    cover = np.zeros(B + 1, np.int32)
    has = np.zeros(B, np.bool_)
    w_inb = np.zeros(B, np.bool_)
    w_str = np.empty(B)
    w_y = np.empty(B)
    w_z = np.empty(B)
    w_tri = np.empty(B, np.int64)
    w_r = np.empty(B)  # per matched bin: hypot(y, z), cos of the incidence angle
    w_cos = np.empty(B)
    w_ok = np.zeros(B, np.bool_)
    c = 0  # next checked pair
    n_checks = k_c.shape[0]
    for k in range(K):
        uk, vk, sk = u[k], v[k], s[k]
        # --- occlusion jumps among the checked pairs of this fan; their shadow cover
        jump[:] = False
        cover[:] = 0
        any_jump = False
        while c < n_checks and k_c[c] == k:
            j = j_c[c]
            ra, rb = rho[k, j], rho[k, j + 1]
            dr = abs(rb - ra)
            lin_mid = half * (ra + rb)
            rm = rho_mid[c]
            if rm != rm or abs(rm - lin_mid) > jump_tol * dr:
                jump[j] = True
                any_jump = True
                k0, k1 = kbin[k, j], kbin[k, j + 1]
                cover[min(k0, k1)] += 1
                cover[max(k0, k1)] -= 1
            c += 1
        # --- every (pair, bin) crossing; per bin the winner so far
        has[:] = False
        # the pairs that cross a bin (both rays hit, no occlusion jump), listed first in
        # a tight loop: about a quarter of the pairs
        n_x = 0
        for j in range(M - 1):
            if kbin[k, j] != kbin[k, j + 1]:
                ra32, rb32 = rho[k, j], rho[k, j + 1]
                if ra32 == ra32 and rb32 == rb32 and not jump[j]:
                    crossing[n_x] = j
                    n_x += 1
        for i_x in range(n_x):
            j = crossing[i_x]
            ra32, rb32 = rho[k, j], rho[k, j + 1]
            ka, kb = kbin[k, j], kbin[k, j + 1]
            ra, rb = np.float64(ra32), np.float64(rb32)
            ta, tb = np.float64(theta[k, j]), np.float64(theta[k, j + 1])
            tri_a, tri_b = tri[k, j], tri[k, j + 1]
            strength = abs(tb - ta) / abs(rb - ra)
            t_mid = 0.5 * (ta + tb)
            t_half = 0.55 * abs(tb - ta) + 1e-12
            # the first ray's direction: roots more than 90 degrees away cannot lie in a
            # bracket narrower than 1 rad (|t - t_mid| > pi / 2 - 0.5 - 1e-6 > t_half)
            if abs(tb - ta) < 1.0:
                ca0, sa0 = np.float64(cs[k, j, 0]), np.float64(cs[k, j, 1])
                # nor can roots more than phi away: |t - t_mid| > t_half + _EPS_T + 1e-6
                # (the series' error); tested as |cross| > tan(phi) dot, with margins for
                # the float32 direction (< 4e-7 rad) and rounding, and the upper bound
                # phi / (1 - phi^2 / 2.4) >= tan(phi) (phi < 1.5): no atan2 for them
                phi = 1.05 * abs(tb - ta) + 2e-5
                far = 1.0001 * phi / (1.0 - phi * phi / 2.4)
            else:
                ca0, sa0, far = 0.0, 0.0, np.inf  # (dot = 0: far * dot is NaN)
            n_faces = 2 if tri_a != tri_b else 1
            for f in range(n_faces):  # per face: _Roots.update's terms that skip r
                A, Bc, C = _arc_abc(face_planes, tri_a if f == 0 else tri_b, uk, vk, sk)
                k2 = A * A + Bc * Bc
                fc[f, 0], fc[f, 1], fc[f, 2], fc[f, 3] = A, Bc, k2, C * C
                fc[f, 4], fc[f, 5], fc[f, 6] = 1.0 / k2, C * A, C * Bc
            for b in range(min(ka, kb), max(ka, kb)):
                r = range_m[b]
                theta_lin = ta + (r - ra) / (rb - ra) * (tb - ta)
                # _Roots.update, face a's two roots then face b's: the root nearest
                # theta_lin within t_mid +- t_half, the first of equals
                found, from_b = False, False
                bt, bd, by, bz, bexact = 0.0, np.inf, 0.0, 0.0, True
                for f in range(n_faces):
                    A, Bc, k2, cc = fc[f, 0], fc[f, 1], fc[f, 2], fc[f, 3]
                    inv, ca, cb = fc[f, 4], fc[f, 5], fc[f, 6]
                    w = np.sqrt(r * r * k2 - cc)  # NaN where no root
                    wa, wb = w * A, w * Bc
                    for sign in range(2):
                        if sign == 0:
                            y = (ca - wb) * inv
                            z = (cb + wa) * inv
                        else:
                            y = (ca + wb) * inv
                            z = (cb - wa) * inv
                        dot = y * ca0 + z * sa0
                        if dot < 0.0 or abs(ca0 * z - sa0 * y) > far * dot:
                            continue  # far outside the bracket
                        t, exact = _root_angle(y, z, ca0, sa0, ta)
                        e = 0.0 if exact else _EPS_T
                        dm = abs(t - t_mid)
                        if not dm <= t_half + e:  # (NaN: no root)
                            continue
                        if not exact and dm > t_half - e:
                            t, exact, e = math.atan2(z, y), True, 0.0
                            if not abs(t - t_mid) <= t_half:
                                continue
                        d = abs(t - theta_lin)
                        if found:
                            eb = 0.0 if bexact else _EPS_T
                            if not d + e < bd - eb:  # not surely nearer
                                if d - e >= bd + eb:
                                    continue  # surely not nearer
                                if not exact:
                                    t, exact = math.atan2(z, y), True
                                    d = abs(t - theta_lin)
                                if not bexact:
                                    bt, bexact = math.atan2(bz, by), True
                                    bd = abs(bt - theta_lin)
                                if not d < bd:
                                    continue
                        found = True
                        from_b = f == 1
                        bt, bd, by, bz, bexact = t, d, y, z, exact
                if found:
                    y, z = by, bz
                    # in the beam: decided by the exact angle where it is near a limit
                    if not bexact and (abs(bt - th_min) <= _EPS_T or abs(bt - th_max) <= _EPS_T):
                        bt = math.atan2(bz, by)
                    theta_hit = bt
                else:  # no root in the bracket: the interpolated angle
                    theta_hit = theta_lin
                    y = r * math.cos(theta_lin)
                    z = r * math.sin(theta_lin)
                    from_b = abs(ra - r) > abs(rb - r)  # the nearer ray's face
                in_beam = theta_hit >= th_min and theta_hit <= th_max
                # layover: the last by (in_beam, strength, position in the fan) wins
                if has[b]:
                    if w_inb[b] and not in_beam:
                        continue
                    if in_beam == w_inb[b] and not _nan_last_ge(strength, w_str[b]):
                        continue
                has[b] = True
                w_inb[b] = in_beam
                w_str[b] = strength
                w_y[b] = y
                w_z[b] = z
                w_tri[b] = tri_b if from_b else tri_a
        # --- the winners' points, normals (eq. 1-3) and grazing angles; the masks
        # fmin over the fan's first hits, as four independent running minima (one chain
        # of compares would be latency-bound; the least hit is the same in any order)
        m0, m1, m2, m3 = np.nan, np.nan, np.nan, np.nan
        j4 = M - M % 4
        for j in range(0, j4, 4):
            x0, x1, x2, x3 = rho[k, j], rho[k, j + 1], rho[k, j + 2], rho[k, j + 3]
            if x0 == x0 and (m0 != m0 or x0 < m0):
                m0 = x0
            if x1 == x1 and (m1 != m1 or x1 < m1):
                m1 = x1
            if x2 == x2 and (m2 != m2 or x2 < m2):
                m2 = x2
            if x3 == x3 and (m3 != m3 or x3 < m3):
                m3 = x3
        nearest = np.nan
        for x in (m0, m1, m2, m3):
            if x == x and (nearest != nearest or x < nearest):
                nearest = x
        for j in range(j4, M):
            x = rho[k, j]
            if x == x and (nearest != nearest or x < nearest):
                nearest = x
        nearest64 = np.float64(nearest)
        # (libm's hypot and acos in loops of their own: the main loop below then has
        # no calls, which spill its registers)
        for b in range(B):
            if has[b]:
                w_r[b] = math.hypot(w_y[b], w_z[b])
        shadow_count = 0
        w_ok[:] = False
        for b in range(B):
            if any_jump:
                shadow_count += cover[b]
            if has[b]:
                y, z = w_y[b], w_z[b]
                p0 = (y * uk[0] + z * vk[0]) - -sk[0]
                p1 = (y * uk[1] + z * vk[1]) - -sk[1]
                p2 = (y * uk[2] + z * vk[2]) - -sk[2]
                if use_grid:
                    fx = (p0 - grid_x0) / cell
                    fy = (p1 - grid_y0) / cell
                    if fx >= 0 and fx <= nx - 1 and fy >= 0 and fy <= ny - 1:
                        cx = min(max(np.floor(fx), 0.0), nx - 2.0)
                        cy = min(max(np.floor(fy), 0.0), ny - 2.0)
                        tx, ty = fx - cx, fy - cy
                        ix, iy = int(cx), int(cy)
                        gx = _bilinear(grad, iy, ix, 0, tx, ty)
                        gy = _bilinear(grad, iy, ix, 1, tx, ty)
                    else:
                        gx, gy = np.nan, np.nan
                    un = (uk[2] - uk[0] * gx) - uk[1] * gy
                    vn = (vk[2] - vk[0] * gx) - vk[1] * gy
                    normal_len = np.sqrt((1.0 + gx * gx) + gy * gy)
                else:
                    fn = face_normals[w_tri[b]]
                    n0, n1, n2 = fn[0], fn[1], fn[2]
                    d0, d1, d2 = sk[0] - p0, sk[1] - p1, sk[2] - p2
                    if (n0 * d0 + n2 * d2) + n1 * d1 < 0:
                        n0, n1, n2 = n0 * -1.0, n1 * -1.0, n2 * -1.0
                    nn = (n0 * n0 + n2 * n2) + n1 * n1
                    if nn == 0:
                        n0, n1, n2 = np.nan, np.nan, np.nan
                        nn = np.nan
                    un = (uk[0] * n0 + uk[2] * n2) + uk[1] * n1
                    vn = (vk[0] * n0 + vk[2] * n2) + vk[1] * n1
                    normal_len = np.sqrt(nn)
                norm = np.sqrt(un * un + vn * vn)
                if norm < 1e-12:
                    norm = 1e-12
                nlat = un / norm
                if math.isfinite(nlat):  # a normal: the bin is matched
                    den = normal_len * w_r[b]
                    if den < 1e-12:
                        den = 1e-12
                    cos_inc = -(y * un + z * vn) / den
                    if cos_inc < -1.0:
                        cos_inc = -1.0
                    elif cos_inc > 1.0:
                        cos_inc = 1.0
                    pts_out[k, b, 0] = p0
                    pts_out[k, b, 1] = p1
                    pts_out[k, b, 2] = p2
                    nlat_out[k, b] = nlat
                    w_ok[b] = True  # the grazing angle below
                    w_cos[b] = cos_inc
                    if not w_inb[b]:
                        mask_out[k, b] = mask_oob
                    continue
            # unmatched: water column, shadow of an occlusion, or no hit
            if range_m[b] < nearest64:
                mask_out[k, b] = mask_water
            elif shadow_count > 0:
                mask_out[k, b] = mask_shadow
            else:
                mask_out[k, b] = mask_no_hit
        for b in range(B):
            if w_ok[b]:
                graz_out[k, b] = np.pi / 2 - math.acos(w_cos[b])


@njit(**_JIT)
def draped_values_ok(mask, n_lat, points, bad_bits, valid, n_lat_max):  # pragma: no cover
    """Whether ``DrapedLine.validate``'s value checks pass, in one pass.

    Args:
        mask, n_lat, points: C-contiguous ``(P, 2, B)`` uint8, float32 and ``(P, 2, B, 3)``
            float32 arrays (shapes already checked).
        bad_bits: uint8 bits no mask may have; valid: the mask of a valid bin.
        n_lat_max: float32 bound of ``|n_lat|`` at valid bins (compared in float32, as
            numpy compares a float32 array with a Python float).

    Returns:
        True where no mask has a bad bit and every valid bin has ``|n_lat| <= n_lat_max``
        (not NaN) and three finite coordinates; False otherwise (numpy then names it).
    """
    m = mask.reshape(-1)
    nl = n_lat.reshape(-1)
    pts = points.reshape(-1)
    for i in range(m.shape[0]):
        mi = m[i]
        if mi & bad_bits:
            return False
        if mi == valid:
            if not abs(nl[i]) <= n_lat_max:
                return False
            p0, p1, p2 = pts[3 * i], pts[3 * i + 1], pts[3 * i + 2]
            if not (math.isfinite(p0) and math.isfinite(p1) and math.isfinite(p2)):
                return False
    return True
