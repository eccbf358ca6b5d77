"""First-bottom-return detection on a sidescan waterfall (altitude where the altimeter is missing).

Algorithm (per ping, vectorised over pings):

1. **Smooth**: a running median over ``smooth_pings`` pings along track (the seabed edge moves
   little from ping to ping; a one-ping burst is dropped) and a box filter over
   ``smooth_bins`` bins along range (suppresses speckle).
2. **Coarse pick**: levels of the smoothed ping — the water column/shadow level ``floor`` (a low
   quantile) and the seabed level ``top`` (a high quantile) — and the first bin from which
   ``sustain_bins`` consecutive smoothed samples exceed ``floor + coarse_fraction (top - floor)``.
3. **Water-column noise**: mean ``mu`` and standard deviation ``sigma`` of the smoothed samples
   between ``min_range_m`` and the coarse pick (the water column of this ping; when it holds
   fewer than 3 bins, ``floor`` and the robust spread of the darkest bins stand in).
4. **Threshold** ``mu + noise_sigmas * sigma`` (never above the coarse threshold): the final pick
   is the earliest sustained rise above it, at or before the coarse pick.
5. **Sub-bin edge**: smoothing moves the edge earlier by up to ``smooth_bins // 2`` bins, so the
   pick is refined to the first sample (filtered along track only) above the threshold (raised
   for single samples by sqrt(smooth_bins)) within that many bins; the altitude is the leading edge of the picked bin (midway to the previous bin centre).
6. **Along track**: pings without a rise (no contrast) are filled by linear interpolation
   between detected pings, then a running median over ``median_pings`` pings (mirrored at the
   ends) removes isolated false picks (fish, noise bursts).

At nadir on a flat seafloor the first echo arrives at slant range = altitude, so the pick is
the sonar's height above the closest seabed. A surface echo arriving earlier (towfish deeper
than it is high) is excluded with ``min_range_m`` (e.g. a little beyond the sensor depth).
"""

from __future__ import annotations

import numpy as np
from scipy.ndimage import median_filter, uniform_filter1d

__all__ = ["detect_first_return"]


def _first_sustained(above: np.ndarray, sustain: int) -> tuple[np.ndarray, np.ndarray]:
    """Index of the first run of ``sustain`` True values per row, and whether there is one."""
    P, B = above.shape
    csum = np.concatenate([np.zeros((P, 1)), np.cumsum(above, axis=1)], axis=1)
    n_win = B - sustain + 1
    runs = (csum[:, sustain:] - csum[:, :n_win]) == sustain
    return np.argmax(runs, axis=1), runs.any(axis=1)


