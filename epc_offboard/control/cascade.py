"""The control cascade of one vehicle: the position loop (100 Hz,
:mod:`~epc_offboard.control.position`) feeding the attitude loop (200 Hz,
:mod:`~epc_offboard.control.attitude`).

Pure numerics (no asyncio, no MAVLink): the service hands in a VehicleState and a
:class:`~epc_offboard.control.reference.ReferenceHorizon` and gets back setpoints. What is
stored of the controllers is translated by :mod:`epc_offboard.store.experience`.
"""

from __future__ import annotations

import time
from typing import Any

import numpy as np

from epc_offboard.common.airframe import Airframe
from epc_offboard.control import kernels, lwpr, lwpr_kernels, rate_response, trajectories
from epc_offboard.control.attitude import AttitudeControlConfig, AttitudeLoop, AttitudeOutput
from epc_offboard.control.decision import Controller
from epc_offboard.control.epc import ExperienceController
from epc_offboard.control.perturbation import EstimatorConfig
from epc_offboard.control.position import PositionControlConfig, PositionLoop, PositionOutput
from epc_offboard.control.reference import ReferenceHorizon
from epc_offboard.vehicle.state import VehicleState


def _stats(ctrl: Controller) -> dict[str, Any]:
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
    for module in (kernels, lwpr_kernels, trajectories):
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

    def rates_trusted(self, state: VehicleState, target: PositionOutput) -> bool:
        return self.attitude.rates_trusted(state, target)

    def rate_model_trusted(self, now_s: float) -> bool:
        return self.attitude.rate_model_trusted(now_s)

    def attitude_tick(
        self,
        state: VehicleState,
        target: PositionOutput,
        now_s: float | None = None,
        *,
        acting: bool = True,
    ) -> AttitudeOutput:
        return self.attitude.attitude_tick(state, target, now_s, acting=acting)

    def attitude_fallback(
        self, state: VehicleState, target: PositionOutput, now_s: float | None = None
    ) -> AttitudeOutput:
        return self.attitude.attitude_fallback(state, target, now_s)

    def attitude_delegated(
        self, state: VehicleState, target: PositionOutput, now_s: float
    ) -> None:
        self.attitude.attitude_delegated(state, target, now_s)

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
