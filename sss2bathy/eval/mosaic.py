"""Georeferenced sidescan mosaics: every bin of every ping placed on the ground and gridded.

What surveyors' sidescan tools write (a GeoTIFF of backscatter in the survey's projected
CRS, with a PNG quicklook), from a survey folder's lines:

1. **Placement** (:func:`place_line`). ``flat``: each bin's isotemporal arc meets a flat
   seabed ``altitude`` below the sonar (the slant-range correction, with the vehicle's
   attitude: :func:`~sss2bathy.geometry.flat_seabed_depression` and
   :func:`~sss2bathy.geometry.arc_point`; on a level vehicle the ground range is
   ``sqrt(r^2 - h^2)`` across track). ``grid``: each bin is draped on a height grid (the
   reconstructed SIREN map, an MBES grid) by the project's draping
   (:func:`~sss2bathy.draping.drape_line`), which also finds the bins that see no seabed
   there (shadow, no hit).
2. **Values** (:func:`mosaic_values`). ``relative``: the intensity relative to its
   along-track mean at the same slant range (the CNN's ``relative`` channel,
   :func:`~sss2bathy.data.masks.relative_channel`: beam pattern, gain, range and altitude
   divide out), ``median``: the CNN's input normalisation (each head divided by its median
   seabed bin, :func:`~sss2bathy.data.masks.sonar_normalized_intensity`), or ``raw``. Both
   normalisations use the sonar-only mask, so a mosaic never depends on an MBES grid
   except through ``placement=grid``.
3. **Gridding** (:func:`build_mosaic`). Each bin owns its footprint in the waterfall (half
   the way to its neighbouring pings and bins); the footprint is sampled finely enough for
   the cell size (positions interpolated bilinearly between the placed neighbours, the bin's
   own value), so cells between pings or between far-apart bins near nadir are filled, and
   no footprint bridges a masked bin or a step more than :data:`GAP_FACTOR` times the usual
   one (a navigation gap). Overlaps are resolved per cell by ``overlap``: ``nadir`` (the
   default) keeps the sample with the smallest ground range (horizontal distance from its
   ping's sonar: the best resolved, least layover-prone data, as surveyors' tools do;
   ties: the first line, ping, side, bin), ``max`` the largest value, ``mean`` the mean of
   the samples (weighted by footprint). Cells with no sample are no-data (NaN). The gap
   limit uses the median of the steps that move, so navigation that repeats a fix for
   several pings (a real Iver2 line: positions quantised to ~0.22 m, half the ping steps
   0) is bridged.

Which bins are no-data is the ``blank`` set of mask reasons (default water column, no hit
and out of beam: on the real Iver2 line the near-nadir bins outside a 20 deg / 50 deg beam
hold almost no echo, so placed they would paint a dark band beside the track). Shadows are
kept: a sidescan shadow is data, the dark behind a target. Under ``placement=grid`` the draping's own mask decides instead (a
bin in the grid's geometric shadow has no ground position at all).

:func:`write_mosaic` writes the GeoTIFF through :func:`sss2bathy.io.export.write_geotiff`
(projected coordinates, the origin's CRS, provenance tags) and the quicklook;
:func:`write_run_mosaic` is the one call for a run folder. :func:`placement_errors`
measures a placement against the draping on a true grid.
"""

from __future__ import annotations

import logging
import math
import warnings
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from sss2bathy.data.masks import SonarMaskConfig, relative_channel, sonar_normalized_intensity
from sss2bathy.draping import DrapeConfig, as_surface, drape_line
from sss2bathy.eval.maps import axis_labels, grid_over_bounds, north_arrow
from sss2bathy.geometry import arc_point, flat_seabed_depression
from sss2bathy.io.export import add_geotiff_tags, write_geotiff
from sss2bathy.survey import (
    MASK_NO_HIT,
    MASK_VALID,
    MASK_WATER_COLUMN,
    BathyGrid,
    SidescanLine,
    Survey,
)
from sss2bathy.survey.masks import MASK_NAMES
from sss2bathy.utils.atomic import save_figure
from sss2bathy.utils.progress import log_progress

log = logging.getLogger(__name__)

