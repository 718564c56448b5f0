"""MAVLink 2 over UDP for the SITL: PX4 SITL conventions, sans-IO codec on asyncio.

pymavlink's generated ``MAVLink`` class is used as a pure codec: datagrams are fed to
``parse_buffer``, outgoing messages are packed into bytes and sent with ``sendto``. The
endpoint owns no clock: telemetry is emitted when the runner calls :meth:`emit` after each
tick, stamped with vehicle time. Nothing a peer sends can raise out of ``datagram_received``:
malformed, unknown, mis-targeted or badly signed traffic is counted and dropped.
"""

from __future__ import annotations

import asyncio
import math
import struct
from collections.abc import Callable
from dataclasses import dataclass, fields
from typing import Any, cast

import numpy as np
from pymavlink.dialects.v20 import common as mavlink

from epc_offboard.common.frames import quat_to_euler, quat_to_rotation
from epc_offboard.common.signing import enable_signing
from sitl.autopilot import (
    FORCE_DISARM_MAGIC,
    IGNORE_ATTITUDE,
    IGNORE_PITCH_RATE,
    IGNORE_ROLL_RATE,
    IGNORE_THRUST,
    IGNORE_YAW_RATE,
    OFFBOARD,
    AttitudeSetpoint,
    PositionSetpoint,
    Result,
)
from sitl.simulation import Simulation, StateEstimate

Address = tuple[str, int]

# Telemetry streams: config field -> MAVLink message id.
STREAMS: dict[str, int] = {
    "heartbeat_hz": mavlink.MAVLINK_MSG_ID_HEARTBEAT,
    "sys_status_hz": mavlink.MAVLINK_MSG_ID_SYS_STATUS,
    "extended_sys_state_hz": mavlink.MAVLINK_MSG_ID_EXTENDED_SYS_STATE,
    "attitude_hz": mavlink.MAVLINK_MSG_ID_ATTITUDE,
    "attitude_quaternion_hz": mavlink.MAVLINK_MSG_ID_ATTITUDE_QUATERNION,
    "local_position_ned_hz": mavlink.MAVLINK_MSG_ID_LOCAL_POSITION_NED,
    "odometry_hz": mavlink.MAVLINK_MSG_ID_ODOMETRY,
    "global_position_int_hz": mavlink.MAVLINK_MSG_ID_GLOBAL_POSITION_INT,
    "home_position_hz": mavlink.MAVLINK_MSG_ID_HOME_POSITION,
    "attitude_target_hz": mavlink.MAVLINK_MSG_ID_ATTITUDE_TARGET,
    "system_time_hz": mavlink.MAVLINK_MSG_ID_SYSTEM_TIME,
}
# The state a controller runs on: their stamps are what a lockstep answer must reach.
STATE_STREAMS = frozenset(
    {
        mavlink.MAVLINK_MSG_ID_ATTITUDE,
        mavlink.MAVLINK_MSG_ID_ATTITUDE_QUATERNION,
        mavlink.MAVLINK_MSG_ID_LOCAL_POSITION_NED,
        mavlink.MAVLINK_MSG_ID_ODOMETRY,
    }
)
EARTH_RADIUS_M = 6_371_000.0

_CAPABILITIES = (
    mavlink.MAV_PROTOCOL_CAPABILITY_MAVLINK2
    | mavlink.MAV_PROTOCOL_CAPABILITY_SET_ATTITUDE_TARGET
    | mavlink.MAV_PROTOCOL_CAPABILITY_SET_POSITION_TARGET_LOCAL_NED
    | mavlink.MAV_PROTOCOL_CAPABILITY_COMMAND_INT
)


@dataclass
class Counters:
    """What the endpoint and the runner dropped or noticed; printed on exit."""

    received: int = 0
    malformed: int = 0
    unknown: int = 0
    wrong_target: int = 0
    bad_signature: int = 0
    unexpected_sysid: int = 0
    nan_setpoints: int = 0
    commands: int = 0
    setpoints: int = 0
    handler_errors: int = 0
    send_errors: int = 0
    lockstep_timeouts: int = 0
    # fallbacks to real-time pace (after the controller handed the vehicle back: the ones an
    # answer followed)
    lockstep_fallbacks: int = 0
    offboard_failsafes: int = 0
    rtl_entered: int = 0  # ArduCopter personality: RTLs selected (PX4's offboard is RTL there)
    realtime_priority_refused: int = 0  # --realtime-priority: SCHED_FIFO not permitted

    def summary(self) -> str:
        return " ".join(f"{f.name}={getattr(self, f.name)}" for f in fields(self))


