"""Vehicle state from MAVLink messages: decoded, validated, timestamped, predicted forward.

The tracker is fed decoded pymavlink messages by the service and keeps the newest *valid*
sample of each kind. A sample with a NaN, an out-of-range value or a non-unit quaternion is
rejected, counted by reason, and never replaces a good one. Two times are kept per sample:
the vehicle's own timestamp (``time_boot_ms``/``time_usec``) and the local receipt time
(``time.monotonic``). Age is judged by when a sample was MEASURED: in lockstep the stamp is
the clock; in real operation the stamp is mapped to the local clock (``timesync.py``: the
fastest delivery seen, and MAVLink TIMESYNC round trips), so a sample read late is old
whatever its receipt time says.

PX4 sends LOCAL_POSITION_NED and ODOMETRY at only 30 Hz by default while the position loop
runs at 100 Hz, so ``snapshot`` predicts the position forward at constant velocity to the
requested time, up to ``max_predict_s``, and reports how old the underlying samples are.
"""

from __future__ import annotations

import itertools
import logging
import math
import time
from collections import Counter, deque
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from epc_offboard.common import frames
from epc_offboard.common.frames import FloatArray
from epc_offboard.control.types import VehicleState
from epc_offboard.vehicle.dialect import Heartbeat
from epc_offboard.vehicle.dialect_px4 import px4_modes
from epc_offboard.vehicle.timesync import AutopilotClock

log = logging.getLogger(__name__)

MAV_MODE_FLAG_SAFETY_ARMED = 128
MAV_COMP_ID_AUTOPILOT1 = 1
MAV_AUTOPILOT_INVALID = 8  # MAVLink's "not a flight controller"
# MAV_TYPEs of components that are not a flight controller (antenna tracker, GCS, onboard
# computer, gimbal, ADS-B, camera, charging station, FLARM, servo, Open Drone ID, battery,
# parachute, logger, OSD, IMU, GPS, winch, illuminator, gripper): no flight mode in their
# heartbeat. A type past the dialect's last (49) is not one either.
_NOT_AUTOPILOT_TYPES = frozenset(
    {5, 6, 18, 26, 27, 30, 31, 32, 33, 34, 36, 37, 38, 39, 40, 41, 42, 44, 48}
)
_MAV_TYPE_END = 49
_FLAP_LOG_PERIOD_S = 10.0
_HEARD_KEPT = 16  # heartbeats kept to judge forgeries: a period's worth under a flood
_MAX_CLAIMS = 8  # changes being confirmed at once; past it the oldest claim is forgotten
# time_boot_ms is truncated to whole ms while ODOMETRY's time_usec is not: samples of one
# instant can differ by up to a millisecond and must not count as out of order.
_ORDER_TOLERANCE_S = 1.5e-3
_MAX_CANDIDATES = 4  # candidate timelines kept per stream while judging a resync
MAV_FRAME_LOCAL_NED = 1
MAV_FRAME_LOCAL_FRD = 20
MAV_FRAME_BODY_FRD = 12

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
    # Heartbeats. A genuine autopilot sends one every heartbeat_period_s (PX4, ArduPilot:
    # 1 Hz; regular ones arrive heartbeat_jitter_s early or late at most, in order), and
    # ArduPilot one more at once on every mode change. Every change is adopted at once on a
    # calm link. A flap is A, B, A where the two A are a period apart (within the jitter)
    # and nothing follows the second A for a period less the jitter: B lies inside one
    # period of the schedule, and the schedule contradicts it, with no heartbeat of its
    # own (ArduPilot's) changing back: a forged heartbeat between two genuine ones. No
    # genuine sequence is one: PX4's heartbeats are a period apart, so A, B, A spans two;
    # an ArduPilot change back to A comes with its own heartbeat, and the regular one
    # follows it within the period. Judged when the heartbeat after the second A comes.
    # Four heartbeats within a period less the jitter (a regular one and three mode
    # changes: no autopilot changes modes that fast) are a flood of forgeries: a flap too.
    # For heartbeat_calm_s after a flap, a change is adopted only once it has been claimed
    # for heartbeat_confirm_s (a period) with the mode held not claimed meanwhile: while
    # the vehicle keeps sending the mode held, no forgery lasts that long.
    heartbeat_period_s: float = 1.0
    heartbeat_jitter_s: float = 0.3
    heartbeat_calm_s: float = 10.0
    heartbeat_confirm_s: float = 1.0
    # The autopilot's (MAV_TYPE, MAV_AUTOPILOT) is learnt from its first heartbeat, and
    # learnt again only after this long without one.
    heartbeat_relearn_s: float = 5.0
    # The autopilot's clock on ours (timesync.py): how fast the offset may drift without
    # new evidence (s/s; crystals drift 1e-4), the longest TIMESYNC round trip trusted,
    # and how often one is asked for in real time (0: never; lockstep never does).
    max_clock_drift: float = 1.0e-3
    timesync_max_rtt_s: float = 0.05
    timesync_period_s: float = 0.5
    # Innovation gates, as an EKF's: a position further than max_innovation_m (plus what
    # innovation_accel_m_s2 allows over the gap) from where the last sample predicts it, or
    # an attitude further than max_innovation_rad (plus innovation_ang_accel_rad_s2's) from
    # the last one rotated on by its rates, is not flown. resync_samples rejected samples in
    # a row that agree with each other, with none accepted between, are the vehicle's own
    # estimator reset: adopted. With accepted ones between, two streams contradict each
    # other under one system id (forgery): counted, warned once, the held one flown.
    max_innovation_m: float = 1.0
    innovation_accel_m_s2: float = 20.0
    max_innovation_rad: float = 0.35
    innovation_ang_accel_rad_s2: float = 100.0

    def __post_init__(self) -> None:
        if not 0.0 <= self.max_clock_drift < 0.1:
            raise ValueError(f"max_clock_drift must be in [0, 0.1), got {self.max_clock_drift}")
        if self.timesync_max_rtt_s <= 0.0 or self.timesync_period_s < 0.0:
            raise ValueError("timesync_max_rtt_s must be > 0 and timesync_period_s >= 0")
        for name in ("max_innovation_m", "innovation_accel_m_s2", "max_innovation_rad",
                     "innovation_ang_accel_rad_s2"):  # fmt: skip
            if not getattr(self, name) > 0.0:
                raise ValueError(f"{name} must be > 0, got {getattr(self, name)}")


