"""Typed, validated configuration of the synthetic survey generator (the ``data.survey`` group).

The YAML presets (``conf/data/survey/synthetic_d*.yaml``) spell every key out; the
defaults here are those of the Dataset-I analogue at paper scale. Degrees are used in the
configs only and are converted to radians here. Each field declares its config key,
default, bounds and unit once (:func:`~sss2bathy.utils.checks.setting`), and one generic
reader reads them (:func:`~sss2bathy.utils.checks.read_fields`); the ``_read_*`` functions
add only what spans fields or sections. Every bad value or unknown key raises a
``ValueError`` naming the full key (``data.survey.plan.line_spacing_m``), what was expected
and what was found.
"""

from __future__ import annotations

import hashlib
import math
import warnings
from collections.abc import Mapping, Sequence
from dataclasses import asdict, dataclass, replace
from pathlib import Path
from typing import Any

from sss2bathy.utils.atomic import stable_hash
from sss2bathy.utils.checks import ConfigReader, config_error, read_fields, setting

ROOT = "data.survey"

#: Bumped whenever the generator's output changes for the same config (invalidates caches).
GENERATOR_VERSION = 1

#: Top-level keys that do not change the generated data (not part of the config hash).
UNHASHED_KEYS = ("workers",)


# ---------------------------------------------------------------------------- terrain
@dataclass(frozen=True)
class RidgeParams:
    """Rock ridges: random meandering polylines with a rounded cross-section."""

    density_per_ha: float = setting(0.6, ge=0.0)
    height_m: tuple[float, float] = setting((0.8, 2.5), kind="pair", gt=0.0)
    width_m: tuple[float, float] = setting((3.0, 7.0), kind="pair", gt=0.0)
    length_m: tuple[float, float] = setting((25.0, 90.0), kind="pair", gt=0.0)
    meander_rad: float = setting(math.radians(8.0), "meander_deg", unit="deg", ge=0.0, le=90.0)


@dataclass(frozen=True)
class BoulderParams:
    """Boulders: clustered ellipsoidal caps with a power-law size distribution."""

    density_per_ha: float = setting(180.0, ge=0.0)
    diameter_m: tuple[float, float] = setting((0.3, 3.0), kind="pair", gt=0.0)
    size_exponent: float = setting(2.3, gt=0.0)
    height_ratio: tuple[float, float] = setting((0.4, 0.7), kind="pair", gt=0.0, le=1.0)
    clustering: float = setting(1.2, ge=0.0)
    cluster_scale_m: float = setting(25.0, gt=0.0)
    ridge_affinity: float = setting(2.0, ge=0.0)


OBJECT_KINDS = ("box", "hull")


@dataclass(frozen=True)
class ObjectParams:
    """A wreck-like object on the seabed (``data.survey.terrain.objects[i]``).

    ``kind``: ``box`` (a rectangular block with a flat top) or ``hull`` (a ship's hull lying
    upright: a super-elliptic cross-section with near-vertical sides and a flat deck, the
    beam narrowing to a point over the bow's ``bow_fraction`` of the length). The footprint
    (``length_m`` along ``heading_rad``, clockwise from North, by ``beam_m``) is centred at
    ``(x_m, y_m)`` in the local frame; the top is ``height_m`` above the lowest seabed under
    the footprint, so the object stands that high above its surroundings. Its cells take
    ``material`` (None: the boulder material).
    """

    kind: str = setting("hull", kind="choice", choices=OBJECT_KINDS)
    x_m: float = setting(0.0)
    y_m: float = setting(0.0)
    length_m: float = setting(10.0, gt=0.0)
    beam_m: float = setting(4.0, gt=0.0)
    height_m: float = setting(2.0, gt=0.0)
    heading_rad: float = setting(0.0, "heading_deg", unit="deg")
    bow_fraction: float = setting(0.3, ge=0.0, lt=1.0)
    material: str | None = setting(None, kind="text")


