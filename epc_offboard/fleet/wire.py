"""What vehicles of a fleet say to each other over Zenoh: a pure, versioned codec.

No I/O here (no zenoh, no asyncio): bytes in, frozen dataclasses out, and back. Everything a
decoder returns has been validated — anything else raises :class:`WireError` naming what
was wrong — because the bytes come from the network.

Controller messages (binary, little-endian, ``struct``)::

    offset size  field
    0      4     magic b"EPCL"
    4      1     schema version (1)
    5      1     kind: 1 = batch of new controllers, 2 = whole-library snapshot
    6      1     flags: bit 0 = a transitions block follows the entries; other bits 0
    7      1     reserved, 0
    8      16    problem signature (the 32 hex digits of MpcProblem.signature(), as bytes)
    24     1     L = length of the sender's vehicle id (1..32, [A-Za-z0-9_-])
    25     L     vehicle id, ASCII
    .      2     E = entry count (u16)
    per entry:
           2     A = active-set length (u16)
           2*A   sorted unique constraint row indices (u16 each)
           8     importance (f64, finite)
           4     uses (u32)
    if flags bit 0:
           4     T = transition count (u32)
           10*T  from (u16), to (u16) — indices into the entries —, count (u32, >= 1)

The declared counts must account for every byte: a truncated or padded payload is rejected.
Only controllers (active sets) travel, never gains: the receiver rebuilds each from its own
problem and applies it only where its own KKT check passes.

Live references (JSON, UTF-8, so planners written by others can produce them)::

    {"v": 1, "pos_ned_m": [n, e, d],               # required
     "vel_ned_m_s": [vn, ve, vd],                 # optional: track at this velocity
     "yaw_rad": 0.0,                              # optional
     "horizon_dt_s": 0.1,                         # optional, with "horizon_pos_ned_m":
     "horizon_pos_ned_m": [[n, e, d], ...]}       # positions at 1, 2, ... steps after pos
"""

from __future__ import annotations

import enum
import json
import math
import re
import struct
from dataclasses import dataclass
from typing import Any

from epc_offboard.common.errors import EpcError
from epc_offboard.control.library_types import EntryError, LibraryEntry, parse_entry

MAGIC = b"EPCL"
SCHEMA_VERSION = 1
MAX_VEHICLE_ID_LEN = 32
MAX_ENTRIES = 0xFFFF
MAX_REFERENCE_BYTES = 16384
MAX_HORIZON_POINTS = 200
# a fleet or vehicle name, in keys and payloads (sharing.SharingConfig validates with it too)
NAME_RE = re.compile(rf"[A-Za-z0-9_-]{{1,{MAX_VEHICLE_ID_LEN}}}")
_SIG_RE = re.compile(r"[0-9a-f]{32}")

_HEADER = struct.Struct("<4sBBBB16sB")  # magic, version, kind, flags, reserved, sig, id length
_U16 = struct.Struct("<H")
_U32 = struct.Struct("<I")
_ENTRY_TAIL = struct.Struct("<dI")  # importance, uses
_TRANSITION = struct.Struct("<HHI")
_FLAG_TRANSITIONS = 0x01
_INDEX_LIMIT = 0x10000  # active-set indices travel as u16
_U32_MAX = 0xFFFFFFFF


class WireError(EpcError, ValueError):
    """A payload that is not a valid message; the message says what was wrong."""


class MessageKind(enum.IntEnum):
    BATCH = 1  # controllers new since the sender's last batch
    SNAPSHOT = 2  # the sender's whole library (answer to a late joiner's query)


@dataclass(frozen=True)
class ControllerMessage:
    """Controllers of one problem from one vehicle.

    ``signature``: 32 lowercase hex digits (``MpcProblem.signature()``);
    ``transitions``: (from, to, count) over indices into ``entries``.
    """

    kind: MessageKind
    signature: str
    vehicle_id: str
    entries: tuple[LibraryEntry, ...]
    transitions: tuple[tuple[int, int, int], ...] = ()


