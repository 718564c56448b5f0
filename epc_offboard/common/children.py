"""The service's helper processes: started the same way, and dying with the service.

Every helper (the miss worker, the fleet session, the log writer) is a ``spawn``-ed process:
a fresh interpreter, no fork of a threaded process. Each calls :func:`die_with_parent` first
thing, so that a SIGKILLed service (an OOM kill, ``systemctl kill -s KILL``, a crashed test)
leaves no orphan behind: before this, the 168 MB miss worker and multiprocessing's resource
tracker were re-parented to PID 1 and lived on. The resource tracker needs nothing of its
own: it exits when the last process holding its pipe (the service and its spawned children)
is gone.

Linux's parent-death signal (``prctl(PR_SET_PDEATHSIG)``) is delivered when the *thread*
that created the child exits, so helpers are started from the service's main thread (the
event loop's), which lives as long as the process. Elsewhere, or if the parent died before
the child could ask, the re-check of the parent's pid catches it.
"""

from __future__ import annotations

import contextlib
import ctypes
import os
import signal
import sys
from pathlib import Path

_PR_SET_PDEATHSIG = 1  # <linux/prctl.h>


def die_with_parent(parent_pid: int, sig: int | None = signal.SIGKILL) -> None:
    """In a child: be sent ``sig`` when the parent dies, and exit now if it already has.

    ``parent_pid``: the pid the parent had when it started us (``os.getpid()`` there); a
    different ``os.getppid()`` here means we were re-parented already (the race between the
    parent's death and the prctl call). ``sig`` None: no signal, for a child that watches a
    pipe from the parent instead (EOF when it dies) and has work to finish first."""
    if sig is not None and sys.platform.startswith("linux"):
        libc = ctypes.CDLL(None, use_errno=True)
        if libc.prctl(_PR_SET_PDEATHSIG, int(sig), 0, 0, 0) != 0:
            raise OSError(ctypes.get_errno(), "prctl(PR_SET_PDEATHSIG) failed")
    if os.getppid() != parent_pid:
        os._exit(0)


def lower_priority(niceness: int) -> None:
    """In a child: run ``niceness`` below the parent (the control process keeps the CPU)."""
    with contextlib.suppress(OSError):
        os.nice(niceness)


def descendants(pid: int) -> set[int]:
    """Every live process below ``pid`` (children, grandchildren), from /proc (Linux)."""
    children: dict[int, list[int]] = {}
    for stat in Path("/proc").glob("[0-9]*/stat"):
        try:
            text = stat.read_text()
        except OSError:  # gone meanwhile
            continue
        # pid (comm) state ppid ...: comm may hold spaces and parentheses
        fields = text[text.rindex(")") + 2 :].split()
        children.setdefault(int(fields[1]), []).append(int(stat.parent.name))
    out: set[int] = set()
    todo = [pid]
    while todo:
        for child in children.get(todo.pop(), []):
            if child not in out:
                out.add(child)
                todo.append(child)
    return out
