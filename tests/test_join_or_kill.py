"""``children.join_or_kill``: the one join → SIGKILL → join of every helper's stop (the store,
the log writer, the miss worker, the fleet helper), with real processes: one that ends by
itself, one deaf to SIGTERM, one SIGSTOPped (a helper wedged or starved)."""

from __future__ import annotations

import multiprocessing
import os
import signal
import threading
import time
from pathlib import Path
from typing import Any

import pytest

from epc_offboard.common.children import join_or_kill

pytestmark = pytest.mark.timeout(60)



def _pid(proc: Any) -> int:
    """A started process's pid (``Process.pid`` is typed optional: None before start)."""
    assert proc.pid is not None
    return int(proc.pid)

def _deaf_to_sigterm(ready) -> None:
    signal.signal(signal.SIGTERM, signal.SIG_IGN)
    ready.send(True)
    while True:
        time.sleep(1.0)


def _ends(code: int) -> None:
    raise SystemExit(code)


def _started(target, *args):
    ctx = multiprocessing.get_context("spawn")
    proc = ctx.Process(target=target, args=args, daemon=True)
    proc.start()
    return proc


def _deaf() -> multiprocessing.process.BaseProcess:
    ctx = multiprocessing.get_context("spawn")
    read, write = ctx.Pipe(duplex=False)
    proc = ctx.Process(target=_deaf_to_sigterm, args=(write,), daemon=True)
    proc.start()
    assert read.poll(30.0), "the child did not start"  # its SIGTERM ignored from here
    os.kill(_pid(proc), signal.SIGTERM)
    return proc


def _gone(pid: int) -> bool:
    """Reaped: no /proc entry at all (a zombie keeps one, state Z)."""
    return not Path(f"/proc/{pid}").exists()


def test_a_child_that_ends_by_itself_is_joined_and_not_killed():
    proc = _started(_ends, 3)
    assert join_or_kill(proc, 30.0)
    assert proc.exitcode == 3  # its own exit, not SIGKILL's
    assert _gone(_pid(proc))


@pytest.mark.parametrize("wedge", ["deaf to SIGTERM", "SIGSTOPped"])
def test_a_child_that_does_not_end_is_killed_and_reaped_within_the_bound(wedge):
    proc = _deaf()
    if wedge == "SIGSTOPped":
        os.kill(_pid(proc), signal.SIGSTOP)
    assert proc.pid is not None
    t0 = time.monotonic()
    assert not join_or_kill(proc, 0.1, reap_s=30.0)
    took_s = time.monotonic() - t0
    assert proc.exitcode == -signal.SIGKILL
    assert _gone(_pid(proc)), "a zombie left"  # reaped in the call, no zombie
    print(f"{wedge}: killed and reaped {took_s - 0.1:.3f} s after the timeout")


def test_the_reap_wait_is_bounded():
    """``reap_s`` 0: killed, not waited for (the service's stop at its bound); reaped later."""
    proc = _deaf()
    os.kill(_pid(proc), signal.SIGSTOP)
    assert not join_or_kill(proc, 0.0, reap_s=0.0)
    proc.join(30.0)  # SIGKILL ends a stopped process: it was sent
    assert proc.exitcode == -signal.SIGKILL
    assert _gone(_pid(proc))


def test_a_killed_child_reaped_on_a_thread_of_its_own():
    """The fleet helper's failure path: kill and reap off the loops' thread (reap_s None)."""
    proc = _deaf()
    os.kill(_pid(proc), signal.SIGSTOP)
    reaper = threading.Thread(target=join_or_kill, args=(proc, 0.0, None), daemon=True)
    reaper.start()
    reaper.join(30.0)
    assert not reaper.is_alive()
    assert proc.exitcode == -signal.SIGKILL
    assert _gone(_pid(proc))