def _read_objects(r: ConfigReader) -> tuple[ObjectParams, ...]:
    path, value = r.get("objects", None)
    if value is None:
        return ()
    if not isinstance(value, Sequence) or isinstance(value, str | Mapping):
        raise config_error(path, "a list of objects ({kind, x_m, y_m, length_m, ...})", value)
    out = []
    for i, spec in enumerate(value):
        o = ConfigReader(spec, f"{path}[{i}]")
        obj = ObjectParams(**read_fields(o, ObjectParams))
        o.done()
        out.append(obj)
    return tuple(out)


GRID_SUFFIXES = (".tif", ".tiff", ".gtiff", ".asc", ".bag", ".xyz", ".txt", ".csv", ".pts")


@dataclass(frozen=True)
class GridTerrainParams:
    """A real bathymetry grid as the terrain (``data.survey.terrain.grid``).

    The survey's local frame has its origin at the grid's SW cell centre and the grid's CRS,
    so the outputs are georeferenced where the grid is; ``cell_m`` resamples it (None: its
    own cell; required for XYZ points). ``spike_threshold_m``: cells more
    than this from the median of their ``spike_window_cells`` square are removed (None: no
    filter). Holes (no-data and removed spikes) of at most ``fill_max_area_m2`` that do not
    touch the grid's edge are filled for rendering only (flagged); the others are no seabed
    (the sidescan there is masked as no hit). ``detail``: procedural relief and boulders
    below the grid's resolution on a ``detail_cell_m`` render grid. ``materials_raster``:
    a classification (material indices, ``materials_kind: classes``) or backscatter
    (``materials_kind: backscatter``, cut by the class fractions, low backscatter = first
    class) raster in the grid's CRS; None: the procedural material map.
    """

    path: str
    band: int = setting(1, "grid_band", kind="integer", ge=1)
    cell_m: float | None = setting(None, "grid_cell_m", kind="optional_number", gt=0.0)
    source_crs: str | None = setting(None, "grid_crs", kind="text")
    z_positive: str = setting("up", "grid_z_positive", kind="choice", choices=("up", "down"))
    spike_threshold_m: float | None = None
    spike_window_cells: int = 5
    fill_max_area_m2: float = setting(25.0, ge=0.0)
    detail: bool = False
    detail_cell_m: float = setting(0.25, gt=0.0)
    materials_raster: str | None = None
    materials_kind: str = setting("classes", kind="choice", choices=("classes", "backscatter"))


def file_digest(path: str | Path) -> str:
    """SHA-256 of a file (the cache key of a grid terrain, not its machine-specific path)."""
    h = hashlib.sha256()
    with open(path, "rb") as fh:
        for chunk in iter(lambda: fh.read(1 << 20), b""):
            h.update(chunk)
    return h.hexdigest()


def _existing_file(path: str, value: Any, what: str, suffixes: Sequence[str]) -> str:
    if not isinstance(value, str) or not value:
        raise config_error(path, f"a path to {what}", value)
    if Path(value).suffix.lower() not in suffixes:
        raise config_error(path, f"a file ending in one of {list(suffixes)}", value)
    if not Path(value).is_file():
        raise config_error(path, f"an existing {what} (file missing)", value)
    return value


def _read_grid_terrain(r: ConfigReader, grid_path: str) -> GridTerrainParams:
    path = _existing_file(
        grid_path,
        r.raw("grid"),
        "bathymetry grid (GeoTIFF, BAG, ESRI ASCII, XYZ; set data.survey.terrain.grid=PATH, or "
        "SSS2BATHY_REALDATA=FOLDER for the presets)",
        GRID_SUFFIXES,
    )
    spikes = r.section("spike_filter")
    enabled = spikes.boolean("enabled")
    threshold = spikes.number("threshold_m", 1.0, gt=0.0)
    window = spikes.integer("window_cells", 5, ge=3)
    if window % 2 == 0:
        raise config_error(f"{spikes.path}.window_cells", "an odd integer >= 3", window)
    spikes.done()
    detail = r.boolean("detail")
    raster = r.raw("materials_raster")
    if raster is not None:
        raster = _existing_file(
            f"{r.path}.materials_raster", raster, "materials raster", GRID_SUFFIXES
        )
    return GridTerrainParams(
        path=path,
        spike_threshold_m=threshold if enabled else None,
        spike_window_cells=window,
        detail=detail,
        materials_raster=raster,
        **read_fields(r, GridTerrainParams),
    )


