"""CNN normals for the SIREN stage: checkpoint discovery, window origins, exact stitching,
checkpoint loading, masks, cache."""

import logging
import os
import time
from functools import partial

import numpy as np
import pytest
import pytorch_lightning as pl
import torch

from sss2bathy.data import cnn_normals
from sss2bathy.data.cnn_normals import (
    latest_checkpoint,
    line_inputs,
    load_normal_net,
    predict_normals,
    predict_waterfall,
    resolve_cnn_checkpoint,
    stitch_windows,
)
from sss2bathy.data.masks import input_channels, sonar_only_mask
from sss2bathy.data.normalize import normalize_intensity
from sss2bathy.data.windows import line_windows
from sss2bathy.losses import NormalLoss
from sss2bathy.models.normal_cnn import NormalResNet
from sss2bathy.modules.normal_cnn import NormalCNNModule
from sss2bathy.survey import MASK_SHADOW, MASK_VALID, MASK_WATER_COLUMN, SidescanLine, Survey
from sss2bathy.utils.atomic import file_sha256, stable_hash


def test_stitch_reconstructs_waterfall_exactly():
    rng = np.random.default_rng(0)
    waterfall = rng.normal(size=(37, 23)).astype(np.float32)
    h, w = 8, 8
    origins = line_windows(37, 23, h, w, 0.75)
    windows = np.stack([waterfall[p : p + h, b : b + w] for p, b in origins])
    mean, count = stitch_windows(windows, origins, waterfall.shape)
    np.testing.assert_array_equal(mean, waterfall)
    assert count.min() >= 1 and count.max() > 1 and count.dtype == np.int32


def test_stitch_averages_overlaps_and_rejects_outside_windows():
    windows = np.stack([np.ones((2, 3)), 3 * np.ones((2, 3))])
    mean, count = stitch_windows(windows, [(0, 0), (0, 2)], (2, 6))
    np.testing.assert_array_equal(mean[0], [1, 1, 2, 3, 3, np.nan])
    np.testing.assert_array_equal(count[0], [1, 1, 2, 1, 1, 0])
    with pytest.raises(ValueError, match="origins"):
        stitch_windows(windows, [(0, 0), (0, 4)], (2, 6))


def _stitch_loop(windows, origins, shape):
    """The reference: one Python iteration per window (what ``stitch_windows`` vectorises)."""
    total = np.zeros(shape, dtype=np.float64)
    count = np.zeros(shape, dtype=np.int64)
    h, w = windows.shape[1:]
    for win, (p, b) in zip(windows, origins, strict=True):
        total[p : p + h, b : b + w] += win
        count[p : p + h, b : b + w] += 1
    with np.errstate(invalid="ignore", divide="ignore"):
        mean = np.where(count > 0, total / np.maximum(count, 1), np.nan)
    return mean.astype(np.float32), count.astype(np.int32)


@pytest.mark.parametrize("overlap", [0.0, 0.5, 0.75, 0.9])
def test_vectorised_stitch_equals_the_per_window_loop(overlap):
    rng = np.random.default_rng(3)
    shape, (h, w) = (301, 40), (64, 24)
    origins = line_windows(*shape, h, w, overlap)
    # plus irregular windows: stacked several deep, some pixels covered by none
    extra = np.stack([rng.integers(0, shape[0] - h + 1, 9), rng.integers(0, shape[1] - w + 1, 9)])
    origins = np.concatenate([origins, extra.T])
    windows = rng.normal(size=(len(origins), h, w)).astype(np.float32)
    mean, count = stitch_windows(windows, origins, shape)
    ref_mean, ref_count = _stitch_loop(windows, origins, shape)
    np.testing.assert_array_equal(count, ref_count)
    np.testing.assert_array_equal(mean, ref_mean)  # same float64 sums in the same order


def test_predict_waterfall_equals_per_window_forward_and_loop_stitch(checkpoint):
    """Batched gathering + vectorised stitching = running each window alone and averaging
    with a loop, for any batch size (a partial last batch included)."""
    _, net = checkpoint
    intensity = np.random.default_rng(4).normal(size=(45, 2, 20)).astype(np.float32)
    h, w = 16, 12
    for overlap in (0.75, 0.5):
        origins = line_windows(45, 20, h, w, overlap)
        ref = np.empty((45, 2, 20), dtype=np.float32)
        for side in range(2):
            with torch.no_grad():
                preds = np.stack(
                    [
                        net(
                            torch.from_numpy(intensity[p : p + h, side, b : b + w])[None, None]
                        ).numpy()[0, 0]
                        for p, b in origins
                    ]
                )
            ref[:, side] = _stitch_loop(preds, origins, (45, 20))[0]
        for batch in (1, 5, 64):
            out = predict_waterfall(net, intensity, (h, w), overlap, batch_size=batch)
            np.testing.assert_allclose(out, ref, atol=1e-6)


