"""Keeping the control loops' period on a general-purpose OS: garbage collection, scheduling.

* **Garbage collection.** A full (generation 2) collection of Python's cyclic collector walks
  every object the interpreter holds: about 160,000 once numba, OSQP, SciPy and pymavlink are
  loaded, 55-150 ms on this 2-core machine under load, 10-30 attitude periods lost at a
  moment nobody chooses. Once start-up is over, :func:`freeze_startup_objects` moves every
  object alive into the permanent generation (:func:`gc.freeze`), so a collection in flight
  only walks what the flight itself allocated since (tens of microseconds). Every collection
  is timed (:class:`GcMonitor`, through :data:`gc.callbacks`) and reported in the stats.
* **Scheduling.** With ``loops.realtime_priority`` > 0 the thread that runs the loops is
  scheduled ``SCHED_FIFO`` at that priority (:func:`apply_priority`): nothing at normal
  priority on the companion computer (a camera pipeline, a logger, a CPU hog) can then delay
  a tick. Processes started later (the EPC miss worker) are reset to normal scheduling
  (``SCHED_RESET_ON_FORK``): its QP solves must not compete with the loops. The process's
  other threads (the miss worker's executor and queue threads) run ``SCHED_FIFO`` one step
  below the loops: they take the interpreter lock the loops need, and one preempted by a
  normal-priority process while it holds the lock stalls the loops behind it (a priority
  inversion Python's lock cannot resolve; beside two CPU hogs, 15-38 ms position-loop gaps
  and one 0.43 s stall). They block on pipes, so they cost the machine nothing while idle.
  Without the privilege (``CAP_SYS_NICE``; the
  systemd unit's ``CPUSchedulingPolicy=`` grants the same without it) the service says why
  and flies on normal scheduling.
* **CPU affinity.** With ``loops.cpu_affinity`` the loops' thread is pinned to those CPUs
  (:func:`apply_affinity`), as deployments with the kernel's ``isolcpus=`` do: a tick's time
  is the interpreter running on the CPU (its thread's CPU time equals its wall time in real
  time, 0 preemptions under FIFO, see ``timing.py``), and a thread that wakes on whichever
  core is free finds caches another process left. Helpers started later (a restart) inherit
  the pin; the kernel spreads nothing else off those CPUs unless ``isolcpus=`` says so.
* **Cold caches, not interference.** In ``bench --attack`` (FIFO, two hogs) a position
  tick's thread CPU equals its wall time (0 preemptions) and is ~3x its lockstep cost: the
  same ticks run back to back took 117-120 us of thread CPU, paced 10 ms apart (a sleep
  between ticks, as in flight) 333-343 us, with or without two hogs (SCHED_FIFO, load
  22-31). Between two ticks the machine's other work evicts the interpreter's code and
  data from the caches; what shortens the real-time tick is touching less (fewer Python
  calls and objects per tick), not more isolation. ``python -m
  epc_offboard.tools.tick_stages`` times each stage warm and cold (a 64 MB read between
  ticks). The largest growth was not arithmetic but the arguments of compiled calls: numba
  unboxes every array passed in (the estimator's update took ~110: 5 us warm, 48 us cold),
  so a kernel's many arrays are packed into one object (``lwpr_kernels.packed``), and
  chains of small numpy calls are one compiled call (``kernels.disturbance_plan``; LWPR's
  filter step and variation joined it, ``kernels.filtered_plan``). Packing pays for dozens
  of arrays, not for a few: θ's stack (8 arrays) took 30-35 us cold through numba's
  dispatcher and 21-27 us through its entry point, and 41-74 us with four of its arrays
  packed into a typed list (its unboxing calls back into Python; thread CPU, a 64 MB read
  or a 10 ms sleep before each call, load 16-18). A few arrays go through an entry point.
* **Stalls, traced** (``loop.py``'s ``Stall``, the stats' ``stalls``; the collections in the
  loops' thread apart in ``gc``). ``bench --attack --hogs 2`` (quaternion, FIFO, load 13-16):
  no generation-2 collection in flight (186,701 objects frozen), the longest collection
  2.1 ms (generation 1), all in the loops' thread; the position loop's 19 ticks later than
  12 ms (12.0-15.4 ms) came with 0 page faults and 0 preemptions, and the process's other
  threads (the miss worker's pool threads) ran < 1 ms in each: not the interpreter lock.
  11 of them are on the library saver's 5 s pattern: its one ~3.7 ms step and a 1-2 ms
  generation-0/1 collection its allocations start, on the loops' thread. A second run
  (load 3-8.5) had 43 (12.0-22.3 ms), 35 of them waits: the thread blocked (voluntary
  switches, 0 preemptions, no collection) and ran 2-3 ms of a 12-22 ms interval, so it
  slept past its tick. A third run (load 4.5-5.3) with the run-queue wait: 29 of 40 stalls
  were such waits, and in them the thread waited for a CPU for 0 ms (median; at most
  1.8 ms): the CPU was not taken. The 23.0 ms one ran 1.9 ms and slept once, ~21 ms (2
  voluntary switches; a wait for the interpreter lock wakes every 5 ms, the switch
  interval). What it blocked in, found with ``perf record -k CLOCK_MONOTONIC -e
  sched:sched_switch -e sched:sched_wakeup --call-graph=fp`` filtered to the loops'
  thread (kernel stacks of each sleep and of its waker): the interpreter lock's mutex
  (``__lll_lock_wait``, 146 and 383 ms), woken by the miss worker's pool manager and queue
  feeder threads at NORMAL priority: the worker had come up after start-up, and threads
  started by a raised thread begin at normal priority (``SCHED_RESET_ON_FORK``); a CPU hog
  preempted them holding the mutex. Every thread started after :func:`apply_priority` is
  now raised as it starts; and the pool is gone: the loops' thread feeds the miss worker
  through two pipes itself (``miss_solver.py``), so no thread of the control process
  takes its interpreter lock in flight. The other long gaps of that trace: the loops' thread running
  10-25 ms every 5 s (the library saver's slices back to back: ``Loops.room``,
  ``library_keeper.py``), and intervals in which the thread ran (by the scheduler's
  switches) but its CPU clock advanced a fraction of it, with no preemption and no
  run-queue wait: the virtual CPU itself descheduled by the hypervisor (steal time),
  which no setting inside the machine removes.
* **Steal time, measured** (``tools/steal.py``; ``bench --attack`` reports it per window,
  in each position-loop gap over 12 ms, each late attitude tick and each stall). This VM
  (KVM, ``CONFIG_PARAVIRT_TIME_ACCOUNTING``: the kernel counts steal per CPU in
  ``/proc/stat`` and leaves it out of the threads' CPU clocks) stole 3.5-21 ms a second of
  its two CPUs' 2,000 in two runs beside two hogs (load 9-23). The position-loop gaps
  were not it: 172 and 135 gaps over 12 ms, 5 and 10 of them with any steal, 22 and
  37 ms/s of steal in them against 21 and 3.5 over the run; in them the loops' thread
  ran 5 ms (median, of a 12.8 ms gap) and waited for a CPU 0 ms: work on its own thread.
  The late attitude ticks had 6x the run's steal in them (127-132 ms/s), but 11-26 ticks,
  1-6 with any: steal makes some of them, not most. Timing the event loop's steps
  (``asyncio.Handle._run`` wrapped, steps over 1.5 ms) named the work: the fleet-sharing
  task's 50 ms turns (candidates offered, publication, snapshots), 2.3 ms median and up
  to 7 ms on the loops' thread, lay in 100 of the 135 gaps, and the library saver's
  estimator slice (LWPR's three models' npz at once, 4-9 ms every save) in 12 and in 6 of
  the 11 late attitude ticks. A turn now waits for ``Loops.room`` as the saver's slices do,
  and the estimator is serialised a model a slice (``to_bytes_steps``). Alternated with
  main's code under the measurement lock, three pairs (load 6-23, others' work beside):
  gaps over 12 ms in the 20 windows 128, 251 and 284 on main, 73, 23 and 30 after; of
  those left, 46, 9 and 12 had steal in them, at 14-22x the run's rate: what remains is
  mostly the hypervisor's. Not traced: a rare single stretch of work on the loops' thread
  (one a run in two of the three runs after, 31 ms and 106 ms: the thread on its CPU
  31 ms and 75-80 ms of them, no switch at all; main's runs had their largest gaps at
  19-28 ms), the next thing to name with the event loop's steps timed.
* **The event loop's steps, named** (:class:`StepMonitor`, in real time always: a stall's
  ``longest_step``, the stats' ``event_loop_steps``; ``EPC_STEP_SAMPLE_MS`` samples the
  loops' thread's stack in steps longer than that, a diagnosis only). Four ``bench --attack
  --hogs 2`` runs (load 12-24, steal 1.3-12.6 ms/s): no compile in flight (19 signatures
  after the warm-up, 19 at exit), no collection over 5.2 ms. Named, longest first: SIGHUP's
  config read, 14-19 ms of the loops' thread (a 24-27 ms position-loop gap; now read in a
  thread started at start-up: one started by the SIGHUP began at normal priority and the
  loops waited 46 ms for it, load 20); the position loop's own step, 5-24 ms a few times a
  run: the 23.9 ms one was a library hit whose tick computed 23.4 ms with the thread's CPU
  clock running the whole interval (no switch, fault, collection or steal counted), and the
  stack samples in such steps land inside compiled calls that take 50-110 us warm (LWPR's
  update 27 ms, its predict 15.7 ms) or on plain Python lines (a quaternion's rotation, a
  ``sendto``): no piece of code, the virtual CPU running slow (the host's, invisible as
  steal); the library saver's slices, 5-11 ms (the fleet state's texts, 8-10 ms; an LWPR
  model's npz); the fleet turn's candidates, ten offered at once, 2-6 ms (now three a
  slice, each after ``Loops.room``). The late attitude sends of those four runs' windows
  (129) lined up with the steal and the stalls: 67 had steal in them; of the 62 without,
  18 came after a long position-loop step, 15 after a saver's slice, 3 after the reload,
  25 had no stall left to name them (the stats keep the latest 64). A 5 ms period is late
  whenever one step of the thread's runs past the tick it is due (``ROOM_S`` before), which
  a cooperative loop on one thread cannot prevent: the position tick's 0.3-0.5 ms cannot,
  its rare 5-24 ms (above) can.
* **Collections in the loops' slack** (:class:`SlackCollector`, ``loops.collect_in_slack``,
  stop 37). After the start-up freeze the loops' thread still ran 33-37 young collections a
  ``bench --attack`` flight (one every ~5.6 s), 1-4 ms each beside two hogs, wherever an
  allocation crossed the threshold. A census of the young generation at each collection's
  start (a lockstep figure-8, ``gc.callbacks``): 350-480 objects, ~120 tuples held by
  closures' cells, 60-90 asyncio timer handles with their contexts, buffers, coroutines;
  what crossed the threshold was a generator in the rate model's ``excited`` or a state
  sample's admission: the event loop's own machinery and ordinary work, no one site to
  cut. So the collections run where they cost no tick instead (0.1 ms each in lockstep;
  1.1-1.6 ms in real time beside two hogs, in the slack).
* **Every miss attributed** (``loop.py``'s ``misses``; ``bench --attack``'s
  ``attribution``): each gap over 12 ms and each deadline miss gets one verdict from its
  interval's steal on the loops' CPU, run-queue wait, collections, the thread's CPU, the
  process's other threads' CPU and the longest event-loop step (``attack_analysis.attribute``).
* **Work beside the loops on their thread** (the library saver, the fleet's candidates) runs
  in slices of a few ms with the loops' due ticks between them: one stretch of it is a
  late attitude tick and a position-loop gap (``library_keeper.py``).
"""

