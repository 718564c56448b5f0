"""Configuration of the bundled SITL: vehicle, environment, autopilot and link.

One TOML file (``config/vehicles/*.toml``) holds the tables ``[vehicle]``, ``[environment]``,
``[autopilot]``, ``[sitl]`` and ``[ardupilot]`` (the ArduCopter personality's parameters),
and ``[envelope]``, which the offboard service reads from the same file
(:mod:`epc_offboard.common.airframe`);
it is loaded strictly by :func:`epc_offboard.common.configio.load_config` so an unknown or misspelt
key is an error naming the key and the file. Every key carries its unit. Range checks live
in ``__post_init__``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from epc_offboard.common.airframe import AirframeEnvelope
from epc_offboard.common.bundled import bundled_dir
from epc_offboard.common.configio import load_config
from epc_offboard.common.frames import GRAVITY_M_S2

AUTOPILOTS = frozenset({"px4", "ardupilot"})  # SITL personalities

# The packaged default vehicle: config/vehicles/, shipped in the wheel as epc_offboard's data.
DEFAULT_VEHICLE_FILE = bundled_dir() / "vehicles" / "quad_x_1500g.toml"


def _positive(**values: float) -> None:
    for name, value in values.items():
        if not value > 0.0:
            raise ValueError(f"{name} must be > 0, got {value}")


def _non_negative(**values: float) -> None:
    for name, value in values.items():
        if value < 0.0:
            raise ValueError(f"{name} must be >= 0, got {value}")


@dataclass(frozen=True)
class VehicleParams:
    """Rigid body, rotors and airframe drag (thesis 3.2, plus motor lag, limits and drag).

    Rotor i sits at ``arm_length_m`` from the centre, at ``rotor_angles_deg[i]`` measured in the
    body x-y plane from forward (+x) towards right (+y): FRD, so clockwise seen from above.
    ``rotor_yaw_moment_sign[i]`` is the sign of rotor i's reaction moment k_M w^2 about body +z
    (down): +1 for a rotor spinning counter-clockwise seen from above.
    """

    mass_kg: float
    arm_length_m: float
    inertia_diag_kg_m2: tuple[float, float, float]
    k_f_n_s2: float  # rotor thrust F = k_F w^2   [N / (rad/s)^2]
    k_m_n_m_s2: float  # rotor moment M = k_M w^2  [N m / (rad/s)^2]
    motor_time_constant_s: float
    rotor_speed_min_rad_s: float  # armed idle
    rotor_speed_max_rad_s: float
    drag_coeff_body_n_s_m: tuple[float, float, float]  # linear drag per body axis
    rotor_angles_deg: tuple[float, float, float, float] = (45.0, -135.0, -45.0, 135.0)
    rotor_yaw_moment_sign: tuple[float, float, float, float] = (1.0, 1.0, -1.0, -1.0)
    # Airframe aerodynamics beyond the linear drag (rotorpy's multirotor model; all 0: off,
    # the equations of motion are then exactly the linear-drag ones). Per body axis FRD, on
    # the airspeed v_a = R^T (v - v_wind):
    #   body (parasitic) drag, quadratic:  f = -|v_a| c_D (.) v_a              [N / (m/s)^2]
    #   rotor drag (H force) in x, y and induced inflow in z, each rotor's proportional to
    #   its speed:  f = -(sum_i w_i) k (.) v_a   [N / ((rad/s) (m/s)) = kg / rad]
    # The z entry of the latter is the thrust's change with airspeed through the discs: a
    # climb (or a disc tilted into the wind) lowers every rotor's thrust, a descent raises it.
    drag_quadratic_body_n_s2_m2: tuple[float, float, float] = (0.0, 0.0, 0.0)
    rotor_drag_kg_rad: tuple[float, float, float] = (0.0, 0.0, 0.0)

    def __post_init__(self) -> None:
        _positive(
            mass_kg=self.mass_kg,
            arm_length_m=self.arm_length_m,
            k_f_n_s2=self.k_f_n_s2,
            k_m_n_m_s2=self.k_m_n_m_s2,
            motor_time_constant_s=self.motor_time_constant_s,
            rotor_speed_max_rad_s=self.rotor_speed_max_rad_s,
        )
        for i, v in enumerate(self.inertia_diag_kg_m2):
            _positive(**{f"inertia_diag_kg_m2[{i}]": v})
        for name in ("drag_coeff_body_n_s_m", "drag_quadratic_body_n_s2_m2", "rotor_drag_kg_rad"):
            for i, v in enumerate(getattr(self, name)):
                _non_negative(**{f"{name}[{i}]": v})
        if not 0.0 <= self.rotor_speed_min_rad_s < self.rotor_speed_max_rad_s:
            raise ValueError("need 0 <= rotor_speed_min_rad_s < rotor_speed_max_rad_s")
        if any(abs(s) != 1.0 for s in self.rotor_yaw_moment_sign):
            raise ValueError("rotor_yaw_moment_sign entries must be +1 or -1")

    @property
    def aerodynamic(self) -> bool:
        """Quadratic body drag, rotor drag or inflow modelled (else only the linear drag)."""
        return any(self.drag_quadratic_body_n_s2_m2) or any(self.rotor_drag_kg_rad)

    @property
    def max_total_thrust_n(self) -> float:
        """Collective thrust at full rotor speed; SET_ATTITUDE_TARGET thrust 1.0 maps to it."""
        return 4.0 * self.k_f_n_s2 * self.rotor_speed_max_rad_s**2

    @property
    def hover_thrust_norm(self) -> float:
        return self.mass_kg * GRAVITY_M_S2 / self.max_total_thrust_n


@dataclass(frozen=True)
class SurfaceParams:
    """Near-surface disturbance: a plane (wall, gantry) that pulls the vehicle towards it.

    The force points along ``-normal_ned`` (towards the surface) with magnitude
    ``peak_force_n * exp(-distance / decay_length_m)``, plus seeded fluctuation of relative
    standard deviation ``fluctuation_rel``; zero beyond ``range_m``.
    """

    enabled: bool = False
    point_ned_m: tuple[float, float, float] = (5.0, 0.0, 0.0)
    normal_ned: tuple[float, float, float] = (-1.0, 0.0, 0.0)  # unit, pointing away from it
    peak_force_n: float = 2.0
    decay_length_m: float = 0.5
    range_m: float = 3.0
    fluctuation_rel: float = 0.3

    def __post_init__(self) -> None:
        _positive(decay_length_m=self.decay_length_m, range_m=self.range_m)
        _non_negative(peak_force_n=self.peak_force_n, fluctuation_rel=self.fluctuation_rel)
        if abs(math.hypot(*self.normal_ned) - 1.0) > 1e-6:
            raise ValueError(f"normal_ned must be a unit vector, got {self.normal_ned}")


@dataclass(frozen=True)
class EnvironmentParams:
    """Wind (docs/CONTRACTS.md convention) with first-order Gauss-Markov gusts, and a surface."""

    wind_speed_m_s: float = 0.0
    wind_dir_deg: float = 0.0  # towards, counter-clockwise from east
    gust_std_m_s: float = 0.0  # per axis, horizontal; vertical gets half
    gust_time_constant_s: float = 2.0
    # A wind whose speed swings as a sinusoid along its direction (Neural-Fly's fan array:
    # 8.5 + 2.4 sin t m/s): speed(t) = wind_speed_m_s + amplitude sin(rate t + phase), t the
    # vehicle time since the autopilot first entered offboard control (PX4: OFFBOARD;
    # ArduPilot: the first setpoint obeyed in GUIDED after its takeoff), when the service
    # starts its trajectory; before that t = 0 (a steady wind_speed + amplitude sin(phase)).
    # The service starts it when it sees the mode: on ArduPilot the same tick, on PX4 at the
    # heartbeat that confirms it, 0.05-0.15 s later (lockstep neuralfly rows; the same for
    # every method in a row), against up to a whole period (2 pi s) on SITL time.
    # So the gust meets the same stroke of the trajectory however long the takeoff and the
    # hand-over took (on SITL time it did not: max tilt 32-41.5 deg, error 1.9-9.5 cm on
    # the neuralfly figure-8, set by the hand-over instant alone). 0: steady.
    wind_sine_amplitude_m_s: float = 0.0
    wind_sine_rate_rad_s: float = 1.0
    wind_sine_phase_rad: float = 0.0
    surface: SurfaceParams = field(default_factory=SurfaceParams)

    def __post_init__(self) -> None:
        _non_negative(
            wind_speed_m_s=self.wind_speed_m_s,
            gust_std_m_s=self.gust_std_m_s,
            wind_sine_amplitude_m_s=self.wind_sine_amplitude_m_s,
        )
        _positive(
            gust_time_constant_s=self.gust_time_constant_s,
            wind_sine_rate_rad_s=self.wind_sine_rate_rad_s,
        )
        if not math.isfinite(self.wind_sine_phase_rad):
            raise ValueError(f"wind_sine_phase_rad must be finite, got {self.wind_sine_phase_rad}")


@dataclass(frozen=True)
class AutopilotParams:
    """The small PX4-like autopilot: gains (as accelerations per error), limits, timeouts."""

    rate_p_1_s: tuple[float, float, float] = (25.0, 25.0, 10.0)
    rate_i_1_s2: tuple[float, float, float] = (10.0, 10.0, 5.0)
    attitude_p_1_s: tuple[float, float, float] = (7.0, 7.0, 3.0)
    rate_max_rad_s: tuple[float, float, float] = (4.0, 4.0, 2.0)
    # PX4's position cascade and its defaults: MPC_XY_P / MPC_Z_P, MPC_*_VEL_P_ACC,
    # MPC_*_VEL_I_ACC (the velocity integrator is what trims out wind)
    position_p_1_s: tuple[float, float, float] = (0.95, 0.95, 1.0)
    velocity_p_1_s: tuple[float, float, float] = (1.8, 1.8, 4.0)
    velocity_i_1_s2: tuple[float, float, float] = (0.4, 0.4, 2.0)
    max_speed_m_s: tuple[float, float, float] = (12.0, 12.0, 3.0)  # MPC_XY_VEL_MAX, Z
    tilt_max_deg: float = 35.0
    takeoff_altitude_m: float = 2.5
    climb_speed_m_s: float = 1.5
    # A real PX4 (main, SIH) ends its takeoff NAV_MC_ALT_RAD (0.8 m) below the target and
    # holds wherever it brakes: 2.17-2.3 m of 2.5 in cold starts. The takeoff here holds this
    # far below its target instead (0: at the target, within 0.1 m)
    takeoff_hold_short_m: float = 0.0
    land_speed_m_s: float = 0.7
    offboard_loss_timeout_s: float = 1.0  # PX4's COM_OF_LOSS_T
    offboard_min_rate_hz: float = 2.0  # entry needs a setpoint stream above this rate
    disarm_preflight_s: float = 10.0  # armed on the ground without taking off
    disarm_after_land_s: float = 2.0
    # Armings refused right after boot, each with PX4's "Preflight Fail: heading estimate not
    # stable". PX4 main refuses to arm only while EKF2 is initialising or its pre-flight
    # heading innovation check fails (commander's estimatorCheck.cpp), a window of seconds
    # after boot, never a count; PX4 + SIH accepted the first arming in independent flights,
    # so by default none is refused. 1 rehearses a client's retry.
    arm_refusals_after_boot: int = 0
    # How a body-rate command (SET_ATTITUDE_TARGET) shows in the measured rates, as measured
    # on PX4 main + SIH: a dead time (the onboard link, uORB, the loops' scheduling, the
    # motors spinning up), then a first-order lag (PX4's rate loop and SIH's motors). The
    # dead time delays every offboard setpoint inside the autopilot (by this minus the
    # vehicle's motor_time_constant_s, which the physics adds), so quaternion and position
    # setpoints see it too; the lag is the rate loop's closed-loop time constant, for the
    # attitude controller's rate setpoints as well. 0 and 0: the setpoint acts at once and
    # the rate loop is as stiff as its gains make it.
    rate_dead_time_s: float = 0.045
    rate_time_constant_s: float = 0.1
    # A quaternion setpoint (with its thrust) waits this much longer than a body-rate one
    # before PX4's attitude loop flies it: PX4 main + SIH answered the service's quaternion
    # setpoints with 0.14-0.15 s of dead time and a 0.13-0.15 s lag (0.28-0.30 s together;
    # commanded against ground-truth roll and pitch over circles and figure-8s), this
    # personality without it with 0.05 s and 0.13 s
    attitude_setpoint_extra_delay_s: float = 0.1
    # PX4 delivers ATTITUDE_QUATERNION at about 123 Hz however high SET_MESSAGE_INTERVAL
    # asks (and acknowledges the request as accepted); 0: as fast as asked
    attitude_quaternion_max_hz: float = 123.0

    def __post_init__(self) -> None:
        _positive(
            tilt_max_deg=self.tilt_max_deg,
            takeoff_altitude_m=self.takeoff_altitude_m,
            climb_speed_m_s=self.climb_speed_m_s,
            land_speed_m_s=self.land_speed_m_s,
            offboard_loss_timeout_s=self.offboard_loss_timeout_s,
            offboard_min_rate_hz=self.offboard_min_rate_hz,
            disarm_preflight_s=self.disarm_preflight_s,
            disarm_after_land_s=self.disarm_after_land_s,
        )
        if self.arm_refusals_after_boot < 0:
            raise ValueError("arm_refusals_after_boot must be >= 0")
        _non_negative(
            rate_dead_time_s=self.rate_dead_time_s,
            rate_time_constant_s=self.rate_time_constant_s,
            takeoff_hold_short_m=self.takeoff_hold_short_m,
            attitude_quaternion_max_hz=self.attitude_quaternion_max_hz,
            attitude_setpoint_extra_delay_s=self.attitude_setpoint_extra_delay_s,
        )
        if self.attitude_setpoint_extra_delay_s > 0.5:
            raise ValueError("attitude_setpoint_extra_delay_s must be <= 0.5")
        if self.rate_dead_time_s > 0.5 or self.rate_time_constant_s > 1.0:
            raise ValueError(
                "rate_dead_time_s must be <= 0.5 and rate_time_constant_s <= 1.0 "
                f"(no autopilot flies with {self.rate_dead_time_s} s, "
                f"{self.rate_time_constant_s} s)"
            )

    # The motors' lag sits between the rate loop and the measured rates. A step through it
    # and the rate loop's reference lag fits as about one motor time constant more dead time
    # and one less lag (the feedforward catches up); so each piece is set apart by it, and
    # the fit (tests/sitl/identify.py) returns the configured figures within a few ms.

    def setpoint_delay_s(self, vehicle: VehicleParams) -> float:
        """How long an offboard setpoint waits inside the autopilot: the dead time less what
        the motors' lag adds to it (never negative; SimConfig rejects a shorter dead time)."""
        if self.rate_dead_time_s <= 0.0:
            return 0.0
        return max(0.0, self.rate_dead_time_s - vehicle.motor_time_constant_s)

    def rate_reference_time_constant_s(self, vehicle: VehicleParams) -> float:
        """The time constant of the rate loop's reference model (0: none)."""
        if self.rate_time_constant_s <= 0.0:
            return 0.0
        return self.rate_time_constant_s + vehicle.motor_time_constant_s


