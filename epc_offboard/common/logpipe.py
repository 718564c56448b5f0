"""The control process's log lines, written to stderr by a process of their own (issue 21).

A ``logging.StreamHandler(sys.stderr)`` formats each line on the thread that logs it and
writes it with a blocking ``write(2)``: on the loops' thread that write waits whenever
stderr does. Under systemd stderr is a stream socket to journald, which stops reading while
journald is slow, restarting or waiting on its disk (coreos/bugs#990, systemd#20473: services
blocked in their log writes); under a bench or a supervisor it may be a pipe nobody drains.
One such write held the loops' thread 107 ms (stop 36: asleep after one voluntary switch).

:class:`PipeHandler` (a ``logging.Handler``: the level, format and JSON configuration, and
SIGHUP's level change on the root logger, are unchanged) formats the line and writes it to a
pipe, never blocking: a line is sent in chunks of at most ``PIPE_BUF`` bytes, each written
whole (atomic) or not at all; when the pipe is full the line is dropped and counted
(``dropped``), and a line cut after its first chunk is dropped whole by the reader. The
reader is the pump (:func:`pump`, ``python -m epc_offboard.common.logpipe``): a small process
of the standard library alone (no numpy, no service imports: up in tens of ms) that copies
whole lines to the real stderr, blocking there as long as stderr blocks, ``nice`` +10. The
pipe is enlarged to 1 MiB where permitted: seconds of logs wait in it while stderr is held.

The pump ends at EOF, after writing every line the pipe held: when the service closes its
end at exit (:meth:`PipeHandler.close`, from ``logging.shutdown``: it waits a bounded time
for the pump, no later than :meth:`PipeHandler.close_by`'s deadline, the stop's), or dies
(SIGKILL included). It ignores SIGTERM and SIGINT, which a stop sends
to the whole group. If the pump dies (its pipe says EPIPE) a new one is started with a new
pipe by a thread of the handler's own (``log-pump-restart``, started with the first pump):
at most ``_RESTARTS_PER_MIN`` restarts in any minute, counted (``restarts``), the first
said in a log line. Until the new pump is up, beyond that many, and while no pump can
start, lines go straight to stderr, never blocking (a new non-blocking open of the same
pipe or tty, ``MSG_DONTWAIT`` on a socket; a regular file as it is), dropped and counted
when it is full; said once, and the loops fly on; a restart is asked again once the
minute allows. A pump's start is a ``vfork`` and ``exec`` (the new interpreter comes up in
the child): never on the thread that logs, which may be the loops' (it only wakes the
restarting thread).
Before :func:`pipe_stderr` (the start-up, a config error) lines go to stderr as they always
did. The helper processes (fleet helper, miss worker, store and log writers) write their
lines straight to stderr through :class:`DirectHandler` (:func:`direct_stderr`): never
blocking, a line whole or dropped and counted, so a stderr held by journald stalls none of
their work (the fleet helper's session, the miss worker's solves) either.
"""

from __future__ import annotations

import contextlib
import errno
import fcntl
import logging
import math
import os
import select
import signal
import socket
import stat
import struct
import subprocess
import sys
import termios
import threading
import time
from collections import deque
from typing import Any

PIPE_BUF = select.PIPE_BUF  # writes up to this size are atomic
_CHUNK = struct.Struct("<HB")  # payload bytes, flags
_FIRST, _LAST = 1, 2
_BODY = PIPE_BUF - _CHUNK.size  # the most of a line one atomic write carries
_PIPE_BYTES = 1 << 20
_F_SETPIPE_SZ = 1031  # <linux/fcntl.h>
_NICE = 10
_CLOSE_WAIT_S = 2.0  # at exit, the pump's time to write out what is queued (stderr may hold it)
_RESTARTS_PER_MIN = 3  # a dead pump is restarted at most this often in any 60 s
_RESTART_WINDOW_S = 60.0


