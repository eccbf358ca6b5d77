"""Config plumbing shared by the stages."""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path
from typing import Any


def plain_config(cfg: Any, what: str = "data.survey") -> dict[str, Any]:
    """A resolved plain ``dict`` of a ``DictConfig`` or mapping (``what`` names it in errors)."""
    from omegaconf import DictConfig, OmegaConf

    if isinstance(cfg, DictConfig):
        return OmegaConf.to_container(cfg, resolve=True)  # type: ignore[return-value]
    if not isinstance(cfg, Mapping):
        raise ValueError(f"cfg: expected a mapping ({what}), found {type(cfg).__name__}")
    return dict(cfg)


def scale_config(scale: str, conf_dir: str | Path) -> dict[str, Any]:
    """The plain ``scale`` block of ``conf_dir/scale/<scale>.yaml`` (every size of a scale:
    ``siren``, ``cnn`` and ``survey.<preset>``), as Hydra composes it."""
    from omegaconf import OmegaConf

    path = Path(conf_dir) / "scale" / f"{scale}.yaml"
    if not path.is_file():
        options = sorted(p.stem for p in path.parent.glob("*.yaml"))
        raise ValueError(f"scale: expected one of {options} (a file {path}), found {scale!r}")
    root = OmegaConf.create({"scale": OmegaConf.load(path)})
    return OmegaConf.to_container(root.scale, resolve=True)  # type: ignore[return-value]


def survey_preset(survey: str, scale: str, conf_dir: str | Path) -> dict[str, Any]:
    """Plain ``data.survey`` dict of the preset ``conf_dir/data/survey/<survey>.yaml`` at a
    scale, as Hydra composes it: its sized keys take ``scale.survey.<survey>`` of
    ``conf_dir/scale/<scale>.yaml``. For code that reads the presets without Hydra."""
    from omegaconf import OmegaConf

    path = Path(conf_dir) / "data" / "survey" / f"{survey}.yaml"
    if not path.is_file():
        options = sorted(p.stem for p in path.parent.glob("*.yaml"))
        raise ValueError(f"survey: expected one of {options} (a file {path}), found {survey!r}")
    root = OmegaConf.create(
        {"scale": scale_config(scale, conf_dir), "data": {"survey": OmegaConf.load(path)}}
    )
    return OmegaConf.to_container(root.data.survey, resolve=True)  # type: ignore[return-value]
