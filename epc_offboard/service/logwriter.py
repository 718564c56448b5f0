"""The flight log and the MAVLink tlog, written by a process of their own.

The control process only packs: a flight-log row is one fixed-size struct
(:func:`~epc_offboard.service.flightlog.pack_row`), a tlog frame is appended to a block
(time, length, bytes) sent once a position tick or when full. Each record goes through a
pipe in one ``os.write`` of at most ``PIPE_BUF`` bytes, atomic, and never blocks: when the
writer falls behind and the pipe is full, the record is dropped and counted
(:class:`~epc_offboard.common.channel.DropWriter`). The pipe is enlarged (``F_SETPIPE_SZ``,
1 MiB where permitted: a few seconds of logs) so a writer held off the CPU for a moment
loses nothing. CSV formatting and file I/O (a slow SD card, a full disk) happen in the
writer, ``log_writer_nice`` below the control process.

The writer exits at EOF, after writing everything the pipe held: when the service closes
its end, and when it dies (SIGKILL included: the kernel closes the service's end). A writer
that dies is restarted (its files continued, not truncated); the flight flies on meanwhile,
its records dropped and counted.
"""

from __future__ import annotations

import contextlib
import fcntl
import logging
import multiprocessing
import os
import signal
import struct
import termios
import time
from collections import Counter
from dataclasses import dataclass
from typing import Any

from epc_offboard.common import logpipe
from epc_offboard.common.channel import PIPE_BUF, ChannelClosedError, DropWriter
from epc_offboard.common.children import (
    KILL_WAIT_S,
    Backoff,
    die_with_parent,
    join_or_kill,
    lower_priority,
    spawn_fed,
)
from epc_offboard.common.logsetup import LogConfig, setup_logging
from epc_offboard.common.procstats import process_report
from epc_offboard.service.flightlog import ROW, FlightLog
from epc_offboard.vehicle.link import TlogWriter

log = logging.getLogger("epc_offboard.service")

_HEADER = struct.Struct("<BH")  # kind, payload length
_FLIGHT, _TLOG = 1, 2
_FRAME = struct.Struct("<dH")  # a tlog frame in a block: unix time (s), length
_BLOCK = PIPE_BUF - _HEADER.size  # the most payload one atomic write carries
_PIPE_BYTES = 1 << 20
_NICE = 10
_RESTART_S = (1.0, 30.0)
# flight-log rows per write (with the tlog frames received meanwhile): 40 ms of log a write,
# a few rows lost at most if the service is killed
_ROWS_PER_WRITE = 4  # the first and the longest wait before restarting a dead writer


@dataclass(frozen=True)
class _Paths:
    flight_log: str
    tlog: str
    log: LogConfig


def _writer_main(fd_conn: Any, parent_pid: int, paths: _Paths, append: bool) -> None:
    """The writer process: records from the pipe to the files until EOF."""
    # no parent-death signal: the pipe ends (EOF) when the service dies, however, and what
    # it held is still written; a SIGTERM meant for the service's group must not cut that
    die_with_parent(parent_pid, None)
    signal.signal(signal.SIGTERM, signal.SIG_IGN)
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    lower_priority(_NICE)
    setup_logging(paths.log)
    logpipe.direct_stderr()  # a held stderr (journald) holds no record
    flight = FlightLog(paths.flight_log, append=append) if paths.flight_log else None
    tlog = TlogWriter(paths.tlog) if paths.tlog else None
    fd = fd_conn.fileno()
    buf = b""
    try:
        while True:
            chunk = os.read(fd, 1 << 16)
            if not chunk:
                break
            buf += chunk
            while len(buf) >= _HEADER.size:
                kind, n = _HEADER.unpack_from(buf)
                if len(buf) < _HEADER.size + n:
                    break
                payload, buf = buf[_HEADER.size : _HEADER.size + n], buf[_HEADER.size + n :]
                if kind == _FLIGHT and flight is not None:
                    flight.write_packed(payload)
                elif kind == _TLOG and tlog is not None:
                    _write_block(tlog, payload)
            if flight is not None:
                flight.flush()
            if tlog is not None:
                tlog.flush()
    finally:
        if flight is not None:
            flight.close()
        if tlog is not None:
            tlog.close()
        # done: skip the interpreter's teardown, which on a loaded machine took seconds
        # that the service's shutdown (and a lockstep simulator) waited through
        os._exit(0)


def _write_block(tlog: TlogWriter, block: bytes) -> None:
    i = 0
    while i < len(block):
        t_s, n = _FRAME.unpack_from(block, i)
        i += _FRAME.size
        tlog.write(block[i : i + n], t_s)
        i += n


