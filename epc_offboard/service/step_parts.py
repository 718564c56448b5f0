"""A control step timed part by part in real time, and its slow ones kept (issue 21).

A stall's interval says how much of the loops' thread's CPU went by and which event-loop
step was the longest ("task position-loop Loops.periodic"), not which part of that step:
the state read, the miss pump, the reference, the controller's tick, the log row. Stop 37's
attribution found position steps with 4-10 ms of thread CPU of which the controller's tick
was 0.4-3.2 ms, and bursts of 50-87 ms; this names the part.

Cheap enough for every tick: one ``perf_counter`` read (the vDSO's clock, no system call)
per part and a thread-CPU read at the start and the end, written into lists made once; a
record (a dict of the parts) is built only for a step slower than ``slow_s``.
"""

from __future__ import annotations

import resource
import time
from collections import deque
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

# the slow steps kept, per loop (the latest; the stats' ``slow_steps``)
SLOW_STEPS_KEPT = 128
# a step is slow with more thread CPU than its bound, or more wall time than this many
# bounds (a step preempted by the machine: its run-queue wait is the stall's)
WALL_BOUNDS = 2.5


@dataclass(frozen=True)
class SlowStep:
    """A control step whose wall time or thread CPU was over its loop's bound."""

    loop: str
    t_s: float  # the tick's start (loop clock)
    wall_ms: float  # the step's wall time
    thread_cpu_ms: float  # the loops' thread's CPU time in it
    parts_ms: dict[str, float]  # each part's wall time, in order (0: not run this step)
    slowest_part: str  # the part with the most of it
    # kernel signatures compiled (or loaded from numba's cache) during the step: a
    # compile on the control loop (0 expected after start-up)
    compiles: int = 0
    # the thread's context switches in the step, from the rusage its tick started with
    # (None: not known): voluntary, it blocked (a lock, a system call, a fault's I/O) and
    # its wall time beyond its CPU time was a sleep of ours; none of either kind, the
    # thread never left its CPU and that time was the hypervisor's (steal)
    voluntary_switches: int | None = None
    involuntary_switches: int | None = None
    major_faults: int | None = None  # page faults that read a file (a sleep in the fault)

    def as_dict(self) -> dict[str, Any]:
        return {
            "loop": self.loop, "t_s": round(self.t_s, 3), "wall_ms": round(self.wall_ms, 3),
            "thread_cpu_ms": round(self.thread_cpu_ms, 3),
            "parts_ms": {k: round(v, 3) for k, v in self.parts_ms.items()},
            "slowest_part": self.slowest_part, "compiles": self.compiles,
            "voluntary_switches": self.voluntary_switches,
            "involuntary_switches": self.involuntary_switches,
            "major_faults": self.major_faults,
        }  # fmt: skip


