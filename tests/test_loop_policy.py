"""The cascade's loop policy (control/cascade.py), on synthetic states: which command an
attitude tick sends — delegated, late, outside the rate envelope, rate model distrusted,
the attitude EPC, its fallback — in that precedence; when a tick is late; and the px4
baseline's position target. Each precedence is pinned by a tick where two reasons hold at
once, so swapping two branches of the policy fails a test here."""

from __future__ import annotations

import math
from dataclasses import replace
from pathlib import Path
from typing import Literal

import numpy as np
import pytest

from epc_offboard.common import frames
from epc_offboard.control.attitude import AttitudeLoop
from epc_offboard.control.cascade import (
    LATE_ATTITUDE_PERIODS,
    Cascade,
    attitude_command,
    late_tick,
)
from epc_offboard.control.types import (
    AttitudeCommand,
    PositionOutput,
    PositionTarget,
    ReferenceHorizon,
    VehicleState,
)
from epc_offboard.service.config import load_service_config

_CONFIG = Path(__file__).resolve().parent.parent / "config" / "sitl.toml"
_PERIOD_S = 0.005  # the attitude loop's
_EPC_SOURCES = ("hit", "solved", "intermediate", "fallback")


def _cascade(controller: Literal["epc", "pd", "mpc", "px4"] = "epc") -> Cascade:
    cfg = load_service_config(_CONFIG)
    return Cascade(replace(cfg.position, controller=controller), cfg.attitude, cfg.estimator,
                   0.01, attitude_period_s=_PERIOD_S)  # fmt: skip


def _state(roll_deg: float = 0.0, t_s: float = 1.0) -> VehicleState:
    return VehicleState(
        time_s=t_s, pos_ned_m=np.array([0.0, 0.0, -2.5]), vel_ned_m_s=np.zeros(3),
        q_ned_frd=frames.euler_to_quat(math.radians(roll_deg), 0.0, 0.0),
        rate_frd_rad_s=np.zeros(3), position_age_s=0.0, attitude_age_s=0.0,
    )  # fmt: skip


def _level(cascade: Cascade) -> PositionOutput:
    return cascade.hover(_state())


def _distrust_rate_model(loop: AttitudeLoop, now_s: float) -> None:
    """The gate sees the model miss the measured rates by far, for as many checks as it
    averages over: it suspends body rates from ``now_s`` on."""
    for _ in range(loop.gate.min_checks):
        loop.gate.check(now_s, np.full(3, 5.0), np.zeros(3))
    assert not loop.rate_model_trusted(now_s)


OUT_OF_ENVELOPE_DEG = 60.0  # beyond rates_max_tilt_deg (55) and rates_max_error_deg (35)


def _command(cascade: Cascade, state: VehicleState, **kw: object) -> AttitudeCommand:
    kw.setdefault("late", False)
    kw.setdefault("mode", "epc")
    return attitude_command(cascade.attitude, state, _level(cascade), state.time_s, **kw)  # type: ignore[arg-type]


def test_the_autopilot_mode_delegates_whatever_else_holds():
    cascade = _cascade()
    pushed = cascade.attitude.history.last_push_s
    cmd = _command(cascade, _state(OUT_OF_ENVELOPE_DEG), late=True, mode="autopilot")
    assert cmd.source == "delegated"
    assert cmd.rates_frd_rad_s is None
    np.testing.assert_array_equal(cmd.q_target, _level(cascade).q_target)
    assert cmd.thrust_norm == _level(cascade).thrust_norm
    # the autopilot flies the attitude by configuration: nothing stands in for our rates
    assert cascade.attitude.history.last_push_s == pushed


def test_a_late_tick_sends_the_attitude_before_the_envelope_is_judged():
    cascade = _cascade()
    cmd = _command(cascade, _state(OUT_OF_ENVELOPE_DEG), late=True)
    assert (cmd.source, cmd.rates_frd_rad_s) == ("late", None)
    # the autopilot's loop stands in for our rates in the history (a lone late tick spoils
    # neither the prediction nor the identification)
    assert cascade.attitude.history.last_push_s == pytest.approx(1.0)


