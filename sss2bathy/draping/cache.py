"""Draping a whole survey, cached under ``<survey_dir>/draped/<key>/<line>.npz``.

The key is a stable hash of everything the result depends on: the draping algorithm's
version (``DRAPE_ALGORITHM_VERSION``), the draping config
(:meth:`DrapeConfig.cache_dict`), the surface (the MBES grid's heights and geometry, or
the mesh file's SHA-256) and every line's draping inputs (times, positions, rotations,
altitudes, slant ranges and sensor). Hashing the inputs rather than the line files keeps
the key independent of intensities (which draping does not read) and avoids re-reading
every file. A cached file whose embedded key or line hash does not match, or that fails
to load or validate, is recomputed with a warning.
"""

from __future__ import annotations

import hashlib
import json
import logging
from collections.abc import Iterable
from dataclasses import asdict
from pathlib import Path
from typing import Any

import numpy as np

from sss2bathy.draping.config import DrapeConfig
from sss2bathy.draping.drape import DRAPE_ALGORITHM_VERSION, drape_line
from sss2bathy.draping.draped import DRAPED_FORMAT_VERSION, DrapedLine
from sss2bathy.draping.surface import DrapeSurface
from sss2bathy.survey import BathyGrid, SidescanLine, Survey, SurveyFormatError
from sss2bathy.survey import mask_reason_counts as _counts
from sss2bathy.utils.atomic import atomic_write_text, file_sha256, stable_hash
from sss2bathy.utils.progress import log_progress

log = logging.getLogger(__name__)


def _array_hash(*arrays: np.ndarray, extra: Any = None) -> str:
    h = hashlib.sha256()
    for a in arrays:
        a = np.ascontiguousarray(a)
        h.update(str((a.dtype.str, a.shape)).encode())
        h.update(a.tobytes())
    h.update(json.dumps(extra, sort_keys=True, default=str).encode())
    return h.hexdigest()[:16]


def line_input_hash(line: SidescanLine) -> str:
    """Hash of what draping reads from a line (not its intensities)."""
    return _array_hash(
        line.time_s,
        line.position,
        line.rotation,
        line.altitude_m,
        line.range_m,
        extra=asdict(line.sensor),
    )


def grid_hash(grid: BathyGrid) -> str:
    """Hash of a grid's heights and georeferencing."""
    return _array_hash(grid.heights, extra=[grid.x0, grid.y0, grid.cell_size])


def _check_crs(survey: Survey) -> None:
    """Lines (survey origin CRS) and grid must be in the same projected CRS."""
    grid_crs = survey.grid.crs if survey.grid is not None else None
    line_crs = (survey.origin or {}).get("crs")
    if not grid_crs or not line_crs:
        return
    from pyproj import CRS

    try:
        same = CRS.from_user_input(grid_crs) == CRS.from_user_input(line_crs)
    except Exception as exc:  # pyproj.exceptions.CRSError and friends
        raise ValueError(
            f"survey '{survey.name}': cannot compare grid CRS {grid_crs!r} with survey "
            f"origin CRS {line_crs!r} ({exc})"
        ) from exc
    if not same:
        raise ValueError(
            f"survey '{survey.name}': grid CRS {CRS.from_user_input(grid_crs).to_string()} "
            f"differs from the lines' CRS (survey origin) "
            f"{CRS.from_user_input(line_crs).to_string()}; reproject one of them"
        )


def overlap_diagnosis(survey: Survey, lines: list[SidescanLine]) -> str:
    """What the lines' footprint does relative to the survey's grid, in words: outside its
    extent (frame/origin/CRS), or inside it on empty (NaN) cells (holes)."""
    if survey.grid is None:
        return "the lines do not reach the mesh — check that lines and mesh share one frame"
    from sss2bathy.io.grids import footprint_coverage

    cov = footprint_coverage(survey.grid, lines)
    crs = f"lines CRS {(survey.origin or {}).get('crs')}, grid CRS {survey.grid.crs}"
    if cov["inside"] == 0.0:
        return (
            "the lines do not overlap the grid: their footprint lies entirely outside its "
            f"extent — check the survey origin and CRS ({crs})"
        )
    return (
        f"{100 * cov['inside']:.0f}% of the lines' footprint lies inside the grid's extent, "
        f"but {100 * cov['holes']:.0f}% of that falls on empty (NaN) cells: the grid has "
        f"holes under the lines ({100 * cov['grid_nan']:.0f}% of its cells are NaN)"
    )


def _surface_source(
    survey: Survey, survey_dir: Path, cfg: DrapeConfig
) -> tuple[str, dict[str, Any]]:
    """``(hash, description)`` of the surface to drape onto; raises if there is none."""
    if cfg.mesh_path:
        path = Path(cfg.mesh_path)
        path = path if path.is_absolute() else survey_dir / path
        if not path.is_file():
            raise ValueError(
                f"drape.mesh_path: expected an existing mesh file, found none at {path}"
            )
        return file_sha256(path), {"mesh": str(path)}
    if survey.grid is None:
        raise ValueError(
            f"survey '{survey.name}' has no MBES grid to drape onto: survey.grid is None "
            "(no grid.tif in the survey folder) and drape.mesh_path is not set"
        )
    return grid_hash(survey.grid), {"grid": "survey.grid", "shape": list(survey.grid.shape)}


def _build_surface(survey: Survey, survey_dir: Path, cfg: DrapeConfig) -> DrapeSurface:
    if cfg.mesh_path:
        path = Path(cfg.mesh_path)
        return DrapeSurface.from_file(
            path if path.is_absolute() else survey_dir / path, engine=cfg.engine
        )
    assert survey.grid is not None  # checked by _surface_source
    return DrapeSurface.from_grid(survey.grid, engine=cfg.engine)


