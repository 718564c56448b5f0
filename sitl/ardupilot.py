"""The ArduCopter personality: what ArduCopter does wherever it changes what a client does.

Pure logic and numerics, like the PX4 personality it extends (``sitl.autopilot``): the same
vehicle, cascade and rate loop, with ArduCopter's modes, commands, parameters and guided
control (observed on ArduCopter 4.7 / 4.8-dev SITL, see docs/DESIGN.md):

* HEARTBEAT autopilot 3, custom_mode a plain mode number (STABILIZE 0, GUIDED 4, LOITER 5,
  RTL 6, LAND 9, BRAKE 17, GUIDED_NOGPS 20). DO_SET_MODE(1, 6, 0) — PX4's Offboard — is RTL
  here, and counted (``rtl_count``): a client that sends it flies home, not offboard;
* nothing but HEARTBEAT streams until SET_MESSAGE_INTERVAL; ODOMETRY is never sent;
* arming only in GUIDED (this SITL refuses it in modes that cannot take off by command);
  MAV_CMD_NAV_TAKEOFF only in GUIDED, armed and on the ground, with a finite altitude above
  home in param7: a NaN is DENIED (the real SITL crashed on it);
* SET_ATTITUDE_TARGET is obeyed only in GUIDED / GUIDED_NOGPS (and overrides a takeoff in
  progress, as ArduCopter's guided angle control does); body rates all three or none;
* thrust: a CLIMB RATE by default (0.5 holds altitude; PILOT_SPEED_UP / _DN at 1 / 0), or
  with GUID_OPTIONS bit 3 throttle, divided by the current tilt's cosine (angle boost);
* every setpoint waits ``setpoint_delay_s`` (the link, the scheduler), then passes
  ArduCopter's input shaping: body rates through a first-order filter (``rate_input_tc_s``)
  with ATC_ACCEL_*_MAX limits, integrated into an attitude target; quaternions approached
  with ATC_INPUT_TC. The achieved rate matches a body-rate command best about 200 ms later
  at about 0.35 gain, as on ArduCopter 4.8-dev SITL;
* an extra HEARTBEAT the moment the mode changes; no LOCAL_POSITION_NED until the EKF has
  an origin (``ekf_origin_after_boot_s`` after boot);
* GUIDED position targets flown by AC_PosControl: P on position, PID on velocity with
  velocity feedforward, the target's acceleration fed forward, jerk-limited;
* GUID_TIMEOUT (3 s) without setpoints: ArduCopter's guided angle control levels the vehicle
  (yaw kept) and holds altitude (climb rate 0), still in GUIDED — it does not hold position:
  in wind it drifts. New setpoints take control again;
* LOITER and BRAKE hold, LAND lands, RTL (simplified) lands where it is.
"""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np

from epc_offboard.common.arducopter import (  # the mode numbers the dialect reads too
    BRAKE,
    GUID_OPTIONS_THRUST_AS_THROTTLE,
    GUIDED_MODES,
    LAND,
    LOITER,
    RTL,
    STABILIZE,
)
from epc_offboard.common.frames import (
    GRAVITY_M_S2,
    FloatArray,
    quat_conjugate,
    quat_multiply,
    quat_normalize,
    quat_to_rotation,
)
from sitl.autopilot import (
    HOLD,
    IGNORE_ATTITUDE,
    IGNORE_PITCH_RATE,
    IGNORE_ROLL_RATE,
    IGNORE_YAW_RATE,
    OFFBOARD,
    AttitudeSetpoint,
    Autopilot,
    LandedState,
    Result,
)
from sitl.params import ArduPilotParams, AutopilotParams, VehicleParams
from sitl.physics import POS, QUAT, VEL, on_ground

_RATES = IGNORE_ROLL_RATE | IGNORE_PITCH_RATE | IGNORE_YAW_RATE
_IMAX_M_S2 = 10.0  # PSC_VELXY_IMAX (1000 cm/s^2): the velocity integral's share, bounded


