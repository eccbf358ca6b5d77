"""Input encodings: features, explicit Jacobians (vs autograd and finite differences),
second derivatives through the explicit spatial gradient, hash-grid indexing, state dicts."""

from __future__ import annotations

import math

import pytest
import torch
from torch import nn
from torch.func import functional_call

from sss2bathy.models.encoding import (
    HASH_PRIME_Y,
    Encoding,
    FourierFeatures,
    HashGridEncoding,
    encoding_from_state_dict,
)


def _x(n: int, seed: int = 0, lim: float = 1.0) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    return lim * (2 * torch.rand(n, 2, generator=g, dtype=torch.float64) - 1)


def _encodings() -> dict[str, Encoding]:
    return {
        "fourier_gauss": FourierFeatures(n_freq=5, sigma=1.5, learnable=True, seed=3),
        "fourier_axis_noinput": FourierFeatures(
            n_freq=6, kind="axis", max_freq=4.0, include_input=False
        ),
        # level 0 dense ((2+1)^2 <= 16), levels 1-2 hashed
        "hash": HashGridEncoding(
            n_levels=3, log2_table_size=4, base_resolution=2, max_resolution=12, init_scale=1.0
        ),
    }


ENCODINGS = list(_encodings())


def _enc(name: str) -> Encoding:
    return _encodings()[name].double()


class _SineField(nn.Module):
    """A small SIREN over an encoding, with the explicit reverse pass of ``Siren``."""

    def __init__(self, enc: Encoding, hidden: int = 6, omega0: float = 3.0) -> None:
        super().__init__()
        self.enc, self.omega0 = enc, omega0
        self.l1 = nn.Linear(enc.out_dim, hidden)
        self.l2 = nn.Linear(hidden, hidden)
        self.out = nn.Linear(hidden, 1)

    def height(self, x: torch.Tensor) -> torch.Tensor:
        h = self.enc(x)
        for layer in (self.l1, self.l2):
            h = torch.sin(self.omega0 * layer(h))
        return self.out(h).squeeze(-1)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """Explicit spatial gradient ``dz/dx (N, 2)``."""
        feat = self.enc(x)
        h, cosines = feat, []
        for layer in (self.l1, self.l2):
            pre = self.omega0 * layer(h)
            h = torch.sin(pre)
            cosines.append(torch.cos(pre))
        g = self.out.weight
        for layer, cos in zip((self.l2, self.l1), reversed(cosines), strict=True):
            g = (cos * g) @ (self.omega0 * layer.weight)
        return self.enc.vjp(x, g, feat)


class _Explicit(nn.Module):
    """``enc.vjp(x, g)`` or ``enc.jacobian(x)[1]`` as a module, for ``functional_call``."""

    def __init__(self, enc: Encoding) -> None:
        super().__init__()
        self.enc = enc

    def forward(self, x: torch.Tensor, g: torch.Tensor | None = None) -> torch.Tensor:
        return self.enc.jacobian(x)[1] if g is None else self.enc.vjp(x, g)


# ---------------------------------------------------------------- Fourier features
def test_fourier_features_values_and_frequencies():
    enc = FourierFeatures(n_freq=2, kind="axis", max_freq=0.5).double()
    x = torch.tensor([[0.3, -0.7], [1.0, 0.0]], dtype=torch.float64)
    px, py = math.pi * x[:, 0], math.pi * x[:, 1]
    expected = torch.stack([x[:, 0], x[:, 1], px.sin(), py.sin(), px.cos(), py.cos()], dim=1)
    assert enc.out_dim == 6
    torch.testing.assert_close(enc(x), expected, rtol=0, atol=1e-15)

    axis = FourierFeatures(n_freq=8, kind="axis", max_freq=4.0)
    f = axis.freqs
    assert torch.equal((f != 0).sum(1), torch.ones(8, dtype=torch.long))  # axis-aligned
    torch.testing.assert_close(f[:, 0][f[:, 0] != 0], torch.tensor([0.5, 1.0, 2.0, 4.0]))
    torch.testing.assert_close(f[:, 1][f[:, 1] != 0], torch.tensor([0.5, 1.0, 2.0, 4.0]))
    assert axis.out_dim == 2 + 16 and "freqs" not in dict(axis.named_parameters())

    gauss = FourierFeatures(n_freq=4096, sigma=7.0, seed=1)
    assert gauss.freqs.std().item() == pytest.approx(7.0, rel=0.03)
    assert abs(gauss.freqs.mean().item()) < 0.3
    assert torch.equal(
        FourierFeatures(n_freq=8, seed=5).freqs, FourierFeatures(n_freq=8, seed=5).freqs
    )
    assert not torch.equal(FourierFeatures(n_freq=8, seed=5).freqs, FourierFeatures(n_freq=8).freqs)
    gen = torch.Generator().manual_seed(5)
    assert torch.equal(
        FourierFeatures(n_freq=8, seed=gen).freqs, FourierFeatures(n_freq=8, seed=5).freqs
    )
    # sines of many frequencies over uniform x are arcsine-distributed: mean 0, variance 1/2
    feat = gauss(_x(4000).float())[:, 2:]
    assert feat.mean().abs().item() < 0.02 and feat.pow(2).mean().item() == pytest.approx(
        0.5, abs=0.02
    )
    learn = FourierFeatures(n_freq=3, learnable=True, include_input=False)
    assert list(dict(learn.named_parameters())) == ["freqs"] and learn.out_dim == 6


