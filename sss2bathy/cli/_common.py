"""Shared start-up for the entry points: project root, config path, run records, and
one-line user errors.

A user error (a bad file, a bad config value, a missing checkpoint, a typo'd override) ends
an entry point with ONE line on stderr, ``error: <what happened>``, and exit status 2
(:data:`USER_ERROR_EXIT`); ``--trace`` on the command line or ``HYDRA_FULL_ERROR=1`` shows
the traceback instead. Hydra entry points use :func:`hydra_entry` in place of
``@hydra.main``; plain ``argparse`` ones wrap their body in :func:`user_errors`.
"""

from __future__ import annotations

import difflib
import functools
import json
import logging
import os
import re
import subprocess
import sys
import warnings
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import Any

from omegaconf import DictConfig, OmegaConf

from sss2bathy.utils.atomic import atomic_write_text

log = logging.getLogger("sss2bathy")


def project_root() -> Path:
    """The project root: ``$SSS2BATHY_ROOT``, else the checkout this package lives in, else cwd."""
    env = os.environ.get("SSS2BATHY_ROOT")
    if env:
        return Path(env).resolve()
    here = Path(__file__).resolve().parents[2]
    if (here / "conf").is_dir() and (here / "pyproject.toml").is_file():
        return here
    return Path.cwd().resolve()


def config_dir() -> str:
    """Absolute path of ``conf/`` (editable installs and checkouts)."""
    path = project_root() / "conf"
    if not path.is_dir():
        raise FileNotFoundError(
            f"conf/ not found under {path.parent}; run from the project checkout or set "
            "SSS2BATHY_ROOT to it"
        )
    return str(path)


def setup_environment() -> None:
    """Set ``SSS2BATHY_ROOT`` so ``conf/paths`` resolves, and keep glibc from re-faulting the
    memory of large tensors (:func:`sss2bathy.utils.alloc.tune_allocator`; opt out with
    ``SSS2BATHY_MALLOC=default``); call before ``@hydra.main``."""
    from sss2bathy.utils.alloc import tune_allocator

    os.environ.setdefault("SSS2BATHY_ROOT", str(project_root()))
    if TRACE_FLAG in sys.argv[1:]:
        sys.argv = [a for a in sys.argv if a != TRACE_FLAG]
        os.environ[TRACE_ENV] = "1"
        os.environ["HYDRA_FULL_ERROR"] = "1"  # Hydra's own errors with their trace too
    tune_allocator()


# ----------------------------------------------------------------------------- user errors
TRACE_FLAG = "--trace"
TRACE_ENV = "SSS2BATHY_TRACE"
USER_ERROR_EXIT = 2


def show_traceback() -> bool:
    """``--trace`` was given, or ``HYDRA_FULL_ERROR=1``: let errors raise with their trace."""
    return os.environ.get(TRACE_ENV) == "1" or os.environ.get("HYDRA_FULL_ERROR") == "1"


def user_error_types() -> tuple[type[BaseException], ...]:
    """Exceptions that are the user's input, not a bug: reported in one line."""
    from sss2bathy.config_validation import ConfigError
    from sss2bathy.survey import SurveyFormatError

    return (SurveyFormatError, ConfigError, ValueError, FileNotFoundError)


def one_line(message: str) -> str:
    """``message`` on one line (line breaks and runs of blanks become single blanks)."""
    return re.sub(r"\s+", " ", str(message)).strip()


def report_user_error(message: str) -> None:
    """Print ``error: <message>`` as one line on stderr and exit with status 2."""
    print(f"error: {one_line(message)}", file=sys.stderr, flush=True)
    raise SystemExit(USER_ERROR_EXIT)


def user_errors(fn: Callable[..., Any]) -> Callable[..., Any]:
    """Wrap an entry point: user errors (see :func:`user_error_types`) become one line on
    stderr and exit status 2, unless :func:`show_traceback`."""

    @functools.wraps(fn)
    def wrapper(*args: Any, **kwargs: Any) -> Any:
        try:
            return fn(*args, **kwargs)
        except user_error_types() as err:
            if show_traceback():
                raise
            report_user_error(str(err) or type(err).__name__)

    return wrapper


def _suggest(word: str, options: Sequence[str]) -> str:
    close = difflib.get_close_matches(word, list(options), n=3, cutoff=0.6)
    return f"; did you mean {' or '.join(repr(c) for c in close)}?" if close else ""


