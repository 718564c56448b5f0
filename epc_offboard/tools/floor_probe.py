"""The machine's floor beside the loops: a bare 200 Hz loop that does nothing but keep time.

``bench --attack`` starts two of these beside the service for the whole flight (issue 21,
stop 42), at the loops' scheduling (SCHED_FIFO at their priority where permitted, else the
deployed nice), so that they share the machine's load and steal with the loops. Each ticks
on absolute deadlines every ``PERIOD_S`` and, each tick, runs a small fixed compute
(``work``: ``WORK_ITERATIONS`` float additions in Python, ~15-25 us on the 2-core machine
idle) timed by the wall clock and by its thread's CPU clock (steal inflates the first, not
the second). Two processes, one per way of waiting (``WAKES``), not one alternating:

* ``asyncio``: the loops' own wait (``service.clock.sleep_until``: an event loop's timer,
  epoll's timeout in whole milliseconds, rounded up);
* ``sleep``: the best Python has, ``time.sleep`` to the deadline (CPython 3.11:
  ``clock_nanosleep`` on CLOCK_MONOTONIC to an absolute time, in nanoseconds).

Apart, each is a whole 200 Hz loop (a gap of one is not the other's), and neither waits
for the other's interpreter lock.

A tick later than a period is not made up: the loop skips to the next deadline ahead, as
the service's loops do (``Loops._next_tick``). Records per tick, on ``time.monotonic`` (the
bench's and the loops' clock): ``COLUMNS``, float64, written to ``--out`` at the end
(SIGTERM or SIGINT; ``--seconds``), read back by :func:`read_records`. The first stdout
line is ``ready`` and a JSON object: the wake, the pid, whether SCHED_FIFO was applied;
the last, ``done`` and its cost: ``cpu_s`` (its CPU time), ``wall_s``, ``ticks``.

``python -m epc_offboard.tools.floor_probe --wake sleep --out FILE [--fifo 50] [--cpu N]``
"""

from __future__ import annotations

import argparse
import array
import asyncio
import contextlib
import json
import os
import signal
import sys
import time
from pathlib import Path
from typing import Any

from epc_offboard.common.children import die_with_launcher
from epc_offboard.service.clock import sleep_until

PERIOD_S = 0.005  # the attitude loop's: a perfect 200 Hz loop
WORK_ITERATIONS = 300
WAKES = ("asyncio", "sleep")
COLUMNS = ("due_s", "wake_s", "compute_wall_s", "compute_cpu_s")
DEPLOYED_NICE = -5  # config/epc-offboard.service's Nice=: without SCHED_FIFO


def work(n: int = WORK_ITERATIONS) -> float:
    """The tick's fixed compute: ``n`` float additions (no allocation beyond the ints)."""
    x = 0.0
    for i in range(n):
        x += i * 0.5
    return x


class Probe:
    """The ticks' records (``COLUMNS`` in a row per tick) and the stop flag."""

    def __init__(self, period_s: float = PERIOD_S, iterations: int = WORK_ITERATIONS) -> None:
        self.period_s = period_s
        self.iterations = iterations
        self.rows = array.array("d")
        self.stopping = False

    def tick(self, due_s: float) -> float:
        """One tick woken now for ``due_s``: the compute timed, recorded; the next deadline
        (skipping, never bursting, when more than a period behind)."""
        wake_s = time.monotonic()
        cpu0 = time.thread_time()
        wall0 = time.perf_counter()
        work(self.iterations)
        wall_s = time.perf_counter() - wall0
        cpu_s = time.thread_time() - cpu0
        self.rows.extend((due_s, wake_s, wall_s, cpu_s))
        due_s += self.period_s
        now_s = time.monotonic()
        if now_s - due_s > self.period_s:
            due_s += int((now_s - due_s) / self.period_s) * self.period_s
        return due_s

    def run_sleep(self, seconds: float) -> None:
        end_s = time.monotonic() + seconds
        due_s = time.monotonic() + self.period_s
        while not self.stopping and due_s < end_s:
            delay = due_s - time.monotonic()
            if delay > 0.0:
                time.sleep(delay)
            due_s = self.tick(due_s)

    async def run_asyncio(self, seconds: float) -> None:
        loop = asyncio.get_running_loop()
        end_s = time.monotonic() + seconds
        due_s = time.monotonic() + self.period_s
        while not self.stopping and due_s < end_s:
            await sleep_until(loop, due_s)
            due_s = self.tick(due_s)

    def run(self, wake: str, seconds: float) -> None:
        if wake == "sleep":
            self.run_sleep(seconds)
        else:
            asyncio.run(self.run_asyncio(seconds))

    def write(self, path: Path) -> None:
        with path.open("wb") as fh:
            self.rows.tofile(fh)


def read_records(path: Path) -> dict[str, Any]:
    """A probe's records as columns (numpy arrays, ``COLUMNS``); empty when none."""
    import numpy as np

    raw = np.fromfile(path, dtype=np.float64) if path.exists() else np.zeros(0)
    rows = raw[: raw.size - raw.size % len(COLUMNS)].reshape(-1, len(COLUMNS))
    return {name: rows[:, i].copy() for i, name in enumerate(COLUMNS)}


def schedule(fifo: int | None, cpu: int | None) -> bool:
    """This process at the loops' scheduling: SCHED_FIFO at ``fifo`` where permitted (else
    the deployed nice), pinned to ``cpu`` if given; whether SCHED_FIFO was applied. The
    bench's own children's too (the SITL's ``preexec_fn``, the attackers')."""
    if cpu is not None:
        with contextlib.suppress(OSError):
            os.sched_setaffinity(0, {cpu})
    if fifo is not None:
        try:
            os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(fifo))
            return True
        except (PermissionError, OSError):
            pass
    with contextlib.suppress(PermissionError):
        os.nice(DEPLOYED_NICE)
    return False


def main(argv: list[str] | None = None) -> int:
    die_with_launcher()  # SIGTERM when the bench dies, even SIGKILLed: its records, then out
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--wake", choices=WAKES, required=True)
    p.add_argument("--out", required=True)
    p.add_argument("--seconds", type=float, default=3600.0)
    p.add_argument("--fifo", type=int, default=None, metavar="PRIORITY")
    p.add_argument("--cpu", type=int, default=None)
    p.add_argument("--iterations", type=int, default=WORK_ITERATIONS)
    args = p.parse_args(argv)
    probe = Probe(iterations=args.iterations)

    def stop(*_: Any) -> None:
        probe.stopping = True

    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, stop)
    fifo = schedule(args.fifo, args.cpu)
    work(args.iterations)  # warm
    print("ready " + json.dumps({"wake": args.wake, "pid": os.getpid(), "fifo_applied": fifo,
                                 "priority": args.fifo if fifo else None, "cpu": args.cpu,
                                 "period_s": PERIOD_S, "iterations": args.iterations}),
          flush=True)  # fmt: skip
    started_s = time.monotonic()
    probe.run(args.wake, args.seconds)
    probe.write(Path(args.out))
    # what the probe cost the machine: its CPU time (every thread, the interpreter's own
    # included) over its ticking time
    wall_s = time.monotonic() - started_s
    print("done " + json.dumps({"cpu_s": round(time.process_time(), 3),
                                "wall_s": round(wall_s, 3),
                                "ticks": len(probe.rows) // len(COLUMNS)}), flush=True)  # fmt: skip
    return 0


if __name__ == "__main__":
    sys.exit(main())
