"""The service's processes as the stats see them: CPU from ``/proc/<pid>/stat``.

Read at the stats' pace (the end of a flight, a SIGHUP), never per tick. Linux; elsewhere
the CPU figures are absent and the rest (queues, drops, restarts) is still given.
"""

from __future__ import annotations

import math
import os
import time
from typing import Any

_TICKS_PER_S = os.sysconf("SC_CLK_TCK")
# how often a caller on the loops' thread asks a start's StartWatch (``verdict_every``): two
# /proc reads, tens of us, were paid every position tick of a start (2.5-150 s) before stop 42
WATCH_EVERY_S = 0.25
_PAGE_BYTES = os.sysconf("SC_PAGE_SIZE")


def stat_fields(text: str) -> list[str]:
    """``/proc/<pid>/stat``'s fields after "pid (comm) " (comm may hold spaces and
    parentheses), 0-based from the state: ppid [1], utime [11], stime [12], starttime [19],
    rss [21], processor [36]."""
    return text[text.rindex(")") + 2 :].split()


# a helper process's log lines (written, dropped: its ``logpipe.DirectHandler``), counted in
# memory it shares with this process, by pid, with the helper's name (``children.start_counted``)
_LOG_COUNTS: dict[int, tuple[str, Any]] = {}
# by helper name: the lines of its processes that ended (folded in when the next one started;
# before stop 40 each restart left its entry behind and the stats counted the new one's alone)
_ENDED_LOG_COUNTS: dict[str, tuple[int, int]] = {}


def register_log_counts(pid: int, counts: Any, name: str) -> None:
    """``counts`` (two shared int64: lines written, dropped) are ``pid``'s log lines; ``pid``
    is helper ``name``'s process now: the one before it (ended: restarted helpers are started
    after their predecessor's end) is folded into the name's counts and dropped."""
    for old in [p for p, (n, _) in _LOG_COUNTS.items() if n == name and p != pid]:
        _, old_counts = _LOG_COUNTS.pop(old)
        lines, dropped = _ENDED_LOG_COUNTS.get(name, (0, 0))
        _ENDED_LOG_COUNTS[name] = (lines + int(old_counts[0]), dropped + int(old_counts[1]))
    _LOG_COUNTS[pid] = (name, counts)


def log_counts(pid: int) -> tuple[int, int] | None:
    """``pid``'s helper's log lines written and dropped, over its restarts (None: not a
    counted helper's)."""
    entry = _LOG_COUNTS.get(pid)
    if entry is None:
        return None
    name, counts = entry
    lines, dropped = _ENDED_LOG_COUNTS.get(name, (0, 0))
    return lines + int(counts[0]), dropped + int(counts[1])


def process_report(pid: int | None, **extra: Any) -> dict[str, Any]:
    """``pid``'s CPU seconds (user + system), its share of one CPU over its life so far (a
    restarted helper is a new pid: its share counts from its start) and its resident
    memory, with ``extra``; a helper's log lines written and dropped (``log_lines``,
    ``log_dropped``: a stderr held full drops them, never waited for), over its restarts."""
    out: dict[str, Any] = {"pid": pid, **extra}
    counts = log_counts(pid) if pid is not None else None
    if counts is not None:
        out["log_lines"], out["log_dropped"] = counts
    if pid is None:
        return out
    try:
        with open(f"/proc/{pid}/stat") as fh:
            text = fh.read()
        with open("/proc/uptime") as fh:
            uptime_s = float(fh.read().split()[0])
    except OSError:  # gone, or no /proc
        return out
    fields = stat_fields(text)
    cpu_s = (int(fields[11]) + int(fields[12])) / _TICKS_PER_S  # utime, stime
    life_s = uptime_s - int(fields[19]) / _TICKS_PER_S  # starttime
    out["cpu_s"] = round(cpu_s, 2)
    out["rss_mb"] = round(int(fields[21]) * _PAGE_BYTES / 2**20, 1)
    if life_s > 0.1:
        out["cpu_share"] = round(cpu_s / life_s, 3)
    return out


def progress(pid: int) -> tuple[int, int, int] | None:
    """What grows while ``pid`` runs or waits for a CPU: its CPU ticks (every thread: utime
    + stime), its main thread's ns on a CPU and ns queued for one (``schedstat``). None:
    gone (or a zombie). A stopped (SIGSTOP) or blocked process grows none of them. The
    queued ns grow only when a wait ends (the kernel adds it as the thread gets its CPU):
    a process queued now shows as its state, :func:`sample`'s."""
    got = sample(pid)
    return None if got is None else got[1]


