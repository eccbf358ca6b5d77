"""The training sonar a CNN checkpoint stores and the warning for a survey outside it."""

from __future__ import annotations

import logging
import math
from functools import partial
from pathlib import Path

import numpy as np
import pytest
import pytorch_lightning as pl
import torch

from sss2bathy.data import cnn_normals
from sss2bathy.data.cnn_normals import predict_normals
from sss2bathy.data.sonar_envelope import (
    CHECKPOINT_KEY,
    SETTINGS,
    describe,
    envelope_warning,
    line_sonar,
    outside_settings,
    sonar_envelope,
)
from sss2bathy.data.windows import SidescanWindowDataModule
from sss2bathy.losses import NormalLoss
from sss2bathy.models.normal_cnn import NormalResNet
from sss2bathy.modules.normal_cnn import NormalCNNModule
from sss2bathy.survey import SensorParams, SidescanLine, Survey

TRAINED = {
    "frequency_hz": [850e3, 850e3],
    "max_range_m": [30.0, 30.0],
    "bin_m": [0.117, 0.117],
    "tilt_deg": [22.0, 35.0],
    "beam_width_deg": [50.0, 64.0],
    "altitude_m": [8.0, 12.0],
}


def _line(name, n_bins=64, max_range=25.0, altitude=10.0, sensor=None, n_pings=40):
    t = np.arange(n_pings, dtype=np.float64)
    return SidescanLine(
        name=name,
        time_s=t,
        position=np.stack([t, np.zeros_like(t), np.full_like(t, -2.0)], axis=1),
        rotation=np.repeat(np.eye(3)[None], n_pings, axis=0),
        altitude_m=np.linspace(altitude - 1, altitude + 1, n_pings).astype(np.float32),
        intensity=np.random.default_rng(0).random((n_pings, 2, n_bins)).astype(np.float32),
        range_m=np.linspace(max_range / n_bins, max_range, n_bins),
        sensor=sensor or SensorParams(),
    )


# ------------------------------------------------------------------ pure functions
def test_inside_the_trained_range_or_its_tolerance_is_no_warning():
    assert outside_settings(TRAINED, TRAINED) == []
    near = dict(TRAINED, frequency_hz=[900e3, 900e3], tilt_deg=[20.0, 39.0], bin_m=[0.12, 0.12])
    assert outside_settings(TRAINED, near) == []  # +5.9 %, -2°/+4°, +2.6 %
    assert outside_settings(TRAINED, {"tilt_deg": [30.0, 30.0]}) == []  # missing: not compared


@pytest.mark.parametrize(
    "key, value",
    [
        ("frequency_hz", [600e3, 600e3]),
        ("max_range_m", [50.0, 50.0]),
        ("bin_m", [0.059, 0.059]),
        ("tilt_deg", [15.0, 15.0]),
        ("beam_width_deg", [50.0, 75.0]),
        ("altitude_m", [2.6, 11.4]),
    ],
)
def test_each_setting_outside_is_named(key, value):
    assert outside_settings(TRAINED, dict(TRAINED, **{key: value})) == [key]


def test_line_settings_and_envelope_over_lines_use_the_drawn_sonar():
    wide = SensorParams(frequency_hz=600e3)
    lines = [_line("a", 64, 25.0, 10.0), _line("b", 128, 30.0, 4.0, wide)]
    one = line_sonar(lines[0])
    assert one["bin_m"][0] == pytest.approx(25.0 / 64) and one["max_range_m"] == [25.0, 25.0]
    assert one["tilt_deg"] == [pytest.approx(30.0)] * 2
    assert one["altitude_m"][0] == pytest.approx(9.1, abs=1e-3)  # 5th percentile of 9..11
    meta = {"lines": {"a": {"randomized": {"tilt_deg": 22.5, "beam_width_deg": 52.0}}}}
    env = sonar_envelope(Survey("s", lines, metadata=meta), ["a", "b"])
    s = env["settings"]
    assert list(s) == list(SETTINGS) and env["n_lines"] == 2 and env["survey"] == "s"
    assert s["frequency_hz"] == [600e3, 850e3]
    assert s["tilt_deg"] == [22.5, pytest.approx(30.0)]
    assert s["beam_width_deg"] == [52.0, pytest.approx(60.0)]
    assert s["bin_m"] == [pytest.approx(30.0 / 128), pytest.approx(25.0 / 64)]
    assert all(type(v) is float for vals in s.values() for v in vals)  # plain, weights_only


