"""The low-pass n_lat loss term (sss2bathy.losses.normal.lowpass_loss) and its place in
NormalLoss."""

import pytest
import torch

from sss2bathy.losses.normal import NormalLoss, lowpass_loss, masked_box_mean


def _pair(seed: int = 0) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    g = torch.Generator().manual_seed(seed)
    target = torch.rand(2, 1, 32, 48, generator=g) - 0.5
    pred = target + 0.1 * torch.randn(2, 1, 32, 48, generator=g)
    mask = torch.rand(2, 1, 32, 48, generator=g) > 0.2
    return pred, target, mask


def test_box_mean_matches_a_direct_masked_average():
    pred, _, mask = _pair()
    mean, count = masked_box_mean(pred, mask, 4, 8)
    assert mean.shape == (2, 1, 29, 41)
    box, m = pred[1, 0, 5:9, 10:18], mask[1, 0, 5:9, 10:18]
    assert count[1, 0, 5, 10] == m.sum()
    assert mean[1, 0, 5, 10] == pytest.approx(float(box[m].mean()), abs=1e-6)
    swath, _ = masked_box_mean(pred, mask, 4, None)
    assert swath.shape == (2, 1, 29, 1)


def test_a_constant_offset_is_its_value_and_a_perfect_prediction_zero():
    _, target, mask = _pair()
    assert float(lowpass_loss(target + 0.05, target, mask, 8, 16)) == pytest.approx(0.05, abs=1e-6)
    assert float(lowpass_loss(target.clone(), target, mask, 8, None)) == pytest.approx(
        0.0, abs=1e-7
    )


def test_white_noise_is_damped_and_a_smooth_error_is_not():
    g = torch.Generator().manual_seed(3)
    target = torch.zeros(1, 1, 64, 64)
    mask = torch.ones_like(target, dtype=torch.bool)
    noise = 0.1 * torch.randn(1, 1, 64, 64, generator=g)
    ramp = torch.linspace(-0.1, 0.1, 64).view(1, 1, 64, 1).expand(1, 1, 64, 64)
    lp_noise = float(lowpass_loss(noise, target, mask, 16, 16))
    lp_ramp = float(lowpass_loss(ramp, target, mask, 16, 16))
    assert lp_noise < 0.15 * float(noise.abs().mean())
    assert lp_ramp > 0.7 * float(ramp.abs().mean())


def test_invalid_pixels_never_count_and_gradient_flows():
    pred, target, mask = _pair()
    target_nan = torch.where(mask, target, torch.full_like(target, float("nan")))
    pred_bad = torch.where(mask, pred, torch.full_like(pred, 9.0)).requires_grad_(True)
    loss = lowpass_loss(pred_bad, target_nan, mask, 8, 16)
    ref = lowpass_loss(pred, target, mask, 8, 16)
    assert float(loss.detach()) == pytest.approx(float(ref), rel=1e-5)
    loss.backward()
    assert torch.isfinite(pred_bad.grad).all()
    assert pred_bad.grad[mask].abs().sum() > 0
    assert (pred_bad.grad[~mask] == 0).all()
    empty = torch.zeros_like(mask)
    p = pred.clone().requires_grad_(True)
    zero = lowpass_loss(p, target, empty, 8, 16)
    zero.backward()
    assert float(zero) == 0.0


def test_normal_loss_adds_the_weighted_term_only_when_on():
    pred, target, mask = _pair()
    off = NormalLoss(kind="l1")
    assert "loss_lp" not in off(pred, target, mask)
    on = NormalLoss(kind="l1", lowpass_weight=2.0, lowpass_pings=8, lowpass_bins=16)
    out = on(pred, target, mask)
    assert float(out["loss"]) == pytest.approx(
        float(out["loss_l1"] + out["loss_tv"] + 2.0 * out["loss_lp"]), rel=1e-6
    )
    assert NormalLoss.from_config(on.config()).config() == on.config()
    with pytest.raises(ValueError, match="lowpass_pings"):
        NormalLoss(lowpass_pings=0)
    with pytest.raises(ValueError, match="low-pass box"):
        lowpass_loss(pred, target, mask, 64, 16)
