"""Instantiate callbacks and loggers from their config groups; resolve checkpoint paths."""

from __future__ import annotations

import logging
from pathlib import Path

import hydra
from omegaconf import DictConfig

log = logging.getLogger("sss2bathy")


def _instantiate_group(group: DictConfig | None, kind: str) -> list:
    out = []
    if not group:
        return out
    for name, conf in group.items():
        if isinstance(conf, DictConfig) and "_target_" in conf:
            log.debug("instantiating %s %s <%s>", kind, name, conf._target_)
            out.append(hydra.utils.instantiate(conf, _convert_="partial"))
    return out


def instantiate_callbacks(cfg: DictConfig | None) -> list:
    return _instantiate_group(cfg, "callback")


def instantiate_loggers(cfg: DictConfig | None) -> list:
    return _instantiate_group(cfg, "logger")


def resolve_ckpt_path(ckpt_path: str | None, run_dir: Path | None) -> str | None:
    """``None`` | ``last`` (this run's ``checkpoints/last.ckpt`` if present) | a path."""
    if ckpt_path in (None, "", "null"):
        return None
    if ckpt_path == "last":
        if run_dir is not None and (run_dir / "checkpoints" / "last.ckpt").is_file():
            return str(run_dir / "checkpoints" / "last.ckpt")
        log.warning("ckpt_path=last: no last.ckpt in %s; starting fresh", run_dir)
        return None
    path = Path(ckpt_path)
    if not path.is_file():
        raise FileNotFoundError(f"ckpt_path: expected an existing checkpoint file, found {path}")
    return str(path)