@dataclass(frozen=True)
class TerrainParams:
    """Seafloor geometry (metres, radians).

    The terrain covers ``[0, size_m[0]] x [0, size_m[1]]`` (x East, y North) in the local
    frame; heights are negative (z = -depth). With ``grid`` (a real bathymetry grid) the
    grid is the terrain: size, cell, depth and regional slope come from it, and the relief
    and boulder parameters describe the optional sub-cell detail only. ``objects``
    (wreck-like boxes and hulls, :class:`ObjectParams`) stand on either; none: the terrain
    is exactly what it was before objects existed.
    """

    size_m: tuple[float, float] = setting((350.0, 300.0), kind="pair", gt=0.0, ordered=False)
    cell_m: float = setting(0.5, gt=0.0)
    mean_depth_m: float = setting(17.0, gt=0.0)
    regional_slope_rad: float = setting(
        math.radians(2.2), "regional_slope_deg", unit="deg", ge=0.0, lt=45.0
    )
    regional_slope_azimuth_rad: float = setting(
        math.radians(30.0), "regional_slope_azimuth_deg", unit="deg"
    )
    relief_wavelengths_m: tuple[float, ...] = setting(
        (160.0, 80.0, 40.0, 20.0, 8.0, 3.0), kind="numbers", ge=0.0
    )
    relief_amplitudes_m: tuple[float, ...] = setting(
        (2.0, 1.4, 0.7, 0.3, 0.08, 0.03), kind="numbers", ge=0.0
    )
    ridges: RidgeParams = RidgeParams()
    boulders: BoulderParams = BoulderParams()
    texture_cell_m: float = setting(0.25, gt=0.0)
    mbes_noise_m: float = setting(0.02, ge=0.0)
    grid: GridTerrainParams | None = None
    objects: tuple[ObjectParams, ...] = ()


#: procedural-only terrain keys: refused next to ``grid`` (the grid gives them)
_PROCEDURAL_ONLY = (
    "size_m", "cell_m", "mean_depth_m", "regional_slope_deg", "regional_slope_azimuth_deg",
    "ridges",
)  # fmt: skip
#: grid-only terrain keys: refused without ``grid``
_GRID_ONLY = (
    "grid_band", "grid_cell_m", "grid_crs", "grid_z_positive", "spike_filter", "fill_max_area_m2", "detail",
    "detail_cell_m", "materials_raster", "materials_kind",
)  # fmt: skip


