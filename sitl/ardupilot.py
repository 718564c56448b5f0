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
* thrust: a CLIMB RATE by default (0.5 holds altitude; WP_SPD_UP / _DN at 1 / 0), or
  with GUID_OPTIONS bit 3 throttle, divided by the current tilt's cosine (angle boost);
* every setpoint waits ``setpoint_delay_s`` (the main loop reads it), then passes
  ArduCopter's input shaping: quaternions by its command model (AC_AttitudeControl's
  input_quaternion: critically damped with ATC_INPUT_TC, acceleration and jerk bounded by
  ATC_ACC_*_MAX, the shaped rate fed forward); body rates as input_rate_bf_roll_pitch_yaw
  does: the same command model towards the rate asked (ACRO_RP_RATE_TC, 0: ten loop
  periods), the shaped rate turning an attitude target and fed forward, P (ATC_ANG_*_P) on
  the error to that target. The real ArduCopter (4.8-dev SITL, 531699d) answered body-rate
  doublets after 25-35 ms of dead time with a 40 ms lag at gain 1.03; this personality
  after 40-50 ms, 25-30 ms, gain 1.1 (its cascade and motors are a little slower). Its
  yaw is slower: a weak rate loop (ATC_RAT_YAW_P) on an error filtered at 2.5 Hz
  (ATC_RAT_YAW_FLTE): the real one matched a yaw multi-sine best 240 ms later at gain 0.90
  (FOPDT 125 ms, 160 ms, 1.29), this personality 230 ms, 0.91 (115 ms, 160 ms, 1.33);