@dataclass(frozen=True)
class ArduPilotParams:
    """The ArduCopter personality's parameters, under their ArduPilot names (PARAM_SET /
    PARAM_REQUEST_READ reach them by those names; ``--param NAME=VALUE`` sets them at start,
    as ArduPilot SITL's ``--defaults`` file does). Defaults are ArduCopter's."""

    guid_options: int = 0  # GUID_OPTIONS; bit 3 (8): SET_ATTITUDE_TARGET thrust is throttle
    guid_timeout_s: float = 3.0  # GUID_TIMEOUT: setpoints lost this long -> hold position
    input_tc_s: float = 0.15  # ATC_INPUT_TC: time constant of the attitude input shaping
    # PILOT_Y_RATE_TC: the yaw axis's shaping time constant; 0 (the default) shapes over ten
    # main-loop periods (SCHED_LOOP_RATE, 400 Hz in SITL: 25 ms)
    yaw_rate_tc_s: float = 0.0
    loop_rate_hz: float = 400.0  # SCHED_LOOP_RATE
    wp_speed_up_m_s: float = 2.5  # WP_SPD_UP (WPNAV_SPEED_UP before 4.7): climb at thrust 1
    wp_speed_dn_m_s: float = 1.5  # WP_SPD_DN: descent rate at thrust 0 (climb-rate mode)
    disarm_delay_s: float = 10.0  # DISARM_DELAY: armed on the ground, not flying
    # The pilot's throttle stick (0..1; ArduCopter SITL's simulated RC sits at the bottom).
    # LOITER's climb rate follows it (outside THR_DZ of mid stick) up to PILOT_SPD_UP /
    # PILOT_SPD_DN (0: PILOT_SPD_UP's): at the bottom LOITER descends at 2.5 m/s, as the
    # real SITL did (it hit the ground at 2.49 m/s). BRAKE ignores the sticks.
    rc_throttle_norm: float = 0.0
    throttle_deadzone_norm: float = 0.1  # THR_DZ (100 of 1000)
    pilot_speed_up_m_s: float = 2.5  # PILOT_SPD_UP
    pilot_speed_dn_m_s: float = 0.0  # PILOT_SPD_DN
    # No LOCAL_POSITION_NED until the EKF has an origin: ArduCopter 4.8-dev SITL took about
    # 36 s after boot (lockstep: vehicle time, so it costs a few seconds of wall clock)
    ekf_origin_after_boot_s: float = 36.0
    # ATC_ACC_R_MAX, _P_MAX, _Y_MAX (1100, 1100, 270 deg/s^2; ATC_ACCEL_*_MAX in centidegrees
    # before 4.7): the input shaping's limit on the target's angular acceleration, its jerk
    # limited to that over the axis's time constant
    accel_max_frd_rad_s2: tuple[float, float, float] = (19.2, 19.2, 4.7)
    # ATC_ANG_RLL_P, _PIT_P, _YAW_P (4.5 1/s): P on the error to the attitude target that
    # body-rate commands turn (the quaternion path keeps the cascade's attitude_p_1_s, which
    # its fit to the real ArduCopter's quaternion answer was made with)
    # Yaw's 1.5, not ATC_ANG_YAW_P's 4.5: the real ArduCopter's yaw (20 s multi-sine, 0.3-2.1
    # Hz) fits best, 0.015 rad/s rms, as this chain (P 5, FLTE 2.5 Hz, 20-30 ms of delay)
    # with 1.5 on the angle error; with 4.5 the best is 0.072 (a resonance at 0.7 Hz of gain
    # 2.3 the real one, 1.24, does not have). What lowers it in ArduCopter is not found
    rate_angle_p_1_s: tuple[float, float, float] = (4.5, 4.5, 1.5)
    # The yaw rate loop, ArduCopter's (AC_AttitudeControl_Multi's yaw rate PID): why its yaw
    # answers so much later than roll and pitch. ATC_RAT_YAW_P 0.3 and _I 0.02 (the SITL's
    # copter.parm) are motor output per rad/s; the SITL quad (3 kg, 0.35 m) turns a unit of
    # yaw output into about 13 rad/s^2 (SIM_Motor's yaw torque, 0.05 x diagonal x thrust x
    # command, about Izz = m (d/2)^2 / 2): P about 4 1/s where roll's 0.135 gives this
    # personality's 25. Fitted to the real one's yaw (below): P 5.0, I 0.26 (0.02 x 13)
    rate_yaw_p_1_s: float = 5.0
    rate_yaw_i_1_s2: float = 0.26
    # ATC_RAT_RLL_FLTE, _PIT_FLTE, _YAW_FLTE (0, 0, 2.5 Hz): the rate PIDs' error filter (0:
    # none). Yaw's P and I act on the error through 2.5 Hz: a 64 ms lag inside the loop
    rate_error_filter_hz: tuple[float, float, float] = (0.0, 0.0, 2.5)
    # Every setpoint waits for ArduCopter's main loop to read it (its GCS input runs at the
    # loop rate): about a loop period, SCHED_LOOP_RATE's 2.5 ms
    setpoint_delay_s: float = 0.0025
    # ACRO_RP_RATE_TC: the time constant body-rate targets are shaped with (the command
    # model, ATC_ACC_*_MAX bounding the acceleration); 0, ArduCopter's default: ten main-loop
    # periods (25 ms). With it the personality answers body-rate doublets as ArduCopter
    # 4.8-dev SITL did within 15 ms (real: 25-35 ms dead time, 40 ms lag, gain 1.03; this:
    # 40-50 ms, 25-30 ms, 1.1). The old fit (a 0.4 s filter and 52.5 ms more delay, "best
    # match 200 ms later at 0.35 gain") is not what the real one does with commands inside
    # ATC_ACC_R_MAX; commands beyond it (the old service model's body-rate circle chattered
    # at 3-8 Hz, 65 rad/s^2 RMS) are slowed by that limit, which a linear fit reads as lag.
    rate_input_tc_s: float = 0.0
    # A further delay of body-rate setpoints (none measured beyond the main loop's read)
    rate_input_delay_s: float = 0.0
    # AC_PosControl (GUIDED's position control) and its defaults: P on position (PSC_POSXY_P,
    # PSC_POSZ_P), PID on velocity (PSC_VELXY_P/_I/_D; z: PSC_VELZ_P and the integral its
    # PSC_ACCZ_I gives), the target's acceleration fed forward, jerk-limited (PSC_JERK_XY/_Z)
    psc_pos_p_1_s: tuple[float, float, float] = (1.0, 1.0, 1.0)
    psc_vel_p_1_s: tuple[float, float, float] = (2.0, 2.0, 5.0)
    psc_vel_i_1_s2: tuple[float, float, float] = (1.0, 1.0, 2.0)
    psc_vel_d: tuple[float, float, float] = (0.5, 0.5, 0.0)
    psc_vel_d_filter_hz: float = 5.0
    # PSC_VELXY_FF / the z one: velocity target fed forward as acceleration. ArduCopter ships
    # 0; tuned here to the default airframe's drag (SIH's: 1 m/s^2 per m/s), which is what
    # lets GUIDED fly the circle as accurately as the real ArduCopter flies it on its own
    psc_vel_ff_1_s: tuple[float, float, float] = (1.0, 1.0, 0.0)
    psc_jerk_m_s3: tuple[float, float, float] = (5.0, 5.0, 5.0)

    def __post_init__(self) -> None:
        _positive(
            guid_timeout_s=self.guid_timeout_s,
            input_tc_s=self.input_tc_s,
            wp_speed_up_m_s=self.wp_speed_up_m_s,
            wp_speed_dn_m_s=self.wp_speed_dn_m_s,
            loop_rate_hz=self.loop_rate_hz,
            disarm_delay_s=self.disarm_delay_s,
        )
        _positive(pilot_speed_up_m_s=self.pilot_speed_up_m_s)
        _non_negative(
            pilot_speed_dn_m_s=self.pilot_speed_dn_m_s,
            ekf_origin_after_boot_s=self.ekf_origin_after_boot_s,
            setpoint_delay_s=self.setpoint_delay_s,
            rate_input_delay_s=self.rate_input_delay_s,
            yaw_rate_tc_s=self.yaw_rate_tc_s,
        )
        _non_negative(rate_input_tc_s=self.rate_input_tc_s)
        _positive(psc_vel_d_filter_hz=self.psc_vel_d_filter_hz)
        for name in ("psc_pos_p_1_s", "psc_vel_p_1_s", "psc_jerk_m_s3"):
            for i, v in enumerate(getattr(self, name)):
                _positive(**{f"{name}[{i}]": v})
        for name in ("psc_vel_i_1_s2", "psc_vel_d", "psc_vel_ff_1_s"):
            for i, v in enumerate(getattr(self, name)):
                _non_negative(**{f"{name}[{i}]": v})
        for i, v in enumerate(self.accel_max_frd_rad_s2):
            _positive(**{f"accel_max_frd_rad_s2[{i}]": v})
        for i, v in enumerate(self.rate_angle_p_1_s):
            _non_negative(**{f"rate_angle_p_1_s[{i}]": v})
        for i, v in enumerate(self.rate_error_filter_hz):
            _non_negative(**{f"rate_error_filter_hz[{i}]": v})
        _positive(rate_yaw_p_1_s=self.rate_yaw_p_1_s)
        _non_negative(rate_yaw_i_1_s2=self.rate_yaw_i_1_s2)
        for name in ("setpoint_delay_s", "rate_input_delay_s"):
            if getattr(self, name) > 0.5:
                raise ValueError(f"{name} must be <= 0.5, got {getattr(self, name)}")
        if not (0.0 <= self.rc_throttle_norm <= 1.0 and 0.0 <= self.throttle_deadzone_norm < 0.5):
            raise ValueError("rc_throttle_norm must be in 0..1, throttle_deadzone_norm in 0..0.5")
        if not 0 <= self.guid_options < 2**16:
            raise ValueError(f"guid_options must be in 0..65535, got {self.guid_options}")


