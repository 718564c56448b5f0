"""The position loop's command dead time: where the vehicle will be when the command sent now
starts to act.

A quaternion setpoint is not flown at once: PX4 main + SIH answered the service's with
0.14-0.15 s of dead time before a 0.13-0.15 s lag (README, "PX4's answer to a quaternion
setpoint"). The position model (``models.position_model_lagged``) keeps only the lag; the
dead time is handled as the attitude loop handles its own (``control/rate_response.py``):
the commands still in flight are known, so the measured state is carried forward over the
dead time with them, and the QP starts from there, on the reference as it will be then
(the equivalent of augmenting the state with the commands in flight, but the QP keeps its 9
states and the EPC library its parameter vector: a hit is still the QP's optimum).

Pure numerics (no I/O).
"""

from __future__ import annotations

import math

import numpy as np
import numpy.typing as npt

from epc_offboard.common.frames import FloatArray
from epc_offboard.control.models import position_model_lagged, velocity_disturbance_input

# the longest command dead time configurable (s): PX4's quaternion answer is 0.275 s in all
MAX_COMMAND_DEAD_TIME_S = 0.5

# The dead time from a position command to the acceleration it starts to produce, per
# (autopilot, attitude mode), as flown (README "The position loop's command dead time"):
# - PX4 quaternion: PX4 main + SIH answered the attitude with 0.14-0.15 s of dead time before
#   a 0.13-0.15 s lag, and the bundled PX4 personality as it (0.275 s in all). The position
#   model's lag is 0.12 s, and what the QP starts from is the estimate, not the ground
#   truth: on that personality (lockstep, seed 0) the quaternion circle flew 6.32 / 5.35 /
#   4.89 / 4.57 / 4.66 cm with 0 / 0.15 / 0.2 / 0.25 / 0.3 s, the windy figure-8 8.68 /
#   7.10 / 6.17 cm with 0 / 0.15 / 0.25 s. With the heavier position weights (issue 24)
#   and no dead time it oscillated (circle 60 cm, 40 deg of tilt); circle 3.01 / 3.12 /
#   6.89 cm (21 deg) with 0.15 / 0.25 / 0.35 s, windy figure-8 4.13 / 4.47 cm with 0.15 /
#   0.25 s: 0.15 s, the dead time fitted on the real PX4, and the furthest from the
#   oscillation a dead time overestimated by 0.2 s starts;
# - body rates ("epc") on PX4: the attitude EPC predicts over the rate loop's own dead time,
#   but the attitude it reaches still answers the position loop late: circle 4.57 / 4.07 /
#   3.57 / 3.27 / 3.36 / 4.48 cm with 0 / 0.05 / 0.1 / 0.15 / 0.2 / 0.25 s, windy figure-8
#   6.00 / 4.65 / 4.44 cm with 0 / 0.1 / 0.15 s. With the heavier position weights (issue
#   24) it gained nothing then (circle 1.96 cm with 0 and 0.15 s, windy figure-8 2.67 /
#   2.92 cm), and 0.15 s cost the bounded zig-zag's saved library its use (a second
#   flight's misses 119 -> 271 of 319). But the vehicle's acceleration does answer late:
#   fitted on the bundled PX4 personality (lockstep, the model's 0.12 s lag held), a command
#   shows in the ground truth's acceleration 50-60 ms later (circle 50 ms, bounded zig-zag
#   60 ms; free: 80 ms before a 90 ms lag), about the rate loop's own 45 ms. Planned with
#   none, a plan riding a velocity bound brakes just in time for its model and the vehicle
#   overshoots by its acceleration times that dead time: the bounded zig-zag with LWPR's
#   4 m/s^2 of drag compensation flew 3.06 m/s against 3.0 (221 ticks over, seed 0), and no
#   constraint tightening of a few cm/s covers it. With 50 ms (seeds 0 / 1): 0 violations,
#   2.97 / 2.97 m/s, hits 58 -> 70 %; and, since the disturbance along the horizon is in
#   the model (issue 24), the circle's max 0.84 -> 0.47 cm and the windy figure-8's RMSE
#   0.87 -> 0.46 cm (seed 1): 0.05;
# - ArduPilot quaternion (its personality, lockstep, seed 0): circle 5.26 / 4.40 / 3.78 /
#   4.16 / 5.24 cm with 0 / 0.1 / 0.2 / 0.25 / 0.3 s: 0.2 s;
# - ArduPilot body rates: not flown by default ("auto" flies quaternion there). With the
#   measured rate model (40 ms, 45 ms, 1) and no dead time, on its personality (lockstep,
#   seeds 0 / 1): circle 1.97 / 1.93 cm, windy figure-8 2.62 / 2.61 cm; the real
#   ArduCopter's circle 2.92 cm on its EKF (load 12-15). Not swept: 0.
DEFAULT_COMMAND_DEAD_TIME_S: dict[tuple[str, str], float] = {
    ("px4", "autopilot"): 0.15,
    ("px4", "epc"): 0.05,
    ("ardupilot", "autopilot"): 0.2,
    ("ardupilot", "epc"): 0.0,
}


