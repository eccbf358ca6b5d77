"""CNN inference at a scale's size (issue 20, Build 4): windows/s of the normal network's
forward pass in each variant, interleaved in one run (medians), and the projected time
for a survey's lines at each inference overlap.

Variants: ``fp32`` (contiguous: what ``predict_waterfall`` runs in fp32), ``fp32_cl``
(``channels_last``), ``fp32_cn_cl`` (channels-last with the instance norms computed as
per-channel group norms, :func:`sss2bathy.models.normal_cnn.channel_norm_copy`), ``bf16``
(CPU autocast to bfloat16), ``bf16_cl``, ``bf16_net`` (what
``predict_waterfall(precision="bf16")`` runs on a CPU,
:func:`sss2bathy.data.cnn_normals.inference_net`: a bfloat16, channels-last, channel-norm
copy of the network on bfloat16 windows), ``bf16_net_in`` (a plain bfloat16 copy with its
``InstanceNorm2d``, contiguous: what ran before) and ``bf16_net_in_cl`` (that copy
channels-last); each under ``torch.inference_mode``. Random weights: the cost of a forward
pass does not depend on them.

The projection (``projected_min_12_lines``) is windows / windows-per-second for the paper's
12 test lines (2000 pings, 512 bins per side, both heads) at each ``--overlaps`` value
(``data.normals.overlap``: the training 0.75, or 0.5 = half the windows). ``--e2e-pings N``
also runs the whole pipeline (:func:`sss2bathy.data.cnn_normals.predict_waterfall`:
gathering the windows, batches of ``--e2e-batch``, stitching) over an ``N``-ping line and
reports its windows/s as a ratio to the bare forward pass of the same variant (the
pipeline's overhead) and the time of one paper line's stitching.

    python -m benchmarks.cnn_inference --base-width 64 --n-blocks 7 --batch 8 --repeats 3
"""

from __future__ import annotations

import argparse
import copy
import json
import statistics
import time
from collections.abc import Sequence

import torch

VARIANTS = (
    "fp32",
    "fp32_cl",
    "fp32_cn_cl",
    "bf16",
    "bf16_cl",
    "bf16_net",
    "bf16_net_in",
    "bf16_net_in_cl",
)


OVERLAPS = (0.75, 0.5)


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
    overlaps: Sequence[float] = OVERLAPS,
    e2e_pings: int = 0,
    e2e_batch: int = 64,
) -> dict:
    """``{variant: windows/s (median)}`` plus the per-repeat times, interleaved A, B, ...,
    the projection per variant and overlap, and (``e2e_pings > 0``) the pipeline's rate."""
    from sss2bathy.data.cnn_normals import cpu_has_native_bf16, inference_net
    from sss2bathy.models.normal_cnn import NormalResNet, channel_norm_copy

    bad = [v for v in variants if v not in VARIANTS]
    if bad:
        raise ValueError(f"variants: expected some of {VARIANTS}, found {bad}")
    torch.manual_seed(seed)
    net = NormalResNet(in_channels=1, base_width=base_width, n_blocks=n_blocks).eval()
    x = torch.randn(batch, 1, *window)
    cl = torch.channels_last
    x_cl, x_bf16 = x.contiguous(memory_format=cl), x.to(torch.bfloat16)
    # (network, input) of each variant; autocast variants run the fp32 networks under it
    runs = {
        "fp32": lambda: (net, x),
        "fp32_cl": lambda: (copy.deepcopy(net).to(memory_format=cl), x_cl),
        "fp32_cn_cl": lambda: (channel_norm_copy(net).to(memory_format=cl), x_cl),
        "bf16": lambda: (net, x),
        "bf16_cl": lambda: (copy.deepcopy(net).to(memory_format=cl), x_cl),
        "bf16_net": lambda: (inference_net(net, "cpu", "bf16")[0], x_bf16),
        "bf16_net_in": lambda: (copy.deepcopy(net).to(torch.bfloat16), x_bf16),
        "bf16_net_in_cl": lambda: (
            copy.deepcopy(net).to(torch.bfloat16).to(memory_format=cl),
            x_bf16.contiguous(memory_format=cl),
        ),
    }
    nets = {v: runs[v]() for v in variants}

    def run(variant: str) -> tuple[float, float]:
        model, inp = nets[variant]
        autocast = variant in ("bf16", "bf16_cl")
        t0, c0 = time.perf_counter(), time.process_time()
        with (
            torch.inference_mode(),
            torch.autocast("cpu", dtype=torch.bfloat16, enabled=autocast),
        ):
            model(inp)
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
    n_at = {f"overlap_{o:g}": survey_windows(window=window, overlap=o) for o in overlaps}
    threads = torch.get_num_threads()
    out = {
        "config": {"base_width": base_width, "n_blocks": n_blocks, "batch": batch,
                   "window": list(window), "threads": torch.get_num_threads(),
                   "overlaps": list(overlaps),
                   "cpu_capability": torch.backends.cpu.get_cpu_capability(),
                   "native_bf16": cpu_has_native_bf16()},
        "windows_per_s": med,
        "ratio_to_fp32": {v: med[v] / med["fp32"] for v in variants} if "fp32" in med else {},
        "survey_windows_12_lines": n,
        "survey_windows_12_lines_by_overlap": n_at,
        "projected_min_12_lines": {
            f"{v}_{o}": k / r / 60 for v, r in med.items() for o, k in n_at.items()
        },
        # CPU seconds of the process (not the wall): what a quiet machine's cores would
        # spend; divided over `cores` cores, assuming the convolutions scale across them
        "cpu_windows_per_s": cpu_rate,
        "quiet_projection_min_12_lines": {
            f"{v}_{cores}cores": n / r / 60 / (cores / threads)
            for v, r in cpu_rate.items() for cores in (threads, 2)
        },
        "times_s": times,
    }  # fmt: skip
    if e2e_pings > 0:
        out["e2e"] = pipeline(net, med, window, e2e_pings, e2e_batch, variants, seed)
    return out


