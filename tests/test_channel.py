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
