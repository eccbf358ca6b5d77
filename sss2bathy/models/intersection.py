"""Where a height field crosses the sidescan's isotemporal arcs (paper eq. 10-12).

For a bin with sonar position ``s``, rotation ``R``, slant range ``r`` and side ``sigma``
the arc is ``p(theta) = s + r R [0, sigma cos(theta), -sin(theta)]`` (eq. 10) and the
crossing is a root of the signed vertical distance (eq. 11)

    ``f(theta) = Phi(p_x(theta), p_y(theta)) - p_z(theta)``,

which is negative while the arc point is above the seafloor and positive below it. The
beam is ``theta in [theta_lo, theta_hi] = [tilt - alpha/2, tilt + alpha/2]``; theta grows
from the most horizontal direction (far, high) towards nadir (near, low).

Solvers (all vectorised over every bin at once, under ``no_grad``):

* ``"gd"`` — the paper's fixed-step gradient descent (eq. 12),
  ``theta <- theta - (lambda / r) d/dtheta f^2``, from ``theta0`` (the warm start) or the
  tilt, for at most ``max_iter`` steps. A bin stops moving once ``|f| <= tol_m``.
* ``"newton"`` — safeguarded Newton on a bracket: a scan from the beam's upper edge (below)
  finds the *first* crossing (the smallest theta where ``f`` turns from negative, above
  ground, to ``>= 0``, below ground); the iteration starts at the regula-falsi point of
  that bracket, takes Newton steps ``theta - f / f'`` and falls back to bisection whenever
  a step leaves the bracket; the bracket shrinks with every evaluation.
* ``"secant"`` — the same bracket, height-only (the derivative-free steps of Brent's
  method): the first step is the bracket's regula-falsi point, then inverse quadratic
  interpolation through the last three iterates, or the secant through the last two,
  whichever lands inside the bracket; bisection when neither does or the bracket has not
  halved over two evaluations. On a SIREN a height costs about 1/2.4 of a height with
  gradient and this needs about as many evaluations as Newton: the cheaper cold solver.
* ``"bisection"`` — bisection on the same bracket (robust reference, height-only).

Cold scan (bracketing solvers). From the beam's upper edge ``theta_lo`` the scan steps
towards nadir. At an angle where the arc is ``d = -f > 0`` metres above ground no crossing
can lie within ``d / (r sqrt(1 + L^2))`` rad, if the surface's slope along the arc is at
most ``L = scan_max_slope`` (``|f'| <= |grad Phi| |t_xy| + |t_z| <= r sqrt(1 + L^2)``, the
arc's tangent ``t`` having length ``r``): the next angle is that far plus the grid spacing
``(theta_hi - theta_lo) / (n_scan - 1)``. Every stretch not covered by that bound is thus
at most one grid spacing long, as between the angles of a plain grid scan of ``n_scan``
angles, which ``scan_max_slope = inf`` reproduces exactly; high above ground (far from
the crossing) the steps are much longer. The first step that ends with ``f >= 0``
brackets the first crossing, up to features narrower than a grid spacing (or steeper
than ``L`` within the longer steps).

Warm start (``theta0``; NaN = unknown, ``+inf`` = "no crossing last time"), bracketing
solvers: first ``f`` (and ``f'`` for Newton) at ``theta0``: if ``|f| <= tol_m`` (and the
arc goes into the ground there, ``f' > 0``) the bin is done after one evaluation (Newton
also takes the free step ``theta0 - f/f'``). Otherwise one more height on the root's side
(``theta0 + warm_bracket_rad`` if ``theta0`` is above ground, else ``-``; widened 4x and 16x
for the bins that miss) gives a small bracket that replaces the scan. The surface moves
little between epochs, so this is the common case after the first epoch; bins that still
miss are scanned cold. A warm start trusts the previous crossing to still be the first.
Bins marked ``+inf`` are re-scanned only if the beam's two ends now enclose a crossing
(two height evaluations instead of a scan; an arc that starts and ends above ground but
dips into a rock in between stays invalid until the bin is reset to NaN).

A bin is valid when its crossing lies in the beam and ``|f| <= tol_m`` at the returned
angle; invalid bins get ``theta = NaN``. ``n_iter`` counts the solver's surface
evaluations per bin, with a derivative (Newton, gradient descent) or height-only
(secant, bisection), including the warm-start check at ``theta0``; the extra height-only
evaluations of the scan and of the warm brackets are not included.
"""

from __future__ import annotations

