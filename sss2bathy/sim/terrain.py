"""Synthetic seafloor: heights, a coherent material map and per-material texture.

Heights combine a regional slope, multi-scale smooth relief (Gaussian random fields),
meandering rock ridges and clustered boulders (ellipsoidal caps, power-law sizes).
Boulder flanks and ridge slopes give the long tail of the head-plane normal ``n_lat``;
the relief keeps most of it small. The material map thresholds a smooth random field
(coupled to the relief, so mud collects in hollows) by the configured class fractions;
boulders and ridges are rock. Texture is a sub-MBES-resolution reflectivity multiplier
(log-normal noise at a per-material scale, plus sand ripples). Optional wreck-like objects
(boxes, ship hulls: ``terrain.objects``) stand on the finished seabed with near-vertical
sides, so the ray-traced sidescan gives them bright faces and real shadows.
"""

from __future__ import annotations

import dataclasses
import math
import warnings
from dataclasses import dataclass

import numpy as np

from sss2bathy.geometry import attitude_to_rotation, head_plane_normal_from_gradient
from sss2bathy.sim.config import GridTerrainParams, MaterialParams, ObjectParams, TerrainParams
from sss2bathy.survey import BathyGrid


@dataclass
class Terrain:
    """The true seafloor on a regular grid whose SW cell centre is the frame origin.

    Attributes:
        heights: ``(ny, nx)`` heights z (m, negative), row 0 south.
        cell_m: cell size (m).
        materials: ``(ny, nx)`` uint8 material index per cell.
        material_names: names of the material indices.
        texture: ``(tny, tnx)`` float32 reflectivity multiplier on a finer grid.
        texture_cell_m: its cell size (m).
        boulders: ``(K, 4)`` boulder centre x, y (m), diameter (m), height (m).
        no_seabed: ``(ny, nx)`` bool, cells without seabed (a grid terrain's large holes and
            its outside; ``heights`` there are the nearest valid height, for normals and
            altitudes only, and the mesh leaves them out); None: seabed everywhere.
        source: the real grid it was made from (:class:`GridSource`); None: procedural.
    """

    heights: np.ndarray
    cell_m: float
    materials: np.ndarray
    material_names: tuple[str, ...]
    texture: np.ndarray
    texture_cell_m: float
    boulders: np.ndarray
    no_seabed: np.ndarray | None = None
    source: GridSource | None = None

    def __post_init__(self) -> None:
        self.heights = np.asarray(self.heights, dtype=np.float64)
        if not np.isfinite(self.heights).all():
            raise ValueError("heights: expected finite heights (mark holes in no_seabed)")
        if self.no_seabed is not None and self.no_seabed.shape != self.heights.shape:
            raise ValueError(
                f"no_seabed: expected shape {self.heights.shape}, found {self.no_seabed.shape}"
            )
        dzdy, dzdx = np.gradient(self.heights, self.cell_m)
        self.dzdx, self.dzdy = dzdx, dzdy
        self._up_normal = np.stack([-dzdx, -dzdy, np.ones_like(dzdx)], axis=-1)

    @property
    def seabed(self) -> np.ndarray:
        """``(ny, nx)`` bool, cells with seabed."""
        if self.no_seabed is None:
            return np.ones(self.heights.shape, bool)
        return ~self.no_seabed

    @property
    def extent_m(self) -> tuple[float, float]:
        """``(width, height)`` between the outer cell centres (m)."""
        ny, nx = self.heights.shape
        return (nx - 1) * self.cell_m, (ny - 1) * self.cell_m

    def grid(self, crs: str | None = None) -> BathyGrid:
        """The true heights as a :class:`BathyGrid` (no MBES noise; NaN without seabed)."""
        heights = self.heights.astype(np.float32)
        if self.no_seabed is not None:
            heights[self.no_seabed] = np.nan
        return BathyGrid(heights, 0.0, 0.0, self.cell_m, crs)

    def sample_heights(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        """Bilinear true heights at ``(x, y)`` (clamped to the grid)."""
        return bilinear(self.heights, self.cell_m, x, y)

    def to_mesh(self):  # -> trimesh.Trimesh
        return self.grid().to_mesh()


def bilinear(values: np.ndarray, cell: float, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Bilinear interpolation of a grid ``(ny, nx[, k])`` whose cell ``[0, 0]`` is centred at
    the origin; returns ``x.shape[, k]``.

    Same interpolation as :meth:`BathyGrid.sample`, but clamped to the edge cells instead
    of returning NaN outside.
    """
    ny, nx = values.shape[:2]
    fx = np.clip(np.asarray(x, dtype=np.float64) / cell, 0.0, nx - 1.0)
    fy = np.clip(np.asarray(y, dtype=np.float64) / cell, 0.0, ny - 1.0)
    ix = np.minimum(fx.astype(np.int64), nx - 2)
    iy = np.minimum(fy.astype(np.int64), ny - 2)
    tx, ty = fx - ix, fy - iy
    flat = values.reshape(ny * nx, -1)
    i00 = iy * nx + ix
    if values.ndim == 3:
        tx, ty = tx[..., None], ty[..., None]
    else:
        flat = flat[:, 0]
    return (
        np.take(flat, i00, axis=0) * (1 - tx) * (1 - ty)
        + np.take(flat, i00 + 1, axis=0) * tx * (1 - ty)
        + np.take(flat, i00 + nx, axis=0) * (1 - tx) * ty
        + np.take(flat, i00 + nx + 1, axis=0) * tx * ty
    )


class TerrainSurface:
    """:class:`sss2bathy.sim.sonar.Surface` of a :class:`Terrain`.

    Normals come from the bilinearly sampled central-difference gradient of the true
    heights (``[-dz/dx, -dz/dy, 1]``, the same gradient :meth:`BathyGrid.sample_gradient`
    gives), materials from the nearest cell, texture bilinearly.
    """

    def __init__(self, terrain: Terrain) -> None:
        self.terrain = terrain

    def normals(self, points: np.ndarray, tri: np.ndarray) -> np.ndarray:
        t = self.terrain
        return bilinear(t._up_normal, t.cell_m, points[:, 0], points[:, 1])

    def materials(self, points: np.ndarray) -> np.ndarray:
        t = self.terrain
        ny, nx = t.materials.shape
        ix = np.clip(np.rint(points[:, 0] / t.cell_m).astype(np.int64), 0, nx - 1)
        iy = np.clip(np.rint(points[:, 1] / t.cell_m).astype(np.int64), 0, ny - 1)
        return t.materials[iy, ix].astype(np.int64)

    def texture(self, points: np.ndarray) -> np.ndarray:
        t = self.terrain
        return bilinear(t.texture, t.texture_cell_m, points[:, 0], points[:, 1])


# ---------------------------------------------------------------------- random fields
def gaussian_field(
    rng: np.random.Generator, shape: tuple[int, int], sigma_cells: float
) -> np.ndarray:
    """Zero-mean, unit-variance Gaussian random field with a Gaussian covariance.

    White noise filtered (by FFT, on a padded domain so that the periodic wrap does not
    correlate opposite edges) with a Gaussian kernel of ``sigma_cells``; normalised by the
    exact variance of the filter, not by the sample, so large-scale fields on small
    domains keep their amplitude.
    """
    if sigma_cells <= 0:
        raise ValueError(f"sigma_cells: expected > 0, found {sigma_cells}")
    pad = int(math.ceil(3 * sigma_cells))
    ny, nx = shape[0] + 2 * pad, shape[1] + 2 * pad
    noise = rng.standard_normal((ny, nx))
    ky = np.fft.fftfreq(ny)[:, None]
    kx = np.fft.rfftfreq(nx)[None, :]
    filt = np.exp(-2.0 * math.pi**2 * sigma_cells**2 * (kx * kx + ky * ky))
    field = np.fft.irfft2(np.fft.rfft2(noise) * filt, s=(ny, nx))
    # Parseval: variance of filtered unit white noise = mean |H|^2 over the full spectrum.
    full = np.exp(-2.0 * math.pi**2 * sigma_cells**2 * (np.fft.fftfreq(nx)[None, :] ** 2 + ky**2))
    std = math.sqrt(float(np.mean(full**2)))
    return field[pad : pad + shape[0], pad : pad + shape[1]] / std


def smooth_noise_1d(rng: np.random.Generator, n: int, sigma_samples: float) -> np.ndarray:
    """Unit-variance smooth noise of ``n`` samples (Gaussian-filtered white noise)."""
    from scipy.ndimage import gaussian_filter1d

    if sigma_samples <= 0.5:
        return rng.standard_normal(n)
    pad = int(math.ceil(4 * sigma_samples))
    white = rng.standard_normal(n + 2 * pad)
    smooth = gaussian_filter1d(white, sigma_samples, mode="wrap")[pad : pad + n]
    k = np.arange(-pad, pad + 1)
    kernel = np.exp(-0.5 * (k / sigma_samples) ** 2)
    kernel /= kernel.sum()
    return smooth / math.sqrt(float(np.sum(kernel**2)))


# ---------------------------------------------------------------------- generation
def generate_terrain(
    params: TerrainParams, materials: MaterialParams, rng: np.random.Generator
) -> Terrain:
    """Generate the seafloor (deterministic for a given ``rng`` state)."""
    cell = params.cell_m
    nx = int(round(params.size_m[0] / cell)) + 1
    ny = int(round(params.size_m[1] / cell)) + 1
    x = np.arange(nx) * cell
    y = np.arange(ny) * cell
    X, Y = np.meshgrid(x, y)
    width, height = x[-1], y[-1]

    az = params.regional_slope_azimuth_rad
    downhill = (X - width / 2) * math.sin(az) + (Y - height / 2) * math.cos(az)
    regional = -params.mean_depth_m - math.tan(params.regional_slope_rad) * downhill
    relief = np.zeros_like(X)
    for wavelength, amplitude in zip(
        params.relief_wavelengths_m, params.relief_amplitudes_m, strict=True
    ):
        if amplitude > 0:
            relief += amplitude * gaussian_field(rng, X.shape, wavelength / (4 * cell))

    ridges = _ridges(params, rng, x, y)
    boulder_layer, boulders = _boulders(params, rng, x, y, ridges)
    heights = regional + relief + ridges + boulder_layer

    names = materials.names
    mat = _material_map(materials, rng, relief, cell)
    rock = materials.index(materials.boulder_material)
    mat[(boulder_layer > 0.05) | (ridges > 0.3)] = rock
    if params.objects:  # no random draws: the other layers are those without objects
        heights = place_objects(heights, cell, params.objects, mat, materials)
    texture, tcell = _texture(params, materials, rng, mat, cell, width, height)
    return Terrain(heights, cell, mat.astype(np.uint8), names, texture, tcell, boulders)


def _ridges(
    params: TerrainParams, rng: np.random.Generator, x: np.ndarray, y: np.ndarray
) -> np.ndarray:
    """Height field of meandering ridges with a rounded cross-section."""
    p = params.ridges
    cell = x[1] - x[0]
    width, height = x[-1], y[-1]
    out = np.zeros((len(y), len(x)))
    count = int(round(p.density_per_ha * width * height / 1e4))
    step = 2.0
    for _ in range(count):
        length = rng.uniform(*p.length_m)
        h = rng.uniform(*p.height_m)
        w = rng.uniform(*p.width_m)
        n = max(int(math.ceil(length / step)), 2)
        heading = rng.uniform(0, 2 * math.pi) + np.cumsum(rng.normal(0, p.meander_rad, n))
        start = rng.uniform([-0.1 * width, -0.1 * height], [1.1 * width, 1.1 * height])
        pts = start + np.concatenate(
            [[[0.0, 0.0]], np.cumsum(step * np.stack([np.cos(heading), np.sin(heading)], 1), 0)]
        )
        s = np.linspace(0, 1, n + 1)
        taper = np.sqrt(np.clip(np.minimum(s, 1 - s) * 5, 0, 1))
        crest = h * taper * (0.7 + 0.3 * np.tanh(smooth_noise_1d(rng, n + 1, 4.0)))
        lo = np.floor((pts.min(0) - w) / cell).astype(int)
        hi = np.ceil((pts.max(0) + w) / cell).astype(int)
        ix0, iy0 = max(lo[0], 0), max(lo[1], 0)
        ix1, iy1 = min(hi[0], len(x) - 1), min(hi[1], len(y) - 1)
        if ix1 < ix0 or iy1 < iy0:
            continue
        cx, cy = np.meshgrid(x[ix0 : ix1 + 1], y[iy0 : iy1 + 1])
        q = np.stack([cx.ravel(), cy.ravel()], 1)
        a, b = pts[:-1], pts[1:]
        ab = b - a
        u = np.clip(
            np.einsum("qsk,sk->qs", q[:, None] - a[None], ab) / np.sum(ab * ab, 1), 0.0, 1.0
        )
        closest = a[None] + u[..., None] * ab[None]
        dist = np.linalg.norm(q[:, None] - closest, axis=-1)
        crest_at = crest[:-1][None] * (1 - u) + crest[1:][None] * u
        profile = crest_at * np.clip(1 - (dist / w) ** 2, 0, None) ** 1.5
        ridge = profile.max(axis=1).reshape(cx.shape)
        block = out[iy0 : iy1 + 1, ix0 : ix1 + 1]
        np.maximum(block, ridge, out=block)
    return out


# ---------------------------------------------------------------------- objects
def object_frame(obj: ObjectParams, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(u, v)`` (m) of points in an object's frame: ``u`` along its heading (bow
    positive), ``v`` across it (positive to port), from its centre."""
    dx = np.asarray(x, dtype=np.float64) - obj.x_m
    dy = np.asarray(y, dtype=np.float64) - obj.y_m
    s, c = math.sin(obj.heading_rad), math.cos(obj.heading_rad)
    return dx * s + dy * c, -dx * c + dy * s


def object_profile(obj: ObjectParams, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Height (m) of ``obj`` above its base at points ``(x, y)``; 0 outside its footprint.

    ``box``: ``height_m`` over the ``length_m x beam_m`` rectangle. ``hull``: a
    super-elliptic cross-section ``h (1 - |v / b(u)|^4)^(1/4)`` (near-vertical sides, a
    flat deck) whose half-beam ``b(u)`` narrows elliptically to a point over the bow's
    ``bow_fraction`` of the length.
    """
    u, v = object_frame(obj, x, y)
    half_l, half_b = obj.length_m / 2, obj.beam_m / 2
    along = np.abs(u) <= half_l
    if obj.kind == "box":
        return np.where(along & (np.abs(v) <= half_b), obj.height_m, 0.0)
    if obj.kind != "hull":
        raise ValueError(f"obj.kind: expected one of ['box', 'hull'], found {obj.kind!r}")
    bow = obj.bow_fraction * obj.length_m
    t = np.clip((u - (half_l - bow)) / bow, 0.0, 1.0) if bow > 0 else np.zeros_like(u)
    b = half_b * np.sqrt(np.clip(1.0 - t * t, 0.0, None))
    with np.errstate(divide="ignore", invalid="ignore"):
        q = np.where(b > 0, np.abs(v) / b, np.inf)
    inside = along & (q < 1.0)
    section = np.power(np.clip(1.0 - q**4, 0.0, None), 0.25, where=inside, out=np.zeros_like(u))
    return obj.height_m * section


def object_cells(
    obj: ObjectParams, shape: tuple[int, int], cell: float, sub: int = 3
) -> tuple[slice, slice, np.ndarray]:
    """The cell-averaged profile of ``obj`` (``sub`` x ``sub`` samples per cell) on the
    bounding box of its footprint in a grid of ``shape`` whose cell ``[0, 0]`` is centred at
    the origin: ``(rows, cols, profile)``; empty slices when it lies off the grid."""
    ny, nx = shape
    reach = math.hypot(obj.length_m, obj.beam_m) / 2 + cell
    ix0 = max(int(math.floor((obj.x_m - reach) / cell)), 0)
    ix1 = min(int(math.ceil((obj.x_m + reach) / cell)), nx - 1)
    iy0 = max(int(math.floor((obj.y_m - reach) / cell)), 0)
    iy1 = min(int(math.ceil((obj.y_m + reach) / cell)), ny - 1)
    if ix1 < ix0 or iy1 < iy0:
        return slice(0, 0), slice(0, 0), np.zeros((0, 0))
    offs = ((np.arange(sub) + 0.5) / sub - 0.5) * cell
    gx = (np.arange(ix0, ix1 + 1)[:, None] * cell + offs[None]).ravel()
    gy = (np.arange(iy0, iy1 + 1)[:, None] * cell + offs[None]).ravel()
    sx, sy = np.meshgrid(gx, gy)
    prof = object_profile(obj, sx, sy)
    prof = prof.reshape(iy1 - iy0 + 1, sub, ix1 - ix0 + 1, sub).mean(axis=(1, 3))
    return slice(iy0, iy1 + 1), slice(ix0, ix1 + 1), prof


def place_objects(
    heights: np.ndarray,
    cell: float,
    objects: tuple[ObjectParams, ...],
    mat: np.ndarray | None = None,
    materials: MaterialParams | None = None,
) -> np.ndarray:
    """``heights`` with ``objects`` standing on them (a new array).

    Each object's top is its ``height_m`` above the lowest seabed under its footprint; a
    cell takes the higher of the seabed and the object. Cells where the object rises more
    than 5 cm set ``mat`` (in place) to the object's material (None: the boulder
    material of ``materials``).
    """
    out = np.array(heights, dtype=np.float64)
    for obj in objects:
        rows, cols, prof = object_cells(obj, out.shape, cell)
        covered = prof > 0
        if not covered.any():
            continue
        block = out[rows, cols]
        base = float(block[covered].min())
        raised = np.where(covered, base + prof, -np.inf)
        out[rows, cols] = np.maximum(block, raised)
        if mat is not None and materials is not None:
            name = obj.material or materials.boulder_material
            mat[rows, cols][prof > 0.05] = materials.index(name)
    return out


def object_relief(
    heights: np.ndarray,
    cell: float,
    obj: ObjectParams,
    ring_m: tuple[float, float] = (2.0, 6.0),
    top_quantile: float = 0.9,
) -> float:
    """How high ``obj`` stands above its surroundings in a height grid (m; NaN: no data).

    ``heights`` is a grid ``(ny, nx)`` whose cell ``[0, 0]`` is centred at the origin (NaN:
    unmapped). The object's top is the ``top_quantile`` of the heights over its footprint
    (cells it covers by more than half); its surroundings are the median of the cells
    ``ring_m`` (inner, outer) metres outside the footprint. The same number on the true grid
    and on a map scores the map: the true value is ``height_m`` plus the seabed's own relief.
    """
    from scipy.ndimage import distance_transform_edt

    grow = 2 * ring_m[1]
    pad = dataclasses.replace(obj, length_m=obj.length_m + grow, beam_m=obj.beam_m + grow)
    rows, cols, _ = object_cells(pad, heights.shape, cell, sub=1)
    box = np.asarray(heights, dtype=np.float64)[rows, cols]
    if box.size == 0:
        return float("nan")
    full = np.zeros(box.shape)
    r0, c0 = rows.start, cols.start
    r_obj, c_obj, prof = object_cells(obj, heights.shape, cell)
    full[r_obj.start - r0 : r_obj.stop - r0, c_obj.start - c0 : c_obj.stop - c0] = prof
    inside = full > 0.5 * obj.height_m
    if not inside.any():
        return float("nan")
    dist = distance_transform_edt(~inside) * cell
    ring = (dist >= ring_m[0]) & (dist <= ring_m[1])
    top, around = box[inside], box[ring]
    top, around = top[np.isfinite(top)], around[np.isfinite(around)]
    if top.size < max(0.5 * inside.sum(), 1) or around.size < max(0.5 * ring.sum(), 1):
        return float("nan")
    return float(np.quantile(top, top_quantile) - np.median(around))


def _power_law(rng: np.random.Generator, n: int, lo: float, hi: float, a: float) -> np.ndarray:
    """``n`` samples of a truncated power law ``p(d) ~ d^-a`` on ``[lo, hi]``."""
    u = rng.random(n)
    if lo == hi:
        return np.full(n, lo)
    if abs(a - 1.0) < 1e-9:
        return lo * (hi / lo) ** u
    e = 1.0 - a
    return (lo**e + u * (hi**e - lo**e)) ** (1.0 / e)


def _boulders(
    params: TerrainParams,
    rng: np.random.Generator,
    x: np.ndarray,
    y: np.ndarray,
    ridges: np.ndarray,
) -> tuple[np.ndarray, np.ndarray]:
    """Boulder height layer (max of overlapping caps) and the boulder table ``(K, 4)``."""
    p = params.boulders
    cell = x[1] - x[0]
    ny, nx = len(y), len(x)
    count = int(round(p.density_per_ha * x[-1] * y[-1] / 1e4))
    layer = np.zeros((ny, nx))
    if count == 0:
        return layer, np.zeros((0, 4))
    cluster = gaussian_field(rng, (ny, nx), p.cluster_scale_m / (4 * cell))
    logits = p.clustering * cluster + p.ridge_affinity * (ridges > 0.1)
    prob = np.exp(logits - logits.max()).ravel()
    idx = rng.choice(prob.size, size=count, p=prob / prob.sum())
    bx = x[idx % nx] + rng.uniform(-0.5, 0.5, count) * cell
    by = y[idx // nx] + rng.uniform(-0.5, 0.5, count) * cell
    diameter = _power_law(rng, count, *p.diameter_m, p.size_exponent)
    h = diameter * rng.uniform(*p.height_ratio, count)
    aspect = rng.uniform(0.6, 1.0, count)
    angle = rng.uniform(0, math.pi, count)
    burial = rng.uniform(0.1, 0.35, count) * h
    sub = 3  # sub-samples per cell side: small boulders still raise their cell
    offs = (np.arange(sub) + 0.5) / sub - 0.5
    for k in range(count):
        a_ax, b_ax = diameter[k] / 2, diameter[k] / 2 * aspect[k]
        r_cells = int(math.ceil(a_ax / cell)) + 1
        cx, cy = int(round(bx[k] / cell)), int(round(by[k] / cell))
        ix0, ix1 = max(cx - r_cells, 0), min(cx + r_cells, nx - 1)
        iy0, iy1 = max(cy - r_cells, 0), min(cy + r_cells, ny - 1)
        if ix1 < ix0 or iy1 < iy0:
            continue
        gx = (x[ix0 : ix1 + 1, None] + offs[None] * cell).ravel()
        gy = (y[iy0 : iy1 + 1, None] + offs[None] * cell).ravel()
        sx, sy = np.meshgrid(gx - bx[k], gy - by[k])
        c, s = math.cos(angle[k]), math.sin(angle[k])
        u, v = (c * sx + s * sy) / a_ax, (-s * sx + c * sy) / b_ax
        top = h[k] + burial[k]
        cap = np.clip(top * np.sqrt(np.clip(1 - u * u - v * v, 0, None)) - burial[k], 0, None)
        cap = cap.reshape(iy1 - iy0 + 1, sub, ix1 - ix0 + 1, sub).mean(axis=(1, 3))
        block = layer[iy0 : iy1 + 1, ix0 : ix1 + 1]
        np.maximum(block, cap, out=block)
    table = np.stack([bx, by, diameter, h], axis=1)
    return layer, table


def _material_map(
    materials: MaterialParams, rng: np.random.Generator, relief: np.ndarray, cell: float
) -> np.ndarray:
    """Material index per cell: a smooth field, coupled to the relief, cut by fractions."""
    field = gaussian_field(rng, relief.shape, materials.map_scale_m / (4 * cell))
    std = float(relief.std())
    if std > 0 and materials.depth_coupling > 0:
        field = field + materials.depth_coupling * (relief - relief.mean()) / std
    fractions = np.array([c.fraction for c in materials.classes])
    cuts = np.quantile(field, np.clip(np.cumsum(fractions)[:-1], 0, 1))
    return np.searchsorted(cuts, field, side="right").astype(np.uint8)


def _texture(
    params: TerrainParams,
    materials: MaterialParams,
    rng: np.random.Generator,
    mat: np.ndarray,
    cell: float,
    width: float,
    height: float,
) -> tuple[np.ndarray, float]:
    """Per-material reflectivity texture on a grid of ``params.texture_cell_m``."""
    tc = params.texture_cell_m
    tnx, tny = int(round(width / tc)) + 1, int(round(height / tc)) + 1
    tx, ty = np.arange(tnx) * tc, np.arange(tny) * tc
    ix = np.clip(np.rint(tx / cell).astype(int), 0, mat.shape[1] - 1)
    iy = np.clip(np.rint(ty / cell).astype(int), 0, mat.shape[0] - 1)
    mat_t = mat[iy[:, None], ix[None, :]]
    tex = np.ones((tny, tnx))
    TX, TY = np.meshgrid(tx, ty)
    for m, c in enumerate(materials.classes):
        sel = mat_t == m
        if not sel.any():
            continue
        value = np.ones(int(sel.sum()))
        if c.texture_contrast > 0:
            n = gaussian_field(rng, tex.shape, max(c.texture_scale_m / (2 * tc), 0.3))[sel]
            value *= np.exp(c.texture_contrast * n - 0.5 * c.texture_contrast**2)
        if c.ripple_wavelength_m > 0 and c.ripple_contrast > 0:
            lam = c.ripple_wavelength_m
            # crests turn slowly over tens of metres and wander by about a wavelength
            direction = (
                rng.uniform(0, math.pi)
                + 0.15 * gaussian_field(rng, tex.shape, 20.0 / (4 * tc))[sel]
            )
            wobble = 1.0 * gaussian_field(rng, tex.shape, 6 * lam / (4 * tc))[sel]
            phase = (TX[sel] * np.cos(direction) + TY[sel] * np.sin(direction)) / lam
            value *= 1 + min(c.ripple_contrast, 0.95) * np.sin(2 * math.pi * phase + wobble)
        tex[sel] = value
    return tex.astype(np.float32), tc


def mbes_heights(terrain: Terrain, noise_m: float, rng: np.random.Generator) -> np.ndarray:
    """The MBES grid: true heights plus spatially correlated (~1 m) noise of std ``noise_m``."""
    if noise_m <= 0:
        return terrain.heights.astype(np.float32)
    noise = gaussian_field(rng, terrain.heights.shape, max(0.5 / terrain.cell_m, 0.5))
    return (terrain.heights + noise_m * noise).astype(np.float32)


# ---------------------------------------------------------------------- statistics
def nlat_statistics(dzdx: np.ndarray, dzdy: np.ndarray) -> dict[str, float]:
    """Distribution of ``|n_lat|`` over a gradient field seen from both line sets.

    Level vehicles heading North and East (the two perpendicular line sets), both heads;
    ``n_lat`` from :func:`head_plane_normal_from_gradient`.

    Returns:
        fractions below 0.1 / 0.2 and above 0.5, and the 50/90/99/99.9 % quantiles.
    """
    gx = np.asarray(dzdx, dtype=np.float64).ravel()
    gy = np.asarray(dzdy, dtype=np.float64).ravel()
    values = []
    for heading in (0.0, math.pi / 2):
        R = attitude_to_rotation(np.array(heading), np.array(0.0), np.array(0.0))
        for side in (0, 1):
            n_lat, _ = head_plane_normal_from_gradient(gx, gy, R, side)
            values.append(np.abs(n_lat))
    a = np.concatenate(values)
    q = np.quantile(a, [0.5, 0.9, 0.99, 0.999])
    return {
        "frac_below_0.1": float(np.mean(a < 0.1)),
        "frac_below_0.2": float(np.mean(a < 0.2)),
        "frac_above_0.5": float(np.mean(a > 0.5)),
        "q50": float(q[0]),
        "q90": float(q[1]),
        "q99": float(q[2]),
        "q99.9": float(q[3]),
        "max": float(a.max()),
    }


# ---------------------------------------------------------------------- real grids
@dataclass
class GridSource:
    """What a grid terrain was made from (the MBES "truth" and the bookkeeping).

    Attributes:
        heights: ``(ny, nx)`` the grid's heights after the spike filter (NaN: no-data and
            removed spikes), at the grid's own cell: the MBES truth before MBES noise.
        cell_m: the grid's cell size (m).
        origin: ``{"crs", "easting", "northing"}`` of the grid's SW cell centre (the local
            frame's origin).
        spikes: ``(ny, nx)`` bool, cells removed by the spike filter.
        filled: ``(ny, nx)`` bool, cells filled for rendering (small holes).
        no_seabed: ``(ny, nx)`` bool, cells left without seabed (large holes, outside).
    """

    heights: np.ndarray
    cell_m: float
    origin: dict
    spikes: np.ndarray
    filled: np.ndarray
    no_seabed: np.ndarray

    def flags(self) -> np.ndarray:
        """``(ny, nx)`` uint8 per grid cell: 0 valid, 1 filled for rendering, 2 a removed
        spike (filled), 3 no seabed (a large hole or outside), 4 a removed spike in a large
        hole."""
        out = np.zeros(self.heights.shape, np.uint8)
        out[self.filled] = 1
        out[self.no_seabed] = 3
        out[self.spikes] += 1
        return out

    def summary(self) -> dict[str, float | int | str]:
        valid = np.isfinite(self.heights)
        return {
            "cells": int(self.heights.size),
            "cell_m": self.cell_m,
            "valid_fraction": round(float(valid.mean()), 4),
            "spikes_removed": int(self.spikes.sum()),
            "cells_filled": int(self.filled.sum()),
            "cells_no_seabed": int(self.no_seabed.sum()),
        }


def split_holes(
    valid: np.ndarray, cell: float, fill_max_area_m2: float
) -> tuple[np.ndarray, np.ndarray]:
    """Small holes (to fill) and large ones (no seabed) of a validity mask.

    A hole is a 4-connected component of invalid cells; it is small when its area is at
    most ``fill_max_area_m2`` and it does not touch the grid's edge (an edge region is the
    outside of the survey, whatever its size).

    Returns:
        ``(small, large)`` bool masks, ``small | large == ~valid``.
    """
    from scipy.ndimage import label

    invalid = ~np.asarray(valid, dtype=bool)
    labels, n = label(invalid)
    if n == 0:
        return np.zeros_like(invalid), np.zeros_like(invalid)
    area = np.bincount(labels.ravel(), minlength=n + 1) * cell * cell
    edge = np.zeros(n + 1, bool)
    for border in (labels[0], labels[-1], labels[:, 0], labels[:, -1]):
        edge[border] = True
    small_label = (area <= fill_max_area_m2) & ~edge
    small_label[0] = False
    small = small_label[labels]
    return small, invalid & ~small


def fill_holes(heights: np.ndarray, holes: np.ndarray, iterations: int = 200) -> np.ndarray:
    """``heights`` with ``holes`` filled harmonically (Laplace, from the nearest valid
    heights); other NaN cells are left NaN. A filled plane stays that plane."""
    from scipy.ndimage import distance_transform_edt

    h = np.array(heights, dtype=np.float64)
    holes = np.asarray(holes, dtype=bool)
    if not holes.any():
        return h
    valid = np.isfinite(h) & ~holes
    if not valid.any():
        raise ValueError("heights: expected valid cells around the holes, found none")
    idx = distance_transform_edt(~valid, return_distances=False, return_indices=True)
    start = h[tuple(idx)]
    out = np.where(holes, start, h)
    work = np.where(valid | holes, out, np.nan)
    for _ in range(iterations):
        padded = np.pad(work, 1, constant_values=np.nan)
        nb = np.stack([padded[:-2, 1:-1], padded[2:, 1:-1], padded[1:-1, :-2], padded[1:-1, 2:]])
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)
            mean = np.nanmean(nb, axis=0)
        work = np.where(holes & np.isfinite(mean), mean, work)
    out[holes] = work[holes]
    return out


def read_grid_source(params: GridTerrainParams) -> GridSource:
    """Read a grid terrain's file, remove spikes, split its holes (no sub-cell detail)."""
    from sss2bathy.io.grids import read_grid, spike_mask

    grid = read_grid(
        params.path,
        params.cell_m,
        band=params.band,
        source_crs=params.source_crs,
        z_positive=params.z_positive,
    )
    heights = np.array(grid.heights, dtype=np.float64)
    if min(heights.shape) < 8:
        raise ValueError(
            f"data.survey.terrain.grid: expected at least 8 x 8 cells, found "
            f"{heights.shape[0]} x {heights.shape[1]} in {params.path}"
        )
    spikes = np.zeros(heights.shape, bool)
    if params.spike_threshold_m is not None:
        spikes = spike_mask(heights, params.spike_threshold_m, params.spike_window_cells)
        heights[spikes] = np.nan
    small, large = split_holes(np.isfinite(heights), grid.cell_size, params.fill_max_area_m2)
    if large.all():
        raise ValueError(
            f"data.survey.terrain.grid: expected valid cells, found none in {params.path}"
        )
    origin = {"crs": grid.crs, "easting": float(grid.x0), "northing": float(grid.y0)}
    return GridSource(heights, float(grid.cell_size), origin, spikes, small, large)


