"""Start-up validation of composed configs: fail before any heavy work, naming the key.

Each rule is ``(dotted key, predicate, expectation)``; a rule whose key is absent from the
composed config is skipped (not every task has every group).  Stage code still validates
its own arguments; these rules catch the common mistakes before data is generated.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import Any

from omegaconf import DictConfig, OmegaConf


class ConfigError(ValueError):
    """A config value is invalid; the message names the key, expected and found value."""


def _num(pred: Callable[[float], bool]) -> Callable[[Any], bool]:
    def check(v: Any) -> bool:
        return (
            isinstance(v, int | float) and not isinstance(v, bool) and math.isfinite(v) and pred(v)
        )

    return check


positive = _num(lambda v: v > 0)
non_negative = _num(lambda v: v >= 0)
fraction = _num(lambda v: 0 <= v < 1)
beam_width = _num(lambda v: 0 < v < 180)
tilt = _num(lambda v: -90 <= v <= 90)
positive_int = lambda v: isinstance(v, int) and not isinstance(v, bool) and v > 0  # noqa: E731

RULES: list[tuple[str, Callable[[Any], bool], str]] = [
    ("seed", lambda v: isinstance(v, int) and v >= 0, "a non-negative integer"),
    ("torch_threads", positive_int, "a positive integer or null"),
    ("trainer.max_epochs", lambda v: v == -1 or positive_int(v), "a positive integer or -1"),
    ("data.batch_size", positive_int, "a positive integer"),
    ("data.batch_pings", positive_int, "a positive integer"),
    ("data.altimeter_points", positive_int, "a positive integer"),
    ("data.window_pings", positive_int, "a positive integer"),
    ("data.window_bins", positive_int, "a positive integer"),
    ("data.overlap", fraction, "a fraction in [0, 1)"),
    ("data.min_valid_fraction", _num(lambda v: 0 <= v <= 1), "a fraction in [0, 1]"),
    ("data.val_fraction", fraction, "a fraction in [0, 1)"),
    ("data.num_workers", lambda v: isinstance(v, int) and v >= 0, "a non-negative integer"),
    ("data.survey.terrain.cell_m", positive, "a positive number (m)"),
    ("data.survey.beam_width_deg", beam_width, "a value in (0, 180) degrees"),
    ("data.survey.tilt_deg", tilt, "a value in [-90, 90] degrees"),
    ("data.survey.n_bins", positive_int, "a positive integer"),
    ("data.survey.mbes_cell_size", positive, "a positive number (m)"),
    ("data.survey.sonar.beam_width_deg", beam_width, "a value in (0, 180) degrees"),
    ("data.survey.sonar.tilt_deg", tilt, "a value in [-90, 90] degrees"),
    ("data.survey.sonar.n_bins", positive_int, "a positive integer"),
    ("data.survey.sonar.max_range_m", positive, "a positive number (m)"),
    ("data.survey.plan.line_spacing_m", positive, "a positive number (m)"),
    ("data.survey.plan.speed_mps", positive, "a positive number (m/s)"),
    ("data.survey.plan.ping_rate_hz", positive, "a positive number (Hz)"),
    ("model.w_height", non_negative, "a number >= 0"),
    ("model.eval_cell_m", positive, "a positive number (m)"),
    ("model.eval_every_n_epochs", positive_int, "a positive integer"),
    ("model.finder.tol_m", positive, "a positive tolerance (m)"),
    ("model.sensor.shadow_threshold", non_negative, "a number >= 0"),
    ("model.sensor.q", _num(lambda v: v >= 1), "an exponent >= 1"),
    ("model.optimizer.lr", positive, "a positive learning rate"),
]


def _select(cfg: DictConfig, key: str) -> tuple[bool, Any]:
    sentinel = object()
    value = OmegaConf.select(cfg, key, default=sentinel, throw_on_missing=False)
    return (value is not sentinel), value


def validate_config(cfg: DictConfig) -> None:
    """Raise :class:`ConfigError` on the first rule a present key breaks."""
    for key, pred, expected in RULES:
        present, value = _select(cfg, key)
        if present and value is not None and not pred(value):
            raise ConfigError(f"config key '{key}': expected {expected}, found {value!r}")
    for key in ("data.sidescan_split", "data.altimeter_split"):
        present, value = _select(cfg, key)
        if present and value is not None and not isinstance(value, str):
            raise ConfigError(f"config key '{key}': expected a split name, found {value!r}")
    present, w = _select(cfg, "data.window_bins")
    present_b, b = _select(cfg, "data.survey.sonar.n_bins")
    if present and present_b and isinstance(w, int) and isinstance(b, int) and w > b:
        raise ConfigError(
            f"config key 'data.window_bins': expected <= data.survey.sonar.n_bins ({b}), found {w}"
        )