from __future__ import annotations

import asyncio
import gc
import logging
import os
import sys
import threading
import time
from collections import Counter, deque
from dataclasses import dataclass, field
from typing import Any

from epc_offboard.common.errors import EpcError

log = logging.getLogger(__name__)

GIL_SWITCH_S = 0.0005  # the interpreter's switch interval once the loops are raised
_SLOW_COLLECTION_S = 0.001  # a collection longer than this is counted as slow
_GC_EVENTS_KEPT = 64  # the latest slow collections, with their times, in the stats


@dataclass
class GcMonitor:
    """Counts and times the cyclic collector's collections, per generation; the ones in the
    loops' thread apart (``loop_thread``: its ident, set by :func:`prepare`), since only
    those stall a tick, and the longest (``events``: when, generation, how long, which
    thread) for a stall to be traced to one."""

    collections: list[int] = field(default_factory=lambda: [0, 0, 0])
    slow: int = 0  # collections longer than _SLOW_COLLECTION_S
    max_pause_s: float = 0.0
    pause_total_s: float = 0.0  # all collections' time: a stall's share is a difference
    loop_thread: int | None = None
    loop_thread_collections: list[int] = field(default_factory=lambda: [0, 0, 0])
    loop_thread_max_pause_s: float = 0.0
    events: deque[tuple[float, int, float, bool]] = field(
        default_factory=lambda: deque(maxlen=_GC_EVENTS_KEPT)
    )
    _started: float | None = None

    def install(self) -> None:
        if self._callback not in gc.callbacks:
            gc.callbacks.append(self._callback)

    def uninstall(self) -> None:
        if self._callback in gc.callbacks:
            gc.callbacks.remove(self._callback)

    def _callback(self, phase: str, info: dict[str, Any]) -> None:
        if phase == "start":
            self._started = time.perf_counter()
            return
        if self._started is None:
            return
        pause = time.perf_counter() - self._started
        self._started = None
        generation = min(max(int(info.get("generation", 2)), 0), 2)
        self.collections[generation] += 1
        self.max_pause_s = max(self.max_pause_s, pause)
        self.pause_total_s += pause
        in_loops = threading.get_ident() == self.loop_thread
        if in_loops:
            self.loop_thread_collections[generation] += 1
            self.loop_thread_max_pause_s = max(self.loop_thread_max_pause_s, pause)
        if pause > _SLOW_COLLECTION_S:
            self.slow += 1
            self.events.append((time.monotonic() - pause, generation, pause, in_loops))

    def stats(self) -> dict[str, Any]:
        return {
            "collections": list(self.collections),
            "slow_collections": self.slow,
            "max_pause_ms": round(self.max_pause_s * 1e3, 3),
            "loop_thread_collections": list(self.loop_thread_collections),
            "loop_thread_max_pause_ms": round(self.loop_thread_max_pause_s * 1e3, 3),
            "frozen_objects": gc.get_freeze_count(),
            "slow_events": [
                {"t_s": round(t, 4), "generation": g, "ms": round(p * 1e3, 3), "loop_thread": lt}
                for t, g, p, lt in self.events
            ],
        }


