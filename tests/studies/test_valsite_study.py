"""The validation-site study reader: variants and settings from each run's config, maps
scored alike, and only on a validation site."""

from __future__ import annotations

import json

import numpy as np
import pytest
from omegaconf import OmegaConf

from sss2bathy.metrics.bathy import bathy_metrics
from sss2bathy.survey import BathyGrid, Survey
from studies.valsite_study import (
    checkpoint_label,
    main,
    run_settings,
    seed_means,
    study_table,
    to_csv,
)

SHAPE, CELL = (20, 30), 0.5
SITE = "synthetic_d1_valsite_tiny"


def _truth() -> BathyGrid:
    yy, xx = np.mgrid[0 : SHAPE[0], 0 : SHAPE[1]] * CELL
    return BathyGrid(-12.0 + 0.05 * xx - 0.03 * yy + 0.2 * np.sin(xx), 0.0, 0.0, CELL)


def _config(task: str, lr: float = 3e-4, line_offset: bool | None = False) -> dict:
    model = {} if line_offset is None else {"line_offset": line_offset}
    return {
        "task_name": task,
        "scale": {"siren": {"lr": lr, "gamma": 0.7, "max_epochs": 6}},
        "trainer": {"max_epochs": "${scale.siren.max_epochs}"},
        "model": model,
    }


def _run(root, name, data_dir, heights, region, config, survey=SITE, holdout=0.1) -> None:
    run = root / name
    (run / ".hydra").mkdir(parents=True)
    np.savez(run / "map.npz", heights=heights, x0=0.0, y0=0.0, cell_size=CELL, region=region)
    info = {"task_name": config["task_name"], "survey_name": survey, "data_dir": str(data_dir)}
    (run / "run_info.json").write_text(json.dumps(info))
    (run / "metrics.json").write_text(json.dumps({"final/holdout_alt_mae": holdout}))
    OmegaConf.save(OmegaConf.create(config), run / ".hydra" / "config.yaml")


@pytest.fixture()
def study(tmp_path):
    truth = _truth()
    data_dir = tmp_path / "data"
    Survey(SITE, [], truth, splits={"train": [], "test": []}).save(data_dir / SITE)
    root = tmp_path / "study"
    rng = np.random.default_rng(0)
    region = np.ones(SHAPE, bool)
    small = region.copy()
    small[:, :4] = False  # one run scored a smaller area: all are scored on the intersection
    maps = {
        "cnn_lr3e-3": (
            truth.heights + rng.normal(0, 0.4, SHAPE),
            region,
            _config("siren_cnn_n2d", 3e-3),
        ),
        "cnn_scale": (truth.heights + rng.normal(0, 0.2, SHAPE), small, _config("siren_cnn_n2d")),
        "cnn_offset": (truth.heights + 0.3, region, _config("siren_cnn_n2d", line_offset=True)),
        "lambert": (truth.heights - 0.5, region, _config("siren_lambert", line_offset=None)),
    }
    for k, (heights, reg, cfg) in maps.items():
        _run(root, k, data_dir, heights, reg, cfg, holdout=0.2 if k == "lambert" else 0.1)
    return root, truth, maps, small


def test_table_scores_every_run_on_the_common_cells_by_variant(study):
    root, truth, maps, common = study
    rows = study_table(root)
    assert [r["run"] for r in rows] == ["cnn_scale", "cnn_offset", "cnn_lr3e-3", "lambert"]
    for r in rows:
        expected = bathy_metrics(maps[r["run"]][0], truth.heights, CELL, common)
        for key in ("mae", "std", "grad_cs", "n_cells"):
            assert r[key] == pytest.approx(expected[key]), (r["run"], key)
    by_run = {r["run"]: r for r in rows}
    assert by_run["cnn_lr3e-3"]["lr"] == 3e-3 and by_run["cnn_scale"]["epochs"] == 6
    assert by_run["cnn_offset"]["line_offset"] is True
    assert by_run["lambert"]["line_offset"] is False  # a model without the key: off
    assert by_run["lambert"]["holdout_alt_mae"] == 0.2
    assert (
        to_csv(rows)
        .splitlines()[0]
        .startswith("variant,lr,gamma,epochs,line_offset,w_height,cnn,seed,mae")
    )
    assert by_run["lambert"]["cnn"] == "-" and by_run["lambert"]["seed"] == "-"


def test_main_writes_markdown_and_csv(study, capsys):
    root, *_ = study
    assert main([str(root)]) == 0
    md = (root / "valsite_study.md").read_text()
    assert "\n| siren_cnn_n2d | 0.0003 | 0.7 | 6 | False |" in md  # the best CNN row first
    assert len((root / "valsite_study.csv").read_text().splitlines()) == 5
    assert "written:" in capsys.readouterr().out


