"""Generate a whole synthetic survey in memory: terrain, plan, sidescan, MBES grid.

Random streams are independent per stage (``[seed, stage]``) and per line
(``[seed, 3, line]``), so the output is a pure function of the config.
"""

from __future__ import annotations

import dataclasses
import logging
import math
import time
from dataclasses import dataclass
from typing import Any

import numpy as np

from sss2bathy.sim.config import GENERATOR_VERSION, RandomizeParams, SyntheticSurveyConfig
from sss2bathy.sim.plan import PlannedLine, plan_survey, validate_swath
from sss2bathy.sim.sonar import (
    MASK_NO_HIT,
    MASK_SHADOW,
    MASK_WATER_COLUMN,
    MaterialResponse,
    RayCaster,
    ReceiverCalibration,
    absorption_db_per_m,
    calibrate_receiver,
    fan_basis,
    range_bins,
    receive,
    simulate_pings,
    sound_speed_mps,
)
from sss2bathy.sim.terrain import (
    Terrain,
    TerrainSurface,
    generate_terrain,
    grid_mbes_heights,
    grid_terrain,
    mbes_heights,
    nlat_statistics,
)
from sss2bathy.survey import BathyGrid, SensorParams, SidescanLine, Survey, mask_reason_counts
from sss2bathy.utils.progress import log_progress

log = logging.getLogger(__name__)

_STAGE_TERRAIN, _STAGE_PLAN, _STAGE_MBES, _STAGE_LINES, _STAGE_RANDOMIZE = 0, 1, 2, 3, 4


@dataclass
class _Physics:
    """Everything a line simulation needs besides the terrain (picklable)."""

    config: SyntheticSurveyConfig
    response: MaterialResponse
    calibration: ReceiverCalibration
    absorption: float
    sensor: SensorParams


def simulate_line(
    line: PlannedLine,
    index: int,
    physics: _Physics,
    caster: RayCaster,
    surface: TerrainSurface,
) -> SidescanLine:
    """Simulate one planned line into a :class:`SidescanLine` with ground-truth extras."""
    cfg = physics.config
    rng = np.random.default_rng([cfg.seed, _STAGE_LINES, index])
    echoes = simulate_pings(
        caster,
        surface,
        line.position,
        line.rotation,
        cfg.sonar,
        physics.response,
        rng,
        absorption_db_m=physics.absorption,
        altitudes=line.altitude_m,
    )
    intensity = receive(echoes.power_raw, cfg.sonar, physics.calibration, rng, physics.absorption)
    terrain = surface.terrain if isinstance(surface, TerrainSurface) else None
    if terrain is not None and terrain.no_seabed is not None:
        echoes.mask = mask_no_seabed(
            echoes.mask, line.position, line.rotation, line.altitude_m, cfg.sonar, terrain
        )
    return SidescanLine(
        name=line.name,
        time_s=line.time_s,
        position=line.nav_position,
        rotation=line.nav_rotation,
        altitude_m=line.altitude_m.astype(np.float32),
        intensity=intensity,
        range_m=range_bins(cfg.sonar)[0].astype(np.float32),
        sensor=physics.sensor,
        extras={
            "true_n_lat": echoes.n_lat,
            "true_points": echoes.points,
            "true_mask": echoes.mask,
            "true_material": echoes.material,
            "true_position": line.position,
            "true_rotation": line.rotation,
        },
    )


def mask_no_seabed(
    mask: np.ndarray,
    positions: np.ndarray,
    rotations: np.ndarray,
    altitudes: np.ndarray,
    sonar,
    terrain: Terrain,
) -> np.ndarray:
    """``mask`` with the empty bins that look at no seabed (a grid terrain's large holes,
    its outside) marked no hit instead of shadow.

    A bin's ground point is where its slant range meets a level seabed at the ping's
    altitude, along the fan's outward direction; bins nearer than the altitude keep their
    bits.
    """
    r = range_bins(sonar)[0]
    e_out, _ = fan_basis(np.asarray(rotations, dtype=np.float64))
    horiz = e_out[..., :2]
    horiz = horiz / np.maximum(np.linalg.norm(horiz, axis=-1, keepdims=True), 1e-12)
    alt = np.asarray(altitudes, dtype=np.float64)[:, None, None]
    with np.errstate(invalid="ignore"):
        ground = np.sqrt(r[None, None, :] ** 2 - alt**2)  # (P, 1, B); NaN inside the altitude
    xy = positions[:, None, None, :2] + ground[..., None] * horiz[:, :, None, :]
    ix = np.rint(xy[..., 0] / terrain.cell_m)
    iy = np.rint(xy[..., 1] / terrain.cell_m)
    ny, nx = terrain.heights.shape
    known = np.isfinite(ix) & np.isfinite(iy)
    inside = known & (ix >= 0) & (ix < nx) & (iy >= 0) & (iy < ny)
    seabed = np.zeros(mask.shape, bool)
    sel = np.nonzero(inside)
    seabed[sel] = terrain.seabed[iy[sel].astype(np.int64), ix[sel].astype(np.int64)]
    empty = (mask & (MASK_SHADOW | MASK_NO_HIT)) > 0
    relabel = empty & known & ~seabed & ((mask & MASK_WATER_COLUMN) == 0)
    out = mask.copy()
    out[relabel] = MASK_NO_HIT
    return out


