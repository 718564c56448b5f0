"""The offboard state machine: when to stream, arm, take off, ask for offboard, or hold.

Pure logic: it is given what the link and the state tracker know (heartbeat, state age, the
time) and returns what the service should do. It never sends anything itself, which is what
makes every transition testable without a vehicle.

    WAIT_HEARTBEAT --heartbeat--> WAIT_STATE --state fresh--> PREFLIGHT
    PREFLIGHT: arm (opt-in) and take off (opt-in), or wait for the pilot to do it
    PREFLIGHT --airborne--> STREAMING: setpoints stream, offboard not yet requested
    STREAMING --streamed >= min_stream_s (and opt-in)--> OFFBOARD_REQUESTED
    OFFBOARD_REQUESTED --heartbeat says offboard--> OFFBOARD
    OFFBOARD --heartbeat says another mode--> PILOT (pilot or autopilot took over: never
             fight it; keep streaming so the pilot can switch back)
    any --state stale / heartbeat lost--> FAILSAFE: stop streaming, command hold; when state
             is fresh again -> WAIT_STATE (re-entering the ritual from the top)

Setpoints always stream before offboard is requested (PX4 refuses offboard otherwise, and
MAVSDK teaches the same ritual).
"""

from __future__ import annotations

import enum
from dataclasses import dataclass, field

from epc_offboard.state import (
    PX4_AUTO_SUB_LAND,
    PX4_AUTO_SUB_TAKEOFF,
    PX4_MAIN_MODE_AUTO,
    Heartbeat,
)


class Phase(enum.Enum):
    WAIT_HEARTBEAT = "wait_heartbeat"
    WAIT_STATE = "wait_state"
    PREFLIGHT = "preflight"
    STREAMING = "streaming"
    OFFBOARD_REQUESTED = "offboard_requested"
    OFFBOARD = "offboard"
    PILOT = "pilot"
    FAILSAFE = "failsafe"
    LANDING = "landing"  # the service's mission is over: the autopilot lands the vehicle


class Action(enum.Enum):
    ARM = "arm"
    TAKEOFF = "takeoff"
    REQUEST_OFFBOARD = "request_offboard"
    REQUEST_HOLD = "request_hold"


@dataclass(frozen=True)
class OffboardConfig:
    """Opt-in automation (all off for a real vehicle) and the timing of the ritual."""

    auto_arm: bool = False
    auto_takeoff: bool = False
    auto_offboard: bool = False
    takeoff_altitude_m: float = 2.5
    airborne_altitude_m: float = 0.5  # above which the vehicle counts as flying
    settled_climb_rate_m_s: float = 0.3  # ...and climbing or sinking slower than this
    heartbeat_timeout_s: float = 3.0
    max_state_age_s: float = 0.25
    min_stream_s: float = 0.5  # setpoints streamed before offboard is requested
    retry_period_s: float = 1.0  # between repeated arm / takeoff / offboard requests
    hold_confirm_s: float = 2.5  # after a failsafe, wait this long for the heartbeat to show hold

    def __post_init__(self) -> None:
        for name in ("heartbeat_timeout_s", "max_state_age_s", "retry_period_s"):
            if getattr(self, name) <= 0.0:
                raise ValueError(f"{name} must be > 0, got {getattr(self, name)}")
        if self.takeoff_altitude_m <= self.airborne_altitude_m:
            raise ValueError("takeoff_altitude_m must exceed airborne_altitude_m")


@dataclass(frozen=True)
class Inputs:
    now_s: float  # monotonic
    heartbeat: Heartbeat | None
    state_age_s: float
    altitude_m: float | None  # height above home, positive up; None if unknown
    climb_rate_m_s: float = 0.0  # positive up


@dataclass(frozen=True)
class Outputs:
    phase: Phase
    stream_setpoints: bool
    actions: tuple[Action, ...]
    reason: str  # why the phase is what it is, for STATUS= and the log


