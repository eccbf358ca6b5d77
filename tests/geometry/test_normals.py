"""Golden tests for eq. 1-3 (world, vehicle and head-plane normals) and angles."""

import math

import numpy as np
import pytest
import torch

from sss2bathy.geometry import (
    arc_point,
    attitude_to_rotation,
    grazing_angle,
    head_plane_normal,
    head_plane_normal_from_gradient,
    incidence_angle,
    vehicle_normal,
    world_normal,
)


def _R(heading_deg=0.0, pitch_deg=0.0, roll_deg=0.0):
    return attitude_to_rotation(
        np.array(math.radians(heading_deg)),
        np.array(math.radians(pitch_deg)),
        np.array(math.radians(roll_deg)),
    )


def test_flat_seafloor_gives_exact_up_normal():
    n = world_normal(np.zeros(5), np.zeros(5))
    np.testing.assert_array_equal(n, np.tile([0.0, 0.0, 1.0], (5, 1)))
    for side in (0, 1):
        n_lat, n_up = head_plane_normal_from_gradient(np.array(0.0), np.array(0.0), _R(37), side)
        assert float(n_lat) == pytest.approx(0.0, abs=1e-12)
        assert float(n_up) == pytest.approx(1.0)


@pytest.mark.parametrize("heading", [0.0, 90.0, 180.0, 270.0])
def test_plane_tilted_towards_and_away_from_each_head(heading):
    slope = 0.25
    R = _R(heading)
    left = R @ np.array([0.0, 1.0, 0.0])  # world direction of port
    # Height falls towards port: dz along +left = -slope -> port sees it tilted away.
    grad = -slope * left[:2]
    n_port, _ = head_plane_normal_from_gradient(np.array(grad[0]), np.array(grad[1]), R, 0)
    n_stbd, _ = head_plane_normal_from_gradient(np.array(grad[0]), np.array(grad[1]), R, 1)
    expected = slope / math.sqrt(1 + slope**2)
    assert float(n_port) == pytest.approx(expected, abs=1e-12)  # away from port: positive
    assert float(n_stbd) == pytest.approx(-expected, abs=1e-12)  # faces starboard: negative


def test_along_track_slope_does_not_change_n_lat():
    R = _R(0)
    n_lat, n_up = head_plane_normal_from_gradient(np.array(0.0), np.array(0.4), R, 0)
    assert float(n_lat) == pytest.approx(0.0, abs=1e-12)
    assert float(n_up) == pytest.approx(1.0)


def test_roll_shows_up_as_n_lat_on_flat_seafloor():
    # Rolled starboard-down by 10 degrees, flat seafloor looks tilted in the head plane.
    R = _R(0, 0, 10)
    n_port, _ = head_plane_normal_from_gradient(np.array(0.0), np.array(0.0), R, 0)
    n_stbd, _ = head_plane_normal_from_gradient(np.array(0.0), np.array(0.0), R, 1)
    s10 = math.sin(math.radians(10))
    # N_v = R^T z; port axis is raised so world up has a -y component in the vehicle frame.
    assert float(n_port) == pytest.approx(s10, abs=1e-12)
    assert float(n_stbd) == pytest.approx(-s10, abs=1e-12)


def test_pitch_keeps_head_plane_normal_of_flat_seafloor():
    R = _R(45, 8, 0)
    n_lat, n_up = head_plane_normal_from_gradient(np.array(0.0), np.array(0.0), R, 0)
    assert float(n_lat) == pytest.approx(0.0, abs=1e-12)
    assert float(n_up) == pytest.approx(1.0)


def test_vehicle_normal_round_trip():
    R = _R(123, 4, -7)
    N = np.array([0.1, -0.3, 1.0])
    np.testing.assert_allclose(R @ vehicle_normal(N, R), N, atol=1e-12)


def test_head_plane_normal_is_unit_and_gradcheck():
    g = torch.tensor([[0.2, -0.1], [0.0, 0.5], [-0.7, 0.3]], dtype=torch.float64)
    R = torch.as_tensor(_R(30, 5, -3), dtype=torch.float64).expand(3, 3, 3)
    side = torch.tensor([0, 1, 0])

    def f(grad):
        return head_plane_normal_from_gradient(grad[:, 0], grad[:, 1], R, side)

    n_lat, n_up = f(g)
    np.testing.assert_allclose((n_lat**2 + n_up**2).numpy(), 1.0, atol=1e-12)
    assert torch.autograd.gradcheck(lambda x: f(x)[0], (g.clone().requires_grad_(),))


def test_incidence_and_grazing_on_flat_seafloor():
    s = np.array([0.0, 0.0, 0.0])
    R = _R(0)
    theta = math.radians(30)
    p = arc_point(s, R, np.array(20.0), np.array(theta), 0)
    n = world_normal(np.array(0.0), np.array(0.0))
    # Flat seafloor: grazing angle equals the depression angle.
    assert float(grazing_angle(n, p, s)) == pytest.approx(theta)
    assert float(incidence_angle(n, p, s)) == pytest.approx(math.pi / 2 - theta)


def test_head_plane_normal_sign_convention_matches_darkness():
    # A surface facing the sonar has a larger cos(incidence) and negative n_lat.
    R, s = _R(0), np.zeros(3)
    p = arc_point(s, R, np.array(20.0), np.array(math.radians(30)), 0)  # port = West
    facing = world_normal(np.array(-0.3), np.array(0.0))  # rises to the West: faces the sonar
    away = world_normal(np.array(0.3), np.array(0.0))
    assert incidence_angle(facing, p, s) < incidence_angle(away, p, s)
    assert head_plane_normal(vehicle_normal(facing, R), 0)[0] < 0
    assert head_plane_normal(vehicle_normal(away, R), 0)[0] > 0
