"""Benchmarks of the pipeline's hot paths, measured on whatever machine runs them.

``make bench`` (:mod:`sss2bathy.cli.bench`) runs every section and writes
``outputs/bench/bench.json`` and ``outputs/bench/bench.md``. Sections:

* ``siren_step`` — one SIREN training step through the real code path
  (:meth:`~sss2bathy.modules.siren.SirenModule.model_step`: the warm-started intersection
  finder, the explicit input-gradient pass, the normal sensor loss and the altimeter
  height loss; then ``backward`` and the Adam step) on synthetic pings of the paper's
  geometry over a SIREN surface: steps/s, valid bins/s and the **matmul bound**. The bound
  is the time the step's matrix products alone take at the ``torch.mm`` rate: every
  ``mm``/``addmm``/``bmm`` of one step (forward, finder, backward) is recorded with its
  shapes and strides by a dispatch mode, each distinct product is re-timed alone on
  tensors of the same layout, and the counts times those times are summed. The step's
  fraction of its bound is ``bound / step time`` (1 = the step costs no more than its
  products). The recorded FLOPs are checked against an analytic count from the layer
  shapes and the points through each pass (:func:`siren_matmul_flops`).
* ``finder`` — :func:`~sss2bathy.models.intersection.find_intersections` on one batch: the
  paper's fixed-step gradient descent (``gd``) against safeguarded Newton and the
  height-only secant solver (the fit's default), cold and warm-started from the crossings
  on a perturbed surface (a fit's next epoch), at the same tolerance (1 mm); time per
  batch, evaluations per bin, agreement of the valid bins and of the crossing points,
  speed-up ratios.
* ``cnn`` — :class:`~sss2bathy.models.normal_cnn.NormalResNet` +
  :class:`~sss2bathy.losses.normal.NormalLoss` training steps on 64 x 512 windows at the
  demo and paper sizes (``conf/experiment/cnn.yaml``): windows/s.
* ``sim`` — the sidescan simulator (:func:`~sss2bathy.sim.sonar.simulate_pings` and the
  receiver) on a preset's terrain and planned line: pings/s (both heads).
* ``drape`` — :func:`~sss2bathy.draping.drape.drape_line` on the scene of
  :mod:`sss2bathy.draping.benchmark` against casting exactly the rays draping casts with
  the bare intersector: rays/s of both and their ratio.
* ``gpu_projection`` — derived, not measured: the paper-scale SIREN fit's minutes on GPUs
  from the ``siren_step`` section's FLOPs and bound fraction (:mod:`.projection`).
* ``demo_stages`` — the stage wall times of the last ``make demo``
  (``outputs/report/stage_times.json``), read, not re-run.

Every timed figure is measured after warm-up runs, reported as the median of repeated
runs with the spread (min, max, inter-quartile range). On CUDA the timings synchronise
the device before and after each run.
"""

from __future__ import annotations

import copy
import json
import math
import os
import platform
import statistics
import time
from collections import Counter
from collections.abc import Callable, Iterable, Mapping, Sequence
from datetime import datetime, timezone
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch.utils._python_dispatch import TorchDispatchMode

from sss2bathy.utils.atomic import atomic_write_text

SECTIONS = ("siren_step", "finder", "cnn", "sim", "drape", "demo_stages")
SECTION_TITLES = {
    "siren_step": "SIREN training step",
    "finder": "Intersection finder",
    "cnn": "CNN training",
    "sim": "Sidescan simulator",
    "drape": "Draping",
    "demo_stages": "make demo stages",
    "gpu_projection": "Paper-scale SIREN fit, projected",
}
_CONF = Path(__file__).resolve().parents[2] / "conf"


# ---------------------------------------------------------------------- timing helpers
def resolve_device(device: str | torch.device | None = None) -> torch.device:
    """``None``/``"auto"``: CUDA when available, else CPU; otherwise ``torch.device(device)``."""
    if device is None or str(device) == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    dev = torch.device(device)
    if dev.type == "cuda" and not torch.cuda.is_available():
        raise ValueError(f"device: expected an available device, found {device!r} (no CUDA)")
    return dev


def synchronize(device: torch.device) -> None:
    """Wait for queued kernels (CUDA); nothing on CPU."""
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def time_runs(
    fn: Callable[[], Any], warmup: int, repeats: int, device: torch.device | None = None
) -> list[float]:
    """Wall times (s) of ``repeats`` calls of ``fn`` after ``warmup`` untimed calls."""
    if int(warmup) < 0:
        raise ValueError(f"warmup: expected >= 0, found {warmup}")
    if int(repeats) < 1:
        raise ValueError(f"repeats: expected >= 1, found {repeats}")
    dev = device or torch.device("cpu")
    for _ in range(int(warmup)):
        fn()
    times = []
    for _ in range(int(repeats)):
        synchronize(dev)
        t0 = time.perf_counter()
        fn()
        synchronize(dev)
        times.append(time.perf_counter() - t0)
    return times


def summarize(samples: Sequence[float]) -> dict[str, float]:
    """Median, min, max and quartiles (``q1``, ``q3``) of ``samples``, and their count."""
    vals = sorted(float(v) for v in samples)
    if not vals:
        raise ValueError("samples: expected at least one value, found none")
    q1, q3 = (
        (statistics.quantiles(vals, n=4, method="inclusive")[i] for i in (0, 2))
        if len(vals) > 1
        else (vals[0], vals[0])
    )
    return {
        "median": statistics.median(vals),
        "min": vals[0],
        "max": vals[-1],
        "q1": q1,
        "q3": q3,
        "n": len(vals),
    }


def figure(name: str, unit: str, samples: Sequence[float] | float, note: str = "") -> dict:
    """One reported number: ``name`` in ``unit`` with its sample statistics."""
    values = [samples] if isinstance(samples, int | float) else list(samples)
    return {"name": name, "unit": unit, **summarize(values), "note": note}


def _rates(work: float, times: Iterable[float]) -> list[float]:
    return [work / t for t in times]


# ------------------------------------------------------------------ matmul accounting
_MATMUL_OPS = {
    torch.ops.aten.mm.default: "mm",
    torch.ops.aten.addmm.default: "addmm",
    torch.ops.aten.bmm.default: "bmm",
    torch.ops.aten.baddbmm.default: "baddbmm",
}


def _layout(t: torch.Tensor) -> tuple:
    return (tuple(t.shape), tuple(t.stride()), str(t.dtype).removeprefix("torch."))


