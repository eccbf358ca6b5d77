"""Learning-rate schedules of the SIREN fit that are not in ``torch.optim``.

:class:`WallClockExponentialLR` decays the learning rate as ``decay_epochs`` epochs of
``ExponentialLR(gamma)`` would, but over a budget of *wall-clock* seconds:
``lr(t) = lr0 * gamma ** (decay_epochs * min(t / budget, 1))``.
A fit given a time budget (``trainer.max_time``, ``siren_schedule=budget``) then ends its
decay when the budget ends, whatever the machine's speed, instead of being cut off half way
down a decay sized in steps. The price: two runs of the same seed no longer take identical
steps (the rate depends on the clock), so it is not for bit-for-bit comparisons.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from typing import Any

import torch
from torch.optim.lr_scheduler import LRScheduler

from sss2bathy.utils.checks import require_number


class WallClockExponentialLR(LRScheduler):
    """``lr = base_lr * gamma ** (decay_epochs * min(elapsed / budget_s, 1))``, stepped every
    optimiser step (``interval = "step"``: :class:`~sss2bathy.modules.siren.SirenModule`
    reads it).

    ``elapsed`` counts from the scheduler's creation (the start of the fit) and travels in
    :meth:`state_dict`, so a resumed fit continues its decay where it stopped.

    Args:
        optimizer: the optimiser.
        gamma: the decay per epoch of the schedule this one stretches, in (0, 1].
        budget_s: seconds over which the rate decays (> 0); after them it stays at
            ``base_lr * gamma ** decay_epochs``.
        decay_epochs: epochs of that schedule the budget spans (> 0; the fast schedule: 10).
        clock: seconds, monotonic (tests pass their own).
    """

    interval = "step"

    def __init__(
        self,
        optimizer: torch.optim.Optimizer,
        gamma: float,
        budget_s: float,
        decay_epochs: float,
        clock: Callable[[], float] = time.monotonic,
        last_epoch: int = -1,
    ) -> None:
        self.budget_s = float(
            require_number("budget_s", budget_s, lambda v: v > 0, "a positive number of seconds")
        )
        self.gamma = float(
            require_number("gamma", gamma, lambda v: 0 < v <= 1, "a decay factor in (0, 1]")
        )
        self.decay_epochs = float(
            require_number(
                "decay_epochs", decay_epochs, lambda v: v > 0, "a positive number of epochs"
            )
        )
        self.clock = clock
        self._start = clock()
        super().__init__(optimizer, last_epoch)

    def elapsed_s(self) -> float:
        return max(self.clock() - self._start, 0.0)

    def factor(self) -> float:
        """The current multiple of the base rate."""
        return self.gamma ** (self.decay_epochs * min(self.elapsed_s() / self.budget_s, 1.0))

    def get_lr(self) -> list[float]:
        f = self.factor()
        return [base * f for base in self.base_lrs]

    def state_dict(self) -> dict[str, Any]:
        state = {k: v for k, v in self.__dict__.items() if k not in ("optimizer", "clock")}
        state["elapsed_s"] = self.elapsed_s()
        return state

    def load_state_dict(self, state_dict: dict[str, Any]) -> None:
        state = dict(state_dict)
        elapsed = float(state.pop("elapsed_s", 0.0))
        if not math.isfinite(elapsed) or elapsed < 0:
            raise ValueError(f"elapsed_s: expected seconds >= 0, found {elapsed!r}")
        self.__dict__.update(state)
        self._start = self.clock() - elapsed


__all__ = ["WallClockExponentialLR"]