def test_the_warning_names_each_setting_outside_with_both_values():
    survey = Survey("real", [_line("x", 512, 30.0, 7.0, SensorParams(frequency_hz=600e3))])
    assert describe(TRAINED).startswith("850 kHz, 30 m range, 0.117 m bins, tilt 22-35°")
    msg = envelope_warning({"settings": TRAINED}, survey, ["x"], "cnn.ckpt")
    assert msg.startswith("the CNN checkpoint cnn.ckpt was trained on 850 kHz, 30 m range")
    assert "survey 'real': 600 kHz (outside), 30 m range, 0.0586 m bins (outside)" in msg
    assert "6.1-7.9 m altitude (outside)" in msg and "tilt 30°," in msg
    assert msg.endswith("3 setting(s) outside the trained range, its normals may be unreliable")
    assert "\n" not in msg
    inside = Survey("sim", [_line("y", 256, 30.0, 10.0)])
    trained = sonar_envelope(inside, ["y"])
    assert envelope_warning(trained, inside, ["y"], "cnn.ckpt") is None
    unknown = envelope_warning(None, inside, ["y"], "old.ckpt")
    assert "old.ckpt does not record the sonar it was trained on" in unknown
    with pytest.raises(ValueError, match=r"sonar_envelope.settings.bin_m: expected \[min, max\]"):
        envelope_warning({"settings": {"bin_m": [1.0]}}, inside, ["y"], "bad.ckpt")


# ------------------------------------------------------------------ training and use
def _hills(folder: Path) -> Path:
    """Four training lines of 850 kHz, 64 bins over 25 m, 10 m altitude, and a test line."""
    from sss2bathy.survey import BathyGrid

    x = np.arange(-40.0, 40.25, 0.5)
    y = np.arange(-10.0, 60.25, 0.5)
    X, Y = np.meshgrid(x, y)
    grid = BathyGrid(-12.0 + 1.5 * np.sin(X / 4.0) * np.cos(Y / 5.0), x[0], y[0], 0.5)
    lines = []
    for i, name in enumerate(["t0", "t1", "t2", "t3", "test0"]):
        n = 40
        pos = np.stack([np.full(n, -12.0 + 6.0 * i), np.linspace(0, 45, n), np.full(n, -2.0)], 1)
        line = _line(name, 64, 25.0)
        line.position = pos
        line.altitude_m = np.full(n, 10.0, np.float32)
        lines.append(line)
    meta = {"lines": {f"t{i}": {"randomized": {"tilt_deg": 25.0 + 2 * i}} for i in range(4)}}
    splits = {"train": ["t0", "t1", "t2", "t3"], "test": ["test0"]}
    return Survey("hills", lines, grid, splits, metadata=meta).save(folder / "hills")


