"""The offboard service: `epc-offboard run --config FILE`, the wiring of its parts.

One asyncio TaskGroup with named tasks:

* ``supervisor``     — the flight (``supervisor.py``: the offboard state machine, from arm to
  landing and the mission's end), talking to the autopilot (``autopilot.py``: messages in;
  rates, parameters and commands out);
* ``position-loop``  — 100 Hz: state -> reference horizon -> Cascade.position_tick (EPC + LWPR);
* ``attitude-loop``  — 200 Hz: Cascade.attitude_tick -> SET_ATTITUDE_TARGET (rates + thrust),
  or the autopilot's own attitude loop fed quaternion + thrust (``attitude.py``);
  both loops are ``loop.py``'s periodic loop around a tick of this module;
* ``library-saver``  — new controllers and learned models to SQLite, off the event loop;
* ``library-sharing`` — with ``[sharing] enabled``: offers controllers received from the
  fleet to the candidate pools (the miss worker screens them; only a candidate optimal for
  a real tick joins the library), publishes new ones, keeps the snapshot peers query
  (``fleet/sharing.py``);
* ``systemd``        — WATCHDOG=1 only while the control loop ticks (``systemd.py``).

MAVLink arrives through callbacks of the link's DatagramProtocol (no task, no blocking read);
what is sent is encoded by ``vehicle/commands.py``. The numerics live in ``cascade.py``; this
module never does linear algebra. Each position tick is a row of the flight log
(``flightlog.py``).

The control loops never die: an exception in a tick is logged (rate-limited), counted, and
the tick degrades to the cascade's safe hover command.
"""

from __future__ import annotations

import argparse
import asyncio
import json
import logging
import math
import signal
import sys
import time
from collections import Counter
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np

from epc_offboard.common.configio import ConfigError
from epc_offboard.common.frames import FloatArray
from epc_offboard.common.logsetup import LogGate, setup_logging
from epc_offboard.control.cascade import Cascade, PositionOutput
from epc_offboard.control.trajectories import Rejoin, Trajectory, live_reference_horizon
from epc_offboard.fleet.sharing import FleetSharing
from epc_offboard.service.attitude import AttitudeSender
from epc_offboard.service.autopilot import Autopilot
from epc_offboard.service.clock import Clock, VehicleClock, WallClock
from epc_offboard.service.config import ServiceConfig, load_service_config
from epc_offboard.service.flightlog import FlightLog
from epc_offboard.service.loop import Loops, Stop, Tick
from epc_offboard.service.miss_solver import MissSolver
from epc_offboard.service.supervisor import Supervisor
from epc_offboard.service.systemd import Systemd
from epc_offboard.service.timing import LoopTiming
from epc_offboard.store.library import LibrarySnapshot, LibraryStore
from epc_offboard.vehicle import commands
from epc_offboard.vehicle.offboard import Action, Outputs, Phase
from epc_offboard.vehicle.state import StateTracker, VehicleState