def _read_terrain(r: ConfigReader) -> TerrainParams:
    if r.data.get("grid") is not None:
        given = sorted(k for k in _PROCEDURAL_ONLY if k in r.data)
        if given:
            raise ValueError(
                f"{r.path}: expected no {given} next to {r.path}.grid (the grid gives them), "
                f"found {given}"
            )
        grid = _read_grid_terrain(r, f"{r.path}.grid")
    else:
        r.used.add("grid")
        given = sorted(k for k in _GRID_ONLY if k in r.data)
        if given:
            raise ValueError(
                f"{r.path}: keys {given} apply to a grid terrain only; expected "
                f"{r.path}.grid: PATH with them, found no grid"
            )
        grid = None
    values = read_fields(r, TerrainParams)
    size, cell = values["size_m"], values["cell_m"]
    if grid is None and min(size) < 8 * cell:
        raise config_error(f"{r.path}.size_m", f"at least 8 cells ({8 * cell} m) per side", size)
    wl, amp = values["relief_wavelengths_m"], values["relief_amplitudes_m"]
    if len(wl) != len(amp):
        raise config_error(
            f"{r.path}.relief_amplitudes_m", f"{len(wl)} values (one per wavelength)", list(amp)
        )
    if any(w <= 0 for w in wl):
        raise config_error(f"{r.path}.relief_wavelengths_m", "positive wavelengths", list(wl))
    ridges = RidgeParams(**read_fields(r.section("ridges"), RidgeParams))
    boulders = BoulderParams(**read_fields(r.section("boulders"), BoulderParams))
    params = TerrainParams(
        **values, ridges=ridges, boulders=boulders, grid=grid, objects=_read_objects(r)
    )
    if grid is not None:  # 0 = given by the grid
        params = replace(
            params, size_m=(0.0, 0.0), cell_m=0.0, mean_depth_m=0.0, regional_slope_rad=0.0,
            regional_slope_azimuth_rad=0.0, ridges=RidgeParams(density_per_ha=0.0),
        )  # fmt: skip
    r.done()
    return params


# -------------------------------------------------------------------------- materials
@dataclass(frozen=True)
class MaterialClass:
    """One seabed material: its share of the map, backscatter and texture.

    Backscattering cross-section per unit area (not Lambertian unless ``exponent`` = 2 and
    ``specular`` = 0): ``sigma0(i) = mu cos(i)^exponent + specular exp(-i^2 / 2 w^2)``,
    ``i`` the incidence angle, ``w = specular_width_rad``.
    """

    name: str
    fraction: float = setting(0.25, ge=0.0, le=1.0)
    mu: float = setting(1.0, gt=0.0)
    exponent: float = setting(2.0, ge=1.0)
    specular: float = setting(0.0, ge=0.0)
    specular_width_rad: float = setting(
        math.radians(6.0), "specular_width_deg", unit="deg", gt=0.0, lt=90.0
    )
    texture_contrast: float = setting(0.2, ge=0.0)
    texture_scale_m: float = setting(1.0, gt=0.0)
    ripple_wavelength_m: float = setting(0.0, ge=0.0)
    ripple_contrast: float = setting(0.0, ge=0.0)


_MATERIAL_DEFAULTS: dict[str, dict[str, float]] = {
    "mud": dict(
        fraction=0.3,
        mu=0.3,
        exponent=2.6,
        specular=0.6,
        specular_width_deg=5.0,
        texture_contrast=0.12,
        texture_scale_m=3.0,
    ),
    "sand": dict(
        fraction=0.4,
        mu=1.0,
        exponent=1.8,
        specular=1.5,
        specular_width_deg=6.0,
        texture_contrast=0.15,
        texture_scale_m=1.5,
        ripple_wavelength_m=1.2,
        ripple_contrast=0.25,
    ),
    "gravel": dict(
        fraction=0.25,
        mu=2.2,
        exponent=1.4,
        specular=0.8,
        specular_width_deg=9.0,
        texture_contrast=0.45,
        texture_scale_m=0.4,
    ),
    "rock": dict(
        fraction=0.05,
        mu=4.0,
        exponent=1.15,
        specular=3.0,
        specular_width_deg=12.0,
        texture_contrast=0.35,
        texture_scale_m=0.8,
    ),
}


@dataclass(frozen=True)
class MaterialParams:
    """The material map: classes (ordered: low -> high values of the map field)."""

    classes: tuple[MaterialClass, ...]
    map_scale_m: float = setting(30.0, gt=0.0)
    depth_coupling: float = setting(0.6, ge=0.0)
    boulder_material: str = "rock"
    reference_material: str = "sand"

    @property
    def names(self) -> tuple[str, ...]:
        return tuple(c.name for c in self.classes)

    def index(self, name: str) -> int:
        return self.names.index(name)


