"""XTF navigation and attitude: projection helpers and the checks and repairs of the fixes
(stages of :func:`sss2bathy.io.xtf.read_xtf`)."""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from scipy.ndimage import median_filter

from sss2bathy.geometry import attitude_to_rotation
from sss2bathy.io.xtf_checks import nav_units_mismatch, reversed_heading_runs, speed_outliers
from sss2bathy.io.xtf_packets import attitude_time, ping_time
from sss2bathy.survey import SurveyFormatError

NAV_UNITS_METRES = 0
NAV_UNITS_LATLON = 3


# ----------------------------------------------------------------------------- projection
def utm_crs_for(lon: float, lat: float) -> str:
    """``EPSG:326zz`` (north) / ``EPSG:327zz`` (south): the WGS 84 UTM zone holding (lon, lat).

    Zones are the regular 6-degree bands (the Norway/Svalbard exceptions are not applied).
    """
    if not (math.isfinite(lon) and math.isfinite(lat) and abs(lat) <= 90 and abs(lon) <= 180):
        raise ValueError(f"lon/lat: expected a geographic position, found ({lon}, {lat})")
    zone = min(int(math.floor((lon + 180.0) / 6.0)) + 1, 60)
    return f"EPSG:{32600 + zone if lat >= 0 else 32700 + zone}"


def transformer(src: str, dst: str):
    from pyproj import Transformer

    return Transformer.from_crs(src, dst, always_xy=True)


def same_crs(a: Any, b: Any) -> bool:
    from pyproj import CRS

    return CRS.from_user_input(a) == CRS.from_user_input(b)


def crs_string(crs: Any) -> str | None:
    """A compact, round-trippable CRS string (``EPSG:nnnn`` where possible, else WKT)."""
    if crs is None:
        return None
    from pyproj import CRS

    c = CRS.from_user_input(crs)
    epsg = c.to_epsg(min_confidence=90)
    return f"EPSG:{epsg}" if epsg else c.to_wkt()


# ----------------------------------------------------------------------------- navigation
def interp_gaps(t: np.ndarray, values: np.ndarray, valid: np.ndarray) -> np.ndarray:
    """Linear-in-time interpolation of ``(P, K)`` values where ``valid`` is False."""
    out = values.copy()
    for k in range(values.shape[1]):
        out[~valid, k] = np.interp(t[~valid], t[valid], values[valid, k])
    return out


def check_nav(
    path: Path,
    t: np.ndarray,
    xy: np.ndarray,
    valid: np.ndarray,
    max_jump_m: float,
    max_speed_mps: float,
    ping_ids: np.ndarray,
) -> tuple[np.ndarray, int, float]:
    """Drop outlier fixes (-> gaps), refuse jumps and too many outliers.

    Outliers: fixes farther than ``max_jump_m`` from the running median of their neighbours,
    and fixes that left the track faster than ``max_speed_mps``
    (:func:`~sss2bathy.io.xtf_checks.speed_outliers`). Returns the updated validity mask, the
    outlier count and their largest implied speed (m/s; 0 without outliers).
    """
    idx = np.flatnonzero(valid)
    outliers = np.zeros_like(valid)
    if idx.size >= 3:
        win = min(9, idx.size if idx.size % 2 else idx.size - 1)
        med = np.stack([median_filter(xy[idx, k], size=win, mode="nearest") for k in (0, 1)], 1)
        dev = np.linalg.norm(xy[idx] - med, axis=1)
        outliers[idx[dev > max_jump_m]] = True
    fast, speed = speed_outliers(t, xy, valid, max_speed_mps)
    outliers |= fast
    n_valid = int(valid.sum())
    if outliers.sum() > max(0.1 * n_valid, 1):
        j = int(np.argmax(outliers))
        raise SurveyFormatError(
            path,
            "position",
            "at most 10% of the fixes off the track (outliers are interpolated; "
            f"data.survey.max_speed_mps = {max_speed_mps} m/s, data.survey.max_jump_m = "
            f"{max_jump_m} m)",
            f"{int(outliers.sum())} of {n_valid} fixes, the first at ping {ping_ids[j]} "
            f"(implied speeds up to {np.nanmax(np.where(outliers, speed, np.nan)):.0f} m/s)",
        )
    top_speed = float(np.nanmax(np.where(outliers, speed, np.nan))) if outliers.any() else 0.0
    valid = valid & ~outliers
    idx = np.flatnonzero(valid)
    if idx.size >= 2:
        step = np.linalg.norm(np.diff(xy[idx], axis=0), axis=1)
        allowed = max_jump_m + max_speed_mps * np.diff(t[idx])
        bad = np.flatnonzero(step > allowed)
        if bad.size:
            j = idx[bad[0] + 1]
            raise SurveyFormatError(
                path,
                f"ping {ping_ids[j]}: position",
                f"a step below {allowed[bad[0]]:.0f} m (data.survey.max_jump_m + "
                "data.survey.max_speed_mps * dt)",
                f"a jump of {step[bad[0]]:.0f} m in {t[j] - t[idx[bad[0]]]:.2f} s",
            )
    return valid, int(outliers.sum()), top_speed


