"""The offboard service: `epc-offboard run --config FILE`.

One asyncio TaskGroup with named tasks:

* ``supervisor``     — the offboard state machine (the whole flight: arm, takeoff, offboard,
  failsafe, mission end, landing), message-rate requests and measurement, commands;
* ``position-loop``  — 100 Hz: state -> reference horizon -> Cascade.position_tick (EPC + LWPR);
* ``attitude-loop``  — 200 Hz: Cascade.attitude_tick -> SET_ATTITUDE_TARGET (rates + thrust),
  or the autopilot's own attitude loop fed quaternion + thrust (``attitude.mode = "autopilot"``);
* ``library-saver``  — new controllers and learned models to SQLite, off the event loop;
* ``library-sharing`` — with ``[sharing] enabled``: offers controllers received from the
  fleet to the candidate pools (the miss worker screens them; only a candidate optimal for
  a real tick joins the library), publishes new ones, keeps the snapshot peers query
  (``sharing.py``);
* ``systemd``        — READY=1 once state flows, WATCHDOG=1 only while the control loop ticks.

MAVLink arrives through callbacks of the link's DatagramProtocol (no task, no blocking read).
The numerics live in ``cascade.py``; this module never does linear algebra.

The control loops never die: an exception in a tick is logged (rate-limited), counted, and
the tick degrades to the cascade's safe hover command.
"""

from __future__ import annotations

import argparse
import asyncio
import csv
import json
import logging
import math
import signal
import sys
import time
from collections import Counter, deque
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any, TextIO

import numpy as np
from pymavlink.dialects.v20 import common as mavlink

from epc_offboard.common.configio import ConfigError
from epc_offboard.common.logsetup import LogGate, setup_logging
from epc_offboard.common.signing import load_signing_key
from epc_offboard.control.attitude import AttitudeOutput
from epc_offboard.control.cascade import Cascade
from epc_offboard.control.library import LibrarySnapshot
from epc_offboard.control.position import PositionOutput
from epc_offboard.control.reference import ReferenceHorizon
from epc_offboard.control.trajectories import Trajectory
from epc_offboard.fleet.sharing import FleetSharing
from epc_offboard.service import realtime
from epc_offboard.service.clock import Clock, VehicleClock, WallClock
from epc_offboard.service.config import ServiceConfig, load_service_config
from epc_offboard.service.miss_solver import MissSolver
from epc_offboard.service.reference import ReferenceSelector
from epc_offboard.service.timing import LoopTiming
from epc_offboard.store import experience
from epc_offboard.store.library import LibraryStore
from epc_offboard.vehicle.dialect import (
    MAV_AUTOPILOT_INVALID,
    Command,
    Dialect,
    EncodeError,
    Position,
    choose,
    message_interval,
)
from epc_offboard.vehicle.link import MavlinkLink, TlogWriter
from epc_offboard.vehicle.offboard import Action, Inputs, OffboardStateMachine, Outputs, Phase
from epc_offboard.vehicle.rates import RateMonitor
from epc_offboard.vehicle.state import StateTracker, VehicleState

log = logging.getLogger("epc_offboard.service")

# SET_ATTITUDE_TARGET type_mask bits (MAVLink ATTITUDE_TARGET_TYPEMASK)
_IGNORE_RATES = 1 | 2 | 4
_IGNORE_ATTITUDE = 128

_MSG_ATTITUDE_QUATERNION = 31
_MSG_LOCAL_POSITION_NED = 32
_RATE_WINDOW_S = 2.0  # received rates are measured over windows this long
_GLOBAL_MAX_AGE_S = 1.0  # GLOBAL_POSITION_INT older than this is not used
_MAX_PHASE_EVENTS = 200  # phase transitions kept for the stats
_LOCKSTEP_SILENCE_FACTOR = 10.0  # lockstep: wall-clock silence tolerated, x heartbeat timeout


@dataclass(frozen=True)
class _GlobalFix:
    """The newest GLOBAL_POSITION_INT: what an explicit takeoff altitude is computed from."""

    lat_e7: int
    lon_e7: int
    amsl_m: float
    relative_alt_m: float
    received_s: float  # loop clock


class _Stop(Exception):  # noqa: N818 - control flow, not an error
    """Raised inside the TaskGroup to end the service cleanly."""


