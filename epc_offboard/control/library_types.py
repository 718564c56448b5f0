"""The controller library as plain values: one entry type, the snapshot types, one parser.

A leaf module (the standard library and :mod:`epc_offboard.common.errors` only: no numpy, no
SQLite) because four places hold library entries and none of them should pull in the others'
dependencies: the EPC numerics (:mod:`epc_offboard.control.epc`), the SQLite store
(:mod:`epc_offboard.store.database`), the fleet's codec (:mod:`epc_offboard.fleet.wire`, which
a planner or a test may import without numba, OSQP or scipy) and the offline transfer's JSON
(:mod:`epc_offboard.tools.db`). They all build entries through :func:`parse_entry`, so an
active set is judged by one set of rules wherever it comes from.

An active set is the sorted, unique row indices (ints) of the problem's constraint layout
(:class:`~epc_offboard.control.qp.ConstraintRow` order) that hold with equality; a problem
with ``n_con`` rows and ``n_u = N nu`` inputs admits indices ``0 .. n_con - 1`` and at most
``n_u`` rows (more cannot be linearly independent). Only active sets travel and are stored,
never gains: each receiver rebuilds the controller from its own problem.
"""

from __future__ import annotations

import math
from array import array
from collections.abc import Iterator, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Protocol, TypeVar, overload

from epc_offboard.common.errors import EpcError

ActiveSet = tuple[int, ...]
_T = TypeVar("_T")

# how much of a rejected value an error message shows (the value may come from the network)
_SHOWN_CHARS = 60


class EntryError(EpcError, ValueError):
    """A library entry's field (active set, importance, uses) that is not valid; the message
    starts with the field's name. Callers add where the entry came from (their own error)."""


@dataclass(frozen=True)
class LibraryEntry:
    """One stored controller, as EPC, the store, the fleet and the export file hold it.

    ``active_set``: sorted, unique row indices into the problem's constraint layout;
    ``importance``: local last-use tick (0 for imported entries never used here);
    ``uses``: how many ticks it was applied; ``origin``: ``solved`` (this vehicle's own solve),
    ``shared:<vehicle>`` (a fleet candidate that passed the KKT check here), ``prior`` or an
    offline import's tag (the store's column); empty where not known (the wire carries none).
    """

    active_set: ActiveSet
    importance: float = 0.0
    uses: int = 0
    origin: str = ""


@dataclass(frozen=True)
class Transition:
    """How often the controller ``to_set`` followed ``from_set`` (count >= 1)."""

    from_set: ActiveSet
    to_set: ActiveSet
    count: int


class DeferredBlob(Protocol):
    """A model's bytes, built where they are saved (the store process), from copies the
    loops' thread took (``epc_offboard.common.blobs.Npz``)."""

    def build(self) -> bytes: ...


class DeferredText(Protocol):
    """A text of the fleet's state, built where it is saved (``blobs.ReceivedText``)."""

    def build(self) -> str: ...


def blob_bytes(blob: bytes | DeferredBlob) -> bytes:
    """A model's bytes: ``blob``, or built from the copies a saver took (in the store
    process, :meth:`LibraryStore.save_snapshot`: not on the loops' thread)."""
    return blob if isinstance(blob, bytes) else blob.build()


def text_of(text: str | DeferredText) -> str:
    """A fleet state's text: ``text``, or built from the records a saver took (where it is
    saved or exported, as :func:`blob_bytes` a model's bytes)."""
    return text if isinstance(text, str) else text.build()


class _Packed(Sequence[_T]):
    """A sequence of values made when read (:meth:`_at`), equal to any sequence of the same
    values (a tuple the store read back, say)."""

    def _at(self, i: int) -> _T:
        raise NotImplementedError

    @overload
    def __getitem__(self, i: int) -> _T: ...
    @overload
    def __getitem__(self, i: slice) -> tuple[_T, ...]: ...
    def __getitem__(self, i: int | slice) -> _T | tuple[_T, ...]:
        n = len(self)
        if isinstance(i, slice):
            return tuple(self._at(k) for k in range(*i.indices(n)))
        if not -n <= i < n:
            raise IndexError(i)
        return self._at(i % n)

    def __iter__(self) -> Iterator[_T]:
        return (self._at(i) for i in range(len(self)))

    def __eq__(self, other: object) -> bool:
        if not isinstance(other, Sequence) or isinstance(other, str | bytes):
            return False
        return len(self) == len(other) and all(a == b for a, b in zip(self, other, strict=True))

    __hash__ = None  # type: ignore[assignment]