def _read_materials(r: ConfigReader) -> MaterialParams:
    classes_cfg = r.raw("classes")
    if classes_cfg is None:
        classes_cfg = _MATERIAL_DEFAULTS
    if not isinstance(classes_cfg, Mapping) or not classes_cfg:
        raise config_error(
            f"{r.path}.classes", "a non-empty mapping name -> parameters", classes_cfg
        )
    classes = []
    for name, spec in classes_cfg.items():
        c = ConfigReader(spec, f"{r.path}.classes.{name}")
        classes.append(MaterialClass(name=str(name), **read_fields(c, MaterialClass)))
        c.done()
    total = sum(c.fraction for c in classes)
    if not math.isclose(total, 1.0, abs_tol=1e-6):
        raise config_error(f"{r.path}.classes.*.fraction", "fractions summing to 1", total)
    names = [c.name for c in classes]
    params = MaterialParams(
        classes=tuple(classes),
        **read_fields(r, MaterialParams),
        boulder_material=r.choice(
            "boulder_material", "rock" if "rock" in names else names[-1], names
        ),
        reference_material=r.choice(
            "reference_material", "sand" if "sand" in names else names[0], names
        ),
    )
    r.done()
    return params


# ------------------------------------------------------------------------------- plan
@dataclass(frozen=True)
class PlanParams:
    """Lawnmower survey plan (metres, seconds, radians).

    Lines come in two perpendicular sets: the ``main`` set runs along ``main_axis``, the
    ``cross`` set perpendicular to it. Test lines are split half/half between the sets (the
    paper's test lines); ``train_cross_fraction`` of the training lines are cross lines.
    With ``heading_rad`` (clockwise from North) the main lines run at that heading and the
    cross lines at +90 degrees, each clipped to the longest stretch (>= ``min_line_m``)
    whose track stays inside the terrain's valid footprint (a grid terrain's irregular
    outline, ``margin_m`` in from its edge; the swath may leave it: those bins are no hit;
    on procedural terrain the whole swath stays on the terrain), ``line_spacing_m`` apart
    (None: spread over the footprint). A grid terrain without a heading takes the
    footprint's long axis.
    """

    n_train: int = setting(45, kind="integer", ge=0)
    n_test: int = setting(12, kind="integer", ge=0)
    train_cross_fraction: float = setting(0.5, ge=0.0, le=1.0)
    main_axis: str = setting("x", kind="choice", choices=("x", "y"))
    line_spacing_m: float | None = setting(None, kind="optional_number", gt=0.0)
    margin_m: float = setting(2.0, ge=0.0)
    speed_mps: float = setting(2.0, gt=0.0)
    ping_rate_hz: float = setting(12.0, gt=0.0)
    turn_time_s: float = setting(60.0, ge=0.0)
    mount: str = setting("hull", kind="choice", choices=("hull", "auv"))
    sonar_depth_m: float = setting(1.5, ge=0.0)
    altitude_m: float = setting(10.0, gt=0.0)
    altitude_smoothing_m: float = setting(15.0, ge=0.0)
    min_altitude_m: float = setting(2.0, gt=0.0)
    roll_rad: float = setting(math.radians(1.0), "motion.roll_deg", unit="deg", ge=0.0, lt=30.0)
    pitch_rad: float = setting(math.radians(0.5), "motion.pitch_deg", unit="deg", ge=0.0, lt=30.0)
    yaw_rad: float = setting(math.radians(0.5), "motion.yaw_deg", unit="deg", ge=0.0, lt=30.0)
    motion_period_s: float = setting(6.0, "motion.period_s", gt=0.0)
    nav_position_noise_m: float = setting(0.0, "nav_noise.position_m", ge=0.0)
    nav_attitude_noise_rad: float = setting(
        0.0, "nav_noise.attitude_deg", unit="deg", ge=0.0, lt=30.0
    )
    nav_noise_correlation_s: float = setting(10.0, "nav_noise.correlation_s", gt=0.0)
    heading_rad: float | None = setting(None, "heading_deg", kind="optional_number", unit="deg")
    min_line_m: float = setting(20.0, gt=0.0)


