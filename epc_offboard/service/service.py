"""The offboard service: `epc-offboard run --config FILE`, the wiring of its parts.

One asyncio TaskGroup with named tasks:

* ``supervisor``     — the flight (``supervisor.py``: the offboard state machine, from arm to
  landing and the mission's end), talking to the autopilot (``autopilot.py``: messages in;
  rates, parameters and commands out);
* ``position-loop``  — 100 Hz: state -> reference horizon (``reference_selector.py``) ->
  ``Cascade.position_tick`` (``control/position.py``: estimator, EPC, attitude map);
* ``attitude-loop``  — 200 Hz: ``cascade.attitude_command`` (the loop policy,
  ``control/cascade.py``) -> SET_ATTITUDE_TARGET (rates + thrust, or quaternion + thrust
  for the autopilot's own attitude loop), or the px4 baseline's position target
  (``setpoints.py``);
  both loops are ``loop.py``'s periodic loop around a tick of this module;
* ``library-saver``  — new controllers and learned models to SQLite, written by the store
  process (``library_keeper.py``);
* ``library-sharing`` — with ``[sharing] enabled`` or a live reference: the fleet's Zenoh
  session runs in a helper process (``fleet/session.py``); this task takes at most
  ``sharing.candidates_per_s`` decoded candidates a second from it into the candidate pools
  (the miss worker screens them; only a candidate optimal for a real tick joins the
  library), hands it new controllers and snapshots to publish, and restarts it if it dies
  (``fleet/sharing.py``);
* ``systemd``        — WATCHDOG=1 only while the control loop ticks (``systemd.py``).

MAVLink arrives through callbacks of the link's DatagramProtocol (no task, no blocking read);
what is sent is encoded by ``vehicle/commands.py``. The numerics live in ``control/``; this
package never does linear algebra. Each position tick is a row of the flight log
(``flightlog.py``), packed here and formatted and written, with the tlog, by the log writer
process (``logwriter.py``). Before the loops start, start-up objects are frozen out of the garbage
collector and the loops' priority is raised if configured (``realtime.py``).

The control loops never die: an exception in a tick is logged (rate-limited), counted, and
the tick degrades to the cascade's safe hover command.
"""

from __future__ import annotations

import argparse
import asyncio
import faulthandler
import json
import logging
import os
import signal
import sys
import time
from collections import Counter
from concurrent.futures import ThreadPoolExecutor
from dataclasses import replace
from pathlib import Path
from typing import Any

from epc_offboard.common import jit, logpipe
from epc_offboard.common.children import KILL_WAIT_S
from epc_offboard.common.cliargs import check_port_free
from epc_offboard.common.configio import ConfigError
from epc_offboard.common.logsetup import LogGate, setup_logging
from epc_offboard.common.procstats import process_report
from epc_offboard.control.cascade import AttitudeMode, Cascade, compiled_signatures, late_tick
from epc_offboard.control.types import PositionOutput, ReferenceHorizon, VehicleState
from epc_offboard.fleet.sharing import FleetSharing, open_or_fly_alone
from epc_offboard.service import realtime
from epc_offboard.service.autopilot import Autopilot
from epc_offboard.service.clock import Clock, VehicleClock, WallClock
from epc_offboard.service.config import ServiceConfig, load_service_config
from epc_offboard.service.flightlog import pack_row
from epc_offboard.service.library_keeper import LibraryKeeper
from epc_offboard.service.logwriter import LogWriter
from epc_offboard.service.loop import Loops, Stop, Tick
from epc_offboard.service.miss_solver import STOP_TIMEOUT_S, MissSolver
from epc_offboard.service.reference_selector import ReferenceSelector
from epc_offboard.service.setpoints import SetpointSender
from epc_offboard.service.startup import TIMELINE
from epc_offboard.service.step_parts import CompileCounter, StepParts
from epc_offboard.service.supervisor import Supervisor
from epc_offboard.service.systemd import Systemd
from epc_offboard.service.timing import LoopTiming
from epc_offboard.store.database import StoreRefusedError, library_refusal, store_path_refused
from epc_offboard.vehicle import commands
from epc_offboard.vehicle.offboard import Action, Outputs, Phase
from epc_offboard.vehicle.state import StateTracker

