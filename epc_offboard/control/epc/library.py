"""The controller library (thesis 3.1.3, algorithm 1): entries, importance, eviction,
transitions, and the bounded query over them.

An entry is an active set's map (:class:`~epc_offboard.control.epc.maps.ActiveSetMap`) with
its importance (last-use tick), use count and origin. The least important entry is evicted
beyond ``max_size``; transition counts (which controller followed which) order the search.

Query order: the last used controller, then its successors in the transition counts (most
frequent first), then the rest by importance (last use, most recent first). The scan is one
compiled call over the maps in that order (:func:`epc_offboard.control.kernels.query_maps`),
bounded by ``max_checks`` candidates: a query never costs more than that many KKT checks,
whatever the library's size (a stored controller beyond the bound is a miss this tick).

Exchange: entries leave as :class:`~epc_offboard.control.library_types.LibraryEntry` values (the
active set as sorted row indices into the problem's layout, importance, uses, origin), most
important first; transition counts are exported separately, keyed by pairs of indices into
that list; the library saver takes both packed (:meth:`Library.export_packed`: flat arrays,
the same values, no object per entry on the loops' thread).
"""

from __future__ import annotations

import logging
from array import array
from collections import OrderedDict
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from itertools import accumulate, chain, repeat

import numpy as np
import numpy.typing as npt

from epc_offboard.common.frames import FloatArray
from epc_offboard.control import kernels
from epc_offboard.control.epc.maps import ActiveSetMap, DependentActiveSetError
from epc_offboard.control.kernels import new_map_lists, query_maps, store_map
from epc_offboard.control.library_types import LibraryEntry, PackedEntries, PackedTransitions

logger = logging.getLogger(__name__)


@dataclass
class Entry:
    key: int
    map: ActiveSetMap
    importance: float
    uses: int
    origin: str
    slot: int = -1  # its map's index in the compiled scan's arrays


