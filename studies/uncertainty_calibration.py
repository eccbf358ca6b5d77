"""Calibration of ``sss2bathy-map``'s per-cell height uncertainty against MBES truth.

On generated AUV XTF surveys with a known seabed (:func:`studies.xtf_study.make_survey`:
``synthetic_d1`` flown as an AUV, one survey per seed), ``sss2bathy-map method=siren_lambert
verdict.folds=K`` (one process, one fit at a time, ``torch_threads=1``) leaves the final
map and its K fold maps; the raw sigma is their delete-a-fold jackknife
(:func:`sss2bathy.eval.uncertainty.jackknife_sigma`). Runs that already finished (e.g. the
verdict study's, ``python -m studies.xtf_study --verdict-folds 5``) are reused.

1. **Calibrate** on the ``--calibrate`` surveys, per scale preset (the SIREN's size
   changes how far apart the fold fits land): the factor ``c`` that puts 68.3 % of their
   pooled written cells inside ``+-c sigma_J``
   (:func:`sss2bathy.eval.uncertainty.calibrate_scale`) — conf/map.yaml's
   ``uncertainty.calibrated.<map_settings>.<scale>`` (``--map-settings``: the runs' map
   settings, whose fold maps differ in spread).
2. **Evaluate** ``c sigma_J`` on every survey (the ``--evaluate`` ones were not used for
   ``c``): the share of cells whose true height lies within +-1 sigma / +-2 sigma (ideal
   68.3 % / 95.4 %), Spearman's correlation of sigma with |error|, and each survey's own
   factor (what ``c`` would have had to be there).

The d1 preset's seabed is seed 1 (the demo's d1 survey) and the held-out test site's is
seed 11: calibrate on other seeds. The table goes to ``--out`` (Markdown + CSV).

    python -m studies.uncertainty_calibration --calibrate demo:2,3 tiny:2,3 --evaluate demo:1 tiny:1
"""

from __future__ import annotations

import argparse
import math
import shlex
import sys
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from sss2bathy.eval.uncertainty import (
    GAUSS_1SIGMA,
    calibrate_scale,
    calibration_stats,
    fold_members,
    jackknife_sigma,
)
from sss2bathy.survey import BathyGrid, Survey
from studies.tables import fmt_cell, markdown_table, to_csv, write_tables
from studies.xtf_study import (
    make_survey,
    map_command,
    map_on_grid,
    mask_on_grid,
    run_map,
    truth_grid,
)

METHOD = "siren_lambert"
#: where each scale's surveys and runs live by default: the verdict study's folders
STUDY_DIRS = {"tiny": "outputs/verdict_study", "demo": "outputs/verdict_study_demo"}
#: seabeds that settings must not be chosen on (the demo's d1 survey, the held-out site)
TEST_SEEDS = (1, 11)


@dataclass(frozen=True)
class SurveyErrors:
    """One survey's written cells: the map's signed error (map - truth, m) and the raw
    jackknife sigma (m), both on the truth grid."""

    scale: str
    seed: int
    error: np.ndarray
    sigma_j: np.ndarray
    folds: int
    wall_s: float


def parse_specs(specs: Sequence[str]) -> list[tuple[str, int]]:
    """``["demo:2,3", "tiny:1"]`` -> ``[("demo", 2), ("demo", 3), ("tiny", 1)]``."""
    out = []
    for spec in specs:
        scale, _, seeds = str(spec).partition(":")
        if not scale or not seeds:
            raise ValueError(f"survey spec: expected SCALE:SEED[,SEED...], found {spec!r}")
        try:
            out += [(scale, int(s)) for s in seeds.split(",") if s.strip()]
        except ValueError as err:
            raise ValueError(f"survey spec: expected integer seeds, found {spec!r}") from err
    return out


