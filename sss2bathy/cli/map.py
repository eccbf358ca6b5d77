"""``sss2bathy-map``: XTF files (+ optional CNN checkpoint) -> a georeferenced bathymetry map.

sss2bathy-map files=/data/lines
sss2bathy-map files=/data/lines cnn_checkpoint=outputs/runs/cnn/<run>/checkpoints/last.ckpt

One command for the whole job (``conf/map.yaml``): the XTF files are imported into
``paths.data_dir/<name>/`` (``data/survey=xtf``, reused while they are unchanged), the SIREN
is fitted — SIREN-CNN-N2d with a CNN checkpoint, else SIREN-Lambert — holding out blocks of
altimeter points (``data.holdout``), and the run folder gets ``map.tif``, ``map.png`` and
``metrics.json`` with the held-out altimeter MAE beside that of along-track interpolation
of the kept altimeter points. It composes ``conf/train.yaml`` and runs
:func:`sss2bathy.cli.train.fit`, so every ``sss2bathy-train`` override is available through
``overrides=[...]``.
"""

from __future__ import annotations

import difflib
import json
import logging
import math
import re
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from omegaconf import DictConfig, ListConfig, OmegaConf, open_dict

from sss2bathy.cli._common import (
    CliHelp,
    apply_extras,
    hydra_entry,
    log_config,
    setup_environment,
)
from sss2bathy.cli.map_settings import MODES as MAP_SETTINGS
from sss2bathy.cli.map_tiles import (
    is_tile_job,
    register_resolver,
    run_tile_plan,
    tile_settings,
    tile_survey_config,
    write_tile_record,
)
from sss2bathy.eval.overlap import OverlapResult
from sss2bathy.eval.verdict import HEIGHTS_ONLY, INTERPOLATION, KFoldVerdict, kfold_verdict
from sss2bathy.metrics.bathy import MAP_TAGS
from sss2bathy.utils.atomic import atomic_write_text

log = logging.getLogger("sss2bathy.map")

DEFAULT_EXPERIMENT = {True: "siren_cnn_n2d", False: "siren_lambert"}
#: the ``method`` values: SIREN experiments that need no MBES grid
MAP_METHODS = ("siren_lambert", "siren_heights_only", "siren_cnn_n2d")
#: config keys of ``conf/train.yaml`` (what errors from the import and the fit name) as
#: ``conf/map.yaml`` spells them
KEY_ALIASES = {
    "data.survey.": "survey.",
    "data.normals.checkpoint": "cnn_checkpoint",
    "data.holdout.": "holdout.",
}

HELP = CliHelp(
    prog="sss2bathy-map",
    usage="files=PATH [cnn_checkpoint=CKPT] [method=NAME] [KEY=VALUE ...] [--trace]",
    summary=(
        "XTF sidescan lines (+ an optional CNN checkpoint) -> a georeferenced bathymetry "
        "map: map.tif (GeoTIFF), map.png and metrics.json in the run folder, with the "
        "held-out altimeter error beside that of interpolating the altimeter."
    ),
    keys=(
        ("files=PATH", "a folder of .xtf/.jsf files, one file, a glob, or a list [a,b]"),
        (
            "method=NAME",
            f"{', '.join(MAP_METHODS)} (default: siren_cnn_n2d with a "
            "checkpoint, else siren_lambert)",
        ),
        (
            "cnn_checkpoint=CKPT",
            "a CNN checkpoint (.ckpt of sss2bathy-train experiment=cnn), an exported model "
            "(.safetensors) or pretrained (the shipped CNN: method=siren_cnn_n2d's default)",
        ),
        (
            "survey.KEY=VALUE",
            "import and sonar settings, e.g. survey.crs=EPSG:32633 "
            "survey.tilt_deg=20 survey.altitude_tolerance_m=null",
        ),
        ("scale=NAME", "tiny | demo (default) | paper: the fit's size"),
        (
            "map_settings=NAME",
            "detail (default: a smooth SIREN + a detail network for what the sidescan "
            "sees) | scale (smooth) | survey",
        ),
        ("holdout.fraction=F", "altimeter points held out for the score (0.2; 0 = off)"),
        (
            "verdict.folds=K",
            "K-fold held-out verdict: fit vs heights only vs interpolation "
            "(5; 0 = one draw of holdout.fraction)",
        ),
        ("holdout.block_m=M", "the verdict's held-out blocks, m of track (null: auto)"),
        ("mosaic.placement=P", "the sidescan mosaic: map (draped on the map) | flat | none"),
        ("logger=NAME", "tensorboard (default) | none"),
        (
            "tile.size_m=M",
            "large surveys: overlapping tiles of at most M m (docs/large_surveys.md)",
        ),
        ("torch_threads=N", "CPU threads of the fit (default: torch's)"),
        (
            "overrides=[...]",
            "further sss2bathy-train overrides, e.g. 'overrides=[\"trainer.max_epochs=100\"]'",
        ),
        ("paths.output_dir=DIR", "where run folders go (outputs/); paths.data_dir: imports"),
    ),
    examples=(
        "sss2bathy-map files=/data/lines",
        "sss2bathy-map files=/data/line1.xtf cnn_checkpoint=outputs/runs/cnn/RUN/"
        "checkpoints/last.ckpt scale=tiny logger=none",
    ),
)


