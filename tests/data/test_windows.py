"""Windows, flips, normalisation and the SidescanWindowDataModule on a small built survey."""

from __future__ import annotations

import logging
import math
from pathlib import Path

import numpy as np
import pytest
import torch
from hydra.utils import instantiate
from omegaconf import OmegaConf

from sss2bathy.data.normalize import normalize_intensity
from sss2bathy.data.windows import (
    FlipShuffleSampler,
    SidescanWindowDataModule,
    SidescanWindowDataset,
    WindowLine,
    line_windows,
    window_starts,
)
from sss2bathy.draping import drape_survey
from sss2bathy.geometry import attitude_to_rotation
from sss2bathy.survey import BathyGrid, SidescanLine, Survey

ROOT = Path(__file__).resolve().parents[2]


# ------------------------------------------------------------------ fixtures
def _hilly_grid() -> BathyGrid:
    cell = 0.5
    x = np.arange(-40.0, 40.0 + cell / 2, cell)
    y = np.arange(-10.0, 60.0 + cell / 2, cell)
    X, Y = np.meshgrid(x, y)
    z = -18.0 + 1.5 * np.sin(X / 4.0) * np.cos(Y / 5.0)
    return BathyGrid(z, float(x[0]), float(y[0]), cell)


def _line(name: str, x: float, n_pings: int = 40, n_bins: int = 64) -> SidescanLine:
    hd = np.zeros(n_pings)
    pos = np.stack([np.full(n_pings, x), np.linspace(0, 45, n_pings), np.full(n_pings, -8.0)], 1)
    rng = np.linspace(0.4, 25.0, n_bins)
    intensity = np.full((n_pings, 2, n_bins), 40.0, np.float32)
    intensity[:, 1] = 80.0
    return SidescanLine(
        name=name,
        time_s=np.arange(n_pings) * 0.1,
        position=pos,
        rotation=attitude_to_rotation(hd, hd, hd),
        altitude_m=np.full(n_pings, 10.0, np.float32),
        intensity=intensity,
        range_m=rng,
    )


def _save_survey(folder: Path, name: str = "hills", n_train: int = 4) -> Path:
    lines = [_line(f"t{i}", -12.0 + 8.0 * i) for i in range(n_train)] + [_line("test0", 2.0)]
    splits = {"train": [f"t{i}" for i in range(n_train)], "test": ["test0"]}
    return Survey(name, lines, _hilly_grid(), splits).save(folder / name)


@pytest.fixture(scope="module")
def survey_dir(tmp_path_factory) -> Path:
    return _save_survey(tmp_path_factory.mktemp("svy"))


def _ramp_line(name: str = "r", P: int = 20, B: int = 16) -> WindowLine:
    p = np.arange(P, dtype=np.float32)[:, None, None]
    b = np.arange(B, dtype=np.float32)[None, None, :]
    intensity = np.broadcast_to(p + 0.01 * b, (P, 2, B)).astype(np.float32)
    n_lat = np.broadcast_to(-0.02 * p + 0.001 * b, (P, 2, B)).astype(np.float32)
    valid = np.ones((P, 2, B), bool)
    valid[:, :, :2] = False
    return WindowLine(name, intensity, n_lat, valid)


# -------------------------------------------------------------- pure windowing
def test_window_starts_overlap_and_flush_end():
    s = window_starts(100, 16, 0.75)
    assert s.tolist() == list(range(0, 85, 4))  # stride 4 = 25% of 16, last start 84 = 100-16
    assert 1 - np.diff(s)[0] / 16 == 0.75
    s = window_starts(101, 16, 0.75)
    assert s[-1] == 85 and s[-2] == 84 and len(s) == 23
    assert window_starts(16, 16, 0.75).tolist() == [0]
    assert window_starts(2000, 64, 0.75).shape == (122,)
    with pytest.raises(ValueError, match="n: expected an integer >= size"):
        window_starts(10, 16)
    with pytest.raises(ValueError, match="overlap"):
        window_starts(100, 16, 1.0)


def test_line_windows_cover_every_pixel():
    origins = line_windows(70, 150, 16, 64, 0.75)
    assert origins.shape == (len(window_starts(70, 16)) * len(window_starts(150, 64)), 2)
    cover = np.zeros((70, 150), int)
    for p0, b0 in origins:
        cover[p0 : p0 + 16, b0 : b0 + 64] += 1
    assert cover.min() >= 1
    with pytest.raises(ValueError, match="window_pings=16"):
        line_windows(10, 150, 16, 64)


