"""XTF altitude: the altimeter checked against the first bottom return and repaired from it,
and the one-line reports of the altitude repairs and of the sonar settings against the data
(stages of :func:`sss2bathy.io.xtf.read_xtf`)."""

from __future__ import annotations

import logging
import math
import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from sss2bathy.io.bottom import calibrate_to_altimeter, detect_first_return, detector_accuracy
from sss2bathy.io.xtf_checks import (
    AltimeterCheck,
    check_altimeter,
    implausible_altitude,
    max_beam_edge_scale,
)
from sss2bathy.survey import SensorParams, SurveyFormatError
from sss2bathy.survey.model import (
    ALTITUDE_DETECTED,
    ALTITUDE_INTERPOLATED,
    ALTITUDE_MISSING,
    ALTITUDE_RECORDED,
)

# the import's messages come from one logger, whichever stage writes them
log = logging.getLogger("sss2bathy.io.xtf")


# ----------------------------------------------------------------------------- altitude
@dataclass
class Altitude:
    """The altitude of a line and how it was made (:func:`resolve_altitude`)."""

    altitude: np.ndarray  # (P,) m, NaN = none
    source: np.ndarray  # (P,) ALTITUDE_* codes
    check: AltimeterCheck | None  # altimeter vs first return (None: too few pings with both)
    beyond_range: int  # altimeter values above the slant range, rejected
    jumps: int  # altimeter jumps off their neighbours and the first return, rejected
    shifted: int  # filled pings shifted by the nearby altimeter - first return offset
    shift_m: float  # applied to every altimeter value (altitude_offset: apply)
    accuracy: list[float] | None  # [median, max] |error| (m) of the fills, cross-validated
    abs_diff_m: float | None  # median |altimeter - first return|


def resolve_altitude(
    path: Path,
    altitude: np.ndarray,
    picks: Any,
    t: np.ndarray,
    max_range_m: float,
    sensor: SensorParams,
    tolerance_m: float | None,
    offset_mode: str,
) -> Altitude:
    """Altimeter where plausible, the calibrated first bottom return elsewhere; refuses an
    altimeter whose disagreement with the first return is not one offset (or beam-edge scale).
    """
    fr = picks.altitude_m
    fr_picked = np.where(picks.picked, fr, np.nan)
    ok = np.isfinite(altitude) & (altitude > 0)
    max_scale = max_beam_edge_scale(sensor.tilt_rad, sensor.beam_width_rad)
    floor = tolerance_m if tolerance_m is not None else 1.0

    def cross_check(valid: np.ndarray) -> AltimeterCheck | None:
        return check_altimeter(
            np.where(valid, altitude, np.nan), fr_picked, t, tolerance_m, max_scale
        )

    check = cross_check(ok)
    bad = implausible_altitude(altitude, ok, fr_picked, check, max_range_m, floor)
    rejected = bad["beyond_range"] | bad["jump"]
    if rejected.any():
        ok &= ~rejected
        check = cross_check(ok)
    if check is not None and check.model is None:
        raise SurveyFormatError(
            path,
            "SensorPrimaryAltitude",
            "an altimeter that agrees with the first bottom return up to one offset (spread "
            f"and drift within data.survey.altitude_tolerance_m = {tolerance_m} m; null skips "
            "the check)",
            f"altimeter - first return {check.offset_m:+.2f} m median on {check.n} pings with "
            f"spread {check.sigma_m:.2f} m and drift {check.drift_m:+.2f} m over the line (nor "
            f"a beam-edge first return: {check.scale:.2f} x altimeter {check.intercept_m:+.2f} m "
            f"leaves spread {check.scale_sigma_m:.2f} m, drift {check.scale_drift_m:+.2f} m)",
        )
    shift = -check.offset_m if offset_mode == "apply" and check is not None else 0.0
    if check is not None:
        _report_altimeter(path, check, sensor, offset_mode)
    altimeter = np.where(ok, altitude + shift, np.nan)
    # fills carry the detector's local error against the altimeter (nearest pings with both)
    repaired, offset = calibrate_to_altimeter(fr, altimeter)
    out = np.where(ok, altimeter, repaired)
    source = np.full(len(out), ALTITUDE_MISSING, dtype=np.uint8)
    source[ok] = ALTITUDE_RECORDED
    source[~ok & picks.picked] = ALTITUDE_DETECTED
    source[~ok & picks.interpolated & np.isfinite(fr)] = ALTITUDE_INTERPOLATED
    accuracy = detector_accuracy(fr_picked, altimeter) if (~ok).any() else None
    both = ok & picks.picked
    return Altitude(
        altitude=out,
        source=source,
        check=check,
        beyond_range=int(bad["beyond_range"].sum()),
        jumps=int(bad["jump"].sum()),
        shifted=int((~ok & (offset != 0)).sum()),
        shift_m=float(shift),
        accuracy=None if accuracy is None else [accuracy[0], accuracy[1]],
        abs_diff_m=float(np.median(np.abs(altimeter[both] - fr[both]))) if both.any() else None,
    )


