"""Bounded channels between the control process and its helper processes, over OS pipes.

Why pipes (and not a ``multiprocessing.shared_memory`` ring): the kernel does the
synchronisation, on every CPU the service runs on (a hand-made ring of numpy slots needs
memory barriers Python does not give, and companion computers are often ARM); a pipe is
bounded by the kernel (64 KiB by default), a write of at most ``PIPE_BUF`` bytes is atomic,
and the end of the other process shows as EOF, so a dead helper is seen, not guessed. No
``Queue`` either: it pickles per message and has a feeder thread that takes the GIL of the
process that owns it.

The control process's side never blocks and its work is bounded per call:

* :class:`RecordReader` reads at most ``max_records`` fixed-size records (one ``os.read``,
  one ``np.frombuffer``) from a non-blocking pipe; what is not read waits in the pipe, and
  the writer (a helper) is the one that blocks or drops.
* :class:`DropWriter` writes one fixed-size record of at most ``PIPE_BUF`` bytes, atomically,
  or drops it and counts when the pipe is full (the log writer fell behind).
* :class:`FrameOutbox` sends length-prefixed pickled frames (its own data, to a helper),
  without blocking, keeping at most ``max_pending_bytes`` waiting; beyond, a frame is refused.
* :class:`FrameInbox` takes the frames a helper answers with (:func:`write_frame`), reading
  at most ``max_read_bytes`` per call; a frame is unpickled once it is whole.

The helper's side may block: :func:`write_all`, :func:`write_frame`, :func:`read_frames`.
"""

from __future__ import annotations

import os
import pickle
import select
import selectors
import struct
from collections import deque
from collections.abc import Iterator
from typing import Any

import numpy as np
import numpy.typing as npt

from epc_offboard.common.errors import EpcError

_FRAME_HEADER = struct.Struct("<I")
PIPE_BUF = select.PIPE_BUF  # writes up to this size are atomic (POSIX: at least 512)


class ChannelClosedError(EpcError, EOFError):
    """The other end of the pipe is gone (its process died or closed it)."""


class RecordReader:
    """The reading end of a pipe of ``dtype`` records, never blocking.

    A record larger than ``PIPE_BUF`` may arrive in pieces: the remainder is kept for the
    next call, so only whole records are returned."""

    def __init__(self, fd: int, dtype: np.dtype[Any]) -> None:
        os.set_blocking(fd, False)
        self.fd = fd
        self.dtype = dtype
        self._rest = b""
        self.records = 0  # read so far

    def read(self, max_records: int) -> npt.NDArray[Any]:
        """At most ``max_records`` whole records (possibly none); ChannelClosedError at EOF."""
        size = self.dtype.itemsize
        want = max_records * size - len(self._rest)
        data = self._rest
        if want > 0:
            try:
                chunk = os.read(self.fd, want)
            except BlockingIOError:
                chunk = None
            if chunk == b"":
                raise ChannelClosedError("the writer closed the pipe")
            if chunk:
                data += chunk
        whole = len(data) - len(data) % size
        self._rest = data[whole:]
        out = np.frombuffer(data[:whole], dtype=self.dtype)
        self.records += len(out)
        return out


class DropWriter:
    """The writing end of a pipe of fixed-size records, never blocking: a record is written
    whole (``PIPE_BUF`` atomicity) or dropped and counted."""

    def __init__(self, fd: int, record_size: int) -> None:
        if record_size > PIPE_BUF:
            raise ValueError(f"a record of {record_size} bytes exceeds PIPE_BUF ({PIPE_BUF})")
        os.set_blocking(fd, False)
        self.fd = fd
        self.written = 0
        self.dropped = 0

    def write(self, record: bytes) -> bool:
        try:
            os.write(self.fd, record)
        except BlockingIOError:  # the reader fell behind: drop, never wait
            self.dropped += 1
            return False
        except BrokenPipeError as exc:
            raise ChannelClosedError("the reader closed the pipe") from exc
        self.written += 1
        return True


