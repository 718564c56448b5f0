"""The simulation clock: lockstep with the controller, or paced to the wall clock.

Lockstep protocol (the service implements the other side):

1. advance physics one tick (``lockstep_period_s``), emit the telemetry due at that vehicle time;
2. wait until a SET_ATTITUDE_TARGET arrives whose ``time_boot_ms`` is >= the current vehicle
   time in ms (the controller stamps each setpoint with the newest state it used), or until
   ``lockstep_timeout_s`` of wall time passes: then advance anyway and count a timeout.

Until the first SET_ATTITUDE_TARGET, and again after ``lockstep_max_timeouts`` consecutive
timeouts, the clock runs at real-time pace (times ``speedup``) so that a vehicle with no
controller attached behaves normally; the next setpoint puts it back into waiting mode.
A peer that sends commands along with its setpoint must send the setpoint last: datagrams are
handled in arrival order, and the setpoint is what releases the tick.
"""

from __future__ import annotations

import asyncio
import contextlib
import time
from collections.abc import Callable


class LockstepGate:
    """Tracks the newest setpoint stamp and whether the clock must wait for the controller."""

    def __init__(self, enabled: bool, timeout_s: float, max_timeouts: int) -> None:
        self.enabled = enabled
        self.waiting = False
        self.timeout_s = timeout_s
        self.max_timeouts = max_timeouts
        self.newest_stamp_ms = -1
        self.timeouts = 0
        self._consecutive_timeouts = 0
        self._event = asyncio.Event()

    def on_setpoint(self, time_boot_ms: int) -> None:
        self.newest_stamp_ms = max(self.newest_stamp_ms, time_boot_ms)
        if self.enabled:
            self.waiting = True
        self._event.set()

    async def wait_for(self, now_ms: int) -> None:
        """Return once a setpoint stamped >= ``now_ms`` arrived, or after the timeout."""
        deadline = time.monotonic() + self.timeout_s
        while self.newest_stamp_ms < now_ms:
            remaining = deadline - time.monotonic()
            if remaining <= 0.0:
                self.timeouts += 1
                self._consecutive_timeouts += 1
                if self._consecutive_timeouts >= self.max_timeouts:
                    self.waiting = False
                    self._consecutive_timeouts = 0
                return
            self._event.clear()
            with contextlib.suppress(TimeoutError):
                await asyncio.wait_for(self._event.wait(), remaining)
        self._consecutive_timeouts = 0


class Clock:
    """Runs ``tick`` until ``stop`` is set or ``duration_s`` of vehicle time has passed."""

    def __init__(
        self,
        gate: LockstepGate,
        period_s: float,
        speedup: float,
        now_ms: Callable[[], int],
    ) -> None:
        self.gate = gate
        self.period_s = period_s
        self.speedup = speedup
        self._now_ms = now_ms

    async def run(
        self, tick: Callable[[], None], stop: asyncio.Event, duration_s: float | None
    ) -> int:
        """Returns the number of ticks run."""
        ticks = 0
        anchor_wall = time.monotonic()
        anchor_ticks = 0
        max_ticks = None if duration_s is None else round(duration_s / self.period_s)
        while not stop.is_set() and (max_ticks is None or ticks < max_ticks):
            tick()
            ticks += 1
            if self.gate.waiting:
                await self.gate.wait_for(self._now_ms())
                # A setpoint stamped in the future releases ticks without waiting; still let
                # the loop read datagrams and signals between ticks.
                await asyncio.sleep(0)
                anchor_wall, anchor_ticks = time.monotonic(), ticks
                continue
            target = anchor_wall + (ticks - anchor_ticks) * self.period_s / self.speedup
            delay = target - time.monotonic()
            if delay < -0.5:
                # Far behind (loaded machine, debugger): do not sprint to catch up.
                anchor_wall, anchor_ticks = time.monotonic(), ticks
            await asyncio.sleep(max(0.0, delay))
        return ticks
