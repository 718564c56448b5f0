"""The MAVLink receive path: every frame judged by its header before its payload is decoded,
the streams the loops fly on decoded by precompiled ``struct`` layouts, and a budget per
sender so that garbage costs bounded CPU.

Issue 21: fuzzed MAVLink at 1,500 datagrams/s to the service's port cost the loops their
period, because every datagram went through pymavlink's parser (a Python-level CRC, a message
object per frame, a ``BAD_DATA`` object per bad byte run) on the interpreter the loops share.
Here a frame is checked in the order of what each check costs, and dropped at the first that
fails, counted by reason:

1. the datagram: MAVLink 2's magic byte and a minimum length (a datagram that is not
   MAVLink at all costs one comparison); a MAVLink 1 frame is refused (``mavlink1``): PX4 and
   ArduPilot speak MAVLink 2 on the links this service uses, and MAVLink 1 can be neither
   signed nor extended, so accepting it would only widen what a forger can send;
2. the header (one ``struct`` unpack): incompatibility flags (only "signed" is defined),
   system id, component id, message id (only the ids the service reads), the payload
   length against the message's range (MAVLink 2 truncates trailing zero bytes: 1 .. full
   length), the frame fits in what arrived;
3. the CRC with the message's CRC_EXTRA (X.25, computed by the C code of
   ``binascii.crc_hqx`` on bit-reversed bytes: see :func:`x25_crc`);
4. the signature, when signing is configured (:class:`~epc_offboard.common.signing.
   SignatureCheck`: verified before its timestamp is recorded).

Only then is the payload decoded: zero-padded to the full length and unpacked by one
precompiled ``struct.Struct`` for the streams the loops use (:data:`FAST_MESSAGES`), into a
:class:`FastMessage`, a tuple with pymavlink's accessors (``get_type()``,
``get_srcSystem()``, attribute per field), so the tracker reads it as it reads pymavlink's
messages. Everything else the service reads (COMMAND_ACK, PARAM_VALUE, STATUSTEXT, ...) is
decoded by pymavlink, once it has passed the same checks.

Datagrams carry whole frames back to back (MAVLink over UDP): a frame that fails a check
after which its extent cannot be trusted (a bad length, a bad CRC) ends its datagram. A byte
stream (serial, TCP) resynchronises on the next magic byte instead, as pymavlink does.

Per sender (:class:`SourceGate`): frames that fail the header check are charged to a token
bucket of the source address, and to one shared by all sources that have not delivered a
valid frame lately; while either is empty, that source's datagrams are dropped unread
(``throttled``). The link's established peer (the autopilot) is never throttled, and a
source that has delivered a valid frame is not charged to the shared bucket, so a storm
from any number of addresses costs a bounded number of header checks per second and never
drops what the loops need.
"""

from __future__ import annotations

import binascii
import struct
from collections import Counter
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from operator import itemgetter
from typing import Any, ClassVar

from pymavlink.dialects.v20 import common as mavlink

from epc_offboard.common.signing import SignatureCheck

MAGIC_V2 = 0xFD
MAGIC_V1 = 0xFE
HEADER_LEN = 10  # magic, len, incompat, compat, seq, sysid, compid, msgid (3)
CRC_LEN = 2
SIGNATURE_LEN = 13  # link id (1), timestamp (6), signature (6)
IFLAG_SIGNED = 0x01
MIN_PAYLOAD_LEN = 1  # MAVLink 2 never truncates a payload's first byte
MIN_FRAME_LEN = HEADER_LEN + MIN_PAYLOAD_LEN + CRC_LEN
# Frames examined in one datagram: PX4 packs up to an MTU (1500 bytes, ~115 minimal frames)
# into one; more is an attack on the scanner's loop.
MAX_FRAMES_PER_DATAGRAM = 256
# ... from an address other than the peer's while the peer talks (unsigned: nothing of it is
# flown, ``link.MavlinkLink``): 256 frames of the vehicle's own ids packed in one datagram
# took the loops' thread 1.6 ms in one callback (load 10), 16 take ~0.1 ms
MAX_FRAMES_PER_STRANGER_DATAGRAM = 16
INCOMPLETE = -1  # a stream's frame whose header passed and whose rest is still to come

_HEADER = struct.Struct("<BBBBBBBHB")  # ..., msgid low 16 bits, msgid high 8 bits
_CRC = struct.Struct("<H")

