"""The offboard state machine, transition by transition, and its safety invariants as
properties under random heartbeat delays, stale-state gaps and mode lags."""

from __future__ import annotations

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from epc_offboard.common.configio import ConfigError, from_dict
from epc_offboard.vehicle.dialect import Heartbeat
from epc_offboard.vehicle.offboard import (
    LANDED_STATE_IN_AIR,
    LANDED_STATE_ON_GROUND,
    Action,
    Inputs,
    OffboardConfig,
    OffboardStateMachine,
    Phase,
)

AUTO = OffboardConfig(auto_arm=True, auto_takeoff=True, auto_offboard=True)
HOME_AMSL_M = 488.0


def hb(t, *, armed=False, main=3, sub=0):
    return Heartbeat(1, armed, main, sub, t)


def step(sm, t, heartbeat, *, age=0.01, alt=0.0, landed=None, mission=False):
    """The autopilot reports its height above home (GLOBAL_POSITION_INT) and AMSL."""
    return sm.step(
        Inputs(
            t,
            heartbeat,
            age,
            pos_down_m=-alt,
            relative_alt_m=alt,
            amsl_m=HOME_AMSL_M + alt,
            landed_state=landed,
            mission_complete=mission,
        )
    )


def test_full_automatic_ritual():
    sm = OffboardStateMachine(AUTO)
    out = step(sm, 0.0, None, age=float("inf"))
    assert out.phase == Phase.WAIT_HEARTBEAT
    assert not out.stream_setpoints
    out = step(sm, 0.1, hb(0.1), age=float("inf"))
    assert out.phase == Phase.WAIT_STATE
    out = step(sm, 0.2, hb(0.1))
    assert out.phase == Phase.PREFLIGHT
    assert out.actions == (Action.ARM,)
    assert step(sm, 0.3, hb(0.1)).actions == ()  # no request spam inside the retry period
    assert step(sm, 1.3, hb(0.1)).actions == (Action.ARM,)
    out = step(sm, 1.4, hb(1.4, armed=True))
    assert out.actions == (Action.TAKEOFF,)
    assert out.takeoff is not None
    assert out.takeoff.above_home_m == pytest.approx(2.5)
    assert out.takeoff.amsl_m == pytest.approx(HOME_AMSL_M + 2.5)  # explicit, never NaN
    out = step(sm, 2.0, hb(2.0, armed=True, main=4, sub=2), alt=1.0)  # AUTO.TAKEOFF
    assert out.phase == Phase.PREFLIGHT
    assert out.actions == ()
    # the 1 Hz heartbeat still says LOITER (from before the takeoff) while the vehicle
    # climbs: below the takeoff altitude it is not done, and no second takeoff is sent
    out = step(sm, 2.5, hb(2.5, armed=True, main=4, sub=3), alt=1.5)
    assert out.phase == Phase.PREFLIGHT
    assert out.actions == ()
    out = step(sm, 3.0, hb(3.0, armed=True, main=4, sub=3), alt=2.3)  # reached, within 0.3 m
    assert out.phase == Phase.STREAMING
    assert out.stream_setpoints
    assert out.actions == ()
    out = step(sm, 3.2, hb(3.0, armed=True, main=4, sub=3), alt=2.5)
    assert out.phase == Phase.STREAMING  # streams min_stream_s before asking
    out = step(sm, 3.6, hb(3.0, armed=True, main=4, sub=3), alt=2.5)
    assert out.phase == Phase.OFFBOARD_REQUESTED
    assert out.actions == (Action.REQUEST_OFFBOARD,)
    assert out.stream_setpoints
    out = step(sm, 3.7, hb(3.7, armed=True, main=6), alt=2.5)
    assert out.phase == Phase.OFFBOARD
    assert out.stream_setpoints


def test_no_automation_by_default_waits_for_the_pilot():
    sm = OffboardStateMachine(OffboardConfig())
    step(sm, 0.0, hb(0.0))
    out = step(sm, 0.1, hb(0.1))
    assert out.phase == Phase.PREFLIGHT
    assert out.actions == ()
    assert "pilot" in out.reason
    out = step(sm, 5.0, hb(5.0, armed=True, main=4, sub=3), alt=3.0)
    assert out.phase == Phase.STREAMING
    out = step(sm, 9.0, hb(9.0, armed=True, main=4, sub=3), alt=3.0)
    assert out.phase == Phase.STREAMING  # never asks for offboard by itself
    assert out.actions == ()
    out = step(sm, 9.1, hb(9.1, armed=True, main=6), alt=3.0)  # pilot switches to offboard
    assert out.phase == Phase.OFFBOARD


