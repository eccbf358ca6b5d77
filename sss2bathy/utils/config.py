"""Config plumbing shared by the stages."""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any


def plain_config(cfg: Any, what: str = "data.survey") -> dict[str, Any]:
    """A resolved plain ``dict`` of a ``DictConfig`` or mapping (``what`` names it in errors)."""
    from omegaconf import DictConfig, OmegaConf

    if isinstance(cfg, DictConfig):
        return OmegaConf.to_container(cfg, resolve=True)  # type: ignore[return-value]
    if not isinstance(cfg, Mapping):
        raise ValueError(f"cfg: expected a mapping ({what}), found {type(cfg).__name__}")
    return dict(cfg)
