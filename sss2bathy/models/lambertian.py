"""Lambertian forward sidescan model: the baseline sensor model of the SIREN fit.

Bore & Folkesson, "Neural shape-from-shading for survey-scale self-consistent bathymetry
from sidescan" (the paper's reference nils2021) predict each bin's intensity from the
bathymetry and learn the sensor's unknowns jointly with it. For a bin whose arc crosses
the seafloor at ``p`` seen from the sonar ``s``:

    I_pred = K * G(r) * B(theta) * rho(x, y) * M(incidence),    M = max(cos(incidence), 0)^e

* ``K``: global scale (a log-parameter);
* ``G(r)``: range gain (the time-varying gain), piecewise linear over slant range;
* ``B(theta)``: beam pattern over the depression angle, piecewise linear over the beam;
* ``rho``: seabed reflectivity, 1 by default (folded into ``K``) or a learned field;
* ``M``: the Lambertian term from the SIREN normal ``[-dz/dx, -dz/dy, 1]`` at ``p`` and the
  direction ``s - p``, with the exponent ``e`` that fits what the sidescan stores.

**The exponent.** ``q`` is Lambert's exponent *in power*: the received power goes as
``cos(incidence)^q`` (``q = 2``: Lambert's law for backscatter, ``sigma0 = mu cos^2 i``, the
simulator's diffuse term with its materials' exponents 1.15-3.0; ``q = 1``: the plain
cosine law). A sidescan stores **amplitude**: the simulator's receiver records
``gain * sqrt(TVG * power)`` (:func:`sss2bathy.sim.sonar.receive`) and XTF sidescan samples
are the receiver's envelope amplitudes. With ``intensity_kind="amplitude"`` the model
therefore applies ``e = q / 2`` (:func:`lambert_exponent`), with ``"power"`` ``e = q``.
``G``, ``B``, ``rho`` and ``K`` are free, so they take whichever domain the data are in.

``K``, ``G`` and ``B`` are free log-values (``G``, ``B`` on their knots). Only their
product is observable; the reported curves are normalised to geometric mean 1 over the
knots with the level moved into ``K`` (centring the parameters themselves would couple
every knot's gradient to all others, which slows Adam down on weakly observed knots).
``K`` starts from the first batch (mean prediction = mean target). The loss is the mean
absolute intensity difference over the bins the SIREN module hands over; the module adds
the altimeter height loss.

Shadows cannot be rendered by this model, so (as Bore & Folkesson) bins darker than a
fixed threshold on the per-line normalised intensity, and optionally the near range, are
dropped before the fit (:meth:`LambertianSensorModel.bin_mask`).
"""

from __future__ import annotations

import logging
import math
from typing import TYPE_CHECKING, Any

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from sss2bathy.geometry import incidence_cosine, world_normal
from sss2bathy.models.sensors import ArcGeometry, SensorModel
from sss2bathy.utils.checks import require_number

if TYPE_CHECKING:
    from sss2bathy.survey import SensorParams

log = logging.getLogger(__name__)

REFLECTIVITY_KINDS = ("constant", "field")
INTENSITY_KINDS = ("amplitude", "power")


def lambert_exponent(q: float, intensity_kind: str = "amplitude") -> float:
    """The exponent of ``cos(incidence)`` to apply to the stored intensity.

    ``q`` is Lambert's exponent in power (``P ~ cos^q``); an amplitude is ``sqrt(P)``, so
    it goes as ``cos^(q/2)``.

    >>> lambert_exponent(2.0, "amplitude"), lambert_exponent(2.0, "power")
    (1.0, 2.0)
    """
    if intensity_kind not in INTENSITY_KINDS:
        raise ValueError(
            f"intensity_kind: expected one of {INTENSITY_KINDS}, found {intensity_kind!r}"
        )
    if not q > 0.0:
        raise ValueError(f"q: expected a Lambertian exponent in power > 0, found {q}")
    return float(q) / 2.0 if intensity_kind == "amplitude" else float(q)


