"""Scaling study: wall time and peak memory of each stage against the survey's size.

Surveys of 1x, 4x and 16x the demo's area *and* line count (``synthetic_d1`` at scale=demo:
120 m x 100 m, 36 lines, 4 pings/s at 1.5 m/s, 256 bins per side over 30 m), generated
cheaply (:func:`scaled_survey`: a smooth terrain, straight AUV lines 10 m above it, pings from
a flat-seabed return model — the costs measured do not depend on what the pings show) and
written as XTF files with :func:`sss2bathy.io.xtf.write_xtf` plus the terrain as a GeoTIFF
MBES grid. Area x k: sqrt(k) x the lines, each sqrt(k) x as long, so k x the pings; 16x is
about the paper's Dataset I in samples (350 m x 300 m, 57 lines at 12 pings/s, 512 bins).

Each stage runs in its own child process (:func:`measure`: its wall time and its peak
resident memory from ``os.wait4``; the memory after the imports is the baseline):

* ``import``: ``prepare_xtf_survey`` of the XTF files and the grid (the ``sss2bathy-map``
  import);
* ``drape``: :func:`sss2bathy.draping.drape_line` of every line on the MBES grid, one line
  at a time, one thread;
* ``cnn``: CNN inference (:func:`sss2bathy.data.cnn_normals.predict_waterfall`) of every
  line with the demo's network (width 8, 4 blocks) at random weights, 64-ping windows,
  overlap 0.75, one thread (the cost does not depend on the weights);
* ``siren``: ``sss2bathy-map method=siren_lambert`` on the imported survey (cached), one
  thread, ``--siren-steps`` and 3x as many steps: the difference gives the cost per step,
  the rest the fixed cost (table, map evaluation, files). The full fit's cost is
  fixed + per-step x the steps of the demo schedule at that size (6 epochs of
  pings / 16 steps), reported beside the measured runs.

Per stage the cost is fitted to ``a * size^b`` (least squares in log-log; ``b`` with its
standard error, 1 degree of freedom with three sizes). ``--long-line`` measures the import of
one long XTF line (50 MB and 500 MB, 4096 samples per side) for bounded memory; with
``--xtf-module FILE`` another ``sss2bathy/io/xtf.py`` (e.g. ``git show <rev>:...``) reads it,
to compare before and after a change.

    python -m studies.scaling_study --out outputs/scaling_study
    make scaling-study
    python -m studies.scaling_study --long-line --sizes-mb 50 500 --out outputs/scaling_study

Timings on a shared machine are noisy: repeats (``--repeats``) are interleaved by size and
the median is kept.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import resource
import shutil
import subprocess
import sys
import time
from collections.abc import Mapping, Sequence
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np

from studies.tables import fmt_cell, markdown_table, to_csv, write_tables

ROOT = Path(__file__).resolve().parents[1]
STAGES = ("import", "drape", "cnn", "siren")
ORIGIN = {"crs": "EPSG:32633", "easting": 680000.0, "northing": 6580000.0}
# the demo's synthetic_d1 (conf/scale/demo.yaml): area, lines, pings, bins
DEMO = {
    "size_m": (120.0, 100.0),
    "n_lines": 36,
    "speed_mps": 1.5,
    "ping_rate_hz": 4.0,
    "n_bins": 256,
    "max_range_m": 30.0,
    "altitude_m": 10.0,
    "depth_m": 13.0,
}
# the demo's SIREN schedule (conf/scale/demo.yaml): epochs x pings / batch_pings steps
DEMO_EPOCHS, DEMO_BATCH_PINGS = 6, 16


# ----------------------------------------------------------------------------- pure parts
def power_law(sizes: Sequence[float], costs: Sequence[float]) -> dict[str, float]:
    """Least-squares fit of ``cost = a * size^b`` in log-log: ``{"a", "b", "b_se"}``
    (``b_se``: the standard error of ``b``, NaN with fewer than 3 points).

    Raises:
        ValueError: fewer than 2 points, or a size or cost that is not positive.
    """
    x = np.log(np.asarray(sizes, dtype=np.float64))
    c = np.asarray(costs, dtype=np.float64)
    if x.size < 2 or x.size != c.size:
        raise ValueError(f"sizes, costs: expected >= 2 pairs, found {x.size} and {c.size}")
    if not (np.all(np.isfinite(x)) and np.all(c > 0)):
        raise ValueError(f"sizes, costs: expected positive values, found {sizes} {costs}")
    y = np.log(c)
    xm = x - x.mean()
    sxx = float(xm @ xm)
    if sxx == 0:
        raise ValueError(f"sizes: expected at least two different sizes, found {sizes}")
    b = float(xm @ (y - y.mean()) / sxx)
    a = float(math.exp(y.mean() - b * x.mean()))
    resid = y - (math.log(a) + b * x)
    se = math.sqrt(float(resid @ resid) / (x.size - 2) / sxx) if x.size > 2 else math.nan
    return {"a": a, "b": b, "b_se": se}


def survey_plan(k: float) -> dict[str, Any]:
    """The generated survey at ``k`` x the demo's area: sqrt(k) x its lines, each sqrt(k) x
    as long (so k x the pings)."""
    if not k > 0:
        raise ValueError(f"k: expected a positive area factor, found {k}")
    s = math.sqrt(k)
    w, h = DEMO["size_m"]
    n_lines = max(1, round(DEMO["n_lines"] * s))
    length = w * s
    n_pings = int(round(length / DEMO["speed_mps"] * DEMO["ping_rate_hz"]))
    return {
        "k": k,
        "size_m": (w * s, h * s),
        "n_lines": n_lines,
        "pings_per_line": n_pings,
        "pings": n_lines * n_pings,
    }


def siren_projection(
    wall_short: float, wall_long: float, steps_short: int, steps_long: int, pings: int
) -> dict[str, float]:
    """Per-step and fixed cost from two runs of ``steps_short`` and ``steps_long`` steps, and
    the demo schedule's fit (:data:`DEMO_EPOCHS` x ceil(pings / :data:`DEMO_BATCH_PINGS`)
    steps) projected from them."""
    if steps_long <= steps_short:
        raise ValueError(f"steps: expected long > short, found {steps_long} <= {steps_short}")
    per_step = (wall_long - wall_short) / (steps_long - steps_short)
    fixed = wall_short - per_step * steps_short
    steps = DEMO_EPOCHS * math.ceil(pings / DEMO_BATCH_PINGS)
    return {
        "per_step_s": per_step,
        "fixed_s": fixed,
        "schedule_steps": steps,
        "projected_s": fixed + per_step * steps,
    }


# ----------------------------------------------------------------------------- survey
def _terrain(size_m: tuple[float, float], seed: int, cell_m: float = 0.5):
    from sss2bathy.survey import BathyGrid

    rng = np.random.default_rng(seed)
    margin = DEMO["max_range_m"] + 5.0
    nx = int(math.ceil((size_m[0] + 2 * margin) / cell_m)) + 1
    ny = int(math.ceil((size_m[1] + 2 * margin) / cell_m)) + 1
    x = -margin + cell_m * np.arange(nx)
    y = -margin + cell_m * np.arange(ny)
    z = np.full((ny, nx), -DEMO["depth_m"], dtype=np.float64)
    for wavelength, amp in ((80.0, 1.5), (30.0, 0.6), (12.0, 0.25)):
        for _ in range(3):
            kx, ky = rng.normal(size=2)
            norm = math.hypot(kx, ky) or 1.0
            kx, ky = 2 * math.pi / wavelength * kx / norm, 2 * math.pi / wavelength * ky / norm
            phase = rng.uniform(0, 2 * math.pi)
            z += amp / 3 * np.sin(kx * x[None, :] + ky * y[:, None] + phase)
    return BathyGrid(z.astype(np.float32), float(x[0]), float(y[0]), cell_m, ORIGIN["crs"])


def _line(name: str, y: float, x0: float, n_pings: int, grid, t0: float, seed: int):
    from sss2bathy.geometry import attitude_to_rotation
    from sss2bathy.survey import SensorParams, SidescanLine

    dt = 1.0 / DEMO["ping_rate_hz"]
    t = t0 + dt * np.arange(n_pings)
    x = x0 + DEMO["speed_mps"] * dt * np.arange(n_pings)
    yy = np.full(n_pings, y)
    floor = grid.sample(x, yy)
    alt = np.full(n_pings, DEMO["altitude_m"])
    z = floor + alt
    zero = np.zeros(n_pings)
    B = DEMO["n_bins"]
    dr = DEMO["max_range_m"] / B
    range_m = (np.arange(B) + 0.5) * dr
    rng = np.random.default_rng(seed)
    r = range_m[None, None, :]
    a = alt[:, None, None]
    inten = np.where(r >= a, (a / r) ** 2, 0.0) * rng.exponential(1.0, (n_pings, 2, B))
    inten = inten + 0.02 * rng.exponential(1.0, (n_pings, 2, B))
    return SidescanLine(
        name=name,
        time_s=t,
        position=np.stack([x, yy, z], axis=1),
        rotation=attitude_to_rotation(np.full(n_pings, math.pi / 2), zero, zero),
        altitude_m=alt,
        intensity=inten.astype(np.float32),
        range_m=range_m,
        sensor=SensorParams(
            tilt_rad=math.radians(30.0),
            beam_width_rad=math.radians(60.0),
            frequency_hz=850e3,
            sound_speed_mps=1500.0,
        ),
    )


def scaled_survey(out: str | Path, k: float, seed: int = 1) -> Path:
    """Write the survey at ``k`` x the demo's area (:func:`survey_plan`) to ``out``:
    ``line_NNN.xtf`` and ``mbes.tif``; reused when ``out/plan.json`` matches."""
    from sss2bathy.io.xtf import write_xtf
    from sss2bathy.survey.georef import write_geotiff

    out = Path(out)
    plan = survey_plan(k)
    stamp = out / "plan.json"
    want = json.dumps({**plan, "seed": seed}, sort_keys=True)
    if stamp.is_file() and stamp.read_text() == want:
        return out
    if out.exists():
        shutil.rmtree(out)
    out.mkdir(parents=True)
    grid = _terrain(plan["size_m"], seed)
    write_geotiff(grid, out / "mbes.tif", origin=ORIGIN)
    w, h = plan["size_m"]
    spacing = h / plan["n_lines"]
    t0 = 0.0
    for i in range(plan["n_lines"]):
        y = (i + 0.5) * spacing
        line = _line(f"line_{i:03d}", y, 0.0, plan["pings_per_line"], grid, t0, seed * 1000 + i)
        write_xtf(line, out / f"line_{i:03d}.xtf", ORIGIN)
        t0 += plan["pings_per_line"] / DEMO["ping_rate_hz"] + 60.0
    stamp.write_text(want)
    return out


def long_line(path: str | Path, megabytes: float, samples: int = 4096, seed: int = 0) -> Path:
    """One straight XTF line of about ``megabytes`` MB (``samples`` uint16 samples per side
    per ping), written in segments of 2000 pings (bounded memory) and joined packet by packet
    behind the first segment's file header."""
    from sss2bathy.io.xtf import write_xtf
    from sss2bathy.survey import BathyGrid

    path = Path(path)
    per_ping = 2 * samples * 2 + 512  # samples of both sides + headers
    n_pings = max(4, int(megabytes * 1e6 / per_ping))
    if path.is_file() and path.with_suffix(".json").is_file():
        if json.loads(path.with_suffix(".json").read_text()).get("pings") == n_pings:
            return path
    path.parent.mkdir(parents=True, exist_ok=True)
    flat = BathyGrid(np.full((2, 2), -DEMO["depth_m"], np.float32), -1e6, -1e6, 2e6)
    seg = 2000
    tmp = path.with_suffix(".part.xtf")
    with open(path, "wb") as f:
        for i, a in enumerate(range(0, n_pings, seg)):
            n = min(seg, n_pings - a)
            line = _line("long", 0.0, a * 0.375, n, flat, a * 0.25, seed + i)
            # samples per side: resample the model's 256 bins up to `samples`
            idx = np.minimum((np.arange(samples) * DEMO["n_bins"]) // samples, DEMO["n_bins"] - 1)
            dr = DEMO["max_range_m"] / samples
            inten = line.intensity[:, :, idx]
            inten[0, :, -1] = 1.0  # the same VoltScale (max) in every segment
            line = replace(
                line,
                intensity=np.minimum(inten, 1.0),
                range_m=((np.arange(samples) + 0.5) * dr).astype(np.float32),
            )
            write_xtf(line, tmp, ORIGIN, epoch_s=946684800.0)
            raw = tmp.read_bytes()
            f.write(raw if i == 0 else raw[1024:])
    tmp.unlink()
    path.with_suffix(".json").write_text(json.dumps({"pings": n_pings}))
    return path


# ----------------------------------------------------------------------------- children
def _rss_mb() -> float:
    for row in Path("/proc/self/status").read_text().splitlines():
        if row.startswith("VmRSS:"):
            return int(row.split()[1]) / 1024.0
    return math.nan


def _import_cfg(xtf_dir: Path, name: str) -> dict[str, Any]:
    return {
        "files": str(xtf_dir),
        "mbes_grid": str(xtf_dir / "mbes.tif"),
        "name": name,
        "crs": ORIGIN["crs"],
        "n_bins": DEMO["n_bins"],
    }


def child(
    stage: str, xtf_dir: Path, data_dir: Path, name: str, extra: Sequence[str], every: int = 1
) -> dict:
    """Run one stage in this process: its inner wall and CPU time and the memory after the
    imports. ``every``: drape / CNN on every ``every``-th line only (equal lines: the survey's
    cost is ``every`` x that)."""
    import torch

    torch.set_num_threads(1)
    from sss2bathy.io.xtf_survey import prepare_xtf_survey
    from sss2bathy.survey import Survey

    if stage == "import":
        base = _rss_mb()
        t0, c0 = time.perf_counter(), time.process_time()
        prepare_xtf_survey(_import_cfg(xtf_dir, name), data_dir, force=True)
        return {
            "inner_s": time.perf_counter() - t0,
            "cpu_s": time.process_time() - c0,
            "baseline_mb": base,
        }
    if stage == "long_import":
        path = xtf_dir
        if extra:  # another version of the reader (before/after a change)
            import importlib.util

            spec = importlib.util.spec_from_file_location("xtf_other", extra[0])
            mod = importlib.util.module_from_spec(spec)
            sys.modules["xtf_other"] = mod
            spec.loader.exec_module(mod)
            read = mod.read_xtf
        else:
            from sss2bathy.io.xtf import read_xtf as read
        base = _rss_mb()
        t0, c0 = time.perf_counter(), time.process_time()
        line, _ = read(path, DEMO["n_bins"], origin=ORIGIN)
        return {
            "inner_s": time.perf_counter() - t0,
            "cpu_s": time.process_time() - c0,
            "baseline_mb": base,
            "pings": line.n_pings,
            "output_mb": line.intensity.nbytes / 2**20,
        }
    survey = Survey.load(data_dir / name)
    lines = survey.lines[:: max(1, every)]
    if stage == "drape":
        from sss2bathy.draping import as_surface, drape_line

        surface = as_surface(survey.grid)
        cfg = {"threads": 1}

        def work(line: Any) -> None:
            drape_line(line, surface, cfg)

        warm = replace(lines[0], **_first_pings(lines[0], 8))
    elif stage == "cnn":
        from sss2bathy.data.cnn_normals import line_inputs, predict_waterfall
        from sss2bathy.models.normal_cnn import NormalResNet

        torch.manual_seed(0)
        net = NormalResNet(in_channels=1, base_width=8, n_blocks=4, n_down=3).eval()

        def work(line: Any) -> None:
            inputs, _ = line_inputs(line, ["intensity"], None)
            predict_waterfall(net, inputs, (64, line.n_bins), 0.75, 16)

        warm = replace(lines[0], **_first_pings(lines[0], 64))
    else:
        raise ValueError(f"stage: expected one of {STAGES}, found {stage!r}")
    work(warm)  # compilation and first-call costs are not the survey's
    base = _rss_mb()
    t0, c0 = time.perf_counter(), time.process_time()
    for line in lines:
        work(line)
    return {
        "inner_s": time.perf_counter() - t0,
        "cpu_s": time.process_time() - c0,
        "baseline_mb": base,
        "lines_measured": len(lines),
        "lines": len(survey.lines),
    }


def _first_pings(line: Any, n: int) -> dict[str, Any]:
    """The per-ping fields of ``line`` cut to its first ``n`` pings."""
    return {
        "time_s": line.time_s[:n],
        "position": line.position[:n],
        "rotation": line.rotation[:n],
        "altitude_m": line.altitude_m[:n],
        "intensity": line.intensity[:n],
        "extras": {},
        "altitude_source": None,
    }


def measure(cmd: Sequence[str], log_path: Path, env: Mapping[str, str] | None = None) -> dict:
    """Run ``cmd``; its wall seconds, peak resident memory (MB, ``os.wait4``) and the JSON of
    its last output line (a child's report), if any.

    Raises:
        RuntimeError: the command failed (its last log line quoted).
    """
    log_path.parent.mkdir(parents=True, exist_ok=True)
    full_env = {**os.environ, "OMP_NUM_THREADS": "1", "MKL_NUM_THREADS": "1", **(env or {})}
    t0 = time.perf_counter()
    with open(log_path, "w") as f:
        proc = subprocess.Popen(list(cmd), stdout=f, stderr=subprocess.STDOUT, env=full_env)
        _, status, usage = os.wait4(proc.pid, 0)
    wall = time.perf_counter() - t0
    proc.returncode = os.waitstatus_to_exitcode(status)
    lines = log_path.read_text().strip().splitlines()
    if proc.returncode != 0:
        raise RuntimeError(f"{log_path}: exited {proc.returncode}: {(lines or ['?'])[-1]}")
    report: dict[str, Any] = {}
    if lines and lines[-1].startswith("{"):
        report = json.loads(lines[-1])
    cpu = usage.ru_utime + usage.ru_stime
    return {"wall_s": wall, "child_cpu_s": cpu, "peak_mb": usage.ru_maxrss / 1024.0, **report}


def _child_cmd(
    stage: str, xtf_dir: Path, data_dir: Path, name: str, *extra: str, every: int = 1
) -> list[str]:
    return [
        sys.executable,
        "-m",
        "studies.scaling_study",
        "--child",
        stage,
        "--xtf-dir",
        str(xtf_dir),
        "--data-dir",
        str(data_dir),
        "--name",
        name,
        *(["--child-extra", *extra] if extra else []),
        f"--every={every}",
    ]


def _map_cmd(xtf_dir: Path, data_dir: Path, name: str, run_dir: Path, steps: int) -> list[str]:
    overrides = [
        "callbacks=none",
        "trainer.enable_progress_bar=false",
        f"+trainer.max_steps={steps}",
        "trainer.max_epochs=1000",
        "model.log_images=false",
    ]
    return [
        sys.executable,
        "-m",
        "sss2bathy.cli.map",
        f"files={xtf_dir}",
        "method=siren_lambert",
        # the published costs are the smooth SIREN's (the map route's default adds a detail
        # network: pin the settings so a rerun measures the same fit)
        "map_settings=scale",
        f"survey.name={name}",
        f"survey.crs={ORIGIN['crs']}",
        f"survey.mbes_grid={xtf_dir / 'mbes.tif'}",
        f"survey.n_bins={DEMO['n_bins']}",
        "scale=demo",
        "torch_threads=1",
        "logger=none",
        "verdict.folds=0",
        "verdict.overlap.enabled=false",
        "mosaic.placement=none",
        f"paths.data_dir={data_dir}",
        f"paths.output_dir={run_dir.parent}",
        f"hydra.run.dir={run_dir}",
        "overrides=[" + ",".join(f"'{o}'" for o in overrides) + "]",
    ]


# ----------------------------------------------------------------------------- study
def run_sizes(
    out: Path,
    sizes: Sequence[float],
    stages: Sequence[str],
    steps: int,
    repeats: int,
    cnn_lines: int | None = None,
) -> list[dict[str, Any]]:
    """Every stage at every size (repeats interleaved by size; median kept). The cost of a
    stage (``work_s``) is CPU seconds, robust to other load on the machine: the stage's own
    (import, drape, cnn: x lines / lines measured) or the SIREN's projected fit.
    ``cnn_lines``: CNN inference on at most this many lines (evenly spaced) per survey."""
    rows: dict[tuple[float, str], list[dict]] = {}
    plans = {k: survey_plan(k) for k in sizes}
    for k in sizes:
        t0 = time.perf_counter()
        scaled_survey(out / "surveys" / f"x{k:g}", k)
        print(f"survey x{k:g}: {plans[k]['pings']} pings ({time.perf_counter() - t0:.0f} s)")
    for rep in range(repeats):
        for k in sizes:
            xtf_dir = out / "surveys" / f"x{k:g}"
            data_dir = out / "data"
            name = f"scaling_x{k:g}"
            logs = out / "logs" / f"x{k:g}_r{rep}"
            for stage in stages:
                if stage == "siren":
                    runs = {}
                    for n in (steps, 3 * steps):
                        run_dir = out / "runs" / f"x{k:g}_r{rep}_s{n}"
                        cmd = _map_cmd(xtf_dir, data_dir, name, run_dir, n)
                        runs[n] = measure(cmd, logs / f"siren_{n}.log")
                    proj = siren_projection(
                        runs[steps]["child_cpu_s"],
                        runs[3 * steps]["child_cpu_s"],
                        steps,
                        3 * steps,
                        plans[k]["pings"],
                    )
                    res = {
                        "wall_s": runs[steps]["wall_s"],
                        "wall_long_s": runs[3 * steps]["wall_s"],
                        "peak_mb": max(r["peak_mb"] for r in runs.values()),
                        **proj,
                        "work_s": proj["projected_s"],
                    }
                else:
                    n_lines = plans[k]["n_lines"]
                    every = 1
                    if stage == "cnn" and cnn_lines:
                        every = max(1, math.ceil(n_lines / cnn_lines))
                    cmd = _child_cmd(stage, xtf_dir, data_dir, name, every=every)
                    res = measure(cmd, logs / f"{stage}.log")
                    res["work_s"] = (
                        res["cpu_s"] * res.get("lines", 1) / res.get("lines_measured", 1)
                    )
                rows.setdefault((k, stage), []).append(res)
                print(
                    f"x{k:g} {stage} rep {rep}: {res['wall_s']:.1f} s, "
                    f"peak {res['peak_mb']:.0f} MB",
                    flush=True,
                )
    table = []
    for (k, stage), runs in rows.items():
        med = {
            key: float(np.median([r[key] for r in runs]))
            for key in runs[0]
            if isinstance(runs[0][key], (int, float))
        }
        table.append({"k": k, "stage": stage, "pings": plans[k]["pings"], "n": len(runs), **med})
    return table


def exponents(table: Sequence[Mapping[str, Any]]) -> list[dict[str, Any]]:
    """Per stage, power laws against size of the cost (``work_s``), of the peak memory and
    of the working memory (peak above the baseline; NaN where a size's peak does not exceed
    its baseline: the stage needs no more than what its process already held)."""
    out = []
    for stage in dict.fromkeys(r["stage"] for r in table):
        rows = sorted((r for r in table if r["stage"] == stage), key=lambda r: r["k"])
        if len(rows) < 2:
            continue
        ks = [r["k"] for r in rows]
        t = power_law(ks, [r["work_s"] for r in rows])
        m = power_law(ks, [r["peak_mb"] for r in rows])
        work = [r["peak_mb"] - r["baseline_mb"] for r in rows if _number(r.get("baseline_mb"))]
        w = (
            power_law(ks, work)
            if len(work) == len(rows) and min(work) > 0
            else {"b": math.nan, "b_se": math.nan}
        )
        out.append(
            {
                "stage": stage,
                "b_time": t["b"],
                "b_time_se": t["b_se"],
                "b_peak": m["b"],
                "b_peak_se": m["b_se"],
                "b_working": w["b"],
                "b_working_se": w["b_se"],
                "largest_k": ks[-1],
                "largest_pings": rows[-1]["pings"],
                "largest_work_s": rows[-1]["work_s"],
                "largest_peak_mb": rows[-1]["peak_mb"],
            }
        )
    return out


def _number(v: Any) -> bool:
    return isinstance(v, (int, float)) and math.isfinite(v)


def read_table(path: Path) -> list[dict[str, Any]]:
    """The rows of a ``scaling_study.csv`` (numbers as floats, empty cells dropped)."""
    import csv

    rows = []
    with open(path, newline="") as f:
        for raw in csv.DictReader(f):
            row: dict[str, Any] = {}
            for key, value in raw.items():
                if value == "":
                    continue
                try:
                    row[key] = float(value)
                except ValueError:
                    row[key] = value
            rows.append(row)
    return rows


def write_report(out: Path, table: Sequence[Mapping[str, Any]], figure_path: Path) -> str:
    """The rows and the exponents as Markdown + CSV in ``out``, the figure; the Markdown."""
    fits = exponents(table)
    cols = ["stage", "k", "pings", "work_s", "wall_s", "peak_mb", "baseline_mb", "lines_measured"]
    extra_cols = ["per_step_s", "fixed_s", "schedule_steps", "projected_s"]
    md = "\n".join(
        markdown_table(
            cols + extra_cols,
            [[fmt_cell(r.get(c, "")) for c in cols + extra_cols] for r in table],
        )
    )
    fcols = [
        "stage",
        "b_time",
        "b_time_se",
        "b_peak",
        "b_peak_se",
        "b_working",
        "b_working_se",
        "largest_pings",
        "largest_work_s",
        "largest_peak_mb",
    ]
    fits_md = "\n".join(markdown_table(fcols, [[fmt_cell(f[c]) for c in fcols] for f in fits]))
    write_tables(
        out, "scaling_study", md + "\n", to_csv(table, cols + extra_cols, ignore_extra=True)
    )
    write_tables(out, "scaling_fits", fits_md + "\n", to_csv(fits, fcols, ignore_extra=True))
    md += "\n\n" + fits_md
    figure(table, figure_path)
    return md


def figure(table: Sequence[Mapping[str, Any]], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(10, 4))
    for stage in dict.fromkeys(r["stage"] for r in table):
        rows = sorted((r for r in table if r["stage"] == stage), key=lambda r: r["k"])
        ks = [r["k"] for r in rows]
        key = "work_s"
        label = "siren (demo schedule, projected)" if stage == "siren" else stage
        axes[0].loglog(ks, [r[key] for r in rows], "o-", label=label)
        axes[1].loglog(ks, [r["peak_mb"] for r in rows], "o-", label=stage)
    ref = np.array([1.0, 16.0])
    for ax, what in zip(axes, ("CPU time (s)", "peak RSS (MB)"), strict=True):
        lo = ax.get_ylim()[0]
        ax.loglog(ref, 2 * lo * ref, "k:", label="slope 1")
        ax.set_xlabel("survey area and line count (x demo)")
        ax.set_ylabel(what)
        ax.grid(True, which="both", alpha=0.3)
        ax.legend(fontsize=8)
    fig.suptitle("Cost per stage vs survey size (1 thread, shared 2-core CPU)")
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)