_LONG_STEP_S = 0.001  # an event-loop step longer than this is named (and kept)
_LONG_STEPS_KEPT = 256  # the latest long steps, for a stall to be traced to one
_STEP_NAMES_KEPT = 64  # distinct long steps' names counted in the stats
# a long step's name counts its steps over each of these (the stats' ``over_ms``)
_STEP_BINS_S = (0.002, 0.005, 0.010)


@dataclass(frozen=True)
class StepMark:
    """The event loop's steps so far (:class:`StepMonitor`): their time, their count, the
    long ones'; two marks bound an interval (a stall's)."""

    total_s: float = 0.0
    count: int = 0
    long_seen: int = 0


class StepMonitor:
    """Times every step of the asyncio event loop (a callback, or one step of a task: its
    code from one await to the next) on the loops' thread, so a stretch of work between two
    ticks is named: a step longer than ``_LONG_STEP_S`` is kept with what ran (the task's
    name, its coroutine and the line it awaits at after the step; a callback's qualified
    name). ``install`` wraps ``asyncio.Handle._run``, which runs every step: two clock reads
    and three additions a step (~0.3 us; a few hundred steps a second in flight), a name only
    for a long one. Real time only: in lockstep nothing is timed."""

    def __init__(self) -> None:
        self.total_s = 0.0
        self.count = 0
        self.long_seen = 0  # steps longer than _LONG_STEP_S so far
        self.long: deque[tuple[int, float, float, str]] = deque(maxlen=_LONG_STEPS_KEPT)
        # name -> [count, longest s, total s, steps over each of _STEP_BINS_S]
        self.names: dict[str, list[float]] = {}
        self.longest_s = 0.0
        self.longest = ""
        self._original: Any = None
        self._current_t0 = 0.0
        # a diagnosis, not for flight: EPC_STEP_SAMPLE_MS=N samples the loops' thread's Python
        # stack (a thread waking every ms) in each step running longer than N ms, from
        # install() to uninstall() (real time only, one thread however many monitors exist)
        self.samples: deque[tuple[float, float, str]] = deque(maxlen=_LONG_STEPS_KEPT)
        self._sampling: threading.Thread | None = None

    def _start_sampler(self) -> None:
        sample_ms = float(os.environ.get("EPC_STEP_SAMPLE_MS", "0"))
        if sample_ms <= 0 or (self._sampling is not None and self._sampling.is_alive()):
            return
        self._sampling = threading.Thread(target=self._sampler, args=(sample_ms * 1e-3,),
                                          name="step-sampler", daemon=True)  # fmt: skip
        self._sampling.start()

    def _sampler(self, after_s: float) -> None:
        """Every ms while installed: the loops' thread's stack, in a step longer than
        ``after_s`` (the latest sample of each step kept)."""
        import traceback

        main = threading.main_thread().ident
        while self._original is not None:
            time.sleep(0.001)
            t0 = self._current_t0
            if not t0 or self._original is None or time.perf_counter() - t0 <= after_s:
                continue
            frame = sys._current_frames().get(main or 0)
            if frame is None or self._current_t0 != t0:
                continue
            text = " < ".join(f"{os.path.basename(f.filename)}:{f.lineno} {f.name}"
                              for f in reversed(traceback.extract_stack(frame)[-14:]))  # fmt: skip
            if self.samples and self.samples[-1][0] == t0:
                self.samples.pop()
            self.samples.append((t0, time.perf_counter() - t0, text))

    def install(self) -> None:
        """Time every step from now on (process-wide: the service's one event loop)."""
        if self._original is not None:
            return
        handle = asyncio.events.Handle
        original = self._original = handle._run
        clock = time.perf_counter

        def timed_run(h: asyncio.Handle) -> None:
            t0 = self._current_t0 = clock()
            original(h)
            dt = clock() - t0
            self._current_t0 = 0.0
            self.total_s += dt
            self.count += 1
            if dt > _LONG_STEP_S:
                self._long(h, t0, dt)

        handle._run = timed_run  # type: ignore[method-assign,assignment]
        self._start_sampler()

    def uninstall(self) -> None:
        if self._original is not None:
            asyncio.events.Handle._run = self._original  # type: ignore[method-assign]
            self._original = None

    def mark(self) -> StepMark:
        return StepMark(self.total_s, self.count, self.long_seen)

    def longest_since(self, mark: StepMark) -> tuple[float, str]:
        """(s, name) of the longest step that ended since ``mark`` ((0, "") if none was long,
        or the ones since were dropped from the kept)."""
        best = (0.0, "")
        for seq, _, dt, name in reversed(self.long):
            if seq < mark.long_seen:
                break
            if dt > best[0]:
                best = (dt, name)
        return best

    def _long(self, h: asyncio.Handle, t0: float, dt: float) -> None:
        name = step_name(h)
        self.long.append((self.long_seen, t0, dt, name))
        self.long_seen += 1
        seen = self.names.get(name)
        if seen is None and len(self.names) < _STEP_NAMES_KEPT:
            seen = self.names[name] = [0, 0.0, 0.0] + [0] * len(_STEP_BINS_S)
        if seen is not None:
            seen[0] += 1
            seen[1] = max(seen[1], dt)
            seen[2] += dt
            for i, bound in enumerate(_STEP_BINS_S):  # the histogram's bins over 1 ms
                if dt > bound:
                    seen[3 + i] += 1
        if dt > self.longest_s:
            self.longest_s, self.longest = dt, name

    def stats(self) -> dict[str, Any]:
        top = sorted(self.names.items(), key=lambda kv: -kv[1][1])
        return {
            "steps": self.count,
            "steps_ms": round(self.total_s * 1e3, 1),
            "long_steps": self.long_seen,
            "longest_ms": round(self.longest_s * 1e3, 3),
            "longest": self.longest,
            "samples": [{"t0": round(a, 4), "ms": round(b * 1e3, 2), "stack": c}
                        for a, b, c in tuple(self.samples)],
            "long_by_name": [{"name": k, "count": int(v[0]), "longest_ms": round(v[1] * 1e3, 3),
                              "total_ms": round(v[2] * 1e3, 3),
                              "over_ms": {f"{b * 1e3:g}": int(n)
                                          for b, n in zip(_STEP_BINS_S, v[3:], strict=True)}}
                             for k, v in top],
        }  # fmt: skip


