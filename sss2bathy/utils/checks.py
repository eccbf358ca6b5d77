"""Argument checks for constructors: ``<name>: expected <what>, found <value!r>``.

Each check returns the value when it is acceptable and raises :class:`ValueError` with that
one-line message otherwise, so a constructor names its own argument and start-up
(:func:`sss2bathy.config_validation.instantiate_group`) turns it into the config key.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterable
from typing import Any

__all__ = [
    "is_integer",
    "is_number",
    "require",
    "require_bool",
    "require_choice",
    "require_int",
    "require_number",
]


def is_integer(value: Any) -> bool:
    """An ``int`` that is not a ``bool``."""
    return isinstance(value, int) and not isinstance(value, bool)


def is_number(value: Any) -> bool:
    """A finite ``int`` or ``float`` that is not a ``bool``."""
    return isinstance(value, int | float) and not isinstance(value, bool) and math.isfinite(value)


def require(name: str, value: Any, ok: bool, expected: str) -> Any:
    """``value`` when ``ok``; else ``ValueError("<name>: expected <expected>, found ...")``."""
    if not ok:
        raise ValueError(f"{name}: expected {expected}, found {value!r}")
    return value


def require_bool(name: str, value: Any) -> bool:
    """``value`` when it is ``True`` or ``False``."""
    return require(name, value, isinstance(value, bool), "true or false")


def require_int(name: str, value: Any, minimum: int = 1, expected: str | None = None) -> int:
    """``value`` when it is an integer ``>= minimum`` (default: a positive integer)."""
    if expected is None:
        expected = "a positive integer" if minimum == 1 else f"an integer >= {minimum}"
    return require(name, value, is_integer(value) and value >= minimum, expected)


def require_number(
    name: str, value: Any, ok: Callable[[float], bool], expected: str, optional: bool = False
) -> Any:
    """``value`` when it is a finite number with ``ok(value)`` (or ``None`` if ``optional``)."""
    if optional and value is None:
        return None
    return require(name, value, is_number(value) and ok(value), expected)


def require_choice(name: str, value: Any, choices: Iterable[Any]) -> Any:
    """``value`` when it is one of ``choices``."""
    choices = tuple(choices)
    return require(name, value, value in choices, f"one of {list(choices)}")