def _check_points(name: str, value: torch.Tensor, n: int | None = None) -> None:
    if value.ndim != 2 or value.shape[-1] != 3 or (n is not None and value.shape[0] != n):
        expected = f"({n if n is not None else 'N'}, 3)"
        raise ValueError(f"{name}: expected shape {expected}, found {tuple(value.shape)}")


def lambertian_term(
    normal_world: torch.Tensor, point: torch.Tensor, sonar: torch.Tensor, exponent: float = 1.0
) -> torch.Tensor:
    """``max(cos(incidence), 0)^exponent`` of ``N`` bins.

    The incidence is the angle between the surface normal and the direction from the
    point to the sonar; its cosine (:func:`sss2bathy.geometry.incidence_cosine`) is taken
    from the dot product directly, which keeps the gradient finite where the surface
    faces the sonar head-on. Back-facing surfaces (incidence > 90 deg) return 0; for
    exponents below 1 the cosine is floored at 1e-6 in front of the surface so the
    gradient stays finite at grazing incidence.

    Args:
        normal_world: ``(N, 3)`` world normals (any length, e.g. ``[-dz/dx, -dz/dy, 1]``).
        point: ``(N, 3)`` seafloor points (m).
        sonar: ``(N, 3)`` sonar positions (m).
        exponent: the exponent applied, ``> 0`` (:func:`lambert_exponent`: ``q / 2`` for
            amplitude data, ``q`` for power).

    Returns:
        ``(N,)`` values in ``[0, 1]``.
    """
    _check_points("normal_world", normal_world)
    _check_points("point", point, normal_world.shape[0])
    _check_points("sonar", sonar, normal_world.shape[0])
    if not exponent > 0.0:
        raise ValueError(f"exponent: expected > 0, found {exponent}")
    cos = incidence_cosine(normal_world, point, sonar)
    if exponent >= 1.0:
        return cos.clamp(0.0, 1.0) ** exponent
    front = cos > 0.0
    return torch.where(front, cos.clamp(1e-6, 1.0) ** exponent, torch.zeros_like(cos))


def piecewise_linear(x: torch.Tensor, knots: torch.Tensor, values: torch.Tensor) -> torch.Tensor:
    """Piecewise-linear interpolation of ``values`` on ``knots``, constant outside them.

    Differentiable in ``values`` (and in ``x`` inside the knot range). Vectorised:
    one ``searchsorted`` for all samples.

    Args:
        x: ``(...)`` sample positions.
        knots: ``(K,)`` strictly increasing knot positions, ``K >= 2``.
        values: ``(K,)`` values at the knots.

    Returns:
        ``(...)`` interpolated values, dtype of ``values``.
    """
    if knots.ndim != 1 or knots.shape[0] < 2:
        raise ValueError(f"knots: expected shape (K,) with K >= 2, found {tuple(knots.shape)}")
    if values.shape != knots.shape:
        raise ValueError(
            f"values: expected shape {tuple(knots.shape)} (one per knot), found {tuple(values.shape)}"
        )
    if not bool((knots[1:] > knots[:-1]).all()):
        raise ValueError(f"knots: expected strictly increasing positions, found {knots.tolist()}")
    knots = knots.to(x.dtype)
    idx = (torch.searchsorted(knots, x.detach().contiguous(), right=True) - 1).clamp(
        0, knots.shape[0] - 2
    )
    left, right = knots[idx], knots[idx + 1]
    w = ((x - left) / (right - left)).clamp(0.0, 1.0).to(values.dtype)
    return values[idx] * (1.0 - w) + values[idx + 1] * w