def step_name(h: asyncio.Handle) -> str:
    """What an event-loop step ran: a task's name, its coroutine and where it awaits now (the
    step just ended: the line after the work), or a callback's qualified name."""
    callback = getattr(h, "_callback", None)
    owner = getattr(callback, "__self__", None)
    if isinstance(owner, asyncio.Task):
        coro = owner.get_coro()
        return f"task {owner.get_name()} {getattr(coro, '__qualname__', '?')} at {_awaits_at(coro)}"
    name = getattr(callback, "__qualname__", None)
    if name is None:  # a functools.partial, a callable object
        inner = getattr(callback, "func", callback)
        name = getattr(inner, "__qualname__", type(inner).__name__)
    return f"callback {name}"


_ASYNCIO_DIR = os.path.dirname(asyncio.__file__)


def _awaits_at(coro: Any) -> str:
    """file:line function of the innermost coroutine ``coro`` awaits in, asyncio's own left
    out ("done" if none), then, if another, `` < `` the task's own coroutine's line: a task
    awaiting one helper (``Loops.room``) from several places names each step apart."""
    where = outer = "done"
    for _ in range(32):  # a chain of awaits, innermost last
        frame = getattr(coro, "cr_frame", None) or getattr(coro, "gi_frame", None)
        if frame is None:
            break
        code = frame.f_code
        if not code.co_filename.startswith(_ASYNCIO_DIR):
            where = f"{os.path.basename(code.co_filename)}:{frame.f_lineno} {code.co_name}"
            if outer == "done":
                outer = where
        coro = getattr(coro, "cr_await", None) or getattr(coro, "gi_yieldfrom", None)
    return where if outer == where else f"{where} < {outer}"


