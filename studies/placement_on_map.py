"""Where a mosaic draped on the *reconstructed* map puts each sidescan bin, against where
it hits the true seabed, beside the flat-seabed placement.

For a generated AUV XTF survey of :mod:`studies.xtf_study` (its MBES truth in
``truth.npz``) and a finished ``sss2bathy-map`` run on it, per imported line: the
horizontal distance (m) between each bin's placement and its draping on the truth grid,
for the flat seabed at the altimeter depth (the usual slant-range correction) and for the
run's map (``map.npz``: what ``sss2bathy-map``'s ``mosaic.placement=map`` uses), through
:func:`sss2bathy.eval.mosaic.placement_errors`: median and 95th percentile per line.

    python -m studies.placement_on_map outputs/verdict_study_demo --scale demo --seed 1

Or, for a survey that holds its MBES truth (the demo's simulated sites) and finished SIREN
runs on one of its splits (each run's ``map.npz`` is in the survey's frame), per line of the
split and for every run:

    python -m studies.placement_on_map --survey data/synthetic_d1_demo --split test \
        --map SIREN-CNN-N2d=outputs/runs/siren_cnn_n2d/<run> \
        --map SIREN-Lambert=outputs/runs/siren_lambert/<run> [--out docs/studies/placement_d1]
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import Any

import numpy as np

from sss2bathy.eval.mosaic import placement_errors
from sss2bathy.survey import BathyGrid, Survey
from studies.tables import markdown_table, to_csv, write_tables
from studies.xtf_study import StudySurvey, make_survey, truth_grid


def truth_in_frame(survey: StudySurvey, imported: Survey) -> BathyGrid:
    """The survey's MBES truth moved into the imported survey's local frame."""
    truth, (easting, northing) = truth_grid(survey)
    dx = easting - float(imported.origin.get("easting") or 0.0)
    dy = northing - float(imported.origin.get("northing") or 0.0)
    return BathyGrid(truth.heights, truth.x0 + dx, truth.y0 + dy, truth.cell_size, truth.crs)


def run_map_grid(run_dir: Path) -> BathyGrid:
    """A run's final map (``map.npz``, every cell) in the imported survey's frame."""
    with np.load(Path(run_dir) / "map.npz", allow_pickle=False) as saved:
        return BathyGrid(
            np.asarray(saved["heights"], np.float32),
            float(saved["x0"]),
            float(saved["y0"]),
            float(saved["cell_size"]),
        )


def survey_placement(
    survey: Survey, split: str, maps: dict[str, BathyGrid]
) -> tuple[list[str], list[list[Any]]]:
    """Per line of ``split`` of a survey with its MBES truth (``survey.grid``): the flat-seabed
    placement error and, for every map, the error draped on it (median / p95, m)."""
    if survey.grid is None:
        raise ValueError(f"{survey.name}: expected a survey with its MBES grid, found none")
    header = ["line", "flat median (m)", "flat p95 (m)"]
    for label in maps:
        header += [f"{label} median (m)", f"{label} p95 (m)"]
    rows = []
    for line in survey.split_lines(split):
        errors = placement_errors(line, survey.grid, maps)
        row: list[Any] = [line.name]
        for label in ["flat", *maps]:
            row += [f"{errors[label]['median']:.3f}", f"{errors[label]['p95']:.2f}"]
        rows.append(row)
    return header, rows


def _survey_main(args: argparse.Namespace) -> int:
    survey = Survey.load(args.survey)
    maps: dict[str, BathyGrid] = {}
    for item in args.map:
        label, sep, run = item.partition("=")
        if not sep or not (Path(run) / "map.npz").is_file():
            print(
                f"error: --map: expected LABEL=<finished run folder with map.npz>, found {item!r}",
                file=sys.stderr,
            )
            return 2
        maps[label] = run_map_grid(Path(run))
    header, rows = survey_placement(survey, args.split, maps)
    lines = markdown_table(header, rows, "l" + "r" * (len(header) - 1))
    print(f"{survey.name}:{args.split}, placement error against the draping on the MBES truth:")
    print("\n".join(lines))
    if args.out is not None:
        title = f"{survey.name}:{args.split}, bin placement error (m) against the MBES truth"
        csv_text = to_csv([dict(zip(header, r, strict=True)) for r in rows], header)
        write_tables(
            args.out.parent, args.out.name, f"# {title}\n\n" + "\n".join(lines) + "\n", csv_text
        )
    return 0


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("study", type=Path, nargs="?", help="an xtf_study --verdict-folds folder")
    p.add_argument("--scale", default="demo")
    p.add_argument("--seed", type=int, default=1)
    p.add_argument("--run", default="siren_lambert_folds5", help="the run under runs/s<seed>/")
    p.add_argument("--survey", type=Path, help="a survey folder holding its MBES truth")
    p.add_argument("--split", default="test")
    p.add_argument("--map", action="append", default=[], help="LABEL=<SIREN run folder>")
    p.add_argument("--out", type=Path, help="write <out>.md and <out>.csv (with --survey)")
    args = p.parse_args(argv)
    if args.survey is not None:
        return _survey_main(args)
    if args.study is None:
        p.error("expected a study folder, or --survey with --map")
    study = args.study.resolve()
    survey = make_survey(study / "xtf" / f"s{args.seed}", args.seed, scale=args.scale)
    imported = Survey.load(study / "data" / survey.name)
    run_dir = study / "runs" / f"s{args.seed}" / args.run
    if not (run_dir / "map.npz").is_file():
        print(f"error: {run_dir}: expected a finished map run (map.npz)", file=sys.stderr)
        return 2
    truth = truth_in_frame(survey, imported)
    recon = run_map_grid(run_dir)
    rows = []
    for line in imported.lines:
        e = placement_errors(line, truth, recon)
        f, g = e["flat"], e["grid"]
        rows.append(
            [line.name, f"{f['median']:.3f}", f"{f['p95']:.2f}", f"{g['median']:.3f}",
             f"{g['p95']:.2f}", f"{int(g['n'])}"]
        )  # fmt: skip
    header = [
        "line",
        "flat median (m)",
        "flat p95 (m)",
        "draped on the map median (m)",
        "p95 (m)",
        "bins",
    ]
    print(f"{survey.name}, map of {run_dir}:")
    print("\n".join(markdown_table(header, rows, "lrrrrr")))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
