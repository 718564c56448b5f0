"""What an :class:`~epc_offboard.control.epc.controller.ExperienceController` trades with the
world outside its tick: the store's prior and exports, the miss worker's results, and the
fleet's candidates. None of it runs on the hot path but the candidates' check at a miss.

* the store and the offline tools: :meth:`LibraryExchange.import_entries` (validated before
  the library changes), :meth:`~LibraryExchange.export_library`,
  :meth:`~LibraryExchange.export_transitions`, :meth:`~LibraryExchange.pop_new_entries`;
* the miss worker (:mod:`epc_offboard.service.miss_solver`): the loop queues θ in
  ``pending``; what the worker found comes back through :meth:`~LibraryExchange.add_built`
  (its map) or :meth:`~LibraryExchange.add_solved` (the active set), and joins the library
  only after this controller's own KKT check passes at that θ;
* the fleet: received controllers go into the candidate pool
  (:meth:`~LibraryExchange.offer_candidates`, which the fleet reaches only through
  :class:`FleetPort`'s four methods); the worker builds the maps the loop wants
  (:meth:`~LibraryExchange.wanted_maps`, :meth:`~LibraryExchange.attach_maps`), and a miss
  checks them before it counts (:meth:`~LibraryExchange._promote`).
"""

from __future__ import annotations

import logging
from collections.abc import Iterable, Iterator, Mapping
from typing import Literal

import numpy as np
import numpy.typing as npt

from epc_offboard.common.frames import FloatArray
from epc_offboard.control.candidate_pool import CandidatePoolConfig
from epc_offboard.control.epc.candidates import CandidatePool
from epc_offboard.control.epc.library import Entry, Library
from epc_offboard.control.epc.maps import ActiveSetMap, MapBuilder
from epc_offboard.control.library_types import LibraryEntry, PackedEntries, PackedTransitions
from epc_offboard.control.qp import MpcProblem

logger = logging.getLogger(__name__)

ActiveSet = tuple[int, ...]


