"""Vehicle state from MAVLink messages: decoded, validated, timestamped, predicted forward.

The tracker is fed decoded pymavlink messages by the service and keeps the newest *valid*
sample of each kind. A sample with a NaN, an out-of-range value or a non-unit quaternion is
rejected, counted by reason, and never replaces a good one. Two times are kept per sample:
the vehicle's own timestamp (``time_boot_ms``/``time_usec``; drives the lockstep clock) and
the local receipt time (``time.monotonic``; drives staleness checks in real operation).

PX4 sends LOCAL_POSITION_NED and ODOMETRY at only 30 Hz by default while the position loop
runs at 100 Hz, so ``snapshot`` predicts the position forward at constant velocity to the
requested time, up to ``max_predict_s``, and reports how old the underlying samples are.
"""

from __future__ import annotations

import logging
import math
import time
from collections import Counter
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from epc_offboard import frames
from epc_offboard.frames import FloatArray

log = logging.getLogger(__name__)

MAV_MODE_FLAG_SAFETY_ARMED = 128
# time_boot_ms is truncated to whole ms while ODOMETRY's time_usec is not: samples of one
# instant can differ by up to a millisecond and must not count as out of order.
_ORDER_TOLERANCE_S = 1.5e-3
_MAX_CANDIDATES = 4  # candidate timelines kept per stream while judging a resync
MAV_FRAME_LOCAL_NED = 1
MAV_FRAME_LOCAL_FRD = 20
MAV_FRAME_BODY_FRD = 12

# PX4 custom_mode: main mode in bits 16-23, sub mode in bits 24-31.
PX4_MAIN_MODE_POSCTL = 3
PX4_MAIN_MODE_AUTO = 4
PX4_MAIN_MODE_OFFBOARD = 6
PX4_AUTO_SUB_TAKEOFF = 2
PX4_AUTO_SUB_LOITER = 3
PX4_AUTO_SUB_LAND = 6


def px4_custom_mode(main_mode: int, sub_mode: int = 0) -> int:
    return (main_mode << 16) | (sub_mode << 24)


def px4_modes(custom_mode: int) -> tuple[int, int]:
    """(main_mode, sub_mode) of a PX4 custom_mode."""
    return (custom_mode >> 16) & 0xFF, (custom_mode >> 24) & 0xFF


@dataclass(frozen=True)
class StateLimits:
    """Plausibility bounds: a sample outside them is rejected as corrupt, not clipped."""

    max_abs_pos_m: float = 1.0e4
    max_speed_m_s: float = 100.0
    max_rate_rad_s: float = 50.0
    quat_norm_tolerance: float = 0.05
    max_predict_s: float = 0.2
    # A stamp may run ahead of the receive clock by this much (link jitter, batching); more
    # is a spoofed or corrupt stamp, rejected without touching the tracker's vehicle time.
    max_time_jump_s: float = 1.0
    # This many consecutive samples of one stream that agree with each other but not with
    # the tracker's timeline (an autopilot reboot restarting time_boot_ms at 0, or a bad
    # stamp accepted first) move the tracker to their timeline: a resync, never a lockout.
    resync_samples: int = 5


@dataclass(frozen=True)
class Heartbeat:
    system_id: int
    armed: bool
    main_mode: int
    sub_mode: int
    received_s: float  # local monotonic time

    @property
    def offboard(self) -> bool:
        return self.main_mode == PX4_MAIN_MODE_OFFBOARD


@dataclass(frozen=True)
class VehicleState:
    """The newest valid state, predicted to ``time_s``. Arrays are NED/FRD, SI units."""

    time_s: float  # vehicle time this state is for
    pos_ned_m: FloatArray
    vel_ned_m_s: FloatArray
    q_ned_frd: FloatArray  # [w, x, y, z], body FRD -> world NED
    rate_frd_rad_s: FloatArray
    position_age_s: float  # vehicle time since the position sample this is predicted from
    attitude_age_s: float

    @property
    def euler_rad(self) -> tuple[float, float, float]:
        """(roll, pitch, yaw) Z-Y-X."""
        return frames.quat_to_euler(self.q_ned_frd)

    @property
    def yaw_rad(self) -> float:
        return self.euler_rad[2]


@dataclass
class _Sample:
    vehicle_s: float
    received_s: float
    values: tuple[FloatArray, ...]


@dataclass
class _Timeline:
    """One stream's newest accepted stamp and when it came (the receive clock)."""

    vehicle_s: float
    received_s: float

    def admits(self, t_s: float, now: float, max_jump_s: float) -> str | None:
        """None if ``t_s`` continues this timeline, else the reason it does not."""
        if t_s < self.vehicle_s - _ORDER_TOLERANCE_S:
            return "rejected_out_of_order"
        if t_s - self.vehicle_s > (now - self.received_s) + max_jump_s:
            return "rejected_time_jump"
        return None

    def continued_by(self, t_s: float, now: float, limits: StateLimits) -> bool:
        """Whether ``t_s`` advances a candidate timeline: strictly newer (a stream always
        moves on; a repeated stamp is no evidence) and not too far ahead."""
        return t_s > self.vehicle_s and self.admits(t_s, now, limits.max_time_jump_s) is None


