"""The controller library on disk while the service runs: loaded as the prior at start,
saved every ``store.save_period_s`` by the store process, and once more at shutdown.

The library is not thread-safe: the snapshot is taken on the loop's thread
(:func:`~epc_offboard.store.experience.snapshot`), in slices of well under a millisecond
that copy (the estimator's arrays, the fleet's received controllers as packed records:
:mod:`epc_offboard.common.blobs`; the library's entries and transitions as flat arrays,
``library_types.PackedEntries``: no Python object per entry, so no collection a save), and
handed, pickled, to a process of its own
(``epc-store``, nice +10) that makes the npz files and texts and writes them to SQLite; the
loops never wait on the disk nor share their interpreter lock with the formatting or the
write. The hand-over never blocks: a store that falls
behind refuses the snapshot (counted; the next one carries everything). A failing disk is
logged and counted, never a reason to stop flying; a store process that dies is restarted.
SQLite's transactions keep the kill-9 guarantee wherever the write runs: the store process
sees EOF when the service dies, finishes (or never commits) the write in progress, and
exits. At shutdown the last snapshot is saved and waited for (in this process if the store
process cannot take it).
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import multiprocessing
import time
from collections import Counter
from collections.abc import Awaitable, Callable, Iterator, Mapping
from dataclasses import replace
from functools import partial
from typing import Any, NoReturn, TypeVar

import numpy as np

from epc_offboard.common.channel import ChannelClosedError, FrameOutbox
from epc_offboard.common.children import KILL_WAIT_S, Backoff, join_or_kill, spawn_fed
from epc_offboard.common.logsetup import LogConfig
from epc_offboard.common.procstats import process_report
from epc_offboard.control.cascade import Cascade
from epc_offboard.control.library_types import DeferredText, LibrarySnapshot
from epc_offboard.service.config import StoreConfig
from epc_offboard.store import experience
from epc_offboard.store.database import LibraryStore
from epc_offboard.store.process import ERRORS as _ERRORS
from epc_offboard.store.process import SAVES as _SAVES
from epc_offboard.store.process import store_main

log = logging.getLogger("epc_offboard.service")

_MAX_PENDING_BYTES = 64 << 20  # snapshots waiting for the store process, at most
_CLOSE_TIMEOUT_S = 30.0
_T = TypeVar("_T")
_FLUSH_PERIOD_S = 0.2  # the pipe to the store process written this often between saves
FleetState = Mapping[str, str | DeferredText]


class LibraryKeeper:
    """``published``: whether the fleet publishes new controllers (it then takes them from
    the controllers' queues); when nobody does, the queues are emptied here.
    ``fleet_steps``: the fleet's state to keep beside the library, taken in steps
    (``FleetSharing.fleet_state_steps``: None between them, the state last), saved in the
    same snapshot; what the file held at :meth:`open` is :attr:`fleet_saved`."""

    def __init__(
        self,
        cfg: StoreConfig,
        cascade: Cascade,
        counters: Counter[str],
        published: Callable[[], bool],
        log_cfg: LogConfig | None = None,
        fleet_steps: Callable[[], Iterator[FleetState | None]] | None = None,
        room: Callable[[], Awaitable[object]] | None = None,
    ) -> None:
        self.cfg = cfg
        self.cascade = cascade
        self.counters = counters
        self._published = published
        self._fleet_steps = fleet_steps
        # waits until a slice of the save fits between two ticks (``Loops.room``)
        self._room = room or (lambda: asyncio.sleep(0))
        self.slices = 0  # slices of saves run on the loops' thread
        self.slice_max_s = 0.0  # ... the longest
        self.slice_max_stage = ""  # ... what it did ("fleet", "model", "library", "hand-over")
        self.fleet_saved: dict[str, str] = {}
        self._log_cfg = log_cfg or LogConfig()
        self._ctx = multiprocessing.get_context("spawn")
        self._slots_raw = self._ctx.RawArray("q", 2)
        self._slots = np.frombuffer(self._slots_raw, dtype=np.int64)
        self._proc: multiprocessing.process.BaseProcess | None = None
        self._conn: Any = None
        self._outbox: FrameOutbox | None = None
        self._restarts = Backoff()

    def open(self) -> None:
        """Load the library file (``store.path``; "" keeps none) as the prior, then start
        the store process (from the event loop's thread)."""
        if not self.cfg.path:
            return
        store = LibraryStore.open(self.cfg.path)
        try:
            store.label_loops(experience.loop_names(self.cascade))  # for `db info`
            loaded = experience.load(self.cascade, store)
            self.fleet_saved = store.fleet_state()
        finally:
            store.close()
        log.info("library %s: loaded %s", self.cfg.path, loaded)
        self._start()

    def _start(self) -> None:
        self._proc, write = spawn_fed(store_main, "epc-store", self.cfg.path, self._slots_raw,
                                      self._log_cfg)  # fmt: skip
        self._conn = write
        self._outbox = FrameOutbox(write.fileno(), _MAX_PENDING_BYTES)

    async def run(self) -> NoReturn:
        """The ``library-saver`` task."""
        while True:
            await self._flushing(self.cfg.save_period_s)
            if not self._published():
                # nobody publishes them: the store saves the whole library anyway
                for _name, ctrl in self.cascade.experience_controllers():
                    ctrl.pop_new_entries()
            if not self.cfg.path:
                continue
            self.counters["store_errors"] = int(self._slots[_ERRORS])
            if self._outbox is None and self._restarts.due(time.monotonic()):
                self.counters["store_restarts"] += 1
                self._start()
            try:
                snap = await self._sliced_snapshot()
            except Exception as exc:  # never let saving take a loop down
                self.counters["store_snapshot_errors"] += 1
                log.error("snapshotting the library failed: %s", exc)
                continue
            await self._slice("hand-over", partial(self._hand_over, snap))  # pickled, written

    async def _flushing(self, wait_s: float) -> None:
        """Wait ``wait_s``, writing what the pipe takes of the snapshot waiting for the store
        process every ``_FLUSH_PERIOD_S`` (one ``os.write`` of at most the pipe's 64 KiB):
        flushed only at the next save, a snapshot larger than the pipe took several save
        periods to cross, and the frames queued up (2.8 MB waiting at the end of a
        ``bench --attack`` flight, all of it then written at shutdown)."""
        deadline = time.monotonic() + wait_s
        while (left := deadline - time.monotonic()) > 0:
            await asyncio.sleep(min(left, _FLUSH_PERIOD_S))
            outbox = self._outbox
            if outbox is not None and outbox.pending_bytes:
                with contextlib.suppress(ChannelClosedError):  # the next hand-over sees it
                    outbox.flush()

    async def _sliced_snapshot(self) -> LibrarySnapshot:
        """The snapshot, taken in slices that each start when the next tick is at least
        ``Loops.room``'s room away (the whole took the loops' thread for one stretch, 5-30 ms
        beside a fleet: position gaps and late attitude ticks every 5 s, issue 21; slices
        separated by ``sleep(0)`` alone ran back to back whenever no tick was due). Each
        slice copies and the store process formats: the fleet's received controllers a
        bounded number a slice (``FleetSharing.fleet_state_steps``), the estimator a model a
        slice (``to_npz_steps``), then the library's entries."""
        fleet_steps = self._fleet_steps() if self._fleet_steps is not None else iter([{}])
        fleet = None
        while fleet is None:
            fleet = await self._slice("fleet", lambda: next(fleet_steps))
        steps = experience.estimator_model_steps(self.cascade)  # a slice a model: LWPR's
        models = None  # three took 4-9 ms at once, a late attitude tick every save
        while models is None:
            models = await self._slice("model", lambda: next(steps))
        parts = experience.snapshot_steps(self.cascade, models)  # a slice a loop's library
        snap = None
        while snap is None:
            snap = await self._slice("library", lambda: next(parts))
        return replace(snap, fleet=fleet) if fleet else snap

    async def _slice(self, stage: str, step: Callable[[], _T]) -> _T:
        """``step`` run once there is room for it between two ticks; timed and counted."""
        await self._room()
        t0 = time.perf_counter()
        try:
            return step()
        finally:
            self.slices += 1
            took = time.perf_counter() - t0
            if took > self.slice_max_s:
                self.slice_max_s, self.slice_max_stage = took, stage

    def _fleet_part(self) -> dict[str, str | DeferredText]:
        """The fleet's state at once (a shutdown's save)."""
        if self._fleet_steps is None:
            return {}
        *_, state = self._fleet_steps()
        return dict(state) if state is not None else {}

    def _snapshot(self) -> LibrarySnapshot:
        """The library and the fleet's state at once, on the loops' thread (a shutdown's
        save; :meth:`_sliced_snapshot` takes them in the same order). The fleet's first: a
        received controller promoted into the library in between is then in both (offered
        again after a restart, known), never in neither (lost)."""
        fleet = self._fleet_part()
        snap = experience.snapshot(self.cascade)
        return replace(snap, fleet=fleet) if fleet else snap

    def _hand_over(self, snap: LibrarySnapshot) -> bool:
        outbox = self._outbox
        if outbox is None:
            self.counters["store_snapshots_dropped"] += 1
            return False
        try:
            outbox.flush()
            if outbox.send(snap):
                return True
            self.counters["store_snapshots_dropped"] += 1  # it is behind: the next one
        except ChannelClosedError:
            wait_s = self._restarts.failed(time.monotonic())
            self.counters["store_failures"] += 1
            log.warning("library store process died: flying on, restarting it in %.0f s",
                        wait_s)  # fmt: skip
            self._close_pipe(wait_s=0.0)
        return False

    def _close_pipe(self, wait_s: float, reap_s: float = KILL_WAIT_S) -> bool:
        """EOF to the store process and wait ``wait_s`` for it (then killed, and waited
        ``reap_s``); whether it exited, 0."""
        self._outbox = None
        if self._conn is not None:
            self._conn.close()
            self._conn = None
        proc, self._proc = self._proc, None
        if proc is None:
            return False
        return join_or_kill(proc, wait_s, reap_s) and proc.exitcode == 0

    def close(self, timeout_s: float = _CLOSE_TIMEOUT_S, reap_s: float = KILL_WAIT_S) -> None:
        """Save the library as it is now, waiting for the write (shutdown) at most
        ``timeout_s`` (the service's stop: until ``reap_s`` before ``STOP_BOUND_S``). A store
        process not done by then is killed (waited ``reap_s`` more), counted
        (``store_stop_timeouts``): its write uncommitted, SQLite's journal rolls it back and
        the file holds the library as last saved (every save before is committed); it is not
        saved here either (no time left)."""
        if not self.cfg.path:
            return
        try:
            snap = self._snapshot()
        except Exception as exc:
            self.counters["store_errors"] += 1
            log.error("saving the library failed: %s", exc)
            self._close_pipe(0.0, reap_s)
            return
        saved = timed_out = False
        deadline = time.monotonic() + timeout_s
        if self._outbox is not None:  # this snapshot carries everything the queued ones do
            self.counters["store_snapshots_dropped"] += self._outbox.drop_pending()
        if self._hand_over(snap):
            try:
                while self._outbox is not None and self._outbox.pending_bytes:
                    if time.monotonic() > deadline:
                        raise TimeoutError
                    self._outbox.flush()
                    if self._outbox.pending_bytes:  # the store reads it, or ends, or the bound
                        sentinel = self._proc.sentinel if self._proc is not None else None
                        self._outbox.wait_writable(deadline - time.monotonic(), sentinel)
                errors = int(self._slots[_ERRORS])
                saved = self._close_pipe(max(0.0, deadline - time.monotonic()), reap_s)
                timed_out = not saved and time.monotonic() >= deadline
                saved = saved and int(self._slots[_ERRORS]) == errors
            except TimeoutError:
                timed_out = True
                self._close_pipe(0.0, reap_s)
            except ChannelClosedError:
                self._close_pipe(0.0, reap_s)
        else:
            self._close_pipe(0.0, reap_s)
        self.counters["store_errors"] = int(self._slots[_ERRORS])
        if timed_out:
            self.counters["store_stop_timeouts"] += 1
            log.warning("library store process not done in %.1f s: killed; the library file "
                        "holds the last save before", timeout_s)  # fmt: skip
        elif not saved:  # the store process could not: here, as before it existed
            self._save_here(snap)

    def _save_here(self, snap: LibrarySnapshot) -> None:
        try:
            store = LibraryStore.open(self.cfg.path)
            try:
                store.save_snapshot(snap)
            finally:
                store.close()
        except Exception as exc:
            self.counters["store_errors"] += 1
            log.error("saving the library failed: %s", exc)

    def process_stats(self) -> dict[str, Any]:
        """The store process: CPU, what waits for it, saves, errors, restarts."""
        outbox = self._outbox
        return process_report(
            self._proc.pid if self._proc is not None else None,
            queued_bytes=outbox.pending_bytes if outbox is not None else 0,
            saves=int(self._slots[_SAVES]), errors=int(self._slots[_ERRORS]),
            dropped=self.counters["store_snapshots_dropped"],
            failures=self.counters["store_failures"], restarts=self.counters["store_restarts"],
            loop_slices=self.slices, loop_slice_max_ms=round(self.slice_max_s * 1e3, 3),
            loop_slice_max_stage=self.slice_max_stage,
        )  # fmt: skip