__all__ = [
    "DEFAULT_BLANK",
    "GAP_FACTOR",
    "Mosaic",
    "MosaicConfig",
    "NORMALISATIONS",
    "OVERLAP_RULES",
    "PLACEMENTS",
    "PlacedLine",
    "blank_bits",
    "build_mosaic",
    "flat_seabed_points",
    "mosaic_values",
    "place_line",
    "placement_errors",
    "render_mosaic",
    "write_mosaic",
    "write_run_mosaic",
]

PLACEMENTS = ("flat", "grid")
OVERLAP_RULES = ("nadir", "max", "mean")
NORMALISATIONS = ("relative", "median", "raw")
#: mask reasons (names of :data:`sss2bathy.survey.masks.MASK_NAMES`) that are no-data by default
DEFAULT_BLANK = ("water_column", "no_hit", "out_of_beam")
#: a footprint does not bridge a step between neighbouring bins longer than this many times
#: the median step of that bin column (along track) or bin pair (across) over the line
GAP_FACTOR = 8.0
#: at most this many footprint samples per bin along each waterfall axis (odd)
MAX_SAMPLES = 15


# ----------------------------------------------------------------------------- config
@dataclass(frozen=True)
class MosaicConfig:
    """How a mosaic is made (the ``sss2bathy-mosaic`` keys of the same names).

    Attributes:
        resolution: cell size (m, > 0).
        placement: ``flat`` (flat seabed at the altimeter altitude) or ``grid`` (draped on a
            height grid, given to :func:`build_mosaic`).
        overlap: ``nadir`` | ``max`` | ``mean`` (module docstring).
        normalise: ``relative`` | ``median`` | ``raw`` (module docstring).
        blank: mask reasons whose bins are no-data (names of ``MASK_NAMES``).
        sonar_mask: the sonar-only mask's settings (``data.sonar_mask``), used for the
            normalisations and the flat placement's mask.
    """

    resolution: float = 0.1
    placement: str = "flat"
    overlap: str = "nadir"
    normalise: str = "relative"
    blank: tuple[str, ...] = DEFAULT_BLANK
    sonar_mask: SonarMaskConfig = SonarMaskConfig()

    def __post_init__(self) -> None:
        r = self.resolution
        if isinstance(r, bool) or not (isinstance(r, int | float) and math.isfinite(r) and r > 0):
            raise ValueError(f"resolution: expected a cell size in metres > 0, found {r!r}")
        for key, options in (
            ("placement", PLACEMENTS),
            ("overlap", OVERLAP_RULES),
            ("normalise", NORMALISATIONS),
        ):
            if getattr(self, key) not in options:
                raise ValueError(
                    f"{key}: expected one of {list(options)}, found {getattr(self, key)!r}"
                )
        blank_bits(self.blank)
        object.__setattr__(self, "blank", tuple(self.blank))
        object.__setattr__(self, "sonar_mask", SonarMaskConfig.coerce(self.sonar_mask))

    @classmethod
    def coerce(cls, cfg: MosaicConfig | Mapping[str, Any] | None) -> MosaicConfig:
        """A config from ``None`` (defaults), a mapping of its fields, or a config.
        ``normalise`` may also be ``true`` (``relative``) or ``false`` (``raw``)."""
        if cfg is None:
            return cls()
        if isinstance(cfg, MosaicConfig):
            return cfg
        if not isinstance(cfg, Mapping):
            raise ValueError(f"mosaic: expected a mapping, found {type(cfg).__name__}")
        known = set(cls.__dataclass_fields__)
        unknown = sorted(set(map(str, cfg)) - known)
        if unknown:
            raise ValueError(f"mosaic: unknown keys {unknown}; expected some of {sorted(known)}")
        kw = {str(k): v for k, v in cfg.items()}
        if isinstance(kw.get("normalise"), bool):
            kw["normalise"] = "relative" if kw["normalise"] else "raw"
        if "blank" in kw:
            blank = kw["blank"]
            if isinstance(blank, str) or not isinstance(blank, Sequence):
                raise ValueError(
                    f"blank: expected a list of mask reasons of {sorted(MASK_NAMES.values())}, "
                    f"found {blank!r}"
                )
            kw["blank"] = tuple(str(b) for b in blank)
        if "resolution" in kw and isinstance(kw["resolution"], int | float):
            kw["resolution"] = float(kw["resolution"])
        return cls(**kw)


