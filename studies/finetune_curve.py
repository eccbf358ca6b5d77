"""Fine-tuning curve: test skill of the normal CNN on a new site against the number of that
site's lines it was trained on, starting from a trained CNN (``model.init``) and from
scratch.

    python -m studies.finetune_curve --model pretrained --site synthetic_d1_site2 --scale demo
    python -m studies.finetune_curve --model RUN.safetensors --counts 0,2,4 --scale tiny

The question of a user with some multibeam: a CNN trained elsewhere (the shipped one,
``--model pretrained``) scored as it is on the site (0 lines), then fine-tuned on 2, 4, 8
of the site's draped lines, beside the same network trained from random weights on the same
lines. Every run is ``sss2bathy-train experiment=cnn data/survey=<site>`` with the model's
network, input channels and sonar-only mask (``python -m sss2bathy.pretrained overrides``),
the scale's epochs and learning rate, tested on the site's test lines only
(``data.test_surveys=[]``); the 0-line point is ``train=false`` (the model tested as it is).

**One survey, fixed test lines.** As in :mod:`studies.learning_curve`, the site is generated
once with the largest count of training lines (under its own name, ``<site>_<scale>_ft<N>``,
so the site's usual cache is left alone) and each run takes a seeded, nested subset of them
(``data.n_train_lines``: validation lines included, at least 2). **Skill** is the CNN's
test n_lat MAE over the MAE of predicting one constant, the training lines' mean, of the
run with the most lines (the best estimate of the site's mean; the same denominator for
every row, so rows compare by MAE).

Runs go one at a time (``--torch-threads``, ``OMP_NUM_THREADS`` set) into
``<out>/runs/<start>_<NN>/`` with a ``finetune_run.json`` record; ``finetune_curve.{md,csv,png}``
go to ``<out>``; ``--read-only`` only reads the runs and writes those.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import subprocess
import sys
import time
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

from sss2bathy.data.cnn_model_file import sha256
from sss2bathy.data.cnn_normals import check_cnn_model
from sss2bathy.pretrained import model_overrides
from sss2bathy.utils.atomic import atomic_write_text, save_figure
from studies.tables import csv_value, markdown_table, read_json_object, to_csv, write_tables

RUN_RECORD = "finetune_run.json"
STEM = "finetune_curve"
STARTS = ("pretrained", "scratch")
COLUMNS = (
    "start", "n_lines", "mae", "constant_mae", "skill", "run_mae_constant", "test_set",
    "run_s", "run_dir",
)  # fmt: skip
#: quiet runs that write what the reader needs (metrics.json) and no more
QUIET = ("extras.print_config=false", "trainer.enable_progress_bar=false", "logger=none")


# ------------------------------------------------------------------------- running
def parse_counts(text: str) -> list[int]:
    """``"0,2,4,8"`` -> ``[0, 2, 4, 8]`` (sorted, unique; 0 or >= 2, at least one >= 2)."""
    try:
        counts = sorted({int(t) for t in str(text).split(",") if t.strip()})
    except ValueError:
        raise ValueError(f"--counts: expected integers like 0,2,4,8, found {text!r}") from None
    if not counts or 1 in counts or counts[0] < 0 or counts[-1] < 2:
        raise ValueError(
            f"--counts: expected 0 and/or integers >= 2 (a run needs a training and a "
            f"validation line), at least one >= 2, like 0,2,4,8, found {text!r}"
        )
    return counts


def run_command(
    start: str,
    n_lines: int,
    model: Path,
    site: str,
    survey_lines: int,
    scale: str,
    run_dir: Path,
    torch_threads: int,
    overrides: Sequence[str] = (),
) -> list[str]:
    """The ``sss2bathy.cli.train`` command of one point: ``start`` pretrained (weights of
    ``model``) or scratch (its network, random weights) on ``n_lines`` of the site's
    ``survey_lines`` training lines (0: the model tested as it is)."""
    if start not in STARTS:
        raise ValueError(f"start: expected one of {STARTS}, found {start!r}")
    if start == "scratch" and n_lines == 0:
        raise ValueError("n_lines: a network trained from scratch needs lines, found 0")
    if n_lines != 0 and not 2 <= n_lines <= survey_lines:
        raise ValueError(f"n_lines: expected 0 or 2..{survey_lines}, found {n_lines}")
    cmd = [
        sys.executable, "-m", "sss2bathy.cli.train", "experiment=cnn", f"data/survey={site}",
        f"scale={scale}", f"data.survey.plan.n_train={survey_lines}",
        f"data.survey.name={survey_name(site, scale, survey_lines)}", "data.test_surveys=[]",
        f"torch_threads={torch_threads}", f"hydra.run.dir={run_dir}", *QUIET,
        *model_overrides(model),
    ]  # fmt: skip
    if start == "pretrained":
        cmd.append(f"model.init={model}")
    cmd.append(f"data.n_train_lines={n_lines if n_lines else 2}")
    if n_lines == 0:
        cmd.append("train=false")
    return cmd + list(overrides)


def survey_name(site: str, scale: str, survey_lines: int) -> str:
    """The site's survey with ``survey_lines`` training lines, under its own name."""
    return f"{site}_{scale}_ft{survey_lines}"


