"""Siren: init, frame, explicit input gradient (vs autograd and finite differences), blocks,
the fused sine/cosine node and the training precision."""

from __future__ import annotations

import math

import pytest
import torch

from sss2bathy.geometry import attitude_to_rotation, head_plane_normal_from_gradient
from sss2bathy.models.siren import CPU_CHUNK, PRECISIONS, Siren, TwoScaleSiren, _SinCos

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


# ------------------------------------------------------------ blocks, fused nodes, precision
def _param_grads(s: Siren, loss: torch.Tensor) -> list[torch.Tensor]:
    return list(torch.autograd.grad(loss, list(s.parameters())))


def test_blocks_give_the_same_values_and_parameter_gradients():
    xy = _xy(300)
    whole, blocked = _siren(chunk=1000), _siren(chunk=64)  # 5 blocks, the last of 44 points
    z1, g1 = whole.height_and_gradient(xy)
    z2, g2 = blocked.height_and_gradient(xy)
    torch.testing.assert_close(z2, z1, rtol=0, atol=1e-12)
    torch.testing.assert_close(g2, g1, rtol=0, atol=1e-14)
    loss1 = (g1**2).sum() + z1.sum()
    loss2 = (g2**2).sum() + z2.sum()
    for a, b in zip(_param_grads(whole, loss1), _param_grads(blocked, loss2), strict=True):
        torch.testing.assert_close(b, a, rtol=1e-10, atol=1e-12)
    assert torch.equal(blocked.height(xy), torch.cat([blocked.height(c) for c in xy.split(64)]))
    # default: cache-sized blocks on CPU, everything at once elsewhere
    assert _siren().chunk_for(torch.device("cpu")) == CPU_CHUNK
    assert _siren().chunk_for(torch.device("cuda")) is None
    assert _siren(chunk=77).chunk_for(torch.device("cuda")) == 77


