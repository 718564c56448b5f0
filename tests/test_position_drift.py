"""The disturbance along the horizon: a drag that turns with the velocity leaves no steady
offset on a circle.

The QP's model carries the disturbance estimate now as a constant; ``u_p`` cancels the one
LWPR expects at each stage's reference velocity. Held to the reference itself, the plan
counted on that compensation moving the state off the reference and fought it: on the
strict SITL EPC + LWPR flew the circle 1.8 cm outside and 0.8 cm behind, steadily, with the
drag estimate exact. The model with the varying disturbance is the constant one plus the
disturbance's drift (linear), so the QP held to the reference less that drift is exact
(``PositionLoop.disturbance_drift``).

A toy plant isolates it: the achieved acceleration follows the command through exactly the
model's first-order lag, plus a linear drag -D v (SIH's 1 /s); the vehicle state carries
the attitude and thrust of that acceleration. LWPR learns the drag from the flight, as in
the service.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from epc_offboard.common import frames
from epc_offboard.common.frames import GRAVITY_M_S2
from epc_offboard.control.models import accel_to_attitude
from epc_offboard.control.position import PositionLoop
from epc_offboard.control.types import ReferenceHorizon, VehicleState
from epc_offboard.service.config import load_service_config

_CONFIG = Path(__file__).resolve().parent.parent / "config" / "sitl.toml"
_DT_S = 0.01
_RADIUS_M = 1.5
_OMEGA_RAD_S = 2.0 * math.pi / 8.0  # the circle scenario's 8 s lap: 1.18 m/s
_CENTRE_NED_M = np.array([0.0, 0.0, -2.5])
_DRAG_1_S = 1.0


def _circle_stages(t_s: float, steps: int, dt_s: float) -> np.ndarray:
    """(steps + 1, 9) [p, v, a] of the circle at t_s, t_s + dt_s, ..."""
    tk = t_s + dt_s * np.arange(steps + 1)
    c, s = np.cos(_OMEGA_RAD_S * tk), np.sin(_OMEGA_RAD_S * tk)
    w, r = _OMEGA_RAD_S, _RADIUS_M
    stages = np.zeros((steps + 1, 9))
    stages[:, 0:3] = _CENTRE_NED_M + np.column_stack([r * c, r * s, 0.0 * c])
    stages[:, 3:6] = np.column_stack([-r * w * s, r * w * c, 0.0 * c])
    stages[:, 6:9] = np.column_stack([-r * w * w * c, -r * w * w * s, 0.0 * c])
    return stages


def _circle_offset_m(laps: float = 3.0, age_s: float = 0.0) -> tuple[float, float]:
    """(mean radial, mean along-track) error over the last lap (m; outward, ahead).
    ``age_s`` (a whole number of ms): the state flown from is a sample that old, predicted
    on at constant velocity, as the state tracker gives it in real time."""
    cfg = load_service_config(_CONFIG)
    loop = PositionLoop(cfg.position, cfg.estimator, _DT_S)
    tau = np.array(cfg.position.tau_acc_s)
    hover = loop.airframe.hover_thrust_norm
    steps = cfg.position.reference_steps
    start = _circle_stages(0.0, steps, cfg.position.dt_s)[0]
    pos, vel, acc = start[0:3].copy(), start[3:6].copy(), start[6:9].copy()
    n_ticks = round(laps * 2.0 * math.pi / _OMEGA_RAD_S / _DT_S)
    last_lap = round(2.0 * math.pi / _OMEGA_RAD_S / _DT_S)
    radial, along = [], []
    substeps = 10
    h = _DT_S / substeps
    lag = round(age_s / h)
    history = [(pos.copy(), vel.copy())] * (lag + 1)  # the plant's, per substep, newest last
    for k in range(n_ticks):
        t_s = k * _DT_S
        stages = _circle_stages(t_s, steps, cfg.position.dt_s)
        att = accel_to_attitude(acc, 0.0, hover)
        pos_then, vel_then = history[-1 - lag]
        state = VehicleState(
            time_s=t_s, pos_ned_m=pos_then + vel_then * age_s, vel_ned_m_s=vel_then.copy(),
            q_ned_frd=frames.euler_to_quat(att.roll_rad, att.pitch_rad, att.yaw_rad),
            rate_frd_rad_s=np.zeros(3), position_age_s=age_s, attitude_age_s=0.0,
        )  # fmt: skip
        if k >= n_ticks - last_lap:
            err = pos - stages[0, 0:3]
            out_dir = stages[0, 0:3] - _CENTRE_NED_M
            out_dir /= np.linalg.norm(out_dir)
            radial.append(float(err @ out_dir))
            along.append(float(err @ stages[0, 3:6]) / np.linalg.norm(stages[0, 3:6]))
        out = loop.position_tick(state, ReferenceHorizon.at_heading(stages, 0.0))
        cmd = np.asarray(out.acc_cmd_ned_m_s2, dtype=np.float64)
        for _ in range(substeps):  # the model's lag, exact, and the drag
            acc = cmd + (acc - cmd) * np.exp(-h / tau)
            total = acc - _DRAG_1_S * vel
            pos = pos + vel * h + 0.5 * total * h * h
            vel = vel + total * h
            history = [*history[-lag:], (pos.copy(), vel.copy())] if lag else [(pos, vel)]
    assert abs(acc[2]) < GRAVITY_M_S2  # (it flew)
    return float(np.mean(radial)), float(np.mean(along))


def test_a_turning_drag_leaves_no_steady_offset_on_the_circle():
    """Held to the reference itself (main) the toy flew 1.57 cm outside and 0.91 cm behind
    (the strict SITL: 1.8 and 0.8); held to it less the drift, 0.33 and 0.31 cm. Asserted
    within 0.6 cm."""
    radial_m, along_m = _circle_offset_m()
    assert abs(radial_m) < 0.006, (radial_m, along_m)
    assert abs(along_m) < 0.006, (radial_m, along_m)


def test_a_sample_some_ms_old_is_carried_to_the_tick_by_the_models_acceleration():
    """Real time (issue 21): the loop flies from a position sample 1-11 ms old, predicted on
    at constant velocity: its velocity lagged the vehicle's by age x acceleration (6.6-10.7
    ms x a measured in the windy figure-8), and the turns were cut (1.5-1.8 x lockstep's
    error). The model's acceleration carries the QP's initial state on to the tick: 8 ms old,
    the circle flies as a fresh sample does."""
    fresh = _circle_offset_m(age_s=0.0)
    old = _circle_offset_m(age_s=0.008)
    assert abs(old[0] - fresh[0]) < 0.001, (old, fresh)
    assert abs(old[1] - fresh[1]) < 0.001, (old, fresh)