@dataclass(frozen=True)
class NoiseParams:
    """Standard deviations of the seeded Gaussian noise on the published state estimate.

    ``correlation_time_s`` 0: white, a new draw for every estimate published. > 0: an
    estimator's error, which is smooth: each channel a first-order Gauss-Markov process of
    that time constant (stationary standard deviation as given), advanced once per tick.
    """

    position_std_m: float = 0.005
    velocity_std_m_s: float = 0.01
    attitude_std_rad: float = 0.002
    rate_std_rad_s: float = 0.005
    correlation_time_s: float = 0.0

    def __post_init__(self) -> None:
        _non_negative(
            position_std_m=self.position_std_m,
            velocity_std_m_s=self.velocity_std_m_s,
            attitude_std_rad=self.attitude_std_rad,
            rate_std_rad_s=self.rate_std_rad_s,
            correlation_time_s=self.correlation_time_s,
        )


@dataclass(frozen=True)
class TelemetryRates:
    """Default stream rates (Hz, 0 = off); SET_MESSAGE_INTERVAL changes them at run time.

    The defaults are PX4's on its onboard link: the 100/200 Hz loops must ask for more.
    """

    heartbeat_hz: float = 1.0
    sys_status_hz: float = 5.0
    extended_sys_state_hz: float = 5.0
    attitude_hz: float = 100.0
    attitude_quaternion_hz: float = 50.0
    local_position_ned_hz: float = 30.0
    odometry_hz: float = 30.0
    global_position_int_hz: float = 50.0
    home_position_hz: float = 0.5
    attitude_target_hz: float = 50.0
    # 0 by default; a lockstep controller asks for it at its fastest loop's rate: each one is
    # a tick of the vehicle's clock it answers (sitl/lockstep.py), as the wall clock ticks in
    # real time between the state messages
    system_time_hz: float = 0.0

    def __post_init__(self) -> None:
        for name, value in vars(self).items():
            _non_negative(**{name: value})


