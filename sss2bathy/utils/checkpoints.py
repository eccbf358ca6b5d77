"""Checkpoint discovery: the one place that knows where Lightning runs keep their checkpoints.

A Hydra run folder ``<run>/`` holds ``checkpoints/last.ckpt`` (``ModelCheckpoint``'s periodic
save), possibly ``hpc_ckpt_<n>.ckpt`` (what Lightning's SLURM auto-requeue writes into the
trainer's ``default_root_dir``) and ``.hydra/config.yaml`` (the composed config, whose
``scale.name`` says at which scale the run was trained).

Used by the SIREN's ``cnn_checkpoint=latest`` and ``sss2bathy-predict ckpt_path=latest``
(:func:`sss2bathy.data.cnn_normals.latest_checkpoint`: the newest CNN run) and by
``sss2bathy-train ckpt_path=last`` (:func:`sss2bathy.cli.instantiate.latest_resume_checkpoint`:
the newest save of one run).
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import yaml

RUN_CHECKPOINT = "checkpoints/last.ckpt"
RUNS_PATTERNS = ("**/" + RUN_CHECKPOINT,)  # every run below a folder of runs
RESUME_PATTERNS = (RUN_CHECKPOINT, "hpc_ckpt_*.ckpt")  # the saves of one run folder


def find_checkpoints(folder: str | Path, patterns: Sequence[str] = RUNS_PATTERNS) -> list[Path]:
    """Checkpoint files under ``folder`` matching any of the glob ``patterns``, oldest first
    (by modification time, ties by path); ``[]`` when there are none or no ``folder``."""
    if isinstance(patterns, str):
        raise ValueError(f"patterns: expected a sequence of glob patterns, found {patterns!r}")
    folder = Path(folder)
    found = {p for pattern in patterns for p in folder.glob(pattern) if p.is_file()}
    return sorted(found, key=lambda p: (p.stat().st_mtime, str(p)))


def run_scale(ckpt: str | Path) -> str | None:
    """``scale.name`` of the Hydra run a ``<run>/checkpoints/last.ckpt`` belongs to (from
    ``<run>/.hydra/config.yaml``), or None when the run has no readable config."""
    config = Path(ckpt).parent.parent / ".hydra" / "config.yaml"
    if not config.is_file():
        return None
    try:
        data = yaml.safe_load(config.read_text()) or {}
    except (OSError, yaml.YAMLError):
        return None
    scale = data.get("scale") if isinstance(data, dict) else None
    name = scale.get("name") if isinstance(scale, dict) else None
    return str(name) if name is not None else None