class MatmulRecorder(TorchDispatchMode):
    """Records every matrix product dispatched while active (forward and backward).

    ``calls`` counts signatures ``(op, (shape, stride, dtype) of each tensor argument,
    scalar arguments)``; :meth:`flops` sums ``2 n k m`` (times the batch) over them.
    """

    def __init__(self) -> None:
        super().__init__()
        self.calls: Counter = Counter()

    def __torch_dispatch__(self, func, types, args=(), kwargs=None):
        kwargs = kwargs or {}
        name = _MATMUL_OPS.get(func)
        if name is not None:
            tensors = tuple(_layout(a) for a in args if isinstance(a, torch.Tensor))
            scalars = tuple(sorted((k, float(v)) for k, v in kwargs.items()))
            self.calls[(name, tensors, scalars)] += 1
        return func(*args, **kwargs)

    def flops(self, ops: Iterable[str] = ("mm", "addmm", "bmm", "baddbmm")) -> int:
        """Total matmul FLOPs of the recorded products of ``ops``."""
        keep = set(ops)
        return sum(n * signature_flops(sig) for sig, n in self.calls.items() if sig[0] in keep)


def signature_flops(signature: tuple) -> int:
    """FLOPs (``2 n k m``, times the batch for ``bmm``) of one recorded product."""
    name, tensors, _ = signature
    a, b = (tensors[1], tensors[2]) if name in ("addmm", "baddbmm") else tensors[:2]
    if name in ("mm", "addmm"):
        (n, k), (_, m) = a[0], b[0]
        return 2 * n * k * m
    (bt, n, k), (_, _, m) = a[0], b[0]
    return 2 * bt * n * k * m


def _strided_random(layout: tuple, device: torch.device, gen: torch.Generator) -> torch.Tensor:
    shape, stride, dtype = layout
    size = 1 + sum((s - 1) * st for s, st in zip(shape, stride, strict=True) if s > 0)
    buf = torch.randn(size, generator=gen, dtype=getattr(torch, dtype)).to(device)
    return buf.as_strided(shape, stride)


def time_products(
    calls: Mapping[tuple, int],
    repeats: int,
    device: torch.device,
    min_time_s: float = 2e-3,
    seed: int = 0,
) -> list[float]:
    """Re-time every recorded product alone; returns, per repeat, ``sum(count * time)`` (s).

    Each distinct product runs on fresh tensors of its recorded shapes and strides, in a
    loop long enough (``min_time_s``) that the timer's resolution does not matter.
    """
    gen = torch.Generator().manual_seed(seed)
    totals = [0.0] * int(repeats)
    for sig, count in calls.items():
        name, layouts, scalars = sig
        op = getattr(torch.ops.aten, name).default
        args = [_strided_random(lay, device, gen) for lay in layouts]
        kwargs = dict(scalars)

        def call(op=op, args=args, kwargs=kwargs) -> None:
            op(*args, **kwargs)

        call()  # warm-up (allocator, kernel selection)
        synchronize(device)
        t0 = time.perf_counter()
        call()
        synchronize(device)
        once = max(time.perf_counter() - t0, 1e-7)
        loops = max(1, min(1000, int(math.ceil(min_time_s / once))))
        for r in range(int(repeats)):
            synchronize(device)
            t0 = time.perf_counter()
            for _ in range(loops):
                call()
            synchronize(device)
            totals[r] += count * (time.perf_counter() - t0) / loops
    return totals


def siren_matmul_flops(hidden: int, n_layers: int, points: Mapping[str, int]) -> dict[str, int]:
    """Matmul FLOPs of SIREN passes from the layer shapes and the points through each pass.

    Layers: ``n_layers - 1`` sine layers (``2 -> H``, then ``H -> H``) and a linear output
    ``H -> 1``; the explicit input-gradient pass adds one reverse product per sine layer
    (``H x H``, the lowest ``H x 2``). ``points`` (counts of ``(x, y)`` rows):

    * ``height`` / ``height_grad`` — :meth:`~sss2bathy.models.siren.Siren.height` without /
      with a graph (the altimeter loss), backward ``2x`` forward less the input gradient
      of the first layer (the coordinates need none);
    * ``gradient`` / ``gradient_grad`` — :meth:`~sss2bathy.models.siren.Siren.height_and_gradient`
      without a graph (finder) / with one (the normal loss, which uses the gradient only:
      the output layer's product is not back-propagated).

    Returns ``forward``, ``backward`` and ``total`` FLOPs.
    """
    h, s = int(hidden), int(n_layers) - 1
    sine = 2 * (2 * h + (s - 1) * h * h)
    out = 2 * h
    reverse = 2 * ((s - 1) * h * h + 2 * h)
    first_input_grad = 2 * 2 * h
    n = {k: int(points.get(k, 0)) for k in ("height", "height_grad", "gradient", "gradient_grad")}
    forward = (n["height"] + n["height_grad"]) * (sine + out) + (
        n["gradient"] + n["gradient_grad"]
    ) * (sine + out + reverse)
    backward = n["height_grad"] * (2 * (sine + out) - first_input_grad) + n["gradient_grad"] * (
        2 * (sine + reverse) - first_input_grad
    )
    return {"forward": forward, "backward": backward, "total": forward + backward}


