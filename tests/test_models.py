"""Models: ZOH matrices, the exact accel <-> attitude map, the acceleration box."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from epc_offboard.common.frames import GRAVITY_M_S2
from epc_offboard.control.models import (
    AttitudeThrust,
    LinearModel,
    ModelError,
    accel_to_attitude,
    acceleration_box,
    acceleration_limits,
    attitude_model,
    attitude_to_accel,
    limit_tilt,
    position_model,
    position_model_lagged,
    velocity_disturbance_input,
)

HOVER = 0.5


def test_position_model_is_exact_zoh_double_integrator():
    dt = 0.05
    m = position_model(dt)
    I3 = np.eye(3)
    assert np.allclose(m.A, np.block([[I3, dt * I3], [0 * I3, I3]]), atol=1e-14)
    assert np.allclose(m.B, np.vstack([0.5 * dt * dt * I3, dt * I3]), atol=1e-14)
    assert m.dt_s == dt
    assert (m.nx, m.nu) == (6, 3)


def test_lagged_position_model_follows_the_command_with_a_first_order_lag():
    dt, tau = 0.05, (0.12, 0.12, 0.03)
    m = position_model_lagged(dt, tau)
    assert (m.nx, m.nu) == (9, 3)
    e = np.exp(-dt / np.array(tau))
    # a+ = e a + (1 - e) u, exactly (ZOH)
    assert np.allclose(m.A[6:, 6:], np.diag(e))
    assert np.allclose(m.B[6:, :], np.diag(1 - e))
    # p and v integrate a: against a fine Euler simulation of p' = v, v' = a, a' = (u - a)/tau
    x, u = np.array([0.1, -0.2, 0.0, 0.5, 0.0, -0.1, 0.3, -0.4, 1.0]), np.array([1.0, 2.0, -1.0])
    xf, h = x.copy(), dt / 20000
    for _ in range(20000):
        xf = xf + h * np.concatenate([xf[3:6], xf[6:9], (u - xf[6:9]) / np.array(tau)])
    assert np.allclose(m.step(x, u), xf, atol=1e-4)  # Euler's own error is ~3e-5
    # a held command is reached: the steady state is the double integrator's
    a = np.zeros(9)
    for _ in range(200):
        a = m.step(a, u)
    assert np.allclose(a[6:], u)
    # the disturbance enters v (and p) as an uncommanded acceleration, never a
    E = velocity_disturbance_input(m)
    assert np.allclose(E[:6], position_model(dt).B)
    assert np.all(E[6:] == 0.0)
    with pytest.raises(ModelError, match="tau_acc_s"):
        position_model_lagged(dt, (0.1, 0.0, 0.1))


def test_attitude_model_first_order_rate_response():
    dt, tau = 0.005, 0.03
    m = attitude_model(dt, tau)
    e = math.exp(-dt / tau)
    # rate: w+ = e w + (1 - e) w_cmd; angle: th+ = th + tau (1 - e) w + (dt - tau (1 - e)) w_cmd
    assert np.allclose(m.A[3:, 3:], e * np.eye(3))
    assert np.allclose(m.B[3:, :], (1 - e) * np.eye(3))
    assert np.allclose(m.A[:3, 3:], tau * (1 - e) * np.eye(3))
    assert np.allclose(m.B[:3, :], (dt - tau * (1 - e)) * np.eye(3))
    # a held command is followed: rates converge to it
    x = np.zeros(6)
    for _ in range(400):
        x = m.step(x, [0.5, -0.2, 0.1])
    assert np.allclose(x[3:], [0.5, -0.2, 0.1], atol=1e-6)


@pytest.mark.parametrize(
    ("A", "B", "c", "msg"),
    [
        (np.eye(2), np.ones((3, 1)), None, "B must be"),
        (np.ones((2, 3)), np.ones((2, 1)), None, "A must be square"),
        (np.eye(2), np.ones((2, 1)), [1.0], "c must have shape"),
        (np.eye(2) * np.nan, np.ones((2, 1)), None, "non-finite"),
    ],
)
def test_linear_model_rejects_bad_shapes(A, B, c, msg):
    with pytest.raises(ModelError, match=msg):
        LinearModel(A, B, c)


def test_cancelling_input_cancels_a_perturbation_in_range_of_b():
    m = position_model(0.1)
    p = m.B @ np.array([0.3, -0.1, 0.2])
    assert np.allclose(m.B @ m.cancelling_input(p) + p, 0.0, atol=1e-14)


def test_hover_is_level_with_hover_thrust():
    sp = accel_to_attitude([0.0, 0.0, 0.0], 0.7, HOVER)
    assert sp.roll_rad == pytest.approx(0.0, abs=1e-15)
    assert sp.pitch_rad == pytest.approx(0.0, abs=1e-15)
    assert sp.thrust_norm == pytest.approx(HOVER)


@pytest.mark.parametrize("yaw", [0.0, 0.4, math.pi / 2, -2.0])
def test_small_angles_match_thesis_3_13_in_ned(yaw):
    a_n, a_e, a_d = 0.02, -0.03, 0.01
    sp = accel_to_attitude([a_n, a_e, a_d], yaw, HOVER)
    g = GRAVITY_M_S2
    assert sp.roll_rad == pytest.approx((a_e * math.cos(yaw) - a_n * math.sin(yaw)) / g, abs=1e-5)
    assert sp.pitch_rad == pytest.approx(-(a_n * math.cos(yaw) + a_e * math.sin(yaw)) / g,
                                         abs=1e-5)
    # moving down needs less thrust
    assert sp.thrust_norm == pytest.approx(HOVER * (g - a_d) / g, abs=1e-5)


@settings(max_examples=60, deadline=None)
@given(
    a=st.lists(st.floats(-8.0, 8.0), min_size=3, max_size=3),
    yaw=st.floats(-math.pi, math.pi),
)
def test_accel_attitude_round_trip(a, yaw):
    a_ned = np.array(a)
    a_ned[2] = min(a_ned[2], 5.0)  # keep some upward thrust
    sp = accel_to_attitude(a_ned, yaw, HOVER)
    assert np.allclose(attitude_to_accel(sp, HOVER), a_ned, atol=1e-9)
    back = accel_to_attitude(attitude_to_accel(sp, HOVER), yaw, HOVER)
    assert back.roll_rad == pytest.approx(sp.roll_rad, abs=1e-9)
    assert back.pitch_rad == pytest.approx(sp.pitch_rad, abs=1e-9)


def test_attitude_to_accel_tilts_the_right_way():
    # NED/FRD: positive roll accelerates east, nose-down (negative pitch) accelerates north
    a = attitude_to_accel(AttitudeThrust(0.1, 0.0, 0.0, HOVER), HOVER)
    assert a[1] > 0
    a = attitude_to_accel(AttitudeThrust(0.0, -0.1, 0.0, HOVER), HOVER)
    assert a[0] > 0


@pytest.mark.parametrize("tilt_deg", [20.0, 35.0, 60.0])
def test_acceleration_box_corners_are_flyable(tilt_deg):
    tilt = math.radians(tilt_deg)
    t_min, t_max = 0.1, 0.9
    box = acceleration_box(tilt, t_min, t_max, HOVER)
    assert np.all(box.u_min < 0)
    assert np.all(box.u_max > 0)
    for ix in (0, 1):
        for iy in (0, 1):
            for iz in (0, 1):
                a = np.array([
                    (box.u_min, box.u_max)[ix][0],
                    (box.u_min, box.u_max)[iy][1],
                    (box.u_min, box.u_max)[iz][2],
                ])
                sp = accel_to_attitude(a, 0.3, HOVER)
                tilt_now = math.acos(math.cos(sp.roll_rad) * math.cos(sp.pitch_rad))
                assert tilt_now <= tilt + 1e-9
                assert t_min - 1e-9 <= sp.thrust_norm <= t_max + 1e-9


def test_acceleration_box_rejects_limits_not_bracketing_hover():
    with pytest.raises(ModelError, match="bracket hover"):
        acceleration_box(0.5, 0.6, 0.9, HOVER)


LIMITS_45 = acceleration_limits(math.radians(45.0), 0.08, 0.95, HOVER)


def tilt_and_thrust(a):
    sp = accel_to_attitude(a, 0.3, HOVER)
    return math.acos(math.cos(sp.roll_rad) * math.cos(sp.pitch_rad)), sp.thrust_norm


@settings(max_examples=300, deadline=None)
@given(
    a=st.tuples(st.floats(-12, 12), st.floats(-12, 12), st.floats(-6, 6)),
    tilt_deg=st.sampled_from([20.0, 35.0, 45.0, 60.0]),
)
def test_every_acceleration_within_the_limits_is_flyable(a, tilt_deg):
    lim = acceleration_limits(math.radians(tilt_deg), 0.08, 0.95, HOVER)
    a = np.array(a)
    if not lim.contains(a):
        return
    tilt, thrust = tilt_and_thrust(a)
    assert tilt <= math.radians(tilt_deg) + 1e-9
    assert 0.08 - 1e-9 <= thrust <= 0.95 + 1e-9


def test_one_axis_gets_the_cone_when_the_other_needs_nothing():
    """The box of tilt / sqrt(2) per axis gave about 14 deg per axis at 35 deg; the polygon
    gives an axis 92 % of the cone's reach at hover thrust."""
    reach = math.tan(math.radians(45.0)) * GRAVITY_M_S2
    assert LIMITS_45.contains(np.array([0.92 * reach, 0.0, 0.0]))
    assert LIMITS_45.contains(np.array([0.0, -0.92 * reach, 0.0]))
    assert LIMITS_45.contains(np.array([0.65 * reach, 0.65 * reach, 0.0]))
    assert not LIMITS_45.contains(np.array([0.75 * reach, 0.75 * reach, 0.0]))  # > 45 deg
    old = acceleration_box(math.radians(45.0), 0.08, 0.95, HOVER)
    assert old.u_max[0] < 0.5 * reach