def test_sin_cos_node_backward_is_exact():
    pre = torch.randn(40, 7, dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(lambda p: _SinCos.apply(p), (pre,))
    s, c = _SinCos.apply(pre)
    (g_sin,) = torch.autograd.grad(s.sum(), pre)  # the cosine output unused
    torch.testing.assert_close(g_sin, torch.cos(pre).detach())
    s, c = _SinCos.apply(pre)
    (g_cos,) = torch.autograd.grad((3 * c).sum(), pre)  # the sine output unused
    torch.testing.assert_close(g_cos, -3 * torch.sin(pre).detach())


def test_invalid_precision_and_chunk_are_rejected():
    with pytest.raises(ValueError, match="precision"):
        Siren(precision="fp16")
    with pytest.raises(ValueError, match="chunk"):
        Siren(chunk=0)
    assert sorted(PRECISIONS) == ["bf16", "fp32"]


def _paper_siren(precision: str) -> Siren:
    torch.manual_seed(0)
    bounds, relief = (-175.0, -150.0, 175.0, 150.0), 50.0  # slopes ~0.1, as in the benchmark
    return Siren(128, 5, 30.0, bounds, (-18.0 - relief, -18.0 + relief), precision=precision)


def test_bf16_gradient_pass_error_at_paper_size():
    """bf16 hidden layers of the training gradient pass: ~1 % on slopes, < 5e-3 on n_lat."""
    from benchmarks.matmul import MatmulRecorder

    lo, hi = torch.tensor([-175.0, -150.0]), torch.tensor([175.0, 150.0])
    xy = lo + (hi - lo) * torch.rand(4096, 2, generator=torch.Generator().manual_seed(3))
    ref, low = _paper_siren("fp32"), _paper_siren("bf16")
    z32, g32 = ref.height_and_gradient(xy)
    with MatmulRecorder() as rec:
        z16, g16 = low.height_and_gradient(xy)
    dtypes = {lay[2] for sig in rec.calls for lay in sig[1]}
    assert dtypes == {"float32", "bfloat16"}  # hidden H x H in bf16; input/output layers fp32
    assert z16.dtype == g16.dtype == torch.float32 and g16.requires_grad
    n = xy.shape[0]
    R = attitude_to_rotation(
        torch.rand(n, dtype=torch.float64) * 6.28, torch.zeros(n).double(), torch.zeros(n).double()
    ).float()
    side = torch.arange(n) % 2
    n32, _ = head_plane_normal_from_gradient(g32[:, 0], g32[:, 1], R, side)
    n16, _ = head_plane_normal_from_gradient(g16[:, 0], g16[:, 1], R, side)
    err = (n16 - n32).detach().abs()
    assert err.quantile(0.99) < 5e-3 and err.median() < 1.5e-3
    rel = ((g16 - g32).norm(dim=1) / g32.norm(dim=1)).detach()
    assert 1e-4 < rel.median() < 0.03  # bf16 is really used, and close
    # this pass's heights carry bf16 rounding (about 1e-3 of the range, here +-50 m)
    torch.testing.assert_close(z16, z32, rtol=0, atol=0.1)
    # heights and passes without a graph ignore the precision: bit-identical to fp32
    assert torch.equal(low.height(xy), ref.height(xy))
    with torch.no_grad():
        a, b = low.height_and_gradient(xy), ref.height_and_gradient(xy)
    assert torch.equal(a[0], b[0]) and torch.equal(a[1], b[1])


def test_an_enclosing_autocast_acts_like_bf16_and_never_reaches_no_grad_passes():
    xy = _xy(500).float()
    ref, low = _paper_siren("fp32"), _paper_siren("bf16")
    ref.set_frame(BOUNDS, Z_RANGE)
    low.set_frame(BOUNDS, Z_RANGE)
    with torch.no_grad():
        z_nograd, g_nograd = ref.height_and_gradient(xy)
    with torch.autocast("cpu", dtype=torch.bfloat16):
        z_auto, g_auto = ref.height_and_gradient(xy)
        h_auto = ref.height(xy)
        with torch.no_grad():
            z_ng_auto, g_ng_auto = ref.height_and_gradient(xy)
    z_low, g_low = low.height_and_gradient(xy)
    assert torch.equal(g_auto, g_low) and torch.equal(z_auto, z_low)
    assert torch.equal(h_auto, ref.height(xy))
    assert torch.equal(g_ng_auto, g_nograd) and torch.equal(z_ng_auto, z_nograd)


# ------------------------------------------------------------------------ input encodings
def _encoding(kind: str):
    from sss2bathy.models.encoding import FourierFeatures, HashGridEncoding

    if kind == "fourier":
        return FourierFeatures(n_freq=16, sigma=3.0, learnable=True)
    # level 0 dense ((4+1)^2 <= 256), finer levels hashed; tables large enough to matter
    return HashGridEncoding(
        n_levels=4, log2_table_size=8, base_resolution=4, max_resolution=32, init_scale=0.5
    )


ENCODINGS = ["fourier", "hash"]


@pytest.mark.parametrize("kind", ENCODINGS)
def test_encoded_gradient_equals_autograd_and_trains_the_encoding(kind):
    torch.manual_seed(0)
    s = _siren(n_layers=3, hidden=16, chunk=16, encoding=_encoding(kind))
    assert s.sine_layers[0].in_features == s.encoding.out_dim
    xy = _xy(64)  # four blocks
    xr = xy.clone().requires_grad_(True)
    z_ref = s.height(xr)
    (auto,) = torch.autograd.grad(z_ref.sum(), xr, create_graph=True)
    z, grad = s.height_and_gradient(xy)
    assert torch.equal(z, z_ref)
    torch.testing.assert_close(grad, auto, rtol=1e-10, atol=1e-12)
    assert grad.abs().max() > 1e-3
    h = 1e-4  # central differences in world metres
    with torch.no_grad():
        ex, ey = torch.tensor([h, 0.0]).double(), torch.tensor([0.0, h]).double()
        fd = torch.stack(
            [
                (s.height(xy + ex) - s.height(xy - ex)) / (2 * h),
                (s.height(xy + ey) - s.height(xy - ey)) / (2 * h),
            ],
            dim=1,
        )
    torch.testing.assert_close(grad.detach(), fd, rtol=0, atol=1e-6)
    # parameter gradients of a gradient loss (encoding included): explicit == double backward
    names = [k for k, _ in s.named_parameters()]
    assert any(k.startswith("encoding.") for k in names)
    g1 = _param_grads(s, (grad**2).sum() + z.sum())
    g2 = _param_grads(s, (auto**2).sum() + z_ref.sum())
    for name, a, b in zip(names, g1, g2, strict=True):
        torch.testing.assert_close(a, b, rtol=1e-9, atol=1e-11, msg=name)
    enc_grad = g1[names.index(next(k for k in names if k.startswith("encoding.")))]
    assert enc_grad.abs().sum() > 0
    # the in-place pass without a graph (intersection finder, map) computes the same
    with torch.no_grad():
        z2, grad2 = s.height_and_gradient(xy)
    assert torch.equal(z2, z.detach()) and torch.equal(grad2, grad.detach())


@pytest.mark.parametrize("kind", ENCODINGS)
def test_encoded_bf16_training_pass_stays_close(kind):
    torch.manual_seed(0)
    ref = Siren(32, 4, 30.0, BOUNDS, Z_RANGE, encoding=_encoding(kind))
    low = Siren(32, 4, 30.0, BOUNDS, Z_RANGE, precision="bf16", encoding=_encoding(kind))
    low.load_state_dict(ref.state_dict())
    xy = _xy(512).float()
    g32 = ref.height_and_gradient(xy)[1]
    g16 = low.height_and_gradient(xy)[1]  # hidden layers in bf16, encoding + layer 1 fp32
    rel = ((g16 - g32).norm() / g32.norm()).item()
    assert 1e-5 < rel < 0.05
    with torch.no_grad():  # no graph: always fp32, bit-identical
        assert torch.equal(low.height_and_gradient(xy)[1], ref.height_and_gradient(xy)[1])
    assert torch.equal(low.height(xy), ref.height(xy))


@pytest.mark.parametrize("kind", ENCODINGS)
def test_encoded_init_and_state_dict_rebuild(kind):
    torch.manual_seed(0)
    s = Siren(hidden=64, n_layers=3, bounds=BOUNDS, z_range=Z_RANGE, encoding=_encoding(kind))
    d = s.encoding.out_dim
    bound = math.sqrt(6.0 / d) / 30.0  # the hidden-layer init for the encoded first layer
    w = s.sine_layers[0].weight
    assert 0.9 * bound < w.abs().max().item() <= bound + 1e-7
    state = {f"siren.{k}": v for k, v in s.state_dict().items()}
    r = Siren.from_state_dict(state, prefix="siren.")
    assert type(r.encoding) is type(s.encoding) and r.encoding.out_dim == d
    xy = _xy(32).float()
    for a, b in zip(r.height_and_gradient(xy), s.height_and_gradient(xy), strict=True):
        assert torch.equal(a, b)
    plain = Siren(hidden=8, n_layers=3)
    assert plain.encoding is None
    assert not any(k.startswith("encoding") for k in plain.state_dict())
    assert [k for k, _ in plain.named_parameters()] == [
        "sine_layers.0.weight",
        "sine_layers.0.bias",
        "sine_layers.1.weight",
        "sine_layers.1.bias",
        "out_layer.weight",
        "out_layer.bias",
    ]
    assert Siren.from_state_dict(plain.state_dict()).encoding is None


@pytest.mark.parametrize("kind", [None, *ENCODINGS])
def test_empty_input_gives_empty_outputs(kind):
    s = _siren(encoding=None if kind is None else _encoding(kind))
    xy = torch.zeros(0, 2, dtype=torch.float64)
    z, grad = s.height_and_gradient(xy)
    assert z.shape == (0,) and grad.shape == (0, 2) and s.height(xy).shape == (0,)
    with torch.no_grad():
        assert s.height_and_gradient(xy)[1].shape == (0, 2)


def test_encoding_argument_is_validated():
    from sss2bathy.models.encoding import FourierFeatures

    with pytest.raises(ValueError, match="encoding: expected None or an Encoding with in_dim 2"):
        Siren(encoding=FourierFeatures(in_dim=3))
    with pytest.raises(ValueError, match="encoding: .*found Linear"):
        Siren(encoding=torch.nn.Linear(2, 4))


def test_model_config_instantiates_an_encoded_siren():
    """conf/model/siren_normals.yaml's ``siren`` block: ``encoding: null`` by default, and a
    ``_target_`` override builds the encoding through Hydra's recursive instantiation."""
    from pathlib import Path

    import hydra
    from omegaconf import OmegaConf

    path = Path(__file__).resolve().parents[2] / "conf" / "model" / "siren_normals.yaml"
    block = OmegaConf.load(path).siren
    assert block.encoding is None
    block.omega0 = 30.0  # ${scale.siren.omega0} outside a composed config
    plain = hydra.utils.instantiate(block, _recursive_=True, _convert_="partial")()
    assert plain.encoding is None and plain.sine_layers[0].in_features == 2
    block.encoding = {
        "_target_": "sss2bathy.models.encoding.FourierFeatures",
        "n_freq": 16,
        "sigma": 4.0,
    }
    enc = hydra.utils.instantiate(block, _recursive_=True, _convert_="partial")()
    assert type(enc.encoding).__name__ == "FourierFeatures"
    assert enc.sine_layers[0].in_features == 2 + 2 * 16


def test_compiled_no_graph_pass_matches_eager_and_keeps_one_shape():
    torch.manual_seed(0)
    eager = Siren(hidden=16, n_layers=3, bounds=(0, 0, 50, 40), z_range=(-20, -10), chunk=64)
    compiled = Siren(hidden=16, n_layers=3, bounds=(0, 0, 50, 40), z_range=(-20, -10), chunk=64,
                     compile_no_graph=True)  # fmt: skip
    compiled.load_state_dict(eager.state_dict())
    xy = torch.rand(150, 2) * torch.tensor([50.0, 40.0])  # 64 + 64 + 22 (padded to 64)
    with torch.no_grad():
        z_e, g_e = eager.height_and_gradient(xy)
        z_c, g_c = compiled.height_and_gradient(xy)
    assert z_c.shape == (150,) and g_c.shape == (150, 2)
    torch.testing.assert_close(z_c, z_e, atol=1e-5, rtol=1e-6)
    torch.testing.assert_close(g_c, g_e, atol=1e-6, rtol=1e-5)
    # with a graph (training) the eager path runs: bit for bit the eager model's
    z_t, g_t = compiled.height_and_gradient(xy)
    z_r, g_r = eager.height_and_gradient(xy)
    assert torch.equal(z_t, z_r) and torch.equal(g_t, g_r) and g_t.requires_grad
    with pytest.raises(ValueError, match="compile_no_graph: expected true or false"):
        Siren(compile_no_graph="yes")


# ----------------------------------------------------------------- two scales
def _two_scale(**kw) -> TwoScaleSiren:
    torch.manual_seed(3)
    return TwoScaleSiren(
        detail_omega0=60.0, hidden=32, n_layers=3, omega0=10.0,
        bounds=(0.0, 0.0, 100.0, 80.0), z_range=(-20.0, -5.0), **kw,
    )  # fmt: skip


def test_two_scale_starts_as_its_base_and_sums_both_after():
    m = _two_scale()
    xy = torch.rand(200, 2) * torch.tensor([100.0, 80.0])
    base = Siren.height(m, xy)
    assert torch.equal(m.height(xy), base)  # the detail's output layer starts at zero
    assert m.detail_penalty().item() == 0.0
    with torch.no_grad():
        m.detail.out_layer.weight.normal_(0.0, 0.5)
    z, g = m.height_and_gradient(xy)
    torch.testing.assert_close(z, base + m.detail.height(xy))
    torch.testing.assert_close(z, m.height(xy))
    xy_g = xy.clone().requires_grad_(True)
    (auto,) = torch.autograd.grad(m.height(xy_g).sum(), xy_g)
    torch.testing.assert_close(g, auto, atol=1e-4, rtol=1e-4)
    assert m.detail_penalty().item() > 0.0
    # the detail's output maps to +-detail_range_m about zero, over the base's bounds
    assert m.detail.z_range == (-2.0, 2.0) and m.detail.bounds == m.bounds


def test_two_scale_frame_follows_the_base_and_the_state_rebuilds_it():
    m = _two_scale(detail_range_m=3.0)
    m.set_frame((10.0, 20.0, 60.0, 90.0), (-30.0, -1.0))
    assert m.detail.bounds == m.bounds == (10.0, 20.0, 60.0, 90.0)
    assert m.detail.z_range == (-3.0, 3.0) and m.z_range == (-30.0, -1.0)
    with torch.no_grad():
        m.detail.out_layer.weight.normal_()
    state = {f"siren.{k}": v for k, v in m.state_dict().items()}
    rebuilt = Siren.from_state_dict(state, prefix="siren.")
    assert isinstance(rebuilt, TwoScaleSiren)
    assert (rebuilt.detail.omega0, rebuilt.omega0) == (60.0, 10.0)
    xy = torch.rand(50, 2) * 40 + torch.tensor([10.0, 30.0])
    torch.testing.assert_close(rebuilt.height(xy), m.height(xy))


def test_two_scale_rejects_a_bad_detail_range():
    with pytest.raises(ValueError, match="detail_range_m"):
        _two_scale(detail_range_m=0.0)
