"""The offboard state machine: the whole flight, from heartbeat to landing, as pure logic.

It is given what the link and the state tracker know (heartbeat, state age, altitude, the
autopilot's landed state, whether the mission is over) and returns what the service should
do: stream setpoints or not, and which commands to send. It never sends anything itself,
which is what makes every transition — and the safety invariants — testable without a
vehicle.

    WAIT_HEARTBEAT --heartbeat--> WAIT_STATE --state fresh--> PREFLIGHT
    PREFLIGHT: arm (opt-in) and take off (opt-in, ONE takeoff per flight, explicit altitude),
               or wait for the pilot to do it
    PREFLIGHT --altitude reached--> STREAMING: setpoints stream, offboard not yet requested
    STREAMING --streamed >= min_stream_s (and opt-in), the vehicle settled (the flight's
               first entry; or settle_timeout_s waited, counted)--> OFFBOARD_REQUESTED
    OFFBOARD_REQUESTED --heartbeat says offboard--> OFFBOARD
    OFFBOARD --heartbeat says another mode--> PILOT (pilot or autopilot took over: never
             fight it; keep streaming so the pilot can switch back)
    OFFBOARD --mission complete--> LANDING (LAND commanded, streaming stops) --disarmed--> DONE
             or, without mission.land_at_end, HOLD commanded --> DONE
    any controlling phase --autopilot lands by itself--> LANDING (streaming stops: PX4 goes
             back to Offboard after an auto-land if setpoints still stream)
    any --state stale / heartbeat lost--> FAILSAFE: stop streaming, command hold; when state
             is fresh again -> PREFLIGHT (which never takes off again once the vehicle has
             left the ground), or STREAMING if the heartbeat still shows offboard after
             hold_confirm_s; from then on offboard is confirmed only by a heartbeat
             received after the failsafe ended (an older one may predate PX4's own hold)

Safety invariants (property-tested in tests/test_offboard.py under random heartbeat delays,
stale-state gaps and mode lags):

* at most one TAKEOFF per flight, and it carries an explicit altitude;
* never a TAKEOFF while airborne: not once the vehicle has left the ground in this flight,
  not while the altitude is unknown, not while the autopilot reports it in the air;
* airborne is judged on altitude reached, never on climb rate; a flight ends only when the
  vehicle has been disarmed on the ground for ``landed_confirm_s``;
* once a flight has ended in a landing, nothing is automated again (no re-arm, no takeoff):
  the service's job is done.

Setpoints always stream before offboard is requested (PX4 refuses offboard otherwise, and
MAVSDK teaches the same ritual).

The autopilot's dialect (``dialect.py``) says how heartbeat modes read (offboard, takeoff,
hold, land). ArduCopter's (``offboard_before_arming``) changes one thing: PREFLIGHT selects
GUIDED before it arms and before the takeoff (ArduCopter cannot take off from STABILIZE),
and GUIDED + armed on the ground is the takeoff ritual, not offboard flight — control starts
once the takeoff's altitude is reached. Every invariant above holds for both.
"""

from __future__ import annotations

import enum
import math
from dataclasses import dataclass, field

from epc_offboard.vehicle import dialect_px4
from epc_offboard.vehicle.dialect import Action, Dialect, FlightMode, Heartbeat, TakeoffTarget

__all__ = ["Action", "Inputs", "OffboardConfig", "OffboardStateMachine", "Outputs", "Phase"]

# MAV_LANDED_STATE (EXTENDED_SYS_STATE.landed_state)
LANDED_STATE_ON_GROUND = 1
LANDED_STATE_IN_AIR = 2
LANDED_STATE_TAKEOFF = 3
LANDED_STATE_LANDING = 4


