"""A stderr nobody reads never stalls the control loops (issue 21), end to end in REAL TIME.

The service's stderr is a pipe this test holds: read while the vehicle takes off, then not
read and filled to the brim. Every SIGHUP makes the loops' thread log a line ("SIGHUP: ...
reloaded"). With logging's StreamHandler that write blocked until the pipe was read again:
the position loop stopped for as long (seconds). Through the log pump (common/logpipe.py)
the loops keep their period, the lines wait in the pump's pipe and all arrive once stderr
is read again, and none is dropped (counted in stats).
"""

from __future__ import annotations

import contextlib
import csv
import itertools
import os
import select
import signal
import subprocess
import sys
import threading
import time
from dataclasses import dataclass
from datetime import datetime
from pathlib import Path
from typing import Any

import pytest

from epc_offboard.vehicle.dialect_px4 import PX4_MAIN_MODE_OFFBOARD
from tests.rig import Rig, cpu_hog, deployed_priority, unit_stop_timeout_s

pytestmark = [pytest.mark.timeout(240), pytest.mark.one_at_a_time("alone")]

HOLD_S = 3.0  # stderr full and unread this long
SIGHUPS = 5
GAP_BOUND_S = 0.1  # loose (load 6); a blocked write held the loop for all of HOLD_S
# As the unit runs it (default.toml): the loops' thread SCHED_FIFO where the test may raise
# it, else normal scheduling (the service says why). At normal scheduling beside others'
# work the bound judged the machine: 8 of 9 flights at load 16-24 over it, each gap a
# run-queue wait of the loops' thread (769 of a 790 ms interval, 3 ms of its CPU), and a
# config-reload thread preempted holding the interpreter lock (stop 38's 70-90 ms waits,
# ~20 voluntary switches) is FIFO too only when the loops are (realtime.apply_priority)
REALTIME_PRIORITY = 50
_RELOADED = "SIGHUP: trajectory, mission and offboard settings reloaded"
_FILL = b"#" * 4095 + b"\n"


class Stderr:
    """The service's stderr: a pipe read by a thread while ``reading`` is set."""

    def __init__(self) -> None:
        self.read_fd, self.write_fd = os.pipe()
        self.data = bytearray()
        self.reading = threading.Event()
        self.reading.set()
        self._idle = threading.Event()  # the thread is between reads (not reading)
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def _run(self) -> None:
        while not self._stop.is_set():
            if not self.reading.is_set():
                self._idle.set()
                time.sleep(0.01)
                continue
            self._idle.clear()
            ready, _, _ = select.select([self.read_fd], [], [], 0.05)
            if ready:
                chunk = os.read(self.read_fd, 1 << 16)
                if not chunk:
                    return
                self.data += chunk

    def stop_reading_and_fill(self) -> int:
        """Stop reading and fill the pipe to the brim; returns the bytes written."""
        self.reading.clear()
        assert self._idle.wait(5.0)
        filled = 0
        # a description of its own: O_NONBLOCK on write_fd would be the service's stderr's too
        fd = os.open(f"/proc/self/fd/{self.write_fd}", os.O_WRONLY | os.O_NONBLOCK)
        try:
            with contextlib.suppress(BlockingIOError):
                while True:
                    filled += os.write(fd, _FILL)
        finally:
            os.close(fd)
        return filled

    def close(self) -> None:
        """Our writing end closed; read to EOF (every other holder gone)."""
        os.close(self.write_fd)
        self.reading.set()
        self._thread.join(timeout=30.0)
        self._stop.set()
        os.close(self.read_fd)

    def text(self) -> str:
        return bytes(self.data).decode(errors="replace")


def _positions_s(path: Path) -> list[float]:
    if not path.exists():
        return []
    with path.open() as fh:
        return [float(row["t_s"]) for row in csv.DictReader(fh)]