def grid_terrain(
    params: TerrainParams, materials: MaterialParams, rng: np.random.Generator
) -> tuple[Terrain, GridSource]:
    """The terrain of a real grid (``params.grid``), in the grid's frame (SW cell centre = 0).

    Small holes are filled (harmonically) for rendering, large ones and the outside have no
    seabed (their heights are the nearest valid ones, for normals and altitudes only); a
    grid without large holes is a plain rectangle of seabed (``no_seabed`` None). With
    ``detail`` the heights are resampled (bilinearly) to ``detail_cell_m`` and the relief
    components of ``params.relief_wavelengths_m`` no longer than two grid cells plus
    ``params.boulders`` are added. Materials: ``materials_raster`` or the procedural map
    (mud in the hollows of the grid's local relief); boulders are rock.
    """
    from scipy.ndimage import distance_transform_edt, gaussian_filter

    gp = params.grid
    if gp is None:
        raise ValueError("params.grid: expected a grid terrain, found None")
    source = read_grid_source(gp)
    cell = source.cell_m
    render = fill_holes(source.heights, source.filled)
    idx = distance_transform_edt(source.no_seabed, return_distances=False, return_indices=True)
    render = render[tuple(idx)]  # nearest valid height under the holes
    no_seabed = source.no_seabed
    ny, nx = render.shape
    boulders = np.zeros((0, 4))
    if gp.detail:
        dc = gp.detail_cell_m
        if dc >= cell:
            raise ValueError(
                f"data.survey.terrain.detail_cell_m: expected < the grid's cell ({cell} m), "
                f"found {dc}"
            )
        x = np.arange(int(math.floor((nx - 1) * cell / dc + 1e-9)) + 1) * dc
        y = np.arange(int(math.floor((ny - 1) * cell / dc + 1e-9)) + 1) * dc
        X, Y = np.meshgrid(x, y)
        render = bilinear(render, cell, X, Y)
        no_seabed = bilinear(source.no_seabed.astype(np.float64), cell, X, Y) > 0
        for wavelength, amplitude in zip(
            params.relief_wavelengths_m, params.relief_amplitudes_m, strict=True
        ):
            if amplitude > 0 and wavelength <= 2 * cell:
                render = render + amplitude * gaussian_field(rng, X.shape, wavelength / (4 * dc))
        layer, boulders = _boulders(params, rng, x, y, np.zeros(X.shape))
        render = render + layer
        cell = dc
    else:
        layer = np.zeros(render.shape)
    local_relief = render - gaussian_filter(render, materials.map_scale_m / (4 * cell))
    if float(local_relief.std()) < 1e-6:  # level: filter round-off is not relief
        local_relief = np.zeros_like(local_relief)
    mat = _material_map(materials, rng, local_relief, cell)
    if gp.materials_raster is not None:
        mat = _raster_materials(gp, materials, source.origin, mat, cell)
    mat[layer > 0.05] = materials.index(materials.boulder_material)
    if params.objects:
        render = place_objects(render, cell, params.objects, mat, materials)
    ny, nx = render.shape
    texture, tcell = _texture(params, materials, rng, mat, cell, (nx - 1) * cell, (ny - 1) * cell)
    terrain = Terrain(
        render, cell, mat.astype(np.uint8), materials.names, texture, tcell, boulders,
        no_seabed if no_seabed.any() else None, source,
    )  # fmt: skip
    return terrain, source


