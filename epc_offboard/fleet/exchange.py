"""The fleet exchange: peers' messages ↔ offers to this vehicle's libraries, and back. Pure
(no Zenoh, no processes): :mod:`epc_offboard.fleet.session` does the I/O and calls it.

A fleet message, in order (docs/DESIGN.md, "a fleet message, file by file"):

1. the helper process's Zenoh callback (``FleetSession._on_batch`` or ``._on_reply``) hands
   the payload to :meth:`FleetExchange.receive`: size check, the fleet-wide and per-peer
   token buckets, decoding and validation (:func:`~epc_offboard.fleet.wire.decode_controllers`
   against the problem's :class:`~epc_offboard.fleet.records.ProblemSpec`), the sender and
   kind checks, and the message's entries become fixed-size candidate records
   (:func:`candidate_records`, with their likeliest successors) queued in the
   :class:`CandidateInbox` (bounded in total and per peer, fair, duplicates dropped);
2. a forwarding thread there writes them to the control process's pipe;
3. the control process's ``library-sharing`` task (``FleetSharing.poll``) reads at most its
   budget of records a turn and calls :func:`offer_records`, which turns each back into an
   entry (:func:`candidate_of`) and offers it to that problem's :class:`FleetLibrary`;
4. the controller's side of that protocol
   (:class:`epc_offboard.control.epc.exchange.FleetPort`) puts it in the candidate pool; it
   joins the library when it passes this vehicle's KKT check at a miss.

Outgoing: :func:`chunks` splits this vehicle's new controllers into batch payloads and
:func:`snapshot_payload` prepares what a late joiner's library query gets.

Rate limits: one token bucket per sending vehicle id. A bucket that has refilled is
forgotten (a new one is the same), and when the table is full the least recently heard
sender's is dropped: a flood from many rotating ids never locks a new, legitimate peer out.
"""

from __future__ import annotations

import logging
import threading
import time
from collections import Counter, OrderedDict, deque
from collections.abc import Iterator, Mapping, Sequence
from typing import Any, Protocol

import numpy as np
import numpy.typing as npt

from epc_offboard.control.library_types import LibraryEntry
from epc_offboard.fleet.config import SharingConfig
from epc_offboard.fleet.records import ActiveSet, ProblemSpec, Records
from epc_offboard.fleet.wire import (
    MAX_VEHICLE_ID_LEN,
    ControllerMessage,
    MessageKind,
    WireError,
    decode_controllers,
    encode_controllers,
)

log = logging.getLogger("epc_offboard.fleet")

MAX_PEERS = 1024  # token buckets and per-sender counts kept (least recently heard dropped)
_LOG_EVERY_S = 5.0  # at most one log line per reason and peer this often
_TRANSITION_BYTES = 12  # one (from, to, count) on the wire (wire._TRANSITION)

Snapshot = tuple[list[LibraryEntry], dict[tuple[int, int], int]]  # entries, transitions


class FleetLibrary(Protocol):
    """What the exchange needs of one shared controller's library (the controller's side:
    :class:`epc_offboard.control.epc.exchange.FleetPort`)."""

    def offer(self, entry: LibraryEntry, origin: str, successors: tuple[ActiveSet, ...]) -> bool:
        """Take a peer's controller as a candidate (``origin``: ``shared:<vehicle>``);
        whether it was new."""
        ...

    def new_entries(self) -> list[LibraryEntry]:
        """Controllers learned here since the last call (to publish)."""
        ...

    def snapshot(self) -> Snapshot:
        """The library now (what a peer's query gets), most important first."""
        ...

    def fleet_counts(self) -> tuple[int, int]:
        """(candidates waiting in the pool, candidates promoted into the library)."""
        ...

    def received(self) -> list[tuple[LibraryEntry, tuple[ActiveSet, ...]]]:
        """Received controllers not in the library, each with its successors (kept on
        disk by a vehicle that restarts)."""
        ...

    def received_parts(
        self, per_part: int
    ) -> Iterator[list[tuple[LibraryEntry, tuple[ActiveSet, ...]]]]:
        """:meth:`received` in parts of at most ``per_part`` (a saver on the loops' thread
        lets them tick in between)."""
        ...


