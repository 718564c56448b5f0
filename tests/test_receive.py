"""The MAVLink receive path (``vehicle/receive.py``) against pymavlink's codec as the oracle:
random field values encoded by pymavlink decode to what pymavlink decodes; every header
check, the CRC and the signature reject what they must, counted by reason; a byte stream cut
anywhere gives the same messages; a sender's garbage is throttled, the peer's never."""

from __future__ import annotations

import asyncio
import contextlib
import math
import random
import socket
import struct
import time
from collections import Counter
from typing import Any

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from pymavlink.dialects.v20 import common as mavlink

from epc_offboard.common.signing import enable_signing
from epc_offboard.vehicle.link import MavlinkLink
from epc_offboard.vehicle.receive import (
    FAST_LAYOUTS,
    SERVICE_MESSAGE_IDS,
    FrameReceiver,
    ReceiveBudget,
    SourceGate,
    x25_crc,
)
from epc_offboard.vehicle.state import StateTracker

KEY = bytes(range(32))
FAST = {layout.name: layout for layout in FAST_LAYOUTS}
_INT_RANGES = {
    "uint8_t": (0, 2**8 - 1), "int8_t": (-(2**7), 2**7 - 1),
    "uint16_t": (0, 2**16 - 1), "int16_t": (-(2**15), 2**15 - 1),
    "uint32_t": (0, 2**32 - 1), "int32_t": (-(2**31), 2**31 - 1),
    "uint64_t": (0, 2**64 - 1), "int64_t": (-(2**63), 2**63 - 1),
}  # fmt: skip


def receiver(
    *, systems=frozenset({1}), components=frozenset({1}), signature=None, ids=SERVICE_MESSAGE_IDS
):
    counters: Counter[str] = Counter()
    rx = FrameReceiver(
        counters,
        accept_ids=ids,
        accept_systems=systems,
        accept_components=components,
        signature=signature,
        decode_other=mavlink.MAVLink(None).decode,
    )
    return rx, counters


def codec(sysid: int = 1, compid: int = 1, key: bytes | None = None) -> Any:
    mav = mavlink.MAVLink(None, srcSystem=sysid, srcComponent=compid)
    if key is not None:
        enable_signing(mav, key)
    return mav


def field_values(name: str) -> st.SearchStrategy[dict[str, Any]]:
    """Random values for every field of message ``name``, NaN and infinities included."""
    cls = mavlink.mavlink_map[FAST[name].msg_id]
    lengths = dict(zip(cls.ordered_fieldnames, cls.array_lengths, strict=True))
    fields = {}
    for fname, ftype in zip(cls.fieldnames, cls.fieldtypes, strict=True):
        if ftype == "float":
            scalar: st.SearchStrategy[Any] = st.floats(width=32)
        else:
            scalar = st.integers(*_INT_RANGES[ftype])
        n = lengths[fname]
        fields[fname] = st.lists(scalar, min_size=n, max_size=n) if n else scalar
    return st.fixed_dictionaries(fields)


def same(a: Any, b: Any) -> bool:
    if isinstance(a, list):
        return len(a) == len(b) and all(same(x, y) for x, y in zip(a, b, strict=True))
    if isinstance(a, float) and math.isnan(a):
        return isinstance(b, float) and math.isnan(b)
    return bool(a == b) and type(a) is type(b)


def encode(name: str, values: dict[str, Any], mav: Any = None) -> bytes:
    mav = mav or codec()
    cls = mavlink.mavlink_map[FAST[name].msg_id]
    return bytes(cls(**values).pack(mav))


def raw_frame(msg_id: int, crc_extra: int, payload: bytes, seq: int = 0) -> bytes:
    """A MAVLink 2 frame from system 1, component 1 of ``payload`` as given (any length,
    which pymavlink's encoders never make), its CRC right."""
    header = struct.pack("<BBBBBBBHB", 0xFD, len(payload), 0, 0, seq, 1, 1, msg_id, 0)
    return header + payload + struct.pack("<H", x25_crc(header[1:] + payload, crc_extra))


def assert_same_as_pymavlink(frame: bytes, got: Any) -> None:
    oracle = mavlink.MAVLink(None).decode(bytearray(frame))
    assert got.get_type() == oracle.get_type()
    assert got.get_msgId() == oracle.get_msgId()
    assert got.get_srcSystem() == oracle.get_srcSystem()
    assert got.get_srcComponent() == oracle.get_srcComponent()
    assert got.get_seq() == oracle.get_seq()
    assert got.get_msgbuf() == bytes(oracle.get_msgbuf())
    assert sorted(got.get_fieldnames()) == sorted(oracle.get_fieldnames())  # (wire order)
    for fname in oracle.get_fieldnames():
        assert same(getattr(got, fname), getattr(oracle, fname)), fname