@dataclass(frozen=True)
class SitlParams:
    """Simulation clock, lockstep protocol and link behaviour."""

    physics_rate_hz: float = 1000.0
    lockstep_period_s: float = 0.005
    # Lockstep waits this long (wall clock) for the controller's answer to a tick; it is a
    # last resort (a controller gone), counted and reported, never part of a normal run.
    lockstep_timeout_s: float = 2.0
    # consecutive timeouts before falling back to real time: 90 s, longer than the service
    # ever waits itself in lockstep (its miss worker, miss_solver.WAIT_TIMEOUT_S = 30 s); 3
    # (6 s) fell back in the middle of flights beside CPU hogs (stop 41, lock-load)
    lockstep_max_timeouts: int = 45
    # ... and once the controller has handed the vehicle back (a mode request out of offboard:
    # the service's HOLD at its stop, a LAND): 1 (2 s). A service that asked for HOLD and
    # exited left the vehicle waiting 90 s; a landing's answers still come every tick
    lockstep_left_max_timeouts: int = 1
    autopilot: str = "px4"  # the personality: what the autopilot does and says
    # Home: where local NED's origin sits on the globe (PX4 SITL's default, Zurich)
    home_lat_deg: float = 47.397742
    home_lon_deg: float = 8.545594
    home_amsl_m: float = 488.0
    groundtruth_flush_s: float = 1.0  # wall clock
    allowed_source_sysids: tuple[int, ...] = ()  # empty: any
    # The published state is the vehicle's this long ago (the estimator's and the link's
    # latency), stamped when it is sent: a whole number of lockstep periods; 0: the current
    telemetry_delay_s: float = 0.0
    telemetry: TelemetryRates = field(default_factory=TelemetryRates)
    noise: NoiseParams = field(default_factory=NoiseParams)

    def __post_init__(self) -> None:
        _positive(
            physics_rate_hz=self.physics_rate_hz,
            lockstep_period_s=self.lockstep_period_s,
            lockstep_timeout_s=self.lockstep_timeout_s,
            groundtruth_flush_s=self.groundtruth_flush_s,
        )
        if self.physics_rate_hz < 500.0:
            raise ValueError(f"physics_rate_hz must be >= 500, got {self.physics_rate_hz}")
        if self.autopilot not in AUTOPILOTS:
            known = ", ".join(sorted(AUTOPILOTS))
            raise ValueError(f"autopilot must be one of {known}, got {self.autopilot!r}")
        if not (abs(self.home_lat_deg) <= 90.0 and abs(self.home_lon_deg) <= 180.0):
            raise ValueError(f"home ({self.home_lat_deg}, {self.home_lon_deg}) is not on Earth")
        if self.lockstep_max_timeouts < 1:
            raise ValueError("lockstep_max_timeouts must be >= 1")
        if self.lockstep_left_max_timeouts < 1:
            raise ValueError("lockstep_left_max_timeouts must be >= 1")
        _non_negative(telemetry_delay_s=self.telemetry_delay_s)
        delay_ticks = self.telemetry_delay_s / self.lockstep_period_s
        if abs(delay_ticks - round(delay_ticks)) > 1e-9 or self.telemetry_delay_s > 0.5:
            raise ValueError(
                "telemetry_delay_s must be a whole number of lockstep periods, <= 0.5 s "
                f"(got {self.telemetry_delay_s} s at a period of {self.lockstep_period_s} s)"
            )
        substeps = self.lockstep_period_s * self.physics_rate_hz
        if abs(substeps - round(substeps)) > 1e-9 or round(substeps) < 1:
            raise ValueError(
                "lockstep_period_s must be a whole number of physics steps "
                f"(period {self.lockstep_period_s} s at {self.physics_rate_hz} Hz)"
            )

    @property
    def physics_steps_per_tick(self) -> int:
        return round(self.lockstep_period_s * self.physics_rate_hz)

    @property
    def telemetry_delay_ticks(self) -> int:
        return round(self.telemetry_delay_s / self.lockstep_period_s)