class ArduCopter(Autopilot):
    """ArduCopter's behaviour over the PX4-like cascade (internal modes: OFFBOARD = guided
    attitude control, HOLD = holding position, TAKEOFF, LAND)."""

    mav_autopilot = 3  # MAV_AUTOPILOT_ARDUPILOTMEGA
    streams_by_default = False
    sends_odometry = False
    # ArduCopter sends a HEARTBEAT at once on every mode change, besides its 1 Hz ones
    heartbeat_on_mode_change = True

    def __init__(
        self, vehicle: VehicleParams, params: AutopilotParams, ardupilot: ArduPilotParams
    ) -> None:
        super().__init__(
            vehicle,
            replace(
                params,
                offboard_loss_timeout_s=ardupilot.guid_timeout_s,
                disarm_preflight_s=ardupilot.disarm_delay_s,
                arm_refusals_after_boot=0,
                # ArduCopter's lag is in its input shaping (below), not its rate loop
                rate_dead_time_s=0.0,
                rate_time_constant_s=0.0,
                attitude_quaternion_max_hz=0.0,  # ArduCopter reaches the 200 Hz asked for
                attitude_setpoint_extra_delay_s=0.0,  # PX4's (its shaping is below)
            ),
        )
        self.ardupilot = ardupilot
        self._setpoint_delay_s = ardupilot.setpoint_delay_s
        self.number = STABILIZE  # the mode number the heartbeat shows
        self.rtl_count = 0  # RTLs entered: a client that meant something else
        self.ignored_setpoints = 0  # outside GUIDED, or rates neither all nor none
        self._timed_out = False  # GUID_TIMEOUT passed: level, climb rate 0, until setpoints
        self._hover_throttle = vehicle.hover_thrust_norm  # MOT_THST_HOVER
        self._outer_dt_s = 0.005
        self._att_target: FloatArray | None = None  # the shaped attitude target
        self._shaped_rate = np.zeros(3)
        self._climb_integral = 0.0  # m: the climb-rate loop's integral (GUID_OPTIONS 0)
        self._acc_target = np.zeros(3)  # the jerk-limited acceleration target, m/s^2
        self._vel_err_prev: FloatArray | None = None
        self._vel_err_rate = np.zeros(3)  # filtered derivative of the velocity error

    # ---- what the endpoint asks ---------------------------------------------------------------

    @property
    def custom_mode(self) -> int:
        return self.number

    def set_mode_command(self, custom_mode: int, sub_mode: int, t_s: float) -> Result:
        return self.set_number(custom_mode, t_s)

    def set_mode_message(self, custom_mode: int, t_s: float) -> Result:
        return self.set_number(custom_mode, t_s)

    def takeoff_command(self, param7: float, home_amsl_m: float, t_s: float) -> Result:
        """param7 is the altitude ABOVE HOME; NaN or no climb is denied, as is a takeoff
        outside GUIDED, disarmed, or in the air."""
        if not math.isfinite(param7) or param7 <= 0.0:
            return self._refuse("Takeoff: altitude must be a finite height above home")
        if self.number not in GUIDED_MODES or not self.armed:
            return self._refuse("Takeoff: needs GUIDED and armed")
        if self.landed_state != LandedState.ON_GROUND:
            return self._refuse("Takeoff: already flying")
        return self.takeoff(param7, t_s)

    def parameters(self) -> list[tuple[str, float]]:
        ap = self.ardupilot
        return [
            ("ATC_INPUT_TC", ap.input_tc_s),
            ("DISARM_DELAY", ap.disarm_delay_s),
            ("GUID_OPTIONS", float(ap.guid_options)),
            ("GUID_TIMEOUT", ap.guid_timeout_s),
            ("MOT_THST_HOVER", self._hover_throttle),
            ("PILOT_SPEED_DN", ap.pilot_speed_dn_m_s * 100.0),  # cm/s, as ArduPilot's
            ("PILOT_SPEED_UP", ap.pilot_speed_up_m_s * 100.0),
        ]

    def set_parameter(self, name: str, value: float) -> bool:
        """GUID_OPTIONS, GUID_TIMEOUT and ATC_INPUT_TC can be set in flight, as on ArduCopter."""
        ap = self.ardupilot
        try:
            if name == "GUID_OPTIONS" and 0 <= value < 2**16:
                self.ardupilot = replace(ap, guid_options=int(value))
            elif name == "GUID_TIMEOUT":
                self.ardupilot = replace(ap, guid_timeout_s=value)
                self.params = replace(self.params, offboard_loss_timeout_s=value)
            elif name == "ATC_INPUT_TC":
                self.ardupilot = replace(ap, input_tc_s=value)
            else:
                return False
        except ValueError:  # out of range: the parameter keeps its value
            return False
        return True

    def has_position(self, t_s: float) -> bool:
        """ArduCopter streams no LOCAL_POSITION_NED until its EKF has an origin."""
        return t_s >= self.ardupilot.ekf_origin_after_boot_s

    # ---- modes and commands -------------------------------------------------------------------

    def set_number(self, number: int, t_s: float) -> Result:
        """Select ArduCopter mode ``number``."""
        airborne = self.landed_state != LandedState.ON_GROUND
        if number in GUIDED_MODES:
            if self.number not in GUIDED_MODES:
                self._capture_hold()
                self.mode = HOLD  # holds position until setpoints stream (or a takeoff)
            self.intended_mode = OFFBOARD
        elif number in (LOITER, BRAKE):
            self._capture_hold()
            self.mode = self.intended_mode = HOLD
        elif number == LAND:
            if self.armed:
                self.land(t_s)
            else:
                self.mode = self.intended_mode = HOLD
        elif number == RTL:
            self.rtl_count += 1
            if self.armed and airborne:
                self.land(t_s)  # (simplified: home is where it took off, so: down)
            else:
                self.mode = self.intended_mode = HOLD
        elif number == STABILIZE:
            if self.armed and airborne:
                return self._refuse("Mode change: no pilot for STABILIZE in this SITL")
            self.mode = self.intended_mode = HOLD
        else:
            return Result.UNSUPPORTED
        self.number = number
        return Result.ACCEPTED

    def arm(self, arm: bool, t_s: float, force: bool = False) -> Result:
        if arm and not self.armed and self.number not in GUIDED_MODES:
            return self._refuse("Arm: select GUIDED first (no takeoff from this mode)")
        result = super().arm(arm, t_s, force)
        if arm and result == Result.ACCEPTED and self.number in GUIDED_MODES:
            self.mode, self.intended_mode = HOLD, OFFBOARD
        return result

    def on_attitude_setpoint(self, sp: AttitudeSetpoint, t_s: float) -> None:
        rates_ignored = sp.type_mask & _RATES
        if self.number not in GUIDED_MODES or rates_ignored not in (0, _RATES):
            self.ignored_setpoints += 1
            return
        super().on_attitude_setpoint(sp, t_s)
        self._timed_out = False
        self.intended_mode = OFFBOARD  # guided attitude control, even over a takeoff

    # ---- the periodic update ------------------------------------------------------------------

    def update_outer(self, x: FloatArray, t_s: float, dt_s: float) -> None:
        self._outer_dt_s = dt_s
        super().update_outer(x, t_s, dt_s)
        if self.mode != OFFBOARD:
            self._att_target = None  # shaping starts again from the attitude flown
            self._shaped_rate[:] = 0.0
            self._climb_integral = 0.0

    def _supervise(self, x: FloatArray, t_s: float) -> None:
        super()._supervise(x, t_s)
        if self.number in GUIDED_MODES and self.intended_mode == HOLD:
            # a finished takeoff holds in GUIDED: setpoints take control again
            self.intended_mode = OFFBOARD

    def _setpoints_lost(self, t_s: float) -> None:
        """GUID_TIMEOUT: level (yaw kept) at climb rate 0, in GUIDED, until setpoints return
        (counted once per loss). Not a position hold."""
        if self._timed_out:
            return
        self._timed_out = True
        self.failsafe_count += 1
        yaw = self._current_yaw()
        level = (math.cos(yaw / 2.0), 0.0, 0.0, math.sin(yaw / 2.0))
        # (mask: rates ignored; thrust 0.5 read as a climb rate of 0 while timed out)
        self._att_sp = AttitudeSetpoint(_RATES, level, (0.0, 0.0, 0.0), 0.5)

    def _offboard_attitude(
        self, x: FloatArray, sp: AttitudeSetpoint
    ) -> tuple[FloatArray, FloatArray, float]:
        """ArduCopter's input shaping, then its attitude controller; thrust as it reads it."""
        q = x[QUAT]
        alpha = min(1.0, self._outer_dt_s / self.ardupilot.input_tc_s)
        target = q.copy() if self._att_target is None else self._att_target
        if sp.type_mask & IGNORE_ATTITUDE:
            # body rates: filtered, their change limited to ATC_ACCEL_*_MAX, integrated into
            # the attitude target it tracks (AC_AttitudeControl's input_shaping_ang_vel)
            alpha_rate = min(1.0, self._outer_dt_s / self.ardupilot.rate_input_tc_s)
            step = alpha_rate * (np.asarray(sp.rate_frd_rad_s) - self._shaped_rate)
            limit = self._outer_dt_s * np.asarray(self.ardupilot.accel_max_frd_rad_s2)
            self._shaped_rate += np.clip(step, -limit, limit)
            half = 0.5 * self._outer_dt_s * self._shaped_rate
            target = quat_normalize(quat_multiply(target, np.array([1.0, *half])))
            rate = self._shaped_rate + self._attitude_control(q, target)
        else:
            # a quaternion: the target approaches it with time constant ATC_INPUT_TC, and its
            # rotation rate is fed forward (ATC_RATE_FF_ENAB, on by default) to the rate loop
            q_sp = np.asarray(sp.q_wxyz)
            if float(target @ q_sp) < 0.0:
                q_sp = -q_sp
            previous = target
            target = quat_normalize(previous + alpha * (q_sp - previous))
            step = quat_multiply(quat_conjugate(previous), target)
            feedforward = (2.0 / self._outer_dt_s) * (step[1:] if step[0] >= 0.0 else -step[1:])
            rate = feedforward + self._attitude_control(q, target)
        self._att_target = target
        lim = np.asarray(self.params.rate_max_rad_s)
        return target, np.clip(rate, -lim, lim), self._thrust(x, sp.thrust_norm)

    def _acceleration_command(
        self,
        x: FloatArray,
        pos_ref: FloatArray,
        vel_ref: FloatArray,
        dt_s: float,
        acc_ff: FloatArray,
    ) -> FloatArray:
        """AC_PosControl: the target's acceleration, jerk-limited, plus P on position and PID
        on velocity (the integral bounded in acceleration, as its IMAX) with the velocity
        target fed forward -> acceleration (3,)."""
        ap = self.ardupilot
        jerk = np.asarray(ap.psc_jerk_m_s3) * dt_s
        self._acc_target = self._acc_target + np.clip(acc_ff - self._acc_target, -jerk, jerk)
        vel_sp = vel_ref + np.asarray(ap.psc_pos_p_1_s) * (pos_ref - x[POS])
        vmax = np.asarray(self.params.max_speed_m_s)
        vel_err = np.clip(vel_sp, -vmax, vmax) - x[VEL]
        i_gain = np.asarray(ap.psc_vel_i_1_s2)
        bound = np.divide(_IMAX_M_S2, i_gain, out=np.zeros(3), where=i_gain > 0.0)
        self._vel_integral = np.clip(self._vel_integral + vel_err * dt_s, -bound, bound)
        if self._vel_err_prev is not None:
            alpha = -math.expm1(-2.0 * math.pi * ap.psc_vel_d_filter_hz * dt_s)
            slope = (vel_err - self._vel_err_prev) / dt_s
            self._vel_err_rate += alpha * (slope - self._vel_err_rate)
        self._vel_err_prev = vel_err
        return (
            self._acc_target
            + np.asarray(ap.psc_vel_p_1_s) * vel_err
            + i_gain * self._vel_integral
            + np.asarray(ap.psc_vel_d) * self._vel_err_rate
            + np.asarray(ap.psc_vel_ff_1_s) * vel_sp
        )

    def _reset_integrators(self) -> None:
        super()._reset_integrators()
        self._vel_err_prev = None
        self._vel_err_rate = np.zeros(3)

    def _thrust(self, x: FloatArray, thrust: float) -> float:
        """SET_ATTITUDE_TARGET's thrust as the collective thrust this vehicle produces."""
        cos_tilt = float(quat_to_rotation(x[QUAT])[2, 2])
        as_throttle = self.ardupilot.guid_options & GUID_OPTIONS_THRUST_AS_THROTTLE
        if as_throttle and not self._timed_out:
            # throttle plus ArduCopter's angle boost (1 / cos of the tilt, floored at 0.1)
            return min(1.0, thrust / min(max(cos_tilt, 0.1), 1.0))
        # a climb rate: 0.5 holds altitude, 1 climbs at PILOT_SPEED_UP, 0 sinks at _DN
        ap = self.ardupilot
        speed = ap.pilot_speed_up_m_s if thrust >= 0.5 else ap.pilot_speed_dn_m_s
        climb_m_s = (thrust - 0.5) * 2.0 * speed
        if on_ground(x) and climb_m_s <= 0.0:
            return 0.0
        err_m_s = climb_m_s + float(x[VEL][2])  # (NED: up is -vz)
        integral = self._climb_integral + err_m_s * self._outer_dt_s
        self._climb_integral = min(max(integral, -2.0), 2.0)
        acc_up = (
            self.params.velocity_p_1_s[2] * err_m_s
            + self.params.velocity_i_1_s2[2] * self._climb_integral
        )
        thrust_norm = self._hover_throttle * (1.0 + acc_up / GRAVITY_M_S2) / max(cos_tilt, 0.1)
        return min(1.0, max(0.0, thrust_norm))