@settings(max_examples=300, deadline=None)
@given(data=st.binary(max_size=300), extra=st.integers(0, 255))
def test_crc_is_pymavlinks_x25(data, extra):
    assert x25_crc(data, extra) == mavlink.x25crc(data + bytes([extra])).crc


def test_layouts_are_the_dialects():
    for layout in FAST_LAYOUTS:
        cls = mavlink.mavlink_map[layout.msg_id]
        assert cls.msgname == layout.name
        assert cls.crc_extra == layout.crc_extra
        assert cls.unpacker.format == layout.fmt
        assert tuple(cls.ordered_fieldnames) == layout.fields
        arrays = {n: k for n, k in zip(cls.ordered_fieldnames, cls.array_lengths, strict=True) if k}
        assert arrays == layout.arrays


def _round_trip(name: str, values: dict[str, Any]) -> None:
    frame = encode(name, values)
    rx, counters = receiver()
    msgs, failures = rx.datagram(frame)
    assert failures == 0, counters
    assert len(msgs) == 1
    assert_same_as_pymavlink(frame, msgs[0])
    # and through a byte stream, as serial and TCP deliver it
    rx, _ = receiver()
    assert len(rx.stream(frame)) == 1


@pytest.mark.parametrize("name", sorted(FAST))
def test_fast_messages_decode_as_pymavlink_does(name):
    @settings(max_examples=150, deadline=None)
    @given(values=field_values(name))
    def check(values):
        _round_trip(name, values)

    check()


@pytest.mark.parametrize("name", sorted(FAST))
def test_zero_truncated_payloads(name):
    """MAVLink 2 drops trailing zero bytes: an all-zero message travels as 1 byte, one with
    only its first (wire-order) field set as that field's bytes."""
    cls = mavlink.mavlink_map[FAST[name].msg_id]
    lengths = dict(zip(cls.ordered_fieldnames, cls.array_lengths, strict=True))
    zero: dict[str, Any] = {}
    for fname, ftype in zip(cls.fieldnames, cls.fieldtypes, strict=True):
        scalar: Any = 0.0 if ftype == "float" else 0
        zero[fname] = [scalar] * lengths[fname] if lengths[fname] else scalar
    frame = encode(name, zero)
    assert frame[1] == 1  # payload length
    _round_trip(name, zero)
    first = cls.ordered_fieldnames[0]  # never an array in these messages
    size = struct.calcsize("<" + cls.unpacker.format[1])  # its bytes, every one non-zero
    value = 7.0 if isinstance(zero[first], float) else int.from_bytes(bytes(range(1, size + 1)),
                                                                      "little")  # fmt: skip
    one = dict(zero, **{first: value})
    frame = encode(name, one)
    assert frame[1] == size
    _round_trip(name, one)


def test_timesync_with_the_extension_fields_pymavlinks_dialect_lacks():
    """common.xml's TIMESYNC has target_system and target_component after tc1 and ts1
    (extensions); PX4 fills them in every answer: 18 bytes of payload, 2 more than
    pymavlink's dialect knows. They are taken and decoded as pymavlink decodes them (it
    drops what it does not know), and so is any longer payload (a newer dialect's
    extensions). On main every answer of a real PX4 was refused (bad_length): no TIMESYNC
    round trip was ever trusted."""
    mav = codec()
    tc1, ts1 = 1_234_567_000_000, 42
    payloads = [
        (struct.pack("<qq", tc1, ts1) + targets).rstrip(b"\x00")  # MAVLink 2's truncated zeros
        for targets in (b"\xf5\xbf", b"\xf5\x00", b"\x00\x00")
    ]
    payloads.append(struct.pack("<qqBBB", tc1, ts1, 245, 191, 1))  # a 19th byte: newer still
    for payload in payloads:
        frame = raw_frame(111, 34, payload, seq=7)
        rx, counters = receiver()
        msgs, failures = rx.datagram(frame)
        assert failures == 0, (len(payload), counters)
        assert_same_as_pymavlink(frame, msgs[0])
        assert (msgs[0].tc1, msgs[0].ts1) == (tc1, ts1)
    assert mav is not None


def test_other_messages_go_through_pymavlink():
    mav = codec()
    frame = bytes(mav.command_ack_encode(400, 4, 0, 0, 255, 191).pack(mav))
    rx, _ = receiver()
    msgs, _ = rx.datagram(frame)
    assert msgs[0].get_type() == "COMMAND_ACK"
    assert (msgs[0].command, msgs[0].result) == (400, 4)
    frame = bytes(mav.statustext_encode(4, b"Preflight Fail: no GPS").pack(mav))
    msgs, _ = rx.datagram(frame)
    assert msgs[0].text == "Preflight Fail: no GPS"