def _report_altimeter(
    path: Path, check: AltimeterCheck, sensor: SensorParams, offset_mode: str
) -> None:
    """One line: the altimeter - first return offset, its spread and drift, and its cause."""
    tilt, beam = math.degrees(sensor.tilt_rad), math.degrees(sensor.beam_width_rad)
    if check.model == "beam_edge":
        cause = (
            f"not one offset: first return = {check.scale:.2f} x altimeter "
            f"{check.intercept_m:+.2f} m (residual spread {check.scale_sigma_m:.2f} m) - the "
            "detector picks the edge of the vertical beam rather than nadir (tilt "
            f"{tilt:.0f} deg + beam {beam:.0f} deg / 2 below 90 deg puts it up to "
            f"{check.max_scale / 1.25:.2f}x the altitude away)"
        )
    else:
        cause = (
            "one constant offset: the lever arm between the altimeter and the transducers, "
            "or the detector picking a later edge than the altimeter"
        )
    action = (
        f"altimeter shifted by {-check.offset_m:+.2f} m onto the first return "
        "(data.survey.altitude_offset: apply)"
        if offset_mode == "apply"
        else "altimeter kept, offset stored in the line's import stats "
        "(data.survey.altitude_offset: record)"
    )
    loud = check.model == "beam_edge" or offset_mode == "apply" or abs(check.offset_m) > 0.5
    log.log(
        logging.WARNING if loud else logging.INFO,
        "%s: altimeter - first bottom return %+.2f m (median of %d pings; spread %.2f m, drift "
        "%+.2f m per 100 pings, %+.2f m over the line): %s; %s",
        path.name,
        check.offset_m,
        check.n,
        check.sigma_m,
        check.drift_per_100_m,
        check.drift_m,
        cause,
        action,
    )


def fill_accuracy(alt: Altitude, range_m: np.ndarray, sensor: SensorParams) -> str:
    """How accurate the detector fills are, in words (for the repairs WARNING)."""
    if alt.accuracy is not None:
        return (
            "detector fills against the altimeter (cross-validated on pings having both): "
            f"median |error| {alt.accuracy[0]:.2f} m, max {alt.accuracy[1]:.2f} m"
        )
    if alt.check is None and (alt.source == ALTITUDE_RECORDED).sum() == 0:
        bin_m = float(range_m[1] - range_m[0]) if range_m.size > 1 else float("nan")
        top = math.degrees(sensor.tilt_rad + sensor.beam_width_rad / 2)
        edge = f"up to {1 / math.sin(math.radians(top)):.2f}x" if top < 90 else "about 1x"
        return (
            "no altimeter value to check the detector against: expect about one bin "
            f"({bin_m:.3f} m) on flat seabed, absolute offset unknown (where nadir is "
            f"outside the beam the first return is its edge, {edge} the altitude)"
        )
    return "no ping with both altimeter and first return to check the fills against"


