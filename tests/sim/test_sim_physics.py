"""Sidescan physics on analytic scenes: flat floors, tilted planes, a box boulder."""

from __future__ import annotations

import math

import numpy as np
import pytest
import trimesh
from sim_helpers import grid_mesh, north_pings, scene

from sss2bathy.geometry import arc_point, attitude_to_rotation
from sss2bathy.sim.sonar import (
    absorption_db_per_m,
    backscatter,
    beam_pattern,
    calibrate_receiver,
    fan_basis,
    flat_bottom_power,
    range_bins,
    ray_fan,
    receive,
    simulate_pings,
    sound_speed_mps,
)
from sss2bathy.survey import MASK_SHADOW, MASK_VALID, MASK_WATER_COLUMN

ALPHA = 0.3  # dB/m


def _binned(power_raw: np.ndarray, k: int) -> np.ndarray:
    P, S, R = power_raw.shape
    return power_raw.reshape(P, S, R // k, k).sum(-1)


def _flat(sonar, response, altitude=10.0, n=24, seed=0):
    caster, surface = scene(grid_mesh(lambda X, Y: np.full_like(X, -altitude)))
    pos, R = north_pings(n)
    echoes = simulate_pings(
        caster, surface, pos, R, sonar, response, np.random.default_rng(seed),
        absorption_db_m=ALPHA,
    )  # fmt: skip
    return echoes


def test_water_absorption_and_sound_speed_golden():
    salt = absorption_db_per_m(850e3, 8.0, 35.0)
    fresh = absorption_db_per_m(850e3, 8.0, 0.0)
    assert 0.25 < salt < 0.32 and 0.2 < fresh < 0.27
    assert salt - fresh == pytest.approx(0.045, abs=0.01)  # MgSO4 relaxation, salt only
    assert absorption_db_per_m(100e3, 8.0, 35.0) < 0.05  # much weaker at 100 kHz
    assert sound_speed_mps(8.0, 35.0) == pytest.approx(1482.9, abs=0.2)
    with pytest.raises(ValueError, match="frequency_hz"):
        absorption_db_per_m(0.0, 8.0, 35.0)


def test_beam_pattern_half_power_at_edges(sonar):
    lo, hi = sonar.beam_limits_rad
    b = beam_pattern(np.array([lo, sonar.tilt_rad, hi]), sonar)
    np.testing.assert_allclose(b, [0.5, 1.0, 0.5], rtol=1e-12)
    assert beam_pattern(np.array(math.pi / 2), sonar) < 0.1


def test_backscatter_is_not_lambertian(response):
    inc = np.radians([0.0, 30.0, 60.0, 80.0, 95.0])
    s = backscatter(inc, np.zeros(5, int), response)
    assert s[-1] == 0.0  # back-facing
    assert np.all(np.diff(s[:4]) < 0)
    diffuse = response.mu[0] * np.cos(inc[1:4]) ** 1.8
    np.testing.assert_allclose(s[2:4], diffuse[1:], rtol=1e-3)  # specular lobe gone
    assert s[0] > 1.5 * response.mu[0]  # near-normal specular lobe on top of the diffuse term
    lambert = np.cos(inc[1:4]) ** 2
    assert not np.allclose(s[1:4] / s[1], lambert / lambert[0], rtol=0.05)


def test_fan_basis_matches_arc_point():
    rng = np.random.default_rng(3)
    R = attitude_to_rotation(rng.uniform(0, 6, 5), rng.normal(0, 0.1, 5), rng.normal(0, 0.1, 5))
    e_out, e_down = fan_basis(R)
    theta = rng.uniform(0, 1.6, (5, 2))
    side = np.broadcast_to([0, 1], (5, 2)).copy()
    expected = arc_point(np.zeros(3), np.repeat(R[:, None], 2, 1), np.ones((5, 2)), theta, side)
    got = np.cos(theta)[..., None] * e_out + np.sin(theta)[..., None] * e_down
    np.testing.assert_allclose(got, expected, atol=1e-12)


def test_ray_fan_weights_integrate_the_interval(sonar):
    h = np.array([5.0, 10.0, 20.0])
    lo, hi = np.full(3, 0.1), np.full(3, 1.62)
    theta, w = ray_fan(h, lo, hi, sonar, np.random.default_rng(0))
    assert theta.shape == w.shape and theta.shape[:2] == (3, 2)
    np.testing.assert_allclose(w.sum(-1), 1.52, rtol=0.01)
    assert np.all(w[(theta < lo[:, None, None]) | (theta > hi[:, None, None])] == 0)


def test_flat_floor_first_return_at_altitude(sonar, response):
    altitude = 10.0
    echoes = _flat(sonar, response, altitude)
    r_bins, _ = range_bins(sonar)
    width = r_bins[1] - r_bins[0]
    expected = int((altitude - sonar.min_range_m) // width)
    power = _binned(echoes.power_raw, sonar.oversampling)
    first = np.argmax(power > 0, axis=-1)
    assert np.all(np.abs(first - expected) <= 1)
    np.testing.assert_allclose(echoes.first_return_m, altitude, atol=1e-3)
    assert np.all(echoes.mask[..., : expected - 1] == MASK_WATER_COLUMN)
    # through the receiver (speckle, noise, TVG): the first bin clearly above the water
    # column's noise, averaged over pings, is the altitude bin
    cal = calibrate_receiver(sonar, response, 0, altitude, ALPHA)
    img = receive(echoes.power_raw, sonar, cal, np.random.default_rng(1), ALPHA).mean(axis=0)
    noise = img[:, : expected - 5]
    threshold = noise.max(axis=-1, keepdims=True) * 3 + 1e-6
    first_rx = np.argmax(img > threshold, axis=-1)
    assert np.all(np.abs(first_rx - expected) <= 1)


def test_flat_floor_power_matches_analytic_and_falls_with_range(sonar, response):
    altitude = 10.0
    echoes = _flat(sonar, response, altitude, n=32)
    r_bins, r_raw = range_bins(sonar)
    power = _binned(echoes.power_raw, sonar.oversampling).mean(axis=(0, 1))
    analytic = flat_bottom_power(r_raw, altitude, sonar, response, 0, ALPHA)
    analytic = analytic.reshape(-1, sonar.oversampling).sum(-1)
    axis_range = altitude / math.sin(sonar.tilt_rad)  # beam axis on the floor: 20 m
    far = (r_bins > axis_range) & (r_bins < sonar.max_range_m - 0.5)
    np.testing.assert_allclose(power[far], analytic[far], rtol=0.08)
    # received level (before TVG) falls with range beyond the beam axis: 1 m blocks
    blocks = power[far][: (far.sum() // 4) * 4].reshape(-1, 4).mean(-1)
    assert np.all(np.diff(blocks) < 0)
    assert blocks[-1] < 0.3 * blocks[0]


@pytest.mark.parametrize("amplitude, min_ratio", [(0.15, 1.5), (0.3, 2.5)])
def test_slope_facing_sonar_is_brighter(sonar, response, amplitude, min_ratio):
    # Corrugations across the port swath (port looks West, -x): facets facing the sonar
    # (n_lat < 0) and the same facets facing away (n_lat > 0) at the same ranges.
    wavelength = 4.0
    caster, surface = scene(
        grid_mesh(lambda X, Y: -10.0 + amplitude * np.sin(2 * np.pi * X / wavelength), cell=0.25)
    )
    pos, R = north_pings(12)
    echoes = simulate_pings(
        caster, surface, pos, R, sonar, response, np.random.default_rng(0), absorption_db_m=ALPHA
    )
    r_bins, _ = range_bins(sonar)
    sel = (r_bins > 15) & (r_bins < 25)
    power = _binned(echoes.power_raw, sonar.oversampling)[:, 0, sel]
    n_lat = echoes.n_lat[:, 0, sel]
    steepest = 2 * np.pi * amplitude / wavelength
    assert np.nanmin(n_lat) < -0.6 * steepest and np.nanmax(n_lat) > 0.6 * steepest
    facing = power[n_lat < -0.3 * steepest].mean()
    away = power[n_lat > 0.3 * steepest].mean()
    assert facing > min_ratio * away


def test_tilted_plane_n_lat_sign_convention(sonar, response):
    # z = -10 - g x rises towards the far port side (facing port, n_lat < 0) and falls
    # away on starboard (n_lat > 0): |n_lat| = g / sqrt(1 + g^2) exactly.
    g = 0.2
    caster, surface = scene(grid_mesh(lambda X, Y: -10.0 - g * X))
    pos, R = north_pings(4)
    echoes = simulate_pings(
        caster, surface, pos, R, sonar, response, np.random.default_rng(0), absorption_db_m=ALPHA
    )
    valid = echoes.mask == MASK_VALID
    expected = g / math.sqrt(1 + g * g)
    np.testing.assert_allclose(echoes.n_lat[:, 0][valid[:, 0]], -expected, atol=1e-6)
    np.testing.assert_allclose(echoes.n_lat[:, 1][valid[:, 1]], expected, atol=1e-6)


def test_box_boulder_casts_geometric_shadow(sonar, response):
    # Floor 10 m below the sonar; a 2 m high box 10-12 m to port (x in [-12, -10]).
    floor = grid_mesh(lambda X, Y: np.full_like(X, -10.0))
    box = trimesh.creation.box(extents=[2.0, 12.0, 2.0])
    box.apply_translation([-11.0, 0.0, -9.0])
    caster, surface = scene(trimesh.util.concatenate([floor, box]))
    pos, R = north_pings(8)
    echoes = simulate_pings(
        caster, surface, pos, R, sonar, response, np.random.default_rng(0), absorption_db_m=ALPHA
    )
    r_bins, _ = range_bins(sonar)
    width = r_bins[1] - r_bins[0]
    # the ray over the box's far top edge (12 m out, 8 m down) meets the floor 15 m out
    start, end = math.hypot(12.0, 8.0), math.hypot(15.0, 10.0)
    power = _binned(echoes.power_raw, sonar.oversampling)
    for p in range(len(pos)):
        shadow = np.flatnonzero(echoes.mask[p, 0] & MASK_SHADOW)
        assert np.all(np.diff(shadow) == 1)
        assert abs(len(shadow) - (end - start) / width) <= 1
        assert abs(r_bins[shadow[0]] - start) <= width
        assert np.all(power[p, 0, shadow] == 0)
        # starboard sees an open floor: no shadow at all
        assert not np.any(echoes.mask[p, 1] & MASK_SHADOW)
    # layover: the sonar-facing wall (n_lat = -1) and the top (n_lat = 0) share the ranges
    # 12.8-14.1 m; those bins are valid, facing on average and brighter than open floor
    wall = (r_bins > 12.9) & (r_bins < 14.0)
    assert np.all(echoes.mask[:, 0, wall] == MASK_VALID)
    assert np.all((echoes.n_lat[:, 0, wall] < -0.3) & (echoes.n_lat[:, 0, wall] > -1.0))
    assert power[:, 0, wall].mean() > 3.0 * power[:, 1, wall].mean()


def test_receiver_quantises_and_water_column_holds_noise_only(sonar, response):
    echoes = _flat(sonar, response, 10.0, n=8)
    cal = calibrate_receiver(sonar, response, 0, 10.0, ALPHA)
    img = receive(echoes.power_raw, sonar, cal, np.random.default_rng(2), ALPHA)
    assert img.dtype == np.float32 and img.min() >= 0 and img.max() <= 1
    levels = img.astype(np.float64) * (2**sonar.quantisation_bits - 1)
    np.testing.assert_allclose(levels, np.round(levels), atol=1e-3)
    water = echoes.mask == MASK_WATER_COLUMN
    assert np.all(_binned(echoes.power_raw, sonar.oversampling)[water] == 0)
    assert img[water].max() < 0.2 * np.median(img[echoes.mask == MASK_VALID])
    with pytest.raises(ValueError, match="power_raw"):
        receive(echoes.power_raw[..., :-1], sonar, cal, np.random.default_rng(0), ALPHA)


def test_simulate_pings_validates_inputs(sonar, response):
    caster, surface = scene(grid_mesh(lambda X, Y: np.full_like(X, -10.0)))
    pos, R = north_pings(2)
    rng = np.random.default_rng(0)
    with pytest.raises(ValueError, match="positions"):
        simulate_pings(caster, surface, pos[:, :2], R, sonar, response, rng, absorption_db_m=0.3)
    with pytest.raises(ValueError, match="rotations"):
        simulate_pings(caster, surface, pos, R * 2, sonar, response, rng, absorption_db_m=0.3)