class LibraryExchange:
    """The controller's side of the exchange (a mixin of ``ExperienceController``, whose
    state it names below)."""

    problem: MpcProblem
    library: Library
    candidates: CandidatePool
    builder: MapBuilder
    model_epoch: int
    _new: list[LibraryEntry]
    _solves: int
    _learn_failures: int
    _received_shared: int
    _focus_state: tuple[tuple[int, ...] | None, int] | None

    def _learn(self, theta_aug: FloatArray, u_out: FloatArray) -> Entry | None:
        raise NotImplementedError  # the controller's

    def _add(self, amap: ActiveSetMap, importance: float | None = None, uses: int = 0,
             *, least_important: bool = False, origin: str) -> Entry:
        """Into the library; a fleet candidate proven here earns its origin quota, any other
        set stops being a candidate."""
        if origin.startswith("shared:"):  # a candidate proven here: its origin earns quota
            self.candidates.promoted(amap.active, origin)
        else:
            self.candidates.take(amap.active)  # in the library now: no longer a candidate
        return self.library.add(amap, importance, uses, least_important=least_important,
                                origin=origin)

    # -- the query's budget -----------------------------------------------------------------

    def check_cost_us(self) -> float:
        """Worst-case cost of checking one candidate (:meth:`MapBuilder.check_cost_us`)."""
        return self.builder.check_cost_us()

    def checks_within(self, budget_us: float) -> int:
        """How many candidates a query may check to stay within ``budget_us`` (>= 1)."""
        return max(1, int(budget_us / self.check_cost_us()))

    @property
    def query_counters(self) -> dict[str, int]:
        """Candidates checked over all queries, and queries that ended at the budget with
        entries left unchecked."""
        return {"checks": self.library.checks, "budget_exhausted": self.library.budget_exhausted}

    def query_order(self) -> list[tuple[int, ...]]:
        """Active sets in the order the next query will try them (:meth:`Library.query_order`)."""
        return self.library.query_order()

    # -- the store --------------------------------------------------------------------------

    def export_library(self) -> list[LibraryEntry]:
        """Entries, most important first; indices of this list key :meth:`export_transitions`."""
        return self.library.export()

    def export_transitions(self) -> dict[tuple[int, int], int]:
        """Transition counts ``(from, to) -> count`` over indices into :meth:`export_library`."""
        return self.library.export_transitions()

    def export_packed(self) -> tuple[PackedEntries, PackedTransitions]:
        """:meth:`export_library` and :meth:`export_transitions` packed, for the library
        saver on the loops' thread (:meth:`Library.export_packed`)."""
        return self.library.export_packed()

    def contains(self, active_set: tuple[int, ...]) -> bool:
        """Whether the library holds this active set (a cheap test before an import)."""
        return active_set in self.library

    def pop_new_entries(self) -> list[LibraryEntry]:
        """Entries added by solves since the last call (for the store and the publisher)."""
        out, self._new = self._new, []
        return out

    def import_entries(
        self,
        entries: Iterable[LibraryEntry],
        source: Literal["prior", "shared"] = "prior",
        *,
        signature: str | None = None,
        transitions: dict[tuple[int, int], int] | None = None,
    ) -> int:
        """Add validated entries to the library (a prior from the store, an offline import:
        trusted experience); return how many were new. Fleet controllers go through
        :meth:`offer_candidates` instead.

        Everything is validated before the library changes: the problem signature (when
        given), each active set (sorted unique ints in range, at most N nu rows, linearly
        independent), importance and uses, the number of entries (<= max_size) and the
        transition indices and counts. Imported entries are inserted as least important (in
        their given importance order) so local experience wins eviction; they are still
        applied only when they pass the KKT check. Each keeps its ``origin`` (``source``
        when it has none).
        """
        if source not in ("prior", "shared"):
            raise ValueError(f"source must be 'prior' or 'shared', got {source!r}")
        p = self.problem
        if signature is not None and signature != p.signature():
            raise ValueError(
                f"library signature {signature!r} does not match problem {p.signature()!r}"
            )
        items = list(entries)
        if len(items) > self.library.max_size:
            raise ValueError(
                f"{len(items)} entries exceed the size limit {self.library.max_size}"
            )
        maps: list[tuple[LibraryEntry, ActiveSetMap]] = []
        for n, e in enumerate(items):
            maps.append((e, self.builder.validated(n, e)))
        if transitions is not None:
            for (a, b), count in transitions.items():
                if not (0 <= a < len(items) and 0 <= b < len(items)):
                    raise ValueError(f"transition ({a}, {b}) indexes outside the entries")
                if not isinstance(count, int) or count < 1:
                    raise ValueError(f"transition ({a}, {b}) count must be an int >= 1")
        keys: dict[int, int] = {}
        added = 0
        order = sorted(range(len(maps)), key=lambda i: maps[i][0].importance, reverse=True)
        for i in order:
            e, amap = maps[i]
            existing = self.library.get(amap.active)
            if existing is not None:
                keys[i] = existing.key
                continue
            keys[i] = self._add(amap, 0.0, 0, least_important=True,
                                origin=e.origin or source).key
            added += 1
        self.library.add_transitions(keys, transitions or {})
        if source == "shared":
            self._received_shared += added
        logger.debug("imported %d of %d %s entries", added, len(items), source)
        return added

    # -- the miss worker ----------------------------------------------------------------------

    def learn(
        self,
        x0: npt.ArrayLike,
        refs: npt.ArrayLike,
        u_p: npt.ArrayLike | None = None,
        *,
        perturbation: npt.ArrayLike | None = None,
    ) -> LibraryEntry | None:
        """The miss path's full solve for one tick's data, separable from ``step`` so a
        worker can run it off the loop. Returns the (possibly pre-existing) entry or None."""
        return self.learn_theta(self.problem.theta(x0, refs, u_p, perturbation=perturbation))

    def learn_theta(self, theta: FloatArray) -> LibraryEntry | None:
        """:meth:`learn` for a parameter vector (nθ,) built by ``problem.theta`` (as queued in
        ``pending``)."""
        theta_aug = np.append(np.asarray(theta, dtype=np.float64), 1.0)
        e = self._learn(theta_aug, np.empty(self.problem.nu))
        return None if e is None else LibraryEntry(e.map.active, e.importance, e.uses)

    def covers(self, theta: FloatArray) -> bool:
        """Whether a stored controller passes the KKT check at ``theta`` (nθ,): the query,
        without using it (no importance, transition or counter changes)."""
        theta_cols = self.builder.compact(np.append(np.asarray(theta, dtype=np.float64), 1.0))
        p = self.problem
        return self.library.query(theta_cols, np.empty(p.nu), p.u_min, p.u_max) is not None

    def map_of(self, active: tuple[int, ...]) -> ActiveSetMap | None:
        """The library's map of ``active`` (None when it holds no such entry)."""
        entry = self.library.get(active)
        return None if entry is None else entry.map

    def add_solved(
        self, theta: FloatArray, active_set: tuple[int, ...], origin: str = "solved"
    ) -> bool:
        """Add an active set a worker found for ``theta`` (the miss path off the loop), only
        if this controller's own KKT check passes with it at that ``theta``.

        ``origin`` "solved": the worker solved the QP; counted as a QP solve, the entry is
        new experience (published and stored as "solved"). Any other origin (a fleet
        candidate's, ``shared:<vehicle>``): the worker found it in its candidate pool; it is
        promoted with that origin, counted in ``received_shared``, and not published again.
        False, and nothing added, when the set is malformed, dependent or not optimal at
        ``theta``.
        """
        theta_aug = np.append(np.asarray(theta, dtype=np.float64), 1.0)
        solved = origin == "solved"
        if not solved:
            self.candidates.take(tuple(active_set))
        try:
            amap = self.builder.validated(0, LibraryEntry(tuple(active_set), 0.0, 0))
        except ValueError as exc:
            logger.debug("worker's active set refused: %s", exc)
            self._learn_failures += 1
            return False
        return self._admit(theta_aug, amap, origin)

    def add_built(
        self, theta: FloatArray, amap: ActiveSetMap, model_epoch: int, origin: str = "solved"
    ) -> bool | None:
        """:meth:`add_solved` with the map the worker built for the active set (for its model
        ``model_epoch``): no factorisation on the loop (0.3-1.3 ms for the position problem),
        and this controller's own KKT check at ``theta`` (nθ,) still decides. None, and
        nothing done, when the map is not for this controller's model (another epoch or
        layout): :meth:`add_solved` builds it then."""
        if model_epoch != self.model_epoch or not self.builder.fits(amap):
            return None
        if origin != "solved":
            self.candidates.take(amap.active)
        return self._admit(np.append(np.asarray(theta, dtype=np.float64), 1.0), amap, origin)

    def _admit(self, theta_aug: FloatArray, amap: ActiveSetMap, origin: str) -> bool:
        """Add ``amap`` if it passes the KKT check at ``theta_aug`` (the tail of
        :meth:`add_solved` and :meth:`add_built`)."""
        solved = origin == "solved"
        self._solves += solved
        p = self.problem
        if not amap.apply(theta_aug, np.empty(p.nu), p.u_min, p.u_max):
            self._learn_failures += 1
            return False
        lib = self.library
        entry = lib.get(amap.active)
        if entry is not None:
            if lib.max_checks is not None and len(lib) > lib.max_checks:
                # the query's budget did not reach it: make it the most important, so the
                # next query in this region checks it first instead of missing again
                lib.refresh(entry)
            return True
        entry = self._add(amap, origin=origin)
        if solved:
            self._new.append(LibraryEntry(amap.active, entry.importance, entry.uses, origin))
        else:
            self._received_shared += 1
        return True

    # -- the fleet's candidates ---------------------------------------------------------------

    def offer_candidates(
        self, entries: Iterable[LibraryEntry], origin: str, *, signature: str | None = None,
        successors: Mapping[tuple[int, ...], tuple[tuple[int, ...], ...]] | None = None,
    ) -> int:
        """Put received controllers in the candidate pool (no factorisation: cheap on the
        loop); returns how many were new. Malformed ones are counted and skipped; ones in the
        library already are ignored. ``origin``: ``shared:<vehicle>``, the pool's quota key;
        each entry's importance and uses, and its ``successors`` in the sender's transition
        counts (most frequent first), order the backlog (:meth:`CandidatePool.refocus`).
        """
        if signature is not None and signature != self.problem.signature():
            raise ValueError(
                f"library signature {signature!r} does not match problem "
                f"{self.problem.signature()!r}"
            )
        return self.candidates.offer_checked(self.builder.check_entry, self.library, entries,
                                             origin, successors)

    def limit_candidates(self, max_size: int, max_per_origin: int, max_backlog: int = 2048,
                         max_backlog_per_origin: int = 512) -> None:
        """Resize the candidate pool (its candidates are dropped: call before any arrive)."""
        self.candidates = CandidatePool(max_size, max_per_origin, max_backlog,
                                        max_backlog_per_origin)

    def focus_candidates(self) -> int:
        """Bring the candidates most likely next after the controller in use into the pool
        (:meth:`CandidatePool.refocus`; bookkeeping only), when that controller changed or
        an origin was proven since; returns how many entered."""
        last = self.library.last
        root = last.map.active if last is not None else None
        pool = self.candidates
        proven = sum(pool.promotions.values())
        if (root, proven) == self._focus_state:
            return 0
        self._focus_state = (root, proven)
        return pool.refocus(root)

    def wanted_maps(self, limit: int) -> list[tuple[int, ...]]:
        """Candidates of proven origins whose maps a worker should build, likeliest first."""
        return self.candidates.wanted(limit)

    def attach_maps(
        self, built: Iterable[tuple[tuple[int, ...], ActiveSetMap | None]], model_epoch: int
    ) -> int:
        """Take candidate maps built off the loop for model ``model_epoch`` (stale ones are
        ignored): no factorisation here, and the loop checks them before declaring a miss."""
        if model_epoch != self.model_epoch:
            return 0
        attached = 0
        for active, amap in built:
            if amap is not None and (amap.active != active or not self.builder.fits(amap)):
                continue
            attached += self.candidates.attach(active, amap)
        return attached

    def build_candidates(self, budget_s: float | None) -> int:
        """Build candidate maps for up to ``budget_s`` (None: all); returns how many."""
        return self.candidates.build(self.builder.build, budget_s)

    def _promote(
        self, theta_aug: FloatArray, u_out: FloatArray, budget_s: float | None,
        *, build: bool = True,
    ) -> Entry | None:
        """The miss path's first try: a candidate optimal here joins the library (its first
        input written to ``u_out``). ``build`` False: only maps built already are checked."""
        if build:
            self.focus_candidates()
            self.build_candidates(budget_s)
        p = self.problem
        found = self.candidates.find(theta_aug, u_out, p.u_min, p.u_max)
        if found is None:
            return None
        active, cand = found
        self.candidates.take(active)
        assert cand.map is not None
        self._received_shared += 1
        return self._add(cand.map, origin=cand.origin)


