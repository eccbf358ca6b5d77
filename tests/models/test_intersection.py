"""Intersection finder vs analytic arc/surface crossings (plane, sphere cap), all solvers;
the cold scan vs a dense float64 reference on smooth, rough and occluding surfaces."""

from __future__ import annotations

import math
import time

import pytest
import torch

from sss2bathy.geometry import arc_point, attitude_to_rotation
from sss2bathy.models.intersection import (
    FinderSettings,
    find_intersections,
    find_row_intersections,
    neighbour_guess,
    seed_bins,
)
from sss2bathy.models.siren import Siren

BEAM = (0.0, math.radians(60.0))  # tilt 30 deg, beam width 60 deg


def _arc_vectors(sonar, R, r, side):
    sigma = 1.0 - 2.0 * side.double()
    return (sigma * r).unsqueeze(-1) * R[:, :, 1], r.unsqueeze(-1) * R[:, :, 2]


def _solve_cos_sin(A, B, K, sign):
    """theta with A cos + B sin = K; ``sign`` picks phi -+ acos (the crossing direction)."""
    M, phi = torch.hypot(A, B), torch.atan2(B, A)
    ok = (K / M).abs() <= 1
    theta = phi + sign * torch.acos((K / M).clamp(-1, 1))
    return torch.remainder(theta + math.pi, 2 * math.pi) - math.pi, ok


class Plane:
    """z = z0 + gx x + gy y."""

    def __init__(self, z0: float, gx: float, gy: float) -> None:
        self.z0, self.g = z0, torch.tensor([gx, gy], dtype=torch.float64)

    def height(self, xy):
        return self.z0 + xy @ self.g.to(xy.dtype)

    def height_and_gradient(self, xy):
        return self.height(xy), self.g.to(xy.dtype).expand(xy.shape[0], 2)

    def crossing(self, sonar, R, r, side):
        """f(theta) = K0 + A cos + B sin; the root where f turns from < 0 to > 0."""
        u, w = _arc_vectors(sonar, R, r, side)
        K0 = self.z0 + sonar[:, :2] @ self.g - sonar[:, 2]
        A = u[:, :2] @ self.g - u[:, 2]
        B = -(w[:, :2] @ self.g - w[:, 2])
        return _solve_cos_sin(A, B, -K0, -1.0)


class Cap:
    """Upper half of a sphere (centre c, radius rho): z = c_z + sqrt(rho^2 - |xy - c_xy|^2)."""

    def __init__(self, c, rho: float) -> None:
        self.c, self.rho = torch.tensor(c, dtype=torch.float64), rho

    def height_and_gradient(self, xy):
        d = xy - self.c[:2].to(xy.dtype)
        h = torch.sqrt((self.rho**2 - (d**2).sum(-1)).clamp_min(1e-9))
        return self.c[2] + h, -d / h.unsqueeze(-1)

    def height(self, xy):
        return self.height_and_gradient(xy)[0]

    def crossing(self, sonar, R, r, side):
        """|p(theta) - c|^2 = rho^2 with u ⟂ w, |u| = |w| = r; the entering root."""
        u, w = _arc_vectors(sonar, R, r, side)
        d = sonar - self.c
        A, B = 2 * (d * u).sum(-1), -2 * (d * w).sum(-1)
        K = self.rho**2 - (d * d).sum(-1) - r**2
        return _solve_cos_sin(A, B, K, +1.0)


def _bins(n_pings: int, spread: float, ranges: torch.Tensor, seed: int = 0):
    g = torch.Generator().manual_seed(seed)
    xy = (torch.rand(n_pings, 2, generator=g, dtype=torch.float64) * 2 - 1) * spread
    pos = torch.cat([xy, torch.zeros(n_pings, 1, dtype=torch.float64)], 1)
    att = torch.rand(n_pings, 3, generator=g, dtype=torch.float64)
    R = attitude_to_rotation(
        att[:, 0] * 2 * math.pi, (att[:, 1] - 0.5) * 0.2, (att[:, 2] - 0.5) * 0.2
    )
    nb = ranges.shape[0]
    pi = torch.arange(n_pings).repeat_interleave(2 * nb)
    side = torch.arange(2).repeat_interleave(nb).repeat(n_pings)
    r = ranges.double()[torch.arange(nb).repeat(2 * n_pings)]
    return pos[pi], R[pi], r, side


CASES = {
    "plane": (Plane(-15.0, 0.1, -0.05), 15.0, torch.linspace(5.0, 45.0, 40)),
    # sonar above the cap's top: every arc enters the sphere once before leaving it
    "cap": (Cap((0.0, 0.0, -30.0), 25.0), 5.0, torch.linspace(6.0, 29.5, 40)),
}
SOLVERS = {
    "newton": {},
    "secant": {},
    "bisection": {},
    "gd": {"max_iter": 3000, "gd_step": 0.01},
}


