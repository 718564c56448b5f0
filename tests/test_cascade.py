"""The loops' ticks on synthetic states (no processes, no I/O): the lag inverse, the
disturbance observation, hover as an equilibrium, the attitude envelope.

A toy plant integrates exactly what the position loop commands (attitude followed at once,
thrust as sent) plus a known constant disturbance, so what the estimator should learn is
known.
"""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np

from epc_offboard.common import frames
from epc_offboard.control.cascade import Cascade
from epc_offboard.control.models import AttitudeThrust, attitude_to_accel
from epc_offboard.control.perturbation import EstimatorKind
from epc_offboard.control.position import PositionLoop
from epc_offboard.control.trajectories import Trajectory, TrajectoryConfig
from epc_offboard.control.types import PositionOutput, VehicleState
from epc_offboard.service.config import load_service_config

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


def _fly(loop: PositionLoop, disturbance, seconds: float, stale_from_s: float | None = None):
    """Hold 2.5 m up under ``disturbance`` (m/s^2, NED); from ``stale_from_s`` on, the
    position stream stops (the velocity repeats its last sample while attitude goes on) and
    the hold point moves 1 m up, so the commands are far from the equilibrium's."""
    hover = loop.airframe.hover_thrust_norm
    pos, vel = np.array([0.0, 0.0, -2.5]), np.zeros(3)
    q = frames.euler_to_quat(0.0, 0.0, 0.0)
    reference = loop.hold(pos.copy())
    last_pos, last_vel, last_t = pos.copy(), vel.copy(), 0.0
    outs: list[PositionOutput] = []
    stale_s = float("inf") if stale_from_s is None else stale_from_s
    for k in range(round(seconds / _DT_S)):
        t = k * _DT_S
        stale = t >= stale_s
        if stale and t - _DT_S < stale_s:
            reference = loop.hold(pos + np.array([0.0, 0.0, -1.0]))
        if not stale:
            last_pos, last_vel, last_t = pos.copy(), vel.copy(), t
        state = _state(t, last_pos, last_vel, q, position_age_s=t - last_t)
        out = loop.position_tick(state, reference)
        acc = _achieved(out, hover) + np.asarray(disturbance, dtype=float)
        pos, vel = pos + vel * _DT_S + 0.5 * acc * _DT_S**2, vel + acc * _DT_S
        q = out.q_target
        outs.append(out)
    return outs


def test_a_constant_disturbance_is_recovered():
    d = np.array([0.8, -0.5, 0.6])
    out = _fly(_cascade().position, d, seconds=8.0)[-1]
    # the estimate cancels the disturbance: p^ is the disturbance itself
    np.testing.assert_allclose(out.p_hat_ned_m_s2, d, atol=0.1)


def test_a_stopped_position_stream_is_not_learnt_as_a_disturbance():
    """A velocity repeated while its stream stopped used to read as a disturbance that
    cancels the commanded acceleration (learnt for the 0.25 s before the stale-state
    failsafe, then flown after it: a 1.8 m altitude excursion in the soak)."""
    d = np.array([0.0, 0.0, 0.6])  # pushes down: the command climbs against it
    outs = _fly(_cascade().position, d, seconds=6.3, stale_from_s=6.0)
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
        compute_us=0.0,
    )  # fmt: skip
    assert not cascade.rates_trusted(_state(0.0, [0, 0, -2.5], [0, 0, 0], steep), target)


def test_the_lag_inverse_is_exact():
    """The feedforward's commands, fed through the model's lag a[k+1] = alpha a[k] +
    (1 - alpha) u[k] from the reference's (extrapolated) acceleration now, reproduce the
    reference accelerations a_1..a_N: the inverse is exact, not an approximation."""
    loop = _cascade().position
    traj = Trajectory(TrajectoryConfig(shape="figure8", ramp_s=1.0, period_s=6.0),
                      np.array([0.0, 0.0, -2.5]))  # fmt: skip
    for t0_s in (0.3, 0.9, 2.0, 4.7):  # in the ramp and after it
        reference = traj.reference(t0_s, loop.config.dt_s, loop.config.horizon, 0.0)
        a_ref = reference.acc_ned_m_s2[1:]
        assert np.abs(a_ref).max() > 1.0  # a reference worth inverting
        u = loop.feedforward(reference.ahead)
        a = 2.0 * a_ref[0] - a_ref[1]  # a_0 as the feedforward extrapolates it
        flown = []
        for u_k in u:
            a = loop.acc_alpha * a + (1.0 - loop.acc_alpha) * u_k
            flown.append(a)
        np.testing.assert_allclose(flown, a_ref, rtol=0.0, atol=1e-12)


def test_a_constant_synthetic_disturbance_is_recovered_exactly():
    """Through the tick's own observation path (``observe`` on the states the toy plant
    produces: velocity changed by the commanded acceleration plus d). At the hold's
    equilibrium every measurement is d itself to rounding, so what is left is the
    estimator's transient, which decays: the Kalman observer's geometrically (7e-11 m/s^2
    measured after 10 s, asserted 1e-6), LWPR's incremental regression more slowly (5e-4
    m/s^2 measured after 10 s, asserted 2e-3). A biased measurement (e.g. the hover thrust
    instead of the last commanded one in the achieved acceleration) would stay off by the
    bias."""
    cfg = load_service_config(_CONFIG)
    d = np.array([0.8, -0.5, 0.6])
    cases: list[tuple[EstimatorKind, float]] = [("kf", 1e-6), ("lwpr", 2e-3)]
    for kind, tol in cases:
        loop = PositionLoop(cfg.position, replace(cfg.estimator, kind=kind), _DT_S)
        out = _fly(loop, d, seconds=10.0)[-1]
        np.testing.assert_allclose(out.p_hat_ned_m_s2, d, rtol=0.0, atol=tol, err_msg=kind)


def test_hover_is_an_equilibrium():
    """At the hold point, at rest, level, with no disturbance: every tick commands zero
    acceleration, a level attitude at the reference's heading and the hover thrust, and the
    vehicle stays where it is."""
    import math

    loop = _cascade().position
    hover = loop.airframe.hover_thrust_norm
    pos = np.array([1.0, -2.0, -2.5])
    reference = loop.hold(pos)
    q = frames.euler_to_quat(0.0, 0.0, loop.config.yaw_rad)
    for k in range(100):
        out = loop.position_tick(_state(k * _DT_S, pos, np.zeros(3), q), reference)
        np.testing.assert_allclose(out.acc_cmd_ned_m_s2, 0.0, atol=1e-9)
        np.testing.assert_allclose(out.p_hat_ned_m_s2, 0.0, atol=1e-9)
        np.testing.assert_allclose(out.euler_target_rad, (0.0, 0.0, loop.config.yaw_rad),
                                   atol=1e-9)  # fmt: skip
        assert math.isclose(out.thrust_norm, hover, abs_tol=1e-9)
        np.testing.assert_allclose(_achieved(out, hover), 0.0, atol=1e-9)
        q = out.q_target
