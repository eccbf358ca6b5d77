"""The SIREN settings table of a *validation site*: every finished run below a folder,
scored alike.

``make valsite-study`` fits SIREN-GT-N2d, SIREN-CNN-N2d and SIREN-Lambert on
``data/survey=synthetic_d1_valsite`` (d1's recipe on another seabed, flown like d1's test
lines; neither training nor test data) at a few SIREN settings, one run per folder. This
module reads each finished run's variant and settings from its config and scores every map
on the **same cells** against the site's MBES grid (the lambert_tune table's reader,
:func:`studies.lambert_tune.score_run_folder`), and writes
``valsite_study.md`` and ``valsite_study.csv``, grouped by variant, best MAE first.

Runs of more than one survey, or of a survey that is not a validation site (its name must
contain ``valsite``), are refused: the settings this table chooses must never be chosen on
the test lines the paper's tables report.

    python -m studies.valsite_study outputs/valsite_study/demo
"""

from __future__ import annotations

import argparse
import logging
from collections.abc import Mapping
from pathlib import Path
from typing import Any

from omegaconf import OmegaConf

from sss2bathy.eval.report import RunRecord
from studies import tables
from studies.lambert_tune import METRICS, score_run_folder
from studies.tables import fmt_cell, markdown_table, write_tables

log = logging.getLogger("sss2bathy.valsite_study")

SITE_MARK = "valsite"
# (column, config key); the settings the study varies
SETTINGS = (
    ("variant", "task_name"),
    ("lr", "scale.siren.lr"),
    ("gamma", "scale.siren.gamma"),
    ("epochs", "trainer.max_epochs"),
    ("line_offset", "model.line_offset"),
)


def run_settings(config: Mapping[str, Any], where: str = "config") -> dict[str, Any]:
    """The study's settings of one run's (unresolved) Hydra config; ``epochs`` resolved
    against the scale. Raises ``ValueError`` naming a missing key."""
    cfg = OmegaConf.create(dict(config))
    out: dict[str, Any] = {}
    for column, key in SETTINGS:
        value = OmegaConf.select(cfg, key, default="<absent>", throw_on_missing=False)
        if value == "<absent>":
            if column == "line_offset":  # runs of a model without the key (Lambert: off)
                value = False
            else:
                raise ValueError(f"{where}: {key}: expected a value, found none")
        out[column] = "null" if value is None else value
    return out


def _check_site(name: str) -> None:
    if SITE_MARK not in name:
        raise ValueError(
            f"survey_name: expected a validation site (a name with {SITE_MARK!r}, "
            f"e.g. data/survey=synthetic_d1_valsite), found {name!r}"
        )


def study_table(root: str | Path) -> list[dict[str, Any]]:
    """One row per run below ``root``: its settings, its held-out altimeter MAE, the metrics
    on the common cells (:func:`studies.lambert_tune.score_run_folder`) and its
    folder; grouped by variant, best MAE first.

    Raises:
        FileNotFoundError: no finished run, or the site's MBES grid is missing.
        ValueError: runs of several surveys or of one that is not a validation site, or a
            map off the MBES grid.
    """

    def settings_of(run: RunRecord) -> dict[str, Any]:
        return {
            **run_settings(run.info["config"], where=str(run.path)),
            "holdout_alt_mae": run.metrics.get("final/holdout_alt_mae", float("nan")),
        }

    rows = score_run_folder(root, "SIREN", settings_of, _check_site)
    return sorted(rows, key=lambda r: (str(r["variant"]), r["mae"]))


def to_markdown(rows: list[dict[str, Any]], title: str = "SIREN settings, validation site") -> str:
    """Markdown table of :func:`study_table` rows."""
    columns = [c for c, _ in SETTINGS]
    md = [
        f"# {title}",
        "",
        "Each variant fitted to the validation site's lines (never a test survey); map MAE and "
        "STD of the signed height error (m) and gradient cosine similarity on the cells every "
        "run scored, and the held-out altimeter MAE (m, the signal a survey without MBES has). "
        "Grouped by variant, best MAE first.",
        "",
    ]
    md += markdown_table(
        [*columns, "MAE (m)", "STD (m)", "gradient CS", "held-out alt. MAE (m)", "cells", "run"],
        (
            [*(fmt_cell(r[c]) for c in columns), f"{r['mae']:.3f}", f"{r['std']:.3f}"]
            + [f"{r['grad_cs']:.3f}", f"{r['holdout_alt_mae']:.3f}", r["n_cells"], r["run"]]
            for r in rows
        ),
        "l" * len(columns) + "rrrrrl",
    )
    return "\n".join(md) + "\n"


def to_csv(rows: list[dict[str, Any]]) -> str:
    """CSV of :func:`study_table` rows."""
    return tables.to_csv(rows, [*(c for c, _ in SETTINGS), *METRICS, "holdout_alt_mae", "run"])


def main(argv: list[str] | None = None) -> int:
    """``python -m studies.valsite_study ROOT [--out DIR]``."""
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("root", help="folder of the study's runs (searched recursively)")
    p.add_argument("--out", default=None, help="where the table goes (default: ROOT)")
    args = p.parse_args(argv)
    rows = study_table(args.root)
    paths = write_tables(args.out or args.root, "valsite_study", to_markdown(rows), to_csv(rows))
    print(to_markdown(rows))
    print(f"written: {paths['md']}, {paths['csv']}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
