"""The log lines' pump (common/logpipe.py) with a real pump process and a real stderr pipe:
a log call never waits for stderr, every line is written whole or dropped and counted, what
was not dropped arrives, and a dead pump leaves lines going straight to stderr, never
waiting."""

from __future__ import annotations

import contextlib
import json
import logging
import os
import signal
import threading
import time
from typing import Any

from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from epc_offboard.common.logpipe import PIPE_BUF, PipeHandler

HOLD_S = 60.0  # a reader held back (nothing read) at most: a writer that waits meets it
# a log call's time asleep (off the CPU and off its run queue: a write blocked on a pipe,
# a lock waited for), at most; a blocking write sleeps the reader's pauses (up to 0.4 s).
# Its wall time is not judged: a preemption or steal at load is time queued, not waited
EMIT_BOUND_S = 0.1


class SlowReader:
    """The real stderr: a pipe read by a thread that pauses as ``pauses_s`` says."""

    def __init__(self, pauses_s: list[float], hold_s: float = 0.0) -> None:
        self.read_fd, self.write_fd = os.pipe()
        self.data = bytearray()
        self._pauses = list(pauses_s)
        # ``hold_s``: nothing read until :meth:`release` or ``hold_s``; ``held_to_bound``
        # says the bound released it (a writer waited for this reader, or never ended)
        self._hold_s = hold_s
        self._released = threading.Event()
        self.held_to_bound = False
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def release(self) -> None:
        self._released.set()

    def _run(self) -> None:
        if self._hold_s > 0.0:
            self.held_to_bound = not self._released.wait(self._hold_s)
        while True:
            if self._pauses:
                time.sleep(self._pauses.pop(0))
            chunk = os.read(self.read_fd, 8192)
            if not chunk:
                return
            self.data += chunk

    def finish(self, timeout_s: float = 30.0) -> list[bytes]:
        """Every line, once the last writer is gone (EOF)."""
        self._thread.join(timeout_s)
        assert not self._thread.is_alive(), "stderr never reached EOF"
        os.close(self.read_fd)
        return bytes(self.data).splitlines()


class AsleepClock:
    """The calling thread's time asleep so far, in s: wall time less its time on a CPU and
    queued for one (the kernel's ``/proc/thread-self/schedstat``). A blocking call sleeps;
    a thread preempted or starved by a loaded host is queued, not asleep."""

    def __init__(self) -> None:
        self._fd = os.open("/proc/thread-self/schedstat", os.O_RDONLY)

    def __call__(self) -> float:
        wall_ns = time.monotonic_ns()
        run_ns, queued_ns = os.pread(self._fd, 96, 0).split()[:2]
        return (wall_ns - int(run_ns) - int(queued_ns)) * 1e-9

    def close(self) -> None:
        os.close(self._fd)


def test_the_asleep_clock_counts_a_sleep_and_not_cpu() -> None:
    asleep = AsleepClock()
    try:
        t0 = asleep()
        time.sleep(0.2)
        slept = asleep() - t0
        t0 = asleep()
        end = time.thread_time() + 0.2
        while time.thread_time() < end:
            pass
        busy = asleep() - t0
    finally:
        asleep.close()
    assert slept >= 0.19, slept
    assert busy < 0.05, busy  # steal while running, at most (a few ms/s here)


def _logger(handler: logging.Handler, name: str) -> logging.Logger:
    log = logging.getLogger(name)
    log.handlers[:] = [handler]
    log.propagate = False
    log.setLevel(logging.DEBUG)
    handler.setFormatter(logging.Formatter("%(message)s"))
    return log


def _line(k: int, length: int) -> str:
    head = f"L{k:06d} "
    return head + "x" * max(0, length - len(head))


