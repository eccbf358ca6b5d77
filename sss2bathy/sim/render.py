"""Pictures of a survey: sidescan waterfalls and the terrain with the survey lines."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from sss2bathy.survey import SidescanLine, Survey
from sss2bathy.utils.atomic import save_figure


def _pyplot():
    import matplotlib

    matplotlib.use("Agg", force=False)
    import matplotlib.pyplot as plt

    return plt


def waterfall_image(line: SidescanLine, values: np.ndarray | None = None) -> np.ndarray:
    """``(P, 2B)`` image: port mirrored (far port at column 0) left of starboard.

    Args:
        line: the line.
        values: ``(P, 2, B)`` per-bin values to lay out (default: the intensity).
    """
    v = line.intensity if values is None else np.asarray(values)
    if v.shape[:3] != (line.n_pings, 2, line.n_bins):
        raise ValueError(
            f"values: expected shape ({line.n_pings}, 2, {line.n_bins}), found {v.shape}"
        )
    return np.concatenate([v[:, 0, ::-1], v[:, 1]], axis=1)


def render_waterfall(
    line: SidescanLine,
    path: str | Path,
    *,
    truth: bool = True,
    clip_percentile: float = 99.5,
    pings: tuple[int, int] | None = None,
    dpi: int = 110,
) -> Path:
    """Save a line's waterfall as a greyscale PNG (port left, starboard right).

    x axis: signed slant range (m; port negative), y axis: ping index. With ``truth`` and
    the simulator's extras present, panels with the true ``n_lat`` and mask are added.

    Args:
        line: the line to draw.
        path: output PNG (written atomically).
        truth: add ground-truth panels when ``line.extras`` has them.
        clip_percentile: intensities above this percentile are drawn white.
        pings: ``(start, stop)`` ping interval to draw (default: all).
    """
    if not 0 < clip_percentile <= 100:
        raise ValueError(f"clip_percentile: expected in (0, 100], found {clip_percentile}")
    start, stop = (0, line.n_pings) if pings is None else (int(pings[0]), int(pings[1]))
    if not 0 <= start < stop <= line.n_pings:
        raise ValueError(f"pings: expected 0 <= start < stop <= {line.n_pings}, found {pings}")
    plt = _pyplot()
    P = stop - start
    r = line.range_m
    half = float(r[-1] + (r[-1] - r[-2]) / 2) if len(r) > 1 else float(r[-1])
    extent = (-half, half, stop, start)
    panels = [("intensity", waterfall_image(line)[start:stop])]
    if truth and "true_n_lat" in line.extras and "true_mask" in line.extras:
        for key, title in (("true_n_lat", "true n_lat"), ("true_mask", "true mask")):
            panels.append((title, waterfall_image(line, line.extras[key])[start:stop]))
    fig_w = 4.8 * len(panels)
    fig_h = float(np.clip(4.8 * 2 * P / (2 * line.n_bins), 3.5, 12.0))
    fig, axes = plt.subplots(1, len(panels), figsize=(fig_w, fig_h), squeeze=False)
    for ax, (title, data) in zip(axes[0], panels, strict=True):
        if title == "intensity":
            vmax = float(np.percentile(data, clip_percentile)) or 1.0
            im = ax.imshow(data, cmap="gray", vmin=0, vmax=vmax, extent=extent, aspect="auto")
        elif title == "true n_lat":
            im = ax.imshow(
                np.ma.masked_invalid(data), cmap="RdBu_r", vmin=-0.6, vmax=0.6,
                extent=extent, aspect="auto", interpolation="nearest",
            )  # fmt: skip
        else:
            im = ax.imshow(
                data, cmap="tab10", vmin=0, vmax=10, extent=extent, aspect="auto",
                interpolation="nearest",
            )  # fmt: skip
        fig.colorbar(im, ax=ax, fraction=0.04, pad=0.02)
        ax.set_title(f"{line.name}: {title}")
        ax.set_xlabel("slant range (m)   port  <-  |  ->  starboard")
        ax.set_ylabel("ping")
    fig.tight_layout()
    return save_figure(fig, path, dpi=dpi, bbox_inches="tight")


def hillshade(
    heights: np.ndarray, cell: float, azimuth_deg: float = 315.0, altitude_deg: float = 45.0
) -> np.ndarray:
    """``(ny, nx)`` hillshade in [0, 1] of a height grid with row 0 south."""
    dzdy, dzdx = np.gradient(np.asarray(heights, dtype=np.float64), cell)
    az, alt = math.radians(azimuth_deg), math.radians(altitude_deg)
    light = np.array([math.sin(az) * math.cos(alt), math.cos(az) * math.cos(alt), math.sin(alt)])
    n = np.stack([-dzdx, -dzdy, np.ones_like(dzdx)], axis=-1)
    n /= np.linalg.norm(n, axis=-1, keepdims=True)
    return np.clip(n @ light, 0.0, 1.0)


def render_terrain(survey: Survey, path: str | Path, *, dpi: int = 110) -> Path:
    """Save the survey's MBES grid (depth colours x hillshade) with its lines to PNG.

    Training lines are drawn blue, test lines red (other splits grey); each line is
    labelled at its start and an arrow shows its direction.
    """
    if survey.grid is None:
        raise ValueError(f"survey '{survey.name}': expected a grid to draw, found none")
    plt = _pyplot()
    from matplotlib import colormaps

    grid = survey.grid
    h = grid.heights
    finite = np.isfinite(h)
    lo, hi = np.percentile(h[finite], [1, 99]) if finite.any() else (0.0, 1.0)
    depth_rgb = colormaps["viridis"](np.clip((h - lo) / max(hi - lo, 1e-6), 0, 1))[..., :3]
    shade = hillshade(np.where(finite, h, np.nanmean(h)), grid.cell_size)
    rgb = depth_rgb * (0.35 + 0.65 * shade[..., None])
    rgb[~finite] = 1.0
    xmin, ymin, xmax, ymax = grid.bounds
    c = grid.cell_size / 2
    ny, nx = grid.shape
    fig, ax = plt.subplots(figsize=(8.0, 8.0 * ny / max(nx, 1) + 0.8))
    ax.imshow(rgb, origin="lower", extent=(xmin - c, xmax + c, ymin - c, ymax + c))
    split_of = {}
    for split in ("train", "test"):
        for name in survey.splits.get(split, []):
            split_of[name] = split
    colours = {"train": "tab:blue", "test": "tab:red"}
    seen = set()
    for ln in survey.lines:
        split = split_of.get(ln.name, "other")
        colour = colours.get(split, "0.5")
        xy = ln.position[:, :2]
        label = split if split not in seen else None
        seen.add(split)
        ax.plot(xy[:, 0], xy[:, 1], color=colour, lw=1.2, label=label)
        if len(xy) > 1:
            mid = len(xy) // 2
            ax.annotate(
                "", xy=xy[min(mid + 1, len(xy) - 1)], xytext=xy[mid],
                arrowprops=dict(arrowstyle="->", color=colour, lw=1.2),
            )  # fmt: skip
        ax.text(xy[0, 0], xy[0, 1], ln.name.replace("line_", ""), color=colour, fontsize=7)
    sm = plt.cm.ScalarMappable(cmap="viridis", norm=plt.Normalize(vmin=lo, vmax=hi))
    fig.colorbar(sm, ax=ax, fraction=0.04, pad=0.02, label="height z (m)")
    ax.set_xlabel("x East (m)")
    ax.set_ylabel("y North (m)")
    ax.set_title(f"{survey.name}: MBES grid and survey lines")
    ax.legend(loc="upper right", fontsize=8)
    fig.tight_layout()
    return save_figure(fig, path, dpi=dpi, bbox_inches="tight")
