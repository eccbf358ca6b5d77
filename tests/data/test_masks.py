"""Sonar-only masks (water column, beam limits, shadows from intensity, no hit) and inputs."""

from __future__ import annotations

import math

import numpy as np
import pytest

from sss2bathy.data.masks import (
    SonarMaskConfig,
    check_channels,
    flat_seabed_depression,
    input_channels,
    relative_channel,
    sonar_mask,
)
from sss2bathy.data.normalize import relative_intensity
from sss2bathy.geometry import attitude_to_rotation
from sss2bathy.survey import (
    MASK_NO_HIT,
    MASK_OUT_OF_BEAM,
    MASK_SHADOW,
    MASK_VALID,
    MASK_WATER_COLUMN,
)


def test_flat_seabed_depression_meets_the_seabed_on_the_heads_side():
    n = 6
    rot = attitude_to_rotation(
        np.full(n, 0.4), np.linspace(-0.1, 0.1, n), np.linspace(-0.25, 0.25, n)
    )
    r, h = np.linspace(5.0, 30.0, 9), np.full(n, 4.0)
    theta = flat_seabed_depression(r, h, rot)
    for side, sigma in ((0, 1.0), (1, -1.0)):
        th = theta[:, side]
        local = np.stack([np.zeros_like(th), sigma * np.cos(th), -np.sin(th)], -1)
        world = np.einsum("pij,pbj->pbi", rot, local)
        np.testing.assert_allclose(r[None] * world[..., 2], -4.0, atol=1e-9)
        assert (np.cos(th) > 0).all()
    level = flat_seabed_depression(r, h, np.repeat(np.eye(3)[None], n, 0))
    np.testing.assert_allclose(level[:, 0], np.arcsin(4.0 / r)[None].repeat(n, 0))
    assert np.isnan(flat_seabed_depression(np.array([3.0]), np.array([4.0]), rot[:1])).all()


def _scene(n_pings: int = 20, n_bins: int = 40):
    rng = np.random.default_rng(0)
    intensity = rng.uniform(0.6, 1.4, (n_pings, 2, n_bins))
    intensity[5:9, 0, 25:29] = 0.02  # a shadow behind an object (port)
    intensity[12, 1, 30] = np.nan
    altitude = np.full(n_pings, 5.0)
    altitude[15] = np.nan
    range_m = np.linspace(1.0, 30.0, n_bins)
    rotation = np.repeat(np.eye(3)[None], n_pings, 0)
    return intensity, range_m, altitude, rotation


def test_sonar_mask_reasons():
    intensity, r, h, rot = _scene()
    limits = (math.radians(0.0), math.radians(60.0))
    m = sonar_mask(intensity, r, h, rot, limits)
    water = r < 5.0
    oob = ~water & (r < 5.0 / math.sin(math.radians(60.0)))
    ok = np.isfinite(h)
    assert ((m[ok] & MASK_WATER_COLUMN) > 0).tolist() == [[water.tolist()] * 2] * int(ok.sum())
    assert ((m[ok] & MASK_OUT_OF_BEAM) > 0).tolist() == [[oob.tolist()] * 2] * int(ok.sum())
    assert (m[15] & MASK_NO_HIT).all() and m[12, 1, 30] & MASK_NO_HIT
    shadow = (m & MASK_SHADOW) > 0
    expected = np.zeros_like(shadow)
    expected[5:9, 0, 25:29] = True
    np.testing.assert_array_equal(shadow, expected)
    # everything else is valid seabed
    other = np.ones_like(shadow)
    other[:, :, water | oob] = False
    other[~ok] = False
    other[12, 1, 30] = False
    assert (m[other & ~expected] == MASK_VALID).all()
    # parameters: margin, beam limits off, threshold 0 = no shadow detection, smoothing
    m2 = sonar_mask(intensity, r, h, rot, limits, {"nadir_margin_m": 2.0, "beam_limits": False})
    assert ((m2[0, 0] & MASK_WATER_COLUMN) > 0).tolist() == (r < 7.0).tolist()
    assert not (m2 & MASK_OUT_OF_BEAM).any()
    assert not (sonar_mask(intensity, r, h, rot, None, {"shadow_threshold": 0}) & MASK_SHADOW).any()
    smooth = sonar_mask(intensity, r, h, rot, limits, {"shadow_smooth_bins": 3})
    assert ((smooth & MASK_SHADOW) > 0).sum() < shadow.sum()  # edges average with bright bins
    # a different scale of the intensities changes nothing (normalised per head)
    np.testing.assert_array_equal(sonar_mask(intensity * 37.0, r, h, rot, limits), m)


