"""Start-up validation of composed configs: fail before any heavy work, naming the key.

One system, two halves, both run by ``sss2bathy-train`` before any data is made:

* the constructors validate their own arguments (``<argument>: expected ..., found ...``);
  start-up instantiates datamodule, model, callbacks, loggers and trainer first
  (:func:`sss2bathy.cli.train.instantiate_run`, data is made later in ``prepare_data`` /
  ``setup``) and :func:`instantiate_group` turns such an error into a :class:`ConfigError`
  naming the config key (``config key 'model.finder.tol_m': expected ..., found ...``).
  Whole groups with a config class of their own are checked by constructing it here: a
  synthetic ``data.survey`` (:class:`~sss2bathy.sim.config.SyntheticSurveyConfig`, every key,
  test surveys included), ``data.drape`` (:class:`~sss2bathy.draping.DrapeConfig`),
  ``data.sonar_mask``, an xtf survey by the importer's own checks
  (:func:`~sss2bathy.io.xtf_survey.validate_xtf_config`);
* :data:`RULES`, ``(dotted key, predicate, expectation)``, for what no constructor of ours
  sees: top-level run keys (``seed``, ``deterministic``, ``guard.*``, ``scale.siren.*``),
  keys of third-party constructors (Lightning's trainer and checkpoints, torch's optimizers
  and schedulers), the few module keys whose constructor does not check them yet, and the
  cross-key rules in :func:`validate_config`. A rule whose key is absent from the composed
  config (or null) is skipped. Enumerations are imported from the module that owns them
  (:class:`_OneOf`).

Checks that need the data (split names, window size vs the lines' pings) run in the data
modules' ``setup`` and name the config key too.
"""

from __future__ import annotations

import re
from collections.abc import Callable
from typing import Any

from omegaconf import DictConfig, ListConfig, OmegaConf

from sss2bathy.utils.checks import is_integer, is_number


class ConfigError(ValueError):
    """A config value is invalid; the message names the key, expected and found value."""


def _num(pred: Callable[[float], bool]) -> Callable[[Any], bool]:
    """A finite number (:func:`~sss2bathy.utils.checks.is_number`) with ``pred``."""
    return lambda v: is_number(v) and pred(v)


def _int(minimum: int) -> Callable[[Any], bool]:
    """An integer (:func:`~sss2bathy.utils.checks.is_integer`) ``>= minimum``."""
    return lambda v: is_integer(v) and v >= minimum


positive = _num(lambda v: v > 0)
non_negative = _num(lambda v: v >= 0)
positive_int = _int(1)
non_negative_int = _int(0)
boolean = lambda v: isinstance(v, bool)  # noqa: E731


class _OneOf:
    """``v in <module>.<name>`` (a tuple, or a mapping's keys), imported on first use: the
    table names where an enumeration lives instead of copying it."""

    def __init__(self, module: str, name: str) -> None:
        self.module, self.name = module, name

    def choices(self) -> tuple:
        import importlib

        return tuple(getattr(importlib.import_module(self.module), self.name))

    def __call__(self, v: Any) -> bool:
        return v in self.choices()

    def __str__(self) -> str:
        return f"one of {list(self.choices())}"


def _choices(module: str, name: str) -> tuple[Callable[[Any], bool], _OneOf]:
    check = _OneOf(module, name)
    return check, check


