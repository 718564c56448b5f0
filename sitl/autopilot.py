"""A small PX4-like autopilot: modes, arming, takeoff/hold/land, offboard, cascaded control.

Pure logic and numerics: commands and setpoints come in as method calls stamped with vehicle
time, ``update`` turns the vehicle state into rotor speed commands. No sockets, no MAVLink.

Cascade (each loop's gains are accelerations per unit error, so they are mass-independent):
position P -> velocity PI -> desired acceleration -> thrust vector + yaw -> attitude
quaternion (thesis 3.13, without the small-angle linearisation) -> attitude P on the
quaternion error -> body rates -> rate PI -> torques -> inverse effectiveness (the x-layout
generalisation of thesis 3.11) -> rotor forces -> rotor speeds.

Timing as PX4 main + SIH measured it: offboard setpoints reach the controllers after a dead
time, and the rate loop answers its setpoint as a first-order lag (a reference model), so a
body-rate command shows in the measured rates after ``rate_dead_time_s`` then follows with
``rate_time_constant_s``.

Thrust normalisation (SET_ATTITUDE_TARGET): ``thrust_norm * 4 k_F w_max^2`` is the collective
rotor force; 0.52 hovers the default vehicle.
"""

from __future__ import annotations

import math
from collections import deque
from collections.abc import Sequence
from dataclasses import dataclass
from enum import IntEnum

import numpy as np

from epc_offboard.common.frames import (
    GRAVITY_M_S2,
    FloatArray,
    quat_conjugate,
    quat_multiply,
    quat_to_euler,
    quat_to_rotation,
)
from sitl.params import AutopilotParams, VehicleParams
from sitl.physics import POS, QUAT, RATE, VEL, effectiveness_matrix, on_ground


class Result(IntEnum):
    """Command outcome, numbered as MAV_RESULT."""

    ACCEPTED = 0
    TEMPORARILY_REJECTED = 1
    DENIED = 2
    UNSUPPORTED = 3
    FAILED = 4


class LandedState(IntEnum):
    """Numbered as MAV_LANDED_STATE."""

    ON_GROUND = 1
    IN_AIR = 2
    TAKEOFF = 3
    LANDING = 4


@dataclass(frozen=True)
class Mode:
    """PX4 custom mode: main mode and sub mode (custom_mode = main << 16 | sub << 24)."""

    main: int
    sub: int = 0

    @property
    def custom_mode(self) -> int:
        return (self.main << 16) | (self.sub << 24)


POSCTL = Mode(3)
TAKEOFF = Mode(4, 2)
HOLD = Mode(4, 3)  # AUTO.LOITER
LAND = Mode(4, 6)
OFFBOARD = Mode(6)
SETTABLE_MODES = frozenset({POSCTL, TAKEOFF, HOLD, LAND, OFFBOARD})

# SET_ATTITUDE_TARGET type_mask bits
IGNORE_ROLL_RATE = 1
IGNORE_PITCH_RATE = 2
IGNORE_YAW_RATE = 4
IGNORE_THRUST = 64
IGNORE_ATTITUDE = 128
FORCE_DISARM_MAGIC = 21196
_MAX_INTEGRAL_ACC_M_S2 = 5.0  # PX4's param2 that forces a disarm in the air


@dataclass(frozen=True)
class AttitudeSetpoint:
    """An offboard SET_ATTITUDE_TARGET, already decoded: NaN-free, masks applied."""

    type_mask: int
    q_wxyz: tuple[float, float, float, float]
    rate_frd_rad_s: tuple[float, float, float]
    thrust_norm: float


@dataclass(frozen=True)
class PositionSetpoint:
    """An offboard SET_POSITION_TARGET_LOCAL_NED: position, velocity, acceleration feedforward
    and yaw, each None when ignored."""

    pos_ned_m: tuple[float, float, float] | None
    vel_ned_m_s: tuple[float, float, float] | None
    yaw_rad: float | None
    acc_ned_m_s2: tuple[float, float, float] | None = None


@dataclass(frozen=True)
class ActuatorCommand:
    """What the autopilot commanded this step (logged as ground truth)."""

    rotor_speed_rad_s: FloatArray  # (4,)
    thrust_norm: float
    rate_cmd_frd_rad_s: FloatArray  # (3,)
    q_cmd_wxyz: FloatArray  # (4,) attitude command (current attitude in pure rate control)


def cross3(a: FloatArray, b: FloatArray) -> FloatArray:
    """Cross product of two (3,) vectors; np.cross costs ten times more on tiny arrays."""
    a0, a1, a2 = a
    b0, b1, b2 = b
    return np.array([a1 * b2 - a2 * b1, a2 * b0 - a0 * b2, a0 * b1 - a1 * b0])