class LogWriter:
    """The control process's end: ``flight_row`` per position tick, ``tlog`` for the link
    (a :class:`TlogWriter` to it), ``close`` at shutdown. Never blocks; counts in
    ``counters`` (``log_records_dropped``, ``log_writer_restarts``)."""

    def __init__(self, flight_log_path: str, tlog_path: str, log_cfg: LogConfig,
                 counters: Counter[str]) -> None:  # fmt: skip
        self._paths = _Paths(flight_log_path, tlog_path, log_cfg)
        self.counters = counters
        self._proc: multiprocessing.process.BaseProcess | None = None
        self._conn: Any = None
        self._out: DropWriter | None = None
        self._block = bytearray()  # the tlog frames since the last record
        self._pending = bytearray()  # whole records, the next write
        self._pending_records = 0
        self._pending_rows = 0
        self._restarts = Backoff(*_RESTART_S)
        self.tlog = _TlogChannel(self) if tlog_path else None

    def start(self, *, append: bool = False) -> None:
        """Start the writer (from the event loop's thread: its parent-death signal follows
        the thread that started it)."""
        self._proc, write = spawn_fed(_writer_main, "epc-logs", self._paths, append,
                                      pipe_bytes=_PIPE_BYTES)  # fmt: skip
        self._conn = write
        self._out = DropWriter(write.fileno(), PIPE_BUF)

    def flush(self) -> None:
        """Write what is queued now (the tlog frames included)."""
        self._close_block()
        self._flush()

    def pid(self) -> int | None:
        return self._proc.pid if self._proc is not None else None

    def flight_row(self, row: bytes) -> None:
        """One packed flight-log row; the tlog frames of the tick go with it. Written with
        the rows of the next ticks, ``_ROWS_PER_WRITE`` to one ``os.write`` (a write woke the
        writer process, 7 us of the tick's CPU each)."""
        self._close_block()
        self._queue(_FLIGHT, row)
        self._pending_rows += 1
        if self._pending_rows >= _ROWS_PER_WRITE:
            self._flush()

    def add_frame(self, frame: bytes, unix_time_s: float) -> None:
        if len(self._block) + _FRAME.size + len(frame) > _BLOCK:
            self._close_block()
        self._block += _FRAME.pack(unix_time_s, len(frame)) + frame

    def _close_block(self) -> None:
        """The tlog frames so far as one record, queued."""
        if self._block:
            self._queue(_TLOG, bytes(self._block))
            self._block.clear()

    def _queue(self, kind: int, payload: bytes) -> None:
        """A record to the next write: whole records only, at most ``PIPE_BUF`` bytes in all,
        so each write stays atomic."""
        record = _HEADER.pack(kind, len(payload)) + payload
        if len(self._pending) + len(record) > PIPE_BUF:
            self._flush()
        self._pending += record
        self._pending_records += 1

    def _flush(self) -> None:
        """The queued records in one write, or dropped (and counted) when the writer falls
        behind or is down."""
        if not self._pending:
            return
        records, data = self._pending_records, bytes(self._pending)
        self._pending.clear()
        self._pending_records = self._pending_rows = 0
        out = self._out
        if out is None:
            self.counters["log_records_dropped"] += records
            self._maybe_restart()
            return
        try:
            if not out.write(data):
                self.counters["log_records_dropped"] += records
        except ChannelClosedError:
            self._writer_died()

    def _writer_died(self) -> None:
        self.counters["log_writer_failures"] += 1
        wait_s = self._restarts.failed(time.monotonic())
        log.warning("log writer (process %s) died: flying on, its records dropped; "
                    "restarting it in %.0f s", self.pid(), wait_s)  # fmt: skip
        self._close_pipe()
        if self._proc is not None:
            self._proc.join(timeout=0.0)

    def _maybe_restart(self) -> None:
        if not self._restarts.due(time.monotonic()):
            return
        self.counters["log_writer_restarts"] += 1
        self.start(append=True)

    def _close_pipe(self) -> None:
        self._out = None
        if self._conn is not None:
            self._conn.close()
            self._conn = None

    def close(self, timeout_s: float = 20.0, reap_s: float = KILL_WAIT_S) -> None:
        """Send what is pending, close the pipe (EOF), and let the writer finish; killed
        after ``timeout_s`` and waited ``reap_s`` more (the service's stop: both end by
        ``STOP_BOUND_S``; what it had not written
        then is lost, the files as far as it wrote them)."""
        self.flush()
        self._close_pipe()
        if self._proc is not None:
            if not join_or_kill(self._proc, timeout_s, reap_s):
                self.counters["log_writer_stop_timeouts"] += 1
            self._proc = None

    def process_stats(self) -> dict[str, Any]:
        """The writer process: CPU, what waits in the pipe, drops, restarts."""
        queued = None
        if self._conn is not None:
            with contextlib.suppress(OSError):  # FIONREAD on the write end: bytes in the pipe
                queued = struct.unpack("i", fcntl.ioctl(self._conn.fileno(), termios.FIONREAD,
                                                        b"\0\0\0\0"))[0]  # fmt: skip
        return process_report(
            self.pid(), queued_bytes=queued, dropped=self.counters["log_records_dropped"],
            failures=self.counters["log_writer_failures"],
            restarts=self.counters["log_writer_restarts"],
        )  # fmt: skip


class _TlogChannel(TlogWriter):
    """The link's tlog, through the writer process (the link calls write/flush/close)."""

    def __init__(self, writer: LogWriter) -> None:  # no file here: the writer has it
        self._fh = None
        self._writer = writer

    def write(self, frame: bytes, unix_time_s: float | None = None) -> None:
        self._writer.add_frame(frame, time.time() if unix_time_s is None else unix_time_s)

    def flush(self) -> None:
        self._writer.flush()

    def close(self) -> None:
        self.flush()


assert ROW.size + _HEADER.size <= PIPE_BUF  # a flight row is one atomic write
