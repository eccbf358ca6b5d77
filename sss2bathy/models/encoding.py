"""Input encodings for the SIREN, each with an exact, explicit spatial Jacobian.

An encoding ``gamma: R^d -> R^D`` sits between the normalised coordinates ``x`` (``[-1, 1]``
per axis over the survey bounds) and the first layer of the MLP. The normal loss trains
on the height's *spatial* gradient, so a caller that carries ``dz/dgamma`` back by hand
(:meth:`~sss2bathy.models.siren.Siren.height_and_gradient`) needs the encoding's
vector-Jacobian product ``dz/dx = dz/dgamma . dgamma/dx``. Every encoding here computes it
with plain differentiable ops (no ``autograd.grad``), so the result has an ordinary
first-order graph with respect to the parameters: the normal loss trains learnable
encodings, it works under ``torch.no_grad`` and it compiles.

* :class:`FourierFeatures` — ``gamma(x) = [x, sin(2 pi B x), cos(2 pi B x)]`` (Tancik et al.
  2020, "Fourier features let networks learn high frequency functions"), ``B`` isotropic
  Gaussian or log-spaced along the axes, fixed or learnable.
* :class:`HashGridEncoding` — a multiresolution hash grid (Mueller et al. 2022, "Instant
  neural graphics primitives"): per level a table of learnable feature vectors at the
  vertices of a grid, bilinearly interpolated, the finest levels hashed into a fixed-size
  table. Its spatial gradient is linear in the table values (so the normal loss trains
  them) and constant along each axis within a cell (continuous across cell edges in the
  features, not in the gradient).

:func:`encoding_from_state_dict` rebuilds either from a state dict (the encoding's
hyperparameters are in its buffers).
"""

from __future__ import annotations

import math
from abc import ABC, abstractmethod
from collections.abc import Mapping

import torch
from torch import nn

#: Hash primes of Mueller et al. (2022): ``h(i, j) = (i * 1) xor (j * 2654435761) mod T``.
HASH_PRIME_Y = 2654435761

FOURIER_KINDS = ("gaussian", "axis")


def _positive_int(name: str, value: object, minimum: int = 1) -> int:
    if isinstance(value, bool) or not isinstance(value, int) or value < minimum:
        raise ValueError(f"{name}: expected an integer >= {minimum}, found {value!r}")
    return value


def _positive_float(name: str, value: object) -> float:
    try:
        v = float(value)  # type: ignore[arg-type]
    except (TypeError, ValueError):
        v = float("nan")
    if not (math.isfinite(v) and v > 0):
        raise ValueError(f"{name}: expected a positive finite number, found {value!r}")
    return v


def _generator(seed: int | torch.Generator) -> torch.Generator:
    if isinstance(seed, torch.Generator):
        return seed
    if isinstance(seed, bool) or not isinstance(seed, int):
        raise ValueError(f"seed: expected an int or a torch.Generator, found {seed!r}")
    return torch.Generator().manual_seed(seed)


