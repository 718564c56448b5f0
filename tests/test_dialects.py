"""Both autopilot dialects, intent by intent; the dialect chooser; and the state machine
against an ArduCopter-like autopilot: GUIDED before arming, one explicit takeoff, never a
NaN parameter in anything sent to ArduPilot."""

from __future__ import annotations

import math

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from epc_offboard.common import arducopter
from epc_offboard.vehicle import dialect_ardupilot as apm
from epc_offboard.vehicle import dialect_px4 as px4
from epc_offboard.vehicle.autopilots import choose
from epc_offboard.vehicle.dialect import (
    MAV_CMD_DO_SET_MODE,
    Action,
    EncodeError,
    FlightMode,
    Heartbeat,
    Position,
    TakeoffTarget,
)
from epc_offboard.vehicle.offboard import (
    LANDED_STATE_IN_AIR,
    LANDED_STATE_ON_GROUND,
    Inputs,
    OffboardStateMachine,
    Phase,
)
from tests.test_offboard import AUTO, HOME_AMSL_M, fault_schedules

TARGET = TakeoffTarget(2.5, HOME_AMSL_M + 2.5)
WHERE = Position(473977420, 85455940, 90.0)


def ap_hb(t: float, *, armed: bool = False, mode: int = arducopter.STABILIZE) -> Heartbeat:
    return Heartbeat(1, armed, 0, 0, t, custom_mode=mode, autopilot=3)


# -- PX4 -----------------------------------------------------------------------------------


def test_px4_every_intent():
    assert px4.PX4.encode(Action.ARM).command == 400
    assert px4.PX4.encode(Action.ARM).params[0] == 1.0
    takeoff = px4.PX4.encode(Action.TAKEOFF, TARGET, WHERE)
    assert takeoff.command == 22
    assert takeoff.int_frame == 0
    assert takeoff.params[3:] == (90.0, 473977420, 85455940, HOME_AMSL_M + 2.5)
    for action, main, sub in (
        (Action.REQUEST_OFFBOARD, 6, 0),
        (Action.REQUEST_HOLD, 4, 3),
        (Action.LAND, 4, 6),
    ):
        cmd = px4.PX4.encode(action)
        assert (cmd.command, cmd.params[:3]) == (MAV_CMD_DO_SET_MODE, (1.0, main, sub))
    with pytest.raises(EncodeError):
        px4.PX4.encode(Action.TAKEOFF)  # no altitude: never PX4's NaN default
    with pytest.raises(EncodeError):
        px4.PX4.encode(Action.TAKEOFF, TakeoffTarget(2.5, math.nan), WHERE)


def test_px4_modes():
    def mode(main: int, sub: int = 0) -> FlightMode:
        return px4.PX4.mode(Heartbeat(1, True, main, sub, 0.0))

    assert mode(6) == FlightMode.OFFBOARD
    assert mode(4, 2) == FlightMode.TAKEOFF
    assert mode(4, 3) == FlightMode.HOLD
    assert mode(4, 6) == FlightMode.LAND
    assert mode(3) == FlightMode.OTHER
    assert mode(4, 5) == FlightMode.OTHER  # RTL
    assert px4.PX4.wire_thrust(0.6, 0.8) == 0.6
    assert not px4.PX4.offboard_before_arming


# -- ArduPilot -----------------------------------------------------------------------------


def test_ardupilot_every_intent():
    arm = apm.ARDUPILOT.encode(Action.ARM)
    assert (arm.command, arm.params, arm.int_frame) == (400, (1.0,) + (0.0,) * 6, None)
    takeoff = apm.ARDUPILOT.encode(Action.TAKEOFF, TARGET, WHERE)
    # COMMAND_LONG, altitude ABOVE HOME in param7, every other param 0
    assert (takeoff.command, takeoff.int_frame) == (22, None)
    assert takeoff.params == (0.0,) * 6 + (2.5,)
    assert apm.ARDUPILOT.encode(Action.TAKEOFF, TARGET).params[6] == 2.5  # no position needed
    for action, number in (
        (Action.REQUEST_OFFBOARD, 4),  # GUIDED — never PX4's (1, 6, 0), which is RTL here
        (Action.REQUEST_HOLD, 17),  # BRAKE: LOITER's altitude is the pilot's stick
        (Action.LAND, 9),
    ):
        cmd = apm.ARDUPILOT.encode(action)
        assert cmd.command == MAV_CMD_DO_SET_MODE
        assert cmd.params == (1.0, float(number)) + (0.0,) * 5
        assert cmd.params[1] != arducopter.RTL
    for bad in (None, TakeoffTarget(math.nan, 0.0), TakeoffTarget(math.inf, 0.0),
                TakeoffTarget(0.0, 488.0), TakeoffTarget(-1.0, 487.0)):  # fmt: skip
        with pytest.raises(EncodeError):
            apm.ARDUPILOT.encode(Action.TAKEOFF, bad)


