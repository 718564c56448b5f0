"""Physics oracles: thesis eqs 3.9-3.11 in NED/FRD, motor lag, drag and wind, ground."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from epc_offboard.common.frames import (
    GRAVITY_M_S2,
    euler_to_quat,
    quat_multiply,
    quat_to_rotation,
)
from sitl.params import EnvironmentParams, SurfaceParams, load_sim_config
from sitl.physics import (
    QUAT,
    RATE,
    ROTOR,
    VEL,
    Environment,
    QuadrotorModel,
    effectiveness_matrix,
    initial_state,
)

VEHICLE = load_sim_config().vehicle
ZERO3 = np.zeros(3)


def hover_speed(v=VEHICLE) -> float:
    return math.sqrt(v.mass_kg * GRAVITY_M_S2 / (4 * v.k_f_n_s2))


def spinning(speeds, pos_d=-10.0, rate=(0.0, 0.0, 0.0)):
    x = initial_state((0.0, 0.0, pos_d))
    x[ROTOR] = speeds
    x[RATE] = rate
    return x


def test_default_vehicle_hovers_at_a_realistic_normalised_thrust():
    assert 0.4 < VEHICLE.hover_thrust_norm < 0.6
    assert VEHICLE.mass_kg == pytest.approx(1.5)


def test_hover_thrust_balances_weight():
    model = QuadrotorModel(VEHICLE)
    w_h = hover_speed()
    x = spinning(np.full(4, w_h))
    dx = model.derivative(x, np.full(4, w_h), ZERO3, ZERO3)
    np.testing.assert_allclose(dx[VEL], 0.0, atol=1e-12)
    np.testing.assert_allclose(dx[RATE], 0.0, atol=1e-12)
    # and 10 % less thrust accelerates downwards (NED +d) by 0.1 g
    x = spinning(np.full(4, w_h * math.sqrt(0.9)))
    dx = model.derivative(x, x[ROTOR], ZERO3, ZERO3)
    assert dx[5] == pytest.approx(0.1 * GRAVITY_M_S2, rel=1e-9)


def test_free_fall_matches_closed_form():
    model = QuadrotorModel(dataclasses.replace(VEHICLE, drag_coeff_body_n_s_m=(0.0, 0.0, 0.0)))
    x = initial_state((0.0, 0.0, -100.0))
    dt = 0.001
    for _ in range(2000):
        x = model.step(x, np.zeros(4), ZERO3, ZERO3, dt)
    assert x[2] == pytest.approx(-100.0 + 0.5 * GRAVITY_M_S2 * 2.0**2, abs=1e-9)
    assert x[5] == pytest.approx(GRAVITY_M_S2 * 2.0, abs=1e-9)
    np.testing.assert_allclose(x[0:2], 0.0, atol=1e-12)


def test_pure_roll_torque_gives_euler_equation_acceleration():
    """Eq. 3.10: I dw/dt = tau - w x I w, with the gyroscopic term exercised (w != 0)."""
    model = QuadrotorModel(VEHICLE)
    tau_x = 0.2  # N m
    forces = np.linalg.solve(
        effectiveness_matrix(VEHICLE), [VEHICLE.mass_kg * GRAVITY_M_S2, tau_x, 0.0, 0.0]
    )
    speeds = np.sqrt(forces / VEHICLE.k_f_n_s2)
    w = np.array([0.3, -0.4, 0.5])
    dx = model.derivative(spinning(speeds, rate=w), speeds, ZERO3, ZERO3)
    inertia = np.diag(VEHICLE.inertia_diag_kg_m2)
    expected = np.linalg.solve(inertia, np.array([tau_x, 0.0, 0.0]) - np.cross(w, inertia @ w))
    np.testing.assert_allclose(dx[RATE], expected, rtol=1e-12, atol=1e-12)
    # at rest, only roll accelerates: tau / Ixx
    dx = model.derivative(spinning(speeds), speeds, ZERO3, ZERO3)
    np.testing.assert_allclose(dx[RATE], [tau_x / VEHICLE.inertia_diag_kg_m2[0], 0, 0], atol=1e-12)


def test_plus_layout_roll_row_is_thesis_eq_3_10():
    """Rotors 1 front, 2 left, 3 back, 4 right: tau_x = L (F_2 - F_4) as in the thesis."""
    plus = dataclasses.replace(VEHICLE, rotor_angles_deg=(0.0, -90.0, 180.0, 90.0))
    E = effectiveness_matrix(plus)
    forces = np.array([3.0, 4.0, 3.5, 2.5])
    assert (E @ forces)[1] == pytest.approx(plus.arm_length_m * (forces[1] - forces[3]))
    assert (E @ forces)[0] == pytest.approx(forces.sum())


def test_quaternion_stays_unit_under_tumbling():
    model = QuadrotorModel(VEHICLE)
    x = spinning(np.array([900.0, 300.0, 700.0, 500.0]), pos_d=-1000.0, rate=(2.0, -1.0, 3.0))
    cmd = np.array([1000.0, 200.0, 800.0, 400.0])
    for _ in range(3000):
        x = model.step(x, cmd, ZERO3, ZERO3, 0.001)
    assert np.linalg.norm(x[QUAT]) == pytest.approx(1.0, abs=1e-12)
    assert np.linalg.norm(x[RATE]) > 1.0  # it really tumbled


def test_motor_first_order_lag_and_speed_limit():
    model = QuadrotorModel(VEHICLE)
    tau = VEHICLE.motor_time_constant_s
    x = spinning(np.zeros(4), pos_d=-100.0)
    steps = round(tau / 0.0005)
    for _ in range(steps):
        x = model.step(x, np.full(4, 500.0), ZERO3, ZERO3, 0.0005)
    np.testing.assert_allclose(x[ROTOR], 500.0 * (1 - math.exp(-1.0)), rtol=1e-6)
    for _ in range(400):
        x = model.step(x, np.full(4, 5000.0), ZERO3, ZERO3, 0.0005)
    assert x[ROTOR].max() <= VEHICLE.rotor_speed_max_rad_s + 1e-9


def test_wind_acts_through_relative_airspeed_drag():
    """Steady state: a vehicle drifting with the wind feels no drag; held still, f = D w."""
    env = Environment(
        EnvironmentParams(wind_speed_m_s=3.0, wind_dir_deg=45.0), np.random.default_rng(0)
    )
    wind = env.wind_ned_m_s
    np.testing.assert_allclose(wind, [3 * math.sin(math.pi / 4), 3 * math.cos(math.pi / 4), 0])
    model = QuadrotorModel(VEHICLE)
    speeds = np.full(4, hover_speed())
    x = spinning(speeds)
    dx = model.derivative(x, speeds, wind, ZERO3)
    drag = np.asarray(VEHICLE.drag_coeff_body_n_s_m)
    np.testing.assert_allclose(dx[VEL] * VEHICLE.mass_kg, drag * wind, atol=1e-12)
    x[VEL] = wind
    np.testing.assert_allclose(model.derivative(x, speeds, wind, ZERO3)[VEL], 0.0, atol=1e-12)
    # drag acts in body axes: yawed 90 deg, north wind hits the body's y (right) coefficient
    x = spinning(speeds)
    x[QUAT] = euler_to_quat(0.0, 0.0, math.pi / 2)
    anisotropic = dataclasses.replace(VEHICLE, drag_coeff_body_n_s_m=(0.1, 0.4, 0.3))
    dx = QuadrotorModel(anisotropic).derivative(x, speeds, np.array([2.0, 0, 0]), ZERO3)
    assert dx[3] * VEHICLE.mass_kg == pytest.approx(0.4 * 2.0, rel=1e-9)


def test_gusts_are_seeded_and_have_the_configured_spread():
    params = EnvironmentParams(gust_std_m_s=1.0, gust_time_constant_s=0.5)

    def run(seed):
        env = Environment(params, np.random.default_rng(seed))
        out = []
        for _ in range(20000):
            env.advance(0.005)
            out.append(env.wind_ned_m_s.copy())
        return np.array(out)

    a, b = run(3), run(3)
    np.testing.assert_array_equal(a, b)
    assert not np.array_equal(a, run(4))
    assert a[:, 0].std() == pytest.approx(1.0, rel=0.15)
    assert a[:, 2].std() == pytest.approx(0.5, rel=0.15)


def test_ground_holds_a_vehicle_with_rotors_stopped():
    model = QuadrotorModel(VEHICLE)
    x = initial_state()
    for _ in range(100):
        x = model.step(x, np.zeros(4), np.array([5.0, 0, 0]), ZERO3, 0.001)
    np.testing.assert_array_equal(x[0:6], 0.0)


def test_near_surface_disturbance_pulls_towards_the_wall_and_decays():
    surface = SurfaceParams(
        enabled=True,
        point_ned_m=(5.0, 0.0, 0.0),
        normal_ned=(-1.0, 0, 0),
        peak_force_n=2.0,
        decay_length_m=0.5,
        range_m=3.0,
        fluctuation_rel=0.0,
    )
    env = Environment(EnvironmentParams(surface=surface), np.random.default_rng(0))
    near = env.surface_force_ned_n(np.array([4.5, 0.0, -2.0]))  # 0.5 m from the wall
    np.testing.assert_allclose(near, [2.0 * math.exp(-1.0), 0.0, 0.0])  # towards +north
    far = env.surface_force_ned_n(np.array([3.0, 0.0, -2.0]))
    assert 0.0 < far[0] < near[0]
    np.testing.assert_array_equal(env.surface_force_ned_n(np.array([1.0, 0, -2.0])), 0.0)


def test_plus_layout_mixer_has_the_thesis_eq_3_11_pattern():
    """Inverse effectiveness of the plus layout = eq. 3.11's sign pattern, with the pitch and
    yaw columns negated because body y and z flip between the thesis's z-up frame and FRD."""
    plus = dataclasses.replace(
        VEHICLE, rotor_angles_deg=(0.0, -90.0, 180.0, 90.0), rotor_yaw_moment_sign=(-1, 1, -1, 1)
    )
    thesis = np.array([[1, 0, -1, 1], [1, 1, 0, -1], [1, 0, 1, 1], [1, -1, 0, -1]])
    frd = thesis * np.array([1, 1, -1, -1])
    np.testing.assert_array_equal(
        np.sign(np.round(np.linalg.inv(effectiveness_matrix(plus)), 12)), frd
    )


