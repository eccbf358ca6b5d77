"""The sidescan-only route: optimized_metric fallback, and ``sss2bathy-map`` / ``sss2bathy-train``
on a tiny XTF survey without MBES (generated here with the simulator and ``write_xtf``)."""

from __future__ import annotations

import json
import logging
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from omegaconf import OmegaConf

from sss2bathy.cli.map import (
    MapResult,
    check_map_config,
    default_survey_name,
    fold_config,
    map_experiment,
    map_settings_choice,
    mosaic_placement,
    train_overrides,
    verdict_folds,
    write_map_mosaic,
)
from sss2bathy.cli.train import HOLDOUT_METRIC, optimized_value

ROOT = Path(__file__).resolve().parents[2]
CONF = ROOT / "conf"


# ------------------------------------------------------------------ fast: the fallback
def test_optimized_metric_falls_back_to_the_holdout_score_without_mbes(caplog):
    logged = {"train/loss": 0.5, HOLDOUT_METRIC: 0.25, "val/holdout_interp_mae_m": 0.3}
    assert optimized_value("val/map_mae_m", {**logged, "val/map_mae_m": 0.1}, has_mbes=False) == (
        "val/map_mae_m",
        0.1,
    )
    with caplog.at_level(logging.WARNING, logger="sss2bathy.train"):
        assert optimized_value("val/map_mae_m", logged, has_mbes=False) == (HOLDOUT_METRIC, 0.25)
    warnings = [r for r in caplog.records if r.levelno == logging.WARNING]
    assert len(warnings) == 1 and "val/holdout_alt_mae_m" in warnings[0].getMessage()
    caplog.clear()
    with caplog.at_level(logging.WARNING, logger="sss2bathy.train"):
        assert optimized_value("val/map_mae_m", {"train/loss": 0.5}, has_mbes=False) == (None, None)
    assert len([r for r in caplog.records if r.levelno == logging.WARNING]) == 1
    assert optimized_value(None, logged, has_mbes=False) == (None, None)
    # with MBES a metric that was not logged is a configuration error
    with pytest.raises(KeyError, match="optimized_metric 'val/map_mae_m' was not logged"):
        optimized_value("val/map_mae_m", logged, has_mbes=True)


def test_map_config_picks_the_method_and_the_survey_name():
    cfg = OmegaConf.load(CONF / "map.yaml")
    assert map_experiment({"cnn_checkpoint": None}) == "siren_lambert"
    assert map_experiment({"cnn_checkpoint": "x.ckpt"}) == "siren_cnn_n2d"
    assert map_experiment({"method": "siren_heights_only"}) == "siren_heights_only"
    overrides = train_overrides(
        {"overrides": ["trainer.max_epochs=3"]}, {"scale": "tiny", "logger": "none"}
    )
    assert overrides == [
        "experiment=siren_lambert",
        "data/survey=xtf",
        "scale=tiny",
        "logger=none",
        "trainer.max_epochs=3",
    ]
    # the map route's altimeter weight comes before the user's overrides, which win
    assert cfg.w_height == 1.0
    assert train_overrides({"w_height": 1.0, "overrides": ["model.w_height=0.3"]}, {})[-2:] == [
        "model.w_height=1.0",
        "model.w_height=0.3",
    ]
    assert cfg.holdout.fraction > 0  # every map run is scored on held-out altimeter points
    assert default_survey_name("/data/my lines/") == "xtf_my_lines"
    assert default_survey_name(["/d/L01.xtf", "/d/L02.xtf"]) == "xtf_L01"
    assert default_survey_name("/d/run3/*_HF.xtf") == "xtf_run3"
    assert default_survey_name("/d/xtf_2024") == "xtf_2024"


def test_map_summary_says_whether_the_fit_beat_interpolation(tmp_path):
    metrics = {"final/holdout_alt_mae": 0.1, "final/holdout_interp_mae": 0.2, "final/holdout_n": 9}
    text = "\n".join(MapResult(tmp_path, "siren_lambert", "s", metrics, False).summary())
    assert str(tmp_path / "map.tif") in text and str(tmp_path / "metrics.json") in text
    assert "0.100 m (fit) vs 0.200 m" in text and "ratio 0.50" in text and "beats" in text
    worse = {"val/holdout_alt_mae_m": 0.3, "val/holdout_interp_mae_m": 0.2}
    text = "\n".join(MapResult(tmp_path, "siren_lambert", "s", worse, False).summary())
    assert "does NOT beat" in text
    text = "\n".join(MapResult(tmp_path, "siren_lambert", "s", {}, False).summary())
    assert "none held out" in text


