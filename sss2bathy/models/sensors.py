"""The sensor-model seam of the SIREN fit.

A SIREN fit (``modules/siren.py``) finds, for every valid bin of a batch of pings, where
the SIREN surface crosses the bin's isotemporal arc, evaluates the SIREN's height
gradient there (with a graph, so the loss reaches the SIREN), and hands the result to a
*sensor model*, which turns geometry into a loss against the bin's measurement:

* :class:`~sss2bathy.models.normal_sensor.NormalSensorModel` (the paper's method):
  measurement = head-plane normal ``n_lat`` (draped MBES normals or CNN predictions);
* :class:`~sss2bathy.models.lambertian.LambertianSensorModel` (the baseline):
  measurement = sidescan intensity, predicted by a Lambertian forward model.

The two differ only in this component; everything else of the fit is shared.
"""

from __future__ import annotations

from dataclasses import dataclass, fields
from typing import Any

import torch
from torch import nn


@dataclass
class ArcGeometry:
    """Geometry of ``N`` bins at their found seafloor crossings (flattened over pings/bins).

    Attributes:
        points: ``(N, 3)`` world crossing points (m), no graph.
        theta: ``(N,)`` depression angle of the crossing (rad), no graph.
        range_m: ``(N,)`` slant range (m).
        side: ``(N,)`` long, 0 port / 1 starboard.
        sonar: ``(N, 3)`` sonar positions (m).
        rotation: ``(N, 3, 3)`` vehicle -> world rotations.
        grad: ``(N, 2)`` SIREN height gradient ``(dz/dx, dz/dy)`` at the points, **with graph**.
        n_lat, n_up: ``(N,)`` SIREN head-plane normal (eq. 1-3), **with graph**.
        ping: ``(N,)`` long, index of the ping within the batch.
        bin: ``(N,)`` long, bin index within the side.
        line: ``(N,)`` long, line index within the datamodule's sidescan lines.
        height: ``(N,)`` SIREN height at the points' ``x, y``, **with graph** (None where the
            caller did not keep it).
    """

    points: torch.Tensor
    theta: torch.Tensor
    range_m: torch.Tensor
    side: torch.Tensor
    sonar: torch.Tensor
    rotation: torch.Tensor
    grad: torch.Tensor
    n_lat: torch.Tensor
    n_up: torch.Tensor
    ping: torch.Tensor
    bin: torch.Tensor
    line: torch.Tensor
    height: torch.Tensor | None = None

    def select(self, keep: torch.Tensor) -> ArcGeometry:
        """The bins where ``keep`` ``(N,)`` bool is True, every field alike."""
        return ArcGeometry(
            **{
                f.name: None if getattr(self, f.name) is None else getattr(self, f.name)[keep]
                for f in fields(self)
            }
        )


class SensorModel(nn.Module):
    """Base class: what a sensor model must provide.

    Attributes:
        target_key: the batch field holding the measurement, ``(B, 2, n_bins)``:
            ``"n_lat"`` or ``"intensity"``.
    """

    target_key: str = ""

    def bin_mask(self, batch: dict[str, torch.Tensor]) -> torch.Tensor:
        """``(B, 2, n_bins)`` bool: bins this model can use before any geometry is known.

        The default keeps the bins whose ``mask`` is 0; subclasses add their own rules
        (e.g. the Lambertian shadow threshold and near-range cut).
        """
        return batch["mask"] == 0

    def setup_from_data(self, sensor: Any, range_m: torch.Tensor) -> None:
        """Hook called once the data are known: ``sensor`` (:class:`~sss2bathy.survey.SensorParams`)
        and the bins' slant ranges ``range_m (n_bins,)``. Default: nothing to set up."""

    def loss(self, geo: ArcGeometry, target: torch.Tensor) -> tuple[torch.Tensor, dict]:
        """Loss over the ``N`` bins of ``geo`` against ``target (N,)``.

        Returns:
            ``(loss, logs)``: the scalar loss and a dict of named scalars/tensors to log.
        """
        raise NotImplementedError