# A sender's malformed frames forgiven before it is unclean (SourceGate.clean): a genuine link
# drops the odd corrupt frame (a radio's CRC error bridged to UDP, a frame cut in two); a
# fuzzer sends them by the hundred a second
MALFORMED_TOLERATED = 3
# The malformed reasons, each also counted as "bad_data" (the total the stats have always had)
MALFORMED = ("not_mavlink", "mavlink1", "bad_length", "bad_flags", "bad_crc", "frame_limit")


# -- CRC ------------------------------------------------------------------------------------

# bit-reversal of every byte value
_REVERSE = bytes(int(f"{i:08b}"[::-1], 2) for i in range(256))
_REVERSED_BYTE = tuple(bytes((_REVERSE[i],)) for i in range(256))


def x25_crc(data: bytes, crc_extra: int) -> int:
    """MAVLink's checksum (CRC-16/MCRF4XX: X.25's polynomial 0x1021 bit-reflected, initial
    0xFFFF, no final xor) of ``data`` followed by the byte ``crc_extra``.

    ``binascii.crc_hqx`` is the same polynomial unreflected (CRC-16/XMODEM's register): a
    reflected CRC equals the unreflected one over bit-reversed bytes, bit-reversed. Both
    byte reversals are table lookups in C, so a frame's CRC costs no Python-level loop.
    """
    reg = binascii.crc_hqx(data.translate(_REVERSE), 0xFFFF)
    reg = binascii.crc_hqx(_REVERSED_BYTE[crc_extra], reg)
    return (_REVERSE[reg & 0xFF] << 8) | _REVERSE[reg >> 8]


# -- the fast messages ----------------------------------------------------------------------


@dataclass(frozen=True)
class Layout:
    """One message's wire layout: fields in MAVLink's wire order (base fields sorted by type
    size, largest first, then extension fields in definition order); ``fmt`` their ``struct``
    format, arrays as ``Nf``; ``arrays`` the length of each array field."""

    name: str
    msg_id: int
    crc_extra: int
    fmt: str
    fields: tuple[str, ...]
    arrays: dict[str, int] = field(default_factory=dict)


# The streams the loops fly on (common.xml), and the telemetry that comes with them. A test
# checks each against pymavlink's codec.
FAST_LAYOUTS = (
    Layout(
        "HEARTBEAT", 0, 50, "<IBBBBB",
        ("custom_mode", "type", "autopilot", "base_mode", "system_status", "mavlink_version"),
    ),
    Layout(
        "ATTITUDE", 30, 39, "<Iffffff",
        ("time_boot_ms", "roll", "pitch", "yaw", "rollspeed", "pitchspeed", "yawspeed"),
    ),
    Layout(
        "ATTITUDE_QUATERNION", 31, 246, "<Ifffffff4f",
        ("time_boot_ms", "q1", "q2", "q3", "q4", "rollspeed", "pitchspeed", "yawspeed",
         "repr_offset_q"),  # extension
        {"repr_offset_q": 4},
    ),
    Layout(
        "LOCAL_POSITION_NED", 32, 185, "<Iffffff",
        ("time_boot_ms", "x", "y", "z", "vx", "vy", "vz"),
    ),
    Layout(
        "ODOMETRY", 331, 91, "<Qfff4fffffff21f21fBBBBb",
        ("time_usec", "x", "y", "z", "q", "vx", "vy", "vz", "rollspeed", "pitchspeed",
         "yawspeed", "pose_covariance", "velocity_covariance", "frame_id", "child_frame_id",
         "reset_counter", "estimator_type", "quality"),  # the last three: extensions
        {"q": 4, "pose_covariance": 21, "velocity_covariance": 21},
    ),
    # what the autopilot streams beside the state, decoded here too: pymavlink's decode (a
    # message object, ~50 us a frame) made GLOBAL_POSITION_INT, at the state's rate, and the
    # SITL's 10 Hz telemetry burst the costliest datagrams of the receive path
    Layout(
        "GLOBAL_POSITION_INT", 33, 104, "<IiiiihhhH",
        ("time_boot_ms", "lat", "lon", "alt", "relative_alt", "vx", "vy", "vz", "hdg"),
    ),
    Layout("EXTENDED_SYS_STATE", 245, 130, "<BB", ("vtol_state", "landed_state")),
    # common.xml's target_system, target_component follow (extensions pymavlink's dialect
    # lacks): PX4 fills them in every answer, an 18-byte payload, taken (the length check)
    Layout("TIMESYNC", 111, 34, "<qq", ("tc1", "ts1")),
    Layout("SYSTEM_TIME", 2, 137, "<QI", ("time_unix_usec", "time_boot_ms")),
)  # fmt: skip

