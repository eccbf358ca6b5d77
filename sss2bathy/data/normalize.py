"""Per-line sidescan intensity normalisation, shared by the CNN windows and the SIREN stages.

Sidescan intensities (linear, after the sonar's time-varying gain) carry an arbitrary
scale that changes between sonars, surveys, gain settings and even the two heads of one
sonar. Each head of each line is therefore divided by the **median intensity of its
valid bins** (bins on the seabed: not water column, shadow or outside the data), so the
typical seabed reads about 1, and the result is clipped to ``[0, clip_max]`` so a few
specular glints or targets cannot dominate a window. The median is robust to the
long-tailed speckle and to bright targets, and keeps the physics: a bin twice as bright
as the typical seabed reads 2 on every survey.

If a head has no valid bin, the line's median over both heads is used; if the line has
none either, the median of its positive finite bins; failing that, 1.
"""

from __future__ import annotations

import numpy as np

DEFAULT_CLIP_MAX = 8.0


def _median_scale(values: np.ndarray) -> float | None:
    values = values[np.isfinite(values)]
    if values.size == 0:
        return None
    med = float(np.median(values))
    return med if med > 0 else None


def normalize_intensity(
    intensity: np.ndarray, valid_mask: np.ndarray, clip_max: float = DEFAULT_CLIP_MAX
) -> np.ndarray:
    """Normalise one line's waterfalls so the typical valid seabed bin reads about 1.

    Args:
        intensity: ``(P, 2, B)`` linear (non-negative) intensities, side 0 port, 1 starboard.
        valid_mask: ``(P, 2, B)`` bool, True at bins used for the median (seabed bins).
        clip_max: upper clip of the normalised values (> 0).

    Returns:
        ``(P, 2, B)`` float32 in ``[0, clip_max]``: ``intensity / median_valid(head)``;
        non-finite inputs become 0.

    >>> import numpy as np
    >>> x = np.full((4, 2, 3), 50.0); x[:, 1] = 200.0
    >>> normalize_intensity(x, np.ones_like(x, bool))[0].tolist()
    [[1.0, 1.0, 1.0], [1.0, 1.0, 1.0]]
    """
    intensity = np.asarray(intensity)
    valid_mask = np.asarray(valid_mask)
    if intensity.ndim != 3 or intensity.shape[1] != 2:
        raise ValueError(f"intensity: expected shape (P, 2, B), found {intensity.shape}")
    if valid_mask.shape != intensity.shape:
        raise ValueError(
            f"valid_mask: expected shape {intensity.shape} like intensity, found {valid_mask.shape}"
        )
    if valid_mask.dtype != np.bool_:
        raise ValueError(f"valid_mask: expected dtype bool, found {valid_mask.dtype}")
    if not (np.isfinite(clip_max) and clip_max > 0):
        raise ValueError(f"clip_max: expected a positive number, found {clip_max}")
    x = intensity.astype(np.float64)
    finite = np.isfinite(x)
    if np.any(x[finite] < 0):
        raise ValueError(
            f"intensity: expected linear non-negative intensities, found min {x[finite].min()}"
        )
    line_scale = _median_scale(x[valid_mask]) or _median_scale(x[finite & (x > 0)]) or 1.0
    out = np.empty_like(x)
    for side in (0, 1):
        scale = _median_scale(x[:, side][valid_mask[:, side]]) or line_scale
        out[:, side] = x[:, side] / scale
    out = np.where(finite, out, 0.0)
    return np.clip(out, 0.0, clip_max).astype(np.float32)


def box_mean(
    values: np.ndarray,
    weights: np.ndarray,
    size: tuple[int, int],
    modes: tuple[str, str] = ("nearest", "nearest"),
) -> np.ndarray:
    """Weighted box mean over the last two axes of ``(..., P, B)`` (normalised convolution:
    bins of weight 0 do not count); NaN where a box holds no weight. ``modes``: how each of
    the two axes extends past its ends (:func:`scipy.ndimage.uniform_filter`)."""
    from scipy.ndimage import uniform_filter

    full = (1,) * (values.ndim - 2) + tuple(size)
    mode = ("nearest",) * (values.ndim - 2) + tuple(modes)
    num = uniform_filter(values * weights, size=full, mode=mode)
    den = uniform_filter(weights.astype(np.float64), size=full, mode=mode)
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(den > 0, num / np.maximum(den, 1e-300), np.nan)