@settings(max_examples=200, deadline=None)
@given(a=st.tuples(st.floats(-50, 50), st.floats(-50, 50), st.floats(-50, 50)))
def test_limit_tilt_always_lands_inside_and_keeps_what_is_inside(a):
    a = np.array(a)
    out = limit_tilt(a, LIMITS_45)
    assert LIMITS_45.contains(out, tol=1e-9)
    if LIMITS_45.contains(a):
        assert np.allclose(out, a)
    tilt, _ = tilt_and_thrust(out)
    assert tilt <= math.radians(45.0) + 1e-9


# The Neural-Fly plant's envelope (config/vehicles/neuralfly_1500g.toml: hover 0.52)
NF_HOVER = 0.5204


@settings(max_examples=300, deadline=None)
@given(
    a=st.tuples(st.floats(-15, 15), st.floats(-15, 15), st.floats(-9, 6)),
    tilt_deg=st.sampled_from([20.0, 35.0, 45.0, 60.0]),
    share=st.sampled_from([0.3, 0.5, 0.7, 0.9]),
    hover=st.sampled_from([HOVER, NF_HOVER, 0.7]),
)
def test_every_acceleration_within_the_thrust_facets_is_flyable(a, tilt_deg, share, hover):
    lim = acceleration_limits(math.radians(tilt_deg), 0.08, 0.95, hover,
                              vertical_share=share, thrust_facets=True)  # fmt: skip
    a = np.array(a)
    out = limit_tilt(a, lim)
    assert lim.contains(out, tol=1e-9)
    if lim.contains(a):
        assert np.allclose(out, a)
    sp = accel_to_attitude(out, 0.3, hover)
    tilt = math.acos(math.cos(sp.roll_rad) * math.cos(sp.pitch_rad))
    assert tilt <= math.radians(tilt_deg) + 1e-9
    assert 0.08 - 1e-9 <= sp.thrust_norm <= 0.95 + 1e-9


