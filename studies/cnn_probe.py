"""Where a trained normal CNN is wrong on a survey: n_lat error against the draped MBES truth,
beside a constant prediction, overall and per seabed material (the simulator's truth), with
the mean signed error (bias) of each.

    python -m studies.cnn_probe CKPT data/synthetic_d1_demo:test data/synthetic_d2_demo \
        --constant -0.019

Each survey is ``FOLDER[:SPLIT]`` (no split: all its lines). The prediction is the one
SIREN-CNN-N2d uses (:func:`sss2bathy.data.cnn_normals.predict_normals`, sidescan only, cached);
the truth is the survey's draping (MBES) where its mask and the prediction are both valid.
Per-material rows need the simulator's ``true_material`` per bin (synthetic surveys); other
surveys get the overall row only.

This is how the lake-bed bias of the demo CNN was traced to an **altitude prior** (README →
CNN): the same lake bed generated 4.5 m deeper or 2.5 m shallower moves the bias on every
material alike, i.e. the network reads the altitude (which, over a hull-mounted survey of
hills, tells which way the seabed falls away) rather than the sediment.
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from sss2bathy.data.cnn_normals import predict_normals
from sss2bathy.draping import DrapeConfig, drape_survey
from sss2bathy.survey import Survey


def _parse_target(text: str) -> tuple[Path, str | None]:
    folder, _, split = text.partition(":")
    return Path(folder), (split or None)


def _accumulate(acc: dict[Any, list[float]], key: Any, err: np.ndarray, const_err: np.ndarray):
    row = acc.setdefault(key, [0.0, 0.0, 0.0, 0.0])
    row[0] += err.size
    row[1] += float(err.sum())
    row[2] += float(np.abs(err).sum())
    row[3] += float(np.abs(const_err).sum())


def probe_survey(
    ckpt: str | Path,
    folder: str | Path,
    split: str | None,
    constant: float,
    window_cfg: dict[str, Any] | None = None,
) -> dict[str, dict[str, float]]:
    """``{row: {n, bias, mae, constant_mae, skill}}`` for one survey; rows ``all`` and, where
    the survey has the simulator's truth materials, ``material:<name>``. ``window_cfg``:
    the prediction windows (None: the checkpoint's training windows)."""
    folder = Path(folder)
    survey = Survey.load(folder)
    if split is not None and split not in survey.splits:
        raise ValueError(f"{folder}: expected a split of {sorted(survey.splits)}, found {split!r}")
    names = list(survey.splits[split]) if split else [ln.name for ln in survey.lines]
    draped = drape_survey(survey, folder, DrapeConfig(), lines=names)
    predicted = predict_normals(ckpt, survey, folder, names, window_cfg=window_cfg)
    material_names = survey.metadata.get("materials")  # the simulator's class names
    acc: dict[Any, list[float]] = {}
    for name in names:
        pred, _ = predicted[name]
        truth = draped[name]
        ok = truth.valid & np.isfinite(truth.n_lat) & np.isfinite(pred)
        err = (pred - truth.n_lat)[ok]
        const_err = (constant - truth.n_lat)[ok]
        _accumulate(acc, "all", err, const_err)
        mat = survey.line(name).extras.get("true_material")
        if mat is not None:
            mat = np.asarray(mat)[ok]
            for k in np.unique(mat):
                sel = mat == k
                known = isinstance(material_names, list) and int(k) < len(material_names)
                label = material_names[int(k)] if known else int(k)
                _accumulate(acc, f"material:{label}", err[sel], const_err[sel])
    out = {}
    for key, (n, s, a, c) in acc.items():
        if n == 0:
            continue
        out[key] = {
            "n": int(n),
            "bias": s / n,
            "mae": a / n,
            "constant_mae": c / n,
            "skill": (a / c) if c > 0 else float("nan"),
        }
    return out


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog="python -m studies.cnn_probe", description=__doc__.split("\n\n")[0]
    )
    parser.add_argument("ckpt", help="a NormalCNNModule checkpoint")
    parser.add_argument("surveys", nargs="+", help="survey folders, FOLDER[:SPLIT]")
    parser.add_argument(
        "--constant", type=float, default=0.0, help="the constant prediction (training mean)"
    )
    args = parser.parse_args(argv)
    if not Path(args.ckpt).is_file():
        print(f"error: ckpt: expected a checkpoint file, found {args.ckpt}", file=sys.stderr)
        return 2
    print("| survey | bins | rows | n | bias | MAE | constant MAE | skill |")
    print("|---|---|---|---:|---:|---:|---:|---:|")
    for text in args.surveys:
        folder, split = _parse_target(text)
        if not (folder / "survey.yaml").is_file():
            print(f"error: {text}: expected a survey folder with survey.yaml", file=sys.stderr)
            return 2
        for key, row in probe_survey(args.ckpt, folder, split, args.constant).items():
            print(
                f"| {folder.name} | {split or 'all'} | {key} | {row['n']} | {row['bias']:+.4f} "
                f"| {row['mae']:.4f} | {row['constant_mae']:.4f} | {row['skill']:.2f} |"
            )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
