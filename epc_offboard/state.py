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

import math
import time
from collections import Counter
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from epc_offboard import frames
from epc_offboard.frames import FloatArray

MAV_MODE_FLAG_SAFETY_ARMED = 128
# time_boot_ms is truncated to whole ms while ODOMETRY's time_usec is not: samples of one
# instant can differ by up to a millisecond and must not count as out of order.
_ORDER_TOLERANCE_S = 1.5e-3
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
class StateTracker:
    """Keeps the newest valid attitude and position samples of one vehicle."""

    system_id: int
    limits: StateLimits = field(default_factory=StateLimits)
    counters: Counter[str] = field(default_factory=Counter)
    heartbeat: Heartbeat | None = None
    _attitude: _Sample | None = None  # (q, rate)
    _position: _Sample | None = None  # (pos, vel)
    vehicle_time_s: float = 0.0  # newest vehicle timestamp seen in a valid state message

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
            return self._set_attitude(msg.time_boot_ms * 1e-3, now, q, rate)
        if mtype == "ATTITUDE":
            q = frames.euler_to_quat(msg.roll, msg.pitch, msg.yaw)
            rate = np.array([msg.rollspeed, msg.pitchspeed, msg.yawspeed], dtype=np.float64)
            return self._set_attitude(msg.time_boot_ms * 1e-3, now, q, rate)
        if mtype == "LOCAL_POSITION_NED":
            pos = np.array([msg.x, msg.y, msg.z], dtype=np.float64)
            vel = np.array([msg.vx, msg.vy, msg.vz], dtype=np.float64)
            return self._set_position(msg.time_boot_ms * 1e-3, now, pos, vel)
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
        updated = self._set_attitude(t_s, now, q, rate)
        return self._set_position(t_s, now, pos, vel) or updated

    def _valid_quat(self, q: FloatArray) -> bool:
        if not np.all(np.isfinite(q)):
            self.counters["rejected_nan"] += 1
            return False
        if abs(float(np.linalg.norm(q)) - 1.0) > self.limits.quat_norm_tolerance:
            self.counters["rejected_quaternion"] += 1
            return False
        return True

    def _set_attitude(self, t_s: float, now: float, q: FloatArray, rate: FloatArray) -> bool:
        if not self._valid_quat(q):
            return False
        if not np.all(np.isfinite(rate)):
            self.counters["rejected_nan"] += 1
            return False
        if float(np.max(np.abs(rate))) > self.limits.max_rate_rad_s:
            self.counters["rejected_range"] += 1
            return False
        if self._attitude is not None and t_s < self._attitude.vehicle_s - _ORDER_TOLERANCE_S:
            self.counters["rejected_out_of_order"] += 1
            return False
        self._attitude = _Sample(t_s, now, (frames.quat_normalize(q), rate))
        self.vehicle_time_s = max(self.vehicle_time_s, t_s)
        return True

    def _set_position(self, t_s: float, now: float, pos: FloatArray, vel: FloatArray) -> bool:
        if not (np.all(np.isfinite(pos)) and np.all(np.isfinite(vel))):
            self.counters["rejected_nan"] += 1
            return False
        if (
            float(np.max(np.abs(pos))) > self.limits.max_abs_pos_m
            or float(np.linalg.norm(vel)) > self.limits.max_speed_m_s
        ):
            self.counters["rejected_range"] += 1
            return False
        if self._position is not None and t_s < self._position.vehicle_s - _ORDER_TOLERANCE_S:
            self.counters["rejected_out_of_order"] += 1
            return False
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
