"""Round trips and oracles for the frame conventions every other module relies on."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

from epc_offboard.common import frames

angles = st.floats(min_value=-math.pi, max_value=math.pi, allow_nan=False)
small_pitch = st.floats(min_value=-1.5, max_value=1.5, allow_nan=False)
vec3 = st.lists(st.floats(-1e3, 1e3, allow_nan=False), min_size=3, max_size=3)


@given(vec3)
def test_enu_ned_round_trip(v):
    v = np.array(v)
    np.testing.assert_allclose(frames.ned_to_enu(frames.enu_to_ned(v)), v)
    np.testing.assert_allclose(frames.enu_to_ned(frames.ned_to_enu(v)), v)


def test_enu_to_ned_axes():
    np.testing.assert_allclose(frames.enu_to_ned([1.0, 0.0, 0.0]), [0.0, 1.0, 0.0])  # east
    np.testing.assert_allclose(frames.enu_to_ned([0.0, 1.0, 0.0]), [1.0, 0.0, 0.0])  # north
    np.testing.assert_allclose(frames.enu_to_ned([0.0, 0.0, 1.0]), [0.0, 0.0, -1.0])  # up


def test_wind_directions_follow_the_thesis_convention():
    # towards +45 deg (counter-clockwise from east) = towards north-east
    w = frames.wind_vector_ned_m_s(3.0, 45.0)
    np.testing.assert_allclose(w, [3 / math.sqrt(2), 3 / math.sqrt(2), 0.0])
    # towards -135 deg = towards south-west
    w = frames.wind_vector_ned_m_s(1.5, -135.0)
    np.testing.assert_allclose(w, [-1.5 / math.sqrt(2), -1.5 / math.sqrt(2), 0.0], atol=1e-12)
    with pytest.raises(ValueError, match="speed"):
        frames.wind_vector_ned_m_s(-1.0, 0.0)
    with pytest.raises(ValueError, match="finite"):
        frames.wind_vector_ned_m_s(float("nan"), 0.0)


@given(angles, small_pitch, angles)
def test_euler_quat_matches_scipy_and_round_trips(roll, pitch, yaw):
    q = frames.euler_to_quat(roll, pitch, yaw)
    ref = Rotation.from_euler("ZYX", [yaw, pitch, roll]).as_matrix()
    np.testing.assert_allclose(frames.quat_to_rotation(q), ref, atol=1e-12)
    r2, p2, y2 = frames.quat_to_euler(q)
    np.testing.assert_allclose(
        frames.quat_to_rotation(frames.euler_to_quat(r2, p2, y2)), ref, atol=1e-9
    )


@given(angles, small_pitch, angles, angles, small_pitch, angles)
def test_quat_multiply_composes_rotations(r1, p1, y1, r2, p2, y2):
    q1 = frames.euler_to_quat(r1, p1, y1)
    q2 = frames.euler_to_quat(r2, p2, y2)
    np.testing.assert_allclose(
        frames.quat_to_rotation(frames.quat_multiply(q1, q2)),
        frames.quat_to_rotation(q1) @ frames.quat_to_rotation(q2),
        atol=1e-12,
    )
    np.testing.assert_allclose(
        frames.quat_multiply(q1, frames.quat_conjugate(q1)), [1.0, 0, 0, 0], atol=1e-12
    )


def test_quat_normalize_rejects_zero_and_nan():
    with pytest.raises(ValueError, match="quaternion"):
        frames.quat_normalize([0.0, 0.0, 0.0, 0.0])
    with pytest.raises(ValueError, match="quaternion"):
        frames.quat_normalize([float("nan"), 0.0, 0.0, 1.0])


@pytest.mark.parametrize(("a", "w"), [(0.0, 0.0), (math.pi, -math.pi), (3 * math.pi, -math.pi)])
def test_wrap_pi(a, w):
    assert frames.wrap_pi(a) == pytest.approx(w)


def test_tilt_and_angle_between_attitudes():
    import math

    from epc_offboard.common.frames import angle_between_deg, euler_to_quat, tilt_deg

    assert tilt_deg(euler_to_quat(0.0, 0.0, 1.2)) == pytest.approx(0.0, abs=1e-9)
    assert tilt_deg(euler_to_quat(math.radians(30), 0.0, 0.7)) == pytest.approx(30.0)
    assert tilt_deg(euler_to_quat(math.radians(170), 0.0, 0.0)) == pytest.approx(170.0)
    # roll then pitch: the tilt is the angle of body z from world down
    q = euler_to_quat(math.radians(30), math.radians(40), 0.0)
    assert tilt_deg(q) == pytest.approx(
        math.degrees(math.acos(math.cos(math.radians(30)) * math.cos(math.radians(40))))
    )
    a = euler_to_quat(0.0, 0.0, 0.1)
    assert angle_between_deg(a, a) == pytest.approx(0.0, abs=1e-6)
    assert angle_between_deg(a, -a) == pytest.approx(0.0, abs=1e-6)  # same attitude
    assert angle_between_deg(a, euler_to_quat(0.0, math.radians(50), 0.1)) == pytest.approx(50.0)