def check_vehicle_id(name: str, what: str = "vehicle id") -> str:
    """``name`` if it is 1..32 characters of [A-Za-z0-9_-] (safe in a Zenoh key), else raise."""
    if not isinstance(name, str) or not NAME_RE.fullmatch(name):
        raise WireError(f"{what} must be 1..32 characters of [A-Za-z0-9_-], got {name!r}")
    return name


def check_signature(signature: str) -> str:
    if not isinstance(signature, str) or not _SIG_RE.fullmatch(signature):
        raise WireError(f"signature must be 32 lowercase hex digits, got {signature!r}")
    return signature


def encode_controllers(msg: ControllerMessage) -> bytes:
    """The binary form of ``msg`` (see the module docstring); raises WireError if ``msg``
    could not be decoded back (bad id, signature, indices, counts)."""
    sig = bytes.fromhex(check_signature(msg.signature))
    vid = check_vehicle_id(msg.vehicle_id).encode("ascii")
    if len(msg.entries) > MAX_ENTRIES:
        raise WireError(f"{len(msg.entries)} entries exceed the wire limit {MAX_ENTRIES}")
    flags = _FLAG_TRANSITIONS if msg.transitions else 0
    parts = [
        _HEADER.pack(MAGIC, SCHEMA_VERSION, int(msg.kind), flags, 0, sig, len(vid)),
        vid,
        _U16.pack(len(msg.entries)),
    ]
    for n, e in enumerate(msg.entries):
        _parse_entry(n, e.active_set, e.importance, e.uses, n_con=None, max_rows=None)
        parts.append(struct.pack(f"<H{len(e.active_set)}H", len(e.active_set), *e.active_set))
        parts.append(_ENTRY_TAIL.pack(float(e.importance), int(e.uses)))
    if msg.transitions:
        parts.append(_U32.pack(len(msg.transitions)))
        for a, b, count in msg.transitions:
            _check_transition(a, b, count, len(msg.entries))
            parts.append(_TRANSITION.pack(a, b, count))
    return b"".join(parts)


def decode_controllers(
    data: bytes,
    *,
    max_payload_bytes: int,
    max_entries: int = MAX_ENTRIES,
    n_con: int | None = None,
    max_active: int | None = None,
    expect_signature: str | None = None,
) -> ControllerMessage:
    """Parse and validate a controller message.

    ``n_con``: the receiving problem's constraint rows (indices must be < n_con);
    ``max_active``: the most active rows a set may have (the problem's N nu);
    ``expect_signature``: reject a payload for another problem.
    """
    if len(data) > max_payload_bytes:
        raise WireError(f"payload of {len(data)} bytes exceeds the limit {max_payload_bytes}")
    r = _Reader(data)
    magic, version, kind, flags, reserved, sig, id_len = r.unpack(_HEADER, "header")
    if magic != MAGIC:
        raise WireError(f"bad magic {magic!r} (expected {MAGIC!r})")
    if version != SCHEMA_VERSION:
        raise WireError(f"schema version {version} is not supported (this is {SCHEMA_VERSION})")
    if kind not in (MessageKind.BATCH, MessageKind.SNAPSHOT):
        raise WireError(f"unknown message kind {kind}")
    if flags & ~_FLAG_TRANSITIONS or reserved:
        raise WireError(f"unknown flags {flags:#x} / reserved byte {reserved:#x}")
    signature = sig.hex()
    if expect_signature is not None and signature != expect_signature:
        raise WireError(f"signature {signature} does not match the problem {expect_signature}")
    if not 1 <= id_len <= MAX_VEHICLE_ID_LEN:
        raise WireError(f"vehicle id length {id_len} outside 1..{MAX_VEHICLE_ID_LEN}")
    try:
        vehicle_id = r.take(id_len, "vehicle id").decode("ascii")
    except UnicodeDecodeError as exc:
        raise WireError("vehicle id is not ASCII") from exc
    check_vehicle_id(vehicle_id)
    (count,) = r.unpack(_U16, "entry count")
    if count > max_entries:
        raise WireError(f"{count} entries exceed the limit {max_entries}")
    entries = []
    for n in range(count):
        (n_active,) = r.unpack(_U16, f"entry {n} length")
        raw = r.take(2 * n_active, f"entry {n} indices")
        active = struct.unpack(f"<{n_active}H", raw)
        importance, uses = r.unpack(_ENTRY_TAIL, f"entry {n} importance/uses")
        entries.append(_parse_entry(n, active, importance, uses, n_con=n_con, max_rows=max_active))
    transitions: list[tuple[int, int, int]] = []
    if flags & _FLAG_TRANSITIONS:
        (n_trans,) = r.unpack(_U32, "transition count")
        if n_trans * _TRANSITION.size > r.remaining:
            raise WireError(f"{n_trans} transitions declared, {r.remaining} bytes left")
        for _ in range(n_trans):
            a, b, c = r.unpack(_TRANSITION, "transition")
            _check_transition(a, b, c, count)
            transitions.append((a, b, c))
    if r.remaining:
        raise WireError(f"{r.remaining} bytes after the declared content")
    return ControllerMessage(
        MessageKind(kind), signature, vehicle_id, tuple(entries), tuple(transitions)
    )