def test_sonar_mask_config_validation():
    assert SonarMaskConfig.coerce(None) == SonarMaskConfig()
    with pytest.raises(ValueError, match="sonar_mask: unknown keys \\['threshold'\\]"):
        SonarMaskConfig.coerce({"threshold": 0.2})
    with pytest.raises(ValueError, match="sonar_mask.shadow_smooth_pings: expected an odd"):
        SonarMaskConfig(shadow_smooth_pings=2)
    with pytest.raises(ValueError, match="sonar_mask.beam_margin_deg"):
        SonarMaskConfig(beam_margin_deg=50)
    intensity, r, h, rot = _scene()
    with pytest.raises(ValueError, match="altitude_m: expected shape"):
        sonar_mask(intensity, r, h[:-1], rot, None)


def test_input_channels():
    r = np.array([2.0, 4.0, 8.0, 16.0])
    h = np.array([4.0, np.nan])
    x = np.arange(8, dtype=np.float32).reshape(2, 4)
    out = input_channels(x, r, h, 16.0, ["intensity", "grazing", "range"])
    assert out.shape == (3, 2, 4) and out.dtype == np.float32
    np.testing.assert_array_equal(out[0], x)
    np.testing.assert_allclose(out[1], [[0.0, 1.0, 0.5, 0.25], [0.0, 0.0, 0.0, 0.0]])
    np.testing.assert_allclose(out[2], [[0.125, 0.25, 0.5, 1.0]] * 2)
    batched = input_channels(np.stack([x, x]), r, h, 16.0, ["intensity", "grazing"])
    assert batched.shape == (2, 2, 2, 4)
    assert check_channels(None) == ("intensity",)
    for bad in (["grazing", "intensity"], ["intensity", "intensity"], ["intensity", "depth"]):
        with pytest.raises(ValueError, match="input_channels"):
            check_channels(bad)
    rel = np.full_like(x, 2.0)
    out = input_channels(x, r, h, 16.0, ["relative", "range"], relative=rel)
    np.testing.assert_array_equal(out[0], rel)
    assert check_channels(["relative"]) == ("relative",)
    with pytest.raises(ValueError, match="relative: expected the 'relative' channel of shape"):
        input_channels(x, r, h, 16.0, ["intensity", "relative"])
    heads = np.stack([x, x + 10.0])  # (2 heads, P, B): each head's other is the flipped stack
    out = input_channels(heads, r, h, 16.0, ["intensity", "opposite"], opposite=heads[::-1])
    np.testing.assert_array_equal(out[0, 1], x + 10.0)
    np.testing.assert_array_equal(out[1, 1], x)
    with pytest.raises(ValueError, match="opposite: expected the other head's intensity"):
        input_channels(x, r, h, 16.0, ["intensity", "opposite"], opposite=x[:1])


def test_relative_intensity_divides_out_what_every_range_column_has():
    """Range-dependent gain (beam pattern, TVG, sediment's angular response) divides out; a
    bright patch stays bright relative to its surroundings; masked bins do not count."""
    rng = np.random.default_rng(0)
    n_pings, n_bins = 400, 64
    gain = np.exp(-np.linspace(0.0, 3.0, n_bins))  # far range much darker
    speckle = rng.gamma(8.0, 1 / 8.0, (n_pings, 2, n_bins))
    x = speckle * gain[None, None, :] * np.array([1.0, 5.0])[None, :, None]
    x[200:210, 1, 30:34] *= 3.0  # a slope facing the sonar
    valid = np.ones_like(x, bool)
    valid[:, :, :5] = False  # water column: neither counted nor trusted
    x[:, :, :5] = 1e3
    rel = relative_intensity(x, valid, window_pings=101, smooth_bins=1)
    assert rel.shape == x.shape and rel.dtype == np.float32
    col_means = rel[:, :, 5:].mean(axis=0)
    np.testing.assert_allclose(col_means, 1.0, atol=0.05)  # gain and per-head scale gone
    assert rel[200:210, 1, 30:34].mean() > 2.5  # the bright patch reads ~3
    # a dark far range is no darker than the near range once divided
    assert abs(rel[:, 0, 55:].mean() - rel[:, 0, 10:20].mean()) < 0.05
    # the window sees only valid bins; all-masked columns fall back to 1 (no division by 0)
    none = relative_intensity(x, np.zeros_like(valid), window_pings=11, smooth_bins=3)
    np.testing.assert_allclose(none, np.clip(x, 0, 8), rtol=1e-6)
    with pytest.raises(ValueError, match="window_pings: expected a positive integer"):
        relative_intensity(x, valid, window_pings=0)
    with pytest.raises(ValueError, match="valid_mask: expected a bool array"):
        relative_intensity(x, valid.astype(np.uint8))
    # the channel of a line uses the sonar mask's valid bins
    mask = np.where(valid, MASK_VALID, MASK_WATER_COLUMN).astype(np.uint8)
    np.testing.assert_allclose(
        relative_channel(x.astype(np.float32), mask),
        relative_intensity(x.astype(np.float32), valid),
        rtol=1e-6,
    )
