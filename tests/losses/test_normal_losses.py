"""Normal-aware loss (eq. 4-5), masked l1/l2/smooth-l1, total variation, NormalLoss config."""

import math

import pytest
import torch
from hydra import compose, initialize_config_dir
from hydra.utils import instantiate

from sss2bathy.cli._common import config_dir
from sss2bathy.losses import (
    NormalLoss,
    l1_loss,
    l2_loss,
    normal_aware_loss,
    smooth_l1_loss,
    tv_loss,
)

NAN = float("nan")
# 2x2 window, bottom-right pixel invalid (its NaN target must not matter)
PRED = torch.tensor([[0.5, -0.2], [0.0, 0.9]], dtype=torch.float64)
TARGET = torch.tensor([[0.3, -0.4], [0.1, NAN]], dtype=torch.float64)
MASK = torch.tensor([[True, True], [True, False]])
# per valid pixel: |d|, alpha = |gt|, lambda = 1 - min(p+1, g+1) / max(p+1, g+1)
ABS_D = (0.2, 0.2, 0.1)
WEIGHT = (0.3 + (1 - 1.3 / 1.5), 0.4 + (1 - 0.6 / 0.8), 0.1 + (1 - 1.0 / 1.1))


def test_normal_aware_equals_hand_computed_value():
    smooth = [0.5 * d * d for d in ABS_D]  # smooth-l1 with beta 1, |d| < 1
    expected = sum(w * s for w, s in zip(WEIGHT, smooth, strict=True)) / 3
    got = normal_aware_loss(PRED, TARGET, MASK)
    assert got.item() == pytest.approx(expected, rel=1e-12)
    assert got.item() == pytest.approx(0.0075404040, rel=1e-7)
    expected_l1 = sum(w * d for w, d in zip(WEIGHT, ABS_D, strict=True)) / 3
    assert normal_aware_loss(PRED, TARGET, MASK, base="l1").item() == pytest.approx(expected_l1)


def test_masked_pixels_get_no_gradient_even_with_nan_target():
    pred = PRED.clone().requires_grad_(True)
    normal_aware_loss(pred, TARGET, MASK).backward()
    assert torch.isfinite(pred.grad).all()
    assert pred.grad[1, 1] == 0
    assert (pred.grad[MASK] != 0).all()


def test_lambda_detached_is_a_weight_undetached_adds_its_gradient():
    pred = PRED.clone().requires_grad_(True)
    normal_aware_loss(pred, TARGET, MASK, base="l1").backward()
    # detached: d/dp of w * |p - g| / N = w * sign(d) / N
    assert pred.grad[0, 0].item() == pytest.approx(WEIGHT[0] / 3)
    pred2 = PRED.clone().requires_grad_(True)
    loss2 = normal_aware_loss(pred2, TARGET, MASK, base="l1", detach_lambda=False)
    loss2.backward()
    assert loss2.item() == pytest.approx(normal_aware_loss(PRED, TARGET, MASK, base="l1").item())
    # lambda = 1 - (g+1)/(p+1) for p > g: d lambda / dp = (g+1)/(p+1)^2, times l = 0.2
    assert pred2.grad[0, 0].item() == pytest.approx((WEIGHT[0] + 1.3 / 1.5**2 * 0.2) / 3)


def test_lambda_is_zero_for_perfect_prediction_including_minus_one():
    target = torch.tensor([-1.0, -0.5, 0.0, 1.0])
    pred = target.clone().requires_grad_(True)
    loss = normal_aware_loss(pred, target, torch.ones(4, dtype=torch.bool), base="l1")
    assert loss.item() == 0.0
    loss.backward()
    assert torch.isfinite(pred.grad).all()


def test_no_valid_pixel_gives_zero_with_gradient():
    pred = torch.randn(1, 1, 4, 4, requires_grad=True)
    mask = torch.zeros(1, 1, 4, 4, dtype=torch.bool)
    for fn in (normal_aware_loss, l1_loss, l2_loss, smooth_l1_loss):
        loss = fn(pred, torch.full_like(pred, NAN), mask)
        assert loss.item() == 0.0
        loss.backward()
        assert (pred.grad == 0).all()
    assert tv_loss(pred, mask).item() == 0.0


