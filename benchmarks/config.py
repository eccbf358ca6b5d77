"""The project's configs as Hydra composes them, for the benchmarks' presets.

Benchmarks take their sizes from ``conf/`` of the project root they are given (the
runner's ``--root`` or ``$SSS2BATHY_ROOT``), composed with the same defaults lists and
overrides the entry points use, never from hand-merged files.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

from omegaconf import DictConfig, OmegaConf


def project_root(root: str | Path | None = None) -> Path:
    """``root``, else ``$SSS2BATHY_ROOT``, else the current directory; it must hold ``conf/``."""
    given = root if root is not None else os.environ.get("SSS2BATHY_ROOT") or Path.cwd()
    path = Path(given).resolve()
    if not (path / "conf").is_dir():
        raise ValueError(
            f"root: expected the project checkout (a folder with conf/), found {path} "
            "(pass --root or set SSS2BATHY_ROOT)"
        )
    return path


def compose(root: str | Path, config_name: str, overrides: list[str]) -> DictConfig:
    """``config_name`` of ``<root>/conf`` composed with ``overrides`` (Hydra's compose API)."""
    from hydra import compose as hydra_compose
    from hydra import initialize_config_dir
    from hydra.core.global_hydra import GlobalHydra

    conf = project_root(root) / "conf"
    GlobalHydra.instance().clear()
    try:
        with initialize_config_dir(config_dir=str(conf), version_base="1.3"):
            return hydra_compose(config_name=config_name, overrides=list(overrides))
    finally:
        GlobalHydra.instance().clear()


def plain(cfg: DictConfig, key: str) -> Any:
    """The resolved plain value at ``key`` of a composed config (an error names the key)."""
    node = OmegaConf.select(cfg, key, throw_on_missing=True)
    if node is None:
        raise ValueError(f"{key}: expected a value in the composed config, found none")
    if OmegaConf.is_config(node):
        return OmegaConf.to_container(node, resolve=True)
    return node


def survey_preset(root: str | Path, survey: str, scale: str) -> dict:
    """The ``data.survey`` of a survey preset at a scale, as ``sss2bathy-prepare`` composes it."""
    cfg = compose(root, "prepare", [f"data/survey={survey}", f"scale={scale}"])
    return plain(cfg, "data.survey")


def cnn_preset(root: str | Path, scale: str) -> dict[str, Any]:
    """The CNN experiment at a scale (``experiment=cnn scale=<scale>``): network width,
    residual blocks, down-sampling stages, batch, and the composed loss config."""
    cfg = compose(root, "train", ["experiment=cnn", f"scale={scale}"])
    return {
        "base_width": int(plain(cfg, "model.net.base_width")),
        "n_blocks": int(plain(cfg, "model.net.n_blocks")),
        "n_down": int(plain(cfg, "model.net.n_down")),
        "batch_size": int(plain(cfg, "data.batch_size")),
        "loss": plain(cfg, "model.loss"),
    }