class DirectStderr:
    """Stderr written without ever blocking, for when the pump is gone: a line is written
    whole or dropped (the caller counts). A pipe, FIFO or tty is opened anew, non-blocking
    (``O_NONBLOCK`` on fd 2 itself would change it for every process sharing it); a socket
    (journald) is sent to with ``MSG_DONTWAIT``; a regular file is written as it is."""

    def __init__(self, fd: int = 2) -> None:
        self._fd = fd
        self._own_fd: int | None = None
        self._sock: socket.socket | None = None
        mode = os.fstat(fd).st_mode
        if stat.S_ISSOCK(mode):
            self._sock = socket.socket(fileno=os.dup(fd))
        elif not stat.S_ISREG(mode):
            with contextlib.suppress(OSError):  # no /proc: poll before each write instead
                self._own_fd = os.open(f"/proc/self/fd/{fd}",
                                       os.O_WRONLY | os.O_NONBLOCK | os.O_CLOEXEC)  # fmt: skip
        self._regular = stat.S_ISREG(mode)

    def write(self, data: bytes) -> bool:
        """All of ``data`` written now (True), or none of it and False. A line over
        ``PIPE_BUF`` may be cut when the reader falls behind in it (then a newline ends it)."""
        try:
            if self._sock is not None:
                sent = self._sock.send(data, socket.MSG_DONTWAIT)
            elif self._regular:
                sent = os.write(self._fd, data)
            elif self._own_fd is not None:
                sent = os.write(self._own_fd, data)
            else:
                _, ready, _ = select.select([], [self._fd], [], 0.0)
                if not ready:
                    return False
                sent = os.write(self._fd, data[:PIPE_BUF])
        except (BlockingIOError, InterruptedError):
            return False
        except OSError:  # stderr closed, or gone (EPIPE): nothing to write to
            return False
        if sent < len(data):  # a partial write of a long line: end it where it stopped
            if sent:
                self.write(b" [cut]\n")
            return False
        return True

    def close(self) -> None:
        if self._sock is not None:
            self._sock.close()
            self._sock = None
        if self._own_fd is not None:
            os.close(self._own_fd)
            self._own_fd = None


_counts_into: Any = None  # a helper's log lines counted here (shared with the service)


def count_into(counts: Any) -> None:
    """This process's :func:`direct_stderr` counts its lines in ``counts`` (two int64
    shared with the service: written, dropped; ``children.start_counted``)."""
    global _counts_into
    _counts_into = counts


class DirectHandler(logging.Handler):
    """A helper process's log lines written to stderr with :class:`DirectStderr`: never
    waiting, a line whole or dropped (``dropped``; ``lines`` written). ``counts``: where
    they are counted (two int64: written, dropped; shared with the service, which reports
    them); none: here."""

    def __init__(self, stderr_fd: int = 2, counts: Any = None) -> None:
        super().__init__()
        self._stderr_fd = stderr_fd
        self._direct: DirectStderr | None = None
        self._counts = counts if counts is not None else [0, 0]

    @property
    def lines(self) -> int:
        return int(self._counts[0])

    @lines.setter
    def lines(self, n: int) -> None:
        self._counts[0] = n

    @property
    def dropped(self) -> int:
        return int(self._counts[1])

    @dropped.setter
    def dropped(self, n: int) -> None:
        self._counts[1] = n

    def emit(self, record: logging.LogRecord) -> None:
        try:
            data = (self.format(record) + "\n").encode("utf-8", "backslashreplace")
        except RecursionError:
            raise
        except Exception:
            self.handleError(record)
            return
        if self._write(data):
            self.lines += 1
        else:
            self.dropped += 1

    def handleError(self, record: logging.LogRecord) -> None:  # noqa: N802 (logging's name)
        """A line that could not be formatted is dropped and counted: logging's default
        prints a traceback to stderr, a blocking write."""
        self.dropped += 1

    def _write(self, data: bytes) -> bool:
        return self._write_direct(data)

    def _write_direct(self, data: bytes) -> bool:
        if self._direct is None:
            try:
                self._direct = DirectStderr(self._stderr_fd)
            except OSError:  # no stderr at all (closed): the line is dropped, counted
                return False
        return self._direct.write(data)

    def close(self) -> None:
        self.acquire()
        try:
            if self._direct is not None:
                self._direct.close()
                self._direct = None
        finally:
            self.release()
        super().close()


