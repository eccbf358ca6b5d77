"""The report: the paper's tables, PDF curves of signed errors, maps and zoomed panels.

:func:`build_report` gathers the **latest finished run** of each experiment (a run folder
under ``outputs/runs/<task>/`` or ``outputs/multiruns/<task>/.../`` holding ``metrics.json``
and ``run_info.json``) and writes ``outputs/report/``:

* ``index.md`` — every table and figure, with the run folders it came from (links to each
  run folder and its ``.hydra/config.yaml``) and the pipeline's stage times;
* ``index.html`` — the same as one self-contained web page (figures embedded as ``data:``
  URIs, tables as HTML tables; the run and config links are relative, so they work while
  the report stays inside its ``outputs/`` folder);
* ``table_cnn.{md,csv}`` — Table 2 (CNN, test lines of ``synthetic_d1`` and all of ``synthetic_d2``);
* ``table_siren_d1.{md,csv}``, ``table_siren_d2.{md,csv}`` — Tables 3 and 4;
  ``table_siren_d3.{md,csv}`` — the same on ``synthetic_d3`` (another sonar; no paper rows);
* ``pdf_d1.png``, ``pdf_d2.png`` — probability densities of the signed height errors;
* ``maps_d1.png``, ``maps_d2.png`` — bathymetry and HSV gradient, MBES beside every variant;
* ``zoom_d1_<k>.png`` — the roughest areas, gradients of MBES / GT-N2d / CNN-N2d / Lambert
  and the sidescan mosaic there.
* ``results.json``, ``results.md`` — the tables as data and as the results page
  (:mod:`sss2bathy.eval.results`; ``sss2bathy-report --publish`` puts them in ``docs/`` and
  the README).

Which experiments are the rows of which table, under which name and in which order, is the
``pipeline`` key of their files in ``conf/experiment/`` (:mod:`sss2bathy.utils.experiments`).

All SIREN variants of one survey are scored on the **same cells**: the intersection of the
areas their runs scored (each run scores cells near the sonar tracks it used), so a variant
that saw more lines is not judged on a larger, easier or harder area. Every table puts the
paper's numbers beside ours, labelled as measured on the paper's own (real) data.
"""

from __future__ import annotations

import json
import logging
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from sss2bathy.eval.cnn_table import (
    cnn_table_csv,
    cnn_table_markdown,
    constant_rows_from_metrics,
    table_rows_from_metrics,
)
from sss2bathy.eval.results import (
    CNN_KEY,
    RESULTS_JSON,
    RESULTS_MD,
    SIREN_TABLES,
    results_header,
    results_markdown,
    results_table,
    siren_table,
    wall_time_line,
)
from sss2bathy.metrics.bathy import bathy_metrics, map_gradient, signed_error
from sss2bathy.survey import BathyGrid
from sss2bathy.utils.atomic import atomic_write_text, save_figure
from sss2bathy.utils.experiments import Experiment, pipeline_experiments

log = logging.getLogger("sss2bathy.report")

ZOOM_LABELS = ("SIREN-GT-N2d", "SIREN-CNN-N2d", "SIREN-Lambert")


@dataclass
class RunRecord:
    """A finished run: its folder, ``run_info.json`` and ``metrics.json``."""

    path: Path
    info: dict[str, Any]
    metrics: dict[str, float]


@dataclass
class MapRun:
    """A finished SIREN run's map on the MBES grid of its survey."""

    label: str
    run: RunRecord
    heights: np.ndarray
    region: np.ndarray


def table_variants(table: str, experiments: list[Experiment]) -> list[tuple[str, str]]:
    """``(experiment, label)`` of the rows of one report table, in stage order."""
    return [(e.name, e.label) for e in experiments if e.table == table]


