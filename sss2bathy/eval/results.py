"""The demo's results, written from runs, never by hand.

:func:`sss2bathy.eval.report.build_report` collects the tables of the latest runs as data,
``results.json`` (the CNN's rows and constant rows, each SIREN table's rows, the stage
times, and one header: scale, commits, machine, date), and renders them here:

* :func:`results_markdown` — the results page (``docs/results.md``): every table, with the
  paper's numbers beside ours, the figures and the stage times;
* :func:`readme_results` — the README's short tables, between :data:`README_START` and
  :data:`README_END`.

:func:`publish` (``sss2bathy-report --publish``, ``make results``) copies a report's
``results.json`` and figures into ``docs/`` and rewrites ``docs/results.md`` and the README's
block from it, so the three always agree; a test renders the committed ``docs/results.json``
and compares.
"""

from __future__ import annotations

import csv
import io
import json
import math
import os
import shutil
from collections.abc import Mapping, Sequence
from datetime import datetime, timezone
from pathlib import Path
from typing import Any

from sss2bathy.eval.cnn_table import cnn_table_markdown
from sss2bathy.eval.paper_numbers import CNN_TABLE, PAPER_LABEL, SIREN_D1_TABLE, SIREN_D2_TABLE
from sss2bathy.utils.atomic import atomic_write_text
from sss2bathy.utils.machine import cpu_model

RESULTS_JSON = "results.json"
RESULTS_MD = "results.md"
README_START = (
    "<!-- results:start: written by sss2bathy-report --publish from docs/results.json -->"
)
README_END = "<!-- results:end -->"
OURS = "ours (synthetic survey)"
#: The report's SIREN tables: an experiment's ``pipeline.table`` -> (title, the paper's rows,
#: zoomed panels). Their rows, labels and order are the experiments' ``pipeline`` keys
#: (:func:`sss2bathy.eval.report.table_variants`); :data:`CNN_KEY` is the CNN's table.
SIREN_TABLES: dict[str, tuple[str, dict[str, dict], bool]] = {
    "d1": ("SIREN on synthetic_d1 (Table 3)", SIREN_D1_TABLE, True),
    "d2": ("SIREN on synthetic_d2 (Table 4)", SIREN_D2_TABLE, False),
    # the different-sonar stress site (no counterpart in the paper)
    "d3": ("SIREN on synthetic_d3 (another sonar)", {}, False),
}
CNN_KEY = "cnn"
REPORT_TABLES = (CNN_KEY, *SIREN_TABLES)
#: the report's figures of a SIREN table (``<figure>_<key>.png``, the zoomed panels
#: ``zoom_<key>_<k>.png``), published as ``docs/images/<its stem>_<scale>.png``
FIGURES = ("pdf_{key}.png", "maps_{key}.png", "zoom_{key}_*.png")


# ------------------------------------------------------------------------------ tables
def siren_table(rows: dict[str, dict], paper: dict[str, dict], title: str) -> tuple[str, str]:
    """Markdown and CSV of a SIREN table (MAE, STD, gradient CS), ours then the paper's (a
    value missing from a row is an empty cell)."""
    md = [
        f"# {title}",
        "",
        "MAE and STD of the signed height error (m), mean cosine similarity of the gradient "
        "maps (higher is better), on the cells every variant scored. "
        f"Rows labelled *{PAPER_LABEL}* are the published numbers on the paper's real data.",
        "",
        "| source | variant | MAE (m) | STD (m) | gradient CS | cells |",
        "|---|---|---:|---:|---:|---:|",
    ]
    buf = io.StringIO()
    writer = csv.writer(buf, lineterminator="\n")
    writer.writerow(("source", "variant", "mae", "std", "grad_cs", "n_cells"))
    for source, table in ((OURS, rows), (PAPER_LABEL, paper)):
        for label, m in table.items():
            values = [m.get(k) for k in ("mae", "std", "grad_cs")]
            cells = " | ".join("" if v is None else f"{v:.3f}" for v in values)
            n_cells = "" if m.get("n_cells") is None else m["n_cells"]
            md.append(f"| {source} | {label} | {cells} | {n_cells} |")
            writer.writerow((source, label, *("" if v is None else v for v in values), n_cells))
    return "\n".join(md) + "\n", buf.getvalue()


def results_table(
    title: str, survey: str, rows: Mapping[str, Mapping[str, Any]], runs: Sequence[Any]
) -> dict[str, Any]:
    """One SIREN table's entry of ``results.json``: title, survey, each variant's MAE, STD,
    gradient CS and cell count, and the run folders' names."""
    keep = ("mae", "std", "grad_cs", "n_cells")
    return {
        "title": title,
        "survey": survey,
        "rows": {
            label: {k: int(m[k]) if k == "n_cells" else float(m[k]) for k in keep if k in m}
            for label, m in rows.items()
        },
        "runs": [Path(r.path).name for r in runs],
    }