class _Capture:
    """File-like sink for ``MAVLink.send``: keeps the last packed message."""

    def __init__(self) -> None:
        self.data = b""

    def write(self, buf: bytes) -> None:
        self.data = bytes(buf)


@dataclass(frozen=True)
class _Sample:
    """One tick's published estimate and its time: ODOMETRY reports the previous one."""

    time_us: int
    estimate: StateEstimate


class TimesyncAnswer(mavlink.MAVLink_timesync_message):  # type: ignore[misc]
    """TIMESYNC with common.xml's extension fields ``target_system``/``target_component``,
    which pymavlink's dialect lacks: PX4 answers a request (tc1 = 0) with both set to the
    requester's ids, an 18-byte payload (a receiver that knows only tc1 and ts1 must take
    it: a MAVLink 2 receiver ignores extension fields it does not know)."""

    _EXTENDED = struct.Struct("<qqBB")

    def __init__(self, tc1: int, ts1: int, target_system: int, target_component: int) -> None:
        super().__init__(tc1, ts1)
        self.target_system = target_system
        self.target_component = target_component

    def pack(self, mav: Any, force_mavlink1: bool = False) -> bytes:
        payload = self._EXTENDED.pack(self.tc1, self.ts1, self.target_system,
                                      self.target_component)  # fmt: skip
        return cast(bytes, self._pack(mav, self.crc_extra, payload, force_mavlink1=force_mavlink1))


def _finite(*values: float) -> bool:
    return all(math.isfinite(v) for v in values)