def default_survey_name(files: Any) -> str:
    """A survey folder name from ``files``: the folder's name, a file's stem, a glob's
    folder; the first entry of a list."""
    if isinstance(files, Sequence | ListConfig) and not isinstance(files, str):
        if not files:
            raise ValueError("files: expected a folder, file, glob or list of those, found []")
        files = files[0]
    path = Path(str(files)).expanduser()
    if any(c in path.name for c in "*?["):
        path = path.parent
    stem = path.stem if path.suffix.lower() == ".xtf" else path.name
    name = re.sub(r"[^A-Za-z0-9_.-]+", "_", stem).strip("._") or "survey"
    return name if name.lower().startswith("xtf") else f"xtf_{name}"


def map_survey_config(cfg: Mapping[str, Any]) -> dict[str, Any]:
    """The XTF import of a map config (``survey``, plain), its ``name`` defaulted from the
    files (:func:`default_survey_name`)."""
    survey = OmegaConf.to_container(cfg["survey"], resolve=True)
    survey["name"] = survey.get("name") or default_survey_name(survey["files"])
    return survey


def map_experiment(cfg: Mapping[str, Any]) -> str:
    """The ``sss2bathy-train`` experiment of a map config: ``method`` (one of
    :data:`MAP_METHODS`, else ``ValueError``), else SIREN-CNN-N2d with a CNN checkpoint and
    SIREN-Lambert without."""
    method = cfg.get("method")
    if not method:
        return DEFAULT_EXPERIMENT[bool(cfg.get("cnn_checkpoint"))]
    if str(method) not in MAP_METHODS:
        close = difflib.get_close_matches(str(method), MAP_METHODS, n=1, cutoff=0.5)
        hint = f"; did you mean {close[0]}?" if close else ""
        raise ValueError(
            f"method: expected one of {', '.join(MAP_METHODS)} (or null), found "
            f"{str(method)!r}{hint}"
        )
    return str(method)


def map_cnn_checkpoint(cfg: Mapping[str, Any]) -> str | None:
    """The CNN file of a map config, as an absolute path: ``cnn_checkpoint`` (a ``.ckpt``,
    an exported ``.safetensors`` or ``pretrained``, the model shipped in the package), else
    for SIREN-CNN-N2d the shipped model (None when this install ships none)."""
    from sss2bathy.data.cnn_normals import resolve_model_path, shipped_model

    ckpt = cfg.get("cnn_checkpoint")
    if ckpt is None:
        shipped = shipped_model() if map_experiment(cfg) == "siren_cnn_n2d" else None
        return None if shipped is None else str(shipped.resolve())
    path = resolve_model_path(ckpt, "cnn_checkpoint")
    if not path.is_file():
        raise ValueError(
            f"cnn_checkpoint: expected a CNN checkpoint file (sss2bathy-train "
            f"experiment=cnn), an exported model (.safetensors) or 'pretrained', found no "
            f"file at {str(path)!r}"
        )
    return str(path.resolve())


def log_cnn_choice(cfg: Mapping[str, Any]) -> None:
    """One INFO line on where the map's normals come from when no ``cnn_checkpoint`` was
    given: the shipped CNN (SIREN-CNN-N2d), or why the default method is SIREN-Lambert."""
    from sss2bathy.data.cnn_normals import shipped_model

    if cfg.get("cnn_checkpoint") is not None:
        return
    shipped = shipped_model()
    if map_experiment(cfg) == "siren_cnn_n2d" and shipped is not None:
        log.info("cnn_checkpoint: none given: the CNN shipped in the package, %s", shipped)
    elif not cfg.get("method"):
        log.info(
            "method: null = siren_lambert (no cnn_checkpoint; %s)",
            "method=siren_cnn_n2d uses the shipped pretrained CNN"
            if shipped is not None
            else "this install ships no pretrained CNN",
        )


def map_settings_choice(cfg: Mapping[str, Any]) -> str:
    """``map_settings``: ``scale`` (the scale preset's SIREN settings), ``survey`` (omega0
    and steps from the survey's sonar range and extent, with the occlusion term) or
    ``detail`` (the scale's SIREN plus a detail network at the survey's omega0),
    :mod:`sss2bathy.cli.map_settings`."""

    choice = cfg.get("map_settings") or "scale"
    if choice not in MAP_SETTINGS:
        raise ValueError(
            f"map_settings: expected one of {', '.join(MAP_SETTINGS)}, found {str(choice)!r}"
        )
    return str(choice)


def check_map_config(cfg: DictConfig) -> None:
    """What ``sss2bathy-map`` checks before its run folder is made: the method,
    ``map_settings`` and ``verdict.folds``."""
    map_experiment(cfg)
    map_settings_choice(cfg)
    mosaic_placement(cfg)
    verdict_folds(cfg)
    overlap_settings(cfg)
    uncertainty_scale(cfg)
    tile_settings(cfg)


def train_overrides(cfg: Mapping[str, Any], choices: Mapping[str, Any]) -> list[str]:
    """The ``sss2bathy-train`` overrides of a map config: its experiment, the xtf survey
    source, the ``scale`` / ``siren_schedule`` / ``logger`` group ``choices`` it was
    composed with (Hydra's ``runtime.choices``), then its ``overrides``."""
    groups = [f"experiment={map_experiment(cfg)}", "data/survey=xtf"]
    for group, default in (("scale", "demo"), ("siren_schedule", None), ("logger", "none")):
        choice = choices.get(group) or default
        if choice is not None:
            groups.append(f"{group}={choice}")
    # the map route's altimeter weight, before the user's overrides (which win)
    w_height = cfg.get("w_height")
    if w_height is not None:
        groups.append(f"model.w_height={float(w_height)!r}")
    return groups + [str(o) for o in cfg.get("overrides") or []]