class Phase(enum.Enum):
    WAIT_HEARTBEAT = "wait_heartbeat"
    WAIT_STATE = "wait_state"
    PREFLIGHT = "preflight"
    STREAMING = "streaming"
    OFFBOARD_REQUESTED = "offboard_requested"
    OFFBOARD = "offboard"
    PILOT = "pilot"
    FAILSAFE = "failsafe"
    LANDING = "landing"  # a landing was commanded or is seen: the autopilot lands, we stop
    DONE = "done"  # the flight is over (landed and disarmed, or handed over holding)


_NEEDS_OFFBOARD_MODE = "waiting for the offboard mode (GUIDED) before the takeoff"
_CONTROLLING = frozenset({Phase.STREAMING, Phase.OFFBOARD_REQUESTED, Phase.OFFBOARD})
_STREAMING = _CONTROLLING | {Phase.PILOT}


@dataclass(frozen=True)
class OffboardConfig:
    """Opt-in automation (all off for a real vehicle) and the timing of the ritual."""

    auto_arm: bool = False
    auto_takeoff: bool = False
    auto_offboard: bool = False
    takeoff_altitude_m: float = 2.5  # above home, sent explicitly with the one takeoff
    takeoff_reached_tolerance_m: float = 0.3  # within this of the target: takeoff done
    # or within this once the autopilot has ended its takeoff (PX4 ends it NAV_MC_ALT_RAD,
    # 0.8 m, below the target and holds where it brakes)
    takeoff_ended_tolerance_m: float = 0.8
    airborne_altitude_m: float = 0.5  # above home: the vehicle has left the ground
    heartbeat_timeout_s: float = 3.0
    max_state_age_s: float = 0.25
    min_stream_s: float = 0.5  # setpoints streamed before offboard is requested
    retry_period_s: float = 1.0  # between repeated arm / offboard / hold / land requests
    hold_confirm_s: float = 2.5  # after a failsafe, wait this long for the heartbeat to show hold
    landed_confirm_s: float = 2.0  # disarmed on the ground this long: the flight is over
    # control starts (STREAMING) once the vertical speed is below this: ArduCopter handed
    # over 0.3 m below the takeoff's target still climbing 1.5 m/s, and no controller stops
    # that within 0.2 m (airborne itself is still judged on altitude alone)
    settled_vertical_speed_m_s: float = 0.4
    # The first hand-over of a flight (the offboard request; ArduCopter: the stream in
    # GUIDED) waits until the vehicle has been settled this long: the vertical speed under
    # the bound above and the horizontal under this one. Half of PX4's MPC_HOLD_MAX_XY
    # (0.8 m/s: below it PX4 itself locks a hold), so that a swing through zero while the
    # autopilot's hold still flies the vehicle back is not taken for a stop: in 10 m/s wind
    # PX4's takeoff ends 2.4 m downwind, brakes, and flies back at 0.6 m/s; handed over as
    # the speed crossed zero, the loops started from a 35 deg tilt being unwound (41 deg,
    # 9.5 cm mean error; 2.7 once settled). 0.3 s under the bound: the drift under 0.1 m,
    # and a swing through zero faster than 2 m/s^2 (a tilt changing ~12 deg) never passes.
    settled_horizontal_speed_m_s: float = 0.3
    settled_for_s: float = 0.3
    # not settled this long after the hand-over first waited: hand over anyway (logged,
    # counted as ``unsettled_entries``). PX4 holds meanwhile, so waiting costs time only. In
    # calm air PX4's takeoff has braked before the stream's min_stream_s is over (real PX4,
    # SIH: no wait at all); in 8.5 + 2.4 sin t m/s its hold flew the vehicle back the 2.4 m
    # its takeoff drifted and settled 3.9 s after streaming began (3 s: handed over at 0.29
    # m/s, still braking). A hold still moving after 5 s is being pushed by gusts it will
    # not stop either.
    settle_timeout_s: float = 5.0
    # the flight's first hand-over also waits for the controller to be ready (the service's
    # miss worker up: its start took 7-9 s at load 16 beside two CPU hogs, and until then
    # every tick flew the intermediate controller: 3 cm instead of 0.5), at most this long
    # after the hand-over first waited; then it goes, logged and counted. PX4 holds meanwhile.
    controller_ready_timeout_s: float = 20.0

    def __post_init__(self) -> None:
        for name in ("heartbeat_timeout_s", "max_state_age_s", "retry_period_s"):
            if getattr(self, name) <= 0.0:
                raise ValueError(f"{name} must be > 0, got {getattr(self, name)}")
        if not 0.0 <= self.controller_ready_timeout_s <= 600.0:
            raise ValueError(
                f"controller_ready_timeout_s must be 0..600, got {self.controller_ready_timeout_s}"
            )
        for name in ("settled_vertical_speed_m_s", "settled_horizontal_speed_m_s"):
            if not getattr(self, name) > 0.0:
                raise ValueError(f"{name} must be > 0, got {getattr(self, name)}")
        if not 0.0 <= self.settled_for_s <= self.settle_timeout_s:
            raise ValueError(
                "settled_for_s must be >= 0 and <= settle_timeout_s, got "
                f"{self.settled_for_s} and {self.settle_timeout_s}"
            )
        if self.airborne_altitude_m <= 0.0:
            raise ValueError(f"airborne_altitude_m must be > 0, got {self.airborne_altitude_m}")
        if self.takeoff_reached_tolerance_m < 0.0 or self.landed_confirm_s < 0.0:
            raise ValueError("takeoff_reached_tolerance_m and landed_confirm_s must be >= 0")
        if self.takeoff_ended_tolerance_m < self.takeoff_reached_tolerance_m:
            raise ValueError(
                "takeoff_ended_tolerance_m must be >= takeoff_reached_tolerance_m, got "
                f"{self.takeoff_ended_tolerance_m}"
            )
        if self.takeoff_altitude_m - self.takeoff_reached_tolerance_m <= self.airborne_altitude_m:
            raise ValueError(
                "takeoff_altitude_m - takeoff_reached_tolerance_m must exceed airborne_altitude_m"
            )


