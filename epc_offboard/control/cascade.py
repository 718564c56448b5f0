"""The control cascade of one vehicle: the position loop (100 Hz,
:mod:`~epc_offboard.control.position`) feeding the attitude loop (200 Hz,
:mod:`~epc_offboard.control.attitude`), and the loop policy between them.

Pure numerics (no asyncio, no MAVLink): the service hands in a
:class:`~epc_offboard.control.types.VehicleState` and a
:class:`~epc_offboard.control.types.ReferenceHorizon` and gets back the
commands to encode and send. What is stored of the
controllers is translated by :mod:`epc_offboard.store.experience`.

The policy of an attitude tick (:func:`attitude_command`): body rates from the attitude EPC
when they can be trusted; else the attitude itself, which the autopilot's own attitude loop
tracks: with ``attitude.mode = "autopilot"`` always, on a late tick or an old attitude sample
(rates computed now would be flown until the next tick, stale), outside the envelope where
the EPC's hover linearisation holds, and while the attitude loop's model of the autopilot's
rate response does not predict the measured rates (``control/rate_response.py``). An
exception in the attitude EPC degrades to the P-law fallback rates. With the px4 baseline the
autopilot's own position controller flies the reference now (:class:`~epc_offboard.control.
types.PositionTarget`).
"""

from __future__ import annotations

import time
from collections.abc import Callable
from typing import Any, Literal

import numpy as np

from epc_offboard.common.airframe import Airframe
from epc_offboard.control import kernels, lwpr, lwpr_kernels, rate_response, trajectories
from epc_offboard.control.attitude import AttitudeControlConfig, AttitudeLoop
from epc_offboard.control.decision import Controller
from epc_offboard.control.epc import ExperienceController
from epc_offboard.control.perturbation import EstimatorConfig
from epc_offboard.control.position import PositionControlConfig, PositionLoop
from epc_offboard.control.types import (
    AttitudeCommand,
    PositionOutput,
    ReferenceHorizon,
    VehicleState,
)

# an attitude sample older than this many attitude periods is not flown as body rates: a
# 123 Hz stream (8.1 ms) read one tick late is 13 ms old; 20 ms is a stall
LATE_ATTITUDE_PERIODS = 4.0
# a tick started this many periods after its schedule is late
LATE_TICK_PERIODS = 1.5


def late_tick(delay_s: float, attitude_age_s: float, period_s: float) -> bool:
    """Whether an attitude tick started ``delay_s`` after its schedule, on an attitude
    sample ``attitude_age_s`` old, is late (attitude loop period ``period_s``).

    A late tick or an old attitude sample: body rates computed now would be flown until the
    next tick, stale; the attitude itself goes instead, which the autopilot's own attitude
    loop keeps tracking whatever we do next. The attitude loop predicts over the sample's
    age, so an age within the stream's interval (PX4 grants ATTITUDE_QUATERNION 123 Hz,
    8.1 ms) plus a tick or two is normal, not late; and a tick one period behind (lockstep
    against an autopilot that sends no SYSTEM_TIME runs it at the next vehicle time with
    state) is the newest possible: only half a period more, or an age over
    :data:`LATE_ATTITUDE_PERIODS` ticks, is late.
    """
    return (
        delay_s > LATE_TICK_PERIODS * period_s
        or attitude_age_s > LATE_ATTITUDE_PERIODS * period_s
    )


# who flies the attitude: the attitude EPC's body rates, or the autopilot's own attitude loop
# (quaternion + thrust); "auto" is resolved per autopilot before it gets here
AttitudeMode = Literal["epc", "autopilot"]