def sample(pid: int) -> tuple[str, tuple[int, int, int]] | None:
    """``pid``'s state now (``/proc/<pid>/stat``: R running or queued for a CPU, S or D
    asleep, T stopped) and its :func:`progress`, in the same two reads. None: gone."""
    try:
        with open(f"/proc/{pid}/stat") as fh:
            fields = stat_fields(fh.read())
        with open(f"/proc/{pid}/schedstat") as fh:
            on_cpu_ns, queued_ns = (int(x) for x in fh.read().split()[:2])
    except (OSError, ValueError):
        return None
    if fields[0] in ("Z", "X"):
        return None
    return fields[0], (int(fields[11]) + int(fields[12]), on_cpu_ns, queued_ns)


def stopped(pid: int) -> bool:
    """Whether ``pid`` is stopped (SIGSTOP, a tracer): state T or t."""
    try:
        with open(f"/proc/{pid}/stat") as fh:
            return stat_fields(fh.read())[0] in ("T", "t")
    except OSError:
        return False


def tree(pid: int) -> list[int]:
    """``pid`` and its descendants now."""
    out, todo = [], [pid]
    while todo:
        p = todo.pop()
        out.append(p)
        try:
            for task in os.listdir(f"/proc/{p}/task"):
                with open(f"/proc/{p}/task/{task}/children") as fh:
                    todo += [int(c) for c in fh.read().split()]
        except OSError:
            continue
    return out


class StartWatch:
    """A child's start judged by its progress, not by a clock (stop 41): at load 12-17 on
    2 CPUs, importing numpy, numba and Zenoh took a child 93-156 s, every second of it
    running or queued for a CPU. ``verdict`` is None while the child is starting: it is
    alive, and it ran or waited for a CPU within ``stall_s``; otherwise why it is not (gone;
    no progress for ``stall_s``: SIGSTOPped, blocked, wedged; or not up in ``cap_s`` though
    moving: a loop that never ends). Call it at any pace; each call samples ``/proc``
    (:meth:`verdict_every`: at most so often).
    ``waits_on``: a process whose start the child's waits for (the bench's attackers connect
    to the service's fleet helper): while the child is not stopped, that process's tree's
    progress is the child's too."""

    def __init__(self, pid: int, stall_s: float, cap_s: float,
                 waits_on: int | None = None) -> None:  # fmt: skip
        self.pid = pid
        self.waits_on = waits_on
        self.stall_s = stall_s
        self.cap_s = cap_s
        self.started_s = self.moved_s = time.monotonic()
        self._last = self._progress()[0]
        self._asked_s = -math.inf  # when verdict_every last sampled

    def restart_clock(self, now_s: float) -> None:
        """Judge from ``now_s`` on (a start whose clock runs from a later event)."""
        self.started_s = self.moved_s = now_s
        self._last = self._progress()[0]

    def _progress(self) -> tuple[tuple[Any, ...] | None, bool]:
        """What grows while the child (and ``waits_on``'s tree) runs or waits for a CPU, and
        whether one of them is queued or running now (state R). A wait in a run queue grows
        nothing until it ends: a busy child beside two CPU hogs went 0.6 s (nice 0) to 2.4 s
        (nice +10) without any figure of its progress changing, in state R throughout, and
        was judged stalled (stop 44: a 0.5 s stall bound at load 8-12)."""
        own = sample(self.pid)
        if own is None:
            return None, False
        state, counters = own
        if self.waits_on is None or state in ("T", "t"):
            return counters, state == "R"
        others = [sample(p) for p in tree(self.waits_on)]
        seen = (counters, tuple(None if o is None else o[1] for o in others))
        return seen, state == "R" or any(o is not None and o[0] == "R" for o in others)

    def verdict(self, now_s: float | None = None) -> str | None:
        now_s = time.monotonic() if now_s is None else now_s
        seen, runnable = self._progress()
        if seen is None:
            return "it ended"
        if seen != self._last or runnable:
            self._last, self.moved_s = seen, now_s
        if now_s - self.moved_s > self.stall_s:
            return f"no CPU used or waited for in {self.stall_s:g} s (stopped or wedged)"
        if now_s - self.started_s > self.cap_s:
            return f"not up in {self.cap_s:g} s though running"
        return None

    def verdict_every(self, every_s: float, now_s: float | None = None) -> str | None:
        """:meth:`verdict`, sampled at most every ``every_s`` (None between): for a caller
        on the loops' thread that sees the child's end at once by other means (its pipe's
        EOF, its exit), judging the start's stall and cap no sooner than it needs to."""
        now_s = time.monotonic() if now_s is None else now_s
        if now_s - self._asked_s < every_s:
            return None
        self._asked_s = now_s
        return self.verdict(now_s)