def test_ardupilot_modes():
    def mode(number: int) -> FlightMode:
        return apm.ARDUPILOT.mode(ap_hb(0.0, armed=True, mode=number))

    assert mode(arducopter.GUIDED) == FlightMode.OFFBOARD
    assert mode(arducopter.GUIDED_NOGPS) == FlightMode.OFFBOARD
    assert mode(arducopter.LOITER) == FlightMode.HOLD
    assert mode(arducopter.BRAKE) == FlightMode.HOLD
    assert mode(arducopter.LAND) == FlightMode.LAND
    for other in (arducopter.STABILIZE, arducopter.RTL, 3, 16):  # AUTO, POSHOLD: not ours
        assert mode(other) == FlightMode.OTHER
    # a PX4 main mode of 6 in the PX4 bits means nothing to ArduPilot
    assert apm.ARDUPILOT.mode(Heartbeat(1, True, 6, 0, 0.0, custom_mode=6 << 16)) == (
        FlightMode.OTHER
    )
    assert apm.ARDUPILOT.offboard_before_arming


def test_ardupilot_thrust_is_compensated_for_tilt_once():
    # ArduCopter divides throttle by cos(tilt): what we send times that boost is our thrust
    for thrust, cos_tilt in ((0.5, 1.0), (0.6, math.cos(0.4)), (0.7, 0.5)):
        sent = apm.ARDUPILOT.wire_thrust(thrust, cos_tilt)
        assert sent / cos_tilt == pytest.approx(thrust)
    assert apm.ARDUPILOT.wire_thrust(0.5, 0.0) == pytest.approx(0.05)  # boost floored at 0.1


def test_guid_options_gate():
    assert "not read" in apm.guided_refusal(None)
    for refused in (0.0, 1.0, 7.0, math.nan):
        assert "GUID_OPTIONS" in apm.guided_refusal(refused)
    for ok in (8.0, 9.0, 15.0):
        assert apm.guided_refusal(ok) == ""


def test_chooser():
    assert choose("auto", 12) is px4.PX4
    assert choose("auto", 3) is apm.ARDUPILOT
    assert choose("auto", None) is None
    assert choose("auto", 8) is None
    assert choose("px4", 3) is px4.PX4  # forced
    assert choose("ardupilot", None) is apm.ARDUPILOT
    with pytest.raises(ValueError, match="autopilot"):
        choose("apm", 3)


# -- the state machine against an ArduCopter-like autopilot ---------------------------------


def _step(sm, t, heartbeat, *, age=0.01, alt=0.0, landed=None, mission=False):
    return sm.step(
        Inputs(t, heartbeat, age, pos_down_m=-alt, relative_alt_m=alt,
               amsl_m=HOME_AMSL_M + alt, landed_state=landed, mission_complete=mission)
    )  # fmt: skip


def test_ardupilot_ritual_guided_before_arming_then_one_takeoff():
    sm = OffboardStateMachine(AUTO, dialect=apm.ARDUPILOT)
    out = _step(sm, 0.0, ap_hb(0.0))
    assert out.phase == Phase.PREFLIGHT
    assert out.actions == (Action.REQUEST_OFFBOARD,)  # GUIDED first, not ARM
    assert "GUIDED" in out.reason
    assert _step(sm, 0.5, ap_hb(0.0)).actions == ()  # no spam within the retry period
    out = _step(sm, 1.0, ap_hb(1.0, mode=arducopter.GUIDED))
    assert out.actions == (Action.ARM,)
    assert out.phase == Phase.PREFLIGHT  # GUIDED on the ground is not offboard flight
    out = _step(sm, 1.2, ap_hb(1.2, armed=True, mode=arducopter.GUIDED))
    assert out.actions == (Action.TAKEOFF,)
    assert out.takeoff is not None
    assert out.takeoff.above_home_m == pytest.approx(2.5)
    assert not out.stream_setpoints  # setpoints would override the takeoff in GUIDED
    out = _step(sm, 2.0, ap_hb(2.0, armed=True, mode=arducopter.GUIDED), alt=1.2)
    assert (out.phase, out.actions, out.stream_setpoints) == (Phase.PREFLIGHT, (), False)
    out = _step(sm, 3.0, ap_hb(3.0, armed=True, mode=arducopter.GUIDED), alt=2.3)
    assert out.phase == Phase.OFFBOARD  # reached: GUIDED is ours at once
    assert out.stream_setpoints
    # GUIDED left (the pilot, or a failsafe to LAND / RTL): never fought
    out = _step(sm, 4.0, ap_hb(4.0, armed=True, mode=arducopter.RTL), alt=2.5)
    assert out.phase == Phase.PILOT
    assert out.actions == ()
    # stale state in GUIDED: hold is BRAKE (LOITER's altitude follows the pilot's stick)
    _step(sm, 5.0, ap_hb(5.0, armed=True, mode=arducopter.GUIDED), alt=2.5)
    out = _step(sm, 5.1, ap_hb(5.0, armed=True, mode=arducopter.GUIDED), alt=2.5, age=1.0)
    assert out.phase == Phase.FAILSAFE
    assert out.actions == (Action.REQUEST_HOLD,)
    assert apm.ARDUPILOT.encode(out.actions[0]).params[1] == arducopter.BRAKE
    assert sm.takeoffs_sent == 1


