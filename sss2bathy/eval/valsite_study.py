"""The SIREN settings table of a *validation site*: every finished run below a folder,
scored alike.

``make valsite-study`` fits SIREN-GT-N2d, SIREN-CNN-N2d and SIREN-Lambert on
``data/survey=synthetic_d1_valsite`` (d1's recipe on another seabed, flown like d1's test
lines; neither training nor test data) at a few SIREN settings, one run per folder. This
module finds the finished runs (``map.npz``, ``run_info.json``, ``.hydra/config.yaml``:
:func:`sss2bathy.eval.lambert_tune.find_runs`), reads each run's variant and settings from
its config, scores every map on the **same cells** (the intersection of the runs' scored
areas, :func:`sss2bathy.eval.report.score_maps`) against the site's MBES grid, and writes
``valsite_study.md`` and ``valsite_study.csv``, grouped by variant, best MAE first.

Runs of more than one survey, or of a survey that is not a validation site (its name must
contain ``valsite``), are refused: the settings this table chooses must never be chosen on
the test lines the paper's tables report.

    python -m sss2bathy.eval.valsite_study outputs/valsite_study/demo
"""

from __future__ import annotations

import argparse
import csv
import io
import logging
from collections.abc import Mapping
from pathlib import Path
from typing import Any

from omegaconf import OmegaConf

from sss2bathy.eval.lambert_tune import find_runs
from sss2bathy.eval.report import _mbes_grid, load_map_run, score_maps
from sss2bathy.utils.atomic import atomic_write_text

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
METRICS = ("mae", "std", "grad_cs", "n_cells")


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


def study_table(root: str | Path) -> list[dict[str, Any]]:
    """One row per run below ``root``: its settings, its held-out altimeter MAE, the metrics
    on the common cells and its folder; grouped by variant, best MAE first.

    Raises:
        FileNotFoundError: no finished run, or the site's MBES grid is missing.
        ValueError: runs of several surveys or of one that is not a validation site, or a
            map off the MBES grid.
    """
    root = Path(root)
    runs = find_runs(root)
    if not runs:
        raise FileNotFoundError(f"{root}: expected finished SIREN runs (map.npz), found none")
    surveys = {(r.info.get("data_dir"), r.info.get("survey_name")) for r in runs}
    if len(surveys) != 1:
        raise ValueError(f"{root}: expected runs of one survey, found {sorted(map(str, surveys))}")
    name = str(runs[0].info.get("survey_name"))
    if SITE_MARK not in name:
        raise ValueError(
            f"{root}: survey_name: expected a validation site (a name with {SITE_MARK!r}, "
            f"e.g. data/survey=synthetic_d1_valsite), found {name!r}"
        )
    truth = _mbes_grid(runs[0])
    if truth is None:
        raise FileNotFoundError(
            f"{runs[0].path}: expected the MBES grid of survey {name!r} under data_dir "
            f"{runs[0].info.get('data_dir')!r}, found none"
        )
    settings, holdout, maps = {}, {}, []
    for run in runs:
        label = str(run.path.relative_to(root))
        settings[label] = run_settings(run.info["config"], where=str(run.path))
        holdout[label] = run.metrics.get("final/holdout_alt_mae", float("nan"))
        loaded = load_map_run(label, run, truth)
        if loaded is None:
            raise ValueError(f"{run.path}/map.npz: expected a map on the MBES grid, found another")
        maps.append(loaded)
    scores, _ = score_maps(maps, truth)
    rows = [
        {
            **settings[k],
            **{m: scores[k][m] for m in METRICS},
            "holdout_alt_mae": holdout[k],
            "run": k,
        }
        for k in scores
    ]
    return sorted(rows, key=lambda r: (str(r["variant"]), r["mae"]))


def _fmt(value: Any) -> str:
    return f"{value:.3g}" if isinstance(value, float) else str(value)


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
        "| "
        + " | ".join([*columns, "MAE (m)", "STD (m)", "gradient CS", "held-out alt. MAE (m)"])
        + " | cells | run |",
        "|" + "---|" * len(columns) + "---:|---:|---:|---:|---:|---|",
    ]
    for r in rows:
        cells = [_fmt(r[c]) for c in columns]
        cells += [f"{r['mae']:.3f}", f"{r['std']:.3f}", f"{r['grad_cs']:.3f}"]
        cells += [f"{r['holdout_alt_mae']:.3f}", str(r["n_cells"])]
        md.append("| " + " | ".join([*cells, r["run"]]) + " |")
    return "\n".join(md) + "\n"


def to_csv(rows: list[dict[str, Any]]) -> str:
    """CSV of :func:`study_table` rows."""
    buf = io.StringIO()
    fields = [*(c for c, _ in SETTINGS), *METRICS, "holdout_alt_mae", "run"]
    writer = csv.DictWriter(buf, fieldnames=fields, lineterminator="\n")
    writer.writeheader()
    writer.writerows(rows)
    return buf.getvalue()


def main(argv: list[str] | None = None) -> int:
    """``python -m sss2bathy.eval.valsite_study ROOT [--out DIR]``."""
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("root", help="folder of the study's runs (searched recursively)")
    p.add_argument("--out", default=None, help="where the table goes (default: ROOT)")
    args = p.parse_args(argv)
    rows = study_table(args.root)
    out = Path(args.out or args.root)
    out.mkdir(parents=True, exist_ok=True)
    atomic_write_text(out / "valsite_study.md", to_markdown(rows))
    atomic_write_text(out / "valsite_study.csv", to_csv(rows))
    print(to_markdown(rows))
    print(f"written: {out / 'valsite_study.md'}, {out / 'valsite_study.csv'}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