#: Along-track extent (pings) of the reference of :func:`relative_intensity`: long enough to
#: average the seabed's slopes out (at the demo's 4 Hz and 1.5 m/s, 101 pings are ~38 m of
#: track), short enough to follow a slowly changing altitude and sediment.
RELATIVE_WINDOW_PINGS = 101
#: Across-track smoothing (bins) of that reference.
RELATIVE_SMOOTH_BINS = 5


def relative_intensity(
    intensity: np.ndarray,
    valid_mask: np.ndarray,
    window_pings: int = RELATIVE_WINDOW_PINGS,
    smooth_bins: int = RELATIVE_SMOOTH_BINS,
    clip_max: float = DEFAULT_CLIP_MAX,
) -> np.ndarray:
    """Intensity relative to its along-track mean at the same slant range, per head.

    The classic empirical angle-varying gain of backscatter processing: each bin is divided
    by the mean of the valid bins of its head within ``window_pings`` pings along track and
    ``smooth_bins`` bins across (a normalised box filter, so masked bins do not count). What
    a range column has on average — beam pattern, time-varying gain, the sediment's angular
    response at that grazing angle, the altitude — divides out, and what is left is how much
    brighter or darker the bin is than the seabed around it at the same geometry: the slope
    signal. It needs the sidescan alone. Where a bin's window holds no valid bin, the
    head's whole-line mean at that range is used, failing that 1.

    Args:
        intensity: ``(P, 2, B)`` non-negative intensities (e.g. :func:`normalize_intensity`).
        valid_mask: ``(P, 2, B)`` bool, the seabed bins the means are taken over.
        window_pings: along-track extent of the mean (>= 1).
        smooth_bins: across-track extent of the mean (>= 1).
        clip_max: upper clip of the result (> 0).

    Returns:
        ``(P, 2, B)`` float32 in ``[0, clip_max]``; non-finite inputs become 0.

    >>> import numpy as np
    >>> x = np.tile(np.linspace(1.0, 3.0, 6), (8, 2, 1)); x[4, 0, 2] *= 2
    >>> r = relative_intensity(x, np.ones_like(x, bool), window_pings=201, smooth_bins=1)
    >>> round(float(r[4, 0, 2]), 3), round(float(r[0, 1, 5]), 3)
    (1.778, 1.0)
    """
    intensity = np.asarray(intensity)
    valid_mask = np.asarray(valid_mask)
    if intensity.ndim != 3 or intensity.shape[1] != 2:
        raise ValueError(f"intensity: expected shape (P, 2, B), found {intensity.shape}")
    if valid_mask.shape != intensity.shape or valid_mask.dtype != np.bool_:
        raise ValueError(
            f"valid_mask: expected a bool array of shape {intensity.shape}, found "
            f"{valid_mask.dtype} {valid_mask.shape}"
        )
    for name, value in (("window_pings", window_pings), ("smooth_bins", smooth_bins)):
        if not (isinstance(value, int) and not isinstance(value, bool) and value >= 1):
            raise ValueError(f"{name}: expected a positive integer, found {value!r}")
    if not (np.isfinite(clip_max) and clip_max > 0):
        raise ValueError(f"clip_max: expected a positive number, found {clip_max}")
    x = np.where(np.isfinite(intensity), intensity, 0.0).astype(np.float64)
    if np.any(x < 0):
        raise ValueError(f"intensity: expected non-negative intensities, found min {x.min()}")
    w = valid_mask & np.isfinite(intensity)
    heads = (1, 0, 2)  # (P, 2, B) <-> (2, P, B): box_mean works over the last two axes
    size = (min(window_pings, 2 * x.shape[0] + 1), smooth_bins)
    # along track, pings past the line's ends do not exist (constant 0 weight)
    local = box_mean(np.transpose(x, heads), np.transpose(w, heads), size, ("constant", "nearest"))
    local = np.transpose(local, heads)
    # fallback: the head's whole-line mean per range bin, then 1
    count = w.sum(axis=0, keepdims=True)
    with np.errstate(invalid="ignore", divide="ignore"):
        line_mean = np.where(count > 0, (x * w).sum(axis=0, keepdims=True) / count, np.nan)
    ref = np.where(np.isfinite(local), local, np.broadcast_to(line_mean, x.shape))
    ref = np.where(np.isfinite(ref) & (ref > 0), ref, 1.0)
    return np.clip(x / ref, 0.0, clip_max).astype(np.float32)
