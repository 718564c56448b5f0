"""Affine prediction models of the two EPC loops and the acceleration <-> attitude map.

Every model is ``x[k+1] = A x[k] + B u[k] + c~`` with ``c~ = c + p^`` (thesis 3.1.2): ``c`` is
the model's own offset and ``p^`` the perturbation estimate supplied from outside (LWPR, a KF,
or zero). The prediction step ``dt_s`` is configuration and independent of the loop rate: a
100 Hz loop may predict over 20 steps of 0.05 s.

Frames follow :mod:`epc_offboard.common.frames`: world NED, body FRD, Z-Y-X Euler angles.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt
from scipy.linalg import expm

from epc_offboard.common import frames
from epc_offboard.common.errors import EpcError
from epc_offboard.common.frames import GRAVITY_M_S2, FloatArray

# Position loop: x = [p_ned_m(3), v_ned_m_s(3)], u = a_ned_m_s2(3), the desired acceleration
# relative to gravity compensation (u = 0 hovers).
POS_NX = 6  # p(3), v(3)
POS_NU = 3  # a(3)
# Position loop with the inner loop's lag: x = [p_ned_m(3), v_ned_m_s(3), a_ned_m_s2(3)], where
# a is the acceleration the attitude and thrust actually produce; u = the commanded acceleration.
POS_LAG_NX = 9  # p(3), v(3), a(3)
LAG_ACC_STATES = (6, 7, 8)  # where a(3) sits in the lagged model's state
# Attitude loop: x = [roll, pitch, yaw (rad), p, q, r (rad/s, body FRD)], u = body-rate command.
ATT_NX = 6  # roll, pitch, yaw, p, q, r
ATT_NU = 3  # p_cmd, q_cmd, r_cmd


class ModelError(EpcError, ValueError):
    """A model's matrices have inconsistent shapes or non-finite entries."""


@dataclass(frozen=True, eq=False)
class LinearModel:
    """``x[k+1] = A x[k] + B u[k] + c``; ``A`` (nx, nx), ``B`` (nx, nu), ``c`` (nx,).

    ``dt_s`` is the prediction step the matrices were discretised at (None when unknown);
    it is part of a problem's signature.
    """

    A: FloatArray
    B: FloatArray
    c: FloatArray
    dt_s: float | None

    def __init__(
        self,
        A: npt.ArrayLike,
        B: npt.ArrayLike,
        c: npt.ArrayLike | None = None,
        *,
        dt_s: float | None = None,
    ) -> None:
        a = np.array(A, dtype=np.float64)
        b = np.array(B, dtype=np.float64)
        if b.ndim == 1:
            b = b.reshape(-1, 1)
        if a.ndim != 2 or a.shape[0] != a.shape[1]:
            raise ModelError(f"A must be square (nx, nx), got shape {a.shape}")
        if b.ndim != 2 or b.shape[0] != a.shape[0]:
            raise ModelError(f"B must be (nx={a.shape[0]}, nu), got shape {b.shape}")
        cc = np.zeros(a.shape[0]) if c is None else np.array(c, dtype=np.float64).reshape(-1)
        if cc.shape != (a.shape[0],):
            raise ModelError(f"c must have shape ({a.shape[0]},), got {cc.shape}")
        for name, m in (("A", a), ("B", b), ("c", cc)):
            if not np.all(np.isfinite(m)):
                raise ModelError(f"{name} has non-finite entries")
            m.setflags(write=False)
        if dt_s is not None and not (math.isfinite(dt_s) and dt_s > 0.0):
            raise ModelError(f"dt_s must be > 0, got {dt_s}")
        object.__setattr__(self, "A", a)
        object.__setattr__(self, "B", b)
        object.__setattr__(self, "c", cc)
        object.__setattr__(self, "dt_s", dt_s)

    @property
    def nx(self) -> int:
        return int(self.A.shape[0])

    @property
    def nu(self) -> int:
        return int(self.B.shape[1])

    def step(
        self, x: npt.ArrayLike, u: npt.ArrayLike, perturbation: npt.ArrayLike | None = None
    ) -> FloatArray:
        """One prediction step ``A x + B u + c + p^``."""
        out: FloatArray = self.A @ np.asarray(x, dtype=np.float64) + self.B @ np.asarray(
            u, dtype=np.float64
        ) + self.c
        if perturbation is not None:
            out += np.asarray(perturbation, dtype=np.float64)
        return out

    def cancelling_input(self, perturbation: npt.ArrayLike) -> FloatArray:
        """Least-squares input ``u_p = -pinv(B) p^`` that cancels a perturbation."""
        pinv = np.asarray(np.linalg.pinv(self.B), dtype=np.float64)
        out: FloatArray = -pinv @ np.asarray(perturbation, dtype=np.float64)
        return out

    def with_offset(self, c: npt.ArrayLike) -> LinearModel:
        return LinearModel(self.A, self.B, c, dt_s=self.dt_s)