RULES: list[tuple[str, Callable[[Any], bool], str | _OneOf]] = [
    # top-level run keys (conf/train.yaml): no constructor sees them
    ("seed", non_negative_int, "a non-negative integer"),
    ("torch_threads", positive_int, "a positive integer or null"),
    ("deterministic", boolean, "true or false"),
    ("guard.max_consecutive_nonfinite", positive_int, "a positive integer"),
    ("scale.siren.steps_per_epoch", positive_int, "a positive integer or null"),
    ("scale.siren.fast_steps_per_epoch", positive_int, "a positive integer"),
    # siren_schedule=budget's keys (interpolated into data.bin_fraction, the scheduler, ...)
    ("scale.siren.budget_s", positive, "a positive number of seconds"),
    ("scale.siren.bin_fraction", _num(lambda x: 0 < x <= 1), "a fraction in (0, 1]"),
    ("scale.siren.neighbour_start", boolean, "true or false"),
    # third-party constructors: Lightning's trainer and checkpoints, torch's optimizers
    ("trainer.max_epochs", lambda v: v == -1 or positive_int(v), "a positive integer or -1"),
    ("trainer.min_epochs", non_negative_int, "an integer >= 0"),
    ("trainer.check_val_every_n_epoch", positive_int, "a positive integer or null"),
    ("trainer.log_every_n_steps", positive_int, "a positive integer"),
    ("trainer.accumulate_grad_batches", positive_int, "a positive integer"),
    ("trainer.gradient_clip_val", non_negative, "a number >= 0 or null"),
    ("callbacks.epoch_checkpoint.every_n_epochs", non_negative_int, "an integer >= 0"),
    ("callbacks.step_checkpoint.every_n_train_steps", non_negative_int, "an integer >= 0"),
    ("model.optimizer.lr", positive, "a positive learning rate"),
    ("model.scheduler.gamma", _num(lambda x: 0 < x <= 1), "a decay factor in (0, 1]"),
]


def _select(cfg: DictConfig, key: str) -> tuple[bool, Any]:
    sentinel = object()
    value = OmegaConf.select(cfg, key, default=sentinel, throw_on_missing=False)
    return (value is not sentinel), value


def _group_error(err: ValueError, old: str = "", new: str = "") -> ConfigError:
    """A group validator's ``<key>: expected ..., found ...`` as a :class:`ConfigError`
    (the key's prefix ``old`` replaced by ``new``)."""
    key, _, rest = str(err).partition(":")
    key = key.strip()
    if old and key.startswith(old):
        key = new + key[len(old) :]
    return ConfigError(f"config key '{key}':{rest}")


def _plain(cfg: DictConfig, key: str) -> Any:
    node = OmegaConf.select(cfg, key, default=None, throw_on_missing=False)
    if isinstance(node, DictConfig | ListConfig):
        return OmegaConf.to_container(node, resolve=True, throw_on_missing=False)
    return node


def _validate_survey(survey: Any, where: str) -> None:
    """A ``data/survey`` config: synthetic (every key) or xtf; others are checked on use."""
    if not isinstance(survey, dict):
        return
    if survey.get("kind") == "synthetic":
        import warnings

        from sss2bathy.sim.config import ROOT, SyntheticSurveyConfig

        try:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")  # unknown keys: warned when generating
                SyntheticSurveyConfig.from_mapping(survey)
        except ValueError as err:
            raise _group_error(err, ROOT, where) from None
    elif survey.get("kind") == "xtf" and where == "data.survey":
        from sss2bathy.io.xtf_survey import validate_xtf_config

        try:
            validate_xtf_config(survey)
        except ValueError as err:
            raise _group_error(err) from None


def _validate_groups(cfg: DictConfig) -> None:
    _validate_survey(_plain(cfg, "data.survey"), "data.survey")
    for i, extra in enumerate(_plain(cfg, "data.test_surveys") or []):
        _validate_survey(extra, f"data.test_surveys[{i}]")
    sonar_mask = _plain(cfg, "data.sonar_mask")
    if sonar_mask is not None:
        from sss2bathy.data.masks import SonarMaskConfig

        try:
            SonarMaskConfig.coerce(sonar_mask)
        except ValueError as err:
            raise _group_error(err, "sonar_mask", "data.sonar_mask") from None
    for key in ("data.input_channels", "model.input_channels"):
        channels = _plain(cfg, key)
        if channels is not None:
            from sss2bathy.data.masks import check_channels

            try:
                check_channels(channels, key)
            except ValueError as err:
                raise _group_error(err) from None
    drape = _plain(cfg, "data.drape")
    if isinstance(drape, dict):
        from sss2bathy.draping import DrapeConfig

        try:
            DrapeConfig.coerce(drape)
        except ValueError as err:
            raise _group_error(err, "drape.", "data.drape.") from None


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
    for bins_key in ("data.survey.sonar.n_bins", "data.survey.n_bins"):
        present_b, b = _select(cfg, bins_key)
        if present and present_b and isinstance(w, int) and isinstance(b, int) and w > b:
            raise ConfigError(
                f"config key 'data.window_bins': expected <= {bins_key} ({b}) (a window "
                f"within the waterfall), found {w}"
            )
    _, lo = _select(cfg, "trainer.min_epochs")
    _, hi = _select(cfg, "trainer.max_epochs")
    if isinstance(lo, int) and isinstance(hi, int) and hi != -1 and lo > hi:
        raise ConfigError(
            f"config key 'trainer.min_epochs': expected <= trainer.max_epochs ({hi}), found {lo}"
        )
    _validate_groups(cfg)