# ------------------------------------------------------------------ dataset
def test_flip_reverses_pings_and_keeps_n_lat_sign():
    ds = SidescanWindowDataset([_ramp_line()], 8, 16, 0.5, 0.5, flip_augment=True)
    n = len(ds)
    assert n == 2 * len(window_starts(20, 8, 0.5))  # both heads pooled
    a, f = ds[1], ds[1 + n]
    assert not a["flipped"] and f["flipped"]
    for key in ("intensity", "n_lat", "mask"):
        assert torch.equal(f[key], torch.flip(a[key], dims=[1]))
    assert (f["n_lat"] < 0).sum() == (a["n_lat"] < 0).sum()  # values, not signs, move
    assert int(f["ping_start"]) == int(a["ping_start"])
    plain = SidescanWindowDataset([_ramp_line()], 8, 16, 0.5, 0.5, flip_augment=False)
    with pytest.raises(IndexError):
        plain[len(plain)]


def test_flip_sampler_is_seeded_per_epoch():
    s1, s2 = FlipShuffleSampler(50, seed=3), FlipShuffleSampler(50, seed=3)
    e0, e0b = list(s1), list(s2)
    e1 = list(s1)
    assert e0 == e0b and e0 != e1
    assert sorted(i % 50 for i in e0) == list(range(50))
    flips = np.array(e0) >= 50
    assert 10 < flips.sum() < 40
    assert all(i < 50 for i in FlipShuffleSampler(50, flip=False, seed=3))


def test_low_valid_windows_skipped_and_zero_windows_error(caplog):
    line = _ramp_line(P=20, B=16)
    line.valid[:10] = False  # first half of the pings invalid
    with caplog.at_level(logging.INFO, logger="sss2bathy.data.windows"):
        ds = SidescanWindowDataset([line], 8, 16, 0.5, 0.5, name="half")
    starts = window_starts(20, 8, 0.5)  # 0 4 8 12 -> windows from 8 on are >= 7/8*... valid
    kept = [s for s in starts if (min(s + 8, 20) - max(s, 10)) * 14 >= 0.5 * 8 * 16]
    assert len(ds) == 2 * len(kept)
    assert ds.skipped["low_valid_windows"] == 2 * (len(starts) - len(kept))
    assert "skipped" in caplog.text
    with pytest.raises(ValueError, match="zero windows"):
        SidescanWindowDataset([line], 8, 16, 0.5, 1.0, name="strict")
    with pytest.raises(ValueError, match="window_bins"):
        SidescanWindowDataset([line], 8, 32, 0.5, 0.1)
    assert SidescanWindowDataset([line], 8, None, 0.5, 0.1).window_bins == 16


# ------------------------------------------------------------- normalisation
def test_normalize_intensity_per_head_median_and_clip():
    rng = np.random.default_rng(0)
    x = rng.exponential(50.0, size=(30, 2, 40))
    x[:, 1] *= 3.0
    x[0, 0, 0] = 1e6
    valid = np.ones(x.shape, bool)
    valid[:, :, :5] = False
    out = normalize_intensity(x, valid, clip_max=8.0)
    assert out.dtype == np.float32 and out.shape == x.shape
    for side in (0, 1):
        assert np.median(out[:, side][valid[:, side]]) == pytest.approx(1.0, rel=1e-5)
    assert out.max() == 8.0
    only_port = valid.copy()
    only_port[:, 1] = False
    y = normalize_intensity(x, only_port)
    assert np.median(y[:, 0][only_port[:, 0]]) == pytest.approx(1.0, rel=1e-5)
    with pytest.raises(ValueError, match="non-negative"):
        normalize_intensity(-x, valid)
    with pytest.raises(ValueError, match="valid_mask"):
        normalize_intensity(x, valid[:, :1])