def blank_bits(names: Sequence[str]) -> int:
    """The OR of the ``MASK_*`` bits named in ``names`` (``ValueError`` on an unknown name)."""
    by_name = {v: k for k, v in MASK_NAMES.items()}
    bits = 0
    for name in names:
        if name not in by_name:
            raise ValueError(f"blank: expected names of {sorted(by_name)}, found {name!r}")
        bits |= by_name[name]
    return bits


# ----------------------------------------------------------------------------- placement
def flat_seabed_points(line: SidescanLine) -> np.ndarray:
    """``(P, 2, B, 3)`` where each bin's arc meets a flat seabed ``altitude_m`` below the
    sonar (float64, local ENU); NaN where it does not (range below the altitude, no
    altitude). With a level vehicle the point lies ``sqrt(r^2 - h^2)`` across track."""
    theta = flat_seabed_depression(line.range_m, line.altitude_m, line.rotation)
    pos = line.position.astype(np.float64)[:, None, None, :]
    rot = line.rotation.astype(np.float64)[:, None, None, :, :]
    r = np.ascontiguousarray(
        np.broadcast_to(line.range_m.astype(np.float64)[None, None, :], theta.shape)
    )
    side = np.array([0, 1])[None, :, None]
    return np.asarray(arc_point(pos, rot, r, theta, side), dtype=np.float64)


@dataclass
class PlacedLine:
    """One line's bins on the ground.

    Attributes:
        points: ``(P, 2, B, 3)`` float64 local ENU points; NaN where a bin has none.
        ground_range: ``(P, 2, B)`` horizontal distance (m) from the ping's sonar.
        mask: ``(P, 2, B)`` uint8 ``MASK_*`` reasons (0 valid; a bin without a point has
            ``MASK_NO_HIT`` or ``MASK_WATER_COLUMN``).
    """

    points: np.ndarray
    ground_range: np.ndarray
    mask: np.ndarray


def place_line(
    line: SidescanLine,
    placement: str = "flat",
    grid: BathyGrid | Any = None,
    sonar_mask: np.ndarray | None = None,
    drape_cfg: DrapeConfig | Mapping[str, Any] | None = None,
) -> PlacedLine:
    """Every bin of ``line`` on the ground.

    Args:
        line: the sidescan line.
        placement: ``flat`` (:func:`flat_seabed_points`; the mask is ``sonar_mask``, the
            sonar-only mask, plus water column where the arc misses the seabed) or ``grid``
            (:func:`~sss2bathy.draping.drape_line` on ``grid``; the draping's mask, plus no
            hit where the intensity is not finite).
        grid: a ``BathyGrid`` (local frame) or a prepared draping surface, for ``grid``.
        sonar_mask: ``(P, 2, B)`` the sonar-only mask (default: all valid).
        drape_cfg: the draping's settings.
    """
    shape = line.intensity.shape
    if placement == "flat":
        points = flat_seabed_points(line)
        mask = np.zeros(shape, np.uint8) if sonar_mask is None else sonar_mask.copy()
        mask[~np.isfinite(points[..., 0])] |= MASK_WATER_COLUMN
    elif placement == "grid":
        if grid is None:
            raise ValueError("grid: expected a height grid for placement=grid, found none")
        draped = drape_line(line, grid, drape_cfg)
        points = draped.points.astype(np.float64)
        mask = draped.mask.copy()
        mask[~np.isfinite(points[..., 0]) & (mask == MASK_VALID)] |= MASK_NO_HIT
    else:
        raise ValueError(f"placement: expected one of {list(PLACEMENTS)}, found {placement!r}")
    mask[~np.isfinite(line.intensity)] |= MASK_NO_HIT
    d = points[..., :2] - line.position[:, None, None, :2]
    ground = np.hypot(d[..., 0], d[..., 1])
    return PlacedLine(points=points, ground_range=ground, mask=mask)