def test_ardupilot_no_takeoff_outside_guided():
    sm = OffboardStateMachine(AUTO, dialect=apm.ARDUPILOT)
    # the pilot armed in STABILIZE: GUIDED is asked for, no takeoff until it shows
    out = _step(sm, 0.0, ap_hb(0.0, armed=True))
    assert out.actions == (Action.REQUEST_OFFBOARD,)
    assert sm.takeoffs_sent == 0
    out = _step(sm, 1.0, ap_hb(1.0, armed=True, mode=arducopter.GUIDED))
    assert out.actions == (Action.TAKEOFF,)


def test_ardupilot_mission_end_lands_in_land_mode():
    sm = OffboardStateMachine(AUTO, dialect=apm.ARDUPILOT)
    _step(sm, 0.0, ap_hb(0.0, armed=True, mode=arducopter.GUIDED), alt=2.5)
    # the first hand-over once the vehicle has been still for offboard.settled_for_s
    _step(sm, 0.5, ap_hb(0.5, armed=True, mode=arducopter.GUIDED), alt=2.5)
    assert sm.phase == Phase.OFFBOARD
    out = _step(sm, 1.0, ap_hb(1.0, armed=True, mode=arducopter.GUIDED), alt=2.5, mission=True)
    assert out.phase == Phase.LANDING
    assert out.actions == (Action.LAND,)
    assert apm.ARDUPILOT.encode(Action.LAND).params[1] == arducopter.LAND
    out = _step(sm, 2.0, ap_hb(2.0, armed=True, mode=arducopter.LAND), alt=1.0)
    assert out.actions == ()
    assert not out.stream_setpoints


class _ArduCopterLike:
    """A crude ArduCopter: plain modes, GUIDED needed to arm and take off (a takeoff of NaN
    is refused), LOITER / LAND, a heartbeat that lags, auto-disarm on the ground."""

    def __init__(self, hb_lag_s: float) -> None:
        self.t = 0.0
        self.armed = False
        self.alt = 0.0
        self.mode = arducopter.STABILIZE
        self.target: float | None = None
        self.hb_lag_s = hb_lag_s
        self.hb: Heartbeat | None = None
        self.ground_s = 0.0

    def apply(self, cmd_id: int, params: tuple[float, ...]) -> None:
        assert all(math.isfinite(p) for p in params), f"NaN to ArduPilot: {params}"
        if cmd_id == 400 and self.mode == arducopter.GUIDED and self.alt < 0.05:
            self.armed = True
        elif cmd_id == 22 and self.armed and self.mode == arducopter.GUIDED and self.alt < 0.5:
            self.target = params[6]
        elif cmd_id == MAV_CMD_DO_SET_MODE:
            self.mode = round(params[1])
            if self.mode != arducopter.GUIDED:
                self.target = None

    def advance(self, dt: float, push_m_s: float) -> None:
        self.t += dt
        if self.armed and self.target is not None and self.mode == arducopter.GUIDED:
            self.alt = min(self.target, self.alt + 1.5 * dt)
            if self.alt >= self.target - 0.05:
                self.target = None
        elif self.armed and self.mode == arducopter.LAND:
            self.alt = max(0.0, self.alt - 0.7 * dt)
        elif self.armed and self.alt > 0.0:
            self.alt = max(0.0, self.alt + push_m_s * dt)
        self.ground_s = self.ground_s + dt if self.alt <= 0.0 else 0.0
        if self.armed and self.ground_s > 3.0:
            self.armed = False  # landed, or armed and never took off (DISARM_DELAY)
        if self.hb is None or self.t - self.hb.received_s >= 1.0 + self.hb_lag_s:
            self.hb = Heartbeat(1, self.armed, 0, 0, self.t, custom_mode=self.mode, autopilot=3)