* arming in GUIDED refused until the EKF has a position ("PreArm: Need Position
  Estimate"); armed, GUIDED, LOITER, BRAKE and RTL refused without one;
* an extra HEARTBEAT the moment the mode changes; no LOCAL_POSITION_NED until the EKF has
  an origin (``ekf_origin_after_boot_s`` after boot);
* GUIDED position targets flown by AC_PosControl: P on position, PID on velocity with
  velocity feedforward, the target's acceleration fed forward, jerk-limited;
* GUID_TIMEOUT (3 s) without setpoints: ArduCopter's guided angle control levels the vehicle
  (yaw kept) and holds altitude (climb rate 0), still in GUIDED — it does not hold position:
  in wind it drifts. New setpoints take control again;
* LOITER and BRAKE hold position; LOITER's altitude follows the pilot's throttle stick
  (``rc_throttle_norm``: SITL's simulated RC at the bottom descends at 2.5 m/s), BRAKE's
  does not; LAND lands, RTL (simplified) lands where it is.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import replace

import numpy as np

from epc_offboard.common.arducopter import (  # the mode numbers the dialect reads too
    BRAKE,
    GUID_OPTIONS_THRUST_AS_THROTTLE,
    GUIDED,
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
    PositionSetpoint,
    Result,
)
from sitl.params import ArduPilotParams, AutopilotParams, VehicleParams
from sitl.physics import POS, QUAT, VEL, on_ground

_RATES = IGNORE_ROLL_RATE | IGNORE_PITCH_RATE | IGNORE_YAW_RATE
_IMAX_M_S2 = 10.0  # PSC_VELXY_IMAX (1000 cm/s^2): the velocity integral's share, bounded
_NEEDS_POSITION = frozenset({GUIDED, LOITER, BRAKE, RTL})  # Mode::requires_position()


def shaped_rate(error: float, gain_1_s: float, accel_max: float, dt_s: float) -> float:
    """The rate that closes ``error``: ``gain`` x error near zero and, past the error where
    that rate needs more than ``accel_max`` to stop in time, the rate that brakes to the
    target at ``accel_max`` (the two meet with equal value and slope); never more than
    closes the error in one step. ArduPilot's square-root controller."""
    linear_m = accel_max / (gain_1_s * gain_1_s)
    size = abs(error)
    if size > linear_m:
        rate = math.sqrt(2.0 * accel_max * (size - 0.5 * linear_m))
    else:
        rate = gain_1_s * size
    return math.copysign(min(rate, size / dt_s), error)


def command_model(
    error: float,
    rate_in: float,
    state: tuple[float, float],
    accel_max: float,
    tc_s: float,
    dt_s: float,
) -> tuple[float, float]:
    """One axis of ArduCopter's attitude input shaping (AC_AttitudeControl's command model):
    the target's angular rate and acceleration ``state`` (rad/s, rad/s^2) move to close the
    angle ``error`` (rad, target to desired) and follow ``rate_in`` (rad/s) with time
    constant ``tc_s``: the rate asked is the shaped error rate less the rate already closing
    it (a critically damped approach, both poles at -1/tc), the acceleration towards it
    bounded by ``accel_max`` and its change by accel_max / tc. Returns the new state."""
    rate, accel = state
    gain_1_s = 1.0 / tc_s
    closing = shaped_rate(error, gain_1_s, accel_max, dt_s)
    moving = rate - rate_in
    if closing * moving > 0.0:  # already moving towards the target: brake in time
        linear = abs(error) <= accel_max * tc_s * tc_s
        closing -= moving if linear else accel_max * tc_s * moving / abs(closing)
    accel_target = min(max((rate_in + closing - rate) * gain_1_s, -accel_max), accel_max)
    jerk = accel_max * gain_1_s * dt_s
    accel += min(max(accel_target - accel, -jerk), jerk)
    return rate + accel * dt_s, accel


def rotation_vector(q_wxyz: FloatArray) -> FloatArray:
    """The rotation of a unit quaternion (4,) as axis x angle (3,) rad, the short way."""
    w, v = float(q_wxyz[0]), np.asarray(q_wxyz[1:], dtype=np.float64)
    if w < 0.0:
        w, v = -w, -v
    norm = float(np.linalg.norm(v))
    if norm < 1e-12:
        return 2.0 * v
    return (2.0 * math.atan2(norm, w) / norm) * v


class ArduCopter(Autopilot):
    """ArduCopter's behaviour over the PX4-like cascade (internal modes: OFFBOARD = guided
    attitude control, HOLD = holding position, TAKEOFF, LAND)."""

    mav_autopilot = 3  # MAV_AUTOPILOT_ARDUPILOTMEGA
    streams_by_default = False
    sends_odometry = False
    # ArduCopter sends a HEARTBEAT at once on every mode change, besides its 1 Hz ones
    heartbeat_on_mode_change = True
    # its input shaping steps with the main loop: a setpoint waits for the next tick
    setpoints_between_ticks = False

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
                # its yaw rate loop is its own (ArduPilotParams.rate_yaw_p_1_s: the weak one)
                rate_p_1_s=(*params.rate_p_1_s[:2], ardupilot.rate_yaw_p_1_s),
                rate_i_1_s2=(*params.rate_i_1_s2[:2], ardupilot.rate_yaw_i_1_s2),
                attitude_quaternion_max_hz=0.0,  # ArduCopter reaches the 200 Hz asked for
                attitude_setpoint_extra_delay_s=0.0,  # PX4's (its shaping is below)
            ),
        )
        self.ardupilot = ardupilot
        self.number = STABILIZE  # the mode number the heartbeat shows
        self.rtl_count = 0  # RTLs entered: a client that meant something else
        self.ignored_setpoints = 0  # outside GUIDED, or rates neither all nor none
        self._timed_out = False  # GUID_TIMEOUT passed: level, climb rate 0, until setpoints
        self._hover_throttle = vehicle.hover_thrust_norm  # MOT_THST_HOVER
        self._outer_dt_s = 0.005
        self._att_target: FloatArray | None = None  # the shaped attitude target
        self._shaped_rate = np.zeros(3)  # its angular rate (FRD, rad/s)
        self._shaped_accel = [0.0, 0.0, 0.0]  # and acceleration (rad/s^2), quaternion shaping
        self._climb_integral = 0.0  # m: the climb-rate loop's integral (GUID_OPTIONS 0)
        self._acc_target = np.zeros(3)  # the jerk-limited acceleration target, m/s^2
        self._vel_err_prev: FloatArray | None = None
        self._vel_err_rate = np.zeros(3)  # filtered derivative of the velocity error
        # the rate PIDs' error through ATC_RAT_*_FLTE (None: the next error passes as it is,
        # as AC_PID's filter reset); the filter's factor per physics step, computed once
        self._rate_error: list[float] | None = None
        self._rate_error_alpha: tuple[float, ...] | None = None

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
            ("PILOT_Y_RATE_TC", ap.yaw_rate_tc_s),
            ("SCHED_LOOP_RATE", ap.loop_rate_hz),
            ("WP_SPD_DN", ap.wp_speed_dn_m_s),  # m/s (4.8; WPNAV_SPEED_DN in cm/s before)
            ("WP_SPD_UP", ap.wp_speed_up_m_s),
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
        """Select ArduCopter mode ``number``. Armed, a mode that needs a position (GUIDED,
        LOITER, BRAKE, RTL) is refused until the EKF has one; disarmed, any mode is set (the
        arming checks judge it then), as Copter::set_mode does."""
        airborne = self.landed_state != LandedState.ON_GROUND
        if (
            self.armed
            and number in _NEEDS_POSITION
            and number != self.number
            and not self.has_position(t_s)
        ):
            return self._refuse(f"Mode change to {number} failed: requires position")
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
        if arm and not self.armed and self.number in _NEEDS_POSITION and not self.has_position(t_s):
            # AP_Arming_Copter's mandatory position check, for a mode that needs a position
            return self._refuse("PreArm: Need Position Estimate")
        result = super().arm(arm, t_s, force)
        if arm and result == Result.ACCEPTED and self.number in GUIDED_MODES:
            self.mode, self.intended_mode = HOLD, OFFBOARD
        return result

    def _delay_of(self, sp: AttitudeSetpoint | PositionSetpoint) -> float:
        """Every setpoint waits for the main loop to read it; body rates longer (the fit)."""
        ap = self.ardupilot
        body_rates = isinstance(sp, AttitudeSetpoint) and sp.type_mask & IGNORE_ATTITUDE
        return ap.setpoint_delay_s + (ap.rate_input_delay_s if body_rates else 0.0)

    def on_attitude_setpoint(self, sp: AttitudeSetpoint, t_s: float) -> None:
        rates_ignored = sp.type_mask & _RATES
        if self.number not in GUIDED_MODES or rates_ignored not in (0, _RATES):
            self.ignored_setpoints += 1
            return
        super().on_attitude_setpoint(sp, t_s)
        self._timed_out = False
        self.intended_mode = OFFBOARD  # guided attitude control, even over a takeoff

    # ---- the periodic update ------------------------------------------------------------------

    def pilot_climb_rate_m_s(self) -> float:
        """The climb rate the pilot's throttle stick asks of LOITER (m/s, up positive):
        none within the deadzone about mid stick, full PILOT_SPD_UP / _DN at the ends."""
        ap = self.ardupilot
        edge = 0.5 - ap.throttle_deadzone_norm
        if ap.rc_throttle_norm < edge:
            down = ap.pilot_speed_dn_m_s or ap.pilot_speed_up_m_s
            return -down * (edge - ap.rc_throttle_norm) / edge
        if ap.rc_throttle_norm > 1.0 - edge:
            return ap.pilot_speed_up_m_s * (ap.rc_throttle_norm - (1.0 - edge)) / edge
        return 0.0

    def update_outer(self, x: FloatArray, t_s: float, dt_s: float) -> None:
        self._outer_dt_s = dt_s
        if self.number == LOITER and self.mode == HOLD and self.armed and not on_ground(x):
            # ModeLoiter: the pilot's stick sets the climb rate (no pilot: the stick SITL has)
            self._hold_pos_ned_m[2] -= self.pilot_climb_rate_m_s() * dt_s
        super().update_outer(x, t_s, dt_s)
        if self.mode != OFFBOARD:
            self._att_target = None  # shaping starts again from the attitude flown
            self._shaped_rate[:] = 0.0
            self._shaped_accel = [0.0, 0.0, 0.0]
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
        target = q.copy() if self._att_target is None else self._att_target
        if sp.type_mask & IGNORE_ATTITUDE:
            # body rates (AC_AttitudeControl::input_rate_bf_roll_pitch_yaw_rads): the target
            # turns on at its shaped rate, which the command model moves towards the rate
            # asked (ACRO_RP_RATE_TC / PILOT_Y_RATE_TC, ATC_ACC_*_MAX), and that rate is fed
            # forward; the attitude error to the target adds P. The vehicle so follows the
            # command's integral: its rate overshoots the command after a lag to catch up
            # (the real ArduCopter's "gain 1.39" of a first-order fit), not a slow filter
            target = self._turned(target, self._shaped_rate)
            self._shape_rates(np.asarray(sp.rate_frd_rad_s))
            angle_p = np.asarray(self.ardupilot.rate_angle_p_1_s)
            rate = self._shaped_rate + self._attitude_control(q, target, angle_p)
        else:
            # a quaternion (AC_AttitudeControl::input_quaternion): the target turns on at its
            # shaped rate, which the command model moves to close the error to the quaternion
            # asked (ATC_INPUT_TC on roll and pitch, PILOT_Y_RATE_TC on yaw: a critically
            # damped approach, not a first-order one), and that rate is fed forward
            # (ATC_RATE_FF_ENAB, on by default) to the rate loop
            target = self._turned(target, self._shaped_rate)
            error = rotation_vector(quat_multiply(quat_conjugate(target), np.asarray(sp.q_wxyz)))
            self._shape_towards(error)
            rate = self._shaped_rate + self._attitude_control(q, target)
        self._att_target = target
        lim = np.asarray(self.params.rate_max_rad_s)
        return target, np.clip(rate, -lim, lim), self._thrust(x, sp.thrust_norm)

    def _turned(self, target: FloatArray, rate_frd_rad_s: FloatArray) -> FloatArray:
        """The attitude target (4,) turned on by a body rate (3,) over one tick."""
        half = 0.5 * self._outer_dt_s * rate_frd_rad_s
        return quat_normalize(quat_multiply(target, np.array([1.0, *half])))

    def _shape_rates(self, rate_frd_rad_s: FloatArray) -> None:
        """The command model on each axis towards a body rate (no angle error)."""
        ap = self.ardupilot
        loop_tc_s = 10.0 / ap.loop_rate_hz  # a time constant of 0: ten main-loop periods
        rp_tc_s = ap.rate_input_tc_s if ap.rate_input_tc_s > 0.0 else loop_tc_s
        yaw_tc_s = ap.yaw_rate_tc_s if ap.yaw_rate_tc_s > 0.0 else loop_tc_s
        for axis, tc_s in enumerate((rp_tc_s, rp_tc_s, yaw_tc_s)):
            rate, self._shaped_accel[axis] = command_model(
                0.0,
                float(rate_frd_rad_s[axis]),
                (float(self._shaped_rate[axis]), self._shaped_accel[axis]),
                ap.accel_max_frd_rad_s2[axis],
                tc_s,
                self._outer_dt_s,
            )
            self._shaped_rate[axis] = rate

    def _shape_towards(self, error_frd_rad: FloatArray) -> None:
        """The command model on each axis, the target's rate and acceleration updated."""
        ap = self.ardupilot
        loop_tc_s = 10.0 / ap.loop_rate_hz  # a time constant of 0: ten main-loop periods
        yaw_tc_s = ap.yaw_rate_tc_s if ap.yaw_rate_tc_s > 0.0 else loop_tc_s
        for axis, tc_s in enumerate((ap.input_tc_s, ap.input_tc_s, yaw_tc_s)):
            wrapped = math.remainder(float(error_frd_rad[axis]), math.tau)
            rate, self._shaped_accel[axis] = command_model(
                wrapped,
                0.0,
                (float(self._shaped_rate[axis]), self._shaped_accel[axis]),
                ap.accel_max_frd_rad_s2[axis],
                tc_s,
                self._outer_dt_s,
            )
            self._shaped_rate[axis] = rate

    def _rate_control(
        self,
        rate_frd_rad_s: Sequence[float],
        rate_cmd_frd_rad_s: Sequence[float],
        thrust_norm: float,
        dt_s: float,
    ) -> list[float]:
        """The rate loop, its error first through ArduCopter's error filter (ATC_RAT_*_FLTE:
        yaw's 2.5 Hz, the main reason its yaw answers 130 ms late): the PI then acts on the
        filtered error, as AC_PID's P and I do. An axis without a filter passes untouched."""
        alphas = self._rate_error_alpha
        if alphas is None:
            alphas = tuple(
                -math.expm1(-math.tau * hz * dt_s) for hz in self.ardupilot.rate_error_filter_hz
            )
            self._rate_error_alpha = alphas  # (the physics step never changes)
        errors = [c - w for c, w in zip(rate_cmd_frd_rad_s, rate_frd_rad_s, strict=True)]
        if self._rate_error is not None:
            errors = [
                f + a * (e - f) for f, a, e in zip(self._rate_error, alphas, errors, strict=True)
            ]
        self._rate_error = errors
        # the loop's error is command - rate: a filtered axis's command is moved to make it so
        command = [
            w + e if a > 0.0 else c
            for w, e, a, c in zip(rate_frd_rad_s, errors, alphas, rate_cmd_frd_rad_s, strict=True)
        ]
        return super()._rate_control(rate_frd_rad_s, command, thrust_norm, dt_s)

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
        self._rate_error = None
        self._vel_err_prev = None
        self._vel_err_rate = np.zeros(3)

    def _thrust(self, x: FloatArray, thrust: float) -> float:
        """SET_ATTITUDE_TARGET's thrust as the collective thrust this vehicle produces."""
        cos_tilt = float(quat_to_rotation(x[QUAT])[2, 2])
        as_throttle = self.ardupilot.guid_options & GUID_OPTIONS_THRUST_AS_THROTTLE
        if as_throttle and not self._timed_out:
            # throttle plus ArduCopter's angle boost (1 / cos of the tilt, floored at 0.1)
            return min(1.0, thrust / min(max(cos_tilt, 0.1), 1.0))
        # a climb rate: 0.5 holds altitude, 1 climbs at WP_SPD_UP, 0 sinks at WP_SPD_DN
        ap = self.ardupilot
        speed = ap.wp_speed_up_m_s if thrust >= 0.5 else ap.wp_speed_dn_m_s
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
