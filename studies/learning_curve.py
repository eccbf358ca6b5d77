"""Learning curve of the normal CNN: test MAE against the number of training lines and
against training time, beside the constant (training-mean) prediction.

    python -m studies.learning_curve --n-train 8,16,32 --scale demo
    make learning-curve SCALE=demo LC_N_TRAIN=8,16,32

**The test lines stay the same.** ``data.survey.plan.n_train`` alone would not do: the
planner spreads all lines of a set evenly over the terrain and interleaves the test lines
with the training lines (:func:`sss2bathy.sim.plan.plan_survey`), so the test lines move
with the number of training lines (at demo scale the main test lines sit at y = 38.0 /
62.0 m for 8 training lines, 38.9 / 61.1 m for 16, 39.4 / 60.6 m for 32), and the
vehicle motion drawn line after line changes with them. The harness therefore generates
**one** survey with the largest count (under its own name, ``<survey>_lc<N>``, so the
demo's cached survey is left alone) and each run trains on a seeded, nested subset of its
training lines (``data.n_train_lines``, :class:`~sss2bathy.data.windows.SidescanWindowDataModule`):
``n_train`` counts the survey's training lines a run uses, validation lines included, as
``plan.n_train`` does.

Runs go one at a time (``torch_threads`` passed through, ``OMP_NUM_THREADS`` set) into
``<out>/runs/n_train_<N>/``; each leaves ``learning_curve_run.json`` (its ``n_train`` and
the run's wall seconds). The reader takes from each run folder ``metrics.json`` (test MAE
per test set and the constant prediction's, ``data/n_train_lines``), ``metric_curve.csv``
(training seconds: the fit's wall time minus validation) and writes
``<out>/learning_curve.{md,csv,png}``. ``--read-only`` only reads and writes.
"""

from __future__ import annotations

import argparse
import csv
import io
import json
import math
import os
import subprocess
import sys
import time
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

from sss2bathy.utils.atomic import atomic_write_text, save_figure
from studies.tables import csv_value, markdown_table, read_json_object, to_csv, write_tables

RUN_RECORD = "learning_curve_run.json"
STEM = "learning_curve"  # learning_curve.{md,csv,png}
COLUMNS = (
    "n_train", "n_fit_lines", "n_val_lines", "train_s", "fit_wall_s", "run_s", "dataset",
    "mae", "constant_mae", "skill", "run_dir",
)  # fmt: skip


# ------------------------------------------------------------------------- running
def parse_counts(text: str) -> list[int]:
    """``"8,16,32"`` -> ``[8, 16, 32]`` (sorted, unique, each >= 2)."""
    try:
        counts = sorted({int(t) for t in str(text).split(",") if t.strip()})
    except ValueError as exc:
        raise ValueError(f"--n-train: expected integers like 8,16,32, found {text!r}") from exc
    if not counts or counts[0] < 2:
        raise ValueError(f"--n-train: expected integers >= 2 like 8,16,32, found {text!r}")
    return counts


def run_command(
    n_train: int,
    survey_n_train: int,
    survey_name: str,
    scale: str,
    run_dir: Path,
    torch_threads: int,
    overrides: Sequence[str] = (),
) -> list[str]:
    """The ``sss2bathy.cli.train`` command of one point of the curve."""
    if not 2 <= n_train <= survey_n_train:
        raise ValueError(f"n_train: expected 2 <= n_train <= {survey_n_train}, found {n_train}")
    return [
        sys.executable, "-m", "sss2bathy.cli.train", "experiment=cnn", f"scale={scale}",
        f"data.survey.plan.n_train={survey_n_train}", f"data.survey.name={survey_name}",
        f"data.n_train_lines={n_train}", f"torch_threads={torch_threads}",
        f"hydra.run.dir={run_dir}", "extras.print_config=false",
        "trainer.enable_progress_bar=false", *overrides,
    ]  # fmt: skip


def run_learning_curve(
    counts: Sequence[int],
    out_dir: Path,
    scale: str = "demo",
    torch_threads: int = 1,
    survey_name: str | None = None,
    overrides: Sequence[str] = (),
    timeout_s: float | None = None,
) -> list[Path]:
    """Train the CNN experiment once per count in ``counts`` (one at a time) on one survey
    generated with ``max(counts)`` training lines; return the run folders."""
    counts = sorted(set(counts))
    survey_n = counts[-1]
    name = survey_name or f"synthetic_d1_{scale}_lc{survey_n}"
    env = dict(os.environ, OMP_NUM_THREADS=str(torch_threads), HYDRA_FULL_ERROR="1")
    env.setdefault("SSS2BATHY_ROOT", str(Path.cwd()))
    runs = []
    for n in counts:
        run_dir = (Path(out_dir) / "runs" / f"n_train_{n:03d}").resolve()
        cmd = run_command(n, survey_n, name, scale, run_dir, torch_threads, overrides)
        print(f"learning curve: n_train={n}: {' '.join(cmd[1:])}", flush=True)
        start = time.perf_counter()
        proc = subprocess.run(cmd, env=env, timeout=timeout_s)
        if proc.returncode != 0:
            raise RuntimeError(
                f"learning curve: the run with n_train={n} failed (exit {proc.returncode}); "
                f"see {run_dir}"
            )
        record = {"n_train": n, "survey_n_train": survey_n, "survey_name": name,
                  "run_s": time.perf_counter() - start}  # fmt: skip
        atomic_write_text(run_dir / RUN_RECORD, json.dumps(record, indent=2))
        runs.append(run_dir)
    return runs