class FrameOutbox:
    """Pickled frames to a helper, never blocking: :meth:`send` queues and writes what the
    pipe takes, :meth:`flush` writes more later; at most ``max_pending_bytes`` wait."""

    def __init__(self, fd: int, max_pending_bytes: int) -> None:
        os.set_blocking(fd, False)
        self.fd = fd
        self.max_pending_bytes = max_pending_bytes
        self._pending: deque[memoryview] = deque()
        self.pending_bytes = 0
        self.refused = 0
        self._head_started = False  # the first pending frame is partly written

    def send(self, obj: object) -> bool:
        """Queue ``obj``; False (and counted) when that would exceed the bound."""
        frame = _frame(obj)
        if self.pending_bytes + len(frame) > self.max_pending_bytes:
            self.refused += 1
            return False
        self._pending.append(memoryview(frame))
        self.pending_bytes += len(frame)
        self.flush()
        return True

    def flush(self) -> None:
        while self._pending:
            head = self._pending[0]
            try:
                n = os.write(self.fd, head)
            except BlockingIOError:
                return
            except BrokenPipeError as exc:
                raise ChannelClosedError("the reader closed the pipe") from exc
            self.pending_bytes -= n
            if n == len(head):
                self._pending.popleft()
                self._head_started = False
            else:  # a partial write: the rest goes next time, in order
                self._pending[0] = head[n:]
                self._head_started = True

    def wait_writable(self, timeout_s: float, sentinel: int | None = None) -> None:
        """Block until the pipe takes more, ``sentinel`` (the reader's process sentinel:
        its end) is readable, or ``timeout_s`` has passed; no timer's wakeups meanwhile."""
        with selectors.DefaultSelector() as sel:
            sel.register(self.fd, selectors.EVENT_WRITE)
            if sentinel is not None:
                sel.register(sentinel, selectors.EVENT_READ)
            sel.select(max(0.0, timeout_s))

    def drop_pending(self) -> int:
        """Forget the frames not begun yet (a newer one supersedes them); a frame partly
        written is kept, so that the reader still gets whole frames. Returns the frames
        dropped."""
        keep = 1 if self._head_started and self._pending else 0
        dropped = len(self._pending) - keep
        while len(self._pending) > keep:
            self.pending_bytes -= len(self._pending.pop())
        return dropped


class FrameInbox:
    """Pickled frames from a helper (:func:`write_frame`), never blocking: :meth:`read` takes
    what the pipe holds, at most ``max_read_bytes`` (one ``os.read``), and returns the frames
    now whole; a frame's rest waits for the next call."""

    def __init__(self, fd: int, max_read_bytes: int) -> None:
        os.set_blocking(fd, False)
        self.fd = fd
        self.max_read_bytes = max_read_bytes
        self._buf = bytearray()

    def read(self) -> list[Any]:
        """The frames now whole (possibly none); ChannelClosedError at EOF, once the whole
        frames before it are returned."""
        try:
            chunk: bytes | None = os.read(self.fd, self.max_read_bytes)
        except BlockingIOError:
            chunk = None
        buf = self._buf
        if chunk:
            buf += chunk
        out = []
        head = _FRAME_HEADER.size
        while len(buf) >= head:
            (size,) = _FRAME_HEADER.unpack_from(buf)
            if len(buf) < head + size:
                break
            with memoryview(buf) as view:  # no copy; released before the buffer shrinks
                out.append(pickle.loads(view[head : head + size]))
            del buf[: head + size]
        if chunk == b"" and not out:
            raise ChannelClosedError("the writer closed the pipe")
        return out


def _frame(obj: object) -> bytes:
    data = pickle.dumps(obj, protocol=pickle.HIGHEST_PROTOCOL)
    return _FRAME_HEADER.pack(len(data)) + data


def write_frame(fd: int, obj: object) -> None:
    """Blocking write of one pickled frame (the helper's side, to a :class:`FrameInbox`)."""
    write_all(fd, _frame(obj))


def write_all(fd: int, data: bytes) -> None:
    """Blocking write of all of ``data`` (the helper's side); ChannelClosedError if the reader
    is gone."""
    view = memoryview(data)
    try:
        while view:
            view = view[os.write(fd, view) :]
    except BrokenPipeError as exc:
        raise ChannelClosedError("the reader closed the pipe") from exc


def _read_exactly(fd: int, n: int) -> bytes:
    data = b""
    while len(data) < n:
        chunk = os.read(fd, n - len(data))
        if not chunk:
            raise ChannelClosedError("the writer closed the pipe")
        data += chunk
    return data


def read_frames(fd: int) -> Iterator[Any]:
    """The frames a :class:`FrameOutbox` sent, blocking, until the writer closes the pipe
    (the helper's side; the frames come from the control process, its parent)."""
    while True:
        try:
            (size,) = _FRAME_HEADER.unpack(_read_exactly(fd, _FRAME_HEADER.size))
            yield pickle.loads(_read_exactly(fd, size))
        except ChannelClosedError:
            return