# ---------------------------------------------------------------- explicit Jacobians
@pytest.mark.parametrize("name", ENCODINGS)
def test_explicit_jacobian_matches_autograd_and_finite_differences(name):
    enc = _enc(name)
    x = _x(7, seed=1, lim=0.95)
    feat, jac = enc.jacobian(x)
    assert feat.shape == (7, enc.out_dim) and jac.shape == (7, enc.out_dim, 2)
    torch.testing.assert_close(feat, enc(x), rtol=0, atol=0)
    auto = torch.autograd.functional.jacobian(lambda y: enc(y).sum(0), x).permute(1, 0, 2)
    torch.testing.assert_close(jac, auto, rtol=1e-12, atol=1e-12)
    h = 1e-6
    for k in range(2):
        dx = torch.zeros(1, 2, dtype=torch.float64)
        dx[0, k] = h
        fd = (enc(x + dx) - enc(x - dx)) / (2 * h)
        torch.testing.assert_close(jac[..., k], fd, rtol=1e-6, atol=1e-6)
    g = torch.randn(7, enc.out_dim, dtype=torch.float64, generator=torch.Generator().manual_seed(2))
    vjp = enc.vjp(x, g)
    assert vjp.shape == (7, 2)
    torch.testing.assert_close(vjp, torch.einsum("nd,ndk->nk", g, jac), rtol=1e-12, atol=1e-12)
    torch.testing.assert_close(enc.vjp(x, g, feat), vjp, rtol=1e-13, atol=1e-13)
    with torch.no_grad():
        torch.testing.assert_close(enc.vjp(x, g), vjp, rtol=0, atol=0)


@pytest.mark.parametrize("name", ENCODINGS)
def test_vjp_and_jacobian_gradcheck_in_inputs_cotangents_and_parameters(name):
    enc = _enc(name)
    wrapper = _Explicit(enc)
    params = {k: v.detach().clone().requires_grad_(True) for k, v in wrapper.named_parameters()}
    keys = list(params)
    x = _x(4, seed=3, lim=0.9).requires_grad_(True)
    g = torch.randn(4, enc.out_dim, dtype=torch.float64).requires_grad_(True)

    def vjp(x, g, *ps):
        return functional_call(wrapper, dict(zip(keys, ps, strict=True)), (x, g))

    def jac(x, *ps):
        return functional_call(wrapper, dict(zip(keys, ps, strict=True)), (x,))

    assert torch.autograd.gradcheck(vjp, (x, g, *params.values()), eps=1e-6, atol=1e-5)
    assert torch.autograd.gradcheck(jac, (x, *params.values()), eps=1e-6, atol=1e-5)


