"""The flight, step by step: the offboard state machine (``vehicle/offboard.py``) fed what
the autopilot and the state tracker know, its actions sent as commands, its phases logged,
told to systemd and kept for the stats; READY=1 once state flows; and the mission's end.

The whole flight is the state machine's: arm, takeoff, offboard, failsafe, the mission's
end (``Inputs.mission_complete``) and landing (its LANDING phase, LAND resent until the
heartbeat shows it) up to DONE. Only then does the service act: it exits, or with
``mission.linger_after_landing`` stays up for the fleet.
"""

from __future__ import annotations

import asyncio
import logging
import math
import time
from collections import Counter, deque
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from epc_offboard.control.types import VehicleState
from epc_offboard.service.autopilot import Autopilot
from epc_offboard.service.clock import Clock
from epc_offboard.service.config import ServiceConfig
from epc_offboard.service.startup import TIMELINE
from epc_offboard.service.systemd import Systemd
from epc_offboard.vehicle.offboard import Inputs, OffboardStateMachine, Outputs, Phase
from epc_offboard.vehicle.state import StateTracker

log = logging.getLogger("epc_offboard.service")

_MAX_PHASE_EVENTS = 200  # phase transitions kept for the stats
_LOCKSTEP_SILENCE_FACTOR = 10.0  # lockstep: wall-clock silence tolerated, x heartbeat timeout
# waiting for the autopilot (no heartbeat, or no fresh state): a WARNING after this long on
# the wall clock, then after 3x as long again, at most every _WAITING_WARN_MAX_S
WAITING_WARN_FIRST_S = 10.0
_WAITING_WARN_MAX_S = 600.0


@dataclass(frozen=True)
class Step:
    """What one supervisor step decided, with the state it was decided on."""

    outputs: Outputs
    state: VehicleState | None
    phase_changed: bool