def mosaic_values(
    line: SidescanLine, normalise: str = "relative", sonar_cfg: Any = None
) -> tuple[np.ndarray, np.ndarray]:
    """``(values (P, 2, B) float32, sonar-only mask (P, 2, B) uint8)`` of a line.

    ``relative``: :func:`~sss2bathy.data.masks.relative_channel` of the CNN's normalised
    intensity; ``median``: that normalised intensity
    (:func:`~sss2bathy.data.masks.sonar_normalized_intensity`); ``raw``: as recorded."""
    norm, mask = sonar_normalized_intensity(line, sonar_cfg)
    if normalise == "relative":
        values = relative_channel(norm, mask)
    elif normalise == "median":
        values = norm
    elif normalise == "raw":
        values = line.intensity.astype(np.float32)
    else:
        raise ValueError(f"normalise: expected one of {list(NORMALISATIONS)}, found {normalise!r}")
    values = np.where(np.isfinite(line.intensity), values, np.nan).astype(np.float32)
    return values, mask


# ----------------------------------------------------------------------------- gridding
@dataclass
class Mosaic:
    """A gridded mosaic in the survey's local frame.

    Attributes:
        grid: the values (``heights`` holds them; NaN no-data), local frame, the CRS label.
        count: ``(ny, nx)`` footprint samples per cell (all lines).
        config: how it was made.
        lines: names of the lines in it.
    """

    grid: BathyGrid
    count: np.ndarray
    config: MosaicConfig
    lines: list[str]

    @property
    def coverage(self) -> float:
        """Fraction of the cells with a value."""
        return float(np.isfinite(self.grid.heights).mean())


class _Accumulator:
    """Per-cell reduction of footprint samples by an overlap rule."""

    def __init__(self, shape: tuple[int, int], rule: str) -> None:
        self.rule, self.shape = rule, shape
        n = shape[0] * shape[1]
        self.count = np.zeros(n, np.int64)
        if rule == "nadir":
            self.best = np.full(n, np.inf)
            self.value = np.full(n, np.nan)
        elif rule == "max":
            self.value = np.full(n, -np.inf)
        else:
            self.total = np.zeros(n)

    def add(self, cell: np.ndarray, ground: np.ndarray, value: np.ndarray) -> None:
        n = self.count.size
        self.count += np.bincount(cell, minlength=n)
        if self.rule == "nadir":
            order = np.lexsort((ground, cell))  # by cell, then ground range (stable)
            uc, first = np.unique(cell[order], return_index=True)
            g, v = ground[order][first], value[order][first]
            better = g < self.best[uc]
            self.best[uc[better]] = g[better]
            self.value[uc[better]] = v[better]
        elif self.rule == "max":
            np.maximum.at(self.value, cell, value)
        else:
            self.total += np.bincount(cell, weights=value, minlength=n)

    def result(self) -> np.ndarray:
        has = self.count > 0
        if self.rule == "mean":
            out = np.where(has, self.total / np.maximum(self.count, 1), np.nan)
        else:
            out = np.where(has, self.value, np.nan)
        return out.reshape(self.shape).astype(np.float32)


def _odd_samples(step: np.ndarray, cell: float) -> int:
    """Samples per bin along one axis so that they lie at most half a cell apart."""
    step = step[np.isfinite(step)]
    if step.size == 0:
        return 1
    n = int(math.ceil(2.0 * float(np.percentile(step, 99)) / cell))
    n = max(1, min(n, MAX_SAMPLES))
    return n if n % 2 == 1 else n + 1


