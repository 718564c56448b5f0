"""The service's processes as the stats see them: CPU from ``/proc/<pid>/stat``.

Read at the stats' pace (the end of a flight, a SIGHUP), never per tick. Linux; elsewhere
the CPU figures are absent and the rest (queues, drops, restarts) is still given.
"""

from __future__ import annotations

import os
from typing import Any

_TICKS_PER_S = os.sysconf("SC_CLK_TCK")
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