def run_finetune_curve(
    model: str | Path,
    counts: Sequence[int],
    out_dir: Path,
    site: str = "synthetic_d1_site2",
    scale: str = "demo",
    torch_threads: int = 1,
    overrides: Sequence[str] = (),
    timeout_s: float | None = None,
) -> list[Path]:
    """Every point of the curve, one run at a time; returns the run folders."""
    path = check_cnn_model(model, "--model").resolve()
    counts = sorted(set(counts))
    survey_lines = counts[-1]
    env = dict(os.environ, OMP_NUM_THREADS=str(torch_threads), HYDRA_FULL_ERROR="1")
    env.setdefault("SSS2BATHY_ROOT", str(Path.cwd()))
    runs = []
    for start in STARTS:
        for n in counts:
            if start == "scratch" and n == 0:
                continue
            run_dir = (Path(out_dir) / "runs" / f"{start}_{n:02d}").resolve()
            cmd = run_command(
                start, n, path, site, survey_lines, scale, run_dir, torch_threads, overrides
            )
            print(f"finetune curve: {start}, {n} lines: {' '.join(cmd[3:])}", flush=True)
            t0 = time.perf_counter()
            proc = subprocess.run(cmd, env=env, timeout=timeout_s)
            if proc.returncode != 0:
                raise RuntimeError(
                    f"finetune curve: the run {start} with {n} lines failed (exit "
                    f"{proc.returncode}); see {run_dir}"
                )
            record = {
                "start": start, "n_lines": n, "site": site, "scale": scale,
                "survey_lines": survey_lines, "model": str(path), "model_sha256": sha256(path),
                "run_s": time.perf_counter() - t0,
            }  # fmt: skip
            atomic_write_text(run_dir / RUN_RECORD, json.dumps(record, indent=2))
            runs.append(run_dir)
    return runs


# ------------------------------------------------------------------------- reading


def read_run(run_dir: str | Path) -> dict[str, Any]:
    """One row of a finished run: its start, line count, test set, MAE and the constant's."""
    run_dir = Path(run_dir)
    record = read_json_object(run_dir / RUN_RECORD)
    metrics = read_json_object(run_dir / "metrics.json")
    if record.get("start") not in STARTS or not isinstance(record.get("n_lines"), int):
        raise ValueError(
            f"{run_dir / RUN_RECORD}: expected 'start' in {STARTS} and an integer 'n_lines', "
            f"found {record.get('start')!r}, {record.get('n_lines')!r}"
        )
    sets = sorted(
        k.split("/")[1] for k in metrics
        if k.startswith("test/") and k.count("/") == 2 and k.endswith("/nlat_mae")
    )  # fmt: skip
    if len(sets) != 1:
        raise ValueError(
            f"{run_dir / 'metrics.json'}: expected the site's test lines as the one test set "
            f"(test/<set>/nlat_mae), found {sets}"
        )
    name = sets[0]
    const = metrics.get(f"test/{name}/constant/nlat_mae")
    if const is None:
        raise ValueError(
            f"{run_dir / 'metrics.json'}: expected 'test/{name}/constant/nlat_mae' (the "
            "constant prediction), found none"
        )
    return {
        "start": record["start"],
        "n_lines": record["n_lines"],
        "test_set": name,
        "mae": float(metrics[f"test/{name}/nlat_mae"]),
        "run_mae_constant": float(const),
        "run_s": float(record.get("run_s", math.nan)),
        "model": Path(str(record.get("model") or "")).name,
        "run_dir": str(run_dir),
    }


def read_runs(run_dirs: Sequence[str | Path]) -> list[dict[str, Any]]:
    """Rows of every run with the shared skill denominator (the constant MAE of the run
    with the most lines); the runs must share their test set and differ in (start, lines)."""
    rows = [read_run(d) for d in run_dirs]
    if not rows:
        raise ValueError("run_dirs: expected finished runs, found none")
    seen: dict[tuple[str, int], str] = {}
    for r in rows:
        key = (r["start"], r["n_lines"])
        if key in seen:
            raise ValueError(f"{r['run_dir']}: {key} was already read from {seen[key]}")
        seen[key] = r["run_dir"]
    sets = {r["test_set"] for r in rows}
    if len(sets) != 1:
        raise ValueError(f"run_dirs: expected one test set for every run, found {sorted(sets)}")
    most = max(rows, key=lambda r: (r["n_lines"], r["start"] == "scratch"))
    for r in rows:
        r["constant_mae"] = most["run_mae_constant"]
        r["skill"] = r["mae"] / r["constant_mae"] if r["constant_mae"] > 0 else math.nan
    return sorted(rows, key=lambda r: (STARTS.index(r["start"]), r["n_lines"]))


