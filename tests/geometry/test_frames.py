"""Golden tests for frames, attitude conversion and isotemporal arcs."""

import math

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from sss2bathy.geometry import (
    arc_point,
    arc_tangent,
    attitude_to_rotation,
    check_rotations,
    rotation_to_attitude,
)

FWD, LEFT, UP = np.eye(3)


@pytest.mark.parametrize(
    "heading_deg, forward, left",
    [
        (0.0, [0, 1, 0], [-1, 0, 0]),  # North: left is West
        (90.0, [1, 0, 0], [0, 1, 0]),  # East: left is North
        (180.0, [0, -1, 0], [1, 0, 0]),  # South: left is East
        (270.0, [-1, 0, 0], [0, -1, 0]),  # West: left is South
    ],
)
def test_headings(heading_deg, forward, left):
    R = attitude_to_rotation(np.array(math.radians(heading_deg)), np.array(0.0), np.array(0.0))
    np.testing.assert_allclose(R @ FWD, forward, atol=1e-12)
    np.testing.assert_allclose(R @ LEFT, left, atol=1e-12)
    np.testing.assert_allclose(R @ UP, [0, 0, 1], atol=1e-12)


def test_pitch_bow_up_raises_forward_axis():
    R = attitude_to_rotation(np.array(0.0), np.array(math.radians(10)), np.array(0.0))
    fwd = R @ FWD
    assert fwd[2] == pytest.approx(math.sin(math.radians(10)))
    assert fwd[1] == pytest.approx(math.cos(math.radians(10)))


def test_roll_starboard_down_raises_port():
    R = attitude_to_rotation(np.array(0.0), np.array(0.0), np.array(math.radians(5)))
    left = R @ LEFT
    assert left[2] == pytest.approx(math.sin(math.radians(5)))  # port side goes up


def test_batched_shapes_and_torch_in_torch_out():
    h = torch.rand(4, dtype=torch.float64)
    R = attitude_to_rotation(h, torch.zeros_like(h), torch.zeros_like(h))
    assert isinstance(R, torch.Tensor) and R.shape == (4, 3, 3)
    assert check_rotations(R).all()


@settings(max_examples=60, deadline=None)
@given(
    st.floats(0, 2 * math.pi - 1e-6),
    st.floats(-1.4, 1.4),
    st.floats(-math.pi + 1e-3, math.pi - 1e-3),
)
def test_attitude_round_trip(heading, pitch, roll):
    R = attitude_to_rotation(np.array(heading), np.array(pitch), np.array(roll))
    assert check_rotations(torch.as_tensor(R)).item()
    h2, p2, r2 = rotation_to_attitude(R)
    np.testing.assert_allclose(attitude_to_rotation(h2, p2, r2), R, atol=1e-9)
    assert float(p2) == pytest.approx(pitch, abs=1e-9)


def test_check_rotations_rejects_non_orthonormal():
    R = np.eye(3)[None].repeat(3, 0)
    R[1, 0, 0] = 1.1
    R[2] = np.diag([1.0, 1.0, -1.0])  # reflection
    assert check_rotations(torch.as_tensor(R)).tolist() == [True, False, False]


def test_arc_point_flat_level_sonar():
    # Heading North, level: port (side 0) looks West, starboard East.
    R = attitude_to_rotation(np.array(0.0), np.array(0.0), np.array(0.0))
    s = np.array([10.0, 20.0, -2.0])
    theta = np.array(math.radians(30))
    p_port = arc_point(s, R, np.array(10.0), theta, 0)
    p_stbd = arc_point(s, R, np.array(10.0), theta, 1)
    np.testing.assert_allclose(p_port, [10 - 10 * math.cos(theta), 20, -2 - 5], atol=1e-12)
    np.testing.assert_allclose(p_stbd, [10 + 10 * math.cos(theta), 20, -2 - 5], atol=1e-12)


def test_arc_point_range_is_exact():
    R = attitude_to_rotation(np.array([0.3, 2.0]), np.array([0.05, -0.1]), np.array([0.1, 0.2]))
    s = np.zeros((2, 3))
    p = arc_point(s, R, np.array([7.0, 9.0]), np.array([0.4, 1.0]), np.array([0, 1]))
    np.testing.assert_allclose(np.linalg.norm(p, axis=-1), [7.0, 9.0], atol=1e-12)


def test_arc_tangent_gradcheck_and_value():
    R = torch.as_tensor(
        attitude_to_rotation(np.array(0.7), np.array(0.1), np.array(-0.2)), dtype=torch.float64
    )
    s = torch.tensor([1.0, 2.0, 3.0], dtype=torch.float64)
    r = torch.tensor(12.0, dtype=torch.float64)
    theta = torch.tensor(0.5, dtype=torch.float64, requires_grad=True)
    for side in (0, 1):
        jac = torch.autograd.functional.jacobian(
            lambda t, side=side: arc_point(s, R, r, t, side), theta
        )
        np.testing.assert_allclose(jac, arc_tangent(R, r, theta.detach(), side), atol=1e-12)
        assert torch.autograd.gradcheck(lambda t, side=side: arc_point(s, R, r, t, side), (theta,))


def test_side_must_be_integer():
    with pytest.raises(ValueError, match="side"):
        arc_point(torch.zeros(3), torch.eye(3), torch.tensor(1.0), torch.tensor(0.1), 0.0)
