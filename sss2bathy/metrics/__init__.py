"""Metrics: masked torchmetrics metrics of predicted normals (MAE, REL, RMSE, delta)."""

from sss2bathy.metrics.normal import (
    METRIC_NAMES,
    NormalDeltaAccuracy,
    NormalMAE,
    NormalMetrics,
    NormalREL,
    NormalRMSE,
)

__all__ = [
    "METRIC_NAMES",
    "NormalDeltaAccuracy",
    "NormalMAE",
    "NormalMetrics",
    "NormalREL",
    "NormalRMSE",
]
