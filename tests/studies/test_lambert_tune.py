"""The lambert_tune sweep reader: settings from each run's config, maps scored alike."""

from __future__ import annotations

import json

import numpy as np
import pytest
from omegaconf import OmegaConf

from sss2bathy.metrics.bathy import bathy_metrics
from sss2bathy.survey import BathyGrid, Survey
from studies.lambert_tune import find_runs, main, run_settings, to_csv, tune_table

SHAPE, CELL = (20, 30), 0.5


def _truth() -> BathyGrid:
    yy, xx = np.mgrid[0 : SHAPE[0], 0 : SHAPE[1]] * CELL
    return BathyGrid(-12.0 + 0.05 * xx - 0.03 * yy + 0.2 * np.sin(xx), 0.0, 0.0, CELL)


def _config(split: str = "train", **sensor) -> dict:
    base = dict(q=2.0, intensity_kind="amplitude", reflectivity="constant", field_lr=1e-3,
                field_weight=0.01, shadow_threshold=0.3, near_range_cut_m=0.0)  # fmt: skip
    return {
        "task_name": "lambert_tune",
        "data": {"sidescan_split": split, "altimeter_split": "train"},
        "model": {"sensor_lr": 0.01, "sensor": {**base, **sensor}},
    }


def _run(root, name, data_dir, heights, region, config) -> None:
    run = root / name
    (run / ".hydra").mkdir(parents=True)
    np.savez(run / "map.npz", heights=heights, x0=0.0, y0=0.0, cell_size=CELL, region=region)
    info = {"task_name": "lambert_tune", "survey_name": "tiny", "data_dir": str(data_dir)}
    (run / "run_info.json").write_text(json.dumps(info))
    (run / "metrics.json").write_text(json.dumps({"final/mae": 0.0}))
    OmegaConf.save(OmegaConf.create(config), run / ".hydra" / "config.yaml")


@pytest.fixture()
def sweep(tmp_path):
    truth = _truth()
    data_dir = tmp_path / "data"
    Survey("tiny", [], truth, splits={"train": [], "test": []}).save(data_dir / "tiny")
    root = tmp_path / "sweep"
    rng = np.random.default_rng(0)
    region = np.ones(SHAPE, bool)
    small = region.copy()
    small[:, :5] = False  # one run scored a smaller area: all are scored on the intersection
    maps = {
        "grid/0": (truth.heights + rng.normal(0, 0.3, SHAPE), region, _config(q=1.0)),
        "grid/1": (truth.heights + rng.normal(0, 0.1, SHAPE), small, _config(q=2.0)),
        "field/0": (
            truth.heights + 0.5,
            region,
            _config(reflectivity="field", field_lr=1e-2, shadow_threshold=0.0),
        ),
    }
    for name, (heights, reg, cfg) in maps.items():
        _run(root, name, data_dir, heights, reg, cfg)
    return root, truth, maps, small


def test_table_scores_every_run_on_the_common_cells_best_first(sweep):
    root, truth, maps, common = sweep
    rows = tune_table(root)
    assert [r["run"] for r in rows] == ["grid/1", "grid/0", "field/0"]
    for r in rows:
        expected = bathy_metrics(maps[r["run"]][0], truth.heights, CELL, common)
        for key in ("mae", "std", "grad_cs", "n_cells"):
            assert r[key] == pytest.approx(expected[key]), (r["run"], key)
    assert rows[0]["n_cells"] == int(common.sum()) == 20 * 25
    by_run = {r["run"]: r for r in rows}
    assert by_run["grid/0"]["q"] == 1.0 and by_run["grid/0"]["field_lr"] == "-"
    assert by_run["field/0"]["field_lr"] == 0.01 and by_run["field/0"]["shadow_threshold"] == 0.0
    assert to_csv(rows).splitlines()[0].startswith("q,intensity_kind,reflectivity,field_lr")


def test_main_writes_markdown_and_csv(sweep, tmp_path, capsys):
    root, *_ = sweep
    assert main([str(root), "--out", str(tmp_path / "table")]) == 0
    md = (tmp_path / "table" / "lambert_tune.md").read_text()
    assert "\n| 2 | amplitude | constant | - | - | 0.01 | 0.3 | 0 | 0.0" in md  # best row first
    lines = (tmp_path / "table" / "lambert_tune.csv").read_text().splitlines()
    assert len(lines) == 4 and lines[1].endswith(",grid/1")
    assert "written:" in capsys.readouterr().out


def test_runs_on_test_lines_are_refused(sweep):
    root, truth, _, _ = sweep
    data_dir = root.parent / "data"
    _run(root, "leak/0", data_dir, truth.heights, np.ones(SHAPE, bool), _config(split="test"))
    with pytest.raises(ValueError, match="data.sidescan_split: expected 'train'.*found 'test'"):
        tune_table(root)


def test_missing_setting_and_empty_folder_are_clear_errors(tmp_path):
    cfg = _config()
    del cfg["model"]["sensor"]["q"]
    with pytest.raises(ValueError, match="model.sensor.q: expected a value"):
        run_settings(cfg)
    with pytest.raises(FileNotFoundError, match="expected a folder"):
        find_runs(tmp_path / "nowhere")
    (tmp_path / "empty").mkdir()
    with pytest.raises(FileNotFoundError, match="expected finished lambert_tune runs"):
        tune_table(tmp_path / "empty")
