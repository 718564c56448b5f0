"""Reference trajectories for the position loop (pure numerics, NED, SI units).

Every trajectory is a smooth function of time giving position, velocity and acceleration,
anchored at a point (usually where the vehicle was when control began): the path starts
*at* the anchor with zero velocity, and a C2 time warp ramps the progress speed from 0 to 1
over ``ramp_s`` so the controller is never handed a step in position, velocity or
acceleration.

Shapes (horizontal plane; altitude is the anchor's):

* ``hover``    — stay at the anchor;
* ``line``     — to ``anchor + (dx_m, dy_m, dz_m)`` and back, at ``speed_m_s``;
* ``circle``   — radius ``radius_m``, period ``period_s``, centre ``radius_m`` north of the anchor;
* ``figure8``  — lemniscate of Gerono: x = A sin(wt), y = A/2 sin(2wt) (A = ``size_m``);
* ``figure8_vertical`` — the same figure stood up in the north-down plane, Neural-Fly's
  (O'Connell et al., Science Robotics 2022): north = A sin(wt), up = B sin(2wt)
  (A = ``size_m``, B = ``size_z_m``; theirs: 1.25 sin t, 0.75 sin 2t);
* ``zigzag``   — y sweeps ±``amplitude_m`` with a jerk-limited speed profile peaking at
  ``peak_speed_m_s`` (the thesis's experiment: up to 3.75 m/s), optionally advancing north at
  ``forward_speed_m_s``;
* ``waypoints``— straight segments through a list of (north, east, down) offsets, each with a
  jerk-limited speed profile (stop at each waypoint). ``accel_m_s2`` is the profiles' peak
  acceleration.
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, replace
from typing import Any, TypeVar, cast

import numpy as np
import numpy.typing as npt

from epc_offboard.common import jit
from epc_offboard.common.frames import FloatArray
from epc_offboard.control.trajectory_config import Shape as Shape
from epc_offboard.control.trajectory_config import TrajectoryConfig as TrajectoryConfig
from epc_offboard.control.types import STAGE_WIDTH, ReferenceHorizon

_F = TypeVar("_F", bound=Callable[..., Any])

@dataclass(frozen=True)
class RefSample:
    pos_ned_m: FloatArray
    vel_ned_m_s: FloatArray
    acc_ned_m_s2: FloatArray


@dataclass(frozen=True)
class Rejoin:
    """A bumpless way back onto a trajectory that ran on while someone else flew.

    The reference is the trajectory plus a gap e(t) that starts at the vehicle's position
    and velocity error (``e0 = p - p_traj``, ``de0 = v - v_traj`` at ``start_s``) and closes
    critically damped: ``e(t) = (e0 + (de0 + e0 / tau) t) exp(-t / tau)``. Without it a
    re-entry after a failsafe asked for the trajectory metres away at once: saturated
    commands that, with the faults that caused the failsafe, flipped the vehicle.
    """

    gap_ned_m: FloatArray  # e0
    gap_rate_ned_m_s: FloatArray  # de0
    start_s: float
    tau_s: float

    @classmethod
    def onto(
        cls, traj: RefSample, pos_ned_m: FloatArray, vel_ned_m_s: FloatArray, t_s: float,
        tau_s: float,
    ) -> Rejoin:  # fmt: skip
        return cls(pos_ned_m - traj.pos_ned_m, vel_ned_m_s - traj.vel_ned_m_s, t_s, tau_s)

    def rows(self, t_s: npt.ArrayLike) -> FloatArray:
        """(len(t_s), 9) rows [e, de, dde] of the gap at times ``t_s`` (0 before start_s)."""
        t = np.maximum(np.asarray(t_s, dtype=np.float64) - self.start_s, 0.0)[:, None]
        tau = self.tau_s
        a, b = self.gap_ned_m[None, :], (self.gap_rate_ned_m_s + self.gap_ned_m / tau)[None, :]
        decay = np.exp(-t / tau)
        abt = a + b * t  # (each term below its own product and sum: the same numbers)
        out: FloatArray = np.empty((t.shape[0], 9))  # [e, de, dde], every position tick
        np.multiply(abt, decay, out=out[:, 0:3])
        np.multiply(b - abt / tau, decay, out=out[:, 3:6])
        np.multiply(-2.0 * b / tau + abt / tau**2, decay, out=out[:, 6:9])
        return out

    def max_acc_m_s2(self) -> float:
        """The largest acceleration the gap asks of the vehicle (norm, m/s^2), over its
        whole closing (it peaks at the start or once, ~2 tau later; sampled to 8 tau)."""
        t = self.start_s + np.linspace(0.0, 8.0 * self.tau_s, 97)
        return float(np.linalg.norm(self.rows(t)[:, 6:9], axis=1).max())

    def within(self, max_acc_m_s2: float, max_tau_s: float = 30.0) -> Rejoin:
        """This rejoin, slowed (a longer ``tau_s``, never a shorter one) until the gap asks
        for at most ``max_acc_m_s2``. A fixed tau asked a vehicle re-entering at 1.3 m/s
        against a circle turning the other way for 5.5 m/s^2 at once, which the entry ramp
        (rightly) would not command: the vehicle flew 3.9 m past the reference and the QP,
        that far off, climbed 0.9 m buying horizontal authority with thrust."""
        rejoin = self
        while rejoin.tau_s < max_tau_s and rejoin.max_acc_m_s2() > max_acc_m_s2:
            rejoin = replace(rejoin, tau_s=min(rejoin.tau_s * 1.25, max_tau_s))
        return rejoin

    def done(self, t_s: float) -> bool:
        """The gap has closed to nothing that matters (15 time constants: a 3 m gap is then
        below 0.1 mm, so dropping the rejoin is no jump)."""
        return t_s - self.start_s > 15.0 * self.tau_s


# A path in its own progress variable s (seconds of "full speed" travel): p(s), p'(s), p''(s).
PathFn = Callable[[float], tuple[FloatArray, FloatArray, FloatArray]]


def _warp(t_s: float, ramp_s: float) -> tuple[float, float, float]:
    """C2 time warp: s(t), s'(t), s''(t) with s' rising 0 -> 1 over ramp_s as (1 - cos)/2."""
    if t_s <= 0.0:
        return 0.0, 0.0, 0.0
    if t_s >= ramp_s:
        return ramp_s / 2 + (t_s - ramp_s), 1.0, 0.0
    w = math.pi / ramp_s
    s = t_s / 2 - math.sin(w * t_s) / (2 * w)
    return s, (1 - math.cos(w * t_s)) / 2, w * math.sin(w * t_s) / 2


def _trapezoid(
    distance_m: float, v_max: float, a_max: float
) -> Callable[[float], tuple[float, float, float]]:
    """Rest-to-rest profile along a distance, jerk-limited: returns f(t) -> (x, v, a).

    A trapezoidal speed profile whose acceleration phases are raised cosines,
    ``a(t) = a_max sin^2(pi t / T)`` with ``T = 2 v_max / a_max``: acceleration is continuous
    (peak ``a_max``, peak jerk ``pi a_max^2 / (2 v_max)``), as PX4's own jerk-limited
    trajectories are. Why: the position model carries the inner loop's lag, and inverting a
    lag turns an acceleration *step* into a command spike that saturates the acceleration
    box for a stage or two — a chattering active set the library would have to learn anew at
    every corner. Each phase covers ``v_max T / 2``; a distance too short for ``v_max``
    lowers the peak speed to ``sqrt(a_max d / 2)``. Held at the end.
    """
    if distance_m <= 0.0:
        return lambda _t: (0.0, 0.0, 0.0)
    if 2.0 * v_max * v_max / a_max >= distance_m:  # never reaches v_max
        v_max = math.sqrt(a_max * distance_m / 2.0)
    t_acc = 2.0 * v_max / a_max
    d_acc = 0.5 * v_max * t_acc
    t_cruise = (distance_m - 2.0 * d_acc) / v_max
    t_total = 2 * t_acc + t_cruise
    w = 2.0 * math.pi / t_acc

    def ramp(t: float) -> tuple[float, float, float]:
        """The acceleration phase from rest, 0 <= t <= t_acc."""
        x = v_max / t_acc * (0.5 * t * t + (math.cos(w * t) - 1.0) / (w * w))
        v = v_max / t_acc * (t - math.sin(w * t) / w)
        a = v_max / t_acc * (1.0 - math.cos(w * t))
        return x, v, a

    def f(t: float) -> tuple[float, float, float]:
        if t <= 0.0:
            return 0.0, 0.0, 0.0
        if t < t_acc:
            return ramp(t)
        if t < t_acc + t_cruise:
            return d_acc + v_max * (t - t_acc), v_max, 0.0
        if t < t_total:
            x, v, a = ramp(t_total - t)
            return distance_m - x, v, -a
        return distance_m, 0.0, 0.0

    f.duration_s = t_total  # type: ignore[attr-defined]
    return f


def _segments(points: Sequence[FloatArray], v_max: float, a_max: float) -> PathFn:
    """Rest-to-rest straight segments through ``points`` (the first is the start)."""
    legs = []
    t0 = 0.0
    for a, b in itertools.pairwise(points):
        d = b - a
        length = float(np.linalg.norm(d))
        prof = _trapezoid(length, v_max, a_max)
        unit = d / length if length > 0 else np.zeros(3)
        legs.append((t0, a, unit, prof))
        t0 += getattr(prof, "duration_s", 0.0)

    def path(s: float) -> tuple[FloatArray, FloatArray, FloatArray]:
        if not legs:
            return points[0].copy(), np.zeros(3), np.zeros(3)
        leg = legs[0]
        for cand in legs:
            if s >= cand[0]:
                leg = cand
        start_s, a, unit, prof = leg
        x, v, acc = prof(s - start_s)
        return a + unit * x, unit * v, unit * acc

    return path


def make_path(cfg: TrajectoryConfig) -> PathFn:
    """The path of ``cfg.shape`` relative to the anchor (offset zero at s = 0)."""
    zero = np.zeros(3)
    if cfg.shape == "hover":
        return lambda _s: (zero.copy(), zero.copy(), zero.copy())
    if cfg.shape == "circle":
        r, w = cfg.radius_m, 2 * math.pi / cfg.period_s

        def circle(s: float) -> tuple[FloatArray, FloatArray, FloatArray]:
            # centre r north of the anchor; start at the anchor heading east
            c, si = math.cos(w * s), math.sin(w * s)
            return (
                np.array([r - r * c, r * si, 0.0]),
                np.array([r * w * si, r * w * c, 0.0]),
                np.array([r * w * w * c, -r * w * w * si, 0.0]),
            )

        return circle
    if cfg.shape == "figure8":
        a, w = cfg.size_m, 2 * math.pi / cfg.period_s

        def figure8(s: float) -> tuple[FloatArray, FloatArray, FloatArray]:
            return (
                np.array([a * math.sin(w * s), a / 2 * math.sin(2 * w * s), 0.0]),
                np.array([a * w * math.cos(w * s), a * w * math.cos(2 * w * s), 0.0]),
                np.array([-a * w * w * math.sin(w * s), -2 * a * w * w * math.sin(2 * w * s), 0.0]),
            )

        return figure8
    if cfg.shape == "figure8_vertical":
        a, b, w = cfg.size_m, cfg.size_z_m, 2 * math.pi / cfg.period_s

        def figure8_vertical(s: float) -> tuple[FloatArray, FloatArray, FloatArray]:
            # north, and down = -up
            return (
                np.array([a * math.sin(w * s), 0.0, -(b * math.sin(2 * w * s))]),
                np.array([a * w * math.cos(w * s), 0.0, -(2 * b * w * math.cos(2 * w * s))]),
                np.array([-a * w * w * math.sin(w * s), 0.0, 4 * b * w * w * math.sin(2 * w * s)]),
            )

        return figure8_vertical
    if cfg.shape == "zigzag":
        amp = cfg.amplitude_m
        sweep = _trapezoid(2 * amp, cfg.peak_speed_m_s, cfg.accel_m_s2)
        first = _trapezoid(amp, cfg.peak_speed_m_s, cfg.accel_m_s2)
        t_first = float(getattr(first, "duration_s"))  # noqa: B009 - set dynamically
        t_sweep = float(getattr(sweep, "duration_s"))  # noqa: B009
        vf = cfg.forward_speed_m_s

        def zigzag(s: float) -> tuple[FloatArray, FloatArray, FloatArray]:
            if s < t_first:  # anchor -> +amp
                y, vy, ay = first(s)
            else:
                k, tau = divmod(s - t_first, t_sweep)
                y, vy, ay = sweep(tau)
                sign = -1.0 if int(k) % 2 == 0 else 1.0  # +amp -> -amp, then back
                y, vy, ay = amp + sign * y if sign < 0 else -amp + y, sign * vy, sign * ay
            return np.array([vf * s, y, 0.0]), np.array([vf, vy, 0.0]), np.array([0.0, ay, 0.0])

        return zigzag
    if cfg.shape == "line":
        end = np.array([cfg.dx_m, cfg.dy_m, cfg.dz_m])
        return _segments([zero, end, zero], cfg.speed_m_s, cfg.accel_m_s2)
    pts = [zero] + [np.array(w, dtype=np.float64) for w in cfg.waypoints_ned_m]
    return _segments(pts, cfg.speed_m_s, cfg.accel_m_s2)


@dataclass
class Trajectory:
    """A path anchored in NED at ``anchor_ned_m`` starting at time ``start_s``."""

    config: TrajectoryConfig
    anchor_ned_m: FloatArray
    start_s: float = 0.0

    def __post_init__(self) -> None:
        self._path = make_path(self.config)
        self.anchor_ned_m = np.asarray(self.anchor_ned_m, dtype=np.float64).copy()

    def sample(self, t_s: float) -> RefSample:
        s, ds, dds = _warp(t_s - self.start_s, self.config.ramp_s)
        p, dp, ddp = self._path(s)
        return RefSample(self.anchor_ned_m + p, dp * ds, ddp * ds * ds + dp * dds)

    def horizon(self, t0_s: float, dt_s: float, steps: int) -> FloatArray:
        """References for x[1..N] of the position model: (steps, 9) rows [p_ned, v_ned, a_ned]."""
        return self.horizon_from_now(t0_s, dt_s, steps)[1:]

    def horizon_from_now(self, t0_s: float, dt_s: float, steps: int) -> FloatArray:
        """(steps + 1, 9) rows [p_ned, v_ned, a_ned] at ``t0_s + k dt_s``, k = 0..steps: the
        reference now, then the horizon of :meth:`horizon`. Each row equals :meth:`sample` at
        its time to the last bit; circle and figure-8 are one compiled call (the position
        loop's tick: 21 samples in a few us instead of ~130)."""
        out = np.empty((steps + 1, STAGE_WIDTH))
        cfg = self.config
        if cfg.shape in _SHAPE_CODE:
            a, period = (cfg.radius_m, cfg.period_s) if cfg.shape == "circle" else (
                cfg.size_m, cfg.period_s)
            _closed_path_rows(_SHAPE_CODE[cfg.shape], a, cfg.size_z_m, 2 * math.pi / period,
                              cfg.ramp_s, t0_s, dt_s, self.start_s, self.anchor_ned_m, out)
            return out
        if cfg.shape == "hover":
            # every stage is the anchor at rest (sample()'s arithmetic: anchor + 0.0, and
            # zeros): 21 Python-level samples were a fifth of the position step's time
            # in a real-time hover (py-spy, bench --attack)
            out[:, :3] = self.anchor_ned_m + 0.0
            out[:, 3:] = 0.0
            return out
        for k in range(steps + 1):
            r = self.sample(t0_s + k * dt_s)
            out[k, :3] = r.pos_ned_m
            out[k, 3:6] = r.vel_ned_m_s
            out[k, 6:] = r.acc_ned_m_s2
        return out

    def reference(
        self, t0_s: float, dt_s: float, steps: int, yaw_rad: float, rejoin: Rejoin | None = None
    ) -> ReferenceHorizon:
        """The reference horizon from ``t0_s`` (stages 0..``steps``, ``dt_s`` apart): the rows
        of :meth:`horizon_from_now`, plus ``rejoin``'s gap when one is closing, flown at the
        heading ``yaw_rad``."""
        rows = self.horizon_from_now(t0_s, dt_s, steps)
        if rejoin is not None:
            times = t0_s + dt_s * np.arange(steps + 1, dtype=np.float64)
            rows += rejoin.rows(times)  # (rows is this call's own array)
        return ReferenceHorizon.at_heading(rows, yaw_rad)


def _jit(fn: _F) -> _F:
    """numba's njit (cached on disk when it can be), or ``fn`` itself without numba."""
    if not jit.enabled():  # the numpy twins (a cold start, see common.jit)
        return fn
    try:
        import numba
    except ImportError:  # numba is a dependency; without it the same code runs as Python
        return fn
    try:
        return cast(_F, numba.njit(fn, cache=True, nogil=True))
    except RuntimeError:  # no writable cache location
        return cast(_F, numba.njit(fn, cache=False, nogil=True))


_SHAPE_CODE = {"circle": 0, "figure8": 1, "figure8_vertical": 2}


def warm_up() -> None:
    """Compile (or load from the cache) the horizon kernel now, not in the first tick."""
    _closed_path_rows(1, 1.0, 1.0, 1.0, 1.0, 0.0, 0.1, 0.0, np.zeros(3), np.empty((2, 9)))


@_jit
def _closed_path_rows(
    shape: int, a: float, b: float, w: float, ramp_s: float, t0_s: float, dt_s: float,
    start_s: float, anchor: FloatArray, out: FloatArray,
) -> None:
    """Rows of ``out`` (m, 9) at t0_s + k dt_s for the circle (shape 0, radius a), the
    figure-8 (1, size a) or the vertical figure-8 (2, sizes a, b), angular rate w:
    :func:`_warp` and :func:`make_path`'s shapes written out with the same operations in the
    same order (bit-identical)."""
    for k in range(out.shape[0]):
        t = (t0_s + k * dt_s) - start_s
        # _warp
        if t <= 0.0:
            s, ds, dds = 0.0, 0.0, 0.0
        elif t >= ramp_s:
            s, ds, dds = ramp_s / 2 + (t - ramp_s), 1.0, 0.0
        else:
            wr = math.pi / ramp_s
            s = t / 2 - math.sin(wr * t) / (2 * wr)
            ds = (1 - math.cos(wr * t)) / 2
            dds = wr * math.sin(wr * t) / 2
        p2, dp2, ddp2 = 0.0, 0.0, 0.0
        if shape == 0:
            c, si = math.cos(w * s), math.sin(w * s)
            p0, p1 = a - a * c, a * si
            dp0, dp1 = a * w * si, a * w * c
            ddp0, ddp1 = a * w * w * c, -a * w * w * si
        elif shape == 2:
            p0, p1, p2 = a * math.sin(w * s), 0.0, -(b * math.sin(2 * w * s))
            dp0, dp1, dp2 = a * w * math.cos(w * s), 0.0, -(2 * b * w * math.cos(2 * w * s))
            ddp0, ddp1 = -a * w * w * math.sin(w * s), 0.0
            ddp2 = 4 * b * w * w * math.sin(2 * w * s)
        else:
            p0, p1 = a * math.sin(w * s), a / 2 * math.sin(2 * w * s)
            dp0, dp1 = a * w * math.cos(w * s), a * w * math.cos(2 * w * s)
            ddp0 = -a * w * w * math.sin(w * s)
            ddp1 = -2 * a * w * w * math.sin(2 * w * s)
        out[k, 0] = anchor[0] + p0
        out[k, 1] = anchor[1] + p1
        out[k, 2] = anchor[2] + p2
        out[k, 3] = dp0 * ds
        out[k, 4] = dp1 * ds
        out[k, 5] = dp2 * ds
        out[k, 6] = ddp0 * ds * ds + dp0 * dds
        out[k, 7] = ddp1 * ds * ds + dp1 * dds
        out[k, 8] = ddp2 * ds * ds + dp2 * dds


def live_reference_horizon(
    pos_ned_m: Sequence[float],
    vel_ned_m_s: Sequence[float] | None,
    horizon_pos_ned_m: Sequence[Sequence[float]],
    horizon_dt_s: float | None,
    *,
    yaw_rad: float,
    age_s: float,
    dt_s: float,
    steps: int,
) -> ReferenceHorizon:
    """The reference horizon from a planner's live reference received ``age_s`` ago.

    Stages 0..``steps`` at ``age_s + k dt_s`` after the reference's time, rows
    [p_ned, v_ned, 0]: with a horizon, the piecewise-linear path through ``pos`` then
    ``horizon_pos`` (spaced ``horizon_dt_s``), held at its end; with only a velocity, the
    target moving at it; else a hold at ``pos``. Heading ``yaw_rad`` throughout.
    """
    t = age_s + dt_s * np.arange(0, steps + 1)
    pos = np.asarray(pos_ned_m, dtype=np.float64)
    out = np.zeros((steps + 1, STAGE_WIDTH))
    if len(horizon_pos_ned_m) and horizon_dt_s is not None:
        pts = np.vstack([pos, np.asarray(horizon_pos_ned_m, dtype=np.float64)])
        times = horizon_dt_s * np.arange(len(pts))
        out[:, :3] = np.column_stack([np.interp(t, times, pts[:, i]) for i in range(3)])
        seg = np.clip(np.searchsorted(times, t, side="right") - 1, 0, len(pts) - 2)
        vel = (np.diff(pts, axis=0) / horizon_dt_s)[seg]
        vel[t >= times[-1]] = 0.0
        out[:, 3:6] = vel
    elif vel_ned_m_s is not None:
        vel = np.asarray(vel_ned_m_s, dtype=np.float64)
        out[:, :3] = pos + np.outer(t, vel)
        out[:, 3:6] = vel
    else:
        out[:, :3] = pos
    return ReferenceHorizon.at_heading(out, yaw_rad)