@dataclass(frozen=True)
class SimConfig:
    vehicle: VehicleParams
    environment: EnvironmentParams = field(default_factory=EnvironmentParams)
    autopilot: AutopilotParams = field(default_factory=AutopilotParams)
    sitl: SitlParams = field(default_factory=SitlParams)
    ardupilot: ArduPilotParams = field(default_factory=ArduPilotParams)
    # what the offboard service may command this airframe to do (the service reads it from
    # this same file; the SITL's own autopilot keeps its limits in [autopilot])
    envelope: AirframeEnvelope = field(default_factory=AirframeEnvelope)

    def __post_init__(self) -> None:
        dead_s, motor_s = self.autopilot.rate_dead_time_s, self.vehicle.motor_time_constant_s
        if 0.0 < dead_s < motor_s:
            raise ValueError(
                f"autopilot.rate_dead_time_s ({dead_s} s) is shorter than the motors' lag "
                f"alone (vehicle.motor_time_constant_s = {motor_s} s): use 0 or >= {motor_s}"
            )


def load_sim_config(
    path: str | Path | None = None, overrides: dict[str, Any] | None = None
) -> SimConfig:
    """Load a vehicle file (default: the packaged 1.5 kg x-quad) with ``overrides`` on top."""
    return load_config(SimConfig, path or DEFAULT_VEHICLE_FILE, overrides)
