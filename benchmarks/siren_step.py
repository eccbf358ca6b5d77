"""Section ``siren_step``: one SIREN training step through the real code path.

:meth:`~sss2bathy.modules.siren.SirenModule.model_step` (the warm-started intersection
finder, the explicit input-gradient pass, the normal sensor loss and the altimeter height
loss), then ``backward`` and the Adam step, on synthetic pings of the paper's geometry over
a SIREN surface (:mod:`benchmarks.scene`): steps/s, valid bins/s and the **matmul bound**.
The bound is the time the step's matrix products alone take at the ``torch.mm`` rate:
every product of one step (forward, finder, backward) is recorded with its shapes and
strides, each distinct product is re-timed alone on tensors of the same layout, and the
counts times those times are summed (:mod:`benchmarks.matmul`). The step's fraction of its
bound is ``bound / step time`` (1 = the step costs no more than its products). The
recorded FLOPs are checked against an analytic count from the layer shapes and the points
through each pass (:func:`~benchmarks.matmul.siren_matmul_flops`).

The step's sines and cosines are recorded too and re-timed alone at the ``torch.sin`` rate
(the *sine bound*, :func:`~benchmarks.matmul.time_sines`): a SIREN evaluates one sine per
hidden unit and point (two with the gradient), so ``matmul bound / (matmul + sine bound)``
is the *ceiling* of the step's matmul fraction with PyTorch's sine kernels -- what the step
would reach if it did nothing else -- and ``(matmul + sine bound) / step time`` says how much
of the step the two account for.
"""

from __future__ import annotations

import statistics
from collections.abc import Sequence
from typing import Any

import torch

from benchmarks.matmul import MatmulRecorder, siren_matmul_flops, time_products, time_sines
from benchmarks.scene import (
    DEPTH_M,
    SONAR_DEPTH_M,
    bench_siren,
    paper_beam_limits,
    synthetic_pings,
    to_device,
)
from benchmarks.timing import figure, resolve_device, time_runs

TITLE = "SIREN training step"


def siren_module(
    siren: torch.nn.Module,
    lr: float,
    beam_limits: tuple[float, float],
    n_pings: int,
    n_bins: int,
    device: torch.device,
):
    """A :class:`~sss2bathy.modules.siren.SirenModule` with the normal sensor model, set up
    for a survey of ``n_pings`` pings of ``n_bins`` bins in a beam of ``beam_limits``
    (rad) and an empty warm-start cache, without a datamodule."""
    from sss2bathy.models.normal_sensor import NormalSensorModel
    from sss2bathy.modules.siren import SirenModule

    module = SirenModule(
        siren,
        sensor=NormalSensorModel(),
        optimizer=lambda params: torch.optim.Adam(params, lr=lr),
        log_images=False,
    ).to(device)
    module.theta_limits = beam_limits
    module.theta_cache = torch.full((n_pings, 2, n_bins), torch.nan, device=device)
    return module