class PipeHandler(DirectHandler):
    """Log lines formatted here and written to the pump's pipe, never blocking (module
    docstring). Counts: ``lines`` written to the pipe (or to stderr directly after the
    pump's death), ``dropped`` lines lost to a full pipe or stderr, ``restarts`` of a dead
    pump (at most ``restarts_per_min`` in any minute); ``pump_failed``: lines go straight to
    stderr now (no pump)."""

    def __init__(self, stderr_fd: int = 2, pipe_bytes: int = _PIPE_BYTES,
                 restarts_per_min: int = _RESTARTS_PER_MIN) -> None:  # fmt: skip
        super().__init__(stderr_fd)
        self._pipe_bytes = pipe_bytes
        self._restarts_per_min = restarts_per_min
        self._proc: subprocess.Popen[bytes] | None = None
        self._dead: list[subprocess.Popen[bytes]] = []  # pumps that died, until reaped
        self._fd: int | None = None  # the pipe's writing end (non-blocking)
        self._restarted_s: deque[float] = deque()  # the restarts' times (monotonic), last 60 s
        self._said: set[str] = set()  # the pump's fate, said once each
        self._close_by_s = math.inf  # close() waits for the pump until then at the latest
        self._restarter: threading.Thread | None = None  # starts a dead pump's successor
        self._restart_asked = threading.Event()
        self._restart_pending = False  # asked, not yet done (under the handler's lock)
        self._died_pid: int | None = None  # the last pump that died
        self._closed = False
        self.restarts = 0
        self.pump_failed = False

    def start(self) -> None:
        """Start the pump (OSError if it cannot be started: then stay with stderr), and the
        thread that restarts it should it die."""
        self._proc, self._fd = self._spawn()
        if self._restarter is None:
            self._restarter = threading.Thread(target=self._restart_loop, daemon=True,
                                               name="log-pump-restart")  # fmt: skip
            self._restarter.start()

    def _spawn(self) -> tuple[subprocess.Popen[bytes], int]:
        """A new pump reading a new pipe: the process and the pipe's (non-blocking) end."""
        read, write = os.pipe()
        with contextlib.suppress(OSError):  # above the system's ceiling: the default 64 KiB
            fcntl.fcntl(write, _F_SETPIPE_SZ, self._pipe_bytes)
        try:
            proc = subprocess.Popen(
                [sys.executable, "-m", "epc_offboard.common.logpipe"], stdin=read,
                stdout=subprocess.DEVNULL, stderr=self._stderr_fd, close_fds=True,
            )  # fmt: skip
        except BaseException:
            os.close(write)
            raise
        finally:
            os.close(read)
        os.set_blocking(write, False)
        return proc, write

    def pid(self) -> int | None:
        return self._proc.pid if self._proc is not None else None

    def _write(self, data: bytes) -> bool:
        fd = self._fd
        if fd is None and self.pump_failed and not self._restart_pending:
            self._ask_restart()  # a later minute may allow one
        if fd is None:
            return self._write_direct(data)
        last = len(data) - 1
        for at in range(0, len(data), _BODY):  # a long line (a traceback) in atomic chunks
            piece = data[at : at + _BODY]
            flags = (_FIRST if at == 0 else 0) | (_LAST if at + _BODY > last else 0)
            try:
                os.write(fd, _CHUNK.pack(len(piece), flags) + piece)
            except BlockingIOError:  # the pump fell behind: drop (a cut line: whole)
                return False
            except OSError:  # EPIPE: the pump is gone (a line it cut is dropped whole)
                self._pump_died()
                return self._write_direct(data)  # and the next ones, until the new pump
        return True

    def _pump_died(self) -> None:
        """The pump is gone: lines go straight to stderr (``pump_failed``) and a new pump
        is asked of the restarting thread if the minute allows (:meth:`_ask_restart`)."""
        assert self._fd is not None
        os.close(self._fd)
        self._fd = None
        self._died_pid = self.pid()
        if self._proc is not None:
            self._dead.append(self._proc)
            self._proc = None
        self._dead = [p for p in self._dead if p.poll() is None]  # the dead ones reaped
        self.pump_failed = True
        if not self._ask_restart():
            self._say("direct", "log pump (process %s) died and is not restarted now (%d "
                      "restarts in the last minute): log lines go straight to stderr, never "
                      "waiting for it (dropped and counted when it is full); flying on",
                      self._died_pid, len(self._restarted_s))  # fmt: skip

    def _ask_restart(self) -> bool:
        """Wake the restarting thread if fewer than ``restarts_per_min`` pumps started in
        the last minute (the ask counts against it: a start that fails too); False if the
        minute allows none now. Called under the handler's lock, on the thread that logs:
        no process is started here."""
        now = time.monotonic()
        while self._restarted_s and now - self._restarted_s[0] >= _RESTART_WINDOW_S:
            self._restarted_s.popleft()
        if self._closed or len(self._restarted_s) >= self._restarts_per_min:
            return False
        self._restarted_s.append(now)
        self._restart_pending = True
        self._restart_asked.set()
        return True

    def _restart_loop(self) -> None:
        """The ``log-pump-restart`` thread: each ask, a new pump and pipe started here (the
        handler's lock not held meanwhile: lines go straight to stderr), then handed to the
        handler under its lock."""
        while True:
            self._restart_asked.wait()
            self._restart_asked.clear()
            if self._closed:
                return
            try:
                proc, fd = self._spawn()
            except OSError:
                proc = None
            self.acquire()
            try:
                self._restart_pending = False
                if proc is None:
                    continue  # stays direct; the next line asks again when the minute allows
                if self._closed:  # closed meanwhile: EOF ends the new pump at once
                    os.close(fd)
                    self._dead.append(proc)
                    return
                self._proc, self._fd = proc, fd
                self.restarts += 1
                self.pump_failed = False
                self._say("restarted", "log pump (process %s) died: restarted as process %s "
                          "(at most %d restarts a minute, counted; said once)",
                          self._died_pid, proc.pid, self._restarts_per_min)  # fmt: skip
            finally:
                self.release()

    def _say(self, key: str, msg: str, *args: object) -> None:
        """One line about the pump's fate, once per ``key``, formatted as every line is:
        through the new pump, or straight to stderr when there is none."""
        if key in self._said:
            return
        self._said.add(key)
        line = logging.LogRecord("epc_offboard.service", logging.WARNING, __file__, 0, msg,
                                 args, None)  # fmt: skip
        data = (self.format(line) + "\n").encode("utf-8", "backslashreplace")
        if self._fd is None or not self._write(data):
            self._write_direct(data)

    def queued_bytes(self) -> int | None:
        """Bytes waiting in the pipe for the pump (FIONREAD on the writing end)."""
        if self._fd is None:
            return None
        with contextlib.suppress(OSError):
            raw = fcntl.ioctl(self._fd, termios.FIONREAD, b"\0\0\0\0")
            return int(struct.unpack("i", raw)[0])
        return None

    def close_by(self, deadline_s: float) -> None:
        """:meth:`close` waits for the pump until ``deadline_s`` (``time.monotonic``) at the
        latest: the service's stop ends within its bound however long stderr holds the pump."""
        self._close_by_s = deadline_s

    def close(self) -> None:
        """At exit (``logging.shutdown``): EOF to the pump, which writes out every line the
        pipe holds; waited for at most ``_CLOSE_WAIT_S``, and not past :meth:`close_by`'s
        deadline (a stderr that blocks keeps it writing after we are gone: it ignores the
        stop's SIGTERM and ends at EOF)."""
        self.acquire()
        try:
            self._closed = True
            self._restart_asked.set()  # the restarting thread ends (a pump it starts: EOF)
            fd, self._fd = self._fd, None
            if fd is not None:
                os.close(fd)
            wait_s = max(0.0, min(_CLOSE_WAIT_S, self._close_by_s - time.monotonic()))
            if self._proc is not None:
                with contextlib.suppress(subprocess.TimeoutExpired):
                    self._proc.wait(wait_s)
            for dead in self._dead:
                dead.poll()
        finally:
            self.release()
        super().close()  # the direct stderr, if the pump's death opened it