def _raster_materials(
    gp: GridTerrainParams,
    materials: MaterialParams,
    origin: dict,
    procedural: np.ndarray,
    cell: float,
) -> np.ndarray:
    """Materials from a classification or backscatter raster (nearest cell, in the grid's
    CRS); cells it does not cover keep the procedural material."""
    from sss2bathy.io.grids import read_grid

    raster = read_grid(gp.materials_raster, origin=origin)
    ny, nx = procedural.shape
    ix = np.rint((np.arange(nx) * cell - raster.x0) / raster.cell_size).astype(np.int64)
    iy = np.rint((np.arange(ny) * cell - raster.y0) / raster.cell_size).astype(np.int64)
    rny, rnx = raster.shape
    inside = ((ix >= 0) & (ix < rnx))[None, :] & ((iy >= 0) & (iy < rny))[:, None]
    values = np.full(procedural.shape, np.nan)
    sel = np.nonzero(inside)
    values[sel] = raster.heights[np.clip(iy, 0, rny - 1)[sel[0]], np.clip(ix, 0, rnx - 1)[sel[1]]]
    known = np.isfinite(values)
    out = procedural.copy()
    if not known.any():
        raise ValueError(
            f"data.survey.terrain.materials_raster: expected to cover the grid, found no "
            f"overlap ({gp.materials_raster})"
        )
    n = len(materials.classes)
    if gp.materials_kind == "classes":
        v = values[known]
        bad = (v != np.rint(v)) | (v < 0) | (v >= n)
        if bad.any():
            raise ValueError(
                f"data.survey.terrain.materials_raster: expected material indices 0..{n - 1} "
                f"({list(materials.names)}), found {float(v[bad][0])!r} in {gp.materials_raster}"
            )
        out[known] = v.astype(np.uint8)
    else:
        fractions = np.array([c.fraction for c in materials.classes])
        cuts = np.quantile(values[known], np.clip(np.cumsum(fractions)[:-1], 0, 1))
        out[known] = np.searchsorted(cuts, values[known], side="right").astype(np.uint8)
    return out


def grid_mbes_heights(source: GridSource, noise_m: float, rng: np.random.Generator) -> np.ndarray:
    """The MBES grid of a grid terrain: the grid itself (spikes removed, holes NaN) plus
    spatially correlated (~1 m) noise of std ``noise_m``."""
    heights = source.heights.astype(np.float64)
    if noise_m > 0:
        noise = gaussian_field(rng, heights.shape, max(0.5 / source.cell_m, 0.5))
        heights = heights + noise_m * noise
    return heights.astype(np.float32)