# -------------------------------------------------------------------- synthetic scene
def _counting_siren_class():
    from sss2bathy.models.siren import Siren

    class CountingSiren(Siren):
        """A :class:`Siren` that counts the points through each of its passes."""

        def __init__(self, *args: Any, **kwargs: Any) -> None:
            super().__init__(*args, **kwargs)
            self.points: Counter = Counter()

        def height(self, xy: torch.Tensor) -> torch.Tensor:
            self.points["height_grad" if torch.is_grad_enabled() else "height"] += xy.shape[0]
            return super().height(xy)

        forward = height

        def height_and_gradient(self, xy: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
            key = "gradient_grad" if torch.is_grad_enabled() else "gradient"
            self.points[key] += xy.shape[0]
            return super().height_and_gradient(xy)

    return CountingSiren


def synthetic_pings(
    n_pings: int,
    n_bins: int,
    *,
    max_range_m: float = 50.0,
    depth_m: float = 18.0,
    sonar_depth_m: float = 1.5,
    frame_m: tuple[float, float] = (350.0, 300.0),
    altimeter_points: int = 2000,
    n_batches: int = 1,
    seed: int = 0,
) -> tuple[list[dict[str, torch.Tensor]], tuple[float, float, float, float]]:
    """Ping batches of one straight line (paper geometry), without a survey.

    A line heads North through the middle of a ``frame_m`` survey at 2 m/s and 12 pings/s
    with a gentle roll/pitch motion; the sonar is ``sonar_depth_m`` below the surface over
    ``depth_m`` of water. Bins are ``max_range_m / n_bins`` apart; bins closer than the
    altitude are water column (``mask``), the others valid with random targets
    ``n_lat ~ U(-0.4, 0.4)``. Altimeter points lie below random pings at ``-depth_m``.

    Returns:
        ``n_batches`` consecutive batches of ``n_pings`` pings (the keys of
        :mod:`sss2bathy.data.pings`; ``index`` runs over all batches) and the frame bounds
        ``(xmin, ymin, xmax, ymax)`` (m).
    """
    from sss2bathy.geometry import attitude_to_rotation
    from sss2bathy.survey import MASK_WATER_COLUMN

    for name, value in (("n_pings", n_pings), ("n_bins", n_bins), ("n_batches", n_batches)):
        if int(value) < 1:
            raise ValueError(f"{name}: expected >= 1, found {value}")
    gen = torch.Generator().manual_seed(seed)
    total = int(n_pings) * int(n_batches)
    t = torch.arange(total, dtype=torch.float64) / 12.0
    y = 2.0 * t - t[-1]  # centred on the frame
    position = torch.stack(
        [torch.zeros_like(y), y, torch.full_like(y, -float(sonar_depth_m))], 1
    ).float()
    roll = math.radians(1.0) * torch.sin(2 * math.pi * t / 6.0)
    pitch = math.radians(0.5) * torch.cos(2 * math.pi * t / 6.0)
    rotation = attitude_to_rotation(torch.zeros_like(t), pitch, roll).float()
    range_m = torch.linspace(max_range_m / n_bins, max_range_m, int(n_bins))
    altitude = float(depth_m) - float(sonar_depth_m)
    mask = torch.where(range_m < altitude, MASK_WATER_COLUMN, 0).to(torch.uint8)
    batches = []
    for k in range(int(n_batches)):
        sl = slice(k * n_pings, (k + 1) * n_pings)
        pick = torch.randint(int(n_pings), (int(altimeter_points),), generator=gen)
        alt_xy = position[sl][pick, :2]
        altimeter = torch.cat([alt_xy, torch.full((len(pick), 1), -float(depth_m))], 1)
        batches.append(
            {
                "position": position[sl].contiguous(),
                "rotation": rotation[sl].contiguous(),
                "range_m": range_m,
                "n_lat": (torch.rand(n_pings, 2, n_bins, generator=gen) - 0.5) * 0.8,
                "mask": mask.expand(n_pings, 2, n_bins).contiguous(),
                "line": torch.zeros(n_pings, dtype=torch.long),
                "ping": torch.arange(k * n_pings, (k + 1) * n_pings),
                "index": torch.arange(k * n_pings, (k + 1) * n_pings),
                "altimeter": altimeter,
            }
        )
    half_x, half_y = frame_m[0] / 2, frame_m[1] / 2
    return batches, (-half_x, -half_y, half_x, half_y)


def bench_siren(
    hidden: int,
    n_layers: int,
    omega0: float,
    bounds: Sequence[float],
    depth_m: float,
    relief_m: float,
    seed: int,
    counting: bool = False,
    precision: str = "fp32",
):
    """A SIREN surface for the benchmarks: paper init, output range ``-depth_m +- relief_m``.

    A freshly initialised SIREN's output is small (about 1/50 of its range), so
    ``relief_m`` sets the height variations: 50 gives hills of about 1 m with slopes
    around 0.1 (p90 ~0.17) at the paper's ``omega0 = 30`` over 350 m. ``precision`` is the
    SIREN's training precision (:data:`~sss2bathy.models.siren.PRECISIONS`).
    """
    from sss2bathy.models.siren import Siren

    torch.manual_seed(seed)
    cls = _counting_siren_class() if counting else Siren
    z_range = (-depth_m - relief_m, -depth_m + relief_m)
    return cls(hidden, n_layers, omega0, bounds, z_range, precision=precision)


def _to(batch: Mapping[str, torch.Tensor], device: torch.device) -> dict[str, torch.Tensor]:
    return {k: v.to(device) for k, v in batch.items()}


# ------------------------------------------------------------------------- SIREN step
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
    from sss2bathy.models.normal_sensor import NormalSensorModel
    from sss2bathy.models.siren import PRECISIONS
    from sss2bathy.modules.siren import SirenModule
    from sss2bathy.survey import SensorParams
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
    depth = 18.0
    batches, bounds = synthetic_pings(
        n_pings,
        n_bins,
        max_range_m=max_range_m,
        depth_m=depth,
        altimeter_points=altimeter_points,
        n_batches=n_batches,
        seed=seed,
    )
    batches = [_to(b, dev) for b in batches]
    theta_limits = SensorParams(
        math.radians(30.0), math.radians(60.0), 850e3, 1500.0
    ).beam_limits_rad

    def make_run(precision: str) -> dict[str, Any]:
        siren = bench_siren(
            hidden, n_layers, omega0, bounds, depth, relief_m, seed, True, precision
        )
        module = SirenModule(
            siren,
            sensor=NormalSensorModel(),
            optimizer=lambda params: torch.optim.Adam(params, lr=lr),
            log_images=False,
        ).to(dev)
        module.theta_limits = theta_limits
        module.theta_cache = torch.full((n_pings * n_batches, 2, n_bins), torch.nan, device=dev)
        opt = module.configure_optimizers()["optimizer"]
        run: dict[str, Any] = {"k": 0, "valid": [], "iters": [], "times": [], "bound": []}

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

    bins_all = n_pings * 2 * n_bins
    first = runs[names[0]]
    figures: list[dict] = []
    info: dict[str, Any] = {"allocator": vars(allocator), "precisions": {}, "skipped": skipped}
    for p, run in runs.items():
        prefix = "" if p == names[0] else f"{p}: "
        times, bound, valid, rec = run["times"], run["bound"], run["valid"], run["rec"]
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
                [100 * statistics.median(bound) / t for t in times],
                "target >= 70 %" if p == "fp32" else f"of the {p} bound",
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
        info["precisions"][p] = {
            "points": run["points"],
            "analytic_flops": siren_matmul_flops(hidden, n_layers, run["points"]),
            "recorded_siren_flops": rec.flops(("mm", "addmm")),
            "recorded_flops": step_flops,
            "distinct_products": len(rec.calls),
            "products": sum(rec.calls.values()),
            "bound_fraction": statistics.median(bound) / statistics.median(times),
        }
    info.update(info["precisions"][names[0]])
    return {
        "title": SECTION_TITLES["siren_step"],
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
            f"{n_pings} pings x 2 x {n_bins} bins (paper geometry: 50 m range, 16.5 m altitude) "
            f"+ {altimeter_points} altimeter points, {n_layers}-layer width-{hidden} SIREN, "
            "SirenModule.model_step (warm-started finder with the fit's defaults, explicit gradient pass, "
            "normal + height loss) + backward + Adam. Matmul bound: every product of one step "
            "recorded (shape, strides, dtype) and re-timed alone with torch.mm/addmm/bmm. "
            f"Precisions {', '.join(names)} interleaved (bf16: the hidden layers of the "
            "normal-loss gradient pass; finder, heights and map in fp32). Allocator: "
            + ("glibc tuned (mallopt)" if allocator.applied else f"as is ({allocator.reason})")
            + "."
        ),
    }


