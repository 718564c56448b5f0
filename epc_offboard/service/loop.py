"""The service's tasks on the loop clock: waiting for a time, and the one periodic-loop
skeleton both control loops run (wait, tick, timing record, next tick).

In lockstep the loop clock is the vehicle's (``clock.VehicleClock``): a control tick waits
for the vehicle time it is due at however long a loaded machine takes, since a tick run
early, at a stale vehicle time, would make two identical lockstep runs differ.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import math
import os
import resource
import time
from collections import Counter, deque
from collections.abc import Awaitable, Callable
from dataclasses import dataclass
from typing import NamedTuple, NoReturn

from epc_offboard.common.logsetup import LogGate
from epc_offboard.service.clock import Clock, WallClock, sleep_until
from epc_offboard.service.realtime import SlackCollector, StepMark, StepMonitor
from epc_offboard.service.timing import LoopTiming

log = logging.getLogger("epc_offboard.service")

# Loop times closer than this are the same vehicle time (the vehicle clock's resolution is
# 1 ms; the loops' schedules add up float periods).
_SAME_TIME_S = 1e-9


class Stop(Exception):  # noqa: N818 - control flow, not an error
    """Raised inside the service's TaskGroup to end it cleanly."""


@dataclass(frozen=True)
class Tick:
    """One tick of a periodic loop, on the loop clock (s)."""

    start_s: float  # when it runs
    scheduled_s: float  # when it was due
    period_s: float
    # the loops' thread's resource usage as the tick started (``Loops.periodic`` reads it
    # for every tick anyway): a slow step counts its context switches from it
    # (``step_parts.StepParts``); None: not read
    rusage: resource.struct_rusage | None = None


@dataclass(frozen=True)
class Stall:
    """A controlled tick that came more than ``STALL_S`` after the previous one (real time),
    and what the loops' thread did meanwhile: a stall spent in the thread's own CPU is work
    on the event loop (a callback, a collection), one spent off it is waiting (the
    interpreter lock, a timer woken late, the CPU taken)."""

    loop: str
    t_s: float  # when the late tick ran (loop clock)
    interval_ms: float  # since the previous tick's start
    thread_cpu_ms: float  # the loops' thread's CPU time in the interval
    # ... its share in the kernel (the rusage's system time, sampled at the scheduler's tick):
    # a stall of CPU with no event-loop step over 1 ms in it ran no Python; this says
    # whether it was system calls and interrupts in the thread's time or user code; the
    # kernel adjusts its user/system split over the thread's whole life (cputime_adjust),
    # so over one short interval this is a hint blurred by the thread's past
    system_cpu_ms: float
    runqueue_ms: float  # ... time it was runnable but waited for a CPU (NaN: not Linux)
    gc_ms: float  # the collections' time in the interval (any thread)
    minor_faults: int
    major_faults: int
    voluntary_switches: int  # the thread blocked (the interpreter lock, a syscall)
    involuntary_switches: int  # ... was preempted
    # the event loop's steps in the interval (``realtime.StepMonitor``; 0 and "" untimed):
    steps: int  # how many ran (callbacks, tasks' steps)
    steps_ms: float  # ... their time, the ticks' own included
    longest_step_ms: float  # the longest of them (over 1 ms; else 0)
    longest_step: str  # ... what it ran: a task, its coroutine and its await; a callback
    # the process's other threads' CPU time in the interval: Python they ran held the
    # interpreter lock the loops' thread may have waited for (0: no interpreter-lock wait)
    other_threads_cpu_ms: float = 0.0
    period_ms: float = 0.0  # the loop's period
    late_ms: float = 0.0  # how late the tick started against its schedule
    compute_ms: float = 0.0  # the tick's own wall time
    # a deadline miss (the tick started more than a period late or computed longer than
    # one, ``timing.LoopTiming``): its interval runs from the previous tick's start to the
    # end of this tick, so that the lateness and the compute are both inside it
    deadline_miss: bool = False

    def as_dict(self) -> dict[str, float | int | str]:
        return {k: round(v, 3) if isinstance(v, float) else v for k, v in vars(self).items()}