class ReflectivityField(nn.Module):
    """Seabed reflectivity ``rho(x, y) > 0``: a small sine MLP over ``(x, y) / scale_m``.

    ``softplus`` output whose last layer starts at zero weights and the bias
    ``softplus^-1(1)``, so the field starts as ``rho = 1`` everywhere and learns from there.
    Hidden layers use the SIREN initialisation (first layer ``U(+-1/fan_in)``, others
    ``U(+-sqrt(6/fan_in)/omega0)``).

    Args:
        hidden: hidden width.
        layers: number of hidden (sine) layers, ``>= 1``.
        omega0: sine frequency factor.
        scale_m: metres that map to one unit of input (about the survey's half extent).
    """

    def __init__(
        self, hidden: int = 32, layers: int = 2, omega0: float = 30.0, scale_m: float = 100.0
    ) -> None:
        super().__init__()
        if hidden < 1:
            raise ValueError(f"hidden: expected a width >= 1, found {hidden}")
        if layers < 1:
            raise ValueError(f"layers: expected >= 1 hidden layers, found {layers}")
        if not scale_m > 0:
            raise ValueError(f"scale_m: expected > 0 m, found {scale_m}")
        self.omega0 = float(omega0)
        self.scale_m = float(scale_m)
        widths = [2] + [hidden] * layers
        self.hidden = nn.ModuleList(
            nn.Linear(a, b) for a, b in zip(widths[:-1], widths[1:], strict=True)
        )
        self.out = nn.Linear(hidden, 1)
        with torch.no_grad():
            for i, layer in enumerate(self.hidden):
                fan_in = layer.in_features
                bound = 1.0 / fan_in if i == 0 else math.sqrt(6.0 / fan_in) / self.omega0
                layer.weight.uniform_(-bound, bound)
            self.out.weight.zero_()
            self.out.bias.fill_(math.log(math.expm1(1.0)))

    def forward(self, xy: torch.Tensor) -> torch.Tensor:
        """``(N, 2)`` world ``(x, y)`` (m) -> ``(N,)`` reflectivity."""
        if xy.ndim != 2 or xy.shape[-1] != 2:
            raise ValueError(f"xy: expected shape (N, 2), found {tuple(xy.shape)}")
        h = xy / self.scale_m
        for layer in self.hidden:
            h = torch.sin(self.omega0 * layer(h))
        return F.softplus(self.out(h)).squeeze(-1)


