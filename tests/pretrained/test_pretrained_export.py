"""A trained CNN exported as safetensors + JSON: the same network and the same predictions,
validated on load (one line per problem), and the export command's errors."""

from __future__ import annotations

import json
import logging
import shutil
from pathlib import Path

import numpy as np
import pytest
import torch
from safetensors import safe_open

import sss2bathy
from sss2bathy.data import cnn_normals
from sss2bathy.data.cnn_model_file import read_model_weights, sha256
from sss2bathy.data.cnn_normals import (
    check_cnn_model,
    checkpoint_input_spec,
    checkpoint_window_config,
    load_normal_net,
    predict_normals,
    resolve_cnn_checkpoint,
    warn_sonar_outside,
)
from sss2bathy.pretrained import main, model_overrides
from sss2bathy.survey import SensorParams, Survey


def _copy(weights: Path, folder: Path, name: str = "m") -> Path:
    folder.mkdir(parents=True, exist_ok=True)
    meta = json.loads(weights.with_suffix(".json").read_text())
    meta["weights"]["file"] = f"{name}.safetensors"
    shutil.copy(weights, folder / f"{name}.safetensors")
    (folder / f"{name}.json").write_text(json.dumps(meta))
    return folder / f"{name}.safetensors"


def test_export_records_what_inference_and_the_card_need(tiny_run, exported):
    ckpt, _ = tiny_run
    meta = json.loads(exported.with_suffix(".json").read_text())
    assert meta["format"] == "sss2bathy-normal-cnn" and meta["name"] == "tiny"
    assert meta["weights"]["sha256"] == sha256(exported) and len(meta["weights"]["sha256"]) == 64
    assert meta["network"]["_target_"] == "sss2bathy.models.normal_cnn.NormalResNet"
    assert meta["network"]["base_width"] == 2 and meta["input_channels"] == ["intensity"]
    assert meta["windows"] == {
        "window_pings": 16, "window_bins": 32, "overlap": 0.75, "batch_size": 8,
        "overlap_bins": None,
    }  # fmt: skip
    settings = meta["sonar_envelope"]["settings"]
    assert settings["frequency_hz"] == [850e3, 850e3] and settings["max_range_m"] == [25.0, 25.0]
    training = meta["training"]
    assert training["source_sha256"] == sha256(ckpt) and training["global_step"] == 1
    # the command without the machine's folders; the overrides as given
    assert training["command"] == "sss2bathy-train experiment=cnn scale=tiny"
    assert "paths.output_dir=/somewhere/local" in training["overrides"]
    assert training["config"]["trainer"]["max_epochs"] == 1  # interpolation resolved
    assert training["config"]["callbacks"]["dir"] == "${hydra:runtime.output_dir}"  # kept
    assert "paths" not in training["config"]
    # a folder of the machine is never resolved into the record
    assert training["config"]["trainer"]["default_root_dir"] == "${paths.output_dir}"
    assert all("/" not in name for name in meta["metrics"]["sources"])
    assert training["loss"]["kind"] and training["optimizer"]["lr"] == 1e-3
    # validation and test scores only, finite only
    assert meta["metrics"]["values"] == {
        "val/nlat_mae": 0.2,
        "test/hills:test/nlat_mae": 0.3,
        "test/hills:test/constant/nlat_mae": 0.25,
    }
    assert meta["software"]["sss2bathy"] == sss2bathy.__version__
    # the weights file holds tensors only: the network's, by name
    with safe_open(str(exported), framework="pt") as f:
        names = set(f.keys())
    state = torch.load(ckpt, weights_only=True)["state_dict"]
    assert names == {k.removeprefix("net.") for k in state if k.startswith("net.")}


def test_the_exported_model_predicts_bit_for_bit_what_the_checkpoint_does(
    tiny_run, exported, tmp_path
):
    ckpt, survey_dir = tiny_run
    x = torch.randn(3, 1, 16, 40, generator=torch.Generator().manual_seed(5))
    with torch.inference_mode():
        assert torch.equal(load_normal_net(ckpt)(x), load_normal_net(exported)(x))
    assert checkpoint_window_config(exported) == checkpoint_window_config(ckpt)
    assert checkpoint_input_spec(exported) == checkpoint_input_spec(ckpt)
    survey = Survey.load(survey_dir)
    a = predict_normals(ckpt, survey, tmp_path / "a", ["test0", "t0"], device="cpu")
    b = predict_normals(exported, survey, tmp_path / "b", ["test0", "t0"], device="cpu")
    for name in ("test0", "t0"):
        np.testing.assert_array_equal(a[name][0], b[name][0])  # NaN where NaN, else equal
        np.testing.assert_array_equal(a[name][1], b[name][1])
        assert np.isfinite(a[name][0]).sum() > 100


@pytest.mark.parametrize(
    ("field", "value", "message"),
    [
        ("format_version", 2, r"format_version: expected 1 \(what this sss2bathy reads\), found 2"),
        ("input_channels", ["depth"], "input_channels: expected a list of channel names"),
        ("windows.overlap", 1.5, r"windows.overlap: expected a fraction in \[0, 1\), found 1.5"),
        ("windows.window_pings", 0, "windows.window_pings: expected an integer >= 1, found 0"),
        ("network._target_", "os.system", "network._target_: expected a class path in"),
        ("weights.sha256", "abc", "weights.sha256: expected 64 hex digits, found 'abc'"),
        ("sonar_envelope", {"settings": {"bin_m": [1]}}, r"bin_m: expected \[min, max\]"),
        ("sonar_mask", None, "sonar_mask: expected a field"),
    ],
)
def test_loading_validates_the_metadata_in_one_line(exported, tmp_path, field, value, message):
    path = _copy(exported, tmp_path)
    meta = json.loads(path.with_suffix(".json").read_text())
    node, *rest = field.split(".")
    if value is None:
        del meta[node]
    elif rest:
        meta[node][rest[0]] = value
    else:
        meta[node] = value
    path.with_suffix(".json").write_text(json.dumps(meta))
    with pytest.raises(ValueError, match=message) as err:
        load_normal_net(path)
    assert "\n" not in str(err.value) and "m.json" in str(err.value)
    with pytest.raises(ValueError, match="data.normals.checkpoint: .*m.json"):
        check_cnn_model(path, "data.normals.checkpoint")