# ------------------------------------------------------------------------------ finder
def _crossing_points(arcs: Mapping[str, torch.Tensor], theta: torch.Tensor) -> torch.Tensor:
    from sss2bathy.geometry import arc_point

    return arc_point(arcs["sonar"], arcs["R"], arcs["range_m"], theta, arcs["side"])


def _residual_m(surface, arcs: Mapping[str, torch.Tensor], theta: torch.Tensor) -> torch.Tensor:
    with torch.no_grad():
        p = _crossing_points(arcs, torch.nan_to_num(theta))
        return surface.height(p[:, :2].contiguous()) - p[:, 2]


def _agreement(arcs, theta_a, valid_a, theta_b, valid_b) -> dict[str, float]:
    both = valid_a & valid_b
    d = (_crossing_points(arcs, theta_a) - _crossing_points(arcs, theta_b)).norm(dim=-1)
    d = d[both]
    return {
        "same_validity": float((valid_a == valid_b).float().mean()),
        "found_of_reference": float(both.sum() / valid_b.sum().clamp_min(1)),
        "median_point_diff_mm": float(d.median() * 1e3) if d.numel() else float("nan"),
        "max_point_diff_mm": float(d.max() * 1e3) if d.numel() else float("nan"),
    }


def _time_in_turns(
    fns: Mapping[str, Callable[[], Any]],
    repeats: Mapping[str, int],
    warmup: int,
    device: torch.device,
) -> tuple[dict[str, list[float]], dict[str, list[float]]]:
    """Wall and process CPU times (s) of several functions, run in turns (round robin).

    Each round runs every function that still has repeats left, so a background load that
    changes during the measurement weighs on all of them alike (timing one after the other
    would give the first ones a different machine than the last).
    """
    if int(warmup) < 0:
        raise ValueError(f"warmup: expected >= 0, found {warmup}")
    if not repeats or min(int(n) for n in repeats.values()) < 1:
        raise ValueError(f"repeats: expected >= 1 per function, found {dict(repeats)}")
    for _ in range(int(warmup)):
        for fn in fns.values():
            fn()
    wall: dict[str, list[float]] = {k: [] for k in fns}
    cpu: dict[str, list[float]] = {k: [] for k in fns}
    for i in range(max(int(n) for n in repeats.values())):
        for key, fn in fns.items():
            if i >= int(repeats[key]):
                continue
            synchronize(device)
            t0, c0 = time.perf_counter(), time.process_time()
            fn()
            synchronize(device)
            wall[key].append(time.perf_counter() - t0)
            cpu[key].append(time.process_time() - c0)
    return wall, cpu