@dataclass
class StateTracker:
    """Keeps the newest valid attitude and position samples of one vehicle.

    Order is judged per stream (ATTITUDE, ATTITUDE_QUATERNION, LOCAL_POSITION_NED, ODOMETRY
    each keep their own newest stamp): PX4's ODOMETRY carries the estimator's sample time,
    which trails ATTITUDE's, and is not out of order. A sample older than the one held from
    another stream is simply not newer news. Forward jumps are bounded against the receive
    clock, and a consistent new timeline is adopted after ``resync_samples`` samples.
    """

    system_id: int
    limits: StateLimits = field(default_factory=StateLimits)
    counters: Counter[str] = field(default_factory=Counter)
    heartbeat: Heartbeat | None = None
    _attitude: _Sample | None = None  # (q, rate)
    _position: _Sample | None = None  # (pos, vel)
    vehicle_time_s: float = 0.0  # newest vehicle timestamp seen in a valid state message
    _timelines: dict[str, _Timeline] = field(default_factory=dict)  # per stream (4 at most)
    _candidates: dict[str, list[list[_Timeline]]] = field(default_factory=dict)

    def handle(self, msg: Any, received_s: float | None = None) -> bool:
        """Consume one decoded message; True when it updated the state."""
        if msg.get_srcSystem() != self.system_id:
            return False
        now = time.monotonic() if received_s is None else received_s
        mtype = msg.get_type()
        if mtype == "HEARTBEAT":
            main, sub = px4_modes(int(msg.custom_mode))
            self.heartbeat = Heartbeat(
                self.system_id, bool(msg.base_mode & MAV_MODE_FLAG_SAFETY_ARMED), main, sub, now
            )
            return False
        if mtype == "ATTITUDE_QUATERNION":
            q = np.array([msg.q1, msg.q2, msg.q3, msg.q4], dtype=np.float64)
            rate = np.array([msg.rollspeed, msg.pitchspeed, msg.yawspeed], dtype=np.float64)
            return self._set_attitude(mtype, msg.time_boot_ms * 1e-3, now, q, rate)
        if mtype == "ATTITUDE":
            # validated before it is converted: NaN or absurd angles are corrupt, not math
            angles = (msg.roll, msg.pitch, msg.yaw)
            if not all(math.isfinite(a) for a in angles):
                self.counters["rejected_nan"] += 1
                return False
            if max(abs(a) for a in angles) > 2.0 * math.pi:
                self.counters["rejected_range"] += 1
                return False
            q = frames.euler_to_quat(msg.roll, msg.pitch, msg.yaw)
            rate = np.array([msg.rollspeed, msg.pitchspeed, msg.yawspeed], dtype=np.float64)
            return self._set_attitude(mtype, msg.time_boot_ms * 1e-3, now, q, rate)
        if mtype == "LOCAL_POSITION_NED":
            pos = np.array([msg.x, msg.y, msg.z], dtype=np.float64)
            vel = np.array([msg.vx, msg.vy, msg.vz], dtype=np.float64)
            return self._set_position(mtype, msg.time_boot_ms * 1e-3, now, pos, vel)
        if mtype == "ODOMETRY":
            return self._handle_odometry(msg, now)
        return False

    def _handle_odometry(self, msg: Any, now: float) -> bool:
        if msg.frame_id not in (MAV_FRAME_LOCAL_NED, MAV_FRAME_LOCAL_FRD):
            self.counters["odometry_unsupported_frame"] += 1
            return False
        t_s = msg.time_usec * 1e-6
        q = np.array(msg.q, dtype=np.float64)
        rate = np.array([msg.rollspeed, msg.pitchspeed, msg.yawspeed], dtype=np.float64)
        pos = np.array([msg.x, msg.y, msg.z], dtype=np.float64)
        vel = np.array([msg.vx, msg.vy, msg.vz], dtype=np.float64)
        if not self._valid_quat(q):
            return False
        if msg.child_frame_id == MAV_FRAME_BODY_FRD:
            vel = frames.quat_to_rotation(q) @ vel  # PX4 sends body-frame velocity
        if not self._admit("ODOMETRY", t_s, now):
            return False
        updated = self._set_attitude(None, t_s, now, q, rate)
        return self._set_position(None, t_s, now, pos, vel) or updated

    def _admit(self, stream: str | None, t_s: float, now: float) -> bool:
        """Whether stamp ``t_s`` of ``stream`` continues its timeline (None: already
        admitted by the caller). Rejections are counted; a run of them that agree with each
        other is a new timeline (reboot), adopted: resync."""
        if stream is None:
            return True
        if not math.isfinite(t_s):
            self.counters["rejected_time_jump"] += 1
            return False
        line = self._timelines.get(stream)
        reason = None if line is None else line.admits(t_s, now, self.limits.max_time_jump_s)
        if reason is None:
            # (candidates stay: a bad stamp accepted first must not wipe the evidence
            # against it; they are bounded and expire by the jump bound)
            self._timelines[stream] = _Timeline(t_s, now)
            return True
        self.counters[reason] += 1
        # candidate timelines of this stream: a sample extends the one it continues, else
        # starts one (past _MAX_CANDIDATES the shortest, then stalest, is dropped), so
        # interleaved garbage can neither break a genuine new timeline nor grow memory
        runs = self._candidates.setdefault(stream, [])
        run = next((r for r in runs if r[-1].continued_by(t_s, now, self.limits)), None)
        if run is None:
            if len(runs) >= _MAX_CANDIDATES:
                runs.remove(min(runs, key=lambda r: (len(r), r[-1].received_s)))
            run = []
            runs.append(run)
        run.append(_Timeline(t_s, now))
        del run[: -self.limits.resync_samples]
        if len(run) < self.limits.resync_samples:
            return False
        # a new timeline: forget the old one everywhere (every stream restarts with it)
        self.counters["time_resyncs"] += 1
        log.warning(
            "%s: %d consecutive samples on another timeline (%.3f s, was %.3f s): "
            "resynchronised (autopilot reboot or a bad stamp earlier)",
            stream, len(run), t_s, 0.0 if line is None else line.vehicle_s,
        )  # fmt: skip
        self._timelines = {stream: _Timeline(t_s, now)}
        self._candidates.clear()
        self._attitude = self._position = None
        self.vehicle_time_s = t_s
        return True

    def _valid_quat(self, q: FloatArray) -> bool:
        if not np.all(np.isfinite(q)):
            self.counters["rejected_nan"] += 1
            return False
        if abs(float(np.linalg.norm(q)) - 1.0) > self.limits.quat_norm_tolerance:
            self.counters["rejected_quaternion"] += 1
            return False
        return True

    def _set_attitude(
        self, stream: str | None, t_s: float, now: float, q: FloatArray, rate: FloatArray
    ) -> bool:
        if not self._valid_quat(q):
            return False
        if not np.all(np.isfinite(rate)):
            self.counters["rejected_nan"] += 1
            return False
        if float(np.max(np.abs(rate))) > self.limits.max_rate_rad_s:
            self.counters["rejected_range"] += 1
            return False
        if not self._admit(stream, t_s, now):
            return False
        if self._attitude is not None and t_s < self._attitude.vehicle_s - _ORDER_TOLERANCE_S:
            return False  # valid, but older than what another stream already gave
        self._attitude = _Sample(t_s, now, (frames.quat_normalize(q), rate))
        self.vehicle_time_s = max(self.vehicle_time_s, t_s)
        return True

    def _set_position(
        self, stream: str | None, t_s: float, now: float, pos: FloatArray, vel: FloatArray
    ) -> bool:
        if not (np.all(np.isfinite(pos)) and np.all(np.isfinite(vel))):
            self.counters["rejected_nan"] += 1
            return False
        if (
            float(np.max(np.abs(pos))) > self.limits.max_abs_pos_m
            or float(np.linalg.norm(vel)) > self.limits.max_speed_m_s
        ):
            self.counters["rejected_range"] += 1
            return False
        if not self._admit(stream, t_s, now):
            return False
        if self._position is not None and t_s < self._position.vehicle_s - _ORDER_TOLERANCE_S:
            return False  # valid, but older than what another stream already gave
        self._position = _Sample(t_s, now, (pos, vel))
        self.vehicle_time_s = max(self.vehicle_time_s, t_s)
        return True

    def age_s(self, now_s: float, *, vehicle_clock: bool) -> float:
        """Age of the older of the two samples: by vehicle time or by local receipt time."""
        if self._attitude is None or self._position is None:
            return math.inf
        if vehicle_clock:
            oldest = min(self._attitude.vehicle_s, self._position.vehicle_s)
        else:
            oldest = min(self._attitude.received_s, self._position.received_s)
        return max(0.0, now_s - oldest)

    def snapshot(self, at_vehicle_s: float | None = None) -> VehicleState | None:
        """The state predicted to vehicle time ``at_vehicle_s`` (default: newest sample time).

        None until both an attitude and a position sample have arrived.
        """
        if self._attitude is None or self._position is None:
            return None
        t = self.vehicle_time_s if at_vehicle_s is None else at_vehicle_s
        q, rate = self._attitude.values
        pos, vel = self._position.values
        dt_pos = t - self._position.vehicle_s
        # Constant-velocity prediction over the gap between position samples, never further
        # than max_predict_s: beyond that the sample is stale and the service must hold.
        dt_pred = min(max(dt_pos, 0.0), self.limits.max_predict_s)
        return VehicleState(
            time_s=t,
            pos_ned_m=pos + vel * dt_pred,
            vel_ned_m_s=vel.copy(),
            q_ned_frd=q.copy(),
            rate_frd_rad_s=rate.copy(),
            position_age_s=max(dt_pos, 0.0),
            attitude_age_s=max(t - self._attitude.vehicle_s, 0.0),
        )