# ------------------------------------------------------------------------- reading


def _last_curve_row(path: Path) -> dict[str, float]:
    if not path.is_file():
        raise ValueError(f"{path}: expected the run's metric curve, found none")
    rows = list(csv.DictReader(io.StringIO(path.read_text())))
    if not rows or "train_s" not in rows[-1] or "wall_s" not in rows[-1]:
        raise ValueError(f"{path}: expected rows with train_s and wall_s, found {len(rows)} rows")
    return {k: float(rows[-1][k]) for k in ("train_s", "wall_s")}


def _count(metrics: Mapping[str, Any], key: str) -> int | str:
    value = metrics.get(key)
    return int(value) if value is not None else ""


def read_run(run_dir: str | Path) -> list[dict[str, Any]]:
    """One row per test set of a finished learning-curve run (``COLUMNS``)."""
    run_dir = Path(run_dir)
    record = read_json_object(run_dir / RUN_RECORD)
    metrics = read_json_object(run_dir / "metrics.json")
    curve = _last_curve_row(run_dir / "metric_curve.csv")
    if not isinstance(record.get("n_train"), int):
        raise ValueError(
            f"{run_dir / RUN_RECORD}: expected an integer 'n_train', found {record.get('n_train')!r}"
        )
    # n_lat MAE keys: test/<set>/nlat_mae (run records before the nlat_ names: .../mae)
    maes = {
        k.split("/")[1]: float(v) for k, v in metrics.items() if k.startswith("test/")
        and k.count("/") == 2 and k.endswith(("/nlat_mae", "/mae"))
    }  # fmt: skip
    sets = sorted(maes)
    if not sets:
        raise ValueError(
            f"{run_dir / 'metrics.json'}: expected test/<set>/nlat_mae keys, found none"
        )
    rows = []
    for name in sets:
        mae = maes[name]
        const = metrics.get(
            f"test/{name}/constant/nlat_mae", metrics.get(f"test/{name}/constant/mae")
        )
        if const is None:
            raise ValueError(
                f"{run_dir / 'metrics.json'}: expected 'test/{name}/constant/nlat_mae' (the "
                "constant prediction, written by CNNTableWriter), found none"
            )
        const = float(const)
        rows.append(
            {
                "n_train": record["n_train"],
                "n_fit_lines": _count(metrics, "data/n_train_lines"),
                "n_val_lines": _count(metrics, "data/n_val_lines"),
                "train_s": curve["train_s"],
                "fit_wall_s": curve["wall_s"],
                "run_s": float(record.get("run_s", math.nan)),
                "dataset": name,
                "mae": mae,
                "constant_mae": const,
                "skill": mae / const if const > 0 else math.nan,
                "run_dir": str(run_dir),
            }
        )
    return rows


def read_runs(run_dirs: Sequence[str | Path]) -> list[dict[str, Any]]:
    """Rows of every run, sorted by ``n_train`` then test set; the runs must share their
    test sets (the same survey) and differ in ``n_train``."""
    rows, seen = [], {}
    for d in run_dirs:
        run_rows = read_run(d)
        n = run_rows[0]["n_train"]
        if n in seen:
            raise ValueError(f"{d}: n_train={n} was already read from {seen[n]}")
        seen[n] = d
        rows += run_rows
    sets = {r["run_dir"]: set() for r in rows}
    for r in rows:
        sets[r["run_dir"]].add(r["dataset"])
    first = next(iter(sets.values()))
    for run, names in sets.items():
        if names != first:
            raise ValueError(
                f"{run}: expected the test sets {sorted(first)} of the other runs, found "
                f"{sorted(names)} (the curve needs one survey for every run)"
            )
    return sorted(rows, key=lambda r: (r["n_train"], r["dataset"]))


# ------------------------------------------------------------------------- writing


def learning_curve_csv(rows: Sequence[Mapping[str, Any]]) -> str:
    return to_csv(({c: csv_value(r[c]) for c in COLUMNS} for r in rows), COLUMNS)


