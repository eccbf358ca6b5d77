"""The ``data/survey=xtf`` source: XTF files (+ an optional MBES grid) -> a survey folder.

``prepare_xtf_survey(cfg, data_dir)`` reads every XTF file of ``cfg.files`` into a line
(named by the file stem), puts them in one local frame (the origin comes from the first
file: UTM zone of its first position, or ``cfg.crs``), reads the MBES grid into the same
frame (reprojecting it or refusing it, see :func:`sss2bathy.io.grids.read_grid`), and saves
the survey to ``data_dir/<name>/`` atomically. The folder is reused while the config and
the input files (by SHA-256) are unchanged.
"""

from __future__ import annotations

import fnmatch
import glob
import json
import logging
import math
import os
import shutil
import tempfile
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from sss2bathy.io.grids import (
    CRS_MISMATCH,
    STATISTICS,
    Z_POSITIVE,
    SpikeFilter,
    footprint_coverage,
    read_grid,
    shift_grid,
)
from sss2bathy.io.xtf import (
    ALTITUDE_OFFSET,
    MISSING_ATTITUDE,
    NAV_UNITS,
    SENSOR_KEYS,
    read_xtf,
)
from sss2bathy.survey import BathyGrid, Survey, SurveyFormatError
from sss2bathy.utils.atomic import (
    default_dir_mode,
    file_sha256,
    folder_digest_problems,
    stable_hash,
    write_folder_digest,
)
from sss2bathy.utils.checks import (
    is_integer,
    require_bool,
    require_choice,
    require_int,
    require_number,
)
from sss2bathy.utils.config import plain_config
from sss2bathy.utils.progress import log_progress

log = logging.getLogger(__name__)

__all__ = [
    "DEFAULTS",
    "IMPORT_VERSION",
    "prepare_xtf_survey",
    "resolve_files",
    "resolve_splits",
    "validate_xtf_config",
]

#: the sidescan files a folder in ``data.survey.files`` contributes (Edgetech JSF is read
#: through the XTF import: :mod:`sss2bathy.io.jsf`)
SUFFIXES = (".xtf", ".jsf")

# Bump when the import changes what it writes, so cached folders are rebuilt.
IMPORT_VERSION = 5  # 5: the import's WARNINGs stored with the survey

DEFAULTS: dict[str, Any] = {
    "kind": "xtf",
    "name": "xtf_survey",
    "files": None,
    "mbes_grid": None,
    "mbes_cell_size": None,
    "mbes_crs": None,
    "mbes_z_positive": "up",
    "mbes_statistic": "mean",
    "mbes_crs_mismatch": "reproject",
    "mbes_spike_threshold_m": 1.0,
    "mbes_spike_window_cells": 5,
    "mbes_spike_spread_factor": 5.0,
    "n_bins": 512,
    "tilt_deg": None,
    "beam_width_deg": None,
    "frequency_hz": None,
    "sound_speed_mps": None,
    "splits": None,
    "crs": None,
    "channel_pair": 0,
    "port_far_first": True,
    "max_jump_m": 200.0,
    "max_speed_mps": 10.0,
    "max_nav_gap_s": 30.0,
    "missing_attitude": "error",
    "min_first_return_m": 0.0,
    "blanking_m": 0.0,
    "auto_blanking": True,
    "altitude_tolerance_m": 1.0,
    "altitude_offset": "record",
    "nav_units": "file",
}


def resolve_files(files: Any) -> list[Path]:
    """XTF paths from a folder, a glob pattern, a file, or a list of those (sorted, unique)."""
    if files is None or files == "???":
        raise ValueError(
            "data.survey.files: expected a folder, glob or list of XTF files, found none"
        )
    items = [files] if isinstance(files, (str, Path)) else list(files)
    found: list[Path] = []
    for item in items:
        p = Path(str(item)).expanduser()
        if p.is_dir():
            hits = [q for q in p.iterdir() if q.is_file() and q.suffix.lower() in SUFFIXES]
        elif p.is_file():
            hits = [p]
        else:
            hits = [Path(h) for h in glob.glob(str(p), recursive=True) if Path(h).is_file()]
        if not hits:
            raise ValueError(
                f"data.survey.files: expected XTF or JSF files at {str(p)!r}, found none"
            )
        found.extend(hits)
    return sorted({h.resolve() for h in found})


