"""Per-loop timing statistics: rate, period jitter, deadline misses, compute time.

Pure bookkeeping over a bounded window, so a long flight keeps constant memory.

A tick's compute is wall time, and in real time wall time is not all the tick's own work:
the loops' thread may wait for the interpreter lock another thread holds, or be preempted.
Each tick therefore also records the CPU time its thread used (``cpu_s``) and whether the
thread switched out during it, voluntarily (it blocked: the interpreter lock, a lock, a
syscall) or not (preempted); ``compute_cpu_us_*``, ``ticks_blocked`` and
``ticks_preempted`` say which part of a slow tick was the tick's.
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass, field

import numpy as np


@dataclass(frozen=True)
class LoopReport:
    rate_hz: float
    deadline_misses: int
    period_jitter_p99_ms: float
    compute_us_median: float
    compute_us_p99: float
    ticks: int
    compute_cpu_us_median: float = math.nan
    compute_cpu_us_p99: float = math.nan
    ticks_blocked: int = 0
    ticks_preempted: int = 0
    # the longest tick's wall time over the whole run (not the window): a stall of the loops'
    # own thread (a kernel compiled inside a tick: 0.2-1 s) whatever else was starved
    compute_us_max: float = 0.0

    def as_dict(self) -> dict[str, float | int | None]:
        """Rounded to what the figures can mean: tick times are differences of clock readings
        (vehicle time in ms steps, or the wall clock), so a lockstep 100 Hz loop measures
        99.99999999999999 Hz and a jitter of 1.6e-12 ms, which are 100 and 0. Rates to 0.01 Hz,
        times to 1 us (jitter: 0.001 ms; compute: 0.1 us, the timer's useful resolution)."""
        return {
            "rate_hz": round(self.rate_hz, 2),
            "deadline_misses": self.deadline_misses,
            "period_jitter_p99_ms": round(self.period_jitter_p99_ms, 3),
            "compute_us_median": round(self.compute_us_median, 1),
            "compute_us_p99": round(self.compute_us_p99, 1),
            "compute_cpu_us_median": _round_or_none(self.compute_cpu_us_median),
            "compute_cpu_us_p99": _round_or_none(self.compute_cpu_us_p99),
            "ticks_blocked": self.ticks_blocked,
            "ticks_preempted": self.ticks_preempted,
            "compute_us_max": round(self.compute_us_max, 1),
        }


def _round_or_none(value_us: float) -> float | None:
    return None if math.isnan(value_us) else round(value_us, 1)


@dataclass
class LoopTiming:
    """Record each tick's start time (loop clock, s) and compute duration (wall, s).

    A deadline miss is a tick whose compute took longer than the period, or that started more
    than one period late.
    """

    period_s: float
    window: int = 20_000
    ticks: int = 0
    deadline_misses: int = 0
    ticks_blocked: int = 0  # the thread switched out voluntarily during the tick
    ticks_preempted: int = 0  # ... involuntarily
    _starts: deque[float] = field(default_factory=deque)
    _compute: deque[float] = field(default_factory=deque)
    _cpu: deque[float] = field(default_factory=deque)
    _first_start_s: float = math.nan
    _last_start_s: float = math.nan
    _compute_max_s: float = 0.0  # over every tick recorded

    def record(
        self,
        start_s: float,
        compute_s: float,
        scheduled_s: float | None = None,
        *,
        cpu_s: float | None = None,
        blocked: bool = False,
        preempted: bool = False,
    ) -> bool:
        """``cpu_s``: the CPU time the loops' thread used in the tick (None: not measured);
        ``blocked`` / ``preempted``: it switched out during the tick, voluntarily / not.
        Returns whether the tick was a deadline miss."""
        self.ticks += 1
        self.ticks_blocked += blocked
        self.ticks_preempted += preempted
        if cpu_s is not None:
            self._cpu.append(cpu_s)
            if len(self._cpu) > self.window:
                self._cpu.popleft()
        if math.isnan(self._first_start_s):
            self._first_start_s = start_s
        self._last_start_s = start_s
        late = 0.0 if scheduled_s is None else start_s - scheduled_s
        missed = compute_s > self.period_s or late > self.period_s
        self.deadline_misses += missed
        self._starts.append(start_s)
        self._compute.append(compute_s)
        self._compute_max_s = max(self._compute_max_s, compute_s)
        if len(self._starts) > self.window:
            self._starts.popleft()
            self._compute.popleft()
        return missed

    def report(self) -> LoopReport:
        if self.ticks < 2:
            return LoopReport(0.0, self.deadline_misses, 0.0, 0.0, 0.0, self.ticks,
                              compute_us_max=self._compute_max_s * 1e6)  # fmt: skip
        span = self._last_start_s - self._first_start_s
        rate = (self.ticks - 1) / span if span > 0 else 0.0
        periods = np.diff(np.fromiter(self._starts, dtype=np.float64))
        jitter = np.abs(periods - self.period_s)
        compute_us = np.fromiter(self._compute, dtype=np.float64) * 1e6
        cpu_us = np.fromiter(self._cpu, dtype=np.float64) * 1e6
        return LoopReport(
            rate_hz=rate,
            deadline_misses=self.deadline_misses,
            period_jitter_p99_ms=float(np.percentile(jitter, 99)) * 1e3,
            compute_us_median=float(np.median(compute_us)),
            compute_us_p99=float(np.percentile(compute_us, 99)),
            ticks=self.ticks,
            compute_cpu_us_median=float(np.median(cpu_us)) if cpu_us.size else math.nan,
            compute_cpu_us_p99=float(np.percentile(cpu_us, 99)) if cpu_us.size else math.nan,
            ticks_blocked=self.ticks_blocked,
            ticks_preempted=self.ticks_preempted,
            compute_us_max=self._compute_max_s * 1e6,
        )
