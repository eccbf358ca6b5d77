"""The data/survey=xtf source: XTF files (+ MBES grid) -> a cached survey folder that loads."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
import yaml
from omegaconf import OmegaConf

from sss2bathy.data.sources import load_survey
from sss2bathy.io.xtf import write_xtf
from sss2bathy.io.xtf_survey import prepare_xtf_survey, resolve_splits
from sss2bathy.survey import BathyGrid, Survey

CONF = Path(__file__).resolve().parents[2] / "conf" / "data" / "survey" / "xtf.yaml"


@pytest.fixture
def xtf_folder(tmp_path, make_line, origin):
    folder = tmp_path / "raw"
    lines = [
        make_line(f"L{i}", n_pings=40, n_bins=64, seed=i, heading_deg=70 + 20 * i) for i in range(3)
    ]
    for ln in lines:
        write_xtf(ln, folder / f"{ln.name}.xtf", origin)
    return folder, lines


def mbes_grid(path: Path, origin: dict) -> BathyGrid:
    """A flat MBES grid over the lines, in projected coordinates, saved to ``path``."""
    g = BathyGrid(
        np.full((120, 200), -24.0),
        origin["easting"] + 60.0,
        origin["northing"] - 100.0,
        1.0,
        origin["crs"],
    )
    g.save_geotiff(path)
    return g


def config(files, **over):
    cfg = OmegaConf.load(CONF)
    cfg.files = str(files)
    cfg.n_bins = 32
    for k, v in over.items():
        cfg[k] = v
    return cfg


def test_yaml_lists_every_key_and_requires_files():
    cfg = OmegaConf.load(CONF)
    assert cfg.kind == "xtf" and OmegaConf.is_missing(cfg, "files")
    with pytest.raises(ValueError, match="files"):
        prepare_xtf_survey(cfg, "/tmp/unused")


def test_prepare_builds_a_survey_that_loads(tmp_path, xtf_folder, origin):
    folder, lines = xtf_folder
    mbes_grid(tmp_path / "mbes.tif", origin)
    cfg = config(
        folder,
        name="demo_xtf",
        mbes_grid=str(tmp_path / "mbes.tif"),
        splits={"train": ["L0", "L1"], "test": ["L2*"]},
    )
    out = prepare_xtf_survey(cfg, tmp_path / "data")
    assert out == tmp_path / "data" / "demo_xtf"
    survey = Survey.load(out)
    assert [ln.name for ln in survey.lines] == ["L0", "L1", "L2"]
    assert survey.splits == {"train": ["L0", "L1"], "test": ["L2"]}
    assert survey.origin["crs"] == "EPSG:32633"
    for got, want in zip(survey.lines, lines, strict=True):
        assert got.intensity.shape == (40, 2, 32) and got.n_bins == 32
        assert np.all(np.isfinite(got.altitude_m)) and np.all(np.isfinite(got.intensity))
        assert got.extras["first_return_m"].shape == (40,)
        # One frame for every line: positions agree with the written ones up to the origin shift.
        shift = np.array(
            [
                survey.origin["easting"] - origin["easting"],
                survey.origin["northing"] - origin["northing"],
                0.0,
            ]
        )
        assert np.abs(got.position + shift - want.position).max() < 1e-3
    assert survey.lines[0].sensor.tilt_rad == pytest.approx(math.radians(20.0), abs=1e-6)
    # The MBES grid is in the survey's local frame.
    g = survey.grid
    assert g is not None and g.crs == "EPSG:32633"
    assert g.x0 == pytest.approx(origin["easting"] + 60.0 - survey.origin["easting"])
    assert np.nanmax(np.abs(g.heights + 24.0)) == 0.0
    pos = survey.lines[0].position
    assert np.all(np.isfinite(g.sample(pos[:, 0], pos[:, 1])))
    meta = survey.metadata
    assert meta["source"] == "xtf" and set(meta["import_stats"]) >= {"L0", "L1", "L2"}
    assert meta["import_stats"]["_mbes_grid"]["pings_over_grid"] == 1.0
    assert len(survey.altimeter("train").xyz) == 80


def test_cache_reused_until_inputs_change(tmp_path, xtf_folder):
    folder, _ = xtf_folder
    data = tmp_path / "data"
    cfg = config(folder)
    out = prepare_xtf_survey(cfg, data)
    manifest = out / "survey.yaml"
    stamp = manifest.stat().st_mtime_ns
    h1 = yaml.safe_load(manifest.read_text())["metadata"]["source_hash"]
    assert prepare_xtf_survey(cfg, data) == out and manifest.stat().st_mtime_ns == stamp
    (out / "draped").mkdir()  # a downstream cache inside the survey folder
    # A changed file rebuilds (and drops the stale downstream caches).
    raw = (folder / "L1.xtf").read_bytes()
    (folder / "L1.xtf").write_bytes(raw[:-100])
    prepare_xtf_survey(cfg, data)
    h2 = yaml.safe_load(manifest.read_text())["metadata"]["source_hash"]
    assert h2 != h1 and not (out / "draped").exists()
    assert Survey.load(out).line("L1").n_pings == 39  # the truncated ping was skipped
    # A changed config rebuilds too; force rebuilds regardless.
    prepare_xtf_survey(config(folder, n_bins=16), data)
    assert Survey.load(out).lines[0].n_bins == 16
    stamp = manifest.stat().st_mtime_ns
    prepare_xtf_survey(config(folder, n_bins=16), data, force=True)
    assert manifest.stat().st_mtime_ns != stamp
    assert not [p for p in data.iterdir() if p.name.startswith(".")]  # no temporaries left


def test_a_reused_import_repeats_its_stored_warnings_once_per_process(tmp_path, xtf_folder, caplog):
    import logging

    from sss2bathy.io import xtf_survey

    folder, _ = xtf_folder
    data = tmp_path / "data"
    cfg = config(folder, n_bins=16)  # resampled: the reader warns (from N to 16 bins)
    with caplog.at_level(logging.INFO):
        out = prepare_xtf_survey(cfg, data)
    live = [r.getMessage() for r in caplog.records if r.levelno >= logging.WARNING]
    assert any("resampled to 16 bins" in m for m in live)
    stored = yaml.safe_load((out / "survey.yaml").read_text())["metadata"]["import_warnings"]
    assert stored == live  # every WARNING of the import, word for word
    # the same process (a K-fold run's fold fits): nothing repeated
    caplog.clear()
    with caplog.at_level(logging.INFO):
        prepare_xtf_survey(cfg, data)
    assert not [r for r in caplog.records if r.levelno >= logging.WARNING]
    # a new process (the next run on the cached survey): each stored warning again, once
    xtf_survey._SHOWN.clear()
    caplog.clear()
    with caplog.at_level(logging.INFO):
        prepare_xtf_survey(cfg, data)
        prepare_xtf_survey(cfg, data)
    again = [r.getMessage() for r in caplog.records if r.levelno >= logging.WARNING]
    assert again == [f"survey '{out.name}' (stored import): {m}" for m in stored]


def test_glob_files_and_default_split_through_load_survey(tmp_path, xtf_folder):
    folder, _ = xtf_folder
    cfg = config(folder / "L[01].xtf", name="globbed")
    survey, out = load_survey(cfg, tmp_path / "data")
    assert [ln.name for ln in survey.lines] == ["L0", "L1"]
    assert survey.splits == {"test": ["L0", "L1"]} and survey.grid is None
    assert out.name == "globbed"


def test_config_errors_are_named(tmp_path, xtf_folder, origin):
    folder, _ = xtf_folder
    with pytest.raises(ValueError, match="files.*found none"):
        prepare_xtf_survey(config(tmp_path / "empty*.xtf"), tmp_path / "data")
    with pytest.raises(ValueError, match="splits.train.*'Z\\*' matching none"):
        prepare_xtf_survey(config(folder, splits={"train": ["Z*"]}), tmp_path / "data")
    with pytest.raises(ValueError, match="n_bins"):
        prepare_xtf_survey(config(folder, n_bins=1), tmp_path / "data")
    with pytest.raises(ValueError, match="mbes_grid"):
        prepare_xtf_survey(config(folder, mbes_grid=str(tmp_path / "x.tif")), tmp_path / "data")
    other = {"crs": "EPSG:32632", "easting": 900000.0, "northing": 6500000.0}
    mbes_grid(tmp_path / "mbes32.tif", other)
    with pytest.raises(ValueError, match=r"mbes32\.tif.*crs.*UTM zone 33N.*UTM zone 32N"):
        prepare_xtf_survey(
            config(folder, mbes_grid=str(tmp_path / "mbes32.tif"), mbes_crs_mismatch="error"),
            tmp_path / "data",
        )


def test_resolve_splits_patterns_keep_survey_order():
    names = ["a1", "a2", "b1"]
    assert resolve_splits({"x": ["b*", "a1"], "y": "a*"}, names) == {
        "x": ["a1", "b1"],
        "y": ["a1", "a2"],
    }
    assert resolve_splits(None, names) == {"test": names}


def test_files_of_two_sonar_settings_are_refused(tmp_path, make_line, origin):
    folder = tmp_path / "raw"
    write_xtf(make_line("A", n_pings=40, n_bins=64), folder / "A.xtf", origin)
    write_xtf(make_line("B", n_pings=40, n_bins=128, seed=1), folder / "B.xtf", origin)
    with pytest.raises(ValueError) as err:
        prepare_xtf_survey(config(folder), tmp_path / "data")
    msg = str(err.value)
    assert "\n" not in msg and msg.startswith("data.survey.files: expected one sonar setting")
    assert "A.xtf {'frequency_khz': 400.0, 'range_m': 40.0, 'samples_per_side': 64}" in msg
    assert "B.xtf {'frequency_khz': 400.0, 'range_m': 40.0, 'samples_per_side': 128}" in msg
    assert "differing samples_per_side" in msg and "separate surveys" in msg