@pytest.mark.parametrize("solver", list(SOLVERS))
@pytest.mark.parametrize("case", list(CASES))
def test_finder_matches_analytic_crossing_within_1mm(case, solver):
    surface, spread, ranges = CASES[case]
    sonar, R, r, side = _bins(12, spread, ranges)
    theta_true, ok = surface.crossing(sonar, R, r, side)
    in_beam = ok & (theta_true > BEAM[0] + 0.01) & (theta_true < BEAM[1] - 0.01)
    assert in_beam.sum() > 300
    theta, valid, n_iter = find_intersections(
        surface,
        sonar.float(),
        R.float(),
        r.float(),
        side,
        BEAM,
        solver=solver,
        tol_m=1e-4,
        **SOLVERS[solver],
    )
    p = arc_point(sonar, R, r, theta.double(), side)
    p_true = arc_point(sonar, R, r, theta_true, side)
    err = (p - p_true).norm(dim=-1)
    if solver == "gd":
        # the paper's descent from the tilt converges for most bins, never to a wrong point
        assert (valid & in_beam).sum() >= 0.85 * in_beam.sum()
        assert err[valid & in_beam].max() < 1e-3
    else:
        assert valid[in_beam].all()
        assert err[in_beam].max() < 1e-3
        # a bin without a crossing in the beam is never valid
        assert not valid[~ok].any()
    assert torch.isnan(theta[~valid]).all() and torch.isfinite(theta[valid]).all()
    if solver in ("newton", "secant"):
        assert n_iter[in_beam].float().mean() <= 3.0


@pytest.mark.parametrize("solver", ["newton", "secant"])
def test_warm_start_reuses_the_previous_solution(solver):
    surface, spread, ranges = CASES["cap"]
    sonar, R, r, side = _bins(8, spread, ranges, seed=3)
    args = (surface, sonar, R, r, side, BEAM)
    theta, valid, n_cold = find_intersections(*args, tol_m=1e-5, solver=solver)
    calls = {"n": 0}

    class Counting:
        def height(self, xy):
            calls["n"] += xy.shape[0]
            return surface.height(xy)

        def height_and_gradient(self, xy):
            calls["n"] += xy.shape[0]
            return surface.height_and_gradient(xy)

    find_intersections(Counting(), *args[1:], tol_m=1e-5, solver=solver)
    cold_points = calls["n"]
    calls["n"] = 0
    theta2, valid2, n_warm = find_intersections(
        Counting(), *args[1:], theta0=theta, tol_m=1e-5, solver=solver
    )
    assert torch.equal(valid, valid2)
    assert torch.allclose(theta[valid], theta2[valid], atol=1e-7)
    assert n_warm[valid].float().mean() <= n_cold[valid].float().mean()
    assert calls["n"] < 0.5 * cold_points  # no scan for warm bins
    # "no crossing last time" (+inf): the beam's ends still enclose one -> found again;
    # bins without a crossing cost two evaluations instead of a scan
    inf = torch.full_like(theta, torch.inf)
    theta4, valid4, _ = find_intersections(*args, theta0=inf, tol_m=1e-5, solver=solver)
    assert torch.equal(valid, valid4) and torch.allclose(theta[valid], theta4[valid], atol=1e-7)
    calls["n"] = 0
    none = ~valid
    assert none.sum() > 10
    sub = (sonar[none], R[none], r[none], side[none], BEAM)
    find_intersections(Counting(), *sub, theta0=inf[none], tol_m=1e-5, solver=solver)
    assert calls["n"] == 2 * int(none.sum())
    # a stale warm start (wrong by 20 degrees) still finds the same crossing via the scan
    theta3, valid3, _ = find_intersections(
        *args, theta0=theta + math.radians(20.0), tol_m=1e-5, solver=solver
    )
    assert torch.equal(valid, valid3)
    assert torch.allclose(theta[valid], theta3[valid], atol=1e-6)


def test_first_crossing_is_taken_and_out_of_beam_is_invalid():
    # a wall of height rising 1 m/m beyond x = 10 in front of a flat floor at -20: an
    # eastward-looking (starboard, heading north) arc of range 25 first meets the wall
    class Wall:
        def height_and_gradient(self, xy):
            x = xy[:, 0]
            z = torch.where(x > 10.0, -20.0 + (x - 10.0), torch.full_like(x, -20.0))
            gx = torch.where(x > 10.0, torch.ones_like(x), torch.zeros_like(x))
            return z, torch.stack([gx, torch.zeros_like(x)], 1)

        def height(self, xy):
            return self.height_and_gradient(xy)[0]

    R = attitude_to_rotation(torch.zeros(1), torch.zeros(1), torch.zeros(1)).double()
    sonar = torch.zeros(1, 3, dtype=torch.float64)
    side = torch.ones(1, dtype=torch.long)  # starboard looks east when heading north
    theta, valid, _ = find_intersections(
        Wall(), sonar, R, torch.tensor([25.0]).double(), side, (0.0, 1.5), "newton"
    )
    p = arc_point(sonar, R, torch.tensor([25.0]).double(), theta, side)[0]
    assert valid.item() and p[0] > 10.0  # on the wall, not on the floor beyond/below it
    assert abs(p[2] - (-20.0 + p[0] - 10.0)) < 1e-3
    # a beam that ends above the seafloor sees nothing; one that starts below it neither
    for limits in ((0.0, 0.2), (1.2, 1.5)):
        theta, valid, _ = find_intersections(
            Wall(), sonar, R, torch.tensor([25.0]).double(), side, limits, "newton"
        )
        assert not valid.item() and torch.isnan(theta).item()