def bench_finder(
    *,
    n_pings: int = 64,
    n_bins: int = 512,
    max_range_m: float = 50.0,
    hidden: int = 128,
    n_layers: int = 5,
    omega0: float = 30.0,
    relief_m: float = 50.0,
    perturb: float = 2e-3,
    tol_m: float = 1e-3,
    gd_max_iter: int = 2000,
    warmup: int = 1,
    repeats: int = 5,
    gd_repeats: int = 3,
    device: str | torch.device | None = None,
    seed: int = 0,
) -> dict:
    """The intersection finder on one batch: paper gradient descent vs Newton and secant.

    Gradient descent is given as many steps as its slowest converging bin needs (found in
    an untimed run capped at ``gd_max_iter``), so it stops as soon as it has reached the
    accuracy it can reach; the bins without a crossing run all of them, as in the paper.
    Newton and the secant solver (height-only) run with the finder's defaults: the cold
    scan (slope-bounded steps, ``n_scan`` resolution) and then their refinement.

    The warm start is the cold Newton solution on the SIREN, used on a copy whose weights
    moved by ``perturb`` (relative, Gaussian; a fit's next epoch): the root-mean-square
    height change is reported. Accuracy is the same for all (``|f| <= tol_m``); agreement
    compares valid bins and crossing points with Newton on the same surface. All solvers
    are timed in turns (:func:`_time_in_turns`); the SIREN counts the points of its height
    and height-with-gradient passes, reported per bin for each solver.
    """
    from sss2bathy.models.intersection import find_intersections
    from sss2bathy.survey import SensorParams

    dev = resolve_device(device)
    depth = 18.0
    (batch,), bounds = synthetic_pings(
        n_pings, n_bins, max_range_m=max_range_m, depth_m=depth, altimeter_points=1, seed=seed
    )
    batch = _to(batch, dev)
    surface = bench_siren(hidden, n_layers, omega0, bounds, depth, relief_m, seed, True).to(dev)
    moved = copy.deepcopy(surface)
    gen = torch.Generator().manual_seed(seed + 1)
    with torch.no_grad():
        for p in moved.parameters():
            p.add_(perturb * p.abs().mean() * torch.randn(p.shape, generator=gen).to(dev))
    pi, si, bi = (batch["mask"] == 0).nonzero(as_tuple=True)
    arcs = {
        "sonar": batch["position"][pi],
        "R": batch["rotation"][pi],
        "range_m": batch["range_m"][bi],
        "side": si,
    }
    limits = SensorParams(math.radians(30.0), math.radians(60.0), 850e3, 1500.0).beam_limits_rad

    def solve(surf, solver: str, theta0=None, max_iter=None):
        return find_intersections(
            surf,
            arcs["sonar"],
            arcs["R"],
            arcs["range_m"],
            arcs["side"],
            limits,
            solver=solver,
            theta0=theta0,
            max_iter=max_iter,
            tol_m=tol_m,
        )

    ref_theta, ref_valid, _ = solve(surface, "newton")
    theta0 = torch.where(ref_valid, ref_theta, torch.inf)
    moved_theta, moved_valid, _ = solve(moved, "newton")
    # Gradient descent runs a fixed number of steps on the bins that never converge (no
    # crossing in the beam): give it just the steps its slowest converging bin needs.
    gd_iters = {}
    for key, surf, t0 in (("gd", surface, None), ("gd_warm", moved, theta0)):
        _, valid, n_iter = solve(surf, "gd", t0, gd_max_iter)
        gd_iters[key] = int(n_iter[valid].max()) if bool(valid.any()) else gd_max_iter
    cold, warm = (ref_theta, ref_valid), (moved_theta, moved_valid)
    runs = {
        "gd": (surface, "gd", None, gd_iters["gd"], gd_repeats, cold),
        "newton": (surface, "newton", None, None, repeats, cold),
        "secant": (surface, "secant", None, None, repeats, cold),
        "gd_warm": (moved, "gd", theta0, gd_iters["gd_warm"], gd_repeats, warm),
        "newton_warm": (moved, "newton", theta0, None, repeats, warm),
        "secant_warm": (moved, "secant", theta0, None, repeats, warm),
    }
    labels = {
        "gd": "paper GD (eq. 12), cold",
        "newton": "Newton, cold",
        "secant": "secant (height-only), cold",
        "gd_warm": "paper GD, warm",
        "newton_warm": "Newton, warm",
        "secant_warm": "secant, warm",
    }
    results: dict[str, dict[str, Any]] = {key: {} for key in runs}

    def runner(key: str) -> Callable[[], None]:
        surf, solver, t0, max_iter, _, _ = runs[key]

        def run() -> None:
            before = Counter(surf.points)
            results[key]["out"] = solve(surf, solver, t0, max_iter)
            results[key]["points"] = Counter(surf.points) - before

        return run

    times, cpu_times = _time_in_turns(
        {key: runner(key) for key in runs},
        {key: run[4] for key, run in runs.items()},
        warmup,
        dev,
    )
    detail: dict[str, dict] = {}
    figures = []
    n_bins_used = int(pi.numel())
    for key, (surf, _, _, _, _, (r_theta, r_valid)) in runs.items():
        theta, valid, n_iter = results[key]["out"]
        points = results[key]["points"]
        res = _residual_m(surf, arcs, theta)[valid].abs()
        it = n_iter[valid].float()
        detail[key] = {
            "valid": int(valid.sum()),
            "iters_mean": float(it.mean()) if it.numel() else float("nan"),
            "iters_max": int(it.max()) if it.numel() else 0,
            "heights_per_bin": points["height"] / max(n_bins_used, 1),
            "gradients_per_bin": points["gradient"] / max(n_bins_used, 1),
            "max_residual_mm": float(res.max() * 1e3) if res.numel() else float("nan"),
            **_agreement(arcs, theta, valid, r_theta, r_valid),
        }
        d = detail[key]
        figures.append(
            figure(
                f"{labels[key]}: time per batch",
                "s",
                times[key],
                f"{d['valid']} valid; evals/bin {d['iters_mean']:.1f} (max {d['iters_max']}); "
                f"surface passes/bin: {d['heights_per_bin']:.2f} heights + "
                f"{d['gradients_per_bin']:.2f} with gradient; "
                f"finds {100 * d['found_of_reference']:.1f} % of Newton's, "
                f"points within {d['max_point_diff_mm']:.1f} mm",
            )
        )
    med = {k: statistics.median(v) for k, v in times.items()}
    cpu_med = {k: statistics.median(v) for k, v in cpu_times.items()}
    pairs = {
        "gd / newton (cold)": ("gd", "newton"),
        "gd / secant (cold)": ("gd", "secant"),
        "gd / newton_warm": ("gd", "newton_warm"),
        "gd_warm / newton_warm": ("gd_warm", "newton_warm"),
        "gd_warm / secant_warm": ("gd_warm", "secant_warm"),
    }
    speedups = {name: med[a] / med[b] for name, (a, b) in pairs.items()}
    cpu_speedups = {name: cpu_med[a] / max(cpu_med[b], 1e-9) for name, (a, b) in pairs.items()}
    for name, value in speedups.items():
        note = "target >= 5x" if "(cold)" in name else ""
        figures.append(figure(f"speed-up {name}", "x", value, note))
    with torch.no_grad():
        xy = _crossing_points(arcs, torch.nan_to_num(ref_theta))[ref_valid][:, :2]
        dz = moved.height(xy) - surface.height(xy)
        _, grad = surface.height_and_gradient(xy)
    slope = grad.norm(dim=-1)
    return {
        "title": SECTION_TITLES["finder"],
        "params": {
            "n_pings": n_pings,
            "n_bins": n_bins,
            "bins_solved": n_bins_used,
            "tol_m": tol_m,
            "gd_max_iter": gd_max_iter,
            "gd_iterations_run": gd_iters,
            "siren": f"{n_layers} x {hidden}, omega0 {omega0}",
            "device": str(dev),
        },
        "figures": figures,
        "info": {
            "solvers": detail,
            "speedups": speedups,
            "cpu_time_speedups": cpu_speedups,
            "warm_start_height_change_rms_m": float(dz.pow(2).mean().sqrt()),
            "surface_slope_median": float(slope.median()),
            "surface_slope_p90": float(slope.quantile(0.9)),
        },
        "notes": (
            f"{n_bins_used} non-water-column bins of {n_pings} pings over a SIREN surface "
            f"(slope median {float(slope.median()):.3f}, p90 {float(slope.quantile(0.9)):.3f}), "
            f"all to |f| <= {tol_m * 1e3:g} mm. Warm: the crossings of the cold solve, on a "
            f"surface moved by {float(dz.pow(2).mean().sqrt()) * 1e3:.1f} mm RMS. 'evals' = "
            "solver evaluations per bin (with a derivative for GD and Newton, height-only for "
            "the secant); 'surface passes' count every point through the SIREN, the cold "
            "scan's and warm brackets' heights included (a height with gradient costs about "
            "2.4 heights on CPU). Newton and secant share the cold scan (slope-bounded steps "
            "from the beam's upper edge, finder defaults). Solvers timed in turns (round "
            "robin) so that a varying background load weighs on all alike; "
            "info.cpu_time_speedups gives the same ratios in process CPU time. Agreement vs "
            "Newton on the same surface."
        ),
    }


# --------------------------------------------------------------------------------- CNN
def cnn_sizes(conf_dir: Path = _CONF) -> dict[str, dict[str, int]]:
    """Network width, residual blocks and batch per scale from ``conf/experiment/cnn.yaml``."""
    from omegaconf import OmegaConf

    cfg = OmegaConf.load(Path(conf_dir) / "experiment" / "cnn.yaml")
    return {
        scale: {k: int(v[k]) for k in ("base_width", "n_blocks", "batch_size")}
        for scale, v in cfg.cnn_scale.items()
    }


