"""The fleet's Zenoh session, in a process of its own (the fleet helper).

Everything a peer can make expensive runs here, at lower priority, never holding the
control process's interpreter lock: Zenoh's threads and the exchange's side of a received
message (:class:`epc_offboard.fleet.exchange.FleetExchange`: the size check, the fleet-wide
and per-peer token buckets, decoding and validation, the candidate inbox), answering library
queries from a prepared snapshot, publishing this vehicle's new controllers. This module
does the I/O: Zenoh, the pipes, the threads; what a message means is the exchange's. The
control process (:class:`epc_offboard.fleet.sharing.FleetSharing`)
reads decoded candidates as fixed-size records (:mod:`epc_offboard.fleet.records`) at most
``candidates_per_s`` a second, and the newest live reference; it sends new controllers and
library snapshots as frames. Counters and a heartbeat are slots of a shared int64 array.

Threads here: Zenoh's (callbacks: check, decode, queue), ``forward-candidates`` and
``forward-reference`` (blocking writes to the control process: when it does not read, they
wait and the inbox drops), ``frames`` (what the control process sends), and the main thread,
which does the rest (publishing, snapshots, library queries on a peer's arrival) and beats
the heartbeat: a main thread that stops turning is a wedged helper, and is restarted.
"""

from __future__ import annotations

import contextlib
import functools
import json
import logging
import os
import queue
import struct
import threading
import time
import zlib
from collections import OrderedDict
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
import numpy.typing as npt
import zenoh

from epc_offboard.common import logpipe
from epc_offboard.common.channel import ChannelClosedError, read_frames, write_all
from epc_offboard.common.children import die_with_parent, lower_priority
from epc_offboard.common.logsetup import LogConfig, setup_logging
from epc_offboard.control.candidate_pool import CandidatePoolConfig
from epc_offboard.control.library_types import LibraryEntry
from epc_offboard.fleet import keys
from epc_offboard.fleet.config import SharingConfig
from epc_offboard.fleet.exchange import (
    MAX_PEERS,
    FleetExchange,
    LimitedLog,
    Snapshot,
    TokenBuckets,
    batch_payloads,
    snapshot_payload,
)
from epc_offboard.fleet.records import STAT_INDEX, ProblemSpec, reference_record
from epc_offboard.fleet.wire import MessageKind, WireError, decode_reference

log = logging.getLogger("epc_offboard.fleet")

_MAX_REFERENCE_BYTES = 16384
_TURN_S = 0.1  # the main thread's heartbeat period when idle
# library snapshot queries (one per arriving peer) and arrival / departure log lines the whole
# fleet may cause: a fleet's genuine arrivals are rare, a flapping token's (1,000 a second,
# rotating ids) are not
_QUERIES_PER_S = 10.0
_QUERY_BURST = 20
_MAX_ARRIVALS = 256  # arrivals waiting for their query; beyond, the oldest is not queried
_REQUERY_ATTEMPTS = 3  # a library query no reply came back to is sent again, this many in all
_REQUERY_S = 1.0  # after this, then twice this
_MAX_ATTACHMENT_BYTES = 65536  # a query's or reply's high-water attachment, at most


def _attachment(obj: object) -> bytes:
    return json.dumps(obj, separators=(",", ":")).encode()


def _read_attachment(raw: zenoh.ZBytes | None) -> dict[str, Any]:
    """A peer's attachment as a dict, or {} (none, too large, or not ours: an outside Zenoh
    client's query gets the whole snapshot, as before)."""
    if raw is None or len(raw) > _MAX_ATTACHMENT_BYTES:
        return {}
    try:
        obj = json.loads(raw.to_bytes())
    except ValueError:
        return {}
    return obj if isinstance(obj, dict) else {}


def numbering(obj: Any, problems: int) -> tuple[int, list[dict[tuple[int, ...], int]]] | None:
    """``{"epoch": e, "numbers": [[[*active_set, number], ...] per problem]}`` read back
    (None: absent, malformed or for another set of problems)."""
    try:
        numbers = [{tuple(int(a) for a in row[:-1]): int(row[-1]) for row in rows}
                   for rows in obj["numbers"]]  # fmt: skip
        if len(numbers) != problems:
            return None
        return int(obj["epoch"]), numbers
    except (KeyError, TypeError, ValueError, IndexError):
        return None