log = logging.getLogger("epc_offboard.service")


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
        log_gate = LogGate()  # wire- and loop-driven log lines, rate-limited
        self.loops = Loops(self.clock, self.counters, log_gate)
        self._loop_error = self.loops.error
        self.autopilot = Autopilot(cfg, self.clock, self.tracker, self.counters, log_gate)
        self.link = self.autopilot.link
        self.systemd = Systemd(cfg.loops.watchdog_period_s)
        self.supervisor = Supervisor(
            cfg, self.clock, self.tracker, self.autopilot, self.systemd, self.counters,
            self.loops.stopping, self._write_stats,
        )  # fmt: skip
        self.attitude = AttitudeSender(
            self.cascade, self.autopilot, cfg.attitude.max_rate_rad_s, self.counters,
            self._loop_error,
        )  # fmt: skip
        self.position_timing = LoopTiming(1.0 / cfg.loops.position_rate_hz)
        self.attitude_timing = LoopTiming(1.0 / cfg.loops.attitude_rate_hz)
        self.trajectory: Trajectory | None = None
        self._rejoin: Rejoin | None = None  # the way back onto the trajectory after a hold
        self._position_out: PositionOutput | None = None
        self._exit_code = 0
        self.flight_log: FlightLog | None = None
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
        self._live_reference = False  # whether the last position tick flew a live reference

    @property
    def outputs(self) -> Outputs:
        """The state machine's newest step."""
        return self.supervisor.outputs

    # -- tasks ------------------------------------------------------------------------

    async def _supervise(self) -> None:
        """The flight, and what it starts on the reference side: the rejoin when setpoints
        start streaming or offboard is (re)entered, the trajectory once in offboard."""
        period = 1.0 / self.cfg.loops.supervisor_rate_hz
        while True:
            now = self.clock.now_s()
            step = self.supervisor.step(now, mission_complete=self._mission_complete(now))
            out, state = step.outputs, step.state
            entered = step.phase_changed and out.phase in (Phase.STREAMING, Phase.OFFBOARD)
            if entered and state is not None:
                self._start_rejoin(state, now)
            if out.phase == Phase.OFFBOARD and self.trajectory is None and state is not None:
                self._start_trajectory(state, out.altitude_m)
            await self.loops.wait(now + period)

    def _start_rejoin(self, state: VehicleState, now: float) -> None:
        """Setpoints start streaming, or offboard is (re)entered, while a trajectory has run
        on (a failsafe, a pilot): the reference starts where the vehicle is and closes the
        gap smoothly (trajectories.Rejoin) instead of asking for a far point at once."""
        if self.trajectory is None:
            return
        self._rejoin = Rejoin.onto(
            self.trajectory.sample(now), state.pos_ned_m, state.vel_ned_m_s, now,
            self.cfg.trajectory.rejoin_tau_s,
        )  # fmt: skip
        gap = float(np.linalg.norm(self._rejoin.gap_ned_m))
        if gap > 0.05:
            self.counters["trajectory_rejoins"] += 1
            log.info("rejoining the trajectory %.2f m away (tau %.1f s)", gap,
                     self._rejoin.tau_s)  # fmt: skip

    def _reference_rows(self, t_s: float, dt_s: float, steps: int) -> FloatArray:
        """(steps + 1, 9) rows [p, v, a] of the trajectory from ``t_s``, rejoin included."""
        assert self.trajectory is not None
        rows = self.trajectory.horizon_from_now(t_s, dt_s, steps)
        if self._rejoin is not None:
            if self._rejoin.done(t_s):
                self._rejoin = None
            else:
                times = t_s + dt_s * np.arange(steps + 1, dtype=np.float64)
                rows = np.add(rows, self._rejoin.rows(times))
        return rows

    def _start_trajectory(self, state: VehicleState, altitude_m: float | None) -> None:
        anchor = state.pos_ned_m.copy()
        want = self.cfg.trajectory_altitude_m
        if want is not None and altitude_m is not None:
            anchor[2] += altitude_m - want  # down of home = down now + height above home
        self.trajectory = Trajectory(self.cfg.trajectory, anchor, start_s=self.clock.now_s())
        self.cascade.hold_position(anchor)
        log.info("trajectory %s started at %s", self.cfg.trajectory.shape, anchor.round(3).tolist())

    def _mission_complete(self, now: float) -> bool:
        dur = self.cfg.mission.duration_s
        return self.trajectory is not None and dur > 0 and now - self.trajectory.start_s >= dur

    async def _position_step(self, tick: Tick) -> bool:
        state = self.tracker.snapshot()
        # misses solved by the worker join the library here; in lockstep the tick waits
        # for the solve in flight, so it joins at the same tick every run
        self.misses.pump(wait=self.clock.vehicle_time)
        if self.outputs.stream_setpoints and state is not None:
            self._position_out = self._position_tick(state, tick.start_s)
            self.systemd.control_ticked()
        return self.outputs.stream_setpoints  # ticks that control are timed, not idle ones

    @property
    def _autopilot_positions(self) -> bool:
        return self.cfg.position.controller == "px4"

    def _send_position_target(self, state: VehicleState, t_s: float) -> None:
        """The px4 baseline: the reference's position, velocity and acceleration now, to the
        autopilot's own position controller (as MAVSDK's offboard plugin sends them)."""
        if self.trajectory is not None:
            row = self._reference_rows(t_s, 0.0, 0)[0]
            pos, vel, acc = row[:3], row[3:6], row[6:9]
        else:
            pos = self.cascade.hold_refs(state)[0, :3]
            vel = acc = np.zeros(3)
        msg = commands.position_target(
            self.autopilot.target, state.time_s, pos, vel, acc,
            math.radians(self.cfg.position.yaw_deg),
        )  # fmt: skip
        if msg is None:
            self.counters["non_finite_setpoints_replaced"] += 1
            return
        self.link.send(msg)

    def _position_tick(self, state: VehicleState, t_s: float) -> PositionOutput:
        if self._autopilot_positions:  # nothing to compute: the log keeps the reference
            out = self.cascade.hover(state)
            self._log_tick(state, t_s, out)
            return out
        ref_now: FloatArray | None = None  # the trajectory at t_s, for the flight log
        try:
            refs = self._live_refs(state)
            if refs is None and self.trajectory is not None:
                rows = self._reference_rows(
                    t_s, self.cascade.position_dt_s, self.cascade.position_horizon
                )
                ref_now, refs = rows[0], rows[1:]
            elif refs is None:
                refs = self.cascade.hold_refs(state)
            out = self.cascade.position_tick(
                state, refs, learn=self.outputs.phase == Phase.OFFBOARD
            )
        except Exception as exc:  # degrade, never die
            self._loop_error("position", exc)
            out = self.cascade.hover(state)
        self._log_tick(state, t_s, out, ref_now)
        return out

    def _live_refs(self, state: VehicleState) -> FloatArray | None:
        """The reference horizon from a fresh live reference (offboard only), else None."""
        ref = None
        if self.sharing is not None and self.outputs.phase == Phase.OFFBOARD:
            ref = self.sharing.live_reference(time.monotonic(), self.cfg.reference.timeout_s)
        if (ref is not None) != self._live_reference:
            self._live_reference = ref is not None
            if ref is not None:
                log.info("live reference: tracking from %s", list(ref.message.pos_ned_m))
            elif self.sharing is not None:
                self.counters["live_reference_stale"] += 1
                log.warning(
                    "live reference stale (> %.2f s): back to the %s",
                    self.cfg.reference.timeout_s,
                    "trajectory" if self.trajectory is not None else "hold",
                )
                self.cascade.yaw_target_rad = None
                if self.trajectory is None:
                    self.cascade.hold_position(state.pos_ned_m)
        if ref is None:
            return None
        msg = ref.message
        self.cascade.yaw_target_rad = msg.yaw_rad
        return live_reference_horizon(
            msg.pos_ned_m,
            msg.vel_ned_m_s,
            msg.horizon_pos_ned_m,
            msg.horizon_dt_s,
            age_s=time.monotonic() - ref.received_s,
            dt_s=self.cascade.position_dt_s,
            steps=self.cascade.position_horizon,
            width=self.cascade.pos_problem.nx,
        )

    async def _attitude_step(self, tick: Tick) -> bool:
        state = self.tracker.snapshot()
        if self.clock.vehicle_time:
            # lockstep: the answer releases the simulator's next tick, so it goes last,
            # after whatever the other tasks woken at this tick send (commands)
            await asyncio.sleep(0)
        # (ArduPilot without GUID_OPTIONS bit 3 would read our thrust as a climb rate)
        streaming = self.outputs.stream_setpoints and not self.autopilot.offboard_refusal()
        if streaming and state is not None and self._autopilot_positions:
            self._send_position_target(state, tick.start_s)
        elif streaming and state is not None:
            target = self._position_out or self.cascade.hover(state)
            # A late tick or an old attitude sample: body rates computed now would be
            # flown until the next tick, stale; send the attitude itself instead, which
            # the autopilot's own attitude loop keeps tracking whatever we do next.
            period = tick.period_s
            late = tick.start_s - tick.scheduled_s > period or state.attitude_age_s > 2 * period
            self.attitude.send(state, target, late=late)
        elif self.clock.vehicle_time and state is not None:
            # lockstep: the simulator advances only on an answer for each tick; when no
            # setpoint streams (before takeoff, landing) the answer is a SYSTEM_TIME
            self.link.send(commands.system_time(state.time_s))
        return self.outputs.stream_setpoints

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
                snap = self.cascade.store_snapshot()
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
            self.cascade.save_to(self.store)
        except Exception as exc:  # a full disk must not stop the flight
            self.counters["store_errors"] += 1
            log.error("saving the library failed: %s", exc)

    # -- lifecycle --------------------------------------------------------------------

    def _open_store(self) -> None:
        if not self.cfg.store.path:
            return
        self.store = LibraryStore.open(self.cfg.store.path)
        loaded = self.cascade.load_from(self.store)
        log.info("library %s: loaded %s", self.cfg.store.path, loaded)

    def _log_tick(
        self,
        state: VehicleState,
        t_s: float,
        out: PositionOutput,
        ref_now: FloatArray | None = None,
    ) -> None:
        """One flight-log row; ``ref_now`` (9,): the trajectory at ``t_s`` when the tick has
        it already (the first row of its horizon), else it is sampled here."""
        if self.flight_log is None:
            return
        if ref_now is not None:
            ref_pos, ref_vel = ref_now[:3], ref_now[3:6]
        elif self.trajectory is not None:
            row = self._reference_rows(t_s, 0.0, 0)[0]
            ref_pos, ref_vel = row[:3], row[3:6]
        else:
            ref_pos, ref_vel = out.ref_pos_ned_m, np.zeros(3)
        self.flight_log.write(t_s, self.outputs.phase.value, state, ref_pos, ref_vel, out)

    def request_stop(self) -> None:
        self.loops.stopping.set()

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
        self.autopilot.cfg = self.cfg
        self.supervisor.reconfigure(self.cfg)
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
        if self.cfg.log.flight_log_path:
            self.flight_log = FlightLog(self.cfg.log.flight_log_path)
        await self._open_sharing()
        await self.link.open()
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
                tg.create_task(self._supervise(), name="supervisor")
                loops = self.loops
                tg.create_task(
                    loops.periodic("position", self.position_timing, self._position_step),
                    name="position-loop",
                )
                tg.create_task(
                    loops.periodic("attitude", self.attitude_timing, self._attitude_step),
                    name="attitude-loop",
                )
                tg.create_task(self._saver(), name="library-saver")
                if self.sharing is not None and self.sharing.share_library:
                    tg.create_task(self.sharing.run(), name="library-sharing")
                watchdog = self.systemd.watchdog(lambda: self.outputs.stream_setpoints)
                tg.create_task(watchdog, name="systemd")
                tg.create_task(loops.stop_watch(), name="stop")
        except* Stop:
            pass
        finally:
            await self._shutdown()
        return self._exit_code

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

    async def _shutdown(self) -> None:
        self.systemd.notify("STOPPING=1")
        dialect = self.autopilot.dialect
        if dialect is not None and self.outputs.phase in (Phase.OFFBOARD, Phase.OFFBOARD_REQUESTED):
            # leave the vehicle holding, not waiting for our setpoints to time out
            self.autopilot.send_command(dialect.encode(Action.REQUEST_HOLD))
        self.misses.close()
        self._save_library()
        if self.store is not None:
            self.store.close()
        if self.sharing is not None:
            self.sharing.close()
        if self.flight_log is not None:
            self.flight_log.close()
        self._write_stats()
        self.link.close()
        log.info("stopped: %s", dict(self.counters))

    def stats(self) -> dict[str, Any]:
        return {
            "phase": self.outputs.phase.value,
            "phase_events": list(self.supervisor.phase_events),
            **self.autopilot.stats(),  # autopilot, attitude_mode, params
            "takeoffs_sent": self.supervisor.sm.takeoffs_sent,
            "rates_hz": {k: round(v, 1) for k, v in self.autopilot.rates.rates_hz.items()},
            "library": self.cascade.library_stats(),
            "loops": {
                "position": self.position_timing.report().as_dict(),
                "attitude": self.attitude_timing.report().as_dict(),
            },
            "counters": dict(self.counters),
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