@dataclass
class _Sample:
    vehicle_s: float
    received_s: float
    values: tuple[FloatArray, ...]
    # the same values as plain floats: the gates run on every state message (~500/s), where
    # numpy on 3- and 4-vectors costs several times more
    flat: tuple[float, ...] = ()


def _position_innovation(held: _Sample, new: _Sample, limits: StateLimits) -> float:
    """How far (m) ``new``'s position lies outside the gate around ``held``'s prediction
    (<= 0: inside). ``flat``: (x, y, z, vx, vy, vz)."""
    px, py, pz, vx, vy, vz = held.flat
    nx, ny, nz = new.flat[:3]
    dt_s = new.vehicle_s - held.vehicle_s
    ex, ey, ez = nx - px - vx * dt_s, ny - py - vy * dt_s, nz - pz - vz * dt_s
    gate_m = limits.max_innovation_m + 0.5 * limits.innovation_accel_m_s2 * dt_s * dt_s
    return math.sqrt(ex * ex + ey * ey + ez * ez) - gate_m


def _attitude_innovation(held: _Sample, new: _Sample, limits: StateLimits) -> float:
    """How far (rad) ``new``'s attitude lies outside the gate around ``held`` rotated on by
    its rates (<= 0: inside), as frames.quat_integrate_body_rate, in floats. ``flat``:
    (w, x, y, z, rate x, y, z)."""
    w, x, y, z, rx, ry, rz = held.flat
    dt_s = new.vehicle_s - held.vehicle_s
    norm = math.sqrt(rx * rx + ry * ry + rz * rz)
    half = 0.5 * norm * dt_s
    if abs(half) > 1e-12:
        c, k = math.cos(half), math.sin(half) / norm
        bx, by, bz = rx * k, ry * k, rz * k
        w, x, y, z = (
            w * c - x * bx - y * by - z * bz,
            w * bx + x * c + y * bz - z * by,
            w * by - x * bz + y * c + z * bx,
            w * bz + x * by - y * bx + z * c,
        )
    nw, nx, ny, nz = new.flat[:4]
    dot = min(1.0, abs(w * nw + x * nx + y * ny + z * nz))
    gate_rad = limits.max_innovation_rad + 0.5 * limits.innovation_ang_accel_rad_s2 * dt_s**2
    return 2.0 * math.acos(dot) - gate_rad


