"""Masked metrics of predicted n_lat (paper Table "Quantitative Results For CNN").

MAE, REL, RMSE and the accuracies under threshold delta < 1.05^i, i = 1, 2, 3, computed over
valid pixels only. Every metric keeps running sums (``total``, ``count``) reduced with
``dist_reduce_fx="sum"``, so results are exact under DDP and across batches of any size.

Ratio-based metrics use ``n + 1``: ``n_lat`` lies in [-1, 1] and is mostly near 0, so a
ratio of ``n`` itself is undefined or explodes, while ``n + 1`` lies in [0, 2] with most
values near 1. With that shift ``REL = mean |n - n_GT| / (n_GT + 1)`` is close to the MAE,
as the paper's REL (0.0220) is to its MAE (0.0221), and ``delta = max((n+1)/(n_GT+1),
(n_GT+1)/(n+1))`` is a multiplicative error of ~|n - n_GT| near flat seabed. ``n + 1`` is
clamped at ``EPS`` so a value at -1 (a wall facing the sonar) cannot divide by zero.
"""

from __future__ import annotations

import torch
from torchmetrics import Metric, MetricCollection

EPS = 1e-6
DELTA_BASE = 1.05
METRIC_NAMES = ("mae", "rel", "rmse", "delta1", "delta2", "delta3")


class _MaskedNormalMetric(Metric):
    """Base: ``update(pred, target, mask)`` adds per-pixel values over valid pixels."""

    is_differentiable = False
    higher_is_better: bool | None = False
    full_state_update = False

    def __init__(self, **kwargs) -> None:
        super().__init__(**kwargs)
        self.add_state("total", default=torch.tensor(0.0), dist_reduce_fx="sum")
        self.add_state("count", default=torch.tensor(0, dtype=torch.long), dist_reduce_fx="sum")

    def _values(self, pred: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
        raise NotImplementedError

    def update(self, pred: torch.Tensor, target: torch.Tensor, mask: torch.Tensor) -> None:
        """``pred, target [...]`` n_lat, ``mask [...]`` bool (True = valid)."""
        if not isinstance(pred, torch.Tensor) or not isinstance(target, torch.Tensor):
            raise ValueError(
                f"pred, target: expected tensors, found {type(pred).__name__}, "
                f"{type(target).__name__}"
            )
        if target.shape != pred.shape:
            raise ValueError(
                f"target: expected pred's shape {tuple(pred.shape)}, found {tuple(target.shape)}"
            )
        if (
            not isinstance(mask, torch.Tensor)
            or mask.dtype != torch.bool
            or mask.shape != pred.shape
        ):
            raise ValueError(
                f"mask: expected a bool tensor of shape {tuple(pred.shape)}, found "
                f"{getattr(mask, 'dtype', type(mask).__name__)} {tuple(getattr(mask, 'shape', ()))}"
            )
        p = pred.detach()[mask].to(self.total.dtype)
        g = target.detach()[mask].to(self.total.dtype)
        self.total += self._values(p, g).sum()
        self.count += mask.sum()

    def _mean(self) -> torch.Tensor:
        # NaN when no valid pixel was seen: the metric is undefined, not zero
        return self.total / self.count.to(self.total.dtype)


class NormalMAE(_MaskedNormalMetric):
    """Mean absolute error ``mean |n - n_GT|`` over valid pixels."""

    def _values(self, p: torch.Tensor, g: torch.Tensor) -> torch.Tensor:
        return (p - g).abs()

    def compute(self) -> torch.Tensor:
        return self._mean()


class NormalREL(_MaskedNormalMetric):
    """Mean absolute relative error ``mean |n - n_GT| / (n_GT + 1)`` (see module doc)."""

    def _values(self, p: torch.Tensor, g: torch.Tensor) -> torch.Tensor:
        return (p - g).abs() / (g + 1.0).clamp_min(EPS)

    def compute(self) -> torch.Tensor:
        return self._mean()


class NormalRMSE(_MaskedNormalMetric):
    """Root mean squared error ``sqrt(mean (n - n_GT)^2)`` over valid pixels."""

    def _values(self, p: torch.Tensor, g: torch.Tensor) -> torch.Tensor:
        return (p - g).square()

    def compute(self) -> torch.Tensor:
        return self._mean().sqrt()


class NormalDeltaAccuracy(_MaskedNormalMetric):
    """Percentage of valid pixels with ``max((n+1)/(n_GT+1), (n_GT+1)/(n+1)) < threshold``.

    Args:
        threshold: the ratio bound (> 1), e.g. ``1.05 ** i``.
    """

    higher_is_better = True

    def __init__(self, threshold: float = DELTA_BASE, **kwargs) -> None:
        if (
            not isinstance(threshold, int | float)
            or isinstance(threshold, bool)
            or not threshold > 1
        ):
            raise ValueError(f"threshold: expected a number > 1, found {threshold!r}")
        super().__init__(**kwargs)
        self.threshold = float(threshold)

    def _values(self, p: torch.Tensor, g: torch.Tensor) -> torch.Tensor:
        a = (p + 1.0).clamp_min(EPS)
        b = (g + 1.0).clamp_min(EPS)
        return (torch.maximum(a / b, b / a) < self.threshold).to(self.total.dtype)

    def compute(self) -> torch.Tensor:
        return 100.0 * self._mean()


def NormalMetrics(prefix: str | None = None) -> MetricCollection:  # noqa: N802 - a factory
    """The paper's six metrics as a collection keyed ``mae, rel, rmse, delta1..3``
    (optionally prefixed, e.g. ``val/``); ``update(pred, target, mask)`` feeds all.

    ``compute_groups`` is off: grouping is decided from equal states after the first update,
    and delta2/delta3 often start equal (both 100 %), which would merge them for good.
    """
    return MetricCollection(
        {
            "mae": NormalMAE(),
            "rel": NormalREL(),
            "rmse": NormalRMSE(),
            "delta1": NormalDeltaAccuracy(DELTA_BASE),
            "delta2": NormalDeltaAccuracy(DELTA_BASE**2),
            "delta3": NormalDeltaAccuracy(DELTA_BASE**3),
        },
        prefix=prefix,
        compute_groups=False,
    )
