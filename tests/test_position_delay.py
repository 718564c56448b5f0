"""The position loop's Smith predictor (``dead_time_s``, ``state_delay_s``): the state
it plans from is where a plant with that dead time and the model's lag will be when the
tick's command starts to act, and the reference it plans against is as far ahead.

A toy plant (no processes): the achieved acceleration follows the command, sent
``dead_time_s`` earlier, through a first-order lag of the model's own time constant, plus a
constant disturbance; the loop sees the plant's state ``state_delay_s`` late.
"""

from __future__ import annotations

from collections import deque
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from epc_offboard.common import frames
from epc_offboard.control.position import PositionControlConfig, PositionLoop, shift_reference
from epc_offboard.control.trajectories import Trajectory, TrajectoryConfig
from epc_offboard.control.types import VehicleState
from epc_offboard.service.config import load_service_config

_CONFIG = Path(__file__).resolve().parent.parent / "config" / "sitl.toml"
_DT_S = 0.01  # the position loop's period
_DISTURBANCE = np.array([0.4, -0.3, 0.2])


def _loop(dead_time_s: float, state_delay_s: float) -> PositionLoop:
    cfg = load_service_config(_CONFIG)
    position = replace(cfg.position, dead_time_s=dead_time_s, state_delay_s=state_delay_s)
    return PositionLoop(position, replace(cfg.estimator, kind="none"), _DT_S)


def _state(t_s: float, x: np.ndarray) -> VehicleState:
    return VehicleState(
        time_s=t_s, pos_ned_m=x[0:3].copy(), vel_ned_m_s=x[3:6].copy(),
        q_ned_frd=frames.euler_to_quat(0.0, 0.0, 0.0), rate_frd_rad_s=np.zeros(3),
        position_age_s=0.0, attitude_age_s=0.0,
    )  # fmt: skip


def _fly(
    loop: PositionLoop, seconds: float, dead_time_s: float, state_delay_s: float,
    fine_steps: int = 10,
) -> tuple[np.ndarray, np.ndarray]:
    """The figure-8 flown by the toy plant with ``dead_time_s`` and ``state_delay_s``; per
    tick the loop's planned x0 and the plant's true [p, v, a] (a: the lagged acceleration,
    without the disturbance)."""
    cfg = loop.config
    dead = round(dead_time_s / _DT_S)
    stale = round(state_delay_s / _DT_S)
    traj = Trajectory(TrajectoryConfig(shape="figure8", ramp_s=1.0, period_s=6.0),
                      np.array([0.0, 0.0, -2.5]))  # fmt: skip
    tau = np.array(cfg.tau_acc_s)
    x = np.zeros(9)
    x[0:3] = [0.0, 0.0, -2.5]
    pipe: deque[np.ndarray] = deque([np.zeros(3)] * dead)  # commands not yet acting
    truth, planned = [x.copy()], []
    h = _DT_S / fine_steps
    for k in range(round(seconds / _DT_S)):
        seen = truth[max(0, len(truth) - 1 - stale)]
        # the loop's achieved acceleration: the measured attitude's, which a toy plant
        # that flies the lagged acceleration exactly gives back as x[6:9]
        loop.achieved_acceleration = lambda state, ours=True, a=seen[6:9]: a.copy()  # type: ignore[method-assign]
        ref = traj.reference(k * _DT_S, cfg.dt_s, cfg.horizon, 0.0)
        out = loop.position_tick(_state(k * _DT_S, seen), ref)
        planned.append(loop._x0.copy())
        pipe.append(np.asarray(out.acc_cmd_ned_m_s2, dtype=float).copy())
        u = pipe.popleft()
        for _ in range(fine_steps):  # the plant, finer than the loop
            x[0:3] += x[3:6] * h
            x[3:6] += (x[6:9] + _DISTURBANCE) * h
            x[6:9] += (u - x[6:9]) * (1.0 - np.exp(-h / tau))
        truth.append(x.copy())
    return np.array(planned), np.array(truth)