class HighWater:
    """What makes a rejoin O(what is new) (issue 25).

    As an answerer: this vehicle numbers its controllers (per problem, 1, 2, ... in the order
    it first published or snapshotted each active set) under an ``epoch`` (random, per
    numbering). Each publication carries ``{"e": epoch, "p": last number before it, "s":
    last number after it}`` as a Zenoh attachment and each snapshot reply ``{"e", "s"}``.

    As a querier: per (problem, peer), the ``(epoch, number)`` up to which it holds that
    peer's controllers: set by a snapshot reply, advanced by a publication that follows on
    (its ``p`` is what is held). A library query carries ``{"h": {peer: [epoch, number]}}``;
    the peer answers only its controllers numbered above it, and an empty reply when there are
    none. A vehicle that rejoins (a router restarted, a network blip: the peers' liveliness
    tokens come back and each is queried) is answered with what it missed, not with every
    library again. Both tables are saved to a shared buffer that outlives the helper, so a
    restarted helper keeps them too. Without an attachment (an older vehicle, another tool)
    the whole snapshot goes, as before. Thread-safe (Zenoh delivers on several threads).

    A vehicle restarted as a new process numbers under a new epoch: numbers handed out after
    its store's last save may have reached a peer, so the old epoch cannot go on. Its
    library's numbers under the old epoch (``own``, kept by the store) come back as
    ``former``: a peer whose query carries a mark of that epoch is answered only the
    library's controllers the old numbering does not cover up to that mark (one it lacks a
    number for goes too), not the whole library again.
    """

    def __init__(self, problems: int, saved: bytes = b"", signatures: Sequence[str] = ()) -> None:
        # the problems' signatures, for the texts the store keeps (:meth:`save`'s ``texts``)
        self.signatures = list(signatures) or [str(i) for i in range(problems)]
        state = {}
        with contextlib.suppress(ValueError, UnicodeDecodeError):
            state = json.loads(saved.rstrip(b"\0") or b"{}")
        try:
            self.epoch = int(state["epoch"])
            self.numbers = [
                {tuple(row[:-1]): int(row[-1]) for row in rows} for rows in state["numbers"]
            ]
            self.held = {(int(i), str(peer)): (int(e), int(n)) for i, peer, e, n in state["held"]}
            if len(self.numbers) != problems:
                raise ValueError("another set of problems")
        except (KeyError, TypeError, ValueError):
            self.epoch = int.from_bytes(os.urandom(6), "little")
            self.numbers = [{} for _ in range(problems)]
            self.held = {}
        self.former = numbering(state.get("former") if isinstance(state, dict) else None,
                                problems)  # fmt: skip
        # per problem, the active sets of the library the last snapshot held (``own``)
        self.library: list[list[tuple[int, ...]]] = [[] for _ in range(problems)]
        self.last = [max(n.values(), default=0) for n in self.numbers]
        self._lock = threading.Lock()
        self.dirty = False
        # the marks as they stood when every controller they cover had left the helper's
        # inbox, and how many records it had handed out by then: (rows, taken); the
        # control process keeps these for a restart once it has read that many
        self.settled: tuple[list[list[Any]], int] | None = None
        self.unsettled = bool(self.held)

    def number(self, index: int, entries: Sequence[LibraryEntry]) -> tuple[int, int]:
        """Number the active sets not numbered yet; returns (last before, last after)."""
        with self._lock:
            numbers, before = self.numbers[index], self.last[index]
            for e in entries:
                if e.active_set not in numbers:
                    self.last[index] += 1
                    numbers[e.active_set] = self.last[index]
                    self.dirty = True
            return before, self.last[index]

    def forget(self, index: int, entries: Sequence[LibraryEntry], keep: int) -> None:
        """Numbers are kept for the library's controllers and the newest ``keep`` others (a
        long flight numbers thousands of active sets): a forgotten one learned again gets a
        new number, and travels again."""
        with self._lock:
            numbers = self.numbers[index]
            if len(numbers) <= len(entries) + keep:
                return
            live = {e.active_set for e in entries}
            recent = sorted(numbers.values())[-keep:]
            floor = recent[0] if recent else self.last[index] + 1
            self.numbers[index] = {a: n for a, n in numbers.items() if a in live or n >= floor}
            self.dirty = True

    def newer(self, index: int, entries: Sequence[LibraryEntry], since: int,
              former: bool = False) -> list[LibraryEntry]:  # fmt: skip
        """``entries`` numbered above ``since``; ``former``: in the former epoch's numbering,
        where one it does not number is newer too (learned after the store's last save)."""
        with self._lock:
            if former and self.former is not None:
                old = self.former[1][index]
                return [e for e in entries if old.get(e.active_set, since + 1) > since]
            numbers = self.numbers[index]
            return [e for e in entries if numbers.get(e.active_set, 0) > since]

    def of_library(self, index: int, entries: Sequence[LibraryEntry]) -> None:
        """The library's active sets as the last snapshot held them: their numbers are what
        :meth:`save` writes as ``own``, for the store to keep."""
        sets = [e.active_set for e in entries]
        with self._lock:
            if sets != self.library[index]:
                self.library[index] = sets
                self.dirty = True

    def query(self, index: int, peer: str) -> bytes:
        """The attachment of a query to ``peer`` (keys.ANY: every peer) for problem ``index``."""
        with self._lock:
            held = {p: list(v) for (i, p), v in self.held.items()
                    if i == index and (peer == keys.ANY or p == peer)}  # fmt: skip
        return _attachment({"h": held})

    def since(self, query: dict[str, Any], me: str) -> tuple[int, bool]:
        """The number above which a query's sender wants this vehicle's controllers (0: all),
        and whether it counts in the former epoch's numbering (:meth:`newer`)."""
        mine = query.get("h", {}).get(me) if isinstance(query.get("h"), dict) else None
        if not (isinstance(mine, list) and len(mine) == 2 and isinstance(mine[1], int)):
            return 0, False
        if mine[0] == self.epoch:
            return mine[1], False
        if self.former is not None and mine[0] == self.former[0]:
            return mine[1], True
        return 0, False

    def numbered(self, index: int, entries: Sequence[LibraryEntry]) -> int:
        """The highest number among ``entries`` (0: none numbered)."""
        with self._lock:
            numbers = self.numbers[index]
            return max((numbers.get(e.active_set, 0) for e in entries), default=0)

    def reply(self, numbered: int) -> bytes:
        return _attachment({"e": self.epoch, "s": numbered})

    def published(self, before: int, after: int) -> bytes:
        return _attachment({"e": self.epoch, "p": before, "s": after})

    def received(self, index: int, peer: str, att: dict[str, Any], follows_on: bool) -> None:
        """A peer's message arrived (valid); ``att`` its attachment. A snapshot reply
        (``follows_on`` False) sets what is held; a publication advances it only if it
        follows on from what is held (a missed one leaves the gap to the next query)."""
        e, n = att.get("e"), att.get("s")
        if not isinstance(e, int) or not isinstance(n, int):
            return
        with self._lock:
            key = (index, peer)
            if follows_on and self.held.get(key, (e, 0)) != (e, att.get("p")):
                return
            if self.held.get(key) != (e, n):
                self.held[key] = (e, n)
                if len(self.held) > MAX_PEERS * max(1, len(self.numbers)):
                    self.held.pop(next(iter(self.held)))
                self.dirty = self.unsettled = True

    def settle(self, drained: Callable[[], int | None]) -> None:
        """Take the marks as settled if the inbox has handed out every controller they
        cover: ``drained`` (the inbox's) is read after the marks are copied, and a
        controller's records are queued before its mark moves."""
        if not self.unsettled:
            return
        with self._lock:
            rows = [[i, p, e, n] for (i, p), (e, n) in self.held.items()]
            self.unsettled = False
        taken = drained()
        with self._lock:
            if taken is None:
                self.unsettled = True  # some wait: try again on a later turn
            else:
                self.settled = (rows, taken)
                self.dirty = True

    def save(self, buf: Any, texts: Any = None) -> None:
        """Into the shared buffer (a restarted helper reads it); too large: left empty. And
        into ``texts`` (:func:`write_texts`), the control process's: this numbering of the
        library and the settled marks as the texts the store keeps, made here, so that a
        save takes the control process's loops' thread a header and a copy, not a parse
        and a rebuild growing with the peers heard (issue 21: the rotate attack's)."""
        with self._lock:
            self.dirty = False
            # this numbering of the library, for the store
            own = {"epoch": self.epoch, "numbers": [
                [[*a, n[a]] for a in sets if a in n]
                for sets, n in zip(self.library, self.numbers, strict=True)]}  # fmt: skip
            data = _attachment({
                "epoch": self.epoch,
                "numbers": [[[*k, v] for k, v in n.items()] for n in self.numbers],
                "held": [[i, p, e, n] for (i, p), (e, n) in self.held.items()],
                **({"former": {"epoch": self.former[0],
                               "numbers": [[[*a, n] for a, n in f.items()]
                                           for f in self.former[1]]}}
                   if self.former is not None else {}),
                "own": own,
            })  # fmt: skip
            settled = self.settled
        if len(data) >= len(buf):
            data = b""
        buf[: len(data) + 1] = data + b"\0"
        if texts is None:
            return
        sigs = self.signatures
        own_text = _attachment(own)[:-1] + b',"signatures":' + json.dumps(sigs).encode() + b"}"
        marks = b""
        taken = -1
        if settled is not None:
            rows, taken = settled
            marks = _attachment({"held": [[sigs[i], str(p), int(e), int(n)]
                                          for i, p, e, n in rows]})  # fmt: skip
        write_texts(texts, os.getpid(), taken, own_text, marks)