def bench_cnn(
    *,
    configs: Mapping[str, Mapping[str, int]] | None = None,
    window: tuple[int, int] = (64, 512),
    max_batch: int | None = None,
    warmup: int = 1,
    repeats: int = 5,
    lr: float = 2e-4,
    device: str | torch.device | None = None,
    seed: int = 0,
) -> dict:
    """CNN training steps (forward, normal-aware loss + TV, backward, Adam): windows/s.

    Args:
        configs: ``{name: {base_width, n_blocks, batch_size}}``; default the demo and paper
            sizes of ``conf/experiment/cnn.yaml``.
        window: ``(pings, bins)`` of a window.
        max_batch: cap on the batch (CPU: the paper's batch of 64 takes minutes a step);
            windows/s is reported for the batch actually run.
    """
    from omegaconf import OmegaConf

    from sss2bathy.losses.normal import NormalLoss
    from sss2bathy.models.normal_cnn import NormalResNet

    dev = resolve_device(device)
    if configs is None:
        sizes = cnn_sizes()
        configs = {k: sizes[k] for k in ("demo", "paper")}
    loss_cfg = OmegaConf.to_container(OmegaConf.load(_CONF / "loss" / "normal_aware.yaml"))
    loss_fn = NormalLoss.from_config(loss_cfg)
    figures, params = [], {}
    for name, c in configs.items():
        torch.manual_seed(seed)
        batch = int(c["batch_size"]) if max_batch is None else min(int(c["batch_size"]), max_batch)
        net = NormalResNet(base_width=int(c["base_width"]), n_blocks=int(c["n_blocks"])).to(dev)
        opt = torch.optim.Adam(net.parameters(), lr=lr)
        gen = torch.Generator().manual_seed(seed)
        h, w = window
        x = torch.rand(batch, 1, h, w, generator=gen).to(dev)
        target = ((torch.rand(batch, 1, h, w, generator=gen) - 0.5) * 0.8).to(dev)
        mask = (torch.rand(batch, 1, h, w, generator=gen) < 0.8).to(dev)

        def step(net=net, opt=opt, x=x, target=target, mask=mask) -> None:
            opt.zero_grad(set_to_none=True)
            loss_fn(net(x), target, mask)["loss"].backward()
            opt.step()

        times = time_runs(step, warmup, repeats, dev)
        note = f"width {c['base_width']}, {c['n_blocks']} blocks, batch {batch}"
        if batch != int(c["batch_size"]):
            note += f" (configured {c['batch_size']}; capped on {dev.type})"
        figures.append(figure(f"{name}: windows/s", "windows/s", _rates(batch, times), note))
        figures.append(figure(f"{name}: step time", "s", times))
        params[name] = {**{k: int(v) for k, v in c.items()}, "batch_run": batch}
    return {
        "title": SECTION_TITLES["cnn"],
        "params": {"window": list(window), "configs": params, "device": str(dev)},
        "figures": figures,
        "info": {},
        "notes": (
            f"NormalResNet + NormalLoss (conf/loss/normal_aware.yaml) + Adam on random "
            f"{window[0]} x {window[1]} windows, 80 % valid pixels."
        ),
    }


# ------------------------------------------------------------------------ simulator
def survey_preset(survey: str, scale: str, conf_dir: Path = _CONF) -> dict:
    """Plain ``data.survey`` dict of a synthetic preset at a scale (as Hydra composes it)."""
    from omegaconf import OmegaConf

    conf_dir = Path(conf_dir)
    base_path = conf_dir / "data" / "survey" / f"{survey}.yaml"
    sized_path = conf_dir / "survey_scale" / f"{survey}_{scale}.yaml"
    for path in (base_path, sized_path):
        if not path.is_file():
            raise ValueError(f"survey/scale: expected a config at {path}, found none")
    root = OmegaConf.create({"scale": {"name": scale}, "data": {"survey": {}}})
    root.data.survey = OmegaConf.merge(OmegaConf.load(base_path), OmegaConf.load(sized_path))
    return OmegaConf.to_container(root.data.survey, resolve=True)


def bench_sim(
    *,
    survey: str = "synthetic_d1",
    scale: str = "demo",
    n_pings: int = 64,
    warmup: int = 1,
    repeats: int = 3,
    seed: int = 0,
) -> dict:
    """The sidescan simulator (ray-traced pings of both heads + receiver): pings/s.

    The preset's terrain is generated and its survey planned (untimed); the first
    ``n_pings`` pings of the first planned line are then simulated repeatedly.
    """
    from sss2bathy.sim.config import SyntheticSurveyConfig
    from sss2bathy.sim.plan import plan_survey
    from sss2bathy.sim.sonar import (
        MaterialResponse,
        RayCaster,
        absorption_db_per_m,
        calibrate_receiver,
        receive,
        simulate_pings,
    )
    from sss2bathy.sim.terrain import TerrainSurface, generate_terrain

    cfg = SyntheticSurveyConfig.from_mapping(survey_preset(survey, scale))
    t0 = time.perf_counter()
    terrain = generate_terrain(cfg.terrain, cfg.materials, np.random.default_rng([seed, 0]))
    t_terrain = time.perf_counter() - t0
    line = plan_survey(cfg.plan, cfg.sonar, terrain, np.random.default_rng([seed, 1]))[0]
    n = min(int(n_pings), len(line.time_s))
    sonar = cfg.sonar
    absorption = absorption_db_per_m(
        sonar.frequency_hz, sonar.temperature_c, sonar.salinity_ppt, sonar.ph
    )
    response = MaterialResponse.from_params(cfg.materials)
    t0 = time.perf_counter()
    caster, surface = RayCaster(terrain.to_mesh()), TerrainSurface(terrain)
    t_mesh = time.perf_counter() - t0
    calibration = calibrate_receiver(
        sonar,
        response,
        cfg.materials.index(cfg.materials.reference_material),
        min(float(np.median(line.altitude_m)), 0.8 * sonar.max_range_m),
        absorption,
    )

    def run() -> None:
        rng = np.random.default_rng([seed, 3])
        echoes = simulate_pings(
            caster,
            surface,
            line.position[:n],
            line.rotation[:n],
            sonar,
            response,
            rng,
            absorption_db_m=absorption,
            altitudes=line.altitude_m[:n],
        )
        receive(echoes.power_raw, sonar, calibration, rng, absorption)

    times = time_runs(run, warmup, repeats)
    rays_per_head = sonar.n_raw_bins * sonar.rays_per_raw_bin
    figures = [
        figure("pings/s (both heads)", "pings/s", _rates(n, times)),
        figure("time per 1000 pings", "s", [1000 * t / n for t in times]),
    ]
    return {
        "title": SECTION_TITLES["sim"],
        "params": {
            "preset": f"{survey} {scale}",
            "n_pings": n,
            "n_bins": sonar.n_bins,
            "raw_bins": sonar.n_raw_bins,
            "faces": int(len(caster.mesh.faces)) if hasattr(caster, "mesh") else None,
        },
        "figures": figures,
        "info": {"terrain_s": round(t_terrain, 3), "mesh_and_bvh_s": round(t_mesh, 3)},
        "notes": (
            f"simulate_pings + receive on the {survey} {scale} preset ({sonar.n_bins} bins, "
            f"{sonar.n_raw_bins} raw bins, about {rays_per_head:.0f}+ rays per head and ping), "
            f"first {n} pings of the first planned line; terrain and mesh untimed."
        ),
    }