def find_latest_runs(outputs_dir: str | Path) -> dict[str, RunRecord]:
    """``task_name -> latest finished run`` below ``outputs_dir`` (runs and multiruns).

    A run is finished when its ``metrics.json`` exists; latest = newest ``metrics.json``.
    """
    outputs_dir = Path(outputs_dir)
    latest: dict[str, tuple[float, RunRecord]] = {}
    for metrics_path in outputs_dir.glob("*runs/**/metrics.json"):
        run_dir = metrics_path.parent
        info_path = run_dir / "run_info.json"
        if not info_path.is_file():
            continue
        try:
            info = json.loads(info_path.read_text())
            metrics = json.loads(metrics_path.read_text())
        except (OSError, json.JSONDecodeError) as exc:
            log.warning("skipping unreadable run %s: %s", run_dir, exc)
            continue
        task = info.get("task_name")
        stamp = metrics_path.stat().st_mtime
        if task and (task not in latest or stamp > latest[task][0]):
            latest[task] = (stamp, RunRecord(run_dir, info, metrics))
    return {k: v[1] for k, v in latest.items()}


def mbes_grid(run: RunRecord) -> BathyGrid | None:
    """The MBES grid of the run's survey (local frame), or None when the run names no
    survey folder with a ``survey.yaml``."""
    name, data_dir = run.info.get("survey_name"), run.info.get("data_dir")
    if not name or not data_dir:
        return None
    folder = Path(data_dir) / name
    if not (folder / "survey.yaml").is_file():
        return None
    from sss2bathy.survey import Survey  # grid.tif is projected: Survey brings it back local

    return Survey.load_grid(folder)


def _origin_note(run: RunRecord) -> str:
    """The figures' axes are local: say so, with the survey origin."""
    from sss2bathy.survey import Survey

    folder = Path(run.info.get("data_dir", "")) / run.info.get("survey_name", "")
    try:
        origin = Survey.read_manifest(folder).get("origin") or {}
    except Exception:  # no readable manifest: the axes are still local
        origin = {}
    crs = origin.get("crs") or "no CRS"
    return (
        f"axes: local coordinates (m), origin E {float(origin.get('easting', 0.0)):.1f} "
        f"N {float(origin.get('northing', 0.0)):.1f} ({crs})"
    )


def load_map_run(label: str, run: RunRecord, like: BathyGrid) -> MapRun | None:
    """The run's ``map.npz`` if it lies on ``like``'s geometry, else ``None`` (logged)."""
    path = run.path / "map.npz"
    if not path.is_file():
        log.warning("%s: %s has no map.npz; left out of the maps", label, run.path)
        return None
    with np.load(path, allow_pickle=False) as d:
        heights = d["heights"].astype(np.float64)
        region = d["region"].astype(bool) if "region" in d.files else np.isfinite(heights)
        geometry = (float(d["x0"]), float(d["y0"]), float(d["cell_size"]))
    if heights.shape != like.shape or not np.allclose(geometry, (like.x0, like.y0, like.cell_size)):
        log.warning("%s: map geometry differs from the MBES grid; left out", label)
        return None
    return MapRun(label, run, heights, region)


def score_maps(maps: list[MapRun], truth: BathyGrid) -> tuple[dict[str, dict], np.ndarray]:
    """Metrics of every map on the common region (intersection of their regions)."""
    common = np.isfinite(truth.heights)
    for m in maps:
        if not m.label.endswith("Direct-Fit"):
            common &= m.region
    rows = {m.label: bathy_metrics(m.heights, truth.heights, truth.cell_size, common) for m in maps}
    return rows, common


def _save(fig: Any, path: Path) -> Path:
    return save_figure(fig, path, dpi=110)