def test_finder_validates_inputs():
    surface = Plane(-10.0, 0.0, 0.0)
    s, R, r, side = (
        torch.zeros(3, 3),
        torch.eye(3).expand(3, 3, 3),
        torch.ones(3),
        torch.zeros(3, dtype=torch.long),
    )
    with pytest.raises(ValueError, match="solver"):
        find_intersections(surface, s, R, r, side, BEAM, solver="brent")
    with pytest.raises(ValueError, match="R"):
        find_intersections(surface, s, R[:2], r, side, BEAM)
    with pytest.raises(ValueError, match="side"):
        find_intersections(surface, s, R, r, side.float(), BEAM)
    with pytest.raises(ValueError, match="theta_limits"):
        find_intersections(surface, s, R, r, side, (1.0, 0.5))
    with pytest.raises(ValueError, match="tol_m"):
        find_intersections(surface, s, R, r, side, BEAM, tol_m=0.0)
    for bad in (-0.5, math.nan):
        with pytest.raises(ValueError, match="scan_max_slope"):
            find_intersections(surface, s, R, r, side, BEAM, scan_max_slope=bad)


@pytest.mark.parametrize(
    "field, value, expected",
    [
        ("solver", "brent", "one of"),
        ("max_iter", 0, "an integer >= 1 or None"),
        ("max_iter", 2.5, "an integer >= 1 or None"),
        ("tol_m", 0.0, "a positive tolerance in metres"),
        ("tol_m", math.inf, "a positive tolerance in metres"),
        ("gd_step", -0.01, "a positive step"),
        ("warm_start", 2, "true or false"),
        ("n_scan", 1, "an integer >= 2"),
        ("scan_max_slope", -1.0, "a slope >= 0"),
        ("scan_max_slope", math.nan, "a slope >= 0"),
        ("warm_bracket_deg", 0.0, "a positive angle"),
        ("chunk", 0, "an integer >= 1"),
        ("neighbour_start", 1, "true or false"),
        ("seed_stride", 0, "an integer >= 1"),
        ("seed_stride", 2.5, "an integer >= 1"),
    ],
)
def test_finder_settings_name_the_field_expected_and_found(field, value, expected):
    with pytest.raises(ValueError, match=rf"finder\.{field}: expected {expected}.*found {value!r}"):
        FinderSettings(**{field: value})
    with pytest.raises(ValueError, match=rf"finder\.{field}"):
        FinderSettings.from_mapping({field: value})


def test_finder_settings_are_the_one_source_of_defaults():
    cfg = FinderSettings()
    assert (cfg.solver, cfg.iterations, cfg.tol_m, cfg.warm_start) == ("secant", 32, 1e-3, True)
    assert cfg.warm_bracket_rad == math.radians(0.5)
    assert FinderSettings.from_mapping(None) == cfg == FinderSettings.from_mapping({})
    assert FinderSettings.from_mapping(cfg) is cfg
    newton = FinderSettings.from_mapping({"solver": "newton", "max_iter": 5})
    assert (newton.solver, newton.iterations, newton.n_scan) == ("newton", 5, 16)
    with pytest.raises(ValueError, match=r"finder: expected keys among .*found unknown \['tol'\]"):
        FinderSettings.from_mapping({"tol": 1e-3})


def test_find_intersections_takes_settings_and_overrides():
    surface = Plane(-10.0, 0.05, -0.02)
    sonar, R, r, side = _bins(4, 10.0, torch.linspace(12.0, 30.0, 10))
    args = (surface, sonar, R, r, side, BEAM)
    newton = FinderSettings(solver="newton", tol_m=1e-5)
    by_settings = find_intersections(*args, settings=newton)
    by_mapping = find_intersections(*args, settings={"solver": "newton", "tol_m": 1e-5})
    by_keywords = find_intersections(*args, "newton", tol_m=1e-5)
    for a, b in zip(by_settings, by_keywords, strict=True):
        assert torch.equal(a.nan_to_num(), b.nan_to_num())
    for a, b in zip(by_settings, by_mapping, strict=True):
        assert torch.equal(a.nan_to_num(), b.nan_to_num())
    assert by_settings[1].sum() > 20
    # the keyword solver overrides the settings' solver; the secant evaluates no gradient
    assert not torch.equal(find_intersections(*args, "secant", settings=newton)[2], by_settings[2])
    # warm_start=False: theta0 is ignored, the solve is cold
    theta0 = torch.where(by_settings[1], by_settings[0], torch.inf)
    warm = find_intersections(*args, theta0=theta0, settings=newton)
    cold = find_intersections(*args, theta0=theta0, settings=newton.replace(warm_start=False))
    assert warm[2].sum() < by_settings[2].sum()
    for a, b in zip(cold, by_settings, strict=True):
        assert torch.equal(a.nan_to_num(), b.nan_to_num())
    with pytest.raises(ValueError, match="finder: expected keys among"):
        find_intersections(*args, tolerance=1e-3)