def _footprint_samples(xy: np.ndarray, ground: np.ndarray, ok: np.ndarray, cell: float) -> Any:
    """Yield ``(xy (N, 2), ground (N,), bin index (N,))`` of each bin's footprint samples.

    Sub-sample ``(da, db)`` (fractions of a ping and of a bin, within half a step) lies at
    the bilinear interpolation of the bin and its neighbours in the directions of ``da``
    and ``db``; it exists where those neighbours are valid and no step between them is a
    gap (:data:`GAP_FACTOR`)."""
    P, S, B = ok.shape
    step_a = np.full((P, S, B), np.nan)  # ping p -> p + 1
    step_b = np.full((P, S, B), np.nan)  # bin i -> i + 1
    if P > 1:
        pair = ok[1:] & ok[:-1]
        step_a[:-1] = np.where(pair, np.linalg.norm(xy[1:] - xy[:-1], axis=-1), np.nan)
    if B > 1:
        pair = ok[..., 1:] & ok[..., :-1]
        step_b[..., :-1] = np.where(
            pair, np.linalg.norm(xy[..., 1:, :] - xy[..., :-1, :], axis=-1), np.nan
        )
    with np.errstate(all="ignore"), warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # a column without a valid pair
        # medians of the steps that move: navigation that repeats a fix for several pings
        # (positions quantised, fixes slower than pings) has many steps of 0
        lim_a = GAP_FACTOR * np.nanmedian(np.where(step_a > 0, step_a, np.nan), 0, keepdims=True)
        lim_b = GAP_FACTOR * np.nanmedian(np.where(step_b > 0, step_b, np.nan), 0, keepdims=True)
    edge_a = step_a <= lim_a  # NaN compares False: no edge
    edge_b = step_b <= lim_b
    na, nb = _odd_samples(step_a, cell), _odd_samples(step_b, cell)
    p_idx, i_idx = np.arange(P)[:, None, None], np.arange(B)[None, None, :]
    s_idx = np.arange(S)[None, :, None]
    flat_index = (p_idx * S + s_idx) * B + i_idx
    for ka in range(na):
        da = (ka - (na - 1) / 2) / na
        sa = 1 if da > 0 else -1
        pa = np.clip(p_idx + sa, 0, P - 1)
        # the along-track edge between p and p + sa: edge_a at min(p, p + sa)
        ea = edge_a[np.clip(np.minimum(p_idx, p_idx + sa), 0, P - 1), s_idx, i_idx]
        ea = ea & (p_idx + sa >= 0) & (p_idx + sa < P)
        for kb in range(nb):
            db = (kb - (nb - 1) / 2) / nb
            sb = 1 if db > 0 else -1
            ib = np.clip(i_idx + sb, 0, B - 1)
            eb = edge_b[p_idx, s_idx, np.clip(np.minimum(i_idx, i_idx + sb), 0, B - 1)]
            eb = eb & (i_idx + sb >= 0) & (i_idx + sb < B)
            wa, wb = abs(da), abs(db)
            use = ok.copy()
            pts = (1 - wa) * (1 - wb) * xy
            g = (1 - wa) * (1 - wb) * ground
            if wa > 0:
                use &= ea
                pts = pts + wa * (1 - wb) * xy[pa, s_idx, i_idx]
                g = g + wa * (1 - wb) * ground[pa, s_idx, i_idx]
            if wb > 0:
                use &= eb
                pts = pts + (1 - wa) * wb * xy[p_idx, s_idx, ib]
                g = g + (1 - wa) * wb * ground[p_idx, s_idx, ib]
            if wa > 0 and wb > 0:
                # the far corner: its edges to both neighbours
                ea2 = edge_a[np.clip(np.minimum(p_idx, p_idx + sa), 0, P - 1), s_idx, ib]
                eb2 = edge_b[pa, s_idx, np.clip(np.minimum(i_idx, i_idx + sb), 0, B - 1)]
                use &= ea2 & eb2
                pts = pts + wa * wb * xy[pa, s_idx, ib]
                g = g + wa * wb * ground[pa, s_idx, ib]
            if use.any():
                yield pts[use], g[use], np.broadcast_to(flat_index, use.shape)[use]


