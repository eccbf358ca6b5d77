"""Losses for the normal CNN: the normal-aware loss (paper eq. 4-5), plain masked l1 / l2 /
smooth-l1, and total variation across- and along-track.

All functions take ``pred``, ``target`` of the same shape (typically ``[B, 1, H, W]``: H pings
along-track, W bins across-track) and a boolean ``mask`` of that shape (True = valid bin).
They reduce to a scalar mean over valid pixels (or valid neighbour pairs for TV) and return
``0`` -- still connected to ``pred``'s graph, so ``backward()`` works -- when nothing is valid.
Values at invalid pixels never reach the result or its gradient (a NaN target there is fine).
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import torch
from torch import nn

from sss2bathy.utils.checks import require_choice, require_number

BASES = ("l1", "l2", "smooth_l1")
KINDS = ("normal_aware", *BASES)
# short names of the data term, used as logging keys (``loss_na`` etc.)
DATA_TERM_KEYS = {
    "normal_aware": "loss_na",
    "l1": "loss_l1",
    "l2": "loss_l2",
    "smooth_l1": "loss_smooth_l1",
}


def _check(pred: torch.Tensor, mask: torch.Tensor, target: torch.Tensor | None = None) -> None:
    if not isinstance(pred, torch.Tensor) or not pred.is_floating_point():
        raise ValueError(
            f"pred: expected a floating-point tensor, found {type(pred).__name__} "
            f"{getattr(pred, 'dtype', '')}"
        )
    if target is not None and (not isinstance(target, torch.Tensor) or target.shape != pred.shape):
        raise ValueError(
            f"target: expected a tensor of pred's shape {tuple(pred.shape)}, "
            f"found {tuple(getattr(target, 'shape', ()))}"
        )
    if not isinstance(mask, torch.Tensor) or mask.dtype != torch.bool or mask.shape != pred.shape:
        raise ValueError(
            f"mask: expected a bool tensor of pred's shape {tuple(pred.shape)}, found "
            f"{getattr(mask, 'dtype', type(mask).__name__)} {tuple(getattr(mask, 'shape', ()))}"
        )


def _masked_mean(values: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    """Mean of ``values`` where ``mask``; ``0`` (with grad) when ``mask`` is all False."""
    total = torch.where(mask, values, torch.zeros_like(values)).sum()
    return total / mask.sum().clamp_min(1).to(values.dtype)


def _safe_target(pred: torch.Tensor, target: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    # Invalid pixels get the (detached) prediction: zero error there, and a NaN target can not
    # leak NaN into the gradient through ``torch.where``'s unselected branch.
    return torch.where(mask, target, pred.detach())


def pixel_loss(
    pred: torch.Tensor, target: torch.Tensor, base: str = "smooth_l1", beta: float = 1.0
) -> torch.Tensor:
    """Element-wise distance ``l(pred, target)``, same shape as the inputs.

    Args:
        base: ``l1`` (|d|), ``l2`` (d^2) or ``smooth_l1`` (0.5 d^2 / beta if |d| < beta,
            else |d| - 0.5 beta; Girshick 2015).
        beta: smooth-l1 transition point (> 0).
    """
    if base not in BASES:
        raise ValueError(f"base: expected one of {BASES}, found {base!r}")
    diff = pred - target
    if base == "l1":
        return diff.abs()
    if base == "l2":
        return diff.square()
    if not beta > 0:
        raise ValueError(f"beta: expected a positive number, found {beta!r}")
    return nn.functional.smooth_l1_loss(pred, target, reduction="none", beta=beta)


def l1_loss(pred: torch.Tensor, target: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    """Mean |pred - target| over valid pixels; shapes ``[...]``, ``mask`` bool."""
    _check(pred, mask, target)
    return _masked_mean(pixel_loss(pred, _safe_target(pred, target, mask), "l1"), mask)


def l2_loss(pred: torch.Tensor, target: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    """Mean (pred - target)^2 over valid pixels; shapes ``[...]``, ``mask`` bool."""
    _check(pred, mask, target)
    return _masked_mean(pixel_loss(pred, _safe_target(pred, target, mask), "l2"), mask)


def smooth_l1_loss(
    pred: torch.Tensor, target: torch.Tensor, mask: torch.Tensor, beta: float = 1.0
) -> torch.Tensor:
    """Mean smooth-l1(pred, target) over valid pixels; shapes ``[...]``, ``mask`` bool."""
    _check(pred, mask, target)
    return _masked_mean(pixel_loss(pred, _safe_target(pred, target, mask), "smooth_l1", beta), mask)


def normal_aware_weight(
    pred: torch.Tensor, target: torch.Tensor, detach_lambda: bool = True
) -> torch.Tensor:
    """Per-pixel weight ``alpha_N + lambda_N`` of the normal-aware loss (eq. 4-5).

    ``alpha_N = |n_GT|`` and ``lambda_N = 1 - min(n + 1, n_GT + 1) / max(n + 1, n_GT + 1)``
    (0 for a perfect prediction, towards 1 for a bad one). ``n + 1`` is clamped at 0 (for a
    prediction slightly below -1 from a network without ``tanh``); a 0/0 ratio (both at -1)
    counts as a perfect match (lambda 0).

    ``lambda_N`` is detached by default: it acts as a per-pixel weight on ``l`` -- the reading
    of eq. 4 in which "the gradients can still be back-propagated" through ``l`` where
    ``alpha_N ~ 0``, and the way the attention-driven loss the paper builds on (Jiao et al.
    2018) uses its regularisation term. ``detach_lambda=False`` also back-propagates through
    ``lambda_N`` (same value, a different, steeper gradient).
    """
    p1 = (pred.detach() if detach_lambda else pred).add(1.0).clamp_min(0.0)
    g1 = target.add(1.0).clamp_min(0.0)
    lo = torch.minimum(p1, g1)
    hi = torch.maximum(p1, g1)
    ratio = torch.where(hi > 0, lo / hi.clamp_min(torch.finfo(hi.dtype).tiny), torch.ones_like(hi))
    return target.abs() + (1.0 - ratio)


def normal_aware_loss(
    pred: torch.Tensor,
    target: torch.Tensor,
    mask: torch.Tensor,
    base: str = "smooth_l1",
    beta: float = 1.0,
    detach_lambda: bool = True,
) -> torch.Tensor:
    """Normal-aware loss, paper eq. 4: ``mean over valid pixels of (alpha_N + lambda_N) *
    l(pred, target)``, with ``alpha_N``, ``lambda_N`` from :func:`normal_aware_weight`.

    Args:
        pred, target: ``[...]`` n_lat in [-1, 1] (predicted and ground truth).
        mask: ``[...]`` bool, True = valid (not water column, shadow, no hit, out of beam).
        base: the distance ``l``: ``smooth_l1`` (paper), ``l1`` or ``l2``.
        beta: smooth-l1 transition point.
        detach_lambda: treat ``lambda_N`` as a constant weight (default, see
            :func:`normal_aware_weight`).

    Returns:
        scalar; ``0`` (with grad) if no pixel is valid.
    """
    _check(pred, mask, target)
    target = _safe_target(pred, target, mask)
    weight = normal_aware_weight(pred, target, detach_lambda)
    return _masked_mean(weight * pixel_loss(pred, target, base, beta), mask)


def masked_box_mean(
    values: torch.Tensor, mask: torch.Tensor, pings: int, bins: int | None
) -> tuple[torch.Tensor, torch.Tensor]:
    """Masked moving average of ``values [..., H, W]`` over ``pings x bins`` boxes.

    Returns ``(mean, count)`` of shape ``[..., H - pings + 1, W' ]`` (boxes wholly inside
    the window, stride 1; ``bins=None``: the whole width, ``W' = 1`` -- the swath average of
    each run of ``pings`` pings): the mean of the valid values in each box and the number of
    valid pixels it holds (mean 0 where none).
    """
    if values.ndim < 2:
        raise ValueError(f"values: expected at least 2 dims [..., H, W], found {values.ndim}")
    h, w = values.shape[-2:]
    bins = w if bins is None else bins
    if not (1 <= pings <= h and 1 <= bins <= w):
        raise ValueError(
            f"low-pass box: expected 1 <= pings <= {h} and 1 <= bins <= {w} (the window), "
            f"found {pings} x {bins}"
        )
    lead = values.shape[:-2]
    m = mask.to(values.dtype).reshape(-1, 1, h, w)
    v = torch.where(mask, values, torch.zeros_like(values)).reshape(-1, 1, h, w)
    area = float(pings * bins)
    total = nn.functional.avg_pool2d(v, (pings, bins), stride=1) * area
    count = nn.functional.avg_pool2d(m, (pings, bins), stride=1) * area
    mean = total / count.clamp_min(1.0)
    out_shape = (*lead, *mean.shape[-2:])
    return mean.reshape(out_shape), count.reshape(out_shape)


def _kept_boxes(
    pred: torch.Tensor,
    target: torch.Tensor,
    mask: torch.Tensor,
    pings: int,
    bins: int | None,
    min_fraction: float,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Box averages of ``pred`` and ``target`` over the same valid pixels and the boxes at
    least ``min_fraction`` valid: ``(pred means, target means, kept)``."""
    _check(pred, mask, target)
    require_number("min_fraction", min_fraction, lambda v: 0 <= v <= 1, "a fraction in [0, 1]")
    target = _safe_target(pred, target, mask)
    p_mean, count = masked_box_mean(pred, mask, pings, bins)
    t_mean, _ = masked_box_mean(target, mask, pings, bins)
    width = pred.shape[-1] if bins is None else bins
    return p_mean, t_mean, count >= max(1.0, min_fraction * pings * width)


