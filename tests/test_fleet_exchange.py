"""The fleet exchange without Zenoh or processes: a peer's payload in, offers to a library
out, as docs/DESIGN.md's "A fleet message, file by file" tells it (steps 2 and 4)."""

from __future__ import annotations

from collections import Counter
from collections.abc import Iterator

import numpy as np
import pytest

from epc_offboard.control.candidate_pool import CandidatePoolConfig
from epc_offboard.control.epc import ExperienceController
from epc_offboard.control.epc.exchange import FleetPort
from epc_offboard.control.library_types import LibraryEntry
from epc_offboard.fleet.config import SharingConfig
from epc_offboard.fleet.exchange import (
    FleetExchange,
    FleetLibrary,
    LimitedLog,
    Snapshot,
    batch_payloads,
    candidate_dtype,
    offer_records,
)
from epc_offboard.fleet.records import ProblemSpec
from epc_offboard.fleet.wire import MessageKind, decode_controllers
from tests.mpc_cases import position_problem

SIG = "0123456789abcdef0123456789abcdef"
SPEC = ProblemSpec("position", SIG, n_con=12, max_active=3, max_entries=64)


class _Tally:
    def __init__(self) -> None:
        self.counts: Counter[str] = Counter()

    def add(self, name: str, n: int = 1) -> None:
        self.counts[name] += n

    def set(self, name: str, value: int) -> None:
        self.counts[name] = value


class _Bytes:
    """A received payload; ``to_bytes`` fails when ``copied`` is forbidden."""

    def __init__(self, data: bytes, *, copy_allowed: bool = True) -> None:
        self.data, self.copy_allowed = data, copy_allowed

    def __len__(self) -> int:
        return len(self.data)

    def to_bytes(self) -> bytes:
        assert self.copy_allowed, "copied before the size check"
        return self.data


class _Library:
    """A FleetLibrary that records what it is offered."""

    def __init__(self) -> None:
        self.offered: list[tuple[LibraryEntry, str, tuple[tuple[int, ...], ...]]] = []

    def offer(self, entry: LibraryEntry, origin: str,
              successors: tuple[tuple[int, ...], ...]) -> bool:  # fmt: skip
        self.offered.append((entry, origin, successors))
        return True

    def new_entries(self) -> list[LibraryEntry]:
        return []

    def snapshot(self) -> Snapshot:
        return [], {}

    def fleet_counts(self) -> tuple[int, int]:
        return len(self.offered), 0

    def received(self) -> list[tuple[LibraryEntry, tuple[tuple[int, ...], ...]]]:
        return [(e, s) for e, _o, s in self.offered]

    def received_parts(
        self, per_part: int
    ) -> Iterator[list[tuple[LibraryEntry, tuple[tuple[int, ...], ...]]]]:
        received = self.received()
        for at in range(0, len(received), per_part):
            yield received[at : at + per_part]


def _exchange(**cfg: object) -> tuple[FleetExchange, _Tally]:
    tally = _Tally()
    ex = FleetExchange(SharingConfig(vehicle_id="me", fleet="t", **cfg), tally,  # type: ignore[arg-type]
                       candidate_dtype(SPEC.max_active, 4), 4, 512, LimitedLog())  # fmt: skip
    return ex, tally


def _payload(sender: str, entries: list[LibraryEntry]) -> bytes:
    ((payload, chunk),) = batch_payloads(SIG, sender, entries, 4096)
    assert list(chunk) == entries
    return payload


ENTRIES = [LibraryEntry((1,), 2.0, 5), LibraryEntry((0, 4), 1.0, 1)]


def test_a_peers_batch_becomes_offers_with_its_origin() -> None:
    ex, tally = _exchange()
    ex.receive(0, SPEC, "epc/t/sig/ctl/peer", _Bytes(_payload("peer", ENTRIES)),
               MessageKind.BATCH)  # fmt: skip
    assert tally.counts["entries_received"] == 2
    assert len(ex.inbox) == 2
    records = [ex.inbox.take(0.0) for _ in range(2)]
    rows = np.frombuffer(b"".join(r for r in records if r is not None), dtype=ex.dtype)
    library = _Library()
    counters: Counter[str] = Counter()
    assert offer_records(rows, [("position", library)], counters) == 2
    assert {(e.active_set, origin) for e, origin, _ in library.offered} == {
        ((1,), "shared:peer"), ((0, 4), "shared:peer")}  # fmt: skip
    assert counters["entries_offered"] == 2
    assert counters["candidates_taken"] == 2