def flying(sm):
    """A service (re)started while the vehicle flies in offboard: it never saw home."""
    for t, h in ((0.0, hb(0.0, armed=True, main=6)), (0.1, hb(0.1, armed=True, main=6))):
        step(sm, t, h, alt=3.0, landed=LANDED_STATE_IN_AIR)
    assert sm.phase == Phase.OFFBOARD


def test_stale_state_fails_safe_and_recovers():
    sm = OffboardStateMachine(AUTO)
    flying(sm)
    out = step(sm, 0.2, hb(0.2, armed=True, main=6), age=1.0, alt=3.0)
    assert out.phase == Phase.FAILSAFE
    assert not out.stream_setpoints
    assert out.actions == (Action.REQUEST_HOLD,)
    assert "stale" in out.reason
    # fresh again before the 1 Hz heartbeat shows the hold: stay in failsafe, keep asking
    out = step(sm, 0.25, hb(0.1, armed=True, main=6), alt=3.0)
    assert out.phase == Phase.FAILSAFE
    assert not out.stream_setpoints
    out = step(sm, 0.3, hb(0.3, armed=True, main=4, sub=3), age=1.0, alt=3.0)
    assert out.actions == ()  # vehicle already left offboard: no more hold requests
    # fresh again and still airborne: straight back to streaming, the ritual from the top
    out = step(sm, 0.4, hb(0.4, armed=True, main=4, sub=3), alt=3.0)
    assert out.phase == Phase.STREAMING
    assert out.stream_setpoints
    out = step(sm, 1.0, hb(1.0, armed=True, main=4, sub=3), alt=3.0)
    assert out.phase == Phase.OFFBOARD_REQUESTED


def test_offboard_kept_after_failsafe_is_respected():
    sm = OffboardStateMachine(AUTO)
    flying(sm)
    step(sm, 0.2, hb(0.2, armed=True, main=6), age=1.0, alt=3.0)
    assert sm.phase == Phase.FAILSAFE
    out = step(sm, 1.3, hb(1.3, armed=True, main=6), alt=3.0)
    assert out.phase == Phase.FAILSAFE
    assert out.actions == (Action.REQUEST_HOLD,)  # retried after retry_period_s
    out = step(sm, 3.0, hb(2.9, armed=True, main=6), alt=3.0)
    assert out.phase == Phase.STREAMING  # streaming again, no hold asked for
    assert out.stream_setpoints
    assert out.actions == ()
    out = step(sm, 3.1, hb(3.05, armed=True, main=6), alt=3.0)
    assert out.phase == Phase.OFFBOARD


@pytest.mark.parametrize("frozen", [False, True])
def test_after_a_failsafe_offboard_is_confirmed_only_by_a_newer_heartbeat(frozen):
    """The 1 Hz heartbeat that showed offboard when the state came back may predate the
    autopilot's own setpoint-loss hold (COM_OF_LOSS_T): the service then flew and learnt
    as if in control (learn=True) while PX4 held with its own thrust, up to a second,
    and the disturbance estimate wound up (soak: ``offboard`` rows over PX4's HOLD).

    ``frozen``: the autopilot's heartbeats stopped (frozen, link lost) and the first one
    back still shows offboard; else the state went stale (stale_state) under the hold."""
    sm = OffboardStateMachine(AUTO)
    flying(sm)
    if frozen:
        assert step(sm, 5.0, hb(0.1, armed=True, main=6), alt=3.0).phase == Phase.FAILSAFE
        t_back = 8.0  # frozen longer than hold_confirm_s
    else:
        step(sm, 0.2, hb(0.2, armed=True, main=6), age=1.0, alt=3.0)
        assert sm.phase == Phase.FAILSAFE
        t_back = 3.0
    # fresh again; the newest heartbeat (received just before) still shows offboard
    last_offboard = hb(t_back - 0.05, armed=True, main=6)
    out = step(sm, t_back, last_offboard, alt=3.0)
    assert out.phase != Phase.OFFBOARD, out
    assert step(sm, t_back + 0.5, last_offboard, alt=3.0).phase != Phase.OFFBOARD
    # the next heartbeat shows the autopilot's hold: never offboard on the old one
    out = step(sm, t_back + 0.95, hb(t_back + 0.95, armed=True, main=4, sub=3), alt=3.0)
    assert out.phase in (Phase.STREAMING, Phase.OFFBOARD_REQUESTED), out
    # and a heartbeat received after streaming resumed confirms it
    out = step(sm, t_back + 1.2, hb(t_back + 1.2, armed=True, main=6), alt=3.0)
    assert out.phase == Phase.OFFBOARD