def test_inference_overlap_overrides_the_training_one_and_keys_the_cache(checkpoint, tmp_path):
    path, net = checkpoint
    survey = Survey(name="tiny", lines=[make_line("a", 40, 20, 0)])
    window_cfg = {"window_pings": 8, "window_bins": 12, "overlap": 0.75, "batch_size": 4}
    default = predict_normals(path, survey, tmp_path, ["a"], None, window_cfg, "cpu")["a"][0]
    same = predict_normals(path, survey, tmp_path, ["a"], None, window_cfg, "cpu", overlap=0.75)
    half = predict_normals(path, survey, tmp_path, ["a"], None, window_cfg, "cpu", overlap=0.5)
    np.testing.assert_array_equal(same["a"][0], default)
    keys = sorted(p.name for p in (tmp_path / "predictions").iterdir())
    assert len(keys) == 2  # the explicit training overlap shares the default's cache
    # overlap 0.5 = the training windows' predict_waterfall at 0.5, masked
    inputs, sonar = line_inputs(make_line("a", 40, 20, 0), None, None)
    expected = predict_waterfall(net, inputs, (8, 12), 0.5, batch_size=4)
    expected[sonar != MASK_VALID] = np.nan
    np.testing.assert_allclose(half["a"][0], expected, atol=1e-6, equal_nan=True)
    ok = np.isfinite(default)
    assert not np.allclose(half["a"][0][ok], default[ok])  # fewer windows: another average
    for bad in (1.0, -0.1, "0.5", True):
        with pytest.raises(ValueError, match=r"^overlap: expected null .* found"):
            predict_normals(path, survey, tmp_path, ["a"], None, window_cfg, "cpu", overlap=bad)


def make_line(name: str, n_pings: int, n_bins: int, seed: int) -> SidescanLine:
    rng = np.random.default_rng(seed)
    t = np.arange(n_pings, dtype=np.float64)
    return SidescanLine(
        name=name,
        time_s=t,
        position=np.stack([t, np.zeros_like(t), np.full_like(t, -2.0)], axis=1),
        rotation=np.repeat(np.eye(3)[None], n_pings, axis=0),
        altitude_m=np.full(n_pings, 3.0, np.float32),
        intensity=rng.random((n_pings, 2, n_bins)).astype(np.float32),
        range_m=np.linspace(1.0, 12.0, n_bins, dtype=np.float32),
    )


@pytest.fixture(scope="module")
def checkpoint(tmp_path_factory):
    torch.manual_seed(0)
    module = NormalCNNModule(
        net=NormalResNet(base_width=2, n_blocks=1),
        loss=NormalLoss(),
        optimizer=partial(torch.optim.Adam, lr=1e-3),
        image_every_n_epochs=0,
    )
    trainer = pl.Trainer(accelerator="cpu", logger=False, enable_checkpointing=False, max_epochs=0)
    trainer.strategy.connect(module)
    path = tmp_path_factory.mktemp("ckpt") / "cnn.ckpt"
    trainer.save_checkpoint(path)
    return path, module.net.eval()


def test_load_normal_net_rebuilds_the_network_safely(checkpoint, tmp_path):
    path, net = checkpoint
    loaded = load_normal_net(path)
    x = torch.randn(2, 1, 8, 12)
    torch.testing.assert_close(loaded(x), net(x))
    ckpt = torch.load(path, weights_only=True)
    ckpt["hyper_parameters"]["net_config"]["_target_"] = "os.system"
    torch.save(ckpt, tmp_path / "evil.ckpt")
    with pytest.raises(ValueError, match="sss2bathy.models"):
        load_normal_net(tmp_path / "evil.ckpt")