@dataclass(frozen=True, eq=False)
class PackedEntries(_Packed[LibraryEntry]):
    """A library's entries as the loops' thread copies them for the store: flat arrays, no
    Python object per entry (a library of 400 made one young collection a save on the
    loops' thread, issue 21); a :class:`LibraryEntry` is made when one is read (in the
    store process). ``rows``: every entry's active set, one after another, entry ``i``
    ending at ``ends[i]``; ``origins``: the entries' origin strings (shared, not copied)."""

    rows: array[int]  # 'q'
    ends: array[int]  # 'q'
    importance: array[float]  # 'd'
    uses: array[int]  # 'q'
    origins: tuple[str, ...]

    def __len__(self) -> int:
        return len(self.ends)

    def active_set(self, i: int) -> ActiveSet:
        return tuple(self.rows[self.ends[i - 1] if i else 0 : self.ends[i]])

    def _at(self, i: int) -> LibraryEntry:
        return LibraryEntry(self.active_set(i), self.importance[i], self.uses[i],
                            self.origins[i])  # fmt: skip


@dataclass(frozen=True, eq=False)
class PackedTransitions(_Packed[Transition]):
    """A library's transition counts, packed as :class:`PackedEntries`: transition ``i`` is
    ``counts[i]`` from entry ``froms[i]`` to entry ``tos[i]`` (indices into ``entries``)."""

    entries: PackedEntries
    froms: array[int]  # 'q'
    tos: array[int]  # 'q'
    counts: array[int]  # 'q'

    def __len__(self) -> int:
        return len(self.counts)

    def _at(self, i: int) -> Transition:
        return Transition(self.entries.active_set(self.froms[i]),
                          self.entries.active_set(self.tos[i]), self.counts[i])  # fmt: skip


@dataclass(frozen=True)
class SignatureSnapshot:
    """Everything stored under one problem signature (the entries and transitions as tuples,
    or packed as the loops' thread hands them over: :class:`PackedEntries`)."""

    controllers: Sequence[LibraryEntry] = ()
    transitions: Sequence[Transition] = ()
    # name -> opaque blob (or what builds it: a snapshot the loops' thread took)
    models: Mapping[str, bytes | DeferredBlob] = field(default_factory=dict)


@dataclass(frozen=True)
class LibrarySnapshot:
    """A whole library file (or the part of it under some signatures), as plain values."""

    signatures: Mapping[str, SignatureSnapshot]
    # the fleet's state beside the library (``FleetSharing.fleet_state``: received
    # controllers not proven yet, high-water marks), opaque texts by name; empty: not
    # shared, and a save leaves what the file holds (a text may be what builds it)
    fleet: Mapping[str, str | DeferredText] = field(default_factory=dict)

    def counts(self) -> dict[str, int]:
        return {
            "signatures": len(self.signatures),
            "controllers": sum(len(s.controllers) for s in self.signatures.values()),
            "transitions": sum(len(s.transitions) for s in self.signatures.values()),
            "models": sum(len(s.models) for s in self.signatures.values()),
        }


def parse_active_set(
    rows: object, *, n_con: int | None = None, max_rows: int | None = None
) -> ActiveSet:
    """``rows`` (a list or tuple) as an active set, or :class:`EntryError` saying why not.

    Rules: ints (not bools), each in ``0 .. n_con - 1`` (``>= 0`` when ``n_con`` is None),
    strictly increasing (sorted and unique), at most ``max_rows`` of them (checked before
    the elements, so an absurd length costs nothing).
    """
    if not isinstance(rows, list | tuple):
        raise EntryError(f"active_set must be a list or tuple of ints, got {_shown(rows)}")
    if max_rows is not None and len(rows) > max_rows:
        raise EntryError(f"active_set too long: {len(rows)} active rows exceed {max_rows}")
    last = -1
    for i in rows:
        if not isinstance(i, int) or isinstance(i, bool):
            raise EntryError(f"active_set must be a list or tuple of ints, got {_shown(rows)}")
        if i < 0 or (n_con is not None and i >= n_con):
            bound = "0.." if n_con is None else f"0..{n_con - 1}"
            raise EntryError(f"active_set index {i} out of range {bound}")
        if i <= last:
            raise EntryError(f"active_set must be sorted and unique, got {_shown(rows)}")
        last = i
    return tuple(rows)


def parse_entry(
    active_set: object,
    importance: object = 0.0,
    uses: object = 0,
    origin: str = "",
    *,
    n_con: int | None = None,
    max_rows: int | None = None,
) -> LibraryEntry:
    """A validated :class:`LibraryEntry`, or :class:`EntryError` naming the bad field.

    ``active_set`` as :func:`parse_active_set`; ``importance`` a finite number (not a bool);
    ``uses`` an int >= 0 (not a bool).
    """
    rows = parse_active_set(active_set, n_con=n_con, max_rows=max_rows)
    if (
        isinstance(importance, bool)
        or not isinstance(importance, int | float)
        or not _finite(importance)
    ):
        raise EntryError(f"importance must be finite (a number), got {_shown(importance)}")
    if not isinstance(uses, int) or isinstance(uses, bool) or uses < 0:
        raise EntryError(f"uses must be an integer >= 0, got {_shown(uses)}")
    return LibraryEntry(rows, float(importance), uses, origin)


def _finite(value: float) -> bool:
    try:
        return math.isfinite(value)
    except OverflowError:  # an int beyond any float (from JSON, say)
        return False


def _shown(value: object) -> str:
    return repr(value)[:_SHOWN_CHARS]