def quat_from_rotation(R: FloatArray) -> FloatArray:
    """Unit quaternion [w, x, y, z] of a (3, 3) rotation matrix (Shepperd's method), w >= 0."""
    tr = float(np.trace(R))
    if tr > 0.0:
        s = 2.0 * math.sqrt(tr + 1.0)
        q = [0.25 * s, (R[2, 1] - R[1, 2]) / s, (R[0, 2] - R[2, 0]) / s, (R[1, 0] - R[0, 1]) / s]
    elif R[0, 0] > R[1, 1] and R[0, 0] > R[2, 2]:
        s = 2.0 * math.sqrt(1.0 + R[0, 0] - R[1, 1] - R[2, 2])
        q = [(R[2, 1] - R[1, 2]) / s, 0.25 * s, (R[0, 1] + R[1, 0]) / s, (R[0, 2] + R[2, 0]) / s]
    elif R[1, 1] > R[2, 2]:
        s = 2.0 * math.sqrt(1.0 + R[1, 1] - R[0, 0] - R[2, 2])
        q = [(R[0, 2] - R[2, 0]) / s, (R[0, 1] + R[1, 0]) / s, 0.25 * s, (R[1, 2] + R[2, 1]) / s]
    else:
        s = 2.0 * math.sqrt(1.0 + R[2, 2] - R[0, 0] - R[1, 1])
        q = [(R[1, 0] - R[0, 1]) / s, (R[0, 2] + R[2, 0]) / s, (R[1, 2] + R[2, 1]) / s, 0.25 * s]
    qa = np.asarray(q)
    qa /= np.linalg.norm(qa)
    return -qa if qa[0] < 0.0 else qa


def attitude_from_thrust(thrust_dir_ned: FloatArray, yaw_rad: float) -> FloatArray:
    """Quaternion whose body -z axis points along ``thrust_dir_ned`` (unit), Z-Y-X yaw exact.

    As PX4's bodyzToAttitude: body x is kept in the vertical plane of the heading.
    """
    z_b = -thrust_dir_ned
    y_c = np.array([-math.sin(yaw_rad), math.cos(yaw_rad), 0.0])
    x_b = cross3(y_c, z_b)
    x_b /= np.linalg.norm(x_b)
    y_b = cross3(z_b, x_b)
    return quat_from_rotation(np.column_stack([x_b, y_b, z_b]))


