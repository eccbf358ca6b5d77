"""SIREN height field ``z = Phi(x, y)`` with an exact, explicit input gradient.

The bathymetry is an MLP with sine activations (Sitzmann et al. 2020; paper section
"Implicit Neural Representations"). World ``(x, y)`` (m, local ENU) are scaled per axis to
``[-1, 1]`` from the survey bounds; the last layer is linear and its output ``o`` is mapped
to a height by ``z = mid + half * o`` from the survey's height range.

Layer count convention: ``n_layers`` counts *all* linear layers, so the paper's "5-layer
SIREN with hidden size 128" is ``2 -> 128 -> 128 -> 128 -> 128 -> 1``: four sine layers and
one linear output layer.

Input gradient, explicitly. For a sine layer ``h = sin(w0 (W h_prev + b))`` the derivative
is a cosine layer: ``dz/dh_prev = (w0 cos(w0 (W h_prev + b)) * dz/dh) W``. The forward
pass keeps the cosines and a hand-written reverse pass carries ``dz/dh`` from the linear
output layer down to ``(x, y)``: one extra ``N x hidden x hidden`` product per layer,
exactly what ``autograd.grad(create_graph=True)`` computes (and fewer products than
forward-mode tangents, which need one per input dimension), but as plain differentiable
ops: the result has an ordinary first-order graph with respect to the parameters (what
the normal loss trains), works under ``torch.no_grad`` (the intersection finder) and
compiles with ``torch.compile`` (which refuses double backward).

Optional input encoding. With ``encoding`` (:mod:`sss2bathy.models.encoding`: Fourier
features or a multiresolution hash grid) the first sine layer reads ``gamma(x_norm)``
instead of the normalised ``x_norm``; the reverse pass ends with the encoding's explicit
vector-Jacobian product ``dz/dx_norm = dz/dgamma . dgamma/dx_norm`` and then ``1 / in_scale``,
so the gradient stays a plain first-order graph (no ``autograd.grad``) and learnable
encodings are trained by the normal loss too. ``encoding=None`` is the paper's SIREN,
computed exactly as without the option.

Speed (a training step is mostly these passes; measured by ``make bench``):

* ``omega0``, the output scaling and ``1 / in_scale`` are folded into the (tiny) weight
  matrices once per call, so no pass over the ``N x hidden`` pre-activations is spent on
  them;
* each sine layer's ``sin`` and ``cos`` are one autograd node (:class:`_SinCos`) whose
  backward reuses both instead of recomputing them (autograd's ``sin``/``cos`` nodes each
  evaluate the other function again);
* without a graph (the intersection finder, map evaluation) every elementwise step runs
  in place;
* points go through in blocks of ``chunk`` (default :data:`CPU_CHUNK` on CPU, all at once
  elsewhere) so each block's ``N x hidden`` temporaries stay in the core's cache;
* optionally (``compile_no_graph=True``) :meth:`Siren.height_and_gradient` without a graph
  (the intersection finder's pass) runs a ``torch.compile``-d block function at one fixed
  block shape (the last block is zero-padded to it), so a fit compiles once: each layer's
  ``sin`` and ``cos`` become one loop over the pre-activations, as do the reverse pass's
  products with the cosines. 1.47x the CPU time of the eager pass on 8192 points (one
  thread, ``benchmarks/siren_kernels.py``), ~15-50 s to compile; not bit for bit (heights to
  ~2e-6 m, gradients to ~1e-7: ``sin``/``cos`` of another vectorisation, within an ulp), so
  it is off by default; the training pass (with a graph) and :meth:`Siren.height` stay eager.
  vectorisation), so it is off by default.

Precision. ``precision="bf16"`` runs the hidden ``hidden x hidden`` layers of the
training pass of :meth:`Siren.height_and_gradient` (with a graph: the sensor model's
gradients, the bulk of a step's training products) in bfloat16 with float32 accumulation,
which AMX/AVX512-BF16 CPUs and tensor-core GPUs multiply several times faster. The input
layer (pre-activations up to ``+-omega0`` rad, beyond bfloat16's resolution) and the
output layer stay float32; heights (:meth:`Siren.height`: the altimeter anchor, direct
fits) and every pass without a graph (the intersection finder's residual, to 1 mm, and
map evaluation) always run in float32: bfloat16's 8-bit mantissa would put centimetres of
rounding on absolute heights, whereas a normal's direction tolerates its ~0.4 %. An
enclosing ``torch.autocast`` (e.g. Lightning's ``precision="bf16-mixed"``) selects the same
for that pass; the SIREN disables it inside its own passes, so it never reaches the finder.
"""