# Room a collection needs before the next tick of the loops: a young one took 1-4 ms of
# the loops' thread in real time beside two CPU hogs (stop 36/37 benches), an older one
# (generation 1, all the young generation's survivors since) up to 5.4 ms.
SLACK_YOUNG_S = 0.002
SLACK_OLDER_S = 0.004
# A collection due this many thresholds over runs whatever the room: a flight whose ticks
# leave no room still collects (memory bounded), as late as the interpreter would.
_FORCE_FACTOR = 10


class SlackCollector:
    """Real time: the cyclic collector's collections in the loops' slack, not wherever an
    allocation crosses the young generation's threshold. Once :meth:`start`-ed the automatic
    collections are off (:func:`gc.disable`); after each tick of the loops
    (:meth:`after_tick`) the collection the interpreter would have run by now (the same
    thresholds, the oldest generation due; the long-lived share rule of generation 2
    aside) runs when the next tick of either loop is at least ``SLACK_YOUNG_S`` away
    (``SLACK_OLDER_S`` for an older generation). The practice of real-time and
    game loops in garbage-collected languages: automatic collection off around the
    time-critical work, ``gc.collect`` at a moment the program chooses (Martelli, *Python in a
    Nutshell*, module ``gc``: "when you can't afford the delay of a cyclic garbage
    collection run at some crucial time ... suspend automatic garbage collection by calling
    ``gc.disable()`` ... To control when the time needed for collection is spent, you can
    call ``gc.collect()``"). The young collections on the loops' thread (33-36 a
    bench flight, 1-4 ms each beside two hogs) otherwise start inside a tick or just before
    one: a due attitude tick waits for them. Counted: ``gc_collections_in_slack``,
    ``gc_collections_forced`` (no room for ``_FORCE_FACTOR`` thresholds)."""

    def __init__(self, counters: Counter[str]) -> None:
        self.counters = counters
        self.active = False

    def start(self) -> None:
        gc.disable()
        self.active = True

    def stop(self) -> None:
        """The automatic collections back (the service ending: its shutdown allocates)."""
        if self.active:
            self.active = False
            gc.enable()

    @staticmethod
    def due() -> tuple[int, bool]:
        """(the generation to collect, -1 if none; whether it is overdue by ``_FORCE_FACTOR``)."""
        c0, c1, c2 = gc.get_count()
        t0, t1, t2 = gc.get_threshold()
        if t0 <= 0 or c0 <= t0:
            return -1, False
        generation = 2 if c2 > t2 else 1 if c1 > t1 else 0
        return generation, c0 > _FORCE_FACTOR * t0

    def after_tick(self, room_s: float) -> None:
        """A tick of the loops has just run and the next of either is ``room_s`` away."""
        if not self.active:
            return
        generation, overdue = self.due()
        if generation < 0:
            return
        if room_s >= (SLACK_YOUNG_S if generation == 0 else SLACK_OLDER_S):
            self.counters["gc_collections_in_slack"] += 1
        elif overdue:
            self.counters["gc_collections_forced"] += 1
        else:
            return
        gc.collect(generation)