def _read_plan(r: ConfigReader) -> PlanParams:
    params = PlanParams(**read_fields(r, PlanParams))
    r.done()
    if params.n_train + params.n_test < 1:
        raise config_error(f"{r.path}.n_train + n_test", ">= 1 line", 0)
    return params


# ------------------------------------------------------------------------------ sonar
@dataclass(frozen=True)
class SonarParams:
    """Sidescan sensor and receiver chain (SI units, radians).

    Beam pattern (one-way power) over the depression angle theta:
    ``b = max(exp(-ln2 |2 (theta - tilt) / width|^rolloff), 10^(sidelobe_db / 10))`` — -3 dB
    at the nominal beam edges; the echo carries ``b^2``.
    """

    frequency_hz: float = setting(850e3, "frequency_khz", unit="khz", gt=0.0)
    tilt_rad: float = setting(math.radians(25.0), "tilt_deg", unit="deg", ge=0.0, lt=90.0)
    beam_width_rad: float = setting(
        math.radians(50.0), "beam_width_deg", unit="deg", gt=0.0, lt=180.0
    )
    beam_rolloff: float = setting(2.0, gt=0.0)
    sidelobe_db: float = setting(-22.0, lt=0.0)
    min_range_m: float = setting(1.0, gt=0.0)
    max_range_m: float = setting(50.0, gt=0.0)
    n_bins: int = setting(512, kind="integer", ge=2)
    oversampling: int = setting(4, kind="integer", ge=1)
    rays_per_raw_bin: float = setting(1.5, gt=0.0)
    theta_ray_fraction: float = setting(0.25, gt=0.0, lt=1.0)
    salinity_ppt: float = setting(35.0, "water.salinity_ppt", ge=0.0, le=45.0)
    temperature_c: float = setting(8.0, "water.temperature_c", ge=-2.0, le=35.0)
    ph: float = setting(8.0, "water.ph", ge=6.0, le=9.0)
    tvg_spreading_exponent: float = setting(3.0, "tvg.spreading_exponent", ge=0.0, le=6.0)
    tvg_absorption_factor: float = setting(1.0, "tvg.absorption_factor", ge=0.0, le=2.0)
    speckle_looks: float = setting(1.0, gt=0.0)
    snr_db: float = setting(18.0)
    reference_level: float = setting(0.3, gt=0.0, le=1.0)
    quantisation_bits: int = setting(16, kind="integer", ge=1)

    @property
    def n_raw_bins(self) -> int:
        return self.n_bins * self.oversampling

    @property
    def beam_limits_rad(self) -> tuple[float, float]:
        return (self.tilt_rad - self.beam_width_rad / 2, self.tilt_rad + self.beam_width_rad / 2)


def _read_sonar(r: ConfigReader) -> SonarParams:
    params = SonarParams(**read_fields(r, SonarParams))
    r.done()
    if params.max_range_m <= params.min_range_m:
        raise config_error(
            f"{r.path}.max_range_m", f"> min_range_m ({params.min_range_m})", params.max_range_m
        )
    if params.quantisation_bits > 32:
        raise config_error(f"{r.path}.quantisation_bits", "<= 32", params.quantisation_bits)
    return params


# ------------------------------------------------------------------------- randomize
def _optional_pair(key: str, unit: str | None = None, **bounds: float) -> Any:
    """A randomised range of :class:`RandomizeParams`: ``[low, high]``, or null (the
    survey's own value)."""
    return setting(None, key, kind="optional_pair", unit=unit, **bounds)