def zoh_discretize(
    Ac: npt.ArrayLike, Bc: npt.ArrayLike, dt_s: float
) -> tuple[FloatArray, FloatArray]:
    """Exact zero-order-hold discretisation of ``x' = Ac x + Bc u`` over ``dt_s``."""
    ac = np.asarray(Ac, dtype=np.float64)
    bc = np.asarray(Bc, dtype=np.float64)
    nx, nu = bc.shape
    blk = np.zeros((nx + nu, nx + nu))
    blk[:nx, :nx] = ac * dt_s
    blk[:nx, nx:] = bc * dt_s
    e = expm(blk)
    return np.array(e[:nx, :nx]), np.array(e[:nx, nx:])


def position_model(dt_s: float) -> LinearModel:
    """Translational double integrator in NED, ZOH at ``dt_s``.

    Continuous: ``p' = v``, ``v' = a`` (a: desired acceleration, gravity already compensated).
    Discrete (exact ZOH)::

        [p]+   [I  dt I] [p]   [dt²/2 I]
        [v]  = [0   I  ] [v] + [dt I   ] a
    """
    ac = np.zeros((POS_NX, POS_NX))
    ac[0:3, 3:6] = np.eye(3)
    bc = np.zeros((POS_NX, POS_NU))
    bc[3:6, :] = np.eye(3)
    A, B = zoh_discretize(ac, bc, dt_s)
    return LinearModel(A, B, dt_s=dt_s)


def position_model_lagged(dt_s: float, tau_acc_s: tuple[float, float, float]) -> LinearModel:
    """Position model with the inner loop's lag between commanded and achieved acceleration.

    The attitude loop (and, vertically, the motors) makes the achieved acceleration ``a``
    follow the command ``u`` with a first-order lag of time constant ``tau_acc_s[i]`` per
    NED axis, so x = [p, v, a] (9), u = a_cmd (3), ZOH at ``dt_s``::

        p' = v
        v' = a                      (+ the disturbance d, which enters through c~)
        a' = (u - a) / tau

    A double integrator driven directly by ``u`` would predict every acceleration (and so
    every velocity, which the state constraints bound) one inner-loop lag too early.
    """
    tau = np.asarray(tau_acc_s, dtype=np.float64)
    if tau.shape != (3,) or not np.all(np.isfinite(tau)) or np.any(tau <= 0.0):
        raise ModelError(f"tau_acc_s must be three values > 0, got {tau_acc_s}")
    ac = np.zeros((POS_LAG_NX, POS_LAG_NX))
    ac[0:3, 3:6] = np.eye(3)
    ac[3:6, 6:9] = np.eye(3)
    ac[6:9, 6:9] = -np.diag(1.0 / tau)
    bc = np.zeros((POS_LAG_NX, POS_NU))
    bc[6:9, :] = np.diag(1.0 / tau)
    A, B = zoh_discretize(ac, bc, dt_s)
    return LinearModel(A, B, dt_s=dt_s)


def velocity_disturbance_input(model: LinearModel) -> FloatArray:
    """(nx, 3): how a constant acceleration disturbance d (NED, m/s²) enters one step.

    For the position models (x starting with p(3), v(3)) d acts on v' (a force per mass the
    controller did not command) and on nothing after it, so over one ZOH step it adds
    ``E d`` with ``E = [dt²/2 I; dt I; 0]`` whether or not x carries the lagged acceleration.
    """
    if model.dt_s is None or model.nx < 6:
        raise ModelError("velocity_disturbance_input needs a position model with dt_s")
    dt = model.dt_s
    E = np.zeros((model.nx, 3))
    E[0:3, :] = 0.5 * dt * dt * np.eye(3)
    E[3:6, :] = dt * np.eye(3)
    return E


