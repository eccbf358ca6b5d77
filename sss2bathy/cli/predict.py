"""``sss2bathy-predict``: CNN normals for whole lines (the input of SIREN-CNN-N2d).

sss2bathy-predict data/survey=synthetic_d2 ckpt_path=latest split=all
"""

from __future__ import annotations

import logging
from pathlib import Path

from omegaconf import DictConfig

from sss2bathy.cli._common import CliHelp, apply_extras, hydra_entry, setup_environment
from sss2bathy.data.cnn_normals import predict_normals, resolve_cnn_checkpoint
from sss2bathy.data.sources import load_survey
from sss2bathy.draping import DrapedLine, drape_survey
from sss2bathy.draping.render import render_draped

log = logging.getLogger("sss2bathy.predict")


def predict(cfg: DictConfig) -> dict:
    """Predict (or read from the cache) the n_lat waterfalls of ``cfg.split``'s lines;
    ``ckpt_path=latest`` = the newest run under ``<output_dir>/runs/cnn``."""
    survey, folder = load_survey(cfg.data.survey, cfg.paths.data_dir)
    runs_dir = Path(cfg.paths.output_dir) / "runs" / "cnn"
    ckpt = resolve_cnn_checkpoint(cfg.ckpt_path, runs_dir, key="ckpt_path")
    names = [ln.name for ln in survey.split_lines(cfg.split)]
    draped = None
    if cfg.use_draped_mask:
        if survey.grid is None:
            raise ValueError(
                "use_draped_mask: the survey has no MBES grid; set use_draped_mask=false"
            )
        draped = drape_survey(survey, folder, lines=names)
    preds = predict_normals(
        ckpt,
        survey,
        folder,
        names,
        draped,
        window_cfg=None,
        precision=str(cfg.get("precision", "fp32")),
        overlap=cfg.get("overlap"),
        batch_size=cfg.get("batch_size"),
    )
    log.info("predicted %d lines of %s with %s", len(preds), survey.name, ckpt)
    if cfg.render and draped is not None:
        name = names[0]
        n_lat, mask = preds[name]
        shown = DrapedLine(
            draped[name].points, n_lat, draped[name].grazing_rad, mask, dict(draped[name].meta)
        )
        out = folder / "figures" / f"cnn_prediction_{name}.png"
        render_draped(survey.line(name), shown, out)
        log.info("rendered %s", out)
    return preds


setup_environment()


HELP = CliHelp(
    prog="sss2bathy-predict",
    usage="[data/survey=NAME] [ckpt_path=CKPT|latest] [split=NAME|all] [KEY=VALUE ...]",
    summary=(
        "Run a CNN checkpoint over whole lines of a survey and cache the n_lat waterfalls "
        "(the input of SIREN-CNN-N2d) under paths.data_dir/<survey>/predictions/."
    ),
    keys=(
        ("data/survey=NAME", "synthetic_d1 (default), synthetic_d2, ... or xtf"),
        ("ckpt_path=CKPT", "a CNN checkpoint, or latest (newest under outputs/runs/cnn)"),
        ("split=NAME", "a split of the survey (test), or all"),
        ("precision=P", "fp32 (default) | bf16"),
        ("overlap=F", "window overlap in [0, 1) (null: the checkpoint's)"),
        ("render=BOOL", "render one line's prediction to PNG (true)"),
    ),
    examples=(
        "sss2bathy-predict data/survey=synthetic_d2 ckpt_path=latest split=all",
        "sss2bathy-predict data/survey=xtf data.survey.files=/data/lines "
        "ckpt_path=outputs/runs/cnn/RUN/checkpoints/last.ckpt",
    ),
)


@hydra_entry("predict", help=HELP)
def main(cfg: DictConfig) -> None:
    apply_extras(cfg)
    preds = predict(cfg)
    print(f"predicted {len(preds)} lines")


if __name__ == "__main__":
    main()
