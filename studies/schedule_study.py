"""Schedule study: which SIREN schedule reaches the paper schedule's map error soonest.

Every SIREN run writes ``metric_curve.csv`` (:mod:`sss2bathy.eval.metric_curve`):
the map's ``val/map_mae_m`` (and ``val/map_grad_cs``) at each evaluation against its training
seconds. This module reads the runs of a study, takes the *reference* run's final MAE as
the goal (the paper's schedule, ``siren_schedule=paper``), finds when every run first
reaches it, and writes ``schedule_study.{md,json}`` and ``schedule_study.png`` (MAE over
training time, log scale).

Runs without ``metric_curve.csv`` (older runs) are read from their TensorBoard events
(``val/map_mae_m`` against the event wall times, validation included).

A reference run that was stopped before its last epoch is reported as such: its last
evaluated MAE is then the goal, and its wall time so far a lower bound.
"""

from __future__ import annotations

import argparse
import glob
import json
import math
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np
from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

from sss2bathy.eval.metric_curve import read_curve
from sss2bathy.utils.atomic import atomic_write_text, save_figure
from studies.tables import markdown_table

CURVE_FILE = "metric_curve.csv"


def load_run_curve(run_dir: str | Path, key: str = "val/map_mae_m") -> dict[str, np.ndarray]:
    """``{"epoch", "step", "train_s", "wall_s", key}`` arrays of one run (evaluations only).

    Raises:
        FileNotFoundError: neither ``metric_curve.csv`` nor TensorBoard events in ``run_dir``.
        ValueError: the run logged no ``key``.
    """
    run_dir = Path(run_dir)
    csv_path = run_dir / CURVE_FILE
    if csv_path.is_file():
        rows = [r for r in read_curve(csv_path) if math.isfinite(r.get(key, math.nan))]
        if not rows:
            raise ValueError(f"{csv_path}: expected rows with {key!r}, found none")
        return {
            name: np.array([r[name] for r in rows], dtype=float)
            for name in ("epoch", "step", "train_s", "wall_s", key)
        }
    events = sorted(
        glob.glob(str(run_dir / "tensorboard" / "**" / "events.out.tfevents.*"), recursive=True)
    )
    if not events:
        raise FileNotFoundError(
            f"{run_dir}: expected {CURVE_FILE} or tensorboard/events.out.tfevents.*, found neither"
        )
    acc = EventAccumulator(events[-1], size_guidance={"scalars": 0})
    acc.Reload()
    tags = acc.Tags().get("scalars", [])
    if key not in tags:
        raise ValueError(f"{events[-1]}: expected scalar {key!r}, found {sorted(tags)}")
    t0 = min(e.wall_time for tag in tags for e in acc.Scalars(tag)[:1])
    vals = acc.Scalars(key)
    epochs = {e.step: e.value for e in acc.Scalars("epoch")} if "epoch" in tags else {}
    wall = np.array([e.wall_time - t0 for e in vals])
    return {
        "epoch": np.array([epochs.get(e.step, math.nan) for e in vals], dtype=float),
        "step": np.array([e.step for e in vals], dtype=float),
        "train_s": wall,
        "wall_s": wall,
        key: np.array([e.value for e in vals], dtype=float),
    }


def time_to_reach(
    curve: Mapping[str, np.ndarray], goal: float, key: str = "val/map_mae_m", clock: str = "train_s"
) -> float:
    """First ``clock`` value at which ``curve[key] <= goal``; NaN if never reached."""
    hit = np.nonzero(np.asarray(curve[key]) <= goal)[0]
    return float(np.asarray(curve[clock])[hit[0]]) if hit.size else math.nan


def study(
    runs: Mapping[str, str | Path],
    reference: str,
    key: str = "val/map_mae_m",
    clock: str = "train_s",
    reference_epochs: int | None = None,
) -> dict[str, Any]:
    """Compare ``runs`` (``{label: run_dir}``) against ``runs[reference]``'s final ``key``.

    Args:
        runs: run folders by label.
        reference: label of the reference (paper-schedule) run.
        key: the map error to compare (lower is better).
        clock: ``"train_s"`` (training time) or ``"wall_s"``.
        reference_epochs: epochs the reference schedule has in full; if its curve ends
            earlier, the result says it was stopped (``reference_complete`` false).
    """
    if reference not in runs:
        raise ValueError(f"reference: expected one of {sorted(runs)}, found {reference!r}")
    if clock not in ("train_s", "wall_s"):
        raise ValueError(f"clock: expected 'train_s' or 'wall_s', found {clock!r}")
    curves = {label: load_run_curve(path, key) for label, path in runs.items()}
    ref = curves[reference]
    goal = float(ref[key][-1])
    goal_best = float(np.min(ref[key]))
    ref_time = float(ref[clock][-1])
    ref_epochs_done = int(ref["epoch"][-1]) + 1 if math.isfinite(ref["epoch"][-1]) else None
    complete = reference_epochs is None or (
        ref_epochs_done is not None and ref_epochs_done >= reference_epochs
    )
    rows = {}
    for label, c in curves.items():
        t = time_to_reach(c, goal, key, clock)
        rows[label] = {
            "run_dir": str(runs[label]),
            "final": float(c[key][-1]),
            "best": float(np.min(c[key])),
            "epochs": int(c["epoch"][-1]) + 1 if math.isfinite(c["epoch"][-1]) else None,
            "time_s": float(c[clock][-1]),
            "time_to_goal_s": t,
            "fraction_of_reference_time": t / ref_time if math.isfinite(t) else math.nan,
            "time_to_best_goal_s": time_to_reach(c, goal_best, key, clock),
        }
    return {
        "key": key,
        "clock": clock,
        "reference": reference,
        "goal": goal,
        "goal_best": goal_best,
        "reference_time_s": ref_time,
        "reference_epochs_done": ref_epochs_done,
        "reference_epochs_full": reference_epochs,
        "reference_complete": complete,
        "runs": rows,
        "curves": {label: {k: v.tolist() for k, v in c.items()} for label, c in curves.items()},
    }


