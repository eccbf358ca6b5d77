"""Held-out altimeter evaluation: MBES-free cross-validation of a bathymetry fit.

Contiguous blocks of pings have their altimeter points held out of the fit (all the
sidescan is still used); the fitted map is scored at the held-out nadir points, and beside
it the same score of the obvious baseline, **along-track linear interpolation** of the
kept altimeter points of the same line. A map whose held-out MAE is not below the
interpolation's has not learned anything from the sidescan that the altimeter did not
already give.

Blocks: each line is cut into blocks of ``block_pings`` consecutive pings (the last one
shorter) starting at ping 0. ``round(fraction * total blocks)`` blocks are held out, drawn
in a seeded random order over all lines among the blocks that are neither the first nor
the last of their line (so held-out points lie between kept ones: the baseline interpolates,
it does not extrapolate), skipping any block that would leave its line without a kept
altimeter point. Lines of one or two blocks give none; with too few such blocks fewer are
held out. All functions here are pure (arrays in, arrays out).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np


def holdout_blocks(
    n_pings: Sequence[int],
    fraction: float,
    block_pings: int,
    seed: int,
    valid: Sequence[np.ndarray] | None = None,
) -> list[np.ndarray]:
    """Per line a ``(n_pings[i],)`` bool array, ``True`` = the ping's altimeter point is held out.

    Args:
        n_pings: pings per line.
        fraction: share of the blocks to hold out, in ``[0, 1)``; 0 = none.
        block_pings: pings per block (>= 1).
        seed: seed of the block draw (same seed, same blocks).
        valid: per line, ``(n_pings[i],)`` bool, pings with an altimeter point; a block is
            skipped when holding it out would leave its line no valid kept ping. ``None``:
            every ping has one.
    """
    if not 0.0 <= float(fraction) < 1.0:
        raise ValueError(f"holdout.fraction: expected a number in [0, 1), found {fraction}")
    if int(block_pings) < 1:
        raise ValueError(f"holdout.block_pings: expected a positive count, found {block_pings}")
    counts = [int(n) for n in n_pings]
    if valid is None:
        valid = [np.ones(n, bool) for n in counts]
    valid = [np.asarray(v, bool) for v in valid]
    for i, (n, v) in enumerate(zip(counts, valid, strict=True)):
        if v.shape != (n,):
            raise ValueError(f"valid[{i}]: expected shape ({n},), found {v.shape}")
    held = [np.zeros(n, bool) for n in counts]
    block = int(block_pings)
    n_blocks = sum(-(-n // block) for n in counts)
    # interior blocks only: the first and last block of a line bracket its held-out points
    blocks = [(i, s) for i, n in enumerate(counts) for s in range(block, n - block, block)]
    want = int(round(float(fraction) * n_blocks))
    if want == 0:
        return held
    kept_valid = [int(v.sum()) for v in valid]
    order = np.random.default_rng(int(seed)).permutation(len(blocks))
    taken = 0
    for b in order:
        if taken == want:
            break
        i, s = blocks[b]
        n_valid = int(valid[i][s : s + block].sum())
        if n_valid >= kept_valid[i]:
            continue  # the line's last kept altimeter points: keep them for the baseline
        held[i][s : s + block] = True
        kept_valid[i] -= n_valid
        taken += 1
    return held


def along_track_distance(xy: np.ndarray) -> np.ndarray:
    """``(P,)`` cumulative horizontal distance (m) along a line's ``(P, 2)`` positions."""
    xy = np.asarray(xy, np.float64)
    if xy.ndim != 2 or xy.shape[1] != 2:
        raise ValueError(f"xy: expected shape (P, 2), found {xy.shape}")
    step = np.hypot(*np.diff(xy, axis=0).T) if len(xy) > 1 else np.zeros(0)
    return np.concatenate([[0.0], np.cumsum(step)])


def interpolate_along_track(
    s_kept: np.ndarray, z_kept: np.ndarray, s_query: np.ndarray
) -> np.ndarray:
    """Linear interpolation of heights ``z_kept`` at along-track distances ``s_kept`` to
    ``s_query``; beyond the kept ends the nearest kept height (no extrapolated slope).

    ``s_kept`` must be non-decreasing (pings in order); with no kept point the result is NaN.
    """
    s_kept = np.asarray(s_kept, np.float64)
    z_kept = np.asarray(z_kept, np.float64)
    s_query = np.asarray(s_query, np.float64)
    if s_kept.shape != z_kept.shape or s_kept.ndim != 1:
        raise ValueError(
            f"s_kept, z_kept: expected equal 1-D shapes, found {s_kept.shape} and {z_kept.shape}"
        )
    if s_kept.size == 0:
        return np.full(s_query.shape, np.nan)
    if np.any(np.diff(s_kept) < 0):
        raise ValueError("s_kept: expected non-decreasing along-track distances (pings in order)")
    return np.interp(s_query, s_kept, z_kept)