def attitude_model(dt_s: float, rate_time_constant_s: float, gain: float = 1.0) -> LinearModel:
    """Near-hover attitude model, ZOH at ``dt_s``.

    The autopilot's rate loop follows the body-rate command ``w_cmd`` with a first-order lag of
    time constant tau and a static gain K (1 on PX4; ArduCopter's input shaping answers about
    0.35 of a command); near hover Euler-angle rates equal body rates (thesis 3.2.2)::

        [roll, pitch, yaw]' = [p, q, r]
        [p, q, r]'          = (K w_cmd - [p, q, r]) / tau

    The inner loop's dead time is not in these matrices: the attitude loop predicts the
    state over it with the commands already sent (:mod:`epc_offboard.control.rate_response`)
    and starts the QP there, so theta stays (x0, r, c~, U_p) of this 6-state model.
    """
    if not rate_time_constant_s > 0.0:
        raise ModelError(f"rate_time_constant_s must be > 0, got {rate_time_constant_s}")
    if not (math.isfinite(gain) and gain > 0.0):
        raise ModelError(f"gain must be > 0, got {gain}")
    ac = np.zeros((ATT_NX, ATT_NX))
    ac[0:3, 3:6] = np.eye(3)
    ac[3:6, 3:6] = -np.eye(3) / rate_time_constant_s
    bc = np.zeros((ATT_NX, ATT_NU))
    bc[3:6, :] = gain * np.eye(3) / rate_time_constant_s
    A, B = zoh_discretize(ac, bc, dt_s)
    return LinearModel(A, B, dt_s=dt_s)


@dataclass(frozen=True)
class AttitudeThrust:
    """Attitude setpoint of the cascade: Z-Y-X Euler angles (rad) and normalised thrust."""

    roll_rad: float
    pitch_rad: float
    yaw_rad: float
    thrust_norm: float


# g e_z (NED, m/s^2), read-only: subtracted every position tick
_GRAVITY_NED_M_S2 = np.array([0.0, 0.0, GRAVITY_M_S2])
_GRAVITY_NED_M_S2.setflags(write=False)


def accel_to_attitude(
    accel_ned_m_s2: npt.ArrayLike, yaw_rad: float, hover_thrust_norm: float
) -> AttitudeThrust:
    """Exact inverse of :func:`attitude_to_accel` (thesis eq. 3.13 without small angles).

    Newton in NED with thrust along -z_body: ``m a = m g e_z - T R e_z``, so the thrust vector
    is ``T (-R e_z) = m (g e_z - a)`` and the body z axis is ``R e_z = (g e_z - a) / |g e_z - a|``.
    Removing the yaw, ``Rz(-yaw) R e_z = [c(roll) s(pitch), -s(roll), c(roll) c(pitch)]``.
    Thrust is normalised so that ``hover_thrust_norm`` holds ``g``; small angles give 3.13
    in NED: ``roll = (a_e cos(yaw) - a_n sin(yaw)) / g``,
    ``pitch = -(a_n cos(yaw) + a_e sin(yaw)) / g``.
    """
    a = np.asarray(accel_ned_m_s2, dtype=np.float64)
    if a.shape == (3,):
        # f's floats: a - g e_z element by element, and vector_norm's bits (a (3,) dot
        # product is BLAS's sequential sum) without numpy's subtraction and dot (each a
        # machinery a cold position tick paid for; issue 21)
        fx, fy, fz = a.tolist()
        fx, fy, fz = fx - 0.0, fy - 0.0, fz - GRAVITY_M_S2
        mag = math.sqrt(fx * fx + fy * fy + fz * fz)
    else:
        f = a - _GRAVITY_NED_M_S2  # = -(T/m) R e_z
        mag = frames.vector_norm(f)
        fx, fy, fz = f.tolist()
    if mag < 1e-9:
        # free fall: attitude is arbitrary, keep level
        return AttitudeThrust(0.0, 0.0, yaw_rad, 0.0)
    zx, zy, bz = -fx / mag, -fy / mag, -fz / mag  # R e_z, the body z axis (down) in NED
    cy, sy = math.cos(yaw_rad), math.sin(yaw_rad)
    bx = cy * zx + sy * zy  # Rz(-yaw) R e_z
    by = -sy * zx + cy * zy
    roll = math.atan2(-by, math.hypot(bx, bz))
    pitch = math.atan2(bx, bz)
    return AttitudeThrust(roll, pitch, yaw_rad, hover_thrust_norm * mag / GRAVITY_M_S2)


