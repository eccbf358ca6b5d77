"""SIREN-Direct-Fit's objective (the paper's capacity check): the SIREN fitted to the MBES
grid directly, ``mean |Phi(x, y) - z_MBES|`` over random MBES cells of the surveyed area.

It takes the place of a sensor model in :class:`~sss2bathy.modules.siren.SirenModule`
(``model.sensor`` in ``conf/model/siren_direct_fit.yaml``): no arcs, no sidescan, the same
SIREN, optimiser, schedule and evaluation as every other SIREN fit.
"""

from __future__ import annotations

import numpy as np
import torch
from torch import nn

from sss2bathy.losses.siren import height_loss


class MBESCellFit(nn.Module):
    """Loss of the SIREN against ``n_points`` MBES cells drawn (global torch RNG) per step.

    Args:
        n_points: MBES cells per step (>= 1).

    The cells are set once the survey is known (:meth:`set_cells_from_grid`); they are a
    non-persistent buffer (checkpoints carry no survey data).
    """

    title = "SIREN-Direct-Fit"

    def __init__(self, n_points: int = 16384) -> None:
        super().__init__()
        if not isinstance(n_points, int) or isinstance(n_points, bool) or n_points < 1:
            raise ValueError(f"n_points: expected a positive integer, found {n_points!r}")
        self.n_points = n_points
        self.register_buffer("cells", torch.zeros(0, 3), persistent=False)

    def set_cells_from_grid(
        self, x: np.ndarray, y: np.ndarray, heights: np.ndarray | None, region: np.ndarray
    ) -> None:
        """Keep the finite cells of the grid ``heights (ny, nx)`` at ``x (nx,)``, ``y (ny,)``
        inside ``region (ny, nx)`` as ``(N, 3)`` points.

        Raises:
            ValueError: no grid (a survey without MBES), or no finite cell in the region.
        """
        if heights is None:
            raise ValueError(
                "model.sensor (MBESCellFit): expected a survey with an MBES grid, found none"
            )
        ok = region & np.isfinite(heights)
        xx, yy = np.meshgrid(x, y)
        cells = np.stack([xx[ok], yy[ok], heights[ok]], 1).astype(np.float32)
        if cells.shape[0] == 0:
            raise ValueError(
                "model.sensor (MBESCellFit): the MBES grid has no finite cell in the survey region"
            )
        self.cells = torch.from_numpy(cells).to(self.cells.device)

    def loss(self, siren: nn.Module) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
        """``(loss, {"loss_direct": detached loss})`` of one step."""
        if not self.cells.numel():
            raise RuntimeError("MBESCellFit: no MBES cells yet (set_cells_from_grid)")
        pick = torch.randint(self.cells.shape[0], (self.n_points,), device=self.cells.device)
        cells = self.cells[pick]
        loss = height_loss(siren.height(cells[:, :2]), cells[:, 2])
        return loss, {"loss_direct": loss.detach()}


__all__ = ["MBESCellFit"]