@dataclass
class AltimeterSplit:
    """Altimeter points split into those fitted and those held out.

    Attributes:
        fit: ``(M, 3)`` points the fit uses.
        held: ``(K, 3)`` held-out points (nadir x, y and the seabed height z).
        held_line, held_ping: ``(K,)`` line index (in the order given) and ping index.
        interp: ``(K,)`` along-track linear interpolation of the line's kept points at each
            held-out point (the baseline's height).
    """

    fit: np.ndarray
    held: np.ndarray
    held_line: np.ndarray
    held_ping: np.ndarray
    interp: np.ndarray

    @property
    def n_held(self) -> int:
        return int(self.held.shape[0])

    @property
    def fraction(self) -> float:
        """Share of all altimeter points held out."""
        total = self.n_held + int(self.fit.shape[0])
        return self.n_held / total if total else 0.0

    @property
    def interp_mae(self) -> float:
        """Mean |interpolation - held-out height| (m); NaN without held-out points."""
        return holdout_mae(self.interp, self.held[:, 2])


def holdout_mae(pred_z: np.ndarray, true_z: np.ndarray) -> float:
    """Mean absolute height error (m) over finite pairs; NaN when there is none."""
    err = np.abs(np.asarray(pred_z, np.float64) - np.asarray(true_z, np.float64))
    err = err[np.isfinite(err)]
    return float(err.mean()) if err.size else float("nan")


def split_altimeter(
    positions: Sequence[np.ndarray],
    altitudes: Sequence[np.ndarray],
    fraction: float,
    block_pings: int,
    seed: int,
) -> AltimeterSplit:
    """Hold out contiguous ping blocks' altimeter points (:func:`holdout_blocks`) and
    interpolate the kept ones along each line's track at the held-out pings.

    Args:
        positions: per line ``(P, 3)`` sonar positions (world ENU, m).
        altitudes: per line ``(P,)`` altitude above the seabed (m), NaN = none.
        fraction, block_pings, seed: as :func:`holdout_blocks`.

    The seabed point of a ping is its position lowered by its altitude (as
    :meth:`sss2bathy.survey.SidescanLine.altimeter_points`).
    """
    if len(positions) != len(altitudes):
        raise ValueError(
            f"positions, altitudes: expected one array per line each, found {len(positions)} "
            f"and {len(altitudes)}"
        )
    valid = [np.isfinite(np.asarray(a, np.float64)) for a in altitudes]
    held_masks = holdout_blocks(
        [len(a) for a in altitudes], fraction, block_pings, seed, valid=valid
    )
    fit, held, held_line, held_ping, interp = [], [], [], [], []
    for i, (pos, alt, ok, out) in enumerate(
        zip(positions, altitudes, valid, held_masks, strict=True)
    ):
        pos = np.asarray(pos, np.float64)
        alt = np.asarray(alt, np.float64)
        if pos.shape != (len(alt), 3):
            raise ValueError(
                f"positions[{i}]: expected shape ({len(alt)}, 3) to match its altitudes, "
                f"found {pos.shape}"
            )
        pts = pos.copy()
        pts[:, 2] -= alt
        keep, drop = ok & ~out, ok & out
        fit.append(pts[keep])
        held.append(pts[drop])
        held_line.append(np.full(int(drop.sum()), i, np.int64))
        held_ping.append(np.flatnonzero(drop))
        s = along_track_distance(pos[:, :2])
        interp.append(interpolate_along_track(s[keep], pts[keep, 2], s[drop]))
    cat = lambda xs, shape: np.concatenate(xs) if xs else np.zeros(shape)  # noqa: E731
    return AltimeterSplit(
        fit=cat(fit, (0, 3)),
        held=cat(held, (0, 3)),
        held_line=cat(held_line, (0,)).astype(np.int64),
        held_ping=cat(held_ping, (0,)).astype(np.int64),
        interp=cat(interp, (0,)),
    )
