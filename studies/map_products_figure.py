"""One figure of what ``sss2bathy-map`` hands a surveyor, from a finished map run's
GeoTIFFs: the sidescan mosaic draped on the map, the map (heights over its hillshade) and the
per-cell height uncertainty, side by side in the map's projected CRS.

    python -m studies.map_products_figure outputs/runs/map/<run> docs/images/real_line_products.png
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

from sss2bathy.sim.render import hillshade
from sss2bathy.utils.atomic import save_figure

PANELS = ("mosaic.tif", "map.tif", "uncertainty.tif")


def read_band(path: Path) -> tuple[np.ndarray, tuple[float, float, float, float], float]:
    """The first band of a GeoTIFF as float64 with nodata as NaN, row 0 north; its extent
    (left, right, bottom, top) and cell size."""
    import rasterio

    with rasterio.open(path) as src:
        band = src.read(1, masked=True).astype(np.float64).filled(np.nan)
        b = src.bounds
        return band, (b.left, b.right, b.bottom, b.top), float(src.res[0])


def render(run_dir: Path, out: Path, title: str | None = None) -> Path:
    """Save the three panels of ``run_dir`` to ``out`` (PNG)."""
    missing = [name for name in PANELS if not (run_dir / name).is_file()]
    if missing:
        raise ValueError(f"{run_dir}: expected a finished map run with {missing}, found none")
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    mosaic, ext_m, _ = read_band(run_dir / "mosaic.tif")
    heights, ext_h, cell = read_band(run_dir / "map.tif")
    sigma, ext_s, _ = read_band(run_dir / "uncertainty.tif")
    fig, axes = plt.subplots(1, 3, figsize=(15, 5.2), constrained_layout=True)
    lo, hi = np.nanpercentile(mosaic, [2, 98])
    im = axes[0].imshow(mosaic, extent=ext_m, cmap="copper", vmin=lo, vmax=hi)
    fig.colorbar(im, ax=axes[0], shrink=0.8, label="normalised intensity")
    axes[0].set_title("sidescan mosaic, draped on the map")
    # hillshade needs row 0 south; the raster's row 0 is north
    shade = hillshade(np.nan_to_num(heights[::-1], nan=float(np.nanmean(heights))), cell)[::-1]
    zlo, zhi = np.nanpercentile(heights, [1, 99])
    im = axes[1].imshow(heights, extent=ext_h, cmap="viridis", vmin=zlo, vmax=zhi)
    axes[1].imshow(
        np.where(np.isfinite(heights), shade, np.nan), extent=ext_h, cmap="gray", alpha=0.45
    )
    fig.colorbar(im, ax=axes[1], shrink=0.8, label="seabed height (m, up)")
    axes[1].set_title("map (heights over their hillshade)")
    im = axes[2].imshow(sigma, extent=ext_s, cmap="magma")
    fig.colorbar(im, ax=axes[2], shrink=0.8, label="1 sigma (m)")
    axes[2].set_title("height uncertainty")
    for ax in axes:
        ax.set_xlim(min(ext_h[0], ext_m[0]), max(ext_h[1], ext_m[1]))
        ax.set_ylim(min(ext_h[2], ext_m[2]), max(ext_h[3], ext_m[3]))
        ax.set_aspect("equal")
        ax.set_xlabel("easting (m)")
        ax.ticklabel_format(useOffset=False, style="plain")
    axes[0].set_ylabel("northing (m)")
    if title:
        fig.suptitle(title)
    return save_figure(fig, out, dpi=90)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("run", type=Path, help="a finished sss2bathy-map run folder")
    p.add_argument("out", type=Path, help="the PNG to write")
    p.add_argument("--title", default=None)
    args = p.parse_args(argv)
    try:
        print(render(args.run, args.out, args.title))
    except ValueError as err:
        print(f"error: {err}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
