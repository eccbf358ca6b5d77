"""The synthetic scene of the SIREN benchmarks: pings of one line over a SIREN surface.

No survey, no files: a straight line in the paper's geometry (:func:`synthetic_pings`),
the paper's beam (:func:`paper_beam_limits`) and a freshly initialised SIREN whose output
range sets the relief (:func:`bench_siren`), optionally counting the points through each
of its passes (:class:`CountingSiren`).
"""

from __future__ import annotations

import math
from collections import Counter
from collections.abc import Mapping, Sequence
from typing import Any

import torch

from sss2bathy.geometry import attitude_to_rotation
from sss2bathy.models.siren import Siren
from sss2bathy.survey import MASK_WATER_COLUMN, SensorParams

#: water depth (m) and sonar depth below the surface (m) of the synthetic line
DEPTH_M = 18.0
SONAR_DEPTH_M = 1.5


class CountingSiren(Siren):
    """A :class:`Siren` that counts the points through each of its passes.

    ``points``: ``height`` / ``height_grad`` (heights without / with a graph) and
    ``gradient`` / ``gradient_grad`` (heights with input gradients, without / with one).
    """

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        self.points: Counter = Counter()

    def height(self, xy: torch.Tensor) -> torch.Tensor:
        self.points["height_grad" if torch.is_grad_enabled() else "height"] += xy.shape[0]
        return super().height(xy)

    forward = height

    def height_and_gradient(self, xy: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        key = "gradient_grad" if torch.is_grad_enabled() else "gradient"
        self.points[key] += xy.shape[0]
        return super().height_and_gradient(xy)


def paper_beam_limits() -> tuple[float, float]:
    """Beam limits (rad) of the paper's sidescan: 30 deg tilt, 60 deg beam width."""
    return SensorParams(math.radians(30.0), math.radians(60.0), 850e3, 1500.0).beam_limits_rad


def synthetic_pings(
    n_pings: int,
    n_bins: int,
    *,
    max_range_m: float = 50.0,
    depth_m: float = DEPTH_M,
    sonar_depth_m: float = SONAR_DEPTH_M,
    frame_m: tuple[float, float] = (350.0, 300.0),
    altimeter_points: int = 2000,
    n_batches: int = 1,
    seed: int = 0,
) -> tuple[list[dict[str, torch.Tensor]], tuple[float, float, float, float]]:
    """Ping batches of one straight line (paper geometry), without a survey.

    A line heads North through the middle of a ``frame_m`` survey at 2 m/s and 12 pings/s
    with a gentle roll/pitch motion; the sonar is ``sonar_depth_m`` below the surface over
    ``depth_m`` of water. Bins are ``max_range_m / n_bins`` apart; bins closer than the
    altitude are water column (``mask``), the others valid with random targets
    ``n_lat ~ U(-0.4, 0.4)``. Altimeter points lie below random pings at ``-depth_m``.

    Returns:
        ``n_batches`` consecutive batches of ``n_pings`` pings (the keys of
        :mod:`sss2bathy.data.pings`; ``index`` runs over all batches) and the frame bounds
        ``(xmin, ymin, xmax, ymax)`` (m).
    """
    for name, value in (("n_pings", n_pings), ("n_bins", n_bins), ("n_batches", n_batches)):
        if int(value) < 1:
            raise ValueError(f"{name}: expected >= 1, found {value}")
    gen = torch.Generator().manual_seed(seed)
    total = int(n_pings) * int(n_batches)
    t = torch.arange(total, dtype=torch.float64) / 12.0
    y = 2.0 * t - t[-1]  # centred on the frame
    position = torch.stack(
        [torch.zeros_like(y), y, torch.full_like(y, -float(sonar_depth_m))], 1
    ).float()
    roll = math.radians(1.0) * torch.sin(2 * math.pi * t / 6.0)
    pitch = math.radians(0.5) * torch.cos(2 * math.pi * t / 6.0)
    rotation = attitude_to_rotation(torch.zeros_like(t), pitch, roll).float()
    range_m = torch.linspace(max_range_m / n_bins, max_range_m, int(n_bins))
    altitude = float(depth_m) - float(sonar_depth_m)
    mask = torch.where(range_m < altitude, MASK_WATER_COLUMN, 0).to(torch.uint8)
    batches = []
    for k in range(int(n_batches)):
        sl = slice(k * n_pings, (k + 1) * n_pings)
        pick = torch.randint(int(n_pings), (int(altimeter_points),), generator=gen)
        alt_xy = position[sl][pick, :2]
        altimeter = torch.cat([alt_xy, torch.full((len(pick), 1), -float(depth_m))], 1)
        batches.append(
            {
                "position": position[sl].contiguous(),
                "rotation": rotation[sl].contiguous(),
                "range_m": range_m,
                "n_lat": (torch.rand(n_pings, 2, n_bins, generator=gen) - 0.5) * 0.8,
                "mask": mask.expand(n_pings, 2, n_bins).contiguous(),
                "line": torch.zeros(n_pings, dtype=torch.long),
                "ping": torch.arange(k * n_pings, (k + 1) * n_pings),
                "index": torch.arange(k * n_pings, (k + 1) * n_pings),
                "altimeter": altimeter,
            }
        )
    half_x, half_y = frame_m[0] / 2, frame_m[1] / 2
    return batches, (-half_x, -half_y, half_x, half_y)


def bench_siren(
    hidden: int,
    n_layers: int,
    omega0: float,
    bounds: Sequence[float],
    depth_m: float,
    relief_m: float,
    seed: int,
    counting: bool = False,
    precision: str = "fp32",
) -> Siren:
    """A SIREN surface for the benchmarks: paper init, output range ``-depth_m +- relief_m``.

    A freshly initialised SIREN's output is a small fraction of its range, so ``relief_m``
    sets the height variations (the finder section reports the resulting slopes).
    ``precision`` is the SIREN's training precision
    (:data:`~sss2bathy.models.siren.PRECISIONS`); ``counting``: a :class:`CountingSiren`.
    """
    torch.manual_seed(seed)
    cls = CountingSiren if counting else Siren
    z_range = (-depth_m - relief_m, -depth_m + relief_m)
    return cls(hidden, n_layers, omega0, bounds, z_range, precision=precision)


def to_device(batch: Mapping[str, torch.Tensor], device: torch.device) -> dict[str, torch.Tensor]:
    """The batch's tensors on ``device``."""
    return {k: v.to(device) for k, v in batch.items()}