# The texts of HighWater.save for the control process, in a shared buffer: a header (CRC-32 of
# the rest, the writing helper's pid, the records it had handed out when the marks settled,
# -1: none settled; the two texts' lengths), then the texts. The reader (written meanwhile,
# no lock) believes a copy whose CRC matches.
TEXTS_HEADER = struct.Struct("<Iqqii")


def write_texts(buf: Any, pid: int, taken: int, own: bytes, marks: bytes) -> bool:
    """``own`` and ``marks`` into ``buf`` after their header; False (left as it was) when
    they do not fit."""
    end = TEXTS_HEADER.size + len(own) + len(marks)
    if end > len(buf):
        return False
    head = TEXTS_HEADER.pack(0, pid, taken, len(own), len(marks))[4:]
    crc = zlib.crc32(marks, zlib.crc32(own, zlib.crc32(head)))
    view = memoryview(buf).cast("B")
    view[TEXTS_HEADER.size : end] = own + marks
    view[: TEXTS_HEADER.size] = TEXTS_HEADER.pack(crc, pid, taken, len(own), len(marks))
    return True


def read_texts(buf: Any, last_crc: int) -> tuple[int, int, int, bytes, bytes] | None:
    """(crc, pid, taken, own, marks) written by :func:`write_texts`, if new since the copy
    whose CRC was ``last_crc`` and whole (None: nothing new, none written, or caught
    mid-write). One header read when nothing is new; else one copy of the texts, bounded
    by the buffer."""
    view = memoryview(buf).cast("B")
    crc, _, _, own_n, marks_n = TEXTS_HEADER.unpack_from(view, 0)
    end = TEXTS_HEADER.size + own_n + marks_n
    if crc == last_crc or crc == 0 or own_n < 0 or marks_n < 0 or end > len(view):
        return None
    raw = bytes(view[:end])
    crc, pid, taken, own_n2, marks_n2 = TEXTS_HEADER.unpack_from(raw, 0)
    if (own_n2, marks_n2) != (own_n, marks_n) or zlib.crc32(raw[4:]) != crc:
        return None  # written meanwhile: the next save reads it whole
    own_at = TEXTS_HEADER.size
    return crc, pid, taken, raw[own_at : own_at + own_n], raw[own_at + own_n :]


