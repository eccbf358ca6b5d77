"""Which CNN sss2bathy-map and sss2bathy-train use: a .ckpt, an exported .safetensors,
``pretrained`` and, for method=siren_cnn_n2d without a checkpoint, the shipped model."""

from __future__ import annotations

import json
import logging
import shutil
from pathlib import Path
from types import SimpleNamespace

import pytest
from hydra import compose, initialize_config_dir
from omegaconf import OmegaConf

from sss2bathy.callbacks.writers import cnn_checkpoint_of
from sss2bathy.cli.map import (
    compose_train_config,
    log_cnn_choice,
    map_cnn_checkpoint,
    map_experiment,
)
from sss2bathy.cli.train import check_checkpoints
from sss2bathy.data import cnn_normals
from sss2bathy.data.normal_source import NormalSource

ROOT = Path(__file__).resolve().parents[2]


def _ship(exported: Path, folder: Path) -> Path:
    """The exported model copied into ``folder`` as the package's ``normal_cnn``."""
    folder.mkdir(parents=True, exist_ok=True)
    meta = json.loads(exported.with_suffix(".json").read_text())
    meta["weights"]["file"] = "normal_cnn.safetensors"
    shutil.copy(exported, folder / "normal_cnn.safetensors")
    (folder / "normal_cnn.json").write_text(json.dumps(meta))
    return folder / "normal_cnn.safetensors"


def _map_cfg(tmp_path: Path):
    """The composed sss2bathy-map config of method=siren_cnn_n2d without a checkpoint."""
    return compose(
        "map",
        overrides=[
            f"files={tmp_path / 'lines'}",
            "method=siren_cnn_n2d",
            "scale=tiny",
            "map_settings=scale",  # the other settings read the files' navigation: none here
            f"paths.output_dir={tmp_path / 'out'}",
            f"paths.data_dir={tmp_path / 'data'}",
        ],
    )


def _cfg(**kw) -> dict:
    return {"method": None, "cnn_checkpoint": None, **kw}


def test_the_map_route_picks_its_cnn(tiny_run, exported, tmp_path, monkeypatch, caplog):
    ckpt, _ = tiny_run
    shipped = _ship(exported, tmp_path / "pkg")
    monkeypatch.setattr(cnn_normals, "PRETRAINED_DIR", tmp_path / "pkg")
    # method=siren_cnn_n2d without a checkpoint: the shipped model
    cfg = _cfg(method="siren_cnn_n2d")
    assert map_cnn_checkpoint(cfg) == str(shipped.resolve())
    with caplog.at_level(logging.INFO, logger="sss2bathy.map"):
        log_cnn_choice(cfg)
    assert [r.getMessage() for r in caplog.records] == [
        f"cnn_checkpoint: none given: the CNN shipped in the package, {shipped}"
    ]
    # method=null stays SIREN-Lambert, and says the shipped CNN is one override away
    assert map_experiment(_cfg()) == "siren_lambert" and map_cnn_checkpoint(_cfg()) is None
    caplog.clear()
    with caplog.at_level(logging.INFO, logger="sss2bathy.map"):
        log_cnn_choice(_cfg())
    assert "method=siren_cnn_n2d uses the shipped pretrained CNN" in caplog.records[0].getMessage()
    # pretrained, a .ckpt and a .safetensors: SIREN-CNN-N2d with that file
    for given, expected in (("pretrained", shipped), (ckpt, ckpt), (exported, exported)):
        cfg = _cfg(cnn_checkpoint=str(given))
        assert map_experiment(cfg) == "siren_cnn_n2d"
        assert map_cnn_checkpoint(cfg) == str(Path(expected).resolve())
    with pytest.raises(ValueError, match="cnn_checkpoint: expected a CNN checkpoint file"):
        map_cnn_checkpoint(_cfg(cnn_checkpoint=str(tmp_path / "nope.safetensors")))
    # siren_heights_only never takes the shipped CNN
    assert map_cnn_checkpoint(_cfg(method="siren_heights_only")) is None


