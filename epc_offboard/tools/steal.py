"""The hypervisor's share of a real-time flight: steal time beside the loops' thread (issue 21).

On a virtual machine the hypervisor deschedules a virtual CPU when it pleases; the guest's
scheduler still sees the thread it was running as running, and nothing inside the machine
(priority, affinity, fewer objects) shortens that. The kernel counts it per CPU as *steal*
(``/proc/stat``'s eighth column, in clock ticks), and leaves it out of the threads' CPU
clocks (``/proc/<pid>/task/<tid>/schedstat``'s first field, ``time.thread_time``): a
stretch in which the loops' thread was neither sleeping nor waiting for a CPU but its clock
advanced less than the wall clock was stolen.

:class:`StealSampler` reads both every ``SAMPLE_S`` (beside the flight, in the bench's own
process: a read of ``/proc/stat`` costs ~0.1 ms, too much for the loops' thread); the pure
functions line a stretch of time (a window, a position-loop gap, a late attitude tick) up
with them. ``/proc/stat`` counts in 10 ms ticks: a single short gap's steal is known to
within ~10 ms, and what tells is the steal in the gaps against the steal everywhere else.

``python -m epc_offboard.tools.steal --pid PID --out FILE.json [--seconds S]`` samples
beside any process (its main thread), for a run of a bench this module is not part of;
SIGINT or SIGTERM ends it early.
"""

from __future__ import annotations

import argparse
import json
import os
import signal
import threading
import time
from dataclasses import dataclass
from typing import Any

import numpy as np

from epc_offboard.common.frames import FloatArray
from epc_offboard.common.procstats import stat_fields

SAMPLE_S = 0.01  # the kernel's steal moves in 10 ms ticks
_TICK_S = 1.0 / os.sysconf("SC_CLK_TCK")


def read_steal_s(text: str) -> list[float]:
    """Each CPU's steal so far (s) from ``/proc/stat``'s text (``cpuN`` lines, in order)."""
    out = []
    for line in text.splitlines():
        if line.startswith("cpu") and line[3:4].isdigit():
            fields = line.split()
            out.append(int(fields[8]) * _TICK_S if len(fields) > 8 else 0.0)
    return out


def read_thread(pid: int, tid: int) -> tuple[float, float, int] | None:
    """(CPU time s, run-queue wait s, the CPU it last ran on) of a thread; None when gone."""
    base = f"/proc/{pid}/task/{tid}"
    try:
        with open(f"{base}/schedstat", "rb") as fh:
            run_ns, wait_ns = fh.read().split()[:2]
        with open(f"{base}/stat") as fh:
            stat = fh.read()
    except (OSError, ValueError):
        return None
    cpu = int(stat_fields(stat)[36])  # "processor"
    return int(run_ns) * 1e-9, int(wait_ns) * 1e-9, cpu


class StealSampler(threading.Thread):
    """Every ``period_s``: (monotonic s, each CPU's steal s, the thread's CPU s, its
    run-queue wait s, its CPU). ``pid``: the process whose main thread is sampled (the
    service runs its loops there); 0: the machine's steal alone."""

    def __init__(self, pid: int = 0, period_s: float = SAMPLE_S) -> None:
        super().__init__(name="steal-sampler", daemon=True)
        self.pid = pid
        self.period_s = period_s
        self.samples: list[tuple[float, list[float], float, float, int]] = []
        self.stop = threading.Event()

    def run(self) -> None:
        with open("/proc/stat", "rb") as stat:
            while not self.stop.wait(self.period_s):
                stat.seek(0)
                steal = read_steal_s(stat.read().decode())
                t_s = time.monotonic()
                thread = read_thread(self.pid, self.pid) if self.pid else None
                if thread is None:
                    thread = (np.nan, np.nan, -1)
                self.samples.append((t_s, steal, *thread))

    def record(self) -> dict[str, Any]:
        """The samples as columns (JSON-able): ``t_s``, ``steal_s`` (per CPU), ``thread_cpu_s``,
        ``thread_wait_s``, ``thread_on_cpu``."""
        rows = list(self.samples)
        return {
            "t_s": [r[0] for r in rows],
            "steal_s": [r[1] for r in rows],
            "thread_cpu_s": [r[2] for r in rows],
            "thread_wait_s": [r[3] for r in rows],
            "thread_on_cpu": [r[4] for r in rows],
        }


# -- lining stretches of time up with the samples (pure) ---------------------------------------


