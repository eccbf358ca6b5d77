"""SIREN losses (paper eq. 7-9), pure functions.

* :func:`height_loss` — eq. 8: mean absolute signed vertical distance ``|Phi(x, y) - z|``
  at the altimeter points (the norm of a scalar is its absolute value).
* :func:`normal_2d_loss` — eq. 9: mean over valid bins of the Euclidean (L2) norm of the
  difference of the 2D head-plane normals, ``|| (n_lat, n_up) - (n_lat*, n_up*) ||_2``,
  where the target's ``n_up* = sqrt(1 - n_lat*^2)`` (the up component is non-negative by
  convention, so ``n_lat*`` alone determines the target unit vector).
* :func:`total_loss` — eq. 7: ``L = L_normal + w_H L_H``.
* :func:`arc_lowpass` — a moving average of per-bin values along each ping's range arc
  (ours): the across-track low-frequency part of the normal residual, which the normal
  sensor can discount (``NormalSensorModel(lowpass_weight=...)``).
"""

from __future__ import annotations

import torch

# Keeps the square root differentiable where SIREN and target normals coincide exactly.
_SQRT_EPS = 1e-12


def _check_same_shape(**tensors: torch.Tensor) -> None:
    shapes = {k: tuple(v.shape) for k, v in tensors.items()}
    if len(set(shapes.values())) != 1:
        raise ValueError(f"{', '.join(shapes)}: expected equal shapes, found {shapes}")


def height_loss(z_pred: torch.Tensor, z_true: torch.Tensor) -> torch.Tensor:
    """Eq. 8: ``mean |z_pred - z_true|`` (m).

    Args:
        z_pred: ``(M,)`` SIREN heights at the altimeter points' ``(x, y)`` (m).
        z_true: ``(M,)`` altimeter heights (m).

    Returns:
        Scalar; 0 (with graph) when ``M == 0``.
    """
    _check_same_shape(z_pred=z_pred, z_true=z_true)
    if z_pred.numel() == 0:
        return z_pred.sum()
    return (z_pred - z_true).abs().mean()


def normal_2d_loss(
    n_lat: torch.Tensor, n_up: torch.Tensor, n_lat_target: torch.Tensor
) -> torch.Tensor:
    """Eq. 9: mean L2 distance between SIREN and target head-plane unit normals.

    Args:
        n_lat, n_up: ``(N,)`` SIREN head-plane normal at the bins' crossings.
        n_lat_target: ``(N,)`` target lateral component in ``[-1, 1]`` (draped MBES or CNN).

    Returns:
        Scalar in ``[0, 2]``; 0 (with graph) when ``N == 0``.
    """
    _check_same_shape(n_lat=n_lat, n_up=n_up, n_lat_target=n_lat_target)
    if n_lat.numel() == 0:
        return n_lat.sum() + n_up.sum()
    target = n_lat_target.clamp(-1.0, 1.0)
    n_up_target = torch.sqrt((1.0 - target * target).clamp_min(0.0))
    sq = (n_lat - target) ** 2 + (n_up - n_up_target) ** 2
    return torch.sqrt(sq + _SQRT_EPS).mean()


def total_loss(normal: torch.Tensor, height: torch.Tensor, w_height: float = 1.0) -> torch.Tensor:
    """Eq. 7: ``L = L_normal + w_H L_H``."""
    if w_height < 0:
        raise ValueError(f"w_height: expected a non-negative weight, found {w_height}")
    return normal + w_height * height


# bin-index stride between consecutive (ping, side) arcs in arc_lowpass's sort key: wider
# than any arc plus window, so a window never reaches into the next arc
_ARC_STRIDE = 1 << 24


def arc_lowpass(
    values: torch.Tensor, ping: torch.Tensor, side: torch.Tensor, bin: torch.Tensor, width: int
) -> torch.Tensor:
    """Moving average of ``values`` over ``width`` bins centred on each bin, along its own
    ping and side, over the bins present only (missing bins neither count nor contribute).

    Sorted by (ping, side, bin), each window is a pair of binary searches into a cumulative
    sum: no grid sized from the data, so no host sync in a training step.

    Args:
        values: ``(N,)`` per-bin values (no graph is kept: the result is a detached estimate).
        ping, side, bin: ``(N,)`` long: each value's ping (within the batch), side (0 / 1)
            and bin index within the side (below 2**24).
        width: window length in bins (>= 1; odd or even, centred with the extra bin ahead).

    Returns:
        ``(N,)`` the window average at each bin.
    """
    _check_same_shape(values=values, ping=ping, side=side, bin=bin)
    if isinstance(width, bool) or not isinstance(width, int) or not 1 <= width < _ARC_STRIDE:
        raise ValueError(f"width: expected an integer in [1, {_ARC_STRIDE}), found {width!r}")
    with torch.no_grad():
        key = (ping * 2 + side) * _ARC_STRIDE + bin
        key, order = torch.sort(key)
        total = torch.zeros(values.numel() + 1, dtype=torch.float64, device=values.device)
        total[1:] = values.detach()[order].double().cumsum(0)
        lo = torch.searchsorted(key, key - (width - 1) // 2)
        hi = torch.searchsorted(key, key + width // 2, right=True)
        out = torch.empty_like(values)
        out[order] = ((total[hi] - total[lo]) / (hi - lo)).to(values.dtype)
        return out