import dataclasses
import math
import numbers
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import Any, Protocol

import torch

from sss2bathy.geometry import arc_basis

SOLVERS = ("newton", "secant", "gd", "bisection")
DEFAULT_MAX_ITER = {"newton": 16, "secant": 32, "bisection": 48, "gd": 400}
# Warm brackets tried before a cold scan: theta0 -+ warm_bracket_rad * factor.
WARM_EXPANSION = (1.0, 4.0, 16.0)


def _is_int(value: Any) -> bool:
    return isinstance(value, numbers.Integral) and not isinstance(value, bool)


def _is_number(value: Any) -> bool:
    return isinstance(value, numbers.Real) and not isinstance(value, bool)


@dataclass(frozen=True)
class FinderSettings:
    """Settings of :func:`find_intersections`: the one source of the finder's defaults.

    ``model.finder`` of the SIREN configs holds the same keys (:meth:`from_mapping`).

    Attributes:
        solver: ``"secant"`` (height-only, the fastest cold solver) | ``"newton"`` |
            ``"bisection"`` | ``"gd"`` (the paper's fixed-step descent, eq. 12).
        max_iter: solver iterations; ``None`` = per solver, :data:`DEFAULT_MAX_ITER`.
        tol_m: convergence tolerance on ``|f|``, the vertical distance (m).
        gd_step: ``lambda`` of eq. 12 (``"gd"`` only).
        warm_start: whether a caller that keeps each bin's last crossing passes it as
            ``theta0`` (with ``False`` :func:`find_intersections` ignores ``theta0``).
        n_scan: the cold scan's resolution: its longest unbounded step is
            ``(theta_hi - theta_lo) / (n_scan - 1)`` (bracketing solvers).
        scan_max_slope: surface slope ``L`` (m/m) the cold scan assumes where it steps
            further than one grid spacing; ``inf`` = a plain grid of ``n_scan`` angles.
        warm_bracket_deg: half-width of the warm-start bracket (degrees).
        chunk: points per surface evaluation.
        neighbour_start: a bin with no crossing of its own yet starts from the solved bins
            of its ping and side, at the depth below the sonar they give
            (:func:`neighbour_guess`): a warm bracket instead of a cold scan. Pays when
            bins are seldom revisited (a paper-scale survey, few bins per step:
            ``data.bin_fraction``). Like any warm start it trusts the crossing near the
            guess to be the first.
        seed_stride: with ``neighbour_start``, a row (ping and side) with no crossing yet
            first solves every ``seed_stride``-th of its bins cold and starts the rest
            from them (:func:`find_row_intersections`); 1 = all of them cold.
    """

    solver: str = "secant"
    max_iter: int | None = None
    tol_m: float = 1e-3
    gd_step: float = 0.01
    warm_start: bool = True
    n_scan: int = 16
    scan_max_slope: float = 1.0
    warm_bracket_deg: float = 0.5
    chunk: int = 8192
    neighbour_start: bool = False
    seed_stride: int = 8

    def __post_init__(self) -> None:
        def bad(name: str, expected: str) -> ValueError:
            return ValueError(f"finder.{name}: expected {expected}, found {getattr(self, name)!r}")

        def positive(value: Any) -> bool:
            return _is_number(value) and math.isfinite(value) and value > 0

        if self.solver not in SOLVERS:
            raise bad("solver", f"one of {SOLVERS}")
        if self.max_iter is not None and not (_is_int(self.max_iter) and self.max_iter >= 1):
            raise bad("max_iter", "an integer >= 1 or None")
        if not positive(self.tol_m):
            raise bad("tol_m", "a positive tolerance in metres")
        if not positive(self.gd_step):
            raise bad("gd_step", "a positive step")
        if not isinstance(self.warm_start, bool):
            raise bad("warm_start", "true or false")
        if not (_is_int(self.n_scan) and self.n_scan >= 2):
            raise bad("n_scan", "an integer >= 2 (scan angles)")
        if not (_is_number(self.scan_max_slope) and self.scan_max_slope >= 0):
            raise bad("scan_max_slope", "a slope >= 0 (inf allowed)")
        if not positive(self.warm_bracket_deg):
            raise bad("warm_bracket_deg", "a positive angle (degrees)")
        if not (_is_int(self.chunk) and self.chunk >= 1):
            raise bad("chunk", "an integer >= 1 (points)")
        if not isinstance(self.neighbour_start, bool):
            raise bad("neighbour_start", "true or false")
        if not (_is_int(self.seed_stride) and self.seed_stride >= 1):
            raise bad("seed_stride", "an integer >= 1 (1 = every bin of a new row cold)")

    @classmethod
    def from_mapping(cls, finder: Mapping[str, Any] | FinderSettings | None) -> FinderSettings:
        """Settings from a config mapping (keys: the fields), defaults for the rest."""
        if isinstance(finder, FinderSettings):
            return finder
        return cls().replace(**dict(finder or {}))

    def replace(self, **changes: Any) -> FinderSettings:
        """A copy with ``changes`` (field names; an unknown key is an error)."""
        names = sorted(f.name for f in dataclasses.fields(self))
        unknown = sorted(set(changes) - set(names))
        if unknown:
            raise ValueError(f"finder: expected keys among {names}, found unknown {unknown}")
        return dataclasses.replace(self, **changes)

    @property
    def iterations(self) -> int:
        """``max_iter``, or the solver's default (:data:`DEFAULT_MAX_ITER`)."""
        return self.max_iter if self.max_iter is not None else DEFAULT_MAX_ITER[self.solver]

    @property
    def warm_bracket_rad(self) -> float:
        """:attr:`warm_bracket_deg` in radians."""
        return math.radians(self.warm_bracket_deg)


