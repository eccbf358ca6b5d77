"""The ``metric_curve.csv`` file of a run: one row per evaluation, read and written here.

Columns: the base columns :data:`BASE_COLUMNS` (``epoch``, optimizer ``step``, ``wall_s``
since the fit started, ``train_s`` = wall minus validation time, ``lr``), then every
``val/*`` metric of that evaluation. The ``MetricCurve`` callback
(:mod:`sss2bathy.callbacks.curve`) writes it during a fit; the schedule study
(``python -m studies.schedule_study``) reads it. The format lives in ``eval/`` so that
its reader needs nothing from the training layers.
"""

from __future__ import annotations

import csv
import math
from pathlib import Path
from typing import Any

from sss2bathy.utils.atomic import atomic_path

BASE_COLUMNS = ("epoch", "step", "wall_s", "train_s", "lr")


def write_curve(path: str | Path, rows: list[dict[str, Any]]) -> None:
    """Write ``rows`` (dicts) to ``path`` as CSV, base columns first (atomic)."""
    keys = list(BASE_COLUMNS)
    for row in rows:
        keys += [k for k in row if k not in keys]
    with atomic_path(path) as tmp, open(tmp, "w", newline="") as fh:
        writer = csv.DictWriter(fh, fieldnames=keys, restval="")
        writer.writeheader()
        writer.writerows(rows)


def read_curve(path: str | Path) -> list[dict[str, float]]:
    """Rows of a ``metric_curve.csv`` as floats (empty cells -> NaN).

    Raises:
        ValueError: the file lacks one of the base columns or holds a non-number.
    """
    path = Path(path)
    with open(path, newline="") as fh:
        reader = csv.DictReader(fh)
        missing = [c for c in BASE_COLUMNS if c not in (reader.fieldnames or [])]
        if missing:
            raise ValueError(
                f"{path}: expected columns {list(BASE_COLUMNS)}, missing {missing} "
                f"(found {reader.fieldnames})"
            )
        rows = []
        for i, raw in enumerate(reader, start=2):
            row = {}
            for key, value in raw.items():
                try:
                    row[key] = float(value) if value not in ("", None) else math.nan
                except ValueError:
                    raise ValueError(
                        f"{path}, line {i}, column {key!r}: expected a number, found {value!r}"
                    ) from None
            rows.append(row)
    return rows