@dataclass
class Held:
    """What a flight with its stderr held full showed."""

    code: int
    text: str  # everything the service wrote to stderr (the filling taken out)
    filled: int  # bytes the pipe took before it was full
    rows_s: list[float]  # every position tick (flight rows)
    held_from_s: float
    held_to_s: float
    stats: dict[str, Any]
    stop_s: float  # SIGTERM to the service's exit
    stop_wall_s: float  # the SIGTERM's wall-clock time (time.time: the log lines' clock)
    # the SIGHUP lines read before the service was asked to stop: within 20 s of stderr being
    # read again, while it runs (not held back until its stop's flush)
    running_lines: int

    @property
    def held_s(self) -> float:
        return self.held_to_s - self.held_from_s

    @property
    def ticks_s(self) -> list[float]:
        """The position ticks while stderr was held."""
        return [t for t in self.rows_s if self.held_from_s <= t <= self.held_to_s]

    @property
    def loop_gap_s(self) -> float:
        """The position loop's longest interval between ticks from the hold's start to a
        second after it, as the service timed it (``stats.stalls``: every tick later than
        12 ms; none: under 12 ms). A write blocked on stderr: the whole hold, or more."""
        late = [s["interval_ms"] for s in self.stats.get("stalls", [])
                if s["loop"] == "position"
                and self.held_from_s <= s["t_s"] <= self.held_to_s + 1.0]  # fmt: skip
        return max(late, default=0.0) / 1e3

    @property
    def gap_s(self) -> float:
        """The largest interval between position ticks from the hold's start to the first
        tick after it (a loop blocked through it: the whole hold, or more)."""
        after = [t for t in self.rows_s if t > self.held_to_s][:1]
        ticks = [t for t in self.rows_s if t < self.held_from_s][-1:] + self.ticks_s + after
        return max((b - a for a, b in itertools.pairwise(ticks)), default=float("inf"))


def fly_with_stderr_held(tmp: Path, hold_s: float, sighups: int, hogs: int = 0,
                         stop_held: bool = False) -> Held:  # fmt: skip
    """Hover in real time; once hovering, stderr is not read and filled for ``hold_s`` while
    ``sighups`` SIGHUPs (a log line each, on the loops' thread) come; then read again.
    ``stop_held``: the service is stopped (SIGTERM) before stderr is read again."""
    overrides = {
        "mission": {"duration_s": 120.0 + hold_s, "land_at_end": True},
        "trajectory": {"shape": "hover"},
        "loops": {"realtime_priority": REALTIME_PRIORITY},
    }
    rig = Rig(tmp, lockstep=False, speedup=1.0, service_overrides=overrides)
    err = Stderr()
    hog_procs: list[subprocess.Popen[bytes]] = []
    try:
        rig.start_sitl()
        rig.service = subprocess.Popen(
            [sys.executable, "-m", "epc_offboard.cli", "run", "--config", str(rig.config_path)],
            stdout=(tmp / "service.log").open("ab"), stderr=err.write_fd,
            env=dict(os.environ, PYTHONUNBUFFERED="1"), preexec_fn=deployed_priority,
        )  # fmt: skip
        rig.wait_mode(PX4_MAIN_MODE_OFFBOARD, timeout_s=120)
        hog_procs = [cpu_hog(hold_s + 4.0) for _ in range(hogs)]
        time.sleep(2.0)  # hovering
        filled = err.stop_reading_and_fill()
        held_from_s = time.monotonic()
        for _ in range(sighups):  # each: a log line on the loops' thread
            rig.service.send_signal(signal.SIGHUP)
            time.sleep(hold_s / sighups)
        held_to_s = time.monotonic()
        stop_wall_s = time.time()
        if stop_held:
            code, stop_s = rig.stop_service(timeout_s=30.0)
        err.reading.set()  # stderr read again: what waited arrives
        deadline = time.monotonic() + 20.0
        while err.text().count(_RELOADED) < sighups and time.monotonic() < deadline:
            time.sleep(0.1)
        running_lines = 0 if stop_held else err.text().count(_RELOADED)
        if not stop_held:
            stop_wall_s = time.time()
            code, stop_s = rig.stop_service(timeout_s=30.0)
    finally:
        for hog in hog_procs:
            hog.kill()
            hog.wait()
        rig.__exit__()
        err.close()
    return Held(code, err.text().replace(_FILL.decode(), ""), filled,
                _positions_s(tmp / "flight.csv"), held_from_s, held_to_s, rig.stats(),
                stop_s, stop_wall_s, running_lines)  # fmt: skip


