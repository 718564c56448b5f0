"""Quadrotor rigid-body dynamics (thesis 3.2) and its environment: pure numerics, no I/O.

The thesis writes its world frame z-up and thrust along +z_B. Internally everything is NED/FRD
(``epc_offboard.frames``), so, converted once:

  (3.9)   m dv/dt = [0, 0, m g] + R(q) ([0, 0, -sum F_i] + f_drag)          (NED, FRD)
  (3.10)  I dw/dt = tau(F, M) - w x (I w)                                    (FRD)
          F_i = k_F w_i^2,  M_i = k_M w_i^2
          tau = sum_i r_i x [0, 0, -F_i] + [0, 0, sum_i s_i M_i]
              = [sum -y_i F_i, sum x_i F_i, sum s_i M_i]
  rotor:  d w_i/dt = (w_cmd_i - w_i) / tau_motor,  w_cmd clamped to [0, w_max]
  drag:   f_drag = -D R(q)^T (v - v_wind)       (relative airspeed, body axes, linear)
  kinematics: dq/dt = 1/2 q (x) [0, w]

For the thesis's plus layout (rotor 2 left, 4 right at distance L) the roll row is L (F_2 - F_4),
its eq. 3.10; the x layout is the same law with the rotors at 45 degrees.

State vector (NX = 17): pos_ned_m(3), vel_ned_m_s(3), q_wxyz(4), rate_frd_rad_s(3),
rotor_speed_rad_s(4). Integrated by classical RK4; the quaternion is renormalised after each
step. The ground is the plane down = 0 (home altitude): an inelastic contact.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from epc_offboard.frames import GRAVITY_M_S2, FloatArray, quat_to_rotation, wind_vector_ned_m_s
from sitl.params import EnvironmentParams, VehicleParams

NX = 17
POS = slice(0, 3)
VEL = slice(3, 6)
QUAT = slice(6, 10)
RATE = slice(10, 13)
ROTOR = slice(13, 17)


def cross3(a: FloatArray, b: FloatArray) -> FloatArray:
    """Cross product of two (3,) vectors; np.cross costs ten times more on tiny arrays."""
    a0, a1, a2 = a
    b0, b1, b2 = b
    return np.array([a1 * b2 - a2 * b1, a2 * b0 - a0 * b2, a0 * b1 - a1 * b0])


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
    """Equations of motion of one vehicle; ``step`` advances the 17-state by RK4."""

    def __init__(self, params: VehicleParams) -> None:
        self.params = params
        self._inertia_diag = np.asarray(params.inertia_diag_kg_m2, dtype=np.float64)
        self._mix = effectiveness_matrix(params)
        # Rows 1..3 of the effectiveness matrix give the torque from forces F_i.
        self._torque_of_force = self._mix[1:, :]
        self._drag = np.asarray(params.drag_coeff_body_n_s_m, dtype=np.float64)
        self._gravity = np.array([0.0, 0.0, GRAVITY_M_S2])

    def derivative(
        self,
        x: FloatArray,
        rotor_cmd_rad_s: FloatArray,
        wind_ned_m_s: FloatArray,
        ext_force_ned_n: FloatArray,
    ) -> FloatArray:
        """dx/dt (17,) for state ``x`` (17,), rotor commands (4,), wind and external force (3,)."""
        p = self.params
        dx = np.empty(NX)
        R = quat_to_rotation(x[QUAT])
        omega = x[ROTOR]
        forces = p.k_f_n_s2 * omega * omega
        f_body = -self._drag * (R.T @ (x[VEL] - wind_ned_m_s))
        f_body[2] -= forces.sum()
        dx[POS] = x[VEL]
        dx[VEL] = self._gravity + (R @ f_body + ext_force_ned_n) / p.mass_kg
        w = x[RATE]
        inertia = self._inertia_diag
        dx[RATE] = (self._torque_of_force @ forces - cross3(w, inertia * w)) / inertia
        qw, qx, qy, qz = x[QUAT]
        wx, wy, wz = w
        dx[QUAT] = (
            0.5 * (-qx * wx - qy * wy - qz * wz),
            0.5 * (qw * wx + qy * wz - qz * wy),
            0.5 * (qw * wy - qx * wz + qz * wx),
            0.5 * (qw * wz + qx * wy - qy * wx),
        )
        dx[ROTOR] = (rotor_cmd_rad_s - omega) / p.motor_time_constant_s
        return dx

    def step(
        self,
        x: FloatArray,
        rotor_cmd_rad_s: FloatArray,
        wind_ned_m_s: FloatArray,
        ext_force_ned_n: FloatArray,
        dt_s: float,
    ) -> FloatArray:
        """One RK4 step of ``dt_s`` with inputs held; returns the new state (17,)."""
        u = np.clip(rotor_cmd_rad_s, 0.0, self.params.rotor_speed_max_rad_s)
        k1 = self.derivative(x, u, wind_ned_m_s, ext_force_ned_n)
        k2 = self.derivative(x + 0.5 * dt_s * k1, u, wind_ned_m_s, ext_force_ned_n)
        k3 = self.derivative(x + 0.5 * dt_s * k2, u, wind_ned_m_s, ext_force_ned_n)
        k4 = self.derivative(x + dt_s * k3, u, wind_ned_m_s, ext_force_ned_n)
        x_new = x + (dt_s / 6.0) * (k1 + 2.0 * k2 + 2.0 * k3 + k4)
        x_new[QUAT] /= np.linalg.norm(x_new[QUAT])
        if x_new[2] > 0.0:
            x_new = _ground_contact(x, x_new)
        return x_new


def on_ground(x: FloatArray) -> bool:
    """True while the vehicle rests on the ground plane (down >= 0)."""
    return bool(x[2] >= 0.0)


def _ground_contact(x_old: FloatArray, x_new: FloatArray) -> FloatArray:
    """Inelastic ground: no penetration, no sliding, no rotation; the vehicle sits level."""
    out = x_new.copy()
    out[0:2] = x_old[0:2]
    out[2] = 0.0
    out[VEL] = 0.0
    out[RATE] = 0.0
    qw, qx, qy, qz = x_new[QUAT]
    yaw = math.atan2(2 * (qw * qz + qx * qy), 1 - 2 * (qy * qy + qz * qz))
    out[QUAT] = [math.cos(yaw / 2), 0.0, 0.0, math.sin(yaw / 2)]
    return out


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
        s = self.params.surface
        self._surface_point = np.asarray(s.point_ned_m, dtype=np.float64)
        self._surface_normal = np.asarray(s.normal_ned, dtype=np.float64)

    @property
    def wind_ned_m_s(self) -> FloatArray:
        return self.mean_wind_ned_m_s + self.gust_ned_m_s

    def advance(self, dt_s: float) -> None:
        """Exact discretisation of the first-order Gauss-Markov gust process."""
        std = self.params.gust_std_m_s
        if std == 0.0:
            return
        a = math.exp(-dt_s / self.params.gust_time_constant_s)
        sigma = std * np.array([1.0, 1.0, 0.5])
        self.gust_ned_m_s = a * self.gust_ned_m_s + sigma * math.sqrt(1 - a * a) * (
            self.rng.standard_normal(3)
        )

    def surface_force_ned_n(self, pos_ned_m: FloatArray) -> FloatArray:
        """Pull towards the surface, growing exponentially as the vehicle gets closer."""
        s = self.params.surface
        if not s.enabled:
            return np.zeros(3)
        distance_m = float(self._surface_normal @ (pos_ned_m - self._surface_point))
        if distance_m < 0.0 or distance_m > s.range_m:
            return np.zeros(3)
        magnitude = s.peak_force_n * math.exp(-distance_m / s.decay_length_m)
        magnitude *= max(0.0, 1.0 + s.fluctuation_rel * float(self.rng.standard_normal()))
        return -magnitude * self._surface_normal