# ------------------------------------------------------------------------- writing


def finetune_csv(rows: Sequence[Mapping[str, Any]]) -> str:
    return to_csv(({c: csv_value(r[c]) for c in COLUMNS} for r in rows), COLUMNS)


def finetune_markdown(rows: Sequence[Mapping[str, Any]]) -> str:
    model = next((r["model"] for r in rows if r.get("model")), "")
    counts = sorted({r["n_lines"] for r in rows})
    by = {(r["start"], r["n_lines"]): r for r in rows}
    lines = [
        "# Fine-tuning curve of the normal CNN",
        "",
        f"Test n_lat MAE on `{rows[0]['test_set']}` against the number of the site's lines "
        "a run trained on (validation lines included; one survey, so the test lines are the "
        "same for every run), starting from the trained CNN"
        + (f" `{model}`" if model else "")
        + " and from random weights (the same network). Each cell: MAE / skill, skill = MAE "
        f"over the constant prediction's {rows[0]['constant_mae']:.4f} (the training mean "
        "of the run with the most lines). 0 lines: the trained CNN as it is.",
        "",
    ]
    cells = []
    for n in counts:
        row: list[Any] = [n]
        for start in STARTS:
            r = by.get((start, n))
            row.append("" if r is None else f"{r['mae']:.4f} / {r['skill']:.2f}")
        cells.append(row)
    lines += markdown_table(["lines", "from the trained CNN", "from scratch"], cells, "rrr")
    return "\n".join(lines) + "\n"


def plot_finetune_curve(rows: Sequence[Mapping[str, Any]], path: Path) -> Path:
    """Skill against the number of the site's lines, one line per start, the constant at 1."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6, 4))
    for k, start in enumerate(STARTS):
        rr = sorted((r for r in rows if r["start"] == start), key=lambda r: r["n_lines"])
        if rr:
            ax.plot([r["n_lines"] for r in rr], [r["skill"] for r in rr], "-o", color=f"C{k}",
                    label=f"from {'the trained CNN' if start == 'pretrained' else 'scratch'}")  # fmt: skip
    ax.axhline(1.0, color="0.5", ls="--", lw=1, label="constant (training mean)")
    ax.set_xlabel("the site's lines trained on")
    ax.set_ylabel("test skill (CNN MAE / constant MAE)")
    ax.set_title(f"fine-tuning on {rows[0]['test_set']}", fontsize=10)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    fig.tight_layout()
    return save_figure(fig, path, dpi=110)


def write_finetune_curve(
    rows: Sequence[Mapping[str, Any]], out_dir: str | Path
) -> tuple[Path, Path, Path]:
    """``finetune_curve.{md,csv,png}`` in ``out_dir``."""
    if not rows:
        raise ValueError("rows: expected at least one fine-tuning row, found none")
    paths = write_tables(out_dir, STEM, finetune_markdown(rows), finetune_csv(rows))
    png = plot_finetune_curve(rows, Path(out_dir) / f"{STEM}.png")
    return paths["md"], paths["csv"], png


# ------------------------------------------------------------------------- CLI
def main(argv: Sequence[str] | None = None) -> Path:
    parser = argparse.ArgumentParser(
        prog="python -m studies.finetune_curve",
        description="Test skill on a new site vs the number of its lines trained on, from a "
        "trained CNN and from scratch (module docstring).",
    )
    parser.add_argument("--model", default="pretrained", help="a .safetensors, .ckpt or pretrained")
    parser.add_argument("--site", default="synthetic_d1_site2", help="a data/survey preset")
    parser.add_argument("--counts", default="0,2,4,8", help="the site's line counts")
    parser.add_argument("--scale", default="demo")
    parser.add_argument("--torch-threads", type=int, default=1)
    parser.add_argument("--out", default="outputs/finetune_curve")
    parser.add_argument("--timeout-s", type=float, default=None, help="per run")
    parser.add_argument("--read-only", action="store_true", help="only read <out>/runs/*")
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
            counts = parse_counts(args.counts)
            runs = run_finetune_curve(
                args.model, counts, out, args.site, args.scale, args.torch_threads,
                args.overrides, args.timeout_s,
            )  # fmt: skip
        except (ValueError, FileNotFoundError) as err:
            parser.error(str(err))
    md, _, _ = write_finetune_curve(read_runs(runs), out)
    print(md.read_text())
    print(f"fine-tuning curve written to {out}")
    return md


if __name__ == "__main__":
    main()
