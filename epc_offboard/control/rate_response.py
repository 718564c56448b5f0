"""The inner loop's answer to a body-rate command: its model, the commands still in flight,
its online identification, and whether the model can be trusted.

Pure numerics (no I/O). A body-rate command (SET_ATTITUDE_TARGET rates + thrust) shows in
the measured rates after a dead time Td, then follows a first-order lag tau with a static
gain K (PX4 main + SIH: 40-50 ms, 80-120 ms, 1; ArduCopter 4.8-dev SITL: 25-35 ms, 40-46 ms,
1.0-1.04)::

    w'(t) = (K w_cmd(t - Td) - w(t)) / tau            (per body axis)

* :class:`CommandHistory` keeps the commands sent (one per attitude tick, newest first) and
  the measured rate samples. Since the commands in flight are known, the attitude loop
  predicts the state over the sample's age and the dead time with them
  (:meth:`CommandHistory.predict`) and starts its QP there: the exact equivalent of
  augmenting the QP's state with the commands in flight, at a fraction of the cost, and the
  QP's parameter vector (what EPC's library is keyed on) keeps the 6 states of the
  delay-free model.
* :class:`RateIdentifier`: a bank of recursive least-squares fits, one per candidate dead
  time d (a multiple of the tick), of ``w(t) = a w(t - L h) + b mean(w_cmd over [t - d - L h,
  t - d))`` on roll and pitch; the candidate with the least exponentially weighted
  prediction error gives Td, and its (a, b) the lag ``tau = -L h / ln a`` and gain ``K = b /
  (1 - a)``. It learns only while the commands excite the vehicle, and every estimate is
  bounded to physical ranges.
* :class:`RateModelGate`: body rates only while the model in use predicts the measured
  rates, over its dead time and lag, within a bound; otherwise the autopilot's own attitude
  loop (quaternion), until the model has been good again for a while.
"""

from __future__ import annotations

import math
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass
from typing import cast

import numpy as np

from epc_offboard.common import jit
from epc_offboard.common.frames import FloatArray

# Physical ranges every estimate and configured value is bounded to (what an autopilot's rate
# response can be: PX4 measured 40-50 ms + 80-120 ms, ArduCopter 25-35 ms + 40-46 ms).
MAX_DEAD_TIME_S = 0.3
MIN_TIME_CONSTANT_S = 0.005
MAX_TIME_CONSTANT_S = 1.0
MIN_GAIN = 0.05
MAX_GAIN = 2.0


@dataclass(frozen=True)
class RateResponse:
    """How the autopilot's rate loop answers a body-rate command: dead time (s), first-order
    time constant (s), static gain (achieved / commanded rate)."""

    dead_time_s: float
    time_constant_s: float
    gain: float = 1.0

    def __post_init__(self) -> None:
        if not 0.0 <= self.dead_time_s <= MAX_DEAD_TIME_S:
            raise ValueError(
                f"dead_time_s must be in [0, {MAX_DEAD_TIME_S}], got {self.dead_time_s}"
            )
        if not MIN_TIME_CONSTANT_S <= self.time_constant_s <= MAX_TIME_CONSTANT_S:
            raise ValueError(
                f"time_constant_s must be in [{MIN_TIME_CONSTANT_S}, {MAX_TIME_CONSTANT_S}], "
                f"got {self.time_constant_s}"
            )
        if not MIN_GAIN <= self.gain <= MAX_GAIN:
            raise ValueError(f"gain must be in [{MIN_GAIN}, {MAX_GAIN}], got {self.gain}")