def attitude_command(
    loop: AttitudeLoop,
    state: VehicleState,
    target: PositionOutput,
    now_s: float,
    *,
    late: bool,
    mode: AttitudeMode,
    acting: bool = True,
    on_error: Callable[[Exception], None] | None = None,
) -> AttitudeCommand:
    """The attitude tick's command for ``target`` from ``state`` at loop time ``now_s``.

    In order: ``mode`` "autopilot": the attitude, always (source "delegated"); a ``late``
    tick or attitude sample: the attitude ("late"); outside the rate envelope
    (:meth:`AttitudeLoop.rates_trusted`): the attitude ("envelope"); a rate model that does
    not predict the measured rates (:meth:`AttitudeLoop.rate_model_trusted`): the attitude
    ("model"); else the attitude EPC's body rates (its decision's source), or, when it
    raises (handed to ``on_error``), the P-law fallback ("fallback"). ``acting``: the
    autopilot flies our setpoints (offboard), so the rates measured answer them. Each tick
    that sends the attitude while we fly body rates is noted in ``loop`` (the autopilot's
    loop stands in for our rates in its history). The checks run in this order and only as
    far as needed: the rate model's gate keeps time.
    """
    def quaternion(source: Literal["late", "envelope", "model"]) -> AttitudeCommand:
        loop.attitude_delegated(state, target, now_s)  # the autopilot's, in flight
        return AttitudeCommand(target.q_target, None, target.thrust_norm, source)

    if mode == "autopilot":
        return AttitudeCommand(target.q_target, None, target.thrust_norm, "delegated")
    if late:
        return quaternion("late")
    if not loop.rates_trusted(state, target):
        return quaternion("envelope")
    if not loop.rate_model_trusted(now_s):
        return quaternion("model")
    try:
        return loop.attitude_tick(state, target, now_s, acting=acting)
    except Exception as exc:  # degrade, never die: the caller logs and counts it
        if on_error is not None:
            on_error(exc)
        return loop.attitude_fallback(state, target, now_s)


def _stats(ctrl: Controller | None) -> dict[str, Any]:
    if isinstance(ctrl, ExperienceController):
        s = ctrl.stats
        return {
            "size": int(s.size),
            "hits": int(s.hits),
            "misses": int(s.misses),
            "qp_solves": int(s.qp_solves),
            "intermediate": int(s.intermediate),
            "fallback": int(s.fallback),
            "received_shared": int(getattr(s, "received_shared", 0)),
            "candidates": int(s.candidates),
        }
    return {}


def compiled_signatures() -> int:
    """How many compiled signatures the kernels' numba dispatchers hold (0 on the numpy
    twins). A count that grows after ``Cascade.warm_up`` is a compile on the control loop."""
    count = 0
    for module in (kernels, lwpr_kernels, trajectories, rate_response):
        for value in vars(module).values():
            if hasattr(value, "py_func") and hasattr(value, "signatures"):
                count += len(value.signatures)
    for pair in (kernels._NUMBA, kernels._LISTS):
        for fn in pair or ():
            count += len(getattr(fn, "signatures", ()))
    return count