def bench_siren_step(
    *,
    n_pings: int = 64,
    n_bins: int = 512,
    max_range_m: float = 50.0,
    hidden: int = 128,
    n_layers: int = 5,
    omega0: float = 30.0,
    relief_m: float = 50.0,
    altimeter_points: int = 2000,
    n_batches: int = 4,
    warmup: int = 2,
    repeats: int = 7,
    mm_repeats: int = 3,
    lr: float = 2e-4,
    precisions: Sequence[str] = ("fp32", "bf16"),
    device: str | torch.device | None = None,
    seed: int = 0,
) -> dict:
    """One SIREN training step (module docstring), its throughput and its matmul bound.

    ``n_batches`` batches are visited in turn, so each bin's warm start is the crossing of
    ``n_batches`` steps ago (a fit's steady state); warm-up visits every batch at least
    ``warmup`` times before timing.

    Each of ``precisions`` (the SIREN's training precision,
    :data:`~sss2bathy.models.siren.PRECISIONS`) gets its own module from the same initial
    SIREN, batches and schedule; their steps are timed interleaved (one of each per
    repeat) so that load changes hit them alike. A step's products are recorded in the
    dtype they ran in and re-timed in it: a bf16 step's bound is at the bf16 ``torch.mm``
    rate. The bound is re-timed ``mm_repeats`` times spread over the timed repeats. The
    first precision's figures carry the plain names, the others' are prefixed
    ``"<precision>: "``, with their speed-up over the first (per interleaved pair).
    Allocator: :func:`~sss2bathy.utils.alloc.tune_allocator` first (what the entry points do).
    """
    from sss2bathy.models.siren import PRECISIONS
    from sss2bathy.utils.alloc import tune_allocator

    names = list(precisions)
    if not names or len(set(names)) != len(names) or not set(names) <= set(PRECISIONS):
        raise ValueError(
            f"precisions: expected distinct names among {sorted(PRECISIONS)}, found {names}"
        )
    if int(mm_repeats) < 1 or int(mm_repeats) > int(repeats):
        raise ValueError(f"mm_repeats: expected 1 <= mm_repeats <= repeats, found {mm_repeats}")
    allocator = tune_allocator()
    dev = resolve_device(device)
    skipped = []
    if dev.type == "cuda" and not torch.cuda.is_bf16_supported() and len(names) > 1:
        skipped = [p for p in names if p == "bf16"]  # no bf16 tensor cores: nothing to measure
        names = [p for p in names if p != "bf16"]
    batches, bounds = synthetic_pings(
        n_pings,
        n_bins,
        max_range_m=max_range_m,
        depth_m=DEPTH_M,
        altimeter_points=altimeter_points,
        n_batches=n_batches,
        seed=seed,
    )
    batches = [to_device(b, dev) for b in batches]
    beam = paper_beam_limits()

    def make_run(precision: str) -> dict[str, Any]:
        siren = bench_siren(
            hidden, n_layers, omega0, bounds, DEPTH_M, relief_m, seed, True, precision
        )
        module = siren_module(siren, lr, beam, n_pings * n_batches, n_bins, dev)
        opt = module.configure_optimizers()["optimizer"]
        run: dict[str, Any] = {
            "k": 0,
            "valid": [],
            "iters": [],
            "times": [],
            "bound": [],
            "sine": [],
        }

        def step() -> None:
            batch = batches[run["k"] % n_batches]
            run["k"] += 1
            before = siren.points["gradient_grad"]
            opt.zero_grad(set_to_none=True)
            out = module.model_step(batch)
            out["loss"].backward()
            opt.step()
            run["valid"].append(siren.points["gradient_grad"] - before)
            run["iters"].append(float(out["finder_iters"]))

        run.update(siren=siren, step=step)
        return run

    runs = {p: make_run(p) for p in names}
    for run in runs.values():
        for _ in range(max(int(warmup), 1) * n_batches):
            run["step"]()
        # one step with every product recorded and every point counted
        run["siren"].points.clear()
        with MatmulRecorder() as rec:
            run["step"]()
        run["rec"], run["points"] = rec, dict(run["siren"].points)
        run["valid"].clear()
        run["iters"].clear()
    bound_at = {round(i * (repeats - 1) / max(mm_repeats - 1, 1)) for i in range(mm_repeats)}
    for i in range(int(repeats)):
        for run in runs.values():
            run["times"] += time_runs(run["step"], 0, 1, dev)
            if i in bound_at:
                run["bound"] += time_products(run["rec"].calls, 1, dev, seed=seed + i)
                run["sine"] += time_sines(run["rec"].sines, 1, dev, seed=seed + i)

    bins_all = n_pings * 2 * n_bins
    first = runs[names[0]]
    figures: list[dict] = []
    info: dict[str, Any] = {"allocator": vars(allocator), "precisions": {}, "skipped": skipped}
    for p, run in runs.items():
        prefix = "" if p == names[0] else f"{p}: "
        times, bound, valid, rec = run["times"], run["bound"], run["valid"], run["rec"]
        sine = run["sine"]
        mm_med, sine_med = statistics.median(bound), statistics.median(sine)
        ceiling = mm_med / (mm_med + sine_med)
        step_flops = rec.flops()
        mm_note = "the step's products alone at the torch.mm rate"
        if p != "fp32":
            mm_note += f" ({p} products at the {p} rate)"
        figures += [
            figure(prefix + "step time", "s", times),
            figure(prefix + "steps/s", "1/s", [1 / t for t in times]),
            figure(
                prefix + "valid bins/s",
                "bins/s",
                [v / t for v, t in zip(valid, times, strict=True)],
            ),
            figure(
                prefix + "valid bins per step",
                "bins",
                valid,
                f"of {bins_all} ({n_pings} pings x 2 x {n_bins}); "
                f"+ {altimeter_points} altimeter pts",
            ),
            figure(
                prefix + "finder evaluations per bin",
                "evals",
                run["iters"],
                "warm-started, finder defaults",
            ),
            figure(
                prefix + "step matmul work",
                "GFLOP",
                step_flops / 1e9,
                "recorded, fwd + finder + bwd",
            ),
            figure(prefix + "matmul bound", "s", bound, mm_note),
            figure(prefix + "torch.mm rate", "GFLOP/s", [step_flops / b / 1e9 for b in bound]),
            figure(
                prefix + "matmul bound / step time",
                "%",
                [100 * mm_med / t for t in times],
                "target >= 70 %" if p == "fp32" else f"of the {p} bound",
            ),
            figure(
                prefix + "sine bound",
                "s",
                sine,
                f"the step's {rec.sine_elements() / 1e6:.1f} M sin/cos alone at the torch.sin rate",
            ),
            figure(
                prefix + "(matmul + sine bound) / step time",
                "%",
                [100 * (mm_med + sine_med) / t for t in times],
                "the share of the step its products and sines account for",
            ),
            figure(
                prefix + "ceiling: matmul / (matmul + sine bound)",
                "%",
                100 * ceiling,
                "the matmul fraction of a step doing nothing but its products and sines",
            ),
        ]
        if p != names[0]:
            figures.append(
                figure(
                    f"{p}: speed-up over {names[0]}",
                    "x",
                    [a / b for a, b in zip(first["times"], times, strict=True)],
                    "per interleaved pair of steps",
                )
            )
            figures.append(
                figure(
                    f"{p}: matmul bound speed-up over {names[0]}",
                    "x",
                    [a / b for a, b in zip(first["bound"], bound, strict=True)],
                    "the products alone: what the step's speed-up stays below while the rest "
                    "of the step costs the same",
                )
            )
        info["precisions"][p] = {
            "points": run["points"],
            "analytic_flops": siren_matmul_flops(hidden, n_layers, run["points"]),
            "recorded_siren_flops": rec.flops(("mm", "addmm")),
            "recorded_flops": step_flops,
            "distinct_products": len(rec.calls),
            "products": sum(rec.calls.values()),
            "bound_fraction": mm_med / statistics.median(times),
            "sine_elements": rec.sine_elements(),
            "sine_calls": sum(rec.sines.values()),
            "sine_bound_s": sine_med,
            "matmul_fraction_ceiling": ceiling,
        }
    info.update(info["precisions"][names[0]])
    altitude = DEPTH_M - SONAR_DEPTH_M
    return {
        "title": TITLE,
        "params": {
            "n_pings": n_pings,
            "n_bins": n_bins,
            "max_range_m": max_range_m,
            "siren": f"{n_layers} x {hidden}, omega0 {omega0}",
            "altimeter_points": altimeter_points,
            "n_batches": n_batches,
            "precisions": names,
            "device": str(dev),
        },
        "figures": figures,
        "info": info,
        "notes": (
            f"{n_pings} pings x 2 x {n_bins} bins ({max_range_m:g} m range, {altitude:g} m "
            f"altitude) + {altimeter_points} altimeter points, {n_layers}-layer width-{hidden} "
            "SIREN, SirenModule.model_step (warm-started finder with the fit's defaults, "
            "explicit gradient pass, normal + height loss) + backward + Adam. Matmul bound: "
            "every product of one step recorded (shape, strides, dtype) and re-timed alone "
            "with torch.mm/addmm/bmm; its sines and cosines likewise with torch.sin/cos "
            f"(sine bound). Precisions {', '.join(names)} interleaved (bf16: the "
            "hidden layers of the normal-loss gradient pass; finder, heights and map in "
            "fp32). Allocator: "
            + ("glibc tuned (mallopt)" if allocator.applied else f"as is ({allocator.reason})")
            + "."
        ),
    }