def pipe_stderr() -> PipeHandler | None:
    """The root logger's stderr handler replaced by a :class:`PipeHandler` with its
    formatter, and the pump started (the control process, after ``setup_logging``). None,
    and stderr kept, if the pump cannot start (said in a log line)."""
    root = logging.getLogger()
    handler = PipeHandler()
    old = [h for h in root.handlers if isinstance(h, logging.StreamHandler)]
    if old:
        handler.setFormatter(old[0].formatter)
    try:
        handler.start()
    except OSError as exc:
        logging.getLogger("epc_offboard.service").warning(
            "log pump not started (%s): log lines written to stderr directly", exc
        )
        return None
    for h in old:
        root.removeHandler(h)
    root.addHandler(handler)
    # Python's warnings (a numpy RuntimeWarning in a tick) are printed to stderr by
    # ``warnings.showwarning``, a blocking write: through the pump too, once per place
    logging.captureWarnings(True)
    return handler


def direct_stderr(level: int | None = None) -> DirectHandler:
    """A helper process's root logger writes to stderr without ever blocking: its stderr
    handlers (``setup_logging``'s) replaced by a :class:`DirectHandler` with their
    formatter (none: the human format, and ``level``, for a process that set up no
    logging), Python's warnings through it too."""
    from epc_offboard.common.logsetup import HUMAN_FORMAT

    root = logging.getLogger()
    handler = DirectHandler(counts=_counts_into)
    old = [h for h in root.handlers if isinstance(h, logging.StreamHandler)]
    handler.setFormatter(old[0].formatter if old else logging.Formatter(HUMAN_FORMAT))
    for h in old:
        root.removeHandler(h)
    root.addHandler(handler)
    if level is not None:
        root.setLevel(level)
    logging.captureWarnings(True)
    return handler