def compose_train_config(cfg: DictConfig, run_dir: Path, choices: Mapping[str, Any]) -> DictConfig:
    """The ``train`` config a map config stands for (run folder ``run_dir``)."""
    from hydra import compose

    ckpt = map_cnn_checkpoint(cfg)
    survey = map_survey_config(cfg)
    train_cfg = compose("train", overrides=train_overrides(cfg, choices))
    with open_dict(train_cfg):
        train_cfg.data.survey = survey
        if train_cfg.data.normals.source == "cnn" and ckpt is not None:
            train_cfg.data.normals.checkpoint = ckpt
        elif train_cfg.data.normals.source == "cnn":
            raise ValueError(
                f"cnn_checkpoint: expected a CNN checkpoint for method "
                f"{map_experiment(cfg)!r} (CNN normals), found none (and this install ships "
                "no pretrained CNN in sss2bathy/pretrained/)"
            )
        for key in ("fraction", "block_pings", "block_m"):
            if cfg.holdout.get(key) is not None:
                train_cfg.data.holdout[key] = cfg.holdout[key]
        train_cfg.seed = int(cfg.seed)
        train_cfg.torch_threads = cfg.get("torch_threads")
        train_cfg.paths.data_dir = str(cfg.paths.data_dir)
        train_cfg.paths.output_dir = str(cfg.paths.output_dir)
        train_cfg.model.output_dir = str(run_dir)
        train_cfg.run_name = "map"
        # map_settings=survey / detail: the SIREN's omega0 / steps (detail: a detail
        # network's) from the survey's range and extent (cli/map_settings.py), except what
        # the user set in overrides; scale: the scale's own
        # a tile job (tile.index): the pings of its tile, a survey folder cut from the import
        tile_survey = tile_survey_config(cfg, survey)
        mode = map_settings_choice(cfg)
        if mode != "scale":
            from sss2bathy.cli.map_settings import apply_map_settings, scale_of_survey
            from sss2bathy.data.sources import survey_folder

            user = [str(o) for o in cfg.get("overrides") or []]
            # the imported survey (imported here if new: its checks come first; reused by
            # every later fit); a tile's SIREN spans the tile's pings: its omega0 from them
            folder = (
                survey_folder(survey, str(cfg.paths.data_dir))
                if tile_survey is None
                else Path(tile_survey["path"])
            )
            apply_map_settings(train_cfg, scale_of_survey(folder), user, mode=mode)
        if tile_survey is not None:
            train_cfg.data.survey = tile_survey
    return train_cfg