# ------------------------------------------------------------------------------ header
def machine() -> str:
    """The CPU model and core count of this machine (no host name)."""
    return f"{cpu_model()}, {os.cpu_count()} cores"


def results_header(runs: Sequence[Any], stage: Mapping[str, Any] | None) -> dict[str, Any]:
    """``scale``, ``commits`` (short, ``-dirty`` kept), ``machine`` (where the report ran)
    and ``date`` of the results of ``runs`` (:class:`~sss2bathy.eval.report.RunRecord`)."""
    scales = sorted({str(r.info.get("scale")) for r in runs if r.info.get("scale")})
    if not scales and stage:
        scales = [str(stage.get("scale"))]
    commits = []
    for r in runs:
        rev = str(r.info.get("git_revision") or "unknown")
        short = rev[:7] + ("-dirty" if rev.endswith("-dirty") else "")
        if short not in commits:
            commits.append(short)
    return {
        "scale": ", ".join(scales) or "unknown",
        "commits": commits,
        "machine": machine(),
        "date": datetime.now(timezone.utc).strftime("%Y-%m-%d"),
        "source": "the latest finished run of each experiment (sss2bathy-report)",
    }


# --------------------------------------------------------------------------- rendering
def _cnn_rows(results: Mapping[str, Any]) -> tuple[dict, dict]:
    cnn = results.get("cnn") or {}
    return dict(cnn.get("rows") or {}), dict(cnn.get("constant") or {})


def results_markdown(results: Mapping[str, Any]) -> str:
    """The results page of ``results`` (``results.json``): a header line, the CNN table,
    each SIREN table with its figures, the stage times."""
    commits = ", ".join(results.get("commits") or []) or "unknown"
    lines = [
        "# Results of the paper pipeline",
        "",
        f"Scale `{results.get('scale')}` · commit {commits} · {results.get('machine')} · "
        f"{results.get('date')} · from {results.get('source')}.",
        "",
        "Written by `sss2bathy-report --publish` (`make results`) from `docs/results.json`; "
        "do not edit by hand. The paper's numbers stand beside ours, labelled: they were "
        "measured on its own real data, so they orient, they do not compare like for like. "
        "How the numbers moved over time: [results_log.md](results_log.md).",
        "",
        "## CNN (Table 2)",
        "",
    ]
    rows, const = _cnn_rows(results)
    lines += [cnn_table_markdown(rows, const).split("\n", 2)[2]] if rows else ["No CNN run.", ""]
    for key, table in (results.get("siren") or {}).items():
        title, paper, _ = SIREN_TABLES.get(key, (table.get("title", key), {}, False))
        md, _ = siren_table(table["rows"], paper, title)
        lines += [f"## {title}", "", f"Survey `{table.get('survey')}`.", "", md.split("\n", 2)[2]]
        for figure in (results.get("figures") or {}).get(key, []):
            lines += [f"![{table.get('survey')}: {Path(figure).stem}]({figure})", ""]
    stage = results.get("stage_times") or {}
    if stage.get("seconds"):
        lines += ["## Stage times", "", "| stage | seconds |", "|---|---:|"]
        lines += [f"| {k} | {v} |" for k, v in stage["seconds"].items()] + [""]
        lines += wall_time_line(stage)
    return "\n".join(lines).rstrip("\n") + "\n"


def wall_time_line(stage: dict[str, Any]) -> list[str]:
    """The pipeline's wall time up to the report, and how many stages ran at a time (the
    stages' ``total`` is their sum); none when the last run did not finish."""
    wall, jobs = stage.get("wall_seconds"), stage.get("jobs")
    if wall is None:
        return []
    return [
        f"Wall time up to the report: {float(wall) / 60:.1f} min, {jobs} stage(s) at a time "
        "(`total` above is the sum of the stages).",
        "",
    ]


def _f(value: Any, fmt: str) -> str:
    return "" if value is None or not math.isfinite(float(value)) else format(float(value), fmt)