def attitude_to_axis_xyz(
    roll_rad: float, pitch_rad: float, yaw_rad: float
) -> tuple[float, float, float]:
    """The body z axis (FRD: down through the vehicle) in NED as three floats (the position
    tick's scalar arithmetic takes it so): thrust acts along -z_b."""
    cr, sr = math.cos(roll_rad), math.sin(roll_rad)
    cp, sp_ = math.cos(pitch_rad), math.sin(pitch_rad)
    cy, sy = math.cos(yaw_rad), math.sin(yaw_rad)
    return (cy * cr * sp_ + sy * sr, sy * cr * sp_ - cy * sr, cr * cp)


def attitude_to_axis(roll_rad: float, pitch_rad: float, yaw_rad: float) -> FloatArray:
    """The body z axis (FRD: down through the vehicle) in NED, (3,): thrust acts along -z_b."""
    return np.array(attitude_to_axis_xyz(roll_rad, pitch_rad, yaw_rad))


def attitude_to_accel(sp: AttitudeThrust, hover_thrust_norm: float) -> FloatArray:
    """Acceleration (NED, m/s²) produced by an attitude and normalised thrust."""
    z_b = attitude_to_axis(sp.roll_rad, sp.pitch_rad, sp.yaw_rad)
    thrust_m_s2 = GRAVITY_M_S2 * sp.thrust_norm / hover_thrust_norm
    out: FloatArray = np.array([0.0, 0.0, GRAVITY_M_S2]) - thrust_m_s2 * z_b
    return out


@dataclass(frozen=True)
class AccelBox:
    """Input box on the position model's acceleration (NED, m/s²)."""

    u_min: FloatArray
    u_max: FloatArray


def _specific_thrust_limits(
    max_tilt_rad: float,
    min_thrust_norm: float,
    max_thrust_norm: float,
    hover_thrust_norm: float,
    vertical_share: float,
) -> tuple[float, float]:
    """(f_min, f_max) m/s² of normalised thrust limits; ModelError when they are unusable."""
    g = GRAVITY_M_S2
    f_min = g * min_thrust_norm / hover_thrust_norm
    f_max = g * max_thrust_norm / hover_thrust_norm
    if not (0.0 < max_tilt_rad < math.pi / 2):
        raise ModelError(f"max_tilt_rad must be in (0, pi/2), got {max_tilt_rad}")
    if not (0.0 < vertical_share < 1.0):
        raise ModelError(f"vertical_share must be in (0, 1), got {vertical_share}")
    if not (0.0 <= f_min < g < f_max):
        raise ModelError(
            "thrust limits must bracket hover: "
            f"min {min_thrust_norm} < hover {hover_thrust_norm} < max {max_thrust_norm}"
        )
    return f_min, f_max


def acceleration_box(
    max_tilt_rad: float,
    min_thrust_norm: float,
    max_thrust_norm: float,
    hover_thrust_norm: float,
    *,
    vertical_share: float = 0.5,
) -> AccelBox:
    """A conservative acceleration box inside the tilt and thrust limits.

    The true feasible set is ``|f_h| <= tan(tilt) f_z`` and ``f_min <= |f| <= f_max`` for the
    specific thrust ``f = (-a_x, -a_y, g - a_z)``; it is not a box. We keep a box (so the QP's
    input rows stay simple bounds) chosen as follows: the vertical specific thrust ``f_z``
    ranges over ``[f_lo, f_hi]`` with ``f_hi = g + share (f_max - g)`` and
    ``f_lo = max(f_min, (1 - share) g)``; the horizontal half-width is the largest ``h`` such
    that every corner satisfies both limits: ``sqrt(2) h <= tan(tilt) f_lo`` and
    ``2 h² + f_hi² <= f_max²``. Every point of the box is then flyable.
    """
    g = GRAVITY_M_S2
    f_min, f_max = _specific_thrust_limits(
        max_tilt_rad, min_thrust_norm, max_thrust_norm, hover_thrust_norm, vertical_share
    )
    f_hi = g + vertical_share * (f_max - g)
    f_lo = max(f_min, (1.0 - vertical_share) * g)
    h = min(
        math.tan(max_tilt_rad) * f_lo / math.sqrt(2.0),
        math.sqrt((f_max * f_max - f_hi * f_hi) / 2.0),
    )
    return AccelBox(
        u_min=np.array([-h, -h, g - f_hi]),
        u_max=np.array([h, h, g - f_lo]),
    )