def test_the_reference_shift_is_exact_for_a_piecewise_linear_acceleration():
    dt_s, lead_s = 0.05, 0.0425
    t = np.arange(21) * dt_s
    stages = np.zeros((21, 9))
    j = 0.7  # one jerk throughout: the acceleration is linear, the position cubic
    stages[:, 0] = 1.0 + 0.5 * t + 0.2 * t**2 + j * t**3 / 6.0
    stages[:, 3] = 0.5 + 0.4 * t + j * t**2 / 2.0
    stages[:, 6] = 0.4 + j * t
    out = shift_reference(stages, dt_s, lead_s)
    tt = t[1:] + lead_s
    np.testing.assert_allclose(out[:, 0], 1.0 + 0.5 * tt + 0.2 * tt**2 + j * tt**3 / 6.0,
                               rtol=0.0, atol=1e-12)  # fmt: skip
    np.testing.assert_allclose(out[:, 3], 0.5 + 0.4 * tt + j * tt**2 / 2.0, rtol=0.0, atol=1e-12)
    np.testing.assert_allclose(out[:, 6], 0.4 + j * tt, rtol=0.0, atol=1e-12)


@pytest.mark.parametrize(("dead_time_s", "state_delay_s"), [(0.04, 0.0), (0.03, 0.02)])
def test_the_planned_state_is_the_plants_when_the_command_acts(dead_time_s, state_delay_s):
    """The x0 the QP plans from, predicted over the commands still in the pipe, is the
    plant's state ``dead_time_s`` after the tick (to the model's discretisation and the
    disturbance, which the loop does not know here: estimator off), while the measured
    state is far from it."""
    loop = _loop(dead_time_s, state_delay_s)
    planned, truth = _fly(loop, 4.0, dead_time_s, state_delay_s)
    ahead = round(dead_time_s / _DT_S)
    k = np.arange(200, len(planned) - ahead)
    err = planned[k] - truth[k + ahead]
    stale = truth[k - round(state_delay_s / _DT_S)] - truth[k + ahead]
    # the unknown disturbance over the pending time: d (D + delay)^2 / 2 in position
    pending_s = dead_time_s + state_delay_s
    assert np.abs(err[:, 3:6]).max() < np.abs(_DISTURBANCE).max() * pending_s + 1e-3
    assert np.abs(err[:, 6:9]).max() < 1e-3  # the lag is the model's own
    assert np.abs(stale[:, 6:9]).max() > 20.0 * np.abs(err[:, 6:9]).max()


def test_the_predictor_tracks_a_dead_time_plant_better():
    """The figure-8 on a plant with 40 ms of dead time and 20 ms of state delay: with the
    predictor the position error (after the ramp) is smaller than without it."""
    traj = Trajectory(TrajectoryConfig(shape="figure8", ramp_s=1.0, period_s=6.0),
                      np.array([0.0, 0.0, -2.5]))  # fmt: skip
    errors = []
    for dead_time_s, state_delay_s in ((0.0, 0.0), (0.04, 0.02)):  # told, or not
        _, truth = _fly(_loop(dead_time_s, state_delay_s), 6.0, 0.04, 0.02)
        t = np.arange(len(truth)) * _DT_S
        ref = np.array([traj.reference(ti, 0.05, 1, 0.0).stages[0, 0:3] for ti in t])
        errors.append(float(np.linalg.norm(truth[200:, 0:3] - ref[200:], axis=1).mean()))
    assert errors[1] < 0.7 * errors[0], errors


def test_dead_time_config_is_checked():
    with pytest.raises(ValueError, match="dead_time_s"):
        PositionControlConfig(dead_time_s=-0.01)
    with pytest.raises(ValueError, match="state_delay_s"):
        PositionControlConfig(state_delay_s=0.6)