@dataclass(frozen=True)
class Inputs:
    now_s: float  # the loops' clock
    heartbeat: Heartbeat | None
    state_age_s: float
    pos_down_m: float | None = None  # local NED down of the newest state; None if unknown
    relative_alt_m: float | None = None  # the autopilot's height above home, if it says
    amsl_m: float | None = None  # altitude above mean sea level now (GLOBAL_POSITION_INT)
    landed_state: int | None = None  # MAV_LANDED_STATE from EXTENDED_SYS_STATE, if sent
    mission_complete: bool = False  # the service's trajectory has run its duration
    vel_down_m_s: float | None = None  # NED down velocity of the newest state, if known
    speed_horizontal_m_s: float | None = None  # its horizontal speed (north, east), if known
    # the service's controller is ready to fly (its miss worker up): the first hand-over
    # waits for it (OffboardConfig.controller_ready_timeout_s)
    controller_ready: bool = True


@dataclass(frozen=True)
class Outputs:
    phase: Phase
    stream_setpoints: bool
    actions: tuple[Action, ...]
    reason: str  # why the phase is what it is, for STATUS= and the log
    takeoff: TakeoffTarget | None = None  # set when actions holds TAKEOFF
    altitude_m: float | None = None  # height above home as the machine judges it


@dataclass
class _Flight:
    """What one flight (arm to disarm on the ground) has done so far."""

    left_ground: bool = False
    takeoff_sent: bool = False
    takeoff_target: TakeoffTarget | None = None
    takeoff_done: bool = False  # the takeoff's target altitude was reached, or it ended
    takeoff_mode_seen: bool = False  # a heartbeat showed the autopilot's takeoff after ours
    landing: bool = False  # a landing was commanded or seen
    land_commanded: bool = False  # by us, at the mission's end
    land_seen: bool = False  # the heartbeat showed the autopilot landing
    disarmed_on_ground_since_s: float | None = None
    offboard_entered: bool = False  # offboard was confirmed once (later entries: not gated)
    settled_since_s: float | None = None  # under both settle bounds since then (None: moving)
    settle_wait_since_s: float | None = None  # the hand-over first waited for settling then
    settle_timed_out: bool = False  # it waited settle_timeout_s and went (counted once)
    ready_timed_out: bool = False  # it waited controller_ready_timeout_s and went (counted)
    ready_waited: bool = False  # it waited for the controller (said with the hand-over)


