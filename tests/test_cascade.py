"""The position tick's disturbance observation, on synthetic states (no processes, no I/O).

A toy plant integrates exactly what the cascade commands (attitude followed at once, thrust
as sent) plus a known constant disturbance, so what the estimator should learn is known.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from epc_offboard.common import frames
from epc_offboard.control.cascade import Cascade, PositionOutput
from epc_offboard.control.models import AttitudeThrust, attitude_to_accel
from epc_offboard.service.config import load_service_config
from epc_offboard.vehicle.state import VehicleState

_CONFIG = Path(__file__).resolve().parent.parent / "config" / "sitl.toml"
_DT_S = 0.01  # the position loop's period


def _cascade() -> Cascade:
    cfg = load_service_config(_CONFIG)
    return Cascade(cfg.position, cfg.attitude, cfg.estimator, _DT_S)


def _state(t_s, pos, vel, q, position_age_s=0.0) -> VehicleState:
    return VehicleState(
        time_s=t_s,
        pos_ned_m=np.array(pos, dtype=float),
        vel_ned_m_s=np.array(vel, dtype=float),
        q_ned_frd=np.array(q, dtype=float),
        rate_frd_rad_s=np.zeros(3),
        position_age_s=position_age_s,
        attitude_age_s=0.0,
    )


def _achieved(out: PositionOutput, hover_thrust_norm: float) -> np.ndarray:
    roll, pitch, yaw = out.euler_target_rad
    return attitude_to_accel(AttitudeThrust(roll, pitch, yaw, out.thrust_norm), hover_thrust_norm)


def _fly(cascade: Cascade, disturbance, seconds: float, stale_from_s: float | None = None):
    """Hold 2.5 m up under ``disturbance`` (m/s^2, NED); from ``stale_from_s`` on, the
    position stream stops (the velocity repeats its last sample while attitude goes on) and
    the hold point moves 1 m up, so the commands are far from the equilibrium's."""
    hover = cascade.position_cfg.hover_thrust_norm
    pos, vel = np.array([0.0, 0.0, -2.5]), np.zeros(3)
    q = frames.euler_to_quat(0.0, 0.0, 0.0)
    cascade.hold_position(pos.copy())
    last_pos, last_vel, last_t = pos.copy(), vel.copy(), 0.0
    outs: list[PositionOutput] = []
    stale_s = float("inf") if stale_from_s is None else stale_from_s
    for k in range(round(seconds / _DT_S)):
        t = k * _DT_S
        stale = t >= stale_s
        if stale and t - _DT_S < stale_s:
            cascade.hold_position(pos + np.array([0.0, 0.0, -1.0]))
        if not stale:
            last_pos, last_vel, last_t = pos.copy(), vel.copy(), t
        state = _state(t, last_pos, last_vel, q, position_age_s=t - last_t)
        out = cascade.position_tick(state, cascade.hold_refs(state))
        acc = _achieved(out, hover) + np.asarray(disturbance, dtype=float)
        pos, vel = pos + vel * _DT_S + 0.5 * acc * _DT_S**2, vel + acc * _DT_S
        q = out.q_target
        outs.append(out)
    return outs


def test_a_constant_disturbance_is_recovered():
    d = np.array([0.8, -0.5, 0.6])
    out = _fly(_cascade(), d, seconds=8.0)[-1]
    # the estimate cancels the disturbance: p^ is the disturbance itself
    np.testing.assert_allclose(out.p_hat_ned_m_s2, d, atol=0.1)


def test_a_stopped_position_stream_is_not_learnt_as_a_disturbance():
    """A velocity repeated while its stream stopped used to read as a disturbance that
    cancels the commanded acceleration (learnt for the 0.25 s before the stale-state
    failsafe, then flown after it: a 1.8 m altitude excursion in the soak)."""
    d = np.array([0.0, 0.0, 0.6])  # pushes down: the command climbs against it
    outs = _fly(_cascade(), d, seconds=6.3, stale_from_s=6.0)
    before = outs[599].p_hat_ned_m_s2
    np.testing.assert_allclose(before, d, atol=0.1)
    assert outs[-1].acc_cmd_ned_m_s2[2] < -1.0  # climbing towards the new hold point
    for out in outs[600:]:
        np.testing.assert_allclose(out.p_hat_ned_m_s2, before, atol=0.01)


def test_body_rates_are_trusted_only_near_hover_and_near_the_target():
    import math

    cascade = _cascade()
    level = frames.euler_to_quat(0.0, 0.0, 0.3)
    hover = cascade.hover(_state(0.0, [0, 0, -2.5], [0, 0, 0], level))
    assert cascade.rates_trusted(_state(0.0, [0, 0, -2.5], [0, 0, 0], level), hover)
    # 20 deg of roll, 20 deg from a level target: inside
    rolled = frames.euler_to_quat(math.radians(20), 0.0, 0.3)
    assert cascade.rates_trusted(_state(0.0, [0, 0, -2.5], [0, 0, 0], rolled), hover)
    # 40 deg from the target (under the tilt bound): the autopilot's attitude loop takes it
    rolled = frames.euler_to_quat(math.radians(40), 0.0, 0.3)
    assert not cascade.rates_trusted(_state(0.0, [0, 0, -2.5], [0, 0, 0], rolled), hover)
    # tilted 60 deg, even with a target right there: outside the hover linearisation
    steep = frames.euler_to_quat(0.0, math.radians(60), 0.3)
    target = PositionOutput(
        q_target=steep, euler_target_rad=(0.0, math.radians(60), 0.3), thrust_norm=0.5,
        acc_cmd_ned_m_s2=np.zeros(3), p_hat_ned_m_s2=np.zeros(3), source="hit",
        compute_us=0.0, ref_pos_ned_m=np.zeros(3),
    )  # fmt: skip
    assert not cascade.rates_trusted(_state(0.0, [0, 0, -2.5], [0, 0, 0], steep), target)