def _parse_entry(
    n: int, active: object, importance: object, uses: object, *, n_con: int | None,
    max_rows: int | None,
) -> LibraryEntry:
    """Entry ``n`` as the library's one parser takes it (indices below ``n_con``, or the
    u16 limit when None), with a use count that fits a u32; WireError names entry and field."""
    try:
        entry = parse_entry(
            active, importance, uses, n_con=_INDEX_LIMIT if n_con is None else n_con,
            max_rows=max_rows,
        )
    except EntryError as exc:
        raise WireError(f"entry {n}: {exc}") from exc
    if entry.uses > _U32_MAX:
        raise WireError(f"entry {n}: uses must be an integer in 0..2^32-1, got {uses!r}")
    return entry


def _check_transition(a: int, b: int, count: int, n_entries: int) -> None:
    if not (0 <= a < n_entries and 0 <= b < n_entries):
        raise WireError(f"transition ({a}, {b}) indexes outside the {n_entries} entries")
    if not 1 <= count <= 0xFFFFFFFF:
        raise WireError(f"transition ({a}, {b}) count must be in 1..2^32-1, got {count}")


class _Reader:
    def __init__(self, data: bytes) -> None:
        self._data = memoryview(data)
        self._pos = 0

    @property
    def remaining(self) -> int:
        return len(self._data) - self._pos

    def take(self, n: int, what: str) -> bytes:
        if n > self.remaining:
            raise WireError(f"truncated payload: {what} needs {n} bytes, {self.remaining} left")
        out = bytes(self._data[self._pos : self._pos + n])
        self._pos += n
        return out

    def unpack(self, fmt: struct.Struct, what: str) -> tuple[Any, ...]:
        return fmt.unpack(self.take(fmt.size, what))


# -- live references ----------------------------------------------------------------------

Vec3 = tuple[float, float, float]


@dataclass(frozen=True)
class ReferenceMessage:
    """A live reference from a planner: where to be (NED, m) now and, optionally, next.

    ``vel_ned_m_s``: the target moves at this velocity (extrapolated while fresh);
    ``horizon_pos_ned_m``: positions ``horizon_dt_s``, ``2 horizon_dt_s``, ... after ``pos``.
    """

    pos_ned_m: Vec3
    vel_ned_m_s: Vec3 | None = None
    yaw_rad: float | None = None
    horizon_dt_s: float | None = None
    horizon_pos_ned_m: tuple[Vec3, ...] = ()


