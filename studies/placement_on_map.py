"""Where a mosaic draped on the *reconstructed* map puts each sidescan bin, against where
it hits the true seabed, beside the flat-seabed placement.

For a generated AUV XTF survey of :mod:`studies.xtf_study` (its MBES truth in
``truth.npz``) and a finished ``sss2bathy-map`` run on it, per imported line: the
horizontal distance (m) between each bin's placement and its draping on the truth grid,
for the flat seabed at the altimeter depth (the usual slant-range correction) and for the
run's map (``map.npz``: what ``sss2bathy-map``'s ``mosaic.placement=map`` uses), through
:func:`sss2bathy.eval.mosaic.placement_errors`: median and 95th percentile per line.

    python -m studies.placement_on_map outputs/verdict_study_demo --scale demo --seed 1
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

from sss2bathy.eval.mosaic import placement_errors
from sss2bathy.survey import BathyGrid, Survey
from studies.tables import markdown_table
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


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("study", type=Path, help="an xtf_study --verdict-folds folder")
    p.add_argument("--scale", default="demo")
    p.add_argument("--seed", type=int, default=1)
    p.add_argument("--run", default="siren_lambert_folds5", help="the run under runs/s<seed>/")
    args = p.parse_args(argv)
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