def _matrix_form_derivative(x, rotor_cmd, wind, ext):
    """Eqs 3.9/3.10 as matrices (R(q), the effectiveness matrix, np.cross): the oracle the
    scalar arithmetic of QuadrotorModel must agree with."""
    v = VEHICLE
    q, w, o = x[QUAT], x[RATE], x[ROTOR]
    rot = quat_to_rotation(q)
    forces = v.k_f_n_s2 * o**2
    wrench = effectiveness_matrix(v) @ forces  # [collective N, tau_x, tau_y, tau_z N m]
    drag_body = -np.asarray(v.drag_coeff_body_n_s_m) * (rot.T @ (x[VEL] - wind))
    f_body = drag_body + np.array([0.0, 0.0, -wrench[0]])
    inertia = np.asarray(v.inertia_diag_kg_m2)
    dx = np.empty(17)
    dx[0:3] = x[VEL]
    dx[VEL] = (rot @ f_body + ext) / v.mass_kg + np.array([0.0, 0.0, GRAVITY_M_S2])
    dx[QUAT] = 0.5 * quat_multiply(q, np.array([0.0, *w]))
    dx[RATE] = (wrench[1:] - np.cross(w, inertia * w)) / inertia
    dx[ROTOR] = (rotor_cmd - o) / v.motor_time_constant_s
    return dx