def resolve_splits(splits: Mapping[str, Any] | None, names: list[str]) -> dict[str, list[str]]:
    """Split -> line names; entries are names or glob patterns. Default: every line in ``test``."""
    if not splits:
        return {"test": list(names)}
    out: dict[str, list[str]] = {}
    for split, members in splits.items():
        if isinstance(members, str):
            members = [members]
        chosen: list[str] = []
        for pattern in members:
            hits = [n for n in names if fnmatch.fnmatchcase(n, str(pattern))]
            if not hits:
                raise ValueError(
                    f"data.survey.splits.{split}: expected line names or patterns matching "
                    f"{names}, found {pattern!r} matching none"
                )
            chosen.extend(h for h in hits if h not in chosen)
        out[str(split)] = [n for n in names if n in chosen]
    return out


def _jsonable(obj: Any) -> Any:
    def default(o: Any) -> Any:
        if isinstance(o, np.generic):
            return o.item()
        if isinstance(o, (Path, np.ndarray)):
            return str(o) if isinstance(o, Path) else o.tolist()
        return str(o)

    return json.loads(json.dumps(obj, default=default))


def validate_xtf_config(cfg: Mapping[str, Any]) -> None:
    """Check an ``xtf`` ``data.survey`` config (every key of :data:`DEFAULTS` present is
    checked; start-up runs this before any file is read): ``ValueError`` naming the key
    (``data.survey.<key>: expected ..., found ...``); unknown keys are warned about."""
    if cfg.get("kind") != "xtf":
        raise ValueError(f"data.survey.kind: expected 'xtf', found {cfg.get('kind')!r}")
    name = cfg.get("name")
    if not isinstance(name, str) or not name or "/" in name or name.startswith("."):
        raise ValueError(f"data.survey.name: expected a folder name, found {name!r}")
    n_bins = cfg.get("n_bins")
    if n_bins is not None and (not is_integer(n_bins) or n_bins < 2):
        raise ValueError(f"data.survey.n_bins: expected null or an integer >= 2, found {n_bins!r}")
    for key, ok, expected in _NUMBERS:
        if key in cfg:
            optional = key in _NULLABLE
            what = f"{expected} or null" if optional else expected
            require_number(f"data.survey.{key}", cfg[key], ok, what, optional=optional)
    for key, choices in _CHOICES:
        if key in cfg:
            require_choice(f"data.survey.{key}", cfg[key], choices)
    for key in ("port_far_first", "auto_blanking"):
        if key in cfg:
            require_bool(f"data.survey.{key}", cfg[key])
    if "channel_pair" in cfg:
        require_int("data.survey.channel_pair", cfg["channel_pair"], minimum=0)
    window = cfg.get("mbes_spike_window_cells", 5)
    if not is_integer(window) or window < 3 or window % 2 == 0:
        raise ValueError(
            f"data.survey.mbes_spike_window_cells: expected an odd integer >= 3, found {window!r}"
        )
    unknown = sorted(set(cfg) - set(DEFAULTS))
    if unknown:
        log.warning("data.survey: ignoring keys unknown to the xtf source: %s", unknown)


def _positive(v: float) -> bool:
    return v > 0


def _non_negative(v: float) -> bool:
    return v >= 0


#: ``(key, predicate, expectation)`` of the numeric keys; those of :data:`_NULLABLE` may be
#: null (sensor values: from the files; cell size: the raster's; tolerance: no check)
_NUMBERS: tuple[tuple[str, Any, str], ...] = (
    ("tilt_deg", lambda v: -90 <= v <= 90, "a value in [-90, 90] degrees"),
    ("beam_width_deg", lambda v: 0 < v < 180, "a value in (0, 180) degrees"),
    ("frequency_hz", _positive, "a positive frequency (Hz)"),
    ("sound_speed_mps", _positive, "a positive speed (m/s)"),
    ("mbes_cell_size", _positive, "a positive number (m)"),
    ("mbes_spike_threshold_m", _positive, "a positive height (m)"),
    ("mbes_spike_spread_factor", _positive, "a positive factor"),
    ("max_jump_m", _positive, "a positive distance (m)"),
    ("max_speed_mps", _positive, "a positive speed (m/s)"),
    ("max_nav_gap_s", _positive, "a positive duration (s)"),
    ("min_first_return_m", _non_negative, "a distance >= 0 (m)"),
    ("blanking_m", _non_negative, "a distance >= 0 (m)"),
    ("altitude_tolerance_m", _positive, "a positive distance (m)"),
)
_NULLABLE = (
    *SENSOR_KEYS,
    "mbes_cell_size",
    "altitude_tolerance_m",
    "mbes_spike_threshold_m",
    "mbes_spike_spread_factor",
)
_CHOICES: tuple[tuple[str, tuple[str, ...]], ...] = (
    ("mbes_z_positive", Z_POSITIVE),
    ("mbes_statistic", STATISTICS),
    ("mbes_crs_mismatch", CRS_MISMATCH),
    ("missing_attitude", MISSING_ATTITUDE),
    ("altitude_offset", ALTITUDE_OFFSET),
    ("nav_units", NAV_UNITS),
)


