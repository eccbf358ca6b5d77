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
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence

import torch
from torch import nn


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
    ) -> None:
        super().__init__()
        if int(hidden) < 1:
            raise ValueError(f"hidden: expected a positive width, found {hidden}")
        if int(n_layers) < 2:
            raise ValueError(f"n_layers: expected >= 2 linear layers, found {n_layers}")
        if not (math.isfinite(float(omega0)) and float(omega0) > 0):
            raise ValueError(f"omega0: expected a positive number, found {omega0}")
        self.hidden = int(hidden)
        self.n_layers = int(n_layers)
        self.omega0 = float(omega0)
        dims = [2] + [self.hidden] * (self.n_layers - 1)
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

        Biases keep PyTorch's default ``U(+-1/sqrt(fan_in))``, as in the reference SIREN.
        """
        for i, layer in enumerate([*self.sine_layers, self.out_layer]):
            fan_in = layer.in_features
            bound = 1.0 / fan_in if i == 0 else math.sqrt(6.0 / fan_in) / self.omega0
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
        """Rebuild a SIREN (sizes, ``omega0``, frame, weights) from a state dict.

        ``prefix`` selects a sub-dict, e.g. ``"siren."`` inside a Lightning checkpoint.
        """
        sd = {k[len(prefix) :]: v for k, v in state.items() if k.startswith(prefix)}
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

    def height(self, xy: torch.Tensor) -> torch.Tensor:
        """Heights ``z (N,)`` (m) at world ``xy (N, 2)`` (m)."""
        self._check_xy(xy)
        h = self.normalized(xy)
        for layer in self.sine_layers:
            h = torch.sin(self.omega0 * layer(h))
        return self.out_mid + self.out_half * self.out_layer(h).squeeze(-1)

    forward = height

    def height_and_gradient(self, xy: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Heights and their exact spatial gradient, computed explicitly in one call.

        The forward pass keeps each sine layer's ``cos``; a hand-written reverse pass then
        carries ``dz/dh`` down to the input (module docstring). Every operation is a plain
        differentiable op, so the result has an ordinary first-order graph with respect
        to the parameters.

        Args:
            xy: ``(N, 2)`` world coordinates (m).

        Returns:
            ``z (N,)`` heights (m) and ``grad (N, 2)`` = ``(dz/dx, dz/dy)`` (m/m).
        """
        self._check_xy(xy)
        h = self.normalized(xy)
        cosines = []
        for layer in self.sine_layers:
            pre = self.omega0 * layer(h)
            h = torch.sin(pre)
            cosines.append(torch.cos(pre))
        z = self.out_mid + self.out_half * self.out_layer(h).squeeze(-1)
        g = self.out_half * self.out_layer.weight  # (1, hidden): dz/dh of the last layer
        for layer, cos in zip(reversed(self.sine_layers), reversed(cosines), strict=True):
            g = (cos * g) @ (self.omega0 * layer.weight)  # dz/dh of the layer below
        return z, g / self.in_scale

    def extra_repr(self) -> str:
        return (
            f"hidden={self.hidden}, n_layers={self.n_layers}, omega0={self.omega0}, "
            f"bounds={tuple(round(b, 3) for b in self.bounds)}, "
            f"z_range={tuple(round(z, 3) for z in self.z_range)}"
        )
