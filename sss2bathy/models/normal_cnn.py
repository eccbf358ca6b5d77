"""The normal-estimation CNN: sidescan intensity window -> n_lat per pixel (paper Fig. "CNN
architecture": two down-sampling layers, seven residual blocks, two up-sampling layers and a
final convolution; InstanceNorm and ReLU).

The layout is the well-known pix2pix-style ResNet generator: a reflection-padded 7x7 input
convolution, two stride-2 3x3 convolutions that double the width, ``n_blocks`` residual
blocks at 1/4 resolution, two stride-2 transposed convolutions back to full resolution and
a reflection-padded 7x7 convolution to one channel followed by ``tanh`` (n_lat in [-1, 1]).
InstanceNorm has no affine parameters and the convolutions carry biases, as in pix2pix.
"""

from __future__ import annotations

from typing import Any

import torch
from torch import nn

N_DOWN = 2  # stride-2 stages; input height and width must be divisible by 2**N_DOWN
SIZE_MULTIPLE = 2**N_DOWN
# the reflection pad of the residual blocks needs >= 2 rows/columns at 1/4 resolution
MIN_SIZE = 2 * SIZE_MULTIPLE


def _norm(channels: int) -> nn.InstanceNorm2d:
    return nn.InstanceNorm2d(channels, affine=False, track_running_stats=False)


class ResidualBlock(nn.Module):
    """``x + F(x)`` with F = pad-conv3x3-IN-ReLU-[dropout]-pad-conv3x3-IN; shape preserved."""

    def __init__(self, channels: int, use_dropout: bool = False) -> None:
        super().__init__()
        layers: list[nn.Module] = [
            nn.ReflectionPad2d(1),
            nn.Conv2d(channels, channels, kernel_size=3),
            _norm(channels),
            nn.ReLU(inplace=True),
        ]
        if use_dropout:
            layers.append(nn.Dropout(0.5))
        layers += [
            nn.ReflectionPad2d(1),
            nn.Conv2d(channels, channels, kernel_size=3),
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

    ``H`` and ``W`` must be multiples of 4 and at least 8 so that the output has the input's
    size; :meth:`forward` raises ``ValueError`` otherwise.
    """

    def __init__(
        self,
        in_channels: int = 1,
        base_width: int = 64,
        n_blocks: int = 7,
        outer_kernel: int = 7,
        use_dropout: bool = False,
    ) -> None:
        super().__init__()
        for name, value, minimum in (
            ("in_channels", in_channels, 1),
            ("base_width", base_width, 1),
            ("n_blocks", n_blocks, 0),
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

        pad = outer_kernel // 2
        layers: list[nn.Module] = [
            nn.ReflectionPad2d(pad),
            nn.Conv2d(in_channels, base_width, kernel_size=outer_kernel),
            _norm(base_width),
            nn.ReLU(inplace=True),
        ]
        width = base_width
        for _ in range(N_DOWN):
            layers += [
                nn.Conv2d(width, 2 * width, kernel_size=3, stride=2, padding=1),
                _norm(2 * width),
                nn.ReLU(inplace=True),
            ]
            width *= 2
        layers += [ResidualBlock(width, self.use_dropout) for _ in range(n_blocks)]
        for _ in range(N_DOWN):
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
            if size % SIZE_MULTIPLE or size < MIN_SIZE or size <= pad:
                raise ValueError(
                    f"x: expected {name} a multiple of {SIZE_MULTIPLE} and >= "
                    f"{max(MIN_SIZE, pad + 1)}, found {name}={size} (shape {tuple(x.shape)})"
                )
        return self.layers(x)
