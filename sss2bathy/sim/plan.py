"""Survey planning: lawnmower lines in two perpendicular sets, vehicle motion, navigation.

The ``main`` set runs along ``plan.main_axis``, the ``cross`` set perpendicular to it;
within a set consecutive lines alternate direction (lawnmower). Test lines are spread
evenly through both sets, half in each (the paper's 12 test lines, half perpendicular to
the other half). Every line is placed so that its whole swath stays on the terrain, and
:func:`validate_swath` checks it ping by ping from the actual poses.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from sss2bathy.geometry import attitude_to_rotation
from sss2bathy.sim.config import PlanParams, SonarParams
from sss2bathy.sim.sonar import fan_basis
from sss2bathy.sim.terrain import Terrain, smooth_noise_1d


class SwathOutsideTerrainError(ValueError):
    """A line's swath (or the line itself) leaves the terrain grid."""


@dataclass
class PlannedLine:
    """One planned line with its true and recorded navigation.

    Attributes:
        name: line name.
        split: ``train`` or ``test``.
        line_set: ``main`` or ``cross``.
        heading_rad: nominal heading (clockwise from North).
        time_s: ``(P,)`` ping times.
        position: ``(P, 3)`` true sonar positions (m).
        rotation: ``(P, 3, 3)`` true vehicle -> world rotations.
        altitude_m: ``(P,)`` true altitude above the seafloor directly below.
        nav_position: ``(P, 3)`` recorded positions (true + navigation noise).
        nav_rotation: ``(P, 3, 3)`` recorded rotations (true + attitude noise).
    """

    name: str
    split: str
    line_set: str
    heading_rad: float
    time_s: np.ndarray
    position: np.ndarray
    rotation: np.ndarray
    altitude_m: np.ndarray
    nav_position: np.ndarray
    nav_rotation: np.ndarray


def _line_offsets(n: int, lo: float, hi: float, spacing: float | None, set_name: str) -> np.ndarray:
    """Cross-track positions of ``n`` equally spaced lines centred in ``[lo, hi]``."""
    if n == 0:
        return np.zeros(0)
    if hi < lo:
        raise SwathOutsideTerrainError(
            f"data.survey.terrain.size_m: too small for the swath of the {set_name} lines "
            f"(no room between {lo:.1f} m and {hi:.1f} m); enlarge the terrain or reduce "
            "data.survey.sonar.max_range_m"
        )
    if spacing is None:
        spacing = (hi - lo) / (n - 1) if n > 1 else 0.0
    elif (n - 1) * spacing > hi - lo + 1e-9:
        raise ValueError(
            f"data.survey.plan.line_spacing_m: expected <= {(hi - lo) / max(n - 1, 1):.2f} m so "
            f"that {n} {set_name} lines keep their swath on the terrain, found {spacing}"
        )
    return (lo + hi) / 2 + (np.arange(n) - (n - 1) / 2) * spacing


def _test_indices(n_lines: int, n_test: int) -> set[int]:
    """``n_test`` indices spread evenly over ``range(n_lines)``."""
    return {int((j + 0.5) * n_lines / n_test) for j in range(n_test)}