def test_a_full_unread_stderr_never_stalls_the_position_loop(tmp_path):
    held = fly_with_stderr_held(tmp_path, HOLD_S, SIGHUPS)
    tail = held.text[-3000:]
    assert held.filled >= 4096, held.filled
    assert held.code == 0, tail
    # the loops kept their period while stderr was full, as the service timed its ticks: the
    # flight rows' gaps also count rows the log writer (nice +10) lost or a starved SITL's
    # stale state withheld (FIFO, load 24-27: 821 and 2,890 ms row gaps, loop stalls <= 15 ms)
    print(f"largest position gap while stderr was full: {1000 * held.loop_gap_s:.1f} ms "
          f"(flight rows: {1000 * held.gap_s:.1f} ms)")  # fmt: skip
    assert held.ticks_s, tail  # it flew, and controlled, through the hold
    assert held.loop_gap_s < GAP_BOUND_S, f"position loop stalled {held.loop_gap_s:.3f} s:\n{tail}"
    # nothing logged meanwhile was lost: every line arrived once stderr was read, whole, and
    # while the service ran (a line held back until the stop's flush arrived too late: stop
    # 40's suite waited out the 20 s for them once, unexplained, not seen since)
    assert held.running_lines == SIGHUPS, f"{held.running_lines} of {SIGHUPS} before the stop"
    assert held.text.count(_RELOADED) == SIGHUPS, tail
    assert "stopped, its helpers " in held.text, tail  # the last line, flushed at exit
    assert held.stats["counters"]["log_lines_dropped"] == 0
    pump = held.stats["processes"]["log_lines"]
    assert pump["lines"] >= SIGHUPS, pump
    assert pump["dropped"] == 0, pump
    assert not pump["pump_failed"], pump


def test_a_stop_with_stderr_held_full_ends_within_its_bound(tmp_path):
    """SIGTERM while stderr is held full (journald slow): the service exits inside the unit's
    TimeoutStopSec (systemd's SIGKILL never comes), and the pump writes out what was queued
    after it (its last line too) once stderr is read again. Before, the exit waited 2 s
    more for the held pump after the helpers' stop: the pump's wait ends at the stop's
    bound (``service.STOP_S`` after the SIGTERM) or at once if the helpers took longer.

    Not judged against STOP_S + 1 s (stop 42: 4.55 and 4.75 s at load 10.8-19, failed):
    at load the helpers' own stop runs to its bound (``STOP_BOUND_S``, 3 s: the store's
    last save and the miss worker killed there, 3.0-3.23 s at load 16-22) and the
    interpreter's exit after it took 0.3-1.2 s more (stop 43: 3.52-4.19 s)."""
    from epc_offboard.common.logpipe import _CLOSE_WAIT_S
    from epc_offboard.service.service import STOP_BOUND_S, STOP_S

    held = fly_with_stderr_held(tmp_path, 1.0, 1, stop_held=True)
    tail = held.text[-3000:]
    print(f"SIGTERM to exit with stderr held: {held.stop_s:.2f} s")
    assert held.code == 0, tail
    assert unit_stop_timeout_s() > STOP_BOUND_S > STOP_S
    assert held.stop_s < unit_stop_timeout_s(), tail  # the safety: no SIGKILL from systemd
    line = next(x for x in held.text.splitlines() if "stopped, its helpers " in x)
    # (by the pump, after the service exited); the human format's stamp, to the ms
    stopped_wall_s = datetime.strptime(line[:23], "%Y-%m-%d %H:%M:%S,%f").timestamp()
    # the pump was waited for until its deadline or the helpers' stop, whichever came last,
    # and not its own 2 s from there (the old wait: the exit came >= 2 s after it, at any
    # load, once the helpers took STOP_S or more)
    exit_wall_s = held.stop_wall_s + held.stop_s
    waited_s = exit_wall_s - max(held.stop_wall_s + STOP_S, stopped_wall_s)
    print(f"the exit {waited_s:.2f} s after the pump's deadline or the helpers' stop")
    assert waited_s < _CLOSE_WAIT_S, tail


def main() -> int:
    """The measurement: ``python -m tests.test_log_pipe_e2e --hold 30 --hogs 2`` (under the
    measurement lock): the largest position gap while stderr is held full."""
    import argparse
    import json
    import tempfile

    parser = argparse.ArgumentParser(description=main.__doc__)
    parser.add_argument("--hold", type=float, default=30.0)
    parser.add_argument("--sighups", type=int, default=60)
    parser.add_argument("--hogs", type=int, default=2)
    args = parser.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        held = fly_with_stderr_held(Path(tmp), args.hold, args.sighups, args.hogs)
    stalls = held.stats.get("stalls", [])
    print(json.dumps({
        "exit": held.code, "held_s": round(held.held_s, 1), "ticks": len(held.ticks_s),
        "largest_gap_ms": round(1000 * held.gap_s, 1),
        "reloaded_lines": held.text.count(_RELOADED),
        "log_lines_dropped": held.stats["counters"].get("log_lines_dropped"),
        "position_stalls": held.stats["counters"].get("position_stalls", 0),
        "longest_stall_ms": max((s["interval_ms"] for s in stalls if s["loop"] == "position"),
                                default=0),
        "phases": [e["phase"] for e in held.stats["phase_events"]],
    }))  # fmt: skip
    return 0


if __name__ == "__main__":
    sys.exit(main())
