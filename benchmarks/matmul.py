"""Matrix-product accounting: record every product of a step, re-time them alone.

:class:`MatmulRecorder` (a dispatch mode) records each ``mm``/``addmm``/``bmm``/``baddbmm``
with its shapes, strides and dtype, forward and backward; :func:`time_products` re-times
each distinct product on fresh tensors of the same layout, so ``sum(count x time)`` is the
time the products alone take at the ``torch.mm`` rate (the *matmul bound* of a step);
:func:`siren_matmul_flops` is the analytic count to check the recording against.

The recorder also counts the step's sines and cosines (``sin``, ``cos``, in place or not),
which a SIREN cannot skip: one per hidden unit and point, two where the gradient is
needed. :func:`time_sines` re-times them alone at the ``torch.sin``/``torch.cos`` rate (the
*sine bound*), so ``matmul / (matmul + sine bound)`` is the highest fraction of its matmul
bound a step can reach with PyTorch's sine kernels, whatever else it saves.
"""

from __future__ import annotations

import math
import time
from collections import Counter
from collections.abc import Callable, Iterable, Mapping

import torch
from torch.utils._python_dispatch import TorchDispatchMode

from benchmarks.timing import synchronize

_MATMUL_OPS = {
    torch.ops.aten.mm.default: "mm",
    torch.ops.aten.addmm.default: "addmm",
    torch.ops.aten.bmm.default: "bmm",
    torch.ops.aten.baddbmm.default: "baddbmm",
}


_SINE_OPS = {
    torch.ops.aten.sin.default: "sin",
    torch.ops.aten.sin_.default: "sin",
    torch.ops.aten.sin.out: "sin",
    torch.ops.aten.cos.default: "cos",
    torch.ops.aten.cos_.default: "cos",
    torch.ops.aten.cos.out: "cos",
}


def _layout(t: torch.Tensor) -> tuple:
    return (tuple(t.shape), tuple(t.stride()), str(t.dtype).removeprefix("torch."))


class MatmulRecorder(TorchDispatchMode):
    """Records every matrix product dispatched while active (forward and backward).

    ``calls`` counts signatures ``(op, (shape, stride, dtype) of each tensor argument,
    scalar arguments)``; :meth:`flops` sums ``2 n k m`` (times the batch) over them.
    ``sines`` counts ``(sin | cos, (shape, stride, dtype) of the argument)`` of every sine
    and cosine (in place or not); :meth:`sine_elements` sums their elements.
    """

    def __init__(self) -> None:
        super().__init__()
        self.calls: Counter = Counter()
        self.sines: Counter = Counter()

    def __torch_dispatch__(self, func, types, args=(), kwargs=None):
        kwargs = kwargs or {}
        name = _MATMUL_OPS.get(func)
        if name is not None:
            tensors = tuple(_layout(a) for a in args if isinstance(a, torch.Tensor))
            scalars = tuple(sorted((k, float(v)) for k, v in kwargs.items()))
            self.calls[(name, tensors, scalars)] += 1
        sine = _SINE_OPS.get(func)
        if sine is not None:
            self.sines[(sine, _layout(args[0]))] += 1
        return func(*args, **kwargs)

    def sine_elements(self) -> int:
        """Elements of every recorded sine and cosine."""
        return sum(n * math.prod(sig[1][0]) for sig, n in self.sines.items())

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


def _time_alone(
    call: Callable[[], None], repeats: int, device: torch.device, min_time_s: float
) -> list[float]:
    """Seconds per ``call()`` in each of ``repeats`` loops long enough (``min_time_s``) that
    the timer's resolution does not matter, after a warm-up call (allocator, kernels)."""
    call()
    synchronize(device)
    t0 = time.perf_counter()
    call()
    synchronize(device)
    once = max(time.perf_counter() - t0, 1e-7)
    loops = max(1, min(1000, int(math.ceil(min_time_s / once))))
    out = []
    for _ in range(int(repeats)):
        synchronize(device)
        t0 = time.perf_counter()
        for _ in range(loops):
            call()
        synchronize(device)
        out.append((time.perf_counter() - t0) / loops)
    return out


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

        for r, t in enumerate(_time_alone(call, repeats, device, min_time_s)):
            totals[r] += count * t
    return totals


def time_sines(
    sines: Mapping[tuple, int],
    repeats: int,
    device: torch.device,
    min_time_s: float = 2e-3,
    seed: int = 0,
) -> list[float]:
    """Re-time every recorded sine and cosine alone (:meth:`MatmulRecorder.sine_elements`);
    returns, per repeat, ``sum(count * time)`` (s).

    Each runs as ``torch.sin``/``torch.cos`` into a preallocated output of its recorded
    shape and dtype, on arguments of unit-variance normal pre-activations times 3 (a SIREN's
    are of that order; PyTorch's vectorised kernels take the same path for any argument
    below ~100 rad), in a loop of ``min_time_s`` as :func:`time_products`.
    """
    gen = torch.Generator().manual_seed(seed)
    totals = [0.0] * int(repeats)
    for (name, layout), count in sines.items():
        shape, _, dtype = layout
        x = (3 * torch.randn(shape, generator=gen)).to(device=device, dtype=getattr(torch, dtype))
        out = torch.empty_like(x)
        fn = getattr(torch, name)

        def call(fn=fn, x=x, out=out) -> None:
            fn(x, out=out)

        for r, t in enumerate(_time_alone(call, repeats, device, min_time_s)):
            totals[r] += count * t
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