def plot_pdfs(
    maps: list[MapRun],
    truth: BathyGrid,
    region: np.ndarray,
    path: Path,
    title: str = "PDF of signed height errors",
) -> Path:
    """Probability density of the signed errors of every variant (shared bins)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    errors = {m.label: signed_error(m.heights, truth.heights)[region] for m in maps}
    errors = {k: v[np.isfinite(v)] for k, v in errors.items() if np.isfinite(v).any()}
    lim = max((float(np.percentile(np.abs(v), 99.5)) for v in errors.values()), default=1.0)
    bins = np.linspace(-lim, lim, 121)
    fig, ax = plt.subplots(figsize=(7, 4.2))
    for label, err in errors.items():
        density, edges = np.histogram(err, bins=bins, density=True)
        ax.plot(
            0.5 * (edges[1:] + edges[:-1]), density, label=f"{label} (mean {err.mean():+.3f} m)"
        )
    ax.axvline(0.0, color="k", lw=0.6)
    ax.set_xlabel("signed error  map − MBES (m)")
    ax.set_ylabel("probability density (1/m)")
    ax.legend(fontsize=8)
    ax.set_title(title, fontsize=10)
    fig.tight_layout()
    return _save(fig, path)


def _panels(
    truth: BathyGrid,
    maps: list[MapRun],
    region: np.ndarray,
    path: Path,
    window: tuple[slice, slice] | None = None,
    mosaic: np.ndarray | None = None,
    title: str = "",
    axes_note: str = "axes: local coordinates (m)",
) -> Path:
    """Row 1 bathymetry, row 2 HSV gradient; columns MBES then each map (optional mosaic),
    and a last column with the height colour bar (m) and the gradient colour-wheel key.

    All panels share the height colour limits (the MBES range) and the gradient brightness
    scale (the MBES's 99th-percentile slope); north is up, the axes are local metres and
    ``axes_note`` (:func:`_origin_note`) says where the origin is."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from sss2bathy.eval.maps import HEIGHT_LABEL, gradient_hsv, hsv_wheel_key, north_arrow

    rows_sl, cols_sl = window or (slice(None), slice(None))
    sub = region[rows_sl, cols_sl]
    h = truth.cell_size / 2
    xs, ys = truth.x[cols_sl], truth.y[rows_sl]
    extent = (xs[0] - h, xs[-1] + h, ys[0] - h, ys[-1] + h)
    named = [("MBES (ground truth)", truth.heights)] + [(m.label, m.heights) for m in maps]
    tx, ty = map_gradient(truth.heights, truth.cell_size)
    vmax = float(np.nanpercentile(np.hypot(tx, ty)[region], 99)) if region.any() else None
    zt = truth.heights[rows_sl, cols_sl][sub]
    lo, hi = (float(np.nanmin(zt)), float(np.nanmax(zt))) if zt.size else (None, None)
    ncol = len(named) + (mosaic is not None)
    fig, axes = plt.subplots(
        2,
        ncol + 1,
        figsize=(2.7 * ncol + 2.2, 6.4),
        squeeze=False,
        layout="constrained",
        width_ratios=[1.0] * ncol + [0.8],
    )
    image = None
    for j, (label, z) in enumerate(named):
        shown = np.where(sub, z[rows_sl, cols_sl], np.nan)
        image = axes[0, j].imshow(
            shown, origin="lower", extent=extent, cmap="viridis", vmin=lo, vmax=hi
        )
        gx, gy = map_gradient(z, truth.cell_size)
        rgb = gradient_hsv(gx[rows_sl, cols_sl], gy[rows_sl, cols_sl], vmax)
        axes[1, j].imshow(np.where(sub[..., None], rgb, 0.0), origin="lower", extent=extent)
        axes[0, j].set_title(label, fontsize=9)
    if mosaic is not None:
        axes[0, ncol - 1].imshow(
            mosaic[rows_sl, cols_sl], origin="lower", extent=extent, cmap="gray"
        )
        axes[0, ncol - 1].set_title("sidescan mosaic (test lines)", fontsize=9)
        axes[1, ncol - 1].axis("off")
    for ax in axes[:, :ncol].ravel():
        ax.tick_params(labelsize=6)
    for ax in axes[:, 0]:
        ax.set_ylabel("y north (m)", fontsize=7)
    for ax in axes[1, :ncol]:
        ax.set_xlabel("x east (m)", fontsize=7)
    north_arrow(axes[0, 0])
    # the last column: the height colour bar and the gradient key
    axes[0, -1].axis("off")
    if image is not None:
        cax = axes[0, -1].inset_axes((0.05, 0.05, 0.18, 0.9))
        fig.colorbar(image, cax=cax, label=HEIGHT_LABEL)
        cax.yaxis.label.set_fontsize(7)
        cax.tick_params(labelsize=6)
    hsv_wheel_key(axes[1, -1], vmax)
    fig.suptitle(
        title or "bathymetry (top, one colour scale) and gradient in HSV (bottom), north up",
        fontsize=10,
    )
    fig.supxlabel(axes_note, fontsize=7)
    return _save(fig, path)


def roughest_windows(
    truth: BathyGrid, region: np.ndarray, size: int, count: int = 2
) -> list[tuple[slice, slice]]:
    """The ``count`` non-overlapping ``size``-cell windows inside ``region`` where the MBES
    gradient norm has the largest mean (ridges, boulder fields)."""
    from scipy.ndimage import uniform_filter

    gx, gy = map_gradient(truth.heights, truth.cell_size)
    rough = np.where(region, np.hypot(gx, gy), 0.0)
    rough = np.nan_to_num(rough)
    inside = uniform_filter(region.astype(float), size) > 0.95
    score = np.where(inside, uniform_filter(rough, size), -np.inf)
    windows = []
    for _ in range(count):
        if not np.isfinite(score).any():
            break
        r, c = np.unravel_index(int(np.argmax(score)), score.shape)
        r0 = int(np.clip(r - size // 2, 0, truth.shape[0] - size))
        c0 = int(np.clip(c - size // 2, 0, truth.shape[1] - size))
        windows.append((slice(r0, r0 + size), slice(c0, c0 + size)))
        score[max(0, r0 - size) : r0 + 2 * size, max(0, c0 - size) : c0 + 2 * size] = -np.inf
    return windows


def sidescan_mosaic(survey_dir: Path, like: BathyGrid, split: str = "test") -> np.ndarray | None:
    """Mean normalised intensity of the draped valid bins of ``split`` per grid cell."""
    try:
        from sss2bathy.data.normalize import normalize_intensity
        from sss2bathy.draping import drape_survey
        from sss2bathy.survey import Survey

        survey = Survey.load(survey_dir)
        lines = [ln.name for ln in survey.split_lines(split)]
        draped = drape_survey(survey, survey_dir, lines=lines)
    except (OSError, ValueError, KeyError) as exc:
        log.warning("no sidescan mosaic: %s", exc)
        return None
    total = np.zeros(like.shape)
    count = np.zeros(like.shape)
    for name in lines:
        d, line = draped[name], survey.line(name)
        valid = d.mask == 0
        inten = normalize_intensity(line.intensity, valid)[valid]
        pts = d.points[valid]
        ix = np.rint((pts[:, 0] - like.x0) / like.cell_size).astype(int)
        iy = np.rint((pts[:, 1] - like.y0) / like.cell_size).astype(int)
        ok = (ix >= 0) & (ix < like.shape[1]) & (iy >= 0) & (iy < like.shape[0])
        np.add.at(total, (iy[ok], ix[ok]), inten[ok])
        np.add.at(count, (iy[ok], ix[ok]), 1)
    with np.errstate(invalid="ignore"):
        return np.where(count > 0, total / np.maximum(count, 1), np.nan)


def _run_links(label: str, run: RunRecord, out: Path) -> str:
    """A Markdown list item: the run folder and its composed config, relative to ``out``."""
    folder = Path(os.path.relpath(run.path, out)).as_posix()
    config = run.path / ".hydra" / "config.yaml"
    links = f"[run folder]({folder}/)"
    if config.is_file():
        links += f" · [config]({folder}/.hydra/config.yaml)"
    return f"- {label}: {links} (`{run.path}`)"


def _survey_section(
    variants: list[tuple[str, str]],
    runs: dict[str, RunRecord],
    paper: dict[str, dict],
    key: str,
    title: str,
    out: Path,
    zoom: bool,
) -> tuple[list[str], dict[str, Any] | None]:
    """The section of one SIREN table (its files written into ``out``) and the table's
    entry of ``results.json`` (None when no run left a map)."""
    present = [(task, label) for task, label in variants if task in runs]
    if not present:
        return [f"## {title}", "", "No finished run of these experiments was found.", ""], None
    truth = mbes_grid(runs[present[0][0]])
    if truth is None:
        return [f"## {title}", "", "The MBES grid of these runs was not found.", ""], None
    maps = [m for t, lbl in present if (m := load_map_run(lbl, runs[t], truth)) is not None]
    if not maps:
        return [f"## {title}", "", "None of these runs left a map.", ""], None
    survey = runs[present[0][0]].info.get("survey_name") or key
    rows, common = score_maps(maps, truth)
    md, table_csv = siren_table(rows, paper, title)
    atomic_write_text(out / f"table_siren_{key}.md", md)
    atomic_write_text(out / f"table_siren_{key}.csv", table_csv)
    plot_pdfs(
        [m for m in maps if not m.label.endswith("Direct-Fit")],
        truth,
        common,
        out / f"pdf_{key}.png",
        f"{survey}: PDF of the signed height errors (map − MBES) of the SIREN variants",
    )
    note = _origin_note(runs[present[0][0]])
    maps_title = (
        f"{survey}: SIREN variants beside the MBES — bathymetry (top) and gradient in HSV "
        "(bottom), on the cells every variant scored; north up"
    )
    _panels(truth, maps, common, out / f"maps_{key}.png", title=maps_title, axes_note=note)
    lines = [f"## {title}", "", md.split("\n", 2)[2]]
    lines += [f"![{survey}: PDF of the signed height errors](pdf_{key}.png)", ""]
    lines += [f"![{survey}: maps of every SIREN variant beside the MBES](maps_{key}.png)", ""]
    if zoom:
        size = max(16, int(round(min(common.shape) * 0.3)))
        survey_dir = Path(maps[0].run.info["data_dir"]) / maps[0].run.info["survey_name"]
        mosaic = sidescan_mosaic(survey_dir, truth)
        chosen = [m for m in maps if m.label in ZOOM_LABELS]
        for k, window in enumerate(roughest_windows(truth, common, size)):
            name = f"zoom_{key}_{k}.png"
            zoom_title = f"{survey}: roughest area {k + 1} — bathymetry and gradient, north up"
            _panels(truth, chosen, common, out / name, window, mosaic, zoom_title, note)
            lines += [f"![{survey}: zoom on the roughest area {k + 1}]({name})", ""]
    lines += ["Runs:", ""] + [_run_links(m.label, m.run, out) for m in maps] + [""]
    return lines, results_table(title, survey, rows, [m.run for m in maps])


def read_stage_times(outputs_dir: Path) -> dict[str, Any] | None:
    """The pipeline's ``report/stage_times.json`` (None when the pipeline did not run)."""
    times = outputs_dir / "report" / "stage_times.json"
    if not times.is_file():
        return None
    try:
        return json.loads(times.read_text())
    except (OSError, json.JSONDecodeError) as exc:
        log.warning("stage times unreadable (%s): %s", times, exc)
        return None


def stage_times_section(stage: dict[str, Any] | None, runs: dict[str, RunRecord]) -> list[str]:
    """The pipeline's stage wall times as a Markdown table, with each training stage's run;
    none when the pipeline did not run."""
    if not stage:
        return []
    lines = [
        "## Stage times",
        "",
        f"Wall time of each stage of the last pipeline run (scale `{stage.get('scale')}`).",
        "",
        "| stage | seconds | run |",
        "|---|---:|---|",
    ]
    for name, seconds in stage.get("seconds", {}).items():
        run = runs.get(name)
        lines.append(f"| {name} | {seconds} | {f'`{run.path.name}`' if run else ''} |")
    return lines + [""] + wall_time_line(stage)


def build_report(
    outputs_dir: str | Path, out_dir: str | Path | None = None, conf_dir: str | Path | None = None
) -> Path:
    """Write the report of the latest runs under ``outputs_dir``: ``index.md``, the same as
    a self-contained web page ``index.html`` (figures embedded), and the tables as data
    (``results.json``) and as the results page (``results.md``,
    :func:`sss2bathy.eval.results.results_markdown`); return ``index.md``. The tables' rows
    are the experiments of ``conf_dir/experiment`` (default: the project's ``conf/``)."""
    outputs_dir = Path(outputs_dir)
    out = Path(out_dir) if out_dir is not None else outputs_dir / "report"
    out.mkdir(parents=True, exist_ok=True)
    runs = find_latest_runs(outputs_dir)
    experiments = pipeline_experiments(conf_dir)
    index = [
        "# sss2bathy report",
        "",
        "The paper's experiments on the synthetic surveys (latest finished run of each). "
        "The paper's numbers are shown beside ours, labelled: they were measured on its own "
        "real data, so they orient, they do not compare like for like.",
        "",
    ]
    results: dict[str, Any] = {"cnn": None, "siren": {}}
    used: list[RunRecord] = []
    cnn_task = next((task for task, _ in table_variants(CNN_KEY, experiments)), None)
    cnn = runs.get(cnn_task) if cnn_task else None
    rows = table_rows_from_metrics(cnn.metrics) if cnn else {}
    # the constant (training-mean) prediction of each test set, when the run scored one
    const = constant_rows_from_metrics(cnn.metrics) if cnn else {}
    const = {k: v for k, v in const.items() if k in rows}
    index += ["## CNN (Table 2)", ""]
    if rows:
        atomic_write_text(out / "table_cnn.md", cnn_table_markdown(rows, const))
        atomic_write_text(out / "table_cnn.csv", cnn_table_csv(rows, const))
        index += [cnn_table_markdown(rows, const).split("\n", 2)[2], "Run:", ""]
        index += [_run_links("CNN", cnn, out), ""]
        results["cnn"] = {"rows": rows, "constant": const}
        used.append(cnn)
    else:
        index += ["No finished CNN run with test metrics was found.", ""]
    for key, (title, paper, zoom) in SIREN_TABLES.items():
        variants = table_variants(key, experiments)
        lines, table = _survey_section(variants, runs, paper, key, title, out, zoom)
        index += lines
        if table is not None:
            results["siren"][key] = table
            used += [runs[task] for task, _ in variants if task in runs]
    stage = read_stage_times(outputs_dir)
    index += stage_times_section(stage, runs)
    results = {**results_header(used, stage), **results, "stage_times": stage}
    atomic_write_text(out / RESULTS_JSON, json.dumps(results, indent=2) + "\n")
    atomic_write_text(out / RESULTS_MD, results_markdown(results))
    path = out / "index.md"
    text = "\n".join(index)
    atomic_write_text(path, text)
    atomic_write_text(out / "index.html", markdown_to_html(text, out, "sss2bathy report"))
    return path


HTML_STYLE = """
body { font-family: system-ui, sans-serif; max-width: 1400px; margin: 2em auto; padding: 0 1em;
       color: #222; line-height: 1.45; }
h1, h2 { border-bottom: 1px solid #ddd; padding-bottom: .2em; }
table { border-collapse: collapse; margin: 1em 0; font-size: 14px; }
th, td { border: 1px solid #ccc; padding: 3px 8px; }
th { background: #f3f3f3; }
tr:nth-child(even) td { background: #fafafa; }
img { max-width: 100%; height: auto; display: block; margin: .5em 0; }
figure { margin: 1em 0; }
figcaption { font-size: 13px; color: #555; }
code { font-size: 12px; color: #555; }
"""


def markdown_to_html(text: str, folder: Path, title: str) -> str:
    """A self-contained web page of the report's Markdown ``text``: tables as HTML tables,
    each figure (a PNG in ``folder``) embedded as a ``data:`` URI with its alt text as the
    caption; links stay relative (run folders, their ``.hydra/config.yaml``)."""
    import base64
    import html
    import re

    import markdown

    body = markdown.markdown(text, extensions=["tables"], output_format="html")

    def embed(match: re.Match) -> str:
        alt, src = html.unescape(match.group("alt")), html.unescape(match.group("src"))
        png = folder / src
        if not png.is_file():
            log.warning("report: figure %s is missing; left out of index.html", png)
            return f"<p><em>figure missing: {html.escape(src)}</em></p>"
        data = base64.b64encode(png.read_bytes()).decode("ascii")
        return (
            f'<figure><img alt="{html.escape(alt)}" src="data:image/png;base64,{data}" '
            f'data-file="{html.escape(src)}" /><figcaption>{html.escape(alt)}</figcaption>'
            "</figure>"
        )

    pattern = r'<p><img alt="(?P<alt>[^"]*)" src="(?P<src>[^"]+)" ?/?></p>'
    body = re.sub(pattern, embed, body)
    return (
        '<!DOCTYPE html>\n<html lang="en">\n<head>\n<meta charset="utf-8" />\n'
        f"<title>{html.escape(title)}</title>\n<style>{HTML_STYLE}</style>\n</head>\n"
        f"<body>\n{body}\n</body>\n</html>\n"
    )
