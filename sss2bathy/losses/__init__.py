"""Losses: the normal CNN's normal-aware loss, masked l1 / l2 / smooth-l1 and total variation."""

from sss2bathy.losses.normal import (
    DATA_TERM_KEYS,
    KINDS,
    NormalLoss,
    l1_loss,
    l2_loss,
    normal_aware_loss,
    normal_aware_weight,
    pixel_loss,
    smooth_l1_loss,
    tv_loss,
)

__all__ = [
    "DATA_TERM_KEYS",
    "KINDS",
    "NormalLoss",
    "l1_loss",
    "l2_loss",
    "normal_aware_loss",
    "normal_aware_weight",
    "pixel_loss",
    "smooth_l1_loss",
    "tv_loss",
]
