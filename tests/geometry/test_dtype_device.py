"""Every geometry function over dtypes and devices (kornia's parametrisation).

float32 and float64 on the CPU, and on CUDA where a GPU is present: golden values with
tolerances chosen by dtype, outputs on the input's dtype and device, gradcheck in
float64, and the numpy form (the same function through the numpy adapter) equal to the
torch form bit for bit.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from sss2bathy import geometry as G

DEVICES = ["cpu"] + (["cuda"] if torch.cuda.is_available() else [])
DTYPES = [torch.float32, torch.float64]
TOL = {torch.float32: {"atol": 1e-6, "rtol": 1e-5}, torch.float64: {"atol": 1e-12, "rtol": 1e-12}}


@pytest.fixture(params=DEVICES)
def device(request) -> torch.device:
    if request.param == "cuda":
        # golden float32 values: no TF32 in the matrix products
        matmul = torch.backends.cuda.matmul
        old = matmul.allow_tf32
        matmul.allow_tf32 = False
        yield torch.device("cuda")
        matmul.allow_tf32 = old
    else:
        yield torch.device("cpu")


@pytest.fixture(params=DTYPES, ids=["float32", "float64"])
def dtype(request) -> torch.dtype:
    return request.param


def _t(values, device, dtype) -> torch.Tensor:
    return torch.as_tensor(values, dtype=dtype, device=device)


def _close(actual: torch.Tensor, expected, dtype: torch.dtype) -> None:
    expected = torch.as_tensor(expected, dtype=actual.dtype, device=actual.device)
    torch.testing.assert_close(actual, expected, **TOL[dtype])


def _on(t: torch.Tensor, device: torch.device, dtype: torch.dtype) -> None:
    assert t.dtype == dtype and t.device.type == device.type


def _attitudes(device, dtype, n: int = 6) -> torch.Tensor:
    g = torch.Generator().manual_seed(7)
    heading = torch.rand(n, generator=g, dtype=torch.float64) * 2 * math.pi
    pitch, roll = 0.1 * torch.randn(2, n, generator=g, dtype=torch.float64)
    return G.attitude_to_rotation(heading, pitch, roll).to(device, dtype)


def test_attitude_to_rotation(device, dtype):
    quarter = _t([0.0, math.pi / 2], device, dtype)
    zero = torch.zeros_like(quarter)
    R = G.attitude_to_rotation(quarter, zero, zero)
    _on(R, device, dtype)
    _close(R[:, :, 0], [[0.0, 1.0, 0.0], [1.0, 0.0, 0.0]], dtype)  # forward: North, East
    _close(R[:, :, 1], [[-1.0, 0.0, 0.0], [0.0, 1.0, 0.0]], dtype)  # port: West, North
    assert G.check_rotations(_attitudes(device, dtype)).all()
    heading, pitch, roll = G.rotation_to_attitude(R)
    _on(heading, device, dtype)
    _close(heading, [0.0, math.pi / 2], dtype)


def test_side_sign(device, dtype):
    like = torch.zeros(4, device=device, dtype=dtype)
    sigma = G.side_sign(torch.tensor([0, 1, 1, 0], device=device), like)
    _on(sigma, device, dtype)
    assert sigma.tolist() == [1.0, -1.0, -1.0, 1.0]
    assert (G.SIDE_PORT, G.SIDE_STARBOARD) == (0, 1)
    with pytest.raises(ValueError, match="side: expected integer side indices"):
        G.side_sign(torch.tensor([0.0]), like)


def test_arc_basis_golden_and_orthonormal(device, dtype):
    level = G.attitude_to_rotation(*torch.zeros(3, 1, dtype=dtype)).to(device)
    u, w = G.arc_basis(level.expand(2, 3, 3), torch.tensor([0, 1], device=device))
    _on(u, device, dtype)
    _on(w, device, dtype)
    _close(u, [[-1.0, 0.0, 0.0], [1.0, 0.0, 0.0]], dtype)  # heading North: port West
    _close(w, [[0.0, 0.0, 1.0], [0.0, 0.0, 1.0]], dtype)
    R = _attitudes(device, dtype)
    side = torch.tensor([0, 1, 0, 1, 1, 0], device=device)
    u, w = G.arc_basis(R, side)
    _close((u * w).sum(-1), torch.zeros(6), dtype)
    _close(u.norm(dim=-1), torch.ones(6), dtype)
    # side broadcasts against R's batch shape: (6, 1, 3, 3) x (2,) -> (6, 2, 3)
    u2, w2 = G.arc_basis(R[:, None], torch.tensor([0, 1], device=device))
    assert u2.shape == w2.shape == (6, 2, 3)
    torch.testing.assert_close(u2[:, 0], -u2[:, 1], rtol=0, atol=0)


def test_arc_point_and_tangent(device, dtype):
    level = G.attitude_to_rotation(*torch.zeros(3, dtype=dtype)).to(device)
    s = _t([10.0, 20.0, -2.0], device, dtype)
    theta = _t(math.radians(30.0), device, dtype)
    r = _t(10.0, device, dtype)
    c = 10 * math.cos(math.radians(30.0))
    for side, x in ((0, 10 - c), (1, 10 + c)):
        p = G.arc_point(s, level, r, theta, side)
        _on(p, device, dtype)
        _close(p, [x, 20.0, -7.0], dtype)
        t = G.arc_tangent(level, r, theta, side)
        _on(t, device, dtype)
        _close(t, [(1 if side == 0 else -1) * 5.0, 0.0, -c], dtype)
    # the arc in world axes: p = s + r (cos u - sin w), with |p - s| = r
    R = _attitudes(device, dtype)
    side = torch.tensor([0, 1, 0, 1, 1, 0], device=device)
    th = _t(np.linspace(0.1, 1.2, 6), device, dtype)
    rr = _t(np.linspace(5.0, 40.0, 6), device, dtype)
    p = G.arc_point(torch.zeros(6, 3, device=device, dtype=dtype), R, rr, th, side)
    _close(p.norm(dim=-1), rr, dtype)
    u, w = G.arc_basis(R, side)
    _close(p, rr[:, None] * (torch.cos(th)[:, None] * u - torch.sin(th)[:, None] * w), dtype)


def test_normals_golden(device, dtype):
    flat = G.world_normal(
        torch.zeros(3, device=device, dtype=dtype), torch.zeros(3, device=device, dtype=dtype)
    )
    _on(flat, device, dtype)
    assert flat.tolist() == [[0.0, 0.0, 1.0]] * 3  # exact
    R = _attitudes(device, dtype)
    N = _t([[0.1, -0.3, 1.0]] * 6, device, dtype)
    nv = G.vehicle_normal(N, R)
    _on(nv, device, dtype)
    _close((R @ nv.unsqueeze(-1)).squeeze(-1), N, dtype)
    # (3, 4) -> (0.6, 0.8); the zero vector stays zero; NaN stays NaN
    lat, up = G.head_plane_unit(
        _t([3.0, 0.0, math.nan], device, dtype), _t([4.0, 0.0, 1.0], device, dtype)
    )
    _on(lat, device, dtype)
    _close(lat[:2], [0.6, 0.0], dtype)
    _close(up[:2], [0.8, 0.0], dtype)
    assert torch.isnan(lat[2]) and torch.isnan(up[2])
    # a plane falling towards port by ``slope``: n_lat = +-slope / sqrt(1 + slope^2)
    level = G.attitude_to_rotation(*torch.zeros(3, 2, dtype=dtype)).to(device)
    slope = 0.25
    gx = _t([slope, slope], device, dtype)  # heading North: port is West, z rises East
    n_lat, n_up = G.head_plane_normal_from_gradient(
        gx, torch.zeros_like(gx), level, torch.tensor([0, 1], device=device)
    )
    _on(n_lat, device, dtype)
    expected = slope / math.sqrt(1 + slope**2)
    _close(n_lat, [expected, -expected], dtype)
    _close(n_up, [1 / math.sqrt(1 + slope**2)] * 2, dtype)
    # the same through the arc basis, for any attitude
    R = _attitudes(device, dtype)
    side = torch.tensor([0, 1, 0, 1, 1, 0], device=device)
    via_vehicle = G.head_plane_normal(G.vehicle_normal(N, R), side)
    via_basis = G.head_plane_components(N, *G.arc_basis(R, side))
    _on(via_basis[0], device, dtype)
    for a, b in zip(via_basis, via_vehicle, strict=True):
        _close(a, b, dtype)


def test_incidence_golden(device, dtype):
    s = torch.zeros(3, device=device, dtype=dtype)
    level = G.attitude_to_rotation(*torch.zeros(3, dtype=dtype)).to(device)
    theta = math.radians(30.0)
    p = G.arc_point(s, level, _t(20.0, device, dtype), _t(theta, device, dtype), 0)
    up = _t([0.0, 0.0, 2.0], device, dtype)  # any length
    cos = G.incidence_cosine(up, p, s)
    _on(cos, device, dtype)
    _close(cos, math.sin(theta), dtype)  # flat floor: cos(incidence) = sin(depression)
    _close(G.incidence_angle(up, p, s), math.pi / 2 - theta, dtype)
    _close(G.grazing_angle(up, p, s), theta, dtype)
    _close(G.incidence_cosine(-up, p, s), -math.sin(theta), dtype)  # back-facing: < 0


def test_gradcheck_float64():
    g = torch.Generator().manual_seed(3)
    lat, up = torch.randn(2, 5, generator=g, dtype=torch.float64)
    assert torch.autograd.gradcheck(
        lambda a, b: G.head_plane_unit(a, b), (lat.requires_grad_(), up.requires_grad_())
    )
    n = torch.randn(5, 3, generator=g, dtype=torch.float64) + torch.tensor([0.0, 0.0, 3.0])
    p = torch.randn(5, 3, generator=g, dtype=torch.float64)
    s = p + torch.randn(5, 3, generator=g, dtype=torch.float64) + torch.tensor([0.0, 0.0, 5.0])
    assert torch.autograd.gradcheck(G.incidence_cosine, (n.requires_grad_(), p, s))
    R = _attitudes(torch.device("cpu"), torch.float64, 5)
    side = torch.tensor([0, 1, 1, 0, 1])
    th = torch.linspace(0.1, 1.0, 5, dtype=torch.float64).requires_grad_()
    assert torch.autograd.gradcheck(
        lambda t: G.arc_point(p, R, torch.full((5,), 9.0, dtype=torch.float64), t, side), (th,)
    )


def test_numpy_form_equals_torch_form_bit_for_bit():
    """The numpy adapter is the same function: numpy in, numpy out, identical bits."""
    rng = np.random.default_rng(5)
    n = 64
    R = G.attitude_to_rotation(rng.uniform(0, 6.3, n), rng.normal(0, 0.1, n), rng.normal(0, 0.1, n))
    side = rng.integers(0, 2, n)
    s, p = rng.normal(size=(n, 3)), rng.normal(size=(n, 3)) - [0, 0, 10]
    grad = rng.normal(0, 0.3, (n, 2))
    r, theta = rng.uniform(5, 40, n), rng.uniform(0, 1.2, n)
    N = G.world_normal(grad[:, 0], grad[:, 1])
    cases = {
        "side_sign": (G.side_sign, (side, r)),
        "arc_basis": (G.arc_basis, (R, side)),
        "arc_point": (G.arc_point, (s, R, r, theta, side)),
        "arc_tangent": (G.arc_tangent, (R, r, theta, side)),
        "world_normal": (G.world_normal, (grad[:, 0], grad[:, 1])),
        "vehicle_normal": (G.vehicle_normal, (N, R)),
        "head_plane_unit": (G.head_plane_unit, (grad[:, 0], grad[:, 1])),
        "head_plane_normal": (G.head_plane_normal, (G.vehicle_normal(N, R), side)),
        "head_plane_components": (G.head_plane_components, (N, *G.arc_basis(R, side))),
        "head_plane_normal_from_gradient": (
            G.head_plane_normal_from_gradient,
            (grad[:, 0], grad[:, 1], R, side),
        ),
        "incidence_cosine": (G.incidence_cosine, (N, p, s)),
        "incidence_angle": (G.incidence_angle, (N, p, s)),
        "grazing_angle": (G.grazing_angle, (N, p, s)),
        "rotation_to_attitude": (G.rotation_to_attitude, (R,)),
    }
    for name, (fn, args) in cases.items():
        out_np = fn(*args)
        out_t = fn(*(torch.as_tensor(a) for a in args))
        outs_np = out_np if isinstance(out_np, tuple) else (out_np,)
        outs_t = out_t if isinstance(out_t, tuple) else (out_t,)
        for a, b in zip(outs_np, outs_t, strict=True):
            assert isinstance(a, np.ndarray) and isinstance(b, torch.Tensor), name
            np.testing.assert_array_equal(a, b.numpy(), err_msg=name)
