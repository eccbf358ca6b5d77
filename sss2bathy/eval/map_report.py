"""The report of one ``sss2bathy-map`` run: ``report.html``, one self-contained web page a
surveyor can send on (figures embedded, the run folder's files linked relative to it).

:func:`write_map_report` reads only what the run folder holds: ``map.png``, a hillshade of
``map.npz`` (:func:`hillshade_png`, written beside it), ``uncertainty.png``, ``mosaic.png``
and ``gradient_hsv.png``; the coverage and uncertainty numbers of ``metrics.json``; the
K-fold verdict table with its spread (``verdict.json``); the import's WARNING lines
(``map.log``, each message once, with its count) and the import counts of the survey
(``survey.yaml``'s ``import_stats``, found through ``run_info.json``); the settings
(``.hydra/overrides.yaml``, ``config.yaml``); the provenance (``map.tif``'s tags) and
whether each raster is a cloud-optimised GeoTIFF (:func:`sss2bathy.io.export.cog_layout`).
Something the folder lacks is left out with one line saying so.
"""

from __future__ import annotations

import html
import json
import logging
import math
import re
from collections import Counter
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from sss2bathy.eval.report import markdown_to_html
from sss2bathy.eval.verdict import LABELS
from sss2bathy.utils.atomic import atomic_write_text, save_figure

log = logging.getLogger(__name__)

#: a map run folder holds these (what :func:`is_map_run` looks for)
MAP_RUN_FILES = ("map.tif", "map.npz", "metrics.json")
RASTERS = ("map.tif", "uncertainty.tif", "mosaic.tif")
#: preformatted text that wraps (long command lines, summary lines)
PRE = '<pre style="white-space: pre-wrap; font-size: 12px">'
LOG_LINE = re.compile(r"^\[[^\]]*\]\[(?P<logger>[^\]]*)\]\[WARNING\] - (?P<msg>.*)$")


def is_map_run(folder: str | Path) -> bool:
    """Whether ``folder`` is a finished ``sss2bathy-map`` (or SIREN) run: it holds
    :data:`MAP_RUN_FILES`."""
    return all((Path(folder) / name).is_file() for name in MAP_RUN_FILES)


def log_warnings(log_text: str) -> list[tuple[str, str, int]]:
    """The WARNING messages of a run's log (Hydra's ``[time][logger][WARNING] - msg``
    lines), each once in first-seen order: ``(logger, message, count)``."""
    counts: Counter[tuple[str, str]] = Counter()
    order: list[tuple[str, str]] = []
    for line in log_text.splitlines():
        match = LOG_LINE.match(line.strip())
        if not match:
            continue
        key = (match.group("logger"), match.group("msg").strip())
        if key not in counts:
            order.append(key)
        counts[key] += 1
    return [(lg, msg, counts[(lg, msg)]) for lg, msg in order]