# What each autopilot was measured to do (docs/DESIGN.md, Real autopilots): the defaults when the
# configuration does not say. ArduCopter 4.8-dev SITL (531699d) answered body-rate doublets
# inside ATC_ACC_R_MAX after 25-35 ms of dead time with a 40 ms lag at gain 1.03, and this
# identifier found 25 ms, 40-46 ms, 0.99-1.04 in its body-rate flights (circle, figure-8 in
# wind); on the bundled ArduCopter personality 40 ms, 47 ms, 1.02. Its input shaping is the
# command model towards the rate asked (25 ms by default) and an attitude target the shaped
# rate turns, fed forward: no slow filter. The old default (100 ms, 0.3 s, 0.9: a fit to a
# personality that filtered body rates with 0.4 s) made the attitude EPC command 3-8 Hz
# chatter beyond ATC_ACC_R_MAX on the real one (a circle flew off by 12 m, 48 deg of tilt);
# a fit to that chatter read "40 ms, 0.136 s, gain 1.39". The dead time here is the
# personality's (15 ms more than the real one's: the identifier adopts the shorter in
# flight, and an overestimate by 15 ms costs less than an underestimate).
PX4_RATE_RESPONSE = RateResponse(dead_time_s=0.045, time_constant_s=0.1, gain=1.0)
ARDUPILOT_RATE_RESPONSE = RateResponse(dead_time_s=0.04, time_constant_s=0.045, gain=1.0)

# The model error tolerated before body rates are suspended (RateModelGate), per autopilot:
# ArduCopter bounds the shaped rate's change by ATC_ACC_R/P_MAX (19.2 rad/s^2), which a linear
# model does not hold, so a large step (entry into a 3 m/s wind: 29 deg asked at once) is
# mispredicted by up to 0.4-0.5 rad/s for a moment. At PX4's 0.4 the personality's windy
# figure-8 suspended body rates on entry, and the quaternion loop it fell back to (with the
# position loop set for body rates) left the envelope (76 deg); at 0.6 it flew 2.6 cm, 29 deg.
DEFAULT_MODEL_ERROR_MAX_RAD_S = {"px4": 0.4, "ardupilot": 0.6}


def default_rate_response(autopilot: str) -> RateResponse:
    """The measured response of ``autopilot`` ("ardupilot"; anything else is PX4's)."""
    return ARDUPILOT_RATE_RESPONSE if autopilot == "ardupilot" else PX4_RATE_RESPONSE


def default_model_error_max_rad_s(autopilot: str) -> float:
    """The model error ``autopilot`` ("ardupilot"; anything else: PX4's) is allowed."""
    return DEFAULT_MODEL_ERROR_MAX_RAD_S.get(autopilot, DEFAULT_MODEL_ERROR_MAX_RAD_S["px4"])


@dataclass(frozen=True)
class _Weights:
    """The response over j ticks of a unit command held j ticks before the end, and of the
    initial rate: closed forms of the ZOH first-order lag at the tick ``h``.

    Over m ticks from (angle0, rate0) with commands u_j (j = 0: the newest, acting last)::

        rate_m  = alpha^m rate0 + sum_j rate_w[j] u_j
        angle_m = angle0 + rate0_to_angle[m] rate0 + sum_j angle_w[j] u_j
    """

    alpha_pow: FloatArray  # (n + 1,) alpha^m
    rate0_to_angle: FloatArray  # (n + 1,)
    rate_w: FloatArray  # (n,) K alpha^j (1 - alpha)
    angle_w: FloatArray  # (n,) K (gamma + beta (1 - alpha^j))


def _weights(response: RateResponse, period_s: float, n: int) -> _Weights:
    tau, k = response.time_constant_s, response.gain
    alpha = math.exp(-period_s / tau)
    beta = tau * (1.0 - alpha)  # the angle a unit rate adds over one tick
    gamma = period_s - beta  # the angle a unit command adds over its own tick
    pw = alpha ** np.arange(n + 1, dtype=np.float64)
    return _Weights(
        alpha_pow=pw,
        rate0_to_angle=beta * (1.0 - pw) / (1.0 - alpha),
        rate_w=k * pw[:n] * (1.0 - alpha),
        angle_w=k * (gamma + beta * (1.0 - pw[:n])),
    )