class Counters:
    """The shared int64 slots (:data:`~epc_offboard.fleet.records.STAT_NAMES`): this process
    writes them (under a lock: several threads count), the control process reads them."""

    def __init__(self, slots: npt.NDArray[np.int64]) -> None:
        self.slots = slots
        self._lock = threading.Lock()

    def add(self, name: str, n: int = 1) -> None:
        with self._lock:
            self.slots[STAT_INDEX[name]] += n

    def set(self, name: str, value: int) -> None:
        self.slots[STAT_INDEX[name]] = value


class _LatestReference:
    """The newest live reference waiting to be forwarded (a newer one replaces it)."""

    def __init__(self) -> None:
        self._rec: bytes | None = None
        self._cond = threading.Condition()
        self.superseded = 0

    def put(self, rec: bytes) -> None:
        with self._cond:
            if self._rec is not None:
                self.superseded += 1
            self._rec = rec
            self._cond.notify()

    def take(self, timeout_s: float) -> bytes | None:
        with self._cond:
            if self._rec is None:
                self._cond.wait(timeout_s)
            rec, self._rec = self._rec, None
            return rec


@dataclass
class _Problem:
    index: int
    spec: ProblemSpec
    fleet: str
    snapshot: bytes = b""  # read by Zenoh's threads (one reference swap: atomic)
    # what the snapshot was made of (a delta answer's source) and its highest number
    library: tuple[list[LibraryEntry], dict[tuple[int, int], int], int] = ([], {}, 0)

    def key(self, template: str, vehicle: str) -> str:
        """This problem's key of ``template`` (:mod:`.keys`) for ``vehicle`` (or keys.ANY)."""
        return keys.problem_key(template, self.fleet, self.spec.signature, vehicle)