STALL_S = 0.012  # issue 21's bound on the position loop's gap (or two periods, if less)
STALLS_KEPT = 256  # the latest stalls (and, apart, deadline misses), in the stats
# Work beside the loops on their thread (``Loops.room``) starts only this long before the
# next tick is due: a slice of it that fits runs between two ticks, not across one.
ROOM_S = 0.002
# ... and a slice started then ends by this (``Loops.room``'s deadline): the ~1 ms issue 21
# allows a step on the loops' thread that is not a tick, and never nearer than
# ``SLICE_MARGIN_S`` to the next tick due
SLICE_S = 0.001
SLICE_MARGIN_S = 0.0005


class _Mark(NamedTuple):
    """What a stall's interval is measured from, taken as a tick starts."""

    start_s: float  # loop clock
    cpu_s: float  # the loops' thread's CPU time
    gc_s: float  # the collections' total pause
    rusage: resource.struct_rusage  # the thread's faults and switches
    runqueue_s: float  # its run-queue wait
    steps: StepMark  # the event loop's steps
    process_cpu_s: float  # the whole process's CPU time (its other threads' = this - cpu_s)


class _RunqueueClock:
    """The calling thread's total wait on a run queue (runnable, no CPU), from the kernel's
    schedstat: a stall spent there is the CPU taken (by an equal or higher real-time
    priority, an interrupt), one spent neither there nor running is the thread asleep (a
    late wake-up, the interpreter lock). NaN where the file is missing."""

    def __init__(self) -> None:
        self._fd: int | None = None
        with contextlib.suppress(OSError):
            self._fd = os.open("/proc/thread-self/schedstat", os.O_RDONLY)

    def close(self) -> None:
        if self._fd is not None:
            os.close(self._fd)
            self._fd = None

    def read_s(self) -> float:
        if self._fd is None:
            return math.nan
        try:
            return int(os.pread(self._fd, 96, 0).split()[1]) * 1e-9
        except (OSError, ValueError, IndexError):
            return math.nan