def test_records_for_an_unknown_problem_are_counted_not_offered() -> None:
    ex, _ = _exchange()
    ex.receive(3, SPEC, "epc/t/sig/ctl/peer", _Bytes(_payload("peer", ENTRIES[:1])),
               MessageKind.BATCH)  # fmt: skip
    rec = ex.inbox.take(0.0)
    assert rec is not None
    counters: Counter[str] = Counter()
    library = _Library()
    rows = np.frombuffer(rec, dtype=ex.dtype)
    assert offer_records(rows, [("position", library)], counters) == 0
    assert counters["entries_rejected_by_problem"] == 1
    assert not library.offered


@pytest.mark.parametrize(
    ("key", "payload", "kind", "counter"),
    [
        ("epc/t/sig/ctl/me", _payload("me", ENTRIES), MessageKind.BATCH, "own_ignored"),
        ("epc/t/sig/ctl/peer", _payload("other", ENTRIES), MessageKind.BATCH,
         "rejected_malformed"),  # the key's sender is not the message's
        ("epc/t/sig/lib/peer", _payload("peer", ENTRIES), MessageKind.SNAPSHOT,
         "rejected_malformed"),  # a batch where a snapshot belongs
        ("epc/t/sig/ctl/peer", b"\x00" * 64, MessageKind.BATCH, "rejected_malformed"),
    ],
)
def test_what_is_not_a_valid_peer_message_is_counted_and_dropped(
    key: str, payload: bytes, kind: MessageKind, counter: str
) -> None:
    ex, tally = _exchange()
    ex.receive(0, SPEC, key, _Bytes(payload), kind)
    assert tally.counts[counter] == 1
    assert len(ex.inbox) == 0


def test_an_oversized_payload_is_refused_before_it_is_copied() -> None:
    ex, tally = _exchange(max_payload_bytes=1024)
    ex.receive(0, SPEC, "epc/t/sig/ctl/peer", _Bytes(b"\x00" * 2048, copy_allowed=False),
               MessageKind.BATCH)  # fmt: skip
    assert tally.counts["rejected_oversized"] == 1


def test_a_peer_past_its_bucket_is_rate_limited() -> None:
    ex, tally = _exchange(max_messages_per_s=1.0, burst_messages=2)
    for k in range(4):
        ex.receive(0, SPEC, "epc/t/sig/ctl/peer",
                   _Bytes(_payload("peer", [LibraryEntry((k,))])), MessageKind.BATCH)  # fmt: skip
    assert tally.counts["rate_limited"] == 2
    assert tally.counts["entries_received"] == 2


def test_outgoing_batches_decode_to_what_was_learned() -> None:
    (payload, _n), *_ = batch_payloads(SIG, "me", ENTRIES, 4096)
    msg = decode_controllers(payload, max_payload_bytes=4096, max_entries=64, n_con=12,
                             max_active=3, expect_signature=SIG)  # fmt: skip
    assert msg.kind == MessageKind.BATCH
    assert msg.vehicle_id == "me"
    assert [e.active_set for e in msg.entries] == [e.active_set for e in ENTRIES]


def test_the_controllers_fleet_port_is_the_exchanges_library() -> None:
    """The controller's side satisfies the protocol, and a candidate offered through it
    waits in the pool, not in the library (it joins only after this vehicle's KKT check)."""
    ctrl = ExperienceController(position_problem(8))
    port: FleetLibrary = FleetPort(ctrl, CandidatePoolConfig(pool_size=4, per_peer=2))
    assert port.offer(LibraryEntry((1,)), "shared:peer", ())
    assert not port.offer(LibraryEntry((1,)), "shared:peer", ())  # known: not new
    assert port.fleet_counts() == (1, 0)
    assert ctrl.stats.size == 0
    assert port.snapshot() == ([], {})
    assert port.new_entries() == []
