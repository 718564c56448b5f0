"""The clocks that drive the control loops: one interface, two sources of time.

* ``WallClock``: ``time.monotonic`` and ``asyncio.sleep`` — real operation.
* ``VehicleClock``: the vehicle's own timestamps from MAVLink, advanced by the link as
  messages arrive — lockstep simulation, where the SITL only moves on once the controller
  has answered, so waiting for "the next 5 ms" means waiting for the next message.

The loops call ``now_s()`` and ``await wait_until(t)`` and never know which one they have.
"""

from __future__ import annotations

import asyncio
import time
from typing import Protocol


class Clock(Protocol):
    vehicle_time: bool

    def now_s(self) -> float: ...

    async def wait_until(self, t_s: float) -> None: ...


class WallClock:
    vehicle_time = False

    def now_s(self) -> float:
        return time.monotonic()

    async def wait_until(self, t_s: float) -> None:
        delay = t_s - time.monotonic()
        # sleep(0) still yields, so a loop that is late never starves the others
        await asyncio.sleep(max(delay, 0.0))


async def sleep_until(loop: asyncio.AbstractEventLoop, t_s: float) -> None:
    """:meth:`WallClock.wait_until` on ``loop``, the running loop, given: ``asyncio.sleep``
    asks for it (``get_running_loop``), and CPython 3.11 checks the process id on each
    such call, a ``getpid`` system call (2 us at load 10 on the 2-core machine; with
    ``asyncio.timeout``'s, four a tick of each loop)."""
    delay = t_s - time.monotonic()
    if delay <= 0.0:
        await asyncio.sleep(0)  # still yields (and asks nobody for the loop)
        return
    woken = loop.create_future()
    timer = loop.call_at(loop.time() + delay, _wake, woken)
    try:
        await woken
    finally:
        timer.cancel()


def _wake(fut: asyncio.Future[None]) -> None:
    if not fut.done():
        fut.set_result(None)


class VehicleClock:
    """Time is the newest vehicle timestamp seen; waiting means waiting for messages."""

    vehicle_time = True

    def __init__(self) -> None:
        self._now_s = 0.0
        self._advanced = asyncio.Event()

    def now_s(self) -> float:
        return self._now_s

    def advance(self, t_s: float) -> None:
        """Called by the link for every timestamped state message."""
        if t_s > self._now_s:
            self._now_s = t_s
            self._advanced.set()

    async def wait_until(self, t_s: float) -> None:
        while self._now_s < t_s - 1e-9:
            self._advanced.clear()
            await self._advanced.wait()
        # Messages of one simulation tick arrive back to back; let the ones already in the
        # socket buffer be decoded before the tick runs, so it sees the whole tick's state.
        await asyncio.sleep(0)
