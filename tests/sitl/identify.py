"""Identify an autopilot's body-rate response from commands and measured rates (tests only).

Two fits, the ones the real autopilots were characterised with:

* :func:`dead_time_and_lag`: a step's response as dead time + first-order lag,
  ``y(t) = y0 + (y1 - y0) (1 - exp(-(t - t_step - d) / tau))`` for ``t > t_step + d``;
* :func:`best_lag_and_gain`: the delay at which the measured rate matches the command best
  (least squares over candidate delays) and the gain of that match.
"""

from __future__ import annotations

import numpy as np

from epc_offboard.common.frames import FloatArray


def dead_time_and_lag(
    t_s: FloatArray, rate: FloatArray, t_step_s: float, before: float, after: float
) -> tuple[float, float]:
    """Dead time and time constant (s) of a step from ``before`` to ``after`` at ``t_step_s``,
    fitted by least squares on a 1 ms grid to samples ``rate`` (n,) at times ``t_s`` (n,)."""
    dt = np.asarray(t_s) - t_step_s
    y = (np.asarray(rate) - before) / (after - before)  # the normalised step response
    taus = np.arange(0.01, 0.4005, 0.001)
    best = (np.inf, 0.0, 0.0)
    for d in np.arange(0.0, 0.2005, 0.001):
        x = np.clip(dt - d, 0.0, None)
        err = np.sum((y[:, None] - (1.0 - np.exp(-x[:, None] / taus[None, :]))) ** 2, axis=0)
        i = int(np.argmin(err))
        if err[i] < best[0]:
            best = (float(err[i]), float(d), float(taus[i]))
    return best[1], best[2]


def best_lag_and_gain(
    dt_s: float, command: FloatArray, rate: FloatArray, max_lag_s: float = 0.5
) -> tuple[float, float]:
    """The delay (s) at which ``rate`` (n,) best matches ``gain * command`` (n,), both sampled
    every ``dt_s``, and that gain (least squares through the origin)."""
    u, y = np.asarray(command), np.asarray(rate)
    best = (np.inf, 0.0, 0.0)
    for k in range(round(max_lag_s / dt_s) + 1):
        uk, yk = u[: len(u) - k], y[k:]
        gain = float(uk @ yk / (uk @ uk))
        err = float(np.mean((yk - gain * uk) ** 2))
        if err < best[0]:
            best = (err, k * dt_s, gain)
    return best[1], best[2]
