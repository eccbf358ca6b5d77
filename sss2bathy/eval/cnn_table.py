"""Table-2-style CNN results (paper "Quantitative Results For CNN"): ours beside the paper's.

Rows are ``{name: {"mae", "rel", "rmse", "delta1", "delta2", "delta3"}}`` with the deltas in
percent (as :func:`sss2bathy.metrics.NormalMetrics` computes them).
"""

from __future__ import annotations

import csv
import io
import math
from collections.abc import Mapping
from pathlib import Path

from sss2bathy.eval.paper_numbers import CNN_TABLE, PAPER_LABEL
from sss2bathy.utils.atomic import atomic_write_text

COLUMNS = ("mae", "rel", "rmse", "delta1", "delta2", "delta3")
HEADERS = ("MAE", "REL", "RMSE", "δ<1.05 (%)", "δ<1.05² (%)", "δ<1.05³ (%)")
OURS_LABEL = "ours (synthetic survey)"
MD_NAME = "cnn_table.md"
CSV_NAME = "cnn_table.csv"


def _fmt(key: str, value: float) -> str:
    if not math.isfinite(value):
        return "n/a"
    return f"{value:.2f}" if key.startswith("delta") else f"{value:.4f}"


def _check_rows(rows: Mapping[str, Mapping[str, float]]) -> dict[str, dict[str, float]]:
    if not isinstance(rows, Mapping) or not rows:
        raise ValueError(f"rows: expected a non-empty mapping name -> metrics, found {rows!r}")
    out = {}
    for name, metrics in rows.items():
        if not isinstance(metrics, Mapping):
            raise ValueError(f"rows['{name}']: expected a mapping of metrics, found {metrics!r}")
        missing = [k for k in COLUMNS if k not in metrics]
        if missing:
            raise ValueError(f"rows['{name}']: expected keys {list(COLUMNS)}, missing {missing}")
        try:
            out[str(name)] = {k: float(metrics[k]) for k in COLUMNS}
        except (TypeError, ValueError) as exc:
            raise ValueError(
                f"rows['{name}']: expected numeric metrics, found {metrics!r}"
            ) from exc
    return out


def cnn_table_markdown(rows: Mapping[str, Mapping[str, float]]) -> str:
    """Markdown table: our rows, then the paper's rows labelled as measured on its own data."""
    ours = _check_rows(rows)
    lines = [
        '# Normal CNN: quantitative results (paper Table "Quantitative Results For CNN")',
        "",
        "Errors are on n_lat (lower is better); accuracies are % of valid bins with "
        "max((n+1)/(n_GT+1), (n_GT+1)/(n+1)) below the threshold (higher is better).",
        f"Rows labelled *{PAPER_LABEL}* are the published numbers on the paper's real "
        "Datasets I/II; ours are on our synthetic surveys: for orientation, not a like-for-like "
        "comparison.",
        "",
        "| source | data set | " + " | ".join(HEADERS) + " |",
        "|---|---|" + "---:|" * len(HEADERS),
    ]
    for source, table in ((OURS_LABEL, ours), (PAPER_LABEL, CNN_TABLE)):
        for name, metrics in table.items():
            cells = " | ".join(_fmt(k, float(metrics[k])) for k in COLUMNS)
            lines.append(f"| {source} | {name} | {cells} |")
    return "\n".join(lines) + "\n"


def cnn_table_csv(rows: Mapping[str, Mapping[str, float]]) -> str:
    """CSV with columns ``source, dataset, mae, rel, rmse, delta1, delta2, delta3``."""
    ours = _check_rows(rows)
    buf = io.StringIO()
    writer = csv.writer(buf, lineterminator="\n")
    writer.writerow(("source", "dataset", *COLUMNS))
    for source, table in ((OURS_LABEL, ours), (PAPER_LABEL, CNN_TABLE)):
        for name, metrics in table.items():
            writer.writerow((source, name, *(repr(float(metrics[k])) for k in COLUMNS)))
    return buf.getvalue()


def write_cnn_table(
    rows: Mapping[str, Mapping[str, float]], out_dir: str | Path
) -> tuple[Path, Path]:
    """Write ``cnn_table.md`` and ``cnn_table.csv`` into ``out_dir`` (atomically).

    Args:
        rows: ``{data set name: {mae, rel, rmse, delta1, delta2, delta3}}`` (deltas in %).
        out_dir: folder, created if needed.

    Returns:
        ``(markdown path, csv path)``.
    """
    markdown, table = cnn_table_markdown(rows), cnn_table_csv(rows)
    out = Path(out_dir)
    md_path, csv_path = out / MD_NAME, out / CSV_NAME
    atomic_write_text(md_path, markdown)
    atomic_write_text(csv_path, table)
    return md_path, csv_path
