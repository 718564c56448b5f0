"""The simulation clock: lockstep with the controller, or paced to the wall clock.

Lockstep protocol (the service implements the other side):

1. advance physics one tick (``lockstep_period_s``) and send the telemetry due at that vehicle
   time, in one datagram;
2. wait for the controller's answer to the newest state it was sent: a SET_ATTITUDE_TARGET,
   SET_POSITION_TARGET_LOCAL_NED or SYSTEM_TIME whose ``time_boot_ms`` reaches the newest
   state stamp sent (ATTITUDE, ATTITUDE_QUATERNION, LOCAL_POSITION_NED, ODOMETRY, and
   SYSTEM_TIME once the controller asked for it: a tick of its clock between state
   messages, so its loops keep their period as in real time). A tick that sent no new
   state needs no new answer.

Physics never advances without that answer, however slow the controller is, so two runs
with the same seed and commands are identical. Before the first answer the clock holds at
its first tick and announces the vehicle (a heartbeat and the tick's telemetry, every
``ANNOUNCE_PERIOD_S``) until a controller joins. Only a controller that has gone (no answer
for ``lockstep_timeout_s``, ``lockstep_max_timeouts`` times in a row) lets the clock fall back
to real-time pace (times ``speedup``); the next answer puts the clock back into lockstep.
A timeout is counted and reported once an answer follows it: the controller was slow. A
fallback to real-time pace (``LockstepGate.fallbacks``, reported as "lockstep fell back to
real time") is counted as it happens, or, after the controller handed the vehicle back, once
an answer follows it: either way physics ran on the wall clock meanwhile, so the flight is
no longer a function of its config and seed. The bound (``lockstep_timeout_s`` x
``lockstep_max_timeouts``) must outlast the controller's own longest wait in lockstep: the
service's miss worker is waited for up to 30 s (``miss_solver.WAIT_TIMEOUT_S``), and beside
CPU hogs the loops' thread itself may not run for seconds; a 6 s bound fell back in the
middle of loaded flights (stop 41, lock-load).

A controller that *left* is told from a starved one by what the autopilot already sees, as
PX4 would: the vehicle taken out of offboard by a mode request (HOLD / LOITER, LAND; the
intended mode, not a failsafe's) hands the vehicle back (:meth:`LockstepGate.on_offboard`).
From then on the controller's silence is bounded by ``lockstep_timeout_s`` x
``lockstep_left_max_timeouts`` (1: 2 s), so a service that asks for HOLD at its stop and
exits leaves the vehicle holding in real time within seconds, not after 90 s. The wait does
not end at the request itself: a controller that hands back and stays (a landing at the end
of a mission, a failsafe hold) still answers every tick, and a flight that fell back there
would part from its seed at the landing. Back in offboard (a request, or ArduCopter's GUIDED
setpoints), the long bound holds again. The ones no answer follows after a hand-back are a
controller that has left (a service that saves its library and exits at the end of a
flight), not a stall, and are not counted; silence without a hand-back (a SIGKILLed service)
is found by the long bound and counted.

A peer that sends commands along with its answer must send the answer last: datagrams are
handled in arrival order, and the answer is what releases the tick.

Real time (no lockstep, or a controller gone) imitates a PX4 on its own clock: a tick is run
when its vehicle time has come on the wall clock (not a tick early: its state goes out when
it was measured), and between two ticks the vehicle's time now (:meth:`Clock.since_tick_us`)
runs on with the monotonic clock, for TIMESYNC and for stamping what arrives.
"""

from __future__ import annotations

import asyncio
import time
from collections.abc import Callable

ANNOUNCE_PERIOD_S = 0.5


