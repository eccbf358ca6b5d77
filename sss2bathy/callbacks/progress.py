"""Progress lines for fits whose output is not a terminal (a log file, a batch job).

Lightning's progress bar redraws one terminal line; redirected to a file it leaves nothing
readable between a stage's start and its end. :class:`ProgressLogger` (``conf/callbacks/
default.yaml``) logs instead, when stdout is not a terminal, a line at least every
``every_s`` seconds of training or validation, and of a test pass (batches)::

    train: epoch 3/50, 1200/20000 steps (6.0 %), 4.21 steps/s, 4 min 45 s elapsed, ETA 1 h 14 min

On a terminal it stays silent and the bar is left as it is.
"""

from __future__ import annotations

import logging
import math
import sys
import time
from collections.abc import Callable
from typing import Any

import pytorch_lightning as pl

from sss2bathy.utils.progress import DEFAULT_EVERY_S, ProgressLog

log = logging.getLogger("sss2bathy.progress")


def _is_terminal(stream: Any) -> bool:
    try:
        return bool(stream.isatty())
    except (AttributeError, ValueError):  # no isatty, or a closed stream
        return False


class ProgressLogger(pl.Callback):
    """A progress line at least every ``every_s`` seconds while fitting (rank 0).

    Args:
        every_s: seconds between lines; positive.
        when: ``"not_tty"`` (default): only when stdout is not a terminal; ``"always"``;
            ``"never"``.
        clock: seconds, monotonic (tests pass a fake one).
        is_terminal: whether stdout is a terminal (default: ``sys.stdout.isatty()`` at the
            start of the fit).
    """

    WHEN = ("not_tty", "always", "never")

    def __init__(
        self,
        every_s: float = DEFAULT_EVERY_S,
        when: str = "not_tty",
        clock: Callable[[], float] = time.monotonic,
        is_terminal: Callable[[], bool] | None = None,
    ) -> None:
        if not (isinstance(every_s, int | float) and not isinstance(every_s, bool)) or not (
            every_s > 0
        ):
            raise ValueError(f"every_s: expected a positive number of seconds, found {every_s!r}")
        if when not in self.WHEN:
            raise ValueError(f"when: expected one of {', '.join(self.WHEN)}, found {when!r}")
        self.every_s = float(every_s)
        self.when = when
        self.clock = clock
        self.is_terminal = is_terminal or (lambda: _is_terminal(sys.stdout))
        self.progress: ProgressLog | None = None
        self.test_progress: ProgressLog | None = None
        self.test_done = 0

    def active(self) -> bool:
        if self.when == "never":
            return False
        return self.when == "always" or not self.is_terminal()

    @staticmethod
    def total_steps(trainer: pl.Trainer) -> float | None:
        """The fit's optimizer steps (``max_steps``, else epochs x batches), None unknown."""
        try:
            total = float(trainer.estimated_stepping_batches)
        except Exception:  # no data loader yet, or an iterable without a length
            return None
        return total if math.isfinite(total) and total > 0 else None

    def on_train_start(self, trainer: pl.Trainer, pl_module: pl.LightningModule) -> None:
        self.progress = None
        if not trainer.is_global_zero or not self.active():
            return
        self.progress = ProgressLog(
            "train",
            self.total_steps(trainer),
            self.every_s,
            unit="steps",
            logger=log,
            clock=self.clock,
            start_done=trainer.global_step,
        )
        log.info(
            "%s (a progress line every %s s: stdout is not a terminal)",
            self.progress.line(trainer.global_step),
            f"{self.every_s:g}",
        )

    def _label(self, trainer: pl.Trainer, phase: str) -> str:
        max_epochs = trainer.max_epochs
        epoch = trainer.current_epoch + 1
        if max_epochs is not None and max_epochs > 0:
            # at the end of a fit the epoch counter has moved past the last epoch
            return f"{phase}: epoch {min(epoch, max_epochs)}/{max_epochs}"
        return f"{phase}: epoch {epoch}"

    def on_train_batch_end(self, trainer: pl.Trainer, *args: Any, **kwargs: Any) -> None:
        if self.progress is not None:
            self.progress.update(trainer.global_step, self._label(trainer, "train"))

    def on_validation_batch_end(self, trainer: pl.Trainer, *args: Any, **kwargs: Any) -> None:
        if self.progress is not None and not trainer.sanity_checking:
            self.progress.update(trainer.global_step, self._label(trainer, "validating"))

    def on_train_end(self, trainer: pl.Trainer, pl_module: pl.LightningModule) -> None:
        if self.progress is not None:
            self.progress.update(trainer.global_step, self._label(trainer, "train done"), True)
            self.progress = None

    # a test pass (``trainer.test``: the CNN's test lines and surveys) counts its batches
    def on_test_start(self, trainer: pl.Trainer, pl_module: pl.LightningModule) -> None:
        self.test_progress, self.test_done = None, 0
        if not trainer.is_global_zero or not self.active():
            return
        try:
            total: float | None = float(sum(trainer.num_test_batches))
        except TypeError:  # an iterable without a length
            total = None
        self.test_progress = ProgressLog(
            "test", total if total and math.isfinite(total) else None, self.every_s,
            unit="batches", logger=log, clock=self.clock,
        )  # fmt: skip

    def on_test_batch_end(self, trainer: pl.Trainer, *args: Any, **kwargs: Any) -> None:
        if self.test_progress is not None:
            self.test_done += 1
            self.test_progress.update(self.test_done)

    def on_test_end(self, trainer: pl.Trainer, pl_module: pl.LightningModule) -> None:
        if self.test_progress is not None and self.test_progress.lines:
            self.test_progress.update(self.test_done, "test done", force=True)
        self.test_progress = None
