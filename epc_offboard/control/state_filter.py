"""The position and velocity the position loop flies from: the measured ones fused with the
model's prediction.

An autopilot's state estimate (PX4 EKF2's output predictor) carries an error that is smooth,
not white: a few mm and cm/s, each correlated over EKF2_TAU_POS / EKF2_TAU_VEL (0.25 s). The
position loop answered the velocity's error as if it were the vehicle's motion (Neural-Fly's
plant at 0 m/s, seed 1: 2.28 cm mean error, 0.96 without the velocity's noise; the position's,
attitude's and rates' noise cost nothing; with the noise put back in the QP's initial state
alone 1.92). A low-pass filter of the velocity does not remove an error that slow: it only
lags the vehicle. What does is the two measurements' disagreement: a velocity error moves
no position, a position error moves with no velocity. Per axis, a Kalman filter of the state
[p, v, e_p, e_v] (the true position and velocity, driven by the model's acceleration, and
the two estimate errors, each a Gauss-Markov process) with p + e_p and v + e_v measured.
Offline on that flight's log against the ground truth: velocity error 3.0 -> 2.0-2.3 cm/s rms
(model acceleration error 1-3 m/s^2), position 5.2 -> 4.9 mm.

The gain is the steady state's (one sample per loop period), computed once. Numerics only:
no I/O, no clock.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from epc_offboard.common.frames import FloatArray


@dataclass(frozen=True)
class StateFilterConfig:
    """The estimate's error the filter is matched to, and the model's trust.

    ``position_noise_m``, ``velocity_noise_m_s``: the estimate errors' standard deviations
    (0 for either: no filter, the measured state as is); ``correlation_s``: their
    correlation time; ``acc_noise_m_s2``: the model acceleration's error (the lagged commands
    plus the disturbance estimate against the vehicle's), white at the loop period;
    ``feed_estimator``: the disturbance estimator learns and looks up at the fused velocity
    too."""

    position_noise_m: float = 0.0
    velocity_noise_m_s: float = 0.0
    correlation_s: float = 0.25
    # the model's error is the disturbance estimate's residual, which wind makes large: a
    # time-varying wind (Neural-Fly's 8.5 + 2.4 sin t) lost 6.2 -> 8.0 cm trusting it to
    # 0.7 m/s^2, and 3 gave calm air as much (1.85 cm) as 0.7 (1.90)
    acc_noise_m_s2: float = 3.0
    # the disturbance learnt and looked up at the fused velocity, not the measured one
    # (with a filter only): LWPR learns each tick's velocity change less the model's
    # acceleration, and the estimate's smooth error, differenced over a tick, read as a
    # disturbance that a forgetting LWPR followed. Neural-Fly's plant at 0 m/s, mean cm after
    # lap 1, seeds 1 / 2: 1.85 / 2.01 -> 1.64 / 1.81 learnt there, 1.64 / 1.73 looked up
    # there too (8.5 + 2.4 sin t, seed 1: 4.76 -> 4.54 learnt there); without the estimate's
    # noise 0.68. The fused velocity's own change is the model's acceleration plus the
    # filter's correction, so the disturbance is still the measurements' to move
    feed_estimator: bool = False

    def __post_init__(self) -> None:
        for name in ("position_noise_m", "velocity_noise_m_s"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value >= 0.0):
                raise ValueError(f"{name} must be >= 0, got {value}")
        for name in ("correlation_s", "acc_noise_m_s2"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value > 0.0):
                raise ValueError(f"{name} must be > 0, got {value}")

    @property
    def enabled(self) -> bool:
        return self.position_noise_m > 0.0 and self.velocity_noise_m_s > 0.0


def steady_gain(cfg: StateFilterConfig, dt_s: float) -> tuple[FloatArray, FloatArray, FloatArray]:
    """(F (4, 4), B (4,), K (4, 2)): one axis's transition, acceleration input and
    steady-state Kalman gain for the state [p, v, e_p, e_v] sampled every ``dt_s``."""
    phi = math.exp(-dt_s / cfg.correlation_s)
    f = np.array([[1.0, dt_s, 0.0, 0.0], [0.0, 1.0, 0.0, 0.0],
                  [0.0, 0.0, phi, 0.0], [0.0, 0.0, 0.0, phi]])  # fmt: skip
    b = np.array([0.5 * dt_s * dt_s, dt_s, 0.0, 0.0])
    q = np.zeros((4, 4))
    q[:2, :2] = cfg.acc_noise_m_s2**2 * np.array([[dt_s**4 / 4.0, dt_s**3 / 2.0],
                                                  [dt_s**3 / 2.0, dt_s**2]])  # fmt: skip
    q[2, 2] = cfg.position_noise_m**2 * (1.0 - phi * phi)
    q[3, 3] = cfg.velocity_noise_m_s**2 * (1.0 - phi * phi)
    h = np.array([[1.0, 0.0, 1.0, 0.0], [0.0, 1.0, 0.0, 1.0]])
    # the measurements are the state's sum exactly: a small floor keeps S invertible
    r = np.diag([1e-10, 1e-10])
    p = np.diag([cfg.position_noise_m**2, cfg.velocity_noise_m_s**2] * 2)
    k = np.zeros((4, 2))
    for _ in range(2000):  # the Riccati iteration converges within a few hundred samples
        p = f @ p @ f.T + q
        k = p @ h.T @ np.linalg.inv(h @ p @ h.T + r)
        p = (np.eye(4) - k @ h) @ p
    return f, b, k


class StateFilter:
    """The fused position and velocity (3,) each of one vehicle, all axes alike.

    ``dt_s``: the samples' period (the loop's); a sample more than 1.5 of it after the last
    (or before it) restarts the filter from the measurement.
    """

    def __init__(self, cfg: StateFilterConfig, dt_s: float) -> None:
        self.config = cfg
        self.dt_s = dt_s
        # (read once: the property is a Python-level call on every position tick, issue 21)
        self._enabled = cfg.enabled
        self._f, self._b, self._k = steady_gain(cfg, dt_s) if cfg.enabled else (
            np.eye(4), np.zeros(4), np.zeros((4, 2)))
        self._t_s = -math.inf
        self._x = np.zeros((4, 3))  # rows p, v, e_p, e_v; a column per axis

    def update(
        self, t_s: float, pos_m: FloatArray, vel_m_s: FloatArray, acc_flown_m_s2: FloatArray,
        acc_disturbance_m_s2: FloatArray,
    ) -> tuple[FloatArray, FloatArray]:
        """The fused (position, velocity) at the sample of time ``t_s`` (s), measured
        ``pos_m``, ``vel_m_s``; the model's acceleration over the step that led to it is
        ``acc_flown_m_s2`` + ``acc_disturbance_m_s2`` (summed here: without a filter, on
        every position tick, not at all). A repeated sample (same time) returns the last
        fused state."""
        if not self._enabled:
            return pos_m, vel_m_s
        acc_model_m_s2 = acc_flown_m_s2 + acc_disturbance_m_s2
        dt_s = t_s - self._t_s
        x = self._x
        if not 0.0 <= dt_s <= 1.5 * self.dt_s:
            x[0], x[1], x[2:] = pos_m, vel_m_s, 0.0
            self._t_s = t_s
        elif dt_s > 0.0:
            x[:] = self._f @ x + np.outer(self._b, acc_model_m_s2)
            innovation = np.stack((pos_m - x[0] - x[2], vel_m_s - x[1] - x[3]))
            x += self._k @ innovation
            self._t_s = t_s
        return x[0].copy(), x[1].copy()
