"""SIREN step near its bound (issue 20, Build 3): ratio micro-benchmarks, interleaved.

Each comparison runs its variants in turns (A, B, A, B, ...) in one process and reports
the median of each, wall and process CPU time (the CPU time is what a quiet core would
spend; on a shared machine the wall time is noisy, the ratio much less so):

* ``sincos``: a block's ``sin`` and ``cos`` of the same pre-activations as two eager ops
  vs one ``torch.compile``-d function (one loop reading the input once: the shared pass
  over memory a fused range reduction would need);
* ``no_graph``: :meth:`Siren.height_and_gradient` without a graph (the intersection
  finder's and map evaluation's pass) eager vs ``torch.compile`` of its block function at
  one fixed block shape (compile time reported apart);
* ``train``: the training pass with a graph (``height_and_gradient`` + a loss +
  ``backward``) at ``precision="fp32"`` vs ``"bf16"``, and the gradient error of bf16.

    python -m benchmarks.siren_kernels --points 8192 --repeats 7
"""

from __future__ import annotations

import argparse
import json
import statistics
import time
from collections.abc import Callable, Mapping

import torch


def in_turns(fns: Mapping[str, Callable[[], object]], repeats: int) -> dict[str, dict]:
    """Median wall and CPU seconds of each function, run in turns after one warm-up each."""
    for fn in fns.values():
        fn()
    wall: dict[str, list[float]] = {k: [] for k in fns}
    cpu: dict[str, list[float]] = {k: [] for k in fns}
    for _ in range(repeats):
        for k, fn in fns.items():
            t0, c0 = time.perf_counter(), time.process_time()
            fn()
            wall[k].append(time.perf_counter() - t0)
            cpu[k].append(time.process_time() - c0)
    first = next(iter(fns))
    out = {}
    for k in fns:
        w, c = statistics.median(wall[k]), statistics.median(cpu[k])
        out[k] = {
            "wall_s": w,
            "cpu_s": c,
            "speedup_wall": statistics.median(wall[first]) / w,
            "speedup_cpu": statistics.median(cpu[first]) / c,
        }
    return out


def bench(points: int = 8192, repeats: int = 7, compile_: bool = True, seed: int = 0) -> dict:
    from sss2bathy.models.siren import CPU_CHUNK, Siren

    torch.manual_seed(seed)
    result: dict[str, object] = {"threads": torch.get_num_threads(), "points": points}
    pre = torch.randn(CPU_CHUNK, 128) * 3

    def eager_sincos():
        return torch.sin(pre), torch.cos(pre)

    fns: dict[str, Callable[[], object]] = {"eager": eager_sincos}
    if compile_:
        fused = torch.compile(lambda p: (torch.sin(p), torch.cos(p)), dynamic=False)
        t0 = time.perf_counter()
        s, c = fused(pre)
        result["sincos_compile_s"] = time.perf_counter() - t0
        result["sincos_max_err"] = max(
            float((s - torch.sin(pre)).abs().max()), float((c - torch.cos(pre)).abs().max())
        )
        fns["compiled"] = lambda: fused(pre)
    result["sincos"] = in_turns(fns, repeats)

    model = Siren(bounds=(0, 0, 350, 300), z_range=(-30, -10))
    xy = torch.rand(points, 2) * torch.tensor([350.0, 300.0])

    def eager_no_graph():
        with torch.no_grad():
            return model.height_and_gradient(xy)

    fns = {"eager": eager_no_graph}
    if compile_:
        compiled = Siren(bounds=(0, 0, 350, 300), z_range=(-30, -10), compile_no_graph=True)
        compiled.load_state_dict(model.state_dict())

        def compiled_no_graph():
            with torch.no_grad():
                return compiled.height_and_gradient(xy)

        t0 = time.perf_counter()
        z_c, g_c = compiled_no_graph()
        result["no_graph_compile_s"] = time.perf_counter() - t0
        z_e, g_e = eager_no_graph()
        result["no_graph_max_err"] = {
            "z_m": float((z_c - z_e).abs().max()),
            "grad": float((g_c - g_e).abs().max()),
        }
        fns["compiled"] = compiled_no_graph
    result["no_graph"] = in_turns(fns, repeats)

    models = {p: Siren(bounds=(0, 0, 350, 300), z_range=(-30, -10), precision=p) for p in
              ("fp32", "bf16")}  # fmt: skip
    models["bf16"].load_state_dict(models["fp32"].state_dict())

    def train(p: str) -> Callable[[], object]:
        def run():
            m = models[p]
            m.zero_grad(set_to_none=True)
            z, g = m.height_and_gradient(xy)
            (g.square().sum() + z.mean()).backward()

        return run

    result["train"] = in_turns({p: train(p) for p in models}, repeats)
    g32 = models["fp32"].height_and_gradient(xy)[1].detach()
    g16 = models["bf16"].height_and_gradient(xy)[1].detach()
    rel = (g16 - g32).norm(dim=1) / g32.norm(dim=1).clamp_min(1e-12)
    result["bf16_grad_rel_err_median"] = float(rel.median())
    return result


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--points", type=int, default=8192)
    p.add_argument("--repeats", type=int, default=7)
    p.add_argument("--no-compile", action="store_true")
    args = p.parse_args(argv)
    print(json.dumps(bench(args.points, args.repeats, not args.no_compile), indent=2))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