class Tally(Protocol):
    """Where the exchange counts (the helper's shared slots)."""

    def add(self, name: str, n: int = 1) -> None: ...

    def set(self, name: str, value: int) -> None: ...


class Payload(Protocol):
    """A received payload (``zenoh.ZBytes``): its size is checked before it is copied."""

    def __len__(self) -> int: ...

    def to_bytes(self) -> bytes: ...


class LimitedLog:
    """Warnings at most one per reason and peer every ``_LOG_EVERY_S`` (thread-safe)."""

    def __init__(self) -> None:
        self._last: dict[tuple[str, str], float] = {}
        self._lock = threading.Lock()

    def __call__(self, reason: str, peer: str, fmt: str, *args: object) -> None:
        now = time.monotonic()
        with self._lock:
            last = self._last.get((reason, peer), -float("inf"))
            if now - last < _LOG_EVERY_S:
                return
            if len(self._last) > MAX_PEERS:
                self._last.clear()
            self._last[(reason, peer)] = now
        log.warning(fmt, *args)


class TokenBuckets:
    """Per-peer token buckets that expire (thread-safe: Zenoh delivers on several threads).

    A bucket idle for its refill time (``burst / rate``) is full again, the same as a new
    one, so it is dropped. At most ``max_peers`` are kept: beyond, the least recently used
    goes. A sender is never refused for being new: spoofed, rotating ids each get a burst,
    which the bounded inbox absorbs.
    """

    def __init__(self, rate_per_s: float, burst: int, max_peers: int = MAX_PEERS) -> None:
        self._rate = rate_per_s
        self._burst = float(burst)
        self._refill_s = burst / rate_per_s
        self._max_peers = max_peers
        self._state: OrderedDict[str, tuple[float, float]] = OrderedDict()  # LRU first
        self._lock = threading.Lock()
        self.evicted = 0  # buckets dropped while not yet refilled (table full)

    def __len__(self) -> int:
        return len(self._state)

    def allow(self, peer: str, now_s: float) -> bool:
        with self._lock:
            state = self._state.pop(peer, None)
            if state is None:
                self._expire(now_s)
                state = (self._burst, now_s)
            tokens, last = state
            tokens = min(self._burst, tokens + (now_s - last) * self._rate)
            ok = tokens >= 1.0
            self._state[peer] = (tokens - 1.0 if ok else tokens, now_s)  # most recent last
            return ok

    def _expire(self, now_s: float) -> None:
        """Make room for one more: drop refilled buckets, then the least recently used."""
        state = self._state
        while state:
            peer, (_tokens, last) = next(iter(state.items()))
            if now_s - last >= self._refill_s:
                del state[peer]
            elif len(state) >= self._max_peers:
                del state[peer]
                self.evicted += 1
            else:
                break


def successors_of(
    msg: ControllerMessage, max_successors: int
) -> dict[tuple[int, ...], tuple[tuple[int, ...], ...]]:
    """Each entry's likeliest successors in the sender's transition counts (most frequent
    first, at most ``max_successors``), by active set."""
    n = len(msg.entries)
    out: dict[int, list[tuple[int, int]]] = {}
    for a, b, count in msg.transitions:
        if 0 <= a < n and 0 <= b < n and a != b:
            out.setdefault(a, []).append((count, b))
    return {
        msg.entries[a].active_set: tuple(
            msg.entries[b].active_set for _, b in sorted(succ, reverse=True)[:max_successors]
        )
        for a, succ in out.items()
    }


def chunks(
    entries: Sequence[LibraryEntry], max_payload_bytes: int
) -> list[tuple[LibraryEntry, ...]]:
    """Split into messages that each fit ``max_payload_bytes`` (in the order given)."""
    budget = max_payload_bytes - 64  # header + id + count
    out: list[tuple[LibraryEntry, ...]] = []
    cur: list[LibraryEntry] = []
    size = 0
    for e in entries:
        n = 14 + 2 * len(e.active_set)
        if n > budget:
            continue
        if size + n > budget or len(cur) >= 0xFFFF:
            out.append(tuple(cur))
            cur, size = [], 0
        cur.append(e)
        size += n
    if cur:
        out.append(tuple(cur))
    return out