from __future__ import annotations

import contextlib
import math
from collections.abc import Iterator, Mapping, Sequence
from typing import Any, NamedTuple

import torch
from torch import nn

from sss2bathy.models.encoding import Encoding, encoding_from_state_dict

#: Training precisions: the hidden layers' dtype in the training pass of the gradient.
PRECISIONS: dict[str, torch.dtype] = {"fp32": torch.float32, "bf16": torch.bfloat16}

#: Points per block on CPU: a block's ``N x 128`` float32 temporaries (1 MiB each) fit a
#: core's L2 cache. Measured on the benchmark's training step (width 128, one thread):
#: blocks of 512 to 2048 points alike, 8192 (the previous finder chunk) ~10 % slower.
CPU_CHUNK = 2048


class _Folded(NamedTuple):
    """Weights of one pass with the constant factors folded in (:meth:`Siren._folded`)."""

    weights: list[torch.Tensor]  # omega0 W_l, (H_l, H_l-1)
    biases: list[torch.Tensor]  # omega0 b_l, (H_l,)
    out_w: torch.Tensor  # half w_o, (1, H)
    out_b: torch.Tensor  # mid + half b_o, (1,)
    first_t: torch.Tensor  # (H, 2) omega0 W_1 / in_scale = d pre_1 / d xy; encoded: omega0 W_1
    in_scale: torch.Tensor  # (2,): d xy / d x_norm, divided out after an encoding's vjp