def lowpass_loss(
    pred: torch.Tensor,
    target: torch.Tensor,
    mask: torch.Tensor,
    pings: int = 16,
    bins: int | None = None,
    min_fraction: float = 0.25,
) -> torch.Tensor:
    """The error of low-passed n_lat: ``mean |box(pred) - box(target)|`` over boxes.

    ``box`` is the masked ``pings x bins`` moving average (:func:`masked_box_mean`, the same
    valid pixels for prediction and truth; ``bins=None``: the swath average over the
    window's width). Only boxes with at least ``min_fraction`` of their pixels valid count.
    This is the error a map integrates (the part of the n_lat error correlated over tens of
    bins and pings); a per-pixel loss barely sees it. ``0`` (with grad) if no box counts.
    """
    p_mean, t_mean, keep = _kept_boxes(pred, target, mask, pings, bins, min_fraction)
    return _masked_mean((p_mean - t_mean).abs(), keep)


def lowpass_slope(
    pred: torch.Tensor,
    target: torch.Tensor,
    mask: torch.Tensor,
    pings: int = 16,
    bins: int | None = None,
    min_fraction: float = 0.25,
) -> torch.Tensor:
    """Least-squares slope of low-passed prediction on low-passed truth, over all boxes.

    The boxes are :func:`lowpass_loss`'s (the same masked ``pings x bins`` averages, only
    those at least ``min_fraction`` valid), pooled over the whole batch: ``cov(box(pred),
    box(target)) / var(box(target))``. 1 = the prediction's slowly varying part follows the
    truth's at full amplitude; below 1 it is shrunk towards the mean (what a pixel loss
    rewards where the network is unsure, and what a map integrates into a flattened relief).
    ``1`` (with grad) where fewer than two boxes count or the truth does not vary.
    """
    p_mean, t_mean, keep = _kept_boxes(pred, target, mask, pings, bins, min_fraction)
    # weighted by the kept boxes rather than indexed by them: no host sync in a training step
    w = keep.to(p_mean.dtype)
    n = w.sum()
    t_c = (t_mean - (t_mean * w).sum() / n.clamp_min(1.0)) * w
    p_c = p_mean - (p_mean * w).sum() / n.clamp_min(1.0)
    var = t_c.square().sum()
    cov = (p_c * t_c).sum()
    ok = (n >= 2) & (var > 0)
    # degenerate: 1, still connected to pred (through the kept boxes only)
    return torch.where(ok, cov / torch.where(ok, var, torch.ones_like(var)), cov * 0.0 + 1.0)


