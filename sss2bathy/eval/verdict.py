"""The K-fold held-out verdict: did the sidescan help the map?

Every method is scored on the same K folds of held-out altimeter blocks
(:func:`sss2bathy.data.holdout.fold_blocks`): the sidescan fit, the SIREN fitted to the
altimeter alone (``siren_heights_only``) and along-track interpolation of the kept
altimeter points. One fold gives each method one held-out MAE (m).

**Comparing two methods** (:func:`paired_comparison`): the per-fold differences
``d_k = MAE_a,k - MAE_b,k`` over the folds where both are finite (pairing removes what the
folds share: a fold of rough seabed is hard for every method), their mean and its
standard error ``s.e. = std(d, ddof=1) / sqrt(n)``. The 95 % interval is
``mean +- t(0.975, n - 1) x s.e.`` (Student's t; 2.78 at 5 folds). When it contains 0 the
comparison is **inconclusive**, else the method with the lower mean MAE wins. The folds'
fits share most of their data, so this interval is, if anything, too narrow: a
conclusive answer still needs the difference to be large against the folds' spread.

**The verdict** (:func:`kfold_verdict`) compares the subject (the sidescan fit) with each
baseline: the sidescan *helped* when it beats every baseline, did *not* help when some
baseline beats it, and is *inconclusive* otherwise. All functions here are pure.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

INTERPOLATION = "interpolation"
HEIGHTS_ONLY = "siren_heights_only"
PLANE = "plane"
#: what a :class:`KFoldVerdict`'s folds hold out, unless it says otherwise
ALTIMETER_BLOCKS = "held-out altimeter blocks"
LABELS = {
    INTERPOLATION: "along-track interpolation",
    PLANE: "plane through the fitted altimeter points",
    HEIGHTS_ONLY: "heights only (SIREN, no sidescan)",
    "siren_lambert": "SIREN-Lambert (sidescan)",
    "siren_cnn_n2d": "SIREN-CNN-N2d (sidescan)",
    "siren_gt_n2d": "SIREN-GT-N2d (sidescan)",
}


@dataclass(frozen=True)
class MethodScores:
    """One method's held-out MAE (m) per fold (NaN: the fold gave no score)."""

    name: str
    mae: tuple[float, ...]

    @property
    def label(self) -> str:
        return LABELS.get(self.name, self.name)

    @property
    def finite(self) -> np.ndarray:
        values = np.asarray(self.mae, np.float64)
        return values[np.isfinite(values)]

    @property
    def n(self) -> int:
        return int(self.finite.size)

    @property
    def mean(self) -> float:
        return float(self.finite.mean()) if self.n else math.nan

    @property
    def std(self) -> float:
        """Sample standard deviation over the folds (ddof 1; NaN under 2 folds)."""
        return float(self.finite.std(ddof=1)) if self.n > 1 else math.nan

    @property
    def low(self) -> float:
        return float(self.finite.min()) if self.n else math.nan

    @property
    def high(self) -> float:
        return float(self.finite.max()) if self.n else math.nan


@dataclass(frozen=True)
class Comparison:
    """:func:`paired_comparison` of methods ``a`` and ``b``.

    Attributes:
        a, b: the methods' names.
        n: folds with both scores.
        mean_diff: mean of ``MAE_a - MAE_b`` over them (m; < 0: ``a`` is better).
        se: its standard error (m).
        half_width: half the 95 % interval, ``t(0.975, n - 1) x se`` (m).
        winner: ``a``'s or ``b``'s name, or None (inconclusive).
    """

    a: str
    b: str
    n: int
    mean_diff: float
    se: float
    half_width: float
    winner: str | None

    @property
    def inconclusive(self) -> bool:
        return self.winner is None

    def describe(self) -> str:
        """``"<a> - <b> = -0.012 +- 0.020 m (95 %, 5 folds): inconclusive"``."""
        a, b = LABELS.get(self.a, self.a), LABELS.get(self.b, self.b)
        if self.n < 2:
            return f"{a} vs {b}: inconclusive ({self.n} paired folds; at least 2 needed)"
        result = (
            "inconclusive (the interval contains 0)"
            if self.winner is None
            else f"{LABELS.get(self.winner, self.winner)} is better"
        )
        return (
            f"{a} - {b} = {self.mean_diff:+.3f} +- {self.half_width:.3f} m "
            f"(95 %, {self.n} folds): {result}"
        )


