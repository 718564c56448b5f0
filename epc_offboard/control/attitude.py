"""The attitude loop (200 Hz): body rates towards the position loop's attitude.

Pure numerics (no asyncio, no MAVLink). :meth:`AttitudeLoop.attitude_tick`: EPC on
x = [roll, pitch, yaw, p, q, r] with body-rate commands as input and the autopilot's rate
response (dead time, first-order lag, gain: :mod:`~epc_offboard.control.rate_response`),
reference = the position loop's attitude with zero rates -> body rates + thrust.

The dead time is handled by prediction: the measured state is carried forward over its age
and the dead time with the commands already sent (they are known), and the QP starts where
the command it chooses begins to act. (A model without the delay, on PX4's 45 ms + 100 ms,
oscillated at about 4.5 Hz and flipped the vehicle.) The response is identified online and
body rates are flown only while the model predicts the measured rates
(:meth:`AttitudeLoop.rate_model_trusted`); outside the envelope where the hover
linearisation holds (:meth:`AttitudeLoop.rates_trusted`) the attitude goes to the
autopilot's own loop too. When the EPC cannot answer, :meth:`AttitudeLoop.attitude_fallback`
is a P law on the angle error.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Any, Literal

import numpy as np

from epc_offboard.common import frames
from epc_offboard.common.airframe import Airframe
from epc_offboard.common.frames import FloatArray
from epc_offboard.control.epc import budgeted_controller
from epc_offboard.control.models import attitude_model
from epc_offboard.control.qp import MpcProblem
from epc_offboard.control.rate_response import (
    MAX_DEAD_TIME_S,
    PX4_RATE_RESPONSE,
    CommandHistory,
    IdentifiedResponse,
    RateIdentifier,
    RateModelGate,
    RatePredictor,
    RateResponse,
    default_model_error_max_rad_s,
    default_rate_response,
)
from epc_offboard.control.types import AttitudeCommand, PositionOutput, VehicleState

Vec3 = tuple[float, float, float]


@dataclass(frozen=True)
class AttitudeControlConfig:
    # epc: body rates from the attitude EPC; autopilot: quaternion + thrust to its own loop;
    # auto: epc on PX4, autopilot on ArduPilot (README "Attitude mode" has both modes' figures)
    mode: Literal["auto", "epc", "autopilot"] = "auto"
    # The QP predicts over horizon * dt_s from where the command sent now starts to act: it
    # must see the rate loop's lag play out (2.5 lags), which 10 steps of the old 10 ms did
    # not. Unset: 25 ms (PX4: 250 ms for a 100 ms lag), longer for a slower response
    # (ArduPilot's 0.3 s: 75 ms). A coarser step than the loop's: the loop still answers
    # every 5 ms with the QP's first input, and a library hit is still the QP's optimum.
    horizon: int = 10
    dt_s: float | None = None
    # The autopilot's rate response (rate_response.py): unset, the measured one of the
    # autopilot flown (link.autopilot; PX4's when "auto"): PX4 45 ms, 100 ms, gain 1;
    # ArduPilot 40 ms, 45 ms, gain 1 (rate_response.py has the measurements).
    rate_dead_time_s: float | None = None
    rate_time_constant_s: float | None = None  # first-order lag
    rate_gain: float | None = None  # achieved / commanded rate
    # Identify the response online and fly the identified dead time once known (its lag and
    # gain are reported, the QP keeps the configured ones: they key its library).
    identify: bool = True
    identify_max_dead_time_s: float = 0.25
    # Body rates only while the model predicts the measured rates (over its dead time and
    # lag) within max(model_error_max_rad_s, model_error_ratio * the rates' RMS) (unset:
    # PX4 0.4 rad/s, ArduPilot 0.6: its acceleration limit, rate_response.py); else
    # quaternion for model_fallback_hold_s (doubling after each failed try), then body rates
    # again on probation until good for model_probation_s.
    model_check: bool = True
    model_error_max_rad_s: float | None = None
    model_error_ratio: float = 0.6
    model_fallback_hold_s: float = 2.0
    model_probation_s: float = 1.0
    q_angle: Vec3 = (60.0, 60.0, 20.0)
    q_rate: Vec3 = (0.3, 0.3, 0.3)
    r_rate: Vec3 = (0.02, 0.02, 0.05)
    fallback_gain_1_s: float = 6.0  # P on angle error when the attitude EPC cannot answer
    library_size: int = 200
    query_budget_us: float = 200.0  # as position.library.query_budget_us
    # The attitude EPC is linearised about hover (Euler angles, body rates). Beyond this tilt,
    # or this far from its attitude target, its body rates are not to be trusted (in a soak
    # under CPU load it chattered between +-max rate at 60 deg and flipped the vehicle): the
    # attitude goes to the autopilot's own (quaternion) attitude loop until back inside.
    rates_max_tilt_deg: float = 55.0
    rates_max_error_deg: float = 35.0

    def __post_init__(self) -> None:
        if self.horizon < 1 or (self.dt_s is not None and not self.dt_s > 0.0):
            raise ValueError("horizon >= 1 and dt_s > 0 are required")
        for key, field_name in (("rate_dead_time_s", "dead_time_s"),
                                ("rate_time_constant_s", "time_constant_s"),
                                ("rate_gain", "gain")):  # fmt: skip
            if getattr(self, key) is None:
                continue
            try:
                dataclasses.replace(PX4_RATE_RESPONSE, **{field_name: getattr(self, key)})
            except ValueError as exc:
                raise ValueError(f"{key}: {exc}") from exc
        if not 0.0 < self.identify_max_dead_time_s <= MAX_DEAD_TIME_S:
            raise ValueError(
                f"identify_max_dead_time_s must be in (0, {MAX_DEAD_TIME_S}], "
                f"got {self.identify_max_dead_time_s}"
            )
        for name in ("model_error_max_rad_s", "model_error_ratio", "model_fallback_hold_s",
                     "model_probation_s"):  # fmt: skip
            if getattr(self, name) is not None and not getattr(self, name) > 0.0:
                raise ValueError(f"{name} must be > 0, got {getattr(self, name)}")
        if not self.query_budget_us > 0.0:
            raise ValueError(f"query_budget_us must be > 0, got {self.query_budget_us}")
        for name in ("rates_max_tilt_deg", "rates_max_error_deg"):
            if not 0.0 < getattr(self, name) <= 180.0:
                raise ValueError(f"{name} must be in (0, 180], got {getattr(self, name)}")

    def rate_response(self, autopilot: str) -> RateResponse:
        """The configured rate response, unset values from ``autopilot``'s measured one."""
        base = default_rate_response(autopilot)
        return RateResponse(
            dead_time_s=_or(self.rate_dead_time_s, base.dead_time_s),
            time_constant_s=_or(self.rate_time_constant_s, base.time_constant_s),
            gain=_or(self.rate_gain, base.gain),
        )


    def prediction_dt_s(self, response: RateResponse) -> float:
        """The QP's step: ``dt_s``, or unset one whose horizon spans 2.5 lags (>= 25 ms)."""
        if self.dt_s is not None:
            return self.dt_s
        return max(0.025, round(2.5 * response.time_constant_s / self.horizon, 3))


