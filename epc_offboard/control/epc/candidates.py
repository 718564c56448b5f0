"""Controllers received from the fleet, waiting to be proven here (thesis 3.1.3 extended to
a fleet: a stored controller is applied only where the KKT check proves it optimal).

Fleet controllers are candidates, not library entries (:class:`CandidatePool`): a bounded
pool, at most a quota per sending vehicle, whose maps are built in slices bounded by time.
A candidate enters the library only when it passes this controller's KKT check for a real
tick's parameters (a miss that it covers): one that is never optimal here never takes a
library slot.
"""

from __future__ import annotations

import time
from collections import Counter, OrderedDict, deque
from collections.abc import Callable, Container, Iterable, Iterator, Mapping
from dataclasses import dataclass
from typing import Literal

from epc_offboard.common.frames import FloatArray
from epc_offboard.control.epc.maps import ActiveSetMap, DependentActiveSetError
from epc_offboard.control.library_types import LibraryEntry


@dataclass
class _Candidate:
    origin: str
    map: ActiveSetMap | None = None  # None until built


@dataclass
class _Known:
    """What an origin told about one controller, kept as a cheap tuple (no map) so a whole
    snapshot can wait in the backlog: the sender's importance (its last-use tick) and use
    count, its likeliest successors in the sender's transition counts, and where it is."""

    origin: str
    importance: float
    uses: int
    successors: tuple[tuple[int, ...], ...]
    state: Literal["backlog", "pool", "promoted"]
    # what :meth:`CandidatePool.known` hands out, built once: the fleet's state for a
    # restart lists every known controller each save, and building ~2,000 frozen entries
    # there took the loops' thread 20-30 ms every 5 s (position gaps of 20-30 ms)
    as_received: tuple[LibraryEntry, tuple[tuple[int, ...], ...]] | None = None

    def received(self, active: tuple[int, ...]) -> tuple[
            LibraryEntry, tuple[tuple[int, ...], ...]]:  # fmt: skip
        if self.as_received is None:
            entry = LibraryEntry(active, self.importance, self.uses, self.origin)
            self.as_received = (entry, self.successors)
        return self.as_received


# successors kept per received controller (the sender's most frequent transitions first)
MAX_SUCCESSORS = 8