def t_quantile(dof: int, level: float = 0.975) -> float:
    """Student's t quantile (scipy)."""
    from scipy.stats import t

    return float(t.ppf(level, dof))


def paired_comparison(a: MethodScores, b: MethodScores) -> Comparison:
    """Paired per-fold comparison of two methods (module docstring)."""
    if len(a.mae) != len(b.mae):
        raise ValueError(
            f"{b.name}: expected one score per fold like {a.name} ({len(a.mae)}), found "
            f"{len(b.mae)}"
        )
    diff = np.asarray(a.mae, np.float64) - np.asarray(b.mae, np.float64)
    diff = diff[np.isfinite(diff)]
    n = int(diff.size)
    if n < 2:
        mean = float(diff.mean()) if n else math.nan
        return Comparison(a.name, b.name, n, mean, math.nan, math.nan, None)
    mean = float(diff.mean())
    se = float(diff.std(ddof=1) / math.sqrt(n))
    half = t_quantile(n - 1) * se
    winner = None
    if abs(mean) > half and mean != 0.0:
        winner = a.name if mean < 0 else b.name
    return Comparison(a.name, b.name, n, mean, se, half, winner)


@dataclass(frozen=True)
class KFoldVerdict:
    """The K-fold table and verdict of one map run.

    Attributes:
        subject: the method whose help is judged (the sidescan fit's experiment).
        scores: every method's per-fold MAE, the subject first.
        comparisons: the subject against each other method.
        block_m: held-out block length (m); block_pings: mean pings per block.
        seconds: wall time of the fold fits (s), or None.
        imaged_share: mean share of the held-out points inside the sonar's footprint (0 on
            single lines: the nadir gap), or None.
        held_out: what the folds hold out, as the sentence says it (e.g.
            :data:`ALTIMETER_BLOCKS`).
    """

    subject: str
    scores: tuple[MethodScores, ...]
    comparisons: tuple[Comparison, ...]
    block_m: float | None = None
    block_pings: float | None = None
    seconds: float | None = None
    imaged_share: float | None = None
    held_out: str = ALTIMETER_BLOCKS

    @property
    def folds(self) -> int:
        return len(self.scores[0].mae) if self.scores else 0

    @property
    def outcome(self) -> str:
        """``"helped"``, ``"did not help"`` or ``"inconclusive"`` (module docstring)."""
        if any(c.winner is not None and c.winner != self.subject for c in self.comparisons):
            return "did not help"
        if self.comparisons and all(c.winner == self.subject for c in self.comparisons):
            return "helped"
        return "inconclusive"

    @property
    def best(self) -> str | None:
        """The method with the lowest mean held-out MAE (whether or not it is conclusive)."""
        finite = [s for s in self.scores if math.isfinite(s.mean)]
        return min(finite, key=lambda s: s.mean).name if finite else None

    def sentence(self) -> str:
        """The verdict in one sentence."""
        subject = LABELS.get(self.subject, self.subject)
        lost = [c for c in self.comparisons if c.winner not in (None, self.subject)]
        open_ = [c for c in self.comparisons if c.winner is None]
        others = lambda cs: " and ".join(LABELS.get(c.b, c.b) for c in cs)  # noqa: E731
        if self.outcome == "helped":
            return (
                f"VERDICT: {subject} beats {others(self.comparisons)} on {self.held_out} in "
                f"{self.folds} folds: the sidescan helped."
            )
        if self.outcome == "did not help":
            won = [c for c in self.comparisons if c.winner == self.subject]
            also = f" (though it beats {others(won)})" if won else ""
            return (
                f"VERDICT: {others(lost)} beats {subject} on {self.held_out} in "
                f"{self.folds} folds: the sidescan did NOT help{also}."
            )
        best = LABELS.get(self.best, self.best) if self.best else "none"
        return (
            f"VERDICT: inconclusive: over {self.folds} folds of {self.held_out} {subject} is "
            f"neither better nor worse than {others(open_)} beyond the folds' spread (the 95 % "
            f"interval of the paired differences contains 0); lowest mean MAE: {best}."
        )

    def table(self) -> list[str]:
        """The K-fold table: method, mean +- std (and min-max) of the held-out MAE, folds."""
        width = max(len("method"), *(len(s.label) for s in self.scores))
        head = f"{'method':{width}s}  {'held-out MAE mean +- std (m)':>29s}  {'min - max (m)':>15s}  folds"
        rows = [head]
        for s in self.scores:
            spread = f"{s.mean:.3f} +- {s.std:.3f}" if s.n > 1 else f"{s.mean:.3f}"
            rows.append(
                f"{s.label:{width}s}  {spread:>29s}  {f'{s.low:.3f} - {s.high:.3f}':>15s}  {s.n}"
            )
        return rows

    def to_dict(self) -> dict[str, Any]:
        """Plain values for ``verdict.json`` / ``metrics.json``."""
        return {
            "subject": self.subject,
            "held_out": self.held_out,
            "folds": self.folds,
            "block_m": self.block_m,
            "block_pings": self.block_pings,
            "seconds": self.seconds,
            "imaged_share": self.imaged_share,
            "outcome": self.outcome,
            "best": self.best,
            "sentence": self.sentence(),
            "methods": {
                s.name: {
                    "mae_per_fold": [float(v) for v in s.mae],
                    "mean": s.mean,
                    "std": s.std,
                    "min": s.low,
                    "max": s.high,
                    "n": s.n,
                }
                for s in self.scores
            },
            "comparisons": [
                {
                    "a": c.a,
                    "b": c.b,
                    "n": c.n,
                    "mean_diff": c.mean_diff,
                    "se": c.se,
                    "half_width_95": c.half_width,
                    "winner": c.winner,
                }
                for c in self.comparisons
            ],
        }

    def metrics(self, prefix: str = "verdict/") -> dict[str, float]:
        """Flat numbers for ``metrics.json``: per method ``<prefix><name>/mae_mean``,
        ``mae_std``, ``n``; ``folds``, ``block_m``, ``block_pings``."""
        out: dict[str, float] = {f"{prefix}folds": float(self.folds)}
        for key, value in (
            ("block_m", self.block_m),
            ("block_pings", self.block_pings),
            ("imaged_share", self.imaged_share),
        ):
            if value is not None:
                out[f"{prefix}{key}"] = float(value)
        for s in self.scores:
            out[f"{prefix}{s.name}/mae_mean"] = s.mean
            out[f"{prefix}{s.name}/mae_std"] = s.std
            out[f"{prefix}{s.name}/n"] = float(s.n)
        return {k: v for k, v in out.items() if math.isfinite(v)}


