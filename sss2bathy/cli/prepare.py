"""``sss2bathy-prepare``: generate or import a survey, drape it on its MBES grid, render figures.

sss2bathy-prepare data/survey=synthetic_d1 scale=demo
sss2bathy-prepare data/survey=xtf data.survey.files=/path/to/xtf data.survey.mbes_grid=mbes.tif
"""

from __future__ import annotations

import logging
import shutil
from pathlib import Path

from omegaconf import DictConfig

from sss2bathy.cli._common import CliHelp, apply_extras, hydra_entry, setup_environment

log = logging.getLogger("sss2bathy.prepare")


def prepare(cfg: DictConfig) -> Path:
    """Make the survey folder exist (cached), drape it if it has a grid; return the folder."""
    from sss2bathy.config_validation import validate_config
    from sss2bathy.data.sources import load_survey

    validate_config(cfg)
    name = cfg.data.survey.get("name")
    existed = bool(name) and (Path(cfg.paths.data_dir) / str(name)).exists()
    survey, folder = load_survey(cfg.data.survey, cfg.paths.data_dir, force=cfg.get("force", False))
    log.info("survey %s: %d lines at %s", survey.name, len(survey.lines), folder)
    if cfg.get("drape", True) and survey.grid is not None:
        from sss2bathy.draping import drape_survey
        from sss2bathy.survey import mask_reason_counts

        try:
            draped = drape_survey(survey, folder)
        except ValueError:
            # An import this call made that cannot be draped is no survey: leave nothing.
            if not existed and cfg.data.survey.get("kind") == "xtf":
                shutil.rmtree(folder, ignore_errors=True)
            raise
        for name, d in draped.items():
            log.info("draped %s: %s", name, mask_reason_counts(d.mask))
    if cfg.get("render", True):
        from sss2bathy.sim.render import render_terrain, render_waterfall

        figures = folder / "figures"
        if survey.grid is not None:
            render_terrain(survey, figures / "terrain.png")
        first = survey.lines[0]
        render_waterfall(first, figures / f"waterfall_{first.name}.png")
        log.info("figures in %s", figures)
    return folder


setup_environment()


HELP = CliHelp(
    prog="sss2bathy-prepare",
    usage="[data/survey=NAME] [scale=NAME] [KEY=VALUE ...] [-m] [--trace]",
    summary=(
        "Generate a synthetic survey or import XTF files into paths.data_dir/<name>/ "
        "(cached while unchanged), drape its lines on its MBES grid, render figures."
    ),
    keys=(
        ("data/survey=NAME", "synthetic_d1 (default), synthetic_d2, synthetic_d3, ... or xtf"),
        ("data.survey.files=PATH", "with data/survey=xtf: a folder, file or glob of .xtf"),
        ("data.survey.mbes_grid=TIF", "with data/survey=xtf: an MBES GeoTIFF to drape on"),
        ("scale=NAME", "tiny | demo (default) | paper"),
        ("drape=BOOL", "drape the lines on the MBES grid (true)"),
        ("force=BOOL", "make the survey again even when the cache matches (false)"),
        ("paths.data_dir=DIR", "where survey folders go (data/)"),
    ),
    examples=(
        "sss2bathy-prepare data/survey=synthetic_d1 scale=demo",
        "sss2bathy-prepare data/survey=xtf data.survey.files=/data/lines "
        "data.survey.mbes_grid=mbes.tif",
    ),
)


@hydra_entry("prepare", help=HELP)
def main(cfg: DictConfig) -> None:
    apply_extras(cfg)
    folder = prepare(cfg)
    print(f"survey ready: {folder}")


if __name__ == "__main__":
    main()