# ------------------------------------------------------------------- constructor checks
_ARGUMENT = re.compile(
    r"^([A-Za-z_][\w]*(?:\[\d+\])?(?:\.[A-Za-z_][\w]*(?:\[\d+\])?)*): (.*)$", re.S
)


_FULL_KEY = re.compile(r"\nfull_key: (\S+)\s*$")


def _root_cause(err: BaseException) -> tuple[BaseException, str | None]:
    """The constructor's own error inside Hydra's ``InstantiationException`` wrappers, and
    the config key of the innermost node Hydra was instantiating (its ``full_key``)."""
    from hydra.errors import InstantiationException

    full_key = None
    while isinstance(err, InstantiationException) and err.__cause__ is not None:
        match = _FULL_KEY.search(str(err))
        if match:
            full_key = match.group(1)
        err = err.__cause__
    return err, full_key


def constructor_error(node: str, err: BaseException, cfg: DictConfig | None = None) -> ConfigError:
    """A constructor's ``<argument>: expected ..., found ...`` as a :class:`ConfigError`
    naming the config key ``<node>.<argument>``, ``node`` being the config node whose
    ``_target_`` raised it: the constructor validated its own argument, this only says
    where in the config it came from. An argument already spelled from the config root
    (``data.survey.plan.n_test``) keeps its name; ``drape.rays_per_bin`` raised for the
    ``data`` node becomes ``data.drape.rays_per_bin``. With the composed ``cfg``: an
    argument the node lacks but exactly one of its sub-nodes holds was raised by that
    sub-node's object, built by the node's own constructor from a ``_partial_`` factory
    (``hidden`` raised for ``model`` is ``model.siren.hidden``); several such sub-nodes are
    all named."""
    message = str(err)
    match = _ARGUMENT.match(message)
    if match is None:
        return ConfigError(f"config node '{node}': {message}")
    argument, rest = match.groups()
    if argument.split(".")[0] in _ROOT_KEYS:
        return ConfigError(f"config key '{argument}': {rest}")
    key = f"{node}.{argument}"
    section = OmegaConf.select(cfg, node, default=None) if cfg is not None else None
    head = argument.split(".")[0].split("[")[0]
    if isinstance(section, DictConfig) and head not in section:
        holders = [
            str(k)
            for k, v in section.items_ex(resolve=False)
            if isinstance(v, DictConfig) and head in v
        ]
        if len(holders) == 1:
            key = f"{node}.{holders[0]}.{argument}"
        elif holders:  # several sub-nodes hold the argument: name each, never a wrong one
            keys = " or ".join(f"'{node}.{h}.{argument}'" for h in holders)
            return ConfigError(f"config key {keys}: {rest}")
    return ConfigError(f"config key '{key}': {rest}")


# first parts of a dotted argument that already name a key from the config root
_ROOT_KEYS = ("data", "model", "trainer", "callbacks", "logger", "scale", "paths")


def instantiate_group(group: str, build: Callable[[], Any], cfg: DictConfig | None = None) -> Any:
    """``build()`` (the instantiation of the ``group`` node of the composed ``cfg``), its
    constructors' ``ValueError`` as a :class:`ConfigError` naming the config key
    (:func:`constructor_error`)."""
    try:
        return build()
    except ConfigError:
        raise
    except Exception as err:  # Hydra wraps constructor errors in InstantiationException
        cause, full_key = _root_cause(err)
        if isinstance(cause, ValueError) and not isinstance(cause, ConfigError):
            raise constructor_error(full_key or group, cause, cfg) from err
        raise