class FleetSession:
    """The Zenoh side of fleet sharing (the helper process's one object)."""

    def __init__(
        self,
        cfg: SharingConfig,
        specs: Sequence[ProblemSpec],
        counters: Counters,
        candidate_dtype: np.dtype[Any],
        max_successors: int,
        *,
        share_library: bool,
        reference: bool,
        inbox_per_peer: int = CandidatePoolConfig.backlog_per_peer,
        saved: bytes = b"",
    ) -> None:
        self.cfg = cfg
        # ``saved``: a previous helper's
        self.high_water = HighWater(len(specs), saved, [s.signature for s in specs])
        self.vehicle_id = cfg.vehicle_id
        self.share_library = share_library
        self.subscribe_reference = reference
        self.counters = counters
        self.dtype = candidate_dtype
        self.max_successors = max_successors
        self.problems = [
            _Problem(i, s, cfg.fleet) for i, s in enumerate(specs)
        ]
        self._log_limited = LimitedLog()
        self.exchange = FleetExchange(cfg, counters, candidate_dtype, max_successors,
                                      inbox_per_peer, self._log_limited)  # fmt: skip
        self.inbox = self.exchange.inbox  # what the forwarding thread hands on
        self.reference = _LatestReference()
        self.tasks: queue.Queue[tuple[Any, ...]] = queue.Queue(maxsize=cfg.queue_size)
        self.peers: dict[int, set[str]] = {}
        self._query_bucket = TokenBuckets(_QUERIES_PER_S, _QUERY_BURST)
        self._peer_log_bucket = TokenBuckets(_QUERIES_PER_S, _QUERY_BURST)
        # to be queried: (problem, peer) -> the attempt (0: an arrival; 1.. asked again)
        self._arrivals: OrderedDict[tuple[int, str], int] = OrderedDict()
        # queries no reply came back to, asked again later: (due, index, peer, attempt)
        self._requery: list[tuple[float, int, str, int]] = []
        self._lock = threading.Lock()
        self._session: zenoh.Session | None = None
        self._declared: list[Any] = []

    def zenoh_config(self) -> zenoh.Config:
        cfg = self.cfg
        conf = (
            zenoh.Config.from_file(cfg.zenoh_config_file)
            if cfg.zenoh_config_file
            else (zenoh.Config())
        )
        for path, value in cfg.zenoh_overrides.items():
            conf.insert_json5(path, json.dumps(value))
        conf.insert_json5("mode", json.dumps(cfg.mode))
        if cfg.listen:
            conf.insert_json5("listen/endpoints", json.dumps(list(cfg.listen)))
        if cfg.connect:
            conf.insert_json5("connect/endpoints", json.dumps(list(cfg.connect)))
        conf.insert_json5("scouting/multicast/enabled", json.dumps(cfg.scouting_multicast))
        return conf

    def open(self, snapshots: Sequence[Snapshot]) -> None:
        """Open the session and declare; ``snapshots``: each problem's library now, ready
        before the queryable can be asked."""
        self._session = s = zenoh.open(self.zenoh_config())
        vid = self.vehicle_id
        if self.share_library:
            for p, (entries, transitions) in zip(self.problems, snapshots, strict=True):
                self.prepare_snapshot(p.index, entries, transitions)
            for p in self.problems:
                self.peers[p.index] = set()
                self._declared += [
                    s.declare_subscriber(
                        p.key(keys.CONTROLLERS, keys.ANY),
                        functools.partial(self._on_batch, p),
                        allowed_origin=zenoh.Locality.REMOTE,
                    ),
                    s.declare_queryable(
                        p.key(keys.LIBRARY, vid), functools.partial(self._on_query, p)
                    ),
                    s.liveliness().declare_subscriber(
                        p.key(keys.ALIVE, keys.ANY),
                        functools.partial(self._on_alive, p),
                        history=True,
                    ),
                    s.liveliness().declare_token(p.key(keys.ALIVE, vid)),
                ]
                self._query_library(p, "*")
        if self.subscribe_reference:
            self._declared.append(
                s.declare_subscriber(keys.reference_key(self.cfg.fleet, vid), self._on_reference)
            )
        log.info(
            "fleet %s: vehicle %s sharing %s (listen %s, connect %s, multicast scouting %s; "
            "process %d)",
            self.cfg.fleet,
            vid,
            ", ".join(f"{p.spec.name} {p.spec.signature}" for p in self.problems)
            if self.share_library
            else "no library",
            list(self.cfg.listen),
            list(self.cfg.connect),
            "on" if self.cfg.scouting_multicast else "off",
            os.getpid(),
        )

    def close(self) -> None:
        for obj in reversed(self._declared):
            try:
                obj.undeclare()
            except Exception as exc:  # closing must not fail the shutdown
                log.debug("undeclare failed: %s", exc)
        self._declared.clear()
        if self._session is not None:
            self._session.close()  # type: ignore[no-untyped-call]
            self._session = None

    # -- the main thread: what the control process asks, and peers' arrivals ---------------

    def handle(self, task: tuple[Any, ...]) -> None:
        kind = task[0]
        if kind == "publish":
            self.publish(task[1], task[2])
            self.counters.set("publish_seq_done", task[3])  # the control process may forget it
        elif kind == "snapshot":
            self.prepare_snapshot(task[1], task[2], task[3])
        elif kind == "peer":
            self._peer_changed(task[1], task[2], task[3])

    def publish(self, index: int, entries: list[LibraryEntry]) -> None:
        """Publish this vehicle's new controllers (most important first), in payloads that
        each fit ``max_payload_bytes``."""
        p = self.problems[index]
        if self._session is None:
            return
        for payload, chunk in batch_payloads(p.spec.signature, self.vehicle_id, entries,
                                             self.cfg.max_payload_bytes):  # fmt: skip
            attachment = self.high_water.published(*self.high_water.number(p.index, chunk))
            try:
                self._session.put(
                    p.key(keys.CONTROLLERS, self.vehicle_id),
                    payload,
                    congestion_control=zenoh.CongestionControl.DROP,
                    attachment=attachment,
                )
            except zenoh.ZError as exc:
                self.counters.add("publish_errors")
                self._log_limited("publish", p.spec.name, "publishing controllers failed: %s", exc)
                continue
            self.counters.add("entries_published", len(chunk))
            self.counters.add("bytes_published", len(payload) + len(attachment))

    def prepare_snapshot(
        self, index: int, entries: list[LibraryEntry], transitions: dict[tuple[int, int], int]
    ) -> None:
        p = self.problems[index]
        self.high_water.number(index, entries)
        self.high_water.forget(index, entries, keep=p.spec.max_entries)
        numbered = self.high_water.numbered(index, entries)
        self.high_water.of_library(index, entries)
        p.snapshot = snapshot_payload(p.spec.signature, self.vehicle_id, entries, transitions,
                                      self.cfg.max_payload_bytes)  # fmt: skip
        p.library = (entries, transitions, numbered)
        self.counters.add("snapshots_prepared")

    def _peer_changed(self, index: int, peer: str, joined: bool) -> None:
        p = self.problems[index]
        peers = self.peers.setdefault(index, set())
        if joined and peer not in peers:
            if len(peers) >= MAX_PEERS:
                return
            peers.add(peer)
            self.counters.add("peer_joins")
            with self._lock:  # its library is queried on the main thread's turn, in budget
                self._arrivals[(index, peer)] = 0
                self._arrivals.move_to_end((index, peer))
                if len(self._arrivals) > _MAX_ARRIVALS:
                    self._arrivals.popitem(last=False)
                    self.counters.add("queries_skipped")
            if self._peer_log_bucket.allow("fleet", time.monotonic()):
                log.info("fleet %s: vehicle %s joined (%s)", self.cfg.fleet, peer, p.spec.name)
        elif not joined and peer in peers:
            peers.discard(peer)
            self.counters.add("peer_leaves")
            if self._peer_log_bucket.allow("fleet", time.monotonic()):
                log.info("fleet %s: vehicle %s left (%s)", self.cfg.fleet, peer, p.spec.name)
        self.counters.set("peers", len(set().union(*self.peers.values())))

    def query_arrivals(self) -> None:
        """Query the library of each peer that arrived and is still here, oldest first, within
        the fleet's query budget (the rest wait for the next turn): a flapping token (1,000
        arrivals a second from rotating ids in ``bench --attack``) made a query and a log line
        of each arrival (19,600 lines a flight); its ids are gone by the next turn, while a
        returning vehicle (a router restarted) is still here and is queried."""
        now = time.monotonic()
        with self._lock:
            due = [r for r in self._requery if r[0] <= now]
            self._requery = [r for r in self._requery if r[0] > now]
            for _, index, peer, attempt in due:
                self._arrivals[(index, peer)] = attempt
        while True:
            with self._lock:
                if not self._arrivals:
                    return
                (index, peer), attempt = next(iter(self._arrivals.items()))
                if peer in self.peers.get(index, ()):
                    if not self._query_bucket.allow("fleet", now):
                        return
                    del self._arrivals[(index, peer)]
                else:  # left again: nothing to query
                    del self._arrivals[(index, peer)]
                    continue
            self._query_library(self.problems[index], peer, attempt)

    def _query_library(self, p: _Problem, peer: str, attempt: int = 0) -> None:
        """Query ``peer``'s library (keys.ANY: every peer's); ``attempt``: how many times
        this peer was asked already without a reply (:meth:`_query_done`)."""
        if self._session is None:
            return
        self.counters.add("queries_sent")
        replied = [False]
        try:
            self._session.get(
                p.key(keys.LIBRARY, peer),
                zenoh.handlers.Callback(
                    functools.partial(self._on_reply, p, replied),
                    functools.partial(self._query_done, p, peer, replied, attempt),
                ),
                timeout=self.cfg.query_timeout_s,
                allowed_destination=zenoh.Locality.REMOTE,  # not our own queryable
                attachment=self.high_water.query(p.index, peer),  # what is held already
            )
        except zenoh.ZError as exc:
            self.counters.add("query_errors")
            self._log_limited("query", peer, "querying %s's library failed: %s", peer, exc)

    # -- Zenoh's threads ------------------------------------------------------------------

    def _on_batch(self, p: _Problem, sample: zenoh.Sample) -> None:
        sender = self.exchange.receive(p.index, p.spec, str(sample.key_expr), sample.payload,
                                       MessageKind.BATCH)  # fmt: skip
        if sender:
            self.high_water.received(p.index, sender, _read_attachment(sample.attachment), True)

    def _on_reply(self, p: _Problem, replied: list[bool], reply: zenoh.Reply) -> None:
        sample = reply.ok
        if sample is None:
            self.counters.add("query_errors")
            return
        replied[0] = True
        if len(sample.payload) == 0:  # the peer holds nothing we lack (:meth:`_on_query`)
            self.counters.add("replies_up_to_date")
            return
        sender = self.exchange.receive(p.index, p.spec, str(sample.key_expr), sample.payload,
                                       MessageKind.SNAPSHOT)  # fmt: skip
        if sender:
            self.high_water.received(p.index, sender, _read_attachment(sample.attachment), False)

    def _query_done(self, p: _Problem, peer: str, replied: list[bool], attempt: int) -> None:
        """A library query ended. With no reply, the peer is asked again, up to
        ``_REQUERY_ATTEMPTS`` times ``_REQUERY_S`` apart while it is still here: a query sent
        as a restarted router brings the fleet back can reach the peer's liveliness token
        before its queryable and be lost (test_fleet_rejoin lost 2 of 3). A peer that holds
        nothing new replies, empty."""
        if replied[0] or attempt + 1 >= _REQUERY_ATTEMPTS:
            return
        with self._lock:
            if peer in self.peers.get(p.index, ()):
                due = time.monotonic() + _REQUERY_S * (attempt + 1)
                self._requery.append((due, p.index, peer, attempt + 1))
                self._requery = self._requery[-_MAX_ARRIVALS:]
                self.counters.add("queries_repeated")

    def _on_query(self, p: _Problem, query: zenoh.Query) -> None:
        """Answer with what the querier does not hold yet (:class:`HighWater`): nothing when
        it holds everything, the controllers numbered above its mark, or the snapshot."""
        self.counters.add("queries_answered")
        hw = self.high_water
        since, former = hw.since(_read_attachment(query.attachment), self.vehicle_id)
        entries, transitions, numbered = p.library
        payload = p.snapshot
        if since:
            newer = hw.newer(p.index, entries, since, former)
            if not newer:  # (numbered <= since)
                # an empty reply, not silence: silence is a lost query, asked again
                # (:meth:`_query_done`), and a repeat racing a publication pulled that
                # publication twice (test_fleet_rejoin, CI)
                self.counters.add("queries_up_to_date")
                self._reply(query, p, b"", hw.reply(numbered))
                return
            keep = {id(e) for e in newer}
            index = {id(e): i for i, e in enumerate(newer)}
            trans = {(index[id(entries[a])], index[id(entries[b])]): n
                     for (a, b), n in transitions.items()
                     if id(entries[a]) in keep and id(entries[b]) in keep}  # fmt: skip
            payload = snapshot_payload(p.spec.signature, self.vehicle_id, newer, trans,
                                       self.cfg.max_payload_bytes)  # fmt: skip
        # the mark the querier holds after this: the snapshot's highest number (one that is
        # newer went out in a publication, or comes with the next snapshot)
        self._reply(query, p, payload, hw.reply(numbered))

    def _reply(self, query: zenoh.Query, p: _Problem, payload: bytes, attachment: bytes) -> None:
        self.counters.add("bytes_answered", len(payload) + len(attachment))
        try:
            query.reply(p.key(keys.LIBRARY, self.vehicle_id), payload, attachment=attachment)
        except zenoh.ZError as exc:
            self.counters.add("query_reply_errors")
            self._log_limited("reply", "", "answering a library query failed: %s", exc)

    def _on_alive(self, p: _Problem, sample: zenoh.Sample) -> None:
        peer = str(sample.key_expr).rsplit("/", 1)[-1]
        if peer == self.vehicle_id:
            return
        joined = sample.kind == zenoh.SampleKind.PUT
        try:  # the query goes from the main thread, not from inside Zenoh's callback
            self.tasks.put_nowait(("peer", p.index, peer, joined))
        except queue.Full:
            self.counters.add("tasks_dropped")

    def _on_reference(self, sample: zenoh.Sample) -> None:
        payload = sample.payload
        if len(payload) > _MAX_REFERENCE_BYTES:
            self.counters.add("reference_rejected")
            return
        try:
            msg = decode_reference(payload.to_bytes(), max_payload_bytes=_MAX_REFERENCE_BYTES)
        except WireError as exc:
            self.counters.add("reference_rejected")
            self._log_limited("reference", "", "rejected a live reference: %s", exc)
            return
        self.counters.add("references_received")
        self.reference.put(reference_record(msg, time.monotonic()).tobytes())