class LambertianSensorModel(SensorModel):
    """Predicts sidescan intensity from SIREN geometry; learns K, G, B (and rho) with it.

    Angles are radians inside; the config gives degrees (``tilt_deg``, ``beam_width_deg``).

    Args:
        tilt_deg: beam axis depression angle (deg); the beam knots span
            ``[tilt - beam_width/2, tilt + beam_width/2]``. Null (with ``beam_width_deg``):
            from the survey, :meth:`setup_from_data` (or :meth:`set_domain`).
        beam_width_deg: full vertical beam width (deg).
        range_min_m, range_max_m: span of the range-gain knots (m), ``0 <= min < max``;
            null: the span of the bins' ranges, :meth:`setup_from_data`.
        n_beam_knots, n_gain_knots: knots of ``B`` and ``G`` (``>= 2``).
        q: Lambert's exponent *in power* (``P ~ cos(incidence)^q``, ``>= 1``; 2 for
            Lambert's law of backscatter, 1 for the plain cosine law).
        intensity_kind: what the sidescan stores, ``"amplitude"`` (the simulator, XTF:
            the model applies ``cos^(q/2)``) or ``"power"`` (``cos^q``).
        reflectivity: ``"constant"`` (rho = 1, folded into K) or ``"field"``
            (:class:`ReflectivityField` over world x, y; its level and ``K`` share one
            scale, only their product is observable).
        field_lr: learning rate of the reflectivity field's parameters (its own optimiser
            group, :meth:`parameter_groups`); ``None``: the sensor's learning rate.
        field_weight: weight of the penalty ``Var(log rho)`` over each batch's crossings,
            added to the loss, so that the field explains broad material contrasts and
            not the slope shading the bathymetry has to explain (0: none).
        shadow_threshold: bins with normalised intensity below this are dropped (shadows).
        near_range_cut_m: bins with slant range below this are dropped (near nadir).
        init_scale: initial ``K`` (> 0).
        calibrate_scale: on the first :meth:`loss` call, set ``K`` so that the mean
            prediction equals the mean target (data-dependent init, averaged over DDP
            ranks); stored in the checkpoint so a resumed run does not redo it.
        field_hidden, field_layers, field_omega0, field_scale_m: the reflectivity field's
            size, frequency and input scale (used with ``reflectivity="field"``).
    """

    target_key = "intensity"

    def __init__(
        self,
        tilt_deg: float | None = None,
        beam_width_deg: float | None = None,
        range_min_m: float | None = None,
        range_max_m: float | None = None,
        n_beam_knots: int = 8,
        n_gain_knots: int = 8,
        q: float = 2.0,
        intensity_kind: str = "amplitude",
        reflectivity: str = "constant",
        field_lr: float | None = None,
        field_weight: float = 0.0,
        shadow_threshold: float = 0.3,
        near_range_cut_m: float = 0.0,
        init_scale: float = 1.0,
        calibrate_scale: bool = True,
        field_hidden: int = 32,
        field_layers: int = 2,
        field_omega0: float = 30.0,
        field_scale_m: float = 100.0,
    ) -> None:
        super().__init__()
        for name, k in (("n_beam_knots", n_beam_knots), ("n_gain_knots", n_gain_knots)):
            if int(k) < 2:
                raise ValueError(f"{name}: expected >= 2 knots, found {k}")
        if not q >= 1.0:
            raise ValueError(f"q: expected a Lambertian exponent in power >= 1, found {q}")
        if reflectivity not in REFLECTIVITY_KINDS:
            raise ValueError(
                f"reflectivity: expected one of {REFLECTIVITY_KINDS}, found {reflectivity!r}"
            )
        if field_lr is not None and not field_lr > 0.0:
            raise ValueError(
                f"field_lr: expected a positive learning rate or null, found {field_lr}"
            )
        if not field_weight >= 0.0:
            raise ValueError(f"field_weight: expected a weight >= 0, found {field_weight}")
        require_number("shadow_threshold", shadow_threshold, lambda v: v >= 0, "a number >= 0")
        # each range first, so a bad value is named even when its partner is null
        tilt_ok = lambda v: -90 <= v <= 90  # noqa: E731
        require_number("tilt_deg", tilt_deg, tilt_ok, "a value in [-90, 90] degrees or null", True)
        width_ok = lambda v: 0 < v < 180  # noqa: E731
        require_number(
            "beam_width_deg", beam_width_deg, width_ok, "a value in (0, 180) degrees or null", True
        )
        if not near_range_cut_m >= 0.0:
            raise ValueError(f"near_range_cut_m: expected >= 0 m, found {near_range_cut_m}")
        if not init_scale > 0.0:
            raise ValueError(f"init_scale: expected > 0, found {init_scale}")

        self.q = float(q)
        self.intensity_kind = intensity_kind
        self.exponent = lambert_exponent(self.q, intensity_kind)
        self.reflectivity = reflectivity
        self.field_lr = None if field_lr is None else float(field_lr)
        self.field_weight = float(field_weight)
        self.shadow_threshold = float(shadow_threshold)
        self.near_range_cut_m = float(near_range_cut_m)
        self.calibrate_scale = bool(calibrate_scale)
        # NaN until the domain is known (from the config here, or set_domain from the data)
        self.register_buffer("beam_knots_rad", torch.full((int(n_beam_knots),), math.nan))
        self.register_buffer("gain_knots_m", torch.full((int(n_gain_knots),), math.nan))
        self.register_buffer("scale_calibrated", torch.tensor(False))
        self.log_scale = nn.Parameter(torch.tensor(math.log(init_scale)))
        self.beam_log_values = nn.Parameter(torch.zeros(int(n_beam_knots)))
        self.gain_log_values = nn.Parameter(torch.zeros(int(n_gain_knots)))
        self.reflectivity_field = (
            ReflectivityField(field_hidden, field_layers, field_omega0, field_scale_m)
            if reflectivity == "field"
            else None
        )
        beam_args, range_args = (tilt_deg, beam_width_deg), (range_min_m, range_max_m)
        for names, args in (
            ("tilt_deg, beam_width_deg", beam_args),
            ("range_min_m, range_max_m", range_args),
        ):
            if (args[0] is None) != (args[1] is None):
                raise ValueError(f"{names}: expected both given or both null, found {args}")
        if tilt_deg is not None:
            tilt, half = math.radians(tilt_deg), math.radians(beam_width_deg) / 2
            self.set_domain(theta_limits_rad=(tilt - half, tilt + half))
        if range_min_m is not None:
            if not 0.0 <= range_min_m < range_max_m:
                raise ValueError(
                    "range_min_m, range_max_m: expected 0 <= range_min_m < range_max_m, "
                    f"found {range_min_m}, {range_max_m}"
                )
            self.set_domain(range_limits_m=(range_min_m, range_max_m))

    def set_domain(
        self,
        theta_limits_rad: tuple[float, float] | None = None,
        range_limits_m: tuple[float, float] | None = None,
    ) -> None:
        """Place the beam-pattern knots over ``theta_limits_rad`` (the beam, depression
        angles) and/or the range-gain knots over ``range_limits_m`` (slant range).

        The learned values stay where they are, knot for knot, so this belongs before the
        fit (:meth:`setup_from_data` calls it for the spans the config leaves null).
        """
        if theta_limits_rad is not None:
            lo, hi = (float(v) for v in theta_limits_rad)
            if not -math.pi / 2 <= lo < hi <= math.pi / 2:
                raise ValueError(
                    f"theta_limits_rad: expected -pi/2 <= lo < hi <= pi/2, found {theta_limits_rad}"
                )
            self.beam_knots_rad.copy_(torch.linspace(lo, hi, self.beam_knots_rad.numel()))
        if range_limits_m is not None:
            lo, hi = (float(v) for v in range_limits_m)
            if not 0.0 <= lo < hi:
                raise ValueError(
                    f"range_limits_m: expected 0 <= lo < hi (m), found {range_limits_m}"
                )
            self.gain_knots_m.copy_(torch.linspace(lo, hi, self.gain_knots_m.numel()))

    def setup_from_data(self, sensor: SensorParams, range_m: torch.Tensor) -> None:
        """Fill the knot spans the config left null from the survey: the beam limits of
        ``sensor`` (:class:`~sss2bathy.survey.SensorParams`) and the span of the bins'
        slant ranges ``range_m (n_bins,)``. Spans given in the config are kept."""
        if not bool(torch.isfinite(self.beam_knots_rad).all()):
            self.set_domain(theta_limits_rad=sensor.beam_limits_rad)
        if not bool(torch.isfinite(self.gain_knots_m).all()):
            range_m = torch.as_tensor(range_m)
            self.set_domain(range_limits_m=(float(range_m.min()), float(range_m.max())))

    @property
    def has_domain(self) -> bool:
        """Whether both knot spans are set."""
        return bool(torch.isfinite(self.beam_knots_rad).all()) and bool(
            torch.isfinite(self.gain_knots_m).all()
        )

    # -- learned curves ------------------------------------------------------------------
    @property
    def scale(self) -> torch.Tensor:
        """Global scale ``K`` (scalar) that goes with :meth:`beam_values`/:meth:`gain_values`."""
        return (self.log_scale + self.beam_log_values.mean() + self.gain_log_values.mean()).exp()

    def beam_values(self) -> torch.Tensor:
        """``(n_beam_knots,)`` beam pattern at its knots, normalised to geometric mean 1."""
        return (self.beam_log_values - self.beam_log_values.mean()).exp()

    def gain_values(self) -> torch.Tensor:
        """``(n_gain_knots,)`` range gain at its knots, normalised to geometric mean 1."""
        return (self.gain_log_values - self.gain_log_values.mean()).exp()

    def beam_pattern_curve(self, n: int = 100) -> tuple[torch.Tensor, torch.Tensor]:
        """``(theta_rad (n,), B (n,))`` over the beam, detached, for logging."""
        knots = self.beam_knots_rad
        theta = torch.linspace(float(knots[0]), float(knots[-1]), n, device=knots.device)
        return theta, piecewise_linear(theta, knots, self.beam_values()).detach()

    def gain_curve(self, n: int = 100) -> tuple[torch.Tensor, torch.Tensor]:
        """``(range_m (n,), G (n,))`` over the gain span, detached, for logging."""
        knots = self.gain_knots_m
        r = torch.linspace(float(knots[0]), float(knots[-1]), n, device=knots.device)
        return r, piecewise_linear(r, knots, self.gain_values()).detach()

    def parameter_groups(self) -> list[dict[str, Any]]:
        """Optimiser groups: ``K``, ``G``, ``B`` (the sensor's learning rate), and the
        reflectivity field with ``lr = field_lr`` when both are set. A group without
        ``"lr"`` takes the caller's sensor learning rate."""
        field = list(self.reflectivity_field.parameters()) if self.reflectivity_field else []
        field_ids = {id(p) for p in field}
        groups: list[dict[str, Any]] = [
            {"params": [p for p in self.parameters() if id(p) not in field_ids]}
        ]
        if field:
            groups.append({"params": field, **({"lr": self.field_lr} if self.field_lr else {})})
        return groups

    # -- SensorModel ---------------------------------------------------------------------
    def bin_mask(self, batch: dict[str, torch.Tensor]) -> torch.Tensor:
        """``(B, 2, n_bins)`` bool: valid mask, intensity >= threshold, range >= near cut.

        NaN intensities fail the threshold and are dropped too.
        """
        for key in ("mask", "intensity", "range_m"):
            if key not in batch:
                raise ValueError(
                    f"batch: expected key {key!r} (set data.need_intensity=true), "
                    f"found keys {sorted(batch)}"
                )
        mask, intensity, range_m = batch["mask"], batch["intensity"], batch["range_m"]
        if intensity.shape != mask.shape or intensity.ndim != 3 or intensity.shape[1] != 2:
            raise ValueError(
                f"batch['intensity']: expected shape (B, 2, n_bins) equal to batch['mask'] "
                f"{tuple(mask.shape)}, found {tuple(intensity.shape)}"
            )
        if range_m.shape != intensity.shape[-1:]:
            raise ValueError(
                f"batch['range_m']: expected shape ({intensity.shape[-1]},), "
                f"found {tuple(range_m.shape)}"
            )
        keep = (mask == 0) & (intensity >= self.shadow_threshold)
        if self.near_range_cut_m > 0.0:
            keep = keep & (range_m >= self.near_range_cut_m)
        return keep

    def predict(self, geo: ArcGeometry) -> torch.Tensor:
        """``(N,)`` predicted normalised intensity; differentiable in ``geo.grad`` and the
        sensor's parameters."""
        return self._predict(geo)[0]

    def _predict(self, geo: ArcGeometry) -> tuple[torch.Tensor, torch.Tensor | None]:
        """``(prediction (N,), reflectivity (N,) or None)``."""
        n = geo.grad.shape[0]
        if geo.grad.ndim != 2 or geo.grad.shape[-1] != 2:
            raise ValueError(f"geo.grad: expected shape (N, 2), found {tuple(geo.grad.shape)}")
        for name, value in (("geo.theta", geo.theta), ("geo.range_m", geo.range_m)):
            if value.shape != (n,):
                raise ValueError(f"{name}: expected shape ({n},), found {tuple(value.shape)}")
        if not self.has_domain:
            raise ValueError(
                "LambertianSensorModel: beam/range knot spans unknown; set tilt_deg, "
                "beam_width_deg, range_min_m, range_max_m, or call setup_from_data() / "
                "set_domain() before the fit"
            )
        normal = world_normal(geo.grad[:, 0], geo.grad[:, 1])
        m = lambertian_term(
            normal, geo.points.to(normal.dtype), geo.sonar.to(normal.dtype), self.exponent
        )
        # the free log-values (not the normalised curves) keep each knot's gradient its own
        b = piecewise_linear(geo.theta, self.beam_knots_rad, self.beam_log_values.exp())
        g = piecewise_linear(geo.range_m, self.gain_knots_m, self.gain_log_values.exp())
        pred = self.log_scale.exp() * g * b * m
        rho = None
        if self.reflectivity_field is not None:
            rho = self.reflectivity_field(geo.points[:, :2].to(pred.dtype))
            pred = pred * rho
        return pred, rho

    def loss(self, geo: ArcGeometry, target: torch.Tensor) -> tuple[torch.Tensor, dict]:
        """Mean absolute intensity error over the ``N`` bins (0 with a graph when N = 0),
        plus ``field_weight * Var(log rho)`` over the bins with a reflectivity field.

        Returns ``(loss, logs)`` with ``intensity_l1``, ``scale``, ``pred_mean`` and
        ``target_mean`` (detached scalars), and with a field ``reflectivity_log_std``.
        """
        n = geo.grad.shape[0]
        if target.shape != (n,):
            raise ValueError(f"target: expected shape ({n},), found {tuple(target.shape)}")
        if self.calibrate_scale and not bool(self.scale_calibrated):
            self._calibrate(geo, target)
        pred, rho = self._predict(geo)
        target = target.to(pred.dtype)
        loss = (pred - target).abs().mean() if n > 0 else pred.sum() * 0.0
        logs = {
            "intensity_l1": loss.detach(),
            "scale": self.scale.detach(),
            "pred_mean": pred.detach().mean() if n > 0 else pred.detach().sum(),
            "target_mean": target.mean() if n > 0 else target.sum(),
        }
        if rho is not None:
            log_rho = rho.clamp_min(1e-12).log()
            spread = log_rho.var(unbiased=False) if n > 1 else log_rho.sum() * 0.0
            logs["reflectivity_log_std"] = spread.detach().sqrt()
            if self.field_weight > 0.0:
                loss = loss + self.field_weight * spread
        return loss, logs

    def _calibrate(self, geo: ArcGeometry, target: torch.Tensor) -> None:
        """Set ``K`` so that the mean prediction matches the mean target on this batch.

        Sums are reduced over DDP ranks (every rank takes part, with or without bins, so
        the ranks stay in step and agree on ``K``); retried on the next batch while no
        rank has a bin.
        """
        with torch.no_grad():
            sums = torch.stack([self.predict(geo).sum(), target.to(self.log_scale.dtype).sum()])
            if torch.distributed.is_available() and torch.distributed.is_initialized():
                torch.distributed.all_reduce(sums)
            if bool(sums[0] > 0) and bool(sums[1] > 0):
                self.log_scale.add_(torch.log(sums[1] / sums[0]))
                self.scale_calibrated.fill_(True)
                log.info("LambertianSensorModel: calibrated scale K = %.4g", float(self.scale))