def test_runs_off_a_validation_site_are_refused(tmp_path, study):
    root, truth, _, _ = study
    other = tmp_path / "other"
    _run(other, "a", tmp_path / "data", truth.heights, np.ones(SHAPE, bool),
         _config("siren_cnn_n2d"), survey="synthetic_d1_tiny")  # fmt: skip
    with pytest.raises(ValueError, match="expected a validation site.*synthetic_d1_tiny"):
        study_table(other)
    _run(root, "leak", tmp_path / "data", truth.heights, np.ones(SHAPE, bool),
         _config("siren_cnn_n2d"), survey="synthetic_d1_tiny")  # fmt: skip
    with pytest.raises(ValueError, match="expected runs of one survey"):
        study_table(root)


def test_missing_setting_and_empty_folder_are_clear_errors(tmp_path):
    cfg = _config("siren_gt_n2d")
    del cfg["scale"]["siren"]["lr"]
    with pytest.raises(ValueError, match="scale.siren.lr: expected a value"):
        run_settings(cfg)
    (tmp_path / "empty").mkdir()
    with pytest.raises(FileNotFoundError, match="expected finished SIREN runs"):
        study_table(tmp_path / "empty")


def test_seed_means_compare_cnns_by_their_maps_against_gt(tmp_path):
    truth = _truth()
    data_dir = tmp_path / "data"
    Survey(SITE, [], truth, splits={"train": [], "test": []}).save(data_dir / SITE)
    root = tmp_path / "seeds"
    region = np.ones(SHAPE, bool)
    offsets = {"gt": 0.1, "a": 0.2, "b": 0.4}
    for label, off in offsets.items():
        for seed, sign in ((42, 1.0), (43, 1.5)):
            cfg = _config("siren_gt_n2d" if label == "gt" else "siren_cnn_n2d")
            cfg["seed"] = seed
            if label != "gt":
                cfg["data"] = {"normals": {"checkpoint": f"/x/runs/{label}/checkpoints/last.ckpt"}}
            _run(root, f"{label}_{seed}", data_dir, truth.heights + sign * off, region, cfg)
    rows = study_table(root)
    assert {r["cnn"] for r in rows} == {"-", "a/last.ckpt", "b/last.ckpt"}
    means = {r["cnn"]: r for r in seed_means(rows)}
    assert means["a/last.ckpt"]["seeds"] == [42, 43]
    assert means["a/last.ckpt"]["maes"] == pytest.approx([0.2, 0.3])
    assert means["a/last.ckpt"]["mae"] == pytest.approx(0.25)
    assert means["a/last.ckpt"]["mae_ratio"] == pytest.approx(2.0)
    assert means["b/last.ckpt"]["mae_ratio"] == pytest.approx(4.0)
    assert means["-"]["mae_ratio"] == pytest.approx(1.0)
    assert main([str(root)]) == 0
    md = (root / "valsite_study.md").read_text()
    assert "## Mean over seeds" in md and "| 0.200 / 0.300 | 0.250 |" in md


def test_each_method_is_compared_at_its_own_best_altimeter_weight(tmp_path):
    """Ratios to SIREN-GT-N2d at the same weight (an override's ``1`` is a config's ``1.0``)
    and to GT-N2d's best weight: the comparison with each method's setting chosen."""
    truth = _truth()
    data_dir = tmp_path / "data"
    Survey(SITE, [], truth, splits={"train": [], "test": []}).save(data_dir / SITE)
    root = tmp_path / "weights"
    region = np.ones(SHAPE, bool)
    fits = {("siren_gt_n2d", 1.0): 0.2, ("siren_gt_n2d", 0.1): 0.1, ("siren_cnn_n2d", 1): 0.3}
    for (task, w), off in fits.items():
        for seed in (42, 43):
            cfg = _config(task)
            cfg["model"]["w_height"] = w
            cfg["seed"] = seed
            _run(root, f"{task}_{w}_{seed}", data_dir, truth.heights + off, region, cfg)
    means = {(r["variant"], float(r["w_height"])): r for r in seed_means(study_table(root))}
    cnn = means[("siren_cnn_n2d", 1.0)]
    assert cnn["mae_ratio"] == pytest.approx(1.5, rel=1e-4)  # against GT-N2d at the same weight
    assert cnn["best_mae_ratio"] == pytest.approx(3.0, rel=1e-4)  # against GT-N2d at its best, 0.1
    assert means[("siren_gt_n2d", 0.1)]["best_mae_ratio"] == pytest.approx(1.0)
    assert main([str(root)]) == 0
    assert "| 1.50 | 1.000 | 3.00 | 1.000 |" in (root / "valsite_study.md").read_text()


def test_checkpoint_labels():
    assert checkpoint_label("pretrained") == "pretrained"
    assert checkpoint_label("outputs/runs/x/ft/checkpoints/last.ckpt") == "ft/last.ckpt"
    assert checkpoint_label("/tmp/model.safetensors") == "model.safetensors"