def _sonar_settings(st: Mapping[str, Any]) -> dict[str, Any]:
    """The recording settings of one imported file (from its ``read_xtf`` stats)."""
    f = st.get("file_frequency_hz")
    return {
        "frequency_khz": None if f is None else round(float(f) / 1e3, 1),
        "range_m": round(float(st["range_window_m"][1]), 1),
        "samples_per_side": int(st["samples_per_side"]),
    }


def _check_one_sonar(stats: Mapping[str, Any], st: Mapping[str, Any]) -> None:
    """Refuse a file recorded with another frequency, range or sample count than the survey's
    first file (a survey holds one sonar setting; import the others as another survey)."""
    firsts = [k for k in stats if not k.startswith("_")]
    if not firsts:
        return
    ref, new = _sonar_settings(stats[firsts[0]]), _sonar_settings(st)
    differ = []
    for key, rel in (("frequency_khz", 0.05), ("range_m", 0.02), ("samples_per_side", 0.0)):
        a, b = ref[key], new[key]
        if a is not None and b is not None and abs(a - b) > rel * max(abs(a), abs(b)):
            differ.append(key)
    if differ:
        raise ValueError(
            f"data.survey.files: expected one sonar setting per survey, found "
            f"{Path(stats[firsts[0]]['file']).name} {ref} and {Path(st['file']).name} {new} "
            f"(differing {', '.join(differ)}; import them as separate surveys with their own "
            "data.survey.name and data.survey.files)"
        )


def _cached_metadata(folder: Path) -> dict[str, Any]:
    manifest = folder / "survey.yaml"
    if not manifest.is_file():
        return {}
    try:
        data = yaml.safe_load(manifest.read_text())
    except yaml.YAMLError:
        return {}
    if not isinstance(data, dict):
        return {}
    meta = data.get("metadata")
    return meta if isinstance(meta, dict) else {}


class _WarningRecorder(logging.Handler):
    """Keeps the WARNING (and worse) messages logged below ``sss2bathy.io`` while attached."""

    def __init__(self) -> None:
        super().__init__(logging.WARNING)
        self.messages: list[str] = []

    def emit(self, record: logging.LogRecord) -> None:
        self.messages.append(record.getMessage())


#: survey folders whose import warnings this process has already shown (a K-fold map run
#: reuses its import once per fit: the stored warnings are repeated once, not per fit)
_SHOWN: set[str] = set()


def _repeat_import_warnings(name: str, folder: Path, stored: Sequence[str] | None) -> None:
    """Log a reused import's ``stored`` WARNINGs (None: an older import stored none) again,
    once per process and folder: a run on a cached survey says what its import repaired or
    doubted as plainly as the first run."""
    key = str(Path(folder).resolve())
    if key in _SHOWN:
        return
    _SHOWN.add(key)
    if stored is None:
        log.info("survey '%s': imported by an older version: its warnings were not stored", name)
        return
    for message in stored:
        log.warning("survey '%s' (stored import): %s", name, message)


def _replace_folder(survey: Survey, folder: Path) -> None:
    """Save into a temporary sibling folder, then swap it in (the old folder goes last)."""
    folder.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{folder.name}.tmp-", dir=folder.parent))
    try:
        os.chmod(tmp, default_dir_mode())  # mkdtemp makes it 0o700 whatever the umask
        survey.save(tmp)
        write_folder_digest(tmp)
        old = None
        if folder.exists():
            old = Path(tempfile.mkdtemp(prefix=f".{folder.name}.old-", dir=folder.parent))
            os.rmdir(old)
            os.replace(folder, old)
        os.replace(tmp, folder)
        if old is not None:
            shutil.rmtree(old, ignore_errors=True)
    finally:
        if tmp.exists():
            shutil.rmtree(tmp, ignore_errors=True)


