"""The normal-estimation CNN: sidescan intensity window -> n_lat per pixel (paper Fig. "CNN
architecture": two down-sampling layers, seven residual blocks, two up-sampling layers and a
final convolution; InstanceNorm and ReLU).

The layout is the well-known pix2pix-style ResNet generator: a reflection-padded 7x7 input
convolution, two stride-2 3x3 convolutions that double the width, ``n_blocks`` residual
blocks at 1/4 resolution, two stride-2 transposed convolutions back to full resolution and
a reflection-padded 7x7 convolution to one channel followed by ``tanh`` (n_lat in [-1, 1]).
InstanceNorm has no affine parameters and the convolutions carry biases, as in pix2pix.

Receptive field (:func:`receptive_field`): 89 pixels with the defaults' 2 down-samplings and
4 residual blocks (``2 * n_blocks`` 3x3 convolutions at 1/4 resolution); the options
``n_down`` (more down-sampling stages, width doubling each) and ``dilation`` (dilated 3x3
convolutions in the residual blocks) widen it cheaply, e.g. ``dilation=2`` gives 153,
``n_down=3`` 169 (4 blocks).
"""

from __future__ import annotations

import copy
from typing import Any

import torch
import torch.nn.functional as F
from torch import nn

N_DOWN = 2  # default stride-2 stages; input height and width must be divisible by 2**n_down
SIZE_MULTIPLE = 2**N_DOWN
# the reflection pad of the residual blocks needs >= 2 rows/columns at 1/4 resolution
MIN_SIZE = 2 * SIZE_MULTIPLE


def receptive_field(
    n_blocks: int, outer_kernel: int = 7, n_down: int = N_DOWN, dilation: int = 1
) -> int:
    """Receptive field (pixels, per axis) of :class:`NormalResNet` with these settings (an
    upper bound: the transposed convolutions make it up to 4 pixels smaller at some
    output pixels)."""
    rf, jump = 1, 1
    layers = [(outer_kernel, 1, 1)] + [(3, 2, 1)] * n_down + [(3, 1, dilation)] * (2 * n_blocks)
    for kernel, stride, dil in layers:
        rf += (kernel - 1) * dil * jump
        jump *= stride
    for _ in range(n_down):  # transposed 3x3 stride 2: one input pixel either side
        jump //= 2
        rf += 2 * jump
    return rf + outer_kernel - 1


def _norm(channels: int) -> nn.InstanceNorm2d:
    return nn.InstanceNorm2d(channels, affine=False, track_running_stats=False)


class ChannelNorm(nn.Module):
    """``InstanceNorm2d(affine=False, track_running_stats=False)`` computed as a group norm
    with one group per channel: the same normalisation (per sample and channel over the
    image, biased variance, ``eps``) through ``F.group_norm``, whose CPU kernel reads
    channels-last tensors as they are. ``InstanceNorm2d`` is a batch norm over a
    ``(1, B C, H, W)`` view, which needs a contiguous copy of a channels-last input: with
    bfloat16 convolutions (which oneDNN runs in channels-last) those copies and reorders were
    a third of the paper network's inference time (``torch.profiler``; see
    :func:`channel_norm_copy`)."""

    def __init__(self, eps: float = 1e-5) -> None:
        super().__init__()
        self.eps = float(eps)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return F.group_norm(x, int(x.shape[1]), eps=self.eps)

    def extra_repr(self) -> str:
        return f"eps={self.eps}"


def channel_norm_copy(net: nn.Module) -> nn.Module:
    """A copy of ``net`` with every ``InstanceNorm2d`` without affine parameters or running
    statistics (the network's :func:`_norm`) replaced by the equivalent :class:`ChannelNorm`
    (the same function; float rounding differs in the last bits). ``net`` is left as it is;
    other modules, parameters and buffers are copied unchanged."""
    out = copy.deepcopy(net)
    for module in out.modules():
        for name, child in list(module.named_children()):
            plain = (
                isinstance(child, nn.InstanceNorm2d)
                and not child.affine
                and not child.track_running_stats
            )
            if plain:
                setattr(module, name, ChannelNorm(child.eps))
    return out


class ResidualBlock(nn.Module):
    """``x + F(x)`` with F = pad-conv3x3-IN-ReLU-[dropout]-pad-conv3x3-IN; shape preserved."""

    def __init__(self, channels: int, use_dropout: bool = False, dilation: int = 1) -> None:
        super().__init__()
        layers: list[nn.Module] = [
            nn.ReflectionPad2d(dilation),
            nn.Conv2d(channels, channels, kernel_size=3, dilation=dilation),
            _norm(channels),
            nn.ReLU(inplace=True),
        ]
        if use_dropout:
            layers.append(nn.Dropout(0.5))
        layers += [
            nn.ReflectionPad2d(dilation),
            nn.Conv2d(channels, channels, kernel_size=3, dilation=dilation),
            _norm(channels),
        ]
        self.body = nn.Sequential(*layers)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return x + self.body(x)