@dataclass(frozen=True)
class AccelLimits:
    """Input limits of the position loop (NED, m/s²): a box and a polytope ``P a <= p``."""

    u_min: FloatArray  # (3,)
    u_max: FloatArray  # (3,)
    P: FloatArray  # (m, 3)
    p: FloatArray  # (m,)

    def contains(self, a: FloatArray, tol: float = 1e-9) -> bool:
        return bool(
            np.all(a >= self.u_min - tol)
            and np.all(a <= self.u_max + tol)
            and np.all(self.P @ a <= self.p + tol)
        )


TILT_POLYGON_SIDES = 8


def acceleration_limits(
    max_tilt_rad: float,
    min_thrust_norm: float,
    max_thrust_norm: float,
    hover_thrust_norm: float,
    *,
    vertical_share: float = 0.5,
    thrust_facets: bool = False,
) -> AccelLimits:
    """The tilt cone and thrust limits as linear constraints on the commanded acceleration.

    Specific thrust ``f = (-a_x, -a_y, g - a_z)``. Vertically ``f_z`` ranges over
    ``[f_lo, f_hi]``: ``f_lo = max(f_min, (1 - share) g)``, ``f_hi = min(g + share (f_max - g),
    f_max cos(tilt))`` (at least a tenth of the spare thrust: a vehicle too weak for the tilt
    limit gets a smaller tilt). Horizontally the tilt cone ``|f_h| <= tan(tilt) f_z`` is
    replaced by the regular octagon inscribed in it at every ``f_z``::

        n_j . a_h + cos(pi/8) tan(tilt) a_z <= cos(pi/8) tan(tilt) g,   n_j at j * 45 deg

    — linear in ``a``, so the QP keeps linear rows. Unlike a per-axis box (whose corners
    must fit the cone, leaving each axis ``1/sqrt(2)`` of it, and which was sized at the
    lowest vertical thrust), one axis gets 92 % of the cone when the other needs nothing, and
    the horizontal authority grows with the vertical thrust actually commanded. Every point
    is flyable: tilt <= max_tilt, and ``|f| <= f_z / cos(tilt) <= f_max``. A degraded input
    is made flyable by :func:`limit_tilt`.

    ``thrust_facets``: the thrust's bound ``|f| <= f_max`` as eight planes instead of the
    vertical cap ``f_max cos(tilt)``, so that ``f_z`` reaches ``g + share (f_max - g)`` while
    the vehicle tilts less than the limit (:func:`_thrust_facets`). The cap held a vehicle
    tilted 30 deg into 12 m/s of wind to 2.9 m/s^2 of climb (the Neural-Fly plant's 0.52
    hover, 45 deg), less than its figure-8 and the inflow's loss ask, with the thrust to
    spare: it sagged 25 cm climbing upwind (issue 24).
    """
    g = GRAVITY_M_S2
    f_min, f_max = _specific_thrust_limits(
        max_tilt_rad, min_thrust_norm, max_thrust_norm, hover_thrust_norm, vertical_share
    )
    f_share = g + vertical_share * (f_max - g)
    if thrust_facets and f_share > f_max * math.cos(max_tilt_rad):
        return _thrust_facets(max_tilt_rad, f_max, f_share, max(f_min, (1.0 - vertical_share) * g))
    # the climb margin is traded for tilt down to a tenth of the spare thrust; beyond that a
    # vehicle too weak for the tilt limit gets the tilt it can fly
    f_hi = min(f_share, f_max * math.cos(max_tilt_rad))
    f_hi_min = g + 0.1 * (f_max - g)
    if f_hi < f_hi_min:
        f_hi = f_hi_min
        max_tilt_rad = math.acos(f_hi / f_max)
    f_lo = max(f_min, (1.0 - vertical_share) * g)
    k = math.cos(math.pi / TILT_POLYGON_SIDES) * math.tan(max_tilt_rad)
    angles = 2.0 * math.pi * np.arange(TILT_POLYGON_SIDES) / TILT_POLYGON_SIDES
    P = np.column_stack([np.cos(angles), np.sin(angles), np.full(TILT_POLYGON_SIDES, k)])
    P[np.abs(P) < 1e-15] = 0.0
    # horizontally the polygon is the only limit: box rows there would never be active,
    # only cost every stored controller check rows
    return AccelLimits(
        u_min=np.array([-math.inf, -math.inf, g - f_hi]),
        u_max=np.array([math.inf, math.inf, g - f_lo]),
        P=P,
        p=np.full(TILT_POLYGON_SIDES, k * g),
    )


