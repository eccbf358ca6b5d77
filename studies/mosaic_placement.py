"""Where a mosaic puts each sidescan bin, against where it hits the true seabed.

For every line of a simulated survey (with its MBES truth), the horizontal distance between
each bin's flat-seabed placement (the usual slant-range correction) and its draping on the
truth grid, and the same for a draping on the truth smoothed by a Gaussian (a stand-in for a
reconstructed map): median and 95th percentile per line
(:func:`sss2bathy.eval.mosaic.placement_errors`).

    python -m studies.mosaic_placement data/synthetic_wrecks [--smooth-m 2.0]
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np
from scipy.ndimage import gaussian_filter

from sss2bathy.eval.mosaic import placement_errors
from sss2bathy.survey import BathyGrid, Survey


def smoothed(grid: BathyGrid, sigma_m: float) -> BathyGrid:
    """``grid`` low-passed by a Gaussian of ``sigma_m`` (NaN cells stay NaN)."""
    h = np.asarray(grid.heights, np.float64)
    ok = np.isfinite(h)
    s = sigma_m / grid.cell_size
    num = gaussian_filter(np.where(ok, h, 0.0), s)
    den = gaussian_filter(ok.astype(np.float64), s)
    with np.errstate(invalid="ignore", divide="ignore"):
        out = np.where(ok, num / den, np.nan)
    return BathyGrid(out.astype(np.float32), grid.x0, grid.y0, grid.cell_size, grid.crs)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("survey", type=Path, help="a simulated survey folder (with its grid)")
    parser.add_argument("--smooth-m", type=float, default=2.0, help="Gaussian sigma (m)")
    args = parser.parse_args(argv)
    survey = Survey.load(args.survey)
    if survey.grid is None:
        print(f"error: survey {args.survey}: expected an MBES grid, found none", file=sys.stderr)
        return 2
    surface = smoothed(survey.grid, args.smooth_m)
    print("| line | flat median (m) | flat p95 (m) | draped on smoothed median (m) | p95 (m) |")
    print("|---|---:|---:|---:|---:|")
    for line in survey.lines:
        e = placement_errors(line, survey.grid, surface)
        f, g = e["flat"], e["grid"]
        print(
            f"| {line.name} | {f['median']:.3f} | {f['p95']:.2f} | {g['median']:.3f} "
            f"| {g['p95']:.2f} |"
        )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
