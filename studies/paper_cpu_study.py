"""Paper-scale CPU study (issue 20): how soon a SIREN fit reaches its map on this CPU.

1. :func:`prepare_commands` prepares the ``synthetic_d1`` survey (``--survey``: another
   synthetic preset, e.g. ``synthetic_d1_valsite``, the validation site on which the budget
   schedule's settings are checked off the test lines) at a scale once, as two
   ``sss2bathy-prepare`` processes so the two costs are timed apart: the simulation
   (``drape=false``) and the draping on the MBES grid (a cache hit on the survey). A cached
   survey is reused (same config hash; :func:`survey_status` says beforehand, a dry compose).
2. :func:`fit_command` fits SIREN-GT-N2d and SIREN-Lambert with ``sss2bathy-train`` (one
   process, one fit at a time) at the paper schedule and at the project's time-budget
   schedule (``siren_schedule=paper|budget``: the fast schedule's decay spread over the
   budget, a quarter of the bins per step; ``fast``, sized in steps, on request), each for
   at most ``budget`` seconds of fitting
   (Lightning's ``trainer.max_time``), evaluating the map ``evals_per_epoch`` times an
   epoch (``trainer.val_check_interval``); ``metric_curve.csv`` of each run holds the map
   MAE against the fit's wall seconds (:mod:`sss2bathy.eval.metric_curve`).
3. :func:`time_to_quality` makes the table: per run its best MAE, the time to reach within
   10 % of the method's best MAE over all its runs, and the MAE of the map the fit holds at
   5, 10 and 20 minutes; :func:`to_markdown` / :func:`to_csv` / :func:`curve_figure` write
   ``paper_cpu_study.{md,csv,png}``.

Times are the curve's ``wall_s`` (seconds since the fit started, map evaluations included;
loading the survey before the fit is not in it, but is in the run's process wall time).

    python -m studies.paper_cpu_study --scale paper --budget-min 20
    python -m studies.paper_cpu_study --scale paper --data-dir /tmp/base/data --dry-run
    python -m studies.paper_cpu_study --survey synthetic_d1_valsite --methods siren_gt_n2d \
        --schedules budget --extra data.bin_fraction=1.0
    make paper-cpu-study [ARGS=...]
"""

from __future__ import annotations

import argparse
import json
import logging
import math
import os
import subprocess
import sys
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from sss2bathy.sim.config import SyntheticSurveyConfig
from sss2bathy.sim.prepare import cache_problem
from sss2bathy.utils.atomic import atomic_write_text, save_figure
from studies import tables
from studies.schedule_study import load_run_curve
from studies.tables import markdown_table, write_tables
from studies.xtf_study import run_logged, survey_config

log = logging.getLogger("sss2bathy.paper_cpu_study")

ROOT = Path(__file__).resolve().parents[1]
CONF = ROOT / "conf"
PRESET = "synthetic_d1"
METHODS: dict[str, str] = {
    "siren_gt_n2d": "SIREN-GT-N2d",
    "siren_lambert": "SIREN-Lambert",
    # the altimeter alone: what the sidescan must beat (--methods siren_heights_only)
    "siren_heights_only": "SIREN-Heights-only",
}
#: run unless ``--methods`` says otherwise
DEFAULT_METHODS = ("siren_gt_n2d", "siren_lambert")
#: budget = the fast schedule's decay spread over the time budget (conf/siren_schedule/budget.yaml)
SCHEDULES = ("paper", "fast", "budget")
#: run unless ``--schedules`` says otherwise: the paper's, and the project's pick for a time
#: budget (the fast schedule sized in steps is cut off by a slow machine; on request)
DEFAULT_SCHEDULES = ("paper", "budget")
KEY = "val/map_mae_m"
CLOCK = "wall_s"
#: "within 10 % of the best MAE"
WITHIN = 0.10
MARKS_MIN = (5.0, 10.0, 20.0)
COLUMNS = (
    "method",
    "schedule",
    "best_mae",
    "method_best_mae",
    "t_within_s",
    "final_mae",
    "map_mae",
    "evaluations",
    "steps",
    "fit_wall_s",
    "process_wall_s",
    "run",
)


# ---------------------------------------------------------------- pure parts