def unwrap_deg(a: np.ndarray) -> np.ndarray:
    return np.degrees(np.unwrap(np.radians(a)))


# ----------------------------------------------------------------------------- stages
def ping_times(path: Path, pings: list[Any], ping_ids: np.ndarray) -> np.ndarray:
    """UTC seconds of each ping. Checks: a valid date and time on every ping and strictly
    increasing times (else :class:`SurveyFormatError` naming the ping). Repairs nothing."""
    t = np.array([ping_time(p, path, k) for p, k in zip(pings, ping_ids, strict=True)])
    dt = np.diff(t)
    if np.any(dt <= 0):
        j = int(np.argmax(dt <= 0)) + 1
        raise SurveyFormatError(
            path,
            f"ping {ping_ids[j]}: time",
            "strictly increasing ping times",
            f"{t[j] - t[j - 1]:+.2f} s after ping {ping_ids[j - 1]}",
        )
    return t


def attitude_from_packets(
    att: list[Any], t: np.ndarray, heading: np.ndarray, pitch: np.ndarray, roll: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray, str]:
    """``(heading, pitch, roll, source)``: the attitude packets interpolated to the ping times
    where they are at least 2, cover every ping and have increasing times
    (``"attitude_packets"``), else the ping headers' values unchanged (``"ping_header"``).
    Pure; repairs nothing."""
    if len(att) >= 2:
        ta = np.array([attitude_time(a) for a in att])
        order = np.argsort(ta, kind="stable")
        ta = ta[order]
        if ta[0] <= t[0] and ta[-1] >= t[-1] and np.all(np.diff(ta) > 0):
            ah = unwrap_deg(np.array([att[i].Heading for i in order], dtype=np.float64))
            heading = np.mod(np.interp(t, ta, ah), 360.0)
            pitch = np.interp(t, ta, np.array([att[i].Pitch for i in order], dtype=np.float64))
            roll = np.interp(t, ta, np.array([att[i].Roll for i in order], dtype=np.float64))
            return heading, pitch, roll, "attitude_packets"
    return heading, pitch, roll, "ping_header"


@dataclass
class Navigation:
    """The fixes of the kept pings (:func:`navigate`), projected into the survey's CRS."""

    keep: slice  # the pings between the first and the last valid fix (the others dropped)
    xy: np.ndarray  # (P, 2) easting, northing in the frame CRS, gaps interpolated
    depth: np.ndarray  # (P,) sensor depth (m, down), gaps interpolated
    frame_crs: Any  # the CRS of ``xy``
    dropped: int  # pings before the first / after the last valid fix
    interpolated: int  # fixes interpolated (missing or outliers)
    outliers: int  # fixes rejected as outliers
    outlier_speed: float  # their largest implied speed (m/s; 0 without outliers)
    from_ship: int  # kept fixes taken from the ship position moved back by the layback
    depth_interpolated: int