def test_single_window_prediction_equals_the_network_on_the_whole_line(checkpoint):
    _, net = checkpoint
    intensity = np.random.default_rng(1).normal(size=(12, 2, 16)).astype(np.float32)
    out = predict_waterfall(net, intensity, (12, 16), 0.75, batch_size=1)
    with torch.no_grad():
        direct = net(torch.from_numpy(intensity).permute(1, 0, 2)[:, None])[:, 0]
    np.testing.assert_allclose(out, direct.permute(1, 0, 2).numpy(), atol=1e-6)
    # overlapping windows: each pixel is the mean of the window predictions covering it
    tiled = predict_waterfall(net, intensity, (8, 8), 0.5, batch_size=3)
    with torch.no_grad():
        first = net(torch.from_numpy(intensity[:8, 0, :8])[None, None])[0, 0].numpy()
    np.testing.assert_allclose(tiled[:2, 0, :4], first[:2, :4], atol=1e-6)  # one window only
    assert np.isfinite(tiled).all() and not np.allclose(tiled, out)


def test_predict_normals_masks_pads_and_caches(checkpoint, tmp_path, monkeypatch, caplog):
    path, net = checkpoint
    lines = [make_line("a", 30, 20, 0), make_line("short", 5, 20, 1)]
    survey = Survey(name="tiny", lines=lines)
    draped = {}
    for ln in lines:
        mask = np.zeros(ln.intensity.shape, np.uint8)
        mask[:, :, :3] = MASK_WATER_COLUMN
        mask[2, 1, 10:12] = MASK_SHADOW
        draped[ln.name] = {"mask": mask}
    window_cfg = {"window_pings": 8, "window_bins": 12, "overlap": 0.75, "batch_size": 4}
    out = predict_normals(path, survey, tmp_path, ["a", "short"], draped, window_cfg, "cpu")
    bare = predict_normals(path, survey, tmp_path, ["a", "short"], None, window_cfg, "cpu")
    for name, (n_lat, mask) in out.items():
        line = survey.line(name)
        sonar = sonar_only_mask(line)
        assert n_lat.shape == mask.shape == line.intensity.shape and n_lat.dtype == np.float32
        # the draped mask only adds masked bins; the predictions themselves ignore it
        np.testing.assert_array_equal(mask, sonar | draped[name]["mask"])
        np.testing.assert_array_equal(bare[name][1], sonar)
        keep = mask == MASK_VALID
        np.testing.assert_array_equal(n_lat[keep], bare[name][0][keep])
        assert np.isnan(n_lat[mask != MASK_VALID]).all()
        assert np.isfinite(n_lat[keep]).all() and np.abs(n_lat[keep]).max() <= 1
    # the short line (5 pings < 8) is zero-padded: same as running the padded window, the
    # input normalised over the sonar-only valid bins
    sonar = sonar_only_mask(survey.line("short"))
    x = normalize_intensity(survey.line("short").intensity, sonar == MASK_VALID)
    padded = np.zeros((8, 2, 20), np.float32)
    padded[:5] = x
    expected = predict_waterfall(net, padded, (8, 12), 0.75)[:5]
    valid = out["short"][1] == MASK_VALID
    np.testing.assert_allclose(out["short"][0][valid], expected[valid], atol=1e-6)

    files = list((tmp_path / "predictions").glob("*/*.npz"))
    assert sorted(f.name for f in files) == ["a.npz", "short.npz"]  # one cache, draped or not
    # cached: no network needed the second time, identical result
    monkeypatch.setattr(cnn_normals, "load_normal_net", lambda *a, **k: pytest.fail("recomputed"))
    again = predict_normals(path, survey, tmp_path, ["a"], draped, window_cfg, "cpu")
    np.testing.assert_array_equal(again["a"][0], out["a"][0])
    monkeypatch.undo()
    # a truncated cache file is detected and rebuilt
    cached = next(f for f in files if f.name == "a.npz")
    cached.write_bytes(cached.read_bytes()[:100])
    with caplog.at_level(logging.WARNING):
        rebuilt = predict_normals(path, survey, tmp_path, ["a"], draped, window_cfg, "cpu")
    assert "unreadable" in caplog.text
    np.testing.assert_allclose(rebuilt["a"][0], out["a"][0], atol=1e-6)