def test_map_summary_shows_coverage_the_k_fold_table_and_the_verdict(tmp_path):
    from sss2bathy.eval.verdict import HEIGHTS_ONLY, INTERPOLATION, kfold_verdict

    verdict = kfold_verdict(
        {
            "siren_lambert": [0.10, 0.20, 0.15, 0.12, 0.30],
            HEIGHTS_ONLY: [0.11, 0.19, 0.16, 0.12, 0.31],
            INTERPOLATION: [0.12, 0.22, 0.14, 0.13, 0.29],
        },
        "siren_lambert",
        block_m=7.0,
        block_pings=57.0,
        seconds=300.0,
        imaged_share=0.0,
    )
    metrics = {
        "final/imaged_area_m2": 2458.5,
        "final/written_area_m2": 2489.5,
        "final/extrapolated_share": 0.0,
        "final/track_region_extrapolated_share": 0.598,
    }
    result = MapResult(tmp_path, "siren_lambert", "s", metrics, False, verdict)
    text = "\n".join(result.summary())
    assert "imaged area: 2458 m^2" in text and "0.0 % of it extrapolated" in text
    assert "59.8 %" in text  # the older disc coverage's share, for comparison
    assert "5 folds, blocks of 7.0 m (~57 pings)" in text
    for label in ("SIREN-Lambert (sidescan)", "heights only", "along-track interpolation"):
        assert label in text
    assert "0.174 +- 0.080" in text  # the sidescan fit's mean +- std over the folds
    assert "VERDICT: inconclusive" in text and "every altimeter point" in text
    assert "inside the sonar's footprint: 0 % (a line's nadir gap" in text
    assert result.score() == pytest.approx(0.174)


def test_fold_fits_are_quiet_unless_the_user_says_otherwise():
    cfg = OmegaConf.load(CONF / "map.yaml")
    assert verdict_folds(cfg) >= 2  # the K-fold verdict is on by default
    cfg.overrides = ["trainer.enable_progress_bar=true", "trainer.max_epochs=3"]
    sub = fold_config(cfg, "siren_heights_only")
    assert sub.method == "siren_heights_only" and cfg.method is None
    assert list(sub.overrides) == [
        "trainer.enable_progress_bar=true",
        "trainer.max_epochs=3",
        "callbacks=progress",
        "+trainer.enable_model_summary=false",
        "+trainer.enable_checkpointing=false",
    ]
    for bad in (-1, 2.5, "five"):
        cfg.verdict.folds = bad
        with pytest.raises(ValueError, match="verdict.folds: expected 0 or 1"):
            verdict_folds(cfg)


def test_mosaic_placement_is_checked():
    cfg = OmegaConf.load(CONF / "map.yaml")
    assert mosaic_placement(cfg) == "map"  # draped on the fitted map by default
    for choice in ("flat", "none"):
        cfg.mosaic.placement = choice
        assert mosaic_placement(cfg) == choice
    cfg.mosaic.placement = "draped"
    with pytest.raises(ValueError, match="mosaic.placement: expected one of map, flat, none"):
        check_map_config(cfg)


def test_a_mosaic_that_cannot_be_made_is_a_warning_not_a_failed_map(tmp_path, monkeypatch, caplog):
    import sss2bathy.eval.mosaic as mosaic_module
    import sss2bathy.survey as survey_module

    def refuse(*args, **kwargs):
        raise ValueError("survey 'x': no bin hits the map")

    monkeypatch.setattr(survey_module.Survey, "load", staticmethod(lambda folder: object()))
    monkeypatch.setattr(mosaic_module, "write_run_mosaic", refuse)
    cfg = OmegaConf.load(CONF / "map.yaml")
    cfg.mosaic.placement = "flat"
    train_cfg = OmegaConf.create(
        {"paths": {"data_dir": str(tmp_path)}, "data": {"survey": {"name": "x"}}}
    )
    with caplog.at_level("WARNING", logger="sss2bathy.map"):
        assert write_map_mosaic(cfg, train_cfg, tmp_path) == []
    assert "sidescan mosaic not written (the map is): survey 'x': no bin hits" in caplog.text


