"""What the fast CNN inference settings cost in accuracy (issue 20, Build 4): n_lat MAE of a
trained checkpoint's predictions against the draped truth on a survey's test lines, for
each inference precision (``data.normals.precision``) and overlap (``data.normals.overlap``), and
the mean absolute change from the fp32 / training-overlap predictions.

Predictions are recomputed in a temporary cache (the survey's own prediction cache is not
touched); the draped truth comes from the survey's draping cache (drapes if missing).
Scored on the bins valid in both the sonar-only mask and the draped mask.

    python -m benchmarks.cnn_inference_accuracy --ckpt outputs/runs/cnn/<run>/checkpoints/last.ckpt \\
        --survey-dir data/synthetic_d1_demo --overlaps 0.75 0.5 --precisions fp32 bf16
"""

from __future__ import annotations

import argparse
import json
import tempfile
import time
from collections.abc import Sequence
from pathlib import Path

import numpy as np
import torch


def accuracy(
    ckpt: str | Path,
    survey_dir: str | Path,
    split: str = "test",
    overlaps: Sequence[float | None] = (None, 0.5),
    precisions: Sequence[str] = ("fp32", "bf16"),
) -> dict:
    """``{"<precision>_overlap_<o>": {"mae", "mae_change_vs_reference", "cpu_s", ...}}``; the
    reference is the first precision at the first overlap."""
    from sss2bathy.data.cnn_normals import checkpoint_window_config, predict_normals
    from sss2bathy.draping import drape_survey
    from sss2bathy.survey import MASK_VALID, Survey

    survey_dir = Path(survey_dir)
    survey = Survey.load(survey_dir)
    names = [ln.name for ln in survey.split_lines(split)]
    draped = drape_survey(survey, survey_dir, lines=names)
    window = checkpoint_window_config(ckpt)
    rows: dict[str, dict] = {}
    reference: dict[str, np.ndarray] | None = None
    with tempfile.TemporaryDirectory() as cache:
        for precision in precisions:
            for overlap in overlaps:
                name = f"{precision}_overlap_{window['overlap'] if overlap is None else overlap:g}"
                c0 = time.process_time()
                out = predict_normals(
                    ckpt, survey, Path(cache) / name, names, draped, None, "cpu", precision, overlap
                )
                cpu_s = time.process_time() - c0
                err, change = [], []
                for n in names:
                    pred, mask = out[n]
                    ok = (mask == MASK_VALID) & np.isfinite(draped[n].n_lat)
                    err.append(np.abs(pred[ok] - draped[n].n_lat[ok]))
                    if reference is not None:
                        change.append(np.abs(pred[ok] - reference[n][ok]))
                if reference is None:
                    reference = {n: out[n][0] for n in names}
                err_all = np.concatenate(err)
                row = {"mae": float(err_all.mean()), "bins": int(err_all.size), "cpu_s": cpu_s}
                if change:
                    ch = np.concatenate(change)
                    row.update(mae_change_vs_reference=float(ch.mean()), max_change=float(ch.max()))
                rows[name] = row
    first = next(iter(rows.values()))
    for row in rows.values():
        row["mae_ratio"] = row["mae"] / first["mae"]
        row["cpu_ratio"] = row["cpu_s"] / first["cpu_s"]
    return {
        "ckpt": str(ckpt),
        "survey": survey.name,
        "lines": names,
        "training_window": window,
        "threads": torch.get_num_threads(),
        "variants": rows,
    }


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--ckpt", required=True)
    p.add_argument("--survey-dir", required=True)
    p.add_argument("--split", default="test")
    p.add_argument("--overlaps", nargs="+", type=float, default=[0.75, 0.5])
    p.add_argument("--precisions", nargs="+", default=["fp32", "bf16"])
    p.add_argument("--threads", type=int, default=0, help="torch threads; 0 = torch's")
    args = p.parse_args(argv)
    if args.threads > 0:
        torch.set_num_threads(args.threads)
    out = accuracy(args.ckpt, args.survey_dir, args.split, args.overlaps, args.precisions)
    print(json.dumps(out, indent=2))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
