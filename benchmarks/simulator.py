"""Section ``sim``: the sidescan simulator on a preset's terrain and planned line.

:func:`~sss2bathy.sim.sonar.simulate_pings` and the receiver on the survey preset as
``sss2bathy-prepare`` composes it at a scale: pings/s (both heads).
"""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np

from benchmarks.config import survey_preset
from benchmarks.timing import figure, rates, time_runs

TITLE = "Sidescan simulator"


def bench_sim(
    *,
    root: str | Path | None = None,
    survey: str = "synthetic_d1",
    scale: str = "demo",
    n_pings: int = 64,
    warmup: int = 1,
    repeats: int = 3,
    seed: int = 0,
) -> dict:
    """The sidescan simulator (ray-traced pings of both heads + receiver): pings/s.

    The preset's terrain is generated and its survey planned (untimed); the first
    ``n_pings`` pings of the first planned line are then simulated repeatedly.
    """
    from sss2bathy.sim.config import SyntheticSurveyConfig
    from sss2bathy.sim.plan import plan_survey
    from sss2bathy.sim.sonar import (
        MaterialResponse,
        RayCaster,
        absorption_db_per_m,
        calibrate_receiver,
        receive,
        simulate_pings,
    )
    from sss2bathy.sim.terrain import TerrainSurface, generate_terrain

    cfg = SyntheticSurveyConfig.from_mapping(survey_preset(root, survey, scale))
    t0 = time.perf_counter()
    terrain = generate_terrain(cfg.terrain, cfg.materials, np.random.default_rng([seed, 0]))
    t_terrain = time.perf_counter() - t0
    line = plan_survey(cfg.plan, cfg.sonar, terrain, np.random.default_rng([seed, 1]))[0]
    n = min(int(n_pings), len(line.time_s))
    sonar = cfg.sonar
    absorption = absorption_db_per_m(
        sonar.frequency_hz, sonar.temperature_c, sonar.salinity_ppt, sonar.ph
    )
    response = MaterialResponse.from_params(cfg.materials)
    t0 = time.perf_counter()
    mesh = terrain.to_mesh()
    caster, surface = RayCaster(mesh), TerrainSurface(terrain)
    t_mesh = time.perf_counter() - t0
    calibration = calibrate_receiver(
        sonar,
        response,
        cfg.materials.index(cfg.materials.reference_material),
        min(float(np.median(line.altitude_m)), 0.8 * sonar.max_range_m),
        absorption,
    )

    def run() -> None:
        rng = np.random.default_rng([seed, 3])
        echoes = simulate_pings(
            caster,
            surface,
            line.position[:n],
            line.rotation[:n],
            sonar,
            response,
            rng,
            absorption_db_m=absorption,
            altitudes=line.altitude_m[:n],
        )
        receive(echoes.power_raw, sonar, calibration, rng, absorption)

    times = time_runs(run, warmup, repeats)
    rays_per_head = sonar.n_raw_bins * sonar.rays_per_raw_bin
    figures = [
        figure("pings/s (both heads)", "pings/s", rates(n, times)),
        figure("time per 1000 pings", "s", [1000 * t / n for t in times]),
    ]
    return {
        "title": TITLE,
        "params": {
            "preset": f"{survey} {scale}",
            "n_pings": n,
            "n_bins": sonar.n_bins,
            "raw_bins": sonar.n_raw_bins,
            "faces": int(len(mesh.faces)),
        },
        "figures": figures,
        "info": {"terrain_s": round(t_terrain, 3), "mesh_and_bvh_s": round(t_mesh, 3)},
        "notes": (
            f"simulate_pings + receive on the {survey} {scale} preset ({sonar.n_bins} bins, "
            f"{sonar.n_raw_bins} raw bins, about {rays_per_head:.0f}+ rays per head and ping), "
            f"first {n} pings of the first planned line; terrain and mesh untimed."
        ),
    }