@dataclass(frozen=True)
class Columns:
    t_s: FloatArray
    steal_s: FloatArray  # (samples, CPUs), cumulative
    thread_cpu_s: FloatArray
    thread_wait_s: FloatArray
    thread_on_cpu: np.ndarray

    @classmethod
    def of(cls, record: dict[str, Any]) -> Columns | None:
        if not record or len(record.get("t_s", ())) < 2:
            return None
        return cls(np.asarray(record["t_s"], dtype=float),
                   np.atleast_2d(np.asarray(record["steal_s"], dtype=float)),
                   np.asarray(record["thread_cpu_s"], dtype=float),
                   np.asarray(record["thread_wait_s"], dtype=float),
                   np.asarray(record["thread_on_cpu"]))  # fmt: skip

    def _at(self, values: FloatArray, t_s: float) -> float:
        return float(np.interp(t_s, self.t_s, values))

    def stretch(self, t0_s: float, t1_s: float) -> dict[str, Any] | None:
        """What the samples say of [t0, t1] (ms; interpolated between samples): the machine's
        steal, the steal of the CPUs the thread was seen on, the thread's CPU time and
        run-queue wait. None outside the sampled span."""
        if t0_s < self.t_s[0] or t1_s > self.t_s[-1] or t1_s <= t0_s:
            return None
        per_cpu = [self._at(self.steal_s[:, c], t1_s) - self._at(self.steal_s[:, c], t0_s)
                   for c in range(self.steal_s.shape[1])]  # fmt: skip
        lo = max(int(np.searchsorted(self.t_s, t0_s)) - 1, 0)
        hi = int(np.searchsorted(self.t_s, t1_s)) + 1
        seen = {int(c) for c in self.thread_on_cpu[lo:hi] if 0 <= c < len(per_cpu)}
        return {
            "ms": t1_s * 1e3 - t0_s * 1e3,
            "steal_ms": round(1e3 * sum(per_cpu), 2),
            "steal_thread_cpu_ms": round(1e3 * max((per_cpu[c] for c in seen), default=0.0), 2),
            "thread_cpu_ms": round(1e3 * (self._at(self.thread_cpu_s, t1_s)
                                          - self._at(self.thread_cpu_s, t0_s)), 2),
            "thread_wait_ms": round(1e3 * (self._at(self.thread_wait_s, t1_s)
                                           - self._at(self.thread_wait_s, t0_s)), 2),
        }  # fmt: skip


def gaps(times_s: FloatArray, over_s: float) -> list[tuple[float, float]]:
    """Each stretch between consecutive ``times_s`` longer than ``over_s``: (start, end)."""
    t = np.asarray(times_s, dtype=float)
    d = np.diff(t)
    return [(float(t[i]), float(t[i + 1])) for i in np.flatnonzero(d > over_s)]


def gap_account(cols: Columns | None, stretches: list[tuple[float, float]]) -> dict[str, Any]:
    """The stretches lined up with the samples, and the steal in them against the steal of
    the whole sampled span (the same length of time, anywhere): ``steal_in_gaps_ms_per_s``
    much above ``steal_ms_per_s`` says the gaps are where the hypervisor took the CPU."""
    if cols is None:
        return {"sampled": False}
    each = [dict(t0_s=round(a, 4), **s) for a, b in stretches
            if (s := cols.stretch(a, b)) is not None]  # fmt: skip
    span_ms = 1e3 * (cols.t_s[-1] - cols.t_s[0])
    total = 1e3 * float(np.sum(cols.steal_s[-1] - cols.steal_s[0]))
    in_ms = sum(e["ms"] for e in each)
    return {
        "sampled": True,
        "steal_ms_per_s": round(1e3 * total / span_ms, 2) if span_ms > 0 else None,
        "steal_in_gaps_ms_per_s": round(1e3 * sum(e["steal_ms"] for e in each) / in_ms, 2)
        if in_ms
        else None,
        "gaps_with_steal": sum(e["steal_ms"] > 0.0 for e in each),
        "gaps": each,
    }


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--pid", type=int, default=0)
    p.add_argument("--out", required=True)
    p.add_argument("--seconds", type=float, default=600.0)
    args = p.parse_args(argv)
    sampler = StealSampler(args.pid)
    for sig in (signal.SIGINT, signal.SIGTERM):  # either ends it, the samples written
        signal.signal(sig, lambda *_: sampler.stop.set())
    sampler.start()
    sampler.stop.wait(args.seconds)
    sampler.stop.set()
    sampler.join()
    with open(args.out, "w", encoding="utf-8") as fh:
        json.dump(sampler.record(), fh)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
