"""Figure of a survey simulated over a real grid: the grid's hillshade with the lines, and a
sidescan waterfall of one line.

    python -m studies.real_figure [SURVEY_FOLDER] [OUT_PNG] [LINE]

defaults: ``data/synthetic_real_1m_demo``, ``outputs/figures/synthetic_real_1m.png`` and the
survey's longest test line. The survey folder is what ``sss2bathy-prepare
data/survey=synthetic_real_1m`` writes.
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

from sss2bathy.sim.render import hillshade, waterfall_image
from sss2bathy.survey import Survey
from sss2bathy.utils.atomic import save_figure


def render_real_survey(survey: Survey, path: str | Path, line: str | None = None) -> Path:
    """Save hillshade (map coordinates of the survey's CRS, lines drawn, the chosen line
    bold) and the chosen line's waterfall side by side as a PNG."""
    if survey.grid is None:
        raise ValueError(f"survey '{survey.name}': expected an MBES grid to draw, found none")
    names = [ln.name for ln in survey.lines]
    if line is None:
        tests = survey.splits.get("test") or names
        line = max(tests, key=lambda n: survey.lines[names.index(n)].n_pings)
    if line not in names:
        raise ValueError(f"line: expected one of {names}, found {line!r}")
    chosen = survey.lines[names.index(line)]
    import matplotlib

    matplotlib.use("Agg", force=False)
    import matplotlib.pyplot as plt

    origin = {"easting": 0.0, "northing": 0.0, "crs": None, **(survey.origin or {})}
    e0, n0 = float(origin["easting"]), float(origin["northing"])
    grid = survey.grid
    h = grid.heights
    finite = np.isfinite(h)
    shade = hillshade(np.where(finite, h, np.nanmedian(h)), grid.cell_size)
    lo, hi = np.percentile(h[finite], [1, 99])
    from matplotlib import colormaps

    rgb = colormaps["viridis"](np.clip((h - lo) / max(hi - lo, 1e-6), 0, 1))[..., :3]
    rgb = rgb * (0.3 + 0.7 * shade[..., None])
    rgb[~finite] = 1.0
    xmin, ymin, xmax, ymax = grid.bounds
    c = grid.cell_size / 2
    extent = (e0 + xmin - c, e0 + xmax + c, n0 + ymin - c, n0 + ymax + c)
    fig, (ax, ax_w) = plt.subplots(
        1, 2, figsize=(13.0, 5.6), gridspec_kw={"width_ratios": [1.5, 1.0]}
    )
    ax.imshow(rgb, origin="lower", extent=extent)
    test = set(survey.splits.get("test", []))
    for ln in survey.lines:
        colour = "tab:red" if ln.name in test else "tab:blue"
        xy = ln.position[:, :2] + [e0, n0]
        ax.plot(xy[:, 0], xy[:, 1], color=colour, lw=2.4 if ln.name == line else 0.9)
    ax.annotate(
        line.replace("line_", ""), chosen.position[0, :2] + [e0, n0], color="tab:red", fontsize=8
    )
    sm = plt.cm.ScalarMappable(cmap="viridis", norm=plt.Normalize(vmin=lo, vmax=hi))
    fig.colorbar(sm, ax=ax, fraction=0.035, pad=0.02, label="MBES height z (m)")
    ax.set_xlabel(f"easting (m, {origin['crs']})")
    ax.set_ylabel("northing (m)")
    ax.ticklabel_format(useOffset=False, style="plain")
    ax.set_title(
        f"{survey.name}: MBES hillshade, lines (red: test)\nwhite: no data, removed spikes"
    )
    img = waterfall_image(chosen)
    vmax = float(np.percentile(img, 99.5)) or 1.0
    r = chosen.range_m
    half = float(r[-1] + (r[-1] - r[-2]) / 2)
    ax_w.imshow(
        img, cmap="gray", vmin=0, vmax=vmax, aspect="auto",
        extent=(-half, half, chosen.n_pings, 0),
    )  # fmt: skip
    ax_w.set_title(f"{line}: simulated sidescan (port left)")
    ax_w.set_xlabel("slant range (m)")
    ax_w.set_ylabel("ping")
    fig.tight_layout()
    return save_figure(fig, path, dpi=110, bbox_inches="tight")


def main(argv: list[str] | None = None) -> int:
    args = sys.argv[1:] if argv is None else argv
    if len(args) > 3 or any(a in ("-h", "--help") for a in args):
        print(__doc__)
        return 0 if args and args[0] in ("-h", "--help") else 2
    folder = Path(args[0] if args else "data/synthetic_real_1m_demo")
    out = Path(args[1] if len(args) > 1 else "outputs/figures/synthetic_real_1m.png")
    if not (folder / "survey.yaml").is_file():
        print(
            f"survey folder: expected {folder}/survey.yaml (run sss2bathy-prepare "
            "data/survey=synthetic_real_1m first), found none",
            file=sys.stderr,
        )
        return 2
    path = render_real_survey(Survey.load(folder), out, args[2] if len(args) > 2 else None)
    print(path)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
