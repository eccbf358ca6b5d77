"""The one timing helper of the benchmarks: devices, warm-up, repeats, medians.

Every timed figure is measured after warm-up runs and reported as the median of repeated
runs with its spread (min, max, quartiles). On CUDA the device is synchronised before and
after each run, so a run's time covers the kernels it queued.
"""

from __future__ import annotations

import statistics
import time
from collections.abc import Callable, Iterable, Mapping, Sequence
from typing import Any

import torch


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
    wall, _ = time_in_turns({"fn": fn}, {"fn": repeats}, warmup, device)
    return wall["fn"]


def time_in_turns(
    fns: Mapping[str, Callable[[], Any]],
    repeats: Mapping[str, int],
    warmup: int,
    device: torch.device | None = None,
) -> tuple[dict[str, list[float]], dict[str, list[float]]]:
    """Wall and process CPU times (s) of several functions, run in turns (round robin).

    Each function is called ``warmup`` times untimed, then each round runs every function
    that still has repeats left, so a background load that changes during the measurement
    weighs on all of them alike (timing one after the other would give the first ones a
    different machine than the last).
    """
    if int(warmup) < 0:
        raise ValueError(f"warmup: expected >= 0, found {warmup}")
    if not repeats or min(int(n) for n in repeats.values()) < 1:
        raise ValueError(f"repeats: expected >= 1 per function, found {dict(repeats)}")
    missing = sorted(set(fns) - set(repeats))
    if missing:
        raise ValueError(f"repeats: expected a count for every function, found none for {missing}")
    dev = device or torch.device("cpu")
    for _ in range(int(warmup)):
        for fn in fns.values():
            fn()
    wall: dict[str, list[float]] = {k: [] for k in fns}
    cpu: dict[str, list[float]] = {k: [] for k in fns}
    for i in range(max(int(repeats[k]) for k in fns)):
        for key, fn in fns.items():
            if i >= int(repeats[key]):
                continue
            synchronize(dev)
            t0, c0 = time.perf_counter(), time.process_time()
            fn()
            synchronize(dev)
            wall[key].append(time.perf_counter() - t0)
            cpu[key].append(time.process_time() - c0)
    return wall, cpu


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


def rates(work: float, times: Iterable[float]) -> list[float]:
    """``work / t`` for each time ``t`` (s): a throughput per repeat."""
    return [work / t for t in times]