@dataclass
class MapResult:
    """A finished map run: its folder, output files, metrics and (``verdict.folds`` >= 2)
    the K-fold verdict."""

    run_dir: Path
    experiment: str
    survey_name: str
    metrics: dict[str, float]
    has_mbes: bool
    verdict: KFoldVerdict | None = None
    #: the leave-one-line-out overlap score (:func:`run_overlap`), or why there is none
    overlap: OverlapResult | None = None
    overlap_note: str | None = None

    @property
    def paths(self) -> dict[str, Path]:
        return {
            "map (GeoTIFF)": self.run_dir / "map.tif",
            "map (PNG)": self.run_dir / "map.png",
            "metrics": self.run_dir / "metrics.json",
            **{
                label: self.run_dir / name
                for label, name in OPTIONAL_OUTPUTS.items()
                if (self.run_dir / name).is_file()
            },
        }

    def metric(self, name: str) -> float | None:
        """``final/<name>`` (the final map's), else the last logged ``val/<name>``."""
        for key in (f"final/{name}", f"val/{MAP_TAGS.get(name, name)}"):
            value = self.metrics.get(key)
            if value is not None and math.isfinite(float(value)):
                return float(value)
        return None

    def score(self) -> float | None:
        """The run's held-out altimeter MAE (m): the K-fold mean of the map's method, else
        the single draw's."""
        if self.verdict is not None:
            mean = self.verdict.scores[0].mean
            return mean if math.isfinite(mean) else None
        return self.metric("holdout_alt_mae")

    def coverage_lines(self) -> list[str]:
        """The written map's coverage: imaged area and extrapolated share."""
        imaged, share = self.metric("imaged_area_m2"), self.metric("extrapolated_share")
        if imaged is None or share is None:
            return []
        written = self.metric("written_area_m2")
        before = self.metric("track_region_extrapolated_share")
        line = f"  imaged area: {imaged:.0f} m^2 (the sonar's footprint of the bins used)"
        if written is not None:
            line += f"; map.tif holds {written:.0f} m^2"
        line += f", {100 * share:.1f} % of it extrapolated"
        if before is not None:
            line += f" (a disc of swath radius around the track: {100 * before:.1f} %)"
        return [line]

    def verdict_lines(self) -> list[str]:
        """The K-fold table and the verdict sentence."""
        v = self.verdict
        if v is None:
            return []
        block = (
            f"blocks of {v.block_m:.1f} m (~{v.block_pings:.0f} pings)"
            if v.block_m is not None and v.block_pings is not None
            else "blocks"
        )
        cost = f", {v.seconds / 60:.1f} min of fits" if v.seconds is not None else ""
        lines = [f"  held-out altimeter, {v.folds} folds, {block}{cost}:"]
        lines += [f"    {row}" for row in v.table()]
        lines += [f"    {c.describe()}" for c in v.comparisons]
        if v.imaged_share is not None:
            lines.append(
                f"    held-out points inside the sonar's footprint: {100 * v.imaged_share:.0f} %"
                + (
                    " (a line's nadir gap: the sidescan reaches them only through the map's "
                    "continuity)"
                    if v.imaged_share < 0.05
                    else ""
                )
            )
        lines.append(f"  {v.sentence()}")
        if self.metric("holdout_alt_mae") is None:
            lines.append("  (map.tif: the fit on every altimeter point)")
        return lines

    def summary(self) -> list[str]:
        """What the command prints: where the files are, the coverage and the held-out
        scores (the K-fold table and verdict with ``verdict.folds`` >= 2)."""
        lines = [f"sss2bathy-map: {self.experiment} on survey '{self.survey_name}'"]
        lines += [f"  {label + ':':18s}{path}" for label, path in self.paths.items()]
        lines += self.coverage_lines()
        lines += self.uncertainty_lines()
        fit, interp = self.metric("holdout_alt_mae"), self.metric("holdout_interp_mae")
        if self.verdict is not None:
            lines += self.verdict_lines()
        elif fit is None or interp is None:
            lines.append(
                "  held-out altimeter: none held out (holdout.fraction=0 or lines too short)"
            )
        else:
            verdict = (
                "the fit beats interpolating the altimeter"
                if fit < interp
                else "the fit does NOT beat interpolating the altimeter"
            )
            n = self.metric("holdout_n")
            lines.append(
                f"  held-out altimeter MAE: {fit:.3f} m (fit) vs {interp:.3f} m (along-track "
                f"interpolation of the kept altimeter), ratio {fit / interp:.2f}"
                + (f", {int(n)} points" if n is not None else "")
                + f": {verdict} (one draw of blocks; verdict.folds=5 for a K-fold verdict)"
            )
        lines += self.overlap_lines()
        if self.has_mbes and self.metric("mae") is not None:
            lines.append(f"  MAE against the MBES grid: {self.metric('mae'):.3f} m")
        return lines

    def uncertainty_lines(self) -> list[str]:
        """The uncertainty layer's summary (``uncertainty/*`` of the metrics)."""
        median = self.metrics.get("uncertainty/sigma_median_m")
        if median is None:
            return []
        p95 = self.metrics.get("uncertainty/sigma_p95_m", math.nan)
        return [
            f"  height uncertainty (uncertainty.tif): 1 sigma median {median:.3f} m, 95th "
            f"percentile {p95:.3f} m ({self.metrics.get('uncertainty/scale', math.nan):g} x "
            f"the jackknife of the {int(self.metrics.get('uncertainty/folds', 0))} fold fits)"
        ]

    def overlap_lines(self) -> list[str]:
        """The overlap score's table and verdict, or the one line saying why there is none."""
        if self.overlap is None:
            return [f"  off-track overlap score: {self.overlap_note}"] if self.overlap_note else []
        v = self.overlap.verdict
        cost = f", {v.seconds / 60:.1f} min of fits" if v.seconds is not None else ""
        lines = [
            f"  off-track overlap score (each fold: one line held out, the map fitted from the "
            f"others and scored at {self.overlap.n_points} of the held-out lines' altimeter "
            f"points inside the others' swath footprint, off their tracks){cost}:"
        ]
        return [*lines, *self.overlap.lines(), f"  OVERLAP {v.sentence()}"]


def verdict_folds(cfg: Mapping[str, Any]) -> int:
    """``verdict.folds`` checked: 0 or 1 = off (one fit holding out ``holdout.fraction``),
    else the number of folds."""
    folds = (cfg.get("verdict") or {}).get("folds", 0)
    folds = 0 if folds is None else folds
    if isinstance(folds, bool) or not isinstance(folds, int) or folds < 0:
        raise ValueError(
            f"verdict.folds: expected 0 or 1 (off: one held-out draw) or a number of folds "
            f">= 2, found {folds!r}"
        )
    return folds


# quieter fold fits (unless the user's overrides set these keys)
FOLD_OVERRIDES = (
    "callbacks=progress",  # progress lines in a log file, no checkpoints or curves
    "trainer.enable_progress_bar=false",
    "+trainer.enable_model_summary=false",
    # a fold's fit is scored, not resumed: no checkpoints in the map's folder
    "+trainer.enable_checkpointing=false",
)


def fold_config(cfg: DictConfig, method: str) -> DictConfig:
    """The map config of one fold fit of ``method``: the user's overrides plus
    :data:`FOLD_OVERRIDES` for keys they do not set."""
    sub = cfg.copy()
    given = [str(o).lstrip("+~").split("=", 1)[0] for o in cfg.get("overrides") or []]
    extra = [o for o in FOLD_OVERRIDES if o.lstrip("+").split("=", 1)[0] not in given]
    with open_dict(sub):
        sub.method = method
        sub.overrides = [*(str(o) for o in cfg.get("overrides") or []), *extra]
    return sub