@dataclass(frozen=True)
class RandomizeParams:
    """Per-line randomised sensor, seabed response and altitude (domain randomisation).

    Every line of the listed ``splits`` draws its own sonar (each given ``[low, high]``
    range, uniform; angles in radians here), receiver gain (dB, uniform), per-material
    backscatter strength (``mu`` times a log-uniform factor) and angular exponent (plus a
    uniform offset), and an altitude offset (the sonar flies that much higher above the
    same seabed, as if the site were deeper under that line). Ranges left ``None`` keep the
    survey's value. Draws use their own random stream per line, so lines outside ``splits``
    are identical to those of the same survey without randomisation.
    """

    splits: tuple[str, ...] = ("train",)
    tilt_rad: tuple[float, float] | None = _optional_pair("sonar.tilt_deg", "deg", gt=0.0, le=89.0)
    beam_width_rad: tuple[float, float] | None = _optional_pair(
        "sonar.beam_width_deg", "deg", gt=0.0, le=179.0
    )
    beam_rolloff: tuple[float, float] | None = _optional_pair("sonar.beam_rolloff", gt=0.0)
    sidelobe_db: tuple[float, float] | None = _optional_pair("sonar.sidelobe_db", le=-1.0)
    tvg_spreading_exponent: tuple[float, float] | None = _optional_pair(
        "sonar.tvg_spreading_exponent", le=6.0
    )
    tvg_absorption_factor: tuple[float, float] | None = _optional_pair(
        "sonar.tvg_absorption_factor", le=2.0
    )
    gain_db: tuple[float, float] | None = _optional_pair("sonar.gain_db")
    mu_scale: tuple[float, float] | None = _optional_pair("materials.mu_scale", gt=0.0)
    exponent_offset: tuple[float, float] | None = _optional_pair("materials.exponent_offset")
    altitude_offset_m: tuple[float, float] | None = _optional_pair("altitude_offset_m")
    #: fly each line at its own altitude drawn from this range, following the seabed like an
    #: AUV (the line's altitude minus its along-track smoothed altitude, plus the draw), so
    #: the altitude says nothing of the slopes below (a hull-mounted sonar over hills is low
    #: exactly where the seabed falls away on both sides)
    altitude_m: tuple[float, float] | None = _optional_pair("altitude_m", gt=0.0)
    #: along-track smoothing (m) of the terrain following
    altitude_smoothing_m: float = setting(15.0, gt=0.0)


def _read_randomize(r: ConfigReader) -> RandomizeParams | None:
    """``None`` unless ``enabled: true`` (the ranges are validated either way)."""
    enabled = r.boolean("enabled")
    path, splits = r.get("splits", ["train"])
    if (
        not isinstance(splits, Sequence)
        or isinstance(splits, str)
        or not splits
        or any(x not in ("train", "test") for x in splits)
    ):
        raise config_error(path, "a non-empty list of 'train' / 'test'", splits)
    sr = r.section("sonar")  # opened first, as the checks read them: sonar, then materials
    r.section("materials")
    params = RandomizeParams(
        splits=tuple(str(x) for x in splits), **read_fields(r, RandomizeParams)
    )
    for key in ("tvg_spreading_exponent", "tvg_absorption_factor"):
        pair = getattr(params, key)
        if pair is not None and pair[0] < 0:
            raise config_error(f"{sr.path}.{key}[0]", "a number >= 0", pair[0])
    r.done()
    return params if enabled else None


