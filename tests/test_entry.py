"""The position loop at an offboard entry, as pure numerics (the flights: test_entry_e2e.py).

Before offboard is confirmed the autopilot flies its own thrust, which the service cannot
see; the estimator still learns the wind then, with the thrust that explains the measured
vertical acceleration. The first tick after a gap in control starts the command from what
the vehicle flies and rate-limits it. The thrust flown follows the command through the
motors' lag, so a thrust step is not learnt as a vertical disturbance.
"""

from __future__ import annotations

import numpy as np

from epc_offboard.common import frames
from epc_offboard.common.frames import GRAVITY_M_S2
from epc_offboard.control.models import accel_to_attitude
from epc_offboard.control.position import PositionLoop
from tests.test_cascade import _DT_S, _cascade, _state

WIND_NED_M_S2 = np.array([0.0, 3.0, 0.0])  # the drag of a 3 m/s wind blowing east


def _holding(loop: PositionLoop, seconds: float, t0_s: float = 0.0) -> np.ndarray:
    """The autopilot holds the vehicle at rest against the wind (tilted into it) while the
    service streams unconfirmed setpoints; returns the last disturbance estimate."""
    att = accel_to_attitude(-WIND_NED_M_S2, 0.0, loop.airframe.hover_thrust_norm)
    q = frames.euler_to_quat(att.roll_rad, att.pitch_rad, att.yaw_rad)
    pos = np.array([0.0, 0.0, -2.5])
    p_hat = np.zeros(3)
    for k in range(round(seconds / _DT_S)):
        state = _state(t0_s + k * _DT_S, pos, np.zeros(3), q)
        p_hat = loop.position_tick(state, loop.hold(pos), learn=False).p_hat_ned_m_s2
    return p_hat


def test_the_wind_is_learnt_while_the_autopilot_holds_before_offboard():
    """The old loop learnt nothing before offboard was confirmed (up to 1 s after PX4 flew
    ours): the estimate started at zero at entry."""
    p_hat = _holding(_cascade().position, 0.5)
    assert np.allclose(p_hat, WIND_NED_M_S2, atol=0.3), p_hat


def test_the_first_command_after_a_gap_starts_from_what_the_vehicle_flies():
    """A (re-)entry 2 m from the reference: the command's horizontal part (the tilt) moves
    from the hold's acceleration by at most entry_jerk_m_s3 per second."""
    loop = _cascade().position
    _holding(loop, 0.5)
    hold_acc = -WIND_NED_M_S2
    cfg = loop.config
    att = accel_to_attitude(hold_acc, 0.0, loop.airframe.hover_thrust_norm)
    q = frames.euler_to_quat(att.roll_rad, att.pitch_rad, att.yaw_rad)
    pos = np.array([0.0, 0.0, -2.5])
    far = loop.hold(pos + np.array([2.0, 0.0, 0.0]))
    t0 = 5.0  # a failsafe's gap
    previous = hold_acc
    for k in range(20):
        out = loop.position_tick(_state(t0 + k * _DT_S, pos, np.zeros(3), q), far, learn=True)
        step = np.linalg.norm((out.acc_cmd_ned_m_s2 - previous)[:2])  # the tilt's part
        assert step <= cfg.entry_jerk_m_s3 * _DT_S + 0.05, (k, out.acc_cmd_ned_m_s2, previous)
        previous = out.acc_cmd_ned_m_s2


def test_a_thrust_step_is_not_learnt_as_a_vertical_disturbance():
    """The vehicle's thrust follows the command through the motors' lag (tau_acc_s[2]):
    taking the command as flown read each step as a vertical disturbance (+6.6 m/s^2 on a
    real PX4 at entry, then a climb)."""
    loop = _cascade().position
    hover = loop.airframe.hover_thrust_norm
    tau = loop.config.tau_acc_s[2]
    pos, vel = np.array([0.0, 0.0, -2.5]), np.zeros(3)
    thrust = hover
    q = frames.euler_to_quat(0.0, 0.0, 0.0)
    worst = 0.0
    for k in range(100):
        reference = loop.hold(np.array([0.0, 0.0, -2.5 - (1.0 if k >= 10 else 0.0)]))
        out = loop.position_tick(_state(k * _DT_S, pos, vel, q), reference, learn=True)
        before = thrust
        thrust += (1.0 - np.exp(-_DT_S / tau)) * (out.thrust_norm - thrust)  # the motors
        acc_down = GRAVITY_M_S2 * (1.0 - 0.5 * (before + thrust) / hover)  # over the step
        pos = pos + vel * _DT_S + 0.5 * np.array([0.0, 0.0, acc_down]) * _DT_S**2
        vel = vel + np.array([0.0, 0.0, acc_down]) * _DT_S
        worst = max(worst, abs(float(out.p_hat_ned_m_s2[2])))
    assert worst < 0.3, worst


def test_the_thrust_gives_the_commanded_vertical_at_the_tilt_flown():
    """Tilting up into the wind the vehicle lags its target by a few degrees; a thrust sized
    for the target's tilt then lifts it (ArduCopter re-entering in 6 m/s wind lagged 3-6 deg
    and climbed 0.15 m). Sized for the tilt flown, its vertical part is the commanded one:
    here the target leans 17 deg into a 3 m/s wind while the vehicle is still level (the old
    thrust gave 0.45 m/s^2 too much lift)."""
    loop = _cascade().position
    _holding(loop, 0.5)
    pos = np.array([0.0, 0.0, -2.5])
    level = frames.euler_to_quat(0.0, 0.0, 0.0)
    for k in range(5):  # on from the hold, the vehicle level
        out = loop.position_tick(_state(0.5 + k * _DT_S, pos, np.zeros(3), level), loop.hold(pos))
        target_tilt = np.degrees(np.arctan2(np.linalg.norm(out.acc_cmd_ned_m_s2[:2]),
                                            GRAVITY_M_S2 - out.acc_cmd_ned_m_s2[2]))  # fmt: skip
        assert target_tilt > 10.0, out.acc_cmd_ned_m_s2  # the target leans, the vehicle not
        specific_thrust = GRAVITY_M_S2 * out.thrust_norm / loop.airframe.hover_thrust_norm
        vertical_acc = GRAVITY_M_S2 - specific_thrust  # NED down, thrust axis vertical
        assert abs(vertical_acc - out.acc_cmd_ned_m_s2[2]) < 0.05, (k, out)
