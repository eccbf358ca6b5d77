"""The occlusion term: a sidescan shadow is seabed the sonar cannot see, so an object's height
lies in the shadow it casts, which neither sensor model predicts from a bin's own crossing.

Along one ping's side, bins in order of range, a crossing ``p`` of the bathymetry is seen
from the sonar ``s`` when nothing closer rises above its line of sight: its depression
angle ``atan((z_s - z_p) / |p_xy - s_xy|)`` is no larger than that of every closer crossing
(:func:`occluding_angle`: the running minimum of the closer bins). A measured shadow bin
whose crossing is seen, or a lit bin whose crossing is hidden, is a violation
(:func:`occlusion_loss`: hinges on the angle, in radians). The crossing heights carry the
graph, so the only way the fit removes a shadow bin's violation is to raise what is
closer (the object's top) or lower the shadowed seabed; the altimeter anchors the latter.
"""

from __future__ import annotations

import math

import torch


def extended_shadow(shadow: torch.Tensor, min_bins: int) -> torch.Tensor:
    """``shadow`` ``(..., B)`` bool kept only where it is part of a run of at least
    ``min_bins`` consecutive bins along range (a morphological opening): a wreck's or a rock's
    shadow is extended, a dark speckle at far range is not. ``min_bins`` <= 1: unchanged."""
    k = int(min_bins)
    if k <= 1 or shadow.shape[-1] < k:
        return shadow if k <= 1 else torch.zeros_like(shadow)
    x = shadow.to(torch.float32).reshape(-1, 1, shadow.shape[-1])
    ones = torch.ones(1, 1, k, dtype=x.dtype, device=x.device)
    # a window of k bins all in shadow (erosion), then every bin of such a window (dilation)
    full = torch.nn.functional.conv1d(x, ones) >= k - 0.5
    opened = torch.nn.functional.conv1d(full.to(x.dtype), ones, padding=k - 1) > 0.5
    return opened.reshape(shadow.shape) & shadow


def shadow_run_bins(min_m: float, range_m: torch.Tensor) -> int:
    """The bins a shadow must run to be ``min_m`` long at the median spacing of the bins'
    slant ranges ``range_m`` ``(B,)``."""
    spacing = float(range_m.diff().median().clamp_min(1e-6))
    return int(math.ceil(float(min_m) / spacing - 1e-6))


def depression_angle(
    points: torch.Tensor, height: torch.Tensor, sonar: torch.Tensor
) -> torch.Tensor:
    """``(N,)`` depression angle (rad, positive below the horizontal) of the crossings at
    ``points[:, :2]`` with heights ``height`` (with graph) seen from ``sonar`` ``(N, 3)``."""
    horizontal = (points[:, :2] - sonar[:, :2]).norm(dim=-1).clamp_min(1e-6)
    return torch.atan2(sonar[:, 2] - height, horizontal)


def occluding_angle(
    angle: torch.Tensor,
    ping: torch.Tensor,
    side: torch.Tensor,
    bin_index: torch.Tensor,
    shape: tuple[int, int, int],
) -> torch.Tensor:
    """``(N,)`` the smallest depression angle among the crossings of the same ping and side
    at a lower bin (closer range): the line of sight a crossing must not lie above to be
    seen; ``+inf`` where no closer bin has a crossing."""
    grid = torch.full(shape, float("inf"), dtype=angle.dtype, device=angle.device)
    grid = grid.index_put((ping, side, bin_index), angle)
    running = torch.cummin(grid, dim=-1).values
    closer = torch.cat([torch.full_like(running[..., :1], float("inf")), running[..., :-1]], -1)
    return closer[ping, side, bin_index]


def occlusion_loss(
    angle: torch.Tensor,
    ping: torch.Tensor,
    side: torch.Tensor,
    bin_index: torch.Tensor,
    shadow: torch.Tensor,
    shape: tuple[int, int, int],
) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
    """Mean hinge violation (rad) over the crossings with a closer one: a measured shadow
    (``shadow`` True) seen, ``relu(occluder - angle)``, or a lit bin hidden,
    ``relu(angle - occluder)``. Returns ``(loss, logs)``; logs: ``shadow_seen`` (fraction of
    shadow bins the bathymetry does not hide) and ``lit_hidden``."""
    occluder = occluding_angle(angle, ping, side, bin_index, shape)
    has = torch.isfinite(occluder)
    occluder = torch.where(has, occluder, angle.detach())
    seen = angle <= occluder
    err = torch.where(shadow, torch.relu(occluder - angle), torch.relu(angle - occluder))
    err = err[has]
    loss = err.mean() if err.numel() else angle.sum() * 0.0
    n_shadow = (shadow & has).sum().clamp_min(1)
    n_lit = (~shadow & has).sum().clamp_min(1)
    logs = {
        "shadow_seen": ((shadow & has & seen).sum() / n_shadow).detach(),
        "lit_hidden": ((~shadow & has & ~seen).sum() / n_lit).detach(),
    }
    return loss, logs


__all__ = [
    "depression_angle",
    "extended_shadow",
    "occluding_angle",
    "occlusion_loss",
    "shadow_run_bins",
]