def report_beam(
    path: Path, sides: list[dict[str, Any]], sensor: SensorParams, max_range_m: float
) -> None:
    """One WARNING where the beam limits of the configured tilt / beam width cut bright seabed
    or keep bins without seabed return (:func:`~sss2bathy.io.xtf_checks.beam_vs_data`)."""
    tilt, beam = math.degrees(sensor.tilt_rad), math.degrees(sensor.beam_width_rad)
    parts = []
    for name, side in zip(("port", "starboard"), sides, strict=True):
        if side.get("masked_bright"):
            a, b, k = side["masked_bright"]
            parts.append(
                f"the beam limits mask {a:.2f}x-{b:.2f}x altitude on {name} where the median "
                f"intensity is {k:.1f} times the noise floor"
            )
        if side.get("kept_dark"):
            a, b, k = side["kept_dark"]
            parts.append(
                f"they keep {a:.2f}x-{b:.2f}x altitude on {name} where the median intensity is "
                f"only {k:.1f} times the noise floor (water column / no seabed)"
            )
    if not parts:
        return
    seen = "; ".join(
        f"{name} seabed return from {s['seabed_from']:.2f}x altitude to "
        + (
            f"{s['seabed_to']:.2f}x"
            if s["seabed_to"] is not None
            else f"the {max_range_m:.0f} m range"
        )
        for name, s in zip(("port", "starboard"), sides, strict=True)
        if s.get("seabed_from") is not None
    )
    log.warning(
        "%s: sonar settings vs data: with tilt %.0f deg and beam width %.0f deg (depression "
        "%.0f..%.0f deg) on a flat seabed %s; %s; check data.survey.tilt_deg / "
        "data.survey.beam_width_deg",
        path.name,
        tilt,
        beam,
        tilt - beam / 2,
        tilt + beam / 2,
        ", ".join(parts),
        seen or "no clear seabed return",
    )


def altitude_from_sonar(
    path: Path,
    intensity: np.ndarray,
    range_m: np.ndarray,
    max_range_m: float,
    altimeter: np.ndarray,
    t: np.ndarray,
    sensor: SensorParams,
    ping_flags: dict[str, int],
    *,
    min_first_return_m: float,
    blanking_m: float,
    auto_blanking: bool,
    tolerance_m: float | None,
    offset_mode: str,
) -> tuple[Any, Altitude]:
    """``(picks, altitude)``: the first bottom return of the mean of both sides
    (:func:`~sss2bathy.io.bottom.detect_first_return`) and the altitude resolved from it and
    the altimeter (:func:`resolve_altitude`; ``max_range_m``: the far end of the range window).

    Checks (else :class:`SurveyFormatError`): the altimeter agrees with the first return up to
    one offset (or the beam-edge scale) within ``tolerance_m``; some ping has an altitude.
    Repairs (one WARNING counting each, with the fills' cross-validated accuracy): altimeter
    values beyond the slant range or jumping off their neighbours rejected, missing altitudes
    filled from the calibrated first return or interpolated between picks; the no-hit pings
    (``ping_flags``, masked before) are counted in the same WARNING.
    """
    with np.errstate(invalid="ignore"), warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # both sides NaN -> NaN: a bad ping
        mean_wf = np.nanmean(intensity.astype(np.float64), axis=1)
    picks = detect_first_return(
        mean_wf,
        range_m,
        min_range_m=min_first_return_m,
        blanking_m=blanking_m,
        auto_blanking=auto_blanking,
    )
    alt = resolve_altitude(path, altimeter, picks, t, max_range_m, sensor, tolerance_m, offset_mode)
    altitude, source = alt.altitude, alt.source
    if not np.isfinite(altitude).any():
        raise SurveyFormatError(
            path,
            "altitude",
            "an altimeter value or a visible first bottom return on some ping",
            f"neither on any of {len(altitude)} pings",
        )
    repairs = {
        "altimeter values beyond the slant range rejected": alt.beyond_range,
        "altimeter jumps (off their neighbours and the first return) rejected": alt.jumps,
        "filled from the detector": int((source == ALTITUDE_DETECTED).sum()),
        "interpolated between detected pings": int((source == ALTITUDE_INTERPOLATED).sum()),
        "of those shifted by the nearest pings' altimeter - first return offset": alt.shifted,
        "left missing (NaN, no altimeter point)": int((source == ALTITUDE_MISSING).sum()),
        "first returns rejected (edge in the blanking zone)": int(picks.rejected.sum()),
        "pings masked as no-hit (constant)": ping_flags["constant"],
        "pings masked as no-hit (saturated)": ping_flags["saturated"],
        "pings masked as no-hit (NaN samples)": ping_flags["nonfinite"],
    }
    if any(repairs.values()):
        log.warning(
            "%s: altitude/sample repairs: %s; blanking %.2f m; %s",
            path.name,
            ", ".join(f"{v} {k}" for k, v in repairs.items() if v),
            picks.blanking_m,
            fill_accuracy(alt, range_m, sensor),
        )
    return picks, alt
