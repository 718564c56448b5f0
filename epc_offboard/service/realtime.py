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
* **Work beside the loops on their thread** (the library saver, the fleet's candidates) runs
  in slices of a few ms with the loops' due ticks between them: one stretch of it is a
  late attitude tick and a position-loop gap (``library_keeper.py``).
"""

from __future__ import annotations

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