def neighbour_guess(theta: torch.Tensor, range_m: torch.Tensor) -> torch.Tensor:
    """Warm-start angles for the bins of ``theta (..., B)`` that have none (NaN), from the
    bins of the same row (ping and side) that have a crossing (finite): the angle at which
    the bin's arc reaches their depth below the sonar, ``asin(d / r)``. Between two solved
    bins the depth ``d = r_n sin(theta_n)`` is interpolated linearly in range; beyond the
    last (or before the first) solved bin of the row it is that bin's depth. Exact on
    ground flat across the head plane, and close on a gentle slope. Bins with a crossing
    or marked ``+inf`` keep their value; rows without a crossing, and bins whose arc
    cannot reach the depth, stay NaN.

    Args:
        theta: ``(..., B)`` depression angles (rad); NaN = unknown, ``+inf`` = no crossing.
        range_m: ``(B,)`` slant range of each bin (m), increasing.
    """
    n_bins = theta.shape[-1]
    if range_m.shape != (n_bins,):
        raise ValueError(f"range_m: expected shape ({n_bins},), found {tuple(range_m.shape)}")
    known = torch.isfinite(theta)
    pos = torch.arange(n_bins, device=theta.device)
    # nearest known bin at or below / at or above each bin (-1 / n_bins when none)
    below = torch.where(known, pos, -1).cummax(-1).values
    above = torch.where(known, pos, n_bins).flip(-1).cummin(-1).values.flip(-1)
    has_below, has_above = below >= 0, above < n_bins
    r = range_m.to(theta.dtype)
    depth = r * torch.sin(torch.nan_to_num(theta, 0.0, 0.0, 0.0))
    i_b, i_a = below.clamp(0, n_bins - 1), above.clamp(0, n_bins - 1)
    d_b, d_a = torch.gather(depth, -1, i_b), torch.gather(depth, -1, i_a)
    r_b, r_a = r[i_b], r[i_a]
    # weight of the bin above; one side only: that side's depth
    w = ((r - r_b) / (r_a - r_b).clamp_min(torch.finfo(r.dtype).tiny)).clamp(0.0, 1.0)
    w = torch.where(has_below, torch.where(has_above, w, 0.0), 1.0)
    ratio = torch.lerp(d_b, d_a, w) / r
    has = has_below | has_above
    guess = torch.where(has & (ratio.abs() <= 1.0), torch.asin(ratio.clamp(-1.0, 1.0)), torch.nan)
    return torch.where(torch.isnan(theta), guess, theta)


def seed_bins(use: torch.Tensor, blank: torch.Tensor, stride: int) -> torch.Tensor:
    """``(..., B)`` bool: every ``stride``-th used bin (the first, then each ``stride``-th
    in order of range) of the rows where ``blank (...)`` is true; none elsewhere."""
    rank = use.long().cumsum(-1) - 1
    return use & blank.unsqueeze(-1) & (rank % stride == 0)


