"""Cached generation of a synthetic survey folder (``data/<name>/``).

The folder is reused when its manifest carries the same config hash (the resolved
config plus the generator version) and its files are all there and match the folder's
digest (``files.sha256.json``: size and SHA-256 of every file); otherwise the survey is
generated, with a warning when a stale or corrupt folder is replaced, into a temporary
folder beside it and renamed into place, so a half-written survey never exists under the
final name. A lock file serialises concurrent preparers.
"""

from __future__ import annotations

import contextlib
import logging
import os
import shutil
import tempfile
import time
from collections.abc import Iterator, Mapping
from pathlib import Path
from typing import Any

import yaml

from sss2bathy.sim.config import SyntheticSurveyConfig
from sss2bathy.survey import BathyGrid
from sss2bathy.utils.atomic import (
    default_dir_mode,
    folder_digest_problems,
    write_folder_digest,
)
from sss2bathy.utils.config import plain_config

log = logging.getLogger(__name__)


@contextlib.contextmanager
def _lock(path: Path) -> Iterator[None]:
    """Exclusive advisory lock on ``path`` (no-op where ``fcntl`` is missing)."""
    try:
        import fcntl
    except ImportError:  # pragma: no cover - Windows
        yield
        return
    path.parent.mkdir(parents=True, exist_ok=True)
    with open(path, "a+") as fh:
        fcntl.flock(fh, fcntl.LOCK_EX)
        try:
            yield
        finally:
            fcntl.flock(fh, fcntl.LOCK_UN)


def cached_hash(folder: Path) -> str | None:
    """The config hash of a complete survey folder, or None if it is missing or incomplete."""
    manifest = folder / "survey.yaml"
    if not manifest.is_file():
        return None
    try:
        data = yaml.safe_load(manifest.read_text())
    except (OSError, yaml.YAMLError):
        return None
    if not isinstance(data, dict):
        return None
    lines = data.get("lines") or []
    if not all((folder / "lines" / f"{name}.npz").is_file() for name in lines):
        return None
    if data.get("grid") and not (folder / data["grid"]).is_file():
        return None
    return (data.get("metadata") or {}).get("config_hash")


def cache_problem(folder: Path, key: str) -> str | None:
    """Why ``folder`` cannot serve as the survey of config hash ``key`` (``None``: it can).

    The folder must be complete with that hash in its manifest, and every file must match
    the folder's digest (size and SHA-256, :func:`~sss2bathy.utils.atomic.
    folder_digest_problems`). A folder from before digests is checked by loading it, and
    gets its digest then.
    """
    cached = cached_hash(folder)
    if cached is None:
        return "missing or incomplete"
    if cached != key:
        return f"stale (config hash {cached}, expected {key})"
    problems = folder_digest_problems(folder)
    if problems is None:
        from sss2bathy.survey import Survey, SurveyFormatError

        try:
            Survey.load(folder)
        except SurveyFormatError as err:
            return f"unreadable ({err})"
        write_folder_digest(folder)
        return None
    if problems:
        return f"corrupt ({'; '.join(problems[:3])}{'; ...' if len(problems) > 3 else ''})"
    return None


def prepare_synthetic(cfg: Mapping[str, Any], data_dir: Path, force: bool = False) -> Path:
    """Make sure ``data_dir/<cfg.name>/`` holds the survey ``cfg`` describes; return it.

    Args:
        cfg: the ``data.survey`` config (``kind: synthetic``), plain or OmegaConf.
        data_dir: parent folder of the survey folders.
        force: regenerate even if the cached folder matches.

    Returns:
        the survey folder (load it with :meth:`sss2bathy.survey.Survey.load`).
    """
    config = SyntheticSurveyConfig.from_mapping(plain_config(cfg))
    data_dir = Path(data_dir)
    folder = data_dir / config.name
    key = config.hash()
    with _lock(data_dir / f".{config.name}.lock"):
        problem = None if force else cache_problem(folder, key)
        if not force and problem is None:
            log.info("survey %s: cache hit (%s)", folder, key)
            return folder
        if problem is not None and folder.exists():
            log.warning("survey %s: cached folder is %s; regenerating", folder, problem)
        from sss2bathy.sim.generate import generate_survey

        log.info("survey %s: generating (config hash %s)", folder, key)
        t0 = time.perf_counter()
        survey, terrain = generate_survey(config)
        survey.metadata["timing_s"]["generate_total"] = round(time.perf_counter() - t0, 3)
        tmp = Path(tempfile.mkdtemp(prefix=f".{config.name}.tmp-", dir=data_dir))
        try:
            from sss2bathy.io.export import write_geotiff

            os.chmod(tmp, default_dir_mode())  # mkdtemp makes it 0o700 whatever the umask
            origin = survey.origin  # a grid terrain's origin is the grid's
            crs = origin.get("crs")
            write_geotiff(terrain.grid(crs), tmp / "truth" / "heights.tif", origin=origin)
            write_geotiff(
                BathyGrid(terrain.materials.astype("float32"), 0.0, 0.0, terrain.cell_m, crs),
                tmp / "truth" / "materials.tif",
                origin=origin,
            )
            if terrain.source is not None:  # which grid cells were filled, spikes, holes
                flags = terrain.source.flags().astype("float32")
                write_geotiff(
                    BathyGrid(flags, 0.0, 0.0, terrain.source.cell_m, crs),
                    tmp / "truth" / "grid_flags.tif",
                    origin=origin,
                )
            survey.save(tmp)
            write_folder_digest(tmp)
            old = None
            if folder.exists():
                old = Path(tempfile.mkdtemp(prefix=f".{config.name}.old-", dir=data_dir))
                folder.rename(old / "survey")
            tmp.rename(folder)
        except BaseException:
            shutil.rmtree(tmp, ignore_errors=True)
            raise
        if old is not None:
            shutil.rmtree(old, ignore_errors=True)
        log.info(
            "survey %s: %d lines in %.1f s", folder, len(survey.lines), time.perf_counter() - t0
        )
    return folder
