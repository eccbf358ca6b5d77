"""What ``sss2bathy-map`` writes beside the map: uncertainty.tif (the verdict's fold maps,
the scale preset's calibrated factor), item.json (STAC) and report.html; every raster a COG."""

from __future__ import annotations

import csv
import json
import logging
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
from omegaconf import OmegaConf

from sss2bathy.cli.map import (
    check_map_config,
    uncertainty_scale,
    write_map_item,
    write_map_uncertainty,
)
from sss2bathy.eval.verdict import kfold_verdict
from sss2bathy.io.export import cog_layout, write_geotiff
from sss2bathy.io.stac import check_item
from sss2bathy.survey import BathyGrid
from tests.cli.test_map import _common as map_test_common
from tests.cli.test_map import _run as run_map_module

ROOT = Path(__file__).resolve().parents[2]
CONF = ROOT / "conf"
ORIGIN = {"crs": "EPSG:32633", "easting": 512300.0, "northing": 6402100.0}


def _map_cfg(**node):
    return OmegaConf.create(
        {
            "method": None,
            "cnn_checkpoint": None,
            "verdict": {"folds": 3},
            "mosaic": {"placement": "none"},
            "uncertainty": {
                "enabled": True,
                "scale": None,
                "calibrated": {"scale": {"demo": 4.97}, "detail": {"demo": 5.5}},
                **node,
            },
            "stac": True,
            "report": False,
        }
    )


def test_the_uncertainty_factor_is_the_scale_presets_calibration_or_the_users(caplog):
    assert uncertainty_scale(_map_cfg(), "demo") == 4.97
    assert uncertainty_scale(_map_cfg(scale=2), "demo") == 2.0
    assert uncertainty_scale(_map_cfg(enabled=False), "demo") is None
    with caplog.at_level(logging.WARNING, logger="sss2bathy.map"):
        assert uncertainty_scale(_map_cfg(), "paper") == 1.0
    assert "no factor for map_settings=scale, scale=paper" in caplog.text
    assert "raw jackknife" in caplog.text
    # the factor of the run's map settings: their fold maps spread differently
    detail = _map_cfg()
    detail.map_settings = "detail"
    assert uncertainty_scale(detail, "demo") == 5.5
    detail.map_settings = "survey"
    caplog.clear()
    with caplog.at_level(logging.WARNING, logger="sss2bathy.map"):
        assert uncertainty_scale(detail, "demo") == 1.0
    assert "no factor for map_settings=survey, scale=demo" in caplog.text
    for node, key in (
        ({"scale": 0}, "uncertainty.scale"),
        ({"calibrated": {"scale": {"tiny": -1}}}, "calibrated.scale.tiny"),
        ({"calibrated": {"demo": 4.97}}, "calibrated.demo: expected factors per scale preset"),
    ):
        with pytest.raises(ValueError, match=key):
            uncertainty_scale(_map_cfg(**node), "demo")


def test_conf_map_turns_the_outputs_on_with_the_studys_factors():
    """conf/map.yaml's calibrated factors are the calibration study's (its CSV)."""
    cfg = OmegaConf.load(CONF / "map.yaml")
    assert cfg.uncertainty.enabled and cfg.uncertainty.scale is None and cfg.stac and cfg.report
    study: dict = {}
    for path in sorted((ROOT / "docs/studies").glob("uncertainty_calibration*.csv")):
        for r in csv.DictReader(path.open()):
            study.setdefault(r["map_settings"], {})[r["scale"]] = round(float(r["c"]), 2)
    assert set(study) == {"scale", "detail"}  # the map settings calibrated
    assert OmegaConf.to_container(cfg.uncertainty.calibrated) == study
    check_map_config(OmegaConf.merge(_map_cfg(), {"uncertainty": cfg.uncertainty}))


def _run_folder(tmp_path):
    """A finished map run (the map, 3 fold maps of siren_lambert) without the fit."""
    run = tmp_path / "run"
    rng = np.random.default_rng(0)
    heights = rng.normal(-20, 0.2, (24, 32)).astype(np.float32)
    covered = np.zeros(heights.shape, bool)
    covered[4:20, 3:30] = True
    geom = {"x0": 0.25, "y0": 0.25, "cell_size": 0.5}
    for k in range(3):
        fold = run / "verdict" / "siren_lambert" / f"fold{k}"
        fold.mkdir(parents=True)
        np.savez(fold / "map.npz", heights=heights + rng.normal(0, 0.1, heights.shape), **geom)
    np.savez(run / "map.npz", heights=heights, coverage=covered, **geom)
    write_geotiff(BathyGrid(heights, 0.25, 0.25, 0.5), run / "map.tif", origin=ORIGIN, mask=covered)
    (run / "metrics.json").write_text("{}")
    return run