@dataclass
class OffboardStateMachine:
    config: OffboardConfig
    phase: Phase = Phase.WAIT_HEARTBEAT
    transitions: int = 0
    _phase_since_s: float = 0.0
    _last_request_s: dict[Action, float] = field(default_factory=dict)
    _reason: str = "no heartbeat yet"

    def _enter(self, phase: Phase, now_s: float, reason: str) -> None:
        if phase != self.phase:
            self.phase = phase
            self._phase_since_s = now_s
            self.transitions += 1
            self._last_request_s.clear()
        self._reason = reason

    def _due(self, action: Action, now_s: float) -> bool:
        last = self._last_request_s.get(action)
        if last is None or now_s - last >= self.config.retry_period_s:
            self._last_request_s[action] = now_s
            return True
        return False

    def step(self, inp: Inputs) -> Outputs:
        cfg = self.config
        now = inp.now_s
        hb = inp.heartbeat
        hb_ok = hb is not None and now - hb.received_s <= cfg.heartbeat_timeout_s
        state_ok = inp.state_age_s <= cfg.max_state_age_s
        controlling = self.phase in (Phase.STREAMING, Phase.OFFBOARD_REQUESTED, Phase.OFFBOARD)

        if not hb_ok:
            if controlling or self.phase == Phase.PILOT:
                self._enter(Phase.FAILSAFE, now, "heartbeat lost")
            elif self.phase != Phase.FAILSAFE:
                self._enter(Phase.WAIT_HEARTBEAT, now, "no heartbeat")
        elif not state_ok:
            if controlling or self.phase == Phase.PILOT:
                self._enter(Phase.FAILSAFE, now, f"state stale ({inp.state_age_s:.3f} s)")
            elif self.phase != Phase.FAILSAFE:
                self._enter(Phase.WAIT_STATE, now, "waiting for fresh state")
        elif self.phase == Phase.FAILSAFE and hb is not None and hb.offboard:
            # Heartbeats come at 1 Hz: give our hold request time to show before deciding the
            # vehicle is (again, by a pilot's choice) in offboard.
            if now - self._phase_since_s >= cfg.hold_confirm_s:
                self._enter(Phase.OFFBOARD, now, "offboard kept after failsafe")
            else:
                self._reason = "state fresh again: waiting for hold to show"
        elif self.phase in (Phase.WAIT_HEARTBEAT, Phase.WAIT_STATE, Phase.FAILSAFE):
            self._enter(Phase.PREFLIGHT, now, "state flowing")

        actions: list[Action] = []
        if self.phase == Phase.FAILSAFE:
            if hb_ok and hb is not None and hb.offboard and self._due(Action.REQUEST_HOLD, now):
                actions.append(Action.REQUEST_HOLD)
            return Outputs(self.phase, False, tuple(actions), self._reason)

        assert hb is not None or self.phase in (Phase.WAIT_HEARTBEAT, Phase.WAIT_STATE)
        if self.phase == Phase.PREFLIGHT and hb is not None:
            self._preflight(hb, inp, actions)
        if self.phase == Phase.STREAMING and hb is not None:
            if hb.offboard:
                self._enter(Phase.OFFBOARD, now, "offboard confirmed")
            elif cfg.auto_offboard and now - self._phase_since_s >= cfg.min_stream_s:
                self._enter(Phase.OFFBOARD_REQUESTED, now, "requesting offboard")
        if self.phase == Phase.OFFBOARD_REQUESTED and hb is not None:
            if hb.offboard:
                self._enter(Phase.OFFBOARD, now, "offboard confirmed")
            elif not hb.armed:
                self._enter(Phase.PREFLIGHT, now, "disarmed")
            elif self._due(Action.REQUEST_OFFBOARD, now):
                actions.append(Action.REQUEST_OFFBOARD)
        if self.phase == Phase.OFFBOARD and hb is not None and not hb.offboard:
            self._enter(Phase.PILOT, now, "left offboard (pilot or autopilot failsafe)")
        if self.phase == Phase.PILOT and hb is not None:
            if hb.offboard:
                self._enter(Phase.OFFBOARD, now, "offboard re-entered by the pilot")
            elif not hb.armed:
                self._enter(Phase.PREFLIGHT, now, "disarmed")
        stream = self.phase in (
            Phase.STREAMING,
            Phase.OFFBOARD_REQUESTED,
            Phase.OFFBOARD,
            Phase.PILOT,
        )
        return Outputs(self.phase, stream, tuple(actions), self._reason)

    def _preflight(self, hb: Heartbeat, inp: Inputs, actions: list[Action]) -> None:
        cfg = self.config
        now = inp.now_s
        if hb.offboard:
            self._enter(Phase.OFFBOARD, now, "already in offboard")
            return
        # A heartbeat comes once a second, so its mode can lag a takeoff just commanded:
        # flying also means the climb has settled, or offboard would cut the takeoff short.
        airborne = (
            inp.altitude_m is not None
            and inp.altitude_m >= cfg.airborne_altitude_m
            and abs(inp.climb_rate_m_s) <= cfg.settled_climb_rate_m_s
        )
        taking_off = hb.main_mode == PX4_MAIN_MODE_AUTO and hb.sub_mode == PX4_AUTO_SUB_TAKEOFF
        landing = hb.main_mode == PX4_MAIN_MODE_AUTO and hb.sub_mode == PX4_AUTO_SUB_LAND
        if hb.armed and airborne and not taking_off and not landing:
            self._enter(Phase.STREAMING, now, "airborne: streaming setpoints")
            return
        if not hb.armed:
            if cfg.auto_arm and self._due(Action.ARM, now):
                actions.append(Action.ARM)
            self._reason = "arming" if cfg.auto_arm else "waiting for the pilot to arm"
            return
        if not airborne and not taking_off and cfg.auto_takeoff and self._due(Action.TAKEOFF, now):
            actions.append(Action.TAKEOFF)
        self._reason = "taking off" if cfg.auto_takeoff else "waiting for takeoff"
