"""The position weights hold an unmodelled disturbance residual close: the steady offset
it leaves is the residual over the position gain.

Issue 24's decomposition: what was left of the circle's and Neural-Fly's figure-8's error
after LWPR was a steady offset (4 cm outside the circle on the strict SITL, with LWPR's
drag exact; removing the cascade's dead time with a Smith predictor moved it by 0.1 cm),
a disturbance residual of a few tenths of a m/s^2 held off by the position gain. A toy
plant that flies the commanded acceleration exactly, with the estimator off, shows the
same offset in isolation.
"""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np

from epc_offboard.common import frames
from epc_offboard.control.models import AttitudeThrust, attitude_to_accel
from epc_offboard.control.position import PositionLoop
from epc_offboard.control.types import VehicleState
from epc_offboard.service.config import load_service_config

_CONFIG = Path(__file__).resolve().parent.parent / "config" / "sitl.toml"
_DT_S = 0.01


def _steady_offset_m(residual_m_s2: np.ndarray, seconds: float = 5.0) -> np.ndarray:
    """Where a hold settles (NED, m, from the hold point) under ``residual_m_s2`` the loop
    does not know (estimator off); the plant flies the commanded attitude and thrust."""
    cfg = load_service_config(_CONFIG)
    loop = PositionLoop(cfg.position, replace(cfg.estimator, kind="none"), _DT_S)
    hold = np.array([0.0, 0.0, -2.5])
    reference = loop.hold(hold)
    pos, vel = hold.copy(), np.zeros(3)
    q = frames.euler_to_quat(0.0, 0.0, 0.0)
    for k in range(round(seconds / _DT_S)):
        state = VehicleState(
            time_s=k * _DT_S, pos_ned_m=pos.copy(), vel_ned_m_s=vel.copy(), q_ned_frd=q,
            rate_frd_rad_s=np.zeros(3), position_age_s=0.0, attitude_age_s=0.0,
        )  # fmt: skip
        out = loop.position_tick(state, reference)
        roll, pitch, yaw = out.euler_target_rad
        acc = (
            attitude_to_accel(
                AttitudeThrust(roll, pitch, yaw, out.thrust_norm), loop.airframe.hover_thrust_norm
            )
            + residual_m_s2
        )
        pos, vel = pos + vel * _DT_S + 0.5 * acc * _DT_S**2, vel + acc * _DT_S
        q = out.q_target
    offset: np.ndarray = pos - hold
    return offset


def test_a_disturbance_residual_leaves_a_small_steady_offset():
    """0.3 m/s^2 the model does not know moves a hold by 3.7 cm horizontally and 2.2 cm
    vertically (asserted 4.5 and 3 cm); the old weights, q_pos (20, 20, 30), q_vel 3, let
    it go 6.7 and 4.0 cm."""
    offset = _steady_offset_m(np.array([0.3, 0.0, 0.3]))
    assert abs(offset[0]) < 0.045, offset
    assert abs(offset[2]) < 0.03, offset
    assert abs(offset[1]) < 1e-3, offset
