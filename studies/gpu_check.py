"""``make gpu-check``: the paper-scale SIREN fit and a paper-width CNN epoch, timed on a GPU.

Where CUDA is present (``--device auto``, the default):

1. the ``scale=paper`` ``synthetic_d1`` survey is prepared once (simulation and draping
   timed apart, the simulator on every core: :func:`studies.paper_cpu_study.prepare_survey`);
   a cached survey under ``--data-dir`` is reused;
2. SIREN-GT-N2d is fitted on it (:func:`studies.paper_cpu_study.fit_command`: the fast
   schedule at 2000 steps per epoch, the recipe of the best known paper-scale map, 0.0766 m
   on the 2-core CPU in 57 min; the map evaluated 4 times an epoch) until its map MAE is
   within 10 % of that best (``--target-mae``, Lightning's ``EarlyStopping`` with a
   ``stopping_threshold``) or for at most ``--siren-budget-s`` seconds; the time to the
   target, to within 10 % of the fit's own best, steps/s and the best MAE are reported;
3. the normal CNN (``experiment=cnn scale=paper``: width 64, 7 blocks, batch 64) trains one
   epoch on the survey's training lines (no test pass), for at most ``--cnn-budget-s``;

and prints the GPU's name and memory with the times, and writes ``<out>/gpu_check.json``
(the fits' logs and run folders beside it). On a machine without CUDA it prints one line
saying so and exits 0; on one whose NVIDIA GPU torch cannot use (a CPU build of torch), one
line on stderr saying what to install, exit status 2. ``--device cpu --scale tiny`` runs the same steps on a CPU at the tiny
scale in a minute or two (a smoke test of the code paths, not a measurement).

    python -m studies.gpu_check                       # make gpu-check
    python -m studies.gpu_check --data-dir /scratch/data --siren-budget-s 300
    python -m studies.gpu_check --device cpu --scale tiny --out /tmp/gpu_check
"""

from __future__ import annotations

import argparse
import json
import logging
import math
import os
import platform
import re
import sys
import time
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

from sss2bathy.utils.atomic import atomic_write_text
from sss2bathy.utils.threads import available_cores
from studies.paper_cpu_study import PRESET, fit_command, prepare_survey
from studies.schedule_study import load_run_curve
from studies.xtf_study import run_logged

log = logging.getLogger("sss2bathy.gpu_check")

ROOT = Path(__file__).resolve().parents[1]
#: the best known paper-scale SIREN-GT-N2d map MAE (m): docs/performance_log.md, "Paper scale
#: on this 2-core CPU" (fast schedule x 2 steps per epoch, 57 min)
BEST_KNOWN_MAE_M = 0.0766
WITHIN = 0.10
MAP_KEY = "val/map_mae_m"
CNN_KEY = "val/nlat_mae"
DEVICES = ("auto", "cuda", "cpu")
#: progress lines in the fits' logs (read back for the CNN epoch's rate)
PROGRESS = ("callbacks.progress.when=always", "callbacks.progress.every_s=10")


def cuda_device() -> dict[str, Any] | None:
    """The first CUDA device's name, memory (GiB) and compute capability, with torch's and
    CUDA's versions; None without one."""
    import torch

    if not torch.cuda.is_available():
        return None
    props = torch.cuda.get_device_properties(0)
    return {
        "name": props.name,
        "memory_gib": round(props.total_memory / 2**30, 1),
        "capability": f"{props.major}.{props.minor}",
        "count": torch.cuda.device_count(),
        "torch": torch.__version__,
        "cuda": torch.version.cuda,
    }


def nvidia_present() -> bool:
    """An NVIDIA driver sees a GPU here (``/proc/driver/nvidia/gpus/*`` or ``/dev/nvidia0``),
    whatever torch says."""
    gpus = Path("/proc/driver/nvidia/gpus")
    return (gpus.is_dir() and any(gpus.iterdir())) or Path("/dev/nvidia0").exists()


def cpu_torch_line() -> str:
    """The one line for a GPU machine whose torch is a CPU build (nothing can be measured)."""
    import torch

    return (
        f"gpu-check: an NVIDIA GPU is present but torch {torch.__version__} has no CUDA; "
        'install a CUDA build first (README: make install TORCH_SPEC="torch --index-url '
        'https://download.pytorch.org/whl/cu124")'
    )