def errors_on_truth(
    final: Mapping[str, np.ndarray], folds: np.ndarray, truth: BathyGrid, shift: Sequence[float]
) -> tuple[np.ndarray, np.ndarray]:
    """The final map's signed error and the jackknife sigma of its ``folds (K, ny, nx)``,
    both sampled at ``truth``'s cell centres (the map frame shifted by ``shift``), on the
    cells the written map holds (its ``coverage``) where all three are finite; flattened."""
    geom = (float(final["x0"]), float(final["y0"]), float(final["cell_size"]))
    pred = map_on_grid(final["heights"], *geom, truth, shift).heights
    sigma = map_on_grid(jackknife_sigma(folds), *geom, truth, shift).heights
    written = mask_on_grid(final["coverage"], *geom, truth, shift)
    ok = written & np.isfinite(pred) & np.isfinite(sigma) & np.isfinite(truth.heights)
    return (pred - truth.heights)[ok], sigma[ok]


def run_map_settings(run_dir: Path) -> str:
    """The ``map_settings`` a finished ``sss2bathy-map`` run was made with (its
    ``.hydra/config.yaml``; ``scale`` where the key is absent: runs from before it)."""
    import yaml

    path = Path(run_dir) / ".hydra" / "config.yaml"
    if not path.is_file():
        raise SystemExit(f"{path}: expected the map run's config, found none")
    return str((yaml.safe_load(path.read_text()) or {}).get("map_settings") or "scale")


def survey_errors(
    scale: str, seed: int, study_dir: Path, folds: int, map_settings: str = "scale"
) -> SurveyErrors:
    """Generate (or reuse) the survey of ``scale`` / ``seed`` and its ``sss2bathy-map``
    run with ``verdict.folds=folds`` and ``map_settings`` under ``study_dir``; its errors
    and sigma. A finished run made with other map settings is refused, not reused."""
    study_dir = Path(study_dir).resolve()
    survey = make_survey(study_dir / "xtf" / f"s{seed}", seed, scale=scale)
    data_dir = study_dir / "data"
    run_dir = study_dir / "runs" / f"s{seed}" / f"{METHOD}_folds{folds}"
    if (run_dir / "metrics.json").is_file() and (run_dir / "verdict.json").is_file():
        found = run_map_settings(run_dir)
        if found != map_settings:
            raise SystemExit(
                f"{run_dir}: expected a run with map_settings={map_settings}, found "
                f"map_settings={found} (--study-dir names another study's folder)"
            )
    else:
        cmd = map_command(
            survey, METHOD, "demo", seed, run_dir, data_dir, scale, verdict_folds=folds,
            map_args=[f"map_settings={map_settings}"],
        )  # fmt: skip
        print(f"{scale} seed {seed}: {shlex.join(cmd)}", flush=True)
        run_map(cmd, run_dir)
    truth, (easting, northing) = truth_grid(survey)
    imported = Survey.load(data_dir / survey.name)
    shift = (
        easting - float(imported.origin.get("easting") or 0.0),
        northing - float(imported.origin.get("northing") or 0.0),
    )
    with np.load(run_dir / "map.npz", allow_pickle=False) as saved:
        final = {k: saved[k] for k in saved.files}
    like = BathyGrid(
        final["heights"], float(final["x0"]), float(final["y0"]), float(final["cell_size"])
    )
    members = fold_members(run_dir, METHOD, like)
    error, sigma = errors_on_truth(final, members.heights, truth, shift)
    wall = run_dir / "study_wall_s.txt"
    return SurveyErrors(
        scale,
        seed,
        error,
        sigma,
        members.k,
        float(wall.read_text()) if wall.is_file() else math.nan,
    )