@pytest.fixture(scope="module")
def trained(tmp_path_factory) -> tuple[Path, Path]:
    """A one-step CNN fit on the hills survey, checkpointed: (checkpoint, survey folder)."""
    tmp = tmp_path_factory.mktemp("envelope")
    survey_dir = _hills(tmp)
    dm = SidescanWindowDataModule(
        survey={"kind": "folder", "path": str(survey_dir)},
        data_dir=str(tmp),
        window_pings=16,
        window_bins=32,
        val_fraction=0.25,
        batch_size=8,
        seed=1,
    )
    torch.manual_seed(0)
    module = NormalCNNModule(
        net=NormalResNet(base_width=2, n_blocks=1),
        loss=NormalLoss(),
        optimizer=partial(torch.optim.Adam, lr=1e-3),
        image_every_n_epochs=0,
    )
    trainer = pl.Trainer(
        accelerator="cpu",
        logger=False,
        enable_checkpointing=False,
        enable_progress_bar=False,
        enable_model_summary=False,
        max_steps=1,
        limit_val_batches=1,
        num_sanity_val_steps=0,
    )
    trainer.fit(module, datamodule=dm)
    path = tmp / "cnn.ckpt"
    trainer.save_checkpoint(path)
    return path, survey_dir


def test_a_cnn_fit_stores_its_training_sonar_and_a_survey_outside_it_warns(
    trained, tmp_path, caplog
):
    path, survey_dir = trained
    ckpt = torch.load(path, weights_only=True)
    env = ckpt[CHECKPOINT_KEY]
    assert env["n_lines"] == 3 and env["survey"] == "hills"  # the validation line left out
    s = env["settings"]
    assert s["frequency_hz"] == [850e3, 850e3] and s["max_range_m"] == [25.0, 25.0]
    assert s["bin_m"] == [pytest.approx(25.0 / 64)] * 2
    assert 25.0 <= s["tilt_deg"][0] < s["tilt_deg"][1] <= 31.0  # the lines' drawn tilts
    assert s["beam_width_deg"] == [pytest.approx(60.0)] * 2
    assert s["altitude_m"] == [10.0, 10.0]

    survey = Survey.load(survey_dir)
    window = {"window_pings": 16, "window_bins": 32, "overlap": 0.5, "batch_size": 4}
    with caplog.at_level(logging.WARNING, logger="sss2bathy.data.cnn_normals"):
        predict_normals(path, survey, tmp_path, ["test0"], None, window, "cpu")
    assert not [r for r in caplog.records if "trained on" in r.getMessage()]

    # the same network told it was trained on a 600 kHz sonar at 50 m: two settings outside
    s2 = dict(s, frequency_hz=[600e3, 600e3], max_range_m=[50.0, 50.0])
    ckpt[CHECKPOINT_KEY] = dict(env, settings=s2)
    other = tmp_path / "other.ckpt"
    torch.save(ckpt, other)
    caplog.clear()
    with caplog.at_level(logging.WARNING, logger="sss2bathy.data.cnn_normals"):
        out = predict_normals(other, survey, tmp_path, ["test0"], None, window, "cpu")
        predict_normals(other, survey, tmp_path, ["test0"], None, window, "cpu")  # once only
    warned = [r.getMessage() for r in caplog.records if "trained on" in r.getMessage()]
    assert len(warned) == 1, warned
    assert f"checkpoint {other} was trained on 600 kHz, 50 m range" in warned[0]
    assert "850 kHz (outside), 25 m range (outside), 0.391 m bins, tilt 30°" in warned[0]
    assert np.isfinite(out["test0"][0]).any()  # never refused

    # a checkpoint from before envelopes: one warning that the sonar is unknown
    del ckpt[CHECKPOINT_KEY]
    old = tmp_path / "old.ckpt"
    torch.save(ckpt, old)
    caplog.clear()
    with caplog.at_level(logging.WARNING, logger="sss2bathy.data.cnn_normals"):
        predict_normals(old, survey, tmp_path, ["test0"], None, window, "cpu")
    unknown = [r.getMessage() for r in caplog.records if "does not record" in r.getMessage()]
    assert len(unknown) == 1 and "850 kHz, 25 m range" in unknown[0]
    assert cnn_normals.checkpoint_sonar_envelope(old) is None
    stored = cnn_normals.checkpoint_sonar_envelope(path)["settings"]["bin_m"][0]
    assert math.isclose(stored, 25.0 / 64)