def to_markdown(result: Mapping[str, Any]) -> str:
    """The study as a Markdown table."""
    key, ref = result["key"], result["reference"]
    lines = [
        "# SIREN schedule study",
        "",
        f"Goal: the reference run **{ref}**'s final {key} = {result['goal']:.4f}, reached after "
        f"{result['reference_time_s']:.0f} s of {result['clock']}; its best on the way: "
        f"{result['goal_best']:.4f}.",
    ]
    if not result["reference_complete"]:
        lines.append(
            f"The reference was stopped after {result['reference_epochs_done']} of "
            f"{result['reference_epochs_full']} epochs: its goal is its MAE so far and its "
            "time a lower bound of the full schedule's."
        )
    head = ["Run", "epochs", f"final {key}", "best", result["clock"], "time to goal (s)"]
    head += ["fraction of reference time", "time to reference best (s)"]
    cells = []
    for label, r in result["runs"].items():
        frac = r["fraction_of_reference_time"]
        cells.append(
            [label, r["epochs"], f"{r['final']:.4f}", f"{r['best']:.4f}", f"{r['time_s']:.0f}"]
            + [f"{r['time_to_goal_s']:.1f}", "-" if not math.isfinite(frac) else f"{frac:.3f}"]
            + [f"{r['time_to_best_goal_s']:.1f}"]
        )
    lines += ["", *markdown_table(head, cells, "l" + "r" * 7)]
    return "\n".join(lines) + "\n"


def plot(result: Mapping[str, Any], path: str | Path) -> Path:
    """MAE over training time (log x) of every run, the goal as a dashed line."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    key, clock = result["key"], result["clock"]
    fig, ax = plt.subplots(figsize=(7, 4.2))
    for label, c in result["curves"].items():
        t = np.maximum(np.asarray(c[clock]), 1e-3)
        ax.plot(t, c[key], marker="." if len(t) < 60 else None, label=label)
    ax.axhline(result["goal"], ls="--", color="k", lw=0.8, label=f"goal {result['goal']:.3f}")
    ax.set_xscale("log")
    ax.set_xlabel(f"{clock} (s)")
    ax.set_ylabel(f"map {key} (m)")
    ax.set_title("SIREN schedule study")
    ax.grid(alpha=0.3, which="both")
    ax.legend(fontsize=8)
    fig.tight_layout()
    return save_figure(fig, path, dpi=120)


def write_study(result: Mapping[str, Any], out_dir: str | Path) -> dict[str, Path]:
    """``schedule_study.md``, ``.json`` and ``.png`` under ``out_dir``."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    md, js = out / "schedule_study.md", out / "schedule_study.json"
    atomic_write_text(md, to_markdown(result))
    atomic_write_text(js, json.dumps(result, indent=1))
    return {"md": md, "json": js, "png": plot(result, out / "schedule_study.png")}


def main(argv: list[str] | None = None) -> int:
    """``python -m studies.schedule_study --run LABEL=DIR ... --reference LABEL``."""
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument(
        "--run",
        action="append",
        required=True,
        metavar="LABEL=DIR",
        help="a run folder and its label (repeat)",
    )
    p.add_argument("--reference", required=True, help="label of the paper-schedule run")
    p.add_argument(
        "--reference-epochs",
        type=int,
        default=None,
        help="epochs of the full reference schedule (to flag a stopped run)",
    )
    p.add_argument("--clock", default="train_s", choices=("train_s", "wall_s"))
    p.add_argument("--out", default="outputs/study")
    args = p.parse_args(argv)
    runs = {}
    for item in args.run:
        label, sep, path = item.partition("=")
        if not sep or not label or not path:
            p.error(f"--run: expected LABEL=DIR, found {item!r}")
        runs[label] = path
    result = study(runs, args.reference, clock=args.clock, reference_epochs=args.reference_epochs)
    paths = write_study(result, args.out)
    print(to_markdown(result))
    print(f"written: {', '.join(str(v) for v in paths.values())}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