@pytest.mark.parametrize("name", ENCODINGS)
def test_explicit_field_gradient_trains_encoding_to_second_order(name):
    """dz/dx through an MLP + encoding equals autograd's, and its derivative with respect
    to every parameter (encoding included) matches finite differences (gradcheck)."""
    torch.manual_seed(0)
    field = _SineField(_enc(name)).double()
    x = _x(5, seed=4, lim=0.9)
    xr = x.clone().requires_grad_(True)
    (auto,) = torch.autograd.grad(field.height(xr).sum(), xr)
    torch.testing.assert_close(field(x), auto, rtol=1e-11, atol=1e-12)

    names = [k for k, _ in field.named_parameters() if k.startswith(("enc.", "l1."))]
    assert any(k.startswith("enc.") for k in names) or name == "fourier_axis_noinput"
    params = {k: v.detach().clone().requires_grad_(True) for k, v in field.named_parameters()}
    trained = [params[k] for k in names]

    def grad_of(*ps):
        return functional_call(field, {**params, **dict(zip(names, ps, strict=True))}, (x,))

    assert torch.autograd.gradcheck(grad_of, tuple(trained), eps=1e-6, atol=1e-5)
    loss = (grad_of(*trained) - 0.1).pow(2).sum()
    grads = torch.autograd.grad(loss, trained)
    assert all(torch.isfinite(gr).all() and gr.abs().sum() > 0 for gr in grads)


# ---------------------------------------------------------------- hash grid
def test_hash_grid_resolutions_and_sizes():
    enc = HashGridEncoding()  # Mueller et al.'s 2-D setup: 16 levels, 16 .. 2048, T = 2^19
    res = enc.resolutions.tolist()
    assert len(res) == 16 and res[0] == 16 and res[-1] == 2048
    assert all(b > a for a, b in zip(res[:-1], res[1:], strict=False))
    assert enc.tables.shape == (16, 2**19, 2) and enc.out_dim == 2 + 32
    assert enc.tables.abs().max().item() <= 1e-4
    one = HashGridEncoding(n_levels=1, base_resolution=8, max_resolution=64, include_input=False)
    assert one.resolutions.tolist() == [8] and one.out_dim == 2


def test_hash_grid_dense_level_interpolates_linear_function_exactly():
    enc = HashGridEncoding(
        n_levels=1, features_per_level=1, log2_table_size=5, base_resolution=4, max_resolution=4
    ).double()  # 5 x 5 vertices = 25 <= 32 rows: dense indexing
    i = torch.arange(32, dtype=torch.float64) % 5
    j = torch.div(torch.arange(32), 5, rounding_mode="floor").double()
    with torch.no_grad():
        enc.tables.copy_((0.3 * i - 1.7 * j + 0.25)[None, :, None])
    x = _x(50, seed=5)
    u = (x + 1) / 2 * 4  # vertex coordinates
    expected = 0.3 * u[:, 0] - 1.7 * u[:, 1] + 0.25
    feat, jac = enc.jacobian(x)
    torch.testing.assert_close(feat[:, 2], expected, rtol=0, atol=1e-12)
    torch.testing.assert_close(feat[:, :2], x, rtol=0, atol=0)
    slope = torch.tensor([0.3 * 2, -1.7 * 2], dtype=torch.float64)  # d u / dx = R / 2 = 2
    torch.testing.assert_close(jac[:, 2, :], slope.expand(50, 2), rtol=0, atol=1e-12)
    # outside [-1, 1]^2 the border cells extrapolate the same linear function
    out = torch.tensor([[1.2, -1.1], [-1.3, 1.05]], dtype=torch.float64)
    uo = (out + 1) / 2 * 4
    torch.testing.assert_close(enc(out)[:, 2], 0.3 * uo[:, 0] - 1.7 * uo[:, 1] + 0.25)


def test_hash_grid_hashed_level_reads_the_hashed_row():
    res, size = 16, 64  # 17^2 > 64: hashed
    enc = HashGridEncoding(
        n_levels=1,
        features_per_level=1,
        log2_table_size=6,
        base_resolution=res,
        max_resolution=res,
        include_input=False,
    ).double()
    with torch.no_grad():
        enc.tables.copy_(torch.arange(size, dtype=torch.float64)[None, :, None])
    ij = torch.tensor([[0, 0], [3, 7], [15, 2], [9, 12], [5, 5]])
    x = ij.double() / res * 2 - 1  # vertices: the feature is that vertex's row
    expected = [(a ^ (b * HASH_PRIME_Y)) % size for a, b in ij.tolist()]
    torch.testing.assert_close(enc(x)[:, 0], torch.tensor(expected, dtype=torch.float64))