# ----------------------------------------------------------------------------- draping
def bench_drape(
    *,
    n_pings: int = 1000,
    n_bins: int = 512,
    size_m: float = 300.0,
    cell_m: float = 0.5,
    engine: str = "auto",
    warmup: int = 1,
    repeats: int = 3,
) -> dict:
    """Draping rays/s against casting the same rays with the bare intersector.

    The scene and the ray recording are :mod:`sss2bathy.draping.benchmark`'s. "Raw" is
    embreex's first-hit call on the recorded rays, already float32 in the scene's frame
    (no conversion, no bookkeeping), one thread like draping; trimesh's embree wrapper
    (``intersects_first``, the previous baseline, which converts and normalises per
    call) is reported too. Draping and the casts run interleaved; ratios are per repeat.
    """
    from sss2bathy.draping.benchmark import (
        bench_line,
        bench_terrain,
        count_rays,
        raw_cast,
        record_rays,
        trimesh_cast,
    )
    from sss2bathy.draping.config import DrapeConfig
    from sss2bathy.draping.drape import drape_line
    from sss2bathy.draping.surface import DrapeSurface

    grid = bench_terrain(size_m=size_m, cell=cell_m)
    line = bench_line(int(n_pings), int(n_bins))
    t0 = time.perf_counter()
    surface = DrapeSurface.from_grid(grid, engine=engine)
    surface.first_hits(line.position[:1], np.array([[0.0, 0.0, -1.0]]))  # builds the BVH
    t_build = time.perf_counter() - t0
    cfg = DrapeConfig(engine=engine)
    batches = record_rays(line, surface, cfg)
    n_rays = count_rays(batches)
    fns: dict[str, Callable[[], Any]] = {
        "drape": lambda: drape_line(line, surface, cfg),
        "raw": raw_cast(surface, batches),
    }
    wrapped = trimesh_cast(surface, batches)
    if wrapped is not None:
        fns["trimesh"] = wrapped
    times, _ = _time_in_turns(fns, dict.fromkeys(fns, repeats), warmup, torch.device("cpu"))
    t_drape, t_raw = times["drape"], times["raw"]
    figures = [
        figure("draping rays/s", "rays/s", _rates(n_rays, t_drape)),
        figure(
            "raw embree rays/s",
            "rays/s",
            _rates(n_rays, t_raw),
            "same rays, bare first-hit call, 1 thread",
        ),
        figure(
            "draping / raw throughput",
            "%",
            [100 * r / d for r, d in zip(t_raw, t_drape, strict=True)],
            "target >= 50 %",
        ),
    ]
    if "trimesh" in times:
        t_wrap = times["trimesh"]
        figures += [
            figure(
                "trimesh intersects_first rays/s",
                "rays/s",
                _rates(n_rays, t_wrap),
                "same rays via trimesh's embree wrapper (previous baseline)",
            ),
            figure(
                "draping / trimesh intersects_first",
                "%",
                [100 * w / d for w, d in zip(t_wrap, t_drape, strict=True)],
            ),
        ]
    figures.append(
        figure("draping time per 1000 pings", "s", [1000 * t / n_pings for t in t_drape])
    )
    return {
        "title": SECTION_TITLES["drape"],
        "params": {
            "engine": surface.engine,
            "n_pings": int(n_pings),
            "n_bins": int(n_bins),
            "faces": int(len(surface.mesh.faces)),
            "rays": int(n_rays),
            "pings_per_chunk": int(cfg.pings_per_chunk),
        },
        "figures": figures,
        "info": {"surface_build_s": round(t_build, 3)},
        "notes": (
            f"drape_line of a {n_pings}-ping line ({n_bins} bins per side) on the draping "
            f"benchmark's {size_m:g} m seabed ({len(surface.mesh.faces)} faces, "
            f"{surface.engine}), {n_rays / (2 * n_pings):.0f} rays per ping and head; "
            "one thread; draping and bare casts interleaved."
        ),
    }


# ------------------------------------------------------------------------ demo stages
def demo_stage_times(path: str | Path) -> dict:
    """The stage wall times of the last ``make demo`` (``stage_times.json``), as figures."""
    path = Path(path)
    if not path.is_file():
        return {
            "title": SECTION_TITLES["demo_stages"],
            "params": {"file": str(path)},
            "figures": [],
            "info": {"missing": True},
            "notes": f"{path} not found: run `make demo` first (not re-run here).",
        }
    data = json.loads(path.read_text())
    seconds = data.get("seconds")
    if not isinstance(seconds, Mapping):
        raise ValueError(f"{path}: expected a 'seconds' mapping of stage times, found {data!r}")
    figures = [figure(str(stage), "s", float(t), "one run") for stage, t in seconds.items()]
    stamp = datetime.fromtimestamp(path.stat().st_mtime, timezone.utc).isoformat(timespec="seconds")
    return {
        "title": SECTION_TITLES["demo_stages"],
        "params": {"file": str(path), "scale": data.get("scale"), "written": stamp},
        "figures": figures,
        "info": {},
        "notes": f"wall times of each stage of the last `make demo` ({stamp}), read from {path}.",
    }


# ------------------------------------------------------------------------------ runner
QUICK: dict[str, dict[str, Any]] = {
    "siren_step": {"warmup": 1, "repeats": 3, "mm_repeats": 2, "n_batches": 2},
    "finder": {"n_pings": 16, "warmup": 1, "repeats": 3, "gd_repeats": 2},
    "cnn": {"warmup": 1, "repeats": 3},
    "sim": {"n_pings": 24, "warmup": 1, "repeats": 3},
    "drape": {"n_pings": 200, "warmup": 1, "repeats": 3},
}
FULL: dict[str, dict[str, Any]] = {
    "siren_step": {"warmup": 2, "repeats": 15, "mm_repeats": 5, "n_batches": 4},
    "finder": {"n_pings": 64, "warmup": 1, "repeats": 7, "gd_repeats": 3},
    "cnn": {"warmup": 1, "repeats": 5},
    "sim": {"n_pings": 96, "warmup": 1, "repeats": 5},
    "drape": {"n_pings": 1000, "warmup": 1, "repeats": 5},
}
# on a CPU the paper's CNN batch of 64 takes minutes per step: windows/s from a smaller one
CPU_CNN_MAX_BATCH = {"quick": 2, "full": 4}


def _cpu_clock() -> tuple[float, float, float] | None:
    """(busy CPU seconds of the machine, of this process, wall time); Linux only."""
    try:
        fields = Path("/proc/stat").read_text().splitlines()[0].split()[1:]
    except (OSError, IndexError):
        return None
    ticks = [float(v) for v in fields]
    idle = ticks[3] + (ticks[4] if len(ticks) > 4 else 0.0)  # idle + iowait
    hz = float(os.sysconf("SC_CLK_TCK"))
    t = os.times()
    own = t.user + t.system + t.children_user + t.children_system
    return (sum(ticks) - idle) / hz, own, time.perf_counter()


def other_load(start: tuple | None, end: tuple | None) -> float | None:
    """Cores kept busy by *other* processes between two :func:`_cpu_clock` readings."""
    if start is None or end is None or end[2] <= start[2]:
        return None
    return max(0.0, ((end[0] - start[0]) - (end[1] - start[1])) / (end[2] - start[2]))


