"""Property-based tests (hypothesis): the survey line loader round-trips every valid line
and rejects every broken one with SurveyFormatError (never another exception); the
geometry keeps rotations orthonormal, head-plane normals unit and arc points at range."""

from __future__ import annotations

import math
import zipfile
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from sss2bathy.geometry import (
    arc_point,
    attitude_to_rotation,
    check_rotations,
    head_plane_normal,
    head_plane_normal_from_gradient,
    rotation_to_attitude,
)
from sss2bathy.survey import SensorParams, SidescanLine, SurveyFormatError

SETTINGS = settings(
    max_examples=60, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture]
)
SENSOR = SensorParams(math.radians(30.0), math.radians(60.0))
ANGLE = st.floats(-10.0, 10.0, allow_nan=False)
KEYS = ("time_s", "position", "rotation", "altitude_m", "intensity", "range_m")


@st.composite
def line_arrays(draw) -> dict[str, np.ndarray]:
    """Arrays of a valid line: increasing times and ranges, proper rotations, NaN altitudes
    allowed (missing readings), any finite intensities."""
    P = draw(st.integers(1, 6))
    B = draw(st.integers(1, 5))
    finite = st.floats(-1e4, 1e4, allow_nan=False)
    steps = np.array(draw(st.lists(st.floats(1e-3, 10.0), min_size=P, max_size=P)))
    angles = np.array(draw(st.lists(ANGLE, min_size=3 * P, max_size=3 * P))).reshape(3, P)
    altitude = np.array(
        draw(st.lists(st.one_of(st.floats(0.0, 100.0), st.just(math.nan)), min_size=P, max_size=P))
    )
    gaps = np.array(draw(st.lists(st.floats(1e-2, 5.0), min_size=B, max_size=B)))
    return {
        "time_s": draw(st.floats(-1e5, 1e5)) + np.cumsum(steps),
        "position": np.array(draw(st.lists(finite, min_size=3 * P, max_size=3 * P))).reshape(P, 3),
        "rotation": np.asarray(attitude_to_rotation(*angles)),
        "altitude_m": altitude.astype(np.float32),
        "intensity": np.array(
            draw(st.lists(st.floats(0.0, 1e6, width=32), min_size=2 * P * B, max_size=2 * P * B)),
            dtype=np.float32,
        ).reshape(P, 2, B),
        "range_m": np.cumsum(gaps).astype(np.float32),
    }


def _save(path: Path, arrays: dict) -> Path:
    with open(path, "wb") as f:
        np.savez(f, **arrays)
    return path


@SETTINGS
@given(arrays=line_arrays())
def test_valid_lines_round_trip(tmp_path, arrays):
    line = SidescanLine.load(_save(tmp_path / "a.npz", arrays), "a", SENSOR)
    line.save(tmp_path / "b.npz")
    again = SidescanLine.load(tmp_path / "b.npz", "a", SENSOR)
    for key in KEYS:
        np.testing.assert_array_equal(getattr(again, key), getattr(line, key))
        np.testing.assert_array_equal(
            getattr(line, key), np.asarray(arrays[key], dtype=getattr(line, key).dtype)
        )


def _break(arrays: dict, how: str, k: int) -> tuple[dict, str]:
    """One defect; returns the broken arrays and the field the error must name."""
    a = {key: np.array(v, copy=True) for key, v in arrays.items()}
    P = a["time_s"].shape[0]
    B = a["range_m"].shape[0]
    if how == "nan_time":
        a["time_s"][k % P] = np.nan
        return a, "time_s"
    if how == "unsorted_time":
        if P < 2:
            a["time_s"] = np.zeros((0,))
        else:
            i = k % (P - 1)
            a["time_s"][i + 1] = a["time_s"][i] - (k % 3)
        return a, "time_s"
    if how == "nan_position":
        a["position"][k % P, k % 3] = np.nan
        return a, "position"
    if how == "position_shape":
        a["position"] = a["position"][:, :2]
        return a, "position"
    if how == "scaled_rotation":
        a["rotation"][k % P] *= 1.5
        return a, "rotation"
    if how == "nan_rotation":
        a["rotation"][k % P, 0, 0] = np.nan
        return a, "rotation"
    if how == "negative_altitude":
        a["altitude_m"][k % P] = -1.0 - k
        return a, "altitude_m"
    if how == "intensity_shape":
        a["intensity"] = a["intensity"][:, :1]
        return a, "intensity"
    if how == "unsorted_range":
        a["range_m"] = np.full(B + 1, 3.0, np.float32)
        return a, "range_m"
    if how == "negative_range":
        a["range_m"] = a["range_m"] - a["range_m"].max() - 1.0
        return a, "range_m"
    if how == "missing_key":
        key = KEYS[k % len(KEYS)]
        del a[key]
        return a, key
    if how == "object_array":
        a["position"] = np.empty(P, dtype=object)
        return a, "file"
    raise AssertionError(how)