def lowpass_gain_loss(
    pred: torch.Tensor,
    target: torch.Tensor,
    mask: torch.Tensor,
    pings: int = 16,
    bins: int | None = None,
    min_fraction: float = 0.25,
) -> torch.Tensor:
    """``max(0, 1 - slope)^2`` of :func:`lowpass_slope`: a penalty on shrunk slow slopes.

    Its gradient raises only the part of the prediction that follows the truth (the slope's
    numerator is the covariance), so, beside a pixel or low-pass error term that penalises
    noise and overshoot, it removes their reward for predicting towards the mean. 0 at a
    slope of 1 or more.
    """
    slope = lowpass_slope(pred, target, mask, pings, bins, min_fraction)
    return nn.functional.relu(1.0 - slope).square()


def tv_loss(
    pred: torch.Tensor,
    mask: torch.Tensor,
    across_track_weight: float = 1.0,
    along_track_weight: float = 1.0,
) -> torch.Tensor:
    """Anisotropic total variation of ``pred [..., H, W]`` over pairs of valid neighbours.

    ``across_track_weight * mean |pred[..., :, j+1] - pred[..., :, j]|`` (bins, W axis)
    ``+ along_track_weight * mean |pred[..., i+1, :] - pred[..., i, :]|`` (pings, H axis),
    each mean taken over the neighbour pairs whose two pixels are valid (so a window's size
    does not change the scale); a direction without a valid pair contributes 0 (with grad).
    """
    _check(pred, mask)
    if pred.ndim < 2:
        raise ValueError(f"pred: expected at least 2 dims [..., H, W], found {tuple(pred.shape)}")
    for name, value in (
        ("across_track_weight", across_track_weight),
        ("along_track_weight", along_track_weight),
    ):
        if not isinstance(value, int | float) or isinstance(value, bool) or not value >= 0:
            raise ValueError(f"{name}: expected a number >= 0, found {value!r}")
    across = _masked_mean(
        (pred[..., :, 1:] - pred[..., :, :-1]).abs(), mask[..., :, 1:] & mask[..., :, :-1]
    )
    along = _masked_mean(
        (pred[..., 1:, :] - pred[..., :-1, :]).abs(), mask[..., 1:, :] & mask[..., :-1, :]
    )
    return across_track_weight * across + along_track_weight * along


