"""``sss2bathy-mosaic``: a georeferenced sidescan mosaic (GeoTIFF + PNG quicklook) of a survey.

sss2bathy-mosaic survey=data/xtf_scotsman-iver2 out=mosaic.tif
sss2bathy-mosaic survey=data/synthetic_d1_demo out=m.tif placement=grid resolution=0.25
sss2bathy-mosaic survey=data/xtf_survey out=m.tif placement=grid grid=outputs/runs/map/RUN/map.tif
"""

from __future__ import annotations

import logging
from pathlib import Path

from omegaconf import DictConfig, OmegaConf

from sss2bathy.cli._common import CliHelp, apply_extras, hydra_entry, setup_environment

log = logging.getLogger("sss2bathy.mosaic")


def check(cfg: DictConfig) -> None:
    """The survey folder, the output path and the grid, before a run folder is made."""
    for key, what in (("survey", "a survey folder"), ("out", "an output GeoTIFF path")):
        if OmegaConf.is_missing(cfg, key) or cfg.get(key) in (None, ""):
            raise ValueError(f"{key}: expected {what} ({key}=...), found none")
    folder = Path(str(cfg.survey)).expanduser()
    if not (folder / "survey.yaml").is_file():
        found = "no such folder" if not folder.exists() else "a folder without survey.yaml"
        raise ValueError(
            f"survey: expected a survey folder holding survey.yaml (sss2bathy-prepare or "
            f"sss2bathy-map makes one), found {str(folder)!r} ({found})"
        )
    out = Path(str(cfg.out))
    if out.suffix.lower() not in (".tif", ".tiff"):
        raise ValueError(f"out: expected a GeoTIFF path ending in .tif, found {str(out)!r}")
    grid = cfg.get("grid")
    if grid is not None:
        if cfg.get("placement") != "grid":
            raise ValueError(
                f"grid: expected null with placement={cfg.get('placement')} (a grid is only "
                f"draped on with placement=grid), found {str(grid)!r}"
            )
        if not Path(str(grid)).expanduser().is_file():
            raise ValueError(f"grid: expected an existing GeoTIFF, found {str(grid)!r}")
    from sss2bathy.eval.mosaic import MosaicConfig

    MosaicConfig.coerce(mosaic_config(cfg))


def mosaic_config(cfg: DictConfig) -> dict:
    """The :class:`~sss2bathy.eval.mosaic.MosaicConfig` fields of the composed config."""
    keys = ("resolution", "placement", "overlap", "normalise", "blank", "sonar_mask")
    plain = OmegaConf.to_container(cfg, resolve=True)
    return {k: plain[k] for k in keys if k in plain}


def mosaic(cfg: DictConfig) -> list[Path]:
    """Build the mosaic of ``cfg.survey`` and write ``cfg.out`` (and its quicklook)."""
    from sss2bathy.eval.mosaic import MosaicConfig, build_mosaic, write_mosaic
    from sss2bathy.io.export import read_geotiff
    from sss2bathy.survey import Survey

    check(cfg)
    if cfg.get("torch_threads"):  # the entry point's start applied the policy's default
        from sss2bathy.utils.threads import apply_thread_policy

        apply_thread_policy(int(cfg.torch_threads), announce=False)
    mcfg = MosaicConfig.coerce(mosaic_config(cfg))
    survey = Survey.load(Path(str(cfg.survey)).expanduser())
    grid = None
    if cfg.get("grid") is not None:
        grid = read_geotiff(Path(str(cfg.grid)).expanduser(), origin=survey.origin)
    split = str(cfg.get("split") or "all")
    lines = [ln.name for ln in survey.split_lines(split)]
    result = build_mosaic(survey, mcfg, grid=grid, lines=lines)
    tracks = [survey.line(n).position[:, :2] for n in lines]
    written = write_mosaic(
        result,
        Path(str(cfg.out)).expanduser(),
        survey.origin,
        png=bool(cfg.get("png", True)),
        track=tracks,
        survey=survey,
    )
    log.info(
        "mosaic of %d lines of %s: %d x %d cells of %g m, %.0f %% with data",
        len(lines),
        survey.name,
        *result.grid.shape[::-1],
        mcfg.resolution,
        100 * result.coverage,
    )
    return written


setup_environment()


HELP = CliHelp(
    prog="sss2bathy-mosaic",
    usage="survey=FOLDER out=FILE.tif [resolution=M] [placement=flat|grid] [KEY=VALUE ...]",
    summary=(
        "Place every sidescan bin of a survey on the ground (flat seabed at the altimeter "
        "altitude, or draped on a height grid), normalise it as the CNN's input is "
        "normalised, and grid it into a GeoTIFF in the survey's projected CRS with a PNG "
        "quicklook beside it."
    ),
    keys=(
        ("survey=FOLDER", "a survey folder (holds survey.yaml)"),
        ("out=FILE.tif", "the output GeoTIFF; the quicklook is FILE.png"),
        ("resolution=M", "cell size in metres (0.1)"),
        ("placement=P", "flat (default) | grid"),
        ("grid=TIF", "heights to drape on with placement=grid (null: the survey's grid.tif)"),
        ("normalise=N", "relative (default, true) | median | raw (false)"),
        ("overlap=R", "nadir (default: smallest ground range wins) | max | mean"),
        ("split=NAME", "the lines: a split of the survey, or all (default)"),
        ("blank=[...]", "no-data mask reasons (water_column, no_hit, out_of_beam)"),
        ("torch_threads=N", "CPU threads (default: torch's)"),
    ),
    examples=tuple(
        line.strip()
        for line in (__doc__ or "").splitlines()
        if line.strip().startswith("sss2bathy-mosaic ")
    ),
)


@hydra_entry("mosaic", help=HELP, check=check)
def main(cfg: DictConfig) -> None:
    apply_extras(cfg)
    for path in mosaic(cfg):
        print(f"wrote {path}")


if __name__ == "__main__":
    main()
