"""Section ``gpu_projection``: how long a paper-scale SIREN fit takes on a GPU, projected
from the measured ``siren_step`` section (derived, not measured).

The paper's SIREN fit (Dataset I) runs 1500 epochs over 12 lines of ~2000 pings in
batches of 64 pings (+ 2000 altimeter points): ``ceil(12 * 2000 / 64) = 375`` steps per
epoch, 562 500 steps, "approximately 12 hours on a single Nvidia GEFORCE RTX 2080 Ti".

Model: a step's matrix products (recorded FLOPs, :func:`benchmarks.siren_step.bench_siren_step`)
run at ``peak * efficiency``, where ``efficiency`` is the fraction of the matmul bound the
step reached where it was measured (the share of the step the products alone would
take); everything that is not a product (sin/cos, the finder's bookkeeping, Adam) is
assumed to scale like on the measuring machine. On a GPU the elementwise work is memory
bound rather than compute bound, so this is an assumption, stated as one; a measurement
replaces it where a GPU is lent (the runner measures the same step there).

Peak rates: NVIDIA H100 SXM5 datasheet, dense (half the "with sparsity" figures):
FP32 67 TFLOP/s, TF32 tensor core 495 TFLOP/s, BF16 tensor core 989 TFLOP/s; RTX 2080 Ti
FP32 13.4 TFLOP/s (the paper's GPU, for a sanity check against its 12 hours).
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from typing import Any

from benchmarks.timing import figure

TITLE = "Paper-scale SIREN fit, projected"
# peak matmul rates (TFLOP/s), dense
GPU_PEAKS_TFLOPS: dict[str, dict[str, float]] = {
    "H100-SXM5": {"fp32": 67.0, "tf32": 495.0, "bf16": 989.0},
    "RTX-2080-Ti": {"fp32": 13.4},
}
PAPER_FIT = {"lines": 12, "pings_per_line": 2000, "batch_pings": 64, "epochs": 1500}


def paper_fit_steps(
    lines: int = PAPER_FIT["lines"],
    pings_per_line: int = PAPER_FIT["pings_per_line"],
    batch_pings: int = PAPER_FIT["batch_pings"],
    epochs: int = PAPER_FIT["epochs"],
) -> int:
    """Optimizer steps of a fit: ``epochs * ceil(lines * pings_per_line / batch_pings)``."""
    for name, v in (
        ("lines", lines),
        ("pings_per_line", pings_per_line),
        ("batch_pings", batch_pings),
        ("epochs", epochs),
    ):
        if not isinstance(v, int) or isinstance(v, bool) or v < 1:
            raise ValueError(f"{name}: expected a positive integer, found {v!r}")
    return epochs * math.ceil(lines * pings_per_line / batch_pings)


def project_fit_minutes(
    flops_per_step: float,
    efficiency: float,
    steps: int | None = None,
    peaks: Mapping[str, Mapping[str, float]] = GPU_PEAKS_TFLOPS,
) -> dict[str, Any]:
    """Projected wall minutes of a fit of ``steps`` steps on each GPU and precision.

    Args:
        flops_per_step: matrix-product FLOPs of one step (fwd + finder + bwd), FLOP.
        efficiency: fraction of the matmul bound a step reaches, in ``(0, 1]``.
        steps: optimizer steps (default :func:`paper_fit_steps`).
        peaks: ``{gpu: {precision: TFLOP/s}}``.

    Returns:
        ``{"steps", "flops_total", "minutes": {gpu: {precision: minutes}}}``.
    """
    if not (math.isfinite(flops_per_step) and flops_per_step > 0):
        raise ValueError(f"flops_per_step: expected a positive number, found {flops_per_step}")
    if not (math.isfinite(efficiency) and 0 < efficiency <= 1):
        raise ValueError(f"efficiency: expected a fraction in (0, 1], found {efficiency}")
    steps = paper_fit_steps() if steps is None else int(steps)
    if steps < 1:
        raise ValueError(f"steps: expected >= 1, found {steps}")
    total = float(flops_per_step) * steps
    minutes = {
        gpu: {
            prec: total / (rate * 1e12 * efficiency) / 60.0
            for prec, rate in rates.items()
            if rate > 0
        }
        for gpu, rates in peaks.items()
    }
    return {"steps": steps, "flops_total": total, "minutes": minutes}


def projection_section(siren_step: Mapping[str, Any], target_minutes: float = 15.0) -> dict:
    """The ``gpu_projection`` section (figures + notes) from the ``siren_step`` section."""
    info = siren_step.get("info", {})
    flops, eff = info.get("recorded_flops"), info.get("bound_fraction")
    if flops is None or eff is None:
        raise ValueError(
            "siren_step: expected info.recorded_flops and info.bound_fraction, "
            f"found keys {sorted(info)}"
        )
    eff = min(float(eff), 1.0)
    proj = project_fit_minutes(float(flops), eff)
    fit = PAPER_FIT
    figures = [
        figure(
            "paper-scale fit: optimizer steps",
            "steps",
            proj["steps"],
            f"{fit['lines']} x {fit['pings_per_line']} pings / {fit['batch_pings']} "
            f"x {fit['epochs']}",
        ),
        figure("matmul work per step (measured)", "GFLOP", float(flops) / 1e9),
        figure("fraction of matmul bound (measured)", "%", 100 * eff),
    ]
    for gpu, by_prec in proj["minutes"].items():
        for prec, minutes in by_prec.items():
            note = f"target <= {target_minutes:g} min" if gpu.startswith("H100") else ""
            figures.append(figure(f"{gpu} {prec}: projected fit", "min", minutes, note))
    return {
        "title": TITLE,
        "params": {"paper_fit": PAPER_FIT, "peaks_tflops": GPU_PEAKS_TFLOPS},
        "figures": figures,
        "info": proj,
        "notes": (
            "Projection, not a measurement: the step's recorded matmul FLOPs x steps of the "
            "paper's fit, at each GPU's datasheet peak times the fraction of the matmul bound "
            "measured here (module benchmarks.projection states the assumptions)."
        ),
    }
