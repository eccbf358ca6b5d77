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

import numpy as np
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


# ------------------------------------------------------------------ baseline and bias
def masked_mean(values, masks) -> float:
    """Mean of ``values`` over their valid bins, pooled over a sequence of arrays.

    This is the constant-prediction baseline's value: the training lines' mean n_lat.

    Args:
        values: sequence of arrays (numpy or torch, any shape), e.g. each training line's
            ``(P, 2, B)`` n_lat.
        masks: sequence of bool arrays of the same shapes (True = valid).

    Raises ``ValueError`` on mismatched shapes, non-bool masks or no valid bin at all.
    """
    values, masks = list(values), list(masks)
    if not values or len(values) != len(masks):
        raise ValueError(
            f"values, masks: expected two equally long non-empty sequences, found "
            f"{len(values)} and {len(masks)}"
        )
    total, count = 0.0, 0
    for i, (v, m) in enumerate(zip(values, masks, strict=True)):
        v, m = np.asarray(v, dtype=np.float64), np.asarray(m)
        if m.dtype != bool or m.shape != v.shape:
            raise ValueError(
                f"masks[{i}]: expected a bool array of shape {v.shape}, found {m.dtype} {m.shape}"
            )
        sel = v[m]
        if not np.isfinite(sel).all():
            raise ValueError(f"values[{i}]: expected finite values at valid bins, found NaN/inf")
        total += float(sel.sum())
        count += int(m.sum())
    if count == 0:
        raise ValueError("masks: expected at least one valid bin, found none")
    return total / count


class LineSideBias:
    """Running sums of prediction and truth per (line, side, bin across track).

    ``update`` takes a batch of windows (``pred, target, mask [B, 1, H, W]`` with the
    windows' ``line, side, bin_start [B]``) and adds, for every bin across track, the sums
    of the prediction and of the truth over the valid pixels and their count. Windows are
    counted as they come (overlapping windows count a bin once per window, as the table's
    metrics do). :meth:`line_side_rows` and :meth:`range_rows` turn the sums into means.
    """

    def __init__(self) -> None:
        # (line, side) -> [sum_pred (n,), sum_true (n,), count (n,)] float64 over bins
        self.sums: dict[tuple[int, int], list] = {}

    def update(
        self,
        pred: torch.Tensor,
        target: torch.Tensor,
        mask: torch.Tensor,
        line: torch.Tensor,
        side: torch.Tensor,
        bin_start: torch.Tensor,
    ) -> None:
        shape = tuple(pred.shape)
        if len(shape) != 4 or shape[1] != 1:
            raise ValueError(f"pred: expected shape [B, 1, H, W], found {shape}")
        if tuple(target.shape) != shape or tuple(mask.shape) != shape:
            raise ValueError(
                f"target, mask: expected pred's shape {shape}, found "
                f"{tuple(target.shape)} and {tuple(mask.shape)}"
            )
        if mask.dtype != torch.bool:
            raise ValueError(f"mask: expected dtype torch.bool, found {mask.dtype}")
        for name, t in (("line", line), ("side", side), ("bin_start", bin_start)):
            if tuple(t.shape) != (shape[0],):
                raise ValueError(f"{name}: expected shape ({shape[0]},), found {tuple(t.shape)}")
        # sums over the pings of each window: (B, W) per bin across track
        p = torch.where(mask, pred.detach(), 0).to(torch.float64)[:, 0].sum(1).cpu().numpy()
        g = torch.where(mask, target.detach(), 0).to(torch.float64)[:, 0].sum(1).cpu().numpy()
        c = mask[:, 0].sum(1).to(torch.float64).cpu().numpy()
        width = shape[3]
        for i, (li, si, b0) in enumerate(
            zip(line.tolist(), side.tolist(), bin_start.tolist(), strict=True)
        ):
            acc = self.sums.get((int(li), int(si)))
            need = int(b0) + width
            if acc is None:
                acc = [np.zeros(need), np.zeros(need), np.zeros(need)]
            elif len(acc[0]) < need:
                acc = [np.pad(a, (0, need - len(a))) for a in acc]
            self.sums[(int(li), int(si))] = acc
            for a, v in zip(acc, (p[i], g[i], c[i]), strict=True):
                a[int(b0) : need] += v

    def line_side_rows(self) -> list[dict[str, float]]:
        """One row per (line, side) with valid bins: ``line, side, count, mean_truth,
        mean_pred, bias`` (bias = mean prediction - mean truth), sorted by line and side."""
        rows = []
        for (li, si), (p, g, c) in sorted(self.sums.items()):
            n = float(c.sum())
            if n == 0:
                continue
            mp, mt = float(p.sum()) / n, float(g.sum()) / n
            rows.append(
                {"line": li, "side": si, "count": n, "mean_truth": mt, "mean_pred": mp,
                 "bias": mp - mt}
            )  # fmt: skip
        return rows

    def range_rows(self, n_range_bins: int = 16) -> list[dict[str, float]]:
        """Bias against range: the bins across track pooled over lines per side and grouped
        into ``n_range_bins`` equal groups of bin index (slant range grows with it).

        Rows ``side, range_bin, bin_lo, bin_hi, count, mean_truth, mean_pred, bias``
        (bins ``[bin_lo, bin_hi)``); groups without valid pixels are left out.
        """
        if not isinstance(n_range_bins, int) or isinstance(n_range_bins, bool) or n_range_bins < 1:
            raise ValueError(f"n_range_bins: expected an integer >= 1, found {n_range_bins!r}")
        if not self.sums:
            return []
        n_bins = max(len(a[0]) for a in self.sums.values())
        edges = np.unique(np.linspace(0, n_bins, min(n_range_bins, n_bins) + 1).round()).astype(int)
        rows = []
        for side in (0, 1):
            tot = np.zeros((3, n_bins))
            for (_, si), acc in self.sums.items():
                if si == side:
                    for k in range(3):
                        tot[k, : len(acc[k])] += acc[k]
            for j, (lo, hi) in enumerate(zip(edges[:-1], edges[1:], strict=True)):
                p, g, c = tot[:, lo:hi].sum(1)
                if c == 0:
                    continue
                rows.append(
                    {"side": side, "range_bin": j, "bin_lo": int(lo), "bin_hi": int(hi),
                     "count": float(c), "mean_truth": g / c, "mean_pred": p / c,
                     "bias": (p - g) / c}
                )  # fmt: skip
        return rows