class CommandHistory:
    """The body-rate commands of the last ``capacity`` attitude ticks (newest first) and the
    newest measured rate samples, on the attitude loop's clock.

    One :meth:`push` per tick. A tick that flew the autopilot's own attitude loop (quaternion)
    pushes a stand-in for the rate setpoints it made, which we do not see. Up to
    ``tolerated`` such ticks in a row (a late tick, as a loaded service has a few hundred a
    flight) keep the history valid evidence; a longer run ends it.
    """

    def __init__(
        self, period_s: float, capacity: int, n_samples: int = 96, tolerated: int = 2
    ) -> None:
        if not period_s > 0.0 or capacity < 2:
            raise ValueError("period_s > 0 and capacity >= 2 are required")
        self.period_s = period_s
        self.capacity = capacity
        # doubled ring, newest first: the newest n commands are always _u[_p : _p + n]
        self._u = np.zeros((2 * capacity, 3))
        self._p = 0
        self.valid_run = 0  # consecutive valid (body-rate) ticks, newest back
        self.tolerated = tolerated
        self._invalid_run = 0
        self.last_push_s = -math.inf
        self.samples: deque[tuple[float, FloatArray]] = deque(maxlen=n_samples)
        self.last_sample_key = math.nan  # the newest sample's own (vehicle) stamp

    def push(self, now_s: float, u_frd_rad_s: FloatArray, *, valid: bool) -> None:
        """The command sent at tick ``now_s`` (held until the next). Ticks the loop lost
        (late in real time) repeat the previous command: the autopilot held it."""
        gap = now_s - self.last_push_s
        missed = 0 if not math.isfinite(gap) else min(int(gap / self.period_s - 0.5), self.capacity)
        for _ in range(missed):
            self._write(self._u[self._p])
        self._write(u_frd_rad_s)
        self._invalid_run = 0 if valid else self._invalid_run + 1
        if self._invalid_run > self.tolerated:
            self.valid_run = 0
        else:
            self.valid_run = min(self.valid_run + 1 + missed, 2 * self.capacity)
        self.last_push_s = now_s

    def _write(self, u: FloatArray) -> None:
        p = (self._p - 1) % self.capacity
        self._u[p] = u
        self._u[p + self.capacity] = u
        self._p = p

    def newest(self, start: int, n: int) -> FloatArray:
        """(n, 3): the commands ``start`` .. ``start + n - 1`` ticks back (0: the newest)."""
        return self._u[self._p + start : self._p + start + n]

    def add_sample(self, t_s: float, rate_frd_rad_s: FloatArray) -> None:
        if self.samples and t_s <= self.samples[-1][0]:
            return  # a sample that does not advance time carries no new evidence
        self.samples.append((t_s, rate_frd_rad_s))

    def rate_at(self, t_s: float) -> FloatArray | None:
        """The measured rate at ``t_s`` interpolated between the samples around it (None when
        the samples held do not reach back that far)."""
        later: tuple[float, FloatArray] | None = None
        for sample in reversed(self.samples):
            if sample[0] <= t_s:
                if later is None:
                    return None
                t0, r0 = sample
                t1, r1 = later
                w = (t_s - t0) / (t1 - t0)
                out: FloatArray = r0 + w * (r1 - r0)
                return out
            later = sample
        return None


@dataclass(frozen=True)
class Prediction:
    """The state predicted over the sample's age and the dead time: Euler angles (rad) and
    body rates (rad/s), each (3,)."""

    angles_rad: FloatArray
    rates_frd_rad_s: FloatArray