# ------------------------------------------------------------------------- cold scan
class Waves:
    """z = z0 + sum_k a_k sin(k_k . xy + phi_k) with |grad z| <= sum_k a_k |k_k| = max_slope."""

    def __init__(self, z0: float, wavelengths: tuple[float, float], max_slope: float, seed: int):
        g = torch.Generator().manual_seed(seed)
        n = 6
        lam = wavelengths[0] + (wavelengths[1] - wavelengths[0]) * torch.rand(
            n, generator=g, dtype=torch.float64
        )
        ang = 2 * math.pi * torch.rand(n, generator=g, dtype=torch.float64)
        self.k = torch.stack([ang.cos(), ang.sin()], 1) * (2 * math.pi / lam).unsqueeze(1)
        self.phi = 2 * math.pi * torch.rand(n, generator=g, dtype=torch.float64)
        w = 0.5 + torch.rand(n, generator=g, dtype=torch.float64)
        self.a = w * max_slope / (w * self.k.norm(dim=1)).sum()
        self.z0 = z0

    def height_and_gradient(self, xy):
        k, a, phi = (t.to(xy.dtype) for t in (self.k, self.a, self.phi))
        arg = xy @ k.T + phi
        return self.z0 + torch.sin(arg) @ a, (torch.cos(arg) * a) @ k

    def height(self, xy):
        return self.height_and_gradient(xy)[0]


class Ridge:
    """A ridge along y on a flat floor ``z0``: trapezoid cross-section of slopes +-``slope``.

    It rises from ``x_foot`` to ``height`` above the floor, is flat for ``top`` m and falls
    back; its slope is at most ``slope`` everywhere (Lipschitz).
    """

    def __init__(self, z0: float, x_foot: float, height: float, top: float, slope: float):
        self.z0, self.x_foot, self.h, self.slope = z0, x_foot, height, slope
        self.x_back = x_foot + 2 * height / slope + top

    def height_and_gradient(self, xy):
        x = xy[:, 0]
        up, down = self.slope * (x - self.x_foot), self.slope * (self.x_back - x)
        h = torch.minimum(up, down).clamp(0.0, self.h)
        ramp = (h > 0) & (h < self.h)
        gx = torch.where(ramp, torch.where(up < down, self.slope, -self.slope), 0.0)
        return self.z0 + h, torch.stack([gx, torch.zeros_like(gx)], 1).to(xy.dtype)

    def height(self, xy):
        return self.height_and_gradient(xy)[0]


def _dense_reference(surface, sonar, R, r, side, limits, m: int = 2001):
    """First crossing from ``f`` on ``m`` angles in float64, refined by bisection.

    Returns ``theta (N,)`` (NaN: none in the beam, or the beam starts below ground), the
    number of entries into the ground along each arc and the width (rad) of the first
    stretch below ground (``inf`` where it reaches the beam's lower edge).
    """
    th = torch.linspace(*limits, m, dtype=torch.float64)
    n = sonar.shape[0]

    def f(theta, idx):
        p = arc_point(sonar[idx], R[idx], r[idx], theta, side[idx])
        return surface.height(p[:, :2]) - p[:, 2]

    rows = torch.arange(n).repeat_interleave(m)
    F = torch.cat(
        [f(t, i) for t, i in zip(th.repeat(n).split(200_000), rows.split(200_000), strict=True)]
    ).reshape(n, m)
    below = F >= 0
    entries = (~below[:, :-1] & below[:, 1:]).sum(1)
    has = below.any(1) & ~below[:, 0]
    e = below.int().argmax(1).clamp_min(1)
    after = (torch.arange(m) > e.unsqueeze(1)) & ~below
    # below ground to the beam's lower edge: as wide as any scan can see
    width = torch.where(after.any(1), th[after.int().argmax(1)] - th[e], torch.inf)
    a, b = th[e - 1], th[e]
    idx = torch.arange(n)
    for _ in range(60):
        mid = 0.5 * (a + b)
        down = f(mid, idx) >= 0
        a, b = torch.where(down, a, mid), torch.where(down, mid, b)
    return torch.where(has, b, torch.nan), entries, width


def _level_starboard_bins(n_pings: int, ranges: torch.Tensor, seed: int = 0):
    """Pings along y (heading north, roll/pitch within 1 deg), starboard (east) bins only."""
    g = torch.Generator().manual_seed(seed)
    y = torch.linspace(-20.0, 20.0, n_pings, dtype=torch.float64)
    pos = torch.stack([torch.zeros_like(y), y, torch.zeros_like(y)], 1)
    tilt = (torch.rand(n_pings, 2, generator=g, dtype=torch.float64) - 0.5) * math.radians(2.0)
    R = attitude_to_rotation(torch.zeros_like(y), tilt[:, 0], tilt[:, 1])
    nb = ranges.shape[0]
    pi = torch.arange(n_pings).repeat_interleave(nb)
    r = ranges.double().repeat(n_pings)
    return pos[pi], R[pi], r, torch.ones(n_pings * nb, dtype=torch.long)


