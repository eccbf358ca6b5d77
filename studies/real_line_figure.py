"""A map run of a real line beside its sidescan mosaic: does the map show what the sidescan sees?

    .venv/bin/python -m studies.real_line_figure RUN_DIR SURVEY_DIR OUT.png [--title TEXT]
        [--before RUN_DIR --before-label TEXT]

``RUN_DIR``: an ``sss2bathy-map`` run folder (its ``map.npz``); ``SURVEY_DIR``: the imported
survey (``data/xtf_<name>``). Three panels on the map's grid: the flat-seabed sidescan
mosaic (:func:`sss2bathy.eval.mosaic.build_mosaic`, shadows kept), the map's heights over
its hillshade, and the hillshade alone (with ``--before``, a fourth: another run's
hillshade, e.g. the same line with the scale's own settings); the maps' relief in the titles.
``--wreck X0 X1 Y0 Y1`` (m, local): a feature's box; its top (90th percentile of the map's
heights inside) above its surroundings (the median 2-6 m outside the box) is printed and
put in the titles (the Iver2 line's wreck: 6 22 50 72).
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np


def hillshade(z: np.ndarray, cell: float, azimuth_deg: float = 315.0, alt_deg: float = 45.0):
    gy, gx = np.gradient(z, cell)
    az, alt = np.radians(azimuth_deg), np.radians(alt_deg)
    slope = np.arctan(np.hypot(gx, gy))
    aspect = np.arctan2(-gx, gy)
    shade = np.sin(alt) * np.cos(slope) + np.cos(alt) * np.sin(slope) * np.cos(az - aspect)
    return np.clip(shade, 0, 1)


def box_relief(
    z: np.ndarray,
    x0: float,
    y0: float,
    cell: float,
    box: tuple[float, float, float, float],
    ring_m: tuple[float, float] = (2.0, 6.0),
    top_quantile: float = 0.9,
) -> float:
    """How high what lies in ``box`` (x0, x1, y0, y1; m) stands above its surroundings on a
    height grid ``z`` (cell ``[0, 0]`` centred at ``(x0, y0)``; NaN unmapped): the
    ``top_quantile`` of the heights inside minus the median of those ``ring_m`` (inner,
    outer) metres outside the box; NaN where either is unmapped."""
    ny, nx = z.shape
    x = x0 + cell * np.arange(nx)
    y = y0 + cell * np.arange(ny)
    dx = np.maximum(np.maximum(box[0] - x, x - box[1]), 0.0)[None, :]
    dy = np.maximum(np.maximum(box[2] - y, y - box[3]), 0.0)[:, None]
    dist = np.hypot(dx, dy)  # from the box (0 inside)
    inside = z[(dist == 0) & np.isfinite(z)]
    ring = z[(dist >= ring_m[0]) & (dist <= ring_m[1]) & np.isfinite(z)]
    if inside.size == 0 or ring.size == 0:
        return float("nan")
    return float(np.quantile(inside, top_quantile) - np.median(ring))


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("run_dir")
    p.add_argument("survey_dir")
    p.add_argument("out")
    p.add_argument("--title", default="")
    p.add_argument("--before", default=None, help="another run folder: its hillshade too")
    p.add_argument("--before-label", default="before")
    p.add_argument("--label", default="map")
    p.add_argument("--zoom", nargs=4, type=float, metavar=("X0", "X1", "Y0", "Y1"))
    p.add_argument("--wreck", nargs=4, type=float, metavar=("X0", "X1", "Y0", "Y1"))
    args = p.parse_args(argv)

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from sss2bathy.eval.mosaic import build_mosaic
    from sss2bathy.survey import Survey

    def load(run_dir: str) -> tuple[np.ndarray, dict]:
        d = np.load(Path(run_dir) / "map.npz")
        # the cells map.tif holds (imaged or altimeter cells); older runs: the fitted region
        shown = d["coverage"] if "coverage" in d.files else d["region"]
        return np.where(shown, d["heights"], np.nan).astype(np.float64), d

    def shaded(z: np.ndarray) -> np.ndarray:
        filled = np.where(np.isfinite(z), z, np.nanmedian(z))
        return np.where(np.isfinite(z), hillshade(filled, cell), np.nan)

    z, d = load(args.run_dir)
    cell = float(d["cell_size"])
    ny, nx = z.shape
    x0, y0 = float(d["x0"]), float(d["y0"])
    extent = (x0 - cell / 2, x0 + (nx - 0.5) * cell, y0 - cell / 2, y0 + (ny - 0.5) * cell)
    survey = Survey.load(Path(args.survey_dir))
    mosaic = build_mosaic(survey, {"resolution": 0.1, "blank": ["water_column", "no_hit"]})
    mg = mosaic.grid
    m_ext = (
        mg.x0 - mg.cell_size / 2,
        mg.x0 + (mg.shape[1] - 0.5) * mg.cell_size,
        mg.y0 - mg.cell_size / 2,
        mg.y0 + (mg.shape[0] - 0.5) * mg.cell_size,
    )
    vals = mg.heights
    lo, hi = np.nanpercentile(vals, [1, 99])
    shade = shaded(z)
    zlo, zhi = np.nanpercentile(z, [0.5, 99.5])

    n = 3 if args.before is None else 4
    fig, axs = plt.subplots(1, n, figsize=(4.5 * n, 4.8), sharex=True, sharey=True)
    axs[0].imshow(vals, origin="lower", extent=m_ext, cmap="copper", vmin=lo, vmax=hi)
    axs[0].set_title("sidescan mosaic (flat seabed)")
    axs[1].imshow(shade, origin="lower", extent=extent, cmap="gray", vmin=0, vmax=1)
    im = axs[1].imshow(z, origin="lower", extent=extent, cmap="viridis", vmin=zlo, vmax=zhi,
                       alpha=0.6)  # fmt: skip
    fig.colorbar(im, ax=axs[1], shrink=0.8, label="height z (m)")
    axs[1].set_title(f"{args.label} (relief {zhi - zlo:.1f} m, 0.5-99.5 %)")
    axs[2].imshow(shade, origin="lower", extent=extent, cmap="gray", vmin=0, vmax=1)
    top = ""
    if args.wreck:
        rise = box_relief(z, x0, y0, cell, tuple(args.wreck))
        print(f"{args.label}: the box's top {rise:.2f} m above its surroundings")
        top = f", wreck top +{rise:.1f} m"
    axs[2].set_title(f"{args.label}: hillshade{top}")
    if args.before is not None:
        zb, db = load(args.before)
        if zb.shape != z.shape or float(db["cell_size"]) != cell:
            raise SystemExit(f"--before: expected a map on the same grid, found {zb.shape}")
        blo, bhi = np.nanpercentile(zb, [0.5, 99.5])
        axs[3].imshow(shaded(zb), origin="lower", extent=extent, cmap="gray", vmin=0, vmax=1)
        top = ""
        if args.wreck:
            rise = box_relief(zb, float(db["x0"]), float(db["y0"]), cell, tuple(args.wreck))
            print(f"{args.before_label}: the box's top {rise:.2f} m above its surroundings")
            top = f", wreck top +{rise:.1f} m"
        axs[3].set_title(f"{args.before_label}: hillshade (relief {bhi - blo:.1f} m{top})")
    for ax in axs:
        for line in survey.lines:
            ax.plot(line.position[:, 0], line.position[:, 1], "r-", lw=0.6)
        ax.set_xlabel("x East (m, local)")
        ax.title.set_fontsize(9)
        if args.zoom:
            ax.set_xlim(*args.zoom[:2])
            ax.set_ylim(*args.zoom[2:])
    axs[0].set_ylabel("y North (m, local)")
    if args.title:
        fig.suptitle(args.title)
    fig.tight_layout()
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out, dpi=66)
    print(f"wrote {out} ({out.stat().st_size // 1024} KB)")


if __name__ == "__main__":
    main()
