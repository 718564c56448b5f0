"""The encoders of what the service sends (vehicle/commands.py), each through pymavlink's
own packer and decoder: what the autopilot reads is what was meant, and never a NaN."""

from __future__ import annotations

import math

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from pymavlink.dialects.v20 import common as mavlink

from epc_offboard.vehicle import commands
from epc_offboard.vehicle.commands import AttitudeSetpoint, Target
from epc_offboard.vehicle.dialect import (
    MAV_CMD_COMPONENT_ARM_DISARM,
    MAV_CMD_SET_MESSAGE_INTERVAL,
    command,
)

TO = Target(7, 1)
RMAX = (4.0, 4.0, 2.0)
LEVEL = AttitudeSetpoint((1.0, 0.0, 0.0, 0.0), None, 0.5)


def wire(msg: mavlink.MAVLink_message):
    """Packed by one MAVLink instance and decoded by another: what the autopilot reads."""
    buf = msg.pack(mavlink.MAVLink(None, srcSystem=255, srcComponent=190))
    return mavlink.MAVLink(None).decode(bytearray(buf))


def attitude(setpoint: AttitudeSetpoint, **kw):
    kw.setdefault("max_rate_rad_s", RMAX)
    kw.setdefault("fallback", lambda: LEVEL)
    msg, replaced = commands.attitude_target(TO, 12.3456, setpoint, **kw)
    return wire(msg), replaced


def test_command_long_and_int_round_trip():
    arm = wire(commands.command_message(TO, command(MAV_CMD_COMPONENT_ARM_DISARM, 1)))
    assert arm.get_type() == "COMMAND_LONG"
    assert (arm.target_system, arm.target_component, arm.command) == (7, 1, 400)
    assert [arm.param1, arm.param2, arm.param7] == [1.0, 0.0, 0.0]
    takeoff = command(22, 0, 0, 0, 90.0, 473977420.0, 85455940.0, 502.5, int_frame=5)
    got = wire(commands.command_message(TO, takeoff))
    assert got.get_type() == "COMMAND_INT"
    assert (got.frame, got.command, got.x, got.y) == (5, 22, 473977420, 85455940)
    assert (got.param4, got.z) == (90.0, 502.5)


def test_rate_requests_ask_for_both_loop_streams_then_the_dialects():
    cmds = commands.rate_requests(200.0, 100.0, ((245, 2.0),))
    assert [c.command for c in cmds] == [MAV_CMD_SET_MESSAGE_INTERVAL] * 3
    assert [(c.params[0], c.params[1]) for c in cmds] == [
        (31.0, 5000.0),
        (32.0, 10000.0),
        (245.0, 500000.0),
    ]


def test_param_request_by_name():
    got = wire(commands.param_request(TO, "GUID_OPTIONS"))
    assert (got.param_id, got.param_index, got.target_system) == ("GUID_OPTIONS", -1, 7)


def test_attitude_rates_are_bounded_and_stamped_with_the_vehicle_time():
    got, replaced = attitude(
        AttitudeSetpoint.of([0.9, 0.1, 0.0, 0.0], [9.0, -1.0, -9.0], 0.6),
        wire_thrust=lambda t: 0.5 * t,
    )
    assert not replaced
    assert got.time_boot_ms == 12346
    assert got.type_mask == commands.IGNORE_ATTITUDE
    assert [got.body_roll_rate, got.body_pitch_rate, got.body_yaw_rate] == [4.0, -1.0, -2.0]
    assert got.thrust == pytest.approx(0.3)
    assert list(got.q) == pytest.approx([0.9, 0.1, 0.0, 0.0])


def test_attitude_only_ignores_the_rates_and_clips_the_thrust():
    got, _ = attitude(AttitudeSetpoint.of([1.0, 0.0, 0.0, 0.0], None, 1.7))
    assert got.type_mask == commands.IGNORE_RATES
    assert got.thrust == 1.0


