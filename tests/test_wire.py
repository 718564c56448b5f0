"""The fleet wire codec: round trips, and every malformed payload rejected with a reason."""

from __future__ import annotations

import contextlib
import json
import math
import struct

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from epc_offboard.control.library_types import LibraryEntry
from epc_offboard.fleet.wire import (
    ControllerMessage,
    MessageKind,
    ReferenceMessage,
    WireError,
    decode_controllers,
    decode_reference,
    encode_controllers,
    encode_reference,
)

SIG = "0123456789abcdef0123456789abcdef"
LIMIT = 1 << 20


def message(**kw) -> ControllerMessage:
    base: dict = {
        "kind": MessageKind.SNAPSHOT,
        "signature": SIG,
        "vehicle_id": "uav-7",
        "entries": (
            LibraryEntry((), 0.0, 0),
            LibraryEntry((1, 5, 200), 12.5, 3),
            LibraryEntry((0, 65535), -1.0, 2**32 - 1),
        ),
        "transitions": ((0, 1, 4), (1, 2, 1)),
    }
    base.update(kw)
    return ControllerMessage(**base)


def decode(data: bytes, **kw) -> ControllerMessage:
    return decode_controllers(data, max_payload_bytes=kw.pop("max_payload_bytes", LIMIT), **kw)


def test_round_trip_with_and_without_transitions():
    for msg in (message(), message(kind=MessageKind.BATCH, transitions=())):
        assert decode(encode_controllers(msg)) == msg


entries_st = st.lists(
    st.builds(
        LibraryEntry,
        st.lists(st.integers(0, 0xFFFF), max_size=30, unique=True).map(lambda v: tuple(sorted(v))),
        st.floats(allow_nan=False, allow_infinity=False),
        st.integers(0, 2**32 - 1),
    ),
    max_size=20,
)


@settings(max_examples=200, deadline=None)
@given(entries=entries_st, vid=st.from_regex(r"[A-Za-z0-9_-]{1,32}", fullmatch=True),
       kind=st.sampled_from(MessageKind), data=st.data())  # fmt: skip
def test_round_trip_property(entries, vid, kind, data):
    n = len(entries)
    trans = ()
    if n:
        trans = tuple(
            data.draw(
                st.lists(
                    st.tuples(
                        st.integers(0, n - 1), st.integers(0, n - 1), st.integers(1, 2**32 - 1)
                    ),
                    max_size=10,
                )
            )
        )
    msg = ControllerMessage(kind, SIG, vid, tuple(entries), trans)
    assert decode(encode_controllers(msg)) == msg


def test_every_truncation_and_any_padding_is_rejected():
    data = encode_controllers(message())
    for cut in range(len(data)):
        with pytest.raises(WireError):
            decode(data[:cut])
    with pytest.raises(WireError, match="bytes after"):
        decode(data + b"\0")


@settings(max_examples=500, deadline=None)
@given(st.binary(max_size=300))
def test_garbage_is_rejected_with_a_wire_error(blob):
    with pytest.raises(WireError):
        decode(blob)


@settings(max_examples=300, deadline=None)
@given(st.data())
def test_flipped_bytes_never_escape_as_another_exception(data):
    raw = bytearray(encode_controllers(message()))
    for _ in range(data.draw(st.integers(1, 4))):
        raw[data.draw(st.integers(0, len(raw) - 1))] = data.draw(st.integers(0, 255))
    with contextlib.suppress(WireError):
        decode(bytes(raw))


def test_oversized_is_rejected_before_parsing():
    data = encode_controllers(message())
    with pytest.raises(WireError, match="exceeds the limit"):
        decode(data, max_payload_bytes=len(data) - 1)
    assert decode(data, max_payload_bytes=len(data)) == message()


def _patch(data: bytes, offset: int, fmt: str, *values) -> bytes:
    raw = bytearray(data)
    struct.pack_into(fmt, raw, offset, *values)
    return bytes(raw)


HEADER_END = 25 + len("uav-7")  # first entry-count byte