def run_verdict(cfg: DictConfig, run_dir: Path, choices: Mapping[str, Any]) -> KFoldVerdict | None:
    """The K-fold verdict (:mod:`sss2bathy.eval.verdict`) of a map config, None when
    ``verdict.folds`` < 2.

    For each fold ``k`` of ``verdict.folds``, the map's method and ``siren_heights_only``
    are fitted with fold ``k``'s blocks of altimeter points held out
    (``data.holdout.folds/fold/block_m``: blocks of ``holdout.block_m`` metres, null = the
    default length, :func:`sss2bathy.data.holdout.default_block_m`); every fold's
    interpolation baseline comes with the split. The fold fits write their maps into
    ``run_dir/verdict/<method>/fold<k>/``; the table goes to ``run_dir/verdict.json``.
    They cost ``2 x folds`` fits (``folds`` with method=siren_heights_only).
    """
    import time

    from sss2bathy.cli.train import fit

    folds = verdict_folds(cfg)
    if folds < 2:
        return None
    subject = map_experiment(cfg)
    methods = [subject] + ([HEIGHTS_ONLY] if subject != HEIGHTS_ONLY else [])
    scores: dict[str, list[float]] = {m: [] for m in (*methods, INTERPOLATION)}
    block_m: list[float] = []
    block_pings: list[float] = []
    imaged: list[float] = []
    start = time.monotonic()
    for fold in range(folds):
        for method in methods:
            fold_dir = Path(run_dir) / "verdict" / method / f"fold{fold}"
            train_cfg = compose_train_config(
                fold_config(cfg, method), fold_dir, {**choices, "logger": "none"}
            )
            with open_dict(train_cfg):
                train_cfg.data.holdout.folds = folds
                train_cfg.data.holdout.fold = fold
            t0 = time.monotonic()
            metrics = fit(train_cfg, fold_dir).metrics

            def value(key: str, metrics: Mapping[str, Any] = metrics) -> float:
                return float(metrics.get(f"final/{key}", math.nan))

            scores[method].append(value("holdout_alt_mae"))
            if method == subject:
                scores[INTERPOLATION].append(value("holdout_interp_mae"))
                block_m.append(value("holdout_block_m"))
                block_pings.append(value("holdout_block_pings"))
                imaged.append(value("holdout_imaged_share"))
            log.info(
                "verdict: fold %d/%d %s: held-out MAE %.3f m (interpolation %.3f m), %.0f s",
                fold + 1, folds, method, value("holdout_alt_mae"),
                value("holdout_interp_mae"), time.monotonic() - t0,
            )  # fmt: skip
    mean = lambda xs: float(np.nanmean(xs)) if np.isfinite(xs).any() else None  # noqa: E731
    verdict = kfold_verdict(
        scores,
        subject,
        mean(block_m),
        mean(block_pings),
        time.monotonic() - start,
        mean(imaged),
    )
    atomic_write_text(
        Path(run_dir) / "verdict.json", json.dumps(verdict.to_dict(), indent=2, sort_keys=True)
    )
    return verdict


def overlap_settings(cfg: Mapping[str, Any]) -> dict[str, Any]:
    """``verdict.overlap`` checked: ``enabled`` (true / false; null = with the K-fold
    verdict, ``verdict.folds`` >= 2) and ``min_points`` (the least overlap points that make
    a held-out line a fold, >= 1)."""
    node = (cfg.get("verdict") or {}).get("overlap") or {}
    enabled = node.get("enabled")
    if enabled is not None and not isinstance(enabled, bool):
        raise ValueError(
            f"verdict.overlap.enabled: expected true, false or null (with verdict.folds >= 2), "
            f"found {enabled!r}"
        )
    enabled = verdict_folds(cfg) >= 2 if enabled is None else enabled
    min_points = node.get("min_points", 10)
    if isinstance(min_points, bool) or not isinstance(min_points, int) or min_points < 1:
        raise ValueError(f"verdict.overlap.min_points: expected a count >= 1, found {min_points!r}")
    return {"enabled": enabled, "min_points": min_points}


def _map_grid(fold_dir: Path) -> tuple[Any, np.ndarray]:
    """A finished fit's ``map.npz``: the map (every cell) and its coverage."""
    from sss2bathy.survey import BathyGrid

    with np.load(Path(fold_dir) / "map.npz", allow_pickle=False) as saved:
        grid = BathyGrid(
            saved["heights"].astype(np.float32),
            float(saved["x0"]),
            float(saved["y0"]),
            float(saved["cell_size"]),
        )
        coverage = np.asarray(saved["coverage"], bool)
    return grid, coverage