class Autopilot:
    """Mode state machine plus the cascaded controllers. Times are vehicle seconds.

    This is the PX4 personality; ``sitl.ardupilot.ArduCopter`` is ArduCopter's. What the
    MAVLink endpoint asks of a personality: the ``custom_mode`` and ``mav_autopilot`` of its
    heartbeat, whether it streams by default, its parameters, and the ``*_command`` methods
    that read a command's parameters as that autopilot does.
    """

    mav_autopilot = 12  # MAV_AUTOPILOT_PX4
    streams_by_default = True  # PX4 streams its onboard link's messages unasked
    sends_odometry = True
    heartbeat_on_mode_change = False  # PX4's mode shows in its next 1 Hz heartbeat
    # real time: a setpoint reaches the rate loop at the physics step its delay ends in
    # (:meth:`apply_due_setpoints`)
    setpoints_between_ticks = True
    rtl_count = 0  # RTLs entered (PX4's RTL is not modelled: always 0 here)

    def __init__(self, vehicle: VehicleParams, params: AutopilotParams) -> None:
        self.vehicle = vehicle
        self.params = params
        self.mode = HOLD
        # PX4's "user intended mode": a failsafe changes ``mode`` but not this; once the
        # failsafe clears (setpoints stream again) PX4 returns to it, armed or not
        self.intended_mode = HOLD
        self.armed = False
        self.status_text: str | None = None  # why the last command was refused
        self._arm_refusals_left = params.arm_refusals_after_boot
        self.landed_state = LandedState.ON_GROUND
        self.failsafe_count = 0
        self._arm_time_s = 0.0
        self._has_flown = False
        self._ground_since_s: float | None = 0.0
        self._hold_pos_ned_m = np.zeros(3)
        self._hold_yaw_rad = 0.0
        self._takeoff_target_d_m = 0.0
        self._ref_pos_ned_m = np.zeros(3)
        self._setpoint_times_s: deque[float] = deque(maxlen=64)
        self._att_sp: AttitudeSetpoint | None = None
        self._pos_sp: PositionSetpoint | None = None
        # setpoints received but not yet seen by the controllers: (due time s, setpoint)
        self._in_transit: deque[tuple[float, AttitudeSetpoint | PositionSetpoint]] = deque()
        # quaternion setpoints as they arrived (outer-loop time): flown
        # attitude_setpoint_extra_delay_s later than a body-rate setpoint would be
        self._attitude_line: deque[tuple[float, AttitudeSetpoint]] = deque()
        self._setpoint_delay_s = params.setpoint_delay_s(vehicle)
        self._rate_ref_tc_s = params.rate_reference_time_constant_s(vehicle)
        # the rate loop's reference (rad/s, FRD): the rate setpoint through a first-order lag
        # of rate_time_constant_s; None until the loop runs (it starts at the rates flown)
        self._rate_ref: list[float] | None = None
        self._vel_integral = np.zeros(3)
        self._rate_integral = [0.0, 0.0, 0.0]
        mix_inv = np.linalg.inv(effectiveness_matrix(vehicle))
        self._mix_collective = mix_inv[:, 0].tolist()
        self._mix_torque = mix_inv[:, 1:]
        self._f_max_n = vehicle.k_f_n_s2 * vehicle.rotor_speed_max_rad_s**2
        self._f_idle_n = vehicle.k_f_n_s2 * vehicle.rotor_speed_min_rad_s**2
        self._last_state: FloatArray | None = None
        self._last_thrust_norm = vehicle.hover_thrust_norm
        self._target: tuple[FloatArray, float, FloatArray] | None = None  # rate, thrust, q
        self._idle_speed_rad_s = 0.0

    # ---- what the endpoint asks ---------------------------------------------------------------

    @property
    def custom_mode(self) -> int:
        return self.mode.custom_mode

    def set_mode_command(self, custom_mode: int, sub_mode: int, t_s: float) -> Result:
        """MAV_CMD_DO_SET_MODE(custom mode enabled, param2, param3): PX4's main and sub mode."""
        return self.set_mode(Mode(custom_mode, sub_mode), t_s)

    def set_mode_message(self, custom_mode: int, t_s: float) -> Result:
        """SET_MODE's custom_mode: main << 16 | sub << 24."""
        return self.set_mode(Mode((custom_mode >> 16) & 0xFF, (custom_mode >> 24) & 0xFF), t_s)

    def takeoff_command(self, param7: float, home_amsl_m: float, t_s: float) -> Result:
        """MAV_CMD_NAV_TAKEOFF: param7 (COMMAND_INT z) is the target altitude AMSL; NaN is
        PX4's default altitude (MIS_TAKEOFF_ALT above the current one)."""
        return self.takeoff(param7 - home_amsl_m if math.isfinite(param7) else None, t_s)

    def parameters(self) -> list[tuple[str, float]]:
        """A read-only view of the config under PX4's parameter names, for ground stations."""
        ap = self.params
        return [
            ("COM_DISARM_LAND", ap.disarm_after_land_s),
            ("COM_DISARM_PRFLT", ap.disarm_preflight_s),
            ("COM_OF_LOSS_T", ap.offboard_loss_timeout_s),
            ("MIS_TAKEOFF_ALT", ap.takeoff_altitude_m),
            ("MPC_LAND_SPEED", ap.land_speed_m_s),
            ("MPC_TKO_SPEED", ap.climb_speed_m_s),
        ]

    def set_parameter(self, name: str, value: float) -> bool:
        """PARAM_SET: False (unchanged) here; PX4's view is read-only."""
        return False

    def has_position(self, t_s: float) -> bool:
        """Whether the estimator has a local position to stream at vehicle time ``t_s``."""
        return True

    # ---- commands -------------------------------------------------------------------------

    def arm(self, arm: bool, t_s: float, force: bool = False) -> Result:
        if arm == self.armed:
            return Result.ACCEPTED
        landed = self.landed_state == LandedState.ON_GROUND
        if arm:
            if not landed:
                return self._refuse("Arming denied: not landed")
            if self._arm_refusals_left > 0:
                self._arm_refusals_left -= 1
                # PX4 main's estimator check (HealthAndArmingChecks/estimatorCheck.cpp)
                return self._refuse("Preflight Fail: heading estimate not stable")
            self.armed = True
            self._arm_time_s = t_s
            self._has_flown = False
            self._reset_integrators()
            return Result.ACCEPTED
        if not landed and not force:
            return Result.DENIED
        self._disarm()
        return Result.ACCEPTED

    def _refuse(self, why: str) -> Result:
        self.status_text = why
        return Result.DENIED

    def set_mode(self, mode: Mode, t_s: float) -> Result:
        if mode not in SETTABLE_MODES:
            return Result.UNSUPPORTED
        if mode == self.mode:
            self.intended_mode = mode
            return Result.ACCEPTED
        if mode == OFFBOARD:
            if not self.offboard_stream_ok(t_s):
                return self._refuse("Switching to Offboard is currently not available")
        elif mode == TAKEOFF:
            return self.takeoff(None, t_s)
        elif mode == LAND:
            return self.land(t_s)
        else:
            self._capture_hold()
        self.mode = self.intended_mode = mode
        return Result.ACCEPTED

    def takeoff(self, altitude_above_home_m: float | None, t_s: float) -> Result:
        """Climb to ``altitude_above_home_m``, then hold there.

        As PX4: with no altitude (NaN) the target is the CURRENT altitude + MIS_TAKEOFF_ALT,
        every time a takeoff is accepted, in the air as well; a repeated takeoff climbs on.
        """
        if not self.armed:
            return self._refuse("Takeoff denied: disarmed")
        pos = self._current_pos()
        if altitude_above_home_m is None or not math.isfinite(altitude_above_home_m):
            self._takeoff_target_d_m = float(pos[2]) - self.params.takeoff_altitude_m
        else:
            # never a descent: PX4 says "Already higher than takeoff altitude" and stays
            self._takeoff_target_d_m = min(-altitude_above_home_m, float(pos[2]))
        if self._takeoff_target_d_m < float(pos[2]):  # a climb ends where PX4's would hold
            short_m = self.params.takeoff_hold_short_m
            self._takeoff_target_d_m = min(self._takeoff_target_d_m + short_m, float(pos[2]))
        self._ref_pos_ned_m = pos.copy()
        self._hold_yaw_rad = self._current_yaw()
        self.mode = self.intended_mode = TAKEOFF
        return Result.ACCEPTED

    def land(self, t_s: float) -> Result:
        if not self.armed:
            return self._refuse("Landing denied: disarmed")
        self._capture_hold()
        self.mode = self.intended_mode = LAND
        return Result.ACCEPTED

    def on_attitude_setpoint(self, sp: AttitudeSetpoint, t_s: float) -> None:
        self._receive(sp, t_s)

    def on_position_setpoint(self, sp: PositionSetpoint, t_s: float) -> None:
        self._receive(sp, t_s)

    def _receive(self, sp: AttitudeSetpoint | PositionSetpoint, t_s: float) -> None:
        """A setpoint arrived: the stream counts at once (PX4's commander sees the offboard
        signal on receipt), the controllers see its value ``_setpoint_delay_s`` later."""
        self._setpoint_times_s.append(t_s)
        delay_s = self._delay_of(sp)
        if delay_s <= 0.0 and not self._in_transit:
            self._apply_setpoint(sp)
        else:
            # in arrival order: a setpoint never overtakes one that waits longer
            due_s = t_s + delay_s
            self._in_transit.append((max(due_s, self._in_transit[-1][0]) if self._in_transit
                                     else due_s, sp))  # fmt: skip

    def _delay_of(self, sp: AttitudeSetpoint | PositionSetpoint) -> float:
        """How long ``sp`` waits before the controllers see it (PX4: every setpoint alike)."""
        return self._setpoint_delay_s

    def _deliver_setpoints(self, t_s: float) -> None:
        """Hand the controllers every setpoint whose delay has passed, in arrival order."""
        transit = self._in_transit
        while transit and transit[0][0] <= t_s + 1e-9:
            self._apply_setpoint(transit.popleft()[1])

    def setpoints_due(self, t_s: float) -> bool:
        """Whether a setpoint in transit reaches the controllers by vehicle time ``t_s``."""
        transit = self._in_transit
        return bool(transit) and transit[0][0] <= t_s + 1e-9

    def apply_due_setpoints(self, x: FloatArray, t_s: float) -> None:
        """Between two outer-loop updates (real time): the setpoints due by ``t_s`` reach
        the controllers now, and an offboard attitude setpoint the rate loop's target, from
        the state ``x`` (17,) of this physics step. PX4 flies a setpoint from the rate-loop
        cycle after its delay (1 kHz), not from the next 200 Hz tick."""
        self._deliver_setpoints(t_s)
        if self.mode == OFFBOARD and self._att_sp is not None and self._target is not None:
            sp = self._delayed_attitude(self._att_sp, t_s)
            q_cmd, rate_cmd, thrust_norm = self._offboard_attitude(x, sp)
            self._target = (rate_cmd, thrust_norm, q_cmd)

    def _apply_setpoint(self, sp: AttitudeSetpoint | PositionSetpoint) -> None:
        if isinstance(sp, AttitudeSetpoint):
            self._att_sp = sp
            self._pos_sp = None
            if not sp.type_mask & IGNORE_THRUST:
                self._last_thrust_norm = sp.thrust_norm
        else:
            self._pos_sp = sp
            self._att_sp = None

    def offboard_stream_ok(self, t_s: float) -> bool:
        """PX4's entry condition: a setpoint stream above ``offboard_min_rate_hz`` is present.

        As PX4's commander judges it: by the age of the last setpoint (its offboard signal is
        "lost" past COM_OF_LOSS_T), not by counting a window. So MAVSDK's ritual — send one
        setpoint, then start offboard while its 20 Hz stream begins — is accepted, as on PX4.
        """
        times = self._setpoint_times_s
        if not times:
            return False
        age_s = t_s - times[-1]
        return age_s <= min(
            1.0 / self.params.offboard_min_rate_hz, self.params.offboard_loss_timeout_s
        )

    # ---- the periodic update --------------------------------------------------------------

    def update_outer(self, x: FloatArray, t_s: float, dt_s: float) -> None:
        """Supervision, position and attitude loops on the true state ``x`` (17,).

        Runs at the tick rate; sets the body-rate and thrust target the inner loop tracks.
        """
        self._last_state = x
        self._deliver_setpoints(t_s)
        self._supervise(x, t_s)
        self._return_to_intended(t_s)
        q = x[QUAT]
        if not self.armed:
            self._idle_speed_rad_s = 0.0
            self._target = None
            return
        if self.mode == OFFBOARD and self._att_sp is not None:
            sp = self._delayed_attitude(self._att_sp, t_s)
            q_cmd, rate_cmd, thrust_norm = self._offboard_attitude(x, sp)
        elif self._on_ground_idle(x):
            self._idle_speed_rad_s = self.vehicle.rotor_speed_min_rad_s
            self._target = None
            return
        else:
            pos_ref, vel_ref, yaw_ref = self._position_reference(x, dt_s)
            q_cmd, thrust_norm = self._position_control(
                x, pos_ref, vel_ref, yaw_ref, dt_s, self._acc_feedforward()
            )
            rate_cmd = self._attitude_control(q, q_cmd)
        if on_ground(x):
            self._reset_integrators()
        self._target = (rate_cmd, thrust_norm, q_cmd)

    def _delayed_attitude(self, sp: AttitudeSetpoint, t_s: float) -> AttitudeSetpoint:
        """The quaternion setpoint PX4's attitude loop flies at ``t_s``: the one that arrived
        ``attitude_setpoint_extra_delay_s`` ago (the first one at once). Body rates pass."""
        extra_s = self.params.attitude_setpoint_extra_delay_s
        line = self._attitude_line
        if extra_s <= 0.0 or sp.type_mask & IGNORE_ATTITUDE:
            line.clear()
            return sp
        if not line or line[-1][1] is not sp:
            line.append((t_s, sp))
        while len(line) > 1 and line[1][0] <= t_s - extra_s + 1e-9:
            line.popleft()
        return line[0][1]

    def update_inner(self, x: FloatArray, dt_s: float) -> ActuatorCommand:
        """The rate loop (physics rate): rotor speed commands for state ``x`` (17,)."""
        return self.command(self.rotor_speeds(x[RATE].tolist(), dt_s), x[QUAT])

    def rotor_speeds(self, rate_frd_rad_s: Sequence[float], dt_s: float) -> list[float]:
        """The rate loop alone, on plain floats: rotor speed commands (4,) rad/s for the
        body rates (3,) flown. The simulation calls it every physics step; a tick's
        :meth:`command` then tells what the last one commanded."""
        if self._target is None:
            return [self._idle_speed_rad_s] * 4
        rate_cmd, thrust_norm, _ = self._target
        return self._rate_control(rate_frd_rad_s, rate_cmd.tolist(), thrust_norm, dt_s)

    def command(self, rotor_speed_rad_s: Sequence[float], q_wxyz: FloatArray) -> ActuatorCommand:
        """What the autopilot commands: rotor speeds (4,) from :meth:`rotor_speeds` and the
        targets they track; ``q_wxyz`` (4,), the attitude flown, stands for the attitude
        command while there is none (disarmed, idle)."""
        speeds = np.array(rotor_speed_rad_s, dtype=np.float64)
        if self._target is None:
            return ActuatorCommand(
                rotor_speed_rad_s=speeds,
                thrust_norm=0.0,
                rate_cmd_frd_rad_s=np.zeros(3),
                q_cmd_wxyz=np.array(q_wxyz, dtype=np.float64),
            )
        rate_cmd, thrust_norm, q_cmd = self._target
        return ActuatorCommand(
            rotor_speed_rad_s=speeds,
            thrust_norm=thrust_norm,
            rate_cmd_frd_rad_s=rate_cmd,
            q_cmd_wxyz=q_cmd,
        )

    def _supervise(self, x: FloatArray, t_s: float) -> None:
        """Landed detection, auto-disarm, offboard loss failsafe, takeoff completion."""
        grounded = on_ground(x)
        if grounded:
            if self._ground_since_s is None:
                self._ground_since_s = t_s
        else:
            self._ground_since_s = None
            self._has_flown = self.armed or self._has_flown
        if self.mode == LAND:
            self.landed_state = LandedState.ON_GROUND if grounded else LandedState.LANDING
        elif self.mode == TAKEOFF:
            self.landed_state = LandedState.TAKEOFF
        else:
            self.landed_state = LandedState.ON_GROUND if grounded else LandedState.IN_AIR
        if not self.armed:
            return
        ground_s = 0.0 if self._ground_since_s is None else t_s - self._ground_since_s
        if (
            grounded
            and not self._has_flown
            and t_s - self._arm_time_s > self.params.disarm_preflight_s
        ):
            self._disarm()
            return
        if grounded and self._has_flown and ground_s > self.params.disarm_after_land_s:
            self._disarm()
            return
        if self.mode == OFFBOARD and (
            not self._setpoint_times_s
            or t_s - self._setpoint_times_s[-1] > self.params.offboard_loss_timeout_s
        ):
            self._setpoints_lost(t_s)
        if self.mode == TAKEOFF and abs(x[2] - self._takeoff_target_d_m) < 0.1:
            self._hold_pos_ned_m = np.array(
                [self._ref_pos_ned_m[0], self._ref_pos_ned_m[1], self._takeoff_target_d_m]
            )
            self.mode = self.intended_mode = HOLD

    def _setpoints_lost(self, t_s: float) -> None:
        """COM_OF_LOSS_T without a setpoint in Offboard: PX4's failsafe holds position."""
        self.failsafe_count += 1
        self._capture_hold()
        self.mode = HOLD

    def _return_to_intended(self, t_s: float) -> None:
        """The failsafe clears when setpoints stream again: back to Offboard, armed or not
        (PX4 does this even after an auto-land has disarmed the vehicle)."""
        if (
            self.intended_mode == OFFBOARD
            and self.mode != OFFBOARD
            and self.offboard_stream_ok(t_s)
        ):
            self.mode = OFFBOARD

    def _disarm(self) -> None:
        self.armed = False
        self._reset_integrators()
        if self.mode in (TAKEOFF, LAND):
            self.mode = HOLD

    def _on_ground_idle(self, x: FloatArray) -> bool:
        """Armed on the ground in a hold-type mode: PX4 spins at idle and waits."""
        return on_ground(x) and self.mode in (HOLD, POSCTL, LAND)

    def _capture_hold(self) -> None:
        self._hold_pos_ned_m = self._current_pos()
        self._hold_yaw_rad = self._current_yaw()
        self._vel_integral[:] = 0.0

    def _current_pos(self) -> FloatArray:
        return np.zeros(3) if self._last_state is None else self._last_state[POS].copy()

    def _current_yaw(self) -> float:
        return 0.0 if self._last_state is None else quat_to_euler(self._last_state[QUAT])[2]

    def _reset_integrators(self) -> None:
        self._vel_integral[:] = 0.0
        self._rate_integral = [0.0, 0.0, 0.0]
        self._rate_ref = None

    # ---- controllers ----------------------------------------------------------------------

    def _position_reference(
        self, x: FloatArray, dt_s: float
    ) -> tuple[FloatArray, FloatArray, float]:
        p = self.params
        zero = np.zeros(3)
        if self.mode == TAKEOFF:
            # The reference climbs at climb speed; the vehicle follows it up to the target.
            ref = self._ref_pos_ned_m
            ref[2] = max(self._takeoff_target_d_m, ref[2] - p.climb_speed_m_s * dt_s)
            climbing = ref[2] > self._takeoff_target_d_m
            vel = np.array([0.0, 0.0, -p.climb_speed_m_s if climbing else 0.0])
            return ref.copy(), vel, self._hold_yaw_rad
        if self.mode == LAND:
            ref = np.array([self._hold_pos_ned_m[0], self._hold_pos_ned_m[1], x[2]])
            return ref, np.array([0.0, 0.0, p.land_speed_m_s]), self._hold_yaw_rad
        if self.mode == OFFBOARD and self._pos_sp is not None:
            sp = self._pos_sp
            pos = x[POS].copy() if sp.pos_ned_m is None else np.asarray(sp.pos_ned_m)
            vel = zero if sp.vel_ned_m_s is None else np.asarray(sp.vel_ned_m_s)
            yaw = self._current_yaw() if sp.yaw_rad is None else sp.yaw_rad
            return pos, vel, yaw
        return self._hold_pos_ned_m.copy(), zero, self._hold_yaw_rad

    def _acc_feedforward(self) -> FloatArray:
        sp = self._pos_sp
        if self.mode != OFFBOARD or sp is None or sp.acc_ned_m_s2 is None:
            return np.zeros(3)
        return np.asarray(sp.acc_ned_m_s2, dtype=np.float64)

    def _position_control(
        self,
        x: FloatArray,
        pos_ref: FloatArray,
        vel_ref: FloatArray,
        yaw_ref: float,
        dt_s: float,
        acc_ff: FloatArray,
    ) -> tuple[FloatArray, float]:
        """PX4's cascade: P on position, PI on velocity, plus acceleration feedforward ->
        acceleration -> (attitude quaternion, normalised thrust)."""
        acc = self._acceleration_command(x, pos_ref, vel_ref, dt_s, acc_ff)
        return self._attitude_for_acceleration(x, acc, yaw_ref)

    def _acceleration_command(
        self,
        x: FloatArray,
        pos_ref: FloatArray,
        vel_ref: FloatArray,
        dt_s: float,
        acc_ff: FloatArray,
    ) -> FloatArray:
        """PX4's MPC: P on position, PI on velocity, plus feedforward -> acceleration (3,)."""
        p = self.params
        # position P -> velocity setpoint (+ feedforward) -> velocity PI -> acceleration
        vel_sp = vel_ref + np.asarray(p.position_p_1_s) * (pos_ref - x[POS])
        vmax = np.asarray(p.max_speed_m_s)
        vel_err = np.clip(vel_sp, -vmax, vmax) - x[VEL]
        i_gain = np.asarray(p.velocity_i_1_s2)
        # the integral's share is bounded in acceleration (anti-windup)
        self._vel_integral = np.clip(
            self._vel_integral + vel_err * dt_s,
            -_MAX_INTEGRAL_ACC_M_S2 / i_gain,
            _MAX_INTEGRAL_ACC_M_S2 / i_gain,
        )
        return acc_ff + np.asarray(p.velocity_p_1_s) * vel_err + i_gain * self._vel_integral

    def _attitude_for_acceleration(
        self, x: FloatArray, acc: FloatArray, yaw_ref: float
    ) -> tuple[FloatArray, float]:
        """Acceleration (3,) NED -> (attitude quaternion, normalised thrust), tilt-limited."""
        p = self.params
        # Specific force the rotors must produce (NED): f = a - g.
        f = acc - np.array([0.0, 0.0, GRAVITY_M_S2])
        f[2] = min(f[2], -0.2 * GRAVITY_M_S2)  # never command thrust pointing down
        horiz = math.hypot(f[0], f[1])
        max_horiz = -f[2] * math.tan(math.radians(p.tilt_max_deg))
        if horiz > max_horiz:
            f[:2] *= max_horiz / horiz
        f_norm = float(np.linalg.norm(f))
        q_cmd = attitude_from_thrust(f / f_norm, yaw_ref)
        # Collective thrust: the part of f along the current body -z axis (as PX4 projects).
        body_up = -quat_to_rotation(x[QUAT])[:, 2]
        collective_n = self.vehicle.mass_kg * max(0.0, float(f @ body_up))
        return q_cmd, collective_n / self.vehicle.max_total_thrust_n

    def _attitude_control(
        self, q: FloatArray, q_cmd: FloatArray, p_1_s: FloatArray | None = None
    ) -> FloatArray:
        """Quaternion-error P controller (``p_1_s``, default attitude_p_1_s) -> body rate
        command (FRD), clamped."""
        q_err = quat_multiply(quat_conjugate(q), q_cmd)
        if q_err[0] < 0.0:
            q_err = -q_err
        gain = np.asarray(self.params.attitude_p_1_s if p_1_s is None else p_1_s)
        rate = 2.0 * gain * q_err[1:]
        lim = np.asarray(self.params.rate_max_rad_s)
        return np.clip(rate, -lim, lim)

    def _offboard_attitude(
        self, x: FloatArray, sp: AttitudeSetpoint
    ) -> tuple[FloatArray, FloatArray, float]:
        q = x[QUAT]
        if sp.type_mask & IGNORE_ATTITUDE:
            ignore = (IGNORE_ROLL_RATE, IGNORE_PITCH_RATE, IGNORE_YAW_RATE)
            rate = np.array(
                [
                    0.0 if sp.type_mask & bit else r
                    for bit, r in zip(ignore, sp.rate_frd_rad_s, strict=True)
                ]
            )
            q_cmd = q.copy()
        else:
            q_cmd = np.asarray(sp.q_wxyz)
            rate = self._attitude_control(q, q_cmd)
        return q_cmd, rate, self._last_thrust_norm

    def _rate_control(
        self,
        rate_frd_rad_s: Sequence[float],
        rate_cmd_frd_rad_s: Sequence[float],
        thrust_norm: float,
        dt_s: float,
    ) -> list[float]:
        """Rate PI -> torques -> rotor forces (inverse effectiveness, desaturated) -> speeds.

        With ``rate_time_constant_s`` > 0 the loop tracks a reference model: the setpoint
        through a first-order lag of that time constant, its slope fed forward as angular
        acceleration, so the closed loop answers a step as that lag (plus the motors'),
        whatever the gains; the gains then only reject disturbances.

        Plain floats (it runs at the physics rate), each operation as numpy did it."""
        wx, wy, wz = rate_frd_rad_s
        tau_s = self._rate_ref_tc_s
        fx = fy = fz = 0.0  # angular acceleration fed forward, rad/s^2
        if tau_s > 0.0:
            ref = list(rate_frd_rad_s) if self._rate_ref is None else self._rate_ref
            fx, fy, fz = ((c - r) / tau_s for c, r in zip(rate_cmd_frd_rad_s, ref, strict=True))
            alpha = -math.expm1(-dt_s / tau_s)  # the exact discretisation of the lag
            rate_cmd_frd_rad_s = [
                r + alpha * (c - r) for c, r in zip(rate_cmd_frd_rad_s, ref, strict=True)
            ]
            self._rate_ref = rate_cmd_frd_rad_s
        ex, ey, ez = (c - w for c, w in zip(rate_cmd_frd_rad_s, rate_frd_rad_s, strict=True))
        # the integral is bounded (anti-windup): min(max(., -0.5), 0.5)
        gx, gy, gz = self._rate_integral
        gx, gy, gz = (
            min(max(gx + ex * dt_s, -0.5), 0.5),
            min(max(gy + ey * dt_s, -0.5), 0.5),
            min(max(gz + ez * dt_s, -0.5), 0.5),
        )
        self._rate_integral = [gx, gy, gz]
        (px, py, pz), (ix_, iy_, iz_) = self.params.rate_p_1_s, self.params.rate_i_1_s2
        jx, jy, jz = self.vehicle.inertia_diag_kg_m2
        hx, hy, hz = jx * wx, jy * wy, jz * wz  # I w; torque = I dw + w x (I w)
        torque = np.array(
            [
                jx * (px * ex + ix_ * gx + fx) + (wy * hz - wz * hy),
                jy * (py * ey + iy_ * gy + fy) + (wz * hx - wx * hz),
                jz * (pz * ez + iz_ * gz + fz) + (wx * hy - wy * hx),
            ]
        )
        collective_n = min(1.0, max(0.0, thrust_norm)) * self.vehicle.max_total_thrust_n
        # Forces = base (collective, equal shares) + delta (torques), via the inverse mixer.
        # (The mixer product stays numpy's: its BLAS kernel sums in its own order, and the
        # SITL's flights must not change in the last digits.)
        base = [collective_n * m for m in self._mix_collective]
        delta = (self._mix_torque @ torque).tolist()
        f_max, f_idle = self._f_max_n, self._f_idle_n
        # Keep the collective, scale the torque part down until every rotor is within limits.
        scale = 1.0
        for b, d in zip(base, delta, strict=True):
            if b + d > f_max and d > 0.0:
                scale = min(scale, max(0.0, (f_max - b) / d))
            elif b + d < f_idle and d < 0.0:
                scale = min(scale, max(0.0, (f_idle - b) / d))
        kf = self.vehicle.k_f_n_s2
        return [
            math.sqrt(min(max(b + scale * d, f_idle), f_max) / kf)
            for b, d in zip(base, delta, strict=True)
        ]