def altitude_summary(planned: list[PlannedLine]) -> dict[str, dict[str, float]]:
    """Sonar altitude above the true seabed: min / median / max over ``all`` pings and per split."""
    groups = {
        "all": planned,
        **{s: [ln for ln in planned if ln.split == s] for s in ("train", "test")},
    }
    out = {}
    for key, lines in groups.items():
        if lines:
            a = np.concatenate([ln.altitude_m for ln in lines])
            out[key] = {
                "min": round(float(a.min()), 3),
                "median": round(float(np.median(a)), 3),
                "max": round(float(a.max()), 3),
            }
    return out


def _draw(rng: np.random.Generator, pair: tuple[float, float] | None, current: float) -> float:
    return current if pair is None else float(rng.uniform(pair[0], pair[1]))


def _smooth_altitude(line: PlannedLine, smoothing_m: float) -> np.ndarray:
    """The line's altitude, Gaussian-smoothed along track over ``smoothing_m`` metres."""
    from scipy.ndimage import gaussian_filter1d

    alt = np.asarray(line.altitude_m, np.float64)
    steps = np.linalg.norm(np.diff(line.position[:, :2], axis=0), axis=1)
    step = float(np.median(steps)) if steps.size else 1.0
    sigma = smoothing_m / max(step, 1e-6)
    return gaussian_filter1d(alt, sigma, mode="nearest") if sigma > 0.5 else alt


def randomize_line(
    line: PlannedLine,
    index: int,
    physics: _Physics,
    randomize: RandomizeParams,
    terrain: Terrain,
    reference_material: int,
    min_altitude_m: float,
) -> tuple[PlannedLine, _Physics, dict[str, Any]]:
    """One line's own sonar, receiver gain, backscatter response and altitude offset.

    Draws come from the stream ``[seed, 4, index]``; returns the (shifted) line, its
    physics and the drawn values (degrees, dB, metres) for the survey metadata. The line's
    recorded sensor stays the survey's nominal one.
    """
    cfg = physics.config
    rng = np.random.default_rng([cfg.seed, _STAGE_RANDOMIZE, index])
    base = cfg.sonar
    sonar = dataclasses.replace(
        base,
        tilt_rad=_draw(rng, randomize.tilt_rad, base.tilt_rad),
        beam_width_rad=_draw(rng, randomize.beam_width_rad, base.beam_width_rad),
        beam_rolloff=_draw(rng, randomize.beam_rolloff, base.beam_rolloff),
        sidelobe_db=_draw(rng, randomize.sidelobe_db, base.sidelobe_db),
        tvg_spreading_exponent=_draw(
            rng, randomize.tvg_spreading_exponent, base.tvg_spreading_exponent
        ),
        tvg_absorption_factor=_draw(
            rng, randomize.tvg_absorption_factor, base.tvg_absorption_factor
        ),
    )
    gain_db = _draw(rng, randomize.gain_db, 0.0)
    n_mat = len(physics.response.names)
    mu_factor = np.ones(n_mat)
    if randomize.mu_scale is not None:
        lo, hi = np.log(randomize.mu_scale[0]), np.log(randomize.mu_scale[1])
        mu_factor = np.exp(rng.uniform(lo, hi, n_mat))
    exp_offset = np.zeros(n_mat)
    if randomize.exponent_offset is not None:
        exp_offset = rng.uniform(*randomize.exponent_offset, n_mat)
    response = dataclasses.replace(
        physics.response,
        mu=physics.response.mu * mu_factor,
        exponent=np.maximum(physics.response.exponent + exp_offset, 1.0),
    )
    offset = _draw(rng, randomize.altitude_offset_m, 0.0)
    # terrain following at a drawn altitude (drawn last: the other draws stay as they were)
    target = None if randomize.altitude_m is None else _draw(rng, randomize.altitude_m, 0.0)
    if offset != 0.0 or target is not None:
        shift = np.full(len(line.altitude_m), offset)
        if target is not None:
            shift += target - _smooth_altitude(line, randomize.altitude_smoothing_m)
        up = np.zeros((len(shift), 3))
        up[:, 2] = shift
        line = dataclasses.replace(
            line,
            position=line.position + up,
            nav_position=line.nav_position + up,
            altitude_m=line.altitude_m + shift,
        )
        low = float(np.nanmin(line.altitude_m))
        if low < min_altitude_m:
            key = "altitude_offset_m" if target is None else "altitude_offset_m / altitude_m"
            raise ValueError(
                f"data.survey.randomize.{key}: expected values that keep every altitude >= "
                f"plan.min_altitude_m ({min_altitude_m} m), found {low:.2f} m on {line.name} "
                f"(offset {offset:+.2f} m, altitude {target})"
            )
        validate_swath(line.name, line.position, line.rotation, sonar, terrain)
    calibration = calibrate_receiver(
        sonar,
        response,
        reference_material,
        physics.calibration.reference_altitude_m,
        physics.absorption,
    )
    calibration = dataclasses.replace(calibration, gain=calibration.gain * 10 ** (gain_db / 20))
    # the lines keep the survey's nominal sensor record (a survey has one sensor, and the
    # CNN sees only intensity); the drawn values go to the metadata
    line_physics = _Physics(
        dataclasses.replace(cfg, sonar=sonar), response, calibration, physics.absorption,
        physics.sensor,
    )  # fmt: skip
    drawn = {
        "tilt_deg": round(math.degrees(sonar.tilt_rad), 3),
        "beam_width_deg": round(math.degrees(sonar.beam_width_rad), 3),
        "beam_rolloff": round(sonar.beam_rolloff, 4),
        "sidelobe_db": round(sonar.sidelobe_db, 3),
        "tvg_spreading_exponent": round(sonar.tvg_spreading_exponent, 4),
        "tvg_absorption_factor": round(sonar.tvg_absorption_factor, 4),
        "gain_db": round(gain_db, 3),
        "mu_factor": [round(float(v), 4) for v in mu_factor],
        "exponent_offset": [round(float(v), 4) for v in exp_offset],
        "altitude_offset_m": round(offset, 3),
    }
    if target is not None:
        drawn["altitude_m"] = round(target, 3)
    return line, line_physics, drawn


