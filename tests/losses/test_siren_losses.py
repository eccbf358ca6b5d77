"""SIREN losses (eq. 7-9) and the normal sensor model."""

from __future__ import annotations

import math

import pytest
import torch

from sss2bathy.losses.siren import arc_lowpass, height_loss, normal_2d_loss, total_loss
from sss2bathy.models.normal_sensor import NormalSensorModel
from sss2bathy.models.sensors import ArcGeometry
from sss2bathy.models.siren import Siren


def test_height_loss_is_mean_absolute_error():
    z = torch.tensor([1.0, -2.0, 3.0], requires_grad=True)
    loss = height_loss(z, torch.tensor([1.5, -2.0, 2.0]))
    assert loss.item() == pytest.approx((0.5 + 0.0 + 1.0) / 3)
    loss.backward()
    assert torch.allclose(z.grad, torch.tensor([-1.0, 0.0, 1.0]) / 3)
    empty = torch.zeros(0, requires_grad=True)
    assert height_loss(empty, torch.zeros(0)).item() == 0.0
    with pytest.raises(ValueError, match="z_pred, z_true"):
        height_loss(z, torch.zeros(2))


def test_normal_2d_loss_golden_values_and_gradient():
    # SIREN normal straight up vs a target tilted to n_lat = 0.6: |(0,1) - (0.6,0.8)|
    n_lat = torch.tensor([0.0, 0.6], requires_grad=True)
    n_up = torch.tensor([1.0, 0.8], requires_grad=True)
    loss = normal_2d_loss(n_lat, n_up, torch.tensor([0.6, 0.6]))
    assert loss.item() == pytest.approx((math.sqrt(0.36 + 0.04) + 0.0) / 2, abs=1e-6)
    loss.backward()
    assert torch.isfinite(n_lat.grad).all() and torch.isfinite(n_up.grad).all()
    assert n_lat.grad[1].abs() < 1e-5  # the matching pair pulls nowhere
    # opposite normals are 2 apart; targets outside [-1, 1] are clipped
    assert normal_2d_loss(
        torch.tensor([1.0]), torch.tensor([0.0]), torch.tensor([-1.0])
    ).item() == pytest.approx(2.0)
    assert normal_2d_loss(
        torch.tensor([1.0]), torch.tensor([0.0]), torch.tensor([1.2])
    ).item() == pytest.approx(0.0, abs=1e-5)
    with pytest.raises(ValueError, match="n_lat"):
        normal_2d_loss(n_lat, n_up[:1], n_lat)


def test_total_loss_weights_height():
    assert total_loss(torch.tensor(0.3), torch.tensor(0.5), 2.0).item() == pytest.approx(1.3)
    with pytest.raises(ValueError, match="w_height"):
        total_loss(torch.tensor(0.0), torch.tensor(0.0), -1.0)


def _geo(n_lat: torch.Tensor) -> ArcGeometry:
    n = n_lat.shape[0]
    z3, z = torch.zeros(n, 3), torch.zeros(n)
    idx = torch.zeros(n, dtype=torch.long)
    return ArcGeometry(
        points=z3,
        theta=z,
        range_m=z + 10,
        side=idx,
        sonar=z3,
        rotation=torch.eye(3).expand(n, 3, 3),
        grad=torch.zeros(n, 2),
        n_lat=n_lat,
        n_up=torch.sqrt(1 - n_lat**2),
        ping=idx,
        bin=idx,
        line=idx,
    )


def test_normal_sensor_model_mask_and_loss():
    sensor = NormalSensorModel()
    assert sensor.target_key == "n_lat"
    batch = {
        "mask": torch.tensor([[[0, 1, 0]], [[0, 0, 2]]], dtype=torch.uint8),
        "n_lat": torch.tensor([[[0.1, 0.2, float("nan")]], [[0.3, 0.4, 0.5]]]),
    }
    assert sensor.bin_mask(batch).tolist() == [[[True, False, False]], [[True, True, False]]]
    pred = torch.tensor([0.0, 0.5])
    loss, logs = sensor.loss(_geo(pred), torch.tensor([0.0, 0.3]))
    assert loss.item() == pytest.approx(
        normal_2d_loss(pred, torch.sqrt(1 - pred**2), torch.tensor([0.0, 0.3])).item()
    )
    assert logs["n_lat_mae"].item() == pytest.approx(0.1)
    with pytest.raises(ValueError, match="target"):
        sensor.loss(_geo(pred), torch.zeros(3))


