"""Which lever cuts the normal CNN's low-frequency n_lat error: trained CNNs scored on unseen
seabed, the error split by scale (:func:`sss2bathy.eval.cnn_table.scale_split`).

    python -m studies.cnn_levers --run demo=outputs/runs/cnn/<stamp> \
        --run pretrain=outputs/runs/pretrain/<stamp> \
        --survey data/synthetic_d1_valsite_demo --survey data/synthetic_d1_site2_demo \
        --out outputs/studies/cnn_levers

Each ``--run LABEL=RUN_DIR`` is a CNN training run (its ``checkpoints/last.ckpt``, or
``--ckpt-name``), or ``--run LABEL=FILE`` one checkpoint or exported model (the
shipped one: ``sss2bathy/pretrained/normal_cnn.safetensors``; the
constant prediction of its skill is the training mean the run's ``metrics.json`` records, or
with ``--constant-from FOLDER[:SPLIT]`` the mean draped n_lat of those training lines).
Each ``--survey FOLDER[:SPLIT]`` is scored on its whole stitched lines (the prediction
SIREN-CNN-N2d uses, :func:`sss2bathy.data.cnn_normals.predict_normals`) against its draping:
pixel MAE and skill, the MAE of the error low-passed over boxes of a few sizes, the mean
|error| per line and side, and the slope of prediction on truth (shrinkage). Levers are
judged on the validation site and site2, never on d1's test lines (``:test`` of
synthetic_d1 crosses the training seabed of the demo CNN). Writes ``cnn_levers.md`` and
``.csv`` into ``--out``.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from studies.tables import fmt_cell, markdown_table, to_csv, write_tables

COLUMNS = (
    "run", "survey", "mae", "skill", "lp4x8_mae", "lp16x32_mae", "lp48x96_mae",
    "lp16x32_share", "swath16_mae", "line_side_bias", "slope", "lp_slope",
)  # fmt: skip


def run_constant(run_dir: Path) -> float | None:
    """The training-mean constant a CNN run recorded (``test/*/constant/value``), or None."""
    path = run_dir / "metrics.json"
    if not path.is_file():
        return None
    metrics = json.loads(path.read_text())
    metrics = metrics.get("metrics", metrics) if isinstance(metrics, dict) else {}
    values = [v for k, v in metrics.items() if str(k).endswith("/constant/value")]
    return float(values[0]) if values else None


def survey_lines(folder: Path, split: str | None) -> tuple[Any, list[str]]:
    """A survey folder and the names of its ``split`` (None: all lines)."""
    from sss2bathy.survey import Survey

    survey = Survey.load(folder)
    if split is not None and split not in survey.splits:
        raise ValueError(f"{folder}: expected a split of {sorted(survey.splits)}, found {split!r}")
    return survey, list(survey.splits[split]) if split else [ln.name for ln in survey.lines]


def mean_truth(folder: Path, split: str | None) -> float:
    """Mean draped n_lat over the valid bins of a survey's lines (a training mean)."""
    from sss2bathy.draping import DrapeConfig, drape_survey

    survey, names = survey_lines(folder, split)
    draped = drape_survey(survey, folder, DrapeConfig(), lines=names)
    total, count = 0.0, 0
    for name in names:
        d = draped[name]
        ok = d.valid & np.isfinite(d.n_lat)
        total += float(d.n_lat[ok].sum())
        count += int(ok.sum())
    return total / max(count, 1)


def heads(ckpt: Path, folder: Path, split: str | None) -> list[tuple[Any, Any, Any]]:
    """``(pred, truth, valid)`` per line and side of a survey (whole stitched lines)."""
    from sss2bathy.data.cnn_normals import predict_normals
    from sss2bathy.draping import DrapeConfig, drape_survey

    survey, names = survey_lines(folder, split)
    draped = drape_survey(survey, folder, DrapeConfig(), lines=names)
    predicted = predict_normals(ckpt, survey, folder, names)
    out = []
    for name in names:
        pred, _ = predicted[name]
        truth = draped[name]
        valid = truth.valid & np.isfinite(truth.n_lat) & np.isfinite(pred)
        for side in (0, 1):
            out.append((pred[:, side], truth.n_lat[:, side], valid[:, side]))
    return out


def score(ckpt: Path, folder: Path, split: str | None, constant: float | None) -> dict:
    """:func:`~sss2bathy.eval.cnn_table.scale_split` of one survey plus ``skill`` (pixel MAE
    over the constant's; NaN without a constant)."""
    from sss2bathy.eval.cnn_table import scale_split

    hs = heads(ckpt, folder, split)
    row = scale_split(hs)
    if constant is None:
        row["skill"] = math.nan
    else:
        err = np.concatenate([np.abs(constant - t[m]) for _, t, m in hs])
        row["skill"] = row["mae"] / float(err.mean())
    return row


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog="python -m studies.cnn_levers", description=__doc__.split("\n\n")[0]
    )
    parser.add_argument(
        "--run", action="append", required=True, help="LABEL=RUN_DIR or LABEL=CHECKPOINT_FILE"
    )
    parser.add_argument("--survey", action="append", required=True, help="FOLDER[:SPLIT]")
    parser.add_argument("--out", required=True, help="output folder")
    parser.add_argument("--ckpt-name", default="last.ckpt", help="checkpoint in checkpoints/")
    parser.add_argument(
        "--constant-from", default=None, help="FOLDER[:SPLIT]: the training lines' mean n_lat"
    )
    args = parser.parse_args(argv)
    fixed = None
    if args.constant_from:
        folder, _, split = args.constant_from.partition(":")
        fixed = mean_truth(Path(folder), split or None)
        print(f"constant prediction: {fixed:+.5f} (mean n_lat of {args.constant_from})")
    runs = []
    for text in args.run:
        label, sep, where = text.partition("=")
        path = Path(where)
        ckpt = path if path.is_file() else path / "checkpoints" / args.ckpt_name
        if not sep or not ckpt.is_file():
            print(
                f"error: --run {text}: expected LABEL=RUN_DIR with {ckpt} or LABEL=FILE",
                file=sys.stderr,
            )
            return 2
        folder = path.parent.parent if path.is_file() else path
        runs.append((label, ckpt, fixed if fixed is not None else run_constant(folder)))
    rows = []
    for label, ckpt, constant in runs:
        for text in args.survey:
            folder, _, split = text.partition(":")
            if not (Path(folder) / "survey.yaml").is_file():
                print(f"error: --survey {text}: expected a survey folder", file=sys.stderr)
                return 2
            row = score(ckpt, Path(folder), split or None, constant)
            rows.append({"run": label, "survey": f"{Path(folder).name}:{split or 'all'}", **row})
            print({k: fmt_cell(rows[-1][k]) for k in COLUMNS}, flush=True)
    md = "\n".join(
        markdown_table(
            COLUMNS,
            ([fmt_cell(r[c]) for c in COLUMNS] for r in rows),
            "ll" + "r" * (len(COLUMNS) - 2),
        )
    )
    paths = write_tables(
        args.out, "cnn_levers", md + "\n", to_csv(rows, COLUMNS, ignore_extra=True)
    )
    print(f"written: {paths}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