@dataclass
class OffboardStateMachine:
    config: OffboardConfig
    phase: Phase = Phase.WAIT_HEARTBEAT
    transitions: int = 0
    takeoffs_sent: int = 0  # over the machine's life (diagnostics, tests)
    flights: int = 0  # flights that ended on the ground
    unsettled_entries: int = 0  # hand-overs made at settle_timeout_s, the vehicle still moving
    unready_entries: int = 0  # hand-overs made at controller_ready_timeout_s, controller not up
    _phase_since_s: float = 0.0
    # Leaving a failsafe, offboard is confirmed only by a heartbeat received after: the 1 Hz
    # heartbeat that showed offboard may predate the autopilot's own setpoint-loss hold, and
    # the loops would fly (and the estimator learn, taking the vehicle's thrust for ours)
    # while the autopilot holds with its own: a disturbance wound up for up to a second.
    _confirm_after_s: float = -math.inf
    _last_request_s: dict[Action, float] = field(default_factory=dict)
    _reason: str = "no heartbeat yet"
    _home_down_m: float | None = None
    _flight: _Flight = field(default_factory=_Flight)
    _settle_note: str = ""  # said with the hand-over that went unsettled, once
    _finished: bool = False  # a flight ended in a landing: automate nothing more
    land_at_end: bool = True  # mission.land_at_end: at the mission's end, land (else hold)
    # how the heartbeat's modes read and whether offboard comes before arming (ArduCopter)
    dialect: Dialect = dialect_px4.PX4

    def _offboard(self, hb: Heartbeat) -> bool:
        return self.dialect.mode(hb) == FlightMode.OFFBOARD

    def _offboard_now(self, hb: Heartbeat) -> bool:
        """Offboard, shown by a heartbeat received since the last failsafe ended."""
        return self._offboard(hb) and hb.received_s > self._confirm_after_s

    def _taking_off(self, hb: Heartbeat) -> bool:
        return self.dialect.mode(hb) == FlightMode.TAKEOFF

    def _landing(self, hb: Heartbeat) -> bool:
        return self.dialect.mode(hb) == FlightMode.LAND

    def _enter(self, phase: Phase, now_s: float, reason: str) -> None:
        if phase != self.phase:
            if self.phase == Phase.FAILSAFE:
                self._confirm_after_s = now_s
            self.phase = phase
            self._phase_since_s = now_s
            self._flight.offboard_entered |= phase == Phase.OFFBOARD
            self.transitions += 1
            self._last_request_s.clear()
        self._reason = reason

    def _due(self, action: Action, now_s: float) -> bool:
        last = self._last_request_s.get(action)
        if last is None or now_s - last >= self.config.retry_period_s:
            self._last_request_s[action] = now_s
            return True
        return False

    # -- altitude and the flight's memory ----------------------------------------------------

    def _altitude(self, inp: Inputs, hb: Heartbeat | None) -> float | None:
        """Height above home: the autopilot's own if it says, else local down against the
        ground captured while disarmed. Home is re-captured only between flights."""
        flight = self._flight
        armed = hb is not None and hb.armed
        if (
            inp.pos_down_m is not None
            and math.isfinite(inp.pos_down_m)
            and hb is not None
            and not armed
            and not flight.left_ground
        ):
            self._home_down_m = inp.pos_down_m
        if inp.relative_alt_m is not None and math.isfinite(inp.relative_alt_m):
            return inp.relative_alt_m
        if inp.pos_down_m is None or self._home_down_m is None or not math.isfinite(inp.pos_down_m):
            return None
        return self._home_down_m - inp.pos_down_m

    def _track_flight(self, inp: Inputs, hb: Heartbeat | None, alt: float | None) -> None:
        cfg = self.config
        flight = self._flight
        in_air_reported = inp.landed_state in (
            LANDED_STATE_IN_AIR,
            LANDED_STATE_TAKEOFF,
            LANDED_STATE_LANDING,
        )
        if (alt is not None and alt >= cfg.airborne_altitude_m) or (
            hb is not None and hb.armed and in_air_reported
        ):
            flight.left_ground = True
        target = flight.takeoff_target
        if target is not None and alt is not None:
            flight.takeoff_done |= alt >= target.above_home_m - cfg.takeoff_reached_tolerance_m
        if target is not None and hb is not None and self._taking_off(hb):
            flight.takeoff_mode_seen = True
        elif target is not None and flight.takeoff_mode_seen and hb is not None and hb.armed:
            # The autopilot says its takeoff is over (PX4: TAKEOFF -> LOITER). A real PX4
            # ends it within NAV_MC_ALT_RAD (0.8 m) of the target and holds wherever it
            # brakes: 2.3 m of 2.5 in one flight, reached 1.2 s after the hold began, and a
            # hold below the tolerance would never have streamed at all.
            ended_m = target.above_home_m - cfg.takeoff_ended_tolerance_m
            flight.takeoff_done |= flight.left_ground and alt is not None and alt >= ended_m
        vz, vh = inp.vel_down_m_s, inp.speed_horizontal_m_s
        # unknown speeds hold nothing back (as the climb's check); a NaN is not still
        still = (vz is None or abs(vz) <= cfg.settled_vertical_speed_m_s) and (
            vh is None or vh <= cfg.settled_horizontal_speed_m_s
        )
        if not still:
            flight.settled_since_s = None
        elif flight.settled_since_s is None:
            flight.settled_since_s = inp.now_s
        if hb is not None and hb.armed and self._landing(hb) and flight.left_ground:
            flight.landing = flight.land_seen = True
        on_ground = (alt is not None and alt < cfg.airborne_altitude_m) and not in_air_reported
        if hb is not None and not hb.armed and on_ground:
            if flight.disarmed_on_ground_since_s is None:
                flight.disarmed_on_ground_since_s = inp.now_s
            if inp.now_s - flight.disarmed_on_ground_since_s >= cfg.landed_confirm_s:
                self._end_flight()
        else:
            flight.disarmed_on_ground_since_s = None

    def _end_flight(self) -> None:
        flight = self._flight
        if flight.left_ground or flight.takeoff_sent:
            self.flights += 1
        automated = self.config.auto_arm or self.config.auto_takeoff
        # The mission's own landing ends the job; with automation on, any landing does (the
        # autopilot landed for a reason: the service never re-arms it by itself).
        if flight.land_commanded or (flight.left_ground and automated):
            self._finished = True
        self._flight = _Flight()

    # -- the step ------------------------------------------------------------------------------

    def step(self, inp: Inputs) -> Outputs:
        cfg = self.config
        now = inp.now_s
        hb = inp.heartbeat
        hb_ok = hb is not None and now - hb.received_s <= cfg.heartbeat_timeout_s
        state_ok = inp.state_age_s <= cfg.max_state_age_s
        alt = self._altitude(inp, hb if hb_ok else None)
        self._track_flight(inp, hb if hb_ok else None, alt)
        flight = self._flight
        actions: list[Action] = []

        if self.phase == Phase.DONE or self._finished:
            self._enter(Phase.DONE, now, "flight over: landed and disarmed")
            return self._out(False, actions, alt)
        if self.phase == Phase.LANDING and not flight.landing:
            # the flight ended (disarmed on the ground) after a landing we did not command,
            # with no automation: wait for the pilot's next flight
            self._enter(Phase.PREFLIGHT, now, "landed")
        if self.phase == Phase.LANDING or (flight.landing and self.phase in _STREAMING):
            return self._landing_step(inp, hb if hb_ok else None, actions, alt)
        if inp.mission_complete and self.phase in _STREAMING:
            return self._mission_end(inp, hb if hb_ok else None, actions, alt)

        controlling = self.phase in _CONTROLLING
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
        elif self.phase == Phase.FAILSAFE and hb is not None and self._offboard(hb):
            # Heartbeats come at 1 Hz: give our hold request time to show before deciding the
            # vehicle is (again, by a pilot's choice) in offboard.
            if now - self._phase_since_s >= cfg.hold_confirm_s:
                # streaming again; OFFBOARD once a heartbeat received from now on shows it
                self._enter(Phase.STREAMING, now, "offboard kept after failsafe")
            else:
                self._reason = "state fresh again: waiting for hold to show"
        elif self.phase in (Phase.WAIT_HEARTBEAT, Phase.WAIT_STATE, Phase.FAILSAFE):
            self._enter(Phase.PREFLIGHT, now, "state flowing")

        if self.phase == Phase.FAILSAFE:
            offboard = hb_ok and hb is not None and self._offboard(hb)
            if offboard and self._due(Action.REQUEST_HOLD, now):
                actions.append(Action.REQUEST_HOLD)
            return self._out(False, actions, alt)
        if self.phase in (Phase.WAIT_HEARTBEAT, Phase.WAIT_STATE) or hb is None:
            return self._out(False, actions, alt)

        if self.phase == Phase.PREFLIGHT:
            takeoff = self._preflight(hb, inp, alt, actions)
            if takeoff is not None:
                return self._out(False, actions, alt, takeoff)
        if self.phase == Phase.STREAMING:
            if self._offboard_now(hb):
                self._enter(Phase.OFFBOARD, now, "offboard confirmed")
            elif cfg.auto_offboard and now - self._phase_since_s >= cfg.min_stream_s:
                unsettled = self._unsettled(inp)
                if unsettled:
                    self._reason = unsettled
                else:
                    reason = self._entry_reason("requesting offboard")
                    self._enter(Phase.OFFBOARD_REQUESTED, now, reason)
        if self.phase == Phase.OFFBOARD_REQUESTED:
            if self._offboard_now(hb):
                self._enter(Phase.OFFBOARD, now, "offboard confirmed")
            elif not hb.armed:
                self._enter(Phase.PREFLIGHT, now, "disarmed")
            elif self._due(Action.REQUEST_OFFBOARD, now):
                actions.append(Action.REQUEST_OFFBOARD)
        if self.phase == Phase.OFFBOARD and not self._offboard(hb):
            self._enter(Phase.PILOT, now, "left offboard (pilot or autopilot failsafe)")
        if self.phase == Phase.PILOT:
            if self._offboard(hb):
                self._enter(Phase.OFFBOARD, now, "offboard re-entered by the pilot")
            elif not hb.armed:
                self._enter(Phase.PREFLIGHT, now, "disarmed")
        return self._out(self.phase in _STREAMING, actions, alt)

    def _out(
        self,
        stream: bool,
        actions: list[Action],
        alt: float | None,
        takeoff: TakeoffTarget | None = None,
    ) -> Outputs:
        return Outputs(self.phase, stream, tuple(actions), self._reason, takeoff, alt)

    def _preflight(
        self, hb: Heartbeat, inp: Inputs, alt: float | None, actions: list[Action]
    ) -> TakeoffTarget | None:
        """Arm and take off (opt-in) or wait; returns the takeoff target when one is sent."""
        cfg = self.config
        now = inp.now_s
        flight = self._flight
        before_arming = self.dialect.offboard_before_arming
        # (ArduCopter: GUIDED + armed on the ground is the takeoff ritual, not offboard flight;
        # once airborne it streams, and STREAMING sees GUIDED as offboard at once)
        if self._offboard_now(hb) and hb.armed and not before_arming:
            self._enter(Phase.OFFBOARD, now, "already in offboard")
            return None
        if self._landing(hb):
            self._reason = "the autopilot is landing"
            return None
        target = flight.takeoff_target
        climbing = target is not None and not flight.takeoff_done
        # Airborne is judged on altitude reached. During our own takeoff: its target (the
        # heartbeat's mode lags by up to a second, so it is not asked); otherwise, as after a
        # pilot's takeoff or a failsafe, off the ground and not in the autopilot's takeoff.
        reached = (
            target.above_home_m - cfg.takeoff_reached_tolerance_m
            if target is not None and climbing
            else cfg.airborne_altitude_m
        )
        flying = hb.armed and alt is not None and alt >= reached
        if flying and (target is not None or not self._taking_off(hb)):
            vz = inp.vel_down_m_s
            if vz is not None and abs(vz) > cfg.settled_vertical_speed_m_s:
                self._reason = f"airborne: waiting for the climb to settle ({-vz:.1f} m/s)"
                return None
            # ArduCopter in GUIDED: streaming IS the hand-over (STREAMING sees GUIDED as
            # offboard at once), so it waits for the vehicle to settle here
            unsettled = self._unsettled(inp) if self._offboard(hb) else ""
            if unsettled:
                self._reason = unsettled
                return None
            reason = self._entry_reason("airborne: streaming setpoints")
            self._enter(Phase.STREAMING, now, reason)
            return None
        if not hb.armed:
            if self._finished:
                self._reason = "flight over: not re-arming"
            elif flight.left_ground:
                self._reason = "disarmed in the air?: waiting"  # never re-arm off the ground
            elif cfg.auto_arm and before_arming and not self._offboard(hb):
                # ArduCopter cannot take off from the mode it boots in: GUIDED first
                if self._due(Action.REQUEST_OFFBOARD, now):
                    actions.append(Action.REQUEST_OFFBOARD)
                self._reason = "selecting the offboard mode (GUIDED) before arming"
            elif cfg.auto_arm:
                if self._due(Action.ARM, now):
                    actions.append(Action.ARM)
                self._reason = "arming"
            else:
                self._reason = "waiting for the pilot to arm"
            return None
        if not cfg.auto_takeoff:
            self._reason = "waiting for takeoff"
            return None
        why_not = self._takeoff_blocked(hb, inp, alt)
        if why_not:
            self._reason = why_not
            if why_not == _NEEDS_OFFBOARD_MODE and self._due(Action.REQUEST_OFFBOARD, now):
                actions.append(Action.REQUEST_OFFBOARD)
            return None
        assert alt is not None  # _takeoff_blocked checked both
        assert inp.amsl_m is not None
        target = TakeoffTarget(cfg.takeoff_altitude_m, inp.amsl_m - alt + cfg.takeoff_altitude_m)
        flight.takeoff_sent = True
        flight.takeoff_target = target
        self.takeoffs_sent += 1
        actions.append(Action.TAKEOFF)
        self._reason = f"taking off to {target.above_home_m:.1f} m"
        return target

    def _unsettled(self, inp: Inputs) -> str:
        """Why the flight's first hand-over must wait for the vehicle to settle ("" once it
        has been under both speed bounds for ``settled_for_s``, or after ``settle_timeout_s``
        of waiting: then counted in ``unsettled_entries``), and for the controller to be ready
        (``Inputs.controller_ready``; at most ``controller_ready_timeout_s``, then counted in
        ``unready_entries``). Later entries (after a failsafe, a pilot) are not held: the
        vehicle is already flying our setpoints or the pilot's.
        """
        cfg = self.config
        flight = self._flight
        now = inp.now_s
        since = flight.settled_since_s
        if flight.offboard_entered:
            return ""
        if flight.settle_wait_since_s is None:
            flight.settle_wait_since_s = now
        waited_s = now - flight.settle_wait_since_s
        if not inp.controller_ready and not flight.ready_timed_out:
            if waited_s < cfg.controller_ready_timeout_s:
                flight.ready_waited = True
                return "airborne: waiting for the controller (its miss worker) to start"
            flight.ready_timed_out = True  # counted once
            self.unready_entries += 1
            self._settle_note += f" (controller not ready after {waited_s:.1f} s)"
        elif flight.ready_waited:  # said once, with the hand-over
            flight.ready_waited = False
            self._settle_note += f" (waited {waited_s:.1f} s for the controller)"
        if flight.settle_timed_out:
            return ""
        if since is not None and now - since >= cfg.settled_for_s:
            return ""
        vh, vz = inp.speed_horizontal_m_s, inp.vel_down_m_s
        speed = "unknown" if vh is None or vz is None else f"{vh:.2f} m/s, {-vz:.2f} up"
        if waited_s >= cfg.settle_timeout_s:
            flight.settle_timed_out = True  # counted once: nothing more to hold this flight
            self.unsettled_entries += 1
            self._settle_note += f" (not settled after {waited_s:.1f} s: {speed})"
            return ""
        return f"airborne: waiting for the vehicle to settle ({speed})"

    def _entry_reason(self, what: str) -> str:
        """The hand-over's reason, saying so when it went before the vehicle had settled."""
        note, self._settle_note = self._settle_note, ""
        return what + note

    def _takeoff_blocked(self, hb: Heartbeat, inp: Inputs, alt: float | None) -> str:
        """Why a takeoff must not be sent now ("" when it may)."""
        flight = self._flight
        if flight.left_ground:
            return "in the air: never taking off again"
        if flight.takeoff_sent:
            return "taking off (one takeoff per flight)"
        if self._finished:
            return "flight over"
        if alt is None:
            return "waiting for the altitude above home"
        if alt >= self.config.airborne_altitude_m:
            return "in the air: never taking off again"
        if inp.landed_state not in (None, LANDED_STATE_ON_GROUND):
            return "the autopilot says it is not on the ground"
        if self._taking_off(hb):
            return "the autopilot is taking off"
        if self.dialect.offboard_before_arming and not self._offboard(hb):
            return _NEEDS_OFFBOARD_MODE
        if inp.amsl_m is None or not math.isfinite(inp.amsl_m):
            return "waiting for the altitude AMSL (GLOBAL_POSITION_INT) for an explicit takeoff"
        return ""

    def _mission_end(
        self, inp: Inputs, hb: Heartbeat | None, actions: list[Action], alt: float | None
    ) -> Outputs:
        """The trajectory is over: land (mission.land_at_end) or hand over holding."""
        if self.land_at_end:
            self._flight.landing = self._flight.land_commanded = True
            self._enter(Phase.LANDING, inp.now_s, "mission complete: landing")
            return self._landing_step(inp, hb, actions, alt)
        if hb is not None and self._due(Action.REQUEST_HOLD, inp.now_s):
            actions.append(Action.REQUEST_HOLD)
        self._enter(Phase.DONE, inp.now_s, "mission complete: holding")
        return self._out(False, actions, alt)

    def _landing_step(
        self, inp: Inputs, hb: Heartbeat | None, actions: list[Action], alt: float | None
    ) -> Outputs:
        """Streaming stops for good. Our own LAND is resent until the heartbeat shows the
        autopilot landing once; after that never again (a pilot may take over the landing)."""
        flight = self._flight
        if self.phase != Phase.LANDING:
            self._enter(Phase.LANDING, inp.now_s, "the autopilot is landing")
        if (
            flight.land_commanded
            and not flight.land_seen
            and hb is not None
            and hb.armed
            and not self._landing(hb)
            and self._due(Action.LAND, inp.now_s)
        ):
            actions.append(Action.LAND)
        return self._out(False, actions, alt)
