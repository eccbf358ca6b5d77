"""``sss2bathy-predict``: CNN normals for whole lines (the input of SIREN-CNN-N2d).

sss2bathy-predict data/survey=synthetic_d2 ckpt_path=latest split=all
"""

from __future__ import annotations

import logging
from pathlib import Path

from omegaconf import DictConfig

from sss2bathy.cli._common import apply_extras, hydra_entry, setup_environment

log = logging.getLogger("sss2bathy.predict")


def resolve_cnn_checkpoint(ckpt_path: str, output_dir: str | Path) -> Path:
    """``latest`` -> newest ``last.ckpt`` of the ``cnn`` runs; otherwise the given path."""
    from sss2bathy.data.pings import latest_checkpoint

    if ckpt_path == "latest":
        return latest_checkpoint(Path(output_dir) / "runs" / "cnn")
    path = Path(ckpt_path)
    if not path.is_file():
        raise FileNotFoundError(f"ckpt_path: expected a CNN checkpoint file, found {path}")
    return path


def predict(cfg: DictConfig) -> dict:
    from sss2bathy.data.sources import load_survey
    from sss2bathy.modules.predict import predict_normals

    survey, folder = load_survey(cfg.data.survey, cfg.paths.data_dir)
    ckpt = resolve_cnn_checkpoint(cfg.ckpt_path, cfg.paths.output_dir)
    names = [ln.name for ln in survey.split_lines(cfg.split)]
    draped = None
    if cfg.use_draped_mask:
        if survey.grid is None:
            raise ValueError(
                "use_draped_mask: the survey has no MBES grid; set use_draped_mask=false"
            )
        from sss2bathy.draping import drape_survey

        draped = drape_survey(survey, folder, lines=names)
    preds = predict_normals(ckpt, survey, folder, names, draped, window_cfg=None)
    log.info("predicted %d lines of %s with %s", len(preds), survey.name, ckpt)
    if cfg.render and draped is not None:
        from sss2bathy.draping import DrapedLine
        from sss2bathy.draping.render import render_draped

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


@hydra_entry("predict")
def main(cfg: DictConfig) -> None:
    apply_extras(cfg)
    preds = predict(cfg)
    print(f"predicted {len(preds)} lines")


if __name__ == "__main__":
    main()