def detect_first_return(
    waterfall: np.ndarray,
    range_m: np.ndarray,
    *,
    smooth_bins: int = 3,
    smooth_pings: int = 3,
    floor_quantile: float = 0.1,
    top_quantile: float = 0.95,
    coarse_fraction: float = 0.5,
    noise_sigmas: float = 5.0,
    sustain_bins: int = 4,
    median_pings: int = 5,
    min_range_m: float = 0.0,
) -> np.ndarray:
    """Altitude (m) of the sonar above the seabed from the first bottom return of each ping.

    Args:
        waterfall: ``(P, B)`` intensities (any linear scale), bin 0 nearest the sonar; e.g. the
            mean of the port and starboard waterfalls.
        range_m: ``(B,)`` slant range of each bin (m), positive and increasing.
        smooth_bins: box-filter width along range (bins, >= 1).
        smooth_pings: box-filter width along track (pings, >= 1).
        floor_quantile: quantile of the smoothed ping taken as the water-column level.
        top_quantile: quantile of the smoothed ping taken as the seabed level.
        coarse_fraction: coarse threshold position between the two levels, in ``(0, 1)``.
        noise_sigmas: final threshold, in water-column noise standard deviations above its mean.
        sustain_bins: consecutive bins that must exceed a threshold (>= 1; more than
            ``smooth_bins`` so that one noise spike cannot pass alone).
        median_pings: running-median window along track (odd, >= 1; 1 disables it).
        min_range_m: picks at slant ranges below this are ignored (surface echo, ringing).

    Returns:
        ``(P,)`` float64 altitudes (m), never NaN.

    Raises:
        ValueError: on bad arguments, or when no ping shows a bottom return.
    """
    w = np.asarray(waterfall, dtype=np.float64)
    r = np.asarray(range_m, dtype=np.float64)
    if w.ndim != 2 or w.shape[0] < 1 or w.shape[1] < 2:
        raise ValueError(f"waterfall: expected a (P, B) array with B >= 2, found shape {w.shape}")
    if r.shape != (w.shape[1],):
        raise ValueError(f"range_m: expected shape ({w.shape[1]},), found {r.shape}")
    if not np.all(np.isfinite(r)) or np.any(r <= 0) or np.any(np.diff(r) <= 0):
        raise ValueError("range_m: expected positive, finite, increasing slant ranges")
    if not np.all(np.isfinite(w)):
        raise ValueError("waterfall: expected finite intensities, found NaN/inf")
    if smooth_pings < 1:
        raise ValueError(f"smooth_pings: expected >= 1, found {smooth_pings}")
    if smooth_bins < 1 or not 1 <= sustain_bins <= w.shape[1]:
        raise ValueError(
            f"smooth_bins/sustain_bins: expected >= 1 and sustain_bins <= {w.shape[1]} bins, "
            f"found {smooth_bins}/{sustain_bins}"
        )
    if median_pings < 1 or median_pings % 2 == 0:
        raise ValueError(f"median_pings: expected an odd number >= 1, found {median_pings}")
    if not 0.0 < coarse_fraction < 1.0:
        raise ValueError(f"coarse_fraction: expected a value in (0, 1), found {coarse_fraction}")
    if not noise_sigmas > 0:
        raise ValueError(f"noise_sigmas: expected > 0, found {noise_sigmas}")
    if not 0.0 <= floor_quantile < top_quantile <= 1.0:
        raise ValueError(
            "floor_quantile/top_quantile: expected 0 <= floor < top <= 1, "
            f"found {floor_quantile}/{top_quantile}"
        )

    P, B = w.shape
    rows, bins = np.arange(P), np.arange(B)
    in_range = r >= min_range_m
    w = median_filter(w, size=(min(smooth_pings, P), 1), mode="nearest")
    s = uniform_filter1d(w, size=smooth_bins, axis=1, mode="nearest")
    floor = np.quantile(s, floor_quantile, axis=1)
    top = np.quantile(s, top_quantile, axis=1)
    coarse_thr = floor + coarse_fraction * (top - floor)
    coarse, found = _first_sustained((s > coarse_thr[:, None]) & in_range, sustain_bins)
    found &= top > floor

    # Water-column statistics between min_range_m and the coarse pick (minus the smoothing),
    # from the samples before range smoothing (independent), scaled to the smoothed signal.
    column = in_range[None, :] & (bins[None, :] < (coarse - smooth_bins)[:, None])
    enough = column.sum(axis=1) >= 3
    col = np.where(column & enough[:, None], w, np.nan)
    col[~enough] = 0.0
    mu = np.where(enough, np.nanmean(col, axis=1), floor)
    sd = np.nanstd(col, axis=1) / np.sqrt(smooth_bins)
    dark = np.where(s <= floor[:, None], s, np.nan)
    mad = 1.4826 * np.nanmedian(np.abs(dark - np.nanmedian(dark, axis=1)[:, None]), axis=1)
    sigma = np.where(enough, sd, mad)
    threshold = np.minimum(mu + noise_sigmas * sigma, coarse_thr)

    above = (s > threshold[:, None]) & in_range[None, :] & (bins[None, :] <= coarse[:, None])
    first, fine_found = _first_sustained(above, min(sustain_bins, B))
    first = np.where(fine_found, np.minimum(first, coarse), coarse)

    half = smooth_bins // 2
    window = np.clip(first[:, None] + np.arange(-half, half + 1)[None, :], 0, B - 1)
    # A single sample is noisier than the range-smoothed signal: its own threshold.
    raw_threshold = np.minimum(mu + noise_sigmas * sigma * np.sqrt(smooth_bins), coarse_thr)
    raw_above = (w[rows[:, None], window] > raw_threshold[:, None]) & in_range[window]
    pick = np.where(raw_above.any(axis=1), window[rows, np.argmax(raw_above, axis=1)], first)
    # Leading edge of the picked bin (bins are range cells centred on range_m).
    edges = np.concatenate([[max(r[0] - 0.5 * (r[1] - r[0]), 0.0)], 0.5 * (r[1:] + r[:-1])])
    altitude = np.maximum(edges[pick], min_range_m)

    if not found.any():
        raise ValueError(
            "waterfall: no first bottom return found in any ping (no bins rise above the "
            "water-column level)"
        )
    if not found.all():
        altitude = np.interp(rows, rows[found], altitude[found])
    if median_pings > 1 and P > 1:
        size = min(median_pings, 2 * ((P - 1) // 2) + 1)
        altitude = median_filter(altitude, size=size, mode="reflect")
    return altitude