class Encoding(nn.Module, ABC):
    """An input encoding ``gamma: (N, in_dim) -> (N, out_dim)`` with an explicit Jacobian.

    Subclasses set ``in_dim`` and ``out_dim`` and implement :meth:`forward`,
    :meth:`jacobian` and :meth:`vjp`.
    """

    in_dim: int
    out_dim: int

    def _check_x(self, x: object) -> torch.Tensor:
        if not isinstance(x, torch.Tensor) or x.ndim != 2 or x.shape[1] != self.in_dim:
            found = tuple(x.shape) if isinstance(x, torch.Tensor) else type(x).__name__
            raise ValueError(f"x: expected a tensor of shape (N, {self.in_dim}), found {found}")
        if not x.is_floating_point():
            raise ValueError(f"x: expected a floating-point tensor, found {x.dtype}")
        return x

    def _check_out(self, name: str, t: object, n: int) -> torch.Tensor:
        if not isinstance(t, torch.Tensor) or tuple(t.shape) != (n, self.out_dim):
            found = tuple(t.shape) if isinstance(t, torch.Tensor) else type(t).__name__
            raise ValueError(
                f"{name}: expected a tensor of shape ({n}, {self.out_dim}), found {found}"
            )
        return t

    @abstractmethod
    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """Features ``(N, out_dim)`` of normalised coordinates ``x (N, in_dim)``."""

    @abstractmethod
    def jacobian(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Features ``(N, out_dim)`` and their Jacobian ``d gamma/dx`` ``(N, out_dim, in_dim)``."""

    @abstractmethod
    def vjp(
        self, x: torch.Tensor, g: torch.Tensor, feat: torch.Tensor | None = None
    ) -> torch.Tensor:
        """``g . d gamma/dx``: ``(N, out_dim)`` cotangents -> ``(N, in_dim)``.

        ``feat`` is ``forward(x)`` of the same ``x`` if the caller has it; encodings that
        can reuse it (Fourier features: the Jacobian is made of the features themselves)
        skip recomputing, the others ignore it.
        """


class FourierFeatures(Encoding):
    """Fourier features ``gamma(x) = [x, sin(2 pi B x), cos(2 pi B x)]``.

    ``B`` (``n_freq x in_dim``, the ``freqs`` parameter or buffer) is in cycles per unit of
    the normalised coordinate; the survey spans 2 units per axis, so a frequency ``f``
    resolves a wavelength of ``extent / (2 f)`` metres.

    Args:
        in_dim: input dimension (2 for ``(x, y)``).
        n_freq: number of frequency vectors (rows of ``B``); ``out_dim`` is
            ``2 n_freq`` (+ ``in_dim`` with ``include_input``).
        sigma: ``kind="gaussian"``: ``B ~ N(0, sigma^2)`` per entry.
        kind: ``"gaussian"`` (default): isotropic random ``B`` (Tancik et al. found it at
            least as good as axis-aligned encodings in 2-D, and seafloor structure has no
            preferred direction relative to the ENU axes, along which axis-aligned
            frequencies leave artefacts); ``"axis"``: deterministic NeRF-style
            frequencies, ``n_freq / in_dim`` per axis log-spaced from 0.5 (one period over
            the survey) to ``max_freq``.
        max_freq: ``kind="axis"``: the highest frequency (>= 0.5).
        learnable: ``B`` is an ``nn.Parameter`` (trained, also through the normal loss's
            gradient) instead of a fixed buffer.
        include_input: prepend ``x`` itself (a low-frequency path).
        seed: seed or ``torch.Generator`` for the Gaussian ``B``.
    """

    def __init__(
        self,
        in_dim: int = 2,
        n_freq: int = 64,
        sigma: float = 10.0,
        kind: str = "gaussian",
        max_freq: float = 64.0,
        learnable: bool = False,
        include_input: bool = True,
        seed: int | torch.Generator = 0,
    ) -> None:
        super().__init__()
        self.in_dim = _positive_int("in_dim", in_dim)
        self.n_freq = _positive_int("n_freq", n_freq)
        if kind not in FOURIER_KINDS:
            raise ValueError(f"kind: expected one of {FOURIER_KINDS}, found {kind!r}")
        if kind == "gaussian":
            sigma = _positive_float("sigma", sigma)
            freqs = sigma * torch.randn(self.n_freq, self.in_dim, generator=_generator(seed))
        else:
            if self.n_freq % self.in_dim:
                raise ValueError(
                    f"n_freq: expected a multiple of in_dim={self.in_dim} for kind='axis', "
                    f"found {n_freq}"
                )
            max_freq = _positive_float("max_freq", max_freq)
            if max_freq < 0.5:
                raise ValueError(f"max_freq: expected >= 0.5 for kind='axis', found {max_freq}")
            per_axis = self.n_freq // self.in_dim
            levels = torch.linspace(math.log2(0.5), math.log2(max_freq), per_axis).exp2()
            eye = torch.eye(self.in_dim)
            freqs = (levels[:, None, None] * eye[None]).reshape(self.n_freq, self.in_dim)
        self.kind = kind
        self.learnable = bool(learnable)
        self.include_input = bool(include_input)
        self.out_dim = 2 * self.n_freq + (self.in_dim if self.include_input else 0)
        if self.learnable:
            self.freqs = nn.Parameter(freqs)
        else:
            self.register_buffer("freqs", freqs)
        self.register_buffer("include_input_flag", torch.tensor(self.include_input))
        self.register_buffer("learnable_flag", torch.tensor(self.learnable))

    @classmethod
    def from_state_dict(
        cls, state: Mapping[str, torch.Tensor], prefix: str = ""
    ) -> FourierFeatures:
        """Rebuild from a state dict (``prefix`` e.g. ``"siren.encoding."``)."""
        try:
            freqs = state[prefix + "freqs"]
            include = bool(state[prefix + "include_input_flag"])
            learnable = bool(state[prefix + "learnable_flag"])
        except KeyError as err:
            raise ValueError(
                f"state: expected FourierFeatures keys under prefix {prefix!r} "
                f"(freqs, include_input_flag, learnable_flag), missing {err}"
            ) from None
        enc = cls(
            in_dim=int(freqs.shape[1]),
            n_freq=int(freqs.shape[0]),
            learnable=learnable,
            include_input=include,
        )
        enc.load_state_dict({k[len(prefix) :]: v for k, v in state.items() if k.startswith(prefix)})
        return enc

    def _phase(self, x: torch.Tensor) -> torch.Tensor:
        return (2 * math.pi) * (x @ self.freqs.to(x.dtype).T)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """Features ``(N, out_dim)``: ``[x, sin(2 pi B x), cos(2 pi B x)]``."""
        x = self._check_x(x)
        p = self._phase(x)
        parts = [torch.sin(p), torch.cos(p)]
        return torch.cat([x, *parts] if self.include_input else parts, dim=1)

    def jacobian(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Features ``(N, out_dim)`` and ``d gamma/dx`` ``(N, out_dim, in_dim)``."""
        feat = self.forward(x)
        s, c = self._sin_cos(feat)
        w = (2 * math.pi) * self.freqs.to(x.dtype)  # (n_freq, in_dim): d phase / dx
        parts = [c[:, :, None] * w, -s[:, :, None] * w]
        if self.include_input:
            eye = torch.eye(self.in_dim, dtype=x.dtype, device=x.device)
            parts.insert(0, eye.expand(x.shape[0], -1, -1))
        return feat, torch.cat(parts, dim=1)

    def _sin_cos(self, feat: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        o = self.in_dim if self.include_input else 0
        return feat[:, o : o + self.n_freq], feat[:, o + self.n_freq :]

    def vjp(
        self, x: torch.Tensor, g: torch.Tensor, feat: torch.Tensor | None = None
    ) -> torch.Tensor:
        """``g . d gamma/dx`` ``(N, in_dim)`` for cotangents ``g (N, out_dim)``.

        ``d sin(p)/dx = cos(p) 2 pi B`` and ``d cos(p)/dx = -sin(p) 2 pi B`` are made of the
        features themselves, so with ``feat = forward(x)`` no sine is recomputed: one
        ``N x n_freq x in_dim`` product.
        """
        x = self._check_x(x)
        g = self._check_out("g", g, x.shape[0])
        feat = self.forward(x) if feat is None else self._check_out("feat", feat, x.shape[0])
        s, c = self._sin_cos(feat)
        gs, gc = self._sin_cos(g)
        out = (gs * c - gc * s) @ ((2 * math.pi) * self.freqs.to(g.dtype))
        return out + g[:, : self.in_dim] if self.include_input else out

    def extra_repr(self) -> str:
        return (
            f"in_dim={self.in_dim}, n_freq={self.n_freq}, kind={self.kind!r}, "
            f"learnable={self.learnable}, include_input={self.include_input}, "
            f"out_dim={self.out_dim}"
        )


class HashGridEncoding(Encoding):
    """Multiresolution hash grid (Mueller et al. 2022) over ``[-1, 1]^2``, bilinear.

    Level ``l`` has a ``R_l x R_l``-cell grid, ``R_l = floor(R_0 b^l)`` with ``b`` such that
    the last level has ``max_resolution`` cells per axis. A vertex ``(i, j)`` reads row
    ``j (R_l + 1) + i`` of the level's table where the grid fits the table (coarse levels,
    no collisions), else row ``(i xor j * 2654435761) mod T``. The feature of a point is the
    bilinear interpolation of its cell's four vertex vectors, levels concatenated
    (level-major): ``out_dim = n_levels * features_per_level`` (+ 2 with ``include_input``).
    Points outside ``[-1, 1]^2`` extrapolate the border cell linearly (the intersection
    finder may step slightly outside the survey).

    The spatial gradient of a bilinear cell is linear in the table values and constant
    along each axis within a cell: continuous features, a gradient that jumps across cell
    edges. Second derivatives with respect to ``x`` are zero along the axes, but the
    gradient's derivative with respect to the tables (what the normal loss needs) exists.

    Args:
        n_levels: number of resolution levels ``L``.
        features_per_level: feature vector length ``F`` per level.
        log2_table_size: ``T = 2^log2_table_size`` rows per level (19 in Mueller et al.).
        base_resolution: cells per axis of the coarsest level (``R_0``).
        max_resolution: cells per axis of the finest level (>= ``base_resolution``).
        include_input: prepend ``x`` itself.
        init_scale: tables start ``U(+-init_scale)`` (1e-4 in Mueller et al.).
        seed: seed or ``torch.Generator`` for the table init.
    """

    def __init__(
        self,
        n_levels: int = 16,
        features_per_level: int = 2,
        log2_table_size: int = 19,
        base_resolution: int = 16,
        max_resolution: int = 2048,
        include_input: bool = True,
        init_scale: float = 1e-4,
        seed: int | torch.Generator = 0,
    ) -> None:
        super().__init__()
        self.in_dim = 2
        self.n_levels = _positive_int("n_levels", n_levels)
        self.features_per_level = _positive_int("features_per_level", features_per_level)
        log2_t = _positive_int("log2_table_size", log2_table_size)
        if log2_t > 30:
            raise ValueError(f"log2_table_size: expected an integer <= 30, found {log2_t}")
        base = _positive_int("base_resolution", base_resolution)
        top = _positive_int("max_resolution", max_resolution)
        if top < base:
            raise ValueError(
                f"max_resolution: expected >= base_resolution={base}, found {max_resolution}"
            )
        if top > 2**24:
            raise ValueError(f"max_resolution: expected <= 2**24, found {max_resolution}")
        init_scale = _positive_float("init_scale", init_scale)
        self.table_size = 2**log2_t
        self.include_input = bool(include_input)
        self.out_dim = self.n_levels * self.features_per_level + (2 if self.include_input else 0)
        growth = (math.log(top) - math.log(base)) / max(self.n_levels - 1, 1)
        res = [
            min(top, math.floor(base * math.exp(growth * lvl) + 1e-6)) for lvl in range(n_levels)
        ]
        tables = torch.rand(
            self.n_levels, self.table_size, self.features_per_level, generator=_generator(seed)
        )
        self.tables = nn.Parameter((2 * tables - 1) * init_scale)
        self.register_buffer("resolutions", torch.tensor(res, dtype=torch.int64))
        self.register_buffer("include_input_flag", torch.tensor(self.include_input))

    @classmethod
    def from_state_dict(
        cls, state: Mapping[str, torch.Tensor], prefix: str = ""
    ) -> HashGridEncoding:
        """Rebuild from a state dict (``prefix`` e.g. ``"siren.encoding."``)."""
        try:
            tables = state[prefix + "tables"]
            include = bool(state[prefix + "include_input_flag"])
            res = state[prefix + "resolutions"]
        except KeyError as err:
            raise ValueError(
                f"state: expected HashGridEncoding keys under prefix {prefix!r} "
                f"(tables, resolutions, include_input_flag), missing {err}"
            ) from None
        n_levels, size, feats = (int(s) for s in tables.shape)
        log2_t = size.bit_length() - 1
        if 2**log2_t != size:
            raise ValueError(f"state: expected a power-of-two table size, found {size}")
        enc = cls(
            n_levels=n_levels,
            features_per_level=feats,
            log2_table_size=log2_t,
            base_resolution=int(res.min()),
            max_resolution=int(res.max()),
            include_input=include,
        )
        enc.load_state_dict({k[len(prefix) :]: v for k, v in state.items() if k.startswith(prefix)})
        return enc

    def _interpolate(
        self, x: torch.Tensor, with_partials: bool
    ) -> tuple[torch.Tensor, torch.Tensor | None, torch.Tensor | None]:
        """Per-level features ``(N, L, F)`` and, optionally, their partials with respect to
        the in-cell fractions ``(fx, fy)``, each ``(N, L, F)``."""
        n_lvl, size = self.n_levels, self.table_size
        res = self.resolutions
        pos = ((x + 1) * 0.5)[:, None, :] * res.to(x.dtype)[:, None]  # (N, L, 2) in cells
        cell = torch.minimum(pos.detach().floor().clamp_min(0), (res - 1).to(x.dtype)[:, None])
        frac = pos - cell  # in [0, 1] inside the domain; the border cell extrapolates
        ij = cell.long()
        i0, j0 = ij[..., 0], ij[..., 1]
        ii = torch.stack([i0, i0 + 1, i0, i0 + 1], dim=-1)  # corners 00, 10, 01, 11: (N, L, 4)
        jj = torch.stack([j0, j0, j0 + 1, j0 + 1], dim=-1)
        dense = ((res + 1) ** 2 <= size)[:, None]  # (L, 1)
        idx = torch.where(
            dense,
            jj * (res + 1)[:, None] + ii,
            torch.bitwise_xor(ii, jj * HASH_PRIME_Y) & (size - 1),
        )
        idx = idx + (torch.arange(n_lvl, device=x.device) * size)[:, None]
        flat = self.tables.to(x.dtype).reshape(n_lvl * size, self.features_per_level)
        v = flat.index_select(0, idx.reshape(-1)).reshape(*idx.shape, self.features_per_level)
        v00, v10, v01, v11 = v.unbind(dim=2)
        fx, fy = frac[..., 0:1], frac[..., 1:2]
        lo = v00 + fx * (v10 - v00)  # along x on the j0 edge
        hi = v01 + fx * (v11 - v01)  # along x on the j0 + 1 edge
        feat = lo + fy * (hi - lo)
        if not with_partials:
            return feat, None, None
        d_fx = (v10 - v00) + fy * ((v11 - v01) - (v10 - v00))
        return feat, d_fx, hi - lo

    def _flatten(self, x: torch.Tensor, feat: torch.Tensor) -> torch.Tensor:
        flat = feat.reshape(x.shape[0], self.n_levels * self.features_per_level)
        return torch.cat([x, flat], dim=1) if self.include_input else flat

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """Features ``(N, out_dim)``: ``[x, level 0 (F), ..., level L-1 (F)]``."""
        x = self._check_x(x)
        return self._flatten(x, self._interpolate(x, with_partials=False)[0])

    def jacobian(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Features ``(N, out_dim)`` and ``d gamma/dx`` ``(N, out_dim, 2)``."""
        x = self._check_x(x)
        feat, d_fx, d_fy = self._interpolate(x, with_partials=True)
        scale = 0.5 * self.resolutions.to(x.dtype)[:, None]  # d frac / dx = R_l / 2
        jac = torch.stack([d_fx * scale, d_fy * scale], dim=-1).reshape(
            x.shape[0], self.n_levels * self.features_per_level, 2
        )
        if self.include_input:
            eye = torch.eye(2, dtype=x.dtype, device=x.device).expand(x.shape[0], -1, -1)
            jac = torch.cat([eye, jac], dim=1)
        return self._flatten(x, feat), jac

    def vjp(
        self, x: torch.Tensor, g: torch.Tensor, feat: torch.Tensor | None = None
    ) -> torch.Tensor:
        """``g . d gamma/dx`` ``(N, 2)`` for cotangents ``g (N, out_dim)``.

        The partials need the four vertex vectors of every level, so the gather is redone
        (``feat`` is accepted for the common interface and ignored).
        """
        x = self._check_x(x)
        g = self._check_out("g", g, x.shape[0])
        _, d_fx, d_fy = self._interpolate(x, with_partials=True)
        o = 2 if self.include_input else 0
        gl = g[:, o:].reshape(x.shape[0], self.n_levels, self.features_per_level)
        scale = 0.5 * self.resolutions.to(x.dtype)
        out = torch.stack([(gl * d_fx).sum(-1) @ scale, (gl * d_fy).sum(-1) @ scale], dim=1)
        return out + g[:, :2] if self.include_input else out

    def extra_repr(self) -> str:
        res = self.resolutions.tolist()
        return (
            f"n_levels={self.n_levels}, features_per_level={self.features_per_level}, "
            f"table_size={self.table_size}, resolutions={res[0]}..{res[-1]}, "
            f"include_input={self.include_input}, out_dim={self.out_dim}"
        )


def encoding_from_state_dict(
    state: Mapping[str, torch.Tensor], prefix: str = "encoding."
) -> Encoding | None:
    """The encoding saved under ``prefix`` in ``state``, or ``None`` if there is none."""
    if prefix + "freqs" in state:
        return FourierFeatures.from_state_dict(state, prefix)
    if prefix + "tables" in state:
        return HashGridEncoding.from_state_dict(state, prefix)
    return None
