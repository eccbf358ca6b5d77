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