def encode_reference(msg: ReferenceMessage) -> bytes:
    body: dict[str, object] = {"v": 1, "pos_ned_m": list(msg.pos_ned_m)}
    if msg.vel_ned_m_s is not None:
        body["vel_ned_m_s"] = list(msg.vel_ned_m_s)
    if msg.yaw_rad is not None:
        body["yaw_rad"] = msg.yaw_rad
    if msg.horizon_pos_ned_m:
        body["horizon_dt_s"] = msg.horizon_dt_s
        body["horizon_pos_ned_m"] = [list(p) for p in msg.horizon_pos_ned_m]
    data = json.dumps(body, allow_nan=False, separators=(",", ":")).encode()
    decode_reference(data)  # what we send must be what we accept
    return data


_REFERENCE_KEYS = {"v", "pos_ned_m", "vel_ned_m_s", "yaw_rad", "horizon_dt_s",
                   "horizon_pos_ned_m"}  # fmt: skip


def decode_reference(
    data: bytes, *, max_payload_bytes: int = MAX_REFERENCE_BYTES
) -> ReferenceMessage:
    """Parse and validate a live reference (JSON); WireError names the bad field."""
    if len(data) > max_payload_bytes:
        raise WireError(f"reference of {len(data)} bytes exceeds the limit {max_payload_bytes}")
    try:
        body = json.loads(data.decode("utf-8"), parse_constant=_reject_constant)
    except WireError:
        raise
    except (ValueError, RecursionError) as exc:  # bad UTF-8 or JSON, absurd ints, deep nesting
        raise WireError(f"reference is not valid UTF-8 JSON: {exc}") from exc
    if not isinstance(body, dict):
        raise WireError("reference must be a JSON object")
    unknown = sorted(set(body) - _REFERENCE_KEYS)
    if unknown:
        raise WireError(f"reference has unknown keys {unknown}")
    if body.get("v") != 1:
        raise WireError(f"reference version must be 1, got {body.get('v')!r}")
    if "pos_ned_m" not in body:
        raise WireError("reference needs pos_ned_m")
    pos = _vec3(body["pos_ned_m"], "pos_ned_m")
    vel = _vec3(body["vel_ned_m_s"], "vel_ned_m_s") if "vel_ned_m_s" in body else None
    yaw = _number(body["yaw_rad"], "yaw_rad") if "yaw_rad" in body else None
    horizon: tuple[Vec3, ...] = ()
    dt: float | None = None
    if "horizon_pos_ned_m" in body or "horizon_dt_s" in body:
        points = body.get("horizon_pos_ned_m")
        if not isinstance(points, list) or not 1 <= len(points) <= MAX_HORIZON_POINTS:
            raise WireError(f"horizon_pos_ned_m must be a list of 1..{MAX_HORIZON_POINTS} points")
        horizon = tuple(_vec3(p, f"horizon_pos_ned_m[{i}]") for i, p in enumerate(points))
        dt = _number(body.get("horizon_dt_s"), "horizon_dt_s")
        if not 0.0 < dt <= 10.0:
            raise WireError(f"horizon_dt_s must be in (0, 10] s, got {dt}")
    return ReferenceMessage(pos, vel, yaw, dt, horizon)


def _reject_constant(name: str) -> float:
    raise WireError(f"reference holds {name}: numbers must be finite")


def _number(value: object, what: str) -> float:
    if isinstance(value, bool) or not isinstance(value, int | float):
        raise WireError(f"{what} must be a number, got {value!r}")
    if not math.isfinite(value) or abs(value) > 1e6:
        raise WireError(f"{what} must be finite and within 1e6, got {value!r}")
    return float(value)


def _vec3(value: object, what: str) -> Vec3:
    if not isinstance(value, list) or len(value) != 3:
        raise WireError(f"{what} must be a list of 3 numbers, got {value!r}")
    x, y, z = (_number(v, what) for v in value)
    return (x, y, z)
