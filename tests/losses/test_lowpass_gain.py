"""The shrinkage penalty on low-passed n_lat (sss2bathy.losses.normal.lowpass_slope,
lowpass_gain_loss) and its place in NormalLoss."""

import pytest
import torch

from sss2bathy.losses.normal import NormalLoss, lowpass_gain_loss, lowpass_slope


def _smooth_truth(seed: int = 0) -> tuple[torch.Tensor, torch.Tensor]:
    g = torch.Generator().manual_seed(seed)
    coarse = torch.randn(2, 1, 4, 6, generator=g) * 0.2
    target = torch.nn.functional.interpolate(coarse, size=(32, 48), mode="bilinear")
    mask = torch.rand(2, 1, 32, 48, generator=g) > 0.2
    return target, mask


def test_slope_reads_the_gain_of_the_slow_part_and_ignores_an_offset_and_white_noise():
    target, mask = _smooth_truth()
    g = torch.Generator().manual_seed(1)
    noise = 0.05 * torch.randn(target.shape, generator=g)
    for gain in (0.5, 1.0, 1.3):
        pred = gain * target + 0.02 + noise
        assert float(lowpass_slope(pred, target, mask, 8, 16)) == pytest.approx(gain, abs=0.05)
    assert float(lowpass_gain_loss(0.6 * target, target, mask, 8, 16)) == pytest.approx(
        0.16, abs=1e-3
    )
    # no penalty at or above a slope of 1: overshoot is the pixel term's to punish
    assert float(lowpass_gain_loss(1.4 * target, target, mask, 8, 16)) == 0.0


def test_gradient_raises_only_the_part_that_follows_the_truth():
    target, mask = _smooth_truth(2)
    pred = (0.5 * target).requires_grad_(True)
    lowpass_gain_loss(pred, target, mask, 8, 16).backward()
    grad = pred.grad
    assert torch.isfinite(grad).all()
    assert (grad[~mask] == 0).all()
    # a descent step moves the prediction towards the truth's pattern (negative correlation
    # of the gradient with the centred truth)
    t = target[mask] - target[mask].mean()
    assert float((grad[mask] * t).sum()) < 0


def test_degenerate_inputs_give_one_with_gradient_and_the_loss_term_is_weighted():
    target, mask = _smooth_truth()
    flat = torch.zeros_like(target)
    pred = target.clone().requires_grad_(True)
    out = lowpass_slope(pred, flat, mask, 8, 16)
    assert float(out.detach()) == 1.0
    out.backward()
    none = torch.zeros_like(mask)
    assert float(lowpass_slope(target, target, none, 8, 16)) == 1.0
    # invalid pixels (inf or NaN there) never reach the value, degenerate or not
    bad = torch.where(mask, target, torch.full_like(target, float("inf")))
    assert float(lowpass_slope(bad, flat, mask, 8, 16)) == 1.0
    assert float(lowpass_slope(bad, target, mask, 8, 16)) == pytest.approx(1.0, abs=1e-5)
    off = NormalLoss(kind="l1")
    assert "loss_gain" not in off(0.5 * target, target, mask)
    on = NormalLoss(kind="l1", lowpass_gain_weight=3.0, lowpass_pings=8, lowpass_bins=16)
    res = on(0.5 * target, target, mask)
    assert float(res["loss_gain"]) == pytest.approx(0.25, abs=1e-3)
    assert float(res["loss"]) == pytest.approx(
        float(res["loss_l1"] + res["loss_tv"] + 3.0 * res["loss_gain"]), rel=1e-6
    )
    assert NormalLoss.from_config(on.config()).config() == on.config()
    with pytest.raises(ValueError, match="lowpass_gain_weight"):
        NormalLoss(lowpass_gain_weight=-1.0)
