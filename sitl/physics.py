"""Quadrotor rigid-body dynamics (thesis 3.2) and its environment: pure numerics, no I/O.

The thesis writes its world frame z-up and thrust along +z_B. Internally everything is NED/FRD
(``epc_offboard.common.frames``), so, converted once:

  (3.9)   m dv/dt = [0, 0, m g] + R(q) ([0, 0, -sum F_i] + f_drag)          (NED, FRD)
  (3.10)  I dw/dt = tau(F, M) - w x (I w)                                    (FRD)
          F_i = k_F w_i^2,  M_i = k_M w_i^2
          tau = sum_i r_i x [0, 0, -F_i] + [0, 0, sum_i s_i M_i]
              = [sum -y_i F_i, sum x_i F_i, sum s_i M_i]
  rotor:  d w_i/dt = (w_cmd_i - w_i) / tau_motor,  w_cmd clamped to [0, w_max]
  drag:   f_drag = -D R(q)^T (v - v_wind)       (relative airspeed, body axes, linear)
  aero (VehicleParams.aerodynamic; off by default), on v_a = R(q)^T (v - v_wind):
          f_aero = -|v_a| C_D (.) v_a - (sum_i w_i) K (.) v_a
          quadratic body drag C_D, rotor drag K_x, K_y and the rotors' inflow K_z (rotorpy)
  kinematics: dq/dt = 1/2 q (x) [0, w]

For the thesis's plus layout (rotor 2 left, 4 right at distance L) the roll row is L (F_2 - F_4),
its eq. 3.10; the x layout is the same law with the rotors at 45 degrees.

State vector (NX = 17): pos_ned_m(3), vel_ned_m_s(3), q_wxyz(4), rate_frd_rad_s(3),
rotor_speed_rad_s(4). Integrated by classical RK4; the quaternion is renormalised after each
step. The ground is the plane down = 0 (home altitude): an inelastic contact.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from epc_offboard.common.frames import GRAVITY_M_S2, FloatArray, wind_vector_ned_m_s
from sitl.params import EnvironmentParams, VehicleParams

NX = 17
POS = slice(0, 3)
VEL = slice(3, 6)
QUAT = slice(6, 10)
RATE = slice(10, 13)
ROTOR = slice(13, 17)


def initial_state(pos_ned_m: tuple[float, float, float] = (0.0, 0.0, 0.0)) -> FloatArray:
    """Vehicle at rest, level, yaw north, rotors stopped."""
    x = np.zeros(NX)
    x[POS] = pos_ned_m
    x[6] = 1.0
    return x


def rotor_geometry(p: VehicleParams) -> tuple[FloatArray, FloatArray]:
    """Rotor positions (4, 3) in FRD metres and yaw moment signs (4,)."""
    ang = np.radians(np.asarray(p.rotor_angles_deg))
    pos = np.stack([p.arm_length_m * np.cos(ang), p.arm_length_m * np.sin(ang), np.zeros(4)], 1)
    return pos, np.asarray(p.rotor_yaw_moment_sign, dtype=np.float64)


def effectiveness_matrix(p: VehicleParams) -> FloatArray:
    """(4, 4) map from rotor forces F_i [N] to [collective thrust N, tau_x, tau_y, tau_z N m]."""
    pos, sign = rotor_geometry(p)
    return np.vstack([np.ones(4), -pos[:, 1], pos[:, 0], sign * p.k_m_n_m_s2 / p.k_f_n_s2])


class QuadrotorModel:
    """Equations of motion of one vehicle; ``step`` advances the 17-state by RK4.

    The arithmetic is scalar Python on lists of floats: on 3- and 4-vectors it is several
    times cheaper than numpy calls, and the SITL runs it 1000 times a second per vehicle.
    ``step_list`` is the core (a tick's substeps chain it without array conversions);
    ``step`` and ``derivative`` are its array faces. Each operation is the one numpy did, in
    the same order, so the results are the same to the last bit.
    """

    def __init__(self, params: VehicleParams) -> None:
        self.params = params
        # Rows 1..3 of the effectiveness matrix give the torque from the rotor forces F_i.
        self._torque_of_force = [list(map(float, r)) for r in effectiveness_matrix(params)[1:]]
        self._rotor_speed_max_rad_s = float(params.rotor_speed_max_rad_s)
        # the parameters _rhs reads, unpacked once per call instead of looked up one by one
        self._rhs_params = (
            params.k_f_n_s2, *params.drag_coeff_body_n_s_m, params.mass_kg,
            *params.inertia_diag_kg_m2, params.motor_time_constant_s,
        )  # fmt: skip
        # None without them: the linear-drag equations, untouched to the last bit
        self._aero_params = (
            (*params.drag_quadratic_body_n_s2_m2, *params.rotor_drag_kg_rad)
            if params.aerodynamic
            else None
        )

    def derivative(
        self,
        x: FloatArray,
        rotor_cmd_rad_s: FloatArray,
        wind_ned_m_s: FloatArray,
        ext_force_ned_n: FloatArray,
    ) -> FloatArray:
        """dx/dt (17,) for state ``x`` (17,), rotor commands (4,), wind and external force (3,)."""
        return np.array(
            self._rhs(
                x.tolist(), rotor_cmd_rad_s.tolist(), wind_ned_m_s.tolist(),
                ext_force_ned_n.tolist(),
            )
        )  # fmt: skip

    def _rhs(
        self, x: Sequence[float], u: Sequence[float], wind: Sequence[float], ext: Sequence[float]
    ) -> list[float]:
        kf, dx_, dy_, dz_, m, ix, iy, iz, tau_m = self._rhs_params
        _, _, _, vn, ve, vd, qw, qx, qy, qz, wx, wy, wz, o1, o2, o3, o4 = x
        # R(q), body FRD -> world NED (frames.quat_to_rotation, written out)
        r00, r01, r02 = (
            1 - 2 * (qy * qy + qz * qz),
            2 * (qx * qy - qw * qz),
            2 * (qx * qz + qw * qy),
        )
        r10, r11, r12 = (
            2 * (qx * qy + qw * qz),
            1 - 2 * (qx * qx + qz * qz),
            2 * (qy * qz - qw * qx),
        )
        r20, r21, r22 = (
            2 * (qx * qz - qw * qy),
            2 * (qy * qz + qw * qx),
            1 - 2 * (qx * qx + qy * qy),
        )
        f1, f2, f3, f4 = kf * o1 * o1, kf * o2 * o2, kf * o3 * o3, kf * o4 * o4
        # f_body = -D R^T (v - v_wind) + [0, 0, -sum F]
        an, ae, ad = vn - wind[0], ve - wind[1], vd - wind[2]
        ux, uy, uz = r00 * an + r10 * ae + r20 * ad, r01 * an + r11 * ae + r21 * ad, (
            r02 * an + r12 * ae + r22 * ad)  # fmt: skip
        bx = -dx_ * ux
        by = -dy_ * uy
        bz = -dz_ * uz - (f1 + f2 + f3 + f4)
        if self._aero_params is not None:
            cx, cy, cz, kx, ky, kz = self._aero_params
            speed = math.sqrt(ux * ux + uy * uy + uz * uz)
            rotors = o1 + o2 + o3 + o4
            bx -= (cx * speed + kx * rotors) * ux
            by -= (cy * speed + ky * rotors) * uy
            bz -= (cz * speed + kz * rotors) * uz
        # (3.9) in NED: dv/dt = g e_d + (R f_body + f_ext) / m
        acc_n = (r00 * bx + r01 * by + r02 * bz + ext[0]) / m
        acc_e = (r10 * bx + r11 * by + r12 * bz + ext[1]) / m
        acc_d = (r20 * bx + r21 * by + r22 * bz + ext[2]) / m + GRAVITY_M_S2
        # (3.10): I dw/dt = tau - w x (I w), I diagonal
        (ax1, ax2, ax3, ax4), (ay1, ay2, ay3, ay4), (az1, az2, az3, az4) = self._torque_of_force
        tx = ax1 * f1 + ax2 * f2 + ax3 * f3 + ax4 * f4
        ty = ay1 * f1 + ay2 * f2 + ay3 * f3 + ay4 * f4
        tz = az1 * f1 + az2 * f2 + az3 * f3 + az4 * f4
        hx, hy, hz = ix * wx, iy * wy, iz * wz
        return [
            vn,
            ve,
            vd,
            acc_n,
            acc_e,
            acc_d,
            0.5 * (-qx * wx - qy * wy - qz * wz),  # dq/dt = 1/2 q (x) [0, w]
            0.5 * (qw * wx + qy * wz - qz * wy),
            0.5 * (qw * wy - qx * wz + qz * wx),
            0.5 * (qw * wz + qx * wy - qy * wx),
            (tx - (wy * hz - wz * hy)) / ix,
            (ty - (wz * hx - wx * hz)) / iy,
            (tz - (wx * hy - wy * hx)) / iz,
            (u[0] - o1) / tau_m,  # first-order motor lag
            (u[1] - o2) / tau_m,
            (u[2] - o3) / tau_m,
            (u[3] - o4) / tau_m,
        ]

    def step(
        self,
        x: FloatArray,
        rotor_cmd_rad_s: FloatArray,
        wind_ned_m_s: FloatArray,
        ext_force_ned_n: FloatArray,
        dt_s: float,
    ) -> FloatArray:
        """One RK4 step of ``dt_s`` with inputs held; returns the new state (17,)."""
        return np.array(
            self.step_list(
                x.tolist(), rotor_cmd_rad_s.tolist(), wind_ned_m_s.tolist(),
                ext_force_ned_n.tolist(), dt_s,
            )
        )  # fmt: skip

    def step_list(
        self,
        x: list[float],
        rotor_cmd_rad_s: Sequence[float],
        wind_ned_m_s: Sequence[float],
        ext_force_ned_n: Sequence[float],
        dt_s: float,
    ) -> list[float]:
        """:meth:`step` on plain lists: state (17,), rotor commands (4,), wind, force (3,)."""
        w_max = self._rotor_speed_max_rad_s
        u = [min(max(w, 0.0), w_max) for w in rotor_cmd_rad_s]  # np.clip(w, 0, w_max)
        wind, ext, rhs = wind_ned_m_s, ext_force_ned_n, self._rhs
        half_dt_s = 0.5 * dt_s
        k1 = rhs(x, u, wind, ext)
        k2 = rhs([a + half_dt_s * k for a, k in zip(x, k1, strict=True)], u, wind, ext)
        k3 = rhs([a + half_dt_s * k for a, k in zip(x, k2, strict=True)], u, wind, ext)
        k4 = rhs([a + dt_s * k for a, k in zip(x, k3, strict=True)], u, wind, ext)
        sixth_dt_s = dt_s / 6.0
        x_new = [
            a + sixth_dt_s * (b1 + 2.0 * b2 + 2.0 * b3 + b4)
            for a, b1, b2, b3, b4 in zip(x, k1, k2, k3, k4, strict=True)
        ]
        qw, qx, qy, qz = x_new[QUAT]
        norm = math.sqrt(qw * qw + qx * qx + qy * qy + qz * qz)
        x_new[QUAT] = [qw / norm, qx / norm, qy / norm, qz / norm]
        if x_new[2] > 0.0:
            _ground_contact(x, x_new)
        return x_new


def on_ground(x: FloatArray) -> bool:
    """True while the vehicle rests on the ground plane (down >= 0)."""
    return bool(x[2] >= 0.0)


def _ground_contact(x_old: list[float], x_new: list[float]) -> None:
    """Inelastic ground, in place on ``x_new``: no penetration, no sliding, no rotation; the
    vehicle sits level."""
    x_new[0:2] = x_old[0:2]
    x_new[2] = 0.0
    x_new[VEL] = [0.0, 0.0, 0.0]
    x_new[RATE] = [0.0, 0.0, 0.0]
    qw, qx, qy, qz = x_new[QUAT]
    yaw = math.atan2(2 * (qw * qz + qx * qy), 1 - 2 * (qy * qy + qz * qz))
    x_new[QUAT] = [math.cos(yaw / 2), 0.0, 0.0, math.sin(yaw / 2)]


@dataclass
class Environment:
    """Wind (mean + Gauss-Markov gusts) and the near-surface force, advanced once per step.

    Seeded: the same ``rng`` seed gives the same gust and surface-fluctuation sequences.
    """

    params: EnvironmentParams
    rng: np.random.Generator

    def __post_init__(self) -> None:
        self.mean_wind_ned_m_s = wind_vector_ned_m_s(
            self.params.wind_speed_m_s, self.params.wind_dir_deg
        )
        self.gust_ned_m_s = np.zeros(3)
        # the sinusoid's swing along the wind's direction, and the time it is evaluated at:
        # 0 until start_profile_clock() (the vehicle's offboard entry, sitl.simulation), so
        # the gust's phase against the trajectory is set, not the hand-over instant's
        self._sine_ned_m_s = wind_vector_ned_m_s(
            self.params.wind_sine_amplitude_m_s, self.params.wind_dir_deg
        )
        self._sine_on = self.params.wind_sine_amplitude_m_s > 0.0
        self._steps = 0
        self._origin_steps: int | None = None  # the step the profile's clock started at
        self._time_s = 0.0
        s = self.params.surface
        self._surface_point = np.asarray(s.point_ned_m, dtype=np.float64)
        self._surface_normal = np.asarray(s.normal_ned, dtype=np.float64)

    @property
    def wind_ned_m_s(self) -> FloatArray:
        if self._sine_on:
            p = self.params
            swing = math.sin(p.wind_sine_rate_rad_s * self._time_s + p.wind_sine_phase_rad)
            return self.mean_wind_ned_m_s + swing * self._sine_ned_m_s + self.gust_ned_m_s
        return self.mean_wind_ned_m_s + self.gust_ned_m_s

    @property
    def profile_time_s(self) -> float:
        """The time the sine profile is evaluated at: seconds since
        :meth:`start_profile_clock`, 0 before it."""
        return self._time_s

    def start_profile_clock(self) -> None:
        """Start the sine profile's time here (once: later calls keep the first origin)."""
        if self._origin_steps is None:
            self._origin_steps = self._steps

    def advance(self, dt_s: float) -> None:
        """Time for the sinusoid (steps since its origin x dt, no summed rounding); exact
        discretisation of the first-order Gauss-Markov gust process."""
        self._steps += 1
        if self._origin_steps is not None:
            self._time_s = (self._steps - self._origin_steps) * dt_s
        std = self.params.gust_std_m_s
        if std == 0.0:
            return
        a = math.exp(-dt_s / self.params.gust_time_constant_s)
        sigma = std * np.array([1.0, 1.0, 0.5])
        self.gust_ned_m_s = a * self.gust_ned_m_s + sigma * math.sqrt(1 - a * a) * (
            self.rng.standard_normal(3)
        )

    def surface_force_ned_n(self, pos_ned_m: FloatArray | Sequence[float]) -> FloatArray:
        """Pull towards the surface, growing exponentially as the vehicle gets closer."""
        s = self.params.surface
        if not s.enabled:
            return np.zeros(3)
        distance_m = float(self._surface_normal @ (np.asarray(pos_ned_m) - self._surface_point))
        if distance_m < 0.0 or distance_m > s.range_m:
            return np.zeros(3)
        magnitude = s.peak_force_n * math.exp(-distance_m / s.decay_length_m)
        magnitude *= max(0.0, 1.0 + s.fluctuation_rel * float(self.rng.standard_normal()))
        return -magnitude * self._surface_normal
