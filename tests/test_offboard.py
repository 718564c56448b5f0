"""The offboard state machine, transition by transition."""

from __future__ import annotations

import pytest

from epc_offboard.configio import ConfigError, from_dict
from epc_offboard.offboard import (
    Action,
    Inputs,
    OffboardConfig,
    OffboardStateMachine,
    Phase,
)
from epc_offboard.state import Heartbeat

AUTO = OffboardConfig(auto_arm=True, auto_takeoff=True, auto_offboard=True)


def hb(t, *, armed=False, main=3, sub=0):
    return Heartbeat(1, armed, main, sub, t)


def step(sm, t, heartbeat, *, age=0.01, alt=0.0, climb=0.0):
    return sm.step(Inputs(t, heartbeat, age, alt, climb))


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
    out = step(sm, 2.0, hb(2.0, armed=True, main=4, sub=2), alt=1.0)  # AUTO.TAKEOFF
    assert out.phase == Phase.PREFLIGHT
    assert out.actions == ()
    # the heartbeat still says LOITER but the vehicle is climbing: not settled, keep waiting
    out = step(sm, 2.5, hb(2.5, armed=True, main=4, sub=3), alt=1.5, climb=1.2)
    assert out.phase == Phase.PREFLIGHT
    out = step(sm, 3.0, hb(3.0, armed=True, main=4, sub=3), alt=2.5)  # AUTO.LOITER
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
    for t, h in ((0.0, hb(0.0, armed=True, main=6)), (0.1, hb(0.1, armed=True, main=6))):
        step(sm, t, h, alt=3.0)
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
    out = step(sm, 3.0, hb(3.0, armed=True, main=6), alt=3.0)
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