class RatePredictor:
    """The model in use (dead time, lag, gain) on the tick grid: the state when the command
    sent now starts to act, and what the model says a rate sample should have been."""

    def __init__(self, response: RateResponse, period_s: float, capacity: int) -> None:
        self.period_s = period_s
        self.capacity = capacity
        self.set_response(response)

    def set_response(self, response: RateResponse) -> None:
        self.response = response
        self.dead_ticks = round(response.dead_time_s / self.period_s)
        self._w = _weights(response, self.period_s, self.capacity)
        self._stacked = np.vstack([self._w.rate_w, self._w.angle_w])
        # the span the model is judged over: its dead time plus its lag
        span_s = response.dead_time_s + response.time_constant_s
        self.check_ticks = max(2, min(round(span_s / self.period_s), self.capacity // 2))

    def ahead(
        self,
        history: CommandHistory,
        angles_rad: FloatArray,
        rates_frd_rad_s: FloatArray,
        age_ticks: int,
    ) -> Prediction:
        """From a sample ``age_ticks`` old, the state when the command sent this tick starts
        to act: ``age_ticks + dead_ticks`` ticks on, driven by the commands already sent."""
        m = max(0, min(age_ticks + self.dead_ticks, self.capacity))
        if m == 0:
            return Prediction(angles_rad, rates_frd_rad_s)
        w = self._w
        both = self._stacked[:, :m] @ history.newest(0, m)  # (2, 3): rates, angles
        rates = w.alpha_pow[m] * rates_frd_rad_s + both[0]
        angles = angles_rad + w.rate0_to_angle[m] * rates_frd_rad_s + both[1]
        return Prediction(angles, rates)

    def check(
        self, history: CommandHistory, t_s: float, rate_frd_rad_s: FloatArray, age_ticks: int
    ) -> FloatArray | None:
        """The model's error on the sample ``(t_s, rate)`` that is ``age_ticks`` old: the rate
        predicted from the sample ``check_ticks`` earlier with the commands sent since,
        minus the measured one (3,). None when the history cannot say (too short, or it
        holds a tick the autopilot's own loop flew)."""
        m = self.check_ticks
        start = age_ticks + self.dead_ticks
        if history.valid_run < start + m or start + m > self.capacity:
            return None
        before = history.rate_at(t_s - m * self.period_s)
        if before is None:
            return None
        w = self._w
        pred = w.alpha_pow[m] * before + w.rate_w[:m] @ history.newest(start, m)
        out: FloatArray = pred - rate_frd_rad_s
        return out


@dataclass(frozen=True)
class IdentifiedResponse:
    """The identifier's best fit: the response and its one-step prediction error (rad/s)."""

    response: RateResponse
    error_rad_s: float
    updates: int  # excited samples it has learnt from


RlsBankUpdate = Callable[..., None]


def rls_bank_update_numpy(
    u_newest: FloatArray,
    window: int,
    rate_now: FloatArray,
    rate_before: FloatArray,
    a: FloatArray,
    b: FloatArray,
    p11: FloatArray,
    p12: FloatArray,
    p22: FloatArray,
    cost: FloatArray,
    forget: float,
    cost_keep: float,
) -> None:
    """One sample into every candidate's RLS, in place (the reference; see the compiled twin).

    ``u_newest`` (n + window, 3): commands newest first, from the sample's tick back;
    candidate d's regressor is the mean of rows ``d .. d + window - 1``. Roll and pitch
    (axes 0, 1) are two observations of the same response.
    """
    n = a.shape[0]
    csum = np.vstack([np.zeros((1, 3)), np.cumsum(u_newest, axis=0)])
    ubar = (csum[window : window + n] - csum[:n]) / window  # (n, 3)
    for axis in (0, 1):
        y, x1, x2 = float(rate_now[axis]), float(rate_before[axis]), ubar[:, axis]
        err = y - a * x1 - b * x2
        px1 = p11 * x1 + p12 * x2
        px2 = p12 * x1 + p22 * x2
        den = forget + x1 * px1 + x2 * px2
        k1, k2 = px1 / den, px2 / den
        a += k1 * err
        b += k2 * err
        p11[:] = (p11 - k1 * px1) / forget
        p12[:] = (p12 - k1 * px2) / forget
        p22[:] = (p22 - k2 * px2) / forget
        cost[:] = cost_keep * cost + (1.0 - cost_keep) * err * err


def _rls_bank_update_loops(
    u_newest: FloatArray,
    window: int,
    rate_now: FloatArray,
    rate_before: FloatArray,
    a: FloatArray,
    b: FloatArray,
    p11: FloatArray,
    p12: FloatArray,
    p22: FloatArray,
    cost: FloatArray,
    forget: float,
    cost_keep: float,
) -> None:
    """:func:`rls_bank_update_numpy` as plain loops, for numba (one call, no temporaries)."""
    n = a.shape[0]
    for axis in range(2):
        y, x1 = rate_now[axis], rate_before[axis]
        s = 0.0
        for j in range(window):
            s += u_newest[j, axis]
        for d in range(n):
            if d > 0:  # slide the window one tick older
                s += u_newest[d + window - 1, axis] - u_newest[d - 1, axis]
            x2 = s / window
            err = y - a[d] * x1 - b[d] * x2
            px1 = p11[d] * x1 + p12[d] * x2
            px2 = p12[d] * x1 + p22[d] * x2
            den = forget + x1 * px1 + x2 * px2
            k1, k2 = px1 / den, px2 / den
            a[d] += k1 * err
            b[d] += k2 * err
            p11[d] = (p11[d] - k1 * px1) / forget
            p12[d] = (p12[d] - k1 * px2) / forget
            p22[d] = (p22[d] - k2 * px2) / forget
            cost[d] = cost_keep * cost[d] + (1.0 - cost_keep) * err * err


def _compile_rls() -> RlsBankUpdate | None:
    """The compiled bank update (numba, cached on disk as kernels.py's), or None: on the
    numpy twins (a cold start, ``common.jit``) numba is not even imported, or the service's
    own warm-up imported it (0.2 s) and compiled this kernel (0.5 s of CPU, several seconds
    of a cold start on a loaded computer) on the way to its first tick."""
    if not jit.enabled():
        return None
    try:
        import numba
    except ImportError:
        return None
    try:
        return cast(RlsBankUpdate, numba.njit(_rls_bank_update_loops, cache=True, nogil=True))
    except RuntimeError:  # no writable cache location: compile in memory
        return cast(RlsBankUpdate, numba.njit(_rls_bank_update_loops, cache=False, nogil=True))


_RLS_JIT = _compile_rls()
rls_bank_update: RlsBankUpdate = _RLS_JIT if _RLS_JIT is not None else rls_bank_update_numpy


def warm_up() -> None:
    """Compile (or load) the bank update now, not in the first excited attitude tick."""
    n, window = 3, 2
    z = np.zeros(n)
    rls_bank_update(np.zeros((n + window, 3)), window, np.zeros(3), np.zeros(3),
                    z.copy(), z.copy(), np.ones(n), z.copy(), np.ones(n), z.copy(), 0.99, 0.99)


class RateIdentifier:
    """Recursive least squares over candidate dead times ``0, h, .., max_dead_time_s`` (h the
    attitude tick), on roll and pitch (ArduCopter and PX4 shape yaw differently).

    Per candidate d: ``w(t) = a w(t - L h) + b ubar_d(t)``, ubar_d the mean command over
    ``[t - d - L h, t - d)``; for the lag model ``a = exp(-L h / tau)``, ``b = K (1 - a)``.
    ``L h`` (``window_s``, 20 ms) is long enough that the command's share of a step is not
    lost in the sensor noise, short against the lag. Forgetting (``memory_s``) lets it follow
    a changed response. Cost per sample: a few vector operations over the candidates.
    """

    def __init__(
        self,
        prior: RateResponse,
        period_s: float,
        *,
        max_dead_time_s: float = 0.25,
        window_s: float = 0.04,
        memory_s: float = 8.0,
        min_excitation_rad_s: float = 0.1,
        min_updates: int = 200,
    ) -> None:
        self.period_s = period_s
        self.prior = prior
        self.window = max(1, round(window_s / period_s))
        self.n_delays = round(max_dead_time_s / period_s) + 1
        self.span = self.n_delays + self.window  # command ticks one update reads
        step_s = self.window * period_s
        self.step_s = step_s
        n = self.n_delays
        a0 = math.exp(-step_s / prior.time_constant_s)
        self.a = np.full(n, a0)
        self.b = np.full(n, prior.gain * (1.0 - a0))
        self.p11 = np.full(n, 10.0)
        self.p12 = np.zeros(n)
        self.p22 = np.full(n, 10.0)
        self.cost = np.zeros(n)  # exponentially weighted squared prediction error
        # a sample arrives about every tick; forgetting and the error average span memory_s
        self.forget = 1.0 - period_s / memory_s
        self.cost_keep = 1.0 - period_s / (0.25 * memory_s)
        self.min_excitation_rad_s = min_excitation_rad_s
        self.min_updates = min_updates
        self.clearly = 0.8
        self.updates = 0
        self._u_mean = [0.0, 0.0]
        self._u_sq = [0.0, 0.0]
        # the excitation is judged over about 0.25 s: long enough to span a manoeuvre's
        # commands, short enough that the quiet (noise-driven, closed-loop) ticks after one
        # are not taken for it
        self._exc_keep = 1.0 - period_s / 0.25

    def excited(self) -> bool:
        """Whether the commands of the last half second vary enough to learn from (std)."""
        floor = self.min_excitation_rad_s**2
        return any(self._u_sq[i] - self._u_mean[i] ** 2 > floor for i in (0, 1))

    def note_command(self, u_frd_rad_s: FloatArray) -> None:
        """Each tick's command (roll, pitch used): the excitation's running variance."""
        k = self._exc_keep
        for i in (0, 1):  # (floats: numpy on two elements costs more than it saves)
            u = float(u_frd_rad_s[i])
            self._u_mean[i] = k * self._u_mean[i] + (1.0 - k) * u
            self._u_sq[i] = k * self._u_sq[i] + (1.0 - k) * u * u

    def update(
        self, history: CommandHistory, rate_now: FloatArray, rate_before: FloatArray, age_ticks: int
    ) -> None:
        """One sample: ``rate_now`` measured ``age_ticks`` ticks ago, ``rate_before`` (both
        (3,), FRD rad/s) one window earlier. The caller checks the history is valid."""
        if not self.excited():
            return
        rls_bank_update(
            history.newest(age_ticks, self.span), self.window, rate_now, rate_before,
            self.a, self.b, self.p11, self.p12, self.p22, self.cost, self.forget, self.cost_keep,
        )  # fmt: skip
        self.updates += 1

    def best(self) -> IdentifiedResponse | None:
        """The candidate with the least error, bounded to physical ranges; None until
        ``min_updates`` excited samples. The prior's dead time is kept unless another
        predicts clearly better (by ``clearly``): closed-loop data of a quiet flight barely
        tells the candidates apart."""
        if self.updates < self.min_updates:
            return None
        i = int(np.argmin(self.cost))
        i_prior = min(round(self.prior.dead_time_s / self.period_s), self.n_delays - 1)
        if not self.cost[i] < self.clearly * self.cost[i_prior]:
            i = i_prior
        a = min(max(float(self.a[i]), 1e-3), 1.0 - 1e-6)
        tau = -self.step_s / math.log(a)
        gain = float(self.b[i]) / (1.0 - a)
        response = RateResponse(
            dead_time_s=min(i * self.period_s, MAX_DEAD_TIME_S),
            time_constant_s=min(max(tau, MIN_TIME_CONSTANT_S), MAX_TIME_CONSTANT_S),
            gain=min(max(gain, MIN_GAIN), MAX_GAIN),
        )
        return IdentifiedResponse(response, math.sqrt(float(self.cost[i])), self.updates)


class RateModelGate:
    """Body rates while the model predicts the measured rates; else the autopilot's attitude
    loop for ``hold_s`` (doubling, up to ``max_hold_s``, after each failed try), then body
    rates on probation: trusted again once good for ``probation_s``.

    Judged on exponentially weighted RMS over ``average_s``: the model's error is bad when
    above ``max(error_max_rad_s, error_ratio * rate RMS)`` (a relative bound, so fast
    manoeuvres with a good model are not mistaken for a bad one). The attitude loop cannot
    tell a good model from a bad one while the autopilot flies its own attitude loop: only
    flying body rates tells, hence the probation.
    """

    def __init__(
        self,
        *,
        error_max_rad_s: float,
        error_ratio: float,
        hold_s: float,
        probation_s: float,
        period_s: float,
        average_s: float = 0.3,
        max_hold_s: float = 30.0,
    ) -> None:
        self.error_max_rad_s = error_max_rad_s
        self.error_ratio = error_ratio
        self.base_hold_s = hold_s
        self.hold_s = hold_s
        self.max_hold_s = max(max_hold_s, hold_s)
        self.probation_s = probation_s
        self.keep = 1.0 - period_s / average_s
        self.min_checks = round(average_s / period_s)
        self.trusted = True
        self.until_s = -math.inf  # fallback: quaternion until then
        self.good_since_s = math.nan  # probation: first good check
        self.fallbacks = 0
        self.events: list[str] = []  # transitions for the service to log
        self._reset()

    def _reset(self) -> None:
        self.err_sq = 0.0
        self.rate_sq = 0.0
        self.checks = 0

    @property
    def error_rms_rad_s(self) -> float:
        return math.sqrt(self.err_sq)

    def use_rates(self, now_s: float) -> bool:
        """Body rates at ``now_s``: trusted, or on probation after the hold."""
        return self.trusted or now_s >= self.until_s

    def check(self, now_s: float, err_frd_rad_s: FloatArray, rate_frd_rad_s: FloatArray) -> None:
        """One check of the model on a measured sample (only while body rates fly)."""
        k = self.keep
        self.err_sq = k * self.err_sq + (1.0 - k) * float(err_frd_rad_s @ err_frd_rad_s)
        self.rate_sq = k * self.rate_sq + (1.0 - k) * float(rate_frd_rad_s @ rate_frd_rad_s)
        self.checks += 1
        if self.checks < self.min_checks:
            return
        # (the averages start at zero: scaled up to what the checks so far weigh)
        scale = 1.0 / (1.0 - k**self.checks)
        err = math.sqrt(self.err_sq * scale)
        bound = max(self.error_max_rad_s, self.error_ratio * math.sqrt(self.rate_sq * scale))
        if err > bound:
            self._fall_back(now_s, err, bound)
        elif not self.trusted:
            if math.isnan(self.good_since_s):
                self.good_since_s = now_s
            elif now_s - self.good_since_s >= self.probation_s:
                self.trusted = True
                self.hold_s = self.base_hold_s
                self.events.append(
                    f"body rates trusted again: the rate model's error {err:.3f} rad/s "
                    f"within {bound:.3f} for {self.probation_s:.1f} s"
                )

    def _fall_back(self, now_s: float, err: float, bound: float) -> None:
        if self.trusted:
            self.events.append(
                f"body rates suspended: the rate model predicts the measured rates "
                f"{err:.3f} rad/s off (bound {bound:.3f}); the autopilot's attitude loop "
                f"flies for {self.hold_s:.1f} s"
            )
        else:  # failed probation: wait longer before the next try
            self.hold_s = min(2.0 * self.hold_s, self.max_hold_s)
        self.trusted = False
        self.fallbacks += 1
        self.until_s = now_s + self.hold_s
        self.good_since_s = math.nan
        self._reset()
