"""What the attitude loop sends, each tick: the setpoint that flies the position loop's
target (SET_ATTITUDE_TARGET), or with the ``px4`` baseline the reference itself to the
autopilot's own position controller (SET_POSITION_TARGET_LOCAL_NED).

Body rates from the cascade's attitude EPC when they can be trusted; else the attitude
itself, which the autopilot's own attitude loop tracks: with ``attitude.mode =
"autopilot"`` always, on a late tick or an old attitude sample (rates computed now would be
flown until the next tick, stale), outside the envelope where the EPC's hover
linearisation holds, and while the attitude loop's model of the autopilot's rate response
does not predict the measured rates (``control/rate_response.py``; said once in the log per
change). An exception in the attitude EPC degrades to the cascade's fallback rates; a
non-finite setpoint to a level hover (``vehicle/commands.py``). Each is counted.
"""

from __future__ import annotations

import logging
from collections import Counter
from collections.abc import Callable

from epc_offboard.control.attitude import AttitudeOutput
from epc_offboard.control.cascade import Cascade
from epc_offboard.control.position import PositionOutput
from epc_offboard.control.reference import ReferenceHorizon
from epc_offboard.service.autopilot import Autopilot
from epc_offboard.vehicle import commands
from epc_offboard.vehicle.state import VehicleState

log = logging.getLogger("epc_offboard.service")


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
        msg = commands.position_target(
            self.autopilot.target, state.time_s, reference.pos_ned_m[0],
            reference.vel_ned_m_s[0], reference.acc_ned_m_s2[0], float(reference.yaw_rad[0]),
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
    ) -> None:
        """Fly ``target`` from ``state`` at tick ``now_s`` (the loops' clock); ``late``: the
        tick or its attitude sample is late; ``acting``: the autopilot flies our setpoints
        (offboard), so the rates measured answer them."""
        cascade = self.cascade
        if self.autopilot.attitude_mode == "autopilot":
            out = AttitudeOutput(None, target.thrust_norm, "delegated")
        elif late:
            self.counters["attitude_late_fallbacks"] += 1
            out = AttitudeOutput(None, target.thrust_norm, "late")
        elif not cascade.rates_trusted(state, target):
            self.counters["attitude_envelope_fallbacks"] += 1
            out = AttitudeOutput(None, target.thrust_norm, "envelope")
        elif not cascade.rate_model_trusted(now_s):
            self.counters["attitude_model_fallback_ticks"] += 1
            out = AttitudeOutput(None, target.thrust_norm, "model")
        else:
            try:
                out = cascade.attitude_tick(state, target, now_s, acting=acting)
            except Exception as exc:
                self._loop_error("attitude", exc)
                out = cascade.attitude_fallback(state, target, now_s)
        if out.rates_frd_rad_s is None and self.autopilot.attitude_mode != "autopilot":
            cascade.attitude_delegated(state, target, now_s)  # the autopilot's, in flight
        self._model_events()

        def hover() -> commands.AttitudeSetpoint:
            level = cascade.hover(state)
            return commands.AttitudeSetpoint.of(level.q_target, None, level.thrust_norm)

        msg, replaced = commands.attitude_target(
            self.autopilot.target, state.time_s,
            commands.AttitudeSetpoint.of(target.q_target, out.rates_frd_rad_s, out.thrust_norm),
            max_rate_rad_s=self.max_rate_rad_s, fallback=hover,
            wire_thrust=lambda thrust: self.autopilot.wire_thrust(thrust, state),
        )  # fmt: skip
        if replaced:  # never a NaN to the autopilot: level at hover thrust instead, counted
            self.counters["non_finite_setpoints_replaced"] += 1
        self.autopilot.link.send(msg)

    def _model_events(self) -> None:
        """The rate-model gate's changes, once each in the log; its fallbacks counted."""
        gate = self.cascade.attitude.gate
        for event in gate.events:
            log.warning("attitude loop: %s", event)
        gate.events.clear()
        if gate.fallbacks != self.counters["attitude_model_fallbacks"]:
            self.counters["attitude_model_fallbacks"] = gate.fallbacks