def test_sonar_only_mask_and_input_validation(checkpoint, tmp_path):
    path, _ = checkpoint
    line = make_line("a", 6, 12, 0)
    line.intensity[:] = 0.5 + 0.5 * line.intensity  # no shadow-dark bin
    line.altitude_m[4] = np.nan
    mask = sonar_only_mask(line, {"beam_limits": False})
    water = line.range_m < 3.0
    assert mask.shape == (6, 2, 12)
    assert (mask[:4, :, water] == MASK_WATER_COLUMN).all() and (mask[:4, :, ~water] == 0).all()
    assert (mask[4] != MASK_VALID).all()
    survey = Survey(name="tiny", lines=[line])
    cfg = {"window_pings": 8, "window_bins": None, "overlap": 0.5}  # None: all 12 bins
    out = predict_normals(path, survey, tmp_path, ["a"], None, cfg, "cpu")
    np.testing.assert_array_equal(out["a"][1], sonar_only_mask(line))
    with pytest.raises(ValueError, match="unknown.*'b'"):
        predict_normals(path, survey, tmp_path, ["b"], None, cfg, "cpu")
    with pytest.raises(ValueError, match="window_bins"):
        predict_normals(path, survey, tmp_path, ["a"], None, {"window_pings": 4, "overlap": 0.5})
    with pytest.raises(ValueError, match="window_cfg.*datamodule"):
        predict_normals(path, survey, tmp_path, ["a"], None, None, "cpu")
    ckpt = torch.load(path, weights_only=True)
    ckpt["datamodule_hyper_parameters"] = {"window_pings": 8, "window_bins": None, "overlap": 0.5}
    torch.save(ckpt, tmp_path / "with_dm.ckpt")
    from_ckpt = predict_normals(tmp_path / "with_dm.ckpt", survey, tmp_path, ["a"], None, None)
    np.testing.assert_array_equal(from_ckpt["a"][0], out["a"][0])
    with pytest.raises(ValueError, match="draped.*'a'"):
        predict_normals(path, survey, tmp_path, ["a"], {}, cfg, "cpu")
    # the checkpoint's sonar-mask parameters drive the input normalisation and the cache key
    ckpt["datamodule_hyper_parameters"]["sonar_mask"] = {"shadow_threshold": 0.9}
    torch.save(ckpt, tmp_path / "strict.ckpt")
    strict = predict_normals(tmp_path / "strict.ckpt", survey, tmp_path, ["a"], None, None)
    assert (strict["a"][1] & MASK_SHADOW).any() and not (out["a"][1] & MASK_SHADOW).any()
    ckpt["datamodule_hyper_parameters"]["sonar_mask"] = {"shadow_threshold": -1}
    torch.save(ckpt, tmp_path / "bad.ckpt")
    with pytest.raises(ValueError, match="sonar_mask.shadow_threshold"):
        predict_normals(tmp_path / "bad.ckpt", survey, tmp_path, ["a"], None, None)


def test_extra_input_channels_from_the_checkpoint(tmp_path):
    """A 2-channel network (intensity, grazing): predict_normals stacks the same inputs as
    the windows do, from the checkpoint alone."""
    torch.manual_seed(0)
    module = NormalCNNModule(
        net=partial(NormalResNet, base_width=2, n_blocks=1),
        loss=NormalLoss(),
        optimizer=partial(torch.optim.Adam, lr=1e-3),
        image_every_n_epochs=0,
        input_channels=["intensity", "grazing"],
    )
    assert module.net.in_channels == 2
    trainer = pl.Trainer(accelerator="cpu", logger=False, enable_checkpointing=False, max_epochs=0)
    trainer.strategy.connect(module)
    path = tmp_path / "cnn2.ckpt"
    trainer.save_checkpoint(path)
    line = make_line("a", 16, 12, 0)
    survey = Survey(name="tiny", lines=[line])
    cfg = {"window_pings": 16, "window_bins": None, "overlap": 0.5}
    n_lat, mask = predict_normals(path, survey, tmp_path, ["a"], None, cfg, "cpu")["a"]
    inputs, sonar = line_inputs(line, ["intensity", "grazing"], None)
    np.testing.assert_array_equal(mask, sonar)
    assert inputs.shape == (16, 2, 2, 12)
    grazing = input_channels(
        np.zeros((16, 12)), line.range_m, line.altitude_m, 12.0, ["intensity", "grazing"]
    )[1]
    np.testing.assert_allclose(inputs[:, 0, 1], grazing)
    with torch.no_grad():
        direct = module.net.eval()(torch.from_numpy(np.transpose(inputs, (1, 2, 0, 3))))[:, 0]
    expected = direct.permute(1, 0, 2).numpy()
    keep = mask == MASK_VALID
    np.testing.assert_allclose(n_lat[keep], expected[keep], atol=1e-6)
    # the opposite channel of a whole line: each head gets the other head's intensity
    both, _ = line_inputs(line, ["intensity", "opposite"], None)
    np.testing.assert_array_equal(both[:, 0, 1], both[:, 1, 0])
    np.testing.assert_array_equal(both[:, 1, 1], both[:, 0, 0])
    assert not np.array_equal(both[:, 0, 0], both[:, 1, 0])
    with pytest.raises(ValueError, match="in_channels"):
        NormalCNNModule(
            net=NormalResNet(base_width=2, n_blocks=1),
            loss=NormalLoss(),
            optimizer=partial(torch.optim.Adam, lr=1e-3),
            input_channels=["intensity", "range"],
        )