def run_overlap(
    cfg: DictConfig, run_dir: Path, choices: Mapping[str, Any]
) -> tuple[OverlapResult | None, str | None]:
    """The leave-one-line-out overlap score (:mod:`sss2bathy.eval.overlap`) of a map config:
    ``(result, None)``, or ``(None, why not)`` (off, one line, no overlap, heights-only).

    Each line with ``verdict.overlap.min_points`` or more altimeter points inside the other
    lines' swath footprint (:func:`~sss2bathy.eval.overlap.offtrack_counts`) is held out in
    turn: the map's method and ``siren_heights_only`` are fitted from the other lines alone
    (sidescan and altimeter; a copy of the survey, ``<name>_overlap``, whose splits
    ``overlap_fit<i>`` / ``overlap_held<i>`` name them) into
    ``run_dir/overlap/<method>/<line>/``, and scored at the held-out line's overlap points
    with the plane through the other lines' altimeter beside them. Costs 2 fits per
    held-out line. The result (or the reason) goes to ``run_dir/overlap.json``.
    """
    import time

    from sss2bathy.cli.train import fit
    from sss2bathy.data.sources import load_survey
    from sss2bathy.eval.overlap import (
        offtrack_counts,
        overlap_unavailable,
        overlap_verdict,
        score_overlap_fold,
        unscored_reason,
    )
    from sss2bathy.survey import Survey

    settings = overlap_settings(cfg)
    if not settings["enabled"]:
        return None, None
    if tile_survey_config(cfg, map_survey_config(cfg)) is not None:
        reason = (
            "not computed in a tile job (tile.index): it holds out whole lines, which a tile "
            "cuts; score the blended map's survey untiled"
        )
        log.info("verdict.overlap: %s", reason)
        return None, reason
    subject = map_experiment(cfg)
    out_json = Path(run_dir) / "overlap.json"
    reason: str | None = None
    if subject == HEIGHTS_ONLY:
        reason = "not computed: method siren_heights_only has no sidescan to judge"
    else:
        base = compose_train_config(cfg, run_dir, choices)
        survey, _ = load_survey(base.data.survey, base.paths.data_dir)
        lines = survey.split_lines(str(base.data.sidescan_split))
        names = [ln.name for ln in lines]
        counts = offtrack_counts(lines, float(base.model.get("eval_cell_m") or 0.5))
        reason = overlap_unavailable(names, counts.tolist(), settings["min_points"])
    if reason is not None:
        log.info("verdict.overlap: %s", reason)
        atomic_write_text(out_json, json.dumps({"computable": False, "reason": reason}, indent=2))
        return None, reason
    held = [i for i, c in enumerate(counts) if c >= settings["min_points"]]
    survey_cfg = OmegaConf.to_container(base.data.survey, resolve=True)
    splits = dict(survey_cfg.get("splits") or {"test": list(names)})
    for i in held:
        splits[f"overlap_fit{i}"] = [n for n in names if n != names[i]]
        splits[f"overlap_held{i}"] = [names[i]]
    survey_cfg.update(splits=splits, name=f"{survey_cfg['name']}_overlap")
    log.info(
        "verdict.overlap: holding out %d of %d lines in turn (%s overlap points), 2 fits each",
        len(held), len(names), ", ".join(f"{names[i]}: {int(counts[i])}" for i in held),
    )  # fmt: skip
    methods = [subject, HEIGHTS_ONLY]
    folds = []
    start = time.monotonic()
    for i in held:
        maps, coverage = {}, None
        for method in methods:
            fold_dir = Path(run_dir) / "overlap" / method / names[i]
            train_cfg = compose_train_config(
                fold_config(cfg, method), fold_dir, {**choices, "logger": "none"}
            )
            with open_dict(train_cfg):
                train_cfg.data.survey = survey_cfg
                train_cfg.data.sidescan_split = f"overlap_fit{i}"
                train_cfg.data.altimeter_split = f"overlap_fit{i}"
                train_cfg.data.holdout.fraction = 0.0
                train_cfg.data.holdout.folds = 0
            t0 = time.monotonic()
            fit(train_cfg, fold_dir)
            maps[method], cov = _map_grid(fold_dir)
            coverage = cov if method == subject else coverage
            log.info(
                "verdict.overlap: %s held out, %s fitted from the other lines, %.0f s",
                names[i], method, time.monotonic() - t0,
            )  # fmt: skip
        copy = Survey.load(Path(str(base.paths.data_dir)) / str(survey_cfg["name"]))
        fold = score_overlap_fold(
            names[i],
            copy.altimeter(f"overlap_held{i}").xyz,
            copy.altimeter(f"overlap_fit{i}").xyz,
            coverage,
            maps,
            maps[subject],
            settings["min_points"],
        )
        log.info(
            "verdict.overlap: %s: %d overlap points, MAE %s",
            fold.line, fold.n_points, ", ".join(f"{k} {v:.3f} m" for k, v in fold.mae.items()),
        )  # fmt: skip
        folds.append(fold)
    reason = unscored_reason(folds, settings["min_points"])
    if reason is not None:
        log.info("verdict.overlap: %s", reason)
        atomic_write_text(out_json, json.dumps({"computable": False, "reason": reason}, indent=2))
        return None, reason
    result = overlap_verdict(folds, subject, seconds=time.monotonic() - start)
    atomic_write_text(out_json, json.dumps(result.to_dict(), indent=2, sort_keys=True))
    return result, None


def run_map(cfg: DictConfig, run_dir: Path, choices: Mapping[str, Any]) -> MapResult:
    """Import, fit and write the map of a ``conf/map.yaml`` config into ``run_dir``
    (``choices``: its group choices, see :func:`train_overrides`). With ``verdict.folds``
    >= 2 the K-fold verdict's fits come first (:func:`run_verdict`) and the map written is
    the fit on every altimeter point (the folds estimate its held-out error)."""
    from sss2bathy.cli.train import fit

    log_cnn_choice(cfg)
    verdict = run_verdict(cfg, run_dir, choices)
    overlap, overlap_note = run_overlap(cfg, run_dir, choices)
    train_cfg = compose_train_config(cfg, run_dir, choices)
    if verdict is not None:
        with open_dict(train_cfg):
            train_cfg.data.holdout.fraction = 0.0
    # the config goes to run_dir/config.yaml once every constructor's check passed; fit
    # validates it (once)
    apply_extras(train_cfg, print_config=False, validate=False)
    result = fit(train_cfg, run_dir, on_checked=lambda: log_config(train_cfg, run_dir))
    if is_tile_job(cfg):
        write_tile_record(cfg, map_survey_config(cfg), Path(run_dir))
    metrics = {}
    for key, value in result.metrics.items():
        try:
            metrics[key] = float(value)
        except (TypeError, ValueError):
            continue
    if verdict is not None:
        metrics.update(verdict.metrics())
        add_to_metrics_json(Path(run_dir) / "metrics.json", verdict.metrics())
    if overlap is not None:
        metrics.update(overlap.metrics("verdict/overlap/"))
        add_to_metrics_json(Path(run_dir) / "metrics.json", overlap.metrics("verdict/overlap/"))
    write_map_mosaic(cfg, train_cfg, Path(run_dir))
    sigma = write_map_uncertainty(
        cfg, train_cfg, Path(run_dir), verdict, str(choices.get("scale") or "demo")
    )
    metrics.update(sigma)
    add_to_metrics_json(Path(run_dir) / "metrics.json", sigma)
    write_map_item(cfg, train_cfg, Path(run_dir), verdict)
    mapped = MapResult(
        Path(run_dir),
        map_experiment(cfg),
        str(train_cfg.data.survey.name),
        metrics,
        result.has_mbes,
        verdict,
        overlap,
        overlap_note,
    )
    write_map_report(cfg, Path(run_dir), mapped.summary())
    return mapped