class _SinCos(torch.autograd.Function):
    """``(sin(x), cos(x))`` as one node: backward ``cos(x) ds - sin(x) dc`` from the saved pair."""

    @staticmethod
    def forward(ctx, pre: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        s, c = torch.sin(pre), torch.cos(pre)
        ctx.save_for_backward(s, c)
        ctx.set_materialize_grads(False)
        return s, c

    @staticmethod
    def backward(ctx, ds: torch.Tensor | None, dc: torch.Tensor | None) -> torch.Tensor | None:
        s, c = ctx.saved_tensors
        if ds is None and dc is None:
            return None
        # in place on each fresh product: one allocation, no extra pass over cold memory
        if dc is None:
            return c * ds
        if ds is None:
            return (s * dc).neg_()
        return (c * ds).addcmul_(s, dc, value=-1)


def _autocast_enabled(device: torch.device) -> bool:
    try:
        return torch.is_autocast_enabled(device.type)
    except (RuntimeError, TypeError):  # a device type autocast does not know
        return False


@contextlib.contextmanager
def autocast_disabled(device: torch.device) -> Iterator[None]:
    """Disable an enclosing ``torch.autocast`` on ``device`` (code that must stay float32;
    the SIREN picks each layer's dtype itself); nothing to do without one."""
    if not _autocast_enabled(device):
        yield
        return
    with torch.autocast(device_type=device.type, enabled=False):
        yield


def _hidden(
    x: torch.Tensor, f: _Folded, graph: bool, keep_cos: bool
) -> tuple[torch.Tensor, list[torch.Tensor]]:
    """The sine layers on one block: the last activations and, if asked, each layer's cos."""
    h, cosines = x, []
    for w, b in zip(f.weights, f.biases, strict=True):
        if h.dtype != w.dtype:
            h = h.to(w.dtype)
        pre = torch.addmm(b, h, w.t())
        if graph and keep_cos:
            h, c = _SinCos.apply(pre)
            cosines.append(c)
        elif graph:
            h = torch.sin(pre)
        else:
            if keep_cos:
                cosines.append(torch.cos(pre))
            h = pre.sin_()
    return h, cosines


def _output(h: torch.Tensor, f: _Folded) -> torch.Tensor:
    return torch.addmm(f.out_b, h.to(f.out_w.dtype), f.out_w.t()).squeeze(-1)


def _height_block(
    x: torch.Tensor, f: _Folded, graph: bool, enc: Encoding | None = None
) -> torch.Tensor:
    """``z (N,)`` of one block of normalised inputs ``x (N, 2)`` (through ``enc`` if any)."""
    return _output(_hidden(x if enc is None else enc(x), f, graph, keep_cos=False)[0], f)


def _gradient_block(
    x: torch.Tensor, f: _Folded, graph: bool, enc: Encoding | None = None
) -> tuple[torch.Tensor, torch.Tensor]:
    """``z (N,)`` and ``dz/d(x, y) (N, 2)`` of one block (the explicit reverse pass).

    With ``enc`` the loop ends at ``dz/dgamma (N, D)`` (``first_t`` is then ``omega0 W_1``),
    which the encoding's vector-Jacobian product takes to ``dz/dx_norm``, and ``1 /
    in_scale`` to ``dz/d(x, y)``. ``feat`` is never written in place (the first layer's
    ``addmm`` makes a fresh tensor), so the vjp may reuse it.
    """
    feat = x if enc is None else enc(x)
    h, cosines = _hidden(feat, f, graph, keep_cos=True)
    z = _output(h, f)
    g = f.out_w
    for layer in range(len(cosines) - 1, -1, -1):
        c = cosines[layer]
        if g.dtype != c.dtype:
            g = g.to(c.dtype)
        u = c * g if graph else c.mul_(g)  # dz/d pre of this layer
        w = f.weights[layer] if layer else f.first_t
        g = u @ (w if u.dtype == w.dtype else w.to(u.dtype))  # dz/dh of the layer below
    if enc is not None:  # dz/dgamma -> dz/dx_norm -> dz/dxy
        g = enc.vjp(x, g.to(x.dtype), feat) / f.in_scale
    return z, g


_COMPILED_GRADIENT_BLOCK: object | None = None


def _compiled_gradient_block():
    """``torch.compile(_gradient_block)`` at static shapes, made on first use (one per
    process; dynamo keeps one graph per block shape and dtype)."""
    global _COMPILED_GRADIENT_BLOCK
    if _COMPILED_GRADIENT_BLOCK is None:
        _COMPILED_GRADIENT_BLOCK = torch.compile(_gradient_block, dynamic=False)
    return _COMPILED_GRADIENT_BLOCK


def _check_pair(name: str, value: Sequence[float], n: int) -> tuple[float, ...]:
    vals = tuple(float(v) for v in value)
    if len(vals) != n or not all(math.isfinite(v) for v in vals):
        raise ValueError(f"{name}: expected {n} finite numbers, found {value!r}")
    return vals


class Siren(nn.Module):
    """SIREN ``Phi: R^2 -> R`` representing seafloor height (m) over world ``(x, y)`` (m).

    Args:
        hidden: width of the hidden layers.
        n_layers: number of linear layers in total (>= 2): ``n_layers - 1`` sine layers
            and a final linear layer.
        omega0: frequency factor ``w0`` of every sine layer (30 in the paper).
        bounds: ``(xmin, ymin, xmax, ymax)`` (m) mapped to ``[-1, 1]`` per axis.
        z_range: ``(zmin, zmax)`` (m); the output ``o`` is mapped to ``mid + half * o``.
        precision: ``"fp32"`` | ``"bf16"``: dtype of the hidden layers in the training pass
            of :meth:`height_and_gradient` (module docstring); everything else is float32.
        chunk: points per block of every pass; ``None`` = :data:`CPU_CHUNK` on CPU, all
            points at once on other devices.
        compile_no_graph: run :meth:`height_and_gradient` without a graph (the finder) through
            ``torch.compile`` at one block shape (module docstring); ``False``: eager.
        encoding: optional input encoding (:class:`~sss2bathy.models.encoding.Encoding`
            with ``in_dim == 2``) between the normalised ``(x, y)`` and the first sine
            layer, whose ``in_features`` becomes ``encoding.out_dim``; ``None``: the plain
            SIREN. Its parameters (if learnable) are submodule parameters of the SIREN.

    The frame (bounds, z range) and ``omega0`` are persistent buffers, so a state dict
    alone rebuilds the model (:meth:`from_state_dict`); :meth:`set_frame` changes the frame
    after construction (the Lightning module builds the SIREN before it knows the survey).
    """

    def __init__(
        self,
        hidden: int = 128,
        n_layers: int = 5,
        omega0: float = 30.0,
        bounds: Sequence[float] = (-1.0, -1.0, 1.0, 1.0),
        z_range: Sequence[float] = (-1.0, 1.0),
        precision: str = "fp32",
        chunk: int | None = None,
        encoding: Encoding | None = None,
        compile_no_graph: bool = False,
    ) -> None:
        super().__init__()
        if not isinstance(compile_no_graph, bool):
            raise ValueError(
                f"compile_no_graph: expected true or false, found {compile_no_graph!r}"
            )
        self.compile_no_graph = compile_no_graph
        if precision not in PRECISIONS:
            raise ValueError(
                f"precision: expected one of {sorted(PRECISIONS)}, found {precision!r}"
            )
        if chunk is not None and (isinstance(chunk, bool) or int(chunk) < 1):
            raise ValueError(f"chunk: expected a positive number of points or None, found {chunk}")
        self.precision = precision
        self.chunk = None if chunk is None else int(chunk)
        if int(hidden) < 1:
            raise ValueError(f"hidden: expected a positive width, found {hidden}")
        if int(n_layers) < 2:
            raise ValueError(f"n_layers: expected >= 2 linear layers, found {n_layers}")
        if not (math.isfinite(float(omega0)) and float(omega0) > 0):
            raise ValueError(f"omega0: expected a positive number, found {omega0}")
        if encoding is not None and not (
            isinstance(encoding, Encoding) and getattr(encoding, "in_dim", None) == 2
        ):
            found = (
                f"an Encoding with in_dim {encoding.in_dim}"
                if isinstance(encoding, Encoding)
                else type(encoding).__name__
            )
            raise ValueError(f"encoding: expected None or an Encoding with in_dim 2, found {found}")
        self.hidden = int(hidden)
        self.n_layers = int(n_layers)
        self.omega0 = float(omega0)
        self.encoding = encoding
        dims = [2 if encoding is None else int(encoding.out_dim)]
        dims += [self.hidden] * (self.n_layers - 1)
        self.sine_layers = nn.ModuleList(
            nn.Linear(a, b) for a, b in zip(dims[:-1], dims[1:], strict=True)
        )
        self.out_layer = nn.Linear(self.hidden, 1)
        self.register_buffer("omega0_buf", torch.tensor(self.omega0))
        self.register_buffer("in_offset", torch.zeros(2))
        self.register_buffer("in_scale", torch.ones(2))
        self.register_buffer("out_mid", torch.tensor(0.0))
        self.register_buffer("out_half", torch.tensor(1.0))
        self.reset_parameters()
        self.set_frame(bounds, z_range)
        self.register_load_state_dict_post_hook(Siren._sync_omega0)

    @staticmethod
    def _sync_omega0(module: nn.Module, incompatible_keys: object) -> None:
        module.omega0 = float(module.omega0_buf)

    # ------------------------------------------------------------------ setup
    @torch.no_grad()
    def reset_parameters(self) -> None:
        """SIREN init: first layer ``U(+-1/fan_in)``, others ``U(+-sqrt(6/fan_in)/omega0)``.

        With an encoding the first layer takes the hidden-layer init too: Fourier features
        are sines of the input like a sine layer's output (variance 1/2), for which that
        init gives unit-variance pre-activations whatever ``fan_in``, whereas
        ``U(+-1/fan_in)`` (meant for 2 coordinates) would shrink them as ``1/sqrt(D)``.
        The encoding keeps its own init. Biases keep PyTorch's default
        ``U(+-1/sqrt(fan_in))``, as in the reference SIREN.
        """
        for i, layer in enumerate([*self.sine_layers, self.out_layer]):
            fan_in = layer.in_features
            first = i == 0 and self.encoding is None
            bound = 1.0 / fan_in if first else math.sqrt(6.0 / fan_in) / self.omega0
            layer.weight.uniform_(-bound, bound)
            b = 1.0 / math.sqrt(fan_in)
            layer.bias.uniform_(-b, b)

    @torch.no_grad()
    def set_frame(self, bounds: Sequence[float], z_range: Sequence[float]) -> None:
        """Set the input scaling from ``(xmin, ymin, xmax, ymax)`` and the output scaling
        from ``(zmin, zmax)`` (m)."""
        xmin, ymin, xmax, ymax = _check_pair("bounds", bounds, 4)
        if not (xmax > xmin and ymax > ymin):
            raise ValueError(f"bounds: expected xmin < xmax and ymin < ymax, found {bounds!r}")
        zmin, zmax = _check_pair("z_range", z_range, 2)
        if not zmax > zmin:
            raise ValueError(f"z_range: expected zmin < zmax, found {z_range!r}")
        self.in_offset.copy_(torch.tensor([(xmin + xmax) / 2, (ymin + ymax) / 2]))
        self.in_scale.copy_(torch.tensor([(xmax - xmin) / 2, (ymax - ymin) / 2]))
        self.out_mid.fill_((zmin + zmax) / 2)
        self.out_half.fill_((zmax - zmin) / 2)

    @property
    def bounds(self) -> tuple[float, float, float, float]:
        """``(xmin, ymin, xmax, ymax)`` (m) mapped to ``[-1, 1]``."""
        lo = (self.in_offset - self.in_scale).tolist()
        hi = (self.in_offset + self.in_scale).tolist()
        return (lo[0], lo[1], hi[0], hi[1])

    @property
    def z_range(self) -> tuple[float, float]:
        """``(zmin, zmax)`` (m) that the output ``[-1, 1]`` maps to."""
        mid, half = float(self.out_mid), float(self.out_half)
        return (mid - half, mid + half)

    @classmethod
    def from_state_dict(cls, state: Mapping[str, torch.Tensor], prefix: str = "") -> Siren:
        """Rebuild a SIREN (sizes, ``omega0``, frame, encoding, weights) from a state dict.

        ``prefix`` selects a sub-dict, e.g. ``"siren."`` inside a Lightning checkpoint. The
        encoding (if any, under ``encoding.``) is rebuilt from its own buffers
        (:func:`~sss2bathy.models.encoding.encoding_from_state_dict`). ``precision`` and
        ``chunk`` are not part of the state: the rebuilt model has the defaults.
        """
        sd = {k[len(prefix) :]: v for k, v in state.items() if k.startswith(prefix)}
        if cls is Siren and "detail_range" in sd:  # a TwoScaleSiren's state
            return TwoScaleSiren.from_state_dict(sd)
        if "out_layer.weight" not in sd or "omega0_buf" not in sd:
            raise ValueError(
                f"state: expected SIREN keys under prefix {prefix!r} "
                f"(out_layer.weight, omega0_buf), found {sorted(sd)[:8]}"
            )
        n_sine = len({k.split(".")[1] for k in sd if k.startswith("sine_layers.")})
        model = cls(
            hidden=int(sd["out_layer.weight"].shape[1]),
            n_layers=n_sine + 1,
            omega0=float(sd["omega0_buf"]),
            encoding=encoding_from_state_dict(sd, "encoding."),
        )
        model.load_state_dict(sd)
        return model

    # ---------------------------------------------------------------- forward
    def _check_xy(self, xy: torch.Tensor) -> None:
        if not isinstance(xy, torch.Tensor) or xy.ndim != 2 or xy.shape[1] != 2:
            shape = tuple(xy.shape) if isinstance(xy, torch.Tensor) else type(xy).__name__
            raise ValueError(f"xy: expected a tensor of shape (N, 2), found {shape}")

    def normalized(self, xy: torch.Tensor) -> torch.Tensor:
        """``(N, 2)`` world ``(x, y)`` (m) -> network input in ``[-1, 1]`` over the bounds."""
        return (xy.to(self.in_scale.dtype) - self.in_offset) / self.in_scale

    def chunk_for(self, device: torch.device) -> int | None:
        """Points per block on ``device`` (``None``: all at once); see ``chunk``."""
        if self.chunk is not None:
            return self.chunk
        return CPU_CHUNK if device.type == "cpu" else None

    def _low_dtype(self, device: torch.device, graph: bool) -> torch.dtype | None:
        """The hidden layers' dtype for a pass: ``None`` (the parameters') unless the pass
        builds a graph and ``precision`` or an enclosing autocast asks for less."""
        if not graph:
            return None
        if self.precision != "fp32":
            return PRECISIONS[self.precision]
        if _autocast_enabled(device):
            dtype = torch.get_autocast_dtype(device.type)
            return dtype if dtype in (torch.bfloat16, torch.float16) else None
        return None

    def _folded(self, low: torch.dtype | None) -> _Folded:
        """The layers with ``omega0``, the output scaling and ``1 / in_scale`` folded in.

        ``pre_l = omega0 (W_l h + b_l) = (omega0 W_l) h + omega0 b_l`` saves a pass over
        every pre-activation; ``z = mid + half (w_o h + b_o)`` likewise. With ``low`` the
        hidden ``H x H`` layers are cast to it (the input layer, whose pre-activations
        reach ``+-omega0``, and the output layer stay in the parameters' dtype).
        """
        w0 = self.omega0_buf.to(self.out_layer.weight.dtype)
        weights, biases = [], []
        for i, layer in enumerate(self.sine_layers):
            w, b = w0 * layer.weight, w0 * layer.bias
            if low is not None and i > 0:
                w, b = w.to(low), b.to(low)
            weights.append(w)
            biases.append(b)
        out_w = self.out_half * self.out_layer.weight  # (1, H): dz/dh of the last layer
        out_b = self.out_mid + self.out_half * self.out_layer.bias
        # the reverse pass ends with d pre_1 / d xy = (omega0 W_1) / in_scale per column;
        # with an encoding at d pre_1 / d gamma = omega0 W_1 (its vjp and 1 / in_scale follow)
        first_t = weights[0] / self.in_scale if self.encoding is None else weights[0]
        return _Folded(weights, biases, out_w, out_b, first_t, self.in_scale)

    def _blocks(self, xy: torch.Tensor) -> list[torch.Tensor]:
        self._check_xy(xy)
        x = self.normalized(xy)
        chunk = self.chunk_for(x.device)
        return [x] if chunk is None or x.shape[0] <= chunk else list(x.split(chunk))

    def _compiled_blocks(
        self, xy: torch.Tensor, f: _Folded
    ) -> list[tuple[torch.Tensor, torch.Tensor]]:
        """The no-graph gradient pass through the compiled block function, every block of
        ``chunk_for(device)`` points (:data:`CPU_CHUNK` where that is all at once): the
        last one zero-padded to it and cropped, so one shape is ever compiled."""
        self._check_xy(xy)
        x = self.normalized(xy)
        chunk = self.chunk_for(x.device) or CPU_CHUNK
        block = _compiled_gradient_block()
        out = []
        for part in x.split(chunk):
            n = part.shape[0]
            if n < chunk:
                part = torch.cat([part, part.new_zeros(chunk - n, part.shape[1])])
            z, g = block(part, f, False, self.encoding)
            out.append((z[:n], g[:n]))
        return out

    def _graph(self, xy: torch.Tensor) -> bool:
        return torch.is_grad_enabled() and (
            xy.requires_grad or any(p.requires_grad for p in self.parameters())
        )

    def height(self, xy: torch.Tensor) -> torch.Tensor:
        """Heights ``z (N,)`` (m) at world ``xy (N, 2)`` (m), always in the parameters' dtype
        (absolute heights to centimetres need float32; ``precision`` is for gradients)."""
        graph = self._graph(xy)
        with autocast_disabled(xy.device):
            f = self._folded(None)
            out = [_height_block(x, f, graph, self.encoding) for x in self._blocks(xy)]
        return out[0] if len(out) == 1 else torch.cat(out)

    forward = height

    def height_and_gradient(self, xy: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Heights and their exact spatial gradient, computed explicitly in one call.

        The forward pass keeps each sine layer's ``cos``; a hand-written reverse pass then
        carries ``dz/dh`` down to the input, through the encoding's explicit vector-Jacobian
        product if there is one (module docstring). With a graph every
        operation is a plain differentiable op (the sine/cosine pair is one autograd node
        whose backward reuses both), so the result has an ordinary first-order graph with
        respect to the parameters; without one (``torch.no_grad``, the intersection
        finder) the same arithmetic runs in place.

        Args:
            xy: ``(N, 2)`` world coordinates (m).

        Returns:
            ``z (N,)`` heights (m) and ``grad (N, 2)`` = ``(dz/dx, dz/dy)`` (m/m). With a
            graph and ``precision="bf16"`` both carry bfloat16 rounding (``z`` about 1e-3 of
            the height range): use :meth:`height` for heights that must be exact.
        """
        graph = self._graph(xy)
        low = self._low_dtype(xy.device, graph)
        with autocast_disabled(xy.device):
            f = self._folded(low)
            if self.compile_no_graph and not graph:
                out = self._compiled_blocks(xy, f)
            else:
                out = [_gradient_block(x, f, graph, self.encoding) for x in self._blocks(xy)]
        if len(out) == 1:
            return out[0]
        return torch.cat([o[0] for o in out]), torch.cat([o[1] for o in out])

    def extra_repr(self) -> str:
        return (
            f"hidden={self.hidden}, n_layers={self.n_layers}, omega0={self.omega0}, "
            f"bounds={tuple(round(b, 3) for b in self.bounds)}, "
            f"z_range={tuple(round(z, 3) for z in self.z_range)}, precision={self.precision}, "
            f"chunk={self.chunk}, compile_no_graph={self.compile_no_graph}"
        )


class TwoScaleSiren(Siren):
    """A SIREN ``Phi`` (the *base*, fitted as :class:`Siren`) plus a finer detail SIREN ``D``:
    ``z = Phi(x, y) + D(x, y)``.

    The base keeps the coarse ``omega0`` that bridges gaps in the data (the altimeter's
    nadir, held-out blocks); the detail network's ``detail_omega0`` places wavelengths the
    size of what a sidescan images (a wreck, a boulder field). :meth:`detail_penalty` (the
    mean squared detail height over points drawn uniformly in the bounds, weighted by the
    module's ``w_detail``) keeps ``D`` near zero wherever no data asks for relief, so the
    detail appears where the sidescan sees it and the map elsewhere is the base's. ``D``'s
    output layer starts at zero: the fit begins from the base alone.

    Args:
        detail_omega0: ``omega0`` of the detail network.
        detail_hidden, detail_layers: its width and number of linear layers.
        detail_range_m: the detail network's output ``[-1, 1]`` maps to ``+-detail_range_m``.
        **base: :class:`Siren`'s arguments for the base (``precision`` and ``chunk`` apply
            to both).
    """

    def __init__(
        self,
        detail_omega0: float = 60.0,
        detail_hidden: int = 64,
        detail_layers: int = 4,
        detail_range_m: float = 2.0,
        **base: Any,
    ) -> None:
        super().__init__(**base)
        if not (math.isfinite(float(detail_range_m)) and float(detail_range_m) > 0):
            raise ValueError(
                f"detail_range_m: expected a positive number of metres, found {detail_range_m}"
            )
        self.detail = Siren(
            hidden=detail_hidden,
            n_layers=detail_layers,
            omega0=detail_omega0,
            precision=self.precision,
            chunk=self.chunk,
            compile_no_graph=self.compile_no_graph,
        )
        with torch.no_grad():
            self.detail.out_layer.weight.zero_()
            self.detail.out_layer.bias.zero_()
        self.register_buffer("detail_range", torch.tensor(float(detail_range_m)))
        self._frame_detail()

    def _frame_detail(self) -> None:
        r = float(self.detail_range)
        self.detail.set_frame(self.bounds, (-r, r))

    @torch.no_grad()
    def set_frame(self, bounds: Sequence[float], z_range: Sequence[float]) -> None:
        super().set_frame(bounds, z_range)
        if hasattr(self, "detail"):  # Siren.__init__ sets the base's frame before D exists
            self._frame_detail()

    def base_height(self, xy: torch.Tensor) -> torch.Tensor:
        """The base's height ``Phi(x, y)`` alone (m)."""
        return super().height(xy)

    def height(self, xy: torch.Tensor) -> torch.Tensor:
        return self.base_height(xy) + self.detail.height(xy)

    forward = height

    def height_and_gradient(self, xy: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        z, g = super().height_and_gradient(xy)
        dz, dg = self.detail.height_and_gradient(xy)
        return z + dz, g + dg

    def detail_penalty(self, n_points: int = 4096) -> torch.Tensor:
        """Mean squared detail height (m^2) at ``n_points`` drawn uniformly in the bounds."""
        u = torch.rand(int(n_points), 2, device=self.in_offset.device) * 2 - 1
        return self.detail.height(self.in_offset + u * self.in_scale).square().mean()

    @classmethod
    def from_state_dict(cls, state: Mapping[str, torch.Tensor], prefix: str = "") -> Siren:
        """Rebuild base and detail (sizes, ``omega0``, frames, weights) from a state dict."""
        sd = {k[len(prefix) :]: v for k, v in state.items() if k.startswith(prefix)}
        base = Siren.from_state_dict({k: v for k, v in sd.items() if not k.startswith("detail")})
        detail = Siren.from_state_dict(sd, "detail.")
        model = cls(
            detail_omega0=detail.omega0,
            detail_hidden=detail.hidden,
            detail_layers=detail.n_layers,
            detail_range_m=float(sd["detail_range"]),
            hidden=base.hidden,
            n_layers=base.n_layers,
            omega0=base.omega0,
            encoding=base.encoding,
        )
        model.load_state_dict(sd)
        return model

    def extra_repr(self) -> str:
        return f"{super().extra_repr()}, detail_range_m={float(self.detail_range)}"