def test_changed_weights_or_a_missing_metadata_file_are_refused(exported, tmp_path):
    path = _copy(exported, tmp_path)
    data = bytearray(path.read_bytes())
    data[-1] ^= 0xFF
    path.write_bytes(bytes(data))
    with pytest.raises(ValueError, match=r"m.safetensors: weights.sha256: expected [0-9a-f]{64}"):
        read_model_weights(path)
    path.with_suffix(".json").unlink()
    with pytest.raises(FileNotFoundError, match=r"m.json: expected the model's metadata"):
        load_normal_net(path)


def test_pretrained_names_the_package_model(exported, tmp_path, monkeypatch):
    monkeypatch.setattr(cnn_normals, "PRETRAINED_DIR", tmp_path / "none")
    with pytest.raises(ValueError, match="cnn_checkpoint: expected 'pretrained' to name the CNN"):
        resolve_cnn_checkpoint("pretrained", None)
    assert cnn_normals.shipped_model() is None
    shipped = _copy(exported, tmp_path / "pkg", "normal_cnn")
    monkeypatch.setattr(cnn_normals, "PRETRAINED_DIR", tmp_path / "pkg")
    assert resolve_cnn_checkpoint("pretrained", None) == shipped
    assert check_cnn_model("pretrained") == shipped
    x = torch.randn(1, 1, 16, 32)
    with torch.inference_mode():
        assert torch.equal(load_normal_net("pretrained")(x), load_normal_net(exported)(x))
    over = model_overrides("pretrained")
    assert "++model.net.base_width=2" in over and "data.input_channels=[intensity]" in over
    assert not any("in_channels=" in o and "input" not in o for o in over)


def test_a_survey_outside_the_exported_models_sonar_is_warned_about(tiny_run, exported, caplog):
    _, survey_dir = tiny_run
    survey = Survey.load(survey_dir)
    line = Survey.load(survey_dir).line("test0")
    line.sensor = SensorParams(frequency_hz=600e3)
    outside = Survey("outside", [line])
    with caplog.at_level(logging.WARNING, logger="sss2bathy.data.cnn_normals"):
        warn_sonar_outside(exported, survey, ["test0"])  # the training sonar: no warning
        warn_sonar_outside(exported, outside, ["test0"])
    warned = [r.getMessage() for r in caplog.records if r.levelno == logging.WARNING]
    assert len(warned) == 1, warned
    assert f"{exported} was trained on 850 kHz" in warned[0] and "600 kHz (outside)" in warned[0]


def test_the_export_command_writes_checks_and_refuses_in_one_line(tiny_run, tmp_path, capsys):
    ckpt, _ = tiny_run
    out = tmp_path / "out"
    assert main(["export", str(ckpt), "--out", str(out), "--name", "mine"]) == 0
    printed = capsys.readouterr().out
    assert "predictions identical" in printed and "sss2bathy-train experiment=cnn" in printed
    assert (out / "mine.safetensors").is_file() and (out / "mine.json").is_file()
    assert main(["show", str(out / "mine.safetensors")]) == 0
    assert "(checked)" in capsys.readouterr().out
    text = tmp_path / "notes.txt"
    text.write_text("not a checkpoint")
    cases = [
        (["export", str(ckpt), "--out", str(out), "--name", "mine"], "--name: expected a model"),
        (["export", str(text), "--out", str(out)], f"ckpt: {text} is not a checkpoint"),
        (["export", str(out / "mine.safetensors")], "found an exported model"),
        (["export", str(tmp_path / "nope.ckpt")], "ckpt: expected a checkpoint file"),
        (["export", str(ckpt), "--out", str(out), "--name", "a/b"], "name: expected a plain"),
        (["show", str(text)], "notes.json: expected the model's metadata"),
    ]
    for argv, message in cases:
        assert main(argv) == 2, argv
        err = capsys.readouterr().err
        assert err.startswith("error: ") and message in err and err.count("\n") == 1, err
    # --force replaces; the same checkpoint gives the same bytes
    digest = sha256(out / "mine.safetensors")
    assert main(["export", str(ckpt), "--out", str(out), "--name", "mine", "--force"]) == 0
    assert sha256(out / "mine.safetensors") == digest


def test_the_shipped_model_is_valid_when_the_package_has_one():
    shipped = cnn_normals.shipped_model()
    if shipped is None:
        pytest.skip(f"no shipped CNN in {cnn_normals.PRETRAINED_DIR} (not exported yet)")
    meta, tensors = read_model_weights(shipped)  # JSON and SHA-256 checked
    net = load_normal_net("pretrained")
    assert {k for k, _ in net.state_dict().items()} == set(tensors)
    assert meta["sonar_envelope"] is not None and meta["training"]["command"]
    assert shipped.stat().st_size < 50e6  # a few MB, package data
