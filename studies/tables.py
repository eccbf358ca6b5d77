"""The studies' one table writer: a Markdown table, the same rows as CSV, both written
atomically beside each other (``<stem>.md``, ``<stem>.csv``)."""

from __future__ import annotations

import csv
import io
import json
import math
from collections.abc import Iterable, Mapping, Sequence
from pathlib import Path
from typing import Any

from sss2bathy.utils.atomic import atomic_write_text


def fmt_cell(value: Any) -> str:
    """A table cell: floats to 3 significant digits, anything else as text."""
    return f"{value:.3g}" if isinstance(value, float) else str(value)


def markdown_table(
    header: Sequence[str], rows: Iterable[Sequence[Any]], align: str | None = None
) -> list[str]:
    """The lines of a Markdown table: ``| a | b |``, the rule (``align``: one letter per
    column, ``l`` left, ``r`` right; all left by default), one line per row (cells as text)."""
    align = "l" * len(header) if align is None else align
    if len(align) != len(header) or set(align) - {"l", "r"}:
        raise ValueError(
            f"align: expected {len(header)} letters of 'l'/'r' for {list(header)}, found {align!r}"
        )
    lines = [
        "| " + " | ".join(header) + " |",
        "|" + "".join("---:|" if a == "r" else "---|" for a in align),
    ]
    for row in rows:
        cells = [str(c) for c in row]
        if len(cells) != len(header):
            raise ValueError(f"row: expected {len(header)} cells {list(header)}, found {cells}")
        lines.append("| " + " | ".join(cells) + " |")
    return lines


def to_csv(
    rows: Iterable[Mapping[str, Any]], fields: Sequence[str], *, ignore_extra: bool = False
) -> str:
    """CSV text (``\\n`` line ends) of ``rows`` under the header ``fields``; a missing key is
    an empty cell, a key not in ``fields`` an error unless ``ignore_extra``."""
    buf = io.StringIO()
    writer = csv.DictWriter(
        buf,
        fieldnames=list(fields),
        lineterminator="\n",
        restval="",
        extrasaction="ignore" if ignore_extra else "raise",
    )
    writer.writeheader()
    writer.writerows(rows)
    return buf.getvalue()


def write_tables(out_dir: str | Path, stem: str, markdown: str, table: str) -> dict[str, Path]:
    """``<out_dir>/<stem>.md`` and ``<stem>.csv`` (folder made), written atomically."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    paths = {"md": out / f"{stem}.md", "csv": out / f"{stem}.csv"}
    atomic_write_text(paths["md"], markdown)
    atomic_write_text(paths["csv"], table)
    return paths


def csv_value(value: Any) -> str:
    """A CSV cell: floats in full (``repr``), non-finite ones empty, anything else as text."""
    if isinstance(value, float):
        return repr(value) if math.isfinite(value) else ""
    return str(value)


def read_json_object(path: Path) -> dict[str, Any]:
    """A run's JSON record as a dict; a missing, unreadable or non-object file is one
    ``ValueError`` naming the path."""
    if not path.is_file():
        raise ValueError(f"{path}: expected a file, found none (did the run finish?)")
    try:
        data = json.loads(path.read_text())
    except json.JSONDecodeError as err:
        raise ValueError(f"{path}: expected JSON, found unreadable text ({err})") from None
    if not isinstance(data, dict):
        raise ValueError(f"{path}: expected a JSON object, found {type(data).__name__}")
    return data
