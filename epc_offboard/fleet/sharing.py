"""Fleet sharing of EPC controller libraries, and live references, over Eclipse Zenoh: the
control process's side.

Keys (:mod:`epc_offboard.fleet.keys`; every one starts with ``epc/``; ``<sig>`` is
``MpcProblem.signature()``)::

    epc/<fleet>/<sig>/ctl/<vehicle>     each batch of new controllers (wire.MessageKind.BATCH)
    epc/<fleet>/<sig>/lib/<vehicle>     queryable: the whole library (MessageKind.SNAPSHOT)
    epc/<fleet>/<sig>/alive/<vehicle>   liveliness token
    epc/<fleet>/<vehicle>/reference     live references for one vehicle (wire.ReferenceMessage)

One set of keys per shared problem (the position and the attitude loop have different
signatures): a vehicle subscribes only to its own signatures, so a peer flying another
problem is never even heard, and a payload whose embedded signature differs from the key's
is rejected. Late joiners query ``lib/*`` at start, and every vehicle queries the library
of a peer whose liveliness token appears.

Processes: the Zenoh session lives in the fleet helper process
(:mod:`epc_offboard.fleet.session`: Zenoh's threads, rate limits, decoding, validation, the
candidate inbox, publishing, answering queries), ``helper_nice`` below this one. Zenoh's
callbacks used to run here, and holding this interpreter's lock to reject a flood is what
starved the control loops (a hovering vehicle fell from 2.5 m to 0.7 m). Now a peer's
messages cost this process nothing: :meth:`FleetSharing.run` — the ``library-sharing`` task
— reads at most ``candidates_per_s`` decoded candidates a second (fixed-size records, one
``os.read`` per turn) and offers them to each controller's candidate pool (bookkeeping, no
factorisation: the pool is bounded in total and per peer, its maps are built by the miss
worker, and a candidate enters the library only when it passes this vehicle's KKT check for
a real tick). It sends new controllers and library snapshots to the helper as frames,
never blocking (a full pipe refuses, counted). The helper's death or silence is survived:
the loops fly on without the fleet (warned, counted) and the helper is restarted with a
growing wait.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import logging
import math
import multiprocessing
import os
import threading
import time
from collections import Counter, deque
from collections.abc import Awaitable, Callable, Iterator, Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from epc_offboard.common.blobs import ReceivedText, received_record
from epc_offboard.common.channel import ChannelClosedError, FrameOutbox, RecordReader
from epc_offboard.common.children import KILL_WAIT_S, Backoff, join_or_kill, start_counted
from epc_offboard.common.logsetup import LogConfig
from epc_offboard.common.procstats import WATCH_EVERY_S, StartWatch, process_report
from epc_offboard.control.candidate_pool import CandidatePoolConfig
from epc_offboard.control.epc import MAX_SUCCESSORS, ExperienceController
from epc_offboard.control.epc.exchange import FleetPort
from epc_offboard.control.library_types import LibraryEntry, text_of
from epc_offboard.fleet import keys
from epc_offboard.fleet.config import SharingConfig
from epc_offboard.fleet.exchange import (
    FleetLibrary,
    candidate_dtype,
    candidate_records,
    offer_records,
    successors_of,
)
from epc_offboard.fleet.records import (
    REFERENCE_DTYPE,
    STAT_INDEX,
    STAT_NAMES,
    ProblemSpec,
    Records,
    reference_of,
)
from epc_offboard.fleet.session import HelperArgs, helper_main, numbering, read_texts
from epc_offboard.fleet.wire import ControllerMessage, ReferenceMessage

__all__ = ["FleetSharing", "LiveReference", "SharingConfig", "open_or_fly_alone"]

log = logging.getLogger(__name__)

_OFFERS_PER_SLICE = 3  # candidates offered in one stretch of the loops' thread
_TURN_S = 0.05  # the library-sharing task's period: candidates, references, the helper
_MAX_OUTBOX_BYTES = 4 << 20  # frames to the helper waiting in this process, at most
# its start (imports, the session's open) is judged by progress (procstats.StartWatch), as
# the miss worker's: it failed once it used and waited for no CPU this long (SIGSTOP, a
# block), or was not up in the cap though running. On a 30 s clock (before stop 42) a helper
# still importing at load 12-17 was killed, and the next alike
_START_TIMEOUT_S = 30.0
_START_CAP_S = 600.0
_STOP_TIMEOUT_S = 2.0  # its session closed and the process ended, or it is killed
_REFERENCES_PER_READ = 4  # the newest of these is kept
_HIGH_WATER_BYTES = 1 << 20  # session.HighWater's saved tables (a larger one is not kept)
_RECORDS_PER_STEP = 64  # received controllers a step of fleet_state_steps takes
_FRAME_ENTRIES = 512  # controllers in one publish frame: far below the outbox's bound
_MARKS, _CANDIDATES, _OWN = "marks", "candidates:", "own"  # fleet_state's names
_NO_MARKS = '{"held":[]}'


def _first(deadline_s: float | None) -> int:
    """The candidates a slice offers before it looks at its deadline (none: a count)."""
    return _OFFERS_PER_SLICE if deadline_s is None else 1


async def _no_room() -> float | None:
    """Without the loops (tests, tools): a slice is a count, not a deadline."""
    await asyncio.sleep(0)
    return None


@dataclass(frozen=True)
class LiveReference:
    message: ReferenceMessage
    received_s: float  # time.monotonic() at arrival (in the helper: the same clock)


class PublishBacklog:
    """This vehicle's new controllers on their way to the fleet, kept until a helper with an
    open session has published them.

    Entries wait here (at most ``max_entries``; beyond, the oldest are dropped and counted)
    while no helper has its session: one starting, one being restarted, none at all. They
    are handed to a running helper as numbered ``publish`` frames and kept until it reports
    (``publish_seq_done``) that it has handled that number; a helper that dies first leaves
    them to be handed again to the next one, in order. Without this, what was learned while
    a helper was down, or sat unread in a dead helper's pipe, never reached the fleet.
    """

    def __init__(self, max_entries: int) -> None:
        self.max_entries = max_entries
        self._waiting: deque[tuple[int, LibraryEntry]] = deque()  # (problem index, entry)
        self._handed: deque[tuple[int, list[tuple[int, LibraryEntry]]]] = deque()  # by seq
        self._seq = 0  # the last frame number given; never reused, across helpers
        self.dropped = 0
        self.refused = False  # the last hand_off stopped at a frame refused (a full pipe)

    def __len__(self) -> int:
        return len(self._waiting) + sum(len(items) for _, items in self._handed)

    def add(self, index: int, entries: Sequence[LibraryEntry]) -> None:
        self._waiting.extend((index, e) for e in entries)
        self._trim()

    @property
    def waiting(self) -> int:
        """Entries not handed to a helper yet."""
        return len(self._waiting)

    def hand_off(self, send: Callable[[tuple[Any, ...]], bool],
                 deadline_s: float | None = None) -> int:  # fmt: skip
        """Send what waits as ``("publish", index, entries, seq)`` frames, one per run of a
        problem; stops at the first frame ``send`` refuses (``refused`` then True), or once
        ``deadline_s`` (time.monotonic) has passed after a frame (the rest on the next
        call). Returns the entries handed."""
        handed = 0
        self.refused = False
        while self._waiting:
            if handed and deadline_s is not None and time.monotonic() >= deadline_s:
                break
            index = self._waiting[0][0]
            items: list[tuple[int, LibraryEntry]] = []
            for item in self._waiting:
                if item[0] != index or len(items) >= _FRAME_ENTRIES:
                    break
                items.append(item)
            seq = self._seq + 1
            if not send(("publish", index, [e for _, e in items], seq)):
                self.refused = True
                break
            self._seq = seq
            for _ in items:
                self._waiting.popleft()
            self._handed.append((seq, items))
            handed += len(items)
        return handed

    def done(self, seq: int) -> None:
        """The helper has handled every frame numbered up to ``seq``."""
        while self._handed and self._handed[0][0] <= seq:
            self._handed.popleft()

    def requeue(self) -> int:
        """The helper died: what it had not handled waits again, first. Returns how many."""
        back = [item for _, items in self._handed for item in items]
        self._handed.clear()
        self._waiting.extendleft(reversed(back))
        self._trim()
        return len(back)

    def _trim(self) -> None:
        while len(self._waiting) > self.max_entries:
            self._waiting.popleft()
            self.dropped += 1


@dataclass
class _Helper:
    """One running helper process and this process's ends of its pipes."""

    process: multiprocessing.process.BaseProcess
    candidates: RecordReader
    references: RecordReader
    outbox: FrameOutbox
    conns: list[Any]  # this process's Connection objects (closed with the helper)
    started_s: float
    watch: StartWatch  # its start's progress (while its session is not open)
    failed: bool = False  # its pipes closed or it could not open its session