log = logging.getLogger("epc_offboard.service")
_MISS_WORKER_POLL_S = 0.05  # real time: how often the start polls whether the worker is up
# the parts of the position and attitude steps, timed in each step (``step_parts.py``); a
# step slower than a fifth of its period (or with a compile in it) is kept, with its parts
POSITION_PARTS = ("state", "pump_collect", "pump_offer", "pump_submit", "rate_gate",
                  "reference", "tick", "log_row", "hand_over")
ATTITUDE_PARTS = ("state", "command", "send")
# each part's index, named once from the tuples (a renamed part fails at import, a moved
# one takes its index along; test_step_parts checks every part is marked by name)
_P_STATE, _P_PUMP, _P_RATE_GATE, _P_REFERENCE, _P_TICK, _P_LOG_ROW, _P_HAND_OVER = map(
    POSITION_PARTS.index,
    ("state", "pump_collect", "rate_gate", "reference", "tick", "log_row", "hand_over"),
)  # the pump's phases (collect, offer, submit) follow ``_P_PUMP`` in this order
_A_STATE, _A_COMMAND, _A_SEND = map(ATTITUDE_PARTS.index, ("state", "command", "send"))
SLOW_STEP_PERIODS = 0.2

# After "stopped", the process ends within this or says where it hangs: once, the
# interpreter's teardown after a finished flight waited minutes (a helper's pipe; CPython
# 3.11's ProcessPoolExecutor has known shutdown deadlocks, gh-125451 and gh-94777). The
# flight's files are written by then. Beyond the unit's TimeoutStopSec (5 s), so under
# systemd its SIGKILL comes first; `sim` and a shell get every thread's stack and exit 1.
EXIT_GRACE_S = 10.0
# SIGTERM (or the mission's end) to exit, as README and the unit file's comment say: the
# log pump is waited for only until then (its stderr, journald, may hold it for longer; it
# writes out what is queued after we are gone). Well inside the unit's TimeoutStopSec (5 s).
STOP_S = 2.0
# Every other wait of the stop ends by this after it was asked (before, the miss worker's
# end took up to 3 s, the fleet helper's 3, the library's last save 30, the log writer's 21,
# one after the other: a SIGSTOPped store and writer held a stop 50 s): the library's last
# save first, then the miss worker, the fleet helper and the log writer, each with what is
# left, killed ``children.KILL_WAIT_S`` before the bound and reaped by it (one killed after
# another took the time is waited for only until the bound: before stop 40, each kill and its
# wait, up to 0.2 s, came after the bound). A store killed before its last
# write commits leaves the library as last saved (SQLite's journal); nothing committed is
# lost. Two seconds of the unit's TimeoutStopSec (5 s) are left for the kills and the exit.
STOP_BOUND_S = 3.0