def build_mosaic(
    survey: Survey,
    cfg: MosaicConfig | Mapping[str, Any] | None = None,
    grid: BathyGrid | None = None,
    lines: Sequence[str] | None = None,
    drape_cfg: DrapeConfig | Mapping[str, Any] | None = None,
) -> Mosaic:
    """Grid the bins of ``survey``'s lines (``lines``: their names; default all) into a mosaic.

    Args:
        survey: the survey (its origin's CRS labels the result).
        cfg: :class:`MosaicConfig` or its fields.
        grid: heights (local frame) to drape on with ``placement=grid``; default the
            survey's own grid.
        lines: the lines to use (default all).
        drape_cfg: the draping's settings with ``placement=grid``.
    """
    cfg = MosaicConfig.coerce(cfg)
    chosen = list(survey.lines) if lines is None else [survey.line(n) for n in lines]
    if not chosen:
        raise ValueError(f"lines: expected at least one line of survey '{survey.name}', found none")
    surface = None
    if cfg.placement == "grid":
        grid = grid if grid is not None else survey.grid
        if grid is None:
            raise ValueError(
                f"grid: placement=grid needs a height grid (the survey '{survey.name}' has no "
                "grid.tif); give grid=<GeoTIFF> or use placement=flat"
            )
        surface = as_surface(grid, DrapeConfig.coerce(drape_cfg).engine)
    bits = blank_bits(cfg.blank)
    placed = []
    for line in log_progress(chosen, "mosaic: placing", unit="lines"):
        values, smask = mosaic_values(line, cfg.normalise, cfg.sonar_mask)
        pl = place_line(line, cfg.placement, surface, smask, drape_cfg)
        # a bin without a point (water column, draped shadow or no hit) is never placed
        ok = (
            ((pl.mask & np.uint8(bits)) == 0) & np.isfinite(pl.points[..., 0]) & np.isfinite(values)
        )
        placed.append((line, pl, values, ok))
        log.debug("mosaic: line %s, %d of %d bins placed", line.name, int(ok.sum()), ok.size)
    xy_all = [pl.points[..., :2][ok] for _, pl, _, ok in placed]
    if sum(len(a) for a in xy_all) == 0:
        raise ValueError(
            f"survey '{survey.name}': no bin could be placed (placement={cfg.placement}, "
            f"blank={list(cfg.blank)}); every bin is masked"
        )
    xy = np.concatenate(xy_all)
    pad = cfg.resolution
    bounds = (
        xy[:, 0].min() - pad,
        xy[:, 1].min() - pad,
        xy[:, 0].max() + pad,
        xy[:, 1].max() + pad,
    )
    crs = (survey.origin or {}).get("crs")
    out = grid_over_bounds(bounds, cfg.resolution, crs=crs, origin=survey.origin)
    ny, nx = out.shape
    acc = _Accumulator((ny, nx), cfg.overlap)
    west, south = out.x0 - cfg.resolution / 2, out.y0 - cfg.resolution / 2
    for _line, pl, values, ok in log_progress(placed, "mosaic: gridding", unit="lines"):
        flat_values = values.reshape(-1)
        for pts, g, idx in _footprint_samples(
            pl.points[..., :2], pl.ground_range, ok, out.cell_size
        ):
            ix = np.floor((pts[:, 0] - west) / cfg.resolution).astype(np.int64)
            iy = np.floor((pts[:, 1] - south) / cfg.resolution).astype(np.int64)
            inside = (ix >= 0) & (ix < nx) & (iy >= 0) & (iy < ny)
            acc.add((iy * nx + ix)[inside], g[inside], flat_values[idx[inside]])
    heights = acc.result()
    mosaic_grid = BathyGrid(heights, out.x0, out.y0, out.cell_size, crs)
    return Mosaic(
        grid=mosaic_grid,
        count=acc.count.reshape(ny, nx),
        config=cfg,
        lines=[ln.name for ln in chosen],
    )


# ----------------------------------------------------------------------------- output
#: the quicklook's colour of no-data cells (not white: white is the strongest echo)
NODATA_COLOUR = "#dce6f0"

VALUE_DESCRIPTION = {
    "relative": "sidescan intensity relative to its along-track mean at the same range (1 = typical)",
    "median": "sidescan intensity / the head's median seabed intensity (1 = typical)",
    "raw": "sidescan intensity as recorded (amplitude-like, after the sonar's gain)",
}