class SitlEndpoint(asyncio.DatagramProtocol):
    """The vehicle's MAVLink link: commands in, telemetry and acknowledgements out."""

    def __init__(
        self,
        sim: Simulation,
        sysid: int,
        telemetry_dests: list[Address],
        counters: Counters,
        signing_key: bytes | None = None,
        on_answer: Callable[[int], None] | None = None,
        on_offboard: Callable[[bool], None] | None = None,
    ) -> None:
        self.sim = sim
        self.sysid = sysid
        self.dests = list(telemetry_dests)
        self.counters = counters
        # a lockstep answer: the time_boot_ms a controller's setpoint (or SYSTEM_TIME) carries
        self.on_answer = on_answer
        # the vehicle's intended mode became offboard (True) or left it on a request (False:
        # the controller handed the vehicle back), after what a peer sent
        self.on_offboard = on_offboard
        self._offboard_intended = sim.autopilot.intended_mode == OFFBOARD
        self.newest_state_stamp_ms = -1  # of the state messages sent so far
        self._previous: _Sample | None = None
        self.transport: asyncio.DatagramTransport | None = None
        self._sink = _Capture()
        self.mav = mavlink.MAVLink(self._sink, srcSystem=sysid, srcComponent=1)
        self.mav.robust_parsing = True
        if signing_key is not None:
            enable_signing(self.mav, signing_key)  # verifies a signature before recording it
        self._allowed_sysids = frozenset(sim.config.sitl.allowed_source_sysids)
        rates = sim.config.sitl.telemetry
        self._default_interval_us = {
            STREAMS[name]: max(
                _interval_us(getattr(rates, name)), self._min_interval_us(STREAMS[name])
            )
            for name in STREAMS
        }
        ap = sim.autopilot
        if not ap.sends_odometry:  # (ArduPilot: SET_MESSAGE_INTERVAL for it is denied)
            del self._default_interval_us[mavlink.MAVLINK_MSG_ID_ODOMETRY]
        if not ap.streams_by_default:  # ArduPilot: nothing but HEARTBEAT until asked
            for msg_id in self._default_interval_us:
                if msg_id != mavlink.MAVLINK_MSG_ID_HEARTBEAT:
                    self._default_interval_us[msg_id] = 0
        self._interval_us = dict(self._default_interval_us)
        # byte-stream peers (a ground station on TCP): each gets all telemetry and replies
        self.stream_peers: dict[Address, Callable[[bytes], None]] = {}
        self._next_due_us = dict.fromkeys(self._interval_us, 0)
        self._mode_announced = sim.autopilot.custom_mode  # the mode the last heartbeat showed
        self._estimate: StateEstimate | None = None
        self._builders: dict[int, Callable[[], Any]] = {
            mavlink.MAVLINK_MSG_ID_HEARTBEAT: self._heartbeat,
            mavlink.MAVLINK_MSG_ID_SYS_STATUS: self._sys_status,
            mavlink.MAVLINK_MSG_ID_EXTENDED_SYS_STATE: self._extended_sys_state,
            mavlink.MAVLINK_MSG_ID_ATTITUDE: self._attitude,
            mavlink.MAVLINK_MSG_ID_ATTITUDE_QUATERNION: self._attitude_quaternion,
            mavlink.MAVLINK_MSG_ID_LOCAL_POSITION_NED: self._local_position_ned,
            mavlink.MAVLINK_MSG_ID_ODOMETRY: self._odometry,
            mavlink.MAVLINK_MSG_ID_GLOBAL_POSITION_INT: self._global_position_int,
            mavlink.MAVLINK_MSG_ID_HOME_POSITION: self._home_position,
            mavlink.MAVLINK_MSG_ID_ATTITUDE_TARGET: self._attitude_target,
            mavlink.MAVLINK_MSG_ID_AUTOPILOT_VERSION: self._autopilot_version,
            mavlink.MAVLINK_MSG_ID_SYSTEM_TIME: self._system_time,
        }

        self._handlers: dict[str, Callable[[Any, Address], None] | None] = {
            "COMMAND_LONG": self._on_command,
            "COMMAND_INT": self._on_command,
            "SET_MODE": self._on_set_mode,
            "SET_ATTITUDE_TARGET": self._on_set_attitude_target,
            "SET_POSITION_TARGET_LOCAL_NED": self._on_set_position_target,
            "TIMESYNC": self._on_timesync,
            "SYSTEM_TIME": self._on_system_time,
            "PARAM_REQUEST_LIST": self._on_param_request,
            "PARAM_REQUEST_READ": self._on_param_request,
            "PARAM_SET": self._on_param_request,
            "MISSION_REQUEST_LIST": self._on_mission_request_list,
            "HEARTBEAT": None,  # peers announce themselves; nothing to do
        }

    # ---- asyncio protocol -----------------------------------------------------------------

    def connection_made(self, transport: asyncio.BaseTransport) -> None:
        self.transport = cast(asyncio.DatagramTransport, transport)

    def error_received(self, exc: Exception) -> None:
        # ICMP port unreachable from a telemetry port nobody listens on: expected, harmless.
        self.counters.send_errors += 1

    def datagram_received(self, data: bytes, addr: Address) -> None:
        self.counters.received += 1
        try:
            msgs = self.mav.parse_buffer(data) or []
        except Exception:
            msgs = []
            self.counters.malformed += 1
        if self.mav.buf_len() > 0:
            # A datagram carries whole messages; a leftover fragment is garbage.
            self.counters.malformed += 1
            self._reset_parser()
        for msg in msgs:
            try:
                self._dispatch(msg, addr)
            except Exception:
                # Decoded but unusable (e.g. a value out of range for an int field): the link
                # never dies on what a peer sends.
                self.counters.handler_errors += 1
        self._announce_mode_change()
        self._note_offboard()

    def stream_received(self, msgs: list[Any], addr: Address) -> None:
        """Messages a byte-stream peer (TCP) sent, already parsed: handled as a datagram's."""
        self.counters.received += 1
        for msg in msgs:
            try:
                self._dispatch(msg, addr)
            except Exception:
                self.counters.handler_errors += 1
        self._announce_mode_change()
        self._note_offboard()

    def _reset_parser(self) -> None:
        self.mav.buf = bytearray()
        self.mav.buf_index = 0
        self.mav.expected_length = mavlink.HEADER_LEN_V1 + 2
        self.mav.have_prefix_error = False

    # ---- outgoing ---------------------------------------------------------------------------

    def _pack(self, msg: Any) -> bytes:
        self.mav.send(msg)
        return self._sink.data

    def _send_bytes(self, data: bytes, extra: Address | None = None) -> None:
        if self.transport is None or not data:
            return
        for dest in self.dests:
            self.transport.sendto(data, dest)
        for write in list(self.stream_peers.values()):
            write(data)
        if extra is not None and extra not in self.dests and extra not in self.stream_peers:
            self.transport.sendto(data, extra)

    def send(self, msg: Any, extra: Address | None = None) -> None:
        """Pack ``msg`` once and send it to every telemetry destination (and ``extra``)."""
        self._send_bytes(self._pack(msg), extra)

    def emit(self) -> None:
        """Send every stream due at the current vehicle time (call once per tick).

        A tick's messages travel in one datagram, as PX4 bundles its streams: a controller
        decodes the whole tick before it answers, so a lockstep run does not depend on how
        the scheduler interleaves datagrams.
        """
        self._announce_mode_change()
        previous = self._previous
        self._estimate = self.sim.estimate()
        now_us = self.sim.time_us
        self._previous = _Sample(now_us, self._estimate)
        batch = bytearray()
        has_position = self.sim.autopilot.has_position(self.sim.time_s)
        for msg_id, interval in self._interval_us.items():
            if interval <= 0 or now_us < self._next_due_us[msg_id]:
                continue
            if msg_id == mavlink.MAVLINK_MSG_ID_LOCAL_POSITION_NED and not has_position:
                continue  # (ArduCopter before its EKF origin; due at once when it comes)
            due = self._next_due_us[msg_id] + interval
            self._next_due_us[msg_id] = due if due > now_us else now_us + interval
            if msg_id == mavlink.MAVLINK_MSG_ID_ODOMETRY:
                # the estimator's sample time, a tick behind the attitude's (as PX4's)
                sample = previous or self._previous
                batch += self._pack(self._odometry(sample))
                stamp_ms = sample.time_us // 1000
            else:
                batch += self._pack(self._builders[msg_id]())
                stamp_ms = self.sim.time_ms
            if msg_id in STATE_STREAMS or msg_id == mavlink.MAVLINK_MSG_ID_SYSTEM_TIME:
                # SYSTEM_TIME, sent only when a controller asked for it: its clock's tick
                self.newest_state_stamp_ms = max(self.newest_state_stamp_ms, stamp_ms)
        self._send_bytes(bytes(batch))

    def _announce_mode_change(self) -> None:
        """ArduCopter's extra HEARTBEAT the moment its mode changes (a command's, or its
        own: a failsafe, a landing); the 1 Hz heartbeats keep their own schedule."""
        mode = self.sim.autopilot.custom_mode
        if mode == self._mode_announced:
            return
        self._mode_announced = mode
        if self.sim.autopilot.heartbeat_on_mode_change:
            self.send(self._heartbeat())

    def _note_offboard(self) -> None:
        """Tell ``on_offboard`` when what a peer sent changed whether the vehicle is meant
        to be in offboard: the intended mode (a request's; PX4's failsafe changes only the mode
        flown), so a controller that hands the vehicle back (HOLD, LAND) is told from one
        that merely went quiet."""
        intended = self.sim.autopilot.intended_mode == OFFBOARD
        if intended == self._offboard_intended:
            return
        self._offboard_intended = intended
        if self.on_offboard is not None:
            self.on_offboard(intended)

    def announce(self) -> None:
        """While lockstep waits for a controller to join: the heartbeat and state of the
        current tick again (same stamps, no new noise), so a controller that starts later
        finds the vehicle and can answer. No position before ArduCopter's EKF origin, as in
        ``emit``: a controller must not fly, nor wait, on a position the vehicle never sent."""
        batch = bytearray(self._pack(self._heartbeat()))
        has_position = self.sim.autopilot.has_position(self.sim.time_s)
        for msg_id, interval in self._interval_us.items():
            if msg_id == mavlink.MAVLINK_MSG_ID_LOCAL_POSITION_NED and not has_position:
                continue
            if interval > 0 and msg_id in STATE_STREAMS:
                batch += self._pack(
                    self._odometry(self._previous)
                    if msg_id == mavlink.MAVLINK_MSG_ID_ODOMETRY
                    else self._builders[msg_id]()
                )
        self._send_bytes(bytes(batch))

    # ---- incoming ---------------------------------------------------------------------------

    def _dispatch(self, msg: Any, addr: Address) -> None:
        mtype = msg.get_type()
        if mtype == "BAD_DATA":
            if "signature" in str(getattr(msg, "reason", "")).lower():
                self.counters.bad_signature += 1
            else:
                self.counters.malformed += 1
            return
        if self._allowed_sysids and msg.get_srcSystem() not in self._allowed_sysids:
            self.counters.unexpected_sysid += 1
            return
        target = getattr(msg, "target_system", None)
        if target is not None and target not in (0, self.sysid):
            self.counters.wrong_target += 1
            return
        handler = self._handlers.get(mtype, self._on_unknown)
        if handler is not None:
            handler(msg, addr)

    def _on_unknown(self, msg: Any, addr: Address) -> None:
        self.counters.unknown += 1

    def _on_command(self, msg: Any, addr: Address) -> None:
        self.counters.commands += 1
        if msg.get_type() == "COMMAND_LONG":
            params = [
                msg.param1,
                msg.param2,
                msg.param3,
                msg.param4,
                msg.param5,
                msg.param6,
                msg.param7,
            ]
        else:  # COMMAND_INT: x, y are scaled integers; only param1-4 and z are used here
            params = [msg.param1, msg.param2, msg.param3, msg.param4, msg.x, msg.y, msg.z]
        self.sim.autopilot.status_text = None
        try:
            result, follow_up = self._command_result(msg.command, params)
        except (ValueError, OverflowError):  # NaN or inf where an integer is meant
            result, follow_up = Result.DENIED, None
        why = self.sim.autopilot.status_text
        if why is not None:  # PX4 says why it refused, as STATUSTEXT (and an EVENT)
            self.send(
                self.mav.statustext_encode(mavlink.MAV_SEVERITY_CRITICAL, why.encode()[:50]),
                extra=addr,
            )
        self.send(
            self.mav.command_ack_encode(
                msg.command, int(result), 0, 0, msg.get_srcSystem(), msg.get_srcComponent()
            ),
            extra=addr,
        )
        if follow_up is not None:
            self.send(follow_up, extra=addr)

    def _command_result(self, command: int, p: list[float]) -> tuple[Result, Any]:
        ap = self.sim.autopilot
        t = self.sim.time_s
        if command == mavlink.MAV_CMD_COMPONENT_ARM_DISARM:
            # unused params may come as NaN (MAVSDK sends them so; PX4 accepts it)
            force = math.isfinite(p[1]) and round(p[1]) == FORCE_DISARM_MAGIC
            return ap.arm(p[0] > 0.5, t, force=force), None
        if command == mavlink.MAV_CMD_DO_SET_MODE:
            if not int(p[0]) & mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED or not _finite(p[1], p[2]):
                return Result.UNSUPPORTED, None
            return ap.set_mode_command(int(p[1]), int(p[2]), t), None
        if command == mavlink.MAV_CMD_NAV_TAKEOFF:
            # param7 / COMMAND_INT z, as the personality reads it (PX4: AMSL, NaN = default;
            # ArduPilot: above home, NaN denied)
            return ap.takeoff_command(p[6], self.sim.config.sitl.home_amsl_m, t), None
        if command == mavlink.MAV_CMD_NAV_LAND:
            return ap.land(t), None
        if command == mavlink.MAV_CMD_SET_MESSAGE_INTERVAL:
            return self._set_interval(int(p[0]), p[1]), None
        if command == mavlink.MAV_CMD_REQUEST_MESSAGE:
            builder = self._builders.get(int(p[0])) if math.isfinite(p[0]) else None
            if builder is None:
                return Result.DENIED, None
            return Result.ACCEPTED, builder()
        if command == mavlink.MAV_CMD_REQUEST_AUTOPILOT_CAPABILITIES:
            return Result.ACCEPTED, self._autopilot_version()
        return Result.UNSUPPORTED, None

    def _set_interval(self, msg_id: int, interval_us: float) -> Result:
        if msg_id not in self._interval_us or not math.isfinite(interval_us):
            return Result.DENIED
        if interval_us < 0:
            self._interval_us[msg_id] = 0
        elif interval_us == 0:
            self._interval_us[msg_id] = self._default_interval_us[msg_id]
        else:
            self._interval_us[msg_id] = max(int(interval_us), self._min_interval_us(msg_id))
        self._next_due_us[msg_id] = self.sim.time_us
        return Result.ACCEPTED  # (also when capped: PX4 acknowledges, then sends slower)

    def _min_interval_us(self, msg_id: int) -> int:
        """The shortest interval the autopilot delivers ``msg_id`` at, whatever is asked."""
        cap_hz = self.sim.autopilot.params.attitude_quaternion_max_hz
        if msg_id == mavlink.MAVLINK_MSG_ID_ATTITUDE_QUATERNION and cap_hz > 0.0:
            return _interval_us(cap_hz)
        return 0

    def _on_set_mode(self, msg: Any, addr: Address) -> None:
        self.counters.commands += 1
        if msg.base_mode & mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED:
            self.sim.autopilot.set_mode_message(msg.custom_mode, self.sim.time_s)

    def _on_set_attitude_target(self, msg: Any, addr: Address) -> None:
        self.counters.setpoints += 1
        mask = msg.type_mask
        used = [] if mask & IGNORE_THRUST else [msg.thrust]
        if not mask & IGNORE_ATTITUDE:
            used += list(msg.q)
        rates = (msg.body_roll_rate, msg.body_pitch_rate, msg.body_yaw_rate)
        for bit, r in zip(
            (IGNORE_ROLL_RATE, IGNORE_PITCH_RATE, IGNORE_YAW_RATE), rates, strict=True
        ):
            if not mask & bit:
                used.append(r)
        q = np.asarray(msg.q, dtype=np.float64)
        use_q = not mask & IGNORE_ATTITUDE
        if not _finite(*used) or (use_q and float(np.linalg.norm(q)) < 0.5):
            self.counters.nan_setpoints += 1
        else:
            qw, qx, qy, qz = (q / np.linalg.norm(q)).tolist() if use_q else (1.0, 0.0, 0.0, 0.0)
            wx, wy, wz = (float(r) if math.isfinite(r) else 0.0 for r in rates)
            thrust = float(msg.thrust) if math.isfinite(msg.thrust) else 0.0
            sp = AttitudeSetpoint(
                type_mask=mask,
                q_wxyz=(qw, qx, qy, qz),
                rate_frd_rad_s=(wx, wy, wz),
                thrust_norm=min(1.0, max(0.0, thrust)),
            )
            self.sim.autopilot.on_attitude_setpoint(sp, self._arrival_s())
        self._answered(msg.time_boot_ms)

    def _answered(self, time_boot_ms: int) -> None:
        if self.on_answer is not None:
            self.on_answer(time_boot_ms)

    def _on_system_time(self, msg: Any, addr: Address) -> None:
        """A controller with nothing to command answers a lockstep tick with SYSTEM_TIME."""
        self._answered(msg.time_boot_ms)

    def _on_set_position_target(self, msg: Any, addr: Address) -> None:
        self.counters.setpoints += 1
        if msg.coordinate_frame != mavlink.MAV_FRAME_LOCAL_NED:
            self.counters.unknown += 1
            return
        mask = msg.type_mask
        pos = None if mask & 0b111 else (msg.x, msg.y, msg.z)
        vel = None if mask & 0b111000 else (msg.vx, msg.vy, msg.vz)
        yaw = None if mask & mavlink.POSITION_TARGET_TYPEMASK_YAW_IGNORE else msg.yaw
        used = [*(pos or ()), *(vel or ()), *([] if yaw is None else [yaw])]
        acc = None if mask & 0b111000000 else (msg.afx, msg.afy, msg.afz)
        used = [*used, *(acc or ())]
        if not used or not _finite(*used):
            self.counters.nan_setpoints += 1
        else:
            self.sim.autopilot.on_position_setpoint(
                PositionSetpoint(pos, vel, yaw, acc), self._arrival_s()
            )
        self._answered(msg.time_boot_ms)

    def _arrival_s(self) -> float:
        """A setpoint's arrival, on the vehicle's clock: its tick's time in lockstep, the
        time now in real time (between ticks), as a PX4 stamps what its link receives."""
        return self.sim.now_us() / 1e6

    def _on_timesync(self, msg: Any, addr: Address) -> None:
        # the time now (PX4 answers with its clock's, not with its last loop cycle's), to
        # the requester by its ids, as PX4 main does (mavlink_timesync.cpp)
        if msg.tc1 == 0:
            answer = TimesyncAnswer(self.sim.now_us() * 1000, msg.ts1,
                                    msg.get_srcSystem(), msg.get_srcComponent())  # fmt: skip
            self.send(answer, extra=addr)

    def _on_param_request(self, msg: Any, addr: Address) -> None:
        """PARAM_REQUEST_LIST sends all; READ and SET answer one (SET changes what the
        personality lets change: ArduPilot's parameters; PX4's view is read-only)."""
        if msg.get_type() == "PARAM_SET" and math.isfinite(msg.param_value):
            self.sim.autopilot.set_parameter(msg.param_id, float(msg.param_value))
        params = self.sim.autopilot.parameters()
        wanted = range(len(params))
        if msg.get_type() != "PARAM_REQUEST_LIST":
            index = getattr(msg, "param_index", -1)
            names = [name for name, _ in params]
            if index < 0 and msg.param_id in names:
                index = names.index(msg.param_id)
            wanted = range(index, index + 1) if 0 <= index < len(params) else range(0)
        for i in wanted:
            name, value = params[i]
            self.send(
                self.mav.param_value_encode(
                    name.encode(), value, mavlink.MAV_PARAM_TYPE_REAL32, len(params), i
                ),
                extra=addr,
            )

    def _on_mission_request_list(self, msg: Any, addr: Address) -> None:
        # No missions here: an empty list lets a ground station finish its connection ritual.
        self.send(
            self.mav.mission_count_encode(
                msg.get_srcSystem(), msg.get_srcComponent(), 0, msg.mission_type
            ),
            extra=addr,
        )

    # ---- message builders (vehicle time, published = noisy estimate) -----------------------

    def _est(self) -> StateEstimate:
        if self._estimate is None:
            self._estimate = self.sim.estimate()
        return self._estimate

    def _heartbeat(self) -> Any:
        ap = self.sim.autopilot
        base = mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED
        if ap.armed:
            base |= mavlink.MAV_MODE_FLAG_SAFETY_ARMED
        state = mavlink.MAV_STATE_ACTIVE if ap.armed else mavlink.MAV_STATE_STANDBY
        return self.mav.heartbeat_encode(
            mavlink.MAV_TYPE_QUADROTOR, ap.mav_autopilot, base, ap.custom_mode, state
        )

    def _sys_status(self) -> Any:
        sensors = (
            mavlink.MAV_SYS_STATUS_SENSOR_3D_GYRO
            | mavlink.MAV_SYS_STATUS_SENSOR_3D_ACCEL
            | mavlink.MAV_SYS_STATUS_SENSOR_ANGULAR_RATE_CONTROL
            | mavlink.MAV_SYS_STATUS_SENSOR_ATTITUDE_STABILIZATION
            | mavlink.MAV_SYS_STATUS_SENSOR_XY_POSITION_CONTROL
            | mavlink.MAV_SYS_STATUS_SENSOR_Z_ALTITUDE_CONTROL
        )
        return self.mav.sys_status_encode(
            sensors, sensors, sensors, 0, 16000, -1, 100, 0, 0, 0, 0, 0, 0
        )

    def _extended_sys_state(self) -> Any:
        return self.mav.extended_sys_state_encode(
            mavlink.MAV_VTOL_STATE_UNDEFINED, int(self.sim.autopilot.landed_state)
        )

    def _attitude(self) -> Any:
        e = self._est()
        roll, pitch, yaw = quat_to_euler(e.q_wxyz)
        return self.mav.attitude_encode(self.sim.time_ms, roll, pitch, yaw, *e.rate_frd_rad_s)

    def _attitude_quaternion(self) -> Any:
        e = self._est()
        return self.mav.attitude_quaternion_encode(
            self.sim.time_ms, *e.q_wxyz, *e.rate_frd_rad_s, [0.0, 0.0, 0.0, 0.0]
        )

    def _local_position_ned(self) -> Any:
        e = self._est()
        return self.mav.local_position_ned_encode(self.sim.time_ms, *e.pos_ned_m, *e.vel_ned_m_s)

    def _global_position_int(self) -> Any:
        e = self._est()
        lat_deg, lon_deg = self._geodetic(e.pos_ned_m)
        cfg = self.sim.config.sitl
        down_m = float(e.pos_ned_m[2])
        yaw_deg = math.degrees(quat_to_euler(e.q_wxyz)[2]) % 360.0
        vn, ve, vd = (round(float(v) * 100.0) for v in e.vel_ned_m_s)
        return self.mav.global_position_int_encode(
            self.sim.time_ms,
            round(lat_deg * 1e7),
            round(lon_deg * 1e7),
            round((cfg.home_amsl_m - down_m) * 1e3),
            round(-down_m * 1e3),
            vn,
            ve,
            vd,
            round(yaw_deg * 100.0) % 36000,
        )

    def _system_time(self) -> Any:
        # time_unix_usec 0: no GPS time (the simulation has none)
        return self.mav.system_time_encode(0, self.sim.time_ms)

    def _home_position(self) -> Any:
        cfg = self.sim.config.sitl
        return self.mav.home_position_encode(
            round(cfg.home_lat_deg * 1e7),
            round(cfg.home_lon_deg * 1e7),
            round(cfg.home_amsl_m * 1e3),
            0.0, 0.0, 0.0,
            [1.0, 0.0, 0.0, 0.0],
            0.0, 0.0, 0.0,
            self.sim.time_us,
        )  # fmt: skip

    def _geodetic(self, pos_ned_m: np.ndarray) -> tuple[float, float]:
        """Latitude and longitude (deg) of a local NED position: flat Earth about home."""
        cfg = self.sim.config.sitl
        lat = cfg.home_lat_deg + math.degrees(float(pos_ned_m[0]) / EARTH_RADIUS_M)
        cos_lat = math.cos(math.radians(cfg.home_lat_deg))
        lon = cfg.home_lon_deg + math.degrees(float(pos_ned_m[1]) / (EARTH_RADIUS_M * cos_lat))
        return lat, lon

    def _odometry(self, sample: _Sample | None = None) -> Any:
        if sample is None:  # asked for (REQUEST_MESSAGE): the newest
            sample = _Sample(self.sim.time_us, self._est())
        e = sample.estimate
        # PX4 sends ODOMETRY velocity in the child frame (body FRD).
        vel_frd = quat_to_rotation(e.q_wxyz).T @ e.vel_ned_m_s
        unknown_cov = [math.nan] + [0.0] * 20
        return self.mav.odometry_encode(
            sample.time_us,
            mavlink.MAV_FRAME_LOCAL_NED,
            mavlink.MAV_FRAME_BODY_FRD,
            *e.pos_ned_m,
            list(e.q_wxyz),
            *vel_frd,
            *e.rate_frd_rad_s,
            unknown_cov,
            unknown_cov,
            0,
            mavlink.MAV_ESTIMATOR_TYPE_NAIVE,
            100,
        )

    def _attitude_target(self) -> Any:
        cmd = self.sim.last_command
        return self.mav.attitude_target_encode(
            self.sim.time_ms, 0, list(cmd.q_cmd_wxyz), *cmd.rate_cmd_frd_rad_s, cmd.thrust_norm
        )

    def _autopilot_version(self) -> Any:
        version = (1 << 24) | (16 << 16)  # 1.16.0, like the PX4 the design notes describe
        return self.mav.autopilot_version_encode(
            _CAPABILITIES, version, 0, 0, 0, [0] * 8, [0] * 8, [0] * 8, 0, 0, self.sysid
        )


def _interval_us(rate_hz: float) -> int:
    return 0 if rate_hz <= 0.0 else round(1e6 / rate_hz)
