"""Sonar-only bin masks and CNN input channels: what a sidescan survey alone can tell.

The sidescan-only stage (SIREN-CNN-N2d, SIREN-Lambert on a new survey) has sidescan,
altimeter and navigation, never the MBES grid. :func:`sonar_mask` masks, per bin
(``MASK_*`` bits of :mod:`sss2bathy.survey.masks`):

* ``MASK_WATER_COLUMN`` — slant range below the altitude plus ``nadir_margin_m`` (before
  the first bottom return on flat seabed);
* ``MASK_NO_HIT`` — pings without altitude, non-finite intensities;
* ``MASK_OUT_OF_BEAM`` — on a flat seabed ``altitude`` below the sonar, the bin's arc
  meets the seabed at a depression angle outside the sensor's vertical beam
  ``tilt +- beam_width / 2`` widened by ``beam_margin_deg`` (``beam_limits: false`` turns
  this off). The vehicle's attitude is used (``rotation``), so roll moves the limits;
* ``MASK_SHADOW`` — among the remaining bins, those whose intensity, normalised per head
  over them (:func:`~sss2bathy.data.normalize.normalize_intensity`: the median seabed
  reads 1) and box-smoothed over ``shadow_smooth_pings x shadow_smooth_bins`` valid
  neighbours, is below ``shadow_threshold``.

The same rule masks the Lambertian fit (``normals=none``), the CNN's prediction input
normalisation and the CNN's training input normalisation, so training and inference see
identical inputs, and removing the MBES grid changes nothing the sidescan stage uses.

:func:`input_channels` stacks the CNN's inputs from the same data: the normalised
intensity, or (``relative``) the intensity relative to its along-track mean at the same
range (:func:`~sss2bathy.data.normalize.relative_intensity`: beam pattern, gain, altitude
and the sediment's mean angular response divide out), and, optionally, the flat-seabed
geometry the network can not see within its receptive field (``grazing``:
``sin g = altitude / r``, 0 before the first return; ``range``: ``r / r_max``), and
(``opposite``) the other head's normalised intensity at the same ping and range: on a seabed
tilted across track one head brightens while the other darkens, whatever the beam pattern
and gain the two heads share, so the pair could tell the slow cross-track slope that one
head's intensity alone confuses with them (measured: it made the demo's CNN and its map worse,
docs/studies/cnn_levers.md).
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import asdict, dataclass
from typing import Any

import numpy as np

from sss2bathy.data.normalize import box_mean, normalize_intensity, relative_intensity
from sss2bathy.geometry.seabed import flat_seabed_depression
from sss2bathy.survey import (
    MASK_NO_HIT,
    MASK_OUT_OF_BEAM,
    MASK_SHADOW,
    MASK_VALID,
    MASK_WATER_COLUMN,
)
from sss2bathy.utils.checks import (
    coerce_config,
    is_integer,
    require,
    require_bool,
    require_number,
)

#: CNN input channels :func:`input_channels` can build; the first is an intensity channel
#: (:data:`INTENSITY_CHANNELS`).
CHANNELS = ("intensity", "relative", "grazing", "range", "opposite")
#: The channels that can come first: the intensity the network reads.
INTENSITY_CHANNELS = ("intensity", "relative")
DEFAULT_CHANNELS = ("intensity",)


@dataclass(frozen=True)
class SonarMaskConfig:
    """Parameters of :func:`sonar_mask` (the ``data.sonar_mask`` config block).

    Attributes:
        nadir_margin_m: bins with slant range < altitude + this are water column (m, >= 0).
        beam_limits: mask bins outside the sensor's vertical beam on flat seabed.
        beam_margin_deg: the beam is widened by this on either side (degrees, in [0, 45]).
        shadow_threshold: smoothed normalised intensity below this is shadow (>= 0; 0 = no
            shadow detection).
        shadow_smooth_pings, shadow_smooth_bins: box of the smoothing (odd, >= 1).
    """

    nadir_margin_m: float = 0.0
    beam_limits: bool = True
    beam_margin_deg: float = 0.0
    shadow_threshold: float = 0.15
    shadow_smooth_pings: int = 1
    shadow_smooth_bins: int = 1

    def __post_init__(self) -> None:
        at_least_0, in_0_45 = "a number >= 0.0", "a number in [0.0, 45.0]"
        require_number(
            "sonar_mask.nadir_margin_m", self.nadir_margin_m, lambda v: v >= 0, at_least_0
        )
        require_number(
            "sonar_mask.beam_margin_deg", self.beam_margin_deg, lambda v: 0 <= v <= 45, in_0_45
        )
        require_number(
            "sonar_mask.shadow_threshold", self.shadow_threshold, lambda v: v >= 0, at_least_0
        )
        require_bool("sonar_mask.beam_limits", self.beam_limits)
        for name in ("shadow_smooth_pings", "shadow_smooth_bins"):
            v = getattr(self, name)
            odd = is_integer(v) and v >= 1 and v % 2 == 1
            require(f"sonar_mask.{name}", v, odd, "an odd integer >= 1")

    @classmethod
    def coerce(cls, cfg: SonarMaskConfig | Mapping[str, Any] | None) -> SonarMaskConfig:
        """A config from ``None`` (defaults), a plain dict / DictConfig, or a config."""
        return coerce_config(cls, cfg, "sonar_mask")

    def to_dict(self) -> dict[str, Any]:
        """Plain values (hparams, cache keys)."""
        return asdict(self)


# ------------------------------------------------------------------------ masks
def sonar_mask(
    intensity: np.ndarray,
    range_m: np.ndarray,
    altitude_m: np.ndarray,
    rotation: np.ndarray,
    beam_limits_rad: tuple[float, float] | None,
    cfg: SonarMaskConfig | Mapping[str, Any] | None = None,
) -> np.ndarray:
    """``(P, 2, B)`` uint8 mask from the sonar alone (module docstring).

    Args:
        intensity: ``(P, 2, B)`` linear intensities (any scale).
        range_m: ``(B,)`` slant ranges (m).
        altitude_m: ``(P,)`` altitude (m), NaN where missing.
        rotation: ``(P, 3, 3)`` vehicle -> world rotations.
        beam_limits_rad: ``(theta_min, theta_max)`` depression angles of the vertical beam,
            or None (no beam limits known).
        cfg: :class:`SonarMaskConfig` or its fields.
    """
    cfg = SonarMaskConfig.coerce(cfg)
    intensity = np.asarray(intensity)
    range_m = np.asarray(range_m, np.float64)
    altitude = np.asarray(altitude_m, np.float64)
    rotation = np.asarray(rotation, np.float64)
    if intensity.ndim != 3 or intensity.shape[1] != 2:
        raise ValueError(f"intensity: expected shape (P, 2, B), found {intensity.shape}")
    n_pings, _, n_bins = intensity.shape
    if range_m.shape != (n_bins,):
        raise ValueError(f"range_m: expected shape ({n_bins},), found {range_m.shape}")
    if altitude.shape != (n_pings,):
        raise ValueError(f"altitude_m: expected shape ({n_pings},), found {altitude.shape}")
    if rotation.shape != (n_pings, 3, 3):
        raise ValueError(f"rotation: expected shape ({n_pings}, 3, 3), found {rotation.shape}")
    has_alt = np.isfinite(altitude)
    near = np.where(has_alt, altitude + cfg.nadir_margin_m, np.inf)
    water = range_m[None, :] < near[:, None]
    mask = np.where(water, MASK_WATER_COLUMN, MASK_VALID).astype(np.uint8)
    mask = np.repeat(mask[:, None, :], 2, axis=1)
    mask[~has_alt] |= MASK_NO_HIT
    mask[~np.isfinite(intensity)] |= MASK_NO_HIT
    if cfg.beam_limits and beam_limits_rad is not None:
        lo, hi = beam_limits_rad
        margin = math.radians(cfg.beam_margin_deg)
        theta = flat_seabed_depression(range_m, np.where(has_alt, altitude, np.nan), rotation)
        outside = np.isfinite(theta) & ((theta < lo - margin) | (theta > hi + margin))
        mask[outside] |= MASK_OUT_OF_BEAM
    if cfg.shadow_threshold > 0:
        seabed = mask == MASK_VALID
        norm = normalize_intensity(intensity, seabed).astype(np.float64)
        size = (cfg.shadow_smooth_pings, cfg.shadow_smooth_bins)
        smooth = box_mean(np.transpose(norm, (1, 0, 2)), np.transpose(seabed, (1, 0, 2)), size)
        dark = np.transpose(smooth, (1, 0, 2)) < cfg.shadow_threshold
        mask[seabed & dark] |= MASK_SHADOW
    return mask


def sonar_only_mask(
    line: Any, cfg: SonarMaskConfig | Mapping[str, Any] | None = None
) -> np.ndarray:
    """:func:`sonar_mask` of a :class:`~sss2bathy.survey.SidescanLine` (its sensor's beam)."""
    sensor = getattr(line, "sensor", None)
    limits = None if sensor is None else tuple(sensor.beam_limits_rad)
    return sonar_mask(line.intensity, line.range_m, line.altitude_m, line.rotation, limits, cfg)


def sonar_normalized_intensity(
    line: Any, cfg: SonarMaskConfig | Mapping[str, Any] | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """``(normalised intensity (P, 2, B) float32, sonar mask (P, 2, B) uint8)`` of a line:
    the intensity normalised over its sonar-only valid bins (the CNN's input, the Lambertian
    target), identical with or without an MBES grid."""
    mask = sonar_only_mask(line, cfg)
    valid = (mask == MASK_VALID) & np.isfinite(line.intensity)
    return normalize_intensity(line.intensity, valid), mask


def relative_channel(intensity: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """``(P, 2, B)`` float32 ``relative`` channel of a line: its normalised ``intensity``
    relative to the along-track mean of the sonar-valid bins (``mask == MASK_VALID``) at the
    same range (:func:`~sss2bathy.data.normalize.relative_intensity`); line-level, so
    training windows and whole-line prediction see the same values."""
    return relative_intensity(intensity, (mask == MASK_VALID) & np.isfinite(intensity))


# ------------------------------------------------------------------------ inputs
def check_channels(channels: Sequence[str] | None, name: str = "input_channels") -> tuple[str, ...]:
    """Validated channel names (``None``: intensity only); ``intensity`` first, no repeats."""
    if channels is None:
        return DEFAULT_CHANNELS
    if isinstance(channels, str) or not isinstance(channels, Sequence):
        raise ValueError(f"{name}: expected a list of channel names, found {channels!r}")
    out = tuple(str(c) for c in channels)
    unknown = [c for c in out if c not in CHANNELS]
    if not out or out[0] not in INTENSITY_CHANNELS or unknown or len(set(out)) != len(out):
        raise ValueError(
            f"{name}: expected distinct names of {list(CHANNELS)} starting with one of "
            f"{list(INTENSITY_CHANNELS)}, found {list(out)}"
        )
    return out


def input_channels(
    intensity: np.ndarray,
    range_m: np.ndarray,
    altitude_m: np.ndarray,
    r_max: float,
    channels: Sequence[str] | None = None,
    relative: np.ndarray | None = None,
    opposite: np.ndarray | None = None,
) -> np.ndarray:
    """Stack the CNN's input channels of a waterfall (or a window of one).

    Args:
        intensity: ``(..., P, B)`` normalised intensity.
        range_m: ``(B,)`` slant ranges of the bins (m).
        altitude_m: ``(P,)`` altitude per ping (m); NaN reads as "no seabed" (grazing 0).
        r_max: the line's largest slant range (m), the scale of ``range``.
        channels: names from :data:`CHANNELS` (None: intensity only).
        relative: ``(..., P, B)`` the ``relative`` channel of the same bins
            (:func:`relative_channel` of the whole line, then cut like ``intensity``);
            needed when ``channels`` holds ``relative``.
        opposite: ``(..., P, B)`` the other head's normalised intensity at the same pings and
            bins (same range); needed when ``channels`` holds ``opposite``.

    Returns:
        ``(..., C, P, B)`` float32: ``intensity``; ``relative``; ``grazing`` = ``altitude / r`` where
        ``r >= altitude`` (the sine of the flat-seabed grazing angle), else 0;
        ``range`` = ``r / r_max``; ``opposite``.
    """
    channels = check_channels(channels)
    x = np.asarray(intensity, np.float32)
    r = np.asarray(range_m, np.float64)
    h = np.asarray(altitude_m, np.float64)
    if x.ndim < 2 or x.shape[-1] != r.shape[0] or x.shape[-2] != h.shape[0]:
        raise ValueError(
            f"intensity: expected shape (..., {h.shape[0]}, {r.shape[0]}) of the altitudes and "
            f"ranges, found {x.shape}"
        )
    if not (math.isfinite(r_max) and r_max > 0):
        raise ValueError(f"r_max: expected a positive range (m), found {r_max!r}")
    given = {"intensity": x, "relative": relative, "opposite": opposite}
    what = {"relative": "the 'relative' channel", "opposite": "the other head's intensity"}
    for name, label in what.items():
        if name in channels and (given[name] is None or np.shape(given[name]) != x.shape):
            found = None if given[name] is None else np.shape(given[name])
            raise ValueError(
                f"{name}: expected {label} of shape {x.shape} like intensity, found {found}"
            )
    out = []
    for name in channels:
        if name in given:
            out.append(np.asarray(given[name], np.float32))
            continue
        if name == "grazing":
            hh = np.nan_to_num(h, nan=0.0)[:, None]
            with np.errstate(invalid="ignore", divide="ignore"):
                g = np.where((r[None, :] >= hh) & (hh > 0), hh / r[None, :], 0.0)
        else:  # range
            g = np.broadcast_to(r[None, :] / r_max, (h.shape[0], r.shape[0]))
        out.append(np.broadcast_to(g.astype(np.float32), x.shape))
    return np.stack(out, axis=-3).astype(np.float32, copy=False)
