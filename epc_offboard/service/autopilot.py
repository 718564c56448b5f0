"""The autopilot as the service knows it, over the link: what it says (state, dialect,
parameters, position fix, landed state, acknowledgements, received rates) and what the
service asks of it (message rates, parameters, the state machine's actions as commands).

Messages arrive through the link's callback (:meth:`Autopilot.on_message`); every command
is encoded by ``vehicle/commands.py``.
"""

from __future__ import annotations

import logging
import math
import time
from collections import Counter, deque
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from pymavlink.dialects.v20 import common as mavlink

from epc_offboard.common.logsetup import LogGate
from epc_offboard.common.signing import load_signing_key
from epc_offboard.control.cascade import AttitudeMode
from epc_offboard.control.types import VehicleState
from epc_offboard.service.clock import Clock, VehicleClock
from epc_offboard.service.config import ServiceConfig
from epc_offboard.vehicle import commands
from epc_offboard.vehicle.autopilots import choose
from epc_offboard.vehicle.dialect import (
    MAV_AUTOPILOT_INVALID,
    MAV_CMD_COMPONENT_ARM_DISARM,
    MAV_CMD_DO_SET_MODE,
    MAV_CMD_NAV_TAKEOFF,
    Action,
    Command,
    Dialect,
    EncodeError,
    Position,
    TakeoffTarget,
)
from epc_offboard.vehicle.link import MavlinkLink, TlogWriter
from epc_offboard.vehicle.rates import RateMonitor
from epc_offboard.vehicle.receive import SERVICE_MESSAGE_IDS
from epc_offboard.vehicle.state import StateTracker

log = logging.getLogger("epc_offboard.service")

_RATE_WINDOW_S = 2.0  # received rates are measured over windows this long
_GLOBAL_MAX_AGE_S = 1.0  # GLOBAL_POSITION_INT older than this is not used
_MAX_TIMESYNC_PENDING = 8  # TIMESYNC requests awaiting an answer (older ones forgotten)
# Commands whose acceptance changes what the heartbeat says (arming, the mode), and how long
# after the accepted ACK a HEARTBEAT is asked for. The 1 Hz heartbeat showed each up to a
# second late, and the state machine waits on it: arm -> takeoff -> offboard confirmed cost
# 0-3 s of a start on a real PX4 (1.2 s in one cold start of 12 s). A real PX4 (main, SIH)
# shows its arming in a heartbeat asked for at the ACK, but a mode a commander cycle later:
# asked for at the ACK, the heartbeat still showed the old mode after DO_SET_MODE and LAND.
_HEARTBEAT_AFTER_ACK_S = {
    MAV_CMD_COMPONENT_ARM_DISARM: 0.0,
    MAV_CMD_DO_SET_MODE: 0.1,
    MAV_CMD_NAV_TAKEOFF: 0.1,
    mavlink.MAV_CMD_NAV_LAND: 0.1,
}


@dataclass(frozen=True)
class GlobalFix:
    """The newest GLOBAL_POSITION_INT: what an explicit takeoff altitude is computed from."""

    lat_e7: int
    lon_e7: int
    amsl_m: float
    relative_alt_m: float
    received_s: float  # loop clock


