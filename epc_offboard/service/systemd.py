"""systemd's notify protocol: READY=1 once state flows, STATUS= on each phase, WATCHDOG=1
only while the control loop ticks (a stalled loop stops the pings and systemd restarts
the service), STOPPING=1. Outside systemd every notify is a no-op."""

from __future__ import annotations

import asyncio
import math
import time
from collections.abc import Callable
from typing import NoReturn


class Systemd:
    def __init__(self, watchdog_period_s: float) -> None:
        from sdnotify import SystemdNotifier

        self.watchdog_period_s = watchdog_period_s
        self._notifier = SystemdNotifier()
        if self._notifier.socket is not None:
            # a notify must never stall the control loop: if the socket's queue is full
            # (nobody reading), the ping is dropped (sdnotify swallows the error), not waited on
            self._notifier.socket.setblocking(False)
        self._control_alive_wall = -math.inf

    def notify(self, state: str) -> None:
        self._notifier.notify(state)

    def control_ticked(self) -> None:
        """The control loop has just ticked: the watchdog may ping."""
        self._control_alive_wall = time.monotonic()

    async def watchdog(self, streaming: Callable[[], bool]) -> NoReturn:
        """A task: WATCHDOG=1 every period while the control loop ticked within two periods,
        or while there is nothing to control yet (``streaming()`` False)."""
        period = self.watchdog_period_s
        while True:
            await asyncio.sleep(period)
            alive = time.monotonic() - self._control_alive_wall < 2 * period
            if alive or not streaming():
                self.notify("WATCHDOG=1")