class CandidatePool:
    """Received controllers not proven here yet: bounded in number, per origin, and in work.

    Two tiers. The pool proper holds at most ``max_size`` candidates, at most a quota per
    origin; only these get maps (one factorisation and ~N nu x n_theta floats each: memory is
    bounded by ``max_size`` maps). Every received controller is also *known* as a cheap
    tuple (active set, the sender's importance, uses and likeliest successors): at most
    ``max_backlog`` in total and ``max_backlog_per_origin`` from one origin, so a late
    joiner's whole snapshot waits here instead of being cut to the newest quota.

    Offers: a vehicle past its quota pushes its own oldest pool candidate back to the backlog
    (replaced); a full pool pushes back the oldest of the origin holding the most, unproven
    origins first. An origin earns a larger quota (``max_per_origin`` more per promotion,
    at most ``max_size - max_per_origin``, so a newcomer always finds room) once its
    candidates are promoted here (:meth:`promoted`): a flood of useless controllers never is,
    so it never earns anything. :meth:`refocus` fills a proven origin's quota with the
    candidates most likely next: its successors of the controller in use (breadth first over
    the sender's transitions), then the sender's use order after it. :meth:`wanted` names
    the proven candidates whose maps should be built (off the loop) and :meth:`attach` takes
    them. Maps are built by :meth:`build` in slices bounded by time; :meth:`find`
    KKT-checks the built ones. Active sets offered since the last :meth:`pop_fresh` are
    kept for a worker that holds its own copy of the pool (:mod:`epc_offboard.service.miss_solver`).
    """

    def __init__(self, max_size: int, max_per_origin: int, max_backlog: int = 2048,
                 max_backlog_per_origin: int = 512) -> None:
        if max_size < 1 or max_per_origin < 1:
            raise ValueError(
                f"candidate pool sizes must be >= 1, got {max_size} and {max_per_origin}"
            )
        if max_backlog < max_size or max_backlog_per_origin < max_per_origin:
            raise ValueError(
                f"candidate backlog ({max_backlog}, {max_backlog_per_origin} per origin) must "
                f"hold at least the pool ({max_size}, {max_per_origin} per origin)"
            )
        self.max_size = max_size
        self.max_per_origin = max_per_origin
        self.max_backlog = max_backlog
        self.max_backlog_per_origin = max_backlog_per_origin
        self._items: OrderedDict[tuple[int, ...], _Candidate] = OrderedDict()  # oldest first
        self._per_origin: Counter[str] = Counter()
        self._known: dict[str, dict[tuple[int, ...], _Known]] = {}  # by origin
        self._known_total = 0
        self._origin_of: dict[tuple[int, ...], str] = {}  # every known set's origin
        self.promotions: Counter[str] = Counter()  # origins whose candidates proved useful
        self._rank: dict[tuple[int, ...], int] = {}  # the last refocus's order (build order)
        self._anchor: dict[str, tuple[int, ...]] = {}  # per origin: its last controller in use
        self._fresh: deque[tuple[tuple[int, ...], str]] = deque(maxlen=max_size)
        self.counters: Counter[str] = Counter()

    def __len__(self) -> int:
        return len(self._items)

    def __contains__(self, active: object) -> bool:
        return active in self._items

    @property
    def unbuilt(self) -> int:
        return sum(c.map is None for c in self._items.values())

    @property
    def backlog(self) -> int:
        """Known controllers waiting outside the pool (tuples only, no map)."""
        return sum(
            k.state == "backlog" for known in self._known.values() for k in known.values()
        )

    def items(self) -> list[tuple[tuple[int, ...], str]]:
        """(active set, origin) of every candidate, oldest first."""
        return [(a, c.origin) for a, c in self._items.items()]

    def known(self) -> list[tuple[LibraryEntry, tuple[tuple[int, ...], ...]]]:
        """Every received controller not promoted (the pool's and the backlog's), as its
        origin sent it, with its successors: what a vehicle that restarts offers itself
        again (:meth:`epc_offboard.fleet.sharing.FleetSharing.fleet_state`)."""
        return [k.as_received or k.received(a) for by_origin in self._known.values()
                for a, k in by_origin.items() if k.state != "promoted"]  # fmt: skip

    def known_parts(self, per_part: int) -> Iterator[
            list[tuple[LibraryEntry, tuple[tuple[int, ...], ...]]]]:  # fmt: skip
        """:meth:`known` in parts of at most ``per_part``, for a caller on the loops' thread
        that lets them tick between parts (listing 2,048 at once took 2-3 ms there, cold,
        under bench --attack). Each origin's controllers are taken when its first part is
        (a C-level copy of its dict); one promoted meanwhile is left out, as it is then in
        the library."""
        for by_origin in list(self._known.values()):
            items = list(by_origin.items())
            for at in range(0, len(items), per_part):
                yield [k.as_received or k.received(a) for a, k in items[at : at + per_part]
                       if k.state != "promoted"]  # fmt: skip

    def proven(self, origin: str) -> bool:
        return self.promotions[origin] > 0

    def quota(self, origin: str) -> int:
        """The pool slots ``origin`` may hold: earned by promotions, never all of them."""
        earned = self.max_per_origin * (1 + self.promotions[origin])
        return max(self.max_per_origin, min(earned, self.max_size - self.max_per_origin))

    def offer(self, active: tuple[int, ...], origin: str, importance: float = 0.0,
              uses: int = 0, successors: tuple[tuple[int, ...], ...] = ()) -> bool:
        """Add a candidate (its shape already validated); False if it is known already."""
        if active in self._items or active in self._origin_of:
            self.counters["known"] += 1
            return False
        if self._per_origin[origin] >= self.quota(origin):
            self._drop_oldest_of(origin)
            self.counters["replaced_over_quota"] += 1
        elif len(self._items) >= self.max_size:
            self._drop_oldest_of(self._fullest_origin())
            self.counters["evicted_pool_full"] += 1
        self._remember(active, _Known(origin, importance, uses, successors[:MAX_SUCCESSORS],
                                      "pool"))
        self._items[active] = _Candidate(origin)
        self._per_origin[origin] += 1
        self._fresh.append((active, origin))
        self.counters["offered"] += 1
        self._trim_known(origin)
        return True

    def offer_checked(
        self, check: Callable[[int, LibraryEntry], LibraryEntry],
        held: Container[tuple[int, ...]], entries: Iterable[LibraryEntry], origin: str,
        successors: Mapping[tuple[int, ...], tuple[tuple[int, ...], ...]] | None = None,
    ) -> int:
        """:meth:`offer` received ``entries``: ones ``check`` refuses (malformed for the
        problem: :meth:`MapBuilder.check_entry <epc_offboard.control.epc.maps.MapBuilder.
        check_entry>`) and ones ``held`` already (in the library) are counted and skipped;
        returns how many were new."""
        added = 0
        for n, received in enumerate(entries):
            try:
                e = check(n, received)
            except ValueError:
                self.counters["rejected_malformed"] += 1
                continue
            if e.active_set in held:
                self.counters["in_library"] += 1
                continue
            succ = successors.get(e.active_set, ()) if successors is not None else ()
            added += self.offer(e.active_set, origin, float(e.importance), int(e.uses), succ)
        return added

    def _fullest_origin(self) -> str:
        """Whose pool candidate gives way when the pool is full: unproven origins first."""
        return max(self._per_origin, key=lambda o: (not self.proven(o), self._per_origin[o]))

    def _drop_oldest_of(self, origin: str) -> None:
        victim = next(a for a, c in self._items.items() if c.origin == origin)
        self._to_backlog(victim)

    def _to_backlog(self, active: tuple[int, ...]) -> None:
        """Out of the pool, map dropped; still known as a tuple (refocus may bring it back)."""
        cand = self.take(active)
        if cand is not None:
            known = self._known.get(cand.origin, {}).get(active)
            if known is not None:
                known.state = "backlog"
                self._origin_of[active] = cand.origin

    def _remember(self, active: tuple[int, ...], known: _Known) -> None:
        by_origin = self._known.setdefault(known.origin, {})
        if active not in by_origin:
            self._known_total += 1
        by_origin[active] = known
        self._origin_of[active] = known.origin

    def _forget(self, origin: str, active: tuple[int, ...]) -> None:
        by_origin = self._known.get(origin)
        if by_origin is None or by_origin.pop(active, None) is None:
            return
        self._known_total -= 1
        if self._origin_of.get(active) == origin:
            del self._origin_of[active]
        if not by_origin:
            del self._known[origin]
            self._anchor.pop(origin, None)
        if self._items.get(active, _Candidate("")).origin == origin:
            self.take(active)

    def _trim_known(self, origin: str) -> None:
        """Keep the backlog bounded: per origin, then in total (unproven origins first, the
        one that sent the most); the least used (then least recently used) goes first."""
        while len(self._known.get(origin, ())) > self.max_backlog_per_origin:
            self._forget_worst(origin)
        while self._known_total > self.max_backlog:
            # the pool is bounded on its own (max_size <= max_backlog): trim outside it
            victim = max(
                self._known,
                key=lambda o: (len(self._known[o]) > self._per_origin[o], not self.proven(o),
                               len(self._known[o])),
            )
            self._forget_worst(victim)

    def _forget_worst(self, origin: str) -> None:
        by_origin = self._known[origin]
        outside = [a for a, k in by_origin.items() if k.state != "pool"]
        worst = min(outside or by_origin,
                    key=lambda a: (by_origin[a].uses, by_origin[a].importance))
        self._forget(origin, worst)
        self.counters["backlog_dropped"] += 1

    def take(self, active: tuple[int, ...]) -> _Candidate | None:
        """Remove and return a candidate (promoted, or dropped)."""
        cand = self._items.pop(active, None)
        if cand is not None:
            self._per_origin[cand.origin] -= 1
            if self._per_origin[cand.origin] <= 0:
                del self._per_origin[cand.origin]
            known = self._known.get(cand.origin, {}).get(active)
            if known is not None and known.state == "pool":
                known.state = "promoted"  # unless the caller says otherwise
                self._origin_of.pop(active, None)
        return cand

    def promoted(self, active: tuple[int, ...], origin: str) -> None:
        """A candidate of ``origin`` joined the library (optimal for a real tick here): the
        origin earns quota, and its successors lead the next :meth:`refocus`."""
        self.take(active)
        self.promotions[origin] += 1
        if len(self.promotions) > self.max_size:  # bounded: the least proven is forgotten
            del self.promotions[min(self.promotions, key=self.promotions.__getitem__)]
        known = self._known.get(origin, {}).get(active)
        if known is not None:
            known.state = "promoted"
            self._origin_of.pop(active, None)

    def refocus(self, root: tuple[int, ...] | None) -> int:
        """Fill each proven origin's quota with its candidates most likely needed next after
        ``root`` (the controller in use): breadth first over the sender's successors, then
        the sender's use order after ``root`` (wrapping), then the most used. Candidates
        that leave the pool keep their tuple in the backlog. Returns how many entered."""
        entered = 0
        for origin in [o for o in self._known if self.proven(o)]:
            by_origin = self._known[origin]
            window = self._window(origin, root, self.quota(origin))
            mine = [a for a, c in self._items.items() if c.origin == origin]
            self._rank.update((a, i) for i, a in enumerate(window))
            keep = set(window)
            for active in mine:
                if active not in keep:
                    self._to_backlog(active)
            for active in window:
                if active in self._items:
                    continue
                if len(self._items) >= self.max_size:
                    fullest = self._fullest_origin()
                    if self.proven(fullest):
                        break  # only proven origins left: no room taken from them
                    self._drop_oldest_of(fullest)
                    self.counters["evicted_pool_full"] += 1
                by_origin[active].state = "pool"
                self._items[active] = _Candidate(origin)
                self._per_origin[origin] += 1
                entered += 1
        self._rank = {a: r for a, r in self._rank.items() if a in self._items}
        self.counters["refocused"] += entered
        return entered

    def _window(self, origin: str, root: tuple[int, ...] | None, size: int
                ) -> list[tuple[int, ...]]:
        """``origin``'s candidates likeliest needed next after ``root`` (its last controller
        this origin sent when ``root`` is a local one): ``root``'s successors in the sender's
        transitions, then what the sender used after ``root`` (its importance order, wrapping)
        for three quarters of ``size``, then the sender's most used."""
        by_origin = self._known[origin]
        if root is not None and root in by_origin:
            self._anchor[origin] = root
        anchor = by_origin.get(self._anchor.get(origin, ()))
        waiting = [a for a, k in by_origin.items() if k.state != "promoted"]
        out: list[tuple[int, ...]] = []
        chosen: set[tuple[int, ...]] = set()

        def take(seq: Iterable[tuple[int, ...]], upto: int) -> None:
            for a in seq:
                if len(out) >= upto:
                    return
                if a not in chosen and a in by_origin and by_origin[a].state != "promoted":
                    chosen.add(a)
                    out.append(a)

        if anchor is not None:
            r = anchor.importance
            take(anchor.successors, size)
            after = sorted(waiting, key=lambda a: (by_origin[a].importance <= r,
                                                   by_origin[a].importance))
            take(after, max(len(out), (3 * size) // 4))
        take(sorted(waiting, key=lambda a: (-by_origin[a].uses, -by_origin[a].importance)), size)
        return out

    def wanted(self, limit: int) -> list[tuple[int, ...]]:
        """Proven origins' pool candidates without a map, most likely needed first."""
        if not self.promotions:
            # no origin proven (a flood's never is): none wanted. The miss worker's pump
            # asks every position tick: walking a full pool of 64 was 15 us warm, a few
            # times that in flight (cold caches, see service/realtime.py)
            return []
        far = len(self._rank)
        todo = [a for a, c in self._items.items() if c.map is None and self.proven(c.origin)]
        todo.sort(key=lambda a: self._rank.get(a, far))
        return todo[:limit]

    def attach(self, active: tuple[int, ...], amap: ActiveSetMap | None) -> bool:
        """Give a pool candidate the map built for it elsewhere (None: its rows were found
        dependent, it is dropped). False when it is no longer in the pool."""
        cand = self._items.get(active)
        if cand is None or cand.map is not None:
            return False
        if amap is None:
            self._forget(cand.origin, active)
            self.counters["rejected_dependent"] += 1
            return False
        cand.map = amap
        self.counters["attached"] += 1
        return True

    def pop_fresh(self) -> list[tuple[tuple[int, ...], str]]:
        """Candidates offered since the last call that are still in the pool."""
        out = [(a, o) for a, o in self._fresh if a in self._items]
        self._fresh.clear()
        return out

    def build(
        self, make_map: Callable[[tuple[int, ...]], ActiveSetMap], budget_s: float | None
    ) -> int:
        """Build unbuilt maps, oldest first, until ``budget_s`` (None: no limit) of the
        calling thread's CPU time is spent (at least one per call, so slices always
        progress); returns how many.

        Dependent sets are dropped. Time, not a count, bounds a slice: a map's cost grows
        with its active rows. CPU time, not the wall clock: a worker preempted (a CPU hog,
        SIGSTOP) in its slice still builds its share of maps, not only the one in hand."""
        t0 = time.thread_time()
        built = 0
        for active in [a for a, c in self._items.items() if c.map is None]:
            if budget_s is not None and built and time.thread_time() - t0 >= budget_s:
                break
            try:
                self._items[active].map = make_map(active)
            except DependentActiveSetError:
                self._forget(self._items[active].origin, active)
                self.counters["rejected_dependent"] += 1
                continue
            built += 1
        self.counters["built"] += built
        return built

    def find(
        self, theta_aug: FloatArray, u_out: FloatArray, u_min: FloatArray, u_max: FloatArray
    ) -> tuple[tuple[int, ...], _Candidate] | None:
        """The newest built candidate that passes the KKT check at ``theta_aug``, if any."""
        for active in reversed(self._items):
            cand = self._items[active]
            if cand.map is not None and cand.map.apply(theta_aug, u_out, u_min, u_max):
                return active, cand
        return None

    def map_of(self, active: tuple[int, ...]) -> ActiveSetMap | None:
        """The map built for a pool candidate (None: not in the pool, or not built yet)."""
        cand = self._items.get(active)
        return None if cand is None else cand.map

    def forget_maps(self) -> None:
        """The model's A or B changed: every map must be built again."""
        for cand in self._items.values():
            cand.map = None