def installed() -> PipeHandler | None:
    """The root logger's :class:`PipeHandler`, if :func:`pipe_stderr` put one there."""
    return next((h for h in logging.getLogger().handlers if isinstance(h, PipeHandler)), None)


def stats(handler: PipeHandler | None) -> dict[str, Any]:
    """The pump as ``stats.processes`` gives it (pid, CPU, the pipe's queue, lines, drops)."""
    from epc_offboard.common.procstats import process_report

    if handler is None:
        return {}
    return process_report(handler.pid(), queued_bytes=handler.queued_bytes(),
                          lines=handler.lines, dropped=handler.dropped,
                          restarts=handler.restarts,
                          pump_failed=handler.pump_failed)  # fmt: skip


# -- the pump ----------------------------------------------------------------------------


def pump(fd_in: int = 0, fd_out: int = 2) -> None:
    """Whole lines from the pipe to stderr until EOF, blocking on stderr as long as it
    blocks; a line whose later chunk was dropped is dropped whole."""
    signal.signal(signal.SIGTERM, signal.SIG_IGN)  # a stop of the group: EOF ends us
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    with contextlib.suppress(OSError):
        os.nice(_NICE)
    buf = bytearray()
    line = bytearray()
    open_line = False
    while True:
        try:
            chunk = os.read(fd_in, 1 << 16)
        except InterruptedError:
            continue
        if not chunk:
            break
        buf += chunk
        out = bytearray()
        at = 0
        while len(buf) - at >= _CHUNK.size:
            n, flags = _CHUNK.unpack_from(buf, at)
            if len(buf) - at < _CHUNK.size + n:
                break
            piece = buf[at + _CHUNK.size : at + _CHUNK.size + n]
            at += _CHUNK.size + n
            if flags & _FIRST:
                line.clear()  # one left open: its rest was dropped
                open_line = True
            if open_line:
                line += piece
                if flags & _LAST:
                    out += line
                    line.clear()
                    open_line = False
        del buf[:at]
        if out and not _write_all(fd_out, bytes(out)):
            break
    os._exit(0)


def _write_all(fd: int, data: bytes) -> bool:
    """Blocking write of all of ``data``; False when stderr is gone."""
    view = memoryview(data)
    while view:
        try:
            view = view[os.write(fd, view) :]
        except BlockingIOError:  # someone made it non-blocking: wait for room
            select.select([], [fd], [])
        except InterruptedError:
            continue
        except OSError as exc:
            if exc.errno in (errno.EPIPE, errno.EBADF, errno.EIO, errno.ENOSPC):
                return False
            raise
    return True


if __name__ == "__main__":
    pump()