def waterfall_image(
    ping: np.ndarray,
    side: np.ndarray,
    bin_index: np.ndarray,
    values: np.ndarray,
    n_pings: int,
    n_bins: int,
) -> np.ndarray:
    """Scatter per-bin values into a ``(n_pings, 2 * n_bins)`` waterfall, NaN elsewhere.

    Port is mirrored so nadir is in the middle: columns ``[port far ... port near |
    starboard near ... starboard far]``.
    """
    ping, side, bin_index = (np.asarray(a, dtype=np.int64) for a in (ping, side, bin_index))
    values = np.asarray(values, dtype=np.float32)
    shapes = {a.shape for a in (ping, side, bin_index, values)}
    if len(shapes) != 1 or values.ndim != 1:
        raise ValueError(
            f"ping, side, bin_index, values: expected equal (N,) shapes, found {shapes}"
        )
    if values.size and (ping.min() < 0 or ping.max() >= n_pings):
        raise ValueError(
            f"ping: expected indices in [0, {n_pings}), found [{ping.min()}, {ping.max()}]"
        )
    if values.size and (bin_index.min() < 0 or bin_index.max() >= n_bins):
        raise ValueError(
            f"bin_index: expected indices in [0, {n_bins}), found "
            f"[{bin_index.min()}, {bin_index.max()}]"
        )
    if values.size and not np.isin(side, (0, 1)).all():
        raise ValueError("side: expected 0 (port) or 1 (starboard)")
    image = np.full((n_pings, 2 * n_bins), np.nan, dtype=np.float32)
    column = np.where(side == 0, n_bins - 1 - bin_index, n_bins + bin_index)
    image[ping, column] = values
    return image