def test_heartbeat_loss_fails_safe():
    sm = OffboardStateMachine(AUTO)
    flying(sm)
    out = step(sm, 5.0, hb(0.1, armed=True, main=6), alt=3.0)
    assert out.phase == Phase.FAILSAFE
    assert not out.stream_setpoints


def test_pilot_takeover_is_never_fought():
    sm = OffboardStateMachine(AUTO)
    flying(sm)
    for t in (0.2, 1.5, 3.0):
        out = step(sm, t, hb(t, armed=True, main=3), alt=3.0)  # POSCTL by the pilot
        assert out.phase == Phase.PILOT
        assert Action.REQUEST_OFFBOARD not in out.actions
        assert out.stream_setpoints


def test_config_validation_names_the_key(tmp_path):
    with pytest.raises(ConfigError, match="max_state_age_s"):
        from_dict(OffboardConfig, {"max_state_age_s": 0.0}, source="svc.toml")
    with pytest.raises(ConfigError, match="unknown key auto_arn"):
        from_dict(OffboardConfig, {"auto_arn": True}, source="svc.toml")


# -- takeoff, landing and the flight's memory ------------------------------------------------


def armed_on_ground(sm, t0=0.0):
    step(sm, t0, hb(t0), alt=0.0)
    step(sm, t0 + 0.1, hb(t0 + 0.1), alt=0.0)
    out = step(sm, t0 + 0.2, hb(t0 + 0.2, armed=True), alt=0.0)
    assert out.actions == (Action.TAKEOFF,)
    return out


def test_one_takeoff_per_flight_while_the_heartbeat_lags():
    """The 98 m climb: PX4's 1 Hz heartbeat still shows the old mode while the vehicle sits
    or climbs slowly; the machine used to send TAKEOFF again (PX4 climbs current + 2.5 m on
    each). Now a takeoff is never repeated, whatever the heartbeat and altitude say."""
    sm = OffboardStateMachine(AUTO)
    armed_on_ground(sm)
    sent = 1
    for k in range(1, 200):
        t = 0.2 + 0.05 * k
        alt = min(2.5, 0.01 * k)  # a slow climb
        out = step(sm, t, hb(t - 0.9, armed=True, main=4, sub=3), alt=alt)
        sent += out.actions.count(Action.TAKEOFF)
    assert sent == 1
    assert sm.takeoffs_sent == 1


def test_failsafe_after_leaving_the_ground_never_takes_off_again():
    sm = OffboardStateMachine(AUTO)
    armed_on_ground(sm)
    step(sm, 1.0, hb(1.0, armed=True, main=4, sub=2), alt=1.0)  # climbing
    out = step(sm, 1.5, hb(1.5, armed=True, main=4, sub=2), age=1.0, alt=1.2)  # stale
    assert out.phase == Phase.WAIT_STATE
    # fresh again, but sinking below the airborne height: still never a takeoff
    for k in range(40):
        t = 2.0 + 0.1 * k
        out = step(sm, t, hb(t, armed=True, main=4, sub=3), alt=0.3)
        assert Action.TAKEOFF not in out.actions
    assert "never taking off again" in out.reason


def test_failsafe_in_offboard_returns_to_streaming_below_the_takeoff_altitude():
    """After a failsafe the vehicle may hold lower than the takeoff altitude (a trajectory
    flown at 1.5 m): it is airborne, so streaming resumes; no takeoff."""
    sm = OffboardStateMachine(AUTO)
    armed_on_ground(sm)
    step(sm, 2.0, hb(2.0, armed=True, main=4, sub=3), alt=2.5)
    assert sm.phase == Phase.STREAMING
    out = step(sm, 3.0, hb(3.0, armed=True, main=6), age=1.0, alt=1.5)
    assert out.phase == Phase.FAILSAFE
    out = step(sm, 4.0, hb(4.0, armed=True, main=4, sub=3), alt=1.5)
    assert out.phase == Phase.STREAMING
    assert Action.TAKEOFF not in out.actions