class FleetPort:
    """One controller as the fleet exchange sees it (``epc_offboard.fleet.exchange.
    FleetLibrary``, matched by shape: ``control/`` imports nothing of the fleet): four
    methods, the only ones the fleet calls, and :meth:`received` for a restart. Sizes the
    controller's candidate pool."""

    def __init__(self, controller: LibraryExchange, pool: CandidatePoolConfig) -> None:
        self._ctrl = controller
        controller.limit_candidates(pool.pool_size, pool.per_peer, pool.backlog_size,
                                    pool.backlog_per_peer)  # fmt: skip
        p = controller.problem
        # what the helper checks a peer's message against (fleet.records.ProblemSpec)
        self.signature, self.n_con, self.max_active = p.signature(), p.n_con, p.n_u
        self.max_entries = controller.library.max_size

    def offer(self, entry: LibraryEntry, origin: str, successors: tuple[ActiveSet, ...]) -> bool:
        """Into the candidate pool (:meth:`LibraryExchange.offer_candidates`); whether new."""
        return self._ctrl.offer_candidates(
            [entry], origin, successors={entry.active_set: successors}) > 0  # fmt: skip

    def new_entries(self) -> list[LibraryEntry]:
        return self._ctrl.pop_new_entries()

    def snapshot(self) -> tuple[list[LibraryEntry], dict[tuple[int, int], int]]:
        return self._ctrl.export_library(), self._ctrl.export_transitions()

    def fleet_counts(self) -> tuple[int, int]:
        return len(self._ctrl.candidates), self._ctrl._received_shared

    def received(self) -> list[tuple[LibraryEntry, tuple[ActiveSet, ...]]]:
        """Received controllers not in the library (yet), with their successors."""
        return self._ctrl.candidates.known()

    def received_parts(
        self, per_part: int
    ) -> Iterator[list[tuple[LibraryEntry, tuple[ActiveSet, ...]]]]:
        """:meth:`received` in parts of at most ``per_part``."""
        return self._ctrl.candidates.known_parts(per_part)
