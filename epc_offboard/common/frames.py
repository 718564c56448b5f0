"""Frames, rotations and the conversions at the product's boundaries.

Internal convention, everywhere in epc_offboard and sitl (chosen to match MAVLink/PX4 so
that the MAVLink boundary is the identity and frame bugs cannot hide there):

* world frame: local NED — x north, y east, z down, metres;
* body frame: FRD — x forward, y right, z down;
* attitude: unit quaternion ``q = [w, x, y, z]`` (Hamilton, scalar first, as MAVLink's
  ATTITUDE_QUATERNION) rotating body-frame vectors into the world frame: ``v_ned = R(q) v_frd``;
* Euler angles: Z-Y-X Tait-Bryan (yaw, then pitch, then roll) as in thesis 3.2.1 and MAVLink
  ATTITUDE, radians.

The thesis writes its world frame z-up (ENU-like) and states wind directions counter-clockwise
from +x = east. Those conversions live here and nowhere else.
"""

from __future__ import annotations

import math

import numpy as np
import numpy.typing as npt

FloatArray = npt.NDArray[np.float64]

GRAVITY_M_S2 = 9.80665

# ENU <-> NED is a fixed permutation with a sign flip: (e, n, u) -> (n, e, -u). It is its own
# inverse, which the round-trip test relies on.
_ENU_TO_NED = np.array([[0.0, 1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, -1.0]])


def enu_to_ned(vec_enu: npt.ArrayLike) -> FloatArray:
    """Convert vector(s) of shape (..., 3) from ENU to NED."""
    out: FloatArray = np.asarray(vec_enu, dtype=np.float64) @ _ENU_TO_NED.T
    return out


def ned_to_enu(vec_ned: npt.ArrayLike) -> FloatArray:
    """Convert vector(s) of shape (..., 3) from NED to ENU."""
    out: FloatArray = np.asarray(vec_ned, dtype=np.float64) @ _ENU_TO_NED.T
    return out


def wind_vector_ned_m_s(speed_m_s: float, dir_deg: float) -> FloatArray:
    """Wind velocity in NED from the docs/CONTRACTS.md convention.

    ``dir_deg`` is the direction the wind blows *towards*, counter-clockwise from +x = east in
    the horizontal plane (the thesis's angles: -135 deg is towards south-west).
    """
    if not (math.isfinite(speed_m_s) and math.isfinite(dir_deg)):
        raise ValueError(f"wind must be finite, got speed={speed_m_s!r} dir={dir_deg!r}")
    if speed_m_s < 0.0:
        raise ValueError(f"wind speed must be >= 0 m/s, got {speed_m_s}")
    dir_rad = math.radians(dir_deg)
    east = speed_m_s * math.cos(dir_rad)
    north = speed_m_s * math.sin(dir_rad)
    return np.array([north, east, 0.0])


def vector_norm(v: FloatArray) -> float:
    """``np.linalg.norm`` of a float array, to the last bit (it is the square root of the
    flattened array's dot product with itself), without its argument handling: a fifth of
    its cost on the control loops' (3,) and (4,) vectors."""
    flat = v.ravel()
    return math.sqrt(flat.dot(flat))


def quat_normalize(q: npt.ArrayLike) -> FloatArray:
    """Return the unit quaternion of ``q`` (shape (4,)), sign fixed so that w >= 0.

    The bits of the array form (``q / vector_norm(q)``, then ``-q`` if w < 0) from the four
    floats: no Python-level call, no numpy temporaries, no ``isfinite`` (it runs twice a
    position tick, in :func:`euler_to_quat`, and every SITL step; issue 21)."""
    qa = np.asarray(q, dtype=np.float64)
    if qa.shape != (4,):
        raise ValueError(f"a quaternion has shape (4,), got {qa.shape}")
    n = math.sqrt(qa.dot(qa))
    if not 1e-12 <= n < math.inf:  # (NaN fails it too: no isfinite call)
        raise ValueError(f"cannot normalise quaternion {qa!r}")
    w, x, y, z = qa.tolist()
    w, x, y, z = w / n, x / n, y / n, z / n
    return np.array([-w, -x, -y, -z] if w < 0.0 else [w, x, y, z])


def quat_multiply(p: npt.ArrayLike, q: npt.ArrayLike) -> FloatArray:
    """Hamilton product ``p ⊗ q`` of two (4,) quaternions [w, x, y, z]."""
    # (Python floats: numpy scalars' arithmetic is the same IEEE arithmetic, three times slower)
    pw, px, py, pz = np.asarray(p, dtype=np.float64).tolist()
    qw, qx, qy, qz = np.asarray(q, dtype=np.float64).tolist()
    return np.array(
        [
            pw * qw - px * qx - py * qy - pz * qz,
            pw * qx + px * qw + py * qz - pz * qy,
            pw * qy - px * qz + py * qw + pz * qx,
            pw * qz + px * qy - py * qx + pz * qw,
        ]
    )