def pipeline(
    net: torch.nn.Module,
    forward_rate: dict[str, float],
    window: tuple[int, int],
    pings: int,
    batch: int,
    variants: Sequence[str],
    seed: int = 0,
) -> dict:
    """Whole-pipeline windows/s of :func:`predict_waterfall` (fp32 / bf16, training overlap
    0.75) over a ``pings x 2 x window_bins`` line, as a ratio to the bare forward pass, and
    the seconds one paper line's stitching takes (both heads)."""
    from sss2bathy.data.cnn_normals import predict_waterfall, stitch_windows
    from sss2bathy.data.windows import line_windows

    rng = torch.Generator().manual_seed(seed)
    line = torch.randn(pings, 2, window[1], generator=rng).numpy()
    n_windows = 2 * len(line_windows(pings, window[1], window[0], window[1], 0.75))
    res: dict = {"pings": pings, "batch": batch, "windows": n_windows}
    for precision in [v for v in ("fp32", "bf16") if v in variants or f"{v}_net" in variants]:
        t0 = time.perf_counter()
        predict_waterfall(net, line, window, 0.75, batch_size=batch, precision=precision)
        rate = n_windows / (time.perf_counter() - t0)
        res[f"{precision}_windows_per_s"] = rate
        bare = forward_rate.get(f"{precision}_net" if precision == "bf16" else precision)
        if bare is not None:  # the bare forward pass of what predict_waterfall runs
            res[f"{precision}_ratio_to_forward"] = rate / bare
    origins = line_windows(2000, window[1], window[0], window[1], 0.75)
    preds = torch.randn(len(origins), *window, generator=rng).numpy()
    t0 = time.perf_counter()
    for _ in range(2):
        stitch_windows(preds, origins, (2000, window[1]))
    res["stitch_s_per_paper_line"] = time.perf_counter() - t0
    return res


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--base-width", type=int, default=64)
    p.add_argument("--n-blocks", type=int, default=7)
    p.add_argument("--batch", type=int, default=8)
    p.add_argument("--repeats", type=int, default=3)
    p.add_argument("--variants", nargs="+", default=list(VARIANTS))
    p.add_argument("--overlaps", nargs="+", type=float, default=list(OVERLAPS))
    p.add_argument("--e2e-pings", type=int, default=0, help="0 = no pipeline run")
    p.add_argument("--e2e-batch", type=int, default=64)
    p.add_argument("--threads", type=int, default=0, help="torch threads; 0 = torch's")
    args = p.parse_args(argv)
    if args.threads > 0:
        torch.set_num_threads(args.threads)
    out = bench(args.base_width, args.n_blocks, args.batch, repeats=args.repeats,
                variants=args.variants, overlaps=args.overlaps, e2e_pings=args.e2e_pings,
                e2e_batch=args.e2e_batch)  # fmt: skip
    print(json.dumps(out, indent=2))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
