"""The autopilot's state machine and controllers, without any networking."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from epc_offboard.common.frames import euler_to_quat, quat_to_euler, quat_to_rotation
from sitl.autopilot import (
    HOLD,
    IGNORE_ATTITUDE,
    IGNORE_THRUST,
    IGNORE_YAW_RATE,
    LAND,
    OFFBOARD,
    TAKEOFF,
    AttitudeSetpoint,
    Autopilot,
    LandedState,
    Mode,
    PositionSetpoint,
    Result,
    attitude_from_thrust,
    quat_from_rotation,
)
from sitl.params import load_sim_config
from sitl.physics import initial_state
from sitl.simulation import Simulation

PX4_CONFIG = load_sim_config()
# most tests arm at once, and see a setpoint at once: the refusal after boot and the
# setpoints' dead time have tests of their own
CONFIG = dataclasses.replace(
    PX4_CONFIG,
    autopilot=dataclasses.replace(
        PX4_CONFIG.autopilot, arm_refusals_after_boot=0, rate_dead_time_s=0.0
    ),
)
LOSS_S = CONFIG.autopilot.offboard_loss_timeout_s
LEVEL = (1.0, 0.0, 0.0, 0.0)
RATES_ONLY = IGNORE_ATTITUDE  # body rates + thrust


def sp(thrust=0.5, q=LEVEL, rates=(0.0, 0.0, 0.0), mask=0b111):
    return AttitudeSetpoint(type_mask=mask, q_wxyz=q, rate_frd_rad_s=rates, thrust_norm=thrust)


def autopilot() -> Autopilot:
    ap = Autopilot(CONFIG.vehicle, CONFIG.autopilot)
    ap.update_outer(initial_state(), 0.0, 0.005)
    return ap


def stream(ap: Autopilot, t0: float, t1: float, hz: float = 50.0, **kw) -> None:
    for k in range(round((t1 - t0) * hz)):
        ap.on_attitude_setpoint(sp(**kw), t0 + k / hz)


def test_custom_mode_encoding_is_px4s():
    assert HOLD.custom_mode == 0x03040000
    assert OFFBOARD.custom_mode == 6 << 16
    assert TAKEOFF.custom_mode == (4 << 16) | (2 << 24)
    assert LAND.custom_mode == (4 << 16) | (6 << 24)


def test_arming_and_mode_rules_on_the_ground():
    ap = autopilot()
    assert ap.mode == HOLD
    assert not ap.armed
    assert ap.takeoff(None, 0.0) == Result.DENIED  # must arm first
    assert ap.set_mode(Mode(5), 0.0) == Result.UNSUPPORTED  # ACRO
    assert ap.set_mode(OFFBOARD, 0.0) == Result.DENIED  # no setpoint stream
    assert ap.arm(True, 0.0) == Result.ACCEPTED
    assert ap.armed
    assert ap.arm(False, 1.0) == Result.ACCEPTED


def test_offboard_needs_a_stream_above_2_hz_and_fails_safe_to_hold():
    ap = autopilot()
    x = initial_state()
    ap.arm(True, 0.0)
    ap.on_attitude_setpoint(sp(), 0.0)
    assert ap.set_mode(OFFBOARD, 0.6) == Result.DENIED  # last setpoint 0.6 s old: < 2 Hz
    ap.on_attitude_setpoint(sp(), 0.6)
    assert ap.set_mode(OFFBOARD, 1.11) == Result.DENIED  # 0.51 s since the last one
    stream(ap, 1.0, 2.0, hz=4.0)
    assert ap.set_mode(OFFBOARD, 2.0) == Result.ACCEPTED
    ap.update_outer(x, 2.0, 0.005)
    assert ap.mode == OFFBOARD
    ap.update_outer(x, 1.75 + LOSS_S - 0.01, 0.005)  # last setpoint at 1.75 s: COM_OF_LOSS_T
    assert ap.mode == OFFBOARD
    ap.update_outer(x, 1.75 + LOSS_S + 0.01, 0.005)
    assert ap.mode == HOLD
    assert ap.failsafe_count == 1
    # the failsafe clears when setpoints stream again: back to Offboard, as PX4
    stream(ap, 3.0, 3.2, hz=50.0)
    ap.update_outer(x, 3.2, 0.005)
    assert ap.mode == OFFBOARD
    # an explicit Hold is the pilot's choice: setpoints no longer bring Offboard back
    assert ap.set_mode(HOLD, 3.3) == Result.ACCEPTED
    stream(ap, 3.3, 3.5, hz=50.0)
    ap.update_outer(x, 3.5, 0.005)
    assert ap.mode == HOLD


def test_px4_accepts_the_first_arming_after_boot_by_default():
    """As PX4 main + SIH did in independent flights: its arming checks refuse only while the
    estimator is not ready, which a client that waits for state does not meet."""
    ap = Autopilot(PX4_CONFIG.vehicle, PX4_CONFIG.autopilot)
    ap.update_outer(initial_state(), 0.0, 0.005)
    assert ap.arm(True, 0.0) == Result.ACCEPTED
    assert ap.status_text is None


def test_a_configured_refusal_after_boot_says_why_as_px4_and_a_retry_succeeds():
    autopilot = dataclasses.replace(PX4_CONFIG.autopilot, arm_refusals_after_boot=1)
    ap = Autopilot(PX4_CONFIG.vehicle, autopilot)
    ap.update_outer(initial_state(), 0.0, 0.005)
    assert ap.arm(True, 0.0) == Result.DENIED
    assert ap.status_text == "Preflight Fail: heading estimate not stable"
    assert not ap.armed
    assert ap.arm(True, 0.5) == Result.ACCEPTED  # the retry succeeds
    assert ap.armed


def fly(sim: Simulation, seconds: float) -> None:
    for _ in range(round(seconds / sim.config.sitl.lockstep_period_s)):
        sim.advance_tick()


def test_a_takeoff_without_altitude_climbs_from_the_current_altitude_every_time():
    """PX4: NaN altitude = current altitude + MIS_TAKEOFF_ALT, each time it is accepted, in
    the air too. This is what made a repeated takeoff climb to 98 m."""
    sim = Simulation(CONFIG, seed=0)
    ap = sim.autopilot
    step_m = CONFIG.autopilot.takeoff_altitude_m
    assert ap.arm(True, 0.0) == Result.ACCEPTED
    for _ in range(3):
        before_m = -sim.state[2]
        assert ap.takeoff(None, sim.time_s) == Result.ACCEPTED
        fly(sim, 2.0 + step_m / CONFIG.autopilot.climb_speed_m_s)
        assert -sim.state[2] == pytest.approx(before_m + step_m, abs=0.3)
    assert -sim.state[2] > 3 * step_m - 0.3
    # an explicit altitude (above home) is where it goes; below the current one it stays
    assert ap.takeoff(10.0, sim.time_s) == Result.ACCEPTED
    fly(sim, 6.0)
    assert -sim.state[2] == pytest.approx(10.0, abs=0.3)
    assert ap.takeoff(2.0, sim.time_s) == Result.ACCEPTED
    fly(sim, 3.0)
    assert -sim.state[2] == pytest.approx(10.0, abs=0.3)


def airborne(altitude_m: float, seconds: float) -> tuple[Simulation, Autopilot]:
    """A simulation armed, taken off to ``altitude_m`` and flown for ``seconds``."""
    sim = Simulation(CONFIG, seed=0)
    sim.autopilot.arm(True, 0.0)
    sim.autopilot.takeoff(altitude_m, 0.0)
    fly(sim, seconds)
    return sim, sim.autopilot


def test_offboard_returns_after_an_auto_land_disarmed_if_setpoints_stream():
    sim, ap = airborne(1.0, 3.0)
    stream(ap, sim.time_s - 0.2, sim.time_s, hz=50.0)
    assert ap.set_mode(OFFBOARD, sim.time_s) == Result.ACCEPTED
    fly(sim, LOSS_S + 0.1)  # setpoints stop: failsafe to Hold
    assert ap.mode == HOLD
    assert ap.failsafe_count == 1
    assert ap.intended_mode == OFFBOARD
    ap.mode = LAND  # the failsafe escalates to a landing (PX4: no RC, no offboard)
    fly(sim, 8.0)
    assert not ap.armed
    assert sim.state[2] == 0.0
    for _ in range(40):  # setpoints still stream to the disarmed vehicle
        ap.on_attitude_setpoint(sp(), sim.time_s)
        sim.advance_tick()
    assert ap.mode == OFFBOARD
    assert not ap.armed


def test_auto_disarm_after_preflight_timeout_without_takeoff():
    ap = autopilot()
    x = initial_state()
    ap.arm(True, 1.0)
    ap.update_outer(x, 1.0 + CONFIG.autopilot.disarm_preflight_s - 0.01, 0.005)
    assert ap.armed
    ap.update_outer(x, 1.0 + CONFIG.autopilot.disarm_preflight_s + 0.01, 0.005)
    assert not ap.armed


def test_rate_setpoints_honour_type_mask_and_thrust():
    ap = autopilot()
    x = initial_state((0.0, 0.0, -5.0))
    ap.arm(True, 0.0)
    stream(ap, 0.0, 0.2, mask=RATES_ONLY | IGNORE_YAW_RATE, rates=(0.3, -0.2, 0.9), thrust=0.6)
    assert ap.set_mode(OFFBOARD, 0.2) == Result.ACCEPTED
    ap.update_outer(x, 0.2, 0.005)
    cmd = ap.update_inner(x, 0.001)
    np.testing.assert_allclose(cmd.rate_cmd_frd_rad_s, [0.3, -0.2, 0.0])  # yaw rate ignored
    assert cmd.thrust_norm == pytest.approx(0.6)
    # ignore-thrust keeps the last thrust; attitude setpoints go through the attitude loop
    q_roll = tuple(euler_to_quat(0.2, 0.0, 0.0))
    ap.on_attitude_setpoint(sp(thrust=0.1, q=q_roll, mask=0b111 | IGNORE_THRUST), 0.21)
    ap.update_outer(x, 0.21, 0.005)
    cmd = ap.update_inner(x, 0.001)
    assert cmd.thrust_norm == pytest.approx(0.6)
    assert cmd.rate_cmd_frd_rad_s[0] > 0.5  # rolls right towards +0.2 rad
    assert abs(cmd.rate_cmd_frd_rad_s[1]) < 1e-9


def test_attitude_from_thrust_vector_round_trips_through_euler():
    # accelerating north (NED +x) needs nose down: negative pitch
    f = np.array([2.0, 0.0, -9.0])
    q = attitude_from_thrust(f / np.linalg.norm(f), yaw_rad=0.3)
    _, pitch, yaw = quat_to_euler(q)
    assert yaw == pytest.approx(0.3)
    assert pitch < -0.1
    q2 = euler_to_quat(0.1, -0.2, 2.5)
    np.testing.assert_allclose(quat_from_rotation(quat_to_rotation(q2)), q2, atol=1e-12)


def test_takeoff_hold_land_and_disarm_on_touchdown():
    sim = Simulation(CONFIG, seed=0)
    ap = sim.autopilot
    assert ap.arm(True, 0.0) == Result.ACCEPTED
    assert ap.takeoff(2.0, 0.0) == Result.ACCEPTED
    modes = set()
    for _ in range(round(4.0 / 0.005)):
        sim.advance_tick()
        modes.add(ap.mode)
    assert TAKEOFF in modes
    assert ap.mode == HOLD
    assert sim.state[2] == pytest.approx(-2.0, abs=0.25)
    assert ap.landed_state == LandedState.IN_AIR
    assert math.hypot(sim.state[0], sim.state[1]) < 0.05
    assert ap.land(sim.time_s) == Result.ACCEPTED
    for _ in range(round(6.5 / 0.005)):
        sim.advance_tick()
    assert sim.state[2] == 0.0
    assert not ap.armed


def test_hold_rejects_a_steady_wind():
    cfg = dataclasses.replace(
        CONFIG, environment=dataclasses.replace(CONFIG.environment, wind_speed_m_s=3.0)
    )
    sim = Simulation(cfg, seed=0)
    sim.autopilot.arm(True, 0.0)
    sim.autopilot.takeoff(2.5, 0.0)
    for _ in range(round(10.0 / 0.005)):
        sim.advance_tick()
    # The integrator trims out the drag: back near the takeoff point, tilted into the wind.
    assert math.hypot(sim.state[0], sim.state[1]) < 0.3
    roll, _, _ = quat_to_euler(sim.state[6:10])
    assert roll < -0.02  # wind towards east: lean west (roll left) into it


def test_acceleration_feedforward_of_a_position_setpoint_is_flown():
    sim, ap = airborne(2.0, 4.0)
    here = (float(sim.state[0]), float(sim.state[1]), float(sim.state[2]))
    target = PositionSetpoint(here, (0.0, 0.0, 0.0), 0.0, acc_ned_m_s2=(2.0, 0.0, 0.0))
    for _ in range(5):
        ap.on_position_setpoint(target, sim.time_s)
        sim.advance_tick()
    assert ap.set_mode(OFFBOARD, sim.time_s) == Result.ACCEPTED
    for _ in range(30):
        ap.on_position_setpoint(target, sim.time_s)
        sim.advance_tick()
    _, pitch, _ = quat_to_euler(sim.state[6:10])
    # nose down within 0.15 s (PX4's dead time and rate-loop lag): accelerating north
    assert pitch < -0.05


def test_position_setpoints_fly_the_vehicle_in_offboard():
    sim = Simulation(CONFIG, seed=0)
    ap = sim.autopilot
    target = PositionSetpoint(pos_ned_m=(1.0, -0.5, -1.5), vel_ned_m_s=None, yaw_rad=0.5)
    ap.arm(True, 0.0)
    for _ in range(5):
        ap.on_position_setpoint(target, sim.time_s)
        sim.advance_tick()
    assert ap.set_mode(OFFBOARD, sim.time_s) == Result.ACCEPTED
    for _ in range(round(6.0 / 0.005)):
        ap.on_position_setpoint(target, sim.time_s)
        sim.advance_tick()
    assert ap.mode == OFFBOARD
    np.testing.assert_allclose(sim.state[0:3], [1.0, -0.5, -1.5], atol=0.15)
    assert quat_to_euler(sim.state[6:10])[2] == pytest.approx(0.5, abs=0.05)


@settings(max_examples=200, deadline=None)
@given(
    north=st.floats(-1, 1),
    east=st.floats(-1, 1),
    up=st.floats(0.2, 1),
    yaw=st.floats(-3.1, 3.1),
)
def test_attitude_from_thrust_points_body_up_along_thrust_with_exact_yaw(north, east, up, yaw):
    f = np.array([north, east, -up])
    f /= np.linalg.norm(f)
    q = attitude_from_thrust(f, yaw)
    R = quat_to_rotation(q)
    np.testing.assert_allclose(-R[:, 2], f, atol=1e-9)
    assert math.cos(quat_to_euler(q)[2] - yaw) == pytest.approx(1.0, abs=1e-9)
    np.testing.assert_allclose(quat_from_rotation(R), q, atol=1e-9)