def no_gpu_line() -> str:
    """The one line a CPU-only machine prints."""
    import torch

    return (
        f"gpu-check: no CUDA GPU on this machine (torch {torch.__version__}, "
        f"{available_cores()} CPU cores); nothing measured"
    )


def target_stop(target_mae: float) -> str:
    """The override of a callback that stops the fit once the map MAE is at most
    ``target_mae`` (evaluated at each map evaluation, never on patience)."""
    if not target_mae > 0:
        raise ValueError(f"target_mae: expected a positive MAE in metres, found {target_mae}")
    return (
        "+callbacks.gpu_check_stop={_target_:pytorch_lightning.callbacks.EarlyStopping,"
        f"monitor:'{MAP_KEY}',mode:min,stopping_threshold:{target_mae:.6g},"
        "patience:1000000,check_on_train_epoch_end:false}"
    )


def cnn_size(scale: str) -> str:
    """``"width 64, 7 blocks, batch 64"`` of the CNN experiment at ``scale`` (composed)."""
    from hydra import compose, initialize_config_dir

    with initialize_config_dir(config_dir=str(ROOT / "conf"), version_base="1.3"):
        cfg = compose("train", overrides=["experiment=cnn", f"scale={scale}"])
    net = cfg.model.net
    return f"width {net.base_width}, {net.n_blocks} blocks, batch {cfg.data.batch_size}"


def accelerator(device: str) -> str:
    return "trainer.accelerator=" + ("gpu" if device == "cuda" else "cpu")


def siren_command(
    scale: str,
    data_dir: Path,
    run_dir: Path,
    budget_s: float,
    device: str,
    target_mae: float | None,
    steps_per_epoch: int = 2000,
    extra: Sequence[str] = (),
) -> list[str]:
    """The SIREN-GT-N2d fit (:func:`studies.paper_cpu_study.fit_command`, fast schedule)."""
    more = [accelerator(device), f"scale.siren.fast_steps_per_epoch={int(steps_per_epoch)}"]
    more += PROGRESS
    if target_mae is not None:
        more.append(target_stop(target_mae))
    return fit_command(
        "siren_gt_n2d", "fast", scale, data_dir, run_dir, budget_s, 4,
        extra=[*more, *extra], preset=PRESET,
    )  # fmt: skip


def cnn_command(
    scale: str, data_dir: Path, run_dir: Path, budget_s: float, device: str,
    extra: Sequence[str] = (),
) -> list[str]:  # fmt: skip
    """One epoch of the CNN experiment on the survey's training lines, at most ``budget_s``
    seconds, validated once at its end, no test pass and no logger."""
    if not budget_s > 0:
        raise ValueError(f"cnn budget: expected a positive number of seconds, found {budget_s}")
    return [
        sys.executable, "-m", "sss2bathy.cli.train", "experiment=cnn", f"scale={scale}",
        f"data/survey={PRESET}", "data.test_surveys=[]", "test=false", "logger=none",
        "trainer.max_epochs=1", "++trainer.min_epochs=0",
        f"++trainer.max_time={{seconds:{max(int(round(budget_s)), 1)}}}",
        "trainer.enable_progress_bar=false", accelerator(device),
        f"paths.data_dir={data_dir}", f"paths.output_dir={run_dir.parent}",
        f"hydra.run.dir={run_dir}", *PROGRESS, *extra,
    ]  # fmt: skip


def siren_summary(
    curve: Mapping[str, Any], target_mae: float | None, process_wall_s: float
) -> dict[str, Any]:
    """The SIREN fit's times from its metric curve (``wall_s`` = seconds since the fit
    started, map evaluations included)."""
    import numpy as np

    mae, wall, step = (np.asarray(curve[k], float) for k in (MAP_KEY, "wall_s", "step"))
    best = float(mae.min())
    own = np.nonzero(mae <= (1 + WITHIN) * best)[0]
    hit = np.nonzero(mae <= target_mae)[0] if target_mae is not None else np.array([], int)
    fit_s = float(wall[-1])
    return {
        "best_mae_m": best,
        "final_mae_m": float(mae[-1]),
        "evaluations": int(mae.size),
        "steps": int(step[-1]),
        "fit_s": fit_s,
        "steps_per_s": float(step[-1] / fit_s) if fit_s > 0 else math.nan,
        "t_within_own_best_s": float(wall[own[0]]),
        "target_mae_m": target_mae,
        "t_target_s": float(wall[hit[0]]) if hit.size else None,
        "process_wall_s": process_wall_s,
    }