def mae_at(curve: Mapping[str, np.ndarray], t_s: float, budget_s: float) -> float:
    """MAE of the map the fit holds at ``t_s`` seconds: its latest evaluation at or before
    ``t_s``; NaN before the first evaluation or beyond the fit's ``budget_s`` (the fit was
    stopped: what it would hold then is unknown). A fit that finished its schedule earlier
    holds its last map until the budget; at the budget itself, the fit's final evaluation
    (made just after the time limit stopped it)."""
    if t_s > budget_s * (1 + 1e-6):
        return math.nan
    if t_s >= budget_s * (1 - 1e-6):  # the end of the budget: the map the fit ended with
        return float(np.asarray(curve[KEY])[-1])
    hit = np.nonzero(np.asarray(curve[CLOCK]) <= t_s)[0]
    return float(np.asarray(curve[KEY])[hit[-1]]) if hit.size else math.nan


def time_to_quality(
    curves: Mapping[tuple[str, str], Mapping[str, np.ndarray]],
    budget_s: float,
    within: float = WITHIN,
    marks_min: Sequence[float] = MARKS_MIN,
    budgets: Mapping[tuple[str, str], float] | None = None,
) -> list[dict[str, Any]]:
    """One row per ``(method, schedule)`` curve (``{"wall_s", "val/map_mae_m", "step"}`` arrays).

    ``t_within_s``: the first ``wall_s`` at which the MAE is within ``within`` of the
    method's best MAE over all its curves (``<= (1 + within) * best``; NaN if never);
    ``mae_<m>min``: :func:`mae_at` ``m`` minutes. ``budgets``: a curve's own budget where it
    is not ``budget_s`` (a longer reference fit, whose best then counts as the method's).
    """
    if not 0 <= within < 1:
        raise ValueError(f"within: expected a fraction in [0, 1), found {within}")
    budgets = dict(budgets or {})
    for key, b in [("budget_s", budget_s), *((f"budgets[{k}]", v) for k, v in budgets.items())]:
        if not b > 0:
            raise ValueError(f"{key}: expected a positive number of seconds, found {b}")
    best: dict[str, float] = {}
    for (method, _), c in curves.items():
        if len(c[KEY]) == 0:
            raise ValueError(f"curves[{method!r}]: expected at least one evaluation, found none")
        best[method] = min(best.get(method, math.inf), float(np.min(c[KEY])))
    rows = []
    for (method, schedule), c in curves.items():
        mae, wall = np.asarray(c[KEY], float), np.asarray(c[CLOCK], float)
        goal = (1 + within) * best[method]
        hit = np.nonzero(mae <= goal)[0]
        row: dict[str, Any] = {
            "method": method,
            "schedule": schedule,
            "best_mae": float(mae.min()),
            "method_best_mae": best[method],
            "t_within_s": float(wall[hit[0]]) if hit.size else math.nan,
            "final_mae": float(mae[-1]),
            "evaluations": int(mae.size),
            "steps": int(np.asarray(c["step"])[-1]),
            "fit_wall_s": float(wall[-1]),
        }
        for m in marks_min:
            row[mark_column(m)] = mae_at(c, 60.0 * m, budgets.get((method, schedule), budget_s))
        rows.append(row)
    return rows


def mark_column(minutes: float) -> str:
    return f"mae_{minutes:g}min"


def _f(value: Any, fmt: str = ".4f") -> str:
    if value is None or (isinstance(value, float) and not math.isfinite(value)):
        return "-"
    return format(value, fmt) if isinstance(value, float) else str(value)


def _marks(rows: Sequence[Mapping[str, Any]]) -> list[str]:
    return [k for k in (rows[0] if rows else {}) if k.startswith("mae_") and k.endswith("min")]


