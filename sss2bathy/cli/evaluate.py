"""``sss2bathy-eval``: score a saved map or SIREN checkpoint against the MBES grid.

sss2bathy-eval ckpt_path=outputs/runs/siren_gt_n2d/<run>/checkpoints/last.ckpt
sss2bathy-eval map_path=outputs/runs/siren_cnn_n2d/<run>/map.tif split=test
"""

from __future__ import annotations

import json
import logging
import math
from pathlib import Path

import numpy as np
from omegaconf import DictConfig

from sss2bathy.cli._common import CliHelp, apply_extras, hydra_entry, setup_environment

log = logging.getLogger("sss2bathy.eval")


def load_map(cfg: DictConfig, like, origin=None):  # -> BathyGrid
    """The map to score, on ``like``'s geometry (from a checkpoint or a GeoTIFF; a
    georeferenced GeoTIFF is shifted back into the local frame by the survey ``origin``)."""
    import torch

    from sss2bathy.eval.maps import siren_to_grid
    from sss2bathy.models.siren import Siren

    if bool(cfg.map_path) == bool(cfg.ckpt_path):
        raise ValueError(
            "map_path, ckpt_path: expected exactly one of them, found "
            f"map_path={cfg.map_path!r}, ckpt_path={cfg.ckpt_path!r}"
        )
    if cfg.ckpt_path:
        path = Path(cfg.ckpt_path)
        if not path.is_file():
            raise FileNotFoundError(f"ckpt_path: expected a checkpoint file, found {path}")
        state = torch.load(path, map_location="cpu", weights_only=True)["state_dict"]
        return siren_to_grid(Siren.from_state_dict(state, prefix="siren."), like)
    from sss2bathy.io.export import read_geotiff

    grid = read_geotiff(cfg.map_path, origin=origin)
    if grid.shape != like.shape or not np.allclose(
        [grid.x0, grid.y0, grid.cell_size], [like.x0, like.y0, like.cell_size]
    ):
        raise ValueError(
            f"map_path: expected a map on the MBES grid's geometry {like.shape} "
            f"({like.x0}, {like.y0}, {like.cell_size} m), found {grid.shape} "
            f"({grid.x0}, {grid.y0}, {grid.cell_size} m)"
        )
    return grid


def evaluate(cfg: DictConfig, out_dir: Path) -> dict:
    from sss2bathy.data.sources import load_survey
    from sss2bathy.eval.maps import map_metrics, save_map_outputs, track_region_mask

    survey, _ = load_survey(cfg.data.survey, cfg.paths.data_dir)
    if survey.grid is None:
        raise ValueError(f"survey '{survey.name}': expected an MBES grid to evaluate against")
    pred = load_map(cfg, survey.grid, survey.origin)
    lines = survey.split_lines(cfg.split)
    track = np.concatenate([ln.position[:, :2] for ln in lines])
    radius = cfg.region_radius_m
    if radius is None:
        r_max = max(float(ln.range_m[-1]) for ln in lines)
        alt = float(np.nanmedian(np.concatenate([ln.altitude_m for ln in lines])))
        radius = math.sqrt(max(r_max**2 - alt**2, 0.0)) or r_max
    region = track_region_mask(survey.grid, track, float(radius))
    metrics = map_metrics(pred, survey.grid, region)
    save_map_outputs(
        out_dir, pred, survey.grid, region, metrics, title="evaluated map", origin=survey.origin
    )
    log.info("metrics: %s", json.dumps(metrics))
    return metrics


setup_environment()


HELP = CliHelp(
    prog="sss2bathy-eval",
    usage="(map_path=TIF | ckpt_path=CKPT) [data/survey=NAME] [split=NAME] [KEY=VALUE ...]",
    summary=(
        "Score a saved SIREN map (GeoTIFF) or checkpoint against the survey's MBES grid over "
        "the cells near a split's sonar tracks; metrics and PNGs go to the run folder."
    ),
    keys=(
        ("map_path=TIF", "a map GeoTIFF (map.tif of a run); or:"),
        ("ckpt_path=CKPT", "a SIREN checkpoint (.ckpt)"),
        ("data/survey=NAME", "the survey the map is of (synthetic_d1 by default)"),
        ("split=NAME", "lines whose tracks define the scored area (test)"),
        ("region_radius_m=M", "radius around the tracks (null: the swath half-width)"),
        ("scale=NAME", "tiny | demo (default) | paper"),
    ),
    examples=(
        "sss2bathy-eval ckpt_path=outputs/runs/siren_gt_n2d/RUN/checkpoints/last.ckpt",
        "sss2bathy-eval map_path=outputs/runs/siren_cnn_n2d/RUN/map.tif split=test",
    ),
)


@hydra_entry("eval", help=HELP)
def main(cfg: DictConfig) -> None:
    from hydra.core.hydra_config import HydraConfig

    apply_extras(cfg)
    out = Path(HydraConfig.get().runtime.output_dir)
    metrics = evaluate(cfg, out)
    print(json.dumps(metrics, indent=2))
    print(f"written to {out}")


if __name__ == "__main__":
    main()
