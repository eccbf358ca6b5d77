"""Render a line's waterfall next to its draped n_lat (like the paper's CNN figure).

Command line::

    python -m sss2bathy.draping.render <survey_dir> <line> <out.png> [--pings A:B]

drapes the line (cached) on the survey's grid and writes the figure.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from sss2bathy.draping.draped import DrapedLine
from sss2bathy.survey import MASK_VALID, SidescanLine
from sss2bathy.survey.masks import MASK_NAMES
from sss2bathy.utils.atomic import save_figure


def _swath(a: np.ndarray) -> np.ndarray:
    """``(P, 2, B)`` -> ``(P, 2B)``: port mirrored left of starboard, nadir in the middle."""
    return np.concatenate([a[:, 0, ::-1], a[:, 1]], axis=1)


def render_draped(
    line: SidescanLine,
    draped: DrapedLine,
    path: str | Path,
    pings: slice | None = None,
    n_lat_limit: float = 0.5,
) -> Path:
    """Write a PNG: waterfall | draped n_lat (masked bins black) | mask reasons.

    Pings run down the page; port is mirrored left of starboard. n_lat uses a diverging
    colormap over ``[-n_lat_limit, n_lat_limit]`` (red = tilted away from the sonar,
    blue = facing it).

    Args:
        line: the sidescan line.
        draped: its draping, shape ``(P, 2, B)`` like ``line.intensity``.
        path: output PNG path (written atomically).
        pings: optional ping slice to show.
        n_lat_limit: colour range of n_lat.

    Returns:
        ``path``.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.colors import ListedColormap

    if draped.shape != line.intensity.shape:
        raise ValueError(
            f"draped: expected shape {line.intensity.shape} of line '{line.name}', "
            f"found {draped.shape}"
        )
    if not n_lat_limit > 0:
        raise ValueError(f"n_lat_limit: expected a positive number, found {n_lat_limit}")
    sl = pings or slice(None)
    inten = _swath(line.intensity[sl]).astype(np.float64)
    valid = _swath(draped.mask[sl] == MASK_VALID)
    lo, hi = np.nanpercentile(inten, [1, 99]) if np.isfinite(inten).any() else (0.0, 1.0)
    n_lat = np.ma.masked_where(~valid, _swath(draped.n_lat[sl]))
    reasons = _swath(draped.mask[sl]).astype(np.float64)
    codes = np.zeros_like(reasons)
    for k, bit in enumerate(sorted(MASK_NAMES), start=1):
        codes[(reasons.astype(np.uint8) & bit) > 0] = k

    r_max = float(line.range_m[-1])
    extent = (-r_max, r_max, inten.shape[0], 0)
    fig, axes = plt.subplots(1, 3, figsize=(15, 5), constrained_layout=True)
    axes[0].imshow(inten, cmap="copper", vmin=lo, vmax=hi, aspect="auto", extent=extent)
    axes[0].set_title(f"{line.name}: waterfall (port | starboard)")
    cmap = plt.get_cmap("RdBu_r").with_extremes(bad="black")
    im = axes[1].imshow(
        n_lat, cmap=cmap, vmin=-n_lat_limit, vmax=n_lat_limit, aspect="auto", extent=extent
    )
    axes[1].set_title("draped n_lat (masked: black)")
    fig.colorbar(im, ax=axes[1], shrink=0.8, label="n_lat")
    names = ["valid"] + [MASK_NAMES[b] for b in sorted(MASK_NAMES)]
    colors = ["#dddddd", "#1f3b73", "#000000", "#8c2d04", "#7a7a00"]
    im2 = axes[2].imshow(
        codes,
        cmap=ListedColormap(colors),
        vmin=-0.5,
        vmax=len(names) - 0.5,
        aspect="auto",
        interpolation="nearest",
        extent=extent,
    )
    cbar = fig.colorbar(im2, ax=axes[2], shrink=0.8, ticks=range(len(names)))
    cbar.ax.set_yticklabels(names)
    axes[2].set_title("mask reason")
    for ax in axes:
        ax.set_xlabel("slant range (m), port < 0 < starboard")
    axes[0].set_ylabel("ping")
    return save_figure(fig, path, dpi=100)


def main(argv: list[str] | None = None) -> None:
    """``python -m sss2bathy.draping.render SURVEY_DIR LINE OUT.png [--pings A:B]``."""
    from sss2bathy.draping.cache import drape_survey
    from sss2bathy.survey import Survey

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("survey_dir")
    parser.add_argument("line")
    parser.add_argument("out")
    parser.add_argument("--pings", default=None, help="ping range A:B")
    args = parser.parse_args(argv)
    survey = Survey.load(args.survey_dir)
    draped = drape_survey(survey, args.survey_dir, lines=[args.line])[args.line]
    pings = None
    if args.pings:
        a, b = (int(v) if v else None for v in args.pings.split(":"))
        pings = slice(a, b)
    print(render_draped(survey.line(args.line), draped, args.out, pings=pings))


if __name__ == "__main__":
    main()