# Worker state for parallel line simulation (one terrain + ray caster per process).
_WORKER: dict[str, Any] = {}


def _worker_init(terrain: Terrain, physics: _Physics) -> None:
    import torch

    torch.set_num_threads(1)
    _WORKER["physics"] = physics
    _WORKER["caster"] = RayCaster(terrain.to_mesh())
    _WORKER["surface"] = TerrainSurface(terrain)


def _worker_line(job: tuple[PlannedLine, int, _Physics | None]) -> SidescanLine:
    line, index, own = job
    physics = own if own is not None else _WORKER["physics"]
    return simulate_line(line, index, physics, _WORKER["caster"], _WORKER["surface"])


def generate_survey(config: SyntheticSurveyConfig) -> tuple[Survey, Terrain]:
    """Generate the survey described by ``config`` (in memory).

    Returns:
        the survey (lines, MBES grid, splits, origin, metadata with the config hash) and
        the true terrain (heights, materials, texture, boulders).
    """
    t_start = time.perf_counter()
    seed = config.seed
    origin = dict(config.origin)
    source = None
    if config.terrain.grid is not None:
        terrain, source = grid_terrain(
            config.terrain, config.materials, np.random.default_rng([seed, _STAGE_TERRAIN])
        )
        origin = dict(source.origin)
    else:
        terrain = generate_terrain(
            config.terrain, config.materials, np.random.default_rng([seed, _STAGE_TERRAIN])
        )
    t_terrain = time.perf_counter()
    planned = plan_survey(
        config.plan, config.sonar, terrain, np.random.default_rng([seed, _STAGE_PLAN])
    )
    sonar = config.sonar
    absorption = absorption_db_per_m(
        sonar.frequency_hz, sonar.temperature_c, sonar.salinity_ppt, sonar.ph
    )
    speed = sound_speed_mps(sonar.temperature_c, sonar.salinity_ppt)
    response = MaterialResponse.from_params(config.materials)
    reference_altitude = float(np.median(np.concatenate([ln.altitude_m for ln in planned])))
    calibration = calibrate_receiver(
        sonar,
        response,
        config.materials.index(config.materials.reference_material),
        min(reference_altitude, 0.8 * sonar.max_range_m),
        absorption,
    )
    physics = _Physics(
        config,
        response,
        calibration,
        absorption,
        SensorParams(sonar.tilt_rad, sonar.beam_width_rad, sonar.frequency_hz, speed),
    )

    # domain randomisation: the listed splits' lines get their own physics (None: shared)
    own: list[_Physics | None] = [None] * len(planned)
    drawn: dict[str, dict[str, Any]] = {}
    if config.randomize is not None:
        ref = config.materials.index(config.materials.reference_material)
        for i, line in enumerate(planned):
            if line.split in config.randomize.splits:
                planned[i], own[i], drawn[line.name] = randomize_line(
                    line, i, physics, config.randomize, terrain, ref, config.plan.min_altitude_m
                )
    jobs = [(line, i, own[i]) for i, line in enumerate(planned)]
    workers = min(config.workers, len(jobs))
    if workers > 1:
        import multiprocessing as mp
        from concurrent.futures import ProcessPoolExecutor

        with ProcessPoolExecutor(
            workers, mp.get_context("spawn"), initializer=_worker_init, initargs=(terrain, physics)
        ) as pool:
            done = pool.map(_worker_line, jobs)
            lines = list(log_progress(done, "simulating", len(jobs), unit="lines"))
    else:
        caster, surface = RayCaster(terrain.to_mesh()), TerrainSurface(terrain)
        lines = []
        for line, i, line_physics in log_progress(jobs, "simulating", unit="lines"):
            lines.append(simulate_line(line, i, line_physics or physics, caster, surface))
            log.debug("simulated %s (%d pings)", line.name, len(line.time_s))
    t_lines = time.perf_counter()

    crs = origin.get("crs")
    mbes_rng = np.random.default_rng([seed, _STAGE_MBES])
    if source is not None:  # the MBES truth is the grid itself, not the rendered surface
        mbes_z = grid_mbes_heights(source, config.terrain.mbes_noise_m, mbes_rng)
        mbes = BathyGrid(mbes_z, 0.0, 0.0, source.cell_m, crs)
    else:
        mbes_z = mbes_heights(terrain, config.terrain.mbes_noise_m, mbes_rng)
        mbes = BathyGrid(mbes_z, 0.0, 0.0, terrain.cell_m, crs)
    splits = {
        "train": [ln.name for ln in planned if ln.split == "train"],
        "test": [ln.name for ln in planned if ln.split == "test"],
    }
    n_pings = sum(ln.n_pings for ln in lines)
    masks = np.concatenate([ln.extras["true_mask"].ravel() for ln in lines])
    true_nlat = np.concatenate(
        [ln.extras["true_n_lat"][ln.extras["true_mask"] == 0].ravel() for ln in lines]
    )
    abs_nlat = np.abs(true_nlat[np.isfinite(true_nlat)])
    metadata = {
        "generator": "sss2bathy.sim",
        "generator_version": GENERATOR_VERSION,
        "config_hash": config.hash(),
        "config": config.to_dict(),
        "materials": list(config.materials.names),
        "lines": {
            ln.name: {
                "split": ln.split,
                "set": ln.line_set,
                "heading_deg": round(math.degrees(ln.heading_rad), 3),
                "pings": int(len(ln.time_s)),
                **({"randomized": drawn[ln.name]} if ln.name in drawn else {}),
            }
            for ln in planned
        },
        "physics": {
            "absorption_db_per_m": absorption,
            "sound_speed_mps": speed,
            "receiver_gain": calibration.gain,
            "noise_power": calibration.noise_power,
            "reference_altitude_m": calibration.reference_altitude_m,
        },
        "terrain": {
            "boulders": int(len(terrain.boulders)),
            "depth_min_m": float(-terrain.heights[terrain.seabed].max()),
            "depth_max_m": float(-terrain.heights[terrain.seabed].min()),
            "material_fractions": {
                name: float(np.mean(terrain.materials == i))
                for i, name in enumerate(terrain.material_names)
            },
            "n_lat_grid": nlat_statistics(
                terrain.dzdx[terrain.seabed], terrain.dzdy[terrain.seabed]
            ),
            **({"grid": source.summary()} if source is not None else {}),
        },
        "n_lat_valid_bins": {
            "frac_below_0.2": float(np.mean(abs_nlat < 0.2)) if abs_nlat.size else float("nan"),
            "frac_above_0.5": float(np.mean(abs_nlat > 0.5)) if abs_nlat.size else float("nan"),
        },
        "altitude_m": altitude_summary(planned),
        "mask_counts": mask_reason_counts(masks),
        "timing_s": {
            "terrain": round(t_terrain - t_start, 3),
            "sidescan": round(t_lines - t_terrain, 3),
            "pings": int(n_pings),
            "pings_per_s": round(n_pings / max(t_lines - t_terrain, 1e-9), 1),
            "workers": int(workers),
        },
    }
    survey = Survey(
        name=config.name,
        lines=lines,
        grid=mbes,
        splits=splits,
        origin=origin,
        metadata=metadata,
    )
    return survey, terrain