def test_no_takeoff_without_an_explicit_altitude():
    sm = OffboardStateMachine(AUTO)
    for t, h in ((0.0, hb(0.0)), (0.1, hb(0.1)), (0.2, hb(0.2, armed=True))):
        out = sm.step(Inputs(t, h, 0.01, pos_down_m=0.0))  # no GLOBAL_POSITION_INT
    assert out.actions == ()
    assert "AMSL" in out.reason
    assert sm.takeoffs_sent == 0


def test_no_takeoff_while_the_autopilot_says_it_is_in_the_air():
    sm = OffboardStateMachine(AUTO)
    step(sm, 0.0, hb(0.0), alt=0.0)
    step(sm, 0.1, hb(0.1), alt=0.0)
    out = step(sm, 0.2, hb(0.2, armed=True), alt=0.1, landed=LANDED_STATE_IN_AIR)
    assert out.actions == ()
    out = step(sm, 0.3, hb(0.3, armed=True), alt=0.1, landed=LANDED_STATE_ON_GROUND)
    assert Action.TAKEOFF not in out.actions  # it has left the ground in this flight


def test_home_is_taken_on_the_ground_when_the_autopilot_gives_no_height_above_home():
    """Local down is not height: PX4's local origin need not be on the ground."""
    sm = OffboardStateMachine(AUTO)
    for t, h in ((0.0, hb(0.0)), (0.1, hb(0.1)), (0.2, hb(0.2, armed=True))):
        out = sm.step(Inputs(t, h, 0.01, pos_down_m=-7.0, amsl_m=HOME_AMSL_M))
    assert out.actions == (Action.TAKEOFF,)
    assert out.altitude_m == pytest.approx(0.0)
    out = sm.step(Inputs(1.0, hb(1.0, armed=True), 0.01, pos_down_m=-9.4, amsl_m=490.4))
    assert out.phase == Phase.STREAMING
    assert out.altitude_m == pytest.approx(2.4)


def in_offboard(sm):
    armed_on_ground(sm)
    step(sm, 2.0, hb(2.0, armed=True, main=4, sub=3), alt=2.5)
    step(sm, 2.6, hb(2.0, armed=True, main=4, sub=3), alt=2.5)
    out = step(sm, 2.7, hb(2.7, armed=True, main=6), alt=2.5)
    assert out.phase == Phase.OFFBOARD


def test_mission_end_lands_stops_streaming_and_ends_the_flight():
    sm = OffboardStateMachine(AUTO)
    in_offboard(sm)
    out = step(sm, 10.0, hb(10.0, armed=True, main=6), alt=2.5, mission=True)
    assert out.phase == Phase.LANDING
    assert out.actions == (Action.LAND,)
    assert not out.stream_setpoints  # PX4 returns to Offboard after landing if they stream
    out = step(sm, 10.5, hb(10.0, armed=True, main=6), alt=2.3, mission=True)
    assert out.actions == ()  # retry period
    out = step(sm, 11.0, hb(11.0, armed=True, main=4, sub=6), alt=2.0, mission=True)
    assert out.actions == ()
    # a pilot takes the landing over: the landing is never commanded again
    for t in (12.0, 13.5, 15.0):
        out = step(sm, t, hb(t, armed=True, main=3), alt=1.0, mission=True)
        assert out.actions == ()
        assert not out.stream_setpoints
    for t in (16.0, 17.0, 18.5):
        out = step(sm, t, hb(t), alt=0.0, mission=True)
    assert out.phase == Phase.DONE
    for t in (20.0, 25.0, 30.0):  # landed: never re-armed, never a takeoff
        out = step(sm, t, hb(t), alt=0.0)
        assert out.actions == ()
    assert sm.takeoffs_sent == 1