@torch.no_grad()
def find_row_intersections(
    surface: HeightField,
    sonar: torch.Tensor,
    R: torch.Tensor,
    range_m: torch.Tensor,
    use: torch.Tensor,
    theta_limits: tuple[float, float],
    rows: torch.Tensor | None = None,
    *,
    settings: FinderSettings | Mapping[str, Any] | None = None,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """:func:`find_intersections` for the bins ``use`` of whole pings, each started from its
    row's last crossings (ping and side: ``rows``).

    With ``settings.neighbour_start`` a bin with no crossing of its own starts from its
    row's solved bins (:func:`neighbour_guess`); a row with none yet (a ping seen for the
    first time) first solves every ``settings.seed_stride``-th of its used bins cold
    (:func:`seed_bins`), and the rest then start from those (coarse to fine). Without
    ``settings.warm_start`` every bin is solved cold.

    Args:
        surface, theta_limits: as :func:`find_intersections`.
        sonar: ``(P, 3)`` sonar positions (m); ``R``: ``(P, 3, 3)`` rotations.
        range_m: ``(B,)`` slant range of each bin (m), increasing.
        use: ``(P, 2, B)`` bool, the bins to solve.
        rows: ``(P, 2, B)`` previous angles (rad; NaN = unknown, ``+inf`` = no crossing
            last time), or ``None`` (all unknown).

    Returns:
        ``rows (P, 2, B)``: ``rows`` (NaN if ``None``) with each used bin's crossing, or
        ``+inf`` where it has none; ``valid`` and ``n_iter (P, 2, B)`` (``False`` / 0 for
        unused bins; ``n_iter`` counts the seeds' cold solve too).
    """
    cfg = FinderSettings.from_mapping(settings)
    if not isinstance(use, torch.Tensor) or use.dtype != torch.bool or use.ndim != 3:
        raise ValueError(
            f"use: expected a (P, 2, B) bool tensor, found {getattr(use, 'shape', use)}"
        )
    n_pings, _, n_bins = use.shape
    if use.shape[1] != 2 or sonar.shape[:1] != (n_pings,) or range_m.shape != (n_bins,):
        raise ValueError(
            f"use (P, 2, B), sonar (P, 3), range_m (B,): found {tuple(use.shape)}, "
            f"{tuple(sonar.shape)}, {tuple(range_m.shape)}"
        )
    if rows is None:
        rows = torch.full(use.shape, torch.nan, device=sonar.device, dtype=sonar.dtype)
    elif rows.shape != use.shape:
        raise ValueError(f"rows: expected shape {tuple(use.shape)}, found {tuple(rows.shape)}")
    rows = rows.clone()
    valid = torch.zeros_like(use)
    n_iter = torch.zeros(use.shape, dtype=torch.long, device=use.device)

    def solve(sel: torch.Tensor, theta0: torch.Tensor | None) -> None:
        pi, si, bi = sel.nonzero(as_tuple=True)
        theta, ok, it = find_intersections(
            surface, sonar[pi], R[pi], range_m[bi], si, theta_limits,
            theta0=None if theta0 is None else theta0[pi, si, bi], settings=cfg,
        )  # fmt: skip
        rows[pi, si, bi] = torch.where(ok, theta, torch.inf).to(rows.dtype)
        valid[pi, si, bi] = ok
        n_iter[pi, si, bi] += it

    if not cfg.warm_start:
        solve(use, None)
        return rows, valid, n_iter
    todo = use
    if cfg.neighbour_start:
        if cfg.seed_stride > 1:
            blank = ~torch.isfinite(rows).any(-1) & use.any(-1)
            if bool(blank.any()):
                seeds = seed_bins(use, blank, cfg.seed_stride)
                solve(seeds, rows)
                todo = use & ~seeds
        theta0 = neighbour_guess(rows, range_m)
    else:
        theta0 = rows
    solve(todo, theta0)
    return rows, valid, n_iter


class HeightField(Protocol):
    """A surface ``z = Phi(x, y)``: what the finder needs (a :class:`~.siren.Siren` is one)."""

    def height(self, xy: torch.Tensor) -> torch.Tensor: ...

    def height_and_gradient(self, xy: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]: ...


def _chunked(fn: Callable, chunk: int, *tensors: torch.Tensor):
    """Apply ``fn`` to row chunks of ``tensors`` and concatenate (CPU caches like chunks)."""
    n = tensors[0].shape[0]
    if n <= chunk:
        return fn(*tensors)
    outs = [fn(*parts) for parts in zip(*(t.split(chunk) for t in tensors), strict=True)]
    if isinstance(outs[0], tuple):
        return tuple(torch.cat(o) for o in zip(*outs, strict=True))
    return torch.cat(outs)


class _Arcs:
    """Arc geometry of ``N`` bins: ``p(theta) = s + u cos(theta) - w sin(theta)``, with
    ``(u, w)`` the range-scaled :func:`~sss2bathy.geometry.arc_basis` (eq. 10)."""

    def __init__(self, sonar, R, range_m, side) -> None:
        r = range_m.to(sonar.dtype)
        u, w = arc_basis(R, side)
        self.sonar = sonar
        self.u = r.unsqueeze(-1) * u  # r sigma (R e_y)
        self.w = r.unsqueeze(-1) * w  # r (R e_z)
        self.r = r

    def point(self, theta: torch.Tensor, idx: torch.Tensor) -> torch.Tensor:
        s, u, w = self.sonar[idx], self.u[idx], self.w[idx]
        return s + u * torch.cos(theta).unsqueeze(-1) - w * torch.sin(theta).unsqueeze(-1)

    def tangent(self, theta: torch.Tensor, idx: torch.Tensor) -> torch.Tensor:
        u, w = self.u[idx], self.w[idx]
        return -u * torch.sin(theta).unsqueeze(-1) - w * torch.cos(theta).unsqueeze(-1)


class _Residual:
    """``f(theta)`` and ``f'(theta)`` of a subset of bins, evaluated in chunks."""

    def __init__(self, surface: HeightField, arcs: _Arcs, chunk: int) -> None:
        self.surface, self.arcs, self.chunk = surface, arcs, chunk

    def value(self, theta: torch.Tensor, idx: torch.Tensor) -> torch.Tensor:
        p = self.arcs.point(theta, idx)
        z = _chunked(self.surface.height, self.chunk, p[:, :2].contiguous())
        return z.to(p.dtype) - p[:, 2]

    def value_and_slope(
        self, theta: torch.Tensor, idx: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor]:
        p = self.arcs.point(theta, idx)
        t = self.arcs.tangent(theta, idx)
        z, grad = _chunked(self.surface.height_and_gradient, self.chunk, p[:, :2].contiguous())
        dz = (grad.to(p.dtype) * t[:, :2]).sum(-1)
        return z.to(p.dtype) - p[:, 2], dz - t[:, 2]


def _check_inputs(sonar, R, range_m, side, theta_limits, theta0):
    if not isinstance(sonar, torch.Tensor) or sonar.ndim != 2 or sonar.shape[1] != 3:
        raise ValueError(f"sonar: expected a (N, 3) tensor, found {getattr(sonar, 'shape', sonar)}")
    n = sonar.shape[0]
    if not isinstance(R, torch.Tensor) or R.shape != (n, 3, 3):
        raise ValueError(f"R: expected shape ({n}, 3, 3), found {getattr(R, 'shape', R)}")
    for name, t in (("range_m", range_m), ("side", side)):
        if not isinstance(t, torch.Tensor) or t.shape != (n,):
            raise ValueError(f"{name}: expected shape ({n},), found {getattr(t, 'shape', t)}")
    if side.is_floating_point():
        raise ValueError("side: expected integer side indices (0 port, 1 starboard), found floats")
    if theta0 is not None and (not isinstance(theta0, torch.Tensor) or theta0.shape != (n,)):
        raise ValueError(
            f"theta0: expected None or shape ({n},), found {getattr(theta0, 'shape', theta0)}"
        )
    lo, hi = (float(v) for v in theta_limits)
    if not (math.isfinite(lo) and math.isfinite(hi) and lo < hi):
        raise ValueError(
            f"theta_limits: expected finite (lo, hi) with lo < hi, found {theta_limits}"
        )
    return lo, hi


@torch.no_grad()
def find_intersections(
    surface: HeightField,
    sonar: torch.Tensor,
    R: torch.Tensor,
    range_m: torch.Tensor,
    side: torch.Tensor,
    theta_limits: tuple[float, float],
    solver: str | None = None,
    theta0: torch.Tensor | None = None,
    *,
    settings: FinderSettings | Mapping[str, Any] | None = None,
    **overrides: Any,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Depression angle where each bin's isotemporal arc crosses ``surface``.

    Args:
        surface: the height field (e.g. a :class:`~sss2bathy.models.siren.Siren`).
        sonar: ``(N, 3)`` sonar positions (m, world ENU).
        R: ``(N, 3, 3)`` vehicle -> world rotations.
        range_m: ``(N,)`` slant ranges (m).
        side: ``(N,)`` long, 0 port / 1 starboard.
        theta_limits: ``(theta_lo, theta_hi)`` beam limits (rad).
        solver: overrides ``settings.solver`` (module docstring).
        theta0: ``(N,)`` warm-start angles (rad), NaN where unknown; ``None`` = cold
            (ignored when ``settings.warm_start`` is false).
        settings: :class:`FinderSettings` (or a mapping of its fields); ``None``: defaults.
        **overrides: fields of :class:`FinderSettings` that replace those of ``settings``
            (``max_iter``, ``tol_m``, ``gd_step``, ``n_scan``, ``scan_max_slope``, ...).

    Returns:
        ``theta (N,)`` (rad, NaN where invalid), ``valid (N,)`` bool and
        ``n_iter (N,)`` long (solver evaluations per bin, see the module docstring).
    """
    if solver is not None:
        overrides["solver"] = solver
    cfg = FinderSettings.from_mapping(settings).replace(**overrides)
    lo, hi = _check_inputs(sonar, R, range_m, side, theta_limits, theta0)
    if not cfg.warm_start:
        theta0 = None
    arcs = _Arcs(sonar, R, range_m, side)
    res = _Residual(surface, arcs, cfg.chunk)
    if cfg.solver == "gd":
        return _gradient_descent(res, arcs, lo, hi, theta0, cfg.iterations, cfg.tol_m, cfg.gd_step)
    return _bracketed_solve(
        res,
        sonar.shape[0],
        lo,
        hi,
        theta0,
        cfg.solver,
        cfg.n_scan,
        float(cfg.scan_max_slope),
        cfg.warm_bracket_rad,
        cfg.tol_m,
        cfg.iterations,
    )


def _gradient_descent(res, arcs, lo, hi, theta0, max_iter, tol_m, step):
    n = arcs.r.shape[0]
    dev, dt = arcs.r.device, arcs.r.dtype
    theta = torch.full((n,), (lo + hi) / 2, device=dev, dtype=dt)
    if theta0 is not None:
        warm = torch.isfinite(theta0)
        theta = torch.where(warm, theta0.to(dt), theta)
    converged = torch.zeros(n, dtype=torch.bool, device=dev)
    n_iter = torch.zeros(n, dtype=torch.long, device=dev)
    active = torch.arange(n, device=dev)
    for _ in range(max_iter):
        if active.numel() == 0:
            break
        th = theta[active]
        f, df = res.value_and_slope(th, active)
        n_iter[active] += 1
        done = f.abs() <= tol_m
        converged[active[done]] = True
        # eq. 12: theta <- theta - (lambda / r) d(f^2)/dtheta
        theta[active] = torch.where(done, th, th - step / arcs.r[active] * 2.0 * f * df)
        keep = ~done & torch.isfinite(theta[active])
        active = active[keep]
    valid = converged & (theta >= lo) & (theta <= hi)
    return torch.where(valid, theta, torch.nan), valid, n_iter


class _Solve:
    """Per-bin state of a bracketing solve: result, brackets ``f(a) < 0 <= f(b)``, counts."""

    def __init__(self, n: int, device: torch.device, dtype: torch.dtype) -> None:
        def nan():
            return torch.full((n,), torch.nan, device=device, dtype=dtype)

        self.theta, self.a, self.b, self.fa, self.fb = nan(), nan(), nan(), nan(), nan()
        self.converged = torch.zeros(n, dtype=torch.bool, device=device)
        self.bracketed = torch.zeros(n, dtype=torch.bool, device=device)
        self.n_iter = torch.zeros(n, dtype=torch.long, device=device)

    def set_bracket(self, idx, a, b, fa, fb) -> None:
        self.a[idx], self.b[idx], self.fa[idx], self.fb[idx] = a, b, fa, fb
        self.bracketed[idx] = True

    def set_done(self, idx, theta) -> None:
        self.theta[idx] = theta
        self.converged[idx] = True


def _bracketed_solve(
    res, n, lo, hi, theta0, solver, n_scan, max_slope, warm_delta, tol_m, max_iter
):
    dev, dt = res.arcs.r.device, res.arcs.r.dtype
    st = _Solve(n, dev, dt)
    cold = torch.ones(n, dtype=torch.bool, device=dev)
    if theta0 is not None:
        cold = _warm_start(res, st, lo, hi, theta0.to(dt), solver, warm_delta, tol_m)
    _scan(res, st, cold.nonzero().squeeze(-1), lo, hi, n_scan, tol_m, dt, max_slope)
    _refine(res, st, solver, max_iter, tol_m)
    return st.theta, st.converged, st.n_iter


def _warm_start(res, st, lo, hi, theta0, solver, warm_delta, tol_m):
    """Solve or bracket the warm-started bins; returns the ``(N,)`` mask still to scan."""
    cold = torch.isnan(theta0) | (theta0 == -torch.inf)
    # Previously no crossing (+inf): re-scan only if the beam's ends now enclose one.
    gone = (theta0 == torch.inf).nonzero().squeeze(-1)
    if gone.numel():
        f_end = res.value(
            torch.cat(
                [
                    torch.full_like(gone, lo, dtype=theta0.dtype),
                    torch.full_like(gone, hi, dtype=theta0.dtype),
                ]
            ),
            torch.cat([gone, gone]),
        )
        f_lo, f_hi = f_end[: gone.numel()], f_end[gone.numel() :]
        cold[gone] = ((f_lo < 0) & (f_hi >= 0)) | (f_lo.abs() <= tol_m) | (f_hi.abs() <= tol_m)
    idx = (torch.isfinite(theta0) & (theta0 >= lo) & (theta0 <= hi)).nonzero().squeeze(-1)
    cold[torch.isfinite(theta0) & ((theta0 < lo) | (theta0 > hi))] = True
    if idx.numel() == 0:
        return cold
    t0 = theta0[idx]
    # 1. Is the previous crossing still on the surface?
    if solver == "newton":
        f0, df0 = res.value_and_slope(t0, idx)
        t_new = t0 - f0 / df0  # the free last Newton step
        ok = (f0.abs() <= tol_m) & (df0 > 0) & (t_new >= lo) & (t_new <= hi)
    else:
        f0 = res.value(t0, idx)
        t_new, ok = t0, f0.abs() <= tol_m
    st.n_iter[idx] += 1
    st.set_done(idx[ok], t_new[ok])
    idx, t0, f0 = idx[~ok], t0[~ok], f0[~ok]
    # 2. One-sided brackets towards the root (above ground: deeper), widening.
    above = f0 < 0
    for factor in WARM_EXPANSION:
        if idx.numel() == 0:
            break
        far = torch.where(above, t0 + warm_delta * factor, t0 - warm_delta * factor).clamp(lo, hi)
        f_far = res.value(far, idx)
        a, b = torch.where(above, t0, far), torch.where(above, far, t0)
        fa, fb = torch.where(above, f0, f_far), torch.where(above, f_far, f0)
        ok = (fa < 0) & (fb >= 0)
        st.set_bracket(idx[ok], a[ok], b[ok], fa[ok], fb[ok])
        idx, t0, f0, above = idx[~ok], t0[~ok], f0[~ok], above[~ok]
    cold[idx] = True
    return cold


def _scan(res, st, active, lo, hi, n_scan, tol_m, dt, max_slope):
    """Cold scan (module docstring): the first step that ends with ``f >= 0``, from ``f < 0``."""
    if active.numel() == 0:
        return
    spacing = (hi - lo) / (n_scan - 1)
    # |f'(theta)| <= |grad Phi| |t_xy| + |t_z| <= sqrt(1 + L^2) |t| with |t| = r
    inv_lip = 0.0 if math.isinf(max_slope) else 1.0 / math.sqrt(1.0 + max_slope**2)
    theta = torch.full((active.numel(),), lo, device=active.device, dtype=dt)
    f_prev = res.value(theta, active)
    # At the beam's upper edge the arc must still be above ground, or the crossing is
    # above the beam (out of beam) -- unless it lies on the edge itself (within tol_m).
    edge = (f_prev >= 0) & (f_prev <= tol_m)
    st.set_bracket(active[edge], theta[edge], theta[edge], f_prev[edge], f_prev[edge])
    up = f_prev < 0
    active, theta, f_prev = active[up], theta[up], f_prev[up]
    while active.numel():
        step = spacing - f_prev * (inv_lip / res.arcs.r[active])
        # a step that would stop within 1e-6 rad of the lower beam edge goes to the edge
        x = torch.where(theta + step >= hi - 1e-6, torch.full_like(theta, hi), theta + step)
        f_k = res.value(x, active)
        hit = f_k >= 0
        st.set_bracket(active[hit], theta[hit], x[hit], f_prev[hit], f_k[hit])
        # Still above ground at the lower beam edge: a crossing only if it is on the edge.
        end = ~hit & (x >= hi)
        edge = end & (f_k.abs() <= tol_m)
        st.set_bracket(active[edge], x[edge], x[edge], f_k[edge], f_k[edge])
        keep = ~hit & ~end & torch.isfinite(f_k)
        active, theta, f_prev = active[keep], x[keep], f_k[keep]


def _refine(res, st, solver, max_iter, tol_m):
    """Newton-with-bisection, secant-with-bisection or bisection inside the brackets."""
    active = (st.bracketed & ~st.converged).nonzero().squeeze(-1)
    a, b, fa, fb = st.a, st.b, st.fa, st.fb
    # A bracket end already on the surface (|f(b)| <= tol, e.g. a beam edge) is the answer.
    exact = fb[active].abs() <= tol_m
    st.set_done(active[exact], b[active[exact]])
    active = active[~exact]
    if solver == "secant":
        _refine_secant(res, st, active, max_iter, tol_m)
        return
    if solver == "newton":
        # Start at the regula-falsi point of the bracket (exact for a locally planar arc).
        x = a[active] - fa[active] * (b[active] - a[active]) / (fb[active] - fa[active])
    else:
        x = 0.5 * (a[active] + b[active])
    for _ in range(max_iter):
        if active.numel() == 0:
            break
        if solver == "newton":
            f, df = res.value_and_slope(x, active)
        else:
            f, df = res.value(x, active), None
        st.n_iter[active] += 1
        done = f.abs() <= tol_m
        below = f >= 0
        a_act = torch.where(below, a[active], x)
        b_act = torch.where(below, x, b[active])
        a[active], b[active] = a_act, b_act
        mid = 0.5 * (a_act + b_act)
        if df is not None:
            step = x - f / df
            inside = torch.isfinite(step) & (step >= a_act) & (step <= b_act)
            x_next = torch.where(inside, step, mid)
            # A converged bin still takes its last Newton step (free, and quadratically
            # closer); outside the bracket it keeps x.
            x_done = torch.where(inside, step, x)
        else:
            x_next, x_done = mid, x
        st.set_done(active[done], x_done[done])
        active, x = active[~done], x_next[~done]


def _refine_secant(res, st, active, max_iter, tol_m):
    """Safeguarded secant / inverse quadratic steps in the brackets of ``active`` (heights)."""
    a, b, fa, fb = (t[active] for t in (st.a, st.b, st.fa, st.fb))
    # The steps go through the latest iterates; before the first evaluation those are the
    # bracket ends (the first step is regula falsi), the better end counting as the later.
    b_last = fb.abs() <= fa.abs()
    x1, f1 = torch.where(b_last, b, a), torch.where(b_last, fb, fa)
    x2, f2 = torch.where(b_last, a, b), torch.where(b_last, fa, fb)
    x = a - fa * (b - a) / (fb - fa)
    # bracket widths before the current and the previous evaluation
    width, width_before = b - a, torch.full_like(a, torch.inf)
    for _ in range(max_iter):
        if active.numel() == 0:
            break
        f = res.value(x, active)
        st.n_iter[active] += 1
        below = f >= 0
        a, fa = torch.where(below, a, x), torch.where(below, fa, f)
        b, fb = torch.where(below, x, b), torch.where(below, f, fb)
        # inverse quadratic interpolation through the last three iterates, else the secant
        # through the last two, else (outside the bracket) bisection
        iqi = (
            x2 * f1 * f / ((f2 - f1) * (f2 - f))
            + x1 * f2 * f / ((f1 - f2) * (f1 - f))
            + x * f2 * f1 / ((f - f2) * (f - f1))
        )
        secant = x - f * (x - x1) / (f - f1)
        step = torch.where(torch.isfinite(iqi) & (iqi > a) & (iqi < b), iqi, secant)
        inside = torch.isfinite(step) & (step > a) & (step < b)
        # A converged bin still takes its last step (free, superlinearly closer); outside
        # the bracket it keeps x.
        done = f.abs() <= tol_m
        st.set_done(active[done], torch.where(inside, step, x)[done])
        slow = (b - a) > 0.5 * width_before
        x_next = torch.where(inside & ~slow, step, 0.5 * (a + b))
        width, width_before = b - a, width
        keep = ~done
        active, a, b, fa, fb, width, width_before = (
            t[keep] for t in (active, a, b, fa, fb, width, width_before)
        )
        x2, f2, x1, f1, x = x1[keep], f1[keep], x[keep], f[keep], x_next[keep]
