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
import fcntl
import multiprocessing
import multiprocessing.context
import multiprocessing.process
import os
import signal
import sys
from collections.abc import Callable
from multiprocessing.connection import Connection
from pathlib import Path
from typing import Any

from epc_offboard.common.procstats import register_log_counts, stat_fields

_PR_SET_PDEATHSIG = 1  # <linux/prctl.h>
_F_SETPIPE_SZ = 1031  # <linux/fcntl.h>


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


LAUNCHER_ENV = "EPC_OFFBOARD_LAUNCHER_PID"  # set by `sim` for the SITLs and services it starts


def launched_env() -> dict[str, str]:
    """The environment entry a launcher (`sim`) gives the SITLs and services it starts, so that
    they end with it (:func:`die_with_launcher`)."""
    return {LAUNCHER_ENV: str(os.getpid())}


def die_with_launcher() -> None:
    """In a SITL or service started by `sim`: SIGTERM (a clean stop: the service holds and
    saves its library) when `sim` dies, even SIGKILLed, so that a killed `sim` (a test's
    timeout, an OOM kill) leaves no vehicle flying; it left both before. Nothing when started
    otherwise (systemd, a shell): then no launcher's pid is in the environment. Call from the
    main thread, first thing."""
    pid = os.environ.pop(LAUNCHER_ENV, "")
    if pid.isdigit():
        die_with_parent(int(pid), signal.SIGTERM)


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
        children.setdefault(int(stat_fields(text)[1]), []).append(int(stat.parent.name))
    out: set[int] = set()
    todo = [pid]
    while todo:
        for child in children.get(todo.pop(), []):
            if child not in out:
                out.add(child)
                todo.append(child)
    return out


class Backoff:
    """When to restart a helper that died: ``first_s`` after its first death, twice as long
    after each next one, at most ``max_s``; a helper that has lived ``max_s`` starts over."""

    def __init__(self, first_s: float = 1.0, max_s: float = 30.0) -> None:
        self.first_s = first_s
        self.max_s = max_s
        self.wait_s = first_s
        self.restart_at_s: float | None = None  # time.monotonic() of the next restart

    def failed(self, now_s: float) -> float:
        """A death at ``now_s``: schedules the restart; returns the wait."""
        wait = self.wait_s
        self.restart_at_s = now_s + wait
        self.wait_s = min(2.0 * wait, self.max_s)
        return wait

    def due(self, now_s: float) -> bool:
        """Whether the scheduled restart is due (then it is no longer scheduled)."""
        if self.restart_at_s is None or now_s < self.restart_at_s:
            return False
        self.restart_at_s = None
        return True

    def lived(self, age_s: float) -> None:
        if age_s > self.max_s:
            self.wait_s = self.first_s


# a SIGKILLed child waited for this long at most (it is reaped in milliseconds; one in a
# disk wait dies when the wait ends): the service's stop stays within its bound
KILL_WAIT_S = 0.2


def join_or_kill(
    proc: multiprocessing.process.BaseProcess, timeout_s: float,
    reap_s: float | None = KILL_WAIT_S,
) -> bool:
    """Wait ``timeout_s`` for ``proc`` to end; one still running then (wedged, SIGSTOPped,
    deaf to SIGTERM) is SIGKILLed and waited for ``reap_s`` more (None: until it is reaped;
    SIGKILL ends a stopped process too). Whether it ended by itself, in time."""
    proc.join(timeout=max(0.0, timeout_s))
    if proc.exitcode is not None:
        return True
    proc.kill()
    proc.join(timeout=None if reap_s is None else max(0.0, reap_s))
    return False


def enlarge_pipe(conn: Connection, nbytes: int) -> None:
    """Make the pipe under ``conn`` hold ``nbytes`` (Linux ``F_SETPIPE_SZ``; elsewhere, or
    above the system's ceiling, it keeps its size)."""
    with contextlib.suppress(OSError):
        fcntl.fcntl(conn.fileno(), _F_SETPIPE_SZ, nbytes)


def start_counted(
    ctx: multiprocessing.context.SpawnContext, target: Callable[..., None],
    args: tuple[Any, ...], name: str,
) -> multiprocessing.process.BaseProcess:
    """``target(*args)`` started in a daemon process of ``ctx`` named ``name``, its log lines
    (``logpipe.direct_stderr``'s handler) counted in memory shared with this process: in
    its ``process_report`` as ``log_lines`` and ``log_dropped``, summed over the processes
    of that ``name`` (a restarted helper's)."""
    counts = ctx.RawArray("q", 2)
    proc = ctx.Process(target=_counted, args=(target, counts, *args), name=name, daemon=True)
    proc.start()
    assert proc.pid is not None
    register_log_counts(proc.pid, counts, name)
    return proc


def _counted(target: Callable[..., None], counts: Any, *args: Any) -> None:
    from epc_offboard.common import logpipe

    # Ctrl-C in a terminal goes to the whole process group: the service stops its helpers
    # itself (EOF, the parent-death signal), so a helper's KeyboardInterrupt was only a
    # traceback on the user's terminal (the miss worker's, the fleet helper's)
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    logpipe.count_into(counts)
    target(*args)


def spawn_fed(
    target: Callable[..., None], name: str, *args: object, pipe_bytes: int = 0
) -> tuple[multiprocessing.process.BaseProcess, Connection]:
    """Start ``target(read_end, parent_pid, *args)`` in a ``spawn``-ed daemon process named
    ``name``, fed through a pipe; returns the process and the pipe's writing end (closing
    it is the child's EOF). ``pipe_bytes``: enlarge the pipe (Linux ``F_SETPIPE_SZ``)."""
    ctx = multiprocessing.get_context("spawn")  # no fork of a threaded process
    read, write = ctx.Pipe(duplex=False)
    if pipe_bytes:
        enlarge_pipe(write, pipe_bytes)
    proc = start_counted(ctx, target, (read, os.getpid(), *args), name)
    read.close()  # the child's end: ours closed, its death is EOF for nobody but it
    return proc, write