def default_command_dead_time_s(autopilot: str, attitude_mode: str) -> float:
    """The measured dead time for ``autopilot`` ("px4", "ardupilot"; another: PX4's) flown
    in ``attitude_mode`` ("epc": body rates, "autopilot": quaternion)."""
    name = autopilot if autopilot in ("px4", "ardupilot") else "px4"
    return DEFAULT_COMMAND_DEAD_TIME_S.get((name, attitude_mode), 0.0)


def check_span_s(name: str, value: float) -> None:
    """A command dead time or a state latency: finite, in [0, MAX_COMMAND_DEAD_TIME_S]."""
    if not (math.isfinite(value) and 0.0 <= value <= MAX_COMMAND_DEAD_TIME_S):
        raise ValueError(f"{name} must be in [0, {MAX_COMMAND_DEAD_TIME_S}], got {value}")


def _ticks(span_s: float, period_s: float) -> int:
    """``span_s`` in whole ticks, halves up (15 ms of 10 ms ticks: 2, not round()'s even)."""
    return math.floor(span_s / period_s + 0.5 + 1e-9)


class DeadTimePredictor:
    """The lagged position model ``x = [p, v, a]`` carried over ``dead_time_s`` plus
    ``latency_s`` with the commands sent in that time, and a disturbance ``d`` held constant
    (it enters v as in the QP's model). The span is carried exactly, not in whole ticks of
    ``period_s``: a span of 1.5 ticks (Neural-Fly's plant: 15 ms of telemetry delay on 10 ms
    ticks) is the oldest command in flight over its last half tick, then one whole tick of
    the newest. Rounded to ticks, the state was carried 5 ms short or long."""

    def __init__(
        self,
        tau_acc_s: tuple[float, float, float],
        period_s: float,
        dead_time_s: float,
        latency_s: float = 0.0,
    ) -> None:
        check_span_s("dead_time_s", dead_time_s)
        check_span_s("latency_s", latency_s)
        self.period_s = period_s
        # ``latency_s``: how old the measured state already is when it arrives, beyond what
        # its time stamp shows (an estimator's output lag and the link). The commands that
        # act from the state's true time to where the command sent now acts were sent over
        # latency + dead time: x0 is carried over both, while the reference window starts
        # at the dead time alone (the plan is for the vehicle as it will be, on the
        # reference as it will be then; a dead time standing in for the latency shifted the
        # reference as well, and the vehicle led it by the latency)
        span = (dead_time_s + latency_s) / period_s
        whole = math.floor(span + 1e-9)
        frac = span - whole if span - whole > 1e-9 else 0.0  # of the oldest command's tick
        n = self.steps = whole + (frac > 0.0)  # the commands in flight
        self.dead_time_s = min(_ticks(dead_time_s, period_s), n) * period_s  # as flown: ticks
        model = position_model_lagged(period_s, tau_acc_s)
        A, B = model.A, model.B
        E = velocity_disturbance_input(model)
        powers = [np.eye(9)]
        for _ in range(n):
            powers.append(A @ powers[-1])
        # x_n = A^n x_0 + sum_j A^(n-1-j) B u_j + sum_j A^j E d; u_0 the oldest in flight
        w = np.zeros((9, 3 * n))
        for j in range(n):
            w[:, 3 * j : 3 * j + 3] = powers[n - 1 - j] @ B
        self._phi = powers[n]
        self._wd = sum(powers[:n], np.zeros((9, 9))) @ E
        if frac:
            # the oldest command acts over the last ``frac`` of its tick only: x_0 is carried
            # that long by the model discretised at that step, then ``whole`` ticks
            part = position_model_lagged(frac * period_s, tau_acc_s)
            carry = powers[whole]
            self._phi = carry @ part.A
            w[:, 0:3] = carry @ part.B
            self._wd = carry @ velocity_disturbance_input(part) + sum(
                powers[:whole], np.zeros((9, 9))) @ E  # fmt: skip
        self._w = w
        # the commands of the last n ticks, oldest first (one row a tick); the newest
        # _in_flight of them were sent without a gap
        self._sent = np.zeros((n, 3))
        self._in_flight = 0
        self._last_sent_s = -math.inf
        self._carried = np.zeros((n, 3))  # ahead()'s commands, the ring left untouched
        # window(): the stage indices of the last (lead, steps, stages) asked for
        self._window_key: tuple[float, int, int] | None = None
        self._window_idx: tuple[npt.NDArray[np.intp], npt.NDArray[np.intp]] | None = None
        self._window_rows: slice | None = None  # the same rows as a slice, where they are one

    def sent(self, t_s: float, acc_cmd_ned_m_s2: FloatArray) -> None:
        """The command sent at tick ``t_s`` (it acts ``dead_time_s`` later)."""
        if not self.steps:
            return
        if t_s - self._last_sent_s > 3.0 * self.period_s:
            self._in_flight = 0
        buf = self._sent
        buf[:-1] = buf[1:]
        buf[-1] = acc_cmd_ned_m_s2
        self._in_flight = min(self._in_flight + 1, self.steps)
        self._last_sent_s = t_s

    def matrices(self) -> tuple[FloatArray, FloatArray, FloatArray]:
        """(Phi (9, 9), W (9, 3 steps), Wd (9, 3)): :meth:`ahead` is ``Phi x0 + W sent +
        Wd d``, ``sent`` the commands in flight flattened, oldest first."""
        return self._phi, self._w, self._wd

    def flight(self, t_s: float) -> tuple[FloatArray, int]:
        """The commands sent (steps, 3; oldest first, the ring itself: read it, do not
        write into it) and how many of its oldest rows were not flown by us at tick ``t_s``
        (:meth:`ahead` takes the acceleration flown now for them)."""
        n = self.steps
        if t_s - self._last_sent_s > 3.0 * self.period_s:
            return self._sent, n
        return self._sent, n - self._in_flight

    def lead(self, step_s: float) -> tuple[int, float]:
        """:meth:`window`'s rows as (base, frac): stages ``base + 1 + k``, ``frac`` of the
        way to the next (0: none)."""
        lead_stages = self.dead_time_s / step_s
        if lead_stages <= 0.0:
            return 0, 0.0
        base = math.floor(lead_stages + 1e-9)
        frac = max(lead_stages - base, 0.0)
        return base, (0.0 if frac < 1e-9 else frac)

    def ahead(self, x0: FloatArray, d_ned_m_s2: FloatArray, t_s: float) -> FloatArray:
        """The state (9,) ``dead_time_s`` after ``x0`` measured at ``t_s``, driven by the
        commands in flight (one a tick). Commands sent before a gap of more than three ticks
        (an entry, a re-entry after a failsafe: nothing of ours was flown) are not in
        flight; the ticks without one keep the acceleration flown now."""
        n = self.steps
        if n == 0:
            return x0
        if t_s - self._last_sent_s > 3.0 * self.period_s:
            self._in_flight = 0
        buf = self._sent
        missing = n - self._in_flight
        if missing:
            # (a copy: the ring keeps what was sent, a later call sees it as it was)
            carried = self._carried
            carried[:] = buf
            carried[:missing] = x0[6:9]
            buf = carried
        out: FloatArray = self._phi @ x0 + self._w @ buf.reshape(-1) + self._wd @ d_ned_m_s2
        return out

    def window(self, stages: FloatArray, step_s: float, steps: int) -> FloatArray:
        """The reference window the QP plans on: (steps, 9) rows of ``stages`` (M + 1, 9),
        ``step_s`` apart from stage 0, at stages ``lead + 1 .. lead + steps`` where ``lead``
        is this dead time in steps; linear between two stages, the last stage held beyond
        the end (a horizon shorter than the lead needs). The stage indices are computed once
        (they change only with the horizon). Without interpolation the window may be a view
        of ``stages``: read it, do not write into it."""
        lead_stages = self.dead_time_s / step_s
        if lead_stages <= 0.0:
            return stages[1 : steps + 1]
        # a whole number of steps that rounding left a hair short (0.15 / 0.05) is whole
        base = math.floor(lead_stages + 1e-9)
        key = (lead_stages, steps, stages.shape[0])
        if key != self._window_key or self._window_idx is None:
            last = stages.shape[0] - 1
            idx = np.minimum(np.arange(base + 1, base + 1 + steps), last)
            self._window_idx = (idx, np.minimum(idx + 1, last))
            self._window_key = key
            # the window's rows as a slice when no stage is held past the end: a view, not
            # numpy's fancy-indexed copy (its machinery was ~25 us of a cold tick in real
            # time, issue 21; the whole-step dead times, PX4's 0.15 s, take no more)
            self._window_rows = slice(base + 1, base + 1 + steps) if base + steps <= last else None
        frac = max(lead_stages - base, 0.0)
        rows = self._window_rows
        lo: FloatArray = stages[self._window_idx[0] if rows is None else rows]
        if frac < 1e-9:
            return lo
        # lo + frac (hi - lo), in that order, in place
        out: FloatArray = stages[self._window_idx[1]]
        out -= lo
        out *= frac
        out += lo
        return out