def _thrust_facets(max_tilt_rad: float, f_max: float, f_hi: float, f_lo: float) -> AccelLimits:
    """The tilt octagon of :func:`acceleration_limits`, ``f_z`` in ``[f_lo, f_hi]``, and the
    thrust sphere ``|f| <= f_max`` between by eight planes (``f_hi > f_max cos(tilt)``).

    Facet j (normal ``n_j`` at j * 45 deg, as the octagon's) passes through the sphere's
    points at the octagon's vertex azimuths (``n_j`` +- 22.5 deg) at two tilts: ``theta_1``,
    where the sphere meets the cap ``f_z = f_hi``, and the limit ``theta_2``::

        alpha n_j . f_h + f_z <= c,  alpha = (cos t1 - cos t2) / (cos(pi/8) (sin t2 - sin t1))
                                     c = f_max (alpha cos(pi/8) sin t2 + cos t2)

    Every vertex of the polytope (the cap's octagon at ``theta_1``, the cone's edges at
    ``theta_2``, the floor's) lies on or inside the sphere, so every point is flyable; in
    ``a`` (``f = (-a_h, g - a_z)``): ``-alpha n_j . a_h - a_z <= c - g``."""
    g = GRAVITY_M_S2
    cos8 = math.cos(math.pi / TILT_POLYGON_SIDES)
    t1, t2 = math.acos(f_hi / f_max), max_tilt_rad
    alpha = (math.cos(t1) - math.cos(t2)) / (cos8 * (math.sin(t2) - math.sin(t1)))
    c = f_max * (alpha * cos8 * math.sin(t2) + math.cos(t2))
    k = cos8 * math.tan(max_tilt_rad)
    angles = 2.0 * math.pi * np.arange(TILT_POLYGON_SIDES) / TILT_POLYGON_SIDES
    n = np.column_stack([np.cos(angles), np.sin(angles)])
    P = np.vstack([
        np.column_stack([n, np.full(TILT_POLYGON_SIDES, k)]),
        np.column_stack([-alpha * n, np.full(TILT_POLYGON_SIDES, -1.0)]),
    ])  # fmt: skip
    P[np.abs(P) < 1e-15] = 0.0
    return AccelLimits(
        u_min=np.array([-math.inf, -math.inf, g - f_hi]),
        u_max=np.array([math.inf, math.inf, g - f_lo]),
        P=P,
        p=np.concatenate([np.full(TILT_POLYGON_SIDES, k * g), np.full(TILT_POLYGON_SIDES, c - g)]),
    )


def limit_tilt(acc_ned_m_s2: FloatArray, limits: AccelLimits) -> FloatArray:
    """``acc`` clipped into the box and scaled horizontally into the polygon: whatever a
    controller (or a degraded tick) asks, what is sent stays within the tilt limit."""
    a = np.minimum(np.maximum(acc_ned_m_s2, limits.u_min), limits.u_max)
    slack = limits.p - limits.P[:, 2] * a[2]  # the polygon's reach at this a_z (> 0)
    reach = limits.P[:, :2] @ a[:2]
    # (maximum.reduce: ndarray.max's value and NaN, without its Python-level wrapper)
    worst = float(np.maximum.reduce(reach / slack))
    if worst > 1.0:
        a[:2] /= worst
    return a