class NormalLoss(nn.Module):
    """The CNN training objective: a data term chosen by name plus total variation.

    Args:
        kind: ``normal_aware`` (paper eq. 4-5), ``l1``, ``l2`` or ``smooth_l1``.
        base: distance inside the normal-aware loss (``smooth_l1`` in the paper).
        beta: smooth-l1 transition point (``smooth_l1`` kind or base).
        detach_lambda: see :func:`normal_aware_weight`.
        tv_across_track: weight of the across-track (bins) TV term, >= 0.
        tv_along_track: weight of the along-track (pings) TV term, >= 0.
        lowpass_weight: weight of the low-pass term (:func:`lowpass_loss`), >= 0 (0: off).
        lowpass_pings, lowpass_bins: its box (``lowpass_bins=None``: the window's width,
            i.e. the swath average of ``lowpass_pings`` pings).
        lowpass_gain_weight: weight of the shrinkage penalty on the same boxes
            (:func:`lowpass_gain_loss`), >= 0 (0: off).

    Calling it with ``(pred, target, mask)`` returns a dict: ``loss`` (the total to
    minimise), the data term under its key in :data:`DATA_TERM_KEYS` (``loss_na`` for the
    normal-aware kind), ``loss_tv`` (the weighted TV sum) and, when its weight is not 0,
    ``loss_lp`` (the unweighted low-pass term) and ``loss_gain`` (the unweighted shrinkage
    penalty).
    """

    def __init__(
        self,
        kind: str = "normal_aware",
        base: str = "smooth_l1",
        beta: float = 1.0,
        detach_lambda: bool = True,
        tv_across_track: float = 0.0,
        tv_along_track: float = 0.0,
        lowpass_weight: float = 0.0,
        lowpass_pings: int = 16,
        lowpass_bins: int | None = None,
        lowpass_gain_weight: float = 0.0,
    ) -> None:
        super().__init__()
        require_choice("kind", kind, KINDS)
        require_choice("base", base, BASES)
        require_number("beta", beta, lambda v: v > 0, "a positive number")
        for name, value in (
            ("tv_across_track", tv_across_track),
            ("tv_along_track", tv_along_track),
        ):
            require_number(name, value, lambda v: v >= 0, "a weight >= 0")
        for name, value in (
            ("lowpass_weight", lowpass_weight),
            ("lowpass_gain_weight", lowpass_gain_weight),
        ):
            require_number(name, value, lambda v: v >= 0, "a weight >= 0")
        for name, value in (("lowpass_pings", lowpass_pings), ("lowpass_bins", lowpass_bins)):
            if value is None and name == "lowpass_bins":
                continue
            if not isinstance(value, int) or isinstance(value, bool) or value < 1:
                raise ValueError(f"loss.{name}: expected an integer >= 1, found {value!r}")
        self.lowpass_weight = float(lowpass_weight)
        self.lowpass_gain_weight = float(lowpass_gain_weight)
        self.lowpass_pings = int(lowpass_pings)
        self.lowpass_bins = None if lowpass_bins is None else int(lowpass_bins)
        self.kind = kind
        self.base = base
        self.beta = float(beta)
        self.detach_lambda = bool(detach_lambda)
        self.tv_across_track = float(tv_across_track)
        self.tv_along_track = float(tv_along_track)

    @classmethod
    def from_config(cls, cfg: NormalLoss | Mapping[str, Any]) -> NormalLoss:
        """A ``NormalLoss`` itself, or one built from a mapping of its arguments
        (``_target_`` ignored)."""
        if isinstance(cfg, NormalLoss):
            return cfg
        if not isinstance(cfg, Mapping):
            raise ValueError(
                f"loss: expected a NormalLoss or a mapping, found {type(cfg).__name__}"
            )
        kwargs = {str(k): v for k, v in cfg.items() if k != "_target_"}
        unknown = sorted(set(kwargs) - set(cls().config()))
        if unknown:
            raise ValueError(
                f"loss: unknown option(s) {unknown}; expected {sorted(cls().config())}"
            )
        return cls(**kwargs)

    def config(self) -> dict[str, Any]:
        """The constructor arguments as plain values (for hparams)."""
        return {
            "kind": self.kind,
            "base": self.base,
            "beta": self.beta,
            "detach_lambda": self.detach_lambda,
            "tv_across_track": self.tv_across_track,
            "tv_along_track": self.tv_along_track,
            "lowpass_weight": self.lowpass_weight,
            "lowpass_pings": self.lowpass_pings,
            "lowpass_bins": self.lowpass_bins,
            "lowpass_gain_weight": self.lowpass_gain_weight,
        }

    def data_term(
        self, pred: torch.Tensor, target: torch.Tensor, mask: torch.Tensor
    ) -> torch.Tensor:
        if self.kind == "normal_aware":
            return normal_aware_loss(pred, target, mask, self.base, self.beta, self.detach_lambda)
        if self.kind == "l1":
            return l1_loss(pred, target, mask)
        if self.kind == "l2":
            return l2_loss(pred, target, mask)
        return smooth_l1_loss(pred, target, mask, self.beta)

    def forward(
        self, pred: torch.Tensor, target: torch.Tensor, mask: torch.Tensor
    ) -> dict[str, torch.Tensor]:
        """``pred, target [B, 1, H, W]``, ``mask [B, 1, H, W]`` bool -> dict of scalars."""
        data = self.data_term(pred, target, mask)
        tv = tv_loss(pred, mask, self.tv_across_track, self.tv_along_track)
        out = {"loss": data + tv, DATA_TERM_KEYS[self.kind]: data, "loss_tv": tv}
        pings = min(self.lowpass_pings, pred.shape[-2])
        bins = None if self.lowpass_bins is None else min(self.lowpass_bins, pred.shape[-1])
        if self.lowpass_weight > 0:
            lp = lowpass_loss(pred, target, mask, pings, bins)
            out["loss"] = out["loss"] + self.lowpass_weight * lp
            out["loss_lp"] = lp
        if self.lowpass_gain_weight > 0:
            gain = lowpass_gain_loss(pred, target, mask, pings, bins)
            out["loss"] = out["loss"] + self.lowpass_gain_weight * gain
            out["loss_gain"] = gain
        return out

    def extra_repr(self) -> str:
        return ", ".join(f"{k}={v}" for k, v in self.config().items())