def _cache_key(cfg: DrapeConfig, surface_hash: str, line_hashes: dict[str, str]) -> str:
    return stable_hash(
        {
            "format": DRAPED_FORMAT_VERSION,
            "algorithm": DRAPE_ALGORITHM_VERSION,
            "config": cfg.cache_dict(),
            "surface": surface_hash,
            "lines": line_hashes,
        }
    )


def drape_key(survey: Survey, survey_dir: str | Path, cfg: DrapeConfig | Any = None) -> str:
    """The cache key (folder name under ``draped/``) of a survey's draping under ``cfg``."""
    cfg = DrapeConfig.coerce(cfg)
    surface_hash, _ = _surface_source(survey, Path(survey_dir), cfg)
    return _cache_key(cfg, surface_hash, {ln.name: line_input_hash(ln) for ln in survey.lines})


def _load_cached(path: Path, key: str, line: SidescanLine, line_hash: str) -> DrapedLine | None:
    if not path.is_file():
        return None
    try:
        draped = DrapedLine.load(path)
    except SurveyFormatError as err:
        log.warning("draped cache %s is unreadable (%s); recomputing", path, err)
        return None
    expected = {"key": key, "line": line.name, "line_hash": line_hash}
    found = {k: draped.meta.get(k) for k in expected}
    if found != expected or draped.shape != (line.n_pings, 2, line.n_bins):
        log.warning(
            "draped cache %s is stale (meta %s, shape %s; expected %s, shape %s); recomputing",
            path,
            found,
            draped.shape,
            expected,
            (line.n_pings, 2, line.n_bins),
        )
        return None
    return draped


def drape_survey(
    survey: Survey,
    survey_dir: str | Path,
    cfg: DrapeConfig | Any = None,
    lines: Iterable[str] | None = None,
) -> dict[str, DrapedLine]:
    """Drape a survey's lines on its MBES grid (or ``cfg.mesh_path``), with a file cache.

    Args:
        survey: the survey (its ``grid`` is the surface unless ``cfg.mesh_path`` is set).
        survey_dir: the survey's folder; results go to ``survey_dir/draped/<key>/``.
        cfg: :class:`DrapeConfig`, a mapping of its fields, or ``None`` for defaults.
        lines: names of the lines to drape (default: all).

    Lines are draped one after another, each on ``cfg.threads`` threads (its chunks of
    pings at once, :func:`~sss2bathy.draping.drape.drape_line`); the thread count does
    not change results and is not part of the cache key.

    Returns:
        ``{line name: DrapedLine}`` in the order of ``lines`` (or the survey's).

    Raises:
        ValueError: no grid and no mesh; grid and lines in different CRSs; unknown line
            names; or no bin of any requested line lands on the surface (the message says
            whether the lines miss the grid's extent or fall on its empty cells; nothing
            is written to the cache then).
    """
    if not isinstance(survey, Survey):
        raise ValueError(f"survey: expected a Survey, found {type(survey).__name__}")
    cfg = DrapeConfig.coerce(cfg)
    survey_dir = Path(survey_dir)
    names = [ln.name for ln in survey.lines] if lines is None else list(lines)
    unknown = sorted(set(names) - {ln.name for ln in survey.lines})
    if unknown:
        raise ValueError(
            f"lines: expected names of lines in survey '{survey.name}', found unknown {unknown}"
        )
    _check_crs(survey)
    surface_hash, surface_desc = _surface_source(survey, survey_dir, cfg)
    line_hashes = {ln.name: line_input_hash(ln) for ln in survey.lines}
    key = _cache_key(cfg, surface_hash, line_hashes)
    folder = survey_dir / "draped" / key
    manifest = folder / "manifest.json"

    # Drape what is not cached in memory first: a draping that lands nowhere raises before
    # anything is written (no all-"no hit" cache left behind).
    result: dict[str, DrapedLine] = {}
    fresh: list[str] = []
    surface: DrapeSurface | None = None
    # a progress line (done, rate, ETA) every 30 s of a long draping
    for name in log_progress(names, "draping", unit="lines"):
        line = survey.line(name)
        draped = _load_cached(folder / f"{name}.npz", key, line, line_hashes[name])
        if draped is None:
            if surface is None:
                surface = _build_surface(survey, survey_dir, cfg)
            draped = drape_line(line, surface, cfg)
            draped.meta = {"key": key, "line": name, "line_hash": line_hashes[name]}
            fresh.append(name)
            counts = _counts(draped.mask)
            log.info("draped line '%s' (%s): %s", name, surface.engine, counts)
            if counts["valid"] == 0:
                log.warning(
                    "line '%s': no valid bin on the surface (%s); %s",
                    name,
                    counts,
                    overlap_diagnosis(survey, [line]),
                )
        result[name] = draped
    if result and not any(d.valid.any() for d in result.values()):
        totals = _counts(np.concatenate([d.mask.ravel() for d in result.values()]))
        raise ValueError(
            f"survey '{survey.name}': no bin of lines {names} lands on the surface "
            f"(mask counts {totals}); " + overlap_diagnosis(survey, [survey.line(n) for n in names])
        )
    if fresh:
        folder.mkdir(parents=True, exist_ok=True)
        if not manifest.is_file():
            atomic_write_text(
                manifest,
                json.dumps(
                    {
                        "key": key,
                        "config": cfg.cache_dict(),
                        "surface": surface_desc,
                        "surface_hash": surface_hash,
                        "line_hashes": line_hashes,
                    },
                    indent=2,
                    sort_keys=True,
                ),
            )
        for name in fresh:
            result[name].save(folder / f"{name}.npz")
    return result