def test_without_a_shipped_model_the_map_route_says_so(tmp_path, monkeypatch, caplog):
    monkeypatch.setattr(cnn_normals, "PRETRAINED_DIR", tmp_path / "empty")
    assert map_cnn_checkpoint(_cfg(method="siren_cnn_n2d")) is None
    with pytest.raises(ValueError, match="cnn_checkpoint: expected 'pretrained' to name the CNN"):
        map_cnn_checkpoint(_cfg(cnn_checkpoint="pretrained"))
    with caplog.at_level(logging.INFO, logger="sss2bathy.map"):
        log_cnn_choice(_cfg())
    assert caplog.records[0].getMessage() == (
        "method: null = siren_lambert (no cnn_checkpoint; this install ships no pretrained CNN)"
    )
    with initialize_config_dir(config_dir=str(ROOT / "conf"), version_base="1.3"):
        cfg = _map_cfg(tmp_path)
        with pytest.raises(ValueError, match="found none \\(and this install ships no pretrained"):
            compose_train_config(cfg, tmp_path / "run", {"scale": "tiny"})


def test_the_fit_reads_the_shipped_model_before_any_data(exported, tmp_path, monkeypatch):
    shipped = _ship(exported, tmp_path / "pkg")
    monkeypatch.setattr(cnn_normals, "PRETRAINED_DIR", tmp_path / "pkg")
    with initialize_config_dir(config_dir=str(ROOT / "conf"), version_base="1.3"):
        cfg = _map_cfg(tmp_path)
        train_cfg = compose_train_config(cfg, tmp_path / "run", {"scale": "tiny"})
    assert train_cfg.data.normals.source == "cnn"
    assert train_cfg.data.normals.checkpoint == str(shipped.resolve())
    check_checkpoints(train_cfg, None, None)  # the exported model reads as a CNN
    for given in ("pretrained", str(exported)):
        check_checkpoints(
            OmegaConf.create({"data": {"normals": {"source": "cnn", "checkpoint": given}}}),
            None,
            None,
        )
    meta = json.loads(shipped.with_suffix(".json").read_text())
    meta["windows"]["overlap"] = 2
    shipped.with_suffix(".json").write_text(json.dumps(meta))
    with pytest.raises(
        ValueError, match=r"data.normals.checkpoint: .*normal_cnn.json: windows.overlap"
    ):
        check_checkpoints(train_cfg, None, None)


@pytest.mark.parametrize("experiment", ["siren_cnn_n2d", "d2_siren_cnn_n2d", "d3_siren_cnn_n2d"])
def test_the_pretrained_experiments_take_the_shipped_cnn(
    exported, tmp_path, monkeypatch, experiment
):
    _ship(exported, tmp_path / "pkg")
    monkeypatch.setattr(cnn_normals, "PRETRAINED_DIR", tmp_path / "pkg")
    with initialize_config_dir(config_dir=str(ROOT / "conf"), version_base="1.3"):
        base = compose("train", overrides=[f"experiment={experiment}", "scale=tiny"])
        cfg = compose("train", overrides=[f"experiment={experiment}_pretrained", "scale=tiny"])
    assert cfg.data.normals.checkpoint == "pretrained" and cfg.data.normals.source == "cnn"
    assert cfg.task_name == f"{experiment}_pretrained"
    # everything else is the experiment's own (its survey, splits, SIREN)
    assert cfg.data.survey.name == base.data.survey.name
    assert cfg.data.sidescan_split == base.data.sidescan_split
    assert cfg.model.siren == base.model.siren
    check_checkpoints(cfg, None, None)
    # the map's provenance names the shipped file (its SHA-256 goes into map.tif)
    dm = SimpleNamespace(normals=NormalSource("cnn", checkpoint="pretrained"))
    assert cnn_checkpoint_of(dm) == tmp_path / "pkg" / "normal_cnn.safetensors"