def plan_survey(
    plan: PlanParams, sonar: SonarParams, terrain: Terrain, rng: np.random.Generator
) -> list[PlannedLine]:
    """Plan every line (true and recorded navigation); raise if a swath leaves the terrain.

    Axis-aligned lawnmower sets over the whole rectangle, or, with ``plan.heading_rad`` or a
    terrain with holes (a real grid), lines at a heading clipped to the valid footprint
    (:func:`footprint_layout`).
    """
    if plan.heading_rad is not None or terrain.no_seabed is not None:
        return _plan_footprint(plan, sonar, terrain, rng)
    width, height = terrain.extent_m
    z_top = float(terrain.heights.max())
    r_max = sonar.max_range_m
    if plan.mount == "hull":
        clearance = -plan.sonar_depth_m - z_top
        reach = math.sqrt(max(r_max**2 - max(clearance, 0.0) ** 2, 0.0))
    else:
        reach = r_max
    motion = max(plan.roll_rad, plan.pitch_rad, plan.yaw_rad, plan.nav_attitude_noise_rad)
    across = reach + plan.margin_m + 4 * plan.nav_position_noise_m
    along = plan.margin_m + r_max * math.sin(min(4 * motion, math.pi / 2)) + 1.0

    n_test_cross = plan.n_test // 2
    n_test_main = plan.n_test - n_test_cross
    n_train_cross = int(round(plan.n_train * plan.train_cross_fraction))
    n_train_main = plan.n_train - n_train_cross
    # main lines run along x (offsets in y) when main_axis == "x"
    extent = {"x": width, "y": height}
    other = {"x": "y", "y": "x"}
    sets = [
        ("main", plan.main_axis, n_train_main, n_test_main),
        ("cross", other[plan.main_axis], n_train_cross, n_test_cross),
    ]
    layout = []
    for set_name, axis, n_train, n_test in sets:
        n = n_train + n_test
        span = extent[other[axis]]
        offsets = _line_offsets(n, across, span - across, plan.line_spacing_m, set_name)
        tests = _test_indices(n, n_test) if n_test else set()
        for k, off in enumerate(offsets):
            layout.append((set_name, axis, off, k % 2 == 1, "test" if k in tests else "train"))

    lines = []
    t0 = 0.0
    for i, (set_name, axis, offset, reverse, split) in enumerate(layout):
        a0, a1 = along, extent[axis] - along
        if a1 - a0 < plan.speed_mps / plan.ping_rate_hz:
            raise SwathOutsideTerrainError(
                f"data.survey.terrain.size_m: {extent[axis]} m along {axis} leaves no room for "
                f"a line after the {along:.1f} m end margins"
            )
        line = _plan_line(
            f"line_{i:03d}", split, set_name, axis, offset, a0, a1, reverse, t0,
            plan, terrain, rng,
        )  # fmt: skip
        validate_swath(line.name, line.position, line.rotation, sonar, terrain)
        lines.append(line)
        t0 = float(line.time_s[-1]) + plan.turn_time_s
    return lines


def _swath_reach(plan: PlanParams, sonar: SonarParams, terrain: Terrain) -> float:
    """Horizontal reach of the swath (m) from the track, for planning."""
    r_max = sonar.max_range_m
    if plan.mount != "hull":
        return r_max
    clearance = -plan.sonar_depth_m - float(terrain.heights.max())
    return math.sqrt(max(r_max**2 - max(clearance, 0.0) ** 2, 0.0))


def footprint_clearance(terrain: Terrain) -> np.ndarray:
    """``(ny, nx)`` distance (m) from each cell centre to the nearest cell without seabed or
    beyond the grid's edge (the footprint's inside distance)."""
    from scipy.ndimage import distance_transform_edt

    padded = np.pad(terrain.seabed, 1, constant_values=False)
    return distance_transform_edt(padded)[1:-1, 1:-1] * terrain.cell_m


def footprint_heading(terrain: Terrain) -> float:
    """Heading (rad, clockwise from North, in [0, pi)) of the valid footprint's long axis."""
    iy, ix = np.nonzero(terrain.seabed)
    xy = np.stack([ix, iy], 1) * terrain.cell_m
    cov = np.cov((xy - xy.mean(0)).T)
    w, v = np.linalg.eigh(cov)
    ex, ey = v[:, int(np.argmax(w))]
    return float(math.atan2(ex, ey) % math.pi)


def _longest_run(ok: np.ndarray) -> tuple[int, int]:
    """``(start, stop)`` of the longest run of True in ``ok`` (``(0, 0)``: none)."""
    if not ok.any():
        return 0, 0
    edges = np.diff(np.concatenate([[0], ok.astype(np.int8), [0]]))
    starts, stops = np.flatnonzero(edges == 1), np.flatnonzero(edges == -1)
    k = int(np.argmax(stops - starts))
    return int(starts[k]), int(stops[k])


