"""Where a start goes: the service's start-up milestones, timed from the process's own start.

"Offboard within N s of a start" is measured here, the same way everywhere: from the moment
the kernel started this process (``/proc/self/stat``'s start time, 10 ms resolution: the
interpreter's own start-up and the imports count) to the supervisor's ``offboard`` phase
(the autopilot's HEARTBEAT showing offboard). Each milestone also carries this process's CPU
seconds so far (``time.process_time``: every thread, no child): a load of 6 stretches the
wall-clock figures several times over, the CPU ones hardly at all, so tests judge those.

The milestones, in order (those a flight does not reach are absent):

* ``entry``: ``epc-offboard run`` reached (the interpreter and the command line are up);
* ``start_up_priority``: the rest of the start-up runs at the loops' SCHED_FIFO priority
  (with ``loops.realtime_priority`` > 0, where permitted);
* ``kernels_chosen``: compiled kernels or their numpy twins (``service/coldstart.py``);
* ``config``: the config file loaded; ``service_built``: the service's parts constructed;
* ``kernels_warm``, ``miss_worker_up``, ``library_open``, ``gc_frozen``, ``link_open``:
  ``Service.run``'s start-up, up to the link;
* ``ready``: the autopilot's state flows (READY=1);
* then each phase of the flight the first time it is entered: ``preflight`` (arming),
  ``streaming`` (airborne, setpoints streaming), ``offboard_requested``, ``offboard``.

One timeline per process (a module global: start-up spans the command line, the cold-start
choice and the service, none of which own the others). Reading ``/proc`` is the only I/O.
"""

from __future__ import annotations

import os
import time
from typing import Any

from epc_offboard.common.procstats import stat_fields

_TICKS_PER_S = os.sysconf("SC_CLK_TCK")


def process_age_s() -> float:
    """Seconds since the kernel started this process (``time.monotonic`` - start when /proc
    is not there: then the age counts from this module's import)."""
    try:
        with open("/proc/self/stat") as fh:
            text = fh.read()
        with open("/proc/uptime") as fh:
            uptime_s = float(fh.read().split()[0])
    except OSError:
        return time.monotonic() - _IMPORTED_MONO_S
    start_ticks = int(stat_fields(text)[19])
    return max(uptime_s - start_ticks / _TICKS_PER_S, 0.0)


_IMPORTED_MONO_S = time.monotonic()


class Timeline:
    """Named milestones: (seconds since the process started, CPU seconds of the process).
    Only the first mark of a name counts (a re-entered phase is not a start-up)."""

    def __init__(self) -> None:
        # the process's age once, then the monotonic clock: /proc/uptime is read at 10 ms
        # resolution and costs a syscall pair, the monotonic clock neither
        self._start_mono_s = time.monotonic() - process_age_s()
        self._marks: dict[str, tuple[float, float]] = {}

    def mark(self, name: str) -> None:
        if name not in self._marks:
            self._marks[name] = (time.monotonic() - self._start_mono_s, time.process_time())

    def since_start_s(self, name: str) -> float | None:
        mark = self._marks.get(name)
        return None if mark is None else mark[0]

    def report(self) -> dict[str, Any]:
        """For stats.json: each milestone's wall and CPU seconds since the process started,
        and the time to offboard (absent when offboard was never reached)."""
        out: dict[str, Any] = {
            "milestones": {
                name: {"t_s": round(t, 3), "cpu_s": round(cpu, 3)}
                for name, (t, cpu) in self._marks.items()
            }
        }
        if "offboard" in self._marks:
            out["offboard_s"] = round(self._marks["offboard"][0], 3)
        return out


TIMELINE = Timeline()
