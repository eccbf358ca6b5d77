"""The one set of setting checks: ``<name>: expected <what>, found <value!r>``.

Each check returns the value when it is acceptable and raises :class:`ValueError` with that
one-line message (:func:`config_error`) otherwise, so a constructor names its own argument
and start-up (:func:`sss2bathy.config_validation.instantiate_group`) turns it into the
config key. Config sections are read the same way: a dataclass declares each field's key,
default, bounds and unit once (:func:`setting`), one generic reader checks and converts
them (:class:`ConfigReader`, :func:`read_fields`) and rejects unknown keys, and
:func:`coerce_config` builds a config dataclass from None, a mapping or itself.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterable, Mapping, Sequence
from typing import Any, TypeVar

T = TypeVar("T")

__all__ = [
    "ConfigReader",
    "check_number",
    "coerce_config",
    "config_error",
    "is_integer",
    "is_number",
    "require",
    "require_bool",
    "require_choice",
    "require_int",
    "require_number",
    "read_fields",
    "setting",
]


def is_integer(value: Any) -> bool:
    """An ``int`` that is not a ``bool``."""
    return isinstance(value, int) and not isinstance(value, bool)


def is_number(value: Any) -> bool:
    """A finite ``int`` or ``float`` that is not a ``bool``."""
    return isinstance(value, int | float) and not isinstance(value, bool) and math.isfinite(value)


def config_error(path: str, expected: str, found: Any) -> ValueError:
    """The one error format of this package: ``<key>: expected <what>, found <value>``."""
    return ValueError(f"{path}: expected {expected}, found {found!r}")


def require(name: str, value: Any, ok: bool, expected: str) -> Any:
    """``value`` when ``ok``; else :func:`config_error`."""
    if not ok:
        raise config_error(name, expected, value)
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


# ------------------------------------------------------------------ config sections
def check_number(
    path: str,
    value: Any,
    *,
    gt: float | None = None,
    ge: float | None = None,
    lt: float | None = None,
    le: float | None = None,
) -> float:
    """``float(value)`` when it is a finite number within the given bounds."""
    if not is_number(value):
        raise config_error(path, "a finite number", value)
    bounds = [(">", gt, value > (gt or 0)), (">=", ge, value >= (ge or 0))]
    bounds += [("<", lt, value < (lt or 0)), ("<=", le, value <= (le or 0))]
    bounds = [(op, limit, ok) for op, limit, ok in bounds if limit is not None]
    if not all(ok for _, _, ok in bounds):
        limits = " and ".join(f"{op} {limit}" for op, limit, _ in bounds)
        raise config_error(path, f"a number {limits}", value)
    return float(value)


#: :func:`setting`'s key in a dataclass field's metadata
SETTING = "sss2bathy.setting"
#: unit conversions from a config's value to the field's (degrees to radians, kHz to Hz)
UNITS: dict[str, Callable[[float], float]] = {"deg": math.radians, "khz": lambda v: 1e3 * v}


def setting(default: Any, key: str | None = None, *, kind: str = "number", **options: Any) -> Any:
    """A dataclass field read from a config section by :func:`read_fields`, its bounds and
    unit declared once, here: ``key`` (default: the field's name; ``water.ph`` reads ``ph``
    of the sub-section ``water``), ``kind`` (a :class:`ConfigReader` method: ``number``,
    ``integer``, ``optional_number``, ``pair``, ``optional_pair``, ``numbers``, ``choice``,
    ``text``), ``unit`` (:data:`UNITS`) and the method's bounds (``gt``, ``ge``, ``lt``,
    ``le``, ``choices``, ``ordered``). A key the config leaves out takes ``default``."""
    from dataclasses import field

    return field(default=default, metadata={SETTING: {"key": key, "kind": kind, **options}})


class ConfigReader:
    """Reads one config section key by key and rejects keys nobody asked for."""

    def __init__(self, data: Any, path: str) -> None:
        if data is None:
            data = {}
        if not isinstance(data, Mapping):
            raise config_error(path, "a mapping", data)
        self.data, self.path, self.used = dict(data), path, set()
        self.sections: dict[str, ConfigReader] = {}

    def get(self, key: str, default: Any) -> tuple[str, Any]:
        """``(full key, value or default)``; the key counts as used."""
        self.used.add(key)
        return f"{self.path}.{key}", self.data.get(key, default)

    def number(self, key: str, default: float, **bounds: float) -> float:
        path, value = self.get(key, default)
        return check_number(path, value, **bounds)

    def integer(self, key: str, default: int, *, ge: int | None = None) -> int:
        path, value = self.get(key, default)
        if isinstance(value, bool) or not isinstance(value, int | float) or value != int(value):
            raise config_error(path, "an integer", value)
        if ge is not None and value < ge:
            raise config_error(path, f"an integer >= {ge}", value)
        return int(value)

    def optional_number(self, key: str, default: float | None, **bounds: float) -> float | None:
        path, value = self.get(key, default)
        return None if value is None else check_number(path, value, **bounds)

    def pair(
        self,
        key: str,
        default: Sequence[float],
        *,
        gt: float | None = None,
        le: float | None = None,
        ordered: bool = True,
    ) -> tuple[float, float]:
        """Two numbers; ``[lo, hi]`` with ``lo <= hi`` when ``ordered``."""
        path, value = self.get(key, default)
        if not isinstance(value, Sequence) or isinstance(value, str) or len(value) != 2:
            raise config_error(path, "a [low, high] pair", value)
        lo = check_number(f"{path}[0]", value[0], gt=gt, le=le)
        hi = check_number(f"{path}[1]", value[1], gt=gt, le=le)
        if ordered and lo > hi:
            raise config_error(path, "low <= high", list(value))
        return lo, hi

    def optional_pair(self, key: str, default: Any = None, **bounds: Any) -> tuple | None:
        """A :meth:`pair`, or None when the key is absent or null."""
        if self.data.get(key) is None:
            self.used.add(key)
            return None
        return self.pair(key, (0.0, 0.0), **bounds)

    def numbers(self, key: str, default: Sequence[float], *, ge: float | None = None) -> tuple:
        path, value = self.get(key, default)
        if not isinstance(value, Sequence) or isinstance(value, str):
            raise config_error(path, "a list of numbers", value)
        return tuple(check_number(f"{path}[{i}]", v, ge=ge) for i, v in enumerate(value))

    def choice(self, key: str, default: str, choices: Sequence[str]) -> str:
        path, value = self.get(key, default)
        if value not in choices:
            raise config_error(path, f"one of {list(choices)}", value)
        return str(value)

    def boolean(self, key: str, default: bool = False) -> bool:
        """``true`` / ``false``; absent or null: ``default``."""
        path, value = self.get(key, None)
        if value is None:
            return default
        return require_bool(path, value)

    def text(self, key: str, default: str | None) -> str | None:
        path, value = self.get(key, default)
        if value is not None and not isinstance(value, str):
            raise config_error(path, "a string", value)
        return value

    def section(self, key: str) -> ConfigReader:
        """The sub-section ``key`` (one reader per key)."""
        if key not in self.sections:
            path, value = self.get(key, None)
            self.sections[key] = ConfigReader(value, path)
        return self.sections[key]

    def raw(self, key: str) -> Any:
        return self.get(key, None)[1]

    def done(self) -> None:
        """Every sub-section read, then this one: an unknown key is an error."""
        for section in self.sections.values():
            section.done()
        unknown = sorted(set(self.data) - self.used)
        if unknown:
            raise ValueError(
                f"{self.path}: unknown key(s) {unknown}; expected some of {sorted(self.used)}"
            )


def read_fields(r: ConfigReader, cls: type, skip: Iterable[str] = ()) -> dict[str, Any]:
    """The values of ``cls``'s :func:`setting` fields (but ``skip``) from the section ``r``,
    checked and converted to the field's unit; a key left out takes the field's default."""
    from dataclasses import fields

    out: dict[str, Any] = {}
    for f in fields(cls):
        spec = dict(f.metadata.get(SETTING) or {})
        if not spec or f.name in skip:
            continue
        section, _, key = (spec.pop("key") or f.name).rpartition(".")
        kind, unit = spec.pop("kind"), spec.pop("unit", None)
        reader = r.section(section) if section else r
        if key not in reader.data:
            reader.used.add(key)
            out[f.name] = f.default
            continue
        value = getattr(reader, kind)(key, None, **spec)
        if unit is not None and value is not None:
            convert = UNITS[unit]
            value = tuple(convert(v) for v in value) if isinstance(value, tuple) else convert(value)
        out[f.name] = value
    return out


def coerce_config(cls: type[T], cfg: Any, name: str) -> T:
    """A config dataclass ``cls`` from ``None`` (its defaults), a mapping whose keys are its
    fields (a plain dict, a DictConfig) or an instance; ``name`` names it in errors."""
    from dataclasses import fields

    if cfg is None:
        return cls()
    if isinstance(cfg, cls):
        return cfg
    if not isinstance(cfg, Mapping):
        raise ValueError(
            f"{name}: expected a mapping or {cls.__name__}, found {type(cfg).__name__}"
        )
    known = {f.name for f in fields(cls)}  # type: ignore[arg-type]
    unknown = sorted(set(cfg) - known)
    if unknown:
        raise ValueError(f"{name}: unknown keys {unknown}; expected some of {sorted(known)}")
    return cls(**{str(k): v for k, v in cfg.items()})