class Service:
    def __init__(self, cfg: ServiceConfig, config_path: str | None = None) -> None:
        self.cfg = cfg
        self.config_path = config_path
        self.clock: Clock = VehicleClock() if cfg.loops.clock == "vehicle" else WallClock()
        self.tracker = StateTracker(
            system_id=cfg.link.target_system,
            component_id=cfg.link.target_component,
            limits=cfg.state_limits,
        )
        self.sm = OffboardStateMachine(cfg.offboard, land_at_end=cfg.mission.land_at_end)
        # the autopilot's dialect: forced by link.autopilot, else from its first heartbeat
        # (until then the state machine sees no heartbeat: nothing is commanded)
        self.dialect: Dialect | None = choose(cfg.link.autopilot, None)
        if self.dialect is not None:
            self.sm.dialect = self.dialect
        self.params: dict[str, float] = {}  # autopilot parameters read (PARAM_VALUE)
        self._params_requested_at = -math.inf
        self.cascade = Cascade(
            cfg.position,
            cfg.attitude,
            cfg.estimator,
            1.0 / cfg.loops.position_rate_hz,
            learn_on_miss=False,
        )
        self.misses = MissSolver(
            dict(self.cascade.experience_controllers()),
            slice_s=cfg.sharing.candidate_slice_s,
        )
        self.counters: Counter[str] = Counter()
        self.references = ReferenceSelector(cfg.position, cfg.reference.timeout_s, self.counters)
        self.position_timing = LoopTiming(1.0 / cfg.loops.position_rate_hz)
        self.attitude_timing = LoopTiming(1.0 / cfg.loops.attitude_rate_hz)
        self.outputs = Outputs(Phase.WAIT_HEARTBEAT, False, (), "starting")
        self.trajectory: Trajectory | None = None
        self._position_out: PositionOutput | None = None
        self._stopping = asyncio.Event()
        self._exit_code = 0
        self._last_rx_wall = -math.inf
        self._rates_requested_at = -math.inf
        self.rates = RateMonitor(
            {
                "ATTITUDE_QUATERNION": cfg.loops.attitude_rate_hz,
                "LOCAL_POSITION_NED": cfg.loops.position_rate_hz,
            }
        )
        self._global: _GlobalFix | None = None
        self._landed_state: int | None = None  # EXTENDED_SYS_STATE, when the autopilot says
        self._ready_sent = False
        self._control_alive_wall = -math.inf
        self._lingering = False  # landed, still up for the fleet (mission.linger_after_landing)
        self.gc_monitor = realtime.GcMonitor()
        self._log_gate = LogGate()  # wire- and loop-driven log lines, rate-limited
        # phase transitions on the loop clock, the newest _MAX_PHASE_EVENTS (a flapping link
        # cannot grow it)
        self.phase_events: deque[dict[str, Any]] = deque(maxlen=_MAX_PHASE_EVENTS)
        self._flight_log: TextIO | None = None
        self._flight_writer: Any = None
        tlog = TlogWriter(cfg.log.tlog_path) if cfg.log.tlog_path else None
        key = load_signing_key(cfg.link.signing_key_file) if cfg.link.signing_key_file else None
        self.link = MavlinkLink(
            cfg.link.url,
            system_id=cfg.link.system_id,
            component_id=cfg.link.component_id,
            on_message=self._on_message,
            accept_system_ids=frozenset({cfg.link.target_system}),
            signing_key=key,
            tlog=tlog,
        )
        self.store: LibraryStore | None = None
        self.sharing: FleetSharing | None = None
        live = cfg.reference.source == "zenoh"
        if cfg.sharing.enabled or live:
            self.sharing = FleetSharing(
                cfg.sharing,
                self.cascade.experience_controllers() if cfg.sharing.enabled else [],
                share_library=cfg.sharing.enabled,
                reference=live,
            )
        from sdnotify import SystemdNotifier

        self._notifier = SystemdNotifier()
        if self._notifier.socket is not None:
            # a notify must never stall the control loop: if the socket's queue is full
            # (nobody reading), the ping is dropped (sdnotify swallows the error), not waited on
            self._notifier.socket.setblocking(False)

    # -- messages ---------------------------------------------------------------------

    def _on_message(self, msg: Any) -> None:
        self._last_rx_wall = time.monotonic()
        now = self.clock.now_s()  # in lockstep vehicle time: heartbeat ages are too
        held = self.tracker.heartbeat
        if self.tracker.handle(msg, received_s=now) and isinstance(self.clock, VehicleClock):
            self.clock.advance(self.tracker.vehicle_time_s)
        mtype = msg.get_type()
        self.rates.record(mtype)
        hb = self.tracker.heartbeat
        if mtype == "HEARTBEAT" and hb is not None and hb is not held:
            # only a heartbeat the tracker accepted (the autopilot's component and kind)
            self._adopt_dialect(hb.autopilot)
        elif mtype == "GLOBAL_POSITION_INT":
            amsl, rel = msg.alt * 1e-3, msg.relative_alt * 1e-3
            if math.isfinite(amsl) and math.isfinite(rel) and abs(rel) < 1e5:
                self._global = _GlobalFix(msg.lat, msg.lon, amsl, rel, now)
        elif mtype == "EXTENDED_SYS_STATE":
            self._landed_state = int(msg.landed_state)
        elif mtype == "PARAM_VALUE" and msg.get_srcSystem() == self.cfg.link.target_system:
            self._on_param(msg)
        elif mtype == "COMMAND_ACK":
            # two counters, whatever the wire says: a fuzzing peer cannot grow the dict
            accepted = msg.result in (mavlink.MAV_RESULT_ACCEPTED, 5)  # 5: in progress
            self.counters["acks_accepted" if accepted else "acks_refused"] += 1
            if not accepted and self._log_gate.open("ack", 1.0):
                log.info(
                    "command %d answered with result %d (%d refusals so far)",
                    msg.command, msg.result, self.counters["acks_refused"],
                )  # fmt: skip

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
            self.dialect = self.sm.dialect = dialect
            log.info(
                "autopilot dialect %s (HEARTBEAT.autopilot %d), attitude mode %s",
                dialect.name, autopilot, self._attitude_mode,
            )  # fmt: skip
            if self.cfg.attitude.mode == "epc" and dialect.default_attitude_mode != "epc":
                log.warning(
                    "attitude.mode = \"epc\" (body rates) on %s: its shaped rate response is "
                    "not the identified model; \"auto\" flies quaternion mode", dialect.name,
                )  # fmt: skip
        elif autopilot != self.dialect.autopilot:
            self.counters["heartbeats_other_autopilot"] += 1
            if self._log_gate.open("autopilot", 10.0):
                log.error(
                    "link.autopilot = %s but HEARTBEAT.autopilot is %d: speaking %s anyway",
                    self.cfg.link.autopilot, autopilot, self.dialect.name,
                )  # fmt: skip

    @property
    def _attitude_mode(self) -> str:
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
        hover = self.cfg.position.hover_thrust_norm
        if name == "MOT_THST_HOVER" and math.isfinite(value) and abs(value - hover) > 0.05:
            self.counters["hover_thrust_mismatch"] += 1
            log.warning(
                "MOT_THST_HOVER is %.3f but position.hover_thrust_norm is %.3f: set it to "
                "the autopilot's learned hover throttle", value, hover,
            )  # fmt: skip

    def _offboard_refusal(self) -> str:
        """Why offboard must not be requested, nor setpoints sent ("" when they may)."""
        return "" if self.dialect is None else self.dialect.offboard_refusal(self.params)

    def _manage_params(self, now: float, link_up: bool) -> None:
        """Read the dialect's parameters at link-up; again (every retry_period_s) while one
        is missing or while they refuse offboard (the user may be setting it now)."""
        if not link_up or self.dialect is None:
            return
        wanted = [
            name
            for name in self.dialect.params_to_read
            if name not in self.params or self._offboard_refusal()
        ]
        if not wanted or now - self._params_requested_at < self.cfg.offboard.retry_period_s:
            return
        self._params_requested_at = now
        for name in wanted:
            self.link.send(
                self.link.mav.param_request_read_encode(
                    self.cfg.link.target_system,
                    self.cfg.link.target_component,
                    name.encode(),
                    -1,
                )
            )

    def _send_command(self, cmd: Command) -> None:
        link = self.link
        sys_id, comp_id = self.cfg.link.target_system, self.cfg.link.target_component
        p = cmd.params
        if cmd.int_frame is None:
            msg = link.mav.command_long_encode(sys_id, comp_id, cmd.command, 0, *p)
        else:
            msg = link.mav.command_int_encode(
                sys_id, comp_id, cmd.int_frame, cmd.command, 0, 0,
                p[0], p[1], p[2], p[3], round(p[4]), round(p[5]), p[6],
            )  # fmt: skip
        link.send(msg)
        self.counters["commands_sent"] += 1

    def _do_action(self, action: Action, out: Outputs, state: VehicleState | None) -> None:
        if self.dialect is None:
            return  # (the state machine sees no heartbeat before a dialect is chosen)
        why = self._offboard_refusal() if action == Action.REQUEST_OFFBOARD else ""
        if why:
            self.counters["offboard_refused"] += 1
            if self._log_gate.open("refusal", 10.0):
                log.error(
                    "not requesting offboard (%s GUIDED) nor sending setpoints: %s "
                    "(%d refusals so far)", self.dialect.name, why,
                    self.counters["offboard_refused"],
                )  # fmt: skip
            return
        fix = self._fresh_global()
        position = (
            None
            if fix is None or state is None
            else Position(fix.lat_e7, fix.lon_e7, math.degrees(state.yaw_rad))
        )
        try:
            cmd = self.dialect.encode(action, out.takeoff, position)
        except EncodeError as exc:
            self.counters["commands_not_encoded"] += 1
            log.error("action %s not sent: %s", action.value, exc)
            return
        if action == Action.TAKEOFF and out.takeoff is not None:
            self.counters["takeoffs_sent"] += 1
            log.info(
                "action: takeoff to %.2f m above home (%.2f m AMSL)",
                out.takeoff.above_home_m, out.takeoff.amsl_m,
            )  # fmt: skip
        else:
            log.info("action: %s", action.value)
        self._send_command(cmd)

    def _fresh_global(self) -> _GlobalFix | None:
        fix = self._global
        if fix is None or self.clock.now_s() - fix.received_s > _GLOBAL_MAX_AGE_S:
            return None
        return fix

    def _request_rates(self) -> None:
        for msg_id, rate in (
            (_MSG_ATTITUDE_QUATERNION, self.cfg.loops.attitude_rate_hz),
            (_MSG_LOCAL_POSITION_NED, self.cfg.loops.position_rate_hz),
        ):
            self._send_command(message_interval(msg_id, rate))
        for msg_id, rate in () if self.dialect is None else self.dialect.extra_streams_hz:
            self._send_command(message_interval(msg_id, rate))

    def _manage_rates(self, now: float, link_up: bool) -> None:
        """Ask for the loops' rates when the link comes up, then again (at most every
        retry_period_s) while a measured stream falls short."""
        measured = self.rates.sample(now, _RATE_WINDOW_S)
        if not link_up:
            return
        first = self._rates_requested_at == -math.inf
        short = measured and self.rates.short()
        if (first or short) and now - self._rates_requested_at >= self.cfg.offboard.retry_period_s:
            if short:
                self.counters["rate_requests_repeated"] += 1
                log.info(
                    "message rates short of the loops' (%s): asking again",
                    ", ".join(f"{k} {self.rates.rates_hz[k]:.0f} Hz" for k in short),
                )
            self._rates_requested_at = now
            self._request_rates()

    # -- tasks ------------------------------------------------------------------------

    async def _supervisor(self) -> None:
        period = 1.0 / self.cfg.loops.supervisor_rate_hz
        # A silent link (nothing at all received) counts as a lost heartbeat. In lockstep the
        # heartbeat's age is judged in vehicle time by the state machine; wall-clock silence
        # only tells a simulator that has gone, and a loaded machine must not look like one
        # (it failed a lockstep figure-8 safe beside a CPU hog: runs must not depend on load).
        silence_s = self.cfg.offboard.heartbeat_timeout_s * (
            _LOCKSTEP_SILENCE_FACTOR if self.clock.vehicle_time else 1.0
        )
        while True:
            now = self.clock.now_s()
            silent = time.monotonic() - self._last_rx_wall > silence_s
            hb = None if silent or self.dialect is None else self.tracker.heartbeat
            age = self.tracker.age_s(now, vehicle_clock=self.clock.vehicle_time)
            state = self.tracker.snapshot()
            fix = self._fresh_global()
            out = self.sm.step(
                Inputs(
                    now,
                    hb,
                    age,
                    pos_down_m=None if state is None else float(state.pos_ned_m[2]),
                    relative_alt_m=None if fix is None else fix.relative_alt_m,
                    amsl_m=None if fix is None else fix.amsl_m,
                    landed_state=self._landed_state,
                    mission_complete=self._mission_complete(now),
                )
            )
            for action in out.actions:
                self._do_action(action, out, state)
            if out.phase != self.outputs.phase:
                self._phase_changed(now, out)
                if out.phase in (Phase.STREAMING, Phase.OFFBOARD) and state is not None:
                    self._start_rejoin(state, now)
            self.outputs = out
            self._manage_rates(now, link_up=hb is not None)
            self._manage_params(now, link_up=hb is not None)
            if not self._ready_sent and age <= self.cfg.offboard.max_state_age_s:
                self._ready_sent = True
                self._notifier.notify("READY=1")
                log.info("link up and state flowing: ready")
            if out.phase == Phase.OFFBOARD and self.trajectory is None and state is not None:
                self._start_trajectory(state, out.altitude_m)
            if out.phase == Phase.DONE and self.cfg.mission.duration_s > 0:
                self._mission_over()
            await self._wait(now + period)

    def _phase_changed(self, now: float, out: Outputs) -> None:
        """Log, tell systemd, count failsafes and keep the transition for the stats (the sim
        report marks them where they happened)."""
        log.info("phase %s -> %s (%s)", self.outputs.phase.value, out.phase.value, out.reason)
        self._notifier.notify(f"STATUS={out.phase.value}: {out.reason}")
        if out.phase == Phase.FAILSAFE:
            self.counters["failsafes"] += 1
        self.phase_events.append(
            {"t_s": round(now, 4), "phase": out.phase.value, "reason": out.reason}
        )

    def _start_rejoin(self, state: VehicleState, now: float) -> None:
        self.references.start_rejoin(self.trajectory, state, now)

    def _start_trajectory(self, state: VehicleState, altitude_m: float | None) -> None:
        anchor = state.pos_ned_m.copy()
        want = self.cfg.trajectory_altitude_m
        if want is not None and altitude_m is not None:
            anchor[2] += altitude_m - want  # down of home = down now + height above home
        self.trajectory = Trajectory(self.cfg.trajectory, anchor, start_s=self.clock.now_s())
        self.references.hold_at(anchor)
        log.info("trajectory %s started at %s", self.cfg.trajectory.shape, anchor.round(3).tolist())

    def _mission_complete(self, now: float) -> bool:
        dur = self.cfg.mission.duration_s
        return self.trajectory is not None and dur > 0 and now - self.trajectory.start_s >= dur

    def _mission_over(self) -> None:
        """The mission's flight is over (landed, or handed over holding): exit, or linger."""
        if not self.cfg.mission.linger_after_landing:
            self._stopping.set()
        elif not self._lingering:
            self._lingering = True
            self._write_stats()  # the flight's figures; rewritten at the stop
            log.info("mission complete: staying up for the fleet until stopped")

    async def _wait(self, t_s: float, *, until_reached: bool = False) -> None:
        """Wait for loop time t_s; in lockstep never longer than a wall-clock second, unless
        ``until_reached``: the control loops then wait for the vehicle clock however long a
        loaded machine takes (a tick run early, at a stale vehicle time, would make two
        identical lockstep runs differ), checking for a stop every second."""
        while True:
            try:
                async with asyncio.timeout(1.0):
                    await self.clock.wait_until(t_s)
                break
            except TimeoutError:
                # (not before the vehicle clock has started: an autopilot that streams nothing
                # until asked, as ArduCopter, gives no time until the loops' rates are requested)
                if self.clock.now_s() > 0.0:
                    self.counters["clock_wait_timeouts"] += 1
            if not until_reached or self._stopping.is_set():
                break
        if self._stopping.is_set():
            raise _Stop

    async def _position_loop(self) -> None:
        period = 1.0 / self.cfg.loops.position_rate_hz
        t_next = self.clock.now_s()
        while True:
            await self._wait(t_next, until_reached=True)
            start = self.clock.now_s()
            wall0 = time.perf_counter()
            state = self.tracker.snapshot()
            # misses solved by the worker join the library here; in lockstep the tick waits
            # for the solve in flight, so it joins at the same tick every run
            self.misses.pump(wait=self.clock.vehicle_time)
            if self.outputs.stream_setpoints and state is not None:
                self._position_out = self._position_tick(state, start)
                self._control_alive_wall = time.monotonic()
            if self.outputs.stream_setpoints:  # timing of the ticks that control, not idle ones
                self.position_timing.record(start, time.perf_counter() - wall0, scheduled_s=t_next)
            t_next = self._next_tick(t_next, period, "position")

    @property
    def _autopilot_positions(self) -> bool:
        return self.cfg.position.controller == "px4"

    def _send_position_target(self, state: VehicleState, t_s: float) -> None:
        """The px4 baseline: the reference's position, velocity and acceleration now, to the
        autopilot's own position controller (as MAVSDK's offboard plugin sends them)."""
        now = self.references.now(state, t_s, self.trajectory)
        values = [float(v) for v in now.stages[0]]
        if not all(math.isfinite(v) for v in values):
            self.counters["non_finite_setpoints_replaced"] += 1
            return
        self.link.send(
            self.link.mav.set_position_target_local_ned_encode(
                self._stamp_ms(state),
                self.cfg.link.target_system,
                self.cfg.link.target_component,
                mavlink.MAV_FRAME_LOCAL_NED,
                mavlink.POSITION_TARGET_TYPEMASK_YAW_RATE_IGNORE,
                *values,
                float(now.yaw_rad[0]),
                0.0,
            )
        )

    def _position_tick(self, state: VehicleState, t_s: float) -> PositionOutput:
        reference: ReferenceHorizon | None = None  # what the flight log shows
        if self._autopilot_positions:  # nothing to compute: the log keeps the reference
            out = self.cascade.hover(state)
            reference = self.references.now(state, t_s, self.trajectory)
            self._log_tick(state, t_s, out, reference)
            return out
        offboard = self.outputs.phase == Phase.OFFBOARD
        try:
            reference = self.references.horizon(
                state, t_s, self.trajectory, self.sharing, offboard=offboard
            )
            out = self.cascade.position_tick(state, reference, learn=offboard)
        except Exception as exc:  # degrade, never die
            self._loop_error("position", exc)
            out = self.cascade.hover(state)
        self._log_tick(state, t_s, out, reference)
        return out

    async def _attitude_loop(self) -> None:
        period = 1.0 / self.cfg.loops.attitude_rate_hz
        t_next = self.clock.now_s()
        while True:
            await self._wait(t_next, until_reached=True)
            start = self.clock.now_s()
            wall0 = time.perf_counter()
            state = self.tracker.snapshot()
            if self.clock.vehicle_time:
                # lockstep: the answer releases the simulator's next tick, so it goes last,
                # after whatever the other tasks woken at this tick send (commands)
                await asyncio.sleep(0)
            # (ArduPilot without GUID_OPTIONS bit 3 would read our thrust as a climb rate)
            streaming = self.outputs.stream_setpoints and not self._offboard_refusal()
            if streaming and state is not None and self._autopilot_positions:
                self._send_position_target(state, start)
            elif streaming and state is not None:
                target = self._position_out or self.cascade.hover(state)
                # A late tick or an old attitude sample: body rates computed now would be
                # flown until the next tick, stale; send the attitude itself instead, which
                # the autopilot's own attitude loop keeps tracking whatever we do next.
                late = start - t_next > period or state.attitude_age_s > 2.0 * period
                self._send_setpoint(state, target, late=late)
            elif self.clock.vehicle_time and state is not None:
                # lockstep: the simulator advances only on an answer for each tick; when no
                # setpoint streams (before takeoff, landing) the answer is a SYSTEM_TIME with
                # the tick's stamp (time_unix_usec 0: no autopilot takes it as a clock)
                self.link.send(self.link.mav.system_time_encode(0, self._stamp_ms(state)))
            if self.outputs.stream_setpoints:
                self.attitude_timing.record(start, time.perf_counter() - wall0, scheduled_s=t_next)
            t_next = self._next_tick(t_next, period, "attitude")

    def _next_tick(self, t_next: float, period: float, loop: str) -> float:
        """The next tick time; when more than a tick behind, skip (never burst) and count it
        if it mattered (while streaming: before that the loops idle)."""
        t_next += period
        now = self.clock.now_s()
        if t_next - now > period:
            # the wait timed out: the clock did not move (lockstep, before an autopilot that
            # streams nothing until asked sends state): run on from the clock, never ahead
            # of it (ahead, every tick would cost a wait timeout)
            t_next = now + period
        if now - t_next > period:
            skipped = int((now - t_next) / period)
            if self.outputs.stream_setpoints:
                self.counters[f"{loop}_ticks_skipped"] += skipped
            t_next += skipped * period
        return t_next

    def _send_setpoint(
        self, state: VehicleState, target: PositionOutput, *, late: bool = False
    ) -> None:
        if self._attitude_mode == "autopilot":
            out = AttitudeOutput(None, target.thrust_norm, "delegated")
        elif late:
            self.counters["attitude_late_fallbacks"] += 1
            out = AttitudeOutput(None, target.thrust_norm, "late")
        elif not self.cascade.rates_trusted(state, target):
            self.counters["attitude_envelope_fallbacks"] += 1
            out = AttitudeOutput(None, target.thrust_norm, "envelope")
        else:
            try:
                out = self.cascade.attitude_tick(state, target)
            except Exception as exc:
                self._loop_error("attitude", exc)
                out = self.cascade.attitude_fallback(state, target)
        q = [float(v) for v in target.q_target]
        thrust = float(out.thrust_norm)
        if out.rates_frd_rad_s is None:
            rates, mask = [0.0, 0.0, 0.0], _IGNORE_RATES
        else:
            # bounded to what the vehicle's rate loop can follow, whatever computed them
            rmax = self.cfg.attitude.max_rate_rad_s
            rates = [
                min(max(float(v), -m), m)
                for v, m in zip(out.rates_frd_rad_s, rmax, strict=True)
            ]
            mask = _IGNORE_ATTITUDE
        if not all(math.isfinite(v) for v in (*q, *rates, thrust)):
            # never a NaN to the autopilot: level at hover thrust instead, counted
            self.counters["non_finite_setpoints_replaced"] += 1
            hover = self.cascade.hover(state)
            q, rates = [float(v) for v in hover.q_target], [0.0, 0.0, 0.0]
            thrust, mask = hover.thrust_norm, _IGNORE_RATES
        if self.dialect is not None:
            # the thrust as the autopilot reads it (ArduCopter adds its own tilt boost)
            roll, pitch, _ = state.euler_rad
            thrust = self.dialect.wire_thrust(thrust, math.cos(roll) * math.cos(pitch))
        stamp_ms = self._stamp_ms(state)
        self.link.send(
            self.link.mav.set_attitude_target_encode(
                stamp_ms,
                self.cfg.link.target_system,
                self.cfg.link.target_component,
                mask,
                q,
                *rates,
                min(max(thrust, 0.0), 1.0),
            )
        )

    @staticmethod
    def _stamp_ms(state: VehicleState) -> int:
        """time_boot_ms of what we send: the vehicle time of the state used (the lockstep
        simulator's "answered" mark)."""
        return round(state.time_s * 1000.0) & 0xFFFFFFFF

    def _loop_error(self, loop: str, exc: Exception) -> None:
        self.counters[f"{loop}_loop_errors"] += 1
        if self._log_gate.open("loop_error", 1.0):
            log.error(
                "%s loop degraded to hover after %s: %s (%d so far)",
                loop,
                type(exc).__name__,
                exc,
                self.counters[f"{loop}_loop_errors"],
            )

    async def _saver(self) -> None:
        while True:
            await asyncio.sleep(self.cfg.store.save_period_s)
            if self.sharing is None or not self.sharing.share_library:
                # nobody publishes them: the store saves the whole library anyway
                for _name, ctrl in self.cascade.experience_controllers():
                    ctrl.pop_new_entries()
            if self.store is None:
                continue
            # the copy on the loop (the library is not thread-safe), the disk off it
            try:
                snap = experience.snapshot(self.cascade)
            except Exception as exc:  # never let saving take a loop down
                self.counters["store_errors"] += 1
                log.error("snapshotting the library failed: %s", exc)
                continue
            await asyncio.to_thread(self._write_library, snap)

    def _write_library(self, snap: LibrarySnapshot) -> None:
        assert self.store is not None
        try:
            self.store.save_snapshot(snap)
        except Exception as exc:  # a full disk must not stop the flight
            self.counters["store_errors"] += 1
            log.error("saving the library failed: %s", exc)

    def _save_library(self) -> None:
        if self.store is None:
            return
        try:
            experience.save(self.cascade, self.store)
        except Exception as exc:  # a full disk must not stop the flight
            self.counters["store_errors"] += 1
            log.error("saving the library failed: %s", exc)

    async def _systemd(self) -> None:
        while True:
            await asyncio.sleep(self.cfg.loops.watchdog_period_s)
            streaming = self.outputs.stream_setpoints
            # Ping only if the control loop itself ticked recently (a stalled loop stops them),
            # or if there is nothing to control yet.
            alive = (
                time.monotonic() - self._control_alive_wall < 2 * self.cfg.loops.watchdog_period_s
            )
            if alive or not streaming:
                self._notifier.notify("WATCHDOG=1")

    # -- lifecycle --------------------------------------------------------------------

    def _open_store(self) -> None:
        if not self.cfg.store.path:
            return
        self.store = LibraryStore.open(self.cfg.store.path)
        loaded = experience.load(self.cascade, self.store)
        log.info("library %s: loaded %s", self.cfg.store.path, loaded)

    def _open_flight_log(self) -> None:
        if not self.cfg.log.flight_log_path:
            return
        path = Path(self.cfg.log.flight_log_path)
        path.parent.mkdir(parents=True, exist_ok=True)
        self._flight_log = path.open("w", newline="")
        self._flight_writer = csv.writer(self._flight_log)
        self._flight_writer.writerow(_FLIGHT_LOG_COLUMNS)

    def _log_tick(
        self,
        state: VehicleState,
        t_s: float,
        out: PositionOutput,
        reference: ReferenceHorizon | None,
    ) -> None:
        """One flight-log row; ``reference``: what the tick flew (its stage 0 is logged), or
        None when the tick failed before it had one (the vehicle's position is logged)."""
        if self._flight_writer is None:
            return
        if reference is not None:
            ref_pos, ref_vel = reference.pos_ned_m[0], reference.vel_ned_m_s[0]
        else:
            ref_pos, ref_vel = state.pos_ned_m, np.zeros(3)
        self._flight_writer.writerow(
            [f"{t_s:.4f}", f"{state.time_s:.4f}", self.outputs.phase.value]
            + [f"{v:.5f}" for v in (*state.pos_ned_m, *state.vel_ned_m_s, *ref_pos, *ref_vel)]
            + [f"{v:.5f}" for v in (*out.acc_cmd_ned_m_s2, *out.p_hat_ned_m_s2, out.thrust_norm)]
            + [out.source, f"{out.compute_us:.1f}"]
        )

    def request_stop(self) -> None:
        self._stopping.set()

    def _reload(self) -> None:
        if self.config_path is None:
            return
        try:
            new = load_service_config(self.config_path)
        except ConfigError as exc:
            log.error("SIGHUP: config not reloaded: %s", exc)
            return
        self.cfg = replace(
            self.cfg, trajectory=new.trajectory, mission=new.mission, offboard=new.offboard
        )
        self.sm.config = new.offboard
        self.sm.land_at_end = new.mission.land_at_end
        if self.trajectory is not None:
            self.trajectory = Trajectory(
                new.trajectory, self.trajectory.anchor_ned_m, self.clock.now_s()
            )
        logging.getLogger().setLevel(new.log.level.upper())
        log.info("SIGHUP: trajectory, mission and offboard settings reloaded")

    async def run(self) -> int:
        # numba compiles (or loads from its cache) each kernel on first use: 0.2-1 s that,
        # inside the first tick, stalled the loops into a stale-state failsafe. Done here,
        # before the link opens, before READY=1 and before any setpoint streams.
        log.info("control kernels compiled and warmed in %.2f s", self.cascade.warm_up())
        t0 = time.perf_counter()
        self.misses.start()
        log.info("EPC miss worker up in %.2f s", time.perf_counter() - t0)
        self._open_store()
        self._open_flight_log()
        await self._open_sharing()
        await self.link.open()
        self._prepare_realtime()
        loop = asyncio.get_running_loop()
        loop.add_signal_handler(signal.SIGTERM, self.request_stop)
        loop.add_signal_handler(signal.SIGINT, self.request_stop)
        loop.add_signal_handler(signal.SIGHUP, self._reload)
        log.info(
            "epc-offboard running: %s, target system %d",
            self.cfg.link.url,
            self.cfg.link.target_system,
        )
        try:
            async with asyncio.TaskGroup() as tg:
                tg.create_task(self._supervisor(), name="supervisor")
                tg.create_task(self._position_loop(), name="position-loop")
                tg.create_task(self._attitude_loop(), name="attitude-loop")
                tg.create_task(self._saver(), name="library-saver")
                if self.sharing is not None and self.sharing.share_library:
                    tg.create_task(self.sharing.run(), name="library-sharing")
                tg.create_task(self._systemd(), name="systemd")
                tg.create_task(self._stop_watch(), name="stop")
        except* _Stop:
            pass
        finally:
            await self._shutdown()
        return self._exit_code

    def _prepare_realtime(self) -> None:
        """Start-up is over: freeze its objects out of the garbage collector and, if
        configured, raise the loops' scheduling priority (service/realtime.py)."""
        frozen = realtime.freeze_startup_objects()
        self.gc_monitor.install()
        try:
            how = realtime.apply_priority(self.cfg.loops.realtime_priority)
        except realtime.PriorityError as exc:
            self.counters["realtime_priority_refused"] += 1
            how = "normal scheduling"
            log.warning("loops.realtime_priority not applied: %s", exc)
        log.info("loops: %s; %d start-up objects frozen out of the garbage collector", how, frozen)

    async def _open_sharing(self) -> None:
        """Join the fleet; a vehicle that cannot still flies, alone (logged, counted)."""
        if self.sharing is None:
            return
        try:
            await self.sharing.open()
        except Exception as exc:
            self.counters["sharing_open_failed"] += 1
            log.error("fleet sharing unavailable, flying without it: %s", exc)
            self.sharing.close()
            self.sharing = None

    async def _stop_watch(self) -> None:
        await self._stopping.wait()
        raise _Stop

    async def _shutdown(self) -> None:
        self._notifier.notify("STOPPING=1")
        if self.dialect is not None and self.outputs.phase in (
            Phase.OFFBOARD,
            Phase.OFFBOARD_REQUESTED,
        ):
            # leave the vehicle holding, not waiting for our setpoints to time out
            self._send_command(self.dialect.encode(Action.REQUEST_HOLD))
        self.misses.close()
        self._save_library()
        if self.store is not None:
            self.store.close()
        if self.sharing is not None:
            self.sharing.close()
        if self._flight_log is not None:
            self._flight_log.close()
        self._write_stats()
        self.link.close()
        self.gc_monitor.uninstall()
        log.info("stopped: %s", dict(self.counters))

    def stats(self) -> dict[str, Any]:
        return {
            "phase": self.outputs.phase.value,
            "phase_events": list(self.phase_events),
            "autopilot": None if self.dialect is None else self.dialect.name,
            "attitude_mode": self._attitude_mode,
            "params": dict(self.params),
            "takeoffs_sent": self.sm.takeoffs_sent,
            "rates_hz": {k: round(v, 1) for k, v in self.rates.rates_hz.items()},
            "library": self.cascade.library_stats(),
            "loops": {
                "position": self.position_timing.report().as_dict(),
                "attitude": self.attitude_timing.report().as_dict(),
            },
            "counters": dict(self.counters),
            "gc": self.gc_monitor.stats(),
            "miss_worker": dict(self.misses.counters),
            "link": dict(self.link.counters),
            "state": dict(self.tracker.counters),
            "sharing": self.sharing.stats() if self.sharing is not None else {},
        }

    def _write_stats(self) -> None:
        if not self.cfg.log.stats_path:
            return
        path = Path(self.cfg.log.stats_path)
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(json.dumps(self.stats(), indent=2))


_FLIGHT_LOG_COLUMNS = [
    "t_s", "vehicle_t_s", "phase",
    "pos_n_m", "pos_e_m", "pos_d_m", "vel_n_m_s", "vel_e_m_s", "vel_d_m_s",
    "ref_pos_n_m", "ref_pos_e_m", "ref_pos_d_m", "ref_vel_n_m_s", "ref_vel_e_m_s", "ref_vel_d_m_s",
    "acc_cmd_n_m_s2", "acc_cmd_e_m_s2", "acc_cmd_d_m_s2",
    "p_hat_n_m_s2", "p_hat_e_m_s2", "p_hat_d_m_s2", "thrust_norm",
    "source", "compute_us",
]  # fmt: skip


def run_service_command(args: argparse.Namespace) -> int:
    from epc_offboard.common.errors import UsageError

    try:
        cfg = load_service_config(args.config)
    except ConfigError as exc:
        raise UsageError(str(exc)) from exc
    setup_logging(cfg.log)
    try:
        service = Service(cfg, args.config)
    except (ConfigError, OSError) as exc:
        raise UsageError(str(exc)) from exc
    try:
        return asyncio.run(service.run())
    except OSError as exc:
        print(f"epc-offboard: {exc}", file=sys.stderr)
        return 1