#: files a map run may hold beside map.tif, map.png and metrics.json (summary labels)
OPTIONAL_OUTPUTS = {
    "mosaic (GeoTIFF)": "mosaic.tif",
    "sigma (GeoTIFF)": "uncertainty.tif",
    "STAC item": "item.json",
    "report": "report.html",
}


def uncertainty_scale(cfg: Mapping[str, Any], preset: str | None = None) -> float | None:
    """``uncertainty``: None when off (``enabled: false``), else its factor: ``scale`` when
    set, else ``calibrated[<map_settings>][preset]`` (the calibration for the run's map
    settings and scale preset: the fold maps of another SIREN spread differently), else 1
    (the raw jackknife) with a WARNING. Without ``preset`` only the values are checked."""
    node = cfg.get("uncertainty") or {}
    if not node.get("enabled", False):
        return None
    calibrated = node.get("calibrated") or {}
    values = [("scale", node.get("scale"))]
    for settings, factors in calibrated.items():
        if settings not in MAP_SETTINGS or not isinstance(factors, Mapping | DictConfig):
            raise ValueError(
                f"uncertainty.calibrated.{settings}: expected factors per scale preset under "
                f"one of the map settings {', '.join(MAP_SETTINGS)}, found "
                f"{settings}: {factors!r}"
            )
        values += [(f"calibrated.{settings}.{k}", v) for k, v in factors.items()]
    for key, value in values:
        if value is None and key == "scale":
            continue
        if isinstance(value, bool) or not isinstance(value, int | float) or not value > 0:
            raise ValueError(
                f"uncertainty.{key}: expected a positive factor (1 = the raw jackknife), "
                f"found {value!r}"
            )
    if node.get("scale") is not None:
        return float(node["scale"])
    if preset is None:
        return math.nan
    settings = map_settings_choice(cfg)
    factors = calibrated.get(settings) or {}
    if preset in factors:
        return float(factors[preset])
    log.warning(
        "uncertainty.calibrated has no factor for map_settings=%s, scale=%s (calibrated: "
        "%s): uncertainty.tif holds the raw jackknife (scale 1), too narrow an error bar; "
        "set uncertainty.scale",
        settings,
        preset,
        ", ".join(f"{m}.{k}" for m, f in calibrated.items() for k in f) or "none",
    )
    return 1.0


def _survey_of(train_cfg: DictConfig) -> Any:
    from sss2bathy.survey import Survey

    return Survey.load(Path(str(train_cfg.paths.data_dir)) / str(train_cfg.data.survey.name))


def write_map_uncertainty(
    cfg: DictConfig,
    train_cfg: DictConfig,
    run_dir: Path,
    verdict: KFoldVerdict | None,
    preset: str = "demo",
) -> dict[str, float]:
    """``uncertainty.tif`` + ``.png`` from the verdict's fold fits
    (:func:`sss2bathy.eval.uncertainty.write_run_uncertainty`, the factor of
    :func:`uncertainty_scale` for the scale ``preset``); its metrics, or ``{}`` when off or
    without the verdict's folds (one line in the log says which)."""
    scale = uncertainty_scale(cfg, preset)
    if scale is None:
        return {}
    if verdict is None:
        log.info(
            "no uncertainty.tif: it comes from the K-fold verdict's fits (verdict.folds >= 2, "
            "found %s)",
            verdict_folds(cfg),
        )
        return {}
    from sss2bathy.eval.uncertainty import write_run_uncertainty
    from sss2bathy.eval.verdict import LABELS

    method = map_experiment(cfg)
    try:
        written = write_run_uncertainty(
            run_dir, method, scale, _survey_of(train_cfg).origin, LABELS.get(method, method)
        )
    except ValueError as err:  # the map is written: an uncertainty that cannot be made is not fatal
        log.warning("uncertainty.tif not written (the map is): %s", err)
        return {}
    log.info(
        "height uncertainty written to %s (1 sigma median %.3f m)",
        written.tif,
        written.summary["median"],
    )
    return written.to_metrics()