def study_rows(
    calibrate: Sequence[SurveyErrors], evaluate: Sequence[SurveyErrors]
) -> tuple[dict[str, float], list[dict[str, Any]]]:
    """``c`` per scale from the pooled ``calibrate`` surveys of that scale and one row per
    survey (both sets), each scored with its scale's ``c``.

    Raises:
        ValueError: an evaluation survey of a scale no calibration survey has.
    """
    scales = sorted({s.scale for s in calibrate})
    c = {
        scale: calibrate_scale(
            np.concatenate([np.abs(s.error) for s in calibrate if s.scale == scale]),
            np.concatenate([s.sigma_j for s in calibrate if s.scale == scale]),
            GAUSS_1SIGMA,
        )
        for scale in scales
    }
    missing = sorted({s.scale for s in evaluate} - set(c))
    if missing:
        raise ValueError(
            f"--evaluate: expected scales that --calibrate has {scales}, found {missing}"
        )
    rows = []
    for role, group in (("calibration", calibrate), ("evaluation", evaluate)):
        for s in group:
            raw = calibration_stats(s.error, s.sigma_j)
            cal = calibration_stats(s.error, c[s.scale] * s.sigma_j)
            rows.append(
                {
                    "set": role,
                    "scale": s.scale,
                    "seed": s.seed,
                    "folds": s.folds,
                    "c": c[s.scale],
                    "cells": int(cal["n"]),
                    "mae_m": cal["mae"],
                    "median_sigma_m": cal["median_sigma"],
                    "within_1sigma": cal["within_1sigma"],
                    "within_2sigma": cal["within_2sigma"],
                    "raw_within_1sigma": raw["within_1sigma"],
                    "raw_within_2sigma": raw["within_2sigma"],
                    "spearman": cal["spearman"],
                    "own_scale": raw["scale_1sigma"],
                    "run_wall_s": s.wall_s,
                }
            )
    return c, rows


def calibration_table_name(map_settings: str) -> str:
    """The table's file stem: ``uncertainty_calibration`` for the scale's map settings,
    ``uncertainty_calibration_<map_settings>`` for others."""
    return "uncertainty_calibration" + ("" if map_settings == "scale" else f"_{map_settings}")


COLUMNS = (
    "map_settings",
    "set",
    "scale",
    "seed",
    "folds",
    "c",
    "cells",
    "mae_m",
    "median_sigma_m",
    "within_1sigma",
    "within_2sigma",
    "raw_within_1sigma",
    "raw_within_2sigma",
    "spearman",
    "own_scale",
    "run_wall_s",
)


def to_markdown(
    c: Mapping[str, float],
    rows: Sequence[Mapping[str, Any]],
    command: str,
    map_settings: str = "scale",
) -> str:
    """The study's page: what was measured, ``c``, the table and the command."""
    pct = lambda v: f"{100 * v:.0f} %"  # noqa: E731
    table = markdown_table(
        [
            "set",
            "scale",
            "seed",
            "c",
            "cells",
            "map MAE (m)",
            "median sigma (m)",
            "within +-1 sigma",
            "within +-2 sigma",
            "raw jackknife +-1 / +-2 sigma",
            "Spearman(sigma, abs error)",
            "own factor",
            "run wall (s)",
        ],
        [
            [
                r["set"],
                r["scale"],
                r["seed"],
                f"{r['c']:.2f}",
                r["cells"],
                fmt_cell(r["mae_m"]),
                fmt_cell(r["median_sigma_m"]),
                pct(r["within_1sigma"]),
                pct(r["within_2sigma"]),
                f"{pct(r['raw_within_1sigma'])} / {pct(r['raw_within_2sigma'])}",
                f"{r['spearman']:.2f}",
                f"{r['own_scale']:.2f}",
                f"{r['run_wall_s']:.0f}",
            ]
            for r in rows
        ],
        "lllrrrrrrrrrr",
    )
    return "\n".join(
        [
            f"# Uncertainty calibration (map_settings={map_settings})",
            "",
            "Generated AUV XTF surveys (synthetic_d1's recipe flown as an AUV, one seabed per "
            f"seed) mapped by `sss2bathy-map method={METHOD} verdict.folds=K "
            f"map_settings={map_settings}`; sigma = c x "
            "the delete-a-fold jackknife of the K fold maps "
            "(`sss2bathy.eval.uncertainty`), scored against the simulated MBES on the "
            "cells map.tif holds. c is fitted per scale preset on that scale's calibration "
            "surveys (68.3 % of their pooled cells inside +-c sigma_J) and applied unchanged "
            "to the evaluation surveys. Ideal shares: 68.3 % within +-1 sigma, 95.4 % within +-2 sigma. "
            "own factor = the c that survey alone would need; run wall = the whole map run "
            "(K fold fits of the method and of heights-only, then the final fit): the "
            "uncertainty itself adds no fit.",
            "",
            f"**c** (conf/map.yaml `uncertainty.calibrated.{map_settings}`): "
            + ", ".join(f"{k} {v:.2f}" for k, v in c.items()),
            "",
            *table,
            "",
            "How to read it:",
            "",
            "- *raw jackknife*: the fold fits differ only in which altimeter blocks they hold "
            "out; they share every sidescan ping, the seed and the forward model, so what "
            "they all get wrong (a seabed that is not Lambertian, a tilt that is off) never "
            "shows in their spread. The raw coverage says how much too narrow that is; c "
            "widens it by one factor per scale preset (the SIREN's size changes how far apart "
            "the folds land, hence a factor per preset), and a preset without one gets the "
            "raw jackknife with a WARNING.",
            "- *within +-1 / +-2 sigma* on the evaluation surveys: how well c carries to "
            "another seabed. A +-2 sigma share below 95 % at +-1 sigma near 68 % means "
            "heavier tails than a Gaussian's.",
            "- *Spearman*: whether sigma ranks the cells by their error (0: sigma says where "
            "the map is bad no better than chance).",
            "- *cost*: sigma needs the K-fold verdict (on by default, `verdict.folds: 5`); "
            "beyond it, reading the K fold maps and writing one GeoTIFF (about a second).",
            "",
            "Command (runs that already finished are reused; new seeds are simulated and "
            "mapped one fit at a time, torch_threads=1):",
            "",
            f"    {command}",
            "",
        ]
    )