def _grid_coverage(grid: BathyGrid, lines: list) -> float:
    xy = np.concatenate([ln.position[:, :2] for ln in lines])
    return float(np.isfinite(grid.sample(xy[:, 0], xy[:, 1])).mean())


def _mbes_spike_filter(merged: Mapping[str, Any]) -> SpikeFilter | None:
    """The MBES grid's spike filter (``data.survey.mbes_spike_*``; threshold null: none)."""
    if merged["mbes_spike_threshold_m"] is None:
        return None
    spread = merged["mbes_spike_spread_factor"]
    return SpikeFilter(
        threshold_m=float(merged["mbes_spike_threshold_m"]),
        window_cells=int(merged["mbes_spike_window_cells"]),
        spread_factor=None if spread is None else float(spread),
        key="data.survey.mbes_spike_threshold_m",
    )


def _check_grid_vertical(grid: BathyGrid, lines: list, path: Path, z_positive: str) -> None:
    """Refuse a grid whose heights cannot be the seabed under the vehicle: all above the
    datum (depths read as heights, or the other way round), or above the vehicle at most
    pings over it."""
    other = "down" if z_positive == "up" else "up"
    hint = f"set data.survey.mbes_z_positive={other}"
    h = grid.heights[np.isfinite(grid.heights)]
    if h.size and h.min() > 0:
        words = "heights" if z_positive == "up" else "depths"
        raise SurveyFormatError(
            path,
            "heights",
            f"seabed heights negative below the datum (data.survey.mbes_z_positive="
            f"{z_positive} reads {words})",
            f"all {h.size} valid cells above 0 m ({h.min():.2f} to {h.max():.2f} m): "
            f"{'depths positive down' if z_positive == 'up' else 'heights positive up'}? "
            f"{hint}",
        )
    pos = np.concatenate([ln.position for ln in lines])
    under = grid.sample(pos[:, 0], pos[:, 1])
    ok = np.isfinite(under) & np.isfinite(pos[:, 2])
    if ok.sum() >= 10:
        above = float((under[ok] > pos[ok, 2]).mean())
        if above > 0.5:
            median = float(np.median(under[ok]))
            cause = f"depths read as heights? {hint}" if median > 0 else "another vertical datum?"
            raise SurveyFormatError(
                path,
                "heights",
                "the seabed below the vehicle at the pings over the grid (one vertical frame: "
                "heights up from the datum the vehicle depth is measured from)",
                f"the grid above it at {100 * above:.0f}% of {int(ok.sum())} pings (grid median "
                f"{median:.2f} m, vehicle median {np.median(pos[ok, 2]):.2f} m): {cause}",
            )


def _outside_grid_error(
    grid: BathyGrid, lines: list, path: Path, origin: Mapping[str, Any], info: Mapping[str, Any]
) -> SurveyFormatError:
    """The error for a grid whose extent holds none of the lines' footprint: both CRSs, the
    file, both extents, and whether the file's own numbers (no reprojection) would fit."""
    lines_crs = origin.get("crs")
    file_crs = info.get("file_crs")
    e0, n0 = float(origin.get("easting", 0.0)), float(origin.get("northing", 0.0))
    xy = np.concatenate([ln.position[:, :2] for ln in lines]) + [e0, n0]
    lo, hi = xy.min(0), xy.max(0)
    ny, nx = grid.shape
    gw, gs = grid.x0 + e0 - grid.cell_size / 2, grid.y0 + n0 - grid.cell_size / 2
    ge, gn = gw + nx * grid.cell_size, gs + ny * grid.cell_size
    label = "no CRS (assumed the lines')" if file_crs is None else f"CRS {file_crs}"
    moved = file_crs is not None and lines_crs is not None and file_crs != lines_crs
    found = (
        f"the grid ({label}{f', reprojected to {lines_crs}' if moved else ''}) spans "
        f"E {gw:.0f}..{ge:.0f}, N {gs:.0f}..{gn:.0f}"
    )
    bounds = info.get("file_bounds")
    if moved and bounds is not None:
        west, south, east, north = bounds
        if lo[0] <= east and hi[0] >= west and lo[1] <= north and hi[1] >= south:
            found += (
                f"; in the file's own coordinates (E {west:.0f}..{east:.0f}, N {south:.0f}.."
                f"{north:.0f}) the lines fall inside it: is its CRS label {file_crs} wrong "
                f"(the lines' is {lines_crs})?"
            )
    return SurveyFormatError(
        path,
        "extent",
        f"a grid under the lines' footprint (lines in CRS {lines_crs}, E {lo[0]:.0f}..{hi[0]:.0f}"
        f", N {lo[1]:.0f}..{hi[1]:.0f})",
        found,
    )