class StepParts:
    """One loop's step, timed part by part: ``start``, then ``part(i)`` at the end of part
    ``i`` (parts skipped in a step stay 0), then ``finish``. A step over ``slow_s`` of
    thread CPU, or ``WALL_BOUNDS`` times that of wall time, is kept in ``slow`` (the latest
    ``kept``) and counted in ``count``. ``compiles``: numba's compiles counted
    (:class:`CompileCounter`): one within a step is kept with it, and makes the step slow;
    None: not asked. ``start``'s ``rusage`` (the thread's, as the step began; the loop
    reads it for each tick anyway): a slow step reads it again and keeps its context
    switches and major faults (one system call, for slow steps only)."""

    def __init__(self, loop: str, parts: Sequence[str], slow_s: float,
                 kept: int = SLOW_STEPS_KEPT,
                 compiles: CompileCounter | None = None) -> None:  # fmt: skip
        self.loop = loop
        self.names = tuple(parts)
        self.slow_s = slow_s
        self.slow: deque[SlowStep] = deque(maxlen=kept)
        self.count = 0  # slow steps seen (kept or pushed out)
        self._compiles = compiles or CompileCounter()  # (never installed: stays 0)
        self._ms = [0.0] * len(self.names)  # made once: written in place every step
        self._t0 = self._last = self._cpu0 = self._start_s = 0.0
        self._compiles0 = 0
        self._rusage0: resource.struct_rusage | None = None

    def start(self, t_s: float, rusage: resource.struct_rusage | None = None) -> None:
        ms = self._ms
        for i in range(len(ms)):
            ms[i] = 0.0
        self._start_s = t_s
        self._rusage0 = rusage
        self._compiles0 = self._compiles.count
        self._cpu0 = time.thread_time()
        self._t0 = self._last = time.perf_counter()

    def part(self, index: int) -> None:
        now = time.perf_counter()
        self._ms[index] += (now - self._last) * 1e3
        self._last = now

    def finish(self) -> SlowStep | None:
        """The step's end: kept (and returned) if it was slow."""
        wall_s = time.perf_counter() - self._t0
        compiles = self._compiles.count - self._compiles0
        if wall_s <= self.slow_s and compiles == 0:
            return None  # (its CPU time is no more than its wall time: not read)
        cpu_s = time.thread_time() - self._cpu0
        if cpu_s <= self.slow_s and wall_s <= WALL_BOUNDS * self.slow_s and compiles == 0:
            return None
        parts = dict(zip(self.names, self._ms, strict=True))
        switches: tuple[int | None, ...] = (None, None, None)
        if (u0 := self._rusage0) is not None:
            u = resource.getrusage(resource.RUSAGE_THREAD)
            switches = (u.ru_nvcsw - u0.ru_nvcsw, u.ru_nivcsw - u0.ru_nivcsw,
                        u.ru_majflt - u0.ru_majflt)  # fmt: skip
        step = SlowStep(self.loop, self._start_s, wall_s * 1e3, cpu_s * 1e3, parts,
                        max(parts, key=parts.__getitem__), compiles, *switches)  # fmt: skip
        self.slow.append(step)
        self.count += 1
        return step


# A hold of numba's compiler lock in which its thread ran at least this much CPU is a
# compile or a load from its cache (those took 4-600 ms here); ``jit.entry_point``'s lookup
# of a signature already compiled also takes the lock, for microseconds of CPU (more of wall
# time when the host preempts the thread in it: CI counted one such hold as a compile).
COMPILE_MIN_MS = 0.5


class CompileCounter:
    """How many times numba compiled a function or loaded one from its cache in this
    process since ``install`` (any dispatcher: ours, and numba's own, such as the typed
    list's methods, which are compiled on their first use and never cached): the outermost
    holds of numba's compiler lock in which the holding thread ran at least
    ``COMPILE_MIN_MS`` of CPU (a compile or a cache load is CPU: 6 ms for the smallest
    kernel; a hold of microseconds preempted on a busy host is long in wall time only and
    not a compile). A call of a signature already compiled never takes the lock. Reading
    ``count`` is a plain attribute; ``longest_ms`` is the wall time the holder lost."""

    def __init__(self) -> None:
        self.count = 0
        self.longest_ms = 0.0  # the longest compile or load seen
        self._depth = 0
        self._t0 = 0.0
        self._cpu0_s = 0.0
        self._listener: Any = None

    def install(self) -> bool:
        """Listen from now; False where numba is missing (nothing to count)."""
        try:
            from numba.core import event
        except ImportError:
            return False
        counter = self

        class _Listener(event.Listener):
            def on_start(self, ev: Any) -> None:
                if counter._depth == 0:
                    counter._t0 = time.perf_counter()
                    counter._cpu0_s = time.thread_time()
                counter._depth += 1

            def on_end(self, ev: Any) -> None:
                counter._depth = max(0, counter._depth - 1)
                if counter._depth == 0:
                    ms = (time.perf_counter() - counter._t0) * 1e3
                    cpu_ms = (time.thread_time() - counter._cpu0_s) * 1e3
                    if cpu_ms >= COMPILE_MIN_MS:
                        counter.count += 1
                        counter.longest_ms = max(counter.longest_ms, ms)

        self._listener = _Listener()
        event.register("numba:compiler_lock", self._listener)  # type: ignore[no-untyped-call]
        return True

    def uninstall(self) -> None:
        if self._listener is None:
            return
        from numba.core import event

        event.unregister("numba:compiler_lock", self._listener)  # type: ignore[no-untyped-call]
        self._listener = None
