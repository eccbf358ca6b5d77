"""Progress lines for long stages whose output goes to a file: every ``every_s`` seconds
one log line with what is done, the percentage, the rate and the time left.

:class:`ProgressLog` is the clock-throttled reporter (the training callback
:class:`sss2bathy.callbacks.progress.ProgressLogger` and any loop use it);
:func:`log_progress` wraps an iterable (an import's files, a drape's lines). Nothing is
logged for a stage shorter than ``every_s``.
"""

from __future__ import annotations

import logging
import math
import time
from collections.abc import Callable, Iterable, Iterator
from typing import TypeVar

T = TypeVar("T")

log = logging.getLogger("sss2bathy.progress")

#: seconds between two progress lines by default
DEFAULT_EVERY_S = 30.0


def format_duration(seconds: float) -> str:
    """``"45 s"``, ``"12 min 05 s"``, ``"2 h 03 min"``; ``"?"`` when unknown."""
    if seconds is None or not math.isfinite(seconds) or seconds < 0:
        return "?"
    s = int(round(seconds))
    if s < 60:
        return f"{s} s"
    if s < 3600:
        return f"{s // 60} min {s % 60:02d} s"
    return f"{s // 3600} h {(s % 3600) // 60:02d} min"


def progress_line(
    label: str,
    done: float,
    total: float | None,
    elapsed_s: float,
    unit: str = "steps",
    rate_done: float | None = None,
) -> str:
    """``"<label>: 1200/20000 steps (6.0 %), 4.21 steps/s, 4 min 45 s elapsed, ETA 1 h
    14 min"``. ``rate_done``: the part of ``done`` made in ``elapsed_s`` (a resumed run's
    earlier steps excluded); default ``done``. Without a finite ``total``: no percentage,
    no ETA."""
    made = done if rate_done is None else rate_done
    rate = made / elapsed_s if elapsed_s > 0 else float("nan")
    known = total is not None and math.isfinite(total) and total > 0
    count = f"{done:.0f}/{total:.0f} {unit}" if known else f"{done:.0f} {unit}"
    parts = [f"{label}: {count}"]
    if known:
        parts[0] += f" ({100.0 * done / total:.1f} %)"
    parts.append(f"{rate:.3g} {unit}/s" if math.isfinite(rate) else f"? {unit}/s")
    parts.append(f"{format_duration(elapsed_s)} elapsed")
    if known:
        eta = (total - done) / rate if math.isfinite(rate) and rate > 0 else float("nan")
        parts.append(f"ETA {format_duration(eta)}")
    return ", ".join(parts)


class ProgressLog:
    """Logs a :func:`progress_line` at most every ``every_s`` seconds.

    Args:
        label: what the stage is (``"import"``, ``"train epoch 3/50"``).
        total: units to do, or None (unknown).
        every_s: seconds between lines (the first after ``every_s`` too); positive.
        unit: the unit's name (``"steps"``, ``"lines"``).
        logger: where the lines go (``sss2bathy.progress``).
        clock: seconds, monotonic (tests pass a fake one).
        start_done: units already done at the start (a resumed run); not counted in
            the rate.
    """

    def __init__(
        self,
        label: str,
        total: float | None = None,
        every_s: float = DEFAULT_EVERY_S,
        unit: str = "steps",
        logger: logging.Logger | None = None,
        clock: Callable[[], float] = time.monotonic,
        start_done: float = 0.0,
    ) -> None:
        if not (isinstance(every_s, int | float) and every_s > 0):
            raise ValueError(f"every_s: expected a positive number of seconds, found {every_s!r}")
        self.label = label
        self.total = total
        self.every_s = float(every_s)
        self.unit = unit
        self.logger = logger or log
        self.clock = clock
        self.start_done = float(start_done)
        self.t0 = clock()
        self.last = self.t0
        self.lines = 0

    def elapsed(self) -> float:
        return self.clock() - self.t0

    def due(self) -> bool:
        """``every_s`` have passed since the last line (or the start)."""
        return self.clock() - self.last >= self.every_s

    def line(self, done: float, label: str | None = None) -> str:
        return progress_line(
            label or self.label,
            done,
            self.total,
            self.elapsed(),
            self.unit,
            rate_done=done - self.start_done,
        )

    def update(self, done: float, label: str | None = None, force: bool = False) -> str | None:
        """Log (and return) the line for ``done`` units when due (or ``force``); else None."""
        if not (force or self.due()):
            return None
        text = self.line(done, label)
        self.logger.info("%s", text)
        self.last = self.clock()
        self.lines += 1
        return text


def log_progress(
    items: Iterable[T],
    label: str,
    total: int | None = None,
    every_s: float = DEFAULT_EVERY_S,
    unit: str = "items",
    logger: logging.Logger | None = None,
) -> Iterator[T]:
    """Yield ``items``, logging a progress line (:class:`ProgressLog`) at most every
    ``every_s`` seconds after an item is done, and a closing line when any was logged."""
    if total is None:
        try:
            total = len(items)  # type: ignore[arg-type]
        except TypeError:
            total = None
    progress = ProgressLog(label, total, every_s, unit, logger)
    done = 0
    for item in items:
        yield item
        done += 1
        progress.update(done)
    if progress.lines:
        progress.update(done, label=f"{label} done", force=True)