# ----------------------------------------------------------------------------- survey
@dataclass(frozen=True)
class SyntheticSurveyConfig:
    """The whole generator config (``data.survey`` with ``kind: synthetic``)."""

    name: str
    seed: int
    origin: dict
    terrain: TerrainParams
    materials: MaterialParams
    plan: PlanParams
    sonar: SonarParams
    workers: int = 1
    randomize: RandomizeParams | None = None

    @classmethod
    def from_mapping(cls, cfg: Mapping[str, Any]) -> SyntheticSurveyConfig:
        """Validate a plain ``data.survey`` mapping (resolved, no OmegaConf nodes)."""
        r = ConfigReader(cfg, ROOT)
        kind = r.text("kind", "synthetic")
        if kind != "synthetic":
            raise config_error(f"{ROOT}.kind", "'synthetic'", kind)
        name = r.text("name", None)
        if not name or "/" in name or "\\" in name or name.startswith(".") or "$" in name:
            raise config_error(f"{ROOT}.name", "a plain folder name (e.g. synthetic_d1_demo)", name)
        seed = r.integer("seed", 0, ge=0)
        terrain = _read_terrain(r.section("terrain"))
        if terrain.grid is None:
            origin = _read_origin(r.section("origin"))
        else:
            path, given = r.get("origin", None)
            if given is not None:
                raise config_error(
                    path, "no origin next to terrain.grid (the grid gives it)", given
                )
            origin = {}
        materials = _read_materials(r.section("materials"))
        for i, obj in enumerate(terrain.objects):
            if obj.material is not None and obj.material not in materials.names:
                raise config_error(
                    f"{ROOT}.terrain.objects[{i}].material",
                    f"one of {list(materials.names)}",
                    obj.material,
                )
        plan = _read_plan(r.section("plan"))
        sonar = _read_sonar(r.section("sonar"))
        workers = r.integer("workers", 1, ge=1)
        randomize = _read_randomize(r.section("randomize"))
        r.text("description", None)
        unknown = sorted(set(r.data) - r.used)
        if unknown:
            warnings.warn(
                f"{ROOT}: ignoring keys {unknown} unknown to the synthetic generator",
                stacklevel=2,
            )
        return cls(name, seed, origin, terrain, materials, plan, sonar, workers, randomize)

    def to_dict(self) -> dict[str, Any]:
        """Plain, JSON/YAML-serialisable dict of the resolved config (radians, SI)."""
        d = asdict(self)
        return _plain(d)

    def hash(self) -> str:
        """Cache key: the resolved config minus unhashed keys, plus the generator version.

        Options that are off (randomize, a grid terrain, a plan heading) leave the key as it
        was before they existed. A grid terrain enters by its file's name and SHA-256, not
        its path, so the same grid anywhere gives the same key.
        """
        d = {k: v for k, v in self.to_dict().items() if k not in UNHASHED_KEYS}
        if d.get("randomize") is None:  # off: the same data (and cache key) as without it
            d.pop("randomize", None)
        for section, key, neutral in _NEUTRAL_KEYS:
            if d[section].get(key) == neutral:
                d[section].pop(key)
        grid = d["terrain"].get("grid")
        if grid is not None:
            if grid.get("cell_m") is None:  # added later; its own cell: the key as before
                grid.pop("cell_m")
            for key in ("path", "materials_raster"):
                if grid[key] is not None:
                    grid[key] = {"name": Path(grid[key]).name, "sha256": file_digest(grid[key])}
        return stable_hash({"generator_version": GENERATOR_VERSION, "config": d})


#: keys added after the first presets, with the value at which they change nothing
_NEUTRAL_KEYS = (
    ("terrain", "grid", None),
    ("plan", "heading_rad", None),
    ("plan", "min_line_m", 20.0),
    ("terrain", "objects", []),
)


def _read_origin(r: ConfigReader) -> dict:
    crs = r.text("crs", "EPSG:32633")
    origin = {
        "crs": crs,
        "easting": r.number("easting", 680000.0),
        "northing": r.number("northing", 6580000.0),
    }
    r.done()
    return origin


def _plain(obj: Any) -> Any:
    if isinstance(obj, dict):
        return {str(k): _plain(v) for k, v in obj.items()}
    if isinstance(obj, list | tuple):
        return [_plain(v) for v in obj]
    if isinstance(obj, float | int | str | bool) or obj is None:
        return obj
    return float(obj)