class Loops:
    """Waits on the loop clock for the service's tasks, ends them once a stop is asked, and
    runs the periodic loops. Counts ``clock_wait_timeouts`` and, per loop, ticks skipped,
    loop errors and (real time) stalls into ``counters``; the latest stalls are ``stalls``.
    ``gc_pause_s``: the garbage collector's total pause so far (``GcMonitor``), for a
    stall's share of it; ``steps``: the event loop's steps timed (installed by the caller),
    for a stall's longest step."""

    def __init__(self, clock: Clock, counters: Counter[str], log_gate: LogGate,
                 gc_pause_s: Callable[[], float] = lambda: 0.0,
                 steps: StepMonitor | None = None,
                 collector: SlackCollector | None = None) -> None:  # fmt: skip
        self.clock = clock
        self.counters = counters
        self._log_gate = log_gate
        self._gc_pause_s = gc_pause_s
        self.steps = steps if steps is not None else StepMonitor()
        # real time: the young collections run after a tick, when the next is far enough
        self.collector = collector
        self.stopping = asyncio.Event()
        self.stalls: deque[Stall] = deque(maxlen=STALLS_KEPT)
        self.misses: deque[Stall] = deque(maxlen=STALLS_KEPT)  # the deadline misses traced
        self._next_due: dict[str, float] = {}  # per loop: when its next tick is due
        self._ticked: asyncio.Future[None] | None = None  # set when a tick has run

    async def room(self, room_s: float = ROOM_S, timeout_s: float = 0.05) -> float | None:
        """Until a tick of the loops has just run and the next one of either loop is at least
        ``room_s`` away: a slice of other work on the loops' thread started now runs between
        two ticks. ``asyncio.sleep(0)`` between slices let the next slice start whenever no
        tick was due at that instant, and slices back to back, 10-25 ms of the library saver
        every 5 s, came between ticks (position-loop gaps of 12-16 ms and late attitude
        ticks beside two CPU hogs). Returns after ``timeout_s`` all the same (loops that do
        not tick: before start-up is over, after a stop).

        Returns the slice's deadline on ``time.monotonic``: ``SLICE_S`` from now, or
        ``SLICE_MARGIN_S`` before the next tick due if sooner; work that can stop in the
        middle stops there (the fleet's candidates). None in lockstep (the vehicle's clock
        stands while the slice runs: a slice is a count there, as every run the same)."""
        loop = asyncio.get_running_loop()
        end = loop.time() + timeout_s
        while (left := end - loop.time()) > 0.0:
            if self._ticked is None or self._ticked.done():
                self._ticked = loop.create_future()
            with contextlib.suppress(TimeoutError):
                async with asyncio.timeout(left):
                    await asyncio.shield(self._ticked)
            due = min(self._next_due.values(), default=math.inf)
            if due - self.clock.now_s() >= room_s:
                return self._slice_deadline(due)
        self.counters["room_timeouts"] += 1
        return self._slice_deadline(min(self._next_due.values(), default=math.inf))

    def _slice_deadline(self, due_s: float) -> float | None:
        if self.clock.vehicle_time:
            return None
        now = self.clock.now_s()
        return min(now + SLICE_S, due_s - SLICE_MARGIN_S)

    async def wait(
        self, t_s: float, *, until_reached: bool = False,
        loop: asyncio.AbstractEventLoop | None = None,
    ) -> None:
        """Wait for loop time t_s; in lockstep never longer than a wall-clock second, unless
        ``until_reached``: the control loops then wait for the vehicle clock however long it
        takes, checking for a stop every second. Raises :class:`Stop` once a stop is asked.
        ``loop``: the running event loop, given by a caller that waits every tick (the
        wall clock's wait then asks nobody for it, see :func:`clock.sleep_until`)."""
        if loop is not None and isinstance(self.clock, WallClock):
            # a wall clock's wait ends by itself: no timeout to arm (the vehicle clock's
            # below waits for messages that may never come)
            await sleep_until(loop, t_s)
            if self.stopping.is_set():
                raise Stop
            return
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
            if not until_reached or self.stopping.is_set():
                break
        if self.stopping.is_set():
            raise Stop

    async def stop_watch(self) -> NoReturn:
        """A task that ends the TaskGroup once a stop is asked."""
        await self.stopping.wait()
        raise Stop

    async def periodic(
        self,
        name: str,
        timing: LoopTiming,
        tick: Callable[[Tick], Awaitable[bool]],
    ) -> NoReturn:
        """Run ``tick`` every ``timing.period_s`` of loop time, forever. ``tick`` returns
        whether it controlled (setpoints stream): only those ticks are timed, and only their
        skips counted (``{name}_ticks_skipped``); before that the loops idle."""
        period = timing.period_s
        t_next = self.clock.now_s()
        before: _Mark | None = None
        loop = asyncio.get_running_loop()  # once: each call is a getpid (CPython 3.11)
        with contextlib.closing(_RunqueueClock()) as runqueue:

            def mark(t_s: float, cpu_s: float, rusage: resource.struct_rusage) -> _Mark:
                """The readers of an interval's end (a tick's start, a missed tick's end)."""
                return _Mark(t_s, cpu_s, self._gc_pause_s(), rusage, runqueue.read_s(),
                             self.steps.mark(), time.process_time())  # fmt: skip

            stall_s = min(STALL_S, 2.0 * period)  # the attitude loop's: a deadline miss
            while True:
                await self.wait(t_next, until_reached=True, loop=loop)
                start = self.clock.now_s()
                # the thread's CPU time and context switches (the rusage's CPU time lags by
                # up to a scheduler tick; the thread clock does not), outside the wall time
                use0 = resource.getrusage(resource.RUSAGE_THREAD)
                cpu0 = time.thread_time()
                # a stall is real time's (in lockstep the vehicle's clock waits for the tick)
                now = None if self.clock.vehicle_time else mark(start, cpu0, use0)
                a_stall = (before, now) if before is not None and now is not None and (
                    start - before[0] > stall_s) else None  # fmt: skip
                what = Tick(start, t_next, period, use0)
                wall0 = time.perf_counter()
                controlled = await tick(what)
                wall = time.perf_counter() - wall0
                if a_stall is not None:  # kept once the tick's own time is known
                    self._stall(name, what, *a_stall, wall)
                if controlled:
                    cpu = time.thread_time() - cpu0
                    # A tick the thread never left took no more wall time than CPU time
                    # (the wall's span lies inside the CPU's): only one that did is asked
                    # how it switched out, a system call a tick saved (~9 us here).
                    use = resource.getrusage(resource.RUSAGE_THREAD) if wall > cpu else use0
                    missed = timing.record(
                        start, wall, scheduled_s=t_next, cpu_s=cpu,
                        blocked=use.ru_nvcsw > use0.ru_nvcsw,
                        preempted=use.ru_nivcsw > use0.ru_nivcsw,
                    )  # fmt: skip
                    if missed and now is not None:  # traced from the previous tick's start
                        end = mark(self.clock.now_s(), time.thread_time(),
                                   resource.getrusage(resource.RUSAGE_THREAD))
                        self._stall(name, what, before or now, end, wall, miss=True)
                before = now if controlled else None
                # In lockstep the next tick is planned from the vehicle time the tick ran
                # at, not the clock now: the tick's answer has released the simulator, and
                # whether its next datagrams were read by now is the scheduler's doing, not
                # the vehicle's.
                t_next = self._next_tick(
                    t_next, period, name if controlled else None,
                    ran_at_s=start if self.clock.vehicle_time else None,
                )  # fmt: skip
                self._next_due[name] = t_next
                if self.collector is not None and controlled and now is not None:
                    due = min(self._next_due.values())
                    self.collector.after_tick(due - self.clock.now_s())
                if self._ticked is not None and not self._ticked.done():
                    self._ticked.set_result(None)  # work waiting for room() may check now

    def _stall(self, name: str, tick: Tick, a: _Mark, b: _Mark, compute_s: float,
               miss: bool = False) -> None:  # fmt: skip
        """Kept: the interval from tick ``a`` to ``b``; a stall counted (``{name}_stalls``),
        a deadline miss (``miss``) kept apart (``misses``)."""
        ua, ub = a.rusage, b.rusage
        if not miss:
            self.counters[f"{name}_stalls"] += 1
        longest_s, longest = self.steps.longest_since(a.steps)
        (self.misses if miss else self.stalls).append(Stall(
            name, tick.start_s, (b.start_s - a.start_s) * 1e3, (b.cpu_s - a.cpu_s) * 1e3,
            (ub.ru_stime - ua.ru_stime) * 1e3, (b.runqueue_s - a.runqueue_s) * 1e3,
            (b.gc_s - a.gc_s) * 1e3,
            ub.ru_minflt - ua.ru_minflt, ub.ru_majflt - ua.ru_majflt,
            ub.ru_nvcsw - ua.ru_nvcsw, ub.ru_nivcsw - ua.ru_nivcsw,
            b.steps.count - a.steps.count, (b.steps.total_s - a.steps.total_s) * 1e3,
            longest_s * 1e3, longest,
            max(0.0, (b.process_cpu_s - a.process_cpu_s) - (b.cpu_s - a.cpu_s)) * 1e3,
            tick.period_s * 1e3, (tick.start_s - tick.scheduled_s) * 1e3, compute_s * 1e3,
            miss,
        ))  # fmt: skip

    def _next_tick(
        self, t_next: float, period: float, counted: str | None, ran_at_s: float | None = None
    ) -> float:
        """The next tick time; when more than a tick behind, skip (never burst), counted
        under ``{counted}_ticks_skipped`` unless None. ``ran_at_s`` (lockstep): the vehicle
        time the tick ran at, which the next tick must come after."""
        t_next += period
        now = self.clock.now_s() if ran_at_s is None else ran_at_s
        if t_next - now > period:
            # the wait timed out: the clock did not move (lockstep, before an autopilot that
            # streams nothing until asked sends state): run on from the clock, never ahead
            # of it (ahead, every tick would cost a wait timeout)
            t_next = now + period
        if now - t_next > period:
            skipped = int((now - t_next) / period)
            if counted is not None:
                self.counters[f"{counted}_ticks_skipped"] += skipped
            t_next += skipped * period
        while ran_at_s is not None and t_next - ran_at_s < _SAME_TIME_S:
            # The vehicle sent no state at the previous tick's time (PX4's 123 Hz attitude
            # against a 200 Hz loop): the tick due then ran at this vehicle time, and so
            # does this one. A second tick at the same vehicle time would run after the
            # first one's answer released the simulator, racing its next datagrams.
            t_next += period
        return t_next

    def error(self, loop: str, exc: Exception) -> None:
        """A tick of ``loop`` degraded to hover after ``exc``: counted, logged (rate-limited)."""
        self.counters[f"{loop}_loop_errors"] += 1
        if self._log_gate.open("loop_error", 1.0):
            log.error(
                "%s loop degraded to hover after %s: %s (%d so far)",
                loop, type(exc).__name__, exc, self.counters[f"{loop}_loop_errors"],
            )  # fmt: skip
