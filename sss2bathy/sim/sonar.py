"""Sidescan physics: ray-traced fan beams, non-Lambertian backscatter, receiver chain.

One ping of one head is simulated by casting a dense fan of rays in the head's plane
(the isotemporal-arc directions of :func:`sss2bathy.geometry.arc_basis`) onto a triangle
mesh, keeping each ray's *first* hit (so occlusion makes shadows), and adding the echo
energy of every hit into the range bin of its slant range (so layover and the footprint
come from the geometry). The energy of a ray of angular weight ``w`` (rad) hitting at
slant range ``r`` with incidence ``i`` (angle between the true surface normal and the ray
back to the sonar) on material ``m`` with texture ``tau`` is::

    E = b(theta)^2 * sigma0_m(i) * tau * w / (r^2 cos i) * 10^(-2 alpha r / 10)

``b`` the one-way beam pattern over the depression angle ``theta``, ``sigma0`` the
backscattering cross-section per unit area (see :func:`backscatter`), ``r^2 w / cos i`` the
ensonified area of the ray (per unit along-track angle), ``1/r^4`` two-way spherical
spreading and ``alpha`` the absorption (dB/m, :func:`absorption_db_per_m`). The bins are
then put through a receiver (:func:`receive`): multiplicative speckle, additive noise,
time-varying gain, downsampling to the output bins, and quantisation.

Ray angles are importance-sampled: one stratified set uniform in flat-bottom slant range
(so every range bin gets rays) and one uniform in angle (so sloping surfaces get rays),
combined with the balance heuristic, which keeps the energy integral unbiased.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Protocol

import numpy as np

from sss2bathy.geometry import (
    arc_basis,
    check_rotations,
    head_plane_components,
    incidence_cosine,
)
from sss2bathy.sim.config import MaterialParams, SonarParams
from sss2bathy.survey import (
    MASK_NO_HIT,
    MASK_OUT_OF_BEAM,
    MASK_SHADOW,
    MASK_WATER_COLUMN,
)

NO_MATERIAL = 255
_SIDES = np.array([0, 1])
_MIN_COS_INCIDENCE = 1e-3


# ------------------------------------------------------------------------ water
def absorption_db_per_m(
    frequency_hz: float,
    temperature_c: float,
    salinity_ppt: float,
    ph: float = 8.0,
    depth_m: float = 10.0,
) -> float:
    """Sound absorption (dB/m, one way) after Ainslie & McColm (1998).

    Boric acid and magnesium sulphate relaxations (both vanish in fresh water) plus the
    viscous pure-water term, which dominates at sidescan frequencies.

    >>> round(absorption_db_per_m(850e3, 8.0, 35.0), 3)  # seawater, 850 kHz
    0.284
    >>> round(absorption_db_per_m(850e3, 8.0, 0.0), 3)  # fresh water
    0.239
    """
    if not frequency_hz > 0:
        raise ValueError(f"frequency_hz: expected > 0, found {frequency_hz}")
    if salinity_ppt < 0:
        raise ValueError(f"salinity_ppt: expected >= 0, found {salinity_ppt}")
    f = frequency_hz / 1e3
    t, s, z = temperature_c, salinity_ppt, depth_m / 1e3
    f1 = 0.78 * math.sqrt(s / 35.0) * math.exp(t / 26.0)
    f2 = 42.0 * math.exp(t / 17.0)
    boric = 0.106 * f1 * f * f / (f1 * f1 + f * f) * math.exp((ph - 8.0) / 0.56) if f1 > 0 else 0.0
    mgso4 = 0.52 * (1 + t / 43.0) * (s / 35.0) * f2 * f * f / (f2 * f2 + f * f) * math.exp(-z / 6)
    water = 0.00049 * f * f * math.exp(-(t / 27.0 + z / 17.0))
    return (boric + mgso4 + water) / 1e3


def sound_speed_mps(temperature_c: float, salinity_ppt: float, depth_m: float = 10.0) -> float:
    """Sound speed (m/s), Medwin (1975).

    >>> round(sound_speed_mps(8.0, 35.0), 1)
    1482.9
    """
    t, s = temperature_c, salinity_ppt
    return (
        1449.2
        + 4.6 * t
        - 0.055 * t * t
        + 0.00029 * t**3
        + (1.34 - 0.01 * t) * (s - 35.0)
        + 0.016 * depth_m
    )


# ------------------------------------------------------------------------ beam and seabed
def beam_pattern(theta: np.ndarray, sonar: SonarParams) -> np.ndarray:
    """One-way power beam pattern over the depression angle ``theta`` (rad), shape kept.

    ``max(exp(-ln2 |2 (theta - tilt) / width|^rolloff), 10^(sidelobe_db / 10))``: 1 on the
    beam axis, 1/2 (-3 dB) at the nominal edges ``tilt +- width / 2``.
    """
    u = np.abs(2.0 * (np.asarray(theta) - sonar.tilt_rad) / sonar.beam_width_rad)
    main = np.exp(-math.log(2.0) * u**sonar.beam_rolloff)
    return np.maximum(main, 10.0 ** (sonar.sidelobe_db / 10.0))


@dataclass(frozen=True)
class MaterialResponse:
    """Per-material angular backscatter parameters as arrays ``(M,)``."""

    names: tuple[str, ...]
    mu: np.ndarray
    exponent: np.ndarray
    specular: np.ndarray
    specular_width_rad: np.ndarray

    @classmethod
    def from_params(cls, materials: MaterialParams) -> MaterialResponse:
        c = materials.classes
        return cls(
            names=materials.names,
            mu=np.array([m.mu for m in c]),
            exponent=np.array([m.exponent for m in c]),
            specular=np.array([m.specular for m in c]),
            specular_width_rad=np.array([m.specular_width_rad for m in c]),
        )

    @classmethod
    def single(
        cls,
        mu: float = 1.0,
        exponent: float = 2.0,
        specular: float = 0.0,
        specular_width_rad: float = math.radians(6.0),
    ) -> MaterialResponse:
        """One material (index 0): handy for analytic tests."""
        return cls(
            ("uniform",),
            np.array([mu]),
            np.array([exponent]),
            np.array([specular]),
            np.array([specular_width_rad]),
        )


def backscatter(
    incidence_rad: np.ndarray, material: np.ndarray, response: MaterialResponse
) -> np.ndarray:
    """Backscattering cross-section per unit area, ``sigma0``; 0 for back-facing hits.

    ``sigma0 = mu_m cos(i)^p_m + s_m exp(-i^2 / (2 w_m^2))``: a diffuse term whose exponent
    depends on the material (Lambert's law is p = 2) plus a near-normal specular lobe.

    Args:
        incidence_rad: ``(N,)`` incidence angles (rad).
        material: ``(N,)`` integer material indices into ``response``.
    """
    inc = np.asarray(incidence_rad, dtype=np.float64)
    m = np.asarray(material)
    cos_i = np.clip(np.cos(inc), 0.0, 1.0)
    w = response.specular_width_rad[m]
    sigma = response.mu[m] * cos_i ** response.exponent[m] + response.specular[m] * np.exp(
        -0.5 * (inc / w) ** 2
    )
    return np.where(inc < math.pi / 2, sigma, 0.0)


def tvg_gain(range_m: np.ndarray, sonar: SonarParams, absorption: float) -> np.ndarray:
    """Time-varying (power) gain ``r^n 10^(2 k alpha r / 10)``."""
    r = np.asarray(range_m, dtype=np.float64)
    k = sonar.tvg_absorption_factor
    return r**sonar.tvg_spreading_exponent * 10.0 ** (2.0 * k * absorption * r / 10.0)


def range_bins(sonar: SonarParams) -> tuple[np.ndarray, np.ndarray]:
    """``(bin centres (B,), raw bin centres (B * oversampling,))`` in metres."""
    span = sonar.max_range_m - sonar.min_range_m
    final = sonar.min_range_m + (np.arange(sonar.n_bins) + 0.5) * span / sonar.n_bins
    raw = sonar.min_range_m + (np.arange(sonar.n_raw_bins) + 0.5) * span / sonar.n_raw_bins
    return final, raw


# ------------------------------------------------------------------------ ray casting
class RayCaster:
    """First-hit ray casting on a triangle mesh (embree, through trimesh).

    Hit distances are recomputed in float64 from the hit triangle's plane, so they are
    exact to double precision even though embree works in float32.
    """

    def __init__(self, mesh) -> None:  # mesh: trimesh.Trimesh
        if len(mesh.faces) == 0:
            raise ValueError("mesh: expected a mesh with faces, found none")
        from trimesh.ray.ray_pyembree import RayMeshIntersector

        self.mesh = mesh
        self._intersector = RayMeshIntersector(mesh)
        self._v0 = np.asarray(mesh.triangles[:, 0], dtype=np.float64)
        self._normals = np.asarray(mesh.face_normals, dtype=np.float64)
        self.z_max = float(mesh.bounds[1, 2])
        self.z_min = float(mesh.bounds[0, 2])
        # build the acceleration structure now rather than inside the first query
        self._intersector.intersects_first(np.zeros((1, 3)), np.array([[0.0, 0.0, 1.0]]))

    def face_normals(self, tri: np.ndarray) -> np.ndarray:
        """Unit normals ``(N, 3)`` of faces ``tri``."""
        return self._normals[tri]

    def first_hits(
        self, origins: np.ndarray, directions: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray]:
        """First hit of each ray.

        Args:
            origins: ``(N, 3)`` ray origins (m).
            directions: ``(N, 3)`` unit directions.

        Returns:
            ``tri (N,)`` int64 face index (-1: miss) and ``t (N,)`` float64 distance along
            the ray (NaN: miss).
        """
        origins = np.asarray(origins, dtype=np.float64)
        directions = np.asarray(directions, dtype=np.float64)
        if len(origins) == 0:
            return np.zeros(0, np.int64), np.zeros(0)
        tri = np.asarray(self._intersector.intersects_first(origins, directions), np.int64)
        t = np.full(len(tri), np.nan)
        ok = tri >= 0
        n = self._normals[tri[ok]]
        denom = np.einsum("ij,ij->i", n, directions[ok])
        num = np.einsum("ij,ij->i", n, self._v0[tri[ok]] - origins[ok])
        with np.errstate(divide="ignore", invalid="ignore"):
            t_ok = num / denom
        t_ok[~np.isfinite(t_ok) | (t_ok < 0)] = np.nan
        t[ok] = t_ok
        tri[~np.isfinite(t)] = -1
        return tri, t

    def altitudes(self, positions: np.ndarray) -> np.ndarray:
        """``(P,)`` distance straight down from each position to the mesh (NaN: none)."""
        down = np.tile([0.0, 0.0, -1.0], (len(positions), 1))
        return self.first_hits(positions, down)[1]


class Surface(Protocol):
    """What the simulator needs to know about the seabed at ray hits."""

    def normals(self, points: np.ndarray, tri: np.ndarray) -> np.ndarray:
        """``(N, 3)`` world normals (any length, pointing up) at hit ``points`` on faces ``tri``."""

    def materials(self, points: np.ndarray) -> np.ndarray:
        """``(N,)`` integer material index at ``points``."""

    def texture(self, points: np.ndarray) -> np.ndarray:
        """``(N,)`` reflectivity multiplier (mean ~1) at ``points``."""


# ------------------------------------------------------------------------ simulation
@dataclass
class PingEchoes:
    """Noise-free echoes of ``P`` pings and the simulator's per-bin ground truth.

    Attributes:
        power_raw: ``(P, 2, R)`` received power per raw range bin before TVG (arbitrary
            linear units), side 0 port / 1 starboard, bin 0 nearest.
        n_lat: ``(P, 2, B)`` energy-weighted head-plane normal of the first-visible hits in
            each output bin (NaN where the bin has no hit).
        points: ``(P, 2, B, 3)`` energy-weighted hit point of each bin (NaN where no hit).
        mask: ``(P, 2, B)`` uint8 mask bits (water column, shadow, no hit, out of beam).
        material: ``(P, 2, B)`` uint8 dominant material of each bin (255 where no hit).
        first_return_m: ``(P, 2)`` slant range of the nearest hit (inf where none).
    """

    power_raw: np.ndarray
    n_lat: np.ndarray
    points: np.ndarray
    mask: np.ndarray
    material: np.ndarray
    first_return_m: np.ndarray


def fan_basis(rotations: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per ping and side, the world directions of depression 0 and pi/2 in the head's plane.

    ``e_out = u`` and ``e_down = -w`` of :func:`sss2bathy.geometry.arc_basis`, so the ray
    direction at depression ``theta`` is ``cos(theta) e_out + sin(theta) e_down``, exactly
    the arc direction ``R [0, sigma cos(theta), -sin(theta)]`` of eq. 10.

    Args:
        rotations: ``(P, 3, 3)`` vehicle -> world.

    Returns:
        ``e_out``, ``e_down``: ``(P, 2, 3)`` each (side 0 port, 1 starboard).
    """
    u, w = arc_basis(np.asarray(rotations)[:, None], _SIDES)
    return u, np.ascontiguousarray(-w)


def _stratified(rng: np.random.Generator, shape: tuple[int, ...], n: int) -> np.ndarray:
    """``shape + (n,)`` jittered stratified samples in [0, 1)."""
    return (np.arange(n) + rng.random((*shape, n))) / n


def ray_fan(
    altitudes: np.ndarray,
    theta_lo: np.ndarray,
    theta_hi: np.ndarray,
    sonar: SonarParams,
    rng: np.random.Generator,
) -> tuple[np.ndarray, np.ndarray]:
    """Depression angles and angular weights of the rays of ``P`` pings, both heads.

    Two stratified sets combined with the balance heuristic: ``N_A`` rays uniform in
    flat-bottom slant range ``r in [h, 1.15 R_max]`` (``theta = asin(h / r)``) and ``N_B``
    uniform in ``theta in [theta_lo, theta_hi]``. The weight of a ray is
    ``1 / (N_A p_A(theta) + N_B p_B(theta))`` so ``sum_j f(theta_j) w_j`` estimates
    ``int f dtheta`` over ``[theta_lo, theta_hi]`` without bias.

    Args:
        altitudes: ``(P,)`` altitude (m) used for the range-uniform set.
        theta_lo, theta_hi: ``(P,)`` angular interval to cover (rad).

    Returns:
        ``theta (P, 2, N)`` and ``weight (P, 2, N)`` (rad); weight 0 marks rays to skip.
    """
    h = np.asarray(altitudes, dtype=np.float64)[:, None, None]
    lo, hi = theta_lo[:, None, None], theta_hi[:, None, None]
    r_far = 1.15 * sonar.max_range_m
    raw_width = (sonar.max_range_m - sonar.min_range_m) / sonar.n_raw_bins
    span = max(r_far - float(np.min(h)), raw_width)
    n_a = max(int(math.ceil(sonar.rays_per_raw_bin * span / raw_width)), 1)
    f = sonar.theta_ray_fraction
    n_b = max(int(math.ceil(n_a * f / (1.0 - f))), 1)
    P = len(altitudes)
    h_c = np.minimum(h, 0.999 * r_far)
    r = h_c + _stratified(rng, (P, 2), n_a) * (r_far - h_c)
    theta_a = np.arcsin(np.clip(h_c / r, -1.0, 1.0))
    theta_b = lo + _stratified(rng, (P, 2), n_b) * (hi - lo)
    theta = np.concatenate([theta_a, theta_b], axis=-1)

    sin_t, cos_t = np.sin(theta), np.cos(theta)
    in_a = (theta >= np.arcsin(h_c / r_far)) & (theta <= math.pi / 2)
    with np.errstate(divide="ignore", invalid="ignore"):
        p_a = np.where(in_a, h_c * cos_t / (sin_t**2 * (r_far - h_c)), 0.0)
    in_b = (theta >= lo) & (theta <= hi)
    p_b = np.where(in_b, 1.0 / (hi - lo), 0.0)
    density = n_a * p_a + n_b * p_b
    weight = np.where(in_b & (density > 0), 1.0 / np.where(density > 0, density, 1.0), 0.0)
    return theta, weight


def simulate_pings(
    caster: RayCaster,
    surface: Surface,
    positions: np.ndarray,
    rotations: np.ndarray,
    sonar: SonarParams,
    response: MaterialResponse,
    rng: np.random.Generator,
    *,
    absorption_db_m: float,
    altitudes: np.ndarray | None = None,
    chunk_pings: int = 32,
) -> PingEchoes:
    """Ray-trace ``P`` pings of both heads and accumulate their echoes into range bins.

    The ray fans of ``chunk_pings`` pings go to the ray caster in one call.

    Args:
        caster: ray caster of the seabed mesh.
        surface: normals, materials and texture of the seabed at hits.
        positions: ``(P, 3)`` sonar positions (world ENU, m).
        rotations: ``(P, 3, 3)`` vehicle -> world rotations.
        sonar: sensor parameters (beam, bins, rays).
        response: per-material backscatter; ``surface.materials`` indexes it.
        rng: random generator (ray jitter).
        absorption_db_m: one-way absorption (dB/m).
        altitudes: ``(P,)`` altitudes used to place the rays (cast straight down if None).
        chunk_pings: pings per ray-casting call.

    Returns:
        :class:`PingEchoes` (noise-free power and ground truth).
    """
    positions = np.asarray(positions, dtype=np.float64)
    rotations = np.asarray(rotations, dtype=np.float64)
    if positions.ndim != 2 or positions.shape[1] != 3 or not np.isfinite(positions).all():
        raise ValueError(f"positions: expected a finite (P, 3) array, found {positions.shape}")
    P = positions.shape[0]
    if rotations.shape != (P, 3, 3) or not check_rotations(rotations).numpy().all():
        raise ValueError(
            f"rotations: expected ({P}, 3, 3) rotation matrices, found {rotations.shape}"
        )
    if altitudes is None:
        altitudes = caster.altitudes(positions)
    altitudes = np.asarray(altitudes, dtype=np.float64)
    if altitudes.shape != (P,):
        raise ValueError(f"altitudes: expected shape ({P},), found {altitudes.shape}")
    altitudes = np.where(np.isfinite(altitudes) & (altitudes > 0), altitudes, sonar.max_range_m)
    if chunk_pings < 1:
        raise ValueError(f"chunk_pings: expected >= 1, found {chunk_pings}")
    if len(response.mu) == 0:
        raise ValueError("response: expected at least one material, found none")

    B, R = sonar.n_bins, sonar.n_raw_bins
    out = PingEchoes(
        power_raw=np.zeros((P, 2, R)),
        n_lat=np.full((P, 2, B), np.nan, np.float32),
        points=np.full((P, 2, B, 3), np.nan, np.float32),
        mask=np.zeros((P, 2, B), np.uint8),
        material=np.full((P, 2, B), NO_MATERIAL, np.uint8),
        first_return_m=np.full((P, 2), np.inf),
    )
    for start in range(0, P, chunk_pings):
        sl = slice(start, min(start + chunk_pings, P))
        _simulate_chunk(
            caster, surface, positions[sl], rotations[sl], altitudes[sl], sonar, response,
            rng, absorption_db_m, out, sl,
        )  # fmt: skip
    return out


def _simulate_chunk(
    caster: RayCaster,
    surface: Surface,
    s: np.ndarray,
    R: np.ndarray,
    h: np.ndarray,
    sonar: SonarParams,
    response: MaterialResponse,
    rng: np.random.Generator,
    absorption: float,
    out: PingEchoes,
    sl: slice,
) -> None:
    Pc = len(s)
    B, Rn, M = sonar.n_bins, sonar.n_raw_bins, len(response.mu)
    r_min, r_max = sonar.min_range_m, sonar.max_range_m
    # Angle of the vehicle's up axis from the vertical: bounds the roll/pitch of the fan.
    tilt_v = np.arccos(np.clip(R[:, 2, 2], -1.0, 1.0))
    h_top = np.maximum(s[:, 2] - caster.z_max, 0.05)
    theta_lo = np.clip(
        np.arctan2(h_top, 1.02 * r_max) - tilt_v - math.radians(0.5), math.radians(0.2), None
    )
    theta_hi = math.pi / 2 + tilt_v + math.radians(1.0)
    theta, weight = ray_fan(h, theta_lo, theta_hi, sonar, rng)
    side = np.broadcast_to(np.array([0, 1])[None, :, None], theta.shape)
    e_out, e_down = fan_basis(R)
    directions = (
        np.cos(theta)[..., None] * e_out[:, :, None] + np.sin(theta)[..., None] * e_down[:, :, None]
    )
    ping = np.broadcast_to(np.arange(Pc)[:, None, None], theta.shape)
    cast = weight.ravel() > 0
    theta_c, w_c = theta.ravel()[cast], weight.ravel()[cast]
    side_c, ping_c = side.ravel()[cast], ping.ravel()[cast]
    d_c = directions.reshape(-1, 3)[cast]
    o_c = s[ping_c]
    tri, t = caster.first_hits(o_c, d_c)
    ps_c = ping_c * 2 + side_c

    hit = np.isfinite(t)
    first = np.full(Pc * 2, np.inf)
    far = np.full(Pc * 2, -np.inf)
    np.minimum.at(first, ps_c[hit], t[hit])
    np.maximum.at(far, ps_c[hit], t[hit])
    out.first_return_m[sl] = first.reshape(Pc, 2)

    keep = hit & (t >= r_min) & (t < r_max)
    t, tri, theta_c, w_c = t[keep], tri[keep], theta_c[keep], w_c[keep]
    ps, d, ping_k = ps_c[keep], d_c[keep], ping_c[keep]
    pts = s[ping_k] + t[:, None] * d

    normals = np.asarray(surface.normals(pts, tri), dtype=np.float64)
    normals = normals / np.linalg.norm(normals, axis=1, keepdims=True)
    cos_i = incidence_cosine(normals, pts, s[ping_k])
    incidence = np.arccos(np.clip(cos_i, -1.0, 1.0))
    material = np.asarray(surface.materials(pts), dtype=np.int64)
    sigma = backscatter(incidence, material, response) * surface.texture(pts)
    energy = (
        beam_pattern(theta_c, sonar) ** 2
        * sigma
        * w_c
        / (t * t * np.maximum(cos_i, _MIN_COS_INCIDENCE))
        * 10.0 ** (-0.2 * absorption * t)
    )

    # Raw bins: linear (tent) splat between the two nearest raw-bin centres, kept inside
    # the hit's output bin so that output-bin energy and ground truth see the same hits.
    b = np.clip(((t - r_min) / ((r_max - r_min) / B)).astype(np.int64), 0, B - 1)
    k = sonar.oversampling
    raw_width = (r_max - r_min) / Rn
    f = (t - r_min) / raw_width - 0.5
    i0 = np.floor(f).astype(np.int64)
    a = f - i0
    first_raw, last_raw = b * k, b * k + k - 1
    n_raw = Pc * 2 * Rn
    power = np.bincount(ps * Rn + np.clip(i0, first_raw, last_raw), energy * (1 - a), n_raw)
    power += np.bincount(ps * Rn + np.clip(i0 + 1, first_raw, last_raw), energy * a, n_raw)
    out.power_raw[sl] = power.reshape(Pc, 2, Rn)

    truth = _bin_truth(
        ps * B + b, Pc * 2 * B, energy, w_c, theta_c, normals, pts, material, R, ps, sonar, M
    )
    n_lat, points, dominant, has_hit, beam_frac = truth
    mask = _bin_masks(has_hit, beam_frac, first, far, range_bins(sonar)[0])
    out.mask[sl] = mask.reshape(Pc, 2, B)
    out.n_lat[sl] = n_lat.reshape(Pc, 2, B)
    out.points[sl] = points.reshape(Pc, 2, B, 3)
    out.material[sl] = dominant.reshape(Pc, 2, B)


def _bin_truth(
    key: np.ndarray,
    n_key: int,
    energy: np.ndarray,
    weight: np.ndarray,
    theta: np.ndarray,
    normals: np.ndarray,
    points: np.ndarray,
    material: np.ndarray,
    R: np.ndarray,
    ps: np.ndarray,
    sonar: SonarParams,
    n_materials: int,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Per-bin ground truth from the hits (``key`` = ping-side * B + bin).

    ``n_lat``: the energy-weighted mean of the hits' head-plane normals ``(n_lat, n_up)``,
    renormalised (geometric ray weights where every hit of the bin carries zero energy);
    ``points``: the same mean of the hit points; the dominant (most energy) material; and
    the geometric fraction of the bin's rays inside the nominal beam.
    """
    u, w = arc_basis(R[:, None], _SIDES)  # (P, 2, 3) each
    hit_lat, hit_up = head_plane_components(normals, u.reshape(-1, 3)[ps], w.reshape(-1, 3)[ps])
    count = np.bincount(key, minlength=n_key)
    has_hit = count > 0
    e_sum = np.bincount(key, energy, n_key)
    wt = np.where((e_sum > 0)[key], energy, weight)
    w_sum = np.bincount(key, wt, n_key)
    lo, hi = sonar.beam_limits_rad
    in_beam = (theta >= lo) & (theta <= hi)
    with np.errstate(divide="ignore", invalid="ignore"):
        lat = np.bincount(key, wt * hit_lat, n_key) / w_sum
        up = np.bincount(key, wt * hit_up, n_key) / w_sum
        n_lat = np.where(has_hit, lat / np.sqrt(lat * lat + up * up), np.nan)
        pts = np.stack([np.bincount(key, wt * points[:, j], n_key) / w_sum for j in range(3)], -1)
        beam_frac = np.bincount(key, weight * in_beam, n_key) / np.bincount(key, weight, n_key)
    pts[~has_hit] = np.nan
    per_material = np.bincount(key * n_materials + material, energy + 1e-300, n_key * n_materials)
    dominant = np.where(has_hit, per_material.reshape(n_key, n_materials).argmax(1), NO_MATERIAL)
    return (
        n_lat.astype(np.float32),
        pts.astype(np.float32),
        dominant.astype(np.uint8),
        has_hit,
        beam_frac,
    )


def _bin_masks(
    has_hit: np.ndarray,
    beam_frac: np.ndarray,
    first: np.ndarray,
    far: np.ndarray,
    r_bin: np.ndarray,
) -> np.ndarray:
    """Mask bits ``(S, B)`` for ``S`` ping-sides from where their hits fell.

    No hit and nearer than the first return: water column; no hit between the first and
    the farthest return (occluded): shadow; no hit beyond every return (or no return at
    all): no hit; hits mostly from rays outside the nominal beam: out of beam.
    """
    S, B = len(first), len(r_bin)
    has_hit = has_hit.reshape(S, B)
    empty = ~has_hit
    any_hit = np.isfinite(first)[:, None]
    before = r_bin[None, :] < first[:, None]
    beyond = r_bin[None, :] >= far[:, None]
    water = empty & any_hit & before
    shadow = empty & any_hit & ~before & ~beyond
    mask = np.zeros((S, B), np.uint8)
    mask[water] |= MASK_WATER_COLUMN
    mask[shadow] |= MASK_SHADOW
    mask[empty & ~water & ~shadow] |= MASK_NO_HIT
    with np.errstate(invalid="ignore"):
        mask[has_hit & (beam_frac.reshape(S, B) < 0.5)] |= MASK_OUT_OF_BEAM
    return mask


# ------------------------------------------------------------------------ receiver
@dataclass(frozen=True)
class ReceiverCalibration:
    """Fixed receiver settings of a survey: output gain and noise power (raw-bin units)."""

    gain: float
    noise_power: float
    reference_altitude_m: float
    reference_range_m: float


def flat_bottom_power(
    range_m: np.ndarray,
    altitude_m: float,
    sonar: SonarParams,
    response: MaterialResponse,
    material: int,
    absorption_db_m: float,
) -> np.ndarray:
    """Expected raw-bin power (pre-TVG) of a flat, untextured bottom seen without roll.

    The continuous version of the ray sum of :func:`simulate_pings`: at slant range ``r``
    the bottom is at depression ``theta = asin(h / r)`` with incidence ``pi/2 - theta``,
    and a raw bin of width ``dr`` spans ``dtheta = h dr / (r^2 cos theta)``. 0 for
    ``r <= h``.
    """
    r = np.asarray(range_m, dtype=np.float64)
    h = float(altitude_m)
    if not h > 0:
        raise ValueError(f"altitude_m: expected > 0, found {altitude_m}")
    dr = (sonar.max_range_m - sonar.min_range_m) / sonar.n_raw_bins
    ok = r > h * (1 + 1e-9)
    rs = np.where(ok, r, 2 * h)
    sin_t = h / rs
    cos_t = np.sqrt(1 - sin_t**2)
    theta = np.arcsin(sin_t)
    incidence = math.pi / 2 - theta
    sigma = backscatter(incidence, np.full(r.shape, material), response)
    e = (
        beam_pattern(theta, sonar) ** 2
        * sigma
        / (rs * rs * sin_t)
        * 10 ** (-0.2 * absorption_db_m * rs)
    )
    return np.where(ok, e * h * dr / (rs * rs * cos_t), 0.0)


def calibrate_receiver(
    sonar: SonarParams,
    response: MaterialResponse,
    reference_material: int,
    altitude_m: float,
    absorption_db_m: float,
) -> ReceiverCalibration:
    """Gain and noise floor from a reference flat bottom at ``altitude_m``.

    The gain maps the TVG-corrected amplitude of the reference bottom on the beam axis to
    ``sonar.reference_level``; the noise power is the reference echo at 98 % of the maximum
    range divided by ``10^(snr_db / 10)``.
    """
    h = float(altitude_m)
    r_max = sonar.max_range_m
    r_ref = float(np.clip(h / math.sin(max(sonar.tilt_rad, 1e-3)), 1.2 * h, 0.9 * r_max))
    r_far = 0.98 * r_max if 0.98 * r_max > 1.05 * h else r_ref
    p = flat_bottom_power(
        np.array([r_ref, r_far]), h, sonar, response, reference_material, absorption_db_m
    )
    if not p[0] > 0:
        raise ValueError(
            f"altitude_m: the reference bottom at {h} m must lie within the range "
            f"({sonar.min_range_m}, {r_max}) m of the sonar"
        )
    gain = sonar.reference_level / math.sqrt(p[0] * tvg_gain(r_ref, sonar, absorption_db_m))
    noise = float(p[1]) / 10.0 ** (sonar.snr_db / 10.0)
    return ReceiverCalibration(gain, noise, h, r_ref)


def receive(
    power_raw: np.ndarray,
    sonar: SonarParams,
    calibration: ReceiverCalibration,
    rng: np.random.Generator,
    absorption_db_m: float,
) -> np.ndarray:
    """The receiver chain: raw echoes -> recorded waterfall ``(P, 2, B)`` float32 in [0, 1].

    Per raw bin: gamma speckle (mean 1, ``speckle_looks`` looks) on the echo, plus
    exponential noise power (complex Gaussian noise); then TVG, averaging of
    ``oversampling`` raw bins per output bin, amplitude (square root), gain, clipping to
    full scale and quantisation to ``2^bits - 1`` levels.
    """
    p = np.asarray(power_raw, dtype=np.float64)
    if p.ndim != 3 or p.shape[1:] != (2, sonar.n_raw_bins):
        raise ValueError(f"power_raw: expected (P, 2, {sonar.n_raw_bins}), found {p.shape}")
    looks = sonar.speckle_looks
    speckle = rng.gamma(looks, 1.0 / looks, size=p.shape)
    noise = rng.exponential(calibration.noise_power, size=p.shape)
    raw_r = range_bins(sonar)[1]
    total = (p * speckle + noise) * tvg_gain(raw_r, sonar, absorption_db_m)
    total = total.reshape(p.shape[0], 2, sonar.n_bins, sonar.oversampling).mean(axis=-1)
    amplitude = np.clip(calibration.gain * np.sqrt(total), 0.0, 1.0)
    levels = float(2**sonar.quantisation_bits - 1)
    return (np.round(amplitude * levels) / levels).astype(np.float32)
