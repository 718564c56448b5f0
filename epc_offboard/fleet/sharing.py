"""Fleet sharing of EPC controller libraries, and live references, over Eclipse Zenoh.

Keys (every one starts with ``epc/``; ``<sig>`` is ``MpcProblem.signature()``)::

    epc/<fleet>/<sig>/ctl/<vehicle>     each batch of new controllers (wire.MessageKind.BATCH)
    epc/<fleet>/<sig>/lib/<vehicle>     queryable: the whole library (MessageKind.SNAPSHOT)
    epc/<fleet>/<sig>/alive/<vehicle>   liveliness token
    epc/<fleet>/<vehicle>/reference     live references for one vehicle (wire.ReferenceMessage)

One set of keys per shared problem (the position and the attitude loop have different
signatures): a vehicle subscribes only to its own signatures, so a peer flying another
problem is never even heard, and a payload whose embedded signature differs from the key's
is rejected. Late joiners query ``lib/*`` at start, and every vehicle queries the library
of a peer whose liveliness token appears (so two vehicles starting together, or one
restarting, still exchange what they had).

Threads: Zenoh calls back on its own threads. Those callbacks only check the size, apply
a per-peer token bucket, decode and validate (``wire``, pure) and hand the message to the
event loop with ``call_soon_threadsafe`` into a queue bounded in messages and in entries
(full: dropped and counted). :meth:`FleetSharing.run` — the ``library-sharing`` task — is the
only code that touches the controllers: it publishes new controllers, refreshes the encoded
snapshot that the queryable answers with, and offers what it received to each controller's
candidate pool, in slices bounded by time. Offering costs no factorisation: the pool
(:class:`epc_offboard.control.epc.CandidatePool`) is bounded in total and per peer, its maps are
built off the loop (the miss worker, :mod:`epc_offboard.service.miss_solver`), and a candidate
enters the library only when it passes this vehicle's KKT check for a real tick. A hostile
or broken peer can therefore fill the pool, never the library, and costs the 100/200 Hz
loops bookkeeping only. Nothing here blocks the control loops on the network: ``put`` drops
under congestion, queries are answered from a prepared snapshot.

Rate limits: one token bucket per sending vehicle id. A bucket that has refilled is
forgotten (a new one is the same), and when the table is full the least recently heard
sender's is dropped: a flood from many rotating ids never locks a new, legitimate peer out.
"""

from __future__ import annotations

import asyncio
import contextlib
import functools
import json
import logging
import threading
import time
from collections import Counter, OrderedDict
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal

import zenoh

from epc_offboard.control.epc import MAX_SUCCESSORS, ExperienceController
from epc_offboard.control.library import LibraryEntry
from epc_offboard.fleet.wire import (
    NAME_RE,
    ControllerMessage,
    MessageKind,
    ReferenceMessage,
    WireError,
    decode_controllers,
    decode_reference,
    encode_controllers,
)

log = logging.getLogger(__name__)

_MAX_PEERS = 1024  # token buckets and per-sender counts kept (least recently heard dropped)
_LOG_EVERY_S = 5.0  # at most one log line per reason and peer this often
_MAX_REFERENCE_BYTES = 16384