DEFECTS = [
    "nan_time",
    "unsorted_time",
    "nan_position",
    "position_shape",
    "scaled_rotation",
    "nan_rotation",
    "negative_altitude",
    "intensity_shape",
    "unsorted_range",
    "negative_range",
    "missing_key",
    "object_array",
]


@SETTINGS
@given(arrays=line_arrays(), how=st.sampled_from(DEFECTS), k=st.integers(0, 100))
def test_broken_lines_raise_survey_format_error_naming_the_field(tmp_path, arrays, how, k):
    broken, field = _break(arrays, how, k)
    with pytest.raises(SurveyFormatError) as err:
        SidescanLine.load(_save(tmp_path / "x.npz", broken), "x", SENSOR)
    assert err.value.field == field and "x.npz" in str(err.value)


def test_non_numeric_arrays_raise_survey_format_error(tmp_path):
    arrays = {
        "time_s": np.array(["t0", "t1"]),
        "position": np.zeros((2, 3)),
        "rotation": np.stack([np.eye(3)] * 2),
        "altitude_m": np.ones(2, np.float32),
        "intensity": np.ones((2, 2, 3), np.float32),
        "range_m": np.arange(1.0, 4.0, dtype=np.float32),
    }
    with pytest.raises(SurveyFormatError, match="time_s"):
        SidescanLine.load(_save(tmp_path / "x.npz", arrays), "x", SENSOR)


@SETTINGS
@given(arrays=line_arrays(), cut=st.floats(0.0, 0.99), junk=st.binary(max_size=64))
def test_truncated_or_garbage_files_raise_survey_format_error(tmp_path, arrays, cut, junk):
    path = _save(tmp_path / "t.npz", arrays)
    data = path.read_bytes()
    path.write_bytes(data[: int(cut * len(data))] + junk)
    try:
        line = SidescanLine.load(path, "t", SENSOR)
    except SurveyFormatError as err:
        assert err.field == "file" or err.field in KEYS
    else:  # only when the damage left a complete archive (junk after the end)
        assert zipfile.is_zipfile(path) and line.n_pings == arrays["time_s"].shape[0]


# ------------------------------------------------------------------ geometry
@settings(max_examples=200, deadline=None)
@given(heading=ANGLE, pitch=ANGLE, roll=ANGLE)
def test_rotations_are_orthonormal_and_invert(heading, pitch, roll):
    R = np.asarray(attitude_to_rotation(np.array(heading), np.array(pitch), np.array(roll)))
    np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-12)
    assert np.linalg.det(R) == pytest.approx(1.0, abs=1e-12)
    assert bool(check_rotations(R))
    if abs(math.cos(pitch)) > 1e-3:  # away from gimbal lock the attitude comes back
        again = np.asarray(attitude_to_rotation(*rotation_to_attitude(R)))
        np.testing.assert_allclose(again, R, atol=1e-9)


@settings(max_examples=200, deadline=None)
@given(
    normal=st.lists(st.floats(-1e3, 1e3), min_size=3, max_size=3),
    side=st.integers(0, 1),
    dzdx=st.floats(-20.0, 20.0),
    dzdy=st.floats(-20.0, 20.0),
    angles=st.lists(ANGLE, min_size=3, max_size=3),
)
def test_head_plane_normals_are_unit(normal, side, dzdx, dzdy, angles):
    n = np.array(normal)
    n_lat, n_up = head_plane_normal(n, side)
    if math.hypot(n[1], n[2]) > 1e-3:
        assert n_lat**2 + n_up**2 == pytest.approx(1.0, abs=1e-9)
        # (a subnormal n_z may underflow to 0 when divided by the norm)
        assert np.sign(n_up) == np.sign(n[2]) or abs(n[2]) < 1e-300
    R = np.asarray(attitude_to_rotation(*np.array(angles)))
    n_lat, n_up = head_plane_normal_from_gradient(np.array(dzdx), np.array(dzdy), R, side)
    assert n_lat**2 + n_up**2 == pytest.approx(1.0, abs=1e-9)
    with pytest.raises(ValueError, match="side"):
        head_plane_normal(n, 0.5)


@settings(max_examples=200, deadline=None)
@given(
    sonar=st.lists(st.floats(-1e5, 1e5), min_size=3, max_size=3),
    angles=st.lists(ANGLE, min_size=3, max_size=3),
    range_m=st.floats(1e-3, 500.0),
    theta=st.floats(-math.pi, math.pi),
    side=st.integers(0, 1),
)
def test_arc_points_lie_at_the_slant_range(sonar, angles, range_m, theta, side):
    s = np.array(sonar)
    R = np.asarray(attitude_to_rotation(*np.array(angles)))
    p = arc_point(s, R, np.array(range_m), np.array(theta), side)
    assert np.linalg.norm(p - s) == pytest.approx(range_m, rel=1e-9, abs=1e-9)
    # the point is in the head's plane: no component along the vehicle's forward axis
    assert abs(float((p - s) @ R[:, 0])) <= 1e-9 * max(range_m, 1.0)