def test_scalar_step_agrees_with_the_matrix_form_rk4():
    """step (plain-float arithmetic) against RK4 on the matrix-form equations, on random
    tilted, spinning, drifting states in wind with an external force."""
    model = QuadrotorModel(VEHICLE)
    rng = np.random.default_rng(7)
    dt = 0.001
    for _ in range(50):
        x = np.zeros(17)
        x[0:3] = rng.uniform(-5.0, 5.0, 3) - [0.0, 0.0, 10.0]
        x[VEL] = rng.uniform(-3.0, 3.0, 3)
        x[QUAT] = euler_to_quat(*rng.uniform(-0.6, 0.6, 3))
        x[RATE] = rng.uniform(-2.0, 2.0, 3)
        x[ROTOR] = rng.uniform(300.0, 900.0, 4)
        cmd = rng.uniform(200.0, 1000.0, 4)
        wind, ext = rng.uniform(-4.0, 4.0, 3), rng.uniform(-2.0, 2.0, 3)
        np.testing.assert_allclose(
            model.derivative(x, cmd, wind, ext),
            _matrix_form_derivative(x, cmd, wind, ext),
            rtol=1e-12, atol=1e-9,
        )  # fmt: skip
        k1 = _matrix_form_derivative(x, cmd, wind, ext)
        k2 = _matrix_form_derivative(x + 0.5 * dt * k1, cmd, wind, ext)
        k3 = _matrix_form_derivative(x + 0.5 * dt * k2, cmd, wind, ext)
        k4 = _matrix_form_derivative(x + dt * k3, cmd, wind, ext)
        expected = x + dt / 6.0 * (k1 + 2.0 * k2 + 2.0 * k3 + k4)
        expected[QUAT] /= np.linalg.norm(expected[QUAT])
        np.testing.assert_allclose(
            model.step(x, cmd, wind, ext, dt), expected, rtol=1e-12, atol=1e-9
        )
