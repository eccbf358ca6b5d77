"""The SIREN-Lambert tuning table: every run of a ``lambert_tune`` sweep, scored alike.

``make lambert-tune`` fits SIREN-Lambert (``conf/experiment/lambert_tune.yaml``) on the
survey's *training* lines for a few sensor settings, one run per Hydra multirun job. This
module finds the finished runs below a folder (each with ``map.npz``, ``run_info.json``
and Hydra's ``.hydra/config.yaml``), reads each run's sensor settings from its config,
scores every map on the **same cells** (the intersection of the areas the runs scored, as
the report does: :func:`sss2bathy.eval.report.score_maps`) against the survey's MBES grid,
and writes ``lambert_tune.md`` and ``lambert_tune.csv``, best MAE first.

A run that fitted or scored on anything but the training lines (``data.sidescan_split`` or
``data.altimeter_split`` not ``train``) is refused: the settings must never be chosen on the
test lines the paper's tables report.

    python -m studies.lambert_tune outputs/multiruns/lambert_tune/demo \\
        --out outputs/lambert_tune/demo
"""

from __future__ import annotations

import argparse
import json
import logging
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any

from omegaconf import OmegaConf

from sss2bathy.eval.report import RunRecord, load_map_run, mbes_grid, score_maps
from studies import tables
from studies.tables import fmt_cell, markdown_table, write_tables

log = logging.getLogger("sss2bathy.lambert_tune")

TUNE_SPLIT = "train"
# (column, config key under the run's config); the sensor keys of the sweep
SETTINGS = (
    ("q", "model.sensor.q"),
    ("intensity_kind", "model.sensor.intensity_kind"),
    ("reflectivity", "model.sensor.reflectivity"),
    ("field_lr", "model.sensor.field_lr"),
    ("field_weight", "model.sensor.field_weight"),
    ("sensor_lr", "model.sensor_lr"),
    ("shadow_threshold", "model.sensor.shadow_threshold"),
    ("near_range_cut_m", "model.sensor.near_range_cut_m"),
)
METRICS = ("mae", "std", "grad_cs", "n_cells")


def run_settings(config: Mapping[str, Any], where: str = "config") -> dict[str, Any]:
    """The sweep's settings of one run's (unresolved) Hydra config, checked for the split.

    Raises:
        ValueError: a split other than ``train``, or a setting missing.
    """
    cfg = OmegaConf.create(dict(config))
    for key in ("data.sidescan_split", "data.altimeter_split"):
        value = OmegaConf.select(cfg, key, default=None)
        if value != TUNE_SPLIT:
            raise ValueError(
                f"{where}: {key}: expected {TUNE_SPLIT!r} (tuning never uses the test lines), "
                f"found {value!r}"
            )
    out: dict[str, Any] = {}
    for column, key in SETTINGS:
        if OmegaConf.select(cfg, key, default="<absent>", throw_on_missing=False) == "<absent>":
            raise ValueError(f"{where}: {key}: expected a value, found none")
        value = OmegaConf.select(cfg, key)
        out[column] = "null" if value is None else value
    # a field's own settings mean nothing without a field
    if out["reflectivity"] != "field":
        out["field_lr"] = out["field_weight"] = "-"
    return out


def find_runs(root: str | Path) -> list[RunRecord]:
    """Finished runs below ``root`` (``map.npz``, ``run_info.json``, ``.hydra/config.yaml``),
    in path order. ``RunRecord.info`` carries ``config`` (the run's Hydra config)."""
    root = Path(root)
    if not root.is_dir():
        raise FileNotFoundError(f"{root}: expected a folder of lambert_tune runs, found none")
    runs = []
    for npz in sorted(root.glob("**/map.npz")):
        run_dir = npz.parent
        info_path, cfg_path = run_dir / "run_info.json", run_dir / ".hydra" / "config.yaml"
        if not info_path.is_file() or not cfg_path.is_file():
            log.warning("%s: no run_info.json or .hydra/config.yaml; skipped", run_dir)
            continue
        info = json.loads(info_path.read_text())
        info["config"] = OmegaConf.to_container(OmegaConf.load(cfg_path), resolve=False)
        metrics_path = run_dir / "metrics.json"
        metrics = json.loads(metrics_path.read_text()) if metrics_path.is_file() else {}
        runs.append(RunRecord(run_dir, info, metrics))
    return runs


