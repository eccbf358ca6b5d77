"""Shared start-up for the entry points: project root, config path, run records."""

from __future__ import annotations

import json
import logging
import os
import subprocess
import warnings
from collections.abc import Mapping
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
    tune_allocator()


def apply_extras(cfg: DictConfig) -> None:
    extras = cfg.get("extras") or {}
    if extras.get("ignore_warnings"):
        warnings.filterwarnings("ignore", category=UserWarning)
        warnings.filterwarnings("ignore", category=FutureWarning)
    if extras.get("print_config"):
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
