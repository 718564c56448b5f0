"""The bounded pipes between the control process and its helpers: real OS pipes."""

from __future__ import annotations

import os
import threading
from typing import Any

import numpy as np
import pytest

from epc_offboard.common.channel import ChannelClosedError, FrameInbox, write_frame


def test_the_inbox_returns_whole_frames_only_then_the_writers_end():
    """A frame larger than one read arrives in pieces: returned once whole, in order; the
    frames written before the writer closed are returned before its EOF is said."""
    r, w = os.pipe()
    try:
        inbox = FrameInbox(r, max_read_bytes=4096)
        big = np.arange(20_000, dtype=np.float64)  # 160 kB: more than one read
        assert inbox.read() == []  # nothing yet: no wait
        def helper() -> None:  # the helper's side blocks until the reader has taken it all
            nonlocal w
            write_frame(w, ("first", big))
            write_frame(w, ("second", None))
            os.close(w)
            w = -1

        writer = threading.Thread(target=helper)
        writer.start()
        got: list[Any] = []
        reads = 0
        while len(got) < 2:
            got += inbox.read()
            reads += 1
            assert reads < 100_000
        writer.join()
        assert reads > 160_000 // 4096  # in pieces
        assert [tag for tag, _ in got] == ["first", "second"]
        assert np.array_equal(got[0][1], big)
        assert got[1][1] is None
        with pytest.raises(ChannelClosedError):
            inbox.read()
    finally:
        os.close(r)
        if w >= 0:
            os.close(w)


def test_the_outbox_drops_the_frames_a_newer_one_supersedes_never_a_started_one():
    """At shutdown the library keeper's last snapshot carries everything the queued ones do:
    the frames not begun are dropped (a slow store process made the shutdown wait for all of
    them, past the 10 s a service is given); one partly written is finished, so the reader
    still reads whole frames only."""
    from epc_offboard.common.channel import FrameOutbox, read_frames

    r, w = os.pipe()
    outbox = FrameOutbox(w, 64 << 20)
    big = [b"x" * 100_000, b"y" * 100_000, b"z" * 100_000]  # each larger than the pipe
    for obj in big:
        assert outbox.send(obj)
    assert outbox.pending_bytes > 200_000
    assert outbox.drop_pending() == 2  # the first is partly in the pipe: kept
    assert outbox.send(b"last")
    got: list[Any] = []
    reader = threading.Thread(target=lambda: got.extend(read_frames(r)))
    reader.start()
    while outbox.pending_bytes:
        outbox.flush()
    os.close(w)
    reader.join(timeout=10)
    assert got == [big[0], b"last"]
    os.close(r)