def mosaic_tags(mosaic: Mosaic, survey: Survey | None = None) -> dict[str, str]:
    """GDAL metadata of a mosaic GeoTIFF (what the values are and how they were placed)."""
    cfg = mosaic.config
    return {
        "SSS2BATHY_UNITS": "unitless" if cfg.normalise != "raw" else "sonar counts",
        "SSS2BATHY_VERTICAL_REFERENCE": "none (a sidescan mosaic holds intensities)",
        "SSS2BATHY_METHOD": f"sidescan mosaic, placement={cfg.placement}",
        "SSS2BATHY_MOSAIC_VALUES": VALUE_DESCRIPTION[cfg.normalise],
        "SSS2BATHY_MOSAIC_OVERLAP": cfg.overlap,
        "SSS2BATHY_MOSAIC_BLANK": ",".join(cfg.blank) or "none",
        "SSS2BATHY_MOSAIC_LINES": ",".join(mosaic.lines),
        **({"SSS2BATHY_SURVEY": survey.name} if survey is not None else {}),
    }


def write_mosaic(
    mosaic: Mosaic,
    path: str | Path,
    origin: Mapping[str, Any] | None,
    png: bool = True,
    track: Sequence[np.ndarray] = (),
    survey: Survey | None = None,
) -> list[Path]:
    """Write the mosaic GeoTIFF (projected: local + ``origin``, its CRS) and, with ``png``,
    its quicklook beside it (same stem, ``.png``); returns the files."""
    path = Path(path)
    if path.suffix.lower() not in (".tif", ".tiff"):
        raise ValueError(f"out: expected a GeoTIFF path ending in .tif, found {str(path)!r}")
    path.parent.mkdir(parents=True, exist_ok=True)
    write_geotiff(mosaic.grid, path, origin=origin, tags=mosaic_tags(mosaic, survey))
    _describe_band(path, mosaic.config.normalise)
    written = [path]
    if png:
        written.append(render_mosaic(mosaic, path.with_suffix(".png"), origin, track=track))
    return written


def _describe_band(path: Path, normalise: str) -> None:
    """The band's unit and description: intensities, not the heights a map holds."""
    # keeps the provenance (and the COG layout: the file is rewritten, not edited)
    add_geotiff_tags(
        path,
        {},
        unit="" if normalise != "raw" else "counts",
        description=VALUE_DESCRIPTION[normalise],
    )