#: the training progress callback's closing line (sss2bathy.callbacks.progress)
DONE_LINE = re.compile(
    r"train done: epoch \d+/\d+: (?P<done>\d+)/(?P<total>\d+) steps .*?, "
    r"(?P<rate>[\d.e+-]+) steps/s, (?P<elapsed>.+?) elapsed"
)


def parse_duration(text: str) -> float:
    """Seconds of :func:`sss2bathy.utils.progress.format_duration`'s ``"1 h 02 min"``,
    ``"12 min 05 s"``, ``"45 s"``."""
    units = {"h": 3600.0, "min": 60.0, "s": 1.0}
    parts = text.split()
    if len(parts) % 2 or not parts or any(u not in units for u in parts[1::2]):
        raise ValueError(f"duration: expected e.g. '12 min 05 s', found {text!r}")
    return sum(float(v) * units[u] for v, u in zip(parts[::2], parts[1::2], strict=True))


def cnn_summary(log_text: str, run_dir: Path, process_wall_s: float) -> dict[str, Any]:
    """The CNN epoch's steps, seconds and rate from its log's closing progress line (the
    epoch may have been cut by its time budget), and its validation MAE when it got that
    far."""
    found = list(DONE_LINE.finditer(log_text))
    if not found:
        raise ValueError(f"{run_dir}.log: expected a 'train done:' progress line, found none")
    m = found[-1]
    done, total = int(m["done"]), int(m["total"])
    try:
        val = float(load_run_curve(run_dir, CNN_KEY)[CNN_KEY][-1])
    except (FileNotFoundError, ValueError):  # stopped by the budget before its validation
        val = None
    return {
        "steps": done,
        "epoch_steps": total,
        "complete": done >= total,
        "train_s": parse_duration(m["elapsed"]),
        "steps_per_s": float(m["rate"]),
        "val_nlat_mae": val,
        "process_wall_s": process_wall_s,
    }


def report_lines(result: Mapping[str, Any]) -> list[str]:
    """What the check prints at its end."""
    gpu = result.get("gpu") or {}
    where = (
        f"{gpu['name']} ({gpu['memory_gib']} GiB, capability {gpu['capability']}, torch "
        f"{gpu['torch']}, CUDA {gpu['cuda']})"
        if gpu
        else f"CPU ({result['machine']['cores']} cores; a smoke test, not a measurement)"
    )
    prep, s, c = result["prepare"], result["siren"], result["cnn"]
    if s.get("target_mae_m") is None:
        target = "no target at this scale"
    else:
        reached = s.get("t_target_s")
        at = f"{reached:.0f} s" if reached is not None else "not reached"
        target = f"to MAE <= {s['target_mae_m']:.4f} m (1.1 x the best known): {at}"
    lines = [
        f"gpu-check on {where}, scale={result['scale']}:",
        f"  prepare: simulation {prep['simulation']['wall_s']:.0f} s "
        f"({prep['simulation']['note']}), draping {prep['draping']['wall_s']:.0f} s",
        f"  SIREN-GT-N2d: best map MAE {s['best_mae_m']:.4f} m after {s['steps']} steps in "
        f"{s['fit_s']:.0f} s ({s['steps_per_s']:.1f} steps/s); within 10 % of its own best at "
        f"{s['t_within_own_best_s']:.0f} s; {target}",
        f"  CNN epoch ({result['cnn_width']}): {c['steps']}/{c['epoch_steps']} steps in "
        f"{c['train_s']:.0f} s ({c['steps_per_s']:.3g} steps/s"
        + ("" if c["complete"] else ", cut by its budget")
        + (f"), val n_lat MAE {c['val_nlat_mae']:.4f}" if c["val_nlat_mae"] is not None else ")"),
        f"  total {result['total_s']:.0f} s; {result['out']}/gpu_check.json",
    ]
    return lines