@pytest.mark.parametrize(
    "setpoint",
    [
        AttitudeSetpoint((math.nan, 0.0, 0.0, 0.0), None, 0.5),
        AttitudeSetpoint((1.0, 0.0, 0.0, 0.0), (0.1, math.nan, 0.0), 0.5),
        AttitudeSetpoint((1.0, 0.0, 0.0, 0.0), (0.1, 0.0, 0.0), math.inf),
    ],
)
def test_a_non_finite_setpoint_is_replaced_by_the_fallback_and_reported(setpoint):
    hover = AttitudeSetpoint((0.7071, 0.0, 0.0, 0.7071), (1.0, 1.0, 1.0), 0.45)
    got, replaced = attitude(setpoint, fallback=lambda: hover)
    assert replaced
    assert got.type_mask == commands.IGNORE_RATES  # the fallback's rates are never sent
    assert list(got.q) == pytest.approx(hover.q_ned_frd)
    assert got.thrust == pytest.approx(0.45)


def test_a_conversion_that_yields_nan_is_replaced_too():
    """The guard judges the thrust as it goes on the wire: a dialect's conversion (ArduPilot's
    tilt compensation) fed a non-finite tilt must not slip a NaN past it."""
    got, replaced = attitude(
        AttitudeSetpoint.of([1, 0, 0, 0], [0.1, 0, 0], 0.5), wire_thrust=lambda t: t * math.nan
    )
    assert replaced
    assert got.type_mask == commands.IGNORE_RATES
    assert got.thrust == pytest.approx(LEVEL.thrust_norm)  # the fallback's own, finite


def test_the_fallback_is_asked_only_when_needed():
    def no_fallback() -> AttitudeSetpoint:
        raise AssertionError("fallback asked for a finite setpoint")

    _, replaced = attitude(AttitudeSetpoint.of([1, 0, 0, 0], [0, 0, 0], 0.5), fallback=no_fallback)
    assert not replaced


anything = st.floats(allow_nan=True, allow_infinity=True, width=32)


@settings(max_examples=200, deadline=None)
@given(
    q=st.lists(anything, min_size=4, max_size=4),
    rates=st.none() | st.lists(anything, min_size=3, max_size=3),
    thrust=anything,
)
def test_never_a_nan_on_the_wire(q, rates, thrust):
    got, replaced = attitude(AttitudeSetpoint.of(q, rates, thrust))
    fields = [*got.q, got.body_roll_rate, got.body_pitch_rate, got.body_yaw_rate, got.thrust]
    assert all(math.isfinite(v) for v in fields)
    # an infinite rate is bounded, not replaced; a NaN anywhere, or an infinite q or thrust, is
    nan_rate = any(math.isnan(v) for v in rates or ())
    assert replaced == (nan_rate or not all(math.isfinite(v) for v in (*q, thrust)))


def test_position_target_round_trip_and_none_when_not_finite():
    msg = commands.position_target(TO, 2.0, [1.0, 2.0, -3.0], [0.5, 0, 0], [0, 0, 0.25], 1.5)
    assert msg is not None
    got = wire(msg)
    assert got.coordinate_frame == mavlink.MAV_FRAME_LOCAL_NED
    assert got.type_mask == mavlink.POSITION_TARGET_TYPEMASK_YAW_RATE_IGNORE
    assert [got.x, got.y, got.z, got.vx, got.afz, got.yaw] == [1.0, 2.0, -3.0, 0.5, 0.25, 1.5]
    assert got.time_boot_ms == 2000
    assert commands.position_target(TO, 2.0, [1.0, math.nan, 0], [0, 0, 0], [0, 0, 0], 0.0) is None


def test_system_time_is_the_lockstep_answer_and_the_stamp_wraps_at_32_bits():
    got = wire(commands.system_time(3.0))
    assert (got.time_unix_usec, got.time_boot_ms) == (0, 3000)
    assert commands.stamp_ms(2**32 / 1000.0 + 0.005) == 5
