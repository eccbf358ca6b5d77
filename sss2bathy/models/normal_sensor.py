"""The paper's sensor model: the measurement of a bin is its head-plane normal ``n_lat``.

Optionally (``line_offset=True``) the fit also learns one ``n_lat`` offset per line and
side, subtracted from the target: a self-calibration of the inverse sensor model, the
normal-model analogue of the Lambertian model's learned gain and beam pattern. A CNN's
error has a low-frequency part, a bias that is nearly constant along a line's side
(README "CNN", ``cnn_bias.png``), and integrated across a swath it tilts the map by
metres; swaths that overlap, seen from both sides, and the altimeter heights constrain
the offsets, which a SIREN surface cannot otherwise absorb. ``offset_weight`` is an L2
prior on them. Sidescan only: nothing of the MBES grid is used.

Optionally (``lowpass_weight < 1``) the across-track low-frequency part of the residual
(SIREN minus target ``n_lat``, a moving average over ``lowpass_bins`` bins along each ping's
arc, :func:`sss2bathy.losses.siren.arc_lowpass`) pulls with that weight only: the target is
moved by ``(1 - lowpass_weight)`` of it (detached), so the slowly varying part of a CNN's
error -- what integrates into height -- is left more to the altimeter and the overlapping
swaths. 1 is eq. 9 exactly.
"""

from __future__ import annotations

import math
from typing import Any

import torch
from torch import nn

from sss2bathy.losses.siren import arc_lowpass, normal_2d_loss
from sss2bathy.models.sensors import ArcGeometry, SensorModel


class NormalSensorModel(SensorModel):
    """Normal loss (eq. 9) between the SIREN's and the target head-plane normals.

    Targets are draped MBES normals (SIREN-GT-N2d) or CNN predictions (SIREN-CNN-N2d),
    ``batch["n_lat"] (B, 2, n_bins)``. Bins whose target is not finite are not used.

    Args:
        line_offset: learn an ``n_lat`` offset per (line, side), subtracted from the target
            (module docstring); sized by :meth:`setup_lines`.
        offset_weight: weight of the offsets' mean square added to the loss (>= 0).
        lowpass_weight: weight in ``[0, 1]`` of the residual's across-track low-pass part
            (module docstring); 1 = eq. 9.
        lowpass_bins: the low-pass window along each arc (bins, >= 2).
    """

    target_key = "n_lat"

    def __init__(
        self,
        line_offset: bool = False,
        offset_weight: float = 0.0,
        lowpass_weight: float = 1.0,
        lowpass_bins: int = 32,
    ) -> None:
        super().__init__()
        if not isinstance(line_offset, bool):
            raise ValueError(f"line_offset: expected true or false, found {line_offset!r}")
        if (
            isinstance(lowpass_weight, bool)
            or not isinstance(lowpass_weight, int | float)
            or not 0.0 <= lowpass_weight <= 1.0
        ):
            raise ValueError(
                f"lowpass_weight: expected a number in [0, 1], found {lowpass_weight!r}"
            )
        if isinstance(lowpass_bins, bool) or not isinstance(lowpass_bins, int) or lowpass_bins < 2:
            raise ValueError(f"lowpass_bins: expected an integer >= 2, found {lowpass_bins!r}")
        self.lowpass_weight = float(lowpass_weight)
        self.lowpass_bins = int(lowpass_bins)
        # (n_lines, 2) when learned, sized by setup_lines() (or by a loaded state dict); off:
        # no parameter at all, so checkpoints of fits without offsets keep their keys
        self.register_parameter("line_offset", None)
        self.use_line_offset = False
        self.offset_weight = 0.0
        if line_offset:
            self.enable_line_offset(offset_weight)

    def enable_line_offset(self, offset_weight: float = 0.0) -> None:
        """Learn the per-(line, side) offsets, with ``offset_weight`` on their mean square."""
        if (
            isinstance(offset_weight, bool)
            or not isinstance(offset_weight, int | float)
            or not math.isfinite(offset_weight)
            or offset_weight < 0
        ):
            raise ValueError(
                f"offset_weight: expected a finite number >= 0, found {offset_weight!r}"
            )
        self.use_line_offset = True
        self.offset_weight = float(offset_weight)
        if self.line_offset is None:
            self.line_offset = nn.Parameter(torch.zeros(0, 2))

    def setup_lines(self, n_lines: int) -> None:
        """Size the per-(line, side) offsets for ``n_lines`` lines (zeros); a no-op when the
        offsets are off or already that size (e.g. restored from a checkpoint)."""
        if not isinstance(n_lines, int) or isinstance(n_lines, bool) or n_lines < 1:
            raise ValueError(f"n_lines: expected an integer >= 1, found {n_lines!r}")
        if not self.use_line_offset or self.line_offset.shape[0] == n_lines:
            return
        self.line_offset = nn.Parameter(torch.zeros(n_lines, 2))

    def _load_from_state_dict(self, state_dict: dict[str, Any], prefix: str, *args: Any) -> None:
        saved = state_dict.get(prefix + "line_offset")
        if saved is not None and self.use_line_offset and saved.shape != self.line_offset.shape:
            self.line_offset = nn.Parameter(torch.zeros_like(saved))
        super()._load_from_state_dict(state_dict, prefix, *args)

    def bin_mask(self, batch: dict[str, torch.Tensor]) -> torch.Tensor:
        """Valid mask bits and a finite target."""
        return super().bin_mask(batch) & torch.isfinite(batch[self.target_key])

    def loss(self, geo: ArcGeometry, target: torch.Tensor) -> tuple[torch.Tensor, dict]:
        """Eq. 9 over the bins of ``geo`` (against the target less its line/side offset when
        learned, plus the offsets' prior); logs the mean absolute ``n_lat`` error too.

        Args:
            geo: the bins' geometry at their crossings (``n_lat``, ``n_up`` with graph).
            target: ``(N,)`` target ``n_lat``.
        """
        if target.shape != geo.n_lat.shape:
            raise ValueError(
                f"target: expected shape {tuple(geo.n_lat.shape)}, found {tuple(target.shape)}"
            )
        logs: dict[str, torch.Tensor] = {}
        prior = None
        if self.use_line_offset:
            if self.line_offset.shape[0] == 0:
                raise RuntimeError("line_offset: not sized; call setup_lines(n_lines) first")
            target = target - self.line_offset[geo.line, geo.side]
            prior = self.offset_weight * self.line_offset.pow(2).mean()
            with torch.no_grad():
                logs["offset_rms"] = self.line_offset.pow(2).mean().sqrt()
        pulled = target  # what the loss pulls towards; the log stays against the target
        if self.lowpass_weight < 1.0:
            low = arc_lowpass(geo.n_lat - target, geo.ping, geo.side, geo.bin, self.lowpass_bins)
            pulled = target + (1.0 - self.lowpass_weight) * low
        loss = normal_2d_loss(geo.n_lat, geo.n_up, pulled)
        with torch.no_grad():
            logs["n_lat_mae"] = (
                (geo.n_lat - target).abs().mean() if target.numel() else loss.detach()
            )
        if prior is not None:
            loss = loss + prior
        return loss, logs

    def offsets(self) -> torch.Tensor:
        """``(n_lines, 2)`` learned offsets (port, starboard); ``(0, 2)`` when off."""
        if self.line_offset is None:
            return torch.zeros(0, 2)
        return self.line_offset.detach().clone()