# what follows the payload's values in a FastMessage
_SRC_SYSTEM, _SRC_COMPONENT, _SEQ, _SIGNED, _FRAME = range(-5, 0)


class FastMessage(tuple[Any, ...]):
    """A decoded message as a tuple: the payload's values in wire order, then source system,
    source component, sequence, signed, and the frame's bytes. Built in one C call; each
    field is a property (``msg.time_boot_ms``), arrays as lists as pymavlink gives them.

    The accessors are pymavlink's (``get_type``, ``get_srcSystem``, ``get_srcComponent``,
    ``get_seq``, ``get_msgId``, ``get_msgbuf``, ``get_signed``, ``get_fieldnames`` (in wire
    order, where pymavlink gives definition order), ``to_dict``).
    """

    __slots__ = ()
    NAME: ClassVar[str] = ""
    MSG_ID: ClassVar[int] = -1
    FIELDNAMES: ClassVar[tuple[str, ...]] = ()

    def get_type(self) -> str:
        return self.NAME

    def get_msgId(self) -> int:  # noqa: N802 - pymavlink's name
        return self.MSG_ID

    def get_srcSystem(self) -> int:  # noqa: N802
        return self[_SRC_SYSTEM]  # type: ignore[no-any-return]

    def get_srcComponent(self) -> int:  # noqa: N802
        return self[_SRC_COMPONENT]  # type: ignore[no-any-return]

    def get_seq(self) -> int:
        return self[_SEQ]  # type: ignore[no-any-return]

    def get_signed(self) -> bool:
        return bool(self[_SIGNED])

    def get_msgbuf(self) -> bytes:
        return bytes(self[_FRAME])

    def get_fieldnames(self) -> list[str]:
        return list(self.FIELDNAMES)

    def to_dict(self) -> dict[str, Any]:
        return {"mavpackettype": self.NAME, **{n: getattr(self, n) for n in self.FIELDNAMES}}

    def __repr__(self) -> str:
        body = ", ".join(f"{n}={getattr(self, n)!r}" for n in self.FIELDNAMES)
        return f"{self.NAME} {{{body}}}"


def _array_getter(start: int, length: int) -> property:
    def get(self: tuple[Any, ...]) -> list[Any]:
        return list(self[start : start + length])

    return property(get)


def _message_class(layout: Layout) -> type[FastMessage]:
    attrs: dict[str, Any] = {
        "__slots__": (),
        "NAME": layout.name,
        "MSG_ID": layout.msg_id,
        "FIELDNAMES": layout.fields,
    }
    index = 0
    for name in layout.fields:
        n = layout.arrays.get(name, 1)
        attrs[name] = (
            _array_getter(index, n) if name in layout.arrays else property(itemgetter(index))
        )
        index += n
    return type(f"Fast_{layout.name}", (FastMessage,), attrs)


@dataclass(frozen=True)
class _Spec:
    """What the header check needs of one accepted message id, and how it is decoded."""

    crc_extra: int
    unpacker: struct.Struct | None  # None: decoded by pymavlink
    make: type[FastMessage] | None


def _specs(ids: Iterable[int]) -> dict[int, _Spec]:
    fast = {layout.msg_id: layout for layout in FAST_LAYOUTS}
    out: dict[int, _Spec] = {}
    for msg_id in ids:
        if msg_id in fast:
            layout = fast[msg_id]
            unpacker = struct.Struct(layout.fmt)
            out[msg_id] = _Spec(layout.crc_extra, unpacker, _message_class(layout))
        elif msg_id in mavlink.mavlink_map:
            cls = mavlink.mavlink_map[msg_id]
            out[msg_id] = _Spec(cls.crc_extra, None, None)
        else:
            raise ValueError(f"message id {msg_id} is not in pymavlink's common dialect")
    return out


FAST_MESSAGES = frozenset(layout.name for layout in FAST_LAYOUTS)