def test_mission_end_without_landing_hands_over_holding():
    sm = OffboardStateMachine(AUTO, land_at_end=False)
    in_offboard(sm)
    out = step(sm, 10.0, hb(10.0, armed=True, main=6), alt=2.5, mission=True)
    assert out.phase == Phase.DONE
    assert out.actions == (Action.REQUEST_HOLD,)
    assert not out.stream_setpoints


def test_an_autopilot_landing_stops_the_stream():
    sm = OffboardStateMachine(OffboardConfig())
    step(sm, 0.0, hb(0.0), alt=0.0)
    step(sm, 0.1, hb(0.1, armed=True, main=6), alt=3.0)
    assert sm.phase == Phase.OFFBOARD
    out = step(sm, 1.0, hb(1.0, armed=True, main=4, sub=6), alt=2.8)  # PX4 lands (failsafe)
    assert out.phase == Phase.LANDING
    assert not out.stream_setpoints
    assert out.actions == ()  # not our landing: nothing to command
    for t in (2.0, 3.0, 4.5):
        out = step(sm, t, hb(t), alt=0.0)
    # no automation: the next flight is the pilot's
    assert out.phase == Phase.PREFLIGHT
    assert "pilot" in out.reason


# -- the invariants as properties ---------------------------------------------------------------


class _Px4Like:
    """A crude PX4: modes, a 1 Hz heartbeat that lags, takeoff to the target, land, disarm."""

    def __init__(self, hb_lag_s: float) -> None:
        self.t = 0.0
        self.armed = False
        self.alt = 0.0
        self.mode = (4, 3)
        self.target = 0.0
        self.arm_refused = False
        self.hb_lag_s = hb_lag_s
        self.hb: Heartbeat | None = None
        self.ground_s = 0.0
        self.last_setpoint_s = -10.0

    def apply(self, action: Action, target_m: float | None) -> None:
        if action == Action.ARM and not self.armed and self.alt < 0.05:
            if self.arm_refused:
                self.armed = True
            self.arm_refused = True
        elif action == Action.TAKEOFF and self.armed:
            assert target_m is not None
            self.mode, self.target = (4, 2), target_m
        elif action == Action.REQUEST_OFFBOARD and self.t - self.last_setpoint_s < 0.5:
            self.mode = (6, 0)
        elif action == Action.REQUEST_HOLD:
            self.mode = (4, 3)
        elif action == Action.LAND and self.armed:
            self.mode = (4, 6)

    def advance(self, dt: float, streaming: bool, push_m_s: float) -> None:
        self.t += dt
        if streaming:
            self.last_setpoint_s = self.t
        if self.mode == (6, 0) and self.t - self.last_setpoint_s > 1.0:
            self.mode = (4, 3)  # COM_OF_LOSS_T
        if self.armed and self.mode == (4, 2):
            self.alt = min(self.target, self.alt + 1.5 * dt)
            if self.alt >= self.target - 0.05:
                self.mode = (4, 3)
        elif self.armed and self.mode == (4, 6):
            self.alt = max(0.0, self.alt - 0.7 * dt)
        elif self.armed and self.alt > 0.0:
            self.alt = max(0.0, self.alt + push_m_s * dt)  # wind, a pilot, the controller
        self.ground_s = self.ground_s + dt if self.alt <= 0.0 else 0.0
        if self.armed and self.ground_s > 2.0 and self.mode in ((4, 6), (4, 3)):
            self.armed = False
        # the heartbeat goes out at 1 Hz and shows the mode of when it went out
        if self.hb is None or self.t - self.hb.received_s >= 1.0 + self.hb_lag_s:
            self.hb = Heartbeat(1, self.armed, *self.mode, self.t)


def fault_schedules(*extra_kinds: str) -> st.SearchStrategy[list[tuple[float, float, str]]]:
    """Up to 8 (start s, length s, kind) faults over a 45 s flight."""
    kinds = ["stale", "hb_loss", "push_up", "push_down", "no_global", *extra_kinds]
    return st.lists(
        st.tuples(
            st.floats(0.0, 40.0),  # start s
            st.floats(0.05, 4.0),  # length s
            st.sampled_from(kinds),
        ),
        max_size=8,
    )


faults = fault_schedules()


