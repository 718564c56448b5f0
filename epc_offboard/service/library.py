"""The controller library on disk while the service runs: loaded as the prior at start,
saved every ``store.save_period_s`` off the event loop, and once more at shutdown.

The library is not thread-safe: the snapshot is taken on the loop's thread
(:func:`~epc_offboard.store.experience.snapshot`) and only the SQLite write runs in a
worker thread. A failing disk is logged and counted, never a reason to stop flying.
"""

from __future__ import annotations

import asyncio
import logging
from collections import Counter
from collections.abc import Callable
from typing import NoReturn

from epc_offboard.control.cascade import Cascade
from epc_offboard.control.library import LibrarySnapshot
from epc_offboard.service.config import StoreConfig
from epc_offboard.store import experience
from epc_offboard.store.library import LibraryStore

log = logging.getLogger("epc_offboard.service")


class LibraryKeeper:
    """``published``: whether the fleet publishes new controllers (it then takes them from
    the controllers' queues); when nobody does, the queues are emptied here."""

    def __init__(
        self,
        cfg: StoreConfig,
        cascade: Cascade,
        counters: Counter[str],
        published: Callable[[], bool],
    ) -> None:
        self.cfg = cfg
        self.cascade = cascade
        self.counters = counters
        self._published = published
        self.store: LibraryStore | None = None

    def open(self) -> None:
        """Open the library file (``store.path``; "" keeps none) and load it as the prior."""
        if not self.cfg.path:
            return
        self.store = LibraryStore.open(self.cfg.path)
        self.store.label_loops(experience.loop_names(self.cascade))  # for `db info`
        loaded = experience.load(self.cascade, self.store)
        log.info("library %s: loaded %s", self.cfg.path, loaded)

    async def run(self) -> NoReturn:
        """The ``library-saver`` task."""
        while True:
            await asyncio.sleep(self.cfg.save_period_s)
            if not self._published():
                # nobody publishes them: the store saves the whole library anyway
                for _name, ctrl in self.cascade.experience_controllers():
                    ctrl.pop_new_entries()
            if self.store is None:
                continue
            try:
                snap = experience.snapshot(self.cascade)
            except Exception as exc:  # never let saving take a loop down
                self.counters["store_errors"] += 1
                log.error("snapshotting the library failed: %s", exc)
                continue
            await asyncio.to_thread(self._write, snap)

    def _write(self, snap: LibrarySnapshot) -> None:
        assert self.store is not None
        try:
            self.store.save_snapshot(snap)
        except Exception as exc:  # a full disk must not stop the flight
            self.counters["store_errors"] += 1
            log.error("saving the library failed: %s", exc)

    def close(self) -> None:
        """Save at once, on the loop's thread (shutdown), and close the file."""
        if self.store is None:
            return
        try:
            self._write(experience.snapshot(self.cascade))
        except Exception as exc:
            self.counters["store_errors"] += 1
            log.error("saving the library failed: %s", exc)
        self.store.close()
        self.store = None
