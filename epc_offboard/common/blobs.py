"""What the loops' thread hands the library store raw, and the store process formats.

A save's npz files (zip) and texts (JSON) took the loops' thread 5-14 ms a piece (issue 21:
an LWPR model's npz up to 13.6 ms, the fleet's received controllers as text 8-10 ms). The
loops' thread now only copies: arrays into an :class:`Npz` (a memcpy each), each received
controller once into a packed byte record (:func:`received_record`, kept while the
controller is known) joined into a :class:`ReceivedText`. Both cross the store's pipe as
they are (numpy arrays and bytes pickle as their buffers) and are built there, by
:meth:`~epc_offboard.store.database.LibraryStore.save_snapshot`, into the very bytes and
texts the loops' thread used to make.

A leaf module (numpy and the standard library): the store process unpickles these types
without importing the controller.
"""

from __future__ import annotations

import io
import json
import math
import struct
from collections.abc import Iterable, Iterator, Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np

# a received controller's record: importance, uses, then the byte lengths of its origin
# and the int32 counts of its active set and successors, then those (see received_record)
_HEAD = struct.Struct("<dqHHH")
_INT64_MAX = (1 << 63) - 1
_FIELD, _RECORD = "\x1f", "\x1e"  # Npz.layout's separators (ASCII unit and record)


@dataclass(frozen=True)
class Npz:
    """An npz file's arrays, copied on the loops' thread into one buffer (``data``), zipped
    by :meth:`build` (in the store process). One buffer, so that the hand-over pickles a
    few objects, not sixty arrays (each array pickled costs ~10 us of the loops' thread).
    ``layout``: one text, a record an array (name, dtype, shape, offset; a nested file's
    offset -1, its :class:`Npz` in ``nested``), not a tuple an array: a save's models then
    leave no object per array for the collector (issue 21: the save's objects made a young
    collection on the loops' thread every save). A nested file is stored as its built
    bytes (uint8), as the estimators keep one model's file in another's."""

    layout: str
    data: bytes
    nested: Mapping[str, Npz]

    @classmethod
    def of(cls, arrays: Mapping[str, Any]) -> Npz:
        """``arrays`` (name -> array, or a nested :class:`Npz`) copied, in this order."""
        layout: list[str] = []
        parts: list[bytes] = []
        nested: dict[str, Npz] = {}
        at = 0
        for name, a in arrays.items():
            if _FIELD in name or _RECORD in name:
                raise ValueError(f"an npz array's name may not hold \\x1e or \\x1f: {name!r}")
            if isinstance(a, Npz):
                nested[name] = a
                layout.append(f"{name}{_FIELD}{_FIELD}{_FIELD}-1")
                continue
            arr = np.asarray(a)
            raw = arr.tobytes()  # the copy (C order)
            shape = ",".join(map(str, arr.shape))
            layout.append(f"{name}{_FIELD}{arr.dtype.str}{_FIELD}{shape}{_FIELD}{at}")
            parts.append(raw)
            at += len(raw)
        return cls(_RECORD.join(layout), b"".join(parts), nested)

    def _records(self) -> Iterator[tuple[str, str, tuple[int, ...], int]]:
        for record in self.layout.split(_RECORD) if self.layout else ():
            name, dtype, shape, at = record.split(_FIELD)
            yield name, dtype, tuple(int(n) for n in shape.split(",") if n), int(at)

    def arrays(self) -> dict[str, Any]:
        """The arrays by name, in order (a nested file as its npz bytes, uint8)."""
        out: dict[str, Any] = {}
        for name, dtype, shape, at in self._records():
            if at < 0:
                out[name] = np.frombuffer(self.nested[name].build(), dtype=np.uint8)
                continue
            dt, count = np.dtype(dtype), math.prod(shape)
            out[name] = (np.frombuffer(self.data, dtype=dt, count=count, offset=at).reshape(shape)
                         if count else np.empty(shape, dtype=dt))  # fmt: skip
        return out

    def build(self) -> bytes:
        buf = io.BytesIO()
        np.savez(buf, **self.arrays())
        return buf.getvalue()


def received_record(
    active_set: tuple[int, ...], origin: str, importance: float, uses: int,
    successors: Iterable[tuple[int, ...]],
) -> bytes:
    """One received controller (a library entry and its likeliest successors) as packed
    bytes: a few microseconds of the loops' thread, once per controller."""
    succ = list(successors)
    ints = [*active_set]
    for s in succ:
        ints.append(len(s))
        ints.extend(s)
    name = origin.encode()
    head = _HEAD.pack(importance, min(int(uses), _INT64_MAX), len(name), len(active_set),
                      len(succ))  # fmt: skip
    return head + name + np.array(ints, dtype=np.int32).tobytes()


def _received_json(records: bytes) -> Iterable[str]:
    """Each record of ``records`` as the JSON text ``FleetSharing.restore`` reads."""
    view, at = memoryview(records), 0
    while at < len(records):
        importance, uses, n_name, n_active, n_succ = _HEAD.unpack_from(view, at)
        at += _HEAD.size
        origin = bytes(view[at : at + n_name]).decode()
        at += n_name
        # the successors' lengths are among the ints: read the active set, then each one
        ints = np.frombuffer(records, dtype=np.int32, count=n_active, offset=at).tolist()
        at += 4 * n_active
        succ = []
        for _ in range(n_succ):
            (n,) = struct.unpack_from("<i", view, at)
            succ.append(np.frombuffer(records, dtype=np.int32, count=n, offset=at + 4).tolist())
            at += 4 * (n + 1)
        yield json.dumps([ints, origin, importance, uses, succ], separators=(",", ":"))


@dataclass(frozen=True)
class ReceivedText:
    """A problem's received controllers (``FleetSharing.fleet_state``'s candidates), as the
    loops' thread joined their records; :meth:`build` is the JSON list of them."""

    records: bytes

    def build(self) -> str:
        return "[" + ",".join(_received_json(self.records)) + "]"