def kfold_verdict(
    scores: Sequence[MethodScores] | Mapping[str, Sequence[float]],
    subject: str,
    block_m: float | None = None,
    block_pings: float | None = None,
    seconds: float | None = None,
    imaged_share: float | None = None,
    held_out: str = ALTIMETER_BLOCKS,
) -> KFoldVerdict:
    """The verdict on ``subject`` against every other method of ``scores`` (module
    docstring); ``scores`` as :class:`MethodScores` or ``{name: per-fold MAE}``;
    ``held_out`` names what the folds hold out (the sentence's words)."""
    if isinstance(scores, Mapping):
        scores = [MethodScores(str(k), tuple(float(v) for v in vs)) for k, vs in scores.items()]
    scores = list(scores)
    names = [s.name for s in scores]
    if subject not in names:
        raise ValueError(f"subject: expected one of the scored methods {names}, found {subject!r}")
    if len({len(s.mae) for s in scores}) > 1:
        raise ValueError(
            f"scores: expected the same number of folds for every method, found "
            f"{ {s.name: len(s.mae) for s in scores} }"
        )
    first = scores[names.index(subject)]
    ordered = [first, *(s for s in scores if s.name != subject)]
    comparisons = tuple(paired_comparison(first, s) for s in ordered[1:])
    return KFoldVerdict(
        subject,
        tuple(ordered),
        comparisons,
        block_m,
        block_pings,
        seconds,
        imaged_share,
        held_out,
    )


__all__ = [
    "ALTIMETER_BLOCKS",
    "HEIGHTS_ONLY",
    "INTERPOLATION",
    "PLANE",
    "Comparison",
    "KFoldVerdict",
    "MethodScores",
    "kfold_verdict",
    "paired_comparison",
]