@dataclass(frozen=True)
class SharingConfig:
    """Fleet sharing of controller libraries over Eclipse Zenoh (:class:`FleetSharing`).

    Keys: ``epc/<fleet>/<signature>/{ctl,lib,alive}/<vehicle_id>``. Only vehicles whose
    problems have identical signatures exchange controllers, and a received controller is
    applied only where the local KKT check passes. For TLS/mTLS and access control give a
    Zenoh JSON5 file in ``zenoh_config_file``; the keys below are set on top of it.
    """

    enabled: bool = False
    fleet: str = "fleet"  # [A-Za-z0-9_-]{1,32}: one key space per fleet
    vehicle_id: str = ""  # [A-Za-z0-9_-]{1,32}, unique in the fleet; required when used
    mode: Literal["peer", "client", "router"] = "peer"
    listen: tuple[str, ...] = ()  # Zenoh endpoints, e.g. "tcp/0.0.0.0:7447"
    connect: tuple[str, ...] = ()  # e.g. "tcp/192.168.1.12:7447", "tls/router.local:7447"
    scouting_multicast: bool = False  # discover peers by UDP multicast (off: explicit only)
    zenoh_config_file: str = ""  # a Zenoh JSON5 config, loaded first
    max_payload_bytes: int = 262_144  # larger payloads are dropped before decoding
    max_messages_per_s: float = 20.0  # per peer, token bucket refill
    burst_messages: int = 40  # per peer, token bucket depth
    fleet_messages_per_s: float = 100.0  # all peers together, checked before decoding
    fleet_burst_messages: int = 200
    queue_size: int = 256  # inbound messages waiting for the event loop; beyond: dropped
    publish_period_s: float = 0.2  # new controllers are batched and published this often
    import_slice_s: float = 0.002  # event-loop time per slice of received controllers
    max_queued_entries: int = 8192  # controllers waiting in the inbound queue; beyond: dropped
    candidate_pool_size: int = 64  # received controllers waiting to prove optimal here
    candidates_per_peer: int = 16  # of those, at most this many from one vehicle (until proven)
    candidate_backlog_size: int = 2048  # received controllers kept as tuples, maps unbuilt
    candidate_backlog_per_peer: int = 512  # of those, at most this many from one vehicle
    candidate_slice_s: float = 0.005  # worker CPU time per slice of candidate factorisations
    query_timeout_s: float = 3.0  # a library snapshot query gives up after this

    def __post_init__(self) -> None:
        if not NAME_RE.fullmatch(self.fleet):
            raise ValueError(f"fleet must be 1..32 characters of [A-Za-z0-9_-], got {self.fleet!r}")
        if self.vehicle_id and not NAME_RE.fullmatch(self.vehicle_id):
            raise ValueError(
                f"vehicle_id must be 1..32 characters of [A-Za-z0-9_-], got {self.vehicle_id!r}"
            )
        if self.enabled and not self.vehicle_id:
            raise ValueError("vehicle_id must be set when sharing is enabled")
        if self.max_payload_bytes < 64:
            raise ValueError(f"max_payload_bytes must be >= 64, got {self.max_payload_bytes}")
        for name in ("max_messages_per_s", "publish_period_s", "query_timeout_s",
                     "import_slice_s", "candidate_slice_s", "fleet_messages_per_s"):
            if getattr(self, name) <= 0.0:
                raise ValueError(f"{name} must be > 0, got {getattr(self, name)}")
        for name in ("burst_messages", "queue_size", "max_queued_entries",
                     "candidate_pool_size", "candidates_per_peer", "fleet_burst_messages"):
            if getattr(self, name) < 1:
                raise ValueError(f"{name} must be >= 1, got {getattr(self, name)}")
        if (self.candidate_backlog_size < self.candidate_pool_size
                or self.candidate_backlog_per_peer < self.candidates_per_peer):
            raise ValueError(
                "candidate_backlog_size / candidate_backlog_per_peer must be >= "
                "candidate_pool_size / candidates_per_peer (the backlog holds the pool's too)"
            )
        for ep in (*self.listen, *self.connect):
            if "/" not in ep:
                raise ValueError(f"endpoint {ep!r} must look like PROTOCOL/ADDRESS:PORT")
        if self.zenoh_config_file and not Path(self.zenoh_config_file).is_file():
            raise ValueError(f"zenoh_config_file {self.zenoh_config_file!r} does not exist")


@dataclass
class _Problem:
    """One shared problem: its controller, its keys and its prepared snapshot."""

    name: str
    ctrl: ExperienceController
    signature: str
    prefix: str  # epc/<fleet>/<sig>
    snapshot: bytes = b""  # encoded on the event loop's behalf, read by Zenoh's threads
    dirty: bool = True


@dataclass(frozen=True)
class LiveReference:
    message: ReferenceMessage
    received_s: float  # time.monotonic() at arrival


class _TokenBuckets:
    """Per-peer token buckets that expire (thread-safe: Zenoh delivers on several threads).

    A bucket idle for its refill time (``burst / rate``) is full again, the same as a new
    one, so it is dropped. At most ``max_peers`` are kept: beyond, the least recently used
    goes. A sender is never refused for being new: spoofed, rotating ids each get a burst,
    which the bounded queue and candidate pool absorb.
    """

    def __init__(self, rate_per_s: float, burst: int, max_peers: int = _MAX_PEERS) -> None:
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