class Autopilot:
    """The conversation with one autopilot. ``cfg`` may be replaced (SIGHUP): it is read
    where used. Counts into the shared ``counters``."""

    def __init__(
        self,
        cfg: ServiceConfig,
        clock: Clock,
        tracker: StateTracker,
        counters: Counter[str],
        log_gate: LogGate,
        tlog: TlogWriter | None = None,
    ) -> None:
        """``tlog``: where the link's frames go (the log writer process's channel)."""
        self.cfg = cfg
        self.clock = clock
        self.tracker = tracker
        self.counters = counters
        self._log_gate = log_gate
        # told the autopilot's own hover thrust (the position loop's vertical prior)
        self.on_hover_thrust: Callable[[float], None] = lambda hover_norm: None
        # told the autopilot and attitude mode flown when the dialect is adopted (the
        # position loop's command dead time; see attitude_path)
        self.on_attitude_path: Callable[[str, AttitudeMode], None] = lambda name, mode: None
        self.target = commands.Target(cfg.link.target_system, cfg.link.target_component)
        # the autopilot's dialect: forced by link.autopilot, else from its first heartbeat
        # (until then the state machine sees no heartbeat: nothing is commanded)
        self.dialect: Dialect | None = choose(cfg.link.autopilot, None)
        self.params: dict[str, float] = {}  # autopilot parameters read (PARAM_VALUE)
        self.rates = RateMonitor(
            {
                "ATTITUDE_QUATERNION": cfg.loops.attitude_rate_hz,
                "LOCAL_POSITION_NED": cfg.loops.position_rate_hz,
            }
        )
        self.landed_state: int | None = None  # EXTENDED_SYS_STATE, when the autopilot says
        self.last_rx_wall_s = -math.inf  # time.monotonic() of the last message
        self._global: GlobalFix | None = None
        self._params_requested_at = -math.inf
        self._withheld_logged: set[str] = set()  # streams whose absence was logged
        self._timesync_sent: dict[int, float] = {}  # ts1 (ns) -> local send time, bounded
        self._timesync_at = -math.inf
        # heartbeats received (loop clock) and the last one asked for: see _ask_heartbeat
        self._heartbeats_rx_s: deque[float] = deque(maxlen=4)
        self._heartbeat_asked_s = -math.inf
        self._heartbeat_due_s = math.inf  # a heartbeat to ask for then (an accepted command)
        key = load_signing_key(cfg.link.signing_key_file) if cfg.link.signing_key_file else None
        self.link = MavlinkLink(
            cfg.link.url,
            system_id=cfg.link.system_id,
            component_id=cfg.link.component_id,
            on_message=self.on_message,
            accept_system_ids=frozenset({cfg.link.target_system}),
            # the autopilot's component sends every stream read (0: any component)
            accept_component_ids=(
                frozenset({cfg.link.target_component}) if cfg.link.target_component else None
            ),
            accept_message_ids=SERVICE_MESSAGE_IDS,
            signing_key=key,
            tlog=tlog,
        )

    # -- what it says ----------------------------------------------------------------------

    def on_message(self, msg: Any) -> None:
        """The link's callback, for every message from the target system."""
        self.last_rx_wall_s = time.monotonic()
        now = self.clock.now_s()  # in lockstep vehicle time: heartbeat ages are too
        held = self.tracker.heartbeat
        mtype = msg.get_type()
        if self.tracker.handle(msg, received_s=now) and isinstance(self.clock, VehicleClock):
            self.clock.advance(self.tracker.vehicle_time_s)
        elif mtype == "SYSTEM_TIME" and isinstance(self.clock, VehicleClock):
            # lockstep: the vehicle's clock ticking between state messages (asked for at the
            # attitude loop's rate), so the loops tick on time as they do in real time, on
            # the newest samples predicted to the tick (PX4 sends ATTITUDE_QUATERNION at
            # ~123 Hz: on state stamps alone the 200 Hz loop ran at 161 Hz, a 10 ms period
            # in every 2-3 ticks)
            self.clock.advance(msg.time_boot_ms * 1e-3)
        self.rates.record(mtype)
        hb = self.tracker.heartbeat
        if mtype == "HEARTBEAT":
            self._heartbeats_rx_s.append(now)  # every one the link passed: as the flood guard
        if mtype == "HEARTBEAT" and hb is not None and hb is not held:
            # only a heartbeat the tracker accepted (the autopilot's component and kind)
            self._adopt_dialect(hb.autopilot)
        elif mtype == "GLOBAL_POSITION_INT":
            amsl, rel = msg.alt * 1e-3, msg.relative_alt * 1e-3
            if math.isfinite(amsl) and math.isfinite(rel) and abs(rel) < 1e5:
                self._global = GlobalFix(msg.lat, msg.lon, amsl, rel, now)
        elif mtype == "TIMESYNC":
            self._on_timesync(msg, now)
        elif mtype == "EXTENDED_SYS_STATE":
            self.landed_state = int(msg.landed_state)
        elif mtype == "PARAM_VALUE" and msg.get_srcSystem() == self.target.system_id:
            self._on_param(msg)
        elif mtype == "COMMAND_ACK":
            # two counters, whatever the wire says: a fuzzing peer cannot grow the dict
            accepted = msg.result in (mavlink.MAV_RESULT_ACCEPTED, 5)  # 5: in progress
            self.counters["acks_accepted" if accepted else "acks_refused"] += 1
            delay_s = _HEARTBEAT_AFTER_ACK_S.get(msg.command)
            if msg.result == mavlink.MAV_RESULT_ACCEPTED and delay_s is not None:
                self.tracker.change_commanded(now)  # what the heartbeats show next is ours
                self._heartbeat_due_s = min(self._heartbeat_due_s, now + delay_s)
                self._heartbeat_due()
            if not accepted and self._log_gate.open("ack", 1.0):
                log.info(
                    "command %d answered with result %d (%d refusals so far)",
                    msg.command, msg.result, self.counters["acks_refused"],
                )  # fmt: skip

    def _heartbeat_due(self) -> None:
        """Ask for the heartbeat an accepted command made due, once it is due."""
        now = self.clock.now_s()
        if now >= self._heartbeat_due_s:
            self._heartbeat_due_s = math.inf
            self._ask_heartbeat(now)

    def _ask_heartbeat(self, now: float) -> None:
        """Ask for a HEARTBEAT now (MAV_CMD_REQUEST_MESSAGE; PX4 and ArduPilot answer it with
        their current one), unless one asked for is still unanswered or that could look like
        a flood to the state tracker's forgery guard (four heartbeats within a period less
        the jitter): asked only while at most one heartbeat falls within that window. A
        window then holds at most two answered requests and one regular heartbeat: never
        four on PX4 (ArduPilot adds its own on a mode change, counted here as heard)."""
        limits = self.cfg.state_limits
        window_s = limits.heartbeat_period_s - limits.heartbeat_jitter_s
        newest_s = self._heartbeats_rx_s[-1] if self._heartbeats_rx_s else -math.inf
        if self._heartbeat_asked_s > newest_s and now - self._heartbeat_asked_s < window_s:
            return  # asked, not yet answered
        if sum(1 for t in self._heartbeats_rx_s if now - t < window_s) > 1:
            self.counters["heartbeat_requests_withheld"] += 1
            return
        self._heartbeat_asked_s = now
        self.counters["heartbeat_requests"] += 1
        self.link.send(commands.command_message(self.target, commands.heartbeat_request()))

    def _on_timesync(self, msg: Any, now: float) -> None:
        """An answer to one of our TIMESYNC requests (tc1 != 0, ts1 one we sent) maps the
        autopilot's clock to ours; its own requests (tc1 = 0) and unknown ts1 are not."""
        sent_s = self._timesync_sent.pop(int(msg.ts1), None)
        if msg.tc1 == 0 or sent_s is None or self.clock.vehicle_time:
            return
        self.tracker.clock.timesync(sent_s, msg.tc1 * 1e-9, now)

    def _adopt_dialect(self, autopilot: int) -> None:
        """The dialect from HEARTBEAT.autopilot (link.autopilot "auto"), once; a forced one
        that the heartbeat contradicts is kept, and the contradiction logged and counted."""
        if autopilot == MAV_AUTOPILOT_INVALID:
            return  # a camera or gimbal of the vehicle
        if self.dialect is None:
            dialect = choose("auto", autopilot)
            if dialect is None:
                self.counters["heartbeats_unknown_autopilot"] += 1
                if self._log_gate.open("autopilot", 10.0):
                    log.error(
                        "HEARTBEAT.autopilot %d is neither PX4 (12) nor ArduPilot (3): "
                        "nothing is commanded; set link.autopilot to fly it", autopilot,
                    )  # fmt: skip
                return
            self.dialect = dialect
            log.info(
                "autopilot dialect %s (HEARTBEAT.autopilot %d), attitude mode %s",
                dialect.name, autopilot, self.attitude_mode,
            )  # fmt: skip
            self.on_attitude_path(*self.attitude_path)
            if self.cfg.attitude.mode == "epc" and dialect.default_attitude_mode != "epc":
                log.warning(
                    "attitude.mode = \"epc\" (body rates) on %s: its shaped rate response is "
                    "slow; \"auto\" flies quaternion mode", dialect.name,
                )  # fmt: skip
            cfg = self.cfg
            if cfg.attitude.mode != "autopilot" and cfg.link.autopilot == "auto" and (
                dialect.name != "px4"
            ):
                # the attitude loop was built before the dialect was known: its model of the
                # rate response is PX4's (control/rate_response.py) unless configured
                log.warning(
                    "link.autopilot = \"auto\": the attitude loop models PX4's body-rate "
                    "response; set link.autopilot = \"%s\" for %s's", dialect.name,
                    dialect.name,
                )  # fmt: skip
        elif autopilot != self.dialect.autopilot:
            self.counters["heartbeats_other_autopilot"] += 1
            if self._log_gate.open("autopilot", 10.0):
                log.error(
                    "link.autopilot = %s but HEARTBEAT.autopilot is %d: speaking %s anyway",
                    self.cfg.link.autopilot, autopilot, self.dialect.name,
                )  # fmt: skip

    @property
    def attitude_path(self) -> tuple[str, AttitudeMode]:
        """(the autopilot: the dialect's name, link.autopilot until one is adopted; the
        attitude mode). It changes only when the dialect is adopted (on_attitude_path)."""
        name = self.cfg.link.autopilot if self.dialect is None else self.dialect.name
        return name, self.attitude_mode

    @property
    def attitude_mode(self) -> AttitudeMode:
        """attitude.mode, "auto" resolved by the dialect ("epc" until one is known)."""
        mode = self.cfg.attitude.mode
        if mode != "auto":
            return mode
        return "epc" if self.dialect is None else self.dialect.default_attitude_mode

    def _on_param(self, msg: Any) -> None:
        name = msg.param_id.rstrip("\x00") if isinstance(msg.param_id, str) else ""
        value = float(msg.param_value)
        if self.dialect is None or name not in self.dialect.params_to_read:
            return
        if self.params.get(name) != value:
            log.info("autopilot parameter %s = %g", name, value)
        self.params[name] = value
        hover = self.cfg.vehicle.hover_thrust_norm
        if name == "MOT_THST_HOVER" and math.isfinite(value):
            self.on_hover_thrust(value)
        if name == "MOT_THST_HOVER" and math.isfinite(value) and abs(value - hover) > 0.05:
            self.counters["hover_thrust_mismatch"] += 1
            log.warning(
                "MOT_THST_HOVER is %.3f but the airframe's hover thrust is %.3f: put the "
                "autopilot's learned hover throttle in %s", value, hover, self.cfg.vehicle.source,
            )  # fmt: skip

    def wire_thrust(self, thrust_norm: float, state: VehicleState) -> float:
        """The collective thrust as the autopilot reads it at ``state``'s tilt (ArduCopter
        adds its own tilt boost)."""
        if self.dialect is None:
            return thrust_norm
        roll, pitch, _ = state.euler_rad
        return self.dialect.wire_thrust(thrust_norm, math.cos(roll) * math.cos(pitch))

    def offboard_refusal(self) -> str:
        """Why offboard must not be requested, nor setpoints sent ("" when they may)."""
        return "" if self.dialect is None else self.dialect.offboard_refusal(self.params)

    def fresh_global(self) -> GlobalFix | None:
        """The newest GLOBAL_POSITION_INT, if younger than a second of loop time."""
        fix = self._global
        if fix is None or self.clock.now_s() - fix.received_s > _GLOBAL_MAX_AGE_S:
            return None
        return fix

    # -- what the service asks of it --------------------------------------------------------

    def send_command(self, cmd: Command) -> None:
        self.link.send(commands.command_message(self.target, cmd))
        self.counters["commands_sent"] += 1

    def do_action(
        self, action: Action, takeoff: TakeoffTarget | None, state: VehicleState | None
    ) -> None:
        """The state machine's ``action`` as the dialect's command (``takeoff``: its target
        when the action is TAKEOFF); not sent while the parameters refuse offboard, nor when
        it cannot be encoded with finite values (both logged and counted)."""
        if self.dialect is None:
            return  # (the state machine sees no heartbeat before a dialect is chosen)
        why = self.offboard_refusal() if action == Action.REQUEST_OFFBOARD else ""
        if why:
            self.counters["offboard_refused"] += 1
            if self._log_gate.open("refusal", 10.0):
                log.error(
                    "not requesting offboard (%s GUIDED) nor sending setpoints: %s "
                    "(%d refusals so far)", self.dialect.name, why,
                    self.counters["offboard_refused"],
                )  # fmt: skip
            return
        fix = self.fresh_global()
        position = (
            None
            if fix is None or state is None
            else Position(fix.lat_e7, fix.lon_e7, math.degrees(state.yaw_rad))
        )
        try:
            cmd = self.dialect.encode(action, takeoff, position)
        except EncodeError as exc:
            self.counters["commands_not_encoded"] += 1
            log.error("action %s not sent: %s", action.value, exc)
            return
        if action == Action.TAKEOFF and takeoff is not None:
            self.counters["takeoffs_sent"] += 1
            log.info(
                "action: takeoff to %.2f m above home (%.2f m AMSL)",
                takeoff.above_home_m, takeoff.amsl_m,
            )  # fmt: skip
        else:
            log.info("action: %s", action.value)
        self.send_command(cmd)

    def manage(self, now: float, link_up: bool) -> None:
        """Each supervisor step: the first heartbeat, the message rates, the parameters, the
        clock."""
        if self.tracker.heartbeat is None and self.last_rx_wall_s > -math.inf:
            # the autopilot streams (its address is known) but its 1 Hz heartbeat, which
            # names the dialect and starts the state machine, may be a second away
            self._ask_heartbeat(now)
        self._heartbeat_due()
        self._manage_rates(now, link_up)
        self._manage_params(now, link_up)
        self._manage_timesync(now, link_up)

    def _manage_timesync(self, now: float, link_up: bool) -> None:
        """A TIMESYNC request every state_limits.timesync_period_s in real time (lockstep
        runs on the autopilot's clock itself: nothing to map, nothing sent)."""
        period = self.cfg.state_limits.timesync_period_s
        if not link_up or period <= 0.0 or self.clock.vehicle_time:
            return
        if now - self._timesync_at < period:
            return
        self._timesync_at = now
        sent = self._timesync_sent
        if len(sent) >= _MAX_TIMESYNC_PENDING:
            del sent[next(iter(sent))]  # unanswered: the oldest is forgotten
        sent_s = self.clock.now_s()  # as close to the send as the round trip's start can be
        msg = commands.timesync_request(sent_s)
        sent[int(msg.ts1)] = sent_s
        self.link.send(msg)
        self.tracker.clock.requested(sent_s)

    def _manage_rates(self, now: float, link_up: bool) -> None:
        """Ask for the loops' rates when the link comes up, again while a measured stream
        falls short, a few times, then accept what the autopilot grants (logged once); a
        stream not sent at all is asked for less and less often (RateMonitor.plan)."""
        measured = self.rates.sample(now, _RATE_WINDOW_S)
        if not link_up:
            return
        rates = self.rates
        plan = rates.plan(now, self.cfg.offboard.retry_period_s, measured=measured)
        for name, hz in plan.accepted_hz.items():
            log.info(
                "%s: accepting %.0f Hz, what the autopilot grants (%.0f Hz asked for, %d "
                "requests)", name, hz, rates.wanted_hz[name], rates.requests,
            )  # fmt: skip
        if not plan.ask:
            return
        if plan.short or plan.withheld:
            self.counters["rate_requests_repeated"] += 1
        if plan.short:
            log.info(
                "message rates short of the loops' (%s): asking again (%d of %d)",
                ", ".join(f"{k} {rates.rates_hz[k]:.0f} Hz" for k in plan.short),
                rates.requests, rates.settle_requests,
            )  # fmt: skip
        for name in plan.withheld:
            if name not in self._withheld_logged:
                self._withheld_logged.add(name)
                log.info(
                    "%s not streamed (ArduPilot sends no position until its EKF has an "
                    "origin): asking again less and less often, up to every %.0f s",
                    name, rates.max_backoff_s,
                )  # fmt: skip
        loops = self.cfg.loops
        extra = () if self.dialect is None else self.dialect.extra_streams_hz
        if self.clock.vehicle_time:  # lockstep: the clock's ticks (on_message)
            extra = (*extra, (mavlink.MAVLINK_MSG_ID_SYSTEM_TIME, loops.attitude_rate_hz))
        for cmd in commands.rate_requests(loops.attitude_rate_hz, loops.position_rate_hz, extra):
            self.send_command(cmd)

    def _manage_params(self, now: float, link_up: bool) -> None:
        """Read the dialect's parameters at link-up; again (every retry_period_s) while one
        is missing or while they refuse offboard (the user may be setting it now)."""
        if not link_up or self.dialect is None:
            return
        wanted = [
            name
            for name in self.dialect.params_to_read
            if name not in self.params or self.offboard_refusal()
        ]
        if not wanted or now - self._params_requested_at < self.cfg.offboard.retry_period_s:
            return
        self._params_requested_at = now
        for name in wanted:
            self.link.send(commands.param_request(self.target, name))

    def stats(self) -> dict[str, Any]:
        return {
            "autopilot": None if self.dialect is None else self.dialect.name,
            "attitude_mode": self.attitude_mode,
            "params": dict(self.params),
            "rate_requests": self.rates.requests,
            "rates_accepted_hz": {k: round(v, 1) for k, v in self.rates.accepted_hz.items()},
        }
