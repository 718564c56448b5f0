"""The library store's process (``epc-store``): snapshots from the service to SQLite.

Started by :class:`epc_offboard.service.library_keeper.LibraryKeeper`; imports only the store and
the shared plumbing (not the controller), so it starts in a fraction of a second.
"""

from __future__ import annotations

import logging
import os
import signal
from typing import Any

import numpy as np

from epc_offboard.common import logpipe
from epc_offboard.common.channel import read_frames
from epc_offboard.common.children import die_with_parent, lower_priority
from epc_offboard.common.logsetup import LogConfig, setup_logging
from epc_offboard.store.database import LibraryStore

log = logging.getLogger("epc_offboard.service")

NICE = 10
SAVES, ERRORS = 0, 1  # the process's counters (shared int64 slots)


def store_main(conn: Any, parent_pid: int, path: str, slots: Any, log_cfg: LogConfig) -> None:
    """The store process: snapshots from the pipe to SQLite until EOF."""
    die_with_parent(parent_pid, None)  # EOF on its pipe ends it, after the write in progress
    signal.signal(signal.SIGTERM, signal.SIG_IGN)  # the service's group's, not ours
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    lower_priority(NICE)
    setup_logging(log_cfg)
    logpipe.direct_stderr()  # a held stderr (journald) holds no save
    counts = np.frombuffer(slots, dtype=np.int64)
    store = LibraryStore.open(path)
    try:
        for snap in read_frames(conn.fileno()):
            try:
                store.save_snapshot(snap)
                counts[SAVES] += 1
            except Exception as exc:  # a full disk must not stop the flight
                counts[ERRORS] += 1
                log.error("saving the library failed: %s", exc)
    finally:
        store.close()
        os._exit(0)  # no interpreter teardown: the service's shutdown waits for this exit