def successors_of(msg: ControllerMessage) -> dict[tuple[int, ...], tuple[tuple[int, ...], ...]]:
    """Each entry's likeliest successors in the sender's transition counts (most frequent
    first, at most :data:`epc_offboard.control.epc.MAX_SUCCESSORS`), by active set."""
    n = len(msg.entries)
    out: dict[int, list[tuple[int, int]]] = {}
    for a, b, count in msg.transitions:
        if 0 <= a < n and 0 <= b < n and a != b:
            out.setdefault(a, []).append((count, b))
    return {
        msg.entries[a].active_set: tuple(
            msg.entries[b].active_set for _, b in sorted(succ, reverse=True)[:MAX_SUCCESSORS]
        )
        for a, succ in out.items()
    }


_TRANSITION_BYTES = 12  # one (from, to, count) on the wire (wire._TRANSITION)


class FleetSharing:
    """One Zenoh session shared by the library exchange and the live-reference subscriber.

    ``controllers``: (name, controller) of every EPC problem to share (their candidate
    pools take the sizes of ``cfg``: construct this before the miss worker starts, which
    copies them); ``share_library`` False opens the session for the reference alone;
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
    ) -> None:
        if not cfg.vehicle_id:
            raise ValueError("sharing.vehicle_id must be set to open a fleet session")
        self.cfg = cfg
        self.vehicle_id = cfg.vehicle_id
        self.share_library = share_library
        self.subscribe_reference = reference
        self.counters: Counter[str] = Counter()
        self.peers: dict[str, set[str]] = {}  # problem name -> vehicle ids seen alive
        self.received_from: Counter[str] = Counter()  # messages past the rate limit, by sender
        self._problems = [
            _Problem(name, ctrl, sig, f"epc/{cfg.fleet}/{sig}")
            for name, ctrl in controllers
            for sig in (ctrl.problem.signature(),)
        ]
        for _name, ctrl in controllers:
            ctrl.limit_candidates(cfg.candidate_pool_size, cfg.candidates_per_peer,
                                  cfg.candidate_backlog_size, cfg.candidate_backlog_per_peer)
        self._buckets = _TokenBuckets(cfg.max_messages_per_s, cfg.burst_messages)
        # all peers together: rotating ids each get a fresh burst, so without a fleet-wide
        # limit a flood is decoded in full on Zenoh's threads, which hold the GIL the
        # control loops need (a flood of 1,200 ids cost the attitude loop 15 % of its ticks)
        self._fleet_bucket = _TokenBuckets(
            cfg.fleet_messages_per_s, cfg.fleet_burst_messages, max_peers=1
        )
        self._lock = threading.Lock()  # counters and log throttle, from Zenoh's threads
        self._last_log: dict[tuple[str, str], float] = {}
        self._queue: asyncio.Queue[tuple[_Problem, ControllerMessage]] = asyncio.Queue(
            maxsize=cfg.queue_size
        )
        self._queued_entries = 0  # entries in _queue (event loop only)
        self._loop: asyncio.AbstractEventLoop | None = None
        self._session: zenoh.Session | None = None
        self._declared: list[Any] = []
        self._reference: LiveReference | None = None

    # -- lifecycle ------------------------------------------------------------------------

    def zenoh_config(self) -> zenoh.Config:
        cfg = self.cfg
        conf = (
            zenoh.Config.from_file(cfg.zenoh_config_file)
            if cfg.zenoh_config_file
            else (zenoh.Config())
        )
        conf.insert_json5("mode", json.dumps(cfg.mode))
        if cfg.listen:
            conf.insert_json5("listen/endpoints", json.dumps(list(cfg.listen)))
        if cfg.connect:
            conf.insert_json5("connect/endpoints", json.dumps(list(cfg.connect)))
        conf.insert_json5("scouting/multicast/enabled", json.dumps(cfg.scouting_multicast))
        return conf

    async def open(self) -> None:
        """Open the session (off the loop: connecting may take a moment) and declare."""
        self._loop = asyncio.get_running_loop()
        conf = self.zenoh_config()
        self._session = await asyncio.to_thread(zenoh.open, conf)
        s = self._session
        vid = self.vehicle_id
        if self.share_library:
            for p in self._problems:  # ready before the queryable can be asked
                self._prepare_snapshot(p, p.ctrl.export_library(), p.ctrl.export_transitions())
                p.dirty = False
            for p in self._problems:
                self.peers[p.name] = set()
                self._declared += [
                    s.declare_subscriber(
                        f"{p.prefix}/ctl/*",
                        functools.partial(self._on_batch, p),
                        allowed_origin=zenoh.Locality.REMOTE,
                    ),
                    s.declare_queryable(
                        f"{p.prefix}/lib/{vid}", functools.partial(self._on_query, p)
                    ),
                    s.liveliness().declare_subscriber(
                        f"{p.prefix}/alive/*",
                        functools.partial(self._on_alive, p),
                        history=True,
                    ),
                    s.liveliness().declare_token(f"{p.prefix}/alive/{vid}"),
                ]
                self._query_library(p, "*")
        if self.subscribe_reference:
            self._declared.append(
                s.declare_subscriber(self.reference_key(self.cfg.fleet, vid), self._on_reference)
            )
        log.info(
            "fleet %s: vehicle %s sharing %s (listen %s, connect %s, multicast scouting %s)",
            self.cfg.fleet,
            vid,
            ", ".join(f"{p.name} {p.signature}" for p in self._problems)
            if self.share_library
            else "no library",
            list(self.cfg.listen),
            list(self.cfg.connect),
            "on" if self.cfg.scouting_multicast else "off",
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

    async def __aenter__(self) -> FleetSharing:
        await self.open()
        return self

    async def __aexit__(self, *exc: object) -> None:
        self.close()

    @staticmethod
    def reference_key(fleet: str, vehicle_id: str) -> str:
        return f"epc/{fleet}/{vehicle_id}/reference"

    # -- the event-loop task --------------------------------------------------------------

    async def run(self) -> None:
        """Offer received controllers to the candidate pools, publish new controllers,
        refresh snapshots. Forever."""
        period = self.cfg.publish_period_s
        next_publish = time.monotonic() + period
        while True:
            wait_s = max(0.0, next_publish - time.monotonic())
            try:
                async with asyncio.timeout(wait_s):
                    problem, msg = await self._queue.get()
                self._queued_entries -= len(msg.entries)
                await self._import(problem, msg)
            except TimeoutError:
                pass
            if time.monotonic() >= next_publish:
                next_publish = time.monotonic() + period
                self.publish_new()
                await self._refresh_snapshots()

    async def _import(self, p: _Problem, msg: ControllerMessage) -> None:
        """Offer ``msg``'s entries to the candidate pool in slices of at most
        ``import_slice_s`` of event-loop time, yielding to the control loops between.

        Offering is bookkeeping (no factorisation); the pool's bounds, not this loop, cap
        what a peer can make the vehicle hold."""
        ctrl = p.ctrl
        origin = f"shared:{msg.vehicle_id}"
        entries = msg.entries
        self._count("entries_received", len(entries))
        if msg.signature != p.signature:  # the decoder checked it; a second look is free
            self._count("entries_rejected_by_problem", len(entries))
            return
        slice_s = self.cfg.import_slice_s
        successors = successors_of(msg)
        # the sender's most used (then most recent) last: a peer past its pool quota keeps
        # its newest in the pool, the rest wait in the backlog
        entries = tuple(sorted(entries, key=lambda e: (e.uses, e.importance)))
        offered = i = 0
        while i < len(entries):
            t0 = time.perf_counter()
            n = 0
            while i < len(entries) and (n == 0 or time.perf_counter() - t0 < slice_s):
                offered += ctrl.offer_candidates(
                    entries[i : i + 1], origin, successors=successors
                )
                i += 1
                n += 1
            self._count("import_slices")
            await asyncio.sleep(0)  # let the 100/200 Hz loops run
        self._count("entries_known", len(entries) - offered)
        if offered:
            self._count("entries_offered", offered)
            log.info(
                "%s: %d new controllers from vehicle %s (%s), candidates now %d of %d",
                p.name,
                offered,
                msg.vehicle_id,
                msg.kind.name.lower(),
                len(ctrl.candidates),
                ctrl.candidates.max_size,
            )

    def publish_new(self) -> int:
        """Publish every controller learned since the last call; returns how many."""
        sent = 0
        for p in self._problems:
            new = p.ctrl.pop_new_entries()
            if not new or not self.share_library or self._session is None:
                continue
            p.dirty = True
            for chunk in self._chunks(new):
                payload = encode_controllers(
                    ControllerMessage(MessageKind.BATCH, p.signature, self.vehicle_id, chunk)
                )
                try:
                    self._session.put(
                        f"{p.prefix}/ctl/{self.vehicle_id}",
                        payload,
                        congestion_control=zenoh.CongestionControl.DROP,
                    )
                except zenoh.ZError as exc:
                    self._count("publish_errors")
                    self._log_limited("publish", p.name, "publishing controllers failed: %s", exc)
                    continue
                sent += len(chunk)
                self._count("entries_published", len(chunk))
        return sent

    def _chunks(self, entries: Sequence[LibraryEntry]) -> list[tuple[LibraryEntry, ...]]:
        """Split into messages that each fit max_payload_bytes (most important first)."""
        budget = self.cfg.max_payload_bytes - 64  # header + id + count
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

    async def _refresh_snapshots(self) -> None:
        for p in self._problems:
            if not self.share_library or not p.dirty:
                continue
            p.dirty = False  # here, not in the worker: an import meanwhile sets it again
            # on the loop: the library is not thread-safe
            entries, transitions = p.ctrl.export_library(), p.ctrl.export_transitions()
            await asyncio.to_thread(self._prepare_snapshot, p, entries, transitions)

    def _prepare_snapshot(
        self, p: _Problem, entries: list[LibraryEntry],
        transitions: dict[tuple[int, int], int] | None = None,
    ) -> None:
        """Encode the snapshot a late joiner's query gets: the most important controllers
        that fit one payload, and as many of their transition counts (most frequent first)
        as still fit — they tell the joiner which controller is likely next."""
        chunks = self._chunks(entries)
        kept = chunks[0] if chunks else ()
        index = {id(e): i for i, e in enumerate(kept)}
        room = self.cfg.max_payload_bytes - 64 - 4 - sum(14 + 2 * len(e.active_set) for e in kept)
        trans = sorted(
            (
                (index[id(entries[a])], index[id(entries[b])], n)
                for (a, b), n in (transitions or {}).items()
                if id(entries[a]) in index and id(entries[b]) in index
            ),
            key=lambda t: -t[2],
        )[: max(0, room // _TRANSITION_BYTES)]
        p.snapshot = encode_controllers(
            ControllerMessage(MessageKind.SNAPSHOT, p.signature, self.vehicle_id, kept,
                              tuple(trans))
        )

    # -- Zenoh's threads ------------------------------------------------------------------

    def _on_batch(self, p: _Problem, sample: zenoh.Sample) -> None:
        self._receive(p, str(sample.key_expr), sample.payload, MessageKind.BATCH)

    def _on_reply(self, p: _Problem, reply: zenoh.Reply) -> None:
        sample = reply.ok
        if sample is None:
            self._count("query_errors")
            return
        self._receive(p, str(sample.key_expr), sample.payload, MessageKind.SNAPSHOT)

    def _receive(self, p: _Problem, key: str, payload: zenoh.ZBytes, kind: MessageKind) -> None:
        sender = key.rsplit("/", 1)[-1]
        if sender == self.vehicle_id:
            self._count("own_ignored")
            return
        self._count("messages_received")
        if len(payload) > self.cfg.max_payload_bytes:
            self._count("rejected_oversized")
            self._log_limited("size", sender, "dropped a %d-byte payload from %s (limit %d)",
                              len(payload), sender, self.cfg.max_payload_bytes)  # fmt: skip
            return
        now = time.monotonic()
        if not self._fleet_bucket.allow("fleet", now):
            self._count("fleet_rate_limited")
            self._log_limited("fleet-rate", "fleet", "rate-limiting the fleet: %s on %s",
                              sender, key)  # fmt: skip
            return
        if not self._buckets.allow(sender, now):
            self._count("rate_limited")
            self._log_limited("rate", sender, "rate-limiting vehicle %s on %s", sender, key)
            return
        with self._lock:
            if sender not in self.received_from and len(self.received_from) >= _MAX_PEERS:
                del self.received_from[next(iter(self.received_from))]  # oldest heard first
            self.received_from[sender] += 1
        try:
            msg = decode_controllers(
                payload.to_bytes(),
                max_payload_bytes=self.cfg.max_payload_bytes,
                max_entries=p.ctrl.max_size,
                n_con=p.ctrl.problem.n_con,
                max_active=p.ctrl.problem.n_u,
                expect_signature=p.signature,
            )
            if msg.vehicle_id != sender:
                raise WireError(f"sender {msg.vehicle_id!r} differs from the key's {sender!r}")
            if msg.kind != kind:
                raise WireError(f"a {msg.kind.name} message where a {kind.name} belongs")
        except WireError as exc:
            self._count("rejected_malformed")
            self._log_limited("malformed", sender, "rejected a payload from %s on %s: %s",
                              sender, key, exc)  # fmt: skip
            return
        self._to_loop(self._enqueue, p, msg)

    def _on_query(self, p: _Problem, query: zenoh.Query) -> None:
        self._count("queries_answered")
        try:
            query.reply(f"{p.prefix}/lib/{self.vehicle_id}", p.snapshot)
        except zenoh.ZError as exc:
            self._count("query_reply_errors")
            self._log_limited("reply", "", "answering a library query failed: %s", exc)

    def _on_alive(self, p: _Problem, sample: zenoh.Sample) -> None:
        peer = str(sample.key_expr).rsplit("/", 1)[-1]
        if peer == self.vehicle_id:
            return
        joined = sample.kind == zenoh.SampleKind.PUT
        self._to_loop(self._peer_changed, p, peer, joined)

    def _on_reference(self, sample: zenoh.Sample) -> None:
        payload = sample.payload
        if len(payload) > _MAX_REFERENCE_BYTES:
            self._count("reference_rejected")
            return
        try:
            msg = decode_reference(payload.to_bytes(), max_payload_bytes=_MAX_REFERENCE_BYTES)
        except WireError as exc:
            self._count("reference_rejected")
            self._log_limited("reference", "", "rejected a live reference: %s", exc)
            return
        self._count("references_received")
        self._reference = LiveReference(msg, time.monotonic())  # one reference swap: atomic

    def _to_loop(self, fn: Any, *args: Any) -> None:
        loop = self._loop
        if loop is None or loop.is_closed():
            return
        with contextlib.suppress(RuntimeError):  # the loop closed meanwhile: shutting down
            loop.call_soon_threadsafe(fn, *args)

    # -- back on the event loop -----------------------------------------------------------

    def _enqueue(self, p: _Problem, msg: ControllerMessage) -> None:
        try:
            if self._queued_entries + len(msg.entries) > self.cfg.max_queued_entries:
                raise asyncio.QueueFull
            self._queue.put_nowait((p, msg))
            self._queued_entries += len(msg.entries)
        except asyncio.QueueFull:
            self._count("dropped_queue_full")
            self._log_limited("queue", "", "inbound queue full: dropped a message from %s",
                              msg.vehicle_id)  # fmt: skip

    def _peer_changed(self, p: _Problem, peer: str, joined: bool) -> None:
        peers = self.peers.setdefault(p.name, set())
        if joined and peer not in peers:
            peers.add(peer)
            log.info("fleet %s: vehicle %s joined (%s)", self.cfg.fleet, peer, p.name)
            self._query_library(p, peer)
        elif not joined and peer in peers:
            peers.discard(peer)
            log.info("fleet %s: vehicle %s left (%s)", self.cfg.fleet, peer, p.name)

    def _query_library(self, p: _Problem, peer: str) -> None:
        if self._session is None:
            return
        self._count("queries_sent")
        try:
            self._session.get(
                f"{p.prefix}/lib/{peer}",
                functools.partial(self._on_reply, p),
                timeout=self.cfg.query_timeout_s,
                allowed_destination=zenoh.Locality.REMOTE,  # not our own queryable
            )
        except zenoh.ZError as exc:
            self._count("query_errors")
            self._log_limited("query", peer, "querying %s's library failed: %s", peer, exc)

    # -- for the service ------------------------------------------------------------------

    def live_reference(self, now_s: float, timeout_s: float) -> LiveReference | None:
        """The newest live reference if younger than ``timeout_s`` (``time.monotonic``)."""
        ref = self._reference
        if ref is None or now_s - ref.received_s > timeout_s:
            return None
        return ref

    def stats(self) -> dict[str, int]:
        with self._lock:
            out = dict(self.counters)
        out["peers"] = len(set().union(*self.peers.values())) if self.peers else 0
        out["rate_buckets"] = len(self._buckets)
        out["rate_buckets_evicted"] = self._buckets.evicted
        out["candidates"] = sum(len(p.ctrl.candidates) for p in self._problems)
        out["promoted"] = sum(p.ctrl.stats.received_shared for p in self._problems)
        return out

    def _count(self, name: str, n: int = 1) -> None:
        with self._lock:
            self.counters[name] += n

    def _log_limited(self, reason: str, peer: str, fmt: str, *args: object) -> None:
        now = time.monotonic()
        with self._lock:
            last = self._last_log.get((reason, peer), -float("inf"))
            if now - last < _LOG_EVERY_S:
                return
            if len(self._last_log) > _MAX_PEERS:
                self._last_log.clear()
            self._last_log[(reason, peer)] = now
        log.warning(fmt, *args)


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