def test_map_outputs_from_a_finished_run(tmp_path, monkeypatch, caplog):
    run = _run_folder(tmp_path)
    line = SimpleNamespace(time_s=np.array([1.378847e9, 1.378848e9]))
    survey = SimpleNamespace(name="xtf_line", origin=ORIGIN, lines=[line])
    monkeypatch.setattr("sss2bathy.cli.map._survey_of", lambda train_cfg: survey)
    cfg = _map_cfg()
    verdict = kfold_verdict(
        {"siren_lambert": [0.1, 0.2, 0.15], "interpolation": [0.2, 0.2, 0.3]}, "siren_lambert"
    )
    # without the verdict's folds: no uncertainty, one line says why
    with caplog.at_level(logging.INFO, logger="sss2bathy.map"):
        assert write_map_uncertainty(cfg, None, run, None, "demo") == {}
    assert "verdict.folds >= 2" in caplog.text
    metrics = write_map_uncertainty(cfg, None, run, verdict, "demo")
    assert metrics["uncertainty/scale"] == 4.97 and metrics["uncertainty/folds"] == 3
    assert (run / "uncertainty.tif").is_file() and (run / "uncertainty.png").is_file()
    # a raster that is not a COG is named; the item describes what is there
    (run / "mosaic.tif").write_bytes((run / "map.tif").read_bytes())
    import rasterio

    with rasterio.open(run / "mosaic.tif", "r+", IGNORE_COG_LAYOUT_BREAK="YES") as dst:
        dst.update_tags(EDITED="1")
    with caplog.at_level(logging.WARNING, logger="sss2bathy.map"):
        path = write_map_item(cfg, None, run, verdict)
    assert "mosaic.tif: not a cloud-optimised GeoTIFF" in caplog.text
    assert "map.tif: not a cloud" not in caplog.text and "uncertainty.tif: not" not in caplog.text
    item = json.loads(path.read_text())
    assert check_item(item) == []
    assert {"map", "uncertainty", "mosaic", "metrics", "uncertainty_png"} <= set(item["assets"])
    assert item["properties"]["sss2bathy:verdict"] == verdict.outcome
    assert item["properties"]["sss2bathy:method"] == "siren_lambert"
    assert item["properties"]["start_datetime"].startswith("2013-09-10")
    cfg.stac = False
    (run / "item.json").unlink()
    assert write_map_item(cfg, None, run, verdict) is None and not (run / "item.json").exists()


# ------------------------------------------------------------------ slow: the whole command


@pytest.mark.slow
def test_sss2bathy_map_writes_uncertainty_stac_and_report(tmp_path):
    """A tiny XTF survey, verdict.folds=2: uncertainty.tif on map.tif's grid, every raster
    a COG, item.json, report.html, and the summary lists them."""
    import rasterio

    from sss2bathy.io.xtf import write_xtf
    from sss2bathy.sim import config as sim_config
    from sss2bathy.sim import generate
    from sss2bathy.utils.config import survey_preset

    cfg = OmegaConf.create(survey_preset("synthetic_d1", "tiny", CONF))
    cfg.name = "sim_tiny"
    survey, _ = generate.generate_survey(
        sim_config.SyntheticSurveyConfig.from_mapping(OmegaConf.to_container(cfg))
    )
    folder = tmp_path / "lines"
    for line in survey.split_lines("test"):
        write_xtf(line, folder / f"{line.name}.xtf", survey.origin)
    run = tmp_path / "run"
    args = [
        f"files={folder}",
        f"survey.crs={survey.origin['crs']}",
        "survey.n_bins=null",
        "verdict.folds=2",
        "verdict.overlap.enabled=false",
        "mosaic.resolution=0.25",
        f"hydra.run.dir={run}",
        *map_test_common(tmp_path),
        'overrides=["callbacks=none","trainer.enable_progress_bar=false"]',
    ]
    proc = run_map_module("sss2bathy.cli.map", args, tmp_path, timeout=900)
    assert proc.returncode == 0, proc.stderr[-3000:]
    for name in ("uncertainty.tif", "item.json", "report.html"):
        assert str(run / name) in proc.stdout, name
    assert "height uncertainty (uncertainty.tif): 1 sigma median" in proc.stdout
    assert "1.38 x the jackknife of the 2 fold fits" in proc.stdout  # tiny's factor
    with rasterio.open(run / "map.tif") as m, rasterio.open(run / "uncertainty.tif") as u:
        assert (u.transform, u.shape, u.crs) == (m.transform, m.shape, m.crs)
        sigma, heights = u.read(1), m.read(1)
    np.testing.assert_array_equal(np.isfinite(sigma), np.isfinite(heights))
    assert np.nanmin(sigma) >= 0 and np.nanmax(sigma) > 0
    for name in ("map.tif", "uncertainty.tif", "mosaic.tif"):
        assert cog_layout(run / name).problems() == [], name
    assert check_item(json.loads((run / "item.json").read_text())) == []
    page = (run / "report.html").read_text()
    assert "VERDICT:" in page and "data:image/png;base64," in page