class FleetSharing:
    """The fleet, seen from the control process: a Zenoh session in a helper process.

    ``controllers``: (name, controller) of every EPC problem to share (their candidate
    pools take the sizes of ``candidates``: construct this before the miss worker starts,
    which copies them); ``share_library`` False opens the session for the reference alone;
    ``reference`` subscribes to this vehicle's live-reference key. Use as
    ``async with FleetSharing(...) as sharing`` and run :meth:`run` as a task; controllers
    are touched only from that task.
    """

    def __init__(
        self,
        cfg: SharingConfig,
        controllers: Sequence[tuple[str, ExperienceController]],
        *,
        share_library: bool = True,
        reference: bool = False,
        log_cfg: LogConfig | None = None,
        candidates: CandidatePoolConfig | None = None,
        room: Callable[[], Awaitable[float | None]] | None = None,
    ) -> None:
        if not cfg.vehicle_id:
            raise ValueError("sharing.vehicle_id must be set to open a fleet session")
        self.cfg = cfg
        self.vehicle_id = cfg.vehicle_id
        self.share_library = share_library
        self.subscribe_reference = reference
        self.log_cfg = log_cfg or LogConfig()  # the helper's log lines, on the same stderr
        self.counters: Counter[str] = Counter()
        # waits until a turn fits between two of the loops' ticks (``Loops.room``); gives the
        # slice's deadline on time.monotonic (None: a slice is _OFFERS_PER_SLICE, a frame)
        self._room: Callable[[], Awaitable[float | None]] = room or _no_room
        pool = self.candidates = candidates or CandidatePoolConfig()
        ports = [(name, FleetPort(ctrl, pool)) for name, ctrl in controllers]
        self.specs = tuple(
            ProblemSpec(name, port.signature, port.n_con, port.max_active, port.max_entries)
            for name, port in ports
        )
        # the exchange sees each controller through its narrow protocol, nothing else
        self._libraries: list[tuple[str, FleetLibrary]] = list(ports)
        max_active = max((s.max_active for s in self.specs), default=1)
        self.candidate_dtype = candidate_dtype(max_active, MAX_SUCCESSORS)
        self._ctx = multiprocessing.get_context("spawn")  # no fork of a threaded process
        # the helper's counters and heartbeat: written there, read here (no lock, no GIL of
        # theirs: int64 slots); one array for every helper, so counts add up across restarts
        self._slots_raw = self._ctx.RawArray("q", len(STAT_NAMES))
        self._slots = np.frombuffer(self._slots_raw, dtype=np.int64)
        # the helper's high-water marks (session.HighWater), kept for the next helper
        self._high_water_raw = self._ctx.RawArray("c", _HIGH_WATER_BYTES)
        # ... and what of them the store keeps, as its texts (session.write_texts)
        self._texts_raw = self._ctx.RawArray("c", _HIGH_WATER_BYTES)
        self._helper: _Helper | None = None
        self._restarts = Backoff(1.0, cfg.helper_restart_max_s)
        self._budget = float(self._per_turn())
        self._budget_at_s = time.monotonic()
        self._dirty = [True] * len(self._libraries)
        self._reference: LiveReference | None = None
        self._backlog = PublishBacklog(cfg.publish_backlog_entries)
        self._read = 0  # candidate records read from the running helper
        # ... read this turn, not offered yet (offer_slice)
        self._to_offer: Records = np.zeros(0, dtype=self.candidate_dtype)
        self._marks_text = _NO_MARKS  # fleet_state's: the marks held, as the store keeps them
        # the helper's texts last read (session.read_texts): (crc, pid, taken, marks)
        self._texts_seen: tuple[int, int, int, str] = (0, 0, -1, "")
        # per problem: each received controller's record by the entry's id (fleet_state)
        # per problem: id(entry) -> (the entry, its record), in two dicts (a tuple a record
        # was an object a new received controller, every save, for the collector)
        self._received_records: dict[int, tuple[dict[int, LibraryEntry], dict[int, bytes]]] = {}
        # fleet_state's: this vehicle's numbering of its library (HighWater's ``own``), as
        # the store keeps it
        self._own = ""

    def _per_turn(self) -> int:
        return max(1, math.ceil(self.cfg.candidates_per_s * _TURN_S))

    # -- lifecycle ------------------------------------------------------------------------

    async def open(self) -> None:
        """Start the helper and wait until its session is open, judged by its progress
        (``_START_TIMEOUT_S`` without CPU, or ``_START_CAP_S`` though running); RuntimeError
        if it cannot open one (the service then flies alone)."""
        self._start_helper()
        helper = self._helper
        assert helper is not None
        why = "see the fleet helper's log"
        while self._slot("state") == 0 and helper.process.is_alive():
            stalled = helper.watch.verdict_every(WATCH_EVERY_S)
            if stalled is not None:
                why = f"not started: {stalled}"
                break
            await asyncio.sleep(0.02)
        if self._slot("state") != 1:
            self._stop_helper(kill=True)
            raise RuntimeError(f"the fleet session did not open ({why})")
        log.info("fleet helper up (process %s, nice +%d)", helper.process.pid,
                 self.cfg.helper_nice)  # fmt: skip

    def close(self, timeout_s: float = _STOP_TIMEOUT_S, reap_s: float = KILL_WAIT_S) -> None:
        """EOF to the helper (it closes its session and exits), waited for ``timeout_s``,
        then killed and waited ``reap_s`` (the service's stop: both end by ``STOP_BOUND_S``)."""
        self._stop_helper(kill=False, timeout_s=timeout_s, reap_s=reap_s)

    async def __aenter__(self) -> FleetSharing:
        await self.open()
        return self

    async def __aexit__(self, *exc: object) -> None:
        self.close()

    @staticmethod
    def reference_key(fleet: str, vehicle_id: str) -> str:
        return keys.reference_key(fleet, vehicle_id)

    def _start_helper(self) -> None:
        """Spawn the helper (from the event loop's thread: its parent-death signal follows
        the thread that started it) with the libraries as they are now."""
        cand_r, cand_w = self._ctx.Pipe(duplex=False)
        ref_r, ref_w = self._ctx.Pipe(duplex=False)
        frames_r, frames_w = self._ctx.Pipe(duplex=False)
        snapshots = tuple(library.snapshot() for _, library in self._libraries)
        args = HelperArgs(self.cfg, self.specs, self.candidate_dtype, MAX_SUCCESSORS,
                          self.share_library, self.subscribe_reference, snapshots, os.getpid(),
                          self.log_cfg, self.candidates.backlog_per_peer)  # fmt: skip
        self._slots[STAT_INDEX["state"]] = 0
        self._slots[STAT_INDEX["heartbeat_ns"]] = 0  # the dead one's beat is not this one's
        self._read = 0
        proc = start_counted(
            self._ctx, helper_main,
            (args, self._slots_raw, cand_w, ref_w, frames_r, self._high_water_raw,
             self._texts_raw),
            "epc-fleet",
        )  # fmt: skip
        for conn in (cand_w, ref_w, frames_r):  # the helper's ends: EOF here when it dies
            conn.close()
        self._helper = _Helper(
            proc,
            RecordReader(cand_r.fileno(), self.candidate_dtype),
            RecordReader(ref_r.fileno(), REFERENCE_DTYPE),
            FrameOutbox(frames_w.fileno(), _MAX_OUTBOX_BYTES),
            [cand_r, ref_r, frames_w],
            time.monotonic(),
            StartWatch(proc.pid or 0, _START_TIMEOUT_S, _START_CAP_S),
        )
        self._dirty = [False] * len(self._libraries)  # it started with the snapshots

    def _stop_helper(
        self, *, kill: bool, timeout_s: float = _STOP_TIMEOUT_S, reap_s: float = KILL_WAIT_S
    ) -> None:
        helper, self._helper = self._helper, None
        if helper is None:
            return
        for conn in helper.conns:  # EOF on its frames pipe: it closes its session and exits
            conn.close()
        proc = helper.process
        if kill:
            # a failed helper, on the loops' thread: SIGKILL, and reaped by a thread of its
            # own. Joined here, a helper SIGSTOPped 20 s and killed took 0.07-1.3 s to exit
            # (its teardown at nice +10 beside two CPU hogs): the loops stood still that
            # long, the state went stale and the vehicle left offboard (bench --attack
            # --freeze fleet, 0.8 m off)
            threading.Thread(target=join_or_kill, args=(proc, 0.0, None), name="fleet-reaper",
                             daemon=True).start()  # fmt: skip
            return
        join_or_kill(proc, timeout_s, reap_s)

    # -- the event-loop task --------------------------------------------------------------

    async def run(self) -> None:
        """Take candidates and references, publish new controllers, refresh snapshots,
        watch the helper. Forever."""
        period = self.cfg.publish_period_s
        next_publish = time.monotonic() + period
        while True:
            # a turn (candidates offered, a publication, the snapshots) takes the loops'
            # thread 2-3 ms, up to 7: started whenever its sleep ended, it came between two
            # ticks due (100 of 135 position-loop gaps over 12 ms beside bench --attack's
            # replay, issue 21); it starts now when a tick has just run and the next is
            # at least ROOM_S away
            #
            # Each slice ends by the deadline ``room`` gives (~1 ms, before the next tick due):
            # the candidates are offered one by one until it passes, the publication handed
            # over a frame at a time, the snapshots one problem at a time. Three candidates a
            # slice, and a publication and its hand-over at once, still took the loops'
            # thread 3-10 ms in a step (stop 37's bench --attack, before late ticks).
            deadline = await self._room()
            now = time.monotonic()
            self.poll(now, deadline)
            while len(self._to_offer):  # the rest of the turn's candidates, a slice at a time
                self.offer_slice(await self._room())
            if now >= next_publish:
                next_publish = now + period
                self.publish_new(await self._room())
                while self._backlog.waiting and self.helper_running():
                    if not self._hand_off(await self._room()):
                        break  # the pipe is full: the rest next turn
                for i in range(len(self._libraries)):
                    if self.share_library and self._dirty[i]:
                        await self._room()
                        self._refresh_snapshot(i)
            await asyncio.sleep(_TURN_S)

    def poll(self, now_s: float, deadline_s: float | None = None) -> int:
        """One turn: the budget's candidates read and, until ``deadline_s`` (time.monotonic;
        None: ``_OFFERS_PER_SLICE``), offered, the newest reference kept, the helper checked
        (restarted when due). Returns the candidates offered."""
        helper = self._helper
        if helper is None:
            if self._restarts.due(now_s):
                self.counters["helper_restarts"] += 1
                log.warning("fleet helper: restarting it")
                self._start_helper()
            return 0
        offered = 0
        try:
            self._read_reference(helper)
            self._budget = min(
                float(self._per_turn()),
                self._budget + (now_s - self._budget_at_s) * self.cfg.candidates_per_s,
            )
            self._budget_at_s = now_s
            n = int(self._budget)
            if n >= 1:
                records = helper.candidates.read(n)
                self._budget -= len(records)
                self._read += len(records)
                waiting = self._to_offer
                self._to_offer = np.concatenate((waiting, records)) if len(waiting) else records
                offered = self.offer_slice(deadline_s)  # a slice's worth (the rest: run)
            helper.outbox.flush()
            self._hand_off(deadline_s)
        except ChannelClosedError:
            helper.failed = True
        self._watch(helper, now_s)
        return offered

    def _watch(self, helper: _Helper, now_s: float) -> None:
        state = self._slot("state")
        beat_s = self._slot("heartbeat_ns") * 1e-9
        if helper.failed or not helper.process.is_alive() or state < 0:
            why = "died"
        elif state == 0 and (stalled := helper.watch.verdict_every(WATCH_EVERY_S, now_s)):
            why = f"did not start: {stalled}"  # (asked every WATCH_EVERY_S, not every turn)
        elif state == 1 and now_s - beat_s > self.cfg.helper_timeout_s:
            why = f"was silent for {now_s - beat_s:.1f} s"
        else:
            self._restarts.lived(now_s - helper.started_s)
            return
        self.counters["helper_failures"] += 1
        log.warning(
            "fleet helper (process %s) %s: flying on without the fleet; restarting it in %.0f s",
            helper.process.pid, why, self._restarts.failed(now_s),
        )  # fmt: skip
        self._backlog.done(self._slot("publish_seq_done"))  # what it did before it failed
        self._stop_helper(kill=True)
        self._reference = None
        self.counters["publish_requeued"] += self._backlog.requeue()

    def offer_slice(self, deadline_s: float | None = None) -> int:
        """Offer the candidates read and waiting one by one until ``deadline_s`` has passed
        (time.monotonic; at least one), or, with no deadline (lockstep: the same every run),
        ``_OFFERS_PER_SLICE`` of them (``run`` waits for ``Loops.room`` before each slice);
        returns how many were new. A turn's ten offered at once took the loops' thread 2-6 ms
        (bench --attack's replay, the event loop's steps timed: the longest step of most
        turns, issue 21), three at once still up to 10 ms beside two hogs (stop 37)."""
        return self._offer(self._next_slice(_first(deadline_s))) + self._offer_until(deadline_s)

    def _offer_until(self, deadline_s: float | None) -> int:
        """After a slice's first: the candidates waiting, one by one until ``deadline_s``."""
        offered = 0
        while deadline_s is not None and len(self._to_offer) and time.monotonic() < deadline_s:
            offered += self._offer(self._next_slice(1))
        return offered

    def _next_slice(self, n: int) -> Records:
        """The next ``n`` candidates waiting (none: offered all the same, counted as before)."""
        head = self._to_offer[:n]
        self._to_offer = self._to_offer[n:]
        return head

    def _offer(self, records: Records) -> int:
        """Candidates read from the helper to their libraries (the fleet bench stamps their
        arrival here)."""
        return offer_records(records, self._libraries, self.counters)

    def offer_message(self, name: str, msg: ControllerMessage) -> int:
        """Offer a decoded message's entries as they would arrive from the helper (a fleet
        query's answer, an import): returns how many were new to the pool."""
        index = next(i for i, (n, _) in enumerate(self._libraries) if n == name)
        records = candidate_records(msg, index, self.candidate_dtype,
                                    successors_of(msg, MAX_SUCCESSORS))  # fmt: skip
        return self._offer(records)

    def _read_reference(self, helper: _Helper) -> None:
        rows = helper.references.read(_REFERENCES_PER_READ)
        if len(rows):
            msg, received_s = reference_of(rows[-1])
            self._reference = LiveReference(msg, received_s)

    def publish_new(self, deadline_s: float | None = None) -> int:
        """Queue every controller learned since the last call for publication, and hand what
        waits to the helper if its session is open (until ``deadline_s``, as
        :meth:`_hand_off`); returns how many were queued."""
        queued = 0
        for i, (_name, library) in enumerate(self._libraries):
            new = library.new_entries()
            if not new or not self.share_library:
                continue
            self._dirty[i] = True
            self._backlog.add(i, new)
            queued += len(new)
        self._hand_off(deadline_s)
        return queued

    def _hand_off(self, deadline_s: float | None = None) -> bool:
        """Publication goes only to a helper whose session is open: one still starting may
        never open it, and one that dies takes its pipe's contents with it. Frames are
        handed until ``deadline_s`` has passed (time.monotonic; at least one; None: all
        that wait). Returns False if the helper refused one (its pipe full)."""
        if not self.helper_running():
            return True
        self._backlog.done(self._slot("publish_seq_done"))
        self._backlog.hand_off(self._send, deadline_s)
        return not self._backlog.refused

    def _refresh_snapshot(self, i: int) -> None:
        """Problem ``i``'s library as the helper answers queries with it (one problem a
        slice: a snapshot is not cut)."""
        # here, on the event loop: the library is not thread-safe
        if self._send(("snapshot", i, *self._libraries[i][1].snapshot())):
            self._dirty[i] = False

    def _send(self, frame: tuple[Any, ...]) -> bool:
        helper = self._helper
        if helper is None or helper.failed:
            return False
        try:
            return helper.outbox.send(frame)
        except ChannelClosedError:
            helper.failed = True
            return False

    # -- a restart: what the store keeps beside the library -------------------------------

    def fleet_state(self) -> dict[str, str]:
        """What a vehicle restarted as a new process needs to ask the fleet only for what is
        new, as texts the library store keeps beside the library: :meth:`fleet_state_steps`
        taken at once, its texts built here (a shutdown's save, tests)."""
        *_, state = self.fleet_state_steps()
        assert state is not None
        return {k: text_of(v) for k, v in state.items()}

    def fleet_state_steps(
        self, per_step: int = _RECORDS_PER_STEP
    ) -> Iterator[dict[str, str | ReceivedText] | None]:
        """:meth:`fleet_state` in steps on the loops' thread (None between them, the state
        last), each at most ``per_step`` received controllers: per problem, every received
        controller not in the library (yet) with its successors, as packed records
        (:func:`~epc_offboard.common.blobs.received_record`, made once per controller and
        kept while it is known) that the store process formats (``ReceivedText``: 2,048 of
        them as text took 8-10 ms of the loops' thread a save, issue 21); and the
        high-water marks up to which they are held (``session.HighWater``). The marks are
        the helper's settled ones, taken only once this process has read every controller
        they cover (one still in the helper's inbox or pipe would otherwise be lost by a
        kill), else the last such; they are taken first, the lists after them, each
        origin's at once (``FleetPort.received_parts``). And this vehicle's own numbering
        of its library, so that after a restart its peers are answered only what they lack
        of it (``HighWater.former``). {} when not sharing a library."""
        if not self.share_library:
            yield {}
            return
        self._settle_marks()
        out: dict[str, str | ReceivedText] = {}
        for i, (spec, (_name, library)) in enumerate(zip(self.specs, self._libraries,
                                                         strict=True)):  # fmt: skip
            entries_before, records_before = self._received_records.get(i, ({}, {}))
            entries: dict[int, LibraryEntry] = {}
            records: dict[int, bytes] = {}
            parts: list[bytes] = []
            for received in library.received_parts(per_step):
                yield None
                for e, succ in received:
                    key = id(e)  # an id is not reused while its entry is kept
                    record = records_before.get(key)
                    if record is None or entries_before.get(key) is not e:
                        record = received_record(e.active_set, e.origin, e.importance, e.uses,
                                                 succ)  # fmt: skip
                    entries[key] = e
                    records[key] = record
                    parts.append(record)
            self._received_records[i] = (entries, records)
            out[_CANDIDATES + spec.signature] = ReceivedText(b"".join(parts))
        out[_MARKS] = self._marks_text
        if self._own:
            out[_OWN] = self._own
        yield out

    def _settle_marks(self) -> None:
        """The helper's settled marks and its numbering of the library, as the store keeps
        them. The helper makes the texts (``HighWater.save``); here, on the loops' thread,
        a save reads a header and, when the helper wrote new ones, copies them (bounded by
        the buffer): parsing the marks and rebuilding them with their signatures here grew
        with the peers heard (rotating ids: every save, issue 21). The marks are taken only
        from the running helper, and once this process has read every controller they
        cover (one still in its inbox or pipe would be lost by a kill), else the last
        such stay; the numbering from any helper (a restart keeps the one it restored
        until a helper writes one)."""
        new = read_texts(self._texts_raw, self._texts_seen[0])
        if new is not None:
            crc, pid, taken, own, marks = new
            try:
                self._texts_seen = (crc, pid, taken, marks.decode())
                if own:
                    self._own = own.decode()
            except UnicodeDecodeError:
                return
        _crc, pid, taken, marks_text = self._texts_seen
        helper = self._helper
        if (marks_text and helper is not None and pid == helper.process.pid
                and 0 <= taken <= self._read):  # fmt: skip
            self._marks_text = marks_text

    def restore(self, saved: Mapping[str, str]) -> int:
        """Before :meth:`open`: offer the received controllers a previous process kept
        (:meth:`fleet_state`) to the candidate pools again, and start from its marks, so the
        fleet's answers hold only what is new. The marks are believed only when every
        problem's controllers read back whole: a missing or corrupt state costs a whole
        pull, never a controller. Returns the candidates offered."""
        index = {spec.signature: i for i, spec in enumerate(self.specs)}
        offered, whole = 0, True
        for sig, i in index.items():
            text = saved.get(_CANDIDATES + sig)
            if text is None:
                whole = False
                continue
            _name, library = self._libraries[i]
            try:
                for active, origin, importance, uses, succ in json.loads(text):
                    entry = LibraryEntry(tuple(active), float(importance), int(uses), origin)
                    offered += library.offer(entry, str(origin),
                                             tuple(tuple(a) for a in succ))  # fmt: skip
            except (ValueError, TypeError):
                whole = False
        marks: list[list[Any]] = []
        with contextlib.suppress(ValueError, TypeError, AttributeError, KeyError):
            marks = [[str(sig), str(p), int(e), int(n)]
                     for sig, p, e, n in json.loads(saved[_MARKS])["held"]
                     if sig in index]  # fmt: skip
        if not whole:
            marks = []
        self._marks_text = json.dumps({"held": marks}, separators=(",", ":"))
        self.counters["restored_candidates"] += offered
        self.counters["restored_marks"] += len(marks)
        held = [[index[sig], p, e, n] for sig, p, e, n in marks]
        # a new epoch (numbers handed out after the last save may have reached a peer),
        # the old one's numbering of the library beside it: HighWater.former
        state: dict[str, Any] = {"epoch": int.from_bytes(os.urandom(6), "little"),
                                 "numbers": [[] for _ in self.specs], "held": held}
        former = self._former(saved.get(_OWN, ""))
        if former is not None:
            state["former"] = former
            self._own = saved[_OWN]  # kept in the store until a helper numbers the library
            self.counters["restored_numbers"] += sum(len(rows) for rows in former["numbers"])
        data = json.dumps(state, separators=(",", ":")).encode()
        if len(data) < _HIGH_WATER_BYTES:  # the first helper starts from these marks
            self._high_water_raw[: len(data) + 1] = data + b"\0"
        return offered

    def _former(self, text: str) -> dict[str, Any] | None:
        """The saved ``own`` numbering (:meth:`fleet_state`) by this process's problem
        order, or None (none, garbage, or no problem in common: the peers pull it whole)."""
        try:
            own = json.loads(text)
            by_sig = dict(zip(own["signatures"], own["numbers"], strict=True))
            numbers = [by_sig.get(spec.signature, []) for spec in self.specs]
            if not any(numbers) or numbering({"epoch": own["epoch"], "numbers": numbers},
                                             len(self.specs)) is None:  # fmt: skip
                return None
            return {"epoch": int(own["epoch"]), "numbers": numbers}
        except (ValueError, TypeError, KeyError):
            return None

    # -- for the service ------------------------------------------------------------------

    def live_reference(self, now_s: float, timeout_s: float) -> LiveReference | None:
        """The newest live reference if younger than ``timeout_s`` (``time.monotonic``)."""
        helper = self._helper
        if helper is not None:
            with contextlib.suppress(ChannelClosedError):  # run() notices the helper's death
                self._read_reference(helper)
        ref = self._reference
        if ref is None or now_s - ref.received_s > timeout_s:
            return None
        return ref

    def _slot(self, name: str) -> int:
        return int(self._slots[STAT_INDEX[name]])

    def stats(self) -> dict[str, int]:
        out = {name: int(v) for name, v in zip(STAT_NAMES, self._slots, strict=True)}
        del out["heartbeat_ns"]
        out.update(self.counters)
        helper = self._helper
        if helper is not None:
            out["outbox_bytes"] = helper.outbox.pending_bytes
            out["outbox_refused"] = helper.outbox.refused
        out["publish_waiting"] = len(self._backlog)
        out["publish_dropped"] = self._backlog.dropped
        counts = [library.fleet_counts() for _, library in self._libraries]
        out["candidates"] = sum(waiting for waiting, _ in counts)
        out["promoted"] = sum(promoted for _, promoted in counts)
        return out

    def process_stats(self) -> dict[str, Any]:
        """The helper process: CPU, its inbox and outbox, drops, failures and restarts."""
        helper = self._helper
        return process_report(
            self.helper_pid(), inbox=self._slot("candidates_waiting"),
            inbox_dropped=self._slot("dropped_queue_full"),
            outbox_bytes=helper.outbox.pending_bytes if helper is not None else 0,
            outbox_refused=helper.outbox.refused if helper is not None else 0,
            candidates_taken=self.counters["candidates_taken"],
            failures=self.counters["helper_failures"], restarts=self.counters["helper_restarts"],
        )  # fmt: skip

    def helper_running(self) -> bool:
        """Whether a helper has its Zenoh session open (until then, new controllers wait in
        the publish backlog)."""
        helper = self._helper
        return helper is not None and not helper.failed and self._slot("state") == 1

    def helper_pid(self) -> int | None:
        """The helper process's pid (fault tests kill it)."""
        return self._helper.process.pid if self._helper is not None else None


async def open_or_fly_alone(
    sharing: FleetSharing | None, counters: Counter[str]
) -> FleetSharing | None:
    """Join the fleet; a vehicle that cannot still flies, alone (logged, counted): returns
    the open session, or None."""
    if sharing is None:
        return None
    try:
        await sharing.open()
    except Exception as exc:
        counters["sharing_open_failed"] += 1
        log.error("fleet sharing unavailable, flying without it: %s", exc)
        sharing.close()
        return None
    return sharing
