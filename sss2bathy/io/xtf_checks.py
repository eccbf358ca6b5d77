"""Plausibility checks of an XTF import: pure functions on the per-ping arrays of ``read_xtf``.

Each check returns numbers (and masks); ``read_xtf`` turns them into one WARNING per repair or
one :class:`~sss2bathy.survey.SurveyFormatError` per refusal.

* :func:`check_altimeter` — the altimeter against the first bottom return: a constant offset
  (a lever arm between altimeter and transducers, or the detector's pick) and its spread and
  drift; or, where the first return is the edge of the vertical beam (nadir outside the beam,
  so the first echo comes at ``altitude / sin(upper beam edge)``), a scale.
* :func:`implausible_altitude` — altimeter values beyond the slant range, or jumping away from
  their neighbours while disagreeing with the first return.
* :func:`speed_outliers` — fixes that moved faster than a vehicle can.
* :func:`reversed_heading_runs` — heading ~180 degrees from the course over ground (a
  port/starboard swap).
* :func:`nav_units_mismatch` — degrees labelled as metres (or metres labelled as degrees).
* :func:`beam_vs_data` — where the flat-seabed beam limits of the configured tilt / beam width
  fall against the seabed return seen in the waterfall.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy.ndimage import median_filter
from scipy.stats import theilslopes

from sss2bathy.geometry.seabed import flat_seabed_depression
from sss2bathy.io.bottom import running_median

__all__ = [
    "AltimeterCheck",
    "beam_vs_data",
    "check_altimeter",
    "course_over_ground",
    "implausible_altitude",
    "nav_units_mismatch",
    "reversed_heading_runs",
    "robust_sigma",
    "runs",
    "speed_outliers",
]

#: MAD -> standard deviation of a normal distribution
MAD_TO_SIGMA = 1.4826
#: fewest pings with both an altimeter value and a first return for the cross-check
MIN_PINGS_BOTH = 10


def robust_sigma(x: np.ndarray) -> float:
    """``1.4826 * median(|x - median(x)|)`` of the finite values (0 for fewer than 2)."""
    x = np.asarray(x, np.float64)
    x = x[np.isfinite(x)]
    if x.size < 2:
        return 0.0
    return float(MAD_TO_SIGMA * np.median(np.abs(x - np.median(x))))


def _theil_sen(y: np.ndarray, x: np.ndarray, max_points: int = 400) -> tuple[float, float]:
    """Robust ``(slope, intercept)`` of ``y ~ x`` (Theil-Sen on at most ``max_points`` evenly
    spaced samples; 0 slope when ``x`` does not vary)."""
    y, x = np.asarray(y, np.float64), np.asarray(x, np.float64)
    if y.size > max_points:
        keep = np.linspace(0, y.size - 1, max_points).round().astype(int)
        y, x = y[keep], x[keep]
    if y.size < 2 or np.ptp(x) == 0:
        return 0.0, float(np.median(y)) if y.size else 0.0
    slope, intercept, _, _ = theilslopes(y, x)
    return float(slope), float(intercept)


def runs(mask: np.ndarray) -> list[tuple[int, int]]:
    """``[(first, last)]`` index ranges (inclusive) of the True runs of a 1-D mask."""
    m = np.concatenate([[False], np.asarray(mask, bool), [False]])
    d = np.diff(m.astype(np.int8))
    return list(zip(np.flatnonzero(d == 1), np.flatnonzero(d == -1) - 1, strict=True))


# ----------------------------------------------------------------------------- altitude
@dataclass(frozen=True)
class AltimeterCheck:
    """The altimeter against the first bottom return over the pings having both.

    Attributes:
        n: pings with both.
        offset_m: median of ``altimeter - first return`` (m).
        sigma_m: robust spread (MAD sigma) of ``altimeter - first return`` (m).
        drift_m: robust linear trend of ``altimeter - first return`` over the line (m, last
            minus first ping); ``drift_per_100_m`` per 100 pings.
        scale, intercept_m: robust fit ``first return = scale * altimeter + intercept``.
        scale_sigma_m, scale_drift_m: spread and drift of that fit's residual (m).
        max_scale: the largest ``scale`` the beam geometry explains.
        model: ``"offset"`` (one offset explains the disagreement within the tolerance),
            ``"beam_edge"`` (a scale within ``max_scale`` does: the first return is the edge
            of the vertical beam) or ``None`` (neither: the file is refused).
    """

    n: int
    offset_m: float
    sigma_m: float
    drift_m: float
    drift_per_100_m: float
    scale: float
    intercept_m: float
    scale_sigma_m: float
    scale_drift_m: float
    max_scale: float
    model: str | None

    @property
    def model_sigma_m(self) -> float:
        """Spread of the explaining model's residual (the offset's where none explains it)."""
        return self.scale_sigma_m if self.model == "beam_edge" else self.sigma_m

    def expected_altimeter(self, first_return_m: np.ndarray) -> np.ndarray:
        """The altimeter value the model expects from a first return."""
        fr = np.asarray(first_return_m, np.float64)
        if self.model == "beam_edge" and self.scale > 0:
            return (fr - self.intercept_m) / self.scale
        return fr + self.offset_m


def max_beam_edge_scale(tilt_rad: float, beam_width_rad: float) -> float:
    """Largest ``first return / altitude`` a flat seabed explains: ``1 / sin(upper beam edge)``
    (1 when nadir is inside the beam), widened by 25 % for pitch, roll and the beam's
    roll-off."""
    top = min(max(tilt_rad + beam_width_rad / 2, math.radians(10.0)), math.pi / 2)
    return 1.25 / math.sin(top)


def check_altimeter(
    altimeter_m: np.ndarray,
    first_return_m: np.ndarray,
    time_s: np.ndarray,
    tolerance_m: float | None,
    max_scale: float,
) -> AltimeterCheck | None:
    """Offset, spread and drift of ``altimeter - first return`` (None: fewer than
    :data:`MIN_PINGS_BOTH` pings with both).

    The disagreement is explained when, within ``tolerance_m``, either one offset does
    (spread and drift of the difference) or a beam-edge scale does (spread and drift of the
    residual of ``first return = scale * altimeter + intercept`` with ``scale`` in
    ``[0.9, max_scale]``). ``tolerance_m=None``: the better of the two, never refused.
    """
    alt = np.asarray(altimeter_m, np.float64)
    fr = np.asarray(first_return_m, np.float64)
    t = np.asarray(time_s, np.float64)
    both = np.isfinite(alt) & np.isfinite(fr)
    n = int(both.sum())
    if n < MIN_PINGS_BOTH:
        return None
    a, f, tt = alt[both], fr[both], t[both]
    d = a - f
    offset = float(np.median(d))
    slope_t, _ = _theil_sen(d, tt)
    span = float(tt[-1] - tt[0])
    dt_ping = float(np.median(np.diff(t))) if t.size > 1 else 0.0
    scale, intercept = _theil_sen(f, a)
    resid = f - (scale * a + intercept)
    rslope, _ = _theil_sen(resid, tt)
    sigma, drift = robust_sigma(d), slope_t * span
    s_sigma, s_drift = robust_sigma(resid), rslope * span
    offset_fits = (sigma, abs(drift))
    scale_fits = (s_sigma, abs(s_drift))
    scale_ok = 0.9 <= scale <= max_scale
    if tolerance_m is None:
        model = "beam_edge" if scale_ok and max(scale_fits) < max(offset_fits) else "offset"
    elif max(offset_fits) <= tolerance_m:
        model = "offset"
    elif scale_ok and max(scale_fits) <= tolerance_m:
        model = "beam_edge"
    else:
        model = None
    return AltimeterCheck(
        n=n,
        offset_m=offset,
        sigma_m=sigma,
        drift_m=drift,
        drift_per_100_m=slope_t * dt_ping * 100.0,
        scale=scale,
        intercept_m=intercept,
        scale_sigma_m=s_sigma,
        scale_drift_m=s_drift,
        max_scale=max_scale,
        model=model,
    )


def implausible_altitude(
    altitude_m: np.ndarray,
    ok: np.ndarray,
    first_return_m: np.ndarray,
    check: AltimeterCheck | None,
    max_range_m: float,
    floor_m: float = 1.0,
    window: int = 101,
) -> dict[str, np.ndarray]:
    """``(P,)`` masks of altimeter values to reject (among ``ok``).

    * ``beyond_range``: above the recording's slant range (the seabed would not be in it);
    * ``jump``, where the ping has a first return: runs of pings whose altimeter minus the
      value the first return implies (:meth:`AltimeterCheck.expected_altimeter`; the seabed's
      relief cancels) leaves the running median of ``window`` pings by more than
      ``max(4 sigma, floor_m)`` (sigma: the robust spread of those deviations), and at whose
      edges the altimeter steps more than the first return does (else the detector jumped,
      not the altimeter); without a first return (or a check), farther than
      ``max(4 sigma, 3 floor_m)`` from the running median of the altimeter itself.
    """
    alt = np.asarray(altitude_m, np.float64)
    fr = np.asarray(first_return_m, np.float64)
    ok = np.asarray(ok, bool)
    beyond = ok & (alt > max_range_m)
    rest = ok & ~beyond
    jump = np.zeros_like(rest)
    with_fr = rest & np.isfinite(fr) if check is not None else np.zeros_like(rest)
    alone = rest & ~with_fr
    if alone.any():
        dev = alt - running_median(alt, rest, window, mode="nearest", fill=np.nan)
        limit = max(4.0 * robust_sigma(dev[rest]), 3.0 * floor_m)
        jump |= alone & (np.abs(dev) > limit)
    idx = np.flatnonzero(with_fr)
    if idx.size >= 3:
        expected = check.expected_altimeter(fr)
        res = (alt - expected)[idx]
        dev = res - median_filter(
            res, size=min(window, 2 * ((idx.size - 1) // 2) + 1), mode="nearest"
        )
        flag = np.abs(dev) > max(4.0 * robust_sigma(dev), floor_m)
        for a, b in runs(flag):
            edges = [(a - 1, a)] if a > 0 else []
            edges += [(b, b + 1)] if b < idx.size - 1 else []
            if not edges:
                continue
            step_alt = sum(abs(alt[idx[i]] - alt[idx[j]]) for i, j in edges)
            step_fr = sum(abs(expected[idx[i]] - expected[idx[j]]) for i, j in edges)
            if step_alt > step_fr:
                jump[idx[a : b + 1]] = True
    return {"beyond_range": beyond, "jump": jump}


# ----------------------------------------------------------------------------- navigation
def speed_outliers(
    t: np.ndarray, xy: np.ndarray, valid: np.ndarray, max_speed_mps: float, window: int = 9
) -> tuple[np.ndarray, np.ndarray]:
    """Fixes that left the track faster than ``max_speed_mps``.

    A valid fix is an outlier when its distance to the running median of ``window`` valid
    fixes exceeds ``max(5 x the line's median such distance / 0.6745, 1 m)`` (noise) and that
    distance, over the time to its nearest valid neighbour, exceeds ``max_speed_mps``.

    Returns:
        ``(outlier, implied_speed)``: ``(P,)`` mask and the implied speed (m/s; NaN where
        not valid).
    """
    valid = np.asarray(valid, bool)
    idx = np.flatnonzero(valid)
    out = np.zeros(valid.shape, bool)
    speed = np.full(valid.shape, np.nan)
    if idx.size < 3:
        return out, speed
    win = min(window, 2 * ((idx.size - 1) // 2) + 1)
    med = np.stack([median_filter(xy[idx, k], size=win, mode="nearest") for k in (0, 1)], 1)
    dev = np.linalg.norm(xy[idx] - med, axis=1)
    ti = t[idx]
    gaps = np.diff(ti)
    near = np.minimum(np.r_[np.inf, gaps], np.r_[gaps, np.inf])
    speed[idx] = dev / np.maximum(near, 1e-3)
    noise = max(5.0 * MAD_TO_SIGMA * float(np.median(dev)), 1.0)
    out[idx] = (dev > noise) & (speed[idx] > max_speed_mps)
    return out, speed


def course_over_ground(
    t: np.ndarray,
    xy: np.ndarray,
    window_s: float = 10.0,
    min_speed_mps: float = 0.3,
    min_distance_m: float = 2.0,
) -> tuple[np.ndarray, np.ndarray]:
    """``(course_deg, valid)`` per ping: the direction of the displacement over ``window_s``
    centred on the ping (clockwise from North); valid where the vehicle moved at least
    ``min_distance_m`` at ``min_speed_mps`` or more (robust to fixes slower than pings)."""
    t = np.asarray(t, np.float64)
    j0 = np.searchsorted(t, t - window_s / 2, side="left")
    j1 = np.searchsorted(t, t + window_s / 2, side="right") - 1
    d = xy[j1] - xy[j0]
    dt = t[j1] - t[j0]
    dist = np.linalg.norm(d, axis=1)
    with np.errstate(invalid="ignore", divide="ignore"):
        speed = np.where(dt > 0, dist / dt, 0.0)
    course = np.mod(np.degrees(np.arctan2(d[:, 0], d[:, 1])), 360.0)
    return course, (dt > 0) & (speed >= min_speed_mps) & (dist >= min_distance_m)


def reversed_heading_runs(
    t: np.ndarray, xy: np.ndarray, heading_deg: np.ndarray, limit_deg: float = 135.0
) -> list[tuple[int, int, float]]:
    """``[(first, last, median heading - course)]`` of the ping runs whose heading differs
    from the course over ground by more than ``limit_deg`` (a vehicle does not survey
    backwards: the heading is off by ~180 degrees, which swaps port and starboard)."""
    course, ok = course_over_ground(t, xy)
    diff = (np.asarray(heading_deg, np.float64) - course + 180.0) % 360.0 - 180.0
    bad = ok & np.isfinite(diff) & (np.abs(diff) > limit_deg)
    return [(int(a), int(b), float(np.median(np.abs(diff[a : b + 1])))) for a, b in runs(bad)]


def nav_units_mismatch(
    x: np.ndarray, y: np.ndarray, t: np.ndarray, valid: np.ndarray, latlon: bool
) -> str | None:
    """Why the coordinates do not look like the stated unit (None when they do).

    * stated metres, found degrees: every fix within +-180 / +-90, and the line, read in
      metres, moved under 0.05 m/s (a survey line does not stand still), while read in
      degrees it moved at 0.2-30 m/s;
    * stated degrees, found metres: most fixes outside +-180 / +-90.
    """
    x, y, t = (np.asarray(a, np.float64) for a in (x, y, t))
    ok = np.asarray(valid, bool) & np.isfinite(x) & np.isfinite(y)
    if ok.sum() < 2:
        return None
    x, y, tt = x[ok], y[ok], t[ok]
    if latlon:
        outside = (np.abs(x) > 180) | (np.abs(y) > 90)
        if outside.mean() > 0.5:
            return (
                f"{int(outside.sum())} of {outside.size} fixes outside +-180/+-90 (x "
                f"{x.min():.1f}..{x.max():.1f}, y {y.min():.1f}..{y.max():.1f}): metres"
            )
        return None
    duration = float(tt[-1] - tt[0])
    if duration < 10.0 or np.any(np.abs(x) > 180) or np.any(np.abs(y) > 90):
        return None
    metres_speed = math.hypot(np.ptp(x), np.ptp(y)) / duration
    lat = math.radians(float(np.median(y)))
    deg_speed = math.hypot(np.ptp(x) * 111_320.0 * math.cos(lat), np.ptp(y) * 110_574.0)
    deg_speed /= duration
    if metres_speed < 0.05 and 0.2 <= deg_speed <= 30.0:
        return (
            f"coordinates that look like degrees (x {x.min():.5f}..{x.max():.5f}, y "
            f"{y.min():.5f}..{y.max():.5f}: in metres the line would move "
            f"{metres_speed:.4f} m/s over {duration:.0f} s, in degrees {deg_speed:.1f} m/s)"
        )
    return None


# ----------------------------------------------------------------------------- sonar settings
def _span(u_lo: np.ndarray, u_hi: np.ndarray, hit: np.ndarray, min_bins: int = 2):
    """The longest run of ``hit`` u-bins: ``(u_from, u_to, first, last)`` or None."""
    best = None
    for a, b in runs(hit):
        if b - a + 1 >= min_bins and (best is None or b - a > best[3] - best[2]):
            best = (float(u_lo[a]), float(u_hi[b]), a, b)
    return best


def beam_vs_data(
    intensity: np.ndarray,
    range_m: np.ndarray,
    altitude_m: np.ndarray,
    rotation: np.ndarray,
    beam_limits_rad: tuple[float, float],
    blanking_m: float = 0.0,
    max_pings: int = 400,
    du: float = 0.05,
    bright: float = 4.0,
    dark: float = 2.0,
) -> list[dict[str, float | None]]:
    """Per side (port, starboard): where the seabed return is, against the flat-seabed
    beam-limit mask of the configured tilt / beam width (``data.masks``' rule).

    Slant range is taken in units of the altitude (``u = r / altitude``). The noise floor is
    the median intensity of the water column (``blanking_m <= r < 0.85 altitude``); per
    ``du``-wide u-bin, the median intensity over at most ``max_pings`` pings (evenly spaced)
    over that floor, and the fraction of the bins there outside the beam.

    Returns:
        One dict per side: ``noise`` (the floor; None when the water column is too short to
        measure), ``seabed_from`` / ``seabed_to`` (u where the median first reaches
        ``bright`` times the floor and where it last stays above ``dark`` times it; None
        if never), ``masked_bright`` = ``(u_from, u_to, ratio)`` (the longest run the beam
        limits mask where the median is at least ``bright`` times the floor), and
        ``kept_dark`` = ``(u_from, u_to, ratio)`` (the longest run past the altitude the
        beam keeps where the median is below ``dark`` times the floor), or None.
    """
    inten = np.asarray(intensity, np.float64)
    alt = np.asarray(altitude_m, np.float64)
    r = np.asarray(range_m, np.float64)
    keep = np.flatnonzero(np.isfinite(alt) & (alt > 0))
    empty = {
        "noise": None,
        "seabed_from": None,
        "seabed_to": None,
        "masked_bright": None,
        "kept_dark": None,
    }
    if keep.size < 5:
        return [dict(empty), dict(empty)]
    if keep.size > max_pings:
        keep = keep[np.linspace(0, keep.size - 1, max_pings).round().astype(int)]
    inten, alt = inten[keep], alt[keep]
    theta = flat_seabed_depression(r, alt, np.asarray(rotation, np.float64)[keep])
    lo, hi = beam_limits_rad
    outside = np.isfinite(theta) & ((theta < lo) | (theta > hi))
    u = r[None, :] / alt[:, None]
    u_max = float(np.nanmax(u))
    edges = np.arange(1.0, u_max + du, du)
    out = []
    for side in (0, 1):
        res = dict(empty)
        w = inten[:, side]
        column = (r[None, :] >= blanking_m) & (u < 0.85) & np.isfinite(w)
        if column.sum() < 50 or edges.size < 3:
            out.append(res)
            continue
        noise = float(np.median(w[column]))
        if not noise > 0:
            noise = float(np.mean(w[column]))
        if not noise > 0:
            out.append(res)
            continue
        res["noise"] = noise
        which = np.digitize(u, edges) - 1
        n_u = edges.size - 1
        ratio = np.full(n_u, np.nan)
        masked = np.zeros(n_u)
        for k in range(n_u):
            sel = (which == k) & np.isfinite(w)
            if sel.sum() >= 10:
                ratio[k] = float(np.median(w[sel])) / noise
                masked[k] = float(outside[:, side][sel].mean())
        has = np.isfinite(ratio)
        lo_u, hi_u = edges[:-1], edges[1:]
        seen = np.flatnonzero(has & (ratio >= bright))
        if seen.size:
            res["seabed_from"] = float(lo_u[seen[0]])
            above = np.flatnonzero(has & (ratio >= dark))
            res["seabed_to"] = None if above[-1] == n_u - 1 else float(hi_u[above[-1]])
        for key, hit in (
            ("masked_bright", has & (masked >= 0.5) & (ratio >= bright)),
            ("kept_dark", has & (masked < 0.5) & (ratio < dark)),
        ):
            s = _span(lo_u, hi_u, hit)
            if s is not None:
                res[key] = (s[0], s[1], float(np.nanmedian(ratio[s[2] : s[3] + 1])))
        out.append(res)
    return out
