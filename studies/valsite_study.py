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

Runs that differ only in their ``seed`` (the SIREN's initialisation, which alone moves a
map's MAE by a few centimetres) are also summarised as one row each: the mean over seeds and
the ratio to SIREN-GT-N2d's mean at the same SIREN settings -- how CNNs (``cnn``: the
run's ``data.normals.checkpoint``) are compared by the map they give.
"""

from __future__ import annotations

import argparse
import logging
import math
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
    ("w_height", "model.w_height"),
    ("cnn", "data.normals.checkpoint"),
    ("seed", "seed"),
)
#: settings a run's config may lack (a model or normals without the key), and their value then
OPTIONAL = {"line_offset": False, "w_height": "-", "cnn": "-", "seed": "-"}
#: the settings a seed summary row is keyed by (all but the seed)
GROUP = tuple(c for c, _ in SETTINGS if c != "seed")
GT_VARIANT = "siren_gt_n2d"


def checkpoint_label(value: Any) -> str:
    """A CNN checkpoint as a table shows it: a name as it is (``pretrained``, ``latest``),
    a path as ``<run>/<file>`` when it lies in a run's ``checkpoints/``, else its file name."""
    text = str(value)
    if "/" not in text:
        return text
    path = Path(text)
    if path.parent.name == "checkpoints":
        return f"{path.parent.parent.name}/{path.name}"
    return path.name


def run_settings(config: Mapping[str, Any], where: str = "config") -> dict[str, Any]:
    """The study's settings of one run's (unresolved) Hydra config; ``epochs`` resolved
    against the scale. Raises ``ValueError`` naming a missing key."""
    cfg = OmegaConf.create(dict(config))
    out: dict[str, Any] = {}
    for column, key in SETTINGS:
        value = OmegaConf.select(cfg, key, default="<absent>", throw_on_missing=False)
        if value == "<absent>":
            if column not in OPTIONAL:
                raise ValueError(f"{where}: {key}: expected a value, found none")
            value = OPTIONAL[column]  # e.g. Lambert: no line offsets, no CNN
        if column == "cnn" and value != "-":
            value = checkpoint_label(value)
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


def seed_means(rows: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """One row per setting over its seeds (:data:`GROUP`): ``seeds``, the per-seed ``maes``,
    the means of MAE, gradient CS and held-out altimeter MAE, and ``mae_ratio`` /
    ``cs_ratio`` to the SIREN-GT-N2d row of the same SIREN settings (NaN without one);
    best MAE first within a variant."""
    groups: dict[tuple, list[dict[str, Any]]] = {}
    for r in rows:
        groups.setdefault(tuple(_setting_key(r[c]) for c in GROUP), []).append(r)
    out = []
    for members in groups.values():
        members = sorted(members, key=lambda r: str(r["seed"]))
        n = len(members)
        out.append(
            {
                **{c: members[0][c] for c in GROUP},
                "seeds": [m["seed"] for m in members],
                "maes": [m["mae"] for m in members],
                **{
                    k: sum(m[k] for m in members) / n for k in ("mae", "grad_cs", "holdout_alt_mae")
                },
            }
        )
    siren = [c for c in GROUP if c not in ("variant", "cnn")]
    gt = {tuple(_setting_key(r[c]) for c in siren): r for r in out if r["variant"] == GT_VARIANT}
    # each method at its own best settings: the ratio to SIREN-GT-N2d's best mean MAE
    best = min((r for r in out if r["variant"] == GT_VARIANT), key=lambda r: r["mae"], default=None)
    for r in out:
        ref = gt.get(tuple(_setting_key(r[c]) for c in siren))
        r["mae_ratio"] = r["mae"] / ref["mae"] if ref else math.nan
        r["cs_ratio"] = r["grad_cs"] / ref["grad_cs"] if ref else math.nan
        r["best_mae_ratio"] = r["mae"] / best["mae"] if best else math.nan
        r["best_cs_ratio"] = r["grad_cs"] / best["grad_cs"] if best else math.nan
    return sorted(out, key=lambda r: (str(r["variant"]), r["mae"]))


def _setting_key(value: Any) -> str:
    """A setting as a grouping key: numbers by value (an override's ``1`` is a config's
    ``1.0``), anything else as its text."""
    if isinstance(value, int | float) and not isinstance(value, bool):
        return repr(float(value))
    return str(value)


def _ratio(value: float, digits: int) -> str:
    return "–" if math.isnan(value) else f"{value:.{digits}f}"  # NaN: no GT-N2d row


def to_markdown(rows: list[dict[str, Any]], title: str = "SIREN settings, validation site") -> str:
    """Markdown table of :func:`study_table` rows (and of their :func:`seed_means` when a
    setting was fitted with more than one seed)."""
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
    means = seed_means(rows)
    if any(len(r["seeds"]) > 1 for r in means):
        md += [
            "",
            "## Mean over seeds",
            "",
            "Runs that differ only in their seed: the mean of their scores, the MAE of each "
            "seed, and the ratios to SIREN-GT-N2d's means at the same SIREN settings and to "
            "its best setting's (each method at its own best: the fair comparison).",
            "",
        ]
        md += markdown_table(
            [*GROUP, "seeds", "MAE per seed (m)", "MAE (m)", "gradient CS"]
            + ["held-out alt. MAE (m)", "MAE / GT-N2d", "CS / GT-N2d"]
            + ["MAE / best GT-N2d", "CS / best GT-N2d"],
            (
                [*(fmt_cell(r[c]) for c in GROUP), " ".join(map(str, r["seeds"]))]
                + [" / ".join(f"{v:.3f}" for v in r["maes"]), f"{r['mae']:.3f}"]
                + [f"{r['grad_cs']:.3f}", f"{r['holdout_alt_mae']:.3f}"]
                + [_ratio(r["mae_ratio"], 2), _ratio(r["cs_ratio"], 3)]
                + [_ratio(r["best_mae_ratio"], 2), _ratio(r["best_cs_ratio"], 3)]
                for r in means
            ),
            "l" * (len(GROUP) + 1) + "lrrrrrrr",
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