class LockstepGate:
    """Tracks the newest answer stamp and whether the clock must wait for the controller."""

    def __init__(
        self, enabled: bool, timeout_s: float, max_timeouts: int, left_max_timeouts: int = 1
    ) -> None:
        self.enabled = enabled
        self.joined = False  # a controller has answered at least once
        self.waiting = enabled  # lockstep holds from the first tick
        self.timeout_s = timeout_s
        self.max_timeouts = max_timeouts
        # the bound once the controller has handed the vehicle back (``on_offboard``)
        self.left_max_timeouts = left_max_timeouts
        self.handed_back = False  # the vehicle left offboard on a request, and is not back
        self.newest_stamp_ms = -1
        self.timeouts = 0  # timeouts an answer followed: the controller was slow, not gone
        # fallbacks to real-time pace (after a hand-back: the ones an answer followed): the
        # flight ran on the wall clock
        self.fallbacks = 0
        self._fell_back = False
        self._unanswered_timeouts = 0
        self._consecutive_timeouts = 0
        # what a wait awaits: the next answer's (``on_answer`` resolves it), or its timer's
        self._waiter: asyncio.Future[None] | None = None

    def on_answer(self, time_boot_ms: int) -> None:
        self.newest_stamp_ms = max(self.newest_stamp_ms, time_boot_ms)
        self.timeouts += self._unanswered_timeouts
        self._unanswered_timeouts = 0
        if self._fell_back:
            self.fallbacks += 1
            self._fell_back = False
        if self.enabled:
            self.waiting = True
            self.joined = True
        waiter = self._waiter
        if waiter is not None and not waiter.done():
            waiter.set_result(None)

    def on_offboard(self, intended: bool) -> None:
        """The vehicle's intended mode became offboard (``intended``: the controller commands
        it) or left it on a request (the controller handed it back: HOLD, LAND)."""
        self.handed_back = not intended

    async def _answer_or(self, loop: asyncio.AbstractEventLoop, timeout_s: float) -> None:
        """Until the next answer, or ``timeout_s``: one future and one timer. (An
        ``asyncio.wait_for`` on an Event ran a task of its own and two more passes of the
        event loop every tick: 63 against 36 us of CPU a tick, 2 % of a lockstep SITL's.)"""
        waiter = loop.create_future()
        self._waiter = waiter
        timer = loop.call_later(timeout_s, _release, waiter)
        try:
            await waiter
        finally:
            timer.cancel()
            self._waiter = None

    async def wait_for(
        self, stamp_ms: int, announce: Callable[[], None], stop: asyncio.Event
    ) -> None:
        """Return once an answer stamped >= ``stamp_ms`` arrived (or the controller is gone).

        A slow answer is waited for, however long: each ``timeout_s`` without one is counted,
        but physics does not advance. Only ``max_timeouts`` in a row mean the controller has
        gone, and the clock falls back to real-time pace (a single timeout that advanced
        physics made two lockstep runs on a loaded machine differ); ``left_max_timeouts``
        once the controller has handed the vehicle back."""
        loop = asyncio.get_running_loop()
        while not self.joined and not stop.is_set():
            announce()
            await self._answer_or(loop, ANNOUNCE_PERIOD_S)
        deadline = time.monotonic() + self.timeout_s
        while self.newest_stamp_ms < stamp_ms and not stop.is_set():
            remaining = deadline - time.monotonic()
            if remaining <= 0.0:
                self._unanswered_timeouts += 1
                self._consecutive_timeouts += 1
                bound = self.left_max_timeouts if self.handed_back else self.max_timeouts
                if self._consecutive_timeouts >= bound:
                    self.waiting = False
                    if self.handed_back:  # left, unless an answer follows
                        self._fell_back = True
                    else:  # gone while commanding (killed), or starved past the bound
                        self.fallbacks += 1
                    self._consecutive_timeouts = 0
                    return
                deadline = time.monotonic() + self.timeout_s
                continue
            await self._answer_or(loop, remaining)
        self._consecutive_timeouts = 0


def _release(waiter: asyncio.Future[None]) -> None:
    """A wait's timer: the wait ends without an answer (its caller counts the timeout)."""
    if not waiter.done():
        waiter.set_result(None)


class Clock:
    """Runs ``tick`` until ``stop`` is set or ``duration_s`` of vehicle time has passed."""

    def __init__(
        self,
        gate: LockstepGate,
        period_s: float,
        speedup: float,
        answer_due_ms: Callable[[], int],
        announce: Callable[[], None] = lambda: None,
    ) -> None:
        self.gate = gate
        self.period_s = period_s
        self.speedup = speedup
        self._answer_due_ms = answer_due_ms
        self._announce = announce
        self._period_us = round(period_s * 1e6)
        # real time: the wall-clock (monotonic) time the newest tick's vehicle time was due
        self._tick_wall_s: float | None = None

    def since_tick_us(self) -> int:
        """Vehicle time (us) since the newest tick's, by the wall clock: 0 in lockstep (the
        vehicle's time is its tick's), in real time how far the wall clock has run past the
        tick's due time, within the tick (so the vehicle's time never runs back at the next
        tick, nor ahead of a tick not yet run)."""
        if self._tick_wall_s is None or self.gate.waiting:
            return 0
        elapsed_us = int((time.monotonic() - self._tick_wall_s) * self.speedup * 1e6)
        return min(max(elapsed_us, 0), self._period_us - 1)

    async def run(
        self, tick: Callable[[], None], stop: asyncio.Event, duration_s: float | None
    ) -> int:
        """Returns the number of ticks run. In lockstep a tick runs, then waits for its
        answer; in real time a tick waits for its due time on the wall clock, then runs."""
        ticks = 0
        anchor_wall = time.monotonic()
        anchor_ticks = 0
        max_ticks = None if duration_s is None else round(duration_s / self.period_s)
        while not stop.is_set() and (max_ticks is None or ticks < max_ticks):
            if not self.gate.waiting:
                target = anchor_wall + (ticks + 1 - anchor_ticks) * self.period_s / self.speedup
                delay = target - time.monotonic()
                if delay < -0.5:
                    # Far behind (loaded machine, debugger): do not sprint to catch up.
                    anchor_wall, anchor_ticks = time.monotonic(), ticks
                    target = anchor_wall + self.period_s / self.speedup
                    delay = self.period_s / self.speedup
                await asyncio.sleep(max(0.0, delay))
                if stop.is_set():
                    break
                self._tick_wall_s = target
            tick()
            ticks += 1
            if self.gate.waiting:
                self._tick_wall_s = None
                await self.gate.wait_for(self._answer_due_ms(), self._announce, stop)
                # An answer stamped in the future releases ticks without waiting; still let
                # the loop read datagrams and signals between ticks.
                await asyncio.sleep(0)
                anchor_wall, anchor_ticks = time.monotonic(), ticks
        return ticks