def test_plain_losses_match_torch_on_valid_pixels():
    g = torch.Generator().manual_seed(1)
    pred = torch.rand(2, 1, 6, 8, generator=g) * 2 - 1
    target = torch.rand(2, 1, 6, 8, generator=g) * 2 - 1
    mask = torch.rand(2, 1, 6, 8, generator=g) > 0.3
    p, t = pred[mask], target[mask]
    F = torch.nn.functional
    torch.testing.assert_close(l1_loss(pred, target, mask), F.l1_loss(p, t))
    torch.testing.assert_close(l2_loss(pred, target, mask), F.mse_loss(p, t))
    torch.testing.assert_close(
        smooth_l1_loss(pred, target, mask, beta=0.1), F.smooth_l1_loss(p, t, beta=0.1)
    )


def test_tv_loss_hand_computed_over_valid_pairs():
    pred = torch.tensor([[0.0, 0.1, 0.4], [0.2, 0.2, 0.0], [0.5, 0.0, 0.3]])
    mask = torch.tensor([[True, True, True], [True, False, True], [True, True, True]])
    # across-track (W) pairs with both valid: row0 (0,1),(1,2); row2 (0,1),(1,2)
    across = (0.1 + 0.3 + 0.5 + 0.3) / 4
    # along-track (H) pairs: col0 (0,1),(1,2); col2 (0,1),(1,2)
    along = (0.2 + 0.3 + 0.4 + 0.3) / 4
    got = tv_loss(pred, mask, across_track_weight=2.0, along_track_weight=0.5)
    assert got.item() == pytest.approx(2.0 * across + 0.5 * along)
    assert tv_loss(pred, mask, 1.0, 0.0).item() == pytest.approx(across)


def test_normal_loss_terms_by_kind():
    g = torch.Generator().manual_seed(2)
    pred = torch.rand(2, 1, 8, 8, generator=g) - 0.5
    target = torch.rand(2, 1, 8, 8, generator=g) - 0.5
    mask = torch.rand(2, 1, 8, 8, generator=g) > 0.2
    na = NormalLoss("normal_aware", tv_across_track=0.1, tv_along_track=0.2)(pred, target, mask)
    assert set(na) == {"loss", "loss_na", "loss_tv"}
    torch.testing.assert_close(na["loss_na"], normal_aware_loss(pred, target, mask))
    torch.testing.assert_close(na["loss_tv"], tv_loss(pred, mask, 0.1, 0.2))
    torch.testing.assert_close(na["loss"], na["loss_na"] + na["loss_tv"])
    l1 = NormalLoss("l1")(pred, target, mask)
    assert set(l1) == {"loss", "loss_l1", "loss_tv"} and l1["loss_tv"].item() == 0.0
    torch.testing.assert_close(l1["loss"], l1_loss(pred, target, mask))


def test_normal_loss_rejects_unknown_kind_and_bad_values_naming_them():
    # "<argument>: expected ..., found ...": start-up names the key (model.loss.<argument>)
    with pytest.raises(ValueError, match=r"^kind: expected one of \[.*'l3'$"):
        NormalLoss(kind="l3")
    with pytest.raises(ValueError, match=r"^base: expected one of \[.*'huber'$"):
        NormalLoss(base="huber")
    with pytest.raises(ValueError, match=r"^beta: expected a positive number, found 0$"):
        NormalLoss(beta=0)
    with pytest.raises(ValueError, match=r"^tv_along_track: expected a weight >= 0, found -1.0$"):
        NormalLoss(tv_along_track=-1.0)
    with pytest.raises(ValueError, match=r"^tv_across_track: expected .* found 'x'$"):
        NormalLoss(tv_across_track="x")
    with pytest.raises(ValueError, match="unknown option.*'tv_weight'"):
        NormalLoss.from_config({"kind": "l1", "tv_weight": 1.0})
    with pytest.raises(ValueError, match="mask"):
        normal_aware_loss(PRED, TARGET, MASK.double())
    with pytest.raises(ValueError, match="target"):
        l1_loss(PRED, TARGET[:1], MASK)


@pytest.mark.parametrize("name", ["normal_aware", "l1", "l2", "smooth_l1"])
def test_every_loss_config_instantiates(name):
    with initialize_config_dir(config_dir=config_dir(), version_base="1.3"):
        cfg = compose(config_name=f"loss/{name}")
    loss = instantiate(cfg.loss)
    assert isinstance(loss, NormalLoss) and loss.kind == name
    assert loss.tv_across_track >= 0 and math.isfinite(loss.tv_along_track)