# What the service reads from its autopilot: the loops' streams, then what the supervisor,
# the dialects and the logs use. A message not listed is dropped by its header.
SERVICE_MESSAGE_IDS = frozenset(
    {
        *(layout.msg_id for layout in FAST_LAYOUTS),
        mavlink.MAVLINK_MSG_ID_GLOBAL_POSITION_INT,
        mavlink.MAVLINK_MSG_ID_EXTENDED_SYS_STATE,
        mavlink.MAVLINK_MSG_ID_PARAM_VALUE,
        mavlink.MAVLINK_MSG_ID_COMMAND_ACK,
        mavlink.MAVLINK_MSG_ID_STATUSTEXT,
        mavlink.MAVLINK_MSG_ID_SYSTEM_TIME,
        mavlink.MAVLINK_MSG_ID_TIMESYNC,
    }
)
ALL_MESSAGE_IDS = frozenset(mavlink.mavlink_map)


# -- the per-source budget ------------------------------------------------------------------


@dataclass(frozen=True)
class ReceiveBudget:
    """How much header-check failure a sender may cost (frames per second, and a burst)."""

    source_rate_per_s: float = 100.0
    source_burst: float = 200.0
    # shared by every source that has not delivered a valid frame in ``good_for_s``:
    # bounds a storm from rotating addresses
    shared_rate_per_s: float = 400.0
    shared_burst: float = 400.0
    good_for_s: float = 5.0
    max_sources: int = 256  # buckets kept; past it the oldest is forgotten
    max_good_sources: int = 16

    def __post_init__(self) -> None:
        for name in ("source_rate_per_s", "source_burst", "shared_rate_per_s", "shared_burst"):
            if not getattr(self, name) > 0.0:
                raise ValueError(f"ReceiveBudget.{name} must be > 0")
        if self.max_sources < 1 or self.max_good_sources < 1:
            raise ValueError("ReceiveBudget: max_sources and max_good_sources must be >= 1")


class _Bucket:
    __slots__ = ("stamp_s", "tokens")

    def __init__(self, tokens: float, stamp_s: float) -> None:
        self.tokens = tokens
        self.stamp_s = stamp_s

    def refill(self, now_s: float, rate_per_s: float, burst: float) -> float:
        self.tokens = min(burst, self.tokens + (now_s - self.stamp_s) * rate_per_s)
        self.stamp_s = now_s
        return self.tokens


class SourceGate:
    """Token buckets of header-check failures per source address (bounded in count), and one
    shared by the sources not known good. Pure bookkeeping: the caller gives the time."""

    def __init__(self, budget: ReceiveBudget) -> None:
        self.budget = budget
        self._buckets: dict[Any, _Bucket] = {}
        self._shared = _Bucket(budget.shared_burst, 0.0)
        self._good: dict[Any, float] = {}  # source -> when it last delivered a valid frame
        # source -> [when it last sent a malformed frame, how many since it was last clean]
        self._dirty: dict[Any, list[float]] = {}

    def admits(self, source: Any, now_s: float) -> bool:
        """Whether a datagram from ``source`` may be read at all."""
        b = self.budget
        bucket = self._buckets.get(source)
        if bucket is not None and bucket.refill(now_s, b.source_rate_per_s, b.source_burst) < 1:
            return False
        if self._is_good(source, now_s):
            return True
        return self._shared.refill(now_s, b.shared_rate_per_s, b.shared_burst) >= 1

    def charge(self, source: Any, failures: int, now_s: float) -> None:
        """``failures`` frames of ``source`` failed the header check."""
        b = self.budget
        bucket = self._buckets.get(source)
        if bucket is None:
            if len(self._buckets) >= b.max_sources:
                del self._buckets[next(iter(self._buckets))]
            bucket = self._buckets[source] = _Bucket(b.source_burst, now_s)
        bucket.tokens -= failures
        if not self._is_good(source, now_s):
            self._shared.tokens -= failures

    def delivered(self, source: Any, now_s: float) -> None:
        """``source`` sent a frame that passed every check."""
        good = self._good
        if source not in good and len(good) >= self.budget.max_good_sources:
            del good[min(good, key=good.__getitem__)]
        good[source] = now_s

    def soiled(self, source: Any, malformed: int, now_s: float) -> None:
        """``source`` sent ``malformed`` frames no autopilot sends (not MAVLink, MAVLink 1,
        bad length, flags or CRC: :data:`MALFORMED`); messages it does not read, or of other
        systems, are an autopilot's everyday traffic and do not count."""
        if malformed <= 0:
            return
        dirty = self._dirty
        seen = dirty.get(source)
        if seen is None:
            if len(dirty) >= self.budget.max_sources:
                del dirty[next(iter(dirty))]
            dirty[source] = [now_s, float(malformed)]
        elif now_s - seen[0] > self.budget.good_for_s:  # clean again meanwhile: a new count
            seen[0], seen[1] = now_s, float(malformed)
        else:
            seen[0] = now_s
            seen[1] += malformed

    def clean(self, source: Any, now_s: float) -> bool:
        """Whether ``source`` has sent at most :data:`MALFORMED_TOLERATED` malformed frames,
        none more than ``good_for_s`` apart: only such a sender may become the link's peer (a
        fuzzer never is), and a peer stays one through a link's rare corrupt frame (a CRC
        error on a radio bridged to UDP) while a second sender talks."""
        seen = self._dirty.get(source)
        return (seen is None or now_s - seen[0] > self.budget.good_for_s
                or seen[1] <= MALFORMED_TOLERATED)  # fmt: skip

    def _is_good(self, source: Any, now_s: float) -> bool:
        seen = self._good.get(source)
        return seen is not None and now_s - seen <= self.budget.good_for_s

    @property
    def sources(self) -> int:
        return len(self._buckets)