def prepare_xtf_survey(cfg: Mapping[str, Any], data_dir: str | Path, force: bool = False) -> Path:
    """Import XTF files (and an optional MBES grid) into ``data_dir/<cfg.name>/``.

    Args:
        cfg: the ``data.survey`` config (see ``conf/data/survey/xtf.yaml`` and :data:`DEFAULTS`).
        data_dir: root of the survey folders.
        force: rebuild even when the cached folder matches.

    Returns:
        The survey folder (loadable with :meth:`Survey.load`).
    """
    user = plain_config(cfg)
    merged = {**DEFAULTS, **user}
    validate_xtf_config(merged)
    files = resolve_files(merged["files"])
    names = [f.stem for f in files]
    if len(set(names)) != len(names):
        dupes = sorted({n for n in names if names.count(n) > 1})
        raise ValueError(
            f"data.survey.files: expected unique file stems (line names), found {dupes}"
        )
    grid_path = Path(str(merged["mbes_grid"])).expanduser() if merged["mbes_grid"] else None
    if grid_path is not None and not grid_path.is_file():
        raise ValueError(
            f"data.survey.mbes_grid: expected an existing file, found {str(grid_path)!r}"
        )

    folder = Path(data_dir) / merged["name"]
    key_cfg = {k: v for k, v in merged.items() if k not in ("files", "mbes_grid")}
    source_hash = stable_hash(
        {
            "version": IMPORT_VERSION,
            "config": key_cfg,
            "files": {str(f): file_sha256(f) for f in files},
            "grid": file_sha256(grid_path) if grid_path else None,
        }
    )
    cached = _cached_metadata(folder)
    if not force and cached.get("source_hash") == source_hash:
        problems = folder_digest_problems(folder)
        if problems is None:  # imported before digests: readable -> record its digest
            try:
                Survey.load(folder)
                write_folder_digest(folder)
                problems = []
            except SurveyFormatError as err:
                problems = [str(err)]
        if not problems:
            log.info("survey '%s': reusing %s (inputs unchanged)", merged["name"], folder)
            _repeat_import_warnings(merged["name"], folder, cached.get("import_warnings"))
            return folder
        log.warning(
            "survey '%s': cached folder %s is corrupt (%s); importing again",
            merged["name"],
            folder,
            "; ".join(problems[:3]),
        )

    read_kwargs = {
        "channel_pair": int(merged["channel_pair"]),
        "port_far_first": bool(merged["port_far_first"]),
        "max_jump_m": float(merged["max_jump_m"]),
        "max_speed_mps": float(merged["max_speed_mps"]),
        "max_nav_gap_s": float(merged["max_nav_gap_s"]),
        "missing_attitude": str(merged["missing_attitude"]),
        "min_first_return_m": float(merged["min_first_return_m"]),
        "blanking_m": float(merged["blanking_m"]),
        "auto_blanking": bool(merged["auto_blanking"]),
        "altitude_tolerance_m": (
            None
            if merged["altitude_tolerance_m"] is None
            else float(merged["altitude_tolerance_m"])
        ),
        "altitude_offset": str(merged["altitude_offset"]),
        "nav_units": str(merged["nav_units"]),
    }
    # the import's WARNINGs are stored with the survey: a later run that reuses it repeats them
    recorder = _WarningRecorder()
    io_log = logging.getLogger("sss2bathy.io")
    io_log.addHandler(recorder)
    try:
        survey = _import_survey(merged, user, files, grid_path, source_hash, read_kwargs)
    finally:
        io_log.removeHandler(recorder)
    survey.metadata["import_warnings"] = list(recorder.messages)
    _replace_folder(survey, folder)
    _SHOWN.add(str(folder.resolve()))
    log.info("survey '%s': %d lines saved to %s", merged["name"], len(survey.lines), folder)
    return folder