def run_long_line(out: Path, sizes_mb: Sequence[float], xtf_module: str | None) -> list[dict]:
    rows = []
    for mb in sizes_mb:
        path = long_line(out / "long" / f"long_{mb:g}mb.xtf", mb)
        size = path.stat().st_size / 2**20
        extra = (xtf_module,) if xtf_module else ()
        cmd = _child_cmd("long_import", path, out, "long", *extra)
        res = measure(cmd, out / "logs" / f"long_{mb:g}mb.log")
        res.update(file_mb=size, reader=xtf_module or "sss2bathy.io.xtf")
        print(
            f"{size:.0f} MB line: {res['wall_s']:.1f} s, peak {res['peak_mb']:.0f} MB "
            f"(baseline {res['baseline_mb']:.0f}, output {res['output_mb']:.0f} MB)",
            flush=True,
        )
        rows.append(res)
    return rows


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--out", type=Path, default=ROOT / "outputs" / "scaling_study")
    parser.add_argument("--sizes", type=float, nargs="+", default=[1.0, 4.0, 16.0])
    parser.add_argument("--stages", nargs="+", default=list(STAGES), choices=STAGES)
    parser.add_argument("--siren-steps", type=int, default=30)
    parser.add_argument("--repeats", type=int, default=1)
    parser.add_argument("--cnn-lines", type=int, default=36, help="CNN on at most N lines")
    parser.add_argument("--long-line", action="store_true", help="the long-line import only")
    parser.add_argument("--sizes-mb", type=float, nargs="+", default=[50.0, 500.0])
    parser.add_argument("--xtf-module", default=None, help="another xtf.py for --long-line")
    parser.add_argument(
        "--refit", action="store_true", help="the exponents and figure of --out's table again"
    )
    parser.add_argument("--figure", type=Path, default=None, help="PNG (default: in --out)")
    parser.add_argument("--child", default=None, help=argparse.SUPPRESS)
    parser.add_argument("--xtf-dir", type=Path, help=argparse.SUPPRESS)
    parser.add_argument("--data-dir", type=Path, help=argparse.SUPPRESS)
    parser.add_argument("--name", help=argparse.SUPPRESS)
    parser.add_argument("--child-extra", nargs="*", default=[], help=argparse.SUPPRESS)
    parser.add_argument("--every", type=int, default=1, help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args.child:
        res = child(
            args.child, args.xtf_dir, args.data_dir, args.name, args.child_extra, args.every
        )
        res["self_peak_mb"] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0
        print(json.dumps(res))
        return 0
    out: Path = args.out
    out.mkdir(parents=True, exist_ok=True)
    if args.long_line:
        rows = run_long_line(out, args.sizes_mb, args.xtf_module)
        cols = [
            "reader",
            "file_mb",
            "pings",
            "cpu_s",
            "wall_s",
            "peak_mb",
            "baseline_mb",
            "output_mb",
        ]
        md = "\n".join(markdown_table(cols, [[fmt_cell(r[c]) for c in cols] for r in rows]))
        stem = "long_line" if args.xtf_module is None else "long_line_other"
        write_tables(out, stem, md + "\n", to_csv(rows, cols, ignore_extra=True))
        print(md)
        return 0
    if args.refit:
        table = read_table(out / "scaling_study.csv")
    else:
        table = run_sizes(
            out, args.sizes, args.stages, args.siren_steps, args.repeats, args.cnn_lines
        )
    md = write_report(out, table, args.figure or out / "scaling_study.png")
    print(md)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