# -------------------------------------------------------------- datamodule
def test_datamodule_batches(survey_dir, tmp_path):
    extra = _save_survey(tmp_path, name="other", n_train=2)
    dm = SidescanWindowDataModule(
        survey={"kind": "folder", "path": str(survey_dir)},
        data_dir=str(tmp_path),
        window_pings=16,
        window_bins=32,
        min_valid_fraction=0.2,
        val_fraction=0.25,
        batch_size=8,
        test_surveys=[{"kind": "folder", "path": str(extra)}],
        seed=1,
    )
    dm.prepare_data()
    dm.setup("fit")
    assert len(dm.val_lines) == 1 and len(dm.train_lines) == 3
    assert set(dm.train_lines + dm.val_lines) == {"t0", "t1", "t2", "t3"}
    batch = next(iter(dm.train_dataloader()))
    expected = {
        "intensity": ((8, 1, 16, 32), torch.float32),
        "inputs": ((8, 1, 16, 32), torch.float32),
        "n_lat": ((8, 1, 16, 32), torch.float32),
        "mask": ((8, 1, 16, 32), torch.bool),
        "line": ((8,), torch.long),
        "side": ((8,), torch.long),
        "ping_start": ((8,), torch.long),
        "bin_start": ((8,), torch.long),
        "flipped": ((8,), torch.bool),
    }
    assert set(batch) == set(expected)
    for key, (shape, dtype) in expected.items():
        assert tuple(batch[key].shape) == shape and batch[key].dtype == dtype, key
    assert torch.isfinite(batch["n_lat"]).all()
    assert (batch["n_lat"][~batch["mask"]] == 0).all()
    # the batch's n_lat is the draped n_lat at (line, side, ping_start, bin_start)
    survey = Survey.load(survey_dir)
    draped = drape_survey(survey, survey_dir, dm.drape_cfg)
    names = dm.train_set.line_names
    for i in range(8):
        d = draped[names[int(batch["line"][i])]]
        p0, b0, side = (
            int(batch["ping_start"][i]),
            int(batch["bin_start"][i]),
            int(batch["side"][i]),
        )
        ref = d.n_lat[p0 : p0 + 16, side, b0 : b0 + 32]
        if batch["flipped"][i]:
            ref = ref[::-1]
        m = batch["mask"][i, 0].numpy()
        np.testing.assert_array_equal(batch["n_lat"][i, 0].numpy()[m], ref[m])
    flips = torch.cat([b["flipped"] for b in dm.train_dataloader()])
    assert 0 < flips.float().mean() < 1
    assert not any(b["flipped"].any() for b in dm.val_dataloader())
    # constant intensities: each head normalises to 1 on valid pixels
    assert torch.allclose(batch["intensity"][batch["mask"]], torch.tensor(1.0))

    dm.setup("test")
    loaders = dm.test_dataloader()
    assert dm.test_set_names == ["hills:test", "other:all"]
    assert len(loaders) == 2
    assert dm.test_sets[0].line_names == ["test0"]
    assert dm.test_sets[1].line_names == ["t0", "t1", "test0"]
    assert next(iter(loaders[1]))["intensity"].shape[1:] == (1, 16, 32)


@pytest.mark.parametrize(
    "channels", [["intensity", "grazing", "range"], ["intensity", "opposite", "range"]]
)
def test_training_inputs_are_the_prediction_inputs(survey_dir, tmp_path, channels):
    """Training windows hold exactly the inputs predict_normals builds from the sidescan
    alone (sonar-only normalisation, same channels); the draped mask only picks the loss."""
    from sss2bathy.data.cnn_normals import line_inputs

    sonar_mask = {"shadow_threshold": 0.1}
    dm = SidescanWindowDataModule(
        survey={"kind": "folder", "path": str(survey_dir)},
        data_dir=str(tmp_path),
        window_pings=16,
        window_bins=32,
        val_fraction=0.25,
        batch_size=8,
        seed=1,
        sonar_mask=sonar_mask,
        input_channels=channels,
    )
    assert dm.hparams["input_channels"] == channels
    assert dm.hparams["sonar_mask"]["shadow_threshold"] == 0.1
    dm.setup("fit")
    survey = Survey.load(survey_dir)
    whole = {n: line_inputs(survey.line(n), channels, sonar_mask)[0] for n in dm.train_lines}
    batch = next(iter(dm.train_dataloader()))
    assert batch["inputs"].shape == (8, 3, 16, 32)
    torch.testing.assert_close(batch["inputs"][:, :1], batch["intensity"])
    for i in range(8):
        name = dm.train_set.line_names[int(batch["line"][i])]
        p0, b0, side = (int(batch[k][i]) for k in ("ping_start", "bin_start", "side"))
        ref = whole[name][p0 : p0 + 16, side, :, b0 : b0 + 32].transpose(1, 0, 2)
        if batch["flipped"][i]:
            ref = ref[:, ::-1]
        np.testing.assert_allclose(batch["inputs"][i].numpy(), ref, atol=0)
    with pytest.raises(ValueError, match="data.input_channels"):
        SidescanWindowDataModule(
            survey={"kind": "folder", "path": str(survey_dir)},
            data_dir=str(tmp_path),
            input_channels=["grazing"],
        )