def batch_payloads(
    signature: str, vehicle_id: str, entries: Sequence[LibraryEntry], max_payload_bytes: int
) -> list[tuple[bytes, Sequence[LibraryEntry]]]:
    """This vehicle's new controllers as BATCH payloads that each fit ``max_payload_bytes``:
    (payload, the entries in it)."""
    return [
        (encode_controllers(ControllerMessage(MessageKind.BATCH, signature, vehicle_id, chunk)),
         chunk)
        for chunk in chunks(entries, max_payload_bytes)
    ]  # fmt: skip


def snapshot_payload(
    signature: str, vehicle_id: str, entries: list[LibraryEntry],
    transitions: dict[tuple[int, int], int] | None, max_payload_bytes: int,
) -> bytes:
    """The snapshot a late joiner's query gets: the most important controllers that fit one
    payload, and as many of their transition counts (most frequent first) as still fit —
    they tell the joiner which controller is likely next."""
    parts = chunks(entries, max_payload_bytes)
    kept = parts[0] if parts else ()
    index = {id(e): i for i, e in enumerate(kept)}
    room = max_payload_bytes - 64 - 4 - sum(14 + 2 * len(e.active_set) for e in kept)
    trans = sorted(
        (
            (index[id(entries[a])], index[id(entries[b])], n)
            for (a, b), n in (transitions or {}).items()
            if id(entries[a]) in index and id(entries[b]) in index
        ),
        key=lambda t: -t[2],
    )[: max(0, room // _TRANSITION_BYTES)]
    return encode_controllers(
        ControllerMessage(MessageKind.SNAPSHOT, signature, vehicle_id, kept, tuple(trans))
    )  # fmt: skip


class CandidateInbox:
    """Decoded candidates waiting for the control process: at most ``max_total`` records,
    ``max_per_peer`` from one sender, handed out one peer at a time in turn (a flood from
    many ids delays a real peer by a turn, never locks it out); an active set already
    handed out recently is dropped as a duplicate."""

    def __init__(self, max_total: int, max_per_peer: int) -> None:
        self.max_total = max_total
        self.max_per_peer = max_per_peer
        self._queues: OrderedDict[str, deque[bytes]] = OrderedDict()  # next turn first
        self._total = 0
        self._seen: OrderedDict[bytes, None] = OrderedDict()  # (problem, active set) keys
        self._cond = threading.Condition()
        self.taken = 0  # records handed out, ever (counted as taken: see :meth:`drained`)

    def __len__(self) -> int:
        return self._total

    def put(self, peer: str, records: npt.NDArray[Any]) -> tuple[int, int, int]:
        """Queue ``records`` from ``peer``; returns (queued, duplicates, dropped)."""
        queued = dup = dropped = 0
        with self._cond:
            q = self._queues.get(peer)
            for rec in records:
                key = rec["problem"].tobytes() + rec["active"][: rec["n_active"]].tobytes()
                if key in self._seen:
                    self._seen.move_to_end(key)
                    dup += 1
                    continue
                if q is not None and len(q) >= self.max_per_peer:
                    q.popleft()  # a peer's newest (its most used last) win its quota
                    self._total -= 1
                    dropped += 1
                elif self._total >= self.max_total or (
                    q is None and len(self._queues) >= MAX_PEERS
                ):
                    dropped += 1
                    continue
                if q is None:
                    q = self._queues[peer] = deque()
                q.append(rec.tobytes())
                self._total += 1
                self._seen[key] = None
                if len(self._seen) > 4 * self.max_total:
                    self._seen.popitem(last=False)
                queued += 1
            if queued:
                self._cond.notify()
        return queued, dup, dropped

    def drained(self) -> int | None:
        """When nothing waits: how many records were ever taken (the forwarder writes each
        to the control process's pipe, in order, after taking it); None while some wait."""
        with self._cond:
            return None if self._total else self.taken

    def take(self, timeout_s: float) -> bytes | None:
        with self._cond:
            if not self._total and not self._cond.wait(timeout_s):
                return None
            if not self._queues:
                return None
            peer, q = next(iter(self._queues.items()))
            rec = q.popleft()
            self._total -= 1
            self.taken += 1
            if q:
                self._queues.move_to_end(peer)  # its next one after everyone else's
            else:
                del self._queues[peer]
            return rec


def candidate_dtype(max_active: int, max_successors: int) -> np.dtype[Any]:
    """One received controller: ``active[:n_active]`` is its active set; successor ``k`` is
    ``successors[k, :successor_len[k]]`` for ``k < n_successors``."""
    return np.dtype(
        [
            ("problem", "u1"),  # index into the shared problems
            ("n_active", "u2"),
            ("n_successors", "u1"),
            ("importance", "f8"),
            ("uses", "u4"),
            ("origin", f"S{MAX_VEHICLE_ID_LEN}"),  # the sender's vehicle id (ASCII, checked)
            ("active", "u2", (max_active,)),
            ("successor_len", "u2", (max_successors,)),
            ("successors", "u2", (max_successors, max_active)),
        ]
    )


def candidate_records(
    msg: ControllerMessage,
    problem: int,
    dtype: np.dtype[Any],
    successors: Mapping[ActiveSet, Sequence[ActiveSet]],
) -> Records:
    """``msg``'s entries as records, the sender's least used first (a peer past its pool
    quota keeps its most used, offered last)."""
    entries = sorted(msg.entries, key=lambda e: (e.uses, e.importance))
    out = np.zeros(len(entries), dtype=dtype)
    max_succ = dtype["successor_len"].shape[0]
    out["problem"] = problem
    out["origin"] = msg.vehicle_id.encode()
    for i, e in enumerate(entries):
        row = out[i]
        row["n_active"] = len(e.active_set)
        row["active"][: len(e.active_set)] = e.active_set
        row["importance"] = e.importance
        row["uses"] = e.uses
        succ = list(successors.get(e.active_set, ()))[:max_succ]
        row["n_successors"] = len(succ)
        for k, s in enumerate(succ):
            row["successor_len"][k] = len(s)
            row["successors"][k, : len(s)] = s
    return out


def candidate_of(row: Any) -> tuple[LibraryEntry, str, tuple[ActiveSet, ...]]:
    """A record back as (entry, origin ``shared:<vehicle>``, successors)."""
    n = int(row["n_active"])
    active = tuple(row["active"][:n].tolist())
    lens = row["successor_len"].tolist()
    succ = tuple(
        tuple(row["successors"][k, : lens[k]].tolist()) for k in range(int(row["n_successors"]))
    )
    entry = LibraryEntry(active, float(row["importance"]), int(row["uses"]))
    return entry, f"shared:{row['origin'].decode()}", succ




class FleetExchange:
    """The helper's side: peers' payloads in, candidate records queued for the control
    process (thread-safe: Zenoh delivers on several threads)."""

    def __init__(
        self, cfg: SharingConfig, tally: Tally, candidate_dtype: np.dtype[Any],
        max_successors: int, inbox_per_peer: int, log_limited: LimitedLog,
    ) -> None:  # fmt: skip
        self.cfg = cfg
        self.vehicle_id = cfg.vehicle_id
        self.tally = tally
        self.dtype = candidate_dtype
        self.max_successors = max_successors
        self.inbox = CandidateInbox(cfg.max_queued_entries, inbox_per_peer)
        self._buckets = TokenBuckets(cfg.max_messages_per_s, cfg.burst_messages)
        # all peers together: rotating ids each get a fresh burst, so without a fleet-wide
        # limit a flood is decoded in full (here, at least, in a process of its own)
        self._fleet_bucket = TokenBuckets(
            cfg.fleet_messages_per_s, cfg.fleet_burst_messages, max_peers=1
        )
        self._senders: OrderedDict[str, None] = OrderedDict()
        self._lock = threading.Lock()
        self._log_limited = log_limited

    def receive(
        self, problem: int, spec: ProblemSpec, key: str, payload: Payload, kind: MessageKind
    ) -> str:
        """One payload from ``key`` (its last part names the sender) for shared problem
        ``problem``: checked, rate-limited, decoded, validated, queued as candidates. Returns
        the sender when the message was valid (its high-water marks may then be believed),
        else ""."""
        sender = key.rsplit("/", 1)[-1]
        if not self._admitted(sender, key, len(payload)):
            return ""
        msg = self._decoded(spec, sender, key, payload, kind)
        if msg is None:
            return ""
        self.tally.add("entries_received", len(msg.entries))
        records = candidate_records(
            msg, problem, self.dtype, successors_of(msg, self.max_successors)
        )
        self._queue(spec, sender, msg.kind, records)
        return sender

    def _admitted(self, sender: str, key: str, size: int) -> bool:
        """Not our own, within the size limit and both token buckets (the sender counted as
        heard): before anything is copied or decoded."""
        count = self.tally.add
        if sender == self.vehicle_id:
            count("own_ignored")
            return False
        count("messages_received")
        count("bytes_received", size)
        if size > self.cfg.max_payload_bytes:
            count("rejected_oversized")
            self._log_limited("size", sender, "dropped a %d-byte payload from %s (limit %d)",
                              size, sender, self.cfg.max_payload_bytes)  # fmt: skip
            return False
        now = time.monotonic()
        if not self._fleet_bucket.allow("fleet", now):
            count("fleet_rate_limited")
            self._log_limited("fleet-rate", "fleet", "rate-limiting the fleet: %s on %s",
                              sender, key)  # fmt: skip
            return False
        if not self._buckets.allow(sender, now):
            count("rate_limited")
            self._log_limited("rate", sender, "rate-limiting vehicle %s on %s", sender, key)
            return False
        with self._lock:
            self._senders.pop(sender, None)
            self._senders[sender] = None
            if len(self._senders) > MAX_PEERS:
                self._senders.popitem(last=False)  # the least recently heard
            self.tally.set("senders", len(self._senders))
        return True

    def _decoded(
        self, spec: ProblemSpec, sender: str, key: str, payload: Payload, kind: MessageKind
    ) -> ControllerMessage | None:
        """The message, valid for ``spec``, from the key's sender, of the kind expected on
        that key; None (counted, logged) when it is not."""
        try:
            msg = decode_controllers(
                payload.to_bytes(),
                max_payload_bytes=self.cfg.max_payload_bytes,
                max_entries=spec.max_entries,
                n_con=spec.n_con,
                max_active=spec.max_active,
                expect_signature=spec.signature,
            )
            if msg.vehicle_id != sender:
                raise WireError(f"sender {msg.vehicle_id!r} differs from the key's {sender!r}")
            if msg.kind != kind:
                raise WireError(f"a {msg.kind.name} message where a {kind.name} belongs")
        except WireError as exc:
            self.tally.add("rejected_malformed")
            self._log_limited("malformed", sender, "rejected a payload from %s on %s: %s",
                              sender, key, exc)  # fmt: skip
            return None
        return msg

    def _queue(self, spec: ProblemSpec, sender: str, kind: MessageKind, records: Records) -> None:
        """Into the inbox, for the forwarding thread (counted: duplicates, drops, gauges)."""
        queued, dup, dropped = self.inbox.put(sender, records)
        self.tally.add("entries_duplicate", dup)
        if dropped:
            self.tally.add("dropped_queue_full", dropped)
            self._log_limited("queue", "", "candidate inbox full: dropped %d from %s",
                              dropped, sender)  # fmt: skip
        self.tally.set("candidates_waiting", len(self.inbox))
        self.tally.set("rate_buckets", len(self._buckets))
        self.tally.set("rate_buckets_evicted", self._buckets.evicted)
        if queued:
            log.log(
                logging.INFO if kind == MessageKind.SNAPSHOT else logging.DEBUG,
                "%s: %d new controllers from vehicle %s (%s), %d waiting for the control process",
                spec.name, queued, sender, kind.name.lower(), len(self.inbox),
            )  # fmt: skip

def offer_records(
    records: Records, libraries: Sequence[tuple[str, FleetLibrary]], counters: Counter[str]
) -> int:
    """The control process's side: offer candidate records, as the helper queued them, to
    their problems' libraries (no factorisation); returns how many were new to a pool."""
    offered = 0
    for row in records:
        index = int(row["problem"])
        if index >= len(libraries):
            counters["entries_rejected_by_problem"] += 1
            continue
        name, library = libraries[index]
        entry, origin, successors = candidate_of(row)
        if library.offer(entry, origin, successors):
            offered += 1
            counters["entries_offered"] += 1
            log.debug("%s: candidate from %s, %d in the pool", name, origin,
                      library.fleet_counts()[0])  # fmt: skip
        else:
            counters["entries_known"] += 1
    counters["candidates_taken"] += len(records)
    return offered