@settings(max_examples=60, deadline=None)
@given(
    faults=faults,
    hb_lag_s=st.floats(0.0, 0.9),
    mission_s=st.one_of(st.none(), st.floats(2.0, 30.0)),
    landed_state_known=st.booleans(),
)
def test_never_a_second_takeoff_and_never_one_in_the_air(
    faults, hb_lag_s, mission_s, landed_state_known
):
    sm = OffboardStateMachine(AUTO)
    ap = _Px4Like(hb_lag_s)
    dt = 0.05
    offboard_since = None
    left_ground = False
    takeoffs = 0
    pushed_up_m = 0.0  # how far the pushes alone could lift it (1 m/s while active)
    out = None
    for k in range(int(45.0 / dt)):
        t = k * dt
        active = {kind for start, length, kind in faults if start <= t < start + length}
        push = 1.0 if "push_up" in active else -1.0 if "push_down" in active else 0.0
        pushed_up_m += dt * max(push, 0.0)
        ap.advance(dt, out is not None and out.stream_setpoints, push)
        left_ground |= ap.alt >= 0.3
        heartbeat = None if "hb_loss" in active else ap.hb
        if heartbeat is not None and "hb_loss" not in active and t - heartbeat.received_s > 5:
            heartbeat = None
        if sm.phase == Phase.OFFBOARD and offboard_since is None:
            offboard_since = t
        mission = mission_s is not None and offboard_since is not None and (
            t - offboard_since >= mission_s
        )
        glob = "no_global" not in active
        landed = None
        if landed_state_known:
            landed = LANDED_STATE_IN_AIR if ap.alt > 0.05 else LANDED_STATE_ON_GROUND
        out = sm.step(
            Inputs(
                t,
                heartbeat,
                1.0 if "stale" in active else 0.01,
                pos_down_m=-ap.alt,
                relative_alt_m=ap.alt if glob else None,
                amsl_m=HOME_AMSL_M + ap.alt if glob else None,
                landed_state=landed,
                mission_complete=mission,
            )
        )
        for action in out.actions:
            if action == Action.TAKEOFF:
                takeoffs += 1
                assert not left_ground, f"takeoff at t={t:.2f} after leaving the ground"
                assert ap.alt < AUTO.airborne_altitude_m
                assert out.takeoff is not None
                assert out.takeoff.amsl_m == pytest.approx(HOME_AMSL_M + 2.5, abs=0.5)
            ap.apply(action, None if out.takeoff is None else out.takeoff.above_home_m)
        if out.phase in (Phase.LANDING, Phase.DONE, Phase.FAILSAFE):
            assert not out.stream_setpoints
    assert takeoffs <= 1
    assert ap.alt <= 2.5 + pushed_up_m + 1e-6  # only the pushes ever exceed the target


def test_control_starts_only_once_the_takeoff_climb_has_settled():
    """ArduCopter's takeoff handed over at the target less the tolerance still climbing
    1.5 m/s: control starting then overshot 0.36-1.1 m. Streaming waits for the climb to
    settle (airborne is still judged on altitude alone: no second takeoff either way)."""
    sm = OffboardStateMachine(AUTO)
    step(sm, 0.0, hb(0.0))
    step(sm, 0.1, hb(0.1))
    assert step(sm, 0.2, hb(0.2, armed=True)).actions == (Action.TAKEOFF,)

    def climbing(t, alt, vel_down):
        return sm.step(
            Inputs(t, hb(t, armed=True, main=4, sub=3), 0.01, pos_down_m=-alt,
                   relative_alt_m=alt, amsl_m=HOME_AMSL_M + alt, vel_down_m_s=vel_down)
        )  # fmt: skip

    out = climbing(1.5, 2.3, -1.5)
    assert out.phase == Phase.PREFLIGHT
    assert not out.stream_setpoints
    assert out.actions == ()
    assert "climb to settle" in out.reason
    out = climbing(2.0, 2.6, -0.2)
    assert out.phase == Phase.STREAMING
    assert out.stream_setpoints