def to_markdown(
    rows: Sequence[Mapping[str, Any]],
    prepare: Mapping[str, Any],
    meta: Mapping[str, Any],
) -> str:
    """The study as Markdown: the preparation times, then the time-to-quality table."""
    marks = _marks(rows)
    lines = [
        f"# Paper-scale CPU study (scale={meta['scale']}, survey {meta['survey']})",
        "",
        f"Command: `{meta['command']}`  ",
        f"Revision {meta.get('revision', '?')}, {meta.get('machine', '')}, "
        f"budget {meta['budget_s'] / 60:g} min of fitting per run, "
        f"{meta['evals_per_epoch']} map evaluations per epoch, threads {meta['threads']}"
        + (
            f", stopped after {meta['holdout_stop']} evaluations without a lower held-out "
            "altimeter MAE (map: the SIREN of its lowest)."
            if meta.get("holdout_stop")
            else "."
        ),
        "",
        "## Survey preparation",
        "",
    ]
    lines += markdown_table(
        ["step", "process wall (s)", "in-process (s)", "note"],
        (
            [step, _f(p.get("wall_s"), ".1f"), _f(p.get("inner_s"), ".1f"), p.get("note", "")]
            for step, p in ((s, prepare.get(s, {})) for s in ("simulation", "draping"))
        ),
        "lrrl",
    )
    head = ["method", "schedule", "best MAE (m)", f"time to {WITHIN:.0%} of best (min)"]
    head += [f"MAE at {k[4:-3]} min" for k in marks]
    head += ["last eval MAE", "exported map MAE", "evals", "steps", "fit wall (min)"]
    lines += [
        "",
        "## Time to quality",
        "",
        f"Best = the method's lowest map MAE over its runs; time = the fit's wall clock "
        f"(map evaluations included) when the MAE first came within {WITHIN:.0%} of it. "
        "MAE at t = the map the fit held at t (its latest evaluation); '-' = none yet, or "
        "beyond the budget.",
        "",
    ]
    cells_of = []
    for r in rows:
        t = r["t_within_s"]
        cells = [
            METHODS.get(r["method"], r["method"]),
            r["schedule"],
            _f(r["best_mae"]),
            _f(t / 60 if math.isfinite(t) else math.nan, ".2f"),
            *(_f(r[k]) for k in marks),
            _f(r["final_mae"]),
            _f(r.get("map_mae", math.nan)),
            str(r["evaluations"]),
            str(r["steps"]),
            _f(r["fit_wall_s"] / 60, ".2f"),
        ]
        cells_of.append(cells)
    lines += markdown_table(head, cells_of, "ll" + "r" * (len(head) - 2))
    failed = meta.get("failed") or {}
    if failed:
        lines += ["", "Failed runs:", ""] + [f"- {k}: {v}" for k, v in failed.items()]
    return "\n".join(lines) + "\n"


def to_csv(rows: Sequence[Mapping[str, Any]]) -> str:
    return tables.to_csv(rows, list(COLUMNS) + _marks(rows), ignore_extra=True)