def footprint_layout(
    heading: float,
    n_lines: int,
    spacing: float | None,
    clearance_m: float,
    step_m: float,
    min_line_m: float,
    terrain: Terrain,
    set_name: str,
) -> list[tuple[np.ndarray, np.ndarray]]:
    """Tracks of ``n_lines`` parallel lines at ``heading`` inside the valid footprint.

    Each track is the longest stretch (points ``step_m`` apart) whose points are at least
    ``clearance_m`` inside the footprint (:func:`footprint_clearance`), kept when it is
    ``min_line_m`` long. Offsets are ``spacing`` apart around the middle of the footprint's
    usable width (None: spread over it).

    Returns:
        ``[(x, y), ...]`` track coordinates (m) in order of their cross-track offset, each
        running along ``heading``.
    """
    if n_lines == 0:
        return []
    clear = footprint_clearance(terrain)
    cell = terrain.cell_m
    ny, nx = clear.shape
    along = np.array([math.sin(heading), math.cos(heading)])
    across = np.array([math.cos(heading), -math.sin(heading)])
    usable = np.argwhere(clear >= clearance_m)[:, ::-1] * cell
    if len(usable) == 0:
        raise SwathOutsideTerrainError(
            f"data.survey.plan.margin_m: no point of the terrain's footprint lies "
            f"{clearance_m:.1f} m inside its edge; lower the margin (or the swath reach)"
        )
    centre = usable.mean(0)
    off = (usable - centre) @ across
    ts = (usable - centre) @ along
    t = np.arange(ts.min() - step_m, ts.max() + step_m, step_m)

    def track(o: float) -> tuple[np.ndarray, np.ndarray]:
        pts = centre + o * across + t[:, None] * along
        ix, iy = np.rint(pts[:, 0] / cell).astype(int), np.rint(pts[:, 1] / cell).astype(int)
        inside = (ix >= 0) & (ix < nx) & (iy >= 0) & (iy < ny)
        ok = np.zeros(len(t), bool)
        ok[inside] = clear[iy[inside], ix[inside]] >= clearance_m
        a, b = _longest_run(ok)
        return pts[a:b, 0], pts[a:b, 1]

    def long_enough(o: float) -> bool:
        x, _ = track(o)
        return (len(x) - 1) * step_m >= min_line_m

    candidates = np.arange(off.min(), off.max() + cell / 2, cell / 2)
    fit = [o for o in candidates if long_enough(o)]
    if not fit:
        raise SwathOutsideTerrainError(
            f"data.survey.plan.min_line_m: no {set_name} line at heading "
            f"{math.degrees(heading):.1f} deg is {min_line_m} m long inside the footprint; "
            "lower min_line_m or margin_m"
        )
    lo, hi = min(fit), max(fit)
    if spacing is None:
        offsets = np.linspace(lo, hi, n_lines + 2)[1:-1] if n_lines > 1 else [(lo + hi) / 2]
    else:
        mid = (lo + hi) / 2
        k = np.arange(-int((hi - lo) / spacing) - 1, int((hi - lo) / spacing) + 2)
        grid = [mid + j * spacing for j in k if lo <= mid + j * spacing <= hi]
        grid = [o for o in grid if long_enough(o)]
        if len(grid) < n_lines:
            raise ValueError(
                f"data.survey.plan.line_spacing_m: expected a spacing that fits {n_lines} "
                f"{set_name} lines of >= {min_line_m} m in the footprint, found {spacing} m "
                f"(room for {len(grid)})"
            )
        offsets = sorted(sorted(grid, key=lambda o: abs(o - mid))[:n_lines])
    tracks = [track(float(o)) for o in offsets]
    short = [i for i, (x, _) in enumerate(tracks) if (len(x) - 1) * step_m < min_line_m]
    if short:
        raise SwathOutsideTerrainError(
            f"data.survey.plan.min_line_m: {len(short)} of {n_lines} {set_name} lines spread "
            f"over the footprint are shorter than {min_line_m} m; set plan.line_spacing_m, "
            "fewer lines or a lower min_line_m"
        )
    return tracks