def test_control_starts_when_the_autopilot_ends_its_takeoff_short_of_the_target():
    """A real PX4 ends its takeoff within NAV_MC_ALT_RAD (0.8 m) of the target, switches to
    LOITER and holds where it brakes: 2.3 m of 2.5 in one cold start, reached 1.2 s after
    the hold began, the 0.3 m tolerance only just met. Once a heartbeat has shown our takeoff
    and a later one shows it over, the takeoff is done at whatever height it held: a hold
    below the tolerance streamed never at all."""
    sm = OffboardStateMachine(AUTO)
    step(sm, 0.0, hb(0.0))
    step(sm, 0.1, hb(0.1))
    assert step(sm, 0.2, hb(0.2, armed=True)).actions == (Action.TAKEOFF,)
    # the heartbeat from before the takeoff (LOITER) says nothing about its end
    out = step(sm, 0.5, hb(0.5, armed=True, main=4, sub=3), alt=0.6)
    assert out.phase == Phase.PREFLIGHT
    out = step(sm, 1.2, hb(1.2, armed=True, main=4, sub=2), alt=1.2)  # AUTO.TAKEOFF
    assert out.phase == Phase.PREFLIGHT
    out = step(sm, 2.2, hb(2.2, armed=True, main=4, sub=3), alt=1.95)  # LOITER: over
    assert out.phase == Phase.STREAMING
    assert out.stream_setpoints
    assert sm.takeoffs_sent == 1
    out = step(sm, 2.8, hb(2.2, armed=True, main=4, sub=3), alt=1.95)
    assert out.phase == Phase.OFFBOARD_REQUESTED
    assert out.actions == (Action.REQUEST_OFFBOARD,)


def _airborne_px4(cfg: OffboardConfig = AUTO) -> OffboardStateMachine:
    """A PX4 flight armed and taken off (the takeoff's target reached)."""
    sm = OffboardStateMachine(cfg)
    step(sm, 0.0, hb(0.0))
    step(sm, 0.1, hb(0.1))
    assert step(sm, 0.2, hb(0.2, armed=True)).actions == (Action.TAKEOFF,)
    return sm


def _holding(sm, t, speed_m_s, vel_down_m_s=0.0, *, main=4, sub=3, heartbeat=None, ready=True):
    """A step at the takeoff's height, moving horizontally at ``speed_m_s``."""
    return sm.step(
        Inputs(t, heartbeat or hb(t, armed=True, main=main, sub=sub), 0.01, pos_down_m=-2.5,
               relative_alt_m=2.5, amsl_m=HOME_AMSL_M + 2.5, vel_down_m_s=vel_down_m_s,
               speed_horizontal_m_s=speed_m_s, controller_ready=ready)
    )  # fmt: skip


def test_the_first_hand_over_waits_for_the_controller_to_be_ready():
    """Issue 21: in real time the miss worker came up 7 s after offboard entry at load 16, and
    every tick until then flew the intermediate controller (3 cm instead of 0.5). The first
    offboard request waits for it (the vehicle settled meanwhile), streaming."""
    sm = _airborne_px4()
    _holding(sm, 1.0, 0.0, ready=False)
    t = 1.5
    while t < 6.0:
        out = _holding(sm, t, 0.0, ready=False)
        assert out.phase == Phase.STREAMING, t
        assert "controller" in out.reason
        assert out.stream_setpoints
        t += 0.1
    out = _holding(sm, t, 0.0, ready=True)
    assert out.phase == Phase.OFFBOARD_REQUESTED
    assert out.reason == f"requesting offboard (waited {t - 1.5:.1f} s for the controller)"
    assert sm.unready_entries == 0


def test_the_wait_for_the_controller_is_bounded_and_counted():
    sm = _airborne_px4()
    _holding(sm, 1.0, 0.0, ready=False)
    t = 1.5
    while t < 1.5 + AUTO.controller_ready_timeout_s - 0.01:
        assert _holding(sm, t, 0.0, ready=False).phase == Phase.STREAMING, t
        t += 0.25
    out = _holding(sm, 1.5 + AUTO.controller_ready_timeout_s, 0.0, ready=False)
    assert out.phase == Phase.OFFBOARD_REQUESTED
    assert "controller not ready after 20.0 s" in out.reason, out.reason
    assert sm.unready_entries == 1


