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
event loop with ``call_soon_threadsafe`` into a bounded queue (full: dropped and counted).
:meth:`FleetSharing.run` — the ``library-sharing`` task — is the only code that touches the
controllers: it imports candidates a few at a time (each costs a factorisation; the 100 and
200 Hz loops share the event loop), publishes new controllers, and refreshes the encoded
snapshot that the queryable answers with. Nothing here blocks the control loops on the
network: ``put`` drops under congestion, queries are answered from a prepared snapshot.
Received controllers are candidates only: the library applies one only where its own KKT
check passes.
"""

from __future__ import annotations

import asyncio
import contextlib
import functools
import json
import logging
import threading
import time
from collections import Counter
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import zenoh

from epc_offboard.config import SharingConfig
from epc_offboard.epc import ExperienceController, LibraryEntry
from epc_offboard.wire import (
    ControllerMessage,
    MessageKind,
    ReferenceMessage,
    WireError,
    decode_controllers,
    decode_reference,
    encode_controllers,
)

log = logging.getLogger(__name__)

_MAX_PEERS = 1024  # token buckets kept; beyond, unknown senders are refused (spoofed keys)
_LOG_EVERY_S = 5.0  # at most one log line per reason and peer this often
_IMPORT_SLICE_S = 0.002  # stop an import slice early after this much event-loop time
_MAX_REFERENCE_BYTES = 16384


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
    """Per-peer token buckets (thread-safe: Zenoh delivers on several threads)."""

    def __init__(self, rate_per_s: float, burst: int) -> None:
        self._rate = rate_per_s
        self._burst = float(burst)
        self._state: dict[str, tuple[float, float]] = {}
        self._lock = threading.Lock()

    def allow(self, peer: str, now_s: float) -> bool:
        with self._lock:
            state = self._state.get(peer)
            if state is None:
                if len(self._state) >= _MAX_PEERS:
                    return False
                state = (self._burst, now_s)
            tokens, last = state
            tokens = min(self._burst, tokens + (now_s - last) * self._rate)
            ok = tokens >= 1.0
            self._state[peer] = (tokens - 1.0 if ok else tokens, now_s)
            return ok


class FleetSharing:
    """One Zenoh session shared by the library exchange and the live-reference subscriber.

    ``controllers``: (name, controller) of every EPC problem to share; ``share_library``
    False opens the session for the reference alone; ``reference`` subscribes to this
    vehicle's live-reference key. Use as ``async with FleetSharing(...) as sharing`` and
    run :meth:`run` as a task; controllers are touched only from that task.
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
        self._buckets = _TokenBuckets(cfg.max_messages_per_s, cfg.burst_messages)
        self._lock = threading.Lock()  # counters and log throttle, from Zenoh's threads
        self._last_log: dict[tuple[str, str], float] = {}
        self._queue: asyncio.Queue[tuple[_Problem, ControllerMessage]] = asyncio.Queue(
            maxsize=cfg.queue_size
        )
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
                self._prepare_snapshot(p, p.ctrl.export_library())
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
        """Import received candidates, publish new controllers, refresh snapshots. Forever."""
        period = self.cfg.publish_period_s
        next_publish = time.monotonic() + period
        while True:
            wait_s = max(0.0, next_publish - time.monotonic())
            try:
                async with asyncio.timeout(wait_s):
                    problem, msg = await self._queue.get()
                await self._import(problem, msg)
            except TimeoutError:
                pass
            if time.monotonic() >= next_publish:
                next_publish = time.monotonic() + period
                self.publish_new()
                await self._refresh_snapshots()

    async def _import(self, p: _Problem, msg: ControllerMessage) -> None:
        """Import ``msg``'s entries a few at a time, yielding to the control loops between."""
        ctrl = p.ctrl
        fresh = [e for e in msg.entries if not ctrl.contains(e.active_set)]
        self._count("entries_received", len(msg.entries))
        self._count("entries_known", len(msg.entries) - len(fresh))
        batch = self.cfg.import_batch_size
        added_total = 0
        i = 0
        while i < len(fresh):
            t0 = time.perf_counter()
            for _ in range(batch):
                if i >= len(fresh):
                    break
                e = fresh[i]
                i += 1
                if ctrl.stats.size >= ctrl.max_size:
                    # local experience wins: shared candidates only fill free slots
                    self._count("entries_dropped_library_full", len(fresh) - i + 1)
                    i = len(fresh)
                    break
                try:
                    added = ctrl.import_entries([e], "shared", signature=msg.signature)
                except ValueError as exc:
                    self._count("entries_rejected_by_problem")
                    self._log_limited(
                        "problem", msg.vehicle_id, "controller %s from %s rejected: %s",
                        e.active_set, msg.vehicle_id, exc,
                    )  # fmt: skip
                    continue
                added_total += added
                if time.perf_counter() - t0 > _IMPORT_SLICE_S:
                    break
            await asyncio.sleep(0)  # let the 100/200 Hz loops run
        if added_total:
            p.dirty = True
            self._count("entries_accepted", added_total)
            log.info(
                "%s: %d new controllers from vehicle %s (%s, library %d)",
                p.name,
                added_total,
                msg.vehicle_id,
                msg.kind.name.lower(),
                ctrl.stats.size,
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
            entries = p.ctrl.export_library()  # on the loop: the library is not thread-safe
            await asyncio.to_thread(self._prepare_snapshot, p, entries)

    def _prepare_snapshot(self, p: _Problem, entries: list[LibraryEntry]) -> None:
        chunks = self._chunks(entries)
        kept = chunks[0] if chunks else ()
        p.snapshot = encode_controllers(
            ControllerMessage(MessageKind.SNAPSHOT, p.signature, self.vehicle_id, kept)
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
        if not self._buckets.allow(sender, time.monotonic()):
            self._count("rate_limited")
            self._log_limited("rate", sender, "rate-limiting vehicle %s on %s", sender, key)
            return
        with self._lock:  # bounded: the buckets admit at most _MAX_PEERS senders
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
            self._queue.put_nowait((p, msg))
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
