"""The sonar a CNN was trained on, and whether a survey's sonar lies inside it.

A CNN learns normals from sidescan recorded by one kind of sonar: its frequency, its range
and bin size, the beam's tilt and vertical width and the altitudes it flew at shape the
intensities it sees. Applied to another sonar (a 600 kHz line at 512 bins to a net trained
on a simulated 850 kHz sonar at 256 bins), its normals may be wrong without any error.

At training, :func:`sonar_envelope` records the training lines' settings (the min and max
over the lines, :data:`SETTINGS`); the CNN module stores that plain dict in its checkpoint
under :data:`CHECKPOINT_KEY`. When CNN normals are computed for a survey,
:func:`envelope_warning` compares the survey's lines with it and returns one warning line
naming every setting outside (with :data:`TOLERANCE`), or one saying the envelope is
unknown for a checkpoint without one. Nothing is ever refused.

Per line: ``frequency_hz`` (the sensor's), ``max_range_m`` (the last bin's slant range),
``bin_m`` (the median slant-range step), ``tilt_deg`` and ``beam_width_deg`` (the line's
own drawn values where a synthetic survey randomised its sonar, ``metadata.lines.<name>.
randomized``; else the sensor's), ``altitude_m`` (the 5th and 95th percentiles of the
line's finite altitudes).
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np

from sss2bathy.survey import SidescanLine, Survey

#: Top-level key of the envelope in a CNN checkpoint.
CHECKPOINT_KEY = "sonar_envelope"
ENVELOPE_VERSION = 1
#: The recorded settings, in the order they are reported.
SETTINGS = ("frequency_hz", "max_range_m", "bin_m", "tilt_deg", "beam_width_deg", "altitude_m")
#: Allowed excess beyond the trained range: ``("rel", f)`` a fraction of the bound,
#: ``("abs", d)`` in the setting's unit.
TOLERANCE: dict[str, tuple[str, float]] = {
    "frequency_hz": ("rel", 0.10),
    "max_range_m": ("rel", 0.10),
    "bin_m": ("rel", 0.10),
    "tilt_deg": ("abs", 5.0),
    "beam_width_deg": ("abs", 5.0),
    "altitude_m": ("rel", 0.10),
}
ALTITUDE_PERCENTILES = (5.0, 95.0)


def line_sonar(line: SidescanLine, randomized: Mapping[str, Any] | None = None) -> dict:
    """One line's settings: ``{setting: [low, high]}`` (low = high except the altitude's
    percentiles); a setting the line does not know (no finite altitude) is left out.

    ``randomized``: the line's drawn sonar (``tilt_deg``, ``beam_width_deg``), which replace
    the sensor's recorded nominal values.
    """
    drawn = randomized or {}
    ranges = np.asarray(line.range_m, dtype=np.float64)
    bin_m = float(np.median(np.diff(ranges))) if ranges.size > 1 else float(ranges[0])
    tilt = drawn.get("tilt_deg", math.degrees(line.sensor.tilt_rad))
    beam = drawn.get("beam_width_deg", math.degrees(line.sensor.beam_width_rad))
    out: dict[str, list[float]] = {
        "frequency_hz": [float(line.sensor.frequency_hz)] * 2,
        "max_range_m": [float(ranges[-1])] * 2,
        "bin_m": [bin_m] * 2,
        "tilt_deg": [float(tilt)] * 2,
        "beam_width_deg": [float(beam)] * 2,
    }
    alt = np.asarray(line.altitude_m, dtype=np.float64)
    alt = alt[np.isfinite(alt)]
    if alt.size:
        out["altitude_m"] = [float(v) for v in np.percentile(alt, ALTITUDE_PERCENTILES)]
    return out


def sonar_envelope(survey: Survey, line_names: Sequence[str]) -> dict[str, Any]:
    """The settings of ``line_names`` of ``survey``: ``{"version", "survey", "n_lines",
    "settings": {setting: [min, max]}}``, plain values only (a checkpoint loads with
    ``weights_only=True``)."""
    if isinstance(line_names, str) or not line_names:
        raise ValueError(f"line_names: expected a list of line names, found {line_names!r}")
    meta = survey.metadata.get("lines") if isinstance(survey.metadata, Mapping) else None
    meta = meta if isinstance(meta, Mapping) else {}
    settings: dict[str, list[float]] = {}
    for name in line_names:
        entry = meta.get(name)
        drawn = entry.get("randomized") if isinstance(entry, Mapping) else None
        for key, (lo, hi) in line_sonar(survey.line(name), drawn).items():
            if key in settings:
                settings[key] = [min(settings[key][0], lo), max(settings[key][1], hi)]
            else:
                settings[key] = [lo, hi]
    ordered = {k: [float(v) for v in settings[k]] for k in SETTINGS if k in settings}
    return {
        "version": ENVELOPE_VERSION,
        "survey": str(survey.name),
        "n_lines": len(line_names),
        "settings": ordered,
    }


def outside_settings(
    trained: Mapping[str, Sequence[float]],
    survey: Mapping[str, Sequence[float]],
    tolerance: Mapping[str, tuple[str, float]] | None = None,
) -> list[str]:
    """The settings (in :data:`SETTINGS` order) whose survey range reaches beyond the trained
    range by more than ``tolerance`` (:data:`TOLERANCE`); settings missing on either side
    are not compared."""
    tol = TOLERANCE if tolerance is None else tolerance
    out = []
    for key in SETTINGS:
        if key not in trained or key not in survey:
            continue
        t_lo, t_hi = (float(v) for v in trained[key])
        s_lo, s_hi = (float(v) for v in survey[key])
        kind, amount = tol.get(key, ("rel", 0.0))
        if kind == "rel":
            low, high = t_lo * (1 - amount), t_hi * (1 + amount)
        else:
            low, high = t_lo - amount, t_hi + amount
        if s_lo < low or s_hi > high:
            out.append(key)
    return out


def _fmt(key: str, values: Sequence[float]) -> str:
    lo, hi = (float(v) for v in values)
    if key == "frequency_hz":
        lo, hi, unit, fmt = lo / 1e3, hi / 1e3, " kHz", "{:.0f}"
    elif key == "bin_m":
        unit, fmt = " m bins", "{:.3g}"
    elif key == "max_range_m":
        unit, fmt = " m range", "{:.3g}"
    elif key == "altitude_m":
        unit, fmt = " m altitude", "{:.1f}"
    else:
        unit, fmt = "°", "{:.0f}"
    text = (
        fmt.format(lo) if fmt.format(lo) == fmt.format(hi) else f"{fmt.format(lo)}-{fmt.format(hi)}"
    )
    prefix = {"tilt_deg": "tilt ", "beam_width_deg": "beam "}.get(key, "")
    return f"{prefix}{text}{unit}"


def describe(settings: Mapping[str, Sequence[float]], outside: Sequence[str] = ()) -> str:
    """``"850 kHz, 30 m range, 0.117 m bins, tilt 30°, ..."``; settings in ``outside``
    marked ``(outside)``."""
    return ", ".join(
        _fmt(k, settings[k]) + (" (outside)" if k in outside else "")
        for k in SETTINGS
        if k in settings
    )


def check_envelope(envelope: Any, where: str) -> dict[str, list[float]] | None:
    """The ``settings`` of a stored envelope, or None when there is none; a malformed one is
    a ``ValueError`` naming ``where``."""
    if envelope is None:
        return None
    settings = envelope.get("settings") if isinstance(envelope, Mapping) else None
    if not isinstance(settings, Mapping):
        raise ValueError(
            f"{where}: expected a mapping with 'settings', found {type(envelope).__name__}"
        )
    out = {}
    for key, values in settings.items():
        ok = (
            isinstance(values, Sequence)
            and len(values) == 2
            and all(isinstance(v, int | float) and math.isfinite(v) for v in values)
        )
        if not ok:
            raise ValueError(f"{where}.settings.{key}: expected [min, max], found {values!r}")
        out[str(key)] = [float(values[0]), float(values[1])]
    return out


def envelope_warning(
    envelope: Any,
    survey: Survey,
    line_names: Sequence[str],
    checkpoint: str,
    tolerance: Mapping[str, tuple[str, float]] | None = None,
) -> str | None:
    """One warning line when ``line_names`` of ``survey`` lie outside a CNN checkpoint's
    training ``envelope`` (or when the checkpoint stores none); None when inside.

    ``checkpoint`` names the checkpoint in the message.
    """
    trained = check_envelope(envelope, f"checkpoint {checkpoint}: {CHECKPOINT_KEY}")
    if trained is None:
        return (
            f"the CNN checkpoint {checkpoint} does not record the sonar it was trained on "
            "(a checkpoint from before sonar envelopes): whether this survey's sonar "
            f"({describe(sonar_envelope(survey, line_names)['settings'])}) is one it knows "
            "is unknown"
        )
    this = sonar_envelope(survey, line_names)["settings"]
    outside = outside_settings(trained, this, tolerance)
    if not outside:
        return None
    return (
        f"the CNN checkpoint {checkpoint} was trained on {describe(trained)}; survey "
        f"'{survey.name}': {describe(this, outside)}: {len(outside)} setting(s) outside the "
        "trained range, its normals may be unreliable"
    )


__all__ = [
    "CHECKPOINT_KEY",
    "SETTINGS",
    "TOLERANCE",
    "describe",
    "envelope_warning",
    "line_sonar",
    "outside_settings",
    "sonar_envelope",
]