def test_map_settings_choice_is_checked():
    cfg = OmegaConf.load(CONF / "map.yaml")
    # by default the scale preset's SIREN plus a detail network at the survey's omega0
    assert map_settings_choice(cfg) == "detail"
    cfg.map_settings = "scale"
    assert map_settings_choice(cfg) == "scale"
    cfg.map_settings = "survey"
    assert map_settings_choice(cfg) == "survey"
    cfg.map_settings = "detail"
    assert map_settings_choice(cfg) == "detail"
    cfg.map_settings = "surevy"
    with pytest.raises(ValueError, match="map_settings: expected one of scale, survey, detail"):
        check_map_config(cfg)


# ------------------------------------------------------------------ end to end
def _run(
    module: str, args: list[str], tmp: Path, timeout: float = 600
) -> subprocess.CompletedProcess:
    env = dict(os.environ, SSS2BATHY_ROOT=str(ROOT), OMP_NUM_THREADS="1", HYDRA_FULL_ERROR="1")
    return subprocess.run(
        [sys.executable, "-m", module, *args],
        cwd=tmp,
        env=env,
        capture_output=True,
        text=True,
        timeout=timeout,
    )


def _common(tmp: Path) -> list[str]:
    return [
        f"paths.data_dir={tmp / 'data'}",
        f"paths.output_dir={tmp / 'outputs'}",
        "scale=tiny",
        "logger=none",
        "torch_threads=1",
    ]


def test_sss2bathy_map_on_an_xtf_survey_without_mbes(tmp_path, tiny_xtf):
    folder, crs = tiny_xtf
    run = tmp_path / "run"
    proc = _run(
        "sss2bathy.cli.map",
        [
            f"files={folder}",
            f"survey.crs={crs}",
            "survey.n_bins=null",
            "holdout.block_pings=10",
            "verdict.folds=0",
            "verdict.overlap.enabled=false",  # its own test: tests/eval/test_overlap.py
            f"hydra.run.dir={run}",
            'overrides=["callbacks=none","trainer.enable_progress_bar=false"]',
            *_common(tmp_path),
        ],
        tmp_path,
    )
    assert proc.returncode == 0, proc.stderr[-3000:]
    for name in ("map.tif", "map.png", "metrics.json"):
        assert (run / name).is_file()
        assert str(run / name) in proc.stdout  # printed where they are
    metrics = json.loads((run / "metrics.json").read_text())
    for key in ("val/holdout_alt_mae_m", "val/holdout_interp_mae_m", "final/holdout_alt_mae"):
        assert np.isfinite(metrics[key]), key
    assert "val/map_mae_m" not in metrics  # no MBES
    assert metrics["final/holdout_n"] > 0
    assert "held-out altimeter MAE" in proc.stdout
    assert (tmp_path / "data" / "xtf_lines" / "survey.yaml").is_file()  # the imported survey


@pytest.mark.slow
@pytest.mark.parametrize("experiment", ["siren_heights_only", "siren_lambert"])
def test_sss2bathy_train_without_mbes_exits_0(tmp_path, tiny_xtf, experiment):
    """The issue's failure: optimized_metric val/map_mae_m with no MBES used to raise a KeyError."""
    folder, crs = tiny_xtf
    run = tmp_path / "run"
    proc = _run(
        "sss2bathy.cli.train",
        [
            f"experiment={experiment}",
            "data/survey=xtf",
            f"data.survey.files={folder}",
            f"data.survey.crs={crs}",
            "data.survey.n_bins=null",
            "data.holdout.block_pings=10",
            "callbacks=none",
            "trainer.enable_progress_bar=false",
            f"hydra.run.dir={run}",
            f"model.output_dir={run}",
            *_common(tmp_path),
        ],
        tmp_path,
    )
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert "returning val/holdout_alt_mae_m" in proc.stderr + proc.stdout
    metrics = json.loads((run / "metrics.json").read_text())
    assert np.isfinite(metrics["val/holdout_alt_mae_m"])
    assert (run / "map.tif").is_file() and (run / "map.png").is_file()