def test_hash_grid_features_continuous_gradient_piecewise_constant():
    enc = _enc("hash")
    edge = 2 * 5 / 12 - 1  # x on a vertical cell edge of the finest level (R = 12)
    y = 0.123
    pts = torch.tensor([[edge - 1e-10, y], [edge + 1e-10, y]], dtype=torch.float64)
    feat, jac = enc.jacobian(pts)
    torch.testing.assert_close(feat[0], feat[1], rtol=0, atol=1e-8)
    assert (jac[0, -2:, 0] - jac[1, -2:, 0]).abs().max() > 1e-3  # the gradient jumps
    # inside a cell, d feat/dx does not change along x
    inside = torch.tensor([[edge + 0.01, y], [edge + 0.1, y]], dtype=torch.float64)
    torch.testing.assert_close(*enc.jacobian(inside)[1][:, :, 0].unbind(0), rtol=0, atol=1e-12)


@pytest.mark.parametrize("name", ENCODINGS)
def test_empty_input_gives_empty_outputs(name):
    """A batch without valid bins (every bin masked) passes zero points through."""
    enc = _enc(name)
    x = torch.zeros(0, 2, dtype=torch.float64)
    assert enc(x).shape == (0, enc.out_dim)
    feat, jac = enc.jacobian(x)
    assert feat.shape == (0, enc.out_dim) and jac.shape == (0, enc.out_dim, 2)
    assert enc.vjp(x, torch.zeros(0, enc.out_dim, dtype=torch.float64)).shape == (0, 2)


# ---------------------------------------------------------------- state dicts, errors
@pytest.mark.parametrize("name", ENCODINGS)
def test_state_dict_roundtrip(name):
    enc = _enc(name)
    state = {f"siren.encoding.{k}": v for k, v in enc.state_dict().items()}
    state["siren.out_layer.weight"] = torch.zeros(1, 4)
    rebuilt = encoding_from_state_dict(state, "siren.encoding.")
    assert type(rebuilt) is type(enc) and rebuilt.out_dim == enc.out_dim
    assert [k for k, _ in rebuilt.named_parameters()] == [k for k, _ in enc.named_parameters()]
    x = _x(9, seed=6)
    torch.testing.assert_close(rebuilt.double()(x), enc(x), rtol=0, atol=0)
    assert encoding_from_state_dict({"out_layer.weight": torch.zeros(1, 4)}) is None


def test_validation_errors_name_argument_expected_and_found():
    cases = [
        (lambda: FourierFeatures(n_freq=0), "n_freq: expected an integer >= 1, found 0"),
        (lambda: FourierFeatures(in_dim=2.0), "in_dim"),
        (lambda: FourierFeatures(sigma=-1.0), "sigma: expected a positive finite number"),
        (lambda: FourierFeatures(sigma="a"), "sigma"),
        (lambda: FourierFeatures(kind="nerf"), r"kind: expected one of .*found 'nerf'"),
        (lambda: FourierFeatures(kind="axis", n_freq=3), "n_freq: expected a multiple of in_dim"),
        (lambda: FourierFeatures(kind="axis", max_freq=0.25), "max_freq: expected >= 0.5"),
        (lambda: FourierFeatures(seed=1.5), "seed"),
        (lambda: HashGridEncoding(n_levels=0), "n_levels"),
        (
            lambda: HashGridEncoding(log2_table_size=31),
            "log2_table_size: expected an integer <= 30",
        ),
        (lambda: HashGridEncoding(base_resolution=32, max_resolution=16), "max_resolution"),
        (lambda: HashGridEncoding(init_scale=0.0), "init_scale"),
        (lambda: FourierFeatures.from_state_dict({"freqs": torch.zeros(2, 2)}), "state:"),
        (lambda: HashGridEncoding.from_state_dict({}, "enc."), r"state: .*'enc\.'"),
    ]
    for make, match in cases:
        with pytest.raises(ValueError, match=match):
            make()
    for name in ENCODINGS:
        enc = _enc(name)
        with pytest.raises(
            ValueError, match=r"x: expected a tensor of shape \(N, 2\), found \(4, 3\)"
        ):
            enc(torch.zeros(4, 3, dtype=torch.float64))
        with pytest.raises(ValueError, match="x: expected a floating-point tensor"):
            enc(torch.zeros(4, 2, dtype=torch.long))
        with pytest.raises(
            ValueError, match=rf"g: expected a tensor of shape \(4, {enc.out_dim}\)"
        ):
            enc.vjp(_x(4), torch.zeros(4, enc.out_dim + 1, dtype=torch.float64))
        if isinstance(enc, FourierFeatures):
            with pytest.raises(ValueError, match="feat: expected"):
                enc.vjp(_x(4), torch.zeros(4, enc.out_dim, dtype=torch.float64), torch.zeros(3))