def _import_survey(
    merged: Mapping[str, Any],
    user: Mapping[str, Any],
    files: Sequence[Path],
    grid_path: Path | None,
    source_hash: str,
    read_kwargs: Mapping[str, Any],
) -> Survey:
    """Read the files (and the grid) of :func:`prepare_xtf_survey` into a :class:`Survey`."""
    sensor = {k: merged[k] for k in SENSOR_KEYS}
    origin: dict[str, Any] | None = None
    lines, stats = [], {}
    # a progress line (done, rate, ETA) every 30 s of a long import
    for path in log_progress(files, "XTF import", unit="files"):
        line, st = read_xtf(
            path, merged["n_bins"], origin=origin, crs=merged["crs"], sensor=sensor, **read_kwargs
        )
        if origin is None:
            origin = dict(st["origin"])
            s = line.sensor
            # Every line shares the first file's sensor (a survey has one sensor).
            sensor = {
                "tilt_deg": math.degrees(s.tilt_rad),
                "beam_width_deg": math.degrees(s.beam_width_rad),
                "frequency_hz": s.frequency_hz,
                "sound_speed_mps": s.sound_speed_mps,
            }
        _check_one_sonar(stats, st)
        lines.append(line)
        stats[line.name] = st
        log.info("survey '%s': read %s (%d pings)", merged["name"], path.name, line.n_pings)
    if origin is None:  # resolve_files never returns an empty list
        raise ValueError("data.survey.files: expected at least one XTF file, found none")

    grid = None
    if grid_path is not None:
        grid_info: dict[str, Any] = {}
        grid_kwargs = {
            "cell_size": merged["mbes_cell_size"],
            "source_crs": merged["mbes_crs"],
            "on_crs_mismatch": merged["mbes_crs_mismatch"],
            "z_positive": merged["mbes_z_positive"],
            "statistic": merged["mbes_statistic"],
            "spikes": _mbes_spike_filter(merged),
            "info": grid_info,
        }
        if origin.get("crs") is None:
            grid = read_grid(grid_path, **grid_kwargs)
            if grid.crs is not None:
                log.info(
                    "survey '%s': navigation in metres without a CRS; taking the grid's",
                    merged["name"],
                )
                origin["crs"] = grid.crs
            grid = shift_grid(grid, origin)
        else:
            grid = read_grid(grid_path, origin=origin, **grid_kwargs)
        coverage = _grid_coverage(grid, lines)
        foot = footprint_coverage(grid, lines)
        if foot["inside"] == 0.0:
            raise _outside_grid_error(grid, lines, grid_path, origin, grid_info)
        _check_grid_vertical(grid, lines, grid_path, str(merged["mbes_z_positive"]))
        if foot["holes"] > 0.5:
            log.warning(
                "survey '%s': the lines overlap the MBES grid (%.0f%% of their footprint inside "
                "its extent) but %.0f%% of that falls on empty (NaN) cells: holes in the grid",
                merged["name"],
                100 * foot["inside"],
                100 * foot["holes"],
            )
        stats["_mbes_grid"] = {
            "file": str(grid_path),
            "pings_over_grid": coverage,
            "footprint_inside_extent": foot["inside"],
            "footprint_on_nan_cells": foot["holes"],
            "file_crs": grid_info.get("file_crs"),
            "untagged_nodata_cells": grid_info.get("untagged_nodata", 0),
            "spikes_removed": grid_info.get("spikes_removed", 0),
            "spike_max_deviation_m": grid_info.get("spike_max_deviation_m", 0.0),
        }

    survey = Survey(
        name=merged["name"],
        lines=lines,
        grid=grid,
        splits=resolve_splits(merged["splits"], [ln.name for ln in lines]),
        origin=origin,
        metadata=_jsonable(
            {
                "source": "xtf",
                "source_hash": source_hash,
                "import_version": IMPORT_VERSION,
                "files": {f.stem: str(f) for f in files},
                "config": user,
                "import_stats": stats,
            }
        ),
    )
    return survey