# |f| <= 0.1 mm is a few mm along an arc that grazes the surface; other crossings of the
# same arc lie more than a grid spacing (> 0.5 m) away
SAME_CROSSING_MM = 5.0


def _points_mm(sonar, R, r, side, theta_a, theta_b):
    pa = arc_point(sonar, R, r, torch.nan_to_num(theta_a), side)
    pb = arc_point(sonar, R, r, torch.nan_to_num(theta_b), side)
    return (pa - pb).norm(dim=-1) * 1e3


@pytest.mark.parametrize("solver", ["newton", "secant", "bisection"])
def test_cold_scan_takes_the_crossing_in_front_of_an_occluding_ridge(solver):
    # A 4 m ridge (slopes 0.95 <= scan_max_slope) beside the track: arcs of 10.4-11.6 m
    # range enter its top or far side, leave through its front face (an occluded stretch)
    # and meet the floor again further down; the first crossing is on the ridge.
    surface = Ridge(-10.0, x_foot=5.0, height=4.0, top=3.0, slope=0.95)
    limits = (0.0, math.radians(80.0))
    spacing = (limits[1] - limits[0]) / 15  # default n_scan = 16
    sonar, R, r, side = _level_starboard_bins(6, torch.linspace(10.4, 11.6, 40))
    ref, entries, width = _dense_reference(surface, sonar, R, r, side, limits)
    occluded = (entries >= 2) & (width > spacing)
    assert occluded.sum() >= 30 and torch.isfinite(ref).all()
    theta, valid, _ = find_intersections(surface, sonar, R, r, side, limits, solver, tol_m=1e-4)
    assert valid.all()
    assert _points_mm(sonar, R, r, side, theta, ref)[width > spacing].max() < SAME_CROSSING_MM
    # on the ridge, not on the floor behind it
    p = arc_point(sonar, R, r, theta, side)
    assert (p[occluded, 2] > -10.0 + 0.5).all()
    # the plain grid scan (scan_max_slope = inf) takes the same crossings
    grid, _, _ = find_intersections(
        surface, sonar, R, r, side, limits, solver, tol_m=1e-4, scan_max_slope=math.inf
    )
    assert _points_mm(sonar, R, r, side, theta, grid).max() < SAME_CROSSING_MM


@pytest.mark.parametrize("kind", ["smooth", "rough"])
def test_cold_scan_matches_a_dense_reference_on_random_surfaces(kind):
    wavelengths, slope = {"smooth": ((20.0, 60.0), 0.3), "rough": ((2.0, 6.0), 0.9)}[kind]
    surface = Waves(-15.0, wavelengths, slope, seed=1)
    sonar, R, r, side = _bins(10, 15.0, torch.linspace(5.0, 45.0, 40), seed=2)
    spacing = (BEAM[1] - BEAM[0]) / 15
    ref, entries, width = _dense_reference(surface, sonar, R, r, side, BEAM)
    found = torch.isfinite(ref)
    assert found.sum() > 500 and (~found).sum() > 100  # near ranges never reach the floor
    wide = ~found | (width > spacing)  # no stretch below ground narrower than the grid
    assert wide.float().mean() > 0.99
    results = {}
    for solver in ("newton", "secant", "bisection"):
        theta, valid, n_iter = find_intersections(
            surface, sonar, R, r, side, BEAM, solver, tol_m=1e-4
        )
        assert torch.equal(valid[wide], found[wide])
        assert _points_mm(sonar, R, r, side, theta, ref)[valid & wide].max() < SAME_CROSSING_MM
        p = arc_point(sonar[valid], R[valid], r[valid], theta[valid], side[valid])
        assert (surface.height(p[:, :2]) - p[:, 2]).abs().max() <= 1e-4
        results[solver] = theta
        if solver != "bisection":  # evaluations per bin to 0.1 mm after the scan
            assert n_iter[valid].float().mean() <= {"smooth": 2.2, "rough": 3.5}[kind]
    # the three solvers agree with each other to the tolerance
    for solver in ("newton", "secant"):
        both = torch.isfinite(results[solver]) & torch.isfinite(results["bisection"])
        d = _points_mm(sonar, R, r, side, results[solver], results["bisection"])
        assert d[both].max() < SAME_CROSSING_MM


class _Counting:
    """Counts the points of height-only and height-and-gradient evaluations."""

    def __init__(self, surface) -> None:
        self.surface, self.heights, self.gradients = surface, 0, 0

    def height(self, xy):
        self.heights += xy.shape[0]
        return self.surface.height(xy)

    def height_and_gradient(self, xy):
        self.gradients += xy.shape[0]
        return self.surface.height_and_gradient(xy)