@pytest.mark.parametrize(
    ("offset", "fmt", "values", "reason"),
    [
        (0, "<4s", (b"XXXX",), "bad magic"),
        (4, "<B", (9,), "schema version 9"),
        (5, "<B", (7,), "unknown message kind"),
        (6, "<B", (0x81,), "unknown flags"),
        (7, "<B", (1,), "reserved"),
        (24, "<B", (0,), "vehicle id length 0"),
        (24, "<B", (40,), "vehicle id length 40"),
        (25, "<B", (ord("/"),), "vehicle id must be"),
        (HEADER_END, "<H", (0,), "bytes after"),
        (HEADER_END + 2 + 2 + 2 * 0 + 0, "<d", (math.nan,), "importance must be finite"),
    ],
)
def test_each_header_field_is_validated(offset, fmt, values, reason):
    data = _patch(encode_controllers(message()), offset, fmt, *values)
    with pytest.raises(WireError, match=reason):
        decode(data)


def test_indices_must_be_sorted_unique_and_in_range():
    one = message(entries=(LibraryEntry((3, 4), 0.0, 0),), transitions=())
    data = encode_controllers(one)
    first_index = HEADER_END + 2 + 2
    with pytest.raises(WireError, match="sorted and unique"):
        decode(_patch(data, first_index, "<HH", 4, 3))
    with pytest.raises(WireError, match="sorted and unique"):
        decode(_patch(data, first_index, "<HH", 4, 4))
    with pytest.raises(WireError, match=r"index 4 out of range 0\.\.3"):
        decode(data, n_con=4)
    with pytest.raises(WireError, match="2 active rows exceed 1"):
        decode(data, max_active=1)
    assert decode(data, n_con=5, max_active=2) == one


def test_limits_signature_and_transitions_are_enforced():
    data = encode_controllers(message())
    with pytest.raises(WireError, match="3 entries exceed the limit 2"):
        decode(data, max_entries=2)
    with pytest.raises(WireError, match="does not match the problem"):
        decode(data, expect_signature="f" * 32)
    bad = message(transitions=((0, 3, 1),))
    with pytest.raises(WireError, match="indexes outside"):
        encode_controllers(bad)
    with pytest.raises(WireError, match="signature must be 32"):
        encode_controllers(message(signature="abc"))
    with pytest.raises(WireError, match="vehicle id"):
        encode_controllers(message(vehicle_id="a/b"))


# -- references ---------------------------------------------------------------------------


def test_reference_round_trip():
    msgs = [
        ReferenceMessage((1.0, 2.0, -3.0)),
        ReferenceMessage((1.0, 2.0, -3.0), (0.5, 0.0, 0.0), 0.3),
        ReferenceMessage((0.0, 0.0, -2.0), None, None, 0.1, ((0.1, 0.0, -2.0), (0.2, 0.0, -2.0))),
    ]
    for msg in msgs:
        assert decode_reference(encode_reference(msg)) == msg


@pytest.mark.parametrize(
    ("body", "reason"),
    [
        (b"\xff\xfe", "not valid UTF-8 JSON"),
        (b"[1, 2]", "JSON object"),
        (b'{"v": 2, "pos_ned_m": [0, 0, 0]}', "version must be 1"),
        (b'{"v": 1}', "needs pos_ned_m"),
        (b'{"v": 1, "pos_ned_m": [0, 0]}', "pos_ned_m must be a list of 3"),
        (b'{"v": 1, "pos_ned_m": [0, 0, NaN]}', "must be finite"),
        (b'{"v": 1, "pos_ned_m": [0, 0, 1e400]}', "must be finite"),
        (b'{"v": 1, "pos_ned_m": [0, 0, true]}', "must be a number"),
        (b'{"v": 1, "pos_ned_m": [0, 0, 0], "vel": [0, 0, 0]}', "unknown keys"),
        (b'{"v": 1, "pos_ned_m": [0, 0, 0], "horizon_dt_s": 0.1}', "horizon_pos_ned_m must"),
        (
            b'{"v": 1, "pos_ned_m": [0, 0, 0], "horizon_dt_s": -1, "horizon_pos_ned_m": [[0,0,0]]}',
            "horizon_dt_s must be in",
        ),
        (b"[" * 5000, "not valid"),
    ],
)
def test_bad_references_are_rejected_naming_the_field(body, reason):
    with pytest.raises(WireError, match=reason):
        decode_reference(body)


def test_oversized_reference_is_rejected():
    body = json.dumps({"v": 1, "pos_ned_m": [0, 0, 0], "yaw_rad": 0.0}).encode()
    with pytest.raises(WireError, match="exceeds the limit"):
        decode_reference(body + b" " * 100, max_payload_bytes=len(body))
