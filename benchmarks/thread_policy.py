"""Thread policies under load: how much a competing busy process slows a fit's steps.

    python -m benchmarks.thread_policy                      # CNN + SIREN steps, 3 policies
    python -m benchmarks.thread_policy --repeats 5 --competitor new-session
    make thread-bench

Each measurement is a fresh worker process (``--worker``) running a fixed number of training
steps of the demo's sizes: the normal CNN (``experiment=cnn scale=demo``: NormalResNet +
NormalLoss + Adam on 64-ping windows) or the SIREN (``experiment=siren_gt_n2d scale=demo``:
:meth:`~sss2bathy.modules.siren.SirenModule.model_step` + backward + Adam on a 16-ping
batch, :mod:`benchmarks.scene`). The OpenMP runtime reads its wait policy once, when torch
loads it, so each policy gets its own process with its own environment:

* ``t2_spin``: 2 threads (or ``--threads``), the runtime's default wait (libgomp spins
  ~300000 iterations, ~ms, at every barrier before sleeping);
* ``t2_passive``: the same threads, ``OMP_WAIT_POLICY=PASSIVE`` (a waiting thread sleeps at
  once, :mod:`sss2bathy.utils.threads`);
* ``t2_spin10k``, ``t2_spin1k``: the same threads spinning at most ``GOMP_SPINCOUNT`` =
  10000 / 1000 rounds before they sleep (bounded spinning: short waits stay cheap, a
  descheduled partner costs little);
* ``t1``: one thread.

Every policy runs quiet and beside one competing ``nice -n 19`` busy loop (``python -c
"while True: pass"``), interleaved (repeat 1 of every policy and load, then repeat 2, ...)
so a change in the machine's other load hits all alike. ``--competitor same-session``
starts the loop in this process's session, where ``nice`` weighs against the fit;
``new-session`` (the default) in its own session, which under Linux's autogroup scheduling
(``/proc/sys/kernel/sched_autogroup_enabled``) is what another user's or another terminal's
job is: ``nice`` then only ranks it within its own session and it takes a full share of
the CPU whatever its nice value. Reported per workload and policy: the median step time
quiet and loaded, their ratio (1 = the competitor costs nothing; 1.5 = it took its fair
third of a 2-core machine) and each against ``t2_spin`` quiet (the first policy's where
``t2_spin`` is not run). Writes
``<out>/thread_policy.json`` and ``<out>/thread_policy.md``.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import time
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

#: policy name -> (torch threads, or None for ``--threads``; environment added)
POLICIES: dict[str, tuple[int | None, dict[str, str]]] = {
    "t2_spin": (None, {}),
    "t2_passive": (None, {"OMP_WAIT_POLICY": "PASSIVE"}),
    # bounded spinning: a waiting thread spins this many rounds, then sleeps
    "t2_spin10k": (None, {"GOMP_SPINCOUNT": "10000"}),
    "t2_spin1k": (None, {"GOMP_SPINCOUNT": "1000"}),
    "t1": (1, {}),
}
WORKLOADS = ("cnn", "siren")
LOADS = ("quiet", "busy")
COMPETITORS = ("new-session", "same-session")
#: the variables a policy controls: removed from the inherited environment first
CONTROLLED = (
    "OMP_WAIT_POLICY",
    "GOMP_SPINCOUNT",
    "KMP_BLOCKTIME",
    "OMP_NUM_THREADS",
    "MKL_NUM_THREADS",
    "SSS2BATHY_THREADS",
)
BUSY_LOOP = "while True: pass"


# ----------------------------------------------------------------------------- the worker
def cnn_step(root: Path, seed: int = 0):
    """One demo-size CNN training step (a closure) on random 64 x 256 windows."""
    import torch

    from benchmarks.config import cnn_preset
    from sss2bathy.losses.normal import NormalLoss
    from sss2bathy.models.normal_cnn import NormalResNet

    c = cnn_preset(root, "demo")
    torch.manual_seed(seed)
    net = NormalResNet(
        base_width=int(c["base_width"]), n_blocks=int(c["n_blocks"]), n_down=int(c["n_down"])
    )
    loss_fn = NormalLoss.from_config(c["loss"])
    opt = torch.optim.Adam(net.parameters(), lr=1e-3)
    gen = torch.Generator().manual_seed(seed)
    shape = (int(c["batch_size"]), 1, 64, 256)
    x = torch.rand(shape, generator=gen)
    target = (torch.rand(shape, generator=gen) - 0.5) * 0.8
    mask = torch.rand(shape, generator=gen) < 0.8

    def step() -> float:
        opt.zero_grad(set_to_none=True)
        loss = loss_fn(net(x), target, mask)["loss"]
        loss.backward()
        opt.step()
        return float(loss.detach())

    return step


def siren_step(seed: int = 0):
    """One demo-size SIREN-GT-N2d training step (a closure): 16 pings x 2 x 256 bins over
    30 m, 128 x 5 layers, omega0 10, four batches in turn (warm-started finder)."""
    import torch

    from benchmarks.scene import DEPTH_M, bench_siren, paper_beam_limits, synthetic_pings
    from benchmarks.siren_step import siren_module

    n_pings, n_bins, n_batches = 16, 256, 4
    batches, bounds = synthetic_pings(
        n_pings, n_bins, max_range_m=30.0, n_batches=n_batches, seed=seed
    )
    siren = bench_siren(128, 5, 10.0, bounds, DEPTH_M, 5.0, seed)
    module = siren_module(
        siren, 3e-4, paper_beam_limits(), n_pings * n_batches, n_bins, torch.device("cpu")
    )
    opt = module.configure_optimizers()["optimizer"]
    state = {"k": 0}

    def step() -> float:
        batch = batches[state["k"] % n_batches]
        state["k"] += 1
        opt.zero_grad(set_to_none=True)
        loss = module.model_step(batch)["loss"]
        loss.backward()
        opt.step()
        return float(loss.detach())

    return step


def run_worker(workload: str, threads: int, steps: int, warmup: int, root: Path) -> dict:
    """``steps`` timed steps of ``workload`` on ``threads`` torch threads (after ``warmup``)."""
    import torch

    torch.set_num_threads(int(threads))
    step = cnn_step(root) if workload == "cnn" else siren_step()
    for _ in range(warmup):
        step()
    times, losses = [], []
    cpu0, t_all = time.process_time(), time.perf_counter()
    for _ in range(steps):
        t0 = time.perf_counter()
        losses.append(step())
        times.append(time.perf_counter() - t0)
    wall = time.perf_counter() - t_all
    return {
        "workload": workload,
        "threads": torch.get_num_threads(),
        "steps": steps,
        "wall_s": wall,
        "step_median_s": statistics.median(times),
        "cpu_s": time.process_time() - cpu0,
        "last_loss": losses[-1],
        "wait_policy": os.environ.get("OMP_WAIT_POLICY"),
    }


# ----------------------------------------------------------------------------- the driver
def policy_env(name: str, threads: int) -> tuple[int, dict[str, str]]:
    """``(torch threads, the worker's environment)`` of policy ``name``."""
    if name not in POLICIES:
        raise ValueError(f"policies: expected names among {sorted(POLICIES)}, found {name!r}")
    n, extra = POLICIES[name]
    n = threads if n is None else n
    env = {k: v for k, v in os.environ.items() if k not in CONTROLLED}
    env.update(extra)
    env.update(OMP_NUM_THREADS=str(n), MKL_NUM_THREADS=str(n))
    # the worker measures the runtime's own behaviour: no policy of the package on top
    env["SSS2BATHY_THREADS"] = "off"
    return n, env


def start_competitor(mode: str) -> subprocess.Popen:
    """One ``nice -n 19`` busy loop, in a new session or in this one (module docstring)."""
    if mode not in COMPETITORS:
        raise ValueError(f"competitor: expected one of {COMPETITORS}, found {mode!r}")
    return subprocess.Popen(
        ["nice", "-n", "19", sys.executable, "-c", BUSY_LOOP],
        start_new_session=(mode == "new-session"),
    )


def stop(proc: subprocess.Popen) -> None:
    proc.terminate()
    try:
        proc.wait(timeout=10)
    except subprocess.TimeoutExpired:
        proc.kill()
        proc.wait()


def measure_once(
    workload: str, policy: str, load: str, args: argparse.Namespace, root: Path
) -> dict:
    """One worker run (with the competitor running throughout when ``load == "busy"``)."""
    n, env = policy_env(policy, args.threads)
    steps = args.cnn_steps if workload == "cnn" else args.siren_steps
    cmd = [sys.executable, "-m", "benchmarks.thread_policy", "--worker", workload]
    cmd += ["--threads", str(n), "--steps", str(steps), "--warmup", str(args.warmup)]
    cmd += ["--root", str(root)]
    rival = start_competitor(args.competitor) if load == "busy" else None
    try:
        time.sleep(0.2 if rival is not None else 0.0)  # the loop is running before the fit
        done = subprocess.run(cmd, env=env, capture_output=True, text=True, cwd=root)
    finally:
        if rival is not None:
            stop(rival)
    if done.returncode != 0:
        raise RuntimeError(f"worker {workload}/{policy}/{load} failed:\n{done.stderr[-2000:]}")
    result = json.loads(done.stdout.strip().splitlines()[-1])
    result.update(policy=policy, load=load)
    return result


def summarize(runs: Sequence[Mapping[str, Any]]) -> list[dict]:
    """Per workload and policy: median step time quiet and busy, busy / quiet, and each
    against the reference policy's quiet median (``t2_spin`` where measured, else the
    first policy run; ``reference`` in each row)."""
    rows = []
    for workload in dict.fromkeys(r["workload"] for r in runs):
        mine = [r for r in runs if r["workload"] == workload]
        policies = list(dict.fromkeys(r["policy"] for r in mine))
        reference = "t2_spin" if "t2_spin" in policies else policies[0]
        ref = [r["step_median_s"] for r in mine if (r["policy"], r["load"]) == (reference, "quiet")]
        ref_s = statistics.median(ref) if ref else None
        for policy in policies:
            row: dict[str, Any] = {"workload": workload, "policy": policy, "reference": reference}
            for load in LOADS:
                sel = [
                    r["step_median_s"] for r in mine if (r["policy"], r["load"]) == (policy, load)
                ]
                row[f"{load}_s"] = statistics.median(sel) if sel else None
                row[f"{load}_all_s"] = sel
            q, b = row["quiet_s"], row["busy_s"]
            row["busy_over_quiet"] = b / q if q and b else None
            row["quiet_vs_reference"] = q / ref_s if q and ref_s else None
            row["busy_vs_reference_quiet"] = b / ref_s if b and ref_s else None
            losses = {r["last_loss"] for r in mine if r["policy"] == policy}
            row["same_loss_in_every_run"] = len(losses) == 1
            rows.append(row)
    return rows


def to_markdown(result: Mapping[str, Any]) -> str:
    p = result["params"]
    ref = result["rows"][0]["reference"] if result["rows"] else "-"
    lines = [
        "# Thread policies under load",
        "",
        f"`{result['command']}` on {p['cores']} usable cores; competitor: one `nice -n 19` "
        f"busy loop ({p['competitor']}); {p['repeats']} interleaved repeats; load average "
        f"before / after: {p['load_before']} / {p['load_after']}.",
        "",
        f"| workload | policy | quiet step (ms) | busy step (ms) | busy / quiet | quiet vs {ref} "
        f"quiet | busy vs {ref} quiet | same loss every run |",
        "|---|---|---:|---:|---:|---:|---:|---|",
    ]
    for r in result["rows"]:
        lines.append(
            f"| {r['workload']} | {r['policy']} | {1e3 * r['quiet_s']:.1f} | "
            f"{1e3 * r['busy_s']:.1f} | {r['busy_over_quiet']:.2f} | "
            f"{r['quiet_vs_reference']:.2f} | {r['busy_vs_reference_quiet']:.2f} | "
            f"{'yes' if r['same_loss_in_every_run'] else 'no'} |"
        )
    return "\n".join(lines) + "\n"


def load_average() -> str:
    try:
        return " ".join(Path("/proc/loadavg").read_text().split()[:3])
    except OSError:
        return "?"


def usable_cores() -> int:
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # not Linux
        return os.cpu_count() or 1


def main(argv: Sequence[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--workloads", default=",".join(WORKLOADS))
    ap.add_argument("--policies", default=",".join(POLICIES))
    ap.add_argument("--threads", type=int, default=None, help="threads of t2_* (default: cores)")
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--cnn-steps", type=int, default=12)
    ap.add_argument("--siren-steps", type=int, default=8)
    ap.add_argument("--warmup", type=int, default=3)
    ap.add_argument("--competitor", choices=COMPETITORS, default="new-session")
    ap.add_argument("--root", default=None, help="project checkout (default: cwd)")
    ap.add_argument("--out", default="outputs/thread_policy")
    ap.add_argument("--worker", choices=WORKLOADS, help=argparse.SUPPRESS)
    ap.add_argument("--steps", type=int, default=0, help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    from benchmarks.config import project_root

    root = project_root(args.root)
    if args.worker:
        print(json.dumps(run_worker(args.worker, args.threads, args.steps, args.warmup, root)))
        return 0
    workloads = [w for w in args.workloads.split(",") if w]
    policies = [p for p in args.policies.split(",") if p]
    for w in workloads:
        if w not in WORKLOADS:
            ap.error(f"--workloads: expected names among {list(WORKLOADS)}, found {w!r}")
    for p in policies:
        if p not in POLICIES:
            ap.error(f"--policies: expected names among {list(POLICIES)}, found {p!r}")
    if args.repeats < 1:
        ap.error(f"--repeats: expected >= 1, found {args.repeats}")
    args.threads = args.threads or usable_cores()
    before = load_average()
    runs = []
    for i in range(args.repeats):
        for w in workloads:
            for p in policies:
                for load in LOADS:
                    r = measure_once(w, p, load, args, root)
                    r["repeat"] = i
                    runs.append(r)
                    print(
                        f"[{i + 1}/{args.repeats}] {w:5s} {p:10s} {load:5s} "
                        f"{1e3 * r['step_median_s']:8.1f} ms/step (load {load_average()})",
                        flush=True,
                    )
    result = {
        "command": "python -m benchmarks.thread_policy " + " ".join(sys.argv[1:]),
        "params": {
            "cores": usable_cores(),
            "threads": args.threads,
            "competitor": args.competitor,
            "repeats": args.repeats,
            "cnn_steps": args.cnn_steps,
            "siren_steps": args.siren_steps,
            "load_before": before,
            "load_after": load_average(),
            "autogroup": Path("/proc/sys/kernel/sched_autogroup_enabled").read_text().strip()
            if Path("/proc/sys/kernel/sched_autogroup_enabled").is_file()
            else None,
        },
        "runs": runs,
        "rows": summarize(runs),
    }
    out = root / args.out
    out.mkdir(parents=True, exist_ok=True)
    (out / "thread_policy.json").write_text(json.dumps(result, indent=2))
    (out / "thread_policy.md").write_text(to_markdown(result))
    print(to_markdown(result))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