def machine_info(device: torch.device) -> dict[str, Any]:
    """What the numbers were measured on."""
    cpu = platform.processor() or platform.machine()
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    info: dict[str, Any] = {
        "cpu": cpu,
        "cpu_count": os.cpu_count(),
        "torch": torch.__version__,
        "torch_threads": torch.get_num_threads(),
        "device": str(device),
        "python": platform.python_version(),
        "ld_preload": os.environ.get("LD_PRELOAD", ""),
    }
    if device.type == "cuda":
        info["gpu"] = torch.cuda.get_device_name(device)
    return info


def run_benchmarks(
    only: Sequence[str] | None = None,
    quick: bool = False,
    device: str | torch.device | None = None,
    stage_times: str | Path | None = None,
    overrides: Mapping[str, Mapping[str, Any]] | None = None,
    progress: Callable[[str], None] | None = None,
) -> dict:
    """Run the chosen sections (default all) and return the results document.

    Args:
        only: section names among :data:`SECTIONS`; ``None`` = all.
        quick: the short sizes of :data:`QUICK` (else :data:`FULL`).
        device: ``"auto"``/``None`` (CUDA if present), ``"cpu"``, ``"cuda"``.
        stage_times: the demo's ``stage_times.json`` (default ``outputs/report/`` of the
            project).
        overrides: per-section keyword arguments replacing the preset's.
        progress: called with a line per finished section.
    """
    names = list(SECTIONS) if only is None else list(only)
    unknown = sorted(set(names) - set(SECTIONS))
    if unknown or not names:
        raise ValueError(f"only: expected names among {SECTIONS}, found {names}")
    dev = resolve_device(device)
    mode = "quick" if quick else "full"
    preset = QUICK if quick else FULL
    overrides = overrides or {}
    stage_times = (
        stage_times or Path(__file__).resolve().parents[2] / "outputs/report/stage_times.json"
    )
    doc: dict[str, Any] = {
        "created": datetime.now(timezone.utc).isoformat(timespec="seconds"),
        "mode": mode,
        "machine": machine_info(dev),
        "load_avg_start": list(os.getloadavg()),
        "sections": {},
    }
    t_all = time.perf_counter()
    clock0 = _cpu_clock()
    for name in names:
        kwargs = {**preset.get(name, {}), **overrides.get(name, {})}
        t0 = time.perf_counter()
        if name == "siren_step":
            result = bench_siren_step(device=dev, **kwargs)
        elif name == "finder":
            result = bench_finder(device=dev, **kwargs)
        elif name == "cnn":
            if dev.type == "cpu":
                kwargs.setdefault("max_batch", CPU_CNN_MAX_BATCH[mode])
            result = bench_cnn(device=dev, **kwargs)
        elif name == "sim":
            result = bench_sim(**kwargs)
        elif name == "drape":
            result = bench_drape(**kwargs)
        else:
            result = demo_stage_times(kwargs.get("path", stage_times))
        result["seconds"] = round(time.perf_counter() - t0, 2)
        doc["sections"][name] = result
        if progress is not None:
            progress(f"{name}: {result['seconds']:.1f} s")
    if "siren_step" in doc["sections"]:
        # derived, not measured: the paper-scale fit from the measured step (projection.py)
        from sss2bathy.eval.projection import projection_section

        proj = projection_section(doc["sections"]["siren_step"])
        proj.update(title=SECTION_TITLES["gpu_projection"], seconds=0.0)
        doc["sections"]["gpu_projection"] = proj
    doc["seconds"] = round(time.perf_counter() - t_all, 2)
    doc["load_avg_end"] = list(os.getloadavg())
    doc["other_load_cores"] = other_load(clock0, _cpu_clock())
    return doc


# ------------------------------------------------------------------------------ report
def _fmt(value: float) -> str:
    if not math.isfinite(value):
        return str(value)
    a = abs(value)
    if a >= 1e6:
        return f"{value / 1e6:.3g} M"
    if a >= 1e4:
        return f"{value / 1e3:.3g} k"
    if a >= 100:
        return f"{value:.0f}"
    return f"{value:.3g}"


def to_markdown(doc: Mapping[str, Any]) -> str:
    """The results document as a Markdown table with a header and per-section notes."""
    m = doc["machine"]
    device = m.get("gpu") or f"{m['device']} ({m['torch_threads']} threads)"
    load0 = ", ".join(f"{v:.2f}" for v in doc["load_avg_start"])
    load1 = ", ".join(f"{v:.2f}" for v in doc.get("load_avg_end", doc["load_avg_start"]))
    lines = [
        "# sss2bathy benchmarks",
        "",
        f"{doc['created']} · mode `{doc['mode']}` · {m['cpu']} ({m['cpu_count']} cores) · "
        f"torch {m['torch']} · device {device} · load average {load0} -> {load1} · "
        f"{doc.get('seconds', 0):.0f} s",
        "",
        "Median of repeated runs after warm-up; spread = min - max and inter-quartile range.",
        "",
    ]
    others = doc.get("other_load_cores")
    if others is not None:
        lines[2] += f" · other processes used {others:.2f} cores meanwhile"
        if others > 0.25:
            lines += [
                f"**Warning:** other processes kept {others:.2f} of {m['cpu_count']} cores "
                "busy during the run: CPU timings are pessimistic and noisy.",
                "",
            ]
    lines += [
        "| Benchmark | Figure | Median | Unit | Min - max | IQR | n | Note |",
        "|---|---|---:|---|---|---|---:|---|",
    ]
    for section in doc["sections"].values():
        for f in section["figures"]:
            single = f["n"] == 1
            spread = "" if single else f"{_fmt(f['min'])} - {_fmt(f['max'])}"
            iqr = "" if single else f"{_fmt(f['q1'])} - {_fmt(f['q3'])}"
            lines.append(
                f"| {section['title']} | {f['name']} | {_fmt(f['median'])} | {f['unit']} | "
                f"{spread} | {iqr} | {f['n']} | {f['note']} |"
            )
    lines += ["", "Notes:", ""]
    for section in doc["sections"].values():
        lines.append(f"- **{section['title']}** ({section['seconds']:.0f} s): {section['notes']}")
    return "\n".join(lines) + "\n"


def _jsonable(obj: Any) -> Any:
    if isinstance(obj, Mapping):
        return {str(k): _jsonable(v) for k, v in obj.items()}
    if isinstance(obj, list | tuple):
        return [_jsonable(v) for v in obj]
    if isinstance(obj, torch.Tensor | np.generic):
        return obj.item()
    if isinstance(obj, float) and not math.isfinite(obj):
        return None
    return obj


def write_report(doc: Mapping[str, Any], out_dir: str | Path) -> dict[str, Path]:
    """Write ``bench.json`` and ``bench.md`` under ``out_dir`` (atomically)."""
    out = Path(out_dir)
    paths = {"json": out / "bench.json", "markdown": out / "bench.md"}
    atomic_write_text(paths["json"], json.dumps(_jsonable(doc), indent=2) + "\n")
    atomic_write_text(paths["markdown"], to_markdown(doc))
    return paths
