"""Per-bin validity mask bits (uint8). 0 = valid; otherwise the OR of the reasons."""

from __future__ import annotations

import numpy as np

MASK_VALID = 0
MASK_WATER_COLUMN = 1  # slant range shorter than the first bottom return (nadir gap)
MASK_SHADOW = 2  # the arc's first visible hit is farther along; this bin sees no seafloor
MASK_NO_HIT = 4  # the arc leaves the mesh / grid (no data)
MASK_OUT_OF_BEAM = 8  # the crossing lies outside the vertical beam

MASK_NAMES = {
    MASK_WATER_COLUMN: "water_column",
    MASK_SHADOW: "shadow",
    MASK_NO_HIT: "no_hit",
    MASK_OUT_OF_BEAM: "out_of_beam",
}


def mask_reason_counts(mask: np.ndarray) -> dict[str, int]:
    """Number of bins per reason (a bin may count under several), plus ``valid`` and ``total``."""
    mask = np.asarray(mask)
    counts = {name: int(np.count_nonzero(mask & bit)) for bit, name in MASK_NAMES.items()}
    counts["valid"] = int(np.count_nonzero(mask == MASK_VALID))
    counts["total"] = int(mask.size)
    return counts