def test_offboard_is_requested_only_once_the_vehicle_has_settled():
    """In 10 m/s wind PX4's takeoff ends 2.4 m downwind, brakes, and its hold flies the
    vehicle back at up to 1.1 m/s: handed over while it still moved (px4-cold: 0.5 m/s, the
    tilt being unwound) the loops started from a transient. The offboard request waits until
    the speed has been under the bounds for settled_for_s, a swing through zero included."""
    sm = _airborne_px4()
    assert _holding(sm, 1.0, 0.8).phase == Phase.STREAMING  # control may stream: it waits
    for t in (1.5, 1.6, 2.0):  # streamed min_stream_s: still drifting
        out = _holding(sm, t, 0.8)
        assert out.phase == Phase.STREAMING, out
        assert "settle" in out.reason
        assert out.stream_setpoints
        assert out.actions == ()
    assert _holding(sm, 2.1, 0.1).phase == Phase.STREAMING  # a swing through zero...
    assert _holding(sm, 2.3, 0.2).phase == Phase.STREAMING
    assert _holding(sm, 2.35, 0.5).phase == Phase.STREAMING  # ...and on: not settled
    assert _holding(sm, 2.4, 0.2, vel_down_m_s=0.5).phase == Phase.STREAMING  # sinking
    for t in (2.5, 2.6, 2.75):
        assert _holding(sm, t, 0.25, vel_down_m_s=-0.3).phase == Phase.STREAMING
    out = _holding(sm, 2.85, 0.25, vel_down_m_s=-0.3)  # over 0.3 s under both bounds
    assert out.phase == Phase.OFFBOARD_REQUESTED
    assert out.actions == (Action.REQUEST_OFFBOARD,)
    assert out.reason == "requesting offboard"
    assert sm.unsettled_entries == 0


def test_an_unsettled_vehicle_is_handed_over_at_the_timeout_and_counted():
    """A hold that never settles (gusts it will not stop) is handed over settle_timeout_s
    after the hand-over first waited, said in the reason and counted once; a later entry
    (after the pilot left offboard) is not held."""
    sm = _airborne_px4()
    _holding(sm, 1.0, 0.8)
    t = 1.5
    while t < 1.5 + AUTO.settle_timeout_s - 0.01:
        assert _holding(sm, t, 0.6).phase == Phase.STREAMING, t
        t += 0.05
    out = _holding(sm, 1.5 + AUTO.settle_timeout_s, 0.6)
    assert out.phase == Phase.OFFBOARD_REQUESTED
    assert "not settled after 5.0 s" in out.reason, out.reason
    assert sm.unsettled_entries == 1
    t += 0.2
    assert _holding(sm, t, 0.6, main=6, sub=0).phase == Phase.OFFBOARD
    assert _holding(sm, t + 0.5, 0.6).phase == Phase.PILOT  # the pilot took it (LOITER)
    assert _holding(sm, t + 1.0, 0.9, main=6, sub=0).phase == Phase.OFFBOARD  # gave it back
    assert sm.unsettled_entries == 1


def test_ardupilot_streams_in_guided_only_once_the_vehicle_has_settled():
    """ArduCopter: GUIDED is on from before the takeoff, so streaming is the hand-over:
    it waits for the settling there."""
    from epc_offboard.vehicle.dialect_ardupilot import ARDUPILOT

    sm = OffboardStateMachine(AUTO, dialect=ARDUPILOT)

    def guided(t, armed=True):  # custom_mode 4: GUIDED
        return Heartbeat(1, armed, 0, 0, t, custom_mode=4, autopilot=3)

    step(sm, 0.0, guided(0.0, armed=False))
    assert step(sm, 0.1, guided(0.1)).actions == (Action.TAKEOFF,)
    assert _holding(sm, 1.0, 0.8, heartbeat=guided(1.0)).phase == Phase.PREFLIGHT
    out = _holding(sm, 1.1, 0.1, heartbeat=guided(1.1))
    assert out.phase == Phase.PREFLIGHT
    assert "settle" in out.reason
    assert not out.stream_setpoints
    out = _holding(sm, 1.45, 0.1, heartbeat=guided(1.45))
    assert out.phase == Phase.OFFBOARD, out  # streaming in GUIDED: offboard at once
    assert out.stream_setpoints


@pytest.mark.parametrize(
    ("key", "value"),
    [("settled_horizontal_speed_m_s", 0.0), ("settled_for_s", -0.1), ("settled_for_s", 6.0),
     ("settle_timeout_s", 0.1)],
)  # fmt: skip
def test_the_settle_keys_are_validated(key, value):
    with pytest.raises(ValueError, match=key.removesuffix("_s").removesuffix("_m")):
        OffboardConfig(**{key: value})