class NormalResNet(nn.Module):
    """Encoder / residual / decoder network mapping ``[B, C, H, W]`` intensity to
    ``[B, 1, H, W]`` n_lat in [-1, 1].

    Args:
        in_channels: input channels (1: the normalised intensity).
        base_width: channels after the input convolution; the residual blocks run at
            ``4 * base_width`` (64 -> 256 in the paper-scale network).
        n_blocks: residual blocks (7 in the paper).
        outer_kernel: odd kernel size of the first and last convolution (7).
        use_dropout: dropout 0.5 inside the residual blocks.
        n_down: stride-2 down-sampling (and up-sampling) stages (2 in the paper).
        dilation: dilation of the residual blocks' 3x3 convolutions (1 in the paper).

    ``H`` and ``W`` must be multiples of ``2**n_down`` and at least ``2**n_down *
    max(2, dilation + 1)`` so that the output has the input's size; :meth:`forward` raises
    ``ValueError`` otherwise.
    """

    def __init__(
        self,
        in_channels: int = 1,
        base_width: int = 64,
        n_blocks: int = 7,
        outer_kernel: int = 7,
        use_dropout: bool = False,
        n_down: int = N_DOWN,
        dilation: int = 1,
    ) -> None:
        super().__init__()
        for name, value, minimum in (
            ("in_channels", in_channels, 1),
            ("base_width", base_width, 1),
            ("n_blocks", n_blocks, 0),
            ("n_down", n_down, 1),
            ("dilation", dilation, 1),
        ):
            if not isinstance(value, int) or isinstance(value, bool) or value < minimum:
                raise ValueError(f"{name}: expected an integer >= {minimum}, found {value!r}")
        if (
            not isinstance(outer_kernel, int)
            or isinstance(outer_kernel, bool)
            or outer_kernel < 1
            or outer_kernel % 2 == 0
        ):
            raise ValueError(
                f"outer_kernel: expected a positive odd integer, found {outer_kernel!r}"
            )
        self.in_channels = in_channels
        self.base_width = base_width
        self.n_blocks = n_blocks
        self.outer_kernel = outer_kernel
        self.use_dropout = bool(use_dropout)
        self.n_down = n_down
        self.dilation = dilation
        self.size_multiple = 2**n_down
        self.min_size = self.size_multiple * max(2, dilation + 1)

        pad = outer_kernel // 2
        layers: list[nn.Module] = [
            nn.ReflectionPad2d(pad),
            nn.Conv2d(in_channels, base_width, kernel_size=outer_kernel),
            _norm(base_width),
            nn.ReLU(inplace=True),
        ]
        width = base_width
        for _ in range(n_down):
            layers += [
                nn.Conv2d(width, 2 * width, kernel_size=3, stride=2, padding=1),
                _norm(2 * width),
                nn.ReLU(inplace=True),
            ]
            width *= 2
        layers += [ResidualBlock(width, self.use_dropout, dilation) for _ in range(n_blocks)]
        for _ in range(n_down):
            layers += [
                nn.ConvTranspose2d(
                    width, width // 2, kernel_size=3, stride=2, padding=1, output_padding=1
                ),
                _norm(width // 2),
                nn.ReLU(inplace=True),
            ]
            width //= 2
        layers += [
            nn.ReflectionPad2d(pad),
            nn.Conv2d(width, 1, kernel_size=outer_kernel),
            nn.Tanh(),
        ]
        self.layers = nn.Sequential(*layers)

    def config(self) -> dict[str, Any]:
        """Constructor arguments as plain values, with the class path under ``_target_``;
        stored in checkpoints so the network can be rebuilt without unpickling code."""
        return {
            "_target_": f"{type(self).__module__}.{type(self).__qualname__}",
            "in_channels": self.in_channels,
            "base_width": self.base_width,
            "n_blocks": self.n_blocks,
            "outer_kernel": self.outer_kernel,
            "use_dropout": self.use_dropout,
            "n_down": self.n_down,
            "dilation": self.dilation,
        }

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """``x [B, in_channels, H, W]`` float -> ``[B, 1, H, W]`` n_lat in [-1, 1]."""
        if x.ndim != 4 or x.shape[1] != self.in_channels:
            raise ValueError(
                f"x: expected shape [B, {self.in_channels}, H, W], found {tuple(x.shape)}"
            )
        h, w = int(x.shape[-2]), int(x.shape[-1])
        pad = self.outer_kernel // 2
        for name, size in (("H", h), ("W", w)):
            if size % self.size_multiple or size < self.min_size or size <= pad:
                raise ValueError(
                    f"x: expected {name} a multiple of {self.size_multiple} and >= "
                    f"{max(self.min_size, pad + 1)}, found {name}={size} (shape {tuple(x.shape)})"
                )
        return self.layers(x)