def write_map_item(
    cfg: DictConfig, train_cfg: DictConfig, run_dir: Path, verdict: KFoldVerdict | None
) -> Path | None:
    """``item.json``: the run's STAC Item (:mod:`sss2bathy.io.stac`) with its rasters, PNGs
    and metrics as assets, the ping times and the processing record; None when ``stac`` is
    off. Every raster is checked to be a cloud-optimised GeoTIFF (a WARNING names what is
    not)."""
    import sys

    import rasterio

    from sss2bathy.io.export import TAG_PREFIX, cog_layout
    from sss2bathy.io.stac import AssetSpec, map_item, write_item

    for name in ("map.tif", "uncertainty.tif", "mosaic.tif"):
        if (run_dir / name).is_file():
            problems = cog_layout(run_dir / name).problems()
            if problems:
                log.warning("%s: not a cloud-optimised GeoTIFF: %s", name, "; ".join(problems))
    if not cfg.get("stac", False):
        return None
    survey = _survey_of(train_cfg)
    times = [t for line in survey.lines for t in (line.time_s[0], line.time_s[-1])]
    with rasterio.open(run_dir / "map.tif") as src:
        tags = src.tags()
    specs = {
        "map": ("map.tif", "bathymetry (m, up)", ("data",)),
        "uncertainty": ("uncertainty.tif", "height uncertainty, 1 sigma (m)", ("data",)),
        "mosaic": ("mosaic.tif", "sidescan mosaic", ("data",)),
        "metrics": ("metrics.json", "metrics and held-out scores", ("metadata",)),
        "verdict": ("verdict.json", "the K-fold held-out verdict", ("metadata",)),
        "map_png": ("map.png", "bathymetry quicklook", ("overview", "visual")),
        "uncertainty_png": ("uncertainty.png", "uncertainty quicklook", ("overview",)),
        "mosaic_png": ("mosaic.png", "mosaic quicklook", ("overview",)),
        "report": ("report.html", "report of the run", ("metadata",)),
    }
    assets = {
        key: AssetSpec(run_dir / name, title, roles)
        for key, (name, title, roles) in specs.items()
        if (run_dir / name).is_file() or name == "report.html" and cfg.get("report", False)
    }
    extra = {"sss2bathy:survey": survey.name}
    if verdict is not None:
        extra["sss2bathy:verdict"] = verdict.outcome
    try:
        item = map_item(
            f"{survey.name}_{run_dir.name}",
            run_dir / "map.tif",
            min(times),
            max(times),
            assets,
            run_dir,
            method=map_experiment(cfg),
            command=list(sys.argv),
            cnn_checkpoint_sha256=tags.get(f"{TAG_PREFIX}CNN_CHECKPOINT_SHA256"),
            properties=extra,
        )
    except ValueError as err:  # the map is written: an item that cannot be made is not fatal
        log.warning("item.json not written (the map is): %s", err)
        return None
    path = write_item(item, run_dir / "item.json")
    log.info("STAC item written to %s", path)
    return path


def write_map_report(cfg: DictConfig, run_dir: Path, summary: Sequence[str]) -> Path | None:
    """``report.html`` (:func:`sss2bathy.eval.map_report.write_map_report`) unless
    ``report`` is off."""
    if not cfg.get("report", False):
        return None
    from sss2bathy.eval.map_report import write_map_report as write

    path = write(run_dir, summary=summary)
    log.info("report written to %s", path)
    return path


MOSAIC_PLACEMENTS = ("map", "flat", "none")


def mosaic_placement(cfg: Mapping[str, Any]) -> str:
    """``mosaic.placement``: ``map`` (each bin draped on the fitted map), ``flat`` (a flat
    seabed at the altimeter depth) or ``none``."""
    node = cfg.get("mosaic") or {}
    choice = str(node.get("placement") or "none")
    if choice not in MOSAIC_PLACEMENTS:
        raise ValueError(
            f"mosaic.placement: expected one of {', '.join(MOSAIC_PLACEMENTS)}, found {choice!r}"
        )
    return choice


def write_map_mosaic(cfg: DictConfig, train_cfg: DictConfig, run_dir: Path) -> list[Path]:
    """The run's sidescan mosaic (``mosaic.tif`` + ``.png``, :mod:`sss2bathy.eval.mosaic`):
    the survey's bins draped on the fitted map (``map.npz``) or on a flat seabed."""
    placement = mosaic_placement(cfg)
    if placement == "none":
        return []
    import numpy as np

    from sss2bathy.eval.mosaic import write_run_mosaic
    from sss2bathy.survey import BathyGrid, Survey

    survey = Survey.load(Path(str(train_cfg.paths.data_dir)) / str(train_cfg.data.survey.name))
    grid = None
    if placement == "map":
        with np.load(run_dir / "map.npz", allow_pickle=False) as saved:
            grid = BathyGrid(
                saved["heights"].astype(np.float32),
                float(saved["x0"]),
                float(saved["y0"]),
                float(saved["cell_size"]),
            )
    options = {"resolution": float(cfg.mosaic.get("resolution") or 0.1)}
    try:
        written = write_run_mosaic(run_dir, survey, grid=grid, cfg=options)
    except ValueError as err:  # the map is written: a mosaic that cannot be made is not fatal
        log.warning("sidescan mosaic not written (the map is): %s", err)
        return []
    log.info("sidescan mosaic (%s placement) written to %s", placement, run_dir / "mosaic.tif")
    return written


def add_to_metrics_json(path: Path, values: Mapping[str, float]) -> None:
    """Merge ``values`` into the run's ``metrics.json`` (written by the map export)."""
    if not path.is_file():
        return
    data = json.loads(path.read_text())
    data.update(values)
    atomic_write_text(path, json.dumps(data, indent=2, sort_keys=True))


setup_environment()
register_resolver()


@hydra_entry("map", help=HELP, check=check_map_config, aliases=KEY_ALIASES)
def main(cfg: DictConfig) -> float | None:
    from hydra.core.hydra_config import HydraConfig

    runtime = HydraConfig.get().runtime
    settings = tile_settings(cfg)
    if settings is not None and settings["index"] is None:  # the tile plan and its commands
        plan = run_tile_plan(cfg, map_survey_config(cfg), Path(runtime.output_dir))
        print("\n".join(plan), flush=True)
        return None
    result = run_map(cfg, Path(runtime.output_dir), dict(runtime.choices))
    print("\n".join(result.summary()), flush=True)
    return result.score()


if __name__ == "__main__":
    main()