def quat_integrate_body_rate(q: FloatArray, rate_frd_rad_s: FloatArray, dt_s: float) -> FloatArray:
    """``q`` (4,) rotated on by constant body rates (3,) FRD for ``dt_s``: the exact solution
    of q' = 1/2 q ⊗ [0, w], ``q ⊗ [cos(|w| dt/2), sin(|w| dt/2) w/|w|]``; unit, w >= 0.
    A negative ``dt_s`` rotates back exactly (a sample carried back in time); before stop 40
    it returned ``q`` unchanged."""
    wx, wy, wz = np.asarray(rate_frd_rad_s, dtype=np.float64).tolist()
    norm = math.sqrt(wx * wx + wy * wy + wz * wz)
    half = 0.5 * norm * dt_s
    if abs(half) < 1e-12:
        return np.array(q, dtype=np.float64)
    k = math.sin(half) / norm
    out = quat_multiply(q, (math.cos(half), wx * k, wy * k, wz * k))
    return -out if out[0] < 0.0 else out


def quat_conjugate(q: npt.ArrayLike) -> FloatArray:
    qa = np.asarray(q, dtype=np.float64)
    return np.array([qa[0], -qa[1], -qa[2], -qa[3]])


def quat_to_rotation(q: npt.ArrayLike) -> FloatArray:
    """Rotation matrix (3, 3) taking body FRD vectors to world NED: ``v_ned = R @ v_frd``."""
    w, x, y, z = np.asarray(q, dtype=np.float64)
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
            [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
            [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
        ]
    )


def euler_to_quat(roll_rad: float, pitch_rad: float, yaw_rad: float) -> FloatArray:
    """Quaternion [w, x, y, z] of Z-Y-X Euler angles (yaw, pitch, roll applied in that order)."""
    cr, sr = math.cos(roll_rad / 2), math.sin(roll_rad / 2)
    cp, sp = math.cos(pitch_rad / 2), math.sin(pitch_rad / 2)
    cy, sy = math.cos(yaw_rad / 2), math.sin(yaw_rad / 2)
    w = cr * cp * cy + sr * sp * sy
    x = sr * cp * cy - cr * sp * sy
    y = cr * sp * cy + sr * cp * sy
    z = cr * cp * sy - sr * sp * cy
    # quat_normalize's bits on the floats (its norm, a (4,) dot product, is BLAS's sequential
    # sum): no array made from a list, no dot or tolist call (a position tick's machinery,
    # each paid cold; issue 21)
    n = math.sqrt(w * w + x * x + y * y + z * z)
    if not 1e-12 <= n < math.inf:
        return quat_normalize([w, x, y, z])  # (raises its error)
    w, x, y, z = w / n, x / n, y / n, z / n
    return np.array([-w, -x, -y, -z] if w < 0.0 else [w, x, y, z])


def quat_to_euler(q: npt.ArrayLike) -> tuple[float, float, float]:
    """Z-Y-X Euler angles (roll_rad, pitch_rad, yaw_rad) of quaternion [w, x, y, z]."""
    # (Python floats: numpy scalars' arithmetic is the same IEEE arithmetic, three times slower)
    w, x, y, z = np.asarray(q, dtype=np.float64).tolist()
    roll = math.atan2(2 * (w * x + y * z), 1 - 2 * (x * x + y * y))
    sinp = max(-1.0, min(1.0, 2 * (w * y - z * x)))
    pitch = math.asin(sinp)
    yaw = math.atan2(2 * (w * z + x * y), 1 - 2 * (y * y + z * z))
    return roll, pitch, yaw


def wrap_pi(angle_rad: float) -> float:
    """Wrap an angle to [-pi, pi)."""
    return (angle_rad + math.pi) % (2 * math.pi) - math.pi


def tilt_deg(q: npt.ArrayLike) -> float:
    """Angle (deg) between body z (FRD down) and world down of attitude ``q`` [w, x, y, z]."""
    w, x, y, z = (float(v) for v in np.asarray(q, dtype=np.float64))
    norm2 = w * w + x * x + y * y + z * z
    cos_tilt = 1.0 - 2.0 * (x * x + y * y) / norm2
    return math.degrees(math.acos(min(1.0, max(-1.0, cos_tilt))))


def angle_between_deg(p: npt.ArrayLike, q: npt.ArrayLike) -> float:
    """The smallest rotation (deg) from attitude ``p`` to attitude ``q`` (sign-agnostic)."""
    a, b = quat_normalize(p), quat_normalize(q)
    dot = abs(float(np.dot(a, b)))
    return math.degrees(2.0 * math.acos(min(1.0, dot)))