def bounded_exit(grace_s: float) -> None:
    """From now, if the process has not ended within ``grace_s``: every thread's stack to
    stderr (the service's log), then ``_exit(1)`` (faulthandler's own timer thread: it
    fires whatever the interpreter's threads hold)."""
    faulthandler.dump_traceback_later(grace_s, exit=True)



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
            cfg.position, cfg.attitude, cfg.estimator, 1.0 / cfg.loops.position_rate_hz,
            learn_on_miss=False, attitude_period_s=1.0 / cfg.loops.attitude_rate_hz,
            autopilot=cfg.link.autopilot, airframe=cfg.vehicle,
        )  # fmt: skip
        controllers = self.cascade.experience_controllers()
        self.misses = MissSolver(dict(controllers), slice_s=cfg.sharing.candidate_slice_s)
        self.counters: Counter[str] = Counter()
        log_gate = LogGate()  # wire- and loop-driven log lines, rate-limited
        self.gc_monitor = realtime.GcMonitor()
        self.step_monitor = realtime.StepMonitor()  # installed in real time (run)
        self._reloads: set[asyncio.Task[None]] = set()  # SIGHUP's reads under way
        # ... in a thread started at start-up: one started by the first SIGHUP began at
        # normal priority, and the loops' thread waited 46 ms (load 20) for it to run
        self._reload_pool = ThreadPoolExecutor(1, thread_name_prefix="config-reload")
        self.collector = realtime.SlackCollector(self.counters)  # started in real time
        self.loops = Loops(self.clock, self.counters, log_gate,
                           gc_pause_s=lambda: self.gc_monitor.pause_total_s,
                           steps=self.step_monitor, collector=self.collector)  # fmt: skip
        self.logs: LogWriter | None = None
        if cfg.log.flight_log_path or cfg.log.tlog_path:
            self.logs = LogWriter(cfg.log.flight_log_path, cfg.log.tlog_path, cfg.log,
                                  self.counters)  # fmt: skip
        self.autopilot = Autopilot(cfg, self.clock, self.tracker, self.counters, log_gate,
                                   tlog=self.logs.tlog if self.logs else None)  # fmt: skip
        self.autopilot.on_hover_thrust = self.cascade.position.set_hover_thrust
        # the position loop's command dead time: decided now, when the dialect is adopted,
        # and while body rates are suspended (_follow_rate_gate)
        self._attitude_path = self.autopilot.attitude_path
        self._rates_suspended = False
        self.autopilot.on_attitude_path = self._use_attitude_path
        self._use_attitude_path(*self._attitude_path)
        self.link = self.autopilot.link
        self.systemd = Systemd(cfg.loops.watchdog_period_s)
        self.supervisor = Supervisor(
            cfg, self.clock, self.tracker, self.autopilot, self.systemd, self.counters,
            self.loops.stopping, self._write_stats, lambda: self._controller_ready,
        )  # fmt: skip
        self.references = ReferenceSelector(
            cfg.position, cfg.trajectory, cfg.trajectory_altitude_m, cfg.reference.timeout_s,
            self.counters,
        )  # fmt: skip
        self.setpoints = SetpointSender(
            self.cascade, self.autopilot, cfg.vehicle.max_rate_frd_rad_s, self.counters,
            self.loops.error,
        )  # fmt: skip
        self.position_timing = LoopTiming(1.0 / cfg.loops.position_rate_hz)
        self.attitude_timing = LoopTiming(1.0 / cfg.loops.attitude_rate_hz)
        # numba's compiles and cache loads, counted from the loops' start (none expected)
        self.compiles = CompileCounter()
        self.position_parts = StepParts(
            "position", POSITION_PARTS, SLOW_STEP_PERIODS / cfg.loops.position_rate_hz,
            compiles=self.compiles)  # fmt: skip
        self.attitude_parts = StepParts(
            "attitude", ATTITUDE_PARTS, SLOW_STEP_PERIODS / cfg.loops.attitude_rate_hz,
            compiles=self.compiles)  # fmt: skip
        # the marks the miss pump and the setpoint sender call, bound once (not every tick)
        self._pump_marks = self._pump_mark
        self._attitude_marks = self._attitude_computed
        # the `run` command's: the process ends within this after "stopped" (bounded_exit)
        self.exit_grace_s: float | None = None
        self._stop_asked_s: float | None = None  # when a stop was asked (monotonic)
        self._position_out: PositionOutput | None = None
        self._processes_at_exit: dict[str, Any] | None = None
        self._signatures_warm = 0  # compiled kernel signatures once warmed (0: numpy twins)
        # the miss worker up (or failed to start): the flight's first hand-over waits for it
        self._controller_ready = False
        self.sharing: FleetSharing | None = None
        live = cfg.reference.source == "zenoh"
        if cfg.sharing.enabled or live:
            self.sharing = FleetSharing(
                cfg.sharing, controllers if cfg.sharing.enabled else [],
                share_library=cfg.sharing.enabled, reference=live, log_cfg=cfg.log,
                candidates=cfg.candidates, room=self.loops.room,
            )  # fmt: skip
        self.library = LibraryKeeper(
            cfg.store, self.cascade, self.counters,
            published=lambda: self.sharing is not None and self.sharing.share_library,
            log_cfg=cfg.log,
            fleet_steps=lambda: (self.sharing.fleet_state_steps() if self.sharing is not None
                                 else iter([{}])),
            room=self.loops.room,
        )  # fmt: skip

    @property
    def outputs(self) -> Outputs:
        """The state machine's newest step."""
        return self.supervisor.outputs

    # -- the three loops ---------------------------------------------------------------

    async def _supervise(self) -> None:
        """The flight, and what it starts on the reference side: the rejoin when setpoints
        start streaming or offboard is (re)entered, the trajectory once in offboard."""
        period = 1.0 / self.cfg.loops.supervisor_rate_hz
        refs = self.references
        while True:
            now = self.clock.now_s()
            done = refs.mission_complete(now, self.cfg.mission.duration_s)
            step = self.supervisor.step(now, mission_complete=done)
            out, state = step.outputs, step.state
            entered = step.phase_changed and out.phase in (Phase.STREAMING, Phase.OFFBOARD)
            if entered and state is not None:
                refs.start_rejoin(state, now)
            if out.phase == Phase.OFFBOARD and refs.trajectory is None and state is not None:
                refs.start_trajectory(state, out.altitude_m, self.clock.now_s())
            # lockstep, once the vehicle clock runs: wait for the vehicle time however long
            # a loaded machine takes; a step run on a wall-clock timeout would read the clock
            # at whatever tick the simulator had reached (an answer may have released it)
            # and shift every later step (a landing 20 ms later under load)
            await self.loops.wait(now + period, until_reached=self.clock.vehicle_time and now > 0.0)

    def _state_at(self, now_s: float) -> VehicleState | None:
        """The state predicted to loop time ``now_s`` (the autopilot's clock mapped to ours
        in real time: the prediction spans how old the samples really are)."""
        tracker, lockstep = self.tracker, self.clock.vehicle_time
        return tracker.snapshot(tracker.vehicle_time_at(now_s, vehicle_clock=lockstep))

    async def _position_step(self, tick: Tick) -> bool:
        parts = self.position_parts
        parts.start(tick.start_s, tick.rusage)
        state = self._state_at(tick.start_s)
        parts.part(_P_STATE)
        # misses solved by the worker join the library here; in lockstep the tick waits
        # for the solve in flight, so it joins at the same tick every run
        self.misses.pump(wait=self.clock.vehicle_time, mark=self._pump_marks)
        if self.outputs.stream_setpoints and state is not None:
            self._position_out = self._position_tick(state, tick.start_s)
            self.misses.hand_over(wait=self.clock.vehicle_time)  # its misses, solved by the next
            self.systemd.control_ticked()
            parts.part(_P_HAND_OVER)
        parts.finish()
        return self.outputs.stream_setpoints  # ticks that control are timed, not idle ones

    def _pump_mark(self, phase: int) -> None:
        """The miss pump's phases (collect, offer, submit) as the position step's parts."""
        self.position_parts.part(_P_PUMP + phase)

    def _attitude_computed(self) -> None:
        self.attitude_parts.part(_A_COMMAND)  # computed and encoded, not yet sent

    def _use_attitude_path(self, autopilot: str, mode: AttitudeMode) -> None:
        self._attitude_path = (autopilot, mode)
        self._rates_suspended = False
        self.cascade.position.use_attitude_path(autopilot, mode)

    def _follow_rate_gate(self, t_s: float) -> None:
        """While the rate model's gate has suspended body rates, the autopilot's attitude
        loop answers the position loop's commands: fly its command dead time (PX4's
        quaternion answer is 0.275 s late; planned as body rates' 0 s, the heavier
        position weights oscillated: circle 60 cm, 40 deg of tilt)."""
        suspended = not self.cascade.attitude.rate_model_trusted(t_s)
        if suspended != self._rates_suspended:
            self._rates_suspended = suspended
            self.counters["position_dead_time_switches"] += 1
            autopilot, mode = self._attitude_path
            self.cascade.position.use_attitude_path(autopilot, "autopilot" if suspended else mode)

    def _position_tick(self, state: VehicleState, t_s: float) -> PositionOutput:
        """One tick of the position loop: the reference horizon, then the cascade's tick
        (with the px4 baseline nothing to compute: the log keeps the reference)."""
        reference: ReferenceHorizon | None = None  # what the flight log shows
        offboard = self.outputs.phase == Phase.OFFBOARD
        parts = self.position_parts
        if self._attitude_path[1] == "epc":
            self._follow_rate_gate(t_s)
        parts.part(_P_RATE_GATE)
        try:
            if self.cascade.flies_reference:  # the autopilot takes the reference now only
                reference = self.references.now(state, t_s)
            else:
                reference = self.references.horizon(state, t_s, self.sharing, offboard=offboard)
            parts.part(_P_REFERENCE)
            out = self.cascade.position_tick(state, reference, learn=offboard)
        except Exception as exc:  # degrade, never die
            self.loops.error("position", exc)
            out = self.cascade.hover(state)
        parts.part(_P_TICK)
        if self.logs is not None and self.cfg.log.flight_log_path:
            self.logs.flight_row(pack_row(t_s, self.outputs.phase.value, state, reference, out))
        parts.part(_P_LOG_ROW)
        return out

    async def _attitude_step(self, tick: Tick) -> bool:
        parts = self.attitude_parts
        parts.start(tick.start_s, tick.rusage)
        state = self._state_at(tick.start_s)
        parts.part(_A_STATE)
        if self.clock.vehicle_time:
            # lockstep: the answer releases the simulator's next tick, so it goes last,
            # after whatever the other tasks woken at this tick send (commands)
            await asyncio.sleep(0)
        # (ArduPilot without GUID_OPTIONS bit 3 would read our thrust as a climb rate)
        streaming = self.outputs.stream_setpoints and not self.autopilot.offboard_refusal()
        if streaming and state is not None and self.cascade.flies_reference:
            self.setpoints.position_target(state, self.references.now(state, tick.start_s))
        elif streaming and state is not None:
            target = self._position_out or self.cascade.hover(state)
            late = late_tick(tick.start_s - tick.scheduled_s, state.attitude_age_s, tick.period_s)
            offboard = self.outputs.phase == Phase.OFFBOARD
            self.setpoints.attitude(state, target, tick.start_s, late=late, acting=offboard,
                                    computed=self._attitude_marks)
        elif self.clock.vehicle_time and state is not None:
            # lockstep: the simulator advances only on an answer for each tick; when no
            # setpoint streams (before takeoff, landing) the answer is a SYSTEM_TIME
            self.link.send(commands.system_time(state.time_s))
        elif self.clock.vehicle_time and self.tracker.vehicle_time_s > 0.0:
            # lockstep with attitude but no position (ArduCopter before its EKF origin, 36 s
            # of vehicle time): the tick is answered all the same, or the simulator would
            # hold (or fall back to real-time pace) until a position it never sends
            self.link.send(commands.system_time(self.clock.now_s()))
        parts.part(_A_SEND)  # (or the command, if no attitude setpoint was sent)
        parts.finish()
        return self.outputs.stream_setpoints

    # -- lifecycle --------------------------------------------------------------------

    def request_stop(self) -> None:
        if self._stop_asked_s is None:
            self._stop_asked_s = time.monotonic()
        self.loops.stopping.set()

    def _reload(self) -> None:
        """SIGHUP: the configuration read and validated in a thread of its own, applied here
        on the loops' thread. Read here it held the loops' thread 14-19 ms (bench --attack,
        the event loop's steps timed: its longest step, a 24-27 ms position-loop gap); in
        the thread it gives the interpreter lock back every switch interval."""
        if self.config_path is None:
            return
        task = asyncio.get_running_loop().create_task(self._reload_from(self.config_path),
                                                      name="config-reload")  # fmt: skip
        self._reloads.add(task)
        task.add_done_callback(self._reloads.discard)

    async def _reload_from(self, config_path: str | Path) -> None:
        try:
            new, merged = await asyncio.get_running_loop().run_in_executor(
                self._reload_pool, _reloaded, self.cfg, config_path)  # fmt: skip
        except ConfigError as exc:
            log.error("SIGHUP: config not reloaded: %s", exc)
            return
        # merged onto the config before any reload that was applied meanwhile: the same
        # config (a reload is all that changes self.cfg, and it replaces what new replaces)
        self.cfg = merged
        self.autopilot.cfg = self.cfg
        self.supervisor.reconfigure(self.cfg)
        self.references.reload(new.trajectory, self.clock.now_s())
        logging.getLogger().setLevel(new.log.level.upper())
        log.info("SIGHUP: trajectory, mission and offboard settings reloaded")

    async def run(self) -> int:
        if self.link.endpoint.mode == "udpin":  # a taken port: said now, not after warm-up
            check_port_free("udp", self.link.endpoint.host, self.link.endpoint.port, "link.url")
        # numba compiles (or loads from its cache) each kernel on first use: 0.2-1 s that,
        # inside the first tick, stalled the loops into a stale-state failsafe. Done here,
        # before the link opens, before READY=1 and before any setpoint streams.
        t0 = time.perf_counter()
        self.misses.start(wait=False)  # the worker's imports overlap the warm-up
        if jit.enabled():
            cold = jit.will_compile()
            if cold:
                log.info("control kernels: %s", jit.COLD_COMPILE_NOTE)
            log.info("control kernels compiled and warmed in %.2f s", self.cascade.warm_up())
            # marked as the background compile marks it, when this cascade is one that
            # compiles every kernel (EPC and LWPR: `run`'s default config's)
            full = self.cfg.position.controller == "epc" and self.cfg.estimator.kind == "lwpr"
            if cold and full and not jit.mark_cache_warm():
                log.warning("cannot mark the kernel cache warm in %s (set NUMBA_CACHE_DIR to a "
                            "writable directory)", jit.cache_dir())  # fmt: skip
        else:  # a cold cache: coldstart.py compiles them in the background for the next start
            log.warning("control kernels: numpy twins (no compiled kernels in the cache: "
                        "compiling them in the background for the next start); warmed in "
                        "%.2f s", self.cascade.warm_up())  # fmt: skip
        self._signatures_warm = compiled_signatures()
        TIMELINE.mark("kernels_warm")
        self.compiles.install()  # from here, a compile is one the loops may meet
        if self.clock.vehicle_time:  # lockstep: every run's first miss meets a worker up
            self._miss_worker_up(t0)
        self.library.open()
        TIMELINE.mark("library_open")
        if self.logs is not None:
            self.logs.start()
        if self.sharing is not None:  # what it held before a restart: only the new is asked
            self.sharing.restore(self.library.fleet_saved)
        self.sharing = await open_or_fly_alone(self.sharing, self.counters)
        # before the link binds: an autopilot streams from boot, and what the socket queues
        # while start-up finishes is read as a burst of old samples. The gc freeze took
        # 1.1-1.9 s on a loaded machine beside a real PX4, and that backlog read as a time
        # jump ("samples on another timeline ... resynchronised") on 7 of 9 starts.
        loops_cfg = self.cfg.loops
        self._reload_pool.submit(int).result()  # its thread up now: raised with the others
        realtime.prepare(loops_cfg.realtime_priority, self.gc_monitor, self.counters,
                         loops_cfg.cpu_affinity)  # fmt: skip
        TIMELINE.mark("gc_frozen")
        if not self.clock.vehicle_time:  # a stall's longest step named (real time only)
            self.step_monitor.install()
            if loops_cfg.collect_in_slack:
                self.collector.start()
        try:
            await self.link.open()
        except OSError as exc:  # a serial device absent, an address not this machine's
            raise OSError(f"link.url {self.cfg.link.url}: cannot open: "
                          f"{exc.strerror or exc}") from exc  # fmt: skip
        TIMELINE.mark("link_open")
        self.supervisor.link_opened()  # the wait for the autopilot starts now, not at build
        loop = asyncio.get_running_loop()
        loop.add_signal_handler(signal.SIGTERM, self.request_stop)
        loop.add_signal_handler(signal.SIGINT, self.request_stop)
        loop.add_signal_handler(signal.SIGHUP, self._reload)
        log.info("epc-offboard running: %s, target system %d", self.cfg.link.url,
                 self.cfg.link.target_system)  # fmt: skip
        frame = self.cascade.position.airframe
        log.info("airframe %s: hover thrust %.3f, tilt limit %g deg", frame.source,
                 frame.hover_thrust_norm, frame.max_tilt_deg)  # fmt: skip
        loops = self.loops
        try:
            async with asyncio.TaskGroup() as tg:
                tg.create_task(self._supervise(), name="supervisor")
                tg.create_task(
                    loops.periodic("position", self.position_timing, self._position_step),
                    name="position-loop",
                )
                tg.create_task(
                    loops.periodic("attitude", self.attitude_timing, self._attitude_step),
                    name="attitude-loop",
                )
                if not self.clock.vehicle_time:  # the worker's start overlaps the flight's
                    tg.create_task(self._miss_worker_polled(t0), name="miss-worker-start")
                tg.create_task(self.library.run(), name="library-saver")
                if self.sharing is not None:
                    tg.create_task(self.sharing.run(), name="library-sharing")
                watchdog = self.systemd.watchdog(lambda: self.outputs.stream_setpoints)
                tg.create_task(watchdog, name="systemd")
                tg.create_task(loops.stop_watch(), name="stop")
        except* Stop:
            pass
        finally:
            self.collector.stop()
            self._shutdown()
        return 0

    def _miss_worker_up(self, t0: float) -> None:  # (sets _controller_ready)
        """Lockstep: wait for the miss worker's start (every run's first miss meets it up)."""
        self.misses.wait_ready()
        self._miss_worker_started(t0)

    async def _miss_worker_polled(self, t0: float) -> None:
        """Real time: the link does not wait for the worker. Its imports (seconds on a loaded
        computer) overlap the arming and the takeoff, during which no miss is solved; its
        misses wait for it (``MissSolver.pump``), and so does the flight's first hand-over
        (``offboard.controller_ready_timeout_s``): at load 16 it came up 7 s after entry and
        every tick until then flew the intermediate controller. Polled on the event loop: no
        thread."""
        try:
            up = self.misses.poll_ready()
            while not up:
                await asyncio.sleep(_MISS_WORKER_POLL_S)
                up = self.misses.poll_ready()
        except Exception as exc:  # the loops fly on: misses stay intermediate
            self.counters["miss_worker_start_failed"] += 1
            log.error("EPC miss worker: %s; misses stay with the intermediate controller", exc)
            self._controller_ready = True  # nothing more to wait for
            return
        self._miss_worker_started(t0)

    def _miss_worker_started(self, t0: float) -> None:
        self._controller_ready = True  # the first hand-over waited for it
        TIMELINE.mark("miss_worker_up")
        log.info("EPC miss worker up in %.2f s", time.perf_counter() - t0)

    def _shutdown(self) -> None:
        self.systemd.notify("STOPPING=1")
        asked_s = self._stop_asked_s if self._stop_asked_s is not None else time.monotonic()
        pump = logpipe.installed()
        if pump is not None:  # the stop's bound holds whatever stderr does
            pump.close_by(asked_s + STOP_S)

        end_s = asked_s + STOP_BOUND_S  # the one deadline of every helper's stop

        def left_s() -> float:  # a helper still running then is killed, reaped by end_s
            return max(0.0, end_s - KILL_WAIT_S - time.monotonic())

        def reap_s() -> float:  # killed late (the others took the time): reaped by end_s
            return min(KILL_WAIT_S, max(0.0, end_s - time.monotonic()))

        self._processes_at_exit = self._process_stats()  # while the helpers still run
        dialect = self.autopilot.dialect
        if dialect is not None and self.outputs.phase in (Phase.OFFBOARD, Phase.OFFBOARD_REQUESTED):
            # leave the vehicle holding, not waiting for our setpoints to time out
            self.autopilot.send_command(dialect.encode(Action.REQUEST_HOLD))
        self.library.close(left_s(), reap_s())  # the last save first: what the stop keeps
        self.misses.close(min(STOP_TIMEOUT_S, left_s()), reap_s())
        if self.sharing is not None:
            self.sharing.close(left_s(), reap_s())
        self.link.close()
        if self.logs is not None:  # after the link: its last frames are in the tlog
            self.logs.close(left_s(), reap_s())
        helpers_s = time.monotonic() - asked_s
        # after every helper's wait, not in their bound (CPU work on this thread: before them,
        # a slow one left the log writer no time at all)
        self._write_stats()
        self.gc_monitor.uninstall()
        self.step_monitor.uninstall()
        self.compiles.uninstall()
        self._reload_pool.shutdown(wait=False)
        log.info("stopped, its helpers %.3f s after it was asked: %s", helpers_s,
                 dict(self.counters))  # fmt: skip
        if self.exit_grace_s is not None:
            bounded_exit(self.exit_grace_s)

    def stats(self) -> dict[str, Any]:
        return {
            "phase": self.outputs.phase.value,
            "phase_events": list(self.supervisor.phase_events),
            "startup": TIMELINE.report(),  # where the start went, from the process's start
            **self.autopilot.stats(),  # autopilot, attitude_mode, params
            "takeoffs_sent": self.supervisor.sm.takeoffs_sent,
            "rates_hz": {k: round(v, 1) for k, v in self.autopilot.rates.rates_hz.items()},
            "library": self.cascade.library_stats(),
            # the body-rate response: in use, identified, the model's error, its fallbacks
            "attitude_rate_model": self.cascade.attitude.rate_model_stats(),
            "loops": {
                "position": self.position_timing.report().as_dict(),
                "attitude": self.attitude_timing.report().as_dict(),
            },
            "counters": self._counters(),
            # what the control loops run: compiled kernels, or their numpy twins (cold cache)
            "kernels": {
                "mode": "compiled" if jit.enabled() and self._signatures_warm > 0 else "numpy",
                "signatures_after_warm_up": self._signatures_warm,
                "signatures": compiled_signatures(),  # more than after warm-up: a loop compile
            },
            "gc": self.gc_monitor.stats(),
            # real time: ticks later than the loops' bound, and what their thread did meanwhile
            "stalls": [stall.as_dict() for stall in self.loops.stalls],
            # ... and each deadline miss, from the previous tick's start to its own end
            "misses": [miss.as_dict() for miss in self.loops.misses],
            "event_loop_steps": self.step_monitor.stats(),  # ... and the long steps by name
            # the control steps over a fifth of their period, part by part
            "slow_steps": self._slow_steps(),
            "miss_worker": dict(self.misses.counters),
            "link": dict(self.link.counters),
            "state": {**self.tracker.counters, **self.tracker.clock.counters},
            "sharing": self.sharing.stats() if self.sharing is not None else {},
            "processes": self._processes_at_exit or self._process_stats(),
        }

    def _slow_steps(self) -> dict[str, Any]:
        steps = sorted((*self.position_parts.slow, *self.attitude_parts.slow),
                       key=lambda step: step.t_s)  # fmt: skip
        return {
            "position": self.position_parts.count, "attitude": self.attitude_parts.count,
            "bound_ms": {"position": self.position_parts.slow_s * 1e3,
                         "attitude": self.attitude_parts.slow_s * 1e3},
            "compiles_after_warm_up": self.compiles.count,
            "compile_longest_ms": round(self.compiles.longest_ms, 3),
            "steps": [step.as_dict() for step in steps],
        }  # fmt: skip

    def _counters(self) -> dict[str, int]:
        out = dict(self.counters)
        lines = logpipe.installed()  # the log lines' pump (`run`): lines it could not take
        if lines is not None:
            out["log_lines_dropped"] = lines.dropped
        return out

    def _process_stats(self) -> dict[str, Any]:
        """Who holds what, and what it costs (issue 21): CPU, queues, drops, restarts."""
        lines = logpipe.installed()
        return {
            "control": process_report(os.getpid()),
            "miss_worker": self.misses.process_stats(),
            **({"fleet": self.sharing.process_stats()} if self.sharing is not None else {}),
            **({"logs": self.logs.process_stats()} if self.logs is not None else {}),
            **({"store": self.library.process_stats()} if self.cfg.store.path else {}),
            **({"log_lines": logpipe.stats(lines)} if lines is not None else {}),
        }

    def _write_stats(self) -> None:
        if not self.cfg.log.stats_path:
            return
        path = Path(self.cfg.log.stats_path)
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(json.dumps(self.stats(), indent=2))


