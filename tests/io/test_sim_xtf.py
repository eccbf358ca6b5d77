"""The simulator's tiny survey through XTF: export, re-import, and the bottom detector on it."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from omegaconf import OmegaConf

from sss2bathy.io.bottom import detect_first_return
from sss2bathy.io.xtf import write_xtf
from sss2bathy.io.xtf_survey import prepare_xtf_survey
from sss2bathy.survey import Survey

CONF = Path(__file__).resolve().parents[2] / "conf"


@pytest.fixture(scope="module")
def sim_survey():
    generate = pytest.importorskip("sss2bathy.sim.generate")
    sim_config = pytest.importorskip("sss2bathy.sim.config")
    from sss2bathy.utils.config import survey_preset

    cfg = OmegaConf.create(survey_preset("synthetic_d1", "tiny", CONF))
    cfg.name = "sim_tiny"
    config = sim_config.SyntheticSurveyConfig.from_mapping(OmegaConf.to_container(cfg))
    survey, _ = generate.generate_survey(config)
    return survey


def test_detector_on_simulated_survey(sim_survey):
    # The simulator's first echo is the nearest seabed (<= the vertical altitude on slopes
    # and boulders): most pings within 2 bins of the altitude, none far off.
    errors = []
    for line in sim_survey.lines:
        dr = float(line.range_m[1] - line.range_m[0])
        est = detect_first_return(line.intensity.mean(axis=1), line.range_m).altitude_m
        errors.append((est - line.altitude_m) / dr)
    err = np.abs(np.concatenate(errors))
    assert np.mean(err <= 2.0) >= 0.9
    assert np.median(err) <= 1.5 and err.max() <= 5.0


def test_simulated_survey_round_trips_through_xtf(tmp_path, sim_survey):
    origin = sim_survey.origin
    for line in sim_survey.lines:
        write_xtf(line, tmp_path / "xtf" / f"{line.name}.xtf", origin)
    cfg = {
        "kind": "xtf",
        "name": "sim_from_xtf",
        "files": str(tmp_path / "xtf"),
        "n_bins": None,
        # The simulator's frame (UTM 33N at 680 km east) lies in zone 34 by longitude: keep it.
        "crs": origin["crs"],
        "splits": {k: list(v) for k, v in sim_survey.splits.items()},
    }
    survey = Survey.load(prepare_xtf_survey(cfg, tmp_path / "data"))
    assert survey.splits == sim_survey.splits
    assert survey.origin["crs"] == origin["crs"]
    shift = np.array(
        [
            survey.origin["easting"] - origin["easting"],
            survey.origin["northing"] - origin["northing"],
            0.0,
        ]
    )
    sensor = sim_survey.lines[0].sensor
    assert survey.lines[0].sensor.tilt_rad == pytest.approx(sensor.tilt_rad, abs=1e-6)
    assert survey.lines[0].sensor.beam_width_rad == pytest.approx(sensor.beam_width_rad, abs=1e-6)
    for got, want in zip(survey.lines, sim_survey.lines, strict=True):
        assert got.intensity.shape == want.intensity.shape
        scale = want.intensity.max(axis=(0, 2))[None, :, None] / 65535
        assert np.all(np.abs(got.intensity - want.intensity) <= 0.51 * scale + 1e-6)
        assert np.abs(got.position + shift - want.position).max() < 1e-3
        np.testing.assert_allclose(got.range_m, want.range_m, atol=1e-4)
        ok = np.isfinite(want.altitude_m)
        np.testing.assert_allclose(got.altitude_m[ok], want.altitude_m[ok], atol=1e-4)
        np.testing.assert_allclose(got.rotation, want.rotation, atol=1e-6)


def test_siren_lambert_end_to_end_from_xtf(tmp_path, sim_survey):
    """XTF files written by the test -> data/survey=xtf -> SIREN-Lambert fit -> a map."""
    from hydra import compose, initialize_config_dir

    from sss2bathy.cli.train import train
    from sss2bathy.survey import BathyGrid

    for line in sim_survey.split_lines("test"):
        write_xtf(line, tmp_path / "xtf" / f"{line.name}.xtf", sim_survey.origin)
    out = tmp_path / "run"
    overrides = [
        "experiment=siren_lambert",
        "scale=tiny",
        "data/survey=xtf",
        f"data.survey.files={tmp_path / 'xtf'}",
        "data.survey.name=xtf_e2e",
        "data.survey.n_bins=null",
        f"data.survey.crs={sim_survey.origin['crs']}",
        f"paths.data_dir={tmp_path / 'data'}",
        f"paths.output_dir={tmp_path / 'outputs'}",
        f"model.output_dir={out}",
        "logger=none",
        "callbacks=none",
        "trainer.max_epochs=1",
        "trainer.enable_progress_bar=false",
        "torch_threads=1",
    ]
    with initialize_config_dir(str(CONF), version_base="1.3"):
        cfg = compose("train", overrides=overrides)
    metrics = train(cfg, run_dir=out)
    assert np.isfinite(float(metrics["train/loss"]))
    # no MBES grid: the map covers the tracks' bounds, heights near the altimeter depths
    grid = BathyGrid.load_geotiff(out / "map.tif")
    depths = np.concatenate([ln.altimeter_points()[:, 2] for ln in sim_survey.lines])
    finite = grid.heights[np.isfinite(grid.heights)]
    assert finite.size > 100
    assert depths.min() - 5 < np.median(finite) < depths.max() + 5
    assert (out / "metrics.json").is_file()
    # georeferenced: the survey's CRS, a navigation fix (local + origin) on a covered cell,
    # no-data far from the tracks
    import rasterio
    from pyproj import CRS

    with rasterio.open(out / "map.tif") as src:
        assert CRS.from_user_input(src.crs) == CRS.from_user_input(sim_survey.origin["crs"])
        assert src.nodata is not None and np.isnan(src.nodata)
        line = sim_survey.split_lines("test")[0]
        px, py = line.position[len(line.position) // 2, :2]
        e, n = sim_survey.origin["easting"], sim_survey.origin["northing"]
        row, col = src.index(px + e, py + n)
        data = src.read(1)
        assert np.isfinite(data[row, col]) and np.isnan(data).any()