@settings(max_examples=8, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(
    bursts=st.lists(st.tuples(st.integers(1, 120), st.integers(1, 3 * PIPE_BUF)),
                    min_size=1, max_size=5),
    pauses_s=st.lists(st.floats(0.0, 0.4), min_size=1, max_size=6),
    gaps_s=st.lists(st.floats(0.0, 0.05), min_size=5, max_size=5),
)  # fmt: skip
def test_a_log_call_never_waits_and_lines_arrive_whole_or_are_counted(bursts, pauses_s, gaps_s):
    """Random bursts of lines (some longer than PIPE_BUF, sent in chunks), a reader of
    random speed: no log call waits longer than the bound; every line the reader gets is
    one that was sent, whole, in order; the reader gets exactly sent - dropped."""
    stderr = SlowReader(pauses_s)
    handler = PipeHandler(stderr_fd=stderr.write_fd, pipe_bytes=65536)
    handler.start()
    os.close(stderr.write_fd)  # the pump holds it now: EOF when the pump ends
    log = _logger(handler, "test.logpipe.property")
    sent: list[str] = []
    slowest_s = 0.0  # the longest a log call slept
    asleep = AsleepClock()
    try:
        for (count, length), gap_s in zip(bursts, gaps_s, strict=False):
            for _ in range(count):
                line = _line(len(sent), length)
                t0 = asleep()
                log.info(line)
                slowest_s = max(slowest_s, asleep() - t0)
                sent.append(line)
            time.sleep(gap_s)
    finally:
        asleep.close()
    handler.close()  # EOF to the pump: it writes what it holds and ends
    got = [g.decode() for g in stderr.finish()]
    assert slowest_s < EMIT_BOUND_S, slowest_s
    assert handler.lines + handler.dropped == len(sent)
    assert len(got) == handler.lines, (len(got), handler.lines, handler.dropped)
    index = {line: k for k, line in enumerate(sent)}
    order = [index[g] for g in got]  # KeyError: a line cut or garbled
    assert order == sorted(order)  # in order, each once


def test_lines_beyond_the_pipe_are_dropped_and_counted_then_the_rest_arrives():
    """Stderr not read at all while 4 MB of lines are logged: the calls return at once,
    what the pipes cannot hold is dropped and counted, and when stderr is read again
    every line not dropped arrives."""
    stderr = SlowReader([], hold_s=HOLD_S)  # nothing read until the calls are done
    handler = PipeHandler(stderr_fd=stderr.write_fd, pipe_bytes=65536)
    handler.start()
    os.close(stderr.write_fd)
    log = _logger(handler, "test.logpipe.full")
    for k in range(4000):
        log.warning(_line(k, 1000))
    stderr.release()
    # all 4000 returned while stderr was not read: none waited for it (a blocking write
    # returns only once the reader's bound lets it read). Before stop 41: < 0.9 s of wall
    # time against a 1 s pause, which the 4000 calls' own CPU passed at load 14-18
    assert not stderr.held_to_bound, "a log call waited for stderr's reader"
    assert handler.dropped > 0
    handler.close()
    got = stderr.finish()
    assert len(got) == handler.lines == 4000 - handler.dropped


def _kill_pump(handler: PipeHandler) -> int:
    """SIGKILL the pump (a real one), once it has written what it was sent; its pid."""
    pid = handler.pid()
    assert pid is not None
    assert handler._proc is not None
    deadline = time.monotonic() + 20.0  # the pump has read what went before (under load
    while handler.queued_bytes() and time.monotonic() < deadline:  # its start takes > 0.5 s)
        time.sleep(0.01)
    time.sleep(0.2)  # ... and written it
    os.kill(pid, signal.SIGKILL)
    handler._proc.wait(timeout=10)
    return pid


def _restarted(handler: PipeHandler, n: int, timeout_s: float = 10.0) -> None:
    """Wait until the handler's restarting thread has started its ``n``-th pump."""
    deadline = time.monotonic() + timeout_s
    while handler.restarts < n and time.monotonic() < deadline:
        time.sleep(0.01)
    assert handler.restarts == n, handler.restarts


def test_a_dead_pump_is_restarted_at_most_n_times_a_minute_then_lines_go_direct():
    """The pump SIGKILLed: the next line goes straight to stderr and a new pump is started
    on a new pipe (by the handler's thread), the restart counted and said once. Past
    ``restarts_per_min`` in a minute the lines go straight to stderr (said once), never
    waiting; every line arrives. Before, a dead pump was never restarted: every later
    line went straight to stderr."""
    read_fd, write_fd = os.pipe()
    handler = PipeHandler(stderr_fd=write_fd, pipe_bytes=65536, restarts_per_min=2)
    handler.start()
    log = _logger(handler, "test.logpipe.restart")
    pids = []
    for k in range(3):
        log.info("line %d", k)  # 1, 2: the pump found dead, a new one asked
        _restarted(handler, k)
        pids.append(_kill_pump(handler))
    log.info("line 3")  # the third death: straight to stderr
    log.info("last")
    assert handler.restarts == 2
    assert handler.pump_failed
    handler.close()
    os.close(write_fd)
    with os.fdopen(read_fd, "rb") as fh:
        lines = fh.read().decode().splitlines()
    assert len(set(pids)) == 3  # lines 0-2 each through a pump of its own, then direct
    assert [x for x in lines if x.startswith("line") or x == "last"] == [
        "line 0", "line 1", "line 2", "line 3", "last"]  # fmt: skip
    assert sum("died: restarted as process" in x for x in lines) == 1, lines
    assert sum("is not restarted now" in x for x in lines) == 1, lines


def test_a_dead_pump_is_restarted_off_the_thread_that_logs(monkeypatch):
    """The pump SIGKILLed while a thread logs (the loops' thread, in the service): the line
    that finds it dead goes straight to stderr, and the new pump is started (a vfork and
    exec) by the handler's own thread, never by the one that logs; lines after the
    restart go through the new pump, and every line arrives. Before, the thread that
    logged the line started the pump itself."""
    import subprocess

    started_on: list[str] = []
    popen = subprocess.Popen

    def spy(*args: Any, **kwargs: Any) -> Any:
        started_on.append(threading.current_thread().name)
        return popen(*args, **kwargs)

    monkeypatch.setattr(subprocess, "Popen", spy)  # logpipe's, the same module
    read_fd, write_fd = os.pipe()
    handler = PipeHandler(stderr_fd=write_fd, pipe_bytes=65536)
    handler.start()
    assert started_on == [threading.current_thread().name]  # the first: at start-up
    log = _logger(handler, "test.logpipe.offthread")
    first = handler.pid()
    call_ms: list[float] = []

    def loops() -> None:
        log.info("before")
        _kill_pump(handler)
        t0 = time.perf_counter()
        log.info("found dead")  # EPIPE: straight to stderr, a restart asked
        call_ms.append(1e3 * (time.perf_counter() - t0))
        _restarted(handler, 1)
        log.info("after")

    thread = threading.Thread(target=loops, name="loops")
    thread.start()
    thread.join(30.0)
    assert not thread.is_alive()
    print(f"the log call that found the pump dead: {call_ms[0]:.2f} ms")
    assert handler.pid() not in (None, first)
    assert not handler.pump_failed
    assert len(started_on) == 2, started_on
    assert started_on[1] == "log-pump-restart", started_on  # not "loops"
    handler.close()
    os.close(write_fd)
    with os.fdopen(read_fd, "rb") as fh:
        lines = fh.read().decode().splitlines()
    assert [x for x in lines if x in ("before", "found dead", "after")] == [
        "before", "found dead", "after"]  # fmt: skip
    assert sum("died: restarted as process" in x for x in lines) == 1, lines


def test_a_dead_pump_leaves_lines_going_straight_to_stderr_never_waiting():
    """The pump SIGKILLed, no restart allowed: the next line is written to stderr directly
    (a non-blocking open of the same pipe), with one warning saying so; a full stderr then
    drops lines, counted, and the call still returns at once."""
    read_fd, write_fd = os.pipe()
    handler = PipeHandler(stderr_fd=write_fd, pipe_bytes=65536, restarts_per_min=0)
    handler.start()
    log = _logger(handler, "test.logpipe.dead")
    log.info("before")
    _kill_pump(handler)
    log.info("after")  # EPIPE: straight to stderr
    assert handler.pump_failed
    os.set_blocking(read_fd, False)
    lines = os.read(read_fd, 1 << 16).decode().splitlines()
    assert lines[0] == "before"
    assert lines[-1] == "after"
    assert sum("log pump (process" in line and "not restarted" in line for line in lines) == 1
    # nobody reads stderr now: lines fill it, then drop; no call waits (a blocking write
    # would never return: no one reads; the thread's bound is the test's, not a figure)
    def flood() -> None:
        for k in range(300):
            log.info(_line(k, 1000))

    logger = threading.Thread(target=flood, daemon=True)
    logger.start()
    logger.join(HOLD_S)
    stuck = logger.is_alive()
    if stuck:  # let it end: read what it waits to write
        with contextlib.suppress(BlockingIOError):
            while logger.is_alive():
                os.read(read_fd, 1 << 16)
    assert not stuck, "a log call waited for stderr"
    assert handler.dropped > 0
    assert handler.lines + handler.dropped == 302
    handler.close()
    os.close(write_fd)
    os.close(read_fd)


def test_the_root_loggers_level_still_decides(tmp_path):
    """SIGHUP sets the root logger's level (service._reload_from): the handler passes what
    the level lets through, as StreamHandler did."""
    read_fd, write_fd = os.pipe()
    handler = PipeHandler(stderr_fd=write_fd, pipe_bytes=65536)
    handler.start()
    log = _logger(handler, "test.logpipe.level")
    log.setLevel(logging.INFO)
    log.debug("hidden")
    log.setLevel(logging.DEBUG)
    log.debug("shown")
    handler.close()
    os.close(write_fd)
    with os.fdopen(read_fd, "rb") as fh:
        assert fh.read().decode().splitlines() == ["shown"]


def test_pipe_stderr_takes_the_root_loggers_stream_and_pythons_warnings(tmp_path):
    """``pipe_stderr`` (the run command's): the root's StreamHandler replaced, its format
    kept, and a Python warning (printed to stderr by a blocking write) logged through the
    pump instead."""
    import subprocess
    import sys

    code = (
        "import logging, warnings\n"
        "from epc_offboard.common.logsetup import LogConfig, setup_logging\n"
        "from epc_offboard.common import logpipe\n"
        "setup_logging(LogConfig(format='json'))\n"
        "handler = logpipe.pipe_stderr()\n"
        "assert logging.getLogger().handlers == [handler]\n"
        "logging.getLogger('x').info('hello')\n"
        "warnings.warn('careful', RuntimeWarning)\n"
        "print(handler.pid())\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         timeout=60, check=True)  # fmt: skip
    pump_pid = int(out.stdout.strip())
    lines = [json.loads(line) for line in out.stderr.splitlines()]
    assert (lines[0]["logger"], lines[0]["msg"]) == ("x", "hello")
    assert lines[1]["logger"] == "py.warnings"
    assert "careful" in lines[1]["msg"]
    assert pump_pid != 0


def test_a_helper_whose_stderr_is_held_logs_without_waiting_and_works_on(tmp_path):
    """A helper process (here the store writer, a real spawned one) whose stderr nobody
    reads (journald held): each failed save's error line is dropped, never waited for, and
    the saves go on; the drops are counted in the helper's ``process_report`` (the stats'
    ``processes.store.log_dropped``). Before, the first line blocked the helper in its write
    for good; then the drops were counted in the helper alone."""
    import multiprocessing

    import numpy as np

    from epc_offboard.common.channel import write_frame
    from epc_offboard.common.children import spawn_fed
    from epc_offboard.common.logsetup import LogConfig
    from epc_offboard.common.procstats import process_report
    from epc_offboard.store.process import ERRORS, store_main

    read_fd, write_fd = os.pipe()
    os.set_blocking(write_fd, False)
    with contextlib.suppress(BlockingIOError):  # stderr full: nobody reads it
        while True:
            os.write(write_fd, b"x" * 4096)
    os.set_blocking(write_fd, True)
    slots = multiprocessing.get_context("spawn").RawArray("q", 2)
    counts = np.frombuffer(slots, dtype=np.int64)
    saved_fd = os.dup(2)
    os.dup2(write_fd, 2)  # the helper's stderr, inherited at its start
    try:
        proc, conn = spawn_fed(store_main, "epc-store", str(tmp_path / "lib.db"), slots,
                               LogConfig())  # fmt: skip
    finally:
        os.dup2(saved_fd, 2)
        os.close(saved_fd)
        os.close(write_fd)
    try:
        for _ in range(50):  # each one fails to save and logs an error line
            write_frame(conn.fileno(), "not a snapshot")
        t0 = time.monotonic()
        while counts[ERRORS] < 50 and time.monotonic() - t0 < 60.0:
            time.sleep(0.05)
        assert counts[ERRORS] == 50  # every save tried, none held by stderr
        # its lines dropped are counted where the service's stats read them (processes.store)
        report = process_report(proc.pid)
        assert report["log_dropped"] >= 50, report
        assert report["log_lines"] == 0, report  # stderr full from the start
        conn.close()  # EOF: the helper ends
        proc.join(30.0)
        assert proc.exitcode == 0
    finally:
        if proc.is_alive():
            proc.kill()
            proc.join(10.0)
        os.close(read_fd)


def test_close_waits_for_a_held_pump_only_until_the_stops_deadline():
    """At exit the handler waits for the pump to write out what is queued, but not past
    ``close_by``'s deadline (the service's stop bound): with stderr held full the pump
    cannot finish, and close returns at the deadline, not after its own 2 s. The pump
    ends by itself once stderr is read again (EOF), every line written."""
    read_fd, write_fd = os.pipe()
    os.set_blocking(write_fd, False)
    filled = 0
    with contextlib.suppress(BlockingIOError):  # stderr full: nobody reads it
        while True:
            filled += os.write(write_fd, b"#" * 4095 + b"\n")
    os.set_blocking(write_fd, True)
    handler = PipeHandler(stderr_fd=write_fd, pipe_bytes=65536)
    handler.start()
    os.close(write_fd)
    log = _logger(handler, "test.logpipe.close_by")
    log.warning("queued behind a held stderr")
    proc = handler._proc
    assert proc is not None
    handler.close_by(time.monotonic() + 0.2)
    t0 = time.monotonic()
    handler.close()
    took_s = time.monotonic() - t0
    assert took_s < 1.5, took_s  # the deadline (load 6); on its own the wait was 2 s
    assert proc.poll() is None  # the pump is still held, writing after we are gone
    with os.fdopen(read_fd, "rb") as fh:  # stderr read again: the pump ends at EOF
        data = fh.read()
    assert proc.wait(timeout=30) == 0
    assert data[filled:].decode().splitlines() == ["queued behind a held stderr"]
