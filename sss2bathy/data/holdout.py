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
held out.

**K folds** (:func:`fold_blocks`, :func:`split_altimeter_fold`): for a verdict that does not
hang on one draw, each line is cut into blocks of ``block_m`` metres of along-track
distance from its first ping (the last one shorter); the blocks holding an altimeter point
that leave at least ``block_m`` of track with altimeter points before and after them
(measured from the line's first and last altimeter point) are *eligible*, and are dealt,
in a seeded random order over all lines, round-robin to ``folds`` folds, so every eligible
block is held out in exactly one fold and each fold holds out blocks at other places of
the survey. Fold ``k`` holds out the altimeter points of its blocks; a whole block at
either end of a line is always kept (the baseline interpolates, never extrapolates). ``block_m`` defaults to
:func:`default_block_m`. All functions here are pure (arrays in, arrays out).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, replace

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


def along_track_blocks(distance_m: np.ndarray, block_m: float) -> np.ndarray:
    """``(P,)`` block index of each ping: ``floor(distance / block_m)``, the blocks being
    ``block_m`` metres of along-track distance (:func:`along_track_distance`) from the
    line's first ping."""
    if not (isinstance(block_m, int | float) and math.isfinite(block_m) and block_m > 0):
        raise ValueError(f"holdout.block_m: expected a positive length (m), found {block_m!r}")
    s = np.asarray(distance_m, np.float64)
    if s.ndim != 1 or (s.size and (not np.isfinite(s).all() or np.any(np.diff(s) < 0))):
        raise ValueError("distance_m: expected finite, non-decreasing along-track distances")
    return np.floor(s / float(block_m)).astype(np.int64)


def default_block_m(line_lengths_m: Sequence[float], swath_width_m: float, folds: int) -> float:
    """The held-out block length (m) of :func:`fold_blocks` when none is given: twice the
    swath width (a held-out block is then longer than the area a ping's swath reaches
    across, so neither the sidescan of the neighbouring kept pings nor the interpolation
    sees over it), shortened on short surveys to ``total length / (folds + 3 x lines)`` so
    each fold still gets a block (every line keeps a whole block at either end and rounding
    loses at most one more)."""
    lengths = [float(v) for v in line_lengths_m]
    if int(folds) < 1:
        raise ValueError(f"verdict.folds: expected a positive number of folds, found {folds}")
    if not swath_width_m > 0:
        raise ValueError(f"swath_width_m: expected a positive width (m), found {swath_width_m}")
    total = sum(lengths)
    if not total > 0:
        raise ValueError(f"line_lengths_m: expected lines of positive length, found {lengths}")
    return float(min(2.0 * float(swath_width_m), total / (int(folds) + 3 * len(lengths))))


def fold_blocks(
    distances_m: Sequence[np.ndarray],
    block_m: float,
    folds: int,
    seed: int,
    valid: Sequence[np.ndarray] | None = None,
) -> list[np.ndarray]:
    """Per line a ``(P_i,)`` int array: the fold (``0 .. folds - 1``) whose held-out set a
    ping's altimeter point belongs to, ``-1`` = kept in every fold (module docstring).

    Args:
        distances_m: per line, ``(P_i,)`` along-track distance of each ping (m).
        block_m: block length (m).
        folds: number of folds (>= 2).
        seed: seed of the deal (same seed, same folds).
        valid: per line ``(P_i,)`` bool, pings with an altimeter point (``None``: all).

    Raises:
        ValueError: fewer eligible blocks than folds (names ``holdout.block_m``).
    """
    if isinstance(folds, bool) or int(folds) != folds or int(folds) < 2:
        raise ValueError(f"verdict.folds: expected an integer >= 2, found {folds!r}")
    folds = int(folds)
    blocks = [along_track_blocks(s, block_m) for s in distances_m]
    if valid is None:
        valid = [np.ones(b.shape, bool) for b in blocks]
    valid = [np.asarray(v, bool) for v in valid]
    eligible: list[tuple[int, int]] = []
    size = float(block_m)
    for i, (b, v, s) in enumerate(zip(blocks, valid, distances_m, strict=True)):
        if v.shape != b.shape:
            raise ValueError(f"valid[{i}]: expected shape {b.shape}, found {v.shape}")
        if not v.any():
            continue
        s = np.asarray(s, np.float64)
        start, end = float(s[v][0]), float(s[v][-1])
        eps = 1e-9 * max(1.0, end)
        # a whole block of kept altimeter points at either end of the line
        eligible += [
            (i, int(k))
            for k in np.unique(b[v])
            if k * size >= start + size - eps and (k + 1) * size <= end - size + eps
        ]
    if len(eligible) < folds:
        total = sum(float(s[-1]) if len(s) else 0.0 for s in map(np.asarray, distances_m))
        raise ValueError(
            f"data.holdout.block_m: expected blocks short enough for {folds} folds (at least "
            f"{folds} blocks with altimeter points between each line's first and last block), "
            f"found {len(eligible)} with blocks of {block_m:.2f} m over {total:.1f} m of "
            f"line; set holdout.block_m shorter or verdict.folds lower"
        )
    order = np.random.default_rng(int(seed)).permutation(len(eligible))
    out = [np.full(b.shape, -1, np.int64) for b in blocks]
    for rank, e in enumerate(order):
        i, k = eligible[e]
        out[i][blocks[i] == k] = rank % folds
    return out


@dataclass
class AltimeterSplit:
    """Altimeter points split into those fitted and those held out.

    Attributes:
        fit: ``(M, 3)`` points the fit uses.
        held: ``(K, 3)`` held-out points (nadir x, y and the seabed height z).
        held_line, held_ping: ``(K,)`` line index (in the order given) and ping index.
        interp: ``(K,)`` along-track linear interpolation of the line's kept points at each
            held-out point (the baseline's height).
        n_blocks: held-out blocks.
        block_m: block length (m) of a K-fold split (None: blocks of pings).
        block_pings: mean pings per held-out block.
        folds, fold: the K-fold split's fold count and fold (0 / None: one random draw).
    """

    fit: np.ndarray
    held: np.ndarray
    held_line: np.ndarray
    held_ping: np.ndarray
    interp: np.ndarray
    n_blocks: int = 0
    block_m: float | None = None
    block_pings: float | None = None
    folds: int = 0
    fold: int | None = None

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
    _check_lines(positions, altitudes)
    valid = [np.isfinite(np.asarray(a, np.float64)) for a in altitudes]
    held_masks = holdout_blocks(
        [len(a) for a in altitudes], fraction, block_pings, seed, valid=valid
    )
    split = split_by_masks(positions, altitudes, held_masks)
    n_blocks = sum(len(np.unique(np.flatnonzero(h) // int(block_pings))) for h in held_masks)
    n_pings = sum(int(h.sum()) for h in held_masks)
    return replace(split, n_blocks=n_blocks, block_pings=n_pings / n_blocks if n_blocks else None)


def split_altimeter_fold(
    positions: Sequence[np.ndarray],
    altitudes: Sequence[np.ndarray],
    folds: int,
    fold: int,
    block_m: float | None,
    seed: int,
    swath_width_m: float | None = None,
) -> AltimeterSplit:
    """Fold ``fold`` of the K-fold split (:func:`fold_blocks`): its blocks' altimeter points
    held out, the rest fitted and interpolated along track at them.

    Args:
        positions, altitudes: as :func:`split_altimeter`.
        folds, fold: the number of folds (>= 2) and the fold held out (``0 .. folds - 1``).
        block_m: block length (m); None = :func:`default_block_m` of ``swath_width_m``.
        seed: seed of the deal of blocks to folds (the same for every fold of a verdict).
        swath_width_m: the swath's full width on the ground (m), for the default length.
    """
    _check_lines(positions, altitudes)
    if isinstance(fold, bool) or int(fold) != fold or not 0 <= int(fold) < int(folds):
        raise ValueError(f"data.holdout.fold: expected an integer in [0, {folds}), found {fold!r}")
    distances = [along_track_distance(np.asarray(p, np.float64)[:, :2]) for p in positions]
    if block_m is None:
        if swath_width_m is None:
            raise ValueError("swath_width_m: expected the swath width for holdout.block_m=null")
        block_m = default_block_m([float(d[-1]) for d in distances], swath_width_m, int(folds))
    valid = [np.isfinite(np.asarray(a, np.float64)) for a in altitudes]
    assignment = fold_blocks(distances, float(block_m), int(folds), seed, valid)
    held_masks = [a == int(fold) for a in assignment]
    split = split_by_masks(positions, altitudes, held_masks)
    blocks = [along_track_blocks(d, float(block_m)) for d in distances]
    n_blocks = sum(len(np.unique(b[h])) for b, h in zip(blocks, held_masks, strict=True))
    n_pings = sum(int(h.sum()) for h in held_masks)
    return replace(
        split,
        n_blocks=n_blocks,
        block_m=float(block_m),
        block_pings=n_pings / n_blocks if n_blocks else None,
        folds=int(folds),
        fold=int(fold),
    )


def split_by_masks(
    positions: Sequence[np.ndarray],
    altitudes: Sequence[np.ndarray],
    held_masks: Sequence[np.ndarray],
) -> AltimeterSplit:
    """Altimeter points of the pings ``held_masks[i]`` (per line ``(P,)`` bool) held out,
    the others fitted; the held-out points get the along-track interpolation of their
    line's kept points."""
    _check_lines(positions, altitudes)
    fit, held, held_line, held_ping, interp = [], [], [], [], []
    for i, (pos, alt, out) in enumerate(zip(positions, altitudes, held_masks, strict=True)):
        pos = np.asarray(pos, np.float64)
        alt = np.asarray(alt, np.float64)
        out = np.asarray(out, bool)
        if pos.shape != (len(alt), 3):
            raise ValueError(
                f"positions[{i}]: expected shape ({len(alt)}, 3) to match its altitudes, "
                f"found {pos.shape}"
            )
        if out.shape != alt.shape:
            raise ValueError(f"held_masks[{i}]: expected shape {alt.shape}, found {out.shape}")
        ok = np.isfinite(alt)
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


def _check_lines(positions: Sequence[np.ndarray], altitudes: Sequence[np.ndarray]) -> None:
    if len(positions) != len(altitudes):
        raise ValueError(
            f"positions, altitudes: expected one array per line each, found {len(positions)} "
            f"and {len(altitudes)}"
        )
