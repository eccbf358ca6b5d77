"""Siren: init, frame, explicit input gradient (vs autograd and finite differences)."""

from __future__ import annotations

import math

import pytest
import torch

from sss2bathy.geometry import attitude_to_rotation, head_plane_normal_from_gradient
from sss2bathy.models.siren import Siren

BOUNDS = (100.0, -50.0, 300.0, 150.0)
Z_RANGE = (-25.0, -9.0)


def _siren(**kw) -> Siren:
    torch.manual_seed(0)
    kw = {"hidden": 32, "n_layers": 4, "bounds": BOUNDS, "z_range": Z_RANGE, **kw}
    return Siren(**kw).double()


def _xy(n: int, seed: int = 1) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    lo = torch.tensor(BOUNDS[:2], dtype=torch.float64)
    hi = torch.tensor(BOUNDS[2:], dtype=torch.float64)
    return lo + (hi - lo) * torch.rand(n, 2, generator=g, dtype=torch.float64)


def test_init_ranges_follow_siren():
    torch.manual_seed(0)
    s = Siren(hidden=256, n_layers=5, omega0=30.0)
    first = s.sine_layers[0].weight
    assert first.abs().max() <= 1.0 / 2 + 1e-7
    assert first.abs().max() > 0.9 * 0.5  # uniform over the whole range
    bound = math.sqrt(6.0 / 256) / 30.0
    for layer in [*s.sine_layers[1:], s.out_layer]:
        assert layer.weight.abs().max() <= bound + 1e-7
        assert layer.weight.abs().max() > 0.95 * bound
    assert len(s.sine_layers) == 4 and s.out_layer.out_features == 1


def test_frame_scales_inputs_and_outputs():
    s = _siren()
    corners = torch.tensor([[BOUNDS[0], BOUNDS[1]], [BOUNDS[2], BOUNDS[3]], [200.0, 50.0]])
    u = s.normalized(corners.double())
    assert torch.allclose(u, torch.tensor([[-1.0, -1.0], [1.0, 1.0], [0.0, 0.0]]).double())
    with torch.no_grad():
        s.out_layer.weight.zero_()
        s.out_layer.bias.fill_(0.5)
    # z = mid + half * out = -17 + 8 * 0.5
    assert torch.allclose(s.height(corners.double()), torch.full((3,), -13.0).double())
    assert s.bounds == pytest.approx(BOUNDS) and s.z_range == pytest.approx(Z_RANGE)
    with pytest.raises(ValueError, match="bounds"):
        s.set_frame((0, 0, 0, 1), Z_RANGE)
    with pytest.raises(ValueError, match="z_range"):
        s.set_frame(BOUNDS, (1.0, 1.0))
    with pytest.raises(ValueError, match="xy"):
        s.height(torch.zeros(5, 3))


def test_explicit_gradient_equals_autograd_and_finite_differences():
    s = _siren()
    xy = _xy(200).requires_grad_(True)
    z, grad = s.height_and_gradient(xy)
    z_ref = s.height(xy)
    (grad_ref,) = torch.autograd.grad(z_ref.sum(), xy, create_graph=True)
    assert torch.allclose(z, z_ref, atol=1e-12)
    assert torch.allclose(grad, grad_ref, atol=1e-12)
    assert grad.abs().max() > 1e-3  # not trivially zero
    h = 1e-4
    with torch.no_grad():
        ex, ey = torch.tensor([h, 0.0]).double(), torch.tensor([0.0, h]).double()
        fd = torch.stack(
            [
                (s.height(xy + ex) - s.height(xy - ex)) / (2 * h),
                (s.height(xy + ey) - s.height(xy - ey)) / (2 * h),
            ],
            dim=1,
        )
    assert torch.allclose(grad.detach(), fd, atol=1e-7)
    # parameter gradients of a gradient loss: explicit forward == double backward
    params = list(s.parameters())
    g1 = torch.autograd.grad((grad**2).sum(), params, retain_graph=True, allow_unused=True)
    g2 = torch.autograd.grad((grad_ref**2).sum(), params, allow_unused=True)
    for a, b in zip(g1, g2, strict=True):
        assert (a is None and b is None) or torch.allclose(a, b, atol=1e-10)


def test_gradient_under_no_grad_matches_and_has_no_graph():
    s = _siren()
    xy = _xy(100)
    z, grad = s.height_and_gradient(xy)
    with torch.no_grad():
        z2, grad2 = s.height_and_gradient(xy)
    assert grad.requires_grad and not grad2.requires_grad
    assert torch.equal(z.detach(), z2) and torch.equal(grad.detach(), grad2)


def test_head_plane_normal_of_siren_equals_finite_differences():
    s = _siren()
    xy = _xy(64, seed=5)
    n = xy.shape[0]
    R = attitude_to_rotation(
        torch.rand(n).double() * 6.28, torch.zeros(n).double(), torch.full((n,), 0.05).double()
    )
    side = torch.arange(n) % 2
    _, grad = s.height_and_gradient(xy)
    n_lat, n_up = head_plane_normal_from_gradient(grad[:, 0], grad[:, 1], R, side)
    h = 1e-4
    with torch.no_grad():
        dzdx = (
            s.height(xy + torch.tensor([h, 0.0]).double())
            - s.height(xy - torch.tensor([h, 0.0]).double())
        ) / (2 * h)
        dzdy = (
            s.height(xy + torch.tensor([0.0, h]).double())
            - s.height(xy - torch.tensor([0.0, h]).double())
        ) / (2 * h)
    fd_lat, fd_up = head_plane_normal_from_gradient(dzdx, dzdy, R, side)
    assert torch.allclose(n_lat.detach(), fd_lat, atol=1e-7)
    assert torch.allclose(n_up.detach(), fd_up, atol=1e-7)
    assert torch.allclose(n_lat**2 + n_up**2, torch.ones(n).double(), atol=1e-9)


def test_state_dict_rebuilds_the_model():
    s = Siren(hidden=16, n_layers=3, omega0=12.0, bounds=BOUNDS, z_range=Z_RANGE)
    state = {f"siren.{k}": v for k, v in s.state_dict().items()}
    s2 = Siren.from_state_dict(state, prefix="siren.")
    assert (s2.hidden, s2.n_layers, s2.omega0) == (16, 3, 12.0)
    xy = _xy(10).float()
    assert torch.equal(s.height(xy), s2.height(xy))
    with pytest.raises(ValueError, match="state"):
        Siren.from_state_dict({"x": torch.zeros(1)})
