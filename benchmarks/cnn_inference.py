"""CNN inference at a scale's size (issue 20, Build 4): windows/s of the normal network's
forward pass in each variant, interleaved in one run (medians), and the projected time
for a survey's lines.

Variants: ``fp32`` (``torch.no_grad``, contiguous), ``fp32_cl`` (``channels_last``),
``bf16`` (CPU autocast to bfloat16), ``bf16_cl``; each under ``torch.inference_mode``.
Random weights: the cost of a forward pass does not depend on them.

    python -m benchmarks.cnn_inference --base-width 64 --n-blocks 7 --batch 8 --repeats 3
"""

from __future__ import annotations

import argparse
import json
import statistics
import time
from collections.abc import Sequence

import torch

VARIANTS = ("fp32", "fp32_cl", "bf16", "bf16_cl")


def survey_windows(
    n_lines: int = 12, pings: int = 2000, bins: int = 512, window=(64, 512), overlap=0.75
) -> int:
    """Windows the CNN stage runs over ``n_lines`` lines (both heads)."""
    from sss2bathy.data.windows import line_windows

    return 2 * n_lines * len(line_windows(pings, bins, window[0], window[1], overlap))


def bench(
    base_width: int = 64,
    n_blocks: int = 7,
    batch: int = 8,
    window: tuple[int, int] = (64, 512),
    repeats: int = 3,
    variants: Sequence[str] = VARIANTS,
    seed: int = 0,
) -> dict:
    """``{variant: windows/s (median)}`` plus the per-repeat times, interleaved A, B, ..."""
    from sss2bathy.models.normal_cnn import NormalResNet

    bad = [v for v in variants if v not in VARIANTS]
    if bad:
        raise ValueError(f"variants: expected some of {VARIANTS}, found {bad}")
    torch.manual_seed(seed)
    net = NormalResNet(in_channels=1, base_width=base_width, n_blocks=n_blocks).eval()
    nets = {"cl": net.to(memory_format=torch.channels_last)}
    x = torch.randn(batch, 1, *window)
    inputs = {"": x, "cl": x.contiguous(memory_format=torch.channels_last)}
    contiguous = NormalResNet(in_channels=1, base_width=base_width, n_blocks=n_blocks).eval()
    contiguous.load_state_dict(net.state_dict())
    nets[""] = contiguous

    def run(variant: str) -> tuple[float, float]:
        fmt = "cl" if variant.endswith("_cl") else ""
        low = variant.startswith("bf16")
        t0, c0 = time.perf_counter(), time.process_time()
        with (
            torch.inference_mode(),
            torch.autocast("cpu", dtype=torch.bfloat16, enabled=low),
        ):
            nets[fmt](inputs[fmt])
        return time.perf_counter() - t0, time.process_time() - c0

    for v in variants:  # warm-up (oneDNN primitive creation)
        run(v)
    times: dict[str, list[float]] = {v: [] for v in variants}
    cpu: dict[str, list[float]] = {v: [] for v in variants}
    for _ in range(repeats):
        for v in variants:
            wall, busy = run(v)
            times[v].append(wall)
            cpu[v].append(busy)
    med = {v: batch / statistics.median(t) for v, t in times.items()}
    cpu_rate = {v: batch / statistics.median(t) for v, t in cpu.items()}
    n = survey_windows(window=window)
    threads = torch.get_num_threads()
    return {
        "config": {"base_width": base_width, "n_blocks": n_blocks, "batch": batch,
                   "window": list(window), "threads": torch.get_num_threads()},
        "windows_per_s": med,
        "ratio_to_fp32": {v: med[v] / med["fp32"] for v in variants} if "fp32" in med else {},
        "survey_windows_12_lines": n,
        "projected_min_12_lines": {v: n / r / 60 for v, r in med.items()},
        # CPU seconds of the process (not the wall): what a quiet machine's cores would
        # spend; divided over `cores` cores, assuming the convolutions scale across them
        "cpu_windows_per_s": cpu_rate,
        "quiet_projection_min_12_lines": {
            f"{v}_{cores}cores": n / r / 60 / (cores / threads)
            for v, r in cpu_rate.items() for cores in (threads, 2)
        },
        "times_s": times,
    }  # fmt: skip


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--base-width", type=int, default=64)
    p.add_argument("--n-blocks", type=int, default=7)
    p.add_argument("--batch", type=int, default=8)
    p.add_argument("--repeats", type=int, default=3)
    p.add_argument("--variants", nargs="+", default=list(VARIANTS))
    args = p.parse_args(argv)
    out = bench(args.base_width, args.n_blocks, args.batch, repeats=args.repeats,
                variants=args.variants)  # fmt: skip
    print(json.dumps(out, indent=2))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
