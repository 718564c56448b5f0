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
# memory it shares with this process, by pid (``children.start_counted``)
_LOG_COUNTS: dict[int, Any] = {}


def register_log_counts(pid: int, counts: Any) -> None:
    """``counts`` (two shared int64: lines written, dropped) are ``pid``'s log lines."""
    _LOG_COUNTS[pid] = counts


def process_report(pid: int | None, **extra: Any) -> dict[str, Any]:
    """``pid``'s CPU seconds (user + system), its share of one CPU over its life so far (a
    restarted helper is a new pid: its share counts from its start) and its resident
    memory, with ``extra``; a helper's log lines written and dropped (``log_lines``,
    ``log_dropped``: a stderr held full drops them, never waited for)."""
    out: dict[str, Any] = {"pid": pid, **extra}
    counts = _LOG_COUNTS.get(pid) if pid is not None else None
    if counts is not None:
        out["log_lines"], out["log_dropped"] = int(counts[0]), int(counts[1])
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
