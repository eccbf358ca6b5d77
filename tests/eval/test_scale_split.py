"""The CNN error split by scale (sss2bathy.eval.cnn_table.scale_split): a low-frequency error
shows in the low-pass MAE, white noise mostly does not; shrinkage shows in the slopes."""

import numpy as np
import pytest

from sss2bathy.eval.cnn_table import lowpass_waterfall, scale_split, write_scale_split


def _truth(seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    truth = 0.2 * rng.standard_normal((200, 128))
    valid = rng.random((200, 128)) > 0.1
    return truth, valid


def test_lowpass_waterfall_averages_valid_pixels_only():
    v = np.arange(20.0).reshape(4, 5)
    m = np.ones((4, 5), bool)
    m[1, 1] = False
    lp, keep = lowpass_waterfall(v, m, 3, 3)
    assert not keep[1, 1]
    box = [v[i, j] for i in range(1, 4) for j in range(1, 4) if m[i, j]]
    assert lp[2, 2] == pytest.approx(np.mean(box))
    with pytest.raises(ValueError, match="pings x bins"):
        lowpass_waterfall(v, m, 0, 3)


def test_low_frequency_error_shows_and_white_noise_mostly_does_not():
    truth, valid = _truth()
    rng = np.random.default_rng(1)
    noise = 0.05 * rng.standard_normal(truth.shape)
    pings = np.arange(200)[:, None]
    bins = np.arange(128)[None, :]
    smooth = 0.05 * np.sin(2 * np.pi * pings / 120) * np.cos(2 * np.pi * bins / 200)
    white = scale_split([(truth + noise, truth, valid)])
    low = scale_split([(truth + smooth, truth, valid)])
    # comparable pixel error, very different low-pass error
    assert white["mae"] > low["mae"]
    assert white["lp16x32_mae"] < 0.05 * white["mae"]
    assert low["lp16x32_mae"] > 0.8 * low["mae"]
    assert low["lp16x32_share"] > 10 * white["lp16x32_share"]
    assert white["slope"] == pytest.approx(1.0, abs=0.02)


def test_bias_per_head_and_shrinkage():
    truth, valid = _truth(2)
    offset = scale_split([(truth + 0.03, truth, valid), (truth - 0.01, truth, valid)])
    assert offset["line_side_bias"] == pytest.approx(0.02, abs=1e-9)
    # a constant error per head is all swath error; a sign flip across each ping is none
    assert offset["swath16_mae"] == pytest.approx(0.02, abs=1e-9)
    flip = np.where(np.arange(truth.shape[1])[None, :] % 2 == 0, 0.05, -0.05)
    full = np.ones_like(valid)
    assert scale_split([(truth + flip, truth, full)])["swath16_mae"] < 1e-9
    shrunk = scale_split([(0.6 * truth, truth, valid)])
    assert shrunk["slope"] == pytest.approx(0.6, abs=1e-6)
    assert shrunk["lp_slope"] == pytest.approx(0.6, abs=1e-6)
    with pytest.raises(ValueError, match="valid pixels"):
        scale_split([(truth, truth, np.zeros_like(valid))])


def test_written_tables(tmp_path):
    truth, valid = _truth(3)
    rows = {"site": scale_split([(truth + 0.01, truth, valid)])}
    md, csv = write_scale_split(rows, tmp_path)
    assert "| site |" in md.read_text()
    assert csv.read_text().splitlines()[0].startswith("dataset,mae,lp4x8_mae")