def freeze_startup_objects() -> int:
    """Collect once, then move every object alive into the permanent generation, which no
    later collection walks. Call once start-up is over (kernels compiled, library loaded)
    and before the loops run. Returns the number of objects frozen."""
    gc.collect()
    gc.freeze()
    return gc.get_freeze_count()


class PriorityError(EpcError, OSError):
    """The scheduling policy could not be set (no privilege, or not Linux)."""


def apply_priority(priority: int, counters: Counter[str] | None = None) -> str:
    """Schedule the calling thread ``SCHED_FIFO`` at ``priority`` (1..99), the process's
    other threads, and those it starts later, one below; 0 leaves the scheduling as it is.
    ``counters``: the threads raised as they start (``threads_raised_at_start``). Returns
    what was done, for the log; raises :class:`PriorityError` naming why it could not."""
    if priority == 0:
        return "normal scheduling (loops.realtime_priority = 0)"
    setter = getattr(os, "sched_setscheduler", None)
    if setter is None:
        raise PriorityError("SCHED_FIFO is not available on this system")
    policy = os.SCHED_FIFO | getattr(os, "SCHED_RESET_ON_FORK", 0)
    try:
        setter(0, policy, os.sched_param(priority))
        others = _raise_other_threads(policy, max(1, priority - 1))
        _raise_threads_at_start(policy, max(1, priority - 1),
                                counters if counters is not None else Counter())  # fmt: skip
        # A thread that holds the interpreter lock gives it up to a waiting one only after
        # the switch interval (5 ms by default): the miss worker's pool threads (gone since)
        # unpickling a returned map held the loops for 3-3.5 ms (perf: the loops' thread in
        # a futex wait, woken by them). Now the loops wait at most this for another thread's
        # slice of Python; a tick of theirs is interrupted for as little when one asks.
        sys.setswitchinterval(GIL_SWITCH_S)
    except PermissionError as exc:
        raise PriorityError(
            f"SCHED_FIFO priority {priority} refused ({exc.strerror}): run with CAP_SYS_NICE, "
            "or set CPUSchedulingPolicy=fifo in the systemd unit"
        ) from exc
    except OSError as exc:
        raise PriorityError(f"SCHED_FIFO priority {priority} refused: {exc}") from exc
    switch = f"interpreter lock switch interval {GIL_SWITCH_S * 1e3:g} ms"
    if not others:
        return f"SCHED_FIFO priority {priority}, {switch}"
    return (
        f"SCHED_FIFO priority {priority}, the process's {others} other thread(s) at "
        f"{max(1, priority - 1)} (they take the interpreter lock the loops need), {switch}"
    )