def test_cold_scan_cost_grid_vs_slope_bounded_steps():
    surface, spread, ranges = CASES["plane"]
    sonar, R, r, side = _bins(12, spread, ranges)
    theta_true, ok = surface.crossing(sonar, R, r, side)
    lo, hi = BEAM
    spacing = (hi - lo) / 15
    # scan_max_slope = inf: a plain grid scan of 16 angles, each bin up to (and including)
    # the first grid angle below ground, or all 16
    k_first = torch.ceil((theta_true - lo) / spacing).long()
    in_beam = ok & (theta_true > lo) & (theta_true <= hi)
    expected = torch.where(in_beam, k_first + 1, 16)
    grid = _Counting(surface)
    th_grid, v_grid, _ = find_intersections(
        grid, sonar, R, r, side, BEAM, "newton", tol_m=1e-4, scan_max_slope=math.inf
    )
    assert grid.heights == int(expected.sum())
    # slope-bounded steps (default scan_max_slope = 1): same crossings, far fewer heights;
    # the Newton refinement costs about the same
    march = _Counting(surface)
    th, valid, _ = find_intersections(march, sonar, R, r, side, BEAM, "newton", tol_m=1e-4)
    assert torch.equal(valid, v_grid)
    assert _points_mm(sonar, R, r, side, th, th_grid)[valid].max() < 0.5
    assert march.heights < 0.45 * grid.heights
    assert march.heights < 4.0 * sonar.shape[0]
    assert march.gradients < 1.15 * grid.gradients
    # the secant refinement evaluates no gradient at all
    secant = _Counting(surface)
    find_intersections(secant, sonar, R, r, side, BEAM, "secant", tol_m=1e-4)
    assert secant.gradients == 0
    assert secant.heights - march.heights < 3.0 * int(valid.sum())