def test_latest_checkpoint(tmp_path):
    with pytest.raises(ValueError, match="data.normals.checkpoint: expected a trained CNN"):
        latest_checkpoint(tmp_path)
    paths = []
    for run in ("2024-01-01_10-00-00", "2024-01-02_10-00-00"):
        ckpt = tmp_path / run / "checkpoints" / "last.ckpt"
        ckpt.parent.mkdir(parents=True)
        ckpt.write_bytes(b"x")
        paths.append(ckpt)
    now = time.time()
    os.utime(paths[0], (now, now))
    os.utime(paths[1], (now - 100, now - 100))
    assert latest_checkpoint(tmp_path) == paths[0]
    # with a scale, only runs of that scale count (the newest run here is a tiny one)
    for ckpt, scale in zip(paths, ("tiny", "demo"), strict=True):
        hydra_dir = ckpt.parent.parent / ".hydra"
        hydra_dir.mkdir()
        (hydra_dir / "config.yaml").write_text(f"scale:\n  name: {scale}\n")
    assert latest_checkpoint(tmp_path, "demo") == paths[1]
    assert latest_checkpoint(tmp_path, "tiny") == paths[0]
    with pytest.raises(ValueError, match=r"expected a CNN run of scale=paper .*'demo', 'tiny'"):
        latest_checkpoint(tmp_path, "paper")


def test_resolve_cnn_checkpoint(tmp_path):
    """``latest`` finds the newest CNN run; a path must be a file; errors name the key."""
    ckpt = tmp_path / "runs" / "a" / "checkpoints" / "last.ckpt"
    ckpt.parent.mkdir(parents=True)
    ckpt.write_bytes(b"x")
    assert resolve_cnn_checkpoint("latest", tmp_path / "runs") == ckpt
    assert resolve_cnn_checkpoint(str(ckpt), None) == ckpt
    with pytest.raises(FileNotFoundError, match="ckpt_path: expected a CNN checkpoint file"):
        resolve_cnn_checkpoint(tmp_path / "nope.ckpt", tmp_path, key="ckpt_path")
    with pytest.raises(ValueError, match="cnn_checkpoint: 'latest' needs the folder"):
        resolve_cnn_checkpoint("latest", None)
    with pytest.raises(ValueError, match=r"scale=paper .*\['None'\]"):
        resolve_cnn_checkpoint("latest", tmp_path / "runs", "paper")