# -- the helper process ----------------------------------------------------------------------


@dataclass(frozen=True)
class HelperArgs:
    """What the helper process is started with (pickled by ``spawn``)."""

    cfg: SharingConfig
    specs: tuple[ProblemSpec, ...]
    candidate_dtype: np.dtype[Any]
    max_successors: int
    share_library: bool
    reference: bool
    snapshots: tuple[Snapshot, ...]
    parent_pid: int
    log: LogConfig
    inbox_per_peer: int  # received controllers held from one vehicle (a library's backlog)


def _forward(
    take: Callable[[float], bytes | None], fd: int, stop: threading.Event, count: Callable[[], None]
) -> None:
    """Hand records to the control process, blocking while it does not read them."""
    try:
        while not stop.is_set():
            rec = take(_TURN_S)
            if rec is not None:
                write_all(fd, rec)
                count()
    except (ChannelClosedError, OSError):
        pass  # the control process is gone
    except Exception:  # a bug here: the helper ends and is restarted, the loops fly on
        log.exception("fleet helper: %s failed", threading.current_thread().name)
    finally:
        stop.set()


def _read_frames(fd: int, tasks: queue.Queue[tuple[Any, ...]], stop: threading.Event) -> None:
    for frame in read_frames(fd):
        tasks.put(frame)  # blocking: a full queue backs up into the control's bounded outbox
    stop.set()  # EOF: the control process closed its end (shutdown) or died