def _raise_other_threads(policy: int, priority: int) -> int:
    """``policy`` at ``priority`` for every thread of this process but the caller; the count.
    A thread that ended meanwhile is skipped."""
    me = threading.get_native_id()
    raised = 0
    for entry in os.listdir("/proc/self/task"):
        tid = int(entry)
        if tid == me:
            continue
        try:
            os.sched_setscheduler(tid, policy, os.sched_param(priority))
        except ProcessLookupError:
            continue
        raised += 1
    return raised


def _raise_threads_at_start(policy: int, priority: int, counters: Counter[str]) -> None:
    """``policy`` at ``priority`` for every thread the threading module starts from now on,
    as its first act (``threading.setprofile``: a hook each new thread calls once, then
    drops). A thread started after the loops were raised began at normal priority
    (``SCHED_RESET_ON_FORK`` holds for threads too): the miss worker's pool manager and
    queue feeder threads, when the worker came up after start-up (15 s at load 13). Holding
    the interpreter lock's mutex when a CPU hog preempted them, they stopped the loops for
    145 and 373 ms (perf: the loops' thread in ``__lll_lock_wait``, woken by them)."""

    def hook(frame: Any, event: str, arg: Any) -> None:
        sys.setprofile(None)  # once per thread: no cost after
        try:
            os.sched_setscheduler(0, policy, os.sched_param(priority))  # 0: this thread
        except OSError:
            counters["threads_not_raised_at_start"] += 1
            return
        counters["threads_raised_at_start"] += 1

    threading.setprofile(hook)