def hillshade_png(
    run_dir: str | Path, azimuth: float = 315.0, altitude: float = 45.0, exaggeration: float = 5.0
) -> Path:
    """``run_dir/hillshade.png``: the map (``map.npz``, the cells ``map.tif`` holds) as a
    grey hillshade lit from ``azimuth`` (degrees clockwise from north) at ``altitude``
    degrees, heights exaggerated ``exaggeration`` times (metre-scale relief over a swath
    shows), axes in local metres; the heights' colours are ``map.png``'s."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.colors import LightSource

    run_dir = Path(run_dir)
    with np.load(run_dir / "map.npz", allow_pickle=False) as saved:
        h = np.asarray(saved["heights"], np.float64)
        covered = np.asarray(saved["coverage"], bool) if "coverage" in saved else None
        x0, y0, cell = (float(saved[k]) for k in ("x0", "y0", "cell_size"))
    shown = np.where(covered, h, np.nan) if covered is not None else h
    finite = np.isfinite(shown)
    if not finite.any():
        raise ValueError(f"{run_dir / 'map.npz'}: expected cells with heights, found none")
    # no-data cells take their nearest height, so the map's edges cast no false slopes
    from scipy.ndimage import distance_transform_edt

    nearest = distance_transform_edt(~finite, return_distances=False, return_indices=True)
    filled = shown[tuple(nearest)]
    ls = LightSource(azdeg=azimuth, altdeg=altitude)
    # row 0 of the grid is south: flip for the light's north, back for imshow(origin=lower)
    shade = ls.hillshade(filled[::-1], vert_exag=exaggeration, dx=cell, dy=cell)[::-1]
    ny, nx = h.shape
    extent = (x0 - cell / 2, x0 + (nx - 0.5) * cell, y0 - cell / 2, y0 + (ny - 0.5) * cell)
    fig, ax = plt.subplots(figsize=(7.5, 5.5))
    ax.imshow(
        np.ma.masked_where(~finite, shade), origin="lower", extent=extent, cmap="gray",
        vmin=0.0, vmax=1.0, interpolation="nearest",
    )  # fmt: skip
    ax.set_title(
        f"hillshade (sun from {azimuth:.0f} deg, {altitude:.0f} deg up; heights x "
        f"{exaggeration:g})",
        fontsize=10,
    )
    ax.set_xlabel("x (m, local east)", fontsize=8)
    ax.set_ylabel("y (m, local north)", fontsize=8)
    ax.set_aspect("equal")
    fig.tight_layout()
    return save_figure(fig, run_dir / "hillshade.png", dpi=110)


def _read_json(path: Path) -> dict[str, Any] | None:
    try:
        return json.loads(path.read_text()) if path.is_file() else None
    except json.JSONDecodeError as err:
        log.warning("report: %s is not valid JSON (%s); left out", path, err)
        return None


def _num(value: Any, fmt: str = ".3f") -> str:
    try:
        v = float(value)
    except (TypeError, ValueError):
        return "–"
    return format(v, fmt) if math.isfinite(v) else "–"


def verdict_section(verdict: Mapping[str, Any] | None) -> list[str]:
    """The K-fold verdict: per method mean +- std, min - max and folds of the held-out
    altimeter MAE; the paired comparisons; the verdict sentence."""
    lines = ["## Held-out altimeter verdict", ""]
    if not verdict:
        return lines + ["No K-fold verdict in this run (verdict.folds < 2).", ""]
    block = _num(verdict.get("block_m"), ".1f")
    lines += [
        f"{verdict.get('folds')} folds of held-out altimeter blocks ({block} m of track each); "
        f"{_num((verdict.get('seconds') or math.nan) / 60, '.1f')} min of fold fits.",
        "",
        "| method | held-out MAE mean (m) | std over folds (m) | min - max (m) | folds |",
        "|---|---:|---:|---:|---:|",
    ]
    for name, m in (verdict.get("methods") or {}).items():
        lines.append(
            f"| {LABELS.get(name, name)} | {_num(m.get('mean'))} | {_num(m.get('std'))} | "
            f"{_num(m.get('min'))} - {_num(m.get('max'))} | {m.get('n')} |"
        )
    lines.append("")
    for c in verdict.get("comparisons") or []:
        a, b = LABELS.get(c["a"], c["a"]), LABELS.get(c["b"], c["b"])
        winner = c.get("winner")
        call = "inconclusive" if winner is None else f"{LABELS.get(winner, winner)} is better"
        lines.append(
            f"- {a} - {b}: {_num(c.get('mean_diff'), '+.3f')} +- "
            f"{_num(c.get('half_width_95'))} m (95 %, {c.get('n')} folds): {call}"
        )
    share = verdict.get("imaged_share")
    if share is not None:
        lines.append(f"- held-out points inside the sonar's footprint: {100 * share:.0f} %")
    lines += ["", f"**{html.escape(str(verdict.get('sentence', '')))}**", ""]
    return lines


def coverage_section(metrics: Mapping[str, Any]) -> list[str]:
    """Coverage and uncertainty numbers of ``metrics.json``."""
    rows = [
        ("imaged area (m²)", metrics.get("final/imaged_area_m2"), ".0f"),
        ("area map.tif holds (m²)", metrics.get("final/written_area_m2"), ".0f"),
        ("extrapolated share of it", metrics.get("final/extrapolated_share"), ".1%"),
        (
            "extrapolated share of a swath-radius disc around the track",
            metrics.get("final/track_region_extrapolated_share"),
            ".1%",
        ),
        ("uncertainty: 1 sigma median (m)", metrics.get("uncertainty/sigma_median_m"), ".3f"),
        ("uncertainty: 1 sigma 95th percentile (m)", metrics.get("uncertainty/sigma_p95_m"), ".3f"),
        ("uncertainty: 1 sigma max (m)", metrics.get("uncertainty/sigma_max_m"), ".3f"),
        ("uncertainty: calibration factor", metrics.get("uncertainty/scale"), ".2f"),
        ("uncertainty: fold fits", metrics.get("uncertainty/folds"), ".0f"),
    ]
    shown = [(k, v, f) for k, v, f in rows if v is not None]
    lines = ["## Coverage and uncertainty", ""]
    if not shown:
        return lines + ["metrics.json holds no coverage numbers.", ""]
    lines += ["| quantity | value |", "|---|---:|"]
    lines += [f"| {k} | {_num(v, f)} |" for k, v, f in shown]
    return lines + [""]


def import_section(run_dir: Path) -> list[str]:
    """The import's WARNING lines from ``map.log`` and the survey's import counts."""
    lines = ["## Import checks and repairs", ""]
    log_path = run_dir / "map.log"
    warnings = log_warnings(log_path.read_text(errors="replace")) if log_path.is_file() else []
    if warnings:
        lines += ["WARNING lines of the run's log (each once; × = how often):", ""]
        lines += [
            f"- `{html.escape(lg)}` {html.escape(msg)}" + (f" (× {n})" if n > 1 else "")
            for lg, msg, n in warnings
        ]
    elif log_path.is_file():
        lines.append(
            "No WARNING in this run's log (a survey already in paths.data_dir is reused, "
            "and its stored import warnings are repeated in the log; one imported by an "
            "older version stored none). Its import counts follow."
        )
    else:
        lines.append("No map.log in the run folder.")
    lines.append("")
    stats = _import_stats(run_dir)
    table = import_counts_table(stats)
    if table:
        lines += ["Import counts (survey.yaml's import_stats, one column per file):", ""]
        lines += table + [""]
    return lines


def import_counts_table(stats: Mapping[str, Mapping[str, Any]]) -> list[str]:
    """A Markdown table of the numeric import counts: one row per count, one column per
    file (``stats``: file -> its ``import_stats``); empty without counts."""

    def number(v: Any) -> bool:
        return isinstance(v, int | float) and not isinstance(v, bool)

    names = list(stats)
    keys: list[str] = []
    for entry in stats.values():
        keys += [k for k, v in entry.items() if number(v) and k not in keys]
    if not keys:
        return []
    header = "| count | " + " | ".join(f"`{html.escape(n)}`" for n in names) + " |"
    rule = "|---|" + "---:|" * len(names)
    rows = [
        f"| {k} | "
        + " | ".join(_num(stats[n].get(k), "g") if number(stats[n].get(k)) else "–" for n in names)
        + " |"
        for k in keys
    ]
    return [header, rule, *rows]


def _import_stats(run_dir: Path) -> dict[str, dict[str, Any]]:
    import yaml

    info = _read_json(run_dir / "run_info.json") or {}
    name, data_dir = info.get("survey_name"), info.get("data_dir")
    if not name or not data_dir:
        return {}
    path = Path(str(data_dir)) / str(name) / "survey.yaml"
    if not path.is_file():
        return {}
    meta = (yaml.safe_load(path.read_text()) or {}).get("metadata") or {}
    stats = meta.get("import_stats") or {}
    return {str(k): v for k, v in stats.items() if isinstance(v, Mapping)}


def provenance_section(run_dir: Path) -> list[str]:
    """``map.tif``'s provenance tags and each raster's COG layout."""
    import rasterio

    from sss2bathy.io.export import cog_layout

    lines = ["## Provenance and files", ""]
    with rasterio.open(run_dir / "map.tif") as src:
        tags = src.tags()
    keys = (
        "SSS2BATHY_METHOD",
        "SSS2BATHY_VERSION",
        "SSS2BATHY_COMMAND",
        "SSS2BATHY_CNN_CHECKPOINT",
        "SSS2BATHY_CNN_CHECKPOINT_SHA256",
        "SSS2BATHY_VERTICAL_REFERENCE",
    )
    lines += ["| map.tif tag | value |", "|---|---|"]
    lines += [f"| {k} | <code>{_cell(tags[k])}</code> |" for k in keys if k in tags]
    lines += ["", "| file | cloud-optimised GeoTIFF |", "|---|---|"]
    for name in RASTERS:
        path = run_dir / name
        if path.is_file():
            problems = cog_layout(path).problems()
            state = "yes" if not problems else "no: " + "; ".join(problems)
            lines.append(f"| [{name}]({name}) | {state} |")
    for name in ("item.json", "metrics.json", "verdict.json", "config.yaml"):
        if (run_dir / name).is_file():
            lines.append(f"| [{name}]({name}) | – |")
    return lines + [""]


def _cell(text: str) -> str:
    """``text`` safe inside a Markdown table cell (HTML-escaped, no ``|``)."""
    return html.escape(str(text)).replace("|", "&#124;")


def settings_section(run_dir: Path) -> list[str]:
    """The command's overrides and the composed fit config, folded."""
    lines = ["## Settings", ""]
    overrides = run_dir / ".hydra" / "overrides.yaml"
    if overrides.is_file():
        lines += [
            "The command's settings (`.hydra/overrides.yaml`):",
            "",
            f"{PRE}{html.escape(overrides.read_text())}</pre>",
            "",
        ]
    config = run_dir / "config.yaml"
    if config.is_file():
        lines += [
            "<details><summary>The fit's whole config (config.yaml)</summary>",
            f"{PRE}{html.escape(config.read_text())}</pre>",
            "</details>",
            "",
        ]
    return lines