def main(argv: Sequence[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--calibrate", nargs="+", required=True, help="SCALE:SEED[,SEED] ...")
    p.add_argument("--evaluate", nargs="*", default=[], help="SCALE:SEED[,SEED] ...")
    p.add_argument("--folds", type=int, default=5)
    p.add_argument(
        "--study-dir",
        nargs="*",
        default=[],
        help="SCALE=DIR: where that scale's surveys and runs are (default: "
        + ", ".join(f"{k}={v}" for k, v in STUDY_DIRS.items())
        + ")",
    )
    p.add_argument(
        "--map-settings",
        default="scale",
        help="the map runs' map_settings (its factors: uncertainty.calibrated.<map-settings>)",
    )
    p.add_argument("--out", default="docs/studies", help="folder of the table (md + csv)")
    args = p.parse_args(argv)
    dirs = dict(STUDY_DIRS)
    for spec in args.study_dir:
        scale, _, folder = spec.partition("=")
        dirs[scale] = folder
    cal, ev = parse_specs(args.calibrate), parse_specs(args.evaluate)
    bad = [seed for _, seed in cal if seed in TEST_SEEDS]
    if bad:
        raise SystemExit(
            f"--calibrate: expected seeds other than the test seabeds {TEST_SEEDS}, found {bad}"
        )

    def load(specs: list[tuple[str, int]]) -> list[SurveyErrors]:
        out = []
        for scale, seed in specs:
            if scale not in dirs:
                raise SystemExit(f"--study-dir: expected a folder for scale {scale!r}, found none")
            out.append(survey_errors(scale, seed, Path(dirs[scale]), args.folds, args.map_settings))
        return out

    c, rows = study_rows(load(cal), load(ev))
    command = "python -m studies.uncertainty_calibration " + shlex.join(
        list(argv) if argv is not None else sys.argv[1:]
    )
    rows = [{**r, "map_settings": args.map_settings} for r in rows]
    paths = write_tables(
        args.out,
        calibration_table_name(args.map_settings),
        to_markdown(c, rows, command, args.map_settings),
        to_csv(rows, COLUMNS),
    )
    print(f"c = {', '.join(f'{k} {v:.3f}' for k, v in c.items())}; table: {paths['md']}")
    for r in rows:
        print(
            f"{r['set']:11s} {r['scale']} s{r['seed']}: +-1 sigma {100 * r['within_1sigma']:.0f} %,"
            f" +-2 sigma {100 * r['within_2sigma']:.0f} %, Spearman {r['spearman']:.2f}"
        )
    return 0


if __name__ == "__main__":
    sys.exit(main())