def test_the_thrust_facets_let_a_tilted_vehicle_climb_with_the_thrust_it_has():
    """Tilted 30 deg into 12 m/s of wind (7.7 m/s^2 of drag to hold), the Neural-Fly plant
    has 17.9 m/s^2 of specific thrust, 15.5 of it vertical at that tilt. The vertical cap
    f_max cos(45 deg) allowed a climb of 2.85 m/s^2 at any tilt (the 25 cm sag climbing
    upwind, issue 24); the facets allow the vertical share's 4.05, and the tilt limit's
    corner at the cap stays as it was."""
    tilt = math.radians(45.0)
    capped = acceleration_limits(tilt, 0.08, 0.95, NF_HOVER)
    facets = acceleration_limits(tilt, 0.08, 0.95, NF_HOVER, thrust_facets=True)
    climb = np.array([7.7, 0.0, -4.0])
    assert not capped.contains(climb)
    assert facets.contains(climb)
    assert capped.u_min[2] == pytest.approx(-2.85, abs=0.01)
    f_max = GRAVITY_M_S2 * 0.95 / NF_HOVER
    assert facets.u_min[2] == pytest.approx(-0.5 * (f_max - GRAVITY_M_S2))
    # north at the cap's f_z, 1 % inside the tilt row
    corner = np.array([0.99 * (capped.p[0] - capped.P[0, 2] * capped.u_min[2]), 0.0,
                       capped.u_min[2]])  # fmt: skip
    assert capped.contains(corner)
    assert facets.contains(corner)
    # a climb the sphere has no thrust for stays out: |f| = 18.4 > 17.9 m/s^2
    assert not facets.contains(np.array([11.0, 0.0, -4.0]))