def run_service_command(args: argparse.Namespace) -> int:
    from epc_offboard.common.bundled import bundled_config
    from epc_offboard.common.errors import UsageError

    given = args.config
    args.config = str(bundled_config(given))  # `--config sitl`: the bundled one
    if not Path(args.config).exists() and "/" not in given and not given.endswith(".toml"):
        import difflib

        from epc_offboard.common.bundled import bundled_names

        names = bundled_names()
        close = difflib.get_close_matches(given, names, n=1)
        raise UsageError(f"{given}: config file not found, nor a bundled config ("
                         f"{', '.join(names)})" + (f": did you mean {close[0]}?" if close else ""))
    try:
        cfg = load_service_config(args.config)
    except ConfigError as exc:
        raise UsageError(str(exc)) from exc
    refused = library_refusal(cfg.store.path) if cfg.store.path else None
    if refused is not None:  # nothing moved: the user's directory or file is theirs
        raise UsageError(store_path_refused(args.config, cfg.store.path, refused))
    TIMELINE.mark("config")
    setup_logging(cfg.log)
    # from here the log lines go through a pump process, never blocking the loops' thread
    # on stderr (common/logpipe.py); what went before (a config error) went straight there
    logpipe.pipe_stderr()
    try:
        service = Service(cfg, args.config)
    except (ConfigError, OSError) as exc:
        raise UsageError(str(exc)) from exc
    TIMELINE.mark("service_built")
    service.exit_grace_s = EXIT_GRACE_S
    try:
        return asyncio.run(service.run())
    except StoreRefusedError as exc:  # the path changed since the check above
        raise UsageError(store_path_refused(args.config, cfg.store.path, str(exc))) from exc
    except OSError as exc:
        print(f"epc-offboard: {exc}", file=sys.stderr)
        return 1


def _reloaded(base: ServiceConfig, config_path: str | Path) -> tuple[ServiceConfig, ServiceConfig]:
    """SIGHUP's work off the loops' thread (the reader's): the file read and validated, and
    ``base`` with its trajectory, mission and offboard settings (what SIGHUP reloads). The
    copy validates the whole config again, the vehicle file read and parsed among it: 5-30
    ms, not for the loops' thread."""
    new = load_service_config(config_path)
    return new, replace(base, trajectory=new.trajectory, mission=new.mission,
                        offboard=new.offboard)  # fmt: skip