def _plan_footprint(
    plan: PlanParams, sonar: SonarParams, terrain: Terrain, rng: np.random.Generator
) -> list[PlannedLine]:
    heading = plan.heading_rad if plan.heading_rad is not None else footprint_heading(terrain)
    grid_terrain = terrain.no_seabed is not None
    # a grid's swath may run off its footprint (no hit there); procedural swaths stay on
    clearance = plan.margin_m
    if not grid_terrain:
        clearance += _swath_reach(plan, sonar, terrain) + 4 * plan.nav_position_noise_m
    clearance = max(clearance, terrain.cell_m)
    step = plan.speed_mps / plan.ping_rate_hz
    n_test_cross = plan.n_test // 2
    n_train_cross = int(round(plan.n_train * plan.train_cross_fraction))
    sets = [
        ("main", heading, plan.n_train - n_train_cross, plan.n_test - n_test_cross),
        ("cross", heading + math.pi / 2, n_train_cross, n_test_cross),
    ]
    lines: list[PlannedLine] = []
    t0 = 0.0
    for set_name, set_heading, n_train, n_test in sets:
        n = n_train + n_test
        tracks = footprint_layout(
            set_heading, n, plan.line_spacing_m, clearance, step, plan.min_line_m, terrain,
            set_name,
        )  # fmt: skip
        tests = _test_indices(n, n_test) if n_test else set()
        for k, (x, y) in enumerate(tracks):
            line_heading = set_heading % (2 * math.pi)
            if k % 2 == 1:
                x, y = x[::-1], y[::-1]
                line_heading = (set_heading + math.pi) % (2 * math.pi)
            line = _fly_line(
                f"line_{len(lines):03d}", "test" if k in tests else "train", set_name,
                np.asarray(x), np.asarray(y), line_heading, t0, plan, terrain, rng,
            )  # fmt: skip
            validate_swath(line.name, line.position, line.rotation, sonar, terrain)
            lines.append(line)
            t0 = float(line.time_s[-1]) + plan.turn_time_s
    return lines


def _plan_line(
    name: str,
    split: str,
    line_set: str,
    axis: str,
    offset: float,
    a0: float,
    a1: float,
    reverse: bool,
    t0: float,
    plan: PlanParams,
    terrain: Terrain,
    rng: np.random.Generator,
) -> PlannedLine:
    step = plan.speed_mps / plan.ping_rate_hz
    n = int(math.floor((a1 - a0) / step)) + 1
    along = a0 + step * np.arange(n)
    if reverse:
        along = along[::-1]
    if axis == "x":
        x, y = along, np.full(n, offset)
        heading = 3 * math.pi / 2 if reverse else math.pi / 2
    else:
        x, y = np.full(n, offset), along
        heading = math.pi if reverse else 0.0
    return _fly_line(name, split, line_set, x, y, heading, t0, plan, terrain, rng)


def _fly_line(
    name: str,
    split: str,
    line_set: str,
    x: np.ndarray,
    y: np.ndarray,
    heading: float,
    t0: float,
    plan: PlanParams,
    terrain: Terrain,
    rng: np.random.Generator,
) -> PlannedLine:
    """A track ``(x, y)`` flown at ``heading``: motion, height (mount), navigation noise."""
    n = len(x)
    time_s = t0 + np.arange(n) / plan.ping_rate_hz
    step = plan.speed_mps / plan.ping_rate_hz

    corr = plan.motion_period_s * plan.ping_rate_hz / 4
    roll = plan.roll_rad * smooth_noise_1d(rng, n, corr)
    pitch = plan.pitch_rad * smooth_noise_1d(rng, n, corr)
    yaw = plan.yaw_rad * smooth_noise_1d(rng, n, corr)
    rotation = attitude_to_rotation(heading + yaw, pitch, roll)

    floor = terrain.sample_heights(x, y)
    if plan.mount == "hull":
        z = np.full(n, -plan.sonar_depth_m)
    else:
        from scipy.ndimage import gaussian_filter1d

        sigma = plan.altitude_smoothing_m / step
        smooth = gaussian_filter1d(floor, sigma, mode="nearest") if sigma > 0.5 else floor
        z = smooth + plan.altitude_m
    position = np.stack([x, y, z], axis=1)
    altitude = z - floor
    low = np.flatnonzero(altitude < plan.min_altitude_m)
    if low.size:
        k = int(low[0])
        raise ValueError(
            f"data.survey.plan.min_altitude_m: expected every altitude >= {plan.min_altitude_m} m, "
            f"found {altitude[k]:.2f} m on {name} at ping {k} ({x[k]:.1f}, {y[k]:.1f}); raise "
            "terrain.mean_depth_m or lower plan.sonar_depth_m"
        )

    nav_corr = plan.nav_noise_correlation_s * plan.ping_rate_hz / 4
    nav_position = position.copy()
    nav_rotation = rotation
    if plan.nav_position_noise_m > 0:
        for k in range(2):
            nav_position[:, k] += plan.nav_position_noise_m * smooth_noise_1d(rng, n, nav_corr)
    if plan.nav_attitude_noise_rad > 0:
        e = [plan.nav_attitude_noise_rad * smooth_noise_1d(rng, n, nav_corr) for _ in range(3)]
        nav_rotation = attitude_to_rotation(heading + yaw + e[0], pitch + e[1], roll + e[2])
    return PlannedLine(
        name, split, line_set, heading, time_s, position, rotation, altitude,
        nav_position, np.asarray(nav_rotation),
    )  # fmt: skip