def render_mosaic(
    mosaic: Mosaic,
    path: str | Path,
    origin: Mapping[str, Any] | None = None,
    track: Sequence[np.ndarray] = (),
    dpi: int = 110,
    max_inches: float = 9.0,
    title: str | None = None,
) -> Path:
    """A greyscale quicklook PNG in projected coordinates (bright = strong echo, dark =
    shadow, no-data pale blue, :data:`NODATA_COLOUR`), clipped at the 99.5th percentile, with the tracks (``(P, 2)``
    local xy each) and a north arrow."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    g = mosaic.grid
    shift = [float((origin or {}).get(k) or 0.0) for k in ("easting", "northing")]
    ny, nx = g.shape
    extent = (
        g.x0 - g.cell_size / 2 + shift[0],
        g.x0 + (nx - 0.5) * g.cell_size + shift[0],
        g.y0 - g.cell_size / 2 + shift[1],
        g.y0 + (ny - 0.5) * g.cell_size + shift[1],
    )
    data = g.heights
    finite = data[np.isfinite(data)]
    vmax = float(np.percentile(finite, 99.5)) if finite.size else 1.0
    aspect = ny / max(nx, 1)
    w = max_inches if aspect <= 1 else max_inches / aspect
    fig, ax = plt.subplots(figsize=(max(w, 3.0), max(w * aspect, 3.0) + 0.6))
    cmap = plt.get_cmap("gray").with_extremes(bad=NODATA_COLOUR)
    im = ax.imshow(
        np.ma.masked_invalid(data[::-1]),
        extent=extent,
        cmap=cmap,
        vmin=0.0,
        vmax=vmax,
        interpolation="nearest",
    )
    for xy in track:
        xy = np.asarray(xy)
        ax.plot(xy[:, 0] + shift[0], xy[:, 1] + shift[1], color="tab:orange", lw=0.6, alpha=0.8)
    xl, yl = axis_labels(origin)
    ax.set_xlabel(xl, fontsize=7)
    ax.set_ylabel(yl, fontsize=7)
    from matplotlib.ticker import ScalarFormatter

    for axis in (ax.xaxis, ax.yaxis):
        fmt = ScalarFormatter(useOffset=False)
        fmt.set_scientific(False)
        axis.set_major_formatter(fmt)
    ax.tick_params(labelsize=6)
    cfg = mosaic.config
    ax.set_title(
        title
        or f"sidescan mosaic ({cfg.placement} placement, {cfg.normalise}, overlap {cfg.overlap}, "
        f"{cfg.resolution:g} m cells)",
        fontsize=8,
    )
    north_arrow(ax)
    cb = fig.colorbar(im, ax=ax, fraction=0.035, pad=0.02)
    cb.ax.tick_params(labelsize=6)
    cb.set_label(VALUE_DESCRIPTION[cfg.normalise], fontsize=6)
    fig.tight_layout()
    return save_figure(fig, path, dpi=dpi)


def write_run_mosaic(
    run_dir: str | Path,
    survey: Survey,
    grid: BathyGrid | None = None,
    cfg: MosaicConfig | Mapping[str, Any] | None = None,
    lines: Sequence[str] | None = None,
    name: str = "mosaic",
) -> list[Path]:
    """A run folder's mosaic: ``<run_dir>/<name>.tif`` and ``.png``.

    With ``grid`` (e.g. the run's reconstructed map as a local-frame ``BathyGrid``) the bins
    are draped on it (``placement=grid``), else placed on a flat seabed; ``cfg`` sets the
    rest (its ``placement`` is overridden by the presence of ``grid``)."""
    cfg = MosaicConfig.coerce(cfg)
    placement = "grid" if grid is not None else "flat"
    if cfg.placement != placement:
        cfg = MosaicConfig(
            cfg.resolution, placement, cfg.overlap, cfg.normalise, cfg.blank, cfg.sonar_mask
        )
    mosaic = build_mosaic(survey, cfg, grid=grid, lines=lines)
    tracks = [ln.position[:, :2] for ln in survey.lines if lines is None or ln.name in lines]
    return write_mosaic(
        mosaic, Path(run_dir) / f"{name}.tif", survey.origin, track=tracks, survey=survey
    )


# ----------------------------------------------------------------------------- accuracy
def placement_errors(
    line: SidescanLine,
    truth: BathyGrid | Any,
    surface: BathyGrid | Mapping[str, BathyGrid] | Any = None,
    drape_cfg: DrapeConfig | Mapping[str, Any] | None = None,
) -> dict[str, dict[str, float]]:
    """Horizontal placement error (m) of each bin against its draping on the true grid.

    The draping of ``line`` on ``truth`` is the truth (bins it finds valid), draped once.
    Returns, for ``flat`` (:func:`flat_seabed_points`) and, with ``surface``, for ``grid``
    (draped on ``surface``, e.g. a reconstructed map) — or, when ``surface`` maps labels to
    grids, for each label — ``{"median", "p95", "max", "n"}`` over the bins valid in both."""
    surfaces = surface if isinstance(surface, Mapping) else {"grid": surface}
    surfaces = {k: v for k, v in surfaces.items() if v is not None}
    if "flat" in surfaces:
        raise ValueError("surface: expected labels other than 'flat' (the flat seabed's)")
    true = drape_line(line, truth, drape_cfg)
    ok_true = true.valid & np.isfinite(true.points[..., 0])
    out: dict[str, dict[str, float]] = {}

    def stats(points: np.ndarray, ok: np.ndarray) -> dict[str, float]:
        both = ok_true & ok
        d = np.hypot(*(points[..., :2][both] - true.points[..., :2][both].astype(np.float64)).T)
        if d.size == 0:
            return {"median": math.nan, "p95": math.nan, "max": math.nan, "n": 0}
        return {
            "median": float(np.median(d)),
            "p95": float(np.percentile(d, 95)),
            "max": float(d.max()),
            "n": int(d.size),
        }

    flat = flat_seabed_points(line)
    out["flat"] = stats(flat, np.isfinite(flat[..., 0]))
    for label, grid in surfaces.items():
        other = drape_line(line, grid, drape_cfg)
        out[label] = stats(other.points.astype(np.float64), other.valid)
    return out