def curve_figure(
    curves: Mapping[tuple[str, str], Mapping[str, np.ndarray]], path: str | Path, title: str
) -> Path:
    """MAE against the fit's wall minutes, one panel per method, one line per schedule."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    methods = list(dict.fromkeys(m for m, _ in curves))
    fig, axes = plt.subplots(1, max(len(methods), 1), figsize=(5.5 * len(methods), 4))
    axes = np.atleast_1d(axes)
    for ax, method in zip(axes, methods, strict=True):
        best = min(float(np.min(c[KEY])) for (m, _), c in curves.items() if m == method)
        for (m, schedule), c in curves.items():
            if m == method:
                ax.plot(np.asarray(c[CLOCK]) / 60, c[KEY], marker="o", ms=3, label=schedule)
        ax.axhline(
            (1 + WITHIN) * best, color="0.4", ls="--", lw=1,
            label=f"{1 + WITHIN:g} x best ({(1 + WITHIN) * best:.3f} m)",
        )  # fmt: skip
        ax.set_yscale("log")
        ax.set_xlabel("fit wall time (min)")
        ax.set_ylabel("map MAE (m)")
        ax.set_title(METHODS.get(method, method))
        ax.grid(True, which="both", alpha=0.3)
        ax.legend(title="siren_schedule")
    fig.suptitle(title)
    fig.tight_layout()
    return save_figure(fig, path)


# ---------------------------------------------------------------- commands


def check_preset(preset: str) -> str:
    """``preset`` if ``conf/data/survey/<preset>.yaml`` is a synthetic survey preset (one the
    simulator makes: ``synthetic_*``), else ``ValueError`` naming what exists."""
    known = sorted(f.stem for f in (CONF / "data" / "survey").glob("synthetic_*.yaml"))
    if preset not in known:
        raise ValueError(
            f"survey: expected a synthetic survey preset, one of {known}, found {preset!r}"
        )
    return preset


def survey_status(scale: str, data_dir: str | Path, preset: str = PRESET) -> dict[str, Any]:
    """Whether ``data_dir`` already holds the survey (a dry compose: nothing is made).

    Returns ``{"name", "config_hash", "folder", "problem"}``; ``problem`` is ``None`` when
    the cached folder serves, else why not (missing, incomplete, stale hash, ...).
    """
    config = SyntheticSurveyConfig.from_mapping(survey_config(preset, scale))
    folder = Path(data_dir) / config.name
    key = config.hash()
    return {
        "name": config.name,
        "config_hash": key,
        "folder": str(folder),
        "problem": cache_problem(folder, key),
    }


def prepare_commands(
    scale: str,
    data_dir: str | Path,
    run_root: str | Path,
    preset: str = PRESET,
    sim_workers: int | None = None,
) -> dict[str, list[str]]:
    """``{"simulation": cmd, "draping": cmd}``: the survey without draping, then draped
    (the second finds the survey cached, so its time is the draping's). ``sim_workers``:
    the simulator's processes (``data.survey.workers``, not part of the cache key); None =
    the preset's."""
    if sim_workers is not None and not (isinstance(sim_workers, int) and sim_workers >= 1):
        raise ValueError(f"sim_workers: expected an integer >= 1 or None, found {sim_workers!r}")
    workers = [] if sim_workers is None else [f"data.survey.workers={sim_workers}"]
    base = [
        sys.executable,
        "-m",
        "sss2bathy.cli.prepare",
        f"data/survey={preset}",
        f"scale={scale}",
        f"paths.data_dir={data_dir}",
        f"paths.output_dir={Path(run_root) / 'prepare'}",
        "render=false",
        *workers,
    ]
    return {
        step: [*base, f"drape={'true' if step == 'draping' else 'false'}",
               f"hydra.run.dir={Path(run_root) / 'prepare' / step}"]
        for step in ("simulation", "draping")
    }  # fmt: skip


def fit_command(
    method: str,
    schedule: str,
    scale: str,
    data_dir: str | Path,
    run_dir: str | Path,
    budget_s: float,
    evals_per_epoch: int = 4,
    threads: int | None = None,
    seed: int = 42,
    extra: Sequence[str] = (),
    holdout_stop: int = 0,
    preset: str = PRESET,
) -> list[str]:
    """The ``sss2bathy-train`` command of one run: at most ``budget_s`` seconds of fitting
    (``trainer.max_time``), a map evaluation ``evals_per_epoch`` times an epoch, no logger;
    ``extra`` = further overrides.

    ``holdout_stop > 0``: stop once the held-out altimeter MAE (``val/holdout_alt_mae_m``, a
    signal without MBES; ``data.holdout``) has not improved for that many evaluations
    (Lightning's ``EarlyStopping``), and map the SIREN of its lowest value
    (``model.select_best=holdout_alt_mae``). 0: off. ``preset``: the survey
    (``data/survey=<preset>``, a synthetic preset of ``conf/data/survey``).
    """
    if method not in METHODS:
        raise ValueError(f"method: expected one of {sorted(METHODS)}, found {method!r}")
    if schedule not in SCHEDULES:
        raise ValueError(f"schedule: expected one of {list(SCHEDULES)}, found {schedule!r}")
    if not (isinstance(evals_per_epoch, int) and evals_per_epoch >= 1):
        raise ValueError(f"evals_per_epoch: expected an integer >= 1, found {evals_per_epoch!r}")
    if not budget_s > 0:
        raise ValueError(f"budget_s: expected a positive number of seconds, found {budget_s}")
    cmd = [
        sys.executable,
        "-m",
        "sss2bathy.cli.train",
        f"experiment={method}",
        f"data/survey={preset}",
        f"scale={scale}",
        f"siren_schedule={schedule}",
        f"seed={int(seed)}",
        "logger=none",
        "trainer.enable_progress_bar=false",
        f"paths.data_dir={data_dir}",
        # anything a run writes outside its run folder stays in the study's folder
        f"paths.output_dir={Path(run_dir).parent}",
        f"hydra.run.dir={run_dir}",
        "model.eval_every_n_epochs=1",
        f"++trainer.val_check_interval={1.0 / evals_per_epoch:.6g}",
        f"++trainer.max_time={{seconds:{max(int(round(budget_s)), 1)}}}",
        # siren_schedule=budget spreads its learning-rate decay over the same seconds
        *([f"scale.siren.budget_s={max(int(round(budget_s)), 1)}"] if schedule == "budget" else []),
        # Lightning ignores a stop request (the time limit) until min_epochs are done: an
        # epoch of a paper-scale survey can outlast the budget
        "++trainer.min_epochs=0",
    ]
    if not (isinstance(holdout_stop, int) and holdout_stop >= 0):
        raise ValueError(f"holdout_stop: expected an integer >= 0, found {holdout_stop!r}")
    if holdout_stop:
        cmd += [
            "model.select_best=holdout_alt_mae",
            "+callbacks.holdout_stop={_target_:pytorch_lightning.callbacks.EarlyStopping,"
            f"monitor:val/holdout_alt_mae_m,mode:min,patience:{holdout_stop},"
            "check_on_train_epoch_end:false}",
        ]
    if threads is not None:
        cmd.append(f"torch_threads={int(threads)}")
    return cmd + list(extra)


def _generation_seconds(folder: Path) -> float:
    """The simulator's own time (``survey.yaml`` metadata ``timing_s.generate_total``)."""
    import yaml

    try:
        meta = yaml.safe_load((folder / "survey.yaml").read_text()).get("metadata") or {}
        return float((meta.get("timing_s") or {}).get("generate_total", math.nan))
    except (OSError, AttributeError, TypeError, ValueError):
        return math.nan


def _draped_ready(folder: Path) -> bool:
    return any(folder.glob("draped/*/manifest.json")) or (folder / "draped/manifest.json").is_file()


def prepare_survey(
    scale: str,
    data_dir: Path,
    out: Path,
    threads: int | None,
    sim_workers: int | None = None,
    preset: str = PRESET,
) -> dict[str, dict[str, Any]]:
    """Run :func:`prepare_commands`; per step its process wall, in-process time and note."""
    status = survey_status(scale, data_dir, preset)
    folder = Path(status["folder"])
    draped_before = _draped_ready(folder)
    cmds = prepare_commands(scale, data_dir, out, preset, sim_workers)
    result: dict[str, dict[str, Any]] = {}
    for step, cmd in cmds.items():
        log.info("prepare %s: %s", step, " ".join(cmd))
        wall = run_logged(cmd, out / "prepare" / f"{step}.log", threads)
        result[step] = {"wall_s": wall, "command": " ".join(cmd[1:])}
    gen = _generation_seconds(folder)
    cached = status["problem"] is None
    result["simulation"]["inner_s"] = gen
    result["simulation"]["note"] = (
        f"cache hit (config hash {status['config_hash']}); in-process = when it was made"
        if cached
        else f"generated (config hash {status['config_hash']})"
    )
    result["draping"]["inner_s"] = math.nan
    result["draping"]["note"] = (
        "cache hit" if draped_before else "draped (process wall includes ~5 s of start-up)"
    )
    return result


def _map_mae(run_dir: Path) -> float:
    """MAE of the map a run exported (``metrics.json`` ``final/mae``: with
    ``select_best`` the SIREN it chose, not the last one); NaN without one."""
    try:
        return float(json.loads((run_dir / "metrics.json").read_text())["final/mae"])
    except (OSError, KeyError, TypeError, ValueError):
        return math.nan


def _revision() -> str:
    try:
        out = subprocess.run(
            ["git", "-C", str(ROOT), "rev-parse", "--short", "HEAD"],
            capture_output=True, text=True, check=True,
        )  # fmt: skip
        return out.stdout.strip()
    except (OSError, subprocess.CalledProcessError):
        return "?"


def parse_reference(text: str) -> tuple[tuple[str, str], Path]:
    """``METHOD:LABEL=RUN_DIR`` -> ``((method, label), run_dir)`` (``--reference``)."""
    head, sep, run_dir = text.partition("=")
    method, colon, label = head.partition(":")
    if not sep or not colon or not label or not run_dir:
        raise ValueError(f"--reference: expected METHOD:LABEL=RUN_DIR, found {text!r}")
    if method not in METHODS:
        raise ValueError(
            f"--reference {text!r}: expected a method in {sorted(METHODS)}, found {method!r}"
        )
    if not Path(run_dir).is_dir():
        raise ValueError(f"--reference {text!r}: expected a run folder, found no folder {run_dir}")
    return (method, label), Path(run_dir)


def run_study(
    out: str | Path,
    scale: str = "paper",
    budget_min: float = 20.0,
    data_dir: str | Path | None = None,
    methods: Sequence[str] = DEFAULT_METHODS,
    schedules: Sequence[str] = DEFAULT_SCHEDULES,
    evals_per_epoch: int = 4,
    threads: int | None = None,
    seed: int = 42,
    marks_min: Sequence[float] = MARKS_MIN,
    extra: Sequence[str] = (),
    command: str = "",
    holdout_stop: int = 0,
    sim_workers: int | None = None,
    references: Mapping[tuple[str, str], str | Path] | None = None,
    tabulate_only: bool = False,
    preset: str = PRESET,
) -> list[dict[str, Any]]:
    """Prepare once, fit every method x schedule (one at a time), write the table/figure.

    ``references``: ``{(method, label): run_dir}`` of further runs of a method made
    elsewhere (e.g. a longer fit, ``parse_reference``): each is a row with its own budget
    (its last evaluation) and its best counts as the method's best. ``tabulate_only``:
    neither prepare nor fit; tabulate every run already in ``out/runs``, of any method
    and schedule (and the references). ``preset``: the survey (:func:`check_preset`).
    """
    check_preset(preset)
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    data_dir = Path(data_dir) if data_dir is not None else ROOT / "data"
    budget_s = 60.0 * float(budget_min)
    if tabulate_only:
        prep_file = out / "prepare.json"
        prep = json.loads(prep_file.read_text()) if prep_file.is_file() else {}
    else:
        prep = prepare_survey(scale, data_dir, out, threads, sim_workers, preset)
        atomic_write_text(out / "prepare.json", json.dumps(prep, indent=2) + "\n")
    curves: dict[tuple[str, str], dict[str, np.ndarray]] = {}
    walls: dict[tuple[str, str], tuple[float, Path]] = {}
    budgets: dict[tuple[str, str], float] = {}
    failed: dict[str, str] = {}
    # tabulating: every run in out/runs, whichever methods and schedules made it
    for method in METHODS if tabulate_only else methods:
        for schedule in SCHEDULES if tabulate_only else schedules:
            run_dir = out / "runs" / f"{method}_{schedule}"
            if tabulate_only and not run_dir.is_dir():
                continue
            try:
                wall = math.nan
                if not tabulate_only:
                    cmd = fit_command(
                        method, schedule, scale, data_dir, run_dir, budget_s,
                        evals_per_epoch, threads, seed, extra, holdout_stop, preset,
                    )  # fmt: skip
                    log.info("fit %s %s: %s", method, schedule, " ".join(cmd))
                    wall = run_logged(cmd, run_dir.with_suffix(".log"), threads)
                curves[(method, schedule)] = load_run_curve(run_dir, KEY)
            except (RuntimeError, FileNotFoundError, ValueError) as err:
                log.error("%s %s failed: %s", method, schedule, err)
                failed[f"{method} {schedule}"] = str(err)
                continue
            walls[(method, schedule)] = (wall, run_dir)
    for (method, label), run_dir in (references or {}).items():
        if method not in METHODS:
            raise ValueError(
                f"references: expected a method in {sorted(METHODS)}, found {method!r}"
            )
        if (method, label) in curves:
            raise ValueError(f"references: {method} {label!r} is also a run of the study")
        curve = load_run_curve(run_dir, KEY)
        curves[(method, label)] = curve
        budgets[(method, label)] = float(curve[CLOCK][-1])
        walls[(method, label)] = (math.nan, Path(run_dir))
    rows = time_to_quality(curves, budget_s, WITHIN, marks_min, budgets) if curves else []
    for row in rows:
        wall, run_dir = walls[(row["method"], row["schedule"])]
        row["process_wall_s"] = wall
        row["run"] = str(run_dir.relative_to(out) if run_dir.is_relative_to(out) else run_dir)
        row["map_mae"] = _map_mae(run_dir)
    meta = {
        "scale": scale,
        "survey": survey_status(scale, data_dir, preset)["name"],
        "budget_s": budget_s,
        "evals_per_epoch": evals_per_epoch,
        "threads": "torch default" if threads is None else threads,
        "holdout_stop": holdout_stop,
        "revision": _revision(),
        "machine": f"{os.cpu_count()} CPUs",
        "command": command or f"python -m studies.paper_cpu_study --scale {scale}",
        "failed": failed,
    }
    write_tables(out, "paper_cpu_study", to_markdown(rows, prep, meta), to_csv(rows))
    if curves:
        curve_figure(curves, out / "paper_cpu_study.png", f"{meta['survey']}: map MAE vs time")
    return rows


def main(argv: list[str] | None = None) -> int:
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(message)s")
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--out", default=str(ROOT / "outputs" / "paper_cpu_study"))
    p.add_argument("--scale", default="paper", help="conf/scale/<scale>.yaml (tiny for tests)")
    p.add_argument("--budget-min", type=float, default=20.0, help="fitting minutes per run")
    p.add_argument("--data-dir", default=None, help="survey folders (default: <root>/data)")
    p.add_argument(
        "--survey",
        default=PRESET,
        help=f"synthetic survey preset, conf/data/survey/<name>.yaml (default {PRESET}; "
        "synthetic_d1_valsite: the validation site, to choose settings off the test lines)",
    )
    p.add_argument("--methods", nargs="+", default=list(DEFAULT_METHODS), choices=list(METHODS))
    p.add_argument(
        "--schedules", nargs="+", default=list(DEFAULT_SCHEDULES), choices=list(SCHEDULES)
    )
    p.add_argument("--evals-per-epoch", type=int, default=4)
    p.add_argument("--threads", type=int, default=None, help="torch threads (default: all)")
    p.add_argument("--seed", type=int, default=42)
    p.add_argument("--marks-min", type=float, nargs="+", default=list(MARKS_MIN))
    p.add_argument("--extra", nargs="*", default=[], help="further sss2bathy-train overrides")
    p.add_argument(
        "--holdout-stop",
        type=int,
        default=0,
        help="stop a fit after N evaluations without a lower held-out altimeter MAE (0: off)",
    )
    p.add_argument(
        "--sim-workers", type=int, default=None, help="simulator processes (default: preset's)"
    )
    p.add_argument(
        "--dry-run", action="store_true", help="say whether the survey is cached; print commands"
    )
    p.add_argument(
        "--reference",
        action="append",
        default=[],
        metavar="METHOD:LABEL=RUN_DIR",
        help="a further run of a method (e.g. a longer fit) whose best counts as the method's "
        "best, tabulated with its own time; repeatable",
    )
    p.add_argument(
        "--tabulate",
        action="store_true",
        help="neither prepare nor fit: tabulate the runs already in --out (and --reference)",
    )
    args = p.parse_args(argv)
    if args.budget_min <= 0:
        p.error(f"--budget-min: expected a positive number of minutes, found {args.budget_min}")
    references: dict[tuple[str, str], Path] = {}
    for text in args.reference:
        try:
            key, run_dir = parse_reference(text)
        except ValueError as err:
            p.error(str(err))
        if key in references:
            p.error(f"--reference {text!r}: {key[0]}:{key[1]} is given twice")
        references[key] = run_dir
    try:
        check_preset(args.survey)
    except ValueError as err:
        p.error(str(err))
    data_dir = Path(args.data_dir) if args.data_dir else ROOT / "data"
    if args.dry_run:
        status = survey_status(args.scale, data_dir, args.survey)
        print(json.dumps(status, indent=2))
        for cmd in prepare_commands(
            args.scale, data_dir, args.out, args.survey, args.sim_workers
        ).values():
            print(" ".join(cmd[1:]))
        for method in args.methods:
            for schedule in args.schedules:
                run_dir = Path(args.out) / "runs" / f"{method}_{schedule}"
                cmd = fit_command(
                    method, schedule, args.scale, data_dir, run_dir, 60 * args.budget_min,
                    args.evals_per_epoch, args.threads, args.seed, args.extra,
                    args.holdout_stop, args.survey,
                )  # fmt: skip
                print(" ".join(cmd[1:]))
        return 0
    rows = run_study(
        args.out, args.scale, args.budget_min, data_dir, args.methods, args.schedules,
        args.evals_per_epoch, args.threads, args.seed, args.marks_min, args.extra,
        command="python -m studies.paper_cpu_study " + " ".join(argv or sys.argv[1:]),
        holdout_stop=args.holdout_stop, sim_workers=args.sim_workers,
        references=references, tabulate_only=args.tabulate, preset=args.survey,
    )  # fmt: skip
    print((Path(args.out) / "paper_cpu_study.md").read_text())
    return 0 if rows else 1


if __name__ == "__main__":
    raise SystemExit(main())
