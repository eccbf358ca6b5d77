"""First-bottom-return detection on a sidescan waterfall (altitude where the altimeter is missing).

Algorithm (per ping, vectorised over pings):

0. **Unusable pings**: pings with non-finite samples, constant pings and pings mostly at the
   waterfall's maximum (saturated) are flagged (``bad``) and get no pick.
1. **Smooth**: a running median over ``smooth_pings`` pings along track (the seabed edge moves
   little from ping to ping; a one-ping burst is dropped) and a box filter over
   ``smooth_bins`` bins along range (suppresses speckle).
2. **Blanking** (transducer ring-down): the zone nearer than ``blanking_m`` is never searched.
   With ``auto_blanking`` the zone is also estimated from the near-field decay of the
   along-track median ping: when that ping starts bright (above the coarse threshold of
   step 3), the ring-down ends where it has decayed to the water-column level (median plus
   3 robust deviations of the dark gap before the bottom rise), plus ``smooth_bins`` bins.
   Per ping, a run of saturated samples from bin 0 extends the zone.
3. **Coarse pick**: levels of the smoothed ping — the water column/shadow level ``floor`` (a low
   quantile) and the seabed level ``top`` (a high quantile) — and the first bin beyond the
   blanking from which ``sustain_bins`` consecutive smoothed samples exceed
   ``floor + coarse_fraction (top - floor)``.
4. **Water-column noise**: mean ``mu`` and standard deviation ``sigma`` of the samples between
   the blanking and the coarse pick (when it holds fewer than 3 bins, ``floor`` and the robust
   spread of the darkest bins stand in).
5. **Threshold** ``mu + noise_sigmas * sigma`` (never above the coarse threshold): the final pick
   is the earliest sustained rise above it, at or before the coarse pick.
6. **Sub-bin edge**: smoothing moves the edge earlier by up to ``smooth_bins // 2`` bins, so the
   pick is refined to the first sample (filtered along track only) above the threshold (raised
   for single samples by sqrt(smooth_bins)) within that many bins; the altitude is the leading
   edge of the picked bin (midway to the previous bin centre).
7. **Unsupported picks are rejected**: a rise that is already above the threshold at the first
   searchable bin may have begun inside the blanking zone, so its edge is unknown (the
   altitude stays NaN, ``rejected``).
8. **Along track**: a running median over ``median_pings`` picked pings removes isolated false
   picks (fish, noise bursts); gaps of at most ``max_fill_pings`` pings between picks are
   filled by linear interpolation (``interpolated``); longer gaps stay NaN.

At nadir on a flat seafloor the first echo arrives at slant range = altitude, so the pick is
the sonar's height above the closest seabed. A surface echo arriving earlier (towfish deeper
than it is high) is excluded with ``min_range_m`` (e.g. a little beyond the sensor depth).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.ndimage import median_filter, uniform_filter1d

__all__ = [
    "BottomPicks",
    "calibrate_to_altimeter",
    "detect_first_return",
    "detector_accuracy",
    "running_median",
]


@dataclass(frozen=True)
class BottomPicks:
    """What the detector found, per ping.

    Attributes:
        altitude_m: ``(P,)`` altitude (m) > 0, NaN where no supported pick.
        picked: ``(P,)`` a supported first return was picked in this ping.
        interpolated: ``(P,)`` filled between picks (short gaps only).
        rejected: ``(P,)`` a rise was found but its edge lies in the blanking zone.
        bad: ``(P,)`` unusable samples (non-finite, constant or saturated over the ping).
        blanking_m: the blanking range used (m; per-ping saturation may extend it).
    """

    altitude_m: np.ndarray
    picked: np.ndarray
    interpolated: np.ndarray
    rejected: np.ndarray
    bad: np.ndarray
    blanking_m: float

    def counts(self) -> dict[str, int]:
        return {
            "picked": int(self.picked.sum()),
            "interpolated": int(self.interpolated.sum()),
            "rejected": int(self.rejected.sum()),
            "bad_pings": int(self.bad.sum()),
            "no_pick": int(np.isnan(self.altitude_m).sum()),
        }


def _first_sustained(above: np.ndarray, sustain: int) -> tuple[np.ndarray, np.ndarray]:
    """Index of the first run of ``sustain`` True values per row, and whether there is one."""
    P, B = above.shape
    csum = np.concatenate([np.zeros((P, 1)), np.cumsum(above, axis=1)], axis=1)
    n_win = B - sustain + 1
    runs = (csum[:, sustain:] - csum[:, :n_win]) == sustain
    return np.argmax(runs, axis=1), runs.any(axis=1)


def bad_pings(w: np.ndarray, saturated_fraction: float = 0.5) -> dict[str, np.ndarray]:
    """``(P,)`` masks of pings that carry no usable echo: ``nonfinite`` (any NaN/inf sample),
    ``constant`` (every sample equal) and ``saturated`` (more than ``saturated_fraction`` of the
    samples at the waterfall's maximum)."""
    w = np.asarray(w, dtype=np.float64)
    nonfinite = ~np.isfinite(w).all(axis=1)
    safe = np.where(np.isfinite(w), w, 0.0)
    constant = ~nonfinite & (np.ptp(safe, axis=1) == 0)
    top = safe[~nonfinite].max() if (~nonfinite).any() else 0.0
    at_top = safe >= top * (1 - 1e-6) if top > 0 else np.zeros_like(safe, bool)
    saturated = ~nonfinite & ~constant & (at_top.mean(axis=1) > saturated_fraction)
    return {"nonfinite": nonfinite, "constant": constant, "saturated": saturated}


def _auto_blanking(s: np.ndarray, coarse_fraction: float, pad_bins: int) -> int:
    """First bin past the ring-down of the along-track median ping (0 when it starts dark)."""
    prof = np.median(s, axis=0)
    floor, top = np.quantile(prof, 0.1), np.quantile(prof, 0.95)
    if not top > floor:
        return 0
    thr = floor + coarse_fraction * (top - floor)
    if prof[0] <= thr:
        return 0
    below = prof <= thr
    if not below.any():
        return prof.size  # bright from the first to the last bin: nothing can be supported
    drop = int(np.argmax(below))
    rise, found = _first_sustained((prof > thr)[None, drop:], min(3, prof.size - drop))
    end = drop + int(rise[0]) if found[0] else prof.size
    gap = prof[drop:end]
    if gap.size < 2:
        return min(end + pad_bins, prof.size)
    tail = gap[gap.size // 2 :]
    level = np.median(tail) + 3.0 * 1.4826 * np.median(np.abs(tail - np.median(tail)))
    settled = int(np.argmax(gap <= level))
    return min(drop + settled + pad_bins, prof.size)


def running_median(
    x: np.ndarray,
    ok: np.ndarray,
    size: int,
    *,
    mode: str = "reflect",
    fill: float | None = None,
) -> np.ndarray:
    """Running median over the ``ok`` entries only (in order), window ``size`` (odd; shrunk
    to the number of entries); the other entries keep ``x`` (``fill=None``) or get ``fill``.
    ``mode``: :func:`scipy.ndimage.median_filter`'s edge mode."""
    out = x.copy() if fill is None else np.full(x.shape, fill, dtype=np.float64)
    idx = np.flatnonzero(ok)
    if idx.size:
        win = max(1, min(size, 2 * ((idx.size - 1) // 2) + 1))
        out[idx] = median_filter(x[idx], size=win, mode=mode)
    return out


@dataclass(frozen=True)
class FirstReturnOptions:
    """The settings of :func:`detect_first_return` (its Args say what each does), with their
    defaults declared once; :meth:`check` refuses a bad one (``ValueError``)."""

    smooth_bins: int = 3
    smooth_pings: int = 3
    floor_quantile: float = 0.1
    top_quantile: float = 0.95
    coarse_fraction: float = 0.5
    noise_sigmas: float = 5.0
    sustain_bins: int = 4
    median_pings: int = 5
    min_range_m: float = 0.0
    blanking_m: float = 0.0
    auto_blanking: bool = True
    saturated_fraction: float = 0.5
    max_fill_pings: int = 5

    def check(self, n_bins: int) -> None:
        """Every setting within its bounds for a waterfall of ``n_bins`` bins."""
        if self.smooth_pings < 1:
            raise ValueError(f"smooth_pings: expected >= 1, found {self.smooth_pings}")
        if self.smooth_bins < 1 or not 1 <= self.sustain_bins <= n_bins:
            raise ValueError(
                f"smooth_bins/sustain_bins: expected >= 1 and sustain_bins <= {n_bins} bins, "
                f"found {self.smooth_bins}/{self.sustain_bins}"
            )
        if self.median_pings < 1 or self.median_pings % 2 == 0:
            raise ValueError(
                f"median_pings: expected an odd number >= 1, found {self.median_pings}"
            )
        if not 0.0 < self.coarse_fraction < 1.0:
            raise ValueError(
                f"coarse_fraction: expected a value in (0, 1), found {self.coarse_fraction}"
            )
        if not self.noise_sigmas > 0:
            raise ValueError(f"noise_sigmas: expected > 0, found {self.noise_sigmas}")
        if not 0.0 <= self.floor_quantile < self.top_quantile <= 1.0:
            raise ValueError(
                "floor_quantile/top_quantile: expected 0 <= floor < top <= 1, "
                f"found {self.floor_quantile}/{self.top_quantile}"
            )
        if not (np.isfinite(self.blanking_m) and self.blanking_m >= 0):
            raise ValueError(f"blanking_m: expected a distance >= 0 (m), found {self.blanking_m}")
        if not 0.0 < self.saturated_fraction <= 1.0:
            raise ValueError(
                f"saturated_fraction: expected a value in (0, 1], found {self.saturated_fraction}"
            )
        if self.max_fill_pings < 0:
            raise ValueError(
                f"max_fill_pings: expected an integer >= 0, found {self.max_fill_pings}"
            )


_F = FirstReturnOptions  # the defaults of detect_first_return's keywords


def detect_first_return(
    waterfall: np.ndarray,
    range_m: np.ndarray,
    *,
    smooth_bins: int = _F.smooth_bins,
    smooth_pings: int = _F.smooth_pings,
    floor_quantile: float = _F.floor_quantile,
    top_quantile: float = _F.top_quantile,
    coarse_fraction: float = _F.coarse_fraction,
    noise_sigmas: float = _F.noise_sigmas,
    sustain_bins: int = _F.sustain_bins,
    median_pings: int = _F.median_pings,
    min_range_m: float = _F.min_range_m,
    blanking_m: float = _F.blanking_m,
    auto_blanking: bool = _F.auto_blanking,
    saturated_fraction: float = _F.saturated_fraction,
    max_fill_pings: int = _F.max_fill_pings,
) -> BottomPicks:
    """Altitude (m) of the sonar above the seabed from the first bottom return of each ping.

    Args:
        waterfall: ``(P, B)`` intensities (any linear scale), bin 0 nearest the sonar; e.g. the
            mean of the port and starboard waterfalls. Non-finite samples flag their ping.
        range_m: ``(B,)`` slant range of each bin (m), positive and increasing.
        smooth_bins: box-filter width along range (bins, >= 1).
        smooth_pings: median-filter width along track (pings, >= 1).
        floor_quantile: quantile of the smoothed ping taken as the water-column level.
        top_quantile: quantile of the smoothed ping taken as the seabed level.
        coarse_fraction: coarse threshold position between the two levels, in ``(0, 1)``.
        noise_sigmas: final threshold, in water-column noise standard deviations above its mean.
        sustain_bins: consecutive bins that must exceed a threshold (>= 1; more than
            ``smooth_bins`` so that one noise spike cannot pass alone).
        median_pings: running-median window along track over picked pings (odd, >= 1).
        min_range_m: picks at slant ranges below this are ignored (surface echo).
        blanking_m: the ring-down/blanking zone (m) never searched.
        auto_blanking: also estimate the blanking zone from the near-field decay.
        saturated_fraction: a ping with more than this fraction of samples at the waterfall's
            maximum is saturated (flagged ``bad``).
        max_fill_pings: longest run of pings without a pick filled by interpolation (0: none).

    Returns:
        :class:`BottomPicks` (altitudes NaN where nothing supports a pick).

    Raises:
        ValueError: on bad arguments.
    """
    w = np.asarray(waterfall, dtype=np.float64)
    r = np.asarray(range_m, dtype=np.float64)
    if w.ndim != 2 or w.shape[0] < 1 or w.shape[1] < 2:
        raise ValueError(f"waterfall: expected a (P, B) array with B >= 2, found shape {w.shape}")
    if r.shape != (w.shape[1],):
        raise ValueError(f"range_m: expected shape ({w.shape[1]},), found {r.shape}")
    if not np.all(np.isfinite(r)) or np.any(r <= 0) or np.any(np.diff(r) <= 0):
        raise ValueError("range_m: expected positive, finite, increasing slant ranges")
    o = FirstReturnOptions(
        smooth_bins=smooth_bins,
        smooth_pings=smooth_pings,
        floor_quantile=floor_quantile,
        top_quantile=top_quantile,
        coarse_fraction=coarse_fraction,
        noise_sigmas=noise_sigmas,
        sustain_bins=sustain_bins,
        median_pings=median_pings,
        min_range_m=min_range_m,
        blanking_m=blanking_m,
        auto_blanking=auto_blanking,
        saturated_fraction=saturated_fraction,
        max_fill_pings=max_fill_pings,
    )
    o.check(w.shape[1])

    P, B = w.shape
    # 0. unusable pings get no pick
    flags = bad_pings(w, o.saturated_fraction)
    bad = flags["nonfinite"] | flags["constant"] | flags["saturated"]
    empty = BottomPicks(
        np.full(P, np.nan), np.zeros(P, bool), np.zeros(P, bool), np.zeros(P, bool), bad, 0.0
    )
    if bad.all():
        return empty
    safe = np.where(np.isfinite(w), w, 0.0)
    # 1. smooth; 2. blanking
    w, s = _smooth(safe, bad, o)
    blank, blanking_used = _blanking(s[~bad], r, o)
    if blank >= B - o.sustain_bins:
        return BottomPicks(
            empty.altitude_m, empty.picked, empty.interpolated, ~bad, bad, blanking_used
        )
    blank_p, searchable = _searchable(safe, bad, blank, r, o)
    # 3. coarse pick; 4.-5. water-column noise and the final threshold; 7. unsupported picks
    floor, coarse_thr, coarse, found = _coarse_pick(s, searchable, bad, o)
    mu, sigma = _water_column(w, s, searchable, coarse, floor, o)
    first, unsupported = _fine_pick(s, mu, sigma, coarse_thr, searchable, coarse, blank_p, r, o)
    rejected = found & unsupported
    found &= ~rejected
    # 6. sub-bin edge
    altitude, found = _leading_edge(w, first, found, mu, sigma, coarse_thr, searchable, r, o)
    # 8. along track
    altitude, interpolated = _along_track(altitude, found, bad, o)
    return BottomPicks(altitude, found, interpolated, rejected, bad, blanking_used)


def _smooth(
    safe: np.ndarray, bad: np.ndarray, o: FirstReturnOptions
) -> tuple[np.ndarray, np.ndarray]:
    """Step 1: ``(w, s)``: the usable pings median-filtered over ``smooth_pings`` pings along
    track (bad pings 0), and ``w`` box-filtered over ``smooth_bins`` bins along range. Pure."""
    good = np.flatnonzero(~bad)
    wg = median_filter(safe[good], size=(min(o.smooth_pings, good.size), 1), mode="nearest")
    w = np.zeros_like(safe)
    w[good] = wg
    return w, uniform_filter1d(w, size=o.smooth_bins, axis=1, mode="nearest")


def _blanking(s_good: np.ndarray, r: np.ndarray, o: FirstReturnOptions) -> tuple[int, float]:
    """Step 2: ``(first searchable bin, its range in m)``: the configured blanking zone, or the
    ring-down of the median ping where ``auto_blanking`` finds a longer one. Pure."""
    blank = int(np.searchsorted(r, o.blanking_m, side="left")) if o.blanking_m > 0 else 0
    if o.auto_blanking:
        blank = max(blank, _auto_blanking(s_good, o.coarse_fraction, o.smooth_bins))
    return blank, float(r[blank - 1]) if 0 < blank <= r.size else 0.0


def _searchable(
    safe: np.ndarray, bad: np.ndarray, blank: int, r: np.ndarray, o: FirstReturnOptions
) -> tuple[np.ndarray, np.ndarray]:
    """Step 2, per ping: ``(first searchable bin (P,), searchable (P, B))``: beyond the
    blanking, beyond a run of saturated samples from bin 0 (plus the smoothing), and at or
    beyond ``min_range_m``. Pure."""
    B = safe.shape[1]
    sat_level = safe[~bad].max()
    saturated = safe >= sat_level * (1 - 1e-6)
    sat_run = np.where(saturated.all(axis=1), B, np.argmin(saturated, axis=1))
    blank_p = np.maximum(blank, np.where(saturated[:, 0], sat_run + o.smooth_bins, 0))
    bins = np.arange(B)
    searchable = (r[None, :] >= o.min_range_m) & (bins[None, :] >= blank_p[:, None])
    return blank_p, searchable


def _coarse_pick(
    s: np.ndarray, searchable: np.ndarray, bad: np.ndarray, o: FirstReturnOptions
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Step 3: ``(floor, coarse threshold, coarse pick bin, found)`` per ping: the first
    searchable sustained rise above ``floor + coarse_fraction (top - floor)``. Pure."""
    floor = np.quantile(s, o.floor_quantile, axis=1)
    top = np.quantile(s, o.top_quantile, axis=1)
    coarse_thr = floor + o.coarse_fraction * (top - floor)
    coarse, found = _first_sustained((s > coarse_thr[:, None]) & searchable, o.sustain_bins)
    found &= (top > floor) & ~bad
    return floor, coarse_thr, coarse, found


def _water_column(
    w: np.ndarray,
    s: np.ndarray,
    searchable: np.ndarray,
    coarse: np.ndarray,
    floor: np.ndarray,
    o: FirstReturnOptions,
) -> tuple[np.ndarray, np.ndarray]:
    """Step 4: ``(mu, sigma)`` per ping: mean and standard deviation (scaled to the smoothed
    signal) of the samples between the blanking and the coarse pick minus the smoothing;
    where they are fewer than 3, ``floor`` and the robust spread of the darkest bins. Pure."""
    bins = np.arange(w.shape[1])
    column = searchable & (bins[None, :] < (coarse - o.smooth_bins)[:, None])
    enough = column.sum(axis=1) >= 3
    col = np.where(column & enough[:, None], w, np.nan)
    col[~enough] = 0.0
    mu = np.where(enough, np.nanmean(col, axis=1), floor)
    sd = np.nanstd(col, axis=1) / np.sqrt(o.smooth_bins)
    dark = np.where(s <= floor[:, None], s, np.nan)
    dark[np.isnan(dark).all(axis=1)] = 0.0
    mad = 1.4826 * np.nanmedian(np.abs(dark - np.nanmedian(dark, axis=1)[:, None]), axis=1)
    return mu, np.where(enough, sd, mad)


def _fine_pick(
    s: np.ndarray,
    mu: np.ndarray,
    sigma: np.ndarray,
    coarse_thr: np.ndarray,
    searchable: np.ndarray,
    coarse: np.ndarray,
    blank_p: np.ndarray,
    r: np.ndarray,
    o: FirstReturnOptions,
) -> tuple[np.ndarray, np.ndarray]:
    """Steps 5 and 7: ``(pick bin, unsupported)`` per ping: the earliest sustained rise above
    ``mu + noise_sigmas * sigma`` (at most the coarse threshold) at or before the coarse
    pick; unsupported where that rise is already above the threshold at the first searchable
    bin (its edge may lie in the blanking zone). Pure."""
    B = s.shape[1]
    bins = np.arange(B)
    threshold = np.minimum(mu + o.noise_sigmas * sigma, coarse_thr)
    above = (s > threshold[:, None]) & searchable & (bins[None, :] <= coarse[:, None])
    first, fine_found = _first_sustained(above, min(o.sustain_bins, B))
    first = np.where(fine_found, np.minimum(first, coarse), coarse)
    start = np.maximum(blank_p, int(np.searchsorted(r, o.min_range_m, side="left")))
    return first, first <= start


def _leading_edge(
    w: np.ndarray,
    first: np.ndarray,
    found: np.ndarray,
    mu: np.ndarray,
    sigma: np.ndarray,
    coarse_thr: np.ndarray,
    searchable: np.ndarray,
    r: np.ndarray,
    o: FirstReturnOptions,
) -> tuple[np.ndarray, np.ndarray]:
    """Step 6: ``(altitude, found)``: the pick refined to the first single sample above its
    own (sqrt(smooth_bins) higher) threshold within ``smooth_bins // 2`` bins, the altitude
    the leading edge of that bin; NaN (not found) where it is not positive. Pure."""
    P, B = w.shape
    rows = np.arange(P)
    half = o.smooth_bins // 2
    window = np.clip(first[:, None] + np.arange(-half, half + 1)[None, :], 0, B - 1)
    # A single sample is noisier than the range-smoothed signal: its own threshold.
    raw_threshold = np.minimum(mu + o.noise_sigmas * sigma * np.sqrt(o.smooth_bins), coarse_thr)
    raw_above = (w[rows[:, None], window] > raw_threshold[:, None]) & np.take_along_axis(
        searchable, window, axis=1
    )
    pick = np.where(raw_above.any(axis=1), window[rows, np.argmax(raw_above, axis=1)], first)
    # Leading edge of the picked bin (bins are range cells centred on range_m).
    edges = np.concatenate([[max(r[0] - 0.5 * (r[1] - r[0]), 0.0)], 0.5 * (r[1:] + r[:-1])])
    altitude = np.where(found, edges[pick], np.nan)
    found = found & (altitude > 0)
    return np.where(found, altitude, np.nan), found


def _along_track(
    altitude: np.ndarray, found: np.ndarray, bad: np.ndarray, o: FirstReturnOptions
) -> tuple[np.ndarray, np.ndarray]:
    """Step 8: ``(altitude, interpolated)``: a running median over ``median_pings`` picked
    pings, and gaps of at most ``max_fill_pings`` pings between picks (not bad pings) filled
    linearly (WARNING-worthy repairs: the caller counts ``interpolated``). Pure."""
    P = altitude.size
    rows = np.arange(P)
    altitude = running_median(altitude, found, o.median_pings)
    interpolated = np.zeros(P, bool)
    idx = np.flatnonzero(found)
    if o.max_fill_pings > 0 and idx.size >= 2:
        gaps = np.diff(idx) - 1
        for a, b, g in zip(idx[:-1], idx[1:], gaps, strict=True):
            if 0 < g <= o.max_fill_pings:
                interpolated[a + 1 : b] = True
        fill = interpolated & ~bad
        interpolated = fill
        altitude[fill] = np.interp(rows[fill], idx, altitude[idx])
    return altitude, interpolated


def calibrate_to_altimeter(
    first_return_m: np.ndarray, altimeter_m: np.ndarray, n_ref: int = 20
) -> tuple[np.ndarray, np.ndarray]:
    """Detector altitudes shifted by the detector's local error against the altimeter.

    The first return is not the altitude everywhere: where the nadir echo is too weak
    (outside the main beam, a dark seabed) the pick is the main beam's first echo, up to
    ``1 / sin(tilt + beam / 2)`` times farther, and a ridge beside the track returns before
    the seabed beneath. Both persist over many pings, so a ping without an altimeter value
    gets ``first_return + median(altimeter - first_return)`` over the ``n_ref`` pings nearest
    in ping order that have both.

    Args:
        first_return_m: ``(P,)`` detector altitudes (NaN: no pick).
        altimeter_m: ``(P,)`` recorded altitudes (NaN: none).
        n_ref: reference pings per offset (>= 1).

    Returns:
        ``(altitude, offset)``: ``(P,)`` calibrated first returns (the raw pick where no ping
        has both values, or where the shift would not leave an altitude > 0) and the offset
        applied (0 there).
    """
    fr = np.asarray(first_return_m, dtype=np.float64)
    alt = np.asarray(altimeter_m, dtype=np.float64)
    if fr.ndim != 1 or alt.shape != fr.shape:
        raise ValueError(
            f"first_return_m, altimeter_m: expected equal 1-D shapes, found {fr.shape} and "
            f"{alt.shape}"
        )
    if int(n_ref) < 1:
        raise ValueError(f"n_ref: expected a count >= 1, found {n_ref}")
    offset = np.zeros(fr.shape)
    ref = np.flatnonzero(np.isfinite(fr) & np.isfinite(alt))
    if ref.size == 0:
        return fr.copy(), offset
    diff = alt[ref] - fr[ref]
    n = min(int(n_ref), ref.size)
    for i in np.flatnonzero(np.isfinite(fr) & ~np.isfinite(alt)):
        k = int(np.searchsorted(ref, i))
        lo, hi = max(0, k - n), min(ref.size, k + n)
        near = np.argsort(np.abs(ref[lo:hi] - i), kind="stable")[:n]
        offset[i] = float(np.median(diff[lo:hi][near]))
    out = fr + offset
    keep = ~(out > 0) & np.isfinite(fr)
    out[keep], offset[keep] = fr[keep], 0.0
    return out, offset


def detector_accuracy(
    first_return_m: np.ndarray, altimeter_m: np.ndarray, every: int = 5, n_ref: int = 20
) -> tuple[float, float, int] | None:
    """How well :func:`calibrate_to_altimeter` replaces the altimeter: cross-validated.

    Every ``every``-th ping having both values is hidden from the calibration and its
    calibrated first return compared with its altimeter value.

    Returns:
        ``(median |error|, max |error|, pings compared)`` (m), or None with fewer than 10
        pings having both.
    """
    fr = np.asarray(first_return_m, dtype=np.float64)
    alt = np.asarray(altimeter_m, dtype=np.float64)
    ref = np.flatnonzero(np.isfinite(fr) & np.isfinite(alt))
    if ref.size < 10:
        return None
    held = ref[:: max(int(every), 2)]
    hidden = alt.copy()
    hidden[held] = np.nan
    est, _ = calibrate_to_altimeter(fr, hidden, n_ref=n_ref)
    err = np.abs(est[held] - alt[held])
    return float(np.median(err)), float(np.max(err)), int(held.size)