def _attitude(mav: Any = None, t_ms: int = 5) -> bytes:
    mav = mav or codec()
    return bytes(mav.attitude_encode(t_ms, 0.1, 0.2, 0.3, 0.0, 0.0, 0.0).pack(mav))


@settings(max_examples=200, deadline=None)
@given(bit=st.integers(0, 10_000))
def test_a_flipped_bit_after_the_magic_is_rejected(bit):
    frame = bytearray(_attitude())
    bit = 8 + bit % (8 * (len(frame) - 1))
    frame[bit // 8] ^= 1 << (bit % 8)
    rx, counters = receiver()
    msgs, failures = rx.datagram(bytes(frame))
    assert msgs == []
    assert failures >= 1
    assert sum(counters.values()) >= 1


def test_rejections_are_counted_by_reason():
    good = _attitude()
    cases = {
        "not_mavlink": b"GET / HTTP/1.1\r\n\r\n",
        "mavlink1": bytes(mavlink.MAVLink_attitude_message(5, 0, 0, 0, 0, 0, 0).pack(
            codec(), force_mavlink1=True)),
        "bad_crc": good[:-1] + bytes([good[-1] ^ 0x55]),
        "bad_length": good[:-3],
        "bad_flags": good[:2] + b"\x02" + good[3:],
        "wrong_system": _attitude(codec(sysid=42)),
        "wrong_component": _attitude(codec(compid=154)),
        "unknown_message": bytes(codec().sys_status_encode(*[0] * 13).pack(codec())),
    }  # fmt: skip
    for reason, dgram in cases.items():
        rx, counters = receiver()
        msgs, failures = rx.datagram(dgram)
        assert (msgs, failures) == ([], 1), reason
        assert counters[reason] == 1, (reason, counters)
    # a payload longer than the fields we know (valid CRC): a newer dialect's extensions,
    # dropped as pymavlink drops them (MAVLink: unknown extensions are ignored), the
    # fields we know decoded; the fast path (ATTITUDE) and pymavlink's (COMMAND_ACK)
    mav = codec()
    for msg_id, crc_extra, known in ((30, 39, 28), (77, 143, 10)):
        frame = raw_frame(msg_id, crc_extra, bytes(range(1, known + 8)))
        rx, counters = receiver()
        msgs, failures = rx.datagram(frame)
        assert failures == 0, (msg_id, counters)
        assert_same_as_pymavlink(frame, msgs[0])
    assert mav is not None


def test_a_datagram_of_several_frames():
    mav = codec()
    other = codec(sysid=42)
    dgram = _attitude(mav, 1) + _attitude(other, 2) + _attitude(mav, 3)
    rx, counters = receiver()
    msgs, failures = rx.datagram(dgram)
    assert [m.time_boot_ms for m in msgs] == [1, 3]
    assert failures == 1
    assert counters["wrong_system"] == 1
    # a bad CRC ends the datagram: the extent of what follows cannot be trusted
    bad = bytearray(_attitude(mav, 4))
    bad[12] ^= 1
    msgs, failures = rx.datagram(_attitude(mav, 5) + bytes(bad) + _attitude(mav, 6))
    assert [m.time_boot_ms for m in msgs] == [5]
    # trailing garbage after good frames
    msgs, failures = rx.datagram(_attitude(mav, 7) + b"\x00\x01junk")
    assert [m.time_boot_ms for m in msgs] == [7]
    assert failures == 1


@settings(max_examples=100, deadline=None)
@given(cuts=st.lists(st.integers(0, 400), max_size=8), noise=st.binary(max_size=20))
def test_a_stream_cut_anywhere_gives_the_same_messages(cuts, noise):
    mav, other = codec(), codec(sysid=42)
    data = (
        noise + _attitude(mav, 1) + _attitude(other, 2) + b"\xfd\x05" + _attitude(mav, 3)
        + bytes(mav.command_ack_encode(1, 0).pack(mav)) + _attitude(mav, 4)
    )  # fmt: skip
    rx, _ = receiver()
    got = []
    start = 0
    for cut in [*sorted({min(c, len(data)) for c in cuts}), len(data)]:
        got += rx.stream(data[start:cut])
        start = cut
    times = [m.time_boot_ms for m in got if m.get_type() == "ATTITUDE"]
    assert times == [1, 3, 4]
    assert [m.get_type() for m in got].count("COMMAND_ACK") == 1


def test_a_stream_shared_with_another_system_counts_its_frames_once():
    """A radio link carries another system's frames too: each counted as a wrong system,
    none as junk, and ours all delivered."""
    mav, other = codec(), codec(sysid=42)
    data = b"".join(_attitude(m, t) for t, m in enumerate([mav, other, other, mav, other]))
    rx, counters = receiver()
    assert [m.time_boot_ms for m in rx.stream(data)] == [0, 3]
    assert counters["wrong_system"] == 3
    assert counters["bad_data"] == 0


def test_signed_frames():
    check = enable_signing(mavlink.MAVLink(None), KEY)
    rx, counters = receiver(signature=check)
    signer = codec(key=KEY)
    frame = _attitude(signer, 9)
    msgs, _ = rx.datagram(frame)
    assert msgs[0].time_boot_ms == 9
    assert msgs[0].get_signed()
    assert_same_as_pymavlink(frame, msgs[0])
    assert rx.datagram(frame)[0] == []  # replayed
    assert rx.datagram(_attitude(codec(), 10))[0] == []  # unsigned
    assert rx.datagram(_attitude(codec(key=bytes(32)), 11))[0] == []  # wrong key
    assert counters["bad_signature"] == 3
    assert check.rejected == {"bad_signature": 1, "replayed": 1, "stale_stream": 0}
    # a frame that fails the header check never reaches the (costly, stateful) signature
    rx.datagram(_attitude(codec(sysid=42, key=KEY), 12))
    assert counters["wrong_system"] == 1
    assert sum(check.rejected.values()) == 2
    # without signing configured, a signed frame is accepted as pymavlink accepts it
    rx, _ = receiver()
    assert rx.datagram(_attitude(codec(key=KEY), 13))[0][0].time_boot_ms == 13


def test_the_gate_throttles_a_garbage_source_and_bounds_rotating_ones():
    budget = ReceiveBudget(source_rate_per_s=10, source_burst=20, shared_rate_per_s=50,
                           shared_burst=50)  # fmt: skip
    gate = SourceGate(budget)
    now = 100.0
    admitted = 0
    for i in range(1000):  # one source, 1000 bad frames in 1 s
        t = now + i * 1e-3
        if gate.admits("bad", t):
            admitted += 1
            gate.charge("bad", 1, t)
    assert admitted <= 20 + 10 + 1
    # the genuine source, known good, is not held back by the shared bucket
    gate.delivered("good", now + 1.0)
    assert gate.admits("good", now + 1.0)
    # rotating sources: bounded by the shared bucket, and the table by max_sources
    admitted = 0
    for i in range(5000):
        t = now + 2.0 + i * 2e-4
        if gate.admits(("10.0.0.1", i), t):
            admitted += 1
            gate.charge(("10.0.0.1", i), 1, t)
    assert admitted <= 50 + 50 + 1
    assert gate.sources <= budget.max_sources
    assert gate.admits("good", now + 3.0)


async def _flood_beside_the_autopilot():
    got: list[Any] = []
    link = MavlinkLink(
        "udpin://127.0.0.1:0", system_id=245, component_id=191, on_message=got.append,
        accept_system_ids=frozenset({1}), accept_component_ids=frozenset({1}),
        accept_message_ids=SERVICE_MESSAGE_IDS,
    )  # fmt: skip
    await link.open()
    port = link.local_address[1]
    autopilot = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    fuzzer = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    fuzzer.setblocking(False)
    mav, stranger = codec(), codec(sysid=42)
    n_good = 200
    t0_s = time.monotonic()
    try:
        for i in range(n_good):
            autopilot.sendto(_attitude(mav, i), ("127.0.0.1", port))
            for j in range(20):  # 20 garbage datagrams per genuine one
                with contextlib.suppress(BlockingIOError):
                    fuzzer.sendto(
                        _attitude(stranger, j) if j % 2 else bytes([0xFD]) + bytes(40),
                        ("127.0.0.1", port),
                    )
            # paced by the reader: the next burst once this genuine frame is read (sent at a
            # fixed rate, at load 25 the socket's buffer overflowed while the loop was off
            # the CPU, and the kernel dropped genuine frames with the garbage)
            async with asyncio.timeout(10):
                while len(got) <= i:  # noqa: ASYNC110
                    await asyncio.sleep(0.002)
        await asyncio.sleep(0.05)
        elapsed_s = time.monotonic() - t0_s
    finally:
        link.close()
        autopilot.close()
        fuzzer.close()
    assert [m.time_boot_ms for m in got] == list(range(n_good))
    c = link.counters
    assert c["throttled"] > c["wrong_system"] + c["bad_data"], c  # most never read
    # the fuzzer's bucket: its burst and its refill while this ran (2 s idle, longer loaded)
    assert c["wrong_system"] + c["bad_data"] <= 200 + 100 * elapsed_s + 1, (c, elapsed_s)


def test_a_garbage_flood_is_throttled_and_the_autopilot_is_not():
    asyncio.run(_flood_beside_the_autopilot())


def test_the_tracker_reads_fast_messages_as_it_reads_pymavlinks():
    """The same flight's frames, decoded by pymavlink and by the fast path, leave two state
    trackers in the same state (state.py is unchanged: the interface is the contract)."""
    rng = random.Random(1)
    mav = codec()
    frames = []
    for i in range(400):
        t_ms = 1000 + 5 * i
        r = [rng.uniform(-0.3, 0.3) for _ in range(6)]
        frames.append(mav.attitude_quaternion_encode(t_ms, 1.0, r[0] / 9, r[1] / 9, r[2] / 9,
                                                     *r[3:]))  # fmt: skip
        if i % 2:
            frames.append(mav.local_position_ned_encode(t_ms, r[0], r[1], -2 + r[2], *r[3:]))
        if i % 7 == 0:
            frames.append(mav.odometry_encode(
                t_ms * 1000, 1, 12, r[0], r[1], -2.0, [1.0, r[2] / 9, 0.0, 0.0], *r[3:], *r[:3],
                [math.nan] + [0.0] * 20, [math.nan] + [0.0] * 20))  # fmt: skip
        if i % 100 == 0:
            frames.append(mav.heartbeat_encode(2, 12, 157, 6 << 16, 4))
            frames.append(mav.attitude_encode(t_ms, math.nan, 0, 0, 0, 0, 0))
    wire = [bytes(f.pack(mav)) for f in frames]
    slow, fast = StateTracker(system_id=1), StateTracker(system_id=1)
    rx, _ = receiver()
    oracle = mavlink.MAVLink(None)
    for k, data in enumerate(wire):
        t = 10.0 + k * 1e-3
        (msg,) = oracle.parse_buffer(data)
        (got,) = rx.datagram(data)[0]
        assert slow.handle(msg, received_s=t) == fast.handle(got, received_s=t)
    a, b = slow.snapshot(), fast.snapshot()
    assert a is not None
    assert b is not None
    for name in ("time_s", "pos_ned_m", "vel_ned_m_s", "q_ned_frd", "rate_frd_rad_s"):
        assert np.array_equal(getattr(a, name), getattr(b, name)), name
    assert slow.heartbeat == fast.heartbeat
    assert slow.counters == fast.counters


def test_rotating_addresses_cost_bounded_work_and_the_peer_is_never_throttled():
    """A flood from 5,000 source addresses (each new, so each with a full bucket of its own)
    is bounded by the bucket the unknown sources share; the peer's garbage is never
    throttled and its genuine frames all arrive."""
    got: list[Any] = []
    link = MavlinkLink(
        "udpin://127.0.0.1:0", system_id=245, component_id=191, on_message=got.append,
        accept_system_ids=frozenset({1}), accept_component_ids=frozenset({1}),
        accept_message_ids=SERVICE_MESSAGE_IDS,
        budget=ReceiveBudget(shared_rate_per_s=100.0, shared_burst=100.0),
    )  # fmt: skip
    peer = ("127.0.0.1", 14580)
    mav, stranger = codec(), codec(sysid=42)
    link._on_datagram(_attitude(mav, 0), peer)  # the autopilot speaks first
    t0_s = time.monotonic()
    for i in range(5000):
        link._on_datagram(_attitude(stranger, i), ("10.0.0.1", 1024 + i))
        link._on_datagram(b"\x00 line noise " * 3, peer)  # the peer's own garbage
        if i % 50 == 0:
            link._on_datagram(_attitude(mav, 1 + i // 50), peer)
    elapsed_s = time.monotonic() - t0_s
    c = link.counters
    # examined: the shared burst and what it refilled while this ran (well under a second
    # idle; the link's clock is the wall clock, so a loaded run refills more)
    examined = 100 + 100 * elapsed_s + 1
    assert c["wrong_system"] <= examined, (c, elapsed_s)
    assert c["throttled"] >= 5000 - examined, (c, elapsed_s)
    assert c["not_mavlink"] == 5000  # the peer's: every datagram read, none throttled
    assert [m.time_boot_ms for m in got] == list(range(101))
    assert link.gate.sources <= ReceiveBudget().max_sources