def learning_curve_markdown(rows: Sequence[Mapping[str, Any]]) -> str:
    sets = list(dict.fromkeys(r["dataset"] for r in rows))
    counts = sorted({r["n_train"] for r in rows})
    by = {(r["n_train"], r["dataset"]): r for r in rows}
    lines = [
        "# Normal CNN learning curve",
        "",
        "Test n_lat MAE against the number of the survey's training lines a run used "
        "(validation lines included; one survey, so the test lines are the same for every "
        "run). Each cell: CNN MAE / constant (training-mean) MAE = skill. Training time: "
        "the fit's wall seconds minus validation.",
        "",
    ]
    cells = []
    for n in counts:
        first = by[(n, sets[0])]
        cells.append([n, first["n_fit_lines"], f"{first['train_s']:.1f}"])
        for s in sets:
            r = by[(n, s)]
            cells[-1].append(f"{r['mae']:.4f} / {r['constant_mae']:.4f} = {r['skill']:.2f}")
    lines += markdown_table(
        ["n_train", "fit lines", "training s", *sets], cells, "r" * (3 + len(sets))
    )
    return "\n".join(lines) + "\n"


def plot_learning_curve(rows: Sequence[Mapping[str, Any]], path: Path) -> Path:
    """Two panels: MAE vs n_train and vs training seconds, a line per test set, its
    constant prediction dashed (the largest run's, the best estimate of the mean)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    sets = list(dict.fromkeys(r["dataset"] for r in rows))
    fig, axes = plt.subplots(1, 2, figsize=(11, 4))
    for k, name in enumerate(sets):
        rr = sorted((r for r in rows if r["dataset"] == name), key=lambda r: r["n_train"])
        colour = f"C{k}"
        for ax, key in zip(axes, ("n_train", "train_s"), strict=True):
            ax.plot([r[key] for r in rr], [r["mae"] for r in rr], "-o", color=colour,
                    label=f"{name}: CNN")  # fmt: skip
            ax.axhline(rr[-1]["constant_mae"], color=colour, ls="--", lw=1,
                       label=f"{name}: constant")  # fmt: skip
    axes[0].set_xlabel("training lines of the survey used (n_train)")
    axes[1].set_xlabel("training time (s, validation excluded)")
    for ax in axes:
        ax.set_ylabel("test n_lat MAE")
        ax.grid(alpha=0.3)
    axes[0].legend(fontsize=7)
    fig.suptitle("normal CNN learning curve", fontsize=10)
    fig.tight_layout()
    return save_figure(fig, path, dpi=110)


def write_learning_curve(
    rows: Sequence[Mapping[str, Any]], out_dir: str | Path
) -> tuple[Path, Path, Path]:
    """``learning_curve.{md,csv,png}`` in ``out_dir``."""
    if not rows:
        raise ValueError("rows: expected at least one learning-curve row, found none")
    paths = write_tables(out_dir, STEM, learning_curve_markdown(rows), learning_curve_csv(rows))
    png = Path(out_dir) / f"{STEM}.png"
    plot_learning_curve(rows, png)
    return paths["md"], paths["csv"], png


# ------------------------------------------------------------------------- CLI
def main(argv: Sequence[str] | None = None) -> Path:
    parser = argparse.ArgumentParser(
        prog="python -m studies.learning_curve",
        description="Train the CNN experiment for several training-line counts on one survey "
        "and plot test MAE vs lines and vs training time (module docstring).",
    )
    parser.add_argument("--n-train", default="8,16,32", help="training-line counts, e.g. 8,16,32")
    parser.add_argument("--scale", default="demo")
    parser.add_argument("--torch-threads", type=int, default=1)
    parser.add_argument("--out", default="outputs/learning_curve")
    parser.add_argument("--survey-name", default=None, help="default: synthetic_d1_<scale>_lc<N>")
    parser.add_argument("--timeout-s", type=float, default=None, help="per run")
    parser.add_argument(
        "--read-only", action="store_true", help="only read <out>/runs/* and write the outputs"
    )
    parser.add_argument("overrides", nargs="*", help="extra Hydra overrides for every run")
    args = parser.parse_args(argv)
    if args.torch_threads < 1:
        parser.error(f"--torch-threads: expected an integer >= 1, found {args.torch_threads}")
    out = Path(args.out)
    if args.read_only:
        runs = sorted(p.parent for p in (out / "runs").glob(f"*/{RUN_RECORD}"))
        if not runs:
            raise SystemExit(f"{out / 'runs'}: expected finished runs ({RUN_RECORD}), found none")
    else:
        try:
            counts = parse_counts(args.n_train)
        except ValueError as exc:
            parser.error(str(exc))
        runs = run_learning_curve(
            counts, out, args.scale, args.torch_threads, args.survey_name, args.overrides,
            args.timeout_s,
        )  # fmt: skip
    md, _, _ = write_learning_curve(read_runs(runs), out)
    print(md.read_text())
    print(f"learning curve written to {out}")
    return md


if __name__ == "__main__":
    main()