def test_bf16_inference_is_close_to_fp32_and_cached_apart(checkpoint, tmp_path):
    path, net = checkpoint
    intensity = np.random.default_rng(2).normal(size=(24, 2, 16)).astype(np.float32)
    fp32 = predict_waterfall(net, intensity, (8, 16), 0.75, batch_size=4)
    bf16 = predict_waterfall(net, intensity, (8, 16), 0.75, batch_size=4, precision="bf16")
    assert bf16.dtype == np.float32 and not np.array_equal(bf16, fp32)  # bf16 did run
    # bfloat16's 8-bit mantissa: on random networks the largest change reaches ~0.034 with
    # the InstanceNorm copy and the channel-norm one alike, the mean ~0.005
    np.testing.assert_allclose(bf16, fp32, atol=0.04)
    assert np.abs(bf16 - fp32).mean() < 0.01
    # a bfloat16 copy ran; the caller's network is left in float32
    assert all(p.dtype == torch.float32 for p in net.parameters())
    low, dtype = cnn_normals.inference_net(net, "cpu", "bf16")
    assert dtype == torch.bfloat16 and low is not net
    assert all(p.dtype == torch.bfloat16 for p in low.parameters()) and not low.training
    # on a CPU: channels-last, instance norms as channel norms (the same function)
    convs = [m for m in low.modules() if isinstance(m, torch.nn.Conv2d) and m.kernel_size[0] > 1]
    assert convs and all(
        m.weight.is_contiguous(memory_format=torch.channels_last) for m in convs
    )
    assert not any(isinstance(m, torch.nn.InstanceNorm2d) for m in low.modules())
    assert cnn_normals.inference_net(net, "cpu", "fp32") == (net, torch.float32)
    assert cnn_normals.inference_net(low, "cpu", "bf16")[0] is low  # already bfloat16
    with pytest.raises(ValueError, match=r"precision: expected one of \['fp32', 'bf16'\]"):
        predict_waterfall(net, intensity, (8, 16), 0.75, precision="fp16")

    survey = Survey(name="tiny", lines=[make_line("a", 30, 20, 0)])
    window_cfg = {"window_pings": 8, "window_bins": 12, "overlap": 0.75, "batch_size": 4}
    a32 = predict_normals(path, survey, tmp_path, ["a"], None, window_cfg, "cpu")["a"][0]
    a16 = predict_normals(path, survey, tmp_path, ["a"], None, window_cfg, "cpu", "bf16")["a"][0]
    keys = sorted(p.name for p in (tmp_path / "predictions").iterdir())
    spec = cnn_normals.checkpoint_input_spec(path)
    fp32_key = stable_hash(
        {"version": cnn_normals.CACHE_VERSION, "ckpt": file_sha256(path), "window": [8, 12, 0.75],
         "channels": list(spec["channels"]), "sonar_mask": spec["sonar_mask"]}
    )  # fmt: skip
    assert len(keys) == 2 and fp32_key in keys  # a cache per precision; fp32's key unchanged
    ok = np.isfinite(a32)
    np.testing.assert_array_equal(ok, np.isfinite(a16))
    np.testing.assert_allclose(a16[ok], a32[ok], atol=0.04)
    assert np.abs(a16[ok] - a32[ok]).mean() < 0.01
    with pytest.raises(ValueError, match="precision: expected one of"):
        predict_normals(path, survey, tmp_path, ["a"], None, window_cfg, "cpu", "half")


def test_bf16_on_a_cpu_without_native_bfloat16_warns(checkpoint, monkeypatch, caplog):
    _, net = checkpoint
    intensity = np.zeros((8, 2, 8), dtype=np.float32)
    monkeypatch.setattr(cnn_normals, "cpu_has_native_bf16", lambda: False)
    with caplog.at_level(logging.WARNING, logger="sss2bathy.data.cnn_normals"):
        predict_waterfall(net, intensity, (8, 8), 0.75, precision="bf16")
    assert "without native bfloat16" in caplog.text
    caplog.clear()
    monkeypatch.setattr(cnn_normals, "cpu_has_native_bf16", lambda: True)
    with caplog.at_level(logging.WARNING, logger="sss2bathy.data.cnn_normals"):
        predict_waterfall(net, intensity, (8, 8), 0.75, precision="bf16")
        predict_waterfall(net, intensity, (8, 8), 0.75)
    assert "without native bfloat16" not in caplog.text


def test_inference_batch_size_does_not_change_predictions(checkpoint, tmp_path, monkeypatch):
    """``batch_size`` (None: CPU_INFERENCE_BATCH on a CPU) only sets windows per pass."""
    path, _ = checkpoint
    survey = Survey(name="tiny", lines=[make_line("a", 30, 20, 0)])
    window_cfg = {"window_pings": 8, "window_bins": 12, "overlap": 0.75, "batch_size": 64}
    calls = []
    real = cnn_normals.predict_waterfall

    def spy(*args, **kwargs):
        calls.append(args[4])
        return real(*args, **kwargs)

    monkeypatch.setattr(cnn_normals, "predict_waterfall", spy)
    default = predict_normals(path, survey, tmp_path / "d", ["a"], None, window_cfg, "cpu")
    three = predict_normals(
        path, survey, tmp_path / "t", ["a"], None, window_cfg, "cpu", batch_size=3
    )
    assert calls == [cnn_normals.CPU_INFERENCE_BATCH, 3]
    np.testing.assert_allclose(default["a"][0], three["a"][0], atol=1e-5, equal_nan=True)
    with pytest.raises(ValueError, match="batch_size: expected null or an integer >= 1, found 0"):
        predict_normals(path, survey, tmp_path, ["a"], None, window_cfg, "cpu", batch_size=0)