def run_check(
    out: Path,
    scale: str = "paper",
    device: str = "cuda",
    data_dir: Path | None = None,
    siren_budget_s: float = 210.0,
    cnn_budget_s: float = 120.0,
    target_mae: float | None = None,
    sim_workers: int | None = None,
    extra: Sequence[str] = (),
) -> dict[str, Any]:
    """Prepare, fit, train one epoch (module docstring); the result written and returned."""
    t0 = time.monotonic()
    out.mkdir(parents=True, exist_ok=True)
    data_dir = Path(data_dir) if data_dir is not None else ROOT / "data"
    gpu = cuda_device() if device == "cuda" else None
    if device == "cuda" and gpu is None:
        raise ValueError("--device cuda: expected a CUDA GPU, found none (torch sees no CUDA)")
    cores = available_cores()
    workers = sim_workers or cores
    log.info("gpu-check: preparing %s at scale=%s (%d simulator processes)", PRESET, scale, workers)
    prep = prepare_survey(scale, data_dir, out, None, workers, PRESET)

    siren_dir = out / "runs" / "siren_gt_n2d"
    cmd = siren_command(scale, data_dir, siren_dir, siren_budget_s, device, target_mae, extra=extra)
    log.info("gpu-check: SIREN-GT-N2d fit: %s", " ".join(cmd[2:]))
    wall = run_logged(cmd, siren_dir.with_suffix(".log"), None)
    siren = siren_summary(load_run_curve(siren_dir, MAP_KEY), target_mae, wall)

    cnn_dir = out / "runs" / "cnn_epoch"
    cmd = cnn_command(scale, data_dir, cnn_dir, cnn_budget_s, device, extra)
    log.info("gpu-check: CNN epoch: %s", " ".join(cmd[2:]))
    wall = run_logged(cmd, cnn_dir.with_suffix(".log"), None)
    cnn = cnn_summary(cnn_dir.with_suffix(".log").read_text(), cnn_dir, wall)

    result = {
        "scale": scale,
        "device": device,
        "gpu": gpu,
        "machine": {"cores": cores, "cpu": platform.processor() or platform.machine()},
        "prepare": prep,
        "siren": siren,
        "cnn": cnn,
        "cnn_width": cnn_size(scale),
        "budgets_s": {"siren": siren_budget_s, "cnn": cnn_budget_s},
        "total_s": time.monotonic() - t0,
        "out": str(out),
        "command": "python -m studies.gpu_check " + " ".join(sys.argv[1:]),
    }
    atomic_write_text(out / "gpu_check.json", json.dumps(result, indent=2) + "\n")
    return result


def main(argv: Sequence[str] | None = None) -> int:
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(message)s")
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--device", choices=DEVICES, default="auto")
    p.add_argument("--scale", default="paper", help="conf/scale/<scale>.yaml (tiny: smoke test)")
    p.add_argument("--out", default=str(ROOT / "outputs" / "gpu_check"))
    p.add_argument("--data-dir", default=None, help="survey folders (default: <root>/data)")
    p.add_argument("--siren-budget-s", type=float, default=210.0)
    p.add_argument("--cnn-budget-s", type=float, default=120.0)
    p.add_argument(
        "--target-mae",
        type=float,
        default=None,
        help=f"stop the fit at this map MAE (m); default at scale=paper 1.1 x {BEST_KNOWN_MAE_M}",
    )
    p.add_argument("--sim-workers", type=int, default=None, help="default: every core")
    p.add_argument("--extra", nargs="*", default=[], help="further sss2bathy-train overrides")
    args = p.parse_args(argv)
    device = args.device
    if device == "auto":
        if cuda_device() is None:
            if nvidia_present():
                print(cpu_torch_line(), file=sys.stderr, flush=True)
                return 2
            print(no_gpu_line(), flush=True)
            return 0
        device = "cuda"
    for name in ("siren_budget_s", "cnn_budget_s"):
        if not getattr(args, name) > 0:
            p.error(f"--{name.replace('_', '-')}: expected > 0 s, found {getattr(args, name)}")
    if args.sim_workers is not None and args.sim_workers < 1:
        p.error(f"--sim-workers: expected an integer >= 1, found {args.sim_workers}")
    target = args.target_mae
    if target is None and args.scale == "paper":
        target = (1 + WITHIN) * BEST_KNOWN_MAE_M
    os.environ.setdefault("SSS2BATHY_ROOT", str(ROOT))
    try:
        result = run_check(
            Path(args.out), args.scale, device,
            Path(args.data_dir) if args.data_dir else None,
            args.siren_budget_s, args.cnn_budget_s, target, args.sim_workers, args.extra,
        )  # fmt: skip
    except (RuntimeError, ValueError, FileNotFoundError) as err:
        print(f"error: {err}", file=sys.stderr, flush=True)
        return 1
    print("\n".join(report_lines(result)), flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