def score_run_folder(
    root: str | Path,
    kind: str,
    settings_of: Callable[[RunRecord], dict[str, Any]],
    check_survey: Callable[[str], None] | None = None,
) -> list[dict[str, Any]]:
    """Every finished run below ``root`` scored alike: one row per run, in path order, of
    ``settings_of(run)`` (which may refuse the run by raising), the run's :data:`METRICS` on
    the cells every run scored (:func:`sss2bathy.eval.report.score_maps`) against the
    survey's MBES grid, and ``run`` (its folder below ``root``). ``kind`` names the runs in
    errors; ``check_survey(survey_name)`` may refuse the survey. Settings and the survey are
    checked before any map is read.

    Raises:
        FileNotFoundError: no finished run, or its survey's MBES grid is missing.
        ValueError: a refused run or survey, runs of different surveys, or a map off the
            MBES grid.
    """
    root = Path(root)
    runs = find_runs(root)
    if not runs:
        raise FileNotFoundError(f"{root}: expected finished {kind} runs (map.npz), found none")
    settings = {str(r.path.relative_to(root)): settings_of(r) for r in runs}
    surveys = {(r.info.get("data_dir"), r.info.get("survey_name")) for r in runs}
    if len(surveys) != 1:
        raise ValueError(f"{root}: expected runs of one survey, found {sorted(map(str, surveys))}")
    name = str(runs[0].info.get("survey_name"))
    if check_survey is not None:
        try:
            check_survey(name)
        except ValueError as err:
            raise ValueError(f"{root}: {err}") from None
    truth = mbes_grid(runs[0])
    if truth is None:
        raise FileNotFoundError(
            f"{runs[0].path}: expected the MBES grid of survey {name!r} under data_dir "
            f"{runs[0].info.get('data_dir')!r}, found none"
        )
    maps = []
    for label, run in zip(settings, runs, strict=True):
        loaded = load_map_run(label, run, truth)
        if loaded is None:
            raise ValueError(f"{run.path}/map.npz: expected a map on the MBES grid, found another")
        maps.append(loaded)
    scores, _ = score_maps(maps, truth)
    return [
        {**settings[label], **{m: scores[label][m] for m in METRICS}, "run": label}
        for label in settings
    ]


def tune_table(root: str | Path) -> list[dict[str, Any]]:
    """One row per run below ``root``: its settings, metrics on the common cells, folder.

    Rows are sorted by MAE (best first).

    Raises:
        FileNotFoundError: no finished run, or its survey's MBES grid is missing.
        ValueError: a run on other than the training lines, runs of different surveys, or
            a map off the MBES grid.
    """
    rows = score_run_folder(
        root, "lambert_tune", lambda run: run_settings(run.info["config"], where=str(run.path))
    )
    return sorted(rows, key=lambda r: r["mae"])


def to_markdown(rows: list[dict[str, Any]], title: str = "SIREN-Lambert tuning") -> str:
    """Markdown table of :func:`tune_table` rows."""
    columns = [c for c, _ in SETTINGS]
    md = [
        f"# {title}",
        "",
        "SIREN-Lambert fitted to the sidescan and altimeter of the survey's *training* lines; "
        "map MAE and STD of the signed height error (m) and gradient cosine similarity, all "
        "runs on the same MBES cells near those lines. Best MAE first.",
        "",
    ]
    md += markdown_table(
        [*columns, "MAE (m)", "STD (m)", "gradient CS", "cells", "run"],
        (
            [*(fmt_cell(r[c]) for c in columns), f"{r['mae']:.3f}", f"{r['std']:.3f}"]
            + [f"{r['grad_cs']:.3f}", r["n_cells"], r["run"]]
            for r in rows
        ),
        "l" * len(columns) + "rrrrl",
    )
    return "\n".join(md) + "\n"


def to_csv(rows: list[dict[str, Any]]) -> str:
    """CSV of :func:`tune_table` rows (settings, metrics, run folder)."""
    return tables.to_csv(rows, [*(c for c, _ in SETTINGS), *METRICS, "run"])


def write_table(rows: list[dict[str, Any]], out_dir: str | Path) -> dict[str, Path]:
    """``lambert_tune.md`` and ``lambert_tune.csv`` under ``out_dir``."""
    return write_tables(out_dir, "lambert_tune", to_markdown(rows), to_csv(rows))


def main(argv: list[str] | None = None) -> int:
    """``python -m studies.lambert_tune ROOT [--out DIR]``."""
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("root", help="folder of the sweep's runs (searched recursively)")
    p.add_argument("--out", default="outputs/lambert_tune", help="where the table goes")
    args = p.parse_args(argv)
    rows = tune_table(args.root)
    paths = write_table(rows, args.out)
    print(to_markdown(rows))
    print(f"written: {', '.join(str(v) for v in paths.values())}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