class Library:
    """The stored controllers of one problem, least important first, with their transition
    counts and the compiled scan's arrays (one slot per entry's map).

    ``tick`` is the clock of importance: the controller advances it once per step.
    """

    def __init__(self, max_size: int, max_checks: int | None = None) -> None:
        if max_size < 1:
            raise ValueError(f"max_size must be >= 1, got {max_size}")
        if max_checks is not None and max_checks < 1:
            raise ValueError(f"max_checks must be >= 1 or None, got {max_checks}")
        self.max_size = max_size
        self.max_checks = max_checks
        self.tick = 0
        self._entries: OrderedDict[int, Entry] = OrderedDict()  # least important first
        self._by_set: dict[tuple[int, ...], int] = {}
        self._succ: dict[int, dict[int, int]] = {}
        self._next_key = 0
        self._last: int | None = None
        # the bounded scan: every entry's map arrays in slots, and the query order as slots
        # (its compiled code is made ready here, where a controller is built: at start-up, in
        # the service and in the miss worker alike, never at the first miss or solve)
        kernels.warm_up()
        self._slot_lists = new_map_lists()  # (maps' M, maps' width) by slot
        self._slot_n_check = np.zeros(0, dtype=np.int64)
        self._free_slots: list[int] = []
        self._order: npt.NDArray[np.int64] | None = None  # None: to rebuild
        self._slot_entry: list[Entry | None] = []  # whose map each slot holds
        self.last_query_checks = 0  # candidates the last query checked (diagnostics, tests)
        self.checks = 0  # candidates checked over all queries
        self.budget_exhausted = 0  # queries that ended at the budget with entries unchecked

    def __len__(self) -> int:
        return len(self._entries)

    def __contains__(self, active: object) -> bool:
        return active in self._by_set

    def get(self, active: tuple[int, ...]) -> Entry | None:
        """The entry of ``active``, if the library holds it."""
        key = self._by_set.get(active)
        return None if key is None else self._entries[key]

    @property
    def last(self) -> Entry | None:
        """The controller used last (the query's first try)."""
        return self._entries.get(self._last) if self._last is not None else None

    # -- adding, evicting -------------------------------------------------------------------

    def add(self, amap: ActiveSetMap, importance: float | None = None, uses: int = 0,
            *, least_important: bool = False, origin: str) -> Entry:
        """Store ``amap`` (importance: now, unless given), evicting the least important
        beyond ``max_size`` (never the entry just added)."""
        key = self._next_key
        self._next_key += 1
        entry = Entry(key, amap, float(self.tick) if importance is None else importance, uses,
                      origin)
        self._entries[key] = entry
        self._by_set[amap.active] = key
        self._store_slot(entry)
        if least_important:
            self._entries.move_to_end(key, last=False)
        while len(self._entries) > self.max_size:
            victim = next(iter(self._entries))
            if victim == key:  # never evict what was just added
                self._entries.move_to_end(victim)
                victim = next(iter(self._entries))
            self._remove(victim)
        return entry

    def _remove(self, key: int) -> None:
        entry = self._entries.pop(key)
        self._by_set.pop(entry.map.active, None)
        self._slot_entry[entry.slot] = None
        self._free_slots.append(entry.slot)  # its arrays stay until the slot is reused
        self._order = None
        self._succ.pop(key, None)
        for succ in self._succ.values():
            succ.pop(key, None)
        if self._last == key:
            self._last = None

    def rebuild(self, build: Callable[[tuple[int, ...]], ActiveSetMap]) -> None:
        """Every entry's map built again by ``build`` (the model's A or B changed); entries
        whose rows became dependent are dropped."""
        for key, e in list(self._entries.items()):
            try:
                e.map = build(e.map.active)
            except DependentActiveSetError:
                logger.debug("dropping %s: dependent under the new model", e.map.active)
                self._remove(key)
                continue
            self._store_slot(e)

    def _store_slot(self, entry: Entry) -> None:
        """Put the entry's map arrays in a slot of the compiled scan (its own, if it has
        one: the map was rebuilt)."""
        amap = entry.map
        if entry.slot < 0:
            if self._free_slots:
                entry.slot = self._free_slots.pop()
            else:
                entry.slot = len(self._slot_entry)
                store_map(self._slot_lists, entry.slot, amap.M, amap.width)
                self._slot_n_check = np.append(self._slot_n_check, amap.n_check)
                self._slot_entry.append(entry)
                self._order = None
                return
        store_map(self._slot_lists, entry.slot, amap.M, amap.width)
        self._slot_n_check[entry.slot] = amap.n_check
        self._slot_entry[entry.slot] = entry
        self._order = None

    # -- use and importance -----------------------------------------------------------------

    def use(self, entry: Entry) -> None:
        """``entry`` was applied this tick: its transition from the last one counted, its
        importance now, first in the next query."""
        key = entry.key
        last = self._last
        if last is not None and last in self._entries:
            succ = self._succ.setdefault(last, {})
            succ[key] = succ.get(key, 0) + 1
        entry.importance = float(self.tick)
        entry.uses += 1
        if last != key:
            self._entries.move_to_end(key)
            self._order = None
        self._last = key

    def refresh(self, entry: Entry) -> None:
        """Make ``entry`` the most important without using it (a query's budget did not
        reach it: the next query in its region checks it first instead of missing again)."""
        entry.importance = float(self.tick)
        self._entries.move_to_end(entry.key)
        self._order = None

    # -- the query --------------------------------------------------------------------------

    def _query_keys(self) -> list[int]:
        """The entries' keys in query order: the last controller, its successors by
        transition count (most frequent first; ties in the order they were first seen),
        then the rest, most important first. Lists, not a generator: the order is rebuilt
        whenever another controller is used (a third of a figure-8's ticks), and a
        generator's step per entry was two Python-level calls (~460 for a full library)."""
        entries = self._entries
        last = self._last
        if last is None or last not in entries:
            return list(reversed(entries))
        first = [last]
        succ = self._succ.get(last)
        if succ:
            first += [key for key in sorted(succ, key=succ.__getitem__, reverse=True)
                      if key != last and key in entries]  # fmt: skip
        if len(first) == 1:
            return first + [key for key in reversed(entries) if key != last]
        tried = set(first)
        return first + [key for key in reversed(entries) if key not in tried]

    def _in_query_order(self) -> list[Entry]:
        entries = self._entries
        return [entries[key] for key in self._query_keys()]

    def query_order(self) -> list[tuple[int, ...]]:
        """Active sets in the order the next query will try them, at most ``max_checks`` of
        them (diagnostics and tests)."""
        order = [e.map.active for e in self._in_query_order()]
        return order if self.max_checks is None else order[: self.max_checks]

    def _query_slots(self) -> npt.NDArray[np.int64]:
        """The slots of :meth:`_in_query_order`, cached until the order can have changed (an
        entry added or removed, another controller used, transitions imported)."""
        if self._order is None:
            entries = self._entries
            self._order = np.array([entries[key].slot for key in self._query_keys()],
                                   dtype=np.int64)  # fmt: skip
        return self._order

    def query(self, theta_cols: FloatArray, u_out: FloatArray, u_min: FloatArray,
              u_max: FloatArray, last_hit: bool | None = None) -> Entry | None:
        """The first entry in query order that passes the KKT check at ``theta_cols`` (the
        columns of ``[theta; 1]`` the maps read: ``MapBuilder.compact``; its first input
        written to ``u_out``), within ``max_checks`` checks; None: a miss. ``last_hit``:
        the answer of :attr:`last`'s check at ``theta_cols``, already made (its input
        written to ``u_out`` if it passed); None: this query makes it."""
        last = self._last
        budget = len(self._entries) if self.max_checks is None else self.max_checks
        checked = 0
        if last is not None:
            # the hot path: the last controller usually still applies
            e = self._entries.get(last)
            if e is not None:
                checked = 1
                if last_hit if last_hit is not None else e.map.check(theta_cols, u_out,
                                                                     u_min, u_max):
                    self.last_query_checks = 1
                    self.checks += 1
                    return e
        order = self._query_slots()
        start = checked  # the last controller, when there is one, is the order's first
        n = min(budget - checked, len(order) - start)
        k = query_maps(*self._slot_lists, self._slot_n_check, order[start:],
                       n, theta_cols, u_out, u_min, u_max) if n > 0 else -1
        checked += n if k < 0 else k + 1
        self.last_query_checks = checked
        self.checks += checked
        if k < 0:
            if len(self._entries) > budget:
                self.budget_exhausted += 1
            return None
        found = self._slot_entry[int(order[start + k])]
        assert found is not None  # the order holds live entries' slots only
        return found

    # -- exchange ---------------------------------------------------------------------------

    def _ordered(self) -> list[Entry]:
        """Entries most important first."""
        return list(reversed(self._entries.values()))

    def export(self) -> list[LibraryEntry]:
        """Entries, most important first; indices of this list key :meth:`export_transitions`."""
        return [
            LibraryEntry(e.map.active, e.importance, e.uses, e.origin) for e in self._ordered()
        ]

    def export_transitions(self) -> dict[tuple[int, int], int]:
        """Transition counts ``(from, to) -> count`` over indices into :meth:`export`."""
        index = {e.key: i for i, e in enumerate(self._ordered())}
        return {
            (index[a], index[b]): n
            for a, succ in self._succ.items()
            if a in index
            for b, n in succ.items()
            if b in index
        }

    def export_packed(self) -> tuple[PackedEntries, PackedTransitions]:
        """:meth:`export` and :meth:`export_transitions` as flat arrays (the same values, in
        the same order): what the library saver copies on the loops' thread, a few objects
        for the whole library where those make one (or two) per entry and transition, and
        a young collection a save."""
        ordered = self._ordered()
        entries = PackedEntries(
            array("q", chain.from_iterable(e.map.active for e in ordered)),
            array("q", accumulate(len(e.map.active) for e in ordered)),
            array("d", [e.importance for e in ordered]),
            array("q", [e.uses for e in ordered]),
            tuple([e.origin for e in ordered]),
        )
        # every key in the transition counts is a held entry's (``_remove`` drops the
        # others): the three columns in C loops, ~0.4 ms for 1,600 counts where a Python
        # loop took 0.6
        index = {e.key: i for i, e in enumerate(ordered)}
        at, succ = index.__getitem__, self._succ
        try:
            lengths = map(len, succ.values())
            triples = (
                array("q", chain.from_iterable(map(repeat, map(at, succ), lengths))),
                array("q", map(at, chain.from_iterable(succ.values()))),
                array("q", chain.from_iterable(map(dict.values, succ.values()))),
            )
        except KeyError:  # a count naming an entry no longer held (not expected): left out,
            kept = self.export_transitions()  # as there
            triples = (array("q", [a for a, _ in kept]), array("q", [b for _, b in kept]),
                       array("q", kept.values()))  # fmt: skip
        return entries, PackedTransitions(entries, *triples)

    def add_transitions(self, keys: Mapping[int, int],
                        transitions: Mapping[tuple[int, int], int]) -> None:
        """Add imported transition counts ``(a, b) -> count``, whose indices ``keys`` maps
        to entry keys (pairs naming an entry no longer held are ignored)."""
        for (a, b), count in transitions.items():
            ka, kb = keys.get(a), keys.get(b)
            if ka in self._entries and kb in self._entries and ka is not None and kb is not None:
                succ = self._succ.setdefault(ka, {})
                succ[kb] = succ.get(kb, 0) + count
                self._order = None