def readme_results(results: Mapping[str, Any]) -> str:
    """The README's short results (between the markers): the CNN's MAE against a constant's,
    the first SIREN table's MAE and gradient CS beside the paper's, one line for the other
    sites."""
    lines = [
        README_START,
        f"At scale `{results.get('scale')}`; every table, its figures, the run it comes from and "
        "the stage times: [`docs/results.md`](docs/results.md).",
        "",
    ]
    rows, const = _cnn_rows(results)
    if rows:
        lines += [
            "**CNN (the paper's Table 2)**: `n_lat` MAE, and skill = CNN MAE / a constant's "
            "(below 1: the CNN beats a constant).",
            "",
            "| test set | CNN MAE | constant MAE | skill |",
            "|---|---:|---:|---:|",
        ]
        for name, m in rows.items():
            c = const.get(name, {}).get("mae")
            skill = m["mae"] / c if c else None
            lines.append(
                f"| {name} | {_f(m['mae'], '.4f')} | {_f(c, '.4f')} | {_f(skill, '.2f')} |"
            )
        for name, m in CNN_TABLE.items():
            lines.append(f"| *paper, its {name}* | *{m['mae']:.4f}* | | |")
        lines.append("")
    siren = list((results.get("siren") or {}).items())
    for key, table in siren[:1]:
        title, paper, _ = SIREN_TABLES.get(key, (table.get("title", key), {}, False))
        lines += [
            f"**{title}**, map MAE against the MBES truth and gradient cosine similarity:",
            "",
            "| variant | MAE (m) | gradient CS | paper MAE / CS |",
            "|---|---:|---:|---:|",
        ]
        for label, m in table["rows"].items():
            p = paper.get(label)
            theirs = f"{p['mae']:.3f} / {p['grad_cs']:.3f}" if p else ""
            mae, cs = _f(m.get("mae"), ".3f"), _f(m.get("grad_cs"), ".3f")
            lines.append(f"| {label} | {mae} | {cs} | {theirs} |")
        lines.append("")
    others = []
    for key, table in siren[1:]:
        title, paper, _ = SIREN_TABLES.get(key, (table.get("title", key), {}, False))
        cells = []
        for label, m in table["rows"].items():
            theirs = f" (paper {paper[label]['mae']:.3f} m)" if label in paper else ""
            cells.append(f"{label} {_f(m.get('mae'), '.3f')} m{theirs}")
        others.append(f"{title}: " + ", ".join(cells))
    if others:
        lines += ["Map MAE elsewhere: " + "; ".join(others) + ".", ""]
    return "\n".join(lines + [README_END])


def replace_block(text: str, block: str, where: str = "README.md") -> str:
    """``text`` with its :data:`README_START` … :data:`README_END` block replaced by
    ``block`` (which carries both markers)."""
    start, end = text.find(README_START), text.find(README_END)
    if start < 0 or end < start:
        raise ValueError(
            f"{where}: expected one block '{README_START}' ... '{README_END}', found "
            f"{'no start marker' if start < 0 else 'no end marker after it'}"
        )
    return text[:start] + block + text[end + len(README_END) :]


def readme_block(text: str) -> str:
    """The results block of a README's ``text``, markers included ('' without one)."""
    start, end = text.find(README_START), text.find(README_END)
    return text[start : end + len(README_END)] if 0 <= start < end else ""


# ----------------------------------------------------------------------------- publish
def publish(report_dir: str | Path, docs_dir: str | Path, readme: str | Path) -> list[Path]:
    """Copy a report's ``results.json`` and its SIREN tables' figures into ``docs_dir``
    (:data:`FIGURES`, as ``images/<figure>_<key>_<scale>.png``), then write ``docs_dir/results.md``
    and the README's results block from it; return the files written."""
    report_dir, docs_dir, readme = Path(report_dir), Path(docs_dir), Path(readme)
    source = report_dir / RESULTS_JSON
    if not source.is_file():
        raise FileNotFoundError(
            f"{source}: expected the report's results (run sss2bathy-report first), found none"
        )
    results = json.loads(source.read_text())
    if not results.get("cnn") and not results.get("siren"):
        raise ValueError(
            f"{source}: expected the tables of at least one finished run, found none "
            "(nothing published)"
        )
    written = []
    figures: dict[str, list[str]] = {}
    scale = str(results.get("scale", "unknown")).replace(", ", "_")
    for key in results.get("siren") or {}:
        for png in (p for f in FIGURES for p in sorted(report_dir.glob(f.format(key=key)))):
            target = docs_dir / "images" / f"{png.stem}_{scale}.png"
            target.parent.mkdir(parents=True, exist_ok=True)
            shutil.copyfile(png, target)
            figures.setdefault(key, []).append(f"images/{target.name}")
            written.append(target)
    results["figures"] = figures
    atomic_write_text(docs_dir / RESULTS_JSON, json.dumps(results, indent=2) + "\n")
    atomic_write_text(docs_dir / RESULTS_MD, results_markdown(results))
    text = replace_block(readme.read_text(encoding="utf-8"), readme_results(results), str(readme))
    atomic_write_text(readme, text)
    return written + [docs_dir / RESULTS_JSON, docs_dir / RESULTS_MD, readme]