def validate_swath(
    name: str,
    positions: np.ndarray,
    rotations: np.ndarray,
    sonar: SonarParams,
    terrain: Terrain,
    n_angles: int = 48,
) -> None:
    """Raise :class:`SwathOutsideTerrainError` if any ping could see beyond the terrain.

    For each ping, side and a fan of depression angles over the whole simulated fan, the
    farthest point where the ray could meet the seabed within ``max_range`` (between the
    terrain's highest and lowest heights) must lie on the grid. On a grid terrain (holes,
    an irregular footprint) only the track is checked: it must be over seabed; swath bins
    beyond the footprint are masked as no hit.
    """
    width, height = terrain.extent_m
    z_top, z_bottom = float(terrain.heights.max()), float(terrain.heights.min())
    positions = np.asarray(positions, dtype=np.float64)
    if terrain.no_seabed is not None:  # a grid terrain: the track must be over seabed
        ix = np.rint(positions[:, 0] / terrain.cell_m).astype(np.int64)
        iy = np.rint(positions[:, 1] / terrain.cell_m).astype(np.int64)
        ny, nx = terrain.heights.shape
        inside = (ix >= 0) & (ix < nx) & (iy >= 0) & (iy < ny)
        on = np.zeros(len(ix), bool)
        on[inside] = terrain.seabed[iy[inside], ix[inside]]
        if not on.all():
            k = int(np.argmin(on))
            raise SwathOutsideTerrainError(
                f"line '{name}': ping {k} at ({positions[k, 0]:.1f}, {positions[k, 1]:.1f}) m "
                "is not over the grid's valid footprint"
            )
        return
    outside = (
        (positions[:, 0] < 0) | (positions[:, 0] > width)
        | (positions[:, 1] < 0) | (positions[:, 1] > height)
    )  # fmt: skip
    if outside.any():
        k = int(np.argmax(outside))
        raise SwathOutsideTerrainError(
            f"line '{name}': ping {k} at ({positions[k, 0]:.1f}, {positions[k, 1]:.1f}) m lies "
            f"outside the terrain [0, {width:.1f}] x [0, {height:.1f}] m"
        )
    theta = np.linspace(math.radians(0.2), math.pi / 2 + math.radians(15), n_angles)
    e_out, e_down = fan_basis(np.asarray(rotations, dtype=np.float64))
    d = np.cos(theta)[:, None] * e_out[:, :, None] + np.sin(theta)[:, None] * e_down[:, :, None]
    s = positions[:, None, None, :]
    dz = np.minimum(d[..., 2], -1e-9)
    t_top = np.clip((s[..., 2] - z_top) / -dz, 0, None)
    t_far = np.minimum(sonar.max_range_m, np.clip((s[..., 2] - z_bottom) / -dz, 0, None))
    relevant = (d[..., 2] < 0) & (t_top <= sonar.max_range_m)
    p = s + t_far[..., None] * d
    bad = relevant & (
        (p[..., 0] < 0) | (p[..., 0] > width) | (p[..., 1] < 0) | (p[..., 1] > height)
    )
    if bad.any():
        k, sd, j = (int(v[0]) for v in np.nonzero(bad))
        raise SwathOutsideTerrainError(
            f"line '{name}': the {('port', 'starboard')[sd]} swath of ping {k} reaches "
            f"({p[k, sd, j, 0]:.1f}, {p[k, sd, j, 1]:.1f}) m, outside the terrain "
            f"[0, {width:.1f}] x [0, {height:.1f}] m; enlarge data.survey.terrain.size_m, "
            "reduce data.survey.sonar.max_range_m or move the line inwards"
        )