def navigate(
    path: Path,
    t: np.ndarray,
    ping_ids: np.ndarray,
    fields: Any,
    heading: np.ndarray,
    nav_units_code: int,
    nav_units: str,
    crs: str | None,
    origin: Any,
    max_jump_m: float,
    max_speed_mps: float,
    max_nav_gap_s: float,
) -> Navigation:
    """Raw fixes -> projected positions (``fields(name)``: a ping header field per ping).

    Checks (else :class:`SurveyFormatError`): coordinates that look like the navigation unit
    (:func:`~sss2bathy.io.xtf_checks.nav_units_mismatch`), at least one valid position (at
    least 2 after the outliers), no step longer than ``max_jump_m + max_speed_mps * dt`` and
    no gap longer than ``max_nav_gap_s``, finite depths somewhere. Repairs (counted in the
    result, reported in the import's navigation WARNING): empty sensor fixes taken from the
    ship fix moved back by the layback along the heading, outlier fixes and missing fixes
    interpolated in time, pings before the first / after the last valid fix dropped, missing
    depths interpolated.
    """
    sx, sy = fields("SensorXcoordinate"), fields("SensorYcoordinate")
    shx, shy = fields("ShipXcoordinate"), fields("ShipYcoordinate")
    layback = np.nan_to_num(fields("Layback"), nan=0.0)
    depth = fields("SensorDepth")

    def plausible(x: np.ndarray, y: np.ndarray) -> np.ndarray:
        ok = np.isfinite(x) & np.isfinite(y) & ~((x == 0) & (y == 0))
        if nav_units_code == NAV_UNITS_LATLON:
            ok &= (np.abs(x) <= 180) & (np.abs(y) <= 90)
        return ok

    has_sensor = np.isfinite(sx) & np.isfinite(sy) & ~((sx == 0) & (sy == 0))
    units_problem = nav_units_mismatch(
        np.where(has_sensor, sx, shx),
        np.where(has_sensor, sy, shy),
        t,
        has_sensor | (np.isfinite(shx) & np.isfinite(shy) & ~((shx == 0) & (shy == 0))),
        latlon=nav_units_code == NAV_UNITS_LATLON,
    )
    if units_problem is not None:
        stated = "latitude/longitude (3)" if nav_units_code == NAV_UNITS_LATLON else "metres (0)"
        source = "NavUnits" if nav_units == "file" else "data.survey.nav_units"
        raise SurveyFormatError(
            path,
            "NavUnits",
            f"coordinates in {stated} as {source} states (set data.survey.nav_units: latlon or "
            "metres when the header is wrong)",
            units_problem,
        )
    sensor_ok = plausible(sx, sy)
    ship_ok = plausible(shx, shy) & ~sensor_ok
    depth_ok = np.isfinite(depth)
    if not (sensor_ok | ship_ok).any():
        raise SurveyFormatError(
            path, "position", "at least one valid sensor or ship position", "none (all 0 or NaN)"
        )

    raw_x, raw_y = np.where(sensor_ok, sx, shx), np.where(sensor_ok, sy, shy)
    if nav_units_code == NAV_UNITS_LATLON:
        source_crs = "EPSG:4326"
        j = int(np.argmax(sensor_ok | ship_ok))
        default_crs = crs or utm_crs_for(float(raw_x[j]), float(raw_y[j]))
    else:
        source_crs = crs if crs is not None else (origin or {}).get("crs")
        default_crs = source_crs
    frame_crs = origin.get("crs") if origin is not None else default_crs
    if nav_units_code == NAV_UNITS_LATLON and frame_crs is None:
        raise SurveyFormatError(
            path, "origin.crs", "a projected CRS for geographic navigation", None
        )
    if source_crs is not None and frame_crs is not None and not same_crs(source_crs, frame_crs):
        ex, ny_ = transformer(source_crs, frame_crs).transform(raw_x, raw_y)
        ex, ny_ = np.asarray(ex, dtype=np.float64), np.asarray(ny_, dtype=np.float64)
    else:
        ex, ny_ = raw_x, raw_y
    nav_ok = sensor_ok | ship_ok
    ex, ny_ = np.where(nav_ok, ex, 0.0), np.where(nav_ok, ny_, 0.0)
    if ship_ok.any():
        h = np.radians(np.where(np.isfinite(heading), heading, 0.0))
        ex = np.where(ship_ok, ex - layback * np.sin(h), ex)
        ny_ = np.where(ship_ok, ny_ - layback * np.cos(h), ny_)
    xy = np.stack([ex, ny_], axis=1)
    nav_ok, outliers, outlier_speed = check_nav(
        path, t, xy, nav_ok, max_jump_m, max_speed_mps, ping_ids
    )
    if nav_ok.sum() < 2:
        raise SurveyFormatError(path, "position", "at least 2 valid fixes", int(nav_ok.sum()))

    # Pings before the first / after the last valid fix cannot be interpolated: skipped.
    first, last = np.flatnonzero(nav_ok)[[0, -1]]
    sl = slice(first, last + 1)
    dropped_nav = len(t) - (last + 1 - first)
    t, xy, nav_ok, depth, depth_ok = t[sl], xy[sl], nav_ok[sl], depth[sl], depth_ok[sl]
    ping_ids = ping_ids[sl]
    good_t = t[nav_ok]
    gaps = np.diff(good_t)
    if gaps.size and gaps.max() > max_nav_gap_s:
        j = int(np.argmax(gaps))
        after = int(np.flatnonzero(t == good_t[j + 1])[0])
        raise SurveyFormatError(
            path,
            f"ping {ping_ids[after]}: position",
            f"navigation gaps up to data.survey.max_nav_gap_s = {max_nav_gap_s} s",
            f"a gap of {gaps[j]:.1f} s",
        )
    nav_interp = int((~nav_ok).sum())
    if nav_interp:
        xy = interp_gaps(t, xy, nav_ok)
    depth_interp = int((~depth_ok).sum())
    if depth_interp:
        if not depth_ok.any():
            raise SurveyFormatError(path, "SensorDepth", "finite sensor depths", "all NaN")
        depth = interp_gaps(t, depth[:, None], depth_ok)[:, 0]
    return Navigation(
        keep=sl,
        xy=xy,
        depth=depth,
        frame_crs=frame_crs,
        dropped=int(dropped_nav),
        interpolated=nav_interp,
        outliers=outliers,
        outlier_speed=outlier_speed,
        from_ship=int(ship_ok[sl].sum()),
        depth_interpolated=depth_interp,
    )