class AffinityError(EpcError, OSError):
    """The CPU affinity could not be set (a CPU this machine does not offer, not Linux)."""


def apply_affinity(cpus: tuple[int, ...]) -> str:
    """Pin the calling thread to ``cpus``; () leaves it as it is. Returns what was done, for
    the log; raises :class:`AffinityError` naming why it could not (nothing is changed)."""
    if not cpus:
        return "no CPU affinity (loops.cpu_affinity = [])"
    getter = getattr(os, "sched_getaffinity", None)
    setter = getattr(os, "sched_setaffinity", None)
    if getter is None or setter is None:
        raise AffinityError("CPU affinity is not available on this system")
    offered = getter(0)
    missing = sorted(set(cpus) - offered)
    if missing:
        raise AffinityError(f"CPU(s) {missing} not offered to this process (it may use "
                            f"{sorted(offered)})")  # fmt: skip
    try:
        setter(0, set(cpus))  # pid 0: the calling thread only
    except OSError as exc:
        raise AffinityError(f"CPU affinity {sorted(cpus)} refused: {exc}") from exc
    return f"pinned to CPU(s) {sorted(cpus)}"


def prepare(
    priority: int, monitor: GcMonitor, counters: Counter[str], cpus: tuple[int, ...] = ()
) -> None:
    """Start-up is over, the loops are next: freeze the start-up objects, time every
    collection from now on, and raise the loops' priority and pin them to ``cpus`` if
    configured (a refusal is logged and counted, never fatal)."""
    frozen = freeze_startup_objects()
    monitor.loop_thread = threading.get_ident()
    monitor.install()
    try:
        log.info("loops: %s", apply_affinity(cpus))
    except AffinityError as exc:
        counters["cpu_affinity_refused"] += 1
        log.warning("loops.cpu_affinity not applied: %s", exc)
    try:
        how = apply_priority(priority, counters)
    except PriorityError as exc:
        counters["realtime_priority_refused"] += 1
        how = "normal scheduling"
        log.warning("loops.realtime_priority not applied: %s", exc)
    log.info("loops: %s; %d start-up objects frozen out of the garbage collector", how, frozen)
