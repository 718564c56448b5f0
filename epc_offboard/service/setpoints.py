"""What the attitude loop sends, each tick, encoded and sent: SET_ATTITUDE_TARGET for the
cascade's :class:`~epc_offboard.control.types.AttitudeCommand` (body rates + thrust, or the
attitude itself for the autopilot's own attitude loop), or, with the px4 baseline,
SET_POSITION_TARGET_LOCAL_NED for the reference now (a :class:`~epc_offboard.control.types.
PositionTarget`).

Which command flies is the cascade's policy (:func:`epc_offboard.control.cascade.
attitude_command`); here each kind of fallback is counted, the rate-model gate's changes
are said once in the log, and a non-finite setpoint is replaced by a level hover
(``vehicle/commands.py``) and counted.
"""

from __future__ import annotations

import logging
from collections import Counter
from collections.abc import Callable

from epc_offboard.control.cascade import Cascade, attitude_command
from epc_offboard.control.types import (
    PositionOutput,
    PositionTarget,
    ReferenceHorizon,
    VehicleState,
)
from epc_offboard.service.autopilot import Autopilot
from epc_offboard.vehicle import commands

log = logging.getLogger("epc_offboard.service")

# the service's counter of each source that sends the attitude instead of body rates
_FALLBACK_COUNTERS = {
    "late": "attitude_late_fallbacks",
    "envelope": "attitude_envelope_fallbacks",
    "model": "attitude_model_fallback_ticks",
}


class SetpointSender:
    def __init__(
        self,
        cascade: Cascade,
        autopilot: Autopilot,
        max_rate_rad_s: tuple[float, float, float],
        counters: Counter[str],
        loop_error: Callable[[str, Exception], None],
    ) -> None:
        self.cascade = cascade
        self.max_rate_rad_s = max_rate_rad_s  # body rates are bounded to these, FRD
        self.autopilot = autopilot
        self.counters = counters
        self._loop_error = loop_error

    def position_target(self, state: VehicleState, reference: ReferenceHorizon) -> None:
        """The px4 baseline: the reference's position, velocity and acceleration now (stage
        0), to the autopilot's own position controller (as MAVSDK's offboard plugin sends
        them); a non-finite one is not sent, and counted."""
        target = PositionTarget.now(reference)
        msg = commands.position_target(
            self.autopilot.target, state.time_s, target.pos_ned_m, target.vel_ned_m_s,
            target.acc_ned_m_s2, target.yaw_rad,
        )  # fmt: skip
        if msg is None:
            self.counters["non_finite_setpoints_replaced"] += 1
            return
        self.autopilot.link.send(msg)

    def attitude(
        self,
        state: VehicleState,
        target: PositionOutput,
        now_s: float,
        *,
        late: bool = False,
        acting: bool = True,
        computed: Callable[[], None] | None = None,
    ) -> None:
        """Fly ``target`` from ``state`` at tick ``now_s`` (the loops' clock): the cascade's
        attitude command (``late``: the tick or its attitude sample is late; ``acting``: the
        autopilot flies our setpoints, so the rates measured answer them), its fallbacks
        counted, encoded as SET_ATTITUDE_TARGET and sent. ``computed``: called once the
        message is encoded, before it is sent (the step's parts)."""
        cmd = attitude_command(
            self.cascade.attitude, state, target, now_s, late=late,
            mode=self.autopilot.attitude_mode, acting=acting,
            on_error=lambda exc: self._loop_error("attitude", exc),
        )  # fmt: skip
        counter = _FALLBACK_COUNTERS.get(cmd.source)
        if counter is not None:
            self.counters[counter] += 1
        self._model_events()
        cascade = self.cascade

        def hover() -> commands.AttitudeSetpoint:
            level = cascade.hover(state)
            return commands.AttitudeSetpoint.of(level.q_target, None, level.thrust_norm)

        msg, replaced = commands.attitude_target(
            self.autopilot.target, state.time_s,
            commands.AttitudeSetpoint.of(cmd.q_target, cmd.rates_frd_rad_s, cmd.thrust_norm),
            max_rate_rad_s=self.max_rate_rad_s, fallback=hover,
            wire_thrust=lambda thrust: self.autopilot.wire_thrust(thrust, state),
        )  # fmt: skip
        if replaced:  # never a NaN to the autopilot: level at hover thrust instead, counted
            self.counters["non_finite_setpoints_replaced"] += 1
        if computed is not None:
            computed()
        self.autopilot.link.send(msg)

    def _model_events(self) -> None:
        """The rate-model gate's changes, once each in the log; its fallbacks counted."""
        gate = self.cascade.attitude.gate
        for event in gate.events:
            log.warning("attitude loop: %s", event)
        gate.events.clear()
        if gate.fallbacks != self.counters["attitude_model_fallbacks"]:
            self.counters["attitude_model_fallbacks"] = gate.fallbacks