class Supervisor:
    """``cfg`` may be replaced (:meth:`reconfigure`, SIGHUP); ``stopping`` is set when the
    mission's flight is over and the service is to exit; ``write_stats`` writes the stats
    file (a lingering service writes the flight's figures at once)."""

    def __init__(
        self,
        cfg: ServiceConfig,
        clock: Clock,
        tracker: StateTracker,
        autopilot: Autopilot,
        systemd: Systemd,
        counters: Counter[str],
        stopping: asyncio.Event,
        write_stats: Callable[[], None],
        controller_ready: Callable[[], bool] = lambda: True,
    ) -> None:
        self.cfg = cfg
        self.clock = clock
        self.tracker = tracker
        self.autopilot = autopilot
        self.systemd = systemd
        self.counters = counters
        self._stopping = stopping
        self._write_stats = write_stats
        self._controller_ready = controller_ready  # the first hand-over waits for it
        self.sm = OffboardStateMachine(cfg.offboard, land_at_end=cfg.mission.land_at_end)
        self.outputs = Outputs(Phase.WAIT_HEARTBEAT, False, (), "starting")
        # phase transitions on the loop clock, the newest _MAX_PHASE_EVENTS (a flapping link
        # cannot grow it)
        self.phase_events: deque[dict[str, Any]] = deque(maxlen=_MAX_PHASE_EVENTS)
        # A silent link (nothing at all received) counts as a lost heartbeat. In lockstep the
        # heartbeat's age is judged in vehicle time by the state machine; wall-clock silence
        # only tells a simulator that has gone, and a loaded machine must not look like one
        # (it failed a lockstep figure-8 safe beside a CPU hog: runs must not depend on load).
        wall_factor = _LOCKSTEP_SILENCE_FACTOR if clock.vehicle_time else 1.0
        self._silence_s = cfg.offboard.heartbeat_timeout_s * wall_factor
        self._ready_sent = False
        self._waiting_since_s = time.monotonic()  # in WAIT_HEARTBEAT / WAIT_STATE since
        self._waiting_warn_first_s = WAITING_WARN_FIRST_S * wall_factor
        self._waiting_warn_s = self._waiting_warn_first_s
        self._lingering = False  # landed, still up for the fleet (mission.linger_after_landing)

    def link_opened(self) -> None:
        """The link is open: the wait for the autopilot is counted from now. Counted from
        the service's construction, a first start's compile (154 s at load 8) was said at
        the link's opening as "no HEARTBEAT ... for 154 s: nothing received" and stood in
        the first sim's warnings."""
        self._waiting_since_s = time.monotonic()

    def reconfigure(self, cfg: ServiceConfig) -> None:
        """New offboard and mission settings (SIGHUP)."""
        self.cfg = cfg
        self.sm.config = cfg.offboard
        self.sm.land_at_end = cfg.mission.land_at_end

    def step(self, now: float, *, mission_complete: bool) -> Step:
        """One step at loop time ``now``; ``mission_complete``: the trajectory has run its
        duration."""
        autopilot = self.autopilot
        silent = time.monotonic() - autopilot.last_rx_wall_s > self._silence_s
        hb = None if silent or autopilot.dialect is None else self.tracker.heartbeat
        if autopilot.dialect is not None:
            self.sm.dialect = autopilot.dialect  # how the heartbeat's modes read
        lockstep = self.clock.vehicle_time
        age = self.tracker.age_s(now, vehicle_clock=lockstep)
        state = self.tracker.snapshot(self.tracker.vehicle_time_at(now, vehicle_clock=lockstep))
        fix = autopilot.fresh_global()
        if not self._ready_sent and age <= self.cfg.offboard.max_state_age_s:
            # before the step: the step that first sees fresh state may also leave for
            # preflight (a heartbeat already in), and "ready" comes before any phase it starts
            self._ready_sent = True
            self.systemd.notify("READY=1")
            TIMELINE.mark("ready")
            log.info("link up and state flowing: ready")
        vel = None if state is None else state.vel_ned_m_s.tolist()
        out = self.sm.step(
            Inputs(
                now,
                hb,
                age,
                pos_down_m=None if state is None else float(state.pos_ned_m[2]),
                relative_alt_m=None if fix is None else fix.relative_alt_m,
                amsl_m=None if fix is None else fix.amsl_m,
                landed_state=autopilot.landed_state,
                mission_complete=mission_complete,
                vel_down_m_s=None if vel is None else float(vel[2]),
                speed_horizontal_m_s=None if vel is None else math.hypot(vel[0], vel[1]),
                controller_ready=self._controller_ready(),
            )
        )
        if self.sm.unsettled_entries > self.counters["unsettled_entries"]:
            self.counters["unsettled_entries"] = self.sm.unsettled_entries
            log.warning("handing over before the vehicle settled: %s", out.reason)
        if self.sm.unready_entries > self.counters["unready_entries"]:
            self.counters["unready_entries"] = self.sm.unready_entries
            log.warning("handing over before the controller was ready: %s", out.reason)
        for action in out.actions:
            autopilot.do_action(action, out.takeoff, state)
        changed = out.phase != self.outputs.phase
        if changed:
            self._phase_changed(now, out)
        self.outputs = out
        self._warn_waiting(out.phase)
        autopilot.manage(now, link_up=hb is not None)
        if out.phase == Phase.DONE and self.cfg.mission.duration_s > 0:
            self._mission_over()
        return Step(out, state, changed)

    def _warn_waiting(self, phase: Phase) -> None:
        """Still waiting for the autopilot's heartbeat or for fresh state: a WARNING after
        WAITING_WARN_FIRST_S, then 3x as long again, saying what the link receives (nothing
        at all: nothing answers on link.url; other system ids: link.target_system)."""
        wall_s = time.monotonic()
        if phase not in (Phase.WAIT_HEARTBEAT, Phase.WAIT_STATE):
            self._waiting_since_s = wall_s
            self._waiting_warn_s = self._waiting_warn_first_s
            return
        waited_s = wall_s - self._waiting_since_s
        if waited_s < self._waiting_warn_s:
            return
        self._waiting_warn_s = min(3.0 * self._waiting_warn_s, _WAITING_WARN_MAX_S)
        link = self.cfg.link
        counters = self.autopilot.link.counters
        if phase == Phase.WAIT_STATE:
            heard = "heartbeats arrive, but no fresh attitude and position state (the " \
                "autopilot's estimator, or its streams: stats.json rates_hz)"
        elif self.autopilot.last_rx_wall_s > -math.inf:
            heard = f"messages from system {link.target_system} arrive, but no HEARTBEAT"
        elif counters["wrong_system"]:
            heard = (f"{counters['wrong_system']} frames from other system ids, none from "
                     f"system {link.target_system}: is link.target_system right?")
        elif counters["datagrams"] or counters["received"]:
            heard = "data arrives, but no MAVLink 2 frame of the autopilot (stats.json link)"
        else:
            heard = "nothing received: is the autopilot sending to this address and port?"
        log.warning("no %s from the autopilot on %s for %.0f s: %s",
                    "fresh state" if phase == Phase.WAIT_STATE else "HEARTBEAT",
                    link.url, waited_s, heard)  # fmt: skip

    def _phase_changed(self, now: float, out: Outputs) -> None:
        """Log, tell systemd, count failsafes and keep the transition for the stats (the sim
        report marks them where they happened)."""
        log.info("phase %s -> %s (%s)", self.outputs.phase.value, out.phase.value, out.reason)
        self.systemd.notify(f"STATUS={out.phase.value}: {out.reason}")
        if out.phase == Phase.FAILSAFE:
            self.counters["failsafes"] += 1
        first = TIMELINE.since_start_s(out.phase.value) is None
        TIMELINE.mark(out.phase.value)
        if first and out.phase == Phase.OFFBOARD:
            log.info("offboard %.1f s after the process started (link open at %.1f s; "
                     "stats.json startup has each step)", TIMELINE.since_start_s("offboard"),
                     TIMELINE.since_start_s("link_open") or 0.0)  # fmt: skip
        self.phase_events.append(
            {"t_s": round(now, 4), "phase": out.phase.value, "reason": out.reason}
        )

    def _mission_over(self) -> None:
        """The mission's flight is over (landed, or handed over holding): exit, or linger."""
        if not self.cfg.mission.linger_after_landing:
            self._stopping.set()
        elif not self._lingering:
            self._lingering = True
            self._write_stats()  # the flight's figures; rewritten at the stop
            log.info("mission complete: staying up for the fleet until stopped")