def test_line_offsets_absorb_a_per_line_side_bias_of_the_target():
    """With offsets equal to a target's per-(line, side) bias, the loss is the unbiased
    target's plus the prior; the offsets get gradients only where their bins are."""
    torch.manual_seed(0)
    n = 12
    pred = (torch.rand(n) - 0.5) * 0.4
    geo = _geo(pred)
    geo.line = torch.arange(n) % 3
    geo.side = (torch.arange(n) // 3) % 2
    truth = pred + (torch.rand(n) - 0.5) * 0.05
    bias = torch.tensor([[0.03, -0.02], [0.0, 0.05], [-0.04, 0.01]])
    sensor = NormalSensorModel(line_offset=True, offset_weight=0.5)
    with pytest.raises(RuntimeError, match="setup_lines"):
        sensor.loss(geo, truth)
    sensor.setup_lines(4)  # line 3 has no bins in the batch
    assert sensor.line_offset.shape == (4, 2) and sensor.line_offset.requires_grad
    with torch.no_grad():
        sensor.line_offset[:3] = bias
    loss, logs = sensor.loss(geo, truth + bias[geo.line, geo.side])
    plain = normal_2d_loss(pred, torch.sqrt(1 - pred**2), truth)
    prior = 0.5 * bias.pow(2).sum() / 8
    assert loss.item() == pytest.approx(plain.item() + prior.item(), rel=1e-5)
    assert logs["offset_rms"].item() == pytest.approx(math.sqrt(bias.pow(2).sum() / 8), rel=1e-5)
    loss.backward()
    grad = sensor.line_offset.grad
    assert torch.all(grad[:3] != 0)
    assert torch.all(grad[3] == 0)  # no bins, zero offset: the prior's gradient is 0 too
    # the offsets off: the target is used as is, no parameter is trained
    off = NormalSensorModel()
    off.setup_lines(4)
    assert off.line_offset is None and off.offsets().shape == (0, 2)
    assert "line_offset" not in off.state_dict()  # checkpoints without offsets keep their keys
    loss_off, logs_off = off.loss(geo, truth)
    assert loss_off.item() == pytest.approx(plain.item()) and "offset_rms" not in logs_off
    with pytest.raises(ValueError, match="offset_weight"):
        NormalSensorModel(line_offset=True, offset_weight=-1.0)
    with pytest.raises(ValueError, match="n_lines"):
        sensor.setup_lines(0)


def test_line_offsets_restore_from_a_state_dict_of_another_size():
    sensor = NormalSensorModel(line_offset=True)
    sensor.setup_lines(5)
    with torch.no_grad():
        sensor.line_offset.fill_(0.02)
    fresh = NormalSensorModel(line_offset=True)
    fresh.load_state_dict(sensor.state_dict())
    assert fresh.line_offset.shape == (5, 2) and torch.allclose(
        fresh.line_offset, torch.full((5, 2), 0.02)
    )
    fresh.setup_lines(5)  # the same size: kept, not zeroed
    assert torch.allclose(fresh.offsets(), torch.full((5, 2), 0.02))


def test_height_loss_alone_drives_a_siren_to_a_plane():
    torch.manual_seed(0)
    bounds, plane = (0.0, 0.0, 100.0, 80.0), (-18.0, 0.04, -0.03)

    def z_true(xy):
        return plane[0] + plane[1] * xy[:, 0] + plane[2] * xy[:, 1]

    siren = Siren(hidden=32, n_layers=3, omega0=3.0, bounds=bounds, z_range=(-22.0, -14.0))
    opt = torch.optim.Adam(siren.parameters(), lr=3e-3)
    g = torch.Generator().manual_seed(1)
    test_xy = torch.rand(2000, 2, generator=g) * torch.tensor([100.0, 80.0])
    mae0 = (siren.height(test_xy) - z_true(test_xy)).abs().mean().item()
    for _ in range(400):
        xy = torch.rand(256, 2, generator=g) * torch.tensor([100.0, 80.0])
        loss = height_loss(siren.height(xy), z_true(xy))
        opt.zero_grad()
        loss.backward()
        opt.step()
    with torch.no_grad():
        z, grad = siren.height_and_gradient(test_xy)
    mae = (z - z_true(test_xy)).abs().mean().item()
    assert mae0 > 0.5 and mae < 0.05
    assert torch.allclose(grad.mean(0), torch.tensor(plane[1:]), atol=5e-3)


def test_arc_lowpass_averages_along_each_ping_and_side_over_present_bins():
    # two pings x two sides x 8 bins, bin 3 of ping 0 port missing
    ping = torch.arange(2).repeat_interleave(16)
    side = torch.arange(2).repeat_interleave(8).repeat(2)
    bin = torch.arange(8).repeat(4)
    keep = ~((ping == 0) & (side == 0) & (bin == 3))
    values = (ping * 100 + side * 10 + bin).float()
    out = arc_lowpass(values[keep], ping[keep], side[keep], bin[keep], 3)
    full = arc_lowpass(values, ping, side, bin, 3)
    # a linear ramp is its own moving average inside an arc; the ends average what exists
    assert full[(ping == 1) & (side == 1)].tolist() == pytest.approx(
        [110.5, 111, 112, 113, 114, 115, 116, 116.5]
    )
    # the missing bin neither counts nor contributes; other arcs never leak in
    port0 = out[:7]  # ping 0, port: bins 0, 1, 2, 4, 5, 6, 7
    assert port0.tolist() == pytest.approx([0.5, 1.0, 1.5, 4.5, 5.0, 6.0, 6.5])
    assert torch.equal(out[7:], full[keep][7:])
    # width 1 is the identity; a window wider than the arc is the arc's mean
    assert torch.equal(arc_lowpass(values, ping, side, bin, 1), values)
    wide = arc_lowpass(values, ping, side, bin, 64)
    assert wide[:8].tolist() == pytest.approx([3.5] * 8)
    assert arc_lowpass(values[:0], ping[:0], side[:0], bin[:0], 3).numel() == 0
    with pytest.raises(ValueError, match="width"):
        arc_lowpass(values, ping, side, bin, 0)


def test_normal_sensor_lowpass_weight_discounts_the_slow_part_of_the_residual():
    """A target off by a constant along an arc (the slow part) costs nothing at weight 0
    and eq. 9's at weight 1; a target off by alternating signs (the fast part) costs the
    same at every weight."""
    n = 64
    pred = torch.linspace(-0.2, 0.2, n)
    geo = _geo(pred)
    geo.bin = torch.arange(n)
    slow = pred + 0.05
    fast = pred + 0.05 * (-1.0) ** torch.arange(n)
    plain = NormalSensorModel()
    blind = NormalSensorModel(lowpass_weight=0.0, lowpass_bins=8)
    half = NormalSensorModel(lowpass_weight=0.5, lowpass_bins=8)
    eq9 = plain.loss(geo, slow)[0].item()
    blind_loss, blind_logs = blind.loss(geo, slow)
    assert blind_loss.item() == pytest.approx(0.0, abs=1e-5)
    assert blind_logs["n_lat_mae"].item() == pytest.approx(0.05)  # against the target as given
    assert eq9 > 0.04
    assert half.loss(geo, slow)[0].item() == pytest.approx(eq9 / 2, rel=0.05)
    fast_eq9 = plain.loss(geo, fast)[0].item()
    assert blind.loss(geo, fast)[0].item() == pytest.approx(fast_eq9, rel=0.02)
    # the pull on the SIREN still flows through its own normals
    geo.n_lat = pred.clone().requires_grad_(True)
    geo.n_up = torch.sqrt(1 - geo.n_lat**2)
    half.loss(geo, slow)[0].backward()
    assert torch.all(geo.n_lat.grad < 0)  # descent raises the SIREN towards the target
    for bad in (-0.1, 1.5, True):
        with pytest.raises(ValueError, match="lowpass_weight"):
            NormalSensorModel(lowpass_weight=bad)
    with pytest.raises(ValueError, match="lowpass_bins"):
        NormalSensorModel(lowpass_bins=1)