def test_opposite_channel_is_the_other_heads_intensity():
    """A window's ``opposite`` channel holds the other head's intensity at the window's own
    pings and bins, for either head (heads told apart by their values)."""
    rng = np.random.default_rng(0)
    n_pings, n_bins = 12, 10
    intensity = rng.random((n_pings, 2, n_bins)).astype(np.float32)
    line = WindowLine(
        name="a",
        intensity=intensity,
        n_lat=np.zeros_like(intensity),
        valid=np.ones(intensity.shape, bool),
        altitude_m=np.full(n_pings, 5.0, np.float32),
        range_m=np.linspace(1.0, 20.0, n_bins).astype(np.float32),
        channels=("intensity", "opposite"),
    )
    pings, bins = slice(2, 8), slice(3, 9)
    for side in (0, 1):
        x = line.inputs(pings, side, bins)
        assert x.shape == (2, 6, 6)
        np.testing.assert_array_equal(x[0], intensity[pings, side, bins])
        np.testing.assert_array_equal(x[1], intensity[pings, 1 - side, bins])


def test_datamodule_errors(survey_dir, tmp_path):
    kw = {"survey": {"kind": "folder", "path": str(survey_dir)}, "data_dir": str(tmp_path)}
    dm = SidescanWindowDataModule(**kw, window_pings=16, window_bins=128)
    with pytest.raises(ValueError, match="window_bins"):
        dm.setup("fit")
    dm = SidescanWindowDataModule(**kw, window_pings=16, window_bins=64, min_valid_fraction=1.0)
    with pytest.raises(ValueError, match="zero windows"):
        dm.setup("fit")
    with pytest.raises(ValueError, match="survey: expected a data/survey config"):
        SidescanWindowDataModule(survey={"path": "x"}, data_dir=str(tmp_path))
    with pytest.raises(ValueError, match="val_fraction"):
        SidescanWindowDataModule(**kw, val_fraction=0.0)
    # "<argument>: expected ..., found ...", the argument named (start-up: data.<argument>)
    for bad, message in [
        ({"val_fraction": "0.1x"}, "val_fraction: expected a fraction in (0, 1), found '0.1x'"),
        ({"min_valid_fraction": 1.5}, "min_valid_fraction: expected a fraction in [0, 1], found"),
        ({"flip_augment": 1}, "flip_augment: expected true or false, found 1"),
        ({"window_pings": 0}, "window_pings: expected a positive integer, found 0"),
        ({"window_bins": 2.0}, "window_bins: expected a positive integer or null, found 2.0"),
        ({"overlap": 1.0}, "overlap: expected a fraction in [0, 1), found 1.0"),
    ]:
        with pytest.raises(ValueError) as err:
            SidescanWindowDataModule(**kw, **bad)
        assert str(err.value).startswith(message)
    with pytest.raises(RuntimeError, match="setup"):
        SidescanWindowDataModule(**kw).train_dataloader()


def test_hydra_config_instantiates(survey_dir, tmp_path):
    data = OmegaConf.load(ROOT / "conf" / "data" / "windows.yaml")
    # its defaults list: the shared sonar-only mask group
    assert {"sonar_mask@sonar_mask": "default"} in OmegaConf.to_container(data.pop("defaults"))
    data.sonar_mask = OmegaConf.load(ROOT / "conf" / "data" / "sonar_mask" / "default.yaml")
    cfg = OmegaConf.create({"seed": 7, "paths": {"data_dir": str(tmp_path)}, "data": data})
    cfg.data.survey = {"kind": "folder", "path": str(survey_dir)}
    cfg.data.window_pings, cfg.data.window_bins = 16, 32
    dm = instantiate(cfg.data, _recursive_=False)
    assert isinstance(dm, SidescanWindowDataModule)
    assert dm.seed == 7 and dm.data_dir == str(tmp_path) and dm.batch_size == 64
    assert dm.overlap == 0.75 and math.isclose(dm.drape_cfg.rays_per_bin, 2.0)
    dm.setup("fit")
    assert len(dm.train_set) > 0
    assert dm.sonar_mask.shadow_threshold == data.sonar_mask.shadow_threshold
    assert dm.input_channels == ("intensity",)
