"""The paper's sensor model: the measurement of a bin is its head-plane normal ``n_lat``."""

from __future__ import annotations

import torch

from sss2bathy.losses.siren import normal_2d_loss
from sss2bathy.models.sensors import ArcGeometry, SensorModel


class NormalSensorModel(SensorModel):
    """Normal loss (eq. 9) between the SIREN's and the target head-plane normals.

    Targets are draped MBES normals (SIREN-GT-N2d) or CNN predictions (SIREN-CNN-N2d),
    ``batch["n_lat"] (B, 2, n_bins)``. Bins whose target is not finite are not used.
    """

    target_key = "n_lat"

    def bin_mask(self, batch: dict[str, torch.Tensor]) -> torch.Tensor:
        """Valid mask bits and a finite target."""
        return super().bin_mask(batch) & torch.isfinite(batch[self.target_key])

    def loss(self, geo: ArcGeometry, target: torch.Tensor) -> tuple[torch.Tensor, dict]:
        """Eq. 9 over the bins of ``geo``; logs the mean absolute ``n_lat`` error too.

        Args:
            geo: the bins' geometry at their crossings (``n_lat``, ``n_up`` with graph).
            target: ``(N,)`` target ``n_lat``.
        """
        if target.shape != geo.n_lat.shape:
            raise ValueError(
                f"target: expected shape {tuple(geo.n_lat.shape)}, found {tuple(target.shape)}"
            )
        loss = normal_2d_loss(geo.n_lat, geo.n_up, target)
        with torch.no_grad():
            n_lat_mae = (geo.n_lat - target).abs().mean() if target.numel() else loss.detach()
        return loss, {"n_lat_mae": n_lat_mae}
