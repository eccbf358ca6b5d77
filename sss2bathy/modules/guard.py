"""Moved to :mod:`sss2bathy.callbacks.guard`; this name stays until the configs and tests
that import it name the new one."""

from sss2bathy.callbacks.guard import (
    GlobalRNGState,
    NonFiniteGuard,
    NonFiniteTrainingError,
    global_rng_state,
    set_global_rng_state,
)

__all__ = [
    "GlobalRNGState",
    "NonFiniteGuard",
    "NonFiniteTrainingError",
    "global_rng_state",
    "set_global_rng_state",
]