@pytest.mark.slow
def test_benchmark_newton_vs_paper_gd_on_a_siren(capsys):
    """Speed-up of the bracketed Newton finder over the paper's descent at equal accuracy.

    A 5 x 128 SIREN fitted for a few hundred steps to a hilly surface; one batch of 64 pings
    x 2 heads x 256 bins. Every solver must reach |f| <= 1 mm; gradient descent gets its
    best step size of a sweep. Run: ``pytest tests/models/test_intersection.py -m slow -s``.
    """
    torch.manual_seed(0)
    siren = Siren(
        hidden=128, n_layers=5, omega0=30.0, bounds=(-60, -60, 60, 60), z_range=(-24, -16)
    )
    opt = torch.optim.Adam(siren.parameters(), lr=1e-4)
    for _ in range(300):
        xy = (torch.rand(4096, 2) * 2 - 1) * 60
        z = -20 + 1.5 * torch.sin(xy[:, 0] / 9) * torch.cos(xy[:, 1] / 13) + 0.02 * xy[:, 0]
        loss = (siren.height(xy) - z).abs().mean()
        opt.zero_grad()
        loss.backward()
        opt.step()
    siren.requires_grad_(False)
    sonar, R, r, side = _bins(64, 30.0, torch.linspace(8.0, 40.0, 256), seed=1)
    sonar[:, 2] = -8.0
    args = (siren, sonar.float(), R.float(), r.float(), side, BEAM)

    def timed(reps: int = 3, **kw):
        times = []
        for _ in range(reps):
            t = time.perf_counter()
            out = find_intersections(*args, tol_m=1e-3, **kw)
            times.append(time.perf_counter() - t)
        return sorted(times)[len(times) // 2], out

    t_newton, (th_n, v_n, it_n) = timed(solver="newton")
    # warm start as in training: last epoch's solution, +inf where there was no crossing
    warm = torch.where(v_n, th_n, torch.inf)
    t_warm, (th_w, v_w, it_w) = timed(solver="newton", theta0=warm)
    # the paper's descent with the best of a few step sizes (fewest iterations per bin)
    runs = {
        step: timed(1, solver="gd", gd_step=step, max_iter=1000) for step in (0.005, 0.01, 0.02)
    }
    step = min(runs, key=lambda k: (-int(runs[k][1][1].sum()), runs[k][0]))
    t_gd, (th_g, v_g, it_g) = runs[step]
    both = v_n & v_g
    agree = (th_n[both] - th_g[both]).abs().max().item()
    with capsys.disabled():
        print(
            f"\nbins {v_n.numel()}: newton cold {t_newton:.3f}s valid {v_n.float().mean():.3f} "
            f"evals/bin {it_n[v_n].float().mean():.2f} | newton warm {t_warm:.3f}s "
            f"evals/bin {it_w[v_w].float().mean():.2f} | gd (step {step}) {t_gd:.3f}s valid "
            f"{v_g.float().mean():.3f} iters/bin {it_g[v_g].float().mean():.1f} "
            f"max {it_g[v_g].max()} | speed-up cold {t_gd / t_newton:.1f}x warm "
            f"{t_gd / t_warm:.1f}x | max |dtheta| {agree:.2e} rad"
        )
    assert v_n.sum() >= v_g.sum()
    assert torch.equal(v_w, v_n)
    assert it_g[both].float().mean() > 5 * it_n[both].float().mean()


# ------------------------------------------------------------ neighbour start
def test_neighbour_guess_puts_unsolved_bins_at_their_rows_solved_depths():
    r = torch.tensor([10.0, 11.0, 12.0, 13.0, 14.0, 15.0])
    depth = 8.0  # flat ground 8 m below the sonar: theta = asin(8 / r) in every bin
    truth = torch.asin(depth / r)
    nan, inf = math.nan, math.inf
    rows = torch.tensor(
        [
            [nan, nan, float(truth[2]), nan, nan, nan],  # one solved bin: all follow it
            [float(truth[0]), nan, nan, nan, inf, nan],  # +inf kept; the last bin
            [nan] * 6,  # nothing solved: stays unknown
        ]
    )
    guess = neighbour_guess(rows, r)
    assert torch.allclose(guess[0], truth, atol=1e-6)
    assert torch.allclose(guess[1, :4], truth[:4], atol=1e-6)
    assert guess[1, 4] == inf and torch.allclose(guess[1, 5], truth[5], atol=1e-6)
    assert torch.isnan(guess[2]).all()
    # between two solved bins the depth is interpolated in range: bin 0 at 8 m, bin 4 at
    # 12 m -> bin 1 at 9 m, bin 3 at 11 m; beyond bin 4 its depth (12 m)
    steep = rows.clone()[1:2]
    steep[0, 4] = float(torch.asin(torch.tensor(12.0 / 14.0)))
    g = neighbour_guess(steep, r)[0]
    assert g[1] == pytest.approx(math.asin(9.0 / 11.0), abs=1e-6)
    assert g[3] == pytest.approx(math.asin(11.0 / 13.0), abs=1e-6)
    assert g[5] == pytest.approx(math.asin(12.0 / 15.0), abs=1e-6)
    # a depth a bin's arc cannot reach (12 m > 11 m range) stays unknown
    short = torch.tensor([[nan, float(torch.asin(torch.tensor(12.0 / 13.0)))]])
    assert torch.isnan(neighbour_guess(short, torch.tensor([11.0, 13.0]))[0, 0])
    with pytest.raises(ValueError, match=r"range_m: expected shape \(6,\), found \(5,\)"):
        neighbour_guess(rows, r[:5])


def test_seed_bins_take_every_stride_th_used_bin_of_blank_rows():
    use = torch.tensor([[1, 0, 1, 1, 0, 1, 1, 1], [1, 1, 1, 1, 1, 1, 1, 1]], dtype=torch.bool)
    seeds = seed_bins(use, torch.tensor([True, False]), 3)
    # used bins of row 0: 0, 2, 3, 5, 6, 7 -> every third from the first: 0 and 5
    assert seeds[0].nonzero().squeeze(-1).tolist() == [0, 5]
    assert not seeds[1].any()


def test_neighbour_start_replaces_cold_scans_with_the_same_crossings():
    from sss2bathy.models.arc_fit import arc_geometry

    # gently sloping ground, as a seabed is mostly: the flat guess is close, not exact
    surface, spread, ranges = Plane(-15.0, 0.02, -0.01), 15.0, torch.linspace(16.0, 45.0, 40)
    g = torch.Generator().manual_seed(5)
    n_pings, n_bins = 6, ranges.shape[0]
    xy = (torch.rand(n_pings, 2, generator=g) * 2 - 1) * spread
    batch = {
        "position": torch.cat([xy, torch.zeros(n_pings, 1)], 1),
        "rotation": attitude_to_rotation(
            torch.rand(n_pings, generator=g) * 6.28, torch.zeros(n_pings), torch.zeros(n_pings)
        ).float(),
        "range_m": ranges.float(),
        "line": torch.zeros(n_pings, dtype=torch.long),
        "index": torch.arange(n_pings),
    }
    calls = {"n": 0}

    class Counting(torch.nn.Module):
        def height(self, xy):
            calls["n"] += xy.shape[0]
            return surface.height(xy)

        def height_and_gradient(self, xy):
            return surface.height_and_gradient(xy)

    use = torch.ones(n_pings, 2, n_bins, dtype=torch.bool)
    first = torch.zeros_like(use)
    first[..., ::8] = True  # a first step solved every 8th bin
    results = {}
    for neighbour in (False, True):
        cache = torch.full((n_pings, 2, n_bins), torch.nan)
        settings = {"neighbour_start": neighbour, "tol_m": 1e-4}
        arc_geometry(Counting(), batch, first, BEAM, settings, cache)
        calls["n"] = 0
        geo, _ = arc_geometry(Counting(), batch, use & ~first, BEAM, settings, cache)
        results[neighbour] = (geo, calls["n"])
    (cold, n_cold), (near, n_near) = results[False], results[True]
    assert torch.equal(cold.bin, near.bin) and torch.equal(cold.ping, near.ping)
    assert torch.allclose(cold.points, near.points, atol=2e-4)  # the same crossings
    assert n_near < 0.75 * n_cold, (n_near, n_cold)  # warm brackets instead of scans


@pytest.mark.parametrize("kind", ["smooth", "rough"])
def test_seeded_rows_find_the_cold_crossings_with_fewer_evaluations(kind):
    # pings seen for the first time: every 8th used bin of a row is solved cold, the rest
    # start from them; the crossings are the cold scan's, for far fewer surface heights
    wavelengths, slope = {"smooth": ((20.0, 60.0), 0.3), "rough": ((4.0, 12.0), 0.6)}[kind]
    surface = _Counting(Waves(-15.0, wavelengths, slope, seed=1))
    n_pings, ranges = 10, torch.linspace(12.0, 45.0, 96)  # a few never reach the floor
    sonar_f, R_f, r_f, side_f = _bins(n_pings, 15.0, ranges, seed=2)
    n_bins = ranges.shape[0]
    sonar = sonar_f.reshape(n_pings, 2 * n_bins, 3)[:, 0]
    R = R_f.reshape(n_pings, 2 * n_bins, 3, 3)[:, 0]
    use = torch.rand(n_pings, 2, n_bins, generator=torch.Generator().manual_seed(3)) < 0.5
    use[0, 1] = False  # a row with nothing to solve
    rows_in = torch.full(use.shape, torch.nan, dtype=torch.float64)
    rows_in[1] = 0.3  # rows solved before (not blank): no seeds there
    out = {}
    for neighbour in (False, True):
        surface.heights = 0
        settings = {"neighbour_start": neighbour, "tol_m": 1e-4, "warm_start": True}
        rows, valid, n_iter = find_row_intersections(
            surface, sonar, R, ranges.double(), use, BEAM, rows_in, settings=settings
        )
        out[neighbour] = rows, valid, n_iter, surface.heights
    (_, valid_c, _, n_c), (rows_s, valid_s, it_s, n_s) = out[False], out[True]
    # unused bins keep their value; used bins without a crossing are +inf
    assert torch.equal(rows_s[~use].isnan(), rows_in[~use].isnan())
    assert (rows_s[use & ~valid_s] == math.inf).all() and not valid_s[~use].any()
    assert (it_s[~use] == 0).all() and (it_s[valid_s] >= 1).all()
    # the flat lists of the same bins, cold, for the reference
    pi, si, bi = use.nonzero(as_tuple=True)
    ref = _dense_reference(surface.surface, sonar[pi], R[pi], ranges.double()[bi], si, BEAM)[0]
    same = _points_mm(sonar[pi], R[pi], ranges.double()[bi], si, rows_s[use], ref)
    found = torch.isfinite(ref)
    assert torch.equal(valid_s[use], valid_c[use])
    agree = (same[found & valid_s[use]] < SAME_CROSSING_MM).float().mean()
    assert agree == 1.0, agree
    # a sixth of the bins have no crossing in the beam and are scanned to its end either
    # way; the rest take about 2/3 of the cold heights (README -> Performance)
    assert (~valid_s[use]).sum() > 100
    assert n_s < 0.82 * n_c, (n_s, n_c)
    # warm_start false: every bin cold, whatever neighbour_start says
    surface.heights = 0
    rows_w, valid_w, _ = find_row_intersections(
        surface, sonar, R, ranges.double(), use, BEAM, rows_in,
        settings={"neighbour_start": True, "warm_start": False, "tol_m": 1e-4},
    )  # fmt: skip
    assert torch.equal(valid_w, valid_c) and surface.heights > n_s
    with pytest.raises(ValueError, match=r"rows: expected shape \(10, 2, 96\), found \(10, 2, 5\)"):
        find_row_intersections(surface, sonar, R, ranges, use, BEAM, rows_in[..., :5])
    with pytest.raises(ValueError, match=r"use: expected a \(P, 2, B\) bool tensor"):
        find_row_intersections(surface, sonar, R, ranges, use.float(), BEAM)


def test_arc_geometry_without_neighbour_start_is_the_flat_warm_started_solve():
    # the row solver under arc_geometry changes nothing by default: the same crossings,
    # cache and statistics as find_intersections on the flat list of used bins
    from sss2bathy.models.arc_fit import arc_geometry

    surface = Waves(-15.0, (20.0, 60.0), 0.3, seed=1)
    n_pings, ranges = 6, torch.linspace(12.0, 45.0, 64)
    sonar_f, R_f, _, _ = _bins(n_pings, 15.0, ranges, seed=2)
    n_bins = ranges.shape[0]
    batch = {
        "position": sonar_f.reshape(n_pings, 2 * n_bins, 3)[:, 0].float(),
        "rotation": R_f.reshape(n_pings, 2 * n_bins, 3, 3)[:, 0].float(),
        "range_m": ranges,
        "line": torch.zeros(n_pings, dtype=torch.long),
        "index": torch.arange(n_pings),
    }
    cache_rows = torch.full((n_pings, 2, n_bins), torch.nan)
    cache_flat = cache_rows.clone()
    for step in range(3):
        use = torch.rand(cache_rows.shape, generator=torch.Generator().manual_seed(step)) < 0.5
        geo, stats = arc_geometry(surface, batch, use, BEAM, {}, cache_rows)
        pi, si, bi = use.nonzero(as_tuple=True)
        theta, valid, n_iter = find_intersections(
            surface, batch["position"][pi], batch["rotation"][pi], ranges[bi], si, BEAM,
            theta0=cache_flat[pi, si, bi],
        )  # fmt: skip
        cache_flat[pi, si, bi] = torch.where(valid, theta, torch.inf)
        assert torch.equal(geo.theta, theta[valid])
        assert torch.equal(cache_rows.nan_to_num(7.0), cache_flat.nan_to_num(7.0))
        assert float(stats["finder_iters"]) == pytest.approx(float(n_iter.float().mean()))