@settings(max_examples=60, deadline=None)
@given(
    faults=fault_schedules("pilot"),  # and the pilot takes over with an RC switch
    hb_lag_s=st.floats(0.0, 0.9),
    mission_s=st.one_of(st.none(), st.floats(2.0, 30.0)),
    landed_state_known=st.booleans(),
)
def test_ardupilot_never_a_nan_never_a_second_takeoff(
    faults, hb_lag_s, mission_s, landed_state_known
):
    sm = OffboardStateMachine(AUTO, dialect=apm.ARDUPILOT)
    ap = _ArduCopterLike(hb_lag_s)
    dt = 0.05
    takeoffs = 0
    left_ground = False
    offboard_since = None
    pushed_up_m = 0.0
    sent = 0
    for k in range(int(45.0 / dt)):
        t = k * dt
        active = {kind for start, length, kind in faults if start <= t < start + length}
        push = 1.0 if "push_up" in active else -1.0 if "push_down" in active else 0.0
        pushed_up_m += dt * max(push, 0.0)
        if "pilot" in active and ap.mode == arducopter.GUIDED:
            ap.mode = arducopter.LOITER  # the pilot takes over (a switch on the RC)
        ap.advance(dt, push)
        left_ground |= ap.alt >= 0.3
        heartbeat = None if "hb_loss" in active else ap.hb
        if sm.phase == Phase.OFFBOARD and offboard_since is None:
            offboard_since = t
        mission = (
            mission_s is not None
            and offboard_since is not None
            and (t - offboard_since >= mission_s)
        )
        glob = "no_global" not in active
        landed = None
        if landed_state_known:
            landed = LANDED_STATE_IN_AIR if ap.alt > 0.05 else LANDED_STATE_ON_GROUND
        out = sm.step(
            Inputs(t, heartbeat, 1.0 if "stale" in active else 0.01, pos_down_m=-ap.alt,
                   relative_alt_m=ap.alt if glob else None,
                   amsl_m=HOME_AMSL_M + ap.alt if glob else None,
                   landed_state=landed, mission_complete=mission)
        )  # fmt: skip
        for action in out.actions:
            if action == Action.TAKEOFF:
                takeoffs += 1
                assert not left_ground
                assert ap.alt < AUTO.airborne_altitude_m
                guided = arducopter.GUIDED
                assert ap.mode == guided or ap.hb is None or ap.hb.custom_mode == guided
            try:
                cmd = apm.ARDUPILOT.encode(action, out.takeoff, None)
            except EncodeError:
                continue
            # the property: whatever the state machine asks, ArduPilot gets finite params
            assert all(math.isfinite(p) for p in cmd.params), cmd
            rtl = arducopter.RTL
            assert not (cmd.command == MAV_CMD_DO_SET_MODE and round(cmd.params[1]) == rtl)
            ap.apply(cmd.command, cmd.params)
            sent += 1
        if out.phase in (Phase.LANDING, Phase.DONE, Phase.FAILSAFE):
            assert not out.stream_setpoints
    assert takeoffs <= 1
    assert ap.alt <= 2.5 + pushed_up_m + 1e-6
    assert sent > 0


def test_the_ardupilot_flight_completes_without_faults():
    """The property test's harness can fail: a clean run arms, takes off once, flies offboard
    and lands."""
    sm = OffboardStateMachine(AUTO, dialect=apm.ARDUPILOT)
    ap = _ArduCopterLike(0.3)
    phases = set()
    for k in range(int(40.0 / 0.05)):
        t = k * 0.05
        ap.advance(0.05, 0.0)
        out = _step(sm, t, ap.hb, alt=ap.alt,
                    mission=sm.phase == Phase.OFFBOARD and t > 15.0)  # fmt: skip
        phases.add(out.phase)
        for action in out.actions:
            cmd = apm.ARDUPILOT.encode(action, out.takeoff)
            ap.apply(cmd.command, cmd.params)
    assert {Phase.OFFBOARD, Phase.LANDING, Phase.DONE} <= phases
    assert sm.takeoffs_sent == 1
    assert sm.flights == 1
    assert not ap.armed
    assert ap.alt == 0.0