def orient(
    path: Path,
    t: np.ndarray,
    xy: np.ndarray,
    attitude: tuple[np.ndarray, np.ndarray, np.ndarray],
    attitude_source: str,
    missing_attitude: str,
    ping_ids: np.ndarray,
) -> tuple[np.ndarray, int]:
    """``(R, pings whose heading came from the track)``: the body-to-ENU rotations of the
    pings from their ``(heading, pitch, roll)`` (degrees).

    Checks (else :class:`SurveyFormatError`): an attitude on every ping (non-finite values, or
    heading, pitch and roll all exactly 0 while the track does not head North, are missing),
    unless ``missing_attitude`` is ``"track"``; no run of headings reversed against the course
    over ground (:func:`~sss2bathy.io.xtf_checks.reversed_heading_runs`). Repairs (counted,
    reported in the navigation WARNING): with ``"track"``, missing attitudes become the course
    made good with zero pitch and roll.
    """
    heading, pitch, roll = attitude
    att_ok = np.isfinite(heading) & np.isfinite(pitch) & np.isfinite(roll)
    course = np.mod(
        np.degrees(np.arctan2(np.gradient(xy[:, 0], t), np.gradient(xy[:, 1], t))), 360.0
    )
    why = "missing (NaN)"
    if attitude_source == "ping_header" and np.all((heading == 0) & (pitch == 0) & (roll == 0)):
        # Every attitude field exactly 0: unrecorded, unless the vehicle really heads North.
        off_north = np.abs((course + 180.0) % 360.0 - 180.0)
        if np.median(off_north) > 45.0:
            att_ok[:] = False
            why = f"missing (all 0 while the track heads {float(np.median(course)):.0f} deg)"
    track_heading_pings = 0
    if not att_ok.all():
        if missing_attitude == "error":
            j = int(np.argmax(~att_ok))
            raise SurveyFormatError(
                path,
                f"ping {ping_ids[j]}: attitude",
                "finite SensorHeading/Pitch/Roll or attitude packets (or "
                "data.survey.missing_attitude: track)",
                why,
            )
        track_heading_pings = int((~att_ok).sum())
        heading = np.where(att_ok, heading, course)
        pitch = np.where(att_ok, pitch, 0.0)
        roll = np.where(att_ok, roll, 0.0)
    reversed_runs = reversed_heading_runs(t, xy, np.where(att_ok, heading, np.nan))
    if reversed_runs:
        a, b, angle = reversed_runs[0]
        n_rev = sum(e - f + 1 for f, e, _ in reversed_runs)
        raise SurveyFormatError(
            path,
            f"pings {ping_ids[a]}-{ping_ids[b]}: SensorHeading",
            "a heading within 135 deg of the course over ground (else port and starboard swap)",
            f"{angle:.0f} deg off the course on {n_rev} pings in {len(reversed_runs)} run(s): "
            "a heading reversed by 180 deg (fix the heading, or read those pings apart)",
        )
    R = attitude_to_rotation(np.radians(heading), np.radians(pitch), np.radians(roll))
    return R, track_heading_pings


def frame_origin(origin: Any, frame_crs: Any, xy: np.ndarray) -> dict[str, Any]:
    """``{"crs", "easting", "northing"}`` of the survey frame: ``origin`` as given, or the
    first position rounded to 100 m in ``frame_crs``. Pure."""
    if origin is None:
        easting = float(np.round(xy[0, 0] / 100.0) * 100.0)
        northing = float(np.round(xy[0, 1] / 100.0) * 100.0)
        return {"crs": crs_string(frame_crs), "easting": easting, "northing": northing}
    return {
        "crs": origin.get("crs"),
        "easting": float(origin.get("easting", 0.0)),
        "northing": float(origin.get("northing", 0.0)),
    }
