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
import logging
import math
import re
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from omegaconf import DictConfig, ListConfig, OmegaConf, open_dict

from sss2bathy.cli._common import (
    CliHelp,
    apply_extras,
    hydra_entry,
    log_config,
    setup_environment,
)
from sss2bathy.metrics.bathy import MAP_TAGS

log = logging.getLogger("sss2bathy.map")

DEFAULT_EXPERIMENT = {True: "siren_cnn_n2d", False: "siren_lambert"}
#: the ``method`` values: SIREN experiments that need no MBES grid
MAP_METHODS = ("siren_lambert", "siren_heights_only", "siren_cnn_n2d")
#: config keys of ``conf/train.yaml`` (what errors from the import and the fit name) as
#: ``conf/map.yaml`` spells them
KEY_ALIASES = {
    "data.survey.": "survey.",
    "data.cnn_checkpoint": "cnn_checkpoint",
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
        ("files=PATH", "a folder of .xtf files, one file, a glob, or a list [a,b]"),
        (
            "method=NAME",
            f"{', '.join(MAP_METHODS)} (default: siren_cnn_n2d with a "
            "checkpoint, else siren_lambert)",
        ),
        ("cnn_checkpoint=CKPT", "a CNN checkpoint (sss2bathy-train experiment=cnn)"),
        (
            "survey.KEY=VALUE",
            "import and sonar settings, e.g. survey.crs=EPSG:32633 "
            "survey.tilt_deg=20 survey.altitude_tolerance_m=null",
        ),
        ("scale=NAME", "tiny | demo (default) | paper: the fit's size"),
        ("holdout.fraction=F", "altimeter points held out for the score (0.2; 0 = off)"),
        ("logger=NAME", "tensorboard (default) | none"),
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


def check_map_config(cfg: DictConfig) -> None:
    """What ``sss2bathy-map`` checks before its run folder is made: the method."""
    map_experiment(cfg)


def train_overrides(cfg: Mapping[str, Any], choices: Mapping[str, Any]) -> list[str]:
    """The ``sss2bathy-train`` overrides of a map config: its experiment, the xtf survey
    source, the ``scale`` / ``siren_schedule`` / ``logger`` group ``choices`` it was
    composed with (Hydra's ``runtime.choices``), then its ``overrides``."""
    groups = [f"experiment={map_experiment(cfg)}", "data/survey=xtf"]
    for group, default in (("scale", "demo"), ("siren_schedule", None), ("logger", "none")):
        choice = choices.get(group) or default
        if choice is not None:
            groups.append(f"{group}={choice}")
    return groups + [str(o) for o in cfg.get("overrides") or []]


def compose_train_config(cfg: DictConfig, run_dir: Path, choices: Mapping[str, Any]) -> DictConfig:
    """The ``train`` config a map config stands for (run folder ``run_dir``)."""
    from hydra import compose

    ckpt = cfg.get("cnn_checkpoint")
    if ckpt is not None:
        path = Path(str(ckpt)).expanduser()
        if not path.is_file():
            raise ValueError(
                f"cnn_checkpoint: expected a CNN checkpoint file (sss2bathy-train "
                f"experiment=cnn), found no file at {str(path)!r}"
            )
        ckpt = str(path.resolve())
    survey = OmegaConf.to_container(cfg.survey, resolve=True)
    survey["name"] = survey.get("name") or default_survey_name(survey["files"])
    train_cfg = compose("train", overrides=train_overrides(cfg, choices))
    with open_dict(train_cfg):
        train_cfg.data.survey = survey
        if ckpt is not None:
            train_cfg.data.cnn_checkpoint = ckpt
        elif train_cfg.data.get("normals") == "cnn":
            raise ValueError(
                f"cnn_checkpoint: expected a CNN checkpoint for method "
                f"{map_experiment(cfg)!r} (CNN normals), found none"
            )
        for key in ("fraction", "block_pings"):
            if cfg.holdout.get(key) is not None:
                train_cfg.data.holdout[key] = cfg.holdout[key]
        train_cfg.seed = int(cfg.seed)
        train_cfg.torch_threads = cfg.get("torch_threads")
        train_cfg.paths.data_dir = str(cfg.paths.data_dir)
        train_cfg.paths.output_dir = str(cfg.paths.output_dir)
        train_cfg.model.output_dir = str(run_dir)
        train_cfg.run_name = "map"
    return train_cfg


@dataclass
class MapResult:
    """A finished map run: its folder, output files and metrics."""

    run_dir: Path
    experiment: str
    survey_name: str
    metrics: dict[str, float]
    has_mbes: bool

    @property
    def paths(self) -> dict[str, Path]:
        return {
            "map (GeoTIFF)": self.run_dir / "map.tif",
            "map (PNG)": self.run_dir / "map.png",
            "metrics": self.run_dir / "metrics.json",
        }

    def metric(self, name: str) -> float | None:
        """``final/<name>`` (the final map's), else the last logged ``val/<name>``."""
        for key in (f"final/{name}", f"val/{MAP_TAGS.get(name, name)}"):
            value = self.metrics.get(key)
            if value is not None and math.isfinite(float(value)):
                return float(value)
        return None

    def summary(self) -> list[str]:
        """What the command prints: where the files are and the held-out scores."""
        lines = [f"sss2bathy-map: {self.experiment} on survey '{self.survey_name}'"]
        lines += [f"  {label + ':':15s}{path}" for label, path in self.paths.items()]
        fit, interp = self.metric("holdout_alt_mae"), self.metric("holdout_interp_mae")
        if fit is None or interp is None:
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
                + f": {verdict}"
            )
        if self.has_mbes and self.metric("mae") is not None:
            lines.append(f"  MAE against the MBES grid: {self.metric('mae'):.3f} m")
        return lines


def run_map(cfg: DictConfig, run_dir: Path, choices: Mapping[str, Any]) -> MapResult:
    """Import, fit and write the map of a ``conf/map.yaml`` config into ``run_dir``
    (``choices``: its group choices, see :func:`train_overrides`)."""
    from sss2bathy.cli.train import fit

    train_cfg = compose_train_config(cfg, run_dir, choices)
    # the config goes to run_dir/config.yaml once every constructor's check passed
    apply_extras(train_cfg, print_config=False)
    result = fit(train_cfg, run_dir, on_checked=lambda: log_config(train_cfg, run_dir))
    metrics = {}
    for key, value in result.metrics.items():
        try:
            metrics[key] = float(value)
        except (TypeError, ValueError):
            continue
    return MapResult(
        Path(run_dir),
        map_experiment(cfg),
        str(train_cfg.data.survey.name),
        metrics,
        result.has_mbes,
    )


setup_environment()


@hydra_entry("map", help=HELP, check=check_map_config, aliases=KEY_ALIASES)
def main(cfg: DictConfig) -> float | None:
    from hydra.core.hydra_config import HydraConfig

    runtime = HydraConfig.get().runtime
    result = run_map(cfg, Path(runtime.output_dir), dict(runtime.choices))
    print("\n".join(result.summary()), flush=True)
    return result.metric("holdout_alt_mae")


if __name__ == "__main__":
    main()
