"""What the service sends the autopilot, as MAVLink messages: pure encoders, values in,
messages out (pymavlink's generated message classes; the link sends them).

* :func:`command_message` — a dialect :class:`~epc_offboard.vehicle.dialect.Command` as
  COMMAND_LONG or COMMAND_INT;
* :func:`rate_requests` — SET_MESSAGE_INTERVAL for the loops' state streams and the dialect's;
* :func:`param_request` — PARAM_REQUEST_READ;
* :func:`attitude_target` — SET_ATTITUDE_TARGET: rates bounded, never a NaN (a non-finite
  setpoint is replaced by the caller's level hover and reported);
* :func:`position_target` — SET_POSITION_TARGET_LOCAL_NED, only ever finite;
* :func:`system_time` — the lockstep answer of a tick that sends no setpoint;
* :func:`timesync_request` — TIMESYNC asking the autopilot for its clock;
* :func:`heartbeat_request` — MAV_CMD_REQUEST_MESSAGE for the autopilot's HEARTBEAT now.

Every message is stamped with :func:`stamp_ms`, the vehicle time of the state it answers.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass

from pymavlink.dialects.v20 import common as mavlink

from epc_offboard.vehicle.dialect import Command, command, message_interval

# SET_ATTITUDE_TARGET type_mask bits (MAVLink ATTITUDE_TARGET_TYPEMASK)
IGNORE_RATES = 1 | 2 | 4
IGNORE_ATTITUDE = 128

MSG_ATTITUDE_QUATERNION = 31
MSG_LOCAL_POSITION_NED = 32


@dataclass(frozen=True)
class Target:
    """The component every command and setpoint is addressed to."""

    system_id: int
    component_id: int


@dataclass(frozen=True)
class AttitudeSetpoint:
    """SET_ATTITUDE_TARGET's content: attitude (w, x, y, z), NED to FRD; body rates FRD,
    rad/s, or None (attitude only: the autopilot's own attitude loop tracks ``q``); the
    normalised collective thrust."""

    q_ned_frd: tuple[float, float, float, float]
    rates_frd_rad_s: tuple[float, float, float] | None
    thrust_norm: float

    @staticmethod
    def of(
        q: Iterable[float], rates_frd_rad_s: Iterable[float] | None, thrust_norm: float
    ) -> AttitudeSetpoint:
        """From arrays or sequences: q (4,), rates (3,) or None."""
        w, x, y, z = (float(v) for v in q)
        if rates_frd_rad_s is None:
            return AttitudeSetpoint((w, x, y, z), None, float(thrust_norm))
        p, r, yw = (float(v) for v in rates_frd_rad_s)
        return AttitudeSetpoint((w, x, y, z), (p, r, yw), float(thrust_norm))


def stamp_ms(time_s: float) -> int:
    """time_boot_ms of what we send: the vehicle time of the state it answers (the lockstep
    simulator's "answered" mark), wrapped to 32 bits."""
    return round(time_s * 1000.0) & 0xFFFFFFFF


def command_message(target: Target, cmd: Command) -> mavlink.MAVLink_message:
    """COMMAND_INT when the command has an ``int_frame`` (x, y = params[4:6] as integers,
    degE7), else COMMAND_LONG; confirmation 0."""
    sys_id, comp_id, p = target.system_id, target.component_id, cmd.params
    if cmd.int_frame is None:
        return mavlink.MAVLink_command_long_message(sys_id, comp_id, cmd.command, 0, *p)
    return mavlink.MAVLink_command_int_message(
        sys_id, comp_id, cmd.int_frame, cmd.command, 0, 0,
        p[0], p[1], p[2], p[3], round(p[4]), round(p[5]), p[6],
    )  # fmt: skip


def rate_requests(
    attitude_rate_hz: float,
    position_rate_hz: float,
    extra_streams_hz: Sequence[tuple[int, float]] = (),
) -> tuple[Command, ...]:
    """SET_MESSAGE_INTERVAL for ATTITUDE_QUATERNION and LOCAL_POSITION_NED at the loops'
    rates, then for the dialect's other streams ((message id, Hz) pairs)."""
    loops = (
        (MSG_ATTITUDE_QUATERNION, attitude_rate_hz),
        (MSG_LOCAL_POSITION_NED, position_rate_hz),
    )
    return tuple(message_interval(msg_id, rate) for msg_id, rate in (*loops, *extra_streams_hz))


def param_request(target: Target, name: str) -> mavlink.MAVLink_message:
    """PARAM_REQUEST_READ of ``name`` (by name: index -1)."""
    return mavlink.MAVLink_param_request_read_message(
        target.system_id, target.component_id, name.encode(), -1
    )


def attitude_target(
    target: Target,
    time_s: float,
    setpoint: AttitudeSetpoint,
    *,
    max_rate_rad_s: Sequence[float],
    fallback: Callable[[], AttitudeSetpoint],
    wire_thrust: Callable[[float], float] = lambda thrust: thrust,
) -> tuple[mavlink.MAVLink_message, bool]:
    """SET_ATTITUDE_TARGET for ``setpoint``; returns the message and whether it was replaced.

    Rates are bounded to ``max_rate_rad_s`` (3,), what the vehicle's rate loop can follow,
    whatever computed them. A NaN or an infinity left after that is never sent: ``fallback()``
    (a level hover, attitude only) goes instead, and the second value is True (the caller
    counts it). ``wire_thrust`` turns the collective thrust into the dialect's; the thrust
    sent is clipped to [0, 1].
    """
    q, thrust = setpoint.q_ned_frd, setpoint.thrust_norm
    rates: tuple[float, ...]
    if setpoint.rates_frd_rad_s is None:
        rates, mask = (0.0, 0.0, 0.0), IGNORE_RATES
    else:
        rates = tuple(
            min(max(v, -m), m)
            for v, m in zip(setpoint.rates_frd_rad_s, max_rate_rad_s, strict=True)
        )
        mask = IGNORE_ATTITUDE
    # judged on the thrust as sent: the dialect's conversion is the last step before the wire
    thrust = wire_thrust(thrust)
    replaced = not all(math.isfinite(v) for v in (*q, *rates, thrust))
    if replaced:
        safe = fallback()
        q, rates, mask = safe.q_ned_frd, (0.0, 0.0, 0.0), IGNORE_RATES
        wired = wire_thrust(safe.thrust_norm)
        thrust = wired if math.isfinite(wired) else safe.thrust_norm
    msg = mavlink.MAVLink_set_attitude_target_message(
        stamp_ms(time_s), target.system_id, target.component_id, mask, list(q), *rates,
        min(max(thrust, 0.0), 1.0),
    )  # fmt: skip
    return msg, replaced


def position_target(
    target: Target,
    time_s: float,
    pos_ned_m: Iterable[float],
    vel_ned_m_s: Iterable[float],
    acc_ned_m_s2: Iterable[float],
    yaw_rad: float,
) -> mavlink.MAVLink_message | None:
    """SET_POSITION_TARGET_LOCAL_NED with position, velocity and acceleration (3,) each and
    a yaw (yaw rate ignored); None when any of them is not finite (nothing to send)."""
    values = [float(v) for v in (*pos_ned_m, *vel_ned_m_s, *acc_ned_m_s2)]
    if not all(math.isfinite(v) for v in (*values, yaw_rad)):
        return None
    return mavlink.MAVLink_set_position_target_local_ned_message(
        stamp_ms(time_s), target.system_id, target.component_id, mavlink.MAV_FRAME_LOCAL_NED,
        mavlink.POSITION_TARGET_TYPEMASK_YAW_RATE_IGNORE, *values, yaw_rad, 0.0,
    )  # fmt: skip


def system_time(time_s: float) -> mavlink.MAVLink_message:
    """SYSTEM_TIME stamped with the tick's vehicle time: the lockstep answer of a tick that
    sends no setpoint (time_unix_usec 0: no autopilot takes it as a clock)."""
    return mavlink.MAVLink_system_time_message(0, stamp_ms(time_s))


def timesync_request(sent_s: float) -> mavlink.MAVLink_message:
    """TIMESYNC request (tc1 = 0) carrying our send time in ns as ts1, which the autopilot
    echoes beside its own time (tc1, ns since its boot: the time_boot_ms clock)."""
    return mavlink.MAVLink_timesync_message(0, round(sent_s * 1e9))


def heartbeat_request() -> Command:
    """MAV_CMD_REQUEST_MESSAGE for a HEARTBEAT (sent at once, off the 1 Hz schedule)."""
    return command(mavlink.MAV_CMD_REQUEST_MESSAGE, mavlink.MAVLINK_MSG_ID_HEARTBEAT)