FIGURES = (
    ("map.png", "bathymetry (map.tif)"),
    ("hillshade.png", "hillshade of the map"),
    ("uncertainty.png", "height uncertainty, 1 sigma (uncertainty.tif)"),
    ("mosaic.png", "sidescan mosaic (mosaic.tif)"),
    ("gradient_hsv.png", "slope direction and steepness (HSV)"),
)


def write_map_report(run_dir: str | Path, summary: Sequence[str] | None = None) -> Path:
    """Write ``run_dir/report.html`` (module docstring); ``summary``: the lines
    ``sss2bathy-map`` printed, shown as they are.

    Raises:
        ValueError: ``run_dir`` is not a finished map run (names what it lacks).
    """
    run_dir = Path(run_dir)
    missing = [name for name in MAP_RUN_FILES if not (run_dir / name).is_file()]
    if missing:
        raise ValueError(
            f"{run_dir}: expected a finished sss2bathy-map run folder ({', '.join(MAP_RUN_FILES)}), "
            f"found no {', '.join(missing)}"
        )
    metrics = _read_json(run_dir / "metrics.json") or {}
    info = _read_json(run_dir / "run_info.json") or {}
    verdict = _read_json(run_dir / "verdict.json")
    try:
        hillshade_png(run_dir)
    except ValueError as err:
        log.warning("report: no hillshade: %s", err)
    survey = info.get("survey_name") or "survey"
    method = LABELS.get(str(info.get("task_name")), info.get("task_name") or "map")
    text = [
        f"# sss2bathy map: {html.escape(str(survey))}",
        "",
        f"{html.escape(str(method))}, run folder `{html.escape(run_dir.name)}`. Heights in m, "
        "up, negative below the sea surface (map.tif's vertical reference below); "
        "no MBES was used.",
        "",
    ]
    if summary:
        text += [f"{PRE}{html.escape(chr(10).join(summary))}</pre>", ""]
    text += ["## Maps", ""]
    for name, caption in FIGURES:
        if (run_dir / name).is_file():
            text += [f"![{caption}]({name})", ""]
        else:
            text += [f"*{caption}: not in this run ({name}).*", ""]
    text += coverage_section(metrics)
    text += verdict_section(verdict)
    overlap = _read_json(run_dir / "overlap.json")
    if overlap and overlap.get("sentence"):
        text += ["## Off-track overlap score", "", html.escape(str(overlap["sentence"])), ""]
    text += import_section(run_dir)
    text += settings_section(run_dir)
    text += provenance_section(run_dir)
    path = run_dir / "report.html"
    atomic_write_text(path, markdown_to_html("\n".join(text), run_dir, f"sss2bathy map: {survey}"))
    return path


__all__ = ["hillshade_png", "import_counts_table", "is_map_run", "log_warnings", "write_map_report"]