def _or(value: float | None, default: float) -> float:
    return default if value is None else value


def attitude_problem(
    cfg: AttitudeControlConfig, response: RateResponse, max_rate_frd_rad_s: Vec3
) -> MpcProblem:
    """The attitude QP: Euler angles and body rates over ``cfg.horizon`` steps of
    ``cfg.prediction_dt_s`` with ``response``'s lag and gain (its dead time is predicted over before
    the QP starts), body-rate commands bounded by the airframe's ``max_rate_frd_rad_s``."""
    rmax = np.array(max_rate_frd_rad_s, dtype=np.float64)
    return MpcProblem(
        attitude_model(cfg.prediction_dt_s(response), response.time_constant_s, response.gain),
        horizon=cfg.horizon,
        Q=np.concatenate([cfg.q_angle, cfg.q_rate]),
        R=np.array(cfg.r_rate, dtype=np.float64),
        u_min=-rmax,
        u_max=rmax,
    )


class AttitudeLoop:
    """The attitude loop's numerics for one vehicle: its QP and EPC (``learn_on_miss`` as
    :class:`~epc_offboard.control.position.PositionLoop`'s), the commands in flight, the
    identification of the rate response and the gate on body rates.

    ``period_s``: the loop's tick (the grid commands are held on); ``autopilot``: whose
    measured rate response fills what the configuration leaves unset; ``airframe``: the
    body rates its rate loop can follow. Every tick calls
    exactly one of :meth:`attitude_tick`, :meth:`attitude_fallback` (body rates sent) or
    :meth:`attitude_delegated` (quaternion sent), with the tick's time ``now_s``.
    """

    def __init__(
        self,
        config: AttitudeControlConfig,
        *,
        learn_on_miss: bool = True,
        period_s: float = 0.005,
        autopilot: str = "px4",
        airframe: Airframe | None = None,
    ) -> None:
        self.config = config
        self.airframe = airframe or Airframe()  # its body-rate limits
        self.period_s = period_s
        self.response = config.rate_response(autopilot)
        self.problem = attitude_problem(config, self.response, self.airframe.max_rate_frd_rad_s)
        self.controller = budgeted_controller(
            self.problem, config.library_size, config.query_budget_us, learn_on_miss
        )
        # commands back over the longest dead time identified, its window and a sample's age
        capacity = round((MAX_DEAD_TIME_S + self.response.time_constant_s + 0.15) / period_s)
        self.history = CommandHistory(period_s, capacity)
        self.predictor = RatePredictor(self.response, period_s, capacity)
        self.identifier = RateIdentifier(
            self.response, period_s, max_dead_time_s=config.identify_max_dead_time_s
        )
        self.identified: IdentifiedResponse | None = None
        self.gate = RateModelGate(
            error_max_rad_s=_or(
                config.model_error_max_rad_s, default_model_error_max_rad_s(autopilot)
            ),
            error_ratio=config.model_error_ratio,
            hold_s=config.model_fallback_hold_s,
            probation_s=config.model_probation_s,
            period_s=period_s,
        )
        self._sample_age_ticks = 0
        self._ticks = 0

    def rates_trusted(self, state: VehicleState, target: PositionOutput) -> bool:
        """Whether the attitude is where the body-rate EPC's hover linearisation holds: tilt
        and distance to the attitude target within ``rates_max_tilt_deg`` /
        ``rates_max_error_deg``. Outside, the attitude goes to the autopilot's own loop."""
        cfg = self.config
        tilt = frames.tilt_deg(state.q_ned_frd)
        error = frames.angle_between_deg(state.q_ned_frd, target.q_target)
        return tilt <= cfg.rates_max_tilt_deg and error <= cfg.rates_max_error_deg

    def rate_model_trusted(self, now_s: float) -> bool:
        """Whether the rate model predicts the measured rates well enough to fly body rates
        (always, with ``model_check`` off)."""
        return not self.config.model_check or self.gate.use_rates(now_s)

    def _observe(self, state: VehicleState, now_s: float) -> None:
        """A new rate sample (its own stamp advanced): into the history, the identifier and
        the model check. Its time on the loop's clock is ``now_s`` less its age."""
        key = state.time_s - state.attitude_age_s
        age_ticks = round(state.attitude_age_s / self.period_s)
        history = self.history
        if key == history.last_sample_key:
            self._sample_age_ticks = round((now_s - history.samples[-1][0]) / self.period_s)
            return
        history.last_sample_key = key
        t_s = now_s - state.attitude_age_s
        rate = state.rate_frd_rad_s
        history.add_sample(t_s, rate)
        self._sample_age_ticks = age_ticks
        if self.config.identify:
            ident = self.identifier
            if history.valid_run >= age_ticks + ident.span:
                before = history.rate_at(t_s - ident.step_s)
                if before is not None:
                    ident.update(history, rate, before, age_ticks)
            self._ticks += 1
            if self._ticks % 20 == 0:  # (argmin and logs: 10 Hz is plenty)
                self._adopt(ident.best())
        if self.config.model_check:
            err = self.predictor.check(history, t_s, rate, age_ticks)
            if err is not None:
                self.gate.check(now_s, err, rate)

    def _adopt(self, best: IdentifiedResponse | None) -> None:
        """The identified dead time replaces the model's (lag and gain key the QP's library:
        reported, not adopted)."""
        self.identified = best
        if best is None:
            return
        dead = best.response.dead_time_s
        if round(dead / self.period_s) != self.predictor.dead_ticks:
            self.predictor.set_response(
                RateResponse(dead, self.response.time_constant_s, self.response.gain)
            )

    def _sent(self, now_s: float, u_frd_rad_s: FloatArray, *, valid: bool) -> None:
        self.history.push(now_s, u_frd_rad_s, valid=valid)
        if valid:
            self.identifier.note_command(u_frd_rad_s)

    def _refs(self, state: VehicleState, target: PositionOutput) -> tuple[FloatArray, FloatArray]:
        """x0 (6,) and the references (N, 6) of x[1..N]: the target attitude at rest."""
        roll, pitch, yaw = state.euler_rad
        troll, tpitch, tyaw = target.euler_target_rad
        # take the short way round in yaw: the reference is expressed next to the current yaw
        tyaw = yaw + frames.wrap_pi(tyaw - yaw)
        x0 = np.array([roll, pitch, yaw, *state.rate_frd_rad_s])
        row = np.array([troll, tpitch, tyaw, 0.0, 0.0, 0.0])
        return x0, np.tile(row, (self.config.horizon, 1))

    def attitude_tick(
        self,
        state: VehicleState,
        target: PositionOutput,
        now_s: float | None = None,
        *,
        acting: bool = True,
    ) -> AttitudeCommand:
        """Body rates for tick ``now_s`` (default: the state's time): the QP from the state
        predicted to when this command starts to act. ``acting``: the autopilot flies our
        setpoints (in offboard); before, what is streamed is no evidence about the response."""
        now = state.time_s if now_s is None else now_s
        self._observe(state, now)
        x0, refs = self._refs(state, target)
        ahead = self.predictor.ahead(self.history, x0[:3], x0[3:], self._sample_age_ticks)
        x0[:3] = ahead.angles_rad
        x0[3:] = ahead.rates_frd_rad_s
        d = self.controller.step(x0, refs)
        u = np.asarray(d.u, dtype=np.float64)
        self._sent(now, u, valid=acting)
        return AttitudeCommand(target.q_target, u, target.thrust_norm, d.source)

    def _p_law(self, state: VehicleState, target: PositionOutput) -> FloatArray:
        x0, refs = self._refs(state, target)
        rmax = np.array(self.airframe.max_rate_frd_rad_s)
        out: FloatArray = np.clip(
            self.config.fallback_gain_1_s * (refs[0, :3] - x0[:3]), -rmax, rmax
        )
        return out

    def attitude_fallback(
        self, state: VehicleState, target: PositionOutput, now_s: float | None = None
    ) -> AttitudeCommand:
        now = state.time_s if now_s is None else now_s
        rates = self._p_law(state, target)
        self._sent(now, rates, valid=True)
        return AttitudeCommand(target.q_target, rates, target.thrust_norm, "fallback")

    def attitude_delegated(
        self, state: VehicleState, target: PositionOutput, now_s: float
    ) -> None:
        """A tick that sent the attitude (quaternion) instead of body rates: the autopilot's
        own attitude loop flies it, a P law on the attitude error like ours, which stands in
        for its unseen rate setpoints (a lone late tick then spoils neither the prediction
        nor the identification; a longer run is no evidence, see CommandHistory.push)."""
        self._observe(state, now_s)
        self._sent(now_s, self._p_law(state, target), valid=False)

    def rate_model_stats(self) -> dict[str, Any]:
        """The rate response in use and identified, the model's error, the gate's count."""
        best = self.identified
        used = self.predictor.response
        return {
            "model": {"dead_time_s": used.dead_time_s, "time_constant_s": used.time_constant_s,
                      "gain": used.gain},
            "identified": None if best is None else {
                "dead_time_s": round(best.response.dead_time_s, 4),
                "time_constant_s": round(best.response.time_constant_s, 4),
                "gain": round(best.response.gain, 3),
                "error_rad_s": round(best.error_rad_s, 4),
                "samples": best.updates,
            },
            "prediction_error_rad_s": round(self.gate.error_rms_rad_s, 4),
            "rates_trusted": self.gate.trusted,
            "fallbacks": self.gate.fallbacks,
        }  # fmt: skip
