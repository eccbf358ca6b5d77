"""Instantiate callbacks and loggers from their config groups; resolve checkpoint paths."""

from __future__ import annotations

import logging
from pathlib import Path

import hydra
from omegaconf import DictConfig

from sss2bathy.utils.checkpoints import FALLBACK_PATTERNS, RESUME_PATTERNS, find_checkpoints

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


def latest_resume_checkpoint(run_dir: Path) -> Path | None:
    """The newest checkpoint to resume a run folder from, or None.

    ``checkpoints/last.ckpt`` (:class:`~sss2bathy.callbacks.LastCheckpoint`'s save, every
    epoch and every N steps) or ``hpc_ckpt_<n>.ckpt`` (what Lightning's SLURM auto-requeue
    writes into the trainer's ``default_root_dir`` on the pre-emption signal, see
    ``conf/trainer/slurm.yaml``), whichever is newer; without either, the newest other
    ``checkpoints/*.ckpt`` (a top-k save such as the CNN's ``epoch_NNNN.ckpt``).
    """
    found = find_checkpoints(run_dir, RESUME_PATTERNS)
    if not found:
        found = find_checkpoints(run_dir, FALLBACK_PATTERNS)
    return found[-1] if found else None


def resolve_ckpt_path(ckpt_path: str | None, run_dir: Path | None) -> str | None:
    """The checkpoint ``trainer.fit`` resumes from (``None``: start fresh).

    ``ckpt_path``:

    * ``None`` / ``"null"``: start fresh;
    * ``"last"``: this run's newest checkpoint (:func:`latest_resume_checkpoint` of
      ``run_dir``), or a fresh start with a warning when there is none yet. Each Hydra run
      gets a new folder, so resume an old run with its folder:
      ``ckpt_path=last hydra.run.dir=<old run dir>`` (training continues there), or
      with ``ckpt_path=<old run dir>`` (the new run gets its own folder);
    * a run folder: its newest checkpoint (an error when it has none);
    * a checkpoint file.

    Only the path is resolved here; ``sss2bathy.cli.train.fit`` reads the file, checks its
    kind and logs where the fit resumes.
    """
    if ckpt_path in (None, "", "null"):
        return None
    if ckpt_path == "last":
        found = latest_resume_checkpoint(run_dir) if run_dir is not None else None
        if found is None:
            log.warning("ckpt_path=last: no checkpoint in %s; starting fresh", run_dir)
            return None
        return str(found)
    path = Path(ckpt_path)
    if path.is_dir():
        found = latest_resume_checkpoint(path)
        if found is None:
            raise FileNotFoundError(
                f"ckpt_path: expected a run folder with checkpoints/last.ckpt, found none in {path}"
            )
        return str(found)
    if not path.is_file():
        raise FileNotFoundError(
            f"ckpt_path: expected 'last', a run folder or a checkpoint file, found {path}"
        )
    return str(path)