def helper_main(args: HelperArgs, slots: Any, candidates_fd: Any, reference_fd: Any,
                frames_fd: Any, saved: Any, texts: Any = None) -> None:  # fmt: skip
    """The fleet helper process: the session, its forwarders, and the main thread's turns
    until the control process closes the frames pipe (or dies)."""
    die_with_parent(args.parent_pid)
    lower_priority(args.cfg.helper_nice)
    setup_logging(args.log)
    logpipe.direct_stderr()  # a held stderr (journald) stalls none of the session's work
    counters = Counters(np.frombuffer(slots, dtype=np.int64))
    session = FleetSession(
        args.cfg, args.specs, counters, args.candidate_dtype, args.max_successors,
        share_library=args.share_library, reference=args.reference,
        inbox_per_peer=args.inbox_per_peer, saved=bytes(saved.raw),
    )  # fmt: skip
    try:
        session.open(args.snapshots)
    except Exception as exc:  # refused by the router (TLS, credentials), no route, bad config
        counters.add("session_open_failures")
        counters.set("state", -1)
        log.error("fleet session could not open: %s", exc)
        return
    # beat before saying open: a state of 1 with no beat yet reads as a helper long silent
    counters.set("heartbeat_ns", time.monotonic_ns())
    counters.set("state", 1)
    stop = threading.Event()
    def counter(name: str) -> Callable[[], None]:
        return functools.partial(counters.add, name)

    threads = [
        threading.Thread(target=_forward, name="forward-candidates", daemon=True,
                         args=(session.inbox.take, candidates_fd.fileno(), stop,
                               counter("candidates_forwarded"))),
        threading.Thread(target=_forward, name="forward-reference", daemon=True,
                         args=(session.reference.take, reference_fd.fileno(), stop,
                               counter("references_forwarded"))),
        threading.Thread(target=_read_frames, args=(frames_fd.fileno(), session.tasks, stop),
                         name="frames", daemon=True),
    ]  # fmt: skip
    for t in threads:
        t.start()
    try:
        while not stop.is_set():
            counters.set("heartbeat_ns", time.monotonic_ns())
            counters.set("candidates_waiting", len(session.inbox))
            counters.set("references_superseded", session.reference.superseded)
            session.query_arrivals()
            session.high_water.settle(session.inbox.drained)
            if session.high_water.dirty:
                session.high_water.save(saved, texts)
            try:
                task = session.tasks.get(timeout=_TURN_S)
            except queue.Empty:
                continue
            try:
                session.handle(task)
            except Exception as exc:  # one bad task must not take the fleet down
                log.error("fleet helper: %s failed: %s", task[0], exc)
    finally:
        session.close()
        os._exit(0)  # no interpreter teardown: the service's shutdown waits for this exit