@dataclass
class _Gate:
    """One kind of state's innovation gate: the run of rejected samples that agree with
    each other, and whether a sample measured after its first was accepted."""

    run: list[_Sample] = field(default_factory=list)
    accepted_since: bool = False


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
    # whose HEARTBEAT carries the flight mode: the autopilot's (config link.target_component;
    # 0 accepts any component, the type checks still apply)
    component_id: int = MAV_COMP_ID_AUTOPILOT1
    counters: Counter[str] = field(default_factory=Counter)
    heartbeat: Heartbeat | None = None
    _attitude: _Sample | None = None  # (q, rate)
    _position: _Sample | None = None  # (pos, vel)
    vehicle_time_s: float = 0.0  # newest vehicle timestamp seen in a valid state message
    _timelines: dict[str, _Timeline] = field(default_factory=dict)  # per stream (4 at most)
    _candidates: dict[str, list[list[_Timeline]]] = field(default_factory=dict)
    _kind: tuple[int, int] | None = None  # the autopilot's (MAV_TYPE, MAV_AUTOPILOT)
    _mode: tuple[bool, int] | None = None  # (armed, custom_mode) of the heartbeat held
    # the last heartbeats heard from the autopilot (held or not): (time, mode)
    _heard: deque[tuple[float, tuple[bool, int]]] = field(
        default_factory=lambda: deque(maxlen=_HEARD_KEPT)
    )
    _flap_s: float = -math.inf  # the last flap: changes need confirming until calm again
    # changes claimed since the mode held was last claimed: mode -> first claimed (bounded)
    _claims: dict[tuple[bool, int], float] = field(default_factory=dict)
    _flap_logged_s: float = -math.inf
    # when the autopilot last accepted a mode or arming change we commanded (local time):
    # an A, B, A around it is the vehicle's own (:meth:`change_commanded`)
    _commanded_s: float = -math.inf
    clock: AutopilotClock = field(init=False)  # the autopilot's stamps on the local clock
    _gates: dict[str, _Gate] = field(default_factory=dict)  # "attitude", "position"
    _conflict_logged: bool = False

    def __post_init__(self) -> None:
        # the skew a round trip shows carries the offset on for two requests' periods
        self.clock = AutopilotClock(self.limits.max_clock_drift, self.limits.timesync_max_rtt_s,
                                    2.0 * self.limits.timesync_period_s)  # fmt: skip

    def handle(self, msg: Any, received_s: float | None = None) -> bool:
        """Consume one decoded message; True when it updated the state."""
        if msg.get_srcSystem() != self.system_id:
            return False
        now = time.monotonic() if received_s is None else received_s
        mtype = msg.get_type()
        if mtype == "HEARTBEAT":
            if not self._accept_heartbeat(msg, now):
                return False
            main, sub = px4_modes(int(msg.custom_mode))
            self.heartbeat = Heartbeat(
                self.system_id,
                bool(msg.base_mode & MAV_MODE_FLAG_SAFETY_ARMED),
                main,
                sub,
                now,
                custom_mode=int(msg.custom_mode),
                autopilot=int(msg.autopilot),
            )
            return False
        # Validation runs on plain floats: this is every state message (some 500 a second
        # per vehicle), and numpy calls on 3- and 4-vectors cost several times more.
        if mtype == "ATTITUDE_QUATERNION":
            q = (msg.q1, msg.q2, msg.q3, msg.q4)
            rate = (msg.rollspeed, msg.pitchspeed, msg.yawspeed)
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
            q = frames.euler_to_quat(msg.roll, msg.pitch, msg.yaw).tolist()
            rate = (msg.rollspeed, msg.pitchspeed, msg.yawspeed)
            return self._set_attitude(mtype, msg.time_boot_ms * 1e-3, now, q, rate)
        if mtype == "LOCAL_POSITION_NED":
            pos = (msg.x, msg.y, msg.z)
            vel = (msg.vx, msg.vy, msg.vz)
            return self._set_position(mtype, msg.time_boot_ms * 1e-3, now, pos, vel)
        if mtype == "ODOMETRY":
            return self._handle_odometry(msg, now)
        return False

    def _accept_heartbeat(self, msg: Any, now: float) -> bool:
        """Whether this HEARTBEAT may replace the one held: the autopilot's (configured
        component, a flight controller's type, the autopilot's kind) and, while heartbeats
        flap, a change confirmed. Counted: ignored, flaps, changes held back."""
        if not self._from_autopilot(msg, now):
            self.counters["heartbeat_ignored"] += 1
            return False
        mode = (bool(msg.base_mode & MAV_MODE_FLAG_SAFETY_ARMED), int(msg.custom_mode))
        self._heard.append((now, mode))
        if self._forged_between() or self._flooded():
            self._flapped(now)
        limits = self.limits
        held, claims = self._mode, self._claims
        if held is None or mode == held:
            if claims:  # changes held back, contradicted: still flapping
                self._flapped(now)
                claims.clear()
            self._mode = mode
            return True
        if now - self._flap_s < limits.heartbeat_calm_s:
            first_s = claims.setdefault(mode, now)
            if now - first_s < limits.heartbeat_confirm_s:
                if len(claims) > _MAX_CLAIMS:
                    del claims[next(iter(claims))]
                self.counters["heartbeat_changes_held"] += 1
                return False
        self._mode = mode
        claims.clear()
        return True

    def change_commanded(self, now_s: float) -> None:
        """The autopilot accepted a mode or arming change we commanded (its COMMAND_ACK, on
        the heartbeats' clock). An A, B, A of heartbeats across it is no forgery: the vehicle
        itself changed twice within a period, at our asking (offboard asked, then Hold on a
        stale state 0.66 s later: a starved SITL at load 9-12 made the service's failsafe
        alternate so, and the heartbeat asked for after the first ack showed B between two
        regular A's; stop 43). The flap guard holds for forgeries at any other time."""
        self._commanded_s = max(self._commanded_s, now_s)

    def _flooded(self) -> bool:
        """Whether four heartbeats came within a period less the jitter: one regular and
        three mode changes, more than any autopilot makes (a flood of forgeries)."""
        heard = self._heard
        if len(heard) < 4:
            return False
        times = [heard[k][0] for k in range(-4, 0)]
        if any(b <= a for a, b in itertools.pairwise(times)):
            # a clock that did not move is no evidence: lockstep's vehicle time stands still
            # until state streams (the simulator repeats its heartbeat meanwhile)
            return False
        limits = self.limits
        return times[-1] - times[0] < limits.heartbeat_period_s - limits.heartbeat_jitter_s

    def _forged_between(self) -> bool:
        """Whether the heartbeats heard show a forgery: h0 says A after a quiet period,
        those after it, all inside the period, say other modes, then h2 says A a period
        after h0, and the newest came a period less the jitter or more after h2 (see
        StateLimits)."""
        heard = list(self._heard)
        if len(heard) < 4:
            return False
        limits = self.limits
        period, jitter = limits.heartbeat_period_s, limits.heartbeat_jitter_s
        quiet = period - jitter
        t3, _ = heard[-1]
        t2, m2 = heard[-2]
        if t3 - t2 < quiet or heard[-3][1] == m2:
            return False
        for k in range(len(heard) - 3, -1, -1):
            t0, m0 = heard[k]
            if m0 != m2:
                continue
            run_ok = heard[k + 1][0] - t0 > 0.0 and heard[-3][0] - t0 < quiet
            quiet_before = k == 0 or t0 - heard[k - 1][0] >= quiet
            ours = t0 < self._commanded_s <= t2  # a change we commanded lies in A, B, A
            return run_ok and quiet_before and abs(t2 - t0 - period) <= jitter and not ours
        return False

    def _from_autopilot(self, msg: Any, now: float) -> bool:
        if self.component_id and msg.get_srcComponent() != self.component_id:
            return False
        kind = (int(msg.type), int(msg.autopilot))
        mav_type, autopilot = kind
        if (
            autopilot == MAV_AUTOPILOT_INVALID
            or mav_type in _NOT_AUTOPILOT_TYPES
            or mav_type >= _MAV_TYPE_END
        ):
            return False
        hb = self.heartbeat
        if hb is None or now - hb.received_s > self.limits.heartbeat_relearn_s:
            self._kind = kind
        return kind == self._kind

    def _flapped(self, now: float) -> None:
        self.counters["heartbeat_flaps"] += 1
        self._flap_s = now
        if now - self._flap_logged_s >= _FLAP_LOG_PERIOD_S:
            self._flap_logged_s = now
            log.warning(
                "heartbeat mode/arming flapping (%d flaps so far): forged heartbeats? a mode "
                "change now needs %.1f s to be believed; MAVLink signing stops this",
                self.counters["heartbeat_flaps"], self.limits.heartbeat_confirm_s,
            )  # fmt: skip

    def _handle_odometry(self, msg: Any, now: float) -> bool:
        if msg.frame_id not in (MAV_FRAME_LOCAL_NED, MAV_FRAME_LOCAL_FRD):
            self.counters["odometry_unsupported_frame"] += 1
            return False
        t_s = msg.time_usec * 1e-6
        q = tuple(msg.q)
        rate = (msg.rollspeed, msg.pitchspeed, msg.yawspeed)
        pos: Sequence[float] = (msg.x, msg.y, msg.z)
        vel: Sequence[float] = (msg.vx, msg.vy, msg.vz)
        if self._quat_norm(q) is None:
            return False
        if msg.child_frame_id == MAV_FRAME_BODY_FRD:
            # PX4 sends body-frame velocity
            vel = (frames.quat_to_rotation(np.array(q)) @ np.array(vel)).tolist()
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
        # The state held is kept, re-stamped on the new timeline where it was measured by
        # our clock: its age goes on, nothing is wiped (a wiped state failed safe 3 ms after
        # a forged time jump: "state stale (inf s)"), and the new timeline's samples must
        # pass the innovation gates against it.
        for sample in (self._attitude, self._position):
            if sample is not None:
                measured = self.clock.to_local(sample.vehicle_s, now)
                local = sample.received_s if measured is None else measured
                sample.vehicle_s = t_s - (now - local)
        self.vehicle_time_s = t_s
        self.clock.reset()  # stamps of the old timeline say nothing of the new one's offset
        return True

    def _quat_norm(self, q: Sequence[float]) -> float | None:
        """The norm of quaternion ``q`` (4,), or None (counted) if it is not a unit one."""
        w, x, y, z = q
        if not (math.isfinite(w) and math.isfinite(x) and math.isfinite(y) and math.isfinite(z)):
            self.counters["rejected_nan"] += 1
            return None
        norm = math.sqrt(w * w + x * x + y * y + z * z)
        if abs(norm - 1.0) > self.limits.quat_norm_tolerance:
            self.counters["rejected_quaternion"] += 1
            return None
        return norm

    def _set_attitude(
        self,
        stream: str | None,
        t_s: float,
        now: float,
        q: Sequence[float],
        rate: Sequence[float],
    ) -> bool:
        norm = self._quat_norm(q)
        if norm is None:
            return False
        wx, wy, wz = rate
        if not (math.isfinite(wx) and math.isfinite(wy) and math.isfinite(wz)):
            self.counters["rejected_nan"] += 1
            return False
        if max(abs(wx), abs(wy), abs(wz)) > self.limits.max_rate_rad_s:
            self.counters["rejected_range"] += 1
            return False
        if not self._admit(stream, t_s, now):
            return False
        if self._attitude is not None and t_s < self._attitude.vehicle_s - _ORDER_TOLERANCE_S:
            return False  # valid, but older than what another stream already gave
        # frames.quat_normalize, on the norm already taken: unit, w >= 0
        qw, qx, qy, qz = (c / norm for c in q)
        if qw < 0.0:
            qw, qx, qy, qz = -qw, -qx, -qy, -qz
        sample = _Sample(
            t_s,
            now,
            (np.array([qw, qx, qy, qz]), np.array([wx, wy, wz], dtype=np.float64)),
            (qw, qx, qy, qz, wx, wy, wz),
        )
        if not self._gated("attitude", self._attitude, sample, _attitude_innovation):
            return False
        self._attitude = sample
        self.vehicle_time_s = max(self.vehicle_time_s, t_s)
        self.clock.observe(t_s, now)
        return True

    def _set_position(
        self,
        stream: str | None,
        t_s: float,
        now: float,
        pos: Sequence[float],
        vel: Sequence[float],
    ) -> bool:
        if not all(math.isfinite(v) for v in (*pos, *vel)):
            self.counters["rejected_nan"] += 1
            return False
        vn, ve, vd = vel
        if (
            max(abs(p) for p in pos) > self.limits.max_abs_pos_m
            or math.sqrt(vn * vn + ve * ve + vd * vd) > self.limits.max_speed_m_s
        ):
            self.counters["rejected_range"] += 1
            return False
        if not self._admit(stream, t_s, now):
            return False
        if self._position is not None and t_s < self._position.vehicle_s - _ORDER_TOLERANCE_S:
            return False  # valid, but older than what another stream already gave
        sample = _Sample(
            t_s,
            now,
            (np.array(pos, dtype=np.float64), np.array(vel, dtype=np.float64)),
            (*pos, *vel),
        )
        if not self._gated("position", self._position, sample, _position_innovation):
            return False
        self._position = sample
        self.vehicle_time_s = max(self.vehicle_time_s, t_s)
        self.clock.observe(t_s, now)
        return True

    def _gated(
        self,
        kind: str,
        held: _Sample | None,
        new: _Sample,
        innovation: Callable[[_Sample, _Sample, StateLimits], float],
    ) -> bool:
        """Whether ``new`` may replace ``held``: inside the innovation gate around the held
        sample's prediction, or the last of a run of rejected samples that agree with each
        other with none accepted between (the vehicle's estimator reset). Rejections and
        conflicts (a run with accepted samples between: two streams under one id) counted;
        a conflict warned once."""
        gate = self._gates.setdefault(kind, _Gate())
        limits = self.limits
        if held is None or innovation(held, new, limits) <= 0.0:
            # (one measured before the run began is no second stream: PX4's ODOMETRY
            # trails LOCAL_POSITION_NED, and may still say the estimate before its reset)
            if gate.run and new.vehicle_s > gate.run[0].vehicle_s:
                gate.accepted_since = True
            return True
        self.counters["rejected_innovation"] += 1
        if gate.run and innovation(gate.run[-1], new, limits) <= 0.0:
            gate.run.append(new)
        else:
            gate.run, gate.accepted_since = [new], False
        if len(gate.run) < limits.resync_samples:
            return False
        two_streams = gate.accepted_since
        gate.run, gate.accepted_since = [], False
        if not two_streams:
            self.counters["estimator_resets"] += 1
            log.warning("%s jumped and stayed: the vehicle's estimator reset, adopted", kind)
            return True
        self.counters["state_conflicts"] += 1
        if not self._conflict_logged:
            self._conflict_logged = True
            log.warning(
                "two %s streams contradict each other under system id %d: flying the one "
                "that agrees with the vehicle's motion; forged telemetry? MAVLink signing "
                "(link.signing_key_file) stops it", kind, self.system_id,
            )  # fmt: skip
        return False

    def age_s(self, now_s: float, *, vehicle_clock: bool) -> float:
        """Age of the older of the two samples since it was MEASURED: ``now_s`` is vehicle
        time (lockstep), or local time, to which the sample's stamp is mapped (a sample
        read late is old, whatever its receipt time)."""
        if self._attitude is None or self._position is None:
            return math.inf
        oldest = min(self._attitude.vehicle_s, self._position.vehicle_s)
        if not vehicle_clock:
            measured = self.clock.to_local(oldest, now_s)
            if measured is None:  # (no mapping: cannot happen once a sample is held)
                measured = min(self._attitude.received_s, self._position.received_s)
            oldest = measured
        return max(0.0, now_s - oldest)

    def vehicle_time_at(self, now_s: float, *, vehicle_clock: bool) -> float | None:
        """The vehicle time the state should be predicted to at loop time ``now_s``: in
        lockstep ``now_s`` itself (the clock is the vehicle's: the newest sample's time, or
        a SYSTEM_TIME tick after it), else ``now_s`` on the autopilot's clock (None before
        any sample)."""
        return now_s if vehicle_clock else self.clock.to_autopilot(now_s)

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
        dt_att = t - self._attitude.vehicle_s
        # Constant-velocity prediction over the gap between position samples, and the
        # attitude rotated on by the measured body rates over the gap between attitude
        # samples (PX4 gives ~123 Hz to a 200 Hz loop), never further than max_predict_s:
        # beyond that the sample is stale and the service must hold.
        horizon = self.limits.max_predict_s
        dt_pred = min(max(dt_pos, 0.0), horizon)
        dt_att_pred = min(max(dt_att, 0.0), horizon)
        return VehicleState(
            time_s=t,
            pos_ned_m=pos + vel * dt_pred,
            vel_ned_m_s=vel.copy(),
            q_ned_frd=frames.quat_integrate_body_rate(q, rate, dt_att_pred),
            rate_frd_rad_s=rate.copy(),
            position_age_s=max(dt_pos, 0.0),
            attitude_age_s=max(dt_att, 0.0),
        )