def test_outside_the_envelope_the_attitude_goes_even_with_a_distrusted_model():
    cascade = _cascade()
    _distrust_rate_model(cascade.attitude, 1.0)
    cmd = _command(cascade, _state(OUT_OF_ENVELOPE_DEG))
    assert (cmd.source, cmd.rates_frd_rad_s) == ("envelope", None)


def test_a_distrusted_rate_model_sends_the_attitude_inside_the_envelope():
    cascade = _cascade()
    _distrust_rate_model(cascade.attitude, 1.0)
    cmd = _command(cascade, _state(5.0))
    assert (cmd.source, cmd.rates_frd_rad_s) == ("model", None)


def test_inside_everything_the_attitude_epc_flies_body_rates():
    cascade = _cascade()
    cmd = _command(cascade, _state(5.0))
    assert cmd.source in _EPC_SOURCES
    assert cmd.rates_frd_rad_s is not None
    assert np.all(np.isfinite(cmd.rates_frd_rad_s))
    # 5 deg of roll towards a level target: the rate rolls back (negative roll rate)
    assert cmd.rates_frd_rad_s[0] < 0.0


def test_an_attitude_epc_that_raises_degrades_to_the_p_law_and_is_reported(monkeypatch):
    cascade = _cascade()

    def boom(*args: object, **kwargs: object) -> None:
        raise RuntimeError("solver blew up")

    monkeypatch.setattr(cascade.attitude.controller, "step", boom)
    errors: list[Exception] = []
    cmd = _command(cascade, _state(5.0), on_error=errors.append)
    assert cmd.source == "fallback"
    assert [str(e) for e in errors] == ["solver blew up"]
    gain = cascade.attitude.config.fallback_gain_1_s
    assert cmd.rates_frd_rad_s is not None
    assert cmd.rates_frd_rad_s[0] == pytest.approx(-gain * math.radians(5.0))


def test_late_ticks():
    period = _PERIOD_S
    assert not late_tick(0.0, 0.0, period)
    assert not late_tick(1.4 * period, 0.0, period)  # lockstep: a period behind is newest
    assert late_tick(1.6 * period, 0.0, period)  # started late
    assert not late_tick(0.0, LATE_ATTITUDE_PERIODS * period * 0.9, period)
    assert late_tick(0.0, LATE_ATTITUDE_PERIODS * period * 1.1, period)  # an old sample


def test_the_px4_baseline_computes_nothing_and_sends_the_reference_now():
    cascade = _cascade("px4")
    assert cascade.flies_reference
    assert cascade.position.controller is None
    stages = np.zeros((1, 9))
    stages[0] = [1, 2, -3, 0.5, 0, 0, 0, 0, 0.25]
    reference = ReferenceHorizon.at_heading(stages, 1.5)
    out = cascade.position_tick(_state(), reference)
    assert out.source == "fallback"  # the level hover: only the flight log shows it
    sp = PositionTarget.now(reference)  # what goes to the autopilot's position controller
    np.testing.assert_array_equal(sp.pos_ned_m, [1, 2, -3])
    np.testing.assert_array_equal(sp.vel_ned_m_s, [0.5, 0, 0])
    np.testing.assert_array_equal(sp.acc_ned_m_s2, [0, 0, 0.25])
    assert sp.yaw_rad == 1.5


def test_the_other_strategies_fly_the_attitude():
    for controller in ("epc", "pd", "mpc"):
        cascade = _cascade(controller)
        assert not cascade.flies_reference
        assert cascade.position.controller is not None
        cmd = attitude_command(cascade.attitude, _state(5.0), _level(cascade), 1.0,
                               late=False, mode="epc")
        assert cmd.rates_frd_rad_s is not None