# -- the receiver ---------------------------------------------------------------------------


class FrameReceiver:
    """Frames in, accepted messages out: the checks of the module docstring, counted by
    reason into ``counters`` (the link's).

    ``accept_systems`` / ``accept_components``: None accepts any. ``signature``: the link's
    check when signing is configured (then an unsigned frame is refused); without one, a
    signed frame is accepted unverified, as pymavlink does. ``decode_other``: pymavlink's
    decoder for the accepted ids that have no fast layout.
    """

    def __init__(
        self,
        counters: Counter[str],
        *,
        accept_ids: Iterable[int],
        accept_systems: frozenset[int] | None,
        accept_components: frozenset[int] | None,
        signature: SignatureCheck | None,
        decode_other: Callable[[bytearray], Any],
        on_mavlink1: Callable[[], None] | None = None,
    ) -> None:
        self.counters = counters
        self._specs = _specs(accept_ids)
        self._systems = accept_systems
        self._components = accept_components
        self._signature = signature
        self._decode_other = decode_other
        self._on_mavlink1 = on_mavlink1
        self._stream = bytearray()  # a byte stream's bytes not yet framed
        self._zeros = bytes(max((s.unpacker.size for s in self._specs.values()
                                 if s.unpacker is not None), default=0))  # fmt: skip

    def reset_stream(self) -> None:
        self._stream.clear()

    # -- entry points -----------------------------------------------------------------------

    def datagram(self, data: bytes,
                 max_frames: int = MAX_FRAMES_PER_DATAGRAM) -> tuple[list[Any], int]:  # fmt: skip
        """The messages of one datagram, and how many of its frames failed a check (what a
        source is charged for); past ``max_frames`` frames the rest is dropped, counted
        (``frame_limit``)."""
        if len(data) < MIN_FRAME_LEN or data[0] != MAGIC_V2:
            self._malformed(
                "mavlink1" if data[:1] == b"\xfe" else "not_mavlink"
            )  # fmt: skip
            return [], 1
        out: list[Any] = []
        failures = 0
        pos, end = 0, len(data)
        for _ in range(max_frames):
            if pos >= end:
                return out, failures
            if end - pos < HEADER_LEN or data[pos] != MAGIC_V2:
                self._malformed("bad_length" if data[pos] == MAGIC_V2 else "not_mavlink")
                return out, failures + 1
            size, msg = self._frame(data, pos, end)
            if msg is not None:
                out.append(msg)
            else:
                failures += 1
            if size <= 0:  # the frame's extent is not to be trusted: the rest is lost
                return out, failures
            pos += size
        if pos >= end:  # exactly max_frames frames: none dropped
            return out, failures
        self._malformed("frame_limit")
        return out, failures + 1

    def stream(self, data: bytes) -> list[Any]:
        """The messages completed by ``data``, a byte stream's next bytes (serial, TCP):
        a frame may be split anywhere; after a bad frame, the next magic byte is tried."""
        buf = self._stream
        buf += data
        out: list[Any] = []
        pos = 0
        end = len(buf)
        view = bytes(buf)
        # the extent a rejected header claimed: the bytes in it are that frame's, counted
        # with it, not again as junk
        claimed = 0
        while True:
            start = view.find(MAGIC_V2, pos, end)
            if start < 0:
                if claimed < end > pos:
                    self._malformed("not_mavlink")
                pos = end
                break
            if start > pos and start > claimed:
                self._malformed("not_mavlink")
            pos = start
            if end - pos < HEADER_LEN:
                break
            used, msg = self._frame(view, pos, end, stream=True)
            if used == INCOMPLETE:
                break  # a plausible frame whose rest has not arrived (at most 280 bytes)
            if msg is not None:
                out.append(msg)
                pos += used
                continue
            # anything else resynchronises on the next magic byte, which may start a
            # genuine frame (a rejected header's length byte is not to be trusted here)
            claimed = max(claimed, pos + used)
            pos += 1
        del buf[:pos]
        return out

    # -- one frame --------------------------------------------------------------------------

    def _frame(self, data: bytes, pos: int, end: int, *, stream: bool = False) -> tuple[int, Any]:
        """Check and decode the frame at ``data[pos]`` (a magic byte, at least HEADER_LEN
        bytes before ``end``). Returns (its size, or 0 when its extent is not to be trusted,
        or INCOMPLETE on a ``stream`` whose frame, its header accepted, has not all arrived;
        the message or None)."""
        _, plen, iflags, _, seq, sysid, compid, id_lo, id_hi = _HEADER.unpack_from(data, pos)
        if iflags & ~IFLAG_SIGNED:
            self._malformed("bad_flags")
            return 0, None
        signed = iflags & IFLAG_SIGNED
        size = HEADER_LEN + plen + CRC_LEN + (SIGNATURE_LEN if signed else 0)
        counters = self.counters
        if self._systems is not None and sysid not in self._systems:
            counters["wrong_system"] += 1
            return size, None
        if self._components is not None and compid not in self._components:
            counters["wrong_component"] += 1
            return size, None
        msg_id = id_lo | (id_hi << 16)
        spec = self._specs.get(msg_id)
        if spec is None:
            counters["unknown_message"] += 1
            return size, None
        # no upper bound short of the length byte's: a payload longer than the fields we know
        # is a newer dialect's extensions (PX4's TIMESYNC answer: 18 bytes, pymavlink's
        # dialect knows 16; stop 43 found every answer of a real PX4 refused as too long),
        # its known fields decoded and the rest dropped, as pymavlink decodes (MAVLink's
        # rule: extensions a receiver does not know are ignored)
        if plen < MIN_PAYLOAD_LEN:
            self._malformed("bad_length")
            return 0, None
        if pos + size > end:
            if stream:
                return INCOMPLETE, None
            self._malformed("bad_length")
            return 0, None
        crc_at = pos + HEADER_LEN + plen
        if _CRC.unpack_from(data, crc_at)[0] != x25_crc(data[pos + 1 : crc_at], spec.crc_extra):
            self._malformed("bad_crc")
            return 0, None
        frame = data[pos : pos + size]
        if self._signature is not None:
            if not signed:
                counters["bad_signature"] += 1
                return size, None
            if not self._signature(bytearray(frame), sysid, compid):
                counters["bad_signature"] += 1
                return size, None
        if spec.unpacker is None:
            try:
                msg = self._decode_other(bytearray(frame))
            except Exception:  # pymavlink's: one frame lost, not the rest of the datagram
                counters["decode_errors"] += 1
                return size, None
            if signed:
                msg._signed = self._signature is not None
                msg._link_id = frame[-SIGNATURE_LEN]
            return size, msg
        assert spec.make is not None
        payload = data[pos + HEADER_LEN : crc_at]
        known = spec.unpacker.size  # the fields we know; a newer dialect's extensions dropped
        if plen < known:
            payload += self._zeros[: known - plen]  # MAVLink 2's truncated zeros
        values = spec.unpacker.unpack_from(payload)
        signed_ok = bool(signed) and self._signature is not None
        return size, tuple.__new__(spec.make, (*values, sysid, compid, seq, signed_ok, frame))

    def _malformed(self, reason: str) -> None:
        counters = self.counters
        counters[reason] += 1
        counters["bad_data"] += 1
        if reason == "mavlink1" and self._on_mavlink1 is not None:
            self._on_mavlink1()