@pytest.mark.slow
def test_sss2bathy_map_with_a_cnn_checkpoint(tmp_path, tiny_xtf):
    """SIREN-CNN-N2d on the XTF survey with a CNN trained elsewhere (tiny synthetic run)."""
    folder, crs = tiny_xtf
    cnn_run = tmp_path / "cnn"
    proc = _run(
        "sss2bathy.cli.train",
        ["experiment=cnn", "trainer.enable_progress_bar=false", f"hydra.run.dir={cnn_run}"]
        + _common(tmp_path),
        tmp_path,
    )
    assert proc.returncode == 0, proc.stderr[-3000:]
    ckpt = cnn_run / "checkpoints" / "last.ckpt"
    run = tmp_path / "run"
    proc = _run(
        "sss2bathy.cli.map",
        [
            f"files={folder}",
            f"cnn_checkpoint={ckpt}",
            f"survey.crs={crs}",
            "survey.n_bins=null",
            "holdout.block_pings=10",
            "verdict.folds=0",  # one held-out draw (the K-fold verdict: its own test)
            f"hydra.run.dir={run}",
            'overrides=["callbacks=none","trainer.enable_progress_bar=false"]',
            *_common(tmp_path),
        ],
        tmp_path,
    )
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert "siren_cnn_n2d" in proc.stdout
    metrics = json.loads((run / "metrics.json").read_text())
    assert np.isfinite(metrics["final/holdout_alt_mae"]) and (run / "map.tif").is_file()
    # the sidescan mosaic draped on the map, in the map's CRS, over the map's extent
    import rasterio

    with rasterio.open(run / "mosaic.tif") as mosaic, rasterio.open(run / "map.tif") as fitted:
        assert mosaic.crs == fitted.crs
        inside = rasterio.coords.disjoint_bounds(mosaic.bounds, fitted.bounds) is False
        assert inside and np.isfinite(mosaic.read(1, masked=True).compressed()).any()
    assert "mosaic (GeoTIFF)" in proc.stdout
    # a missing checkpoint is refused by name
    proc = _run(
        "sss2bathy.cli.map",
        [f"files={folder}", f"cnn_checkpoint={tmp_path / 'nope.ckpt'}", *_common(tmp_path)],
        tmp_path,
    )
    assert proc.returncode != 0 and "cnn_checkpoint: expected a CNN checkpoint file" in proc.stderr


@pytest.mark.slow
def test_sss2bathy_map_k_fold_verdict_end_to_end(tmp_path, tiny_xtf):
    """verdict.folds=2: two folds of the sidescan fit and of heights only, then the map on
    every altimeter point; the table, the verdict and the footprint coverage are reported."""
    folder, crs = tiny_xtf
    run = tmp_path / "run"
    proc = _run(
        "sss2bathy.cli.map",
        [
            f"files={folder}",
            f"survey.crs={crs}",
            "survey.n_bins=null",
            "verdict.folds=2",
            f"hydra.run.dir={run}",
            'overrides=["callbacks=none","trainer.enable_progress_bar=false"]',
            *_common(tmp_path),
        ],
        tmp_path,
    )
    assert proc.returncode == 0, proc.stderr[-3000:]
    verdict = json.loads((run / "verdict.json").read_text())
    assert verdict["folds"] == 2 and verdict["block_m"] > 0 and verdict["block_pings"] > 0
    assert set(verdict["methods"]) == {"siren_lambert", "siren_heights_only", "interpolation"}
    for scores in verdict["methods"].values():
        assert len(scores["mae_per_fold"]) == 2 and np.isfinite(scores["mae_per_fold"]).all()
    assert verdict["outcome"] in ("helped", "did not help", "inconclusive")
    assert 0.0 <= verdict["imaged_share"] <= 1.0
    for fold in (0, 1):
        assert (run / "verdict" / "siren_heights_only" / f"fold{fold}" / "map.tif").is_file()
    metrics = json.loads((run / "metrics.json").read_text())
    assert "final/holdout_alt_mae" not in metrics  # the map: every altimeter point fitted
    assert metrics["verdict/siren_lambert/mae_mean"] == pytest.approx(
        verdict["methods"]["siren_lambert"]["mean"]
    )
    assert metrics["final/extrapolated_share"] == 0.0 and metrics["final/imaged_area_m2"] > 0
    assert "VERDICT:" in proc.stdout and "held-out altimeter, 2 folds" in proc.stdout
    assert "imaged area:" in proc.stdout