class Cascade:
    """Both loops of one vehicle, built from the service config.

    ``loop_period_s``: the position loop's period (its estimator's filter step);
    ``learn_on_miss``: as :class:`~epc_offboard.control.position.PositionLoop`'s;
    ``attitude_period_s`` and ``autopilot``: as :class:`~epc_offboard.control.attitude.
    AttitudeLoop`'s (its tick; whose rate response fills what the config leaves unset);
    ``airframe``: the vehicle's hover thrust and limits (its vehicle file; unset: the
    defaults of :class:`~epc_offboard.common.airframe.Airframe`).
    """

    def __init__(
        self,
        position_cfg: PositionControlConfig,
        attitude_cfg: AttitudeControlConfig,
        estimator_cfg: EstimatorConfig,
        loop_period_s: float = 0.01,
        *,
        learn_on_miss: bool = True,
        attitude_period_s: float = 0.005,
        autopilot: str = "px4",
        airframe: Airframe | None = None,
    ) -> None:
        self.position = PositionLoop(
            position_cfg, estimator_cfg, loop_period_s, learn_on_miss=learn_on_miss,
            airframe=airframe,
        )  # fmt: skip
        self.attitude = AttitudeLoop(
            attitude_cfg, learn_on_miss=learn_on_miss, period_s=attitude_period_s,
            autopilot=autopilot, airframe=airframe,
        )  # fmt: skip
        self._autopilot = autopilot

    def position_tick(
        self, state: VehicleState, reference: ReferenceHorizon, *, learn: bool = True
    ) -> PositionOutput:
        return self.position.position_tick(state, reference, learn=learn)

    def hover(self, state: VehicleState) -> PositionOutput:
        """The safe command when the position loop cannot answer: level, hover thrust."""
        return self.position.hover(state)

    @property
    def flies_reference(self) -> bool:
        """The px4 baseline: the autopilot's own position controller flies the reference
        now (a :class:`PositionTarget` of its stage 0, each attitude tick); the position
        loop computes nothing, and the reference it is handed is the reference now, not a
        horizon."""
        return self.position.controller is None

    def rates_trusted(self, state: VehicleState, target: PositionOutput) -> bool:
        return self.attitude.rates_trusted(state, target)

    def attitude_tick(
        self,
        state: VehicleState,
        target: PositionOutput,
        now_s: float | None = None,
        *,
        acting: bool = True,
    ) -> AttitudeCommand:
        return self.attitude.attitude_tick(state, target, now_s, acting=acting)

    def attitude_fallback(
        self, state: VehicleState, target: PositionOutput, now_s: float | None = None
    ) -> AttitudeCommand:
        return self.attitude.attitude_fallback(state, target, now_s)

    def warm_up(self) -> float:
        """Run both ticks of a scratch cascade with this configuration at hover, so every
        compiled kernel (numba) is compiled or loaded from its cache now, not inside the
        first control tick. Leaves this cascade untouched; returns the seconds it took."""
        t0 = time.perf_counter()
        pos = self.position
        if pos.estimator_cfg.kind == "lwpr":
            lwpr.warm_up()  # every LWPR kernel, whatever the few scratch ticks exercise
        kernels.warm_up()  # the library scan: an empty scratch library never runs it
        trajectories.warm_up()  # the reference horizon the service hands in
        rate_response.warm_up()  # the identifier runs only once the vehicle is excited
        att = self.attitude
        scratch = Cascade(
            pos.config, att.config, pos.estimator_cfg, pos.loop_period_s,
            attitude_period_s=att.period_s, autopilot=self._autopilot, airframe=pos.airframe,
        )  # fmt: skip
        for k in range(3):
            state = VehicleState(
                time_s=k * pos.loop_period_s,
                pos_ned_m=np.array([0.0, 0.0, -2.5]),
                vel_ned_m_s=np.zeros(3),
                q_ned_frd=np.array([1.0, 0.0, 0.0, 0.0]),
                rate_frd_rad_s=np.zeros(3),
                position_age_s=0.0,
                attitude_age_s=0.0,
            )
            reference = scratch.position.hold(state.pos_ned_m)
            target = scratch.position_tick(state, reference, learn=True)
            scratch.attitude_tick(state, target, state.time_s)
        # a learning step, which three ticks at rest do not reach (the estimator learns
        # over a prediction step): its models' update in one call (ModelGroup), compiled for
        # this configuration's number of models
        scratch.position.estimator.observe(np.zeros(3), np.zeros(3))
        return time.perf_counter() - t0

    def experience_controllers(self) -> list[tuple[str, ExperienceController]]:
        """(name, controller) of each EPC problem: what is stored and what the fleet shares.
        The caller owns ``pop_new_entries`` (the service publishes them, or discards them
        when not sharing)."""
        out = [("attitude", self.attitude.controller)]
        if isinstance(self.position.controller, ExperienceController):
            out.insert(0, ("position", self.position.controller))
        return out

    def library_stats(self) -> dict[str, Any]:
        return {
            "position": _stats(self.position.controller),
            "attitude": _stats(self.attitude.controller),
        }