def _override_problem(config_name: str, overrides: list[str]) -> str | None:
    """Compose ``config_name`` with ``overrides`` as Hydra will; the one-line reason it
    fails (with a "did you mean" where a close key or option exists), else ``None``."""
    from hydra import compose, initialize_config_dir
    from hydra.core.global_hydra import GlobalHydra
    from hydra.errors import HydraException, MissingConfigException
    from omegaconf.errors import OmegaConfBaseException

    def attempt(ovr: list[str]) -> tuple[DictConfig | None, Exception | None]:
        GlobalHydra.instance().clear()
        try:
            with initialize_config_dir(config_dir=config_dir(), version_base="1.3"):
                return compose(config_name, overrides=ovr), None
        except (HydraException, OmegaConfBaseException, ValueError) as err:
            return None, err
        finally:
            GlobalHydra.instance().clear()

    _, err = attempt(overrides)
    if err is None:
        return None
    text = one_line(str(err).replace("Set the environment variable HYDRA_FULL_ERROR=1", ""))
    if isinstance(err, MissingConfigException) and err.missing_cfg_file:
        name = str(err.missing_cfg_file).rsplit("/", 1)[-1]
        return one_line(str(err).splitlines()[0]) + _suggest(name, err.options or [])
    match = re.search(r"Could not override '([^']+)'", text)
    if match:
        key = match.group(1)
        parent, _, leaf = key.rpartition(".")
        rest = [o for o in overrides if o.split("=", 1)[0].lstrip("+~") != key]
        base, _ = attempt(rest)
        options: list[str] = []
        if base is not None:
            node = OmegaConf.select(base, parent) if parent else base
            if isinstance(node, DictConfig):
                options = [str(k) for k in node.keys()]
        hint = _suggest(leaf, options)
        return f"unknown config key '{key}'{hint} (to add a new key: +{key}=...)"
    return text


def hydra_entry(config_name: str) -> Callable[[Callable[[DictConfig], Any]], Callable[[], Any]]:
    """``@hydra.main`` for this project's entry points, with one-line user errors.

    Before Hydra runs, a single run's overrides are composed once so that a typo'd key or
    group option is reported in one line with a "did you mean" (Hydra's own short message
    otherwise); inside the task, user errors are one line too (:func:`user_errors`).
    """
    import hydra

    def decorate(task: Callable[[DictConfig], Any]) -> Callable[[], Any]:
        hydra_main = hydra.main(
            version_base="1.3", config_path=config_dir(), config_name=config_name
        )(user_errors(task))

        @functools.wraps(task)
        def entry(cfg_passthrough: DictConfig | None = None) -> Any:
            if cfg_passthrough is not None:
                return hydra_main(cfg_passthrough)
            args = sys.argv[1:]
            plain = all(not a.startswith("-") for a in args)  # no -m, --cfg, --help, ...
            if plain and not show_traceback():
                problem = _override_problem(config_name, args)
                if problem is not None:
                    report_user_error(problem)
            return hydra_main()

        return entry

    return decorate


def apply_extras(cfg: DictConfig, print_config: bool = True) -> None:
    """Validate the composed config (before any dump), then apply ``extras``.

    ``print_config=False`` leaves the dump (``extras.print_config``) to the caller's
    :func:`log_config`, for an entry point whose constructors check more before it
    (``sss2bathy-train`` instantiates its run first)."""
    from sss2bathy.config_validation import validate_config

    validate_config(cfg)
    extras = cfg.get("extras") or {}
    if extras.get("ignore_warnings"):
        warnings.filterwarnings("ignore", category=UserWarning)
        warnings.filterwarnings("ignore", category=FutureWarning)
    if print_config:
        log_config(cfg)


def log_config(cfg: DictConfig) -> None:
    """Log the composed config when ``extras.print_config`` asks for it."""
    if (cfg.get("extras") or {}).get("print_config"):
        log.info("composed config:\n%s", OmegaConf.to_yaml(cfg, resolve=False))


def git_revision() -> str | None:
    try:
        out = subprocess.run(
            ["git", "rev-parse", "HEAD"],
            cwd=project_root(),
            capture_output=True,
            text=True,
            check=True,
            timeout=10,
        )
        dirty = subprocess.run(
            ["git", "status", "--porcelain", "--untracked-files=no"],
            cwd=project_root(),
            capture_output=True,
            text=True,
            timeout=10,
        ).stdout.strip()
        return out.stdout.strip() + ("-dirty" if dirty else "")
    except (OSError, subprocess.SubprocessError):
        return None


def to_jsonable(metrics: Mapping[str, Any]) -> dict[str, float]:
    out = {}
    for k, v in metrics.items():
        try:
            out[k] = float(v)
        except (TypeError, ValueError):
            continue
    return out


def write_run_record(run_dir: Path, cfg: DictConfig, metrics: Mapping[str, Any]) -> None:
    """``run_info.json`` (task, experiment, git revision, seed) and ``metrics.json``."""
    run_dir.mkdir(parents=True, exist_ok=True)
    choices = {}
    try:
        from hydra.core.hydra_config import HydraConfig

        choices = dict(HydraConfig.get().runtime.choices)
    except ValueError:  # not under @hydra.main (compose API)
        pass
    info = {
        "task_name": cfg.get("task_name"),
        "experiment": choices.get("experiment"),
        "scale": choices.get("scale"),
        "survey": choices.get("data/survey"),
        "seed": cfg.get("seed"),
        "survey_name": OmegaConf.select(cfg, "data.survey.name"),
        "data_dir": OmegaConf.select(cfg, "paths.data_dir"),
        "git_revision": git_revision(),
    }
    atomic_write_text(run_dir / "run_info.json", json.dumps(info, indent=2))
    atomic_write_text(run_dir / "metrics.json", json.dumps(to_jsonable(metrics), indent=2))
