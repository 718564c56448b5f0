"""Experience-driven Predictive Control: a library of active sets reused by a KKT check.

A controller is an active set ``a`` of the condensed QP (:mod:`~epc_offboard.control.qp`).
For a fixed model its KKT system (thesis 3.5-3.8)::

    [H    Ga'] [U  ]   [-F theta        ]
    [Ga   0  ] [lam] = [g0_a + S_a theta]

is solved once, symbolically in ``theta``, into ONE stacked affine map ``w = M [theta; 1]``
whose rows are: the active multipliers, every finite bound of the inputs and predicted states
as a shifted slack, and the first input. Applying and checking a stored controller is then
one mat-vec with ``0 <= w <= width`` tests (:mod:`epc_offboard.control.kernels`, compiled by numba,
with an early exit on the first failed row). Checking every bound row (active ones included,
whose slack is zero by construction) is the thesis's "every inactive constraint holds"
without gathering rows.

Query order: the last used controller, then its successors in the transition counts (most
frequent first), then the rest by importance (last use, most recent first). The scan is one
compiled call over the maps in that order (:func:`epc_offboard.control.kernels.query_maps`), bounded
by ``max_checks`` candidates: a query never costs more than that many KKT checks, whatever
the library's size (a stored controller beyond the bound is a miss this tick). A miss calls
:meth:`ExperienceController.learn` (OSQP, polished; active set recovered, rebuilt exactly from
the KKT system and verified by the same check) and, if that fails, the intermediate
controller (short horizon, slack on the state bounds, always feasible), then a bounded hover.

Library exchange: entries carry the active set as sorted row indices into the problem's
layout (:class:`~epc_offboard.control.qp.ConstraintRow` order), their importance, use count and
origin. Transition counts are exported separately, keyed by pairs of indices into the exported list.

Controllers received from the fleet are candidates, not library entries
(:class:`CandidatePool`): a bounded pool, at most a quota per sending vehicle, whose maps are
built in slices bounded by time. A candidate enters the library only when it passes this
controller's KKT check for a real tick's parameters (a miss that it covers): one that is
never optimal here never takes a library slot.
"""

from __future__ import annotations

import logging
import math
import time
from collections import Counter, OrderedDict, deque
from collections.abc import Callable, Iterable, Iterator, Mapping, Sequence
from dataclasses import dataclass
from typing import Literal

import daqp
import numpy as np
import numpy.typing as npt
import scipy.linalg as sla

from epc_offboard.common.errors import EpcError
from epc_offboard.common.frames import FloatArray
from epc_offboard.control import kernels
from epc_offboard.control.decision import Decision
from epc_offboard.control.kernels import apply_map, new_map_lists, query_maps, store_map
from epc_offboard.control.library import EntryError, LibraryEntry, parse_entry
from epc_offboard.control.models import LinearModel
from epc_offboard.control.qp import MpcProblem, OsqpSolver, QpStatus

logger = logging.getLogger(__name__)

# Cholesky pivots of Ga H^-1 Ga' below this fraction of the largest mean cond > ~1e12:
# the rows are treated as linearly dependent.
_DEPENDENCE_RTOL = 1e-6
# the full solve's OSQP tolerances; polishing makes the active set exact, these only need to
# make OSQP's duals point at it
_EPS = 1e-8
_MAX_ITER = 10000
# Worst-case cost of one KKT check in the compiled scan, per multiply-add of its map (a
# candidate refused only at its last row): measured 0.13-0.21 ns on the 2-core development
# machine under load (`epc-offboard bench --service` prints the scan's cost); a query budget
# in us is turned into a number of candidates with it, so the bound holds in the worst case.
CHECK_NS_PER_MAC = 0.2


@dataclass(frozen=True)
class EpcStats:
    hits: int
    misses: int
    qp_solves: int
    size: int
    intermediate: int
    fallback: int
    learn_failures: int
    received_shared: int = 0  # fleet candidates promoted into the library (KKT-checked here)
    candidates: int = 0  # fleet candidates waiting in the pool

    @property
    def hit_rate(self) -> float:
        total = self.hits + self.misses
        return self.hits / total if total else 0.0


class DependentActiveSetError(EpcError, ValueError):
    """The active set's constraint rows are linearly dependent (no unique multipliers)."""


class ActiveSetMap:
    """The cached affine map of one active set, checked and applied by one mat-vec.

    With ``theta_aug = [theta; 1]``, ``w = M theta_aug`` has rows:

    * the active multipliers plus ``tol`` (must be >= 0);
    * one row per finite-bounded component of ``[U; X]``, shifted (and, for rows bounded
      only above, negated) so that its bounds widened by ``tol`` become ``0 <= w <= width``;
    * ``u_0`` (nu), the first input, as is.

    The first ``n_check`` rows are the KKT check (thesis 3.5-3.8: multipliers >= -tol and every
    bound within tol; an active row's slack is zero by construction, so checking all rows is
    checking the inactive ones). :func:`epc_offboard.control.kernels.apply_map` evaluates it.
    """

    __slots__ = ("M", "U", "active", "lam", "n_check", "width")

    def __init__(self, problem: MpcProblem, active: tuple[int, ...], geom: _ProblemGeometry,
                 tol: float) -> None:
        idx = np.asarray(active, dtype=np.intp)
        Ga = problem.G[idx]
        E1 = sla.cho_solve(geom.h_chol, Ga.T).T  # Ga H^-1  (na, nU)
        W = E1 @ Ga.T
        if len(active):
            try:
                w_chol = sla.cho_factor(W)
            except np.linalg.LinAlgError as exc:
                raise DependentActiveSetError(f"active set {active} is dependent") from exc
            d = np.abs(np.diag(w_chol[0]))
            if d.min() <= _DEPENDENCE_RTOL * float(d.max()):
                raise DependentActiveSetError(f"active set {active} is dependent")
            # lam = -W^-1 (E1 F theta + S_a theta + g0_a)   (thesis 3.8)
            L_theta = -sla.cho_solve(w_chol, E1 @ problem.F + problem.S[idx])
            l_0 = -sla.cho_solve(w_chol, problem.g0[idx])
        else:
            L_theta = np.zeros((0, problem.n_theta))
            l_0 = np.zeros(0)
        # U = -H^-1 (F theta + Ga' lam)   (thesis 3.6)
        U_aug = np.hstack([-geom.hinv_f - E1.T @ L_theta, (-E1.T @ l_0)[:, None]])
        UX_aug = np.vstack([U_aug, geom.xb_aug + geom.xb_bbar @ U_aug, geom.poly_rows(U_aug)])
        L_aug = np.hstack([L_theta, l_0[:, None]])
        chk = geom.chk_sign[:, None] * UX_aug[geom.chk_rows]
        chk[:, -1] += geom.chk_offset
        lam_chk = L_aug.copy()
        lam_chk[:, -1] += tol
        self.M = np.ascontiguousarray(np.vstack([lam_chk, chk, U_aug[: problem.nu]]))
        self.width = np.concatenate([np.full(len(active), np.inf), geom.chk_width])
        self.n_check = len(self.width)
        self.U = U_aug
        self.lam = L_aug
        self.active = active

    def apply(self, theta_aug: FloatArray, u_out: FloatArray, u_min: FloatArray,
              u_max: FloatArray) -> bool:
        """KKT-check at ``theta_aug``; if it passes write the clipped first input to
        ``u_out`` and return True."""
        return apply_map(self.M, self.width, theta_aug, self.n_check, u_out, u_min, u_max)


class _ProblemGeometry:
    """Per-model quantities shared by every active set's map (see :class:`ActiveSetMap`)."""

    def poly_rows(self, U_aug: FloatArray) -> FloatArray:
        """``poly @ U_aug`` stage by stage (``poly`` is block diagonal): a batch of small
        products instead of one (N npoly, N nu) product, which OpenBLAS spread over threads
        and which took 14 ms on two busy cores (1.5 ms idle) for the position problem."""
        P = self._poly_stage
        n_stage, nu = P.shape
        N, cols = U_aug.shape[0] // nu, U_aug.shape[1]
        out: FloatArray = (P @ U_aug.reshape(N, nu, cols)).reshape(N * n_stage, cols)
        return out

    def __init__(self, problem: MpcProblem, tol: float) -> None:
        self.h_chol = sla.cho_factor(problem.H)
        self.hinv_f = sla.cho_solve(self.h_chol, problem.F)
        nx, N = problem.nx, problem.horizon
        bounded = np.isfinite(problem.x_min) | np.isfinite(problem.x_max)
        rows = np.array([k * nx + i for k in range(N) for i in range(nx) if bounded[i]],
                        dtype=np.intp)
        # bounded X rows as affine maps of theta_aug (through x0 and c~) and of U
        xt = np.zeros((len(rows), problem.n_theta + 1))
        xt[:, :nx] = problem.Phi[rows]
        c0 = nx + N * nx
        xt[:, c0 : c0 + nx] = problem.Psi[rows]
        self.xb_aug = xt
        self.xb_bbar = problem.Bbar[rows]
        # the input polytope's rows per stage, P u_k <= p: bounded above only
        self.poly = np.kron(np.eye(N), problem.u_poly_P)
        self._poly_stage = np.ascontiguousarray(problem.u_poly_P)
        n_poly = self.poly.shape[0]
        lo = np.concatenate([np.tile(problem.u_min, N), np.tile(problem.x_min[bounded], N),
                             np.full(n_poly, -np.inf)])
        hi = np.concatenate([np.tile(problem.u_max, N), np.tile(problem.x_max[bounded], N),
                             np.tile(problem.u_poly_p, N)])
        lo_f, hi_f = np.isfinite(lo), np.isfinite(hi)
        self.chk_rows = np.flatnonzero(lo_f | hi_f)
        lo, hi, lo_f = lo[self.chk_rows], hi[self.chk_rows], lo_f[self.chk_rows]
        # w = v - (lo - tol) in [0, hi - lo + 2 tol]; rows bounded only above: w = hi + tol - v
        self.chk_sign = np.where(lo_f, 1.0, -1.0)
        self.chk_offset = np.where(lo_f, -(lo - tol), hi + tol)
        with np.errstate(invalid="ignore"):
            self.chk_width = np.where(lo_f, hi - lo + 2.0 * tol, np.inf)


@dataclass
class _Entry:
    key: int
    map: ActiveSetMap
    importance: float
    uses: int
    origin: str
    slot: int = -1  # its map's index in the compiled scan's arrays


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
        """Build unbuilt maps, oldest first, until ``budget_s`` (None: no limit) of CPU time
        is spent (at least one per call, so slices always progress); returns how many.

        Dependent sets are dropped. Time, not a count, bounds a slice: a map's cost grows
        with its active rows."""
        t0 = time.perf_counter()
        built = 0
        for active in [a for a, c in self._items.items() if c.map is None]:
            if budget_s is not None and built and time.perf_counter() - t0 >= budget_s:
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

    def forget_maps(self) -> None:
        """The model's A or B changed: every map must be built again."""
        for cand in self._items.values():
            cand.map = None


class ExperienceController:
    """EPC over one :class:`MpcProblem` (thesis algorithm 1).

    ``max_size`` bounds the library (least important evicted); ``tol`` is the KKT check's
    tolerance (multipliers >= -tol, bounds within tol); ``intermediate_horizon`` the short
    horizon of the slack QP; ``learn_on_miss`` False leaves the full solve to the caller
    (``step`` applies the intermediate controller and queues the parameter vectors in
    :attr:`pending`, for a worker to pass to :meth:`learn_theta`); ``with_prediction`` adds the
    predicted trajectory to hit decisions (one more mat-vec); ``max_candidates`` and
    ``max_candidates_per_origin`` bound the pool of fleet candidates (:class:`CandidatePool`;
    with ``learn_on_miss`` a miss builds and checks them before solving, without it the
    worker holds a copy and does both off the loop).

    Not thread-safe: ``step``, ``learn`` and the library methods share the solver and the
    library, so a worker running ``learn`` must be serialised with the loop (or hand its
    entries back through :meth:`import_entries`, which re-validates them).
    """

    def __init__(
        self,
        problem: MpcProblem,
        *,
        max_size: int = 500,
        tol: float = 1e-9,
        intermediate_horizon: int = 5,
        slack_weight: float = 1e3,
        learn_on_miss: bool = True,
        with_prediction: bool = False,
        max_pending: int = 8,
        max_candidates: int = 64,
        max_candidates_per_origin: int = 16,
        max_checks: int | None = None,
        max_candidate_backlog: int = 2048,
        max_candidate_backlog_per_origin: int = 512,
    ) -> None:
        if max_size < 1:
            raise ValueError(f"max_size must be >= 1, got {max_size}")
        if max_checks is not None and max_checks < 1:
            raise ValueError(f"max_checks must be >= 1 or None, got {max_checks}")
        if not (tol > 0.0 and math.isfinite(tol)):
            raise ValueError(f"tol must be a positive finite number, got {tol}")
        if intermediate_horizon < 1:
            raise ValueError(f"intermediate_horizon must be >= 1, got {intermediate_horizon}")
        self.max_size = max_size
        self.tol = tol
        self.learn_on_miss = learn_on_miss
        self.with_prediction = with_prediction
        self._int_horizon = min(intermediate_horizon, problem.horizon)
        self._slack_weight = slack_weight
        self._max_pending = max_pending
        self.pending: list[FloatArray] = []
        self._entries: OrderedDict[int, _Entry] = OrderedDict()  # least important first
        self._by_set: dict[tuple[int, ...], int] = {}
        self._succ: dict[int, dict[int, int]] = {}
        self._next_key = 0
        self._last: int | None = None
        self._tick = 0
        self._new: list[LibraryEntry] = []
        self._hits = self._misses = self._solves = 0
        self._intermediate = self._fallback = self._learn_failures = 0
        self._received_shared = 0
        self.candidates = CandidatePool(max_candidates, max_candidates_per_origin,
                                        max_candidate_backlog, max_candidate_backlog_per_origin)
        self.model_epoch = 0  # counts changes of A or B: maps built before are stale
        # (root, promotions) of the last refocus
        self._focus_state: tuple[tuple[int, ...] | None, int] | None = None
        # the bounded scan: every entry's map arrays in slots, and the query order as slots
        # (its compiled code is made ready here, where a controller is built: at start-up, in
        # the service and in the miss worker alike, never at the first miss or solve)
        kernels.warm_up()
        self.max_checks = max_checks
        self._slot_lists = new_map_lists()  # (maps' M, maps' width) by slot
        self._slot_n_check = np.zeros(0, dtype=np.int64)
        self._free_slots: list[int] = []
        self._order: npt.NDArray[np.int64] | None = None  # None: to rebuild
        self._slot_entry: list[_Entry | None] = []  # whose map each slot holds
        self.last_query_checks = 0  # candidates the last query checked (diagnostics, tests)
        self._checks = 0
        self._budget_exhausted = 0
        self._setup(problem)

    # -- model ------------------------------------------------------------------------------

    def _setup(self, problem: MpcProblem) -> None:
        self.problem = problem
        self._geom = _ProblemGeometry(problem, self.tol)
        self._solver = OsqpSolver(problem.H, problem.G, polish=True, eps_abs=_EPS, eps_rel=_EPS,
                                  max_iter=_MAX_ITER)
        # theta_aug = [theta; 1]: the maps carry their constant as a last column
        self._theta_aug = np.zeros(problem.n_theta + 1)
        self._theta_aug[-1] = 1.0
        self._intermediate_qp = _IntermediateQp(problem, self._int_horizon, self._slack_weight)

    def set_model(self, model: LinearModel) -> None:
        """Adopt a new model of equal size; rebuild every cached map (the library is kept).

        Entries whose rows become dependent under the new model are dropped.
        """
        old = self.problem.model
        if np.array_equal(old.A, model.A) and np.array_equal(old.B, model.B):
            # only the offset changed: it enters through theta, the maps stay valid
            self.problem = self.problem.with_offset(model)
            return
        self._setup(self.problem.with_model(model))
        self.model_epoch += 1
        self.candidates.forget_maps()
        for key, e in list(self._entries.items()):
            try:
                e.map = ActiveSetMap(self.problem, e.map.active, self._geom, self.tol)
            except DependentActiveSetError:
                logger.debug("dropping %s: dependent under the new model", e.map.active)
                self._remove(key)
                continue
            self._store_slot(e)

    # -- the loop ---------------------------------------------------------------------------

    def step(
        self,
        x0: npt.ArrayLike,
        refs: npt.ArrayLike,
        u_p: npt.ArrayLike | None = None,
        *,
        perturbation: npt.ArrayLike | None = None,
    ) -> Decision:
        """One control tick. ``x0`` (nx,), ``refs`` (N, nx) absolute references for x_1..x_N,
        ``u_p`` (nu,) or (N, nu) nominal input, ``perturbation`` p^ (nx,) added to the model
        offset.

        With a perturbation and no ``u_p``, ``u_p = -pinv(B) p^`` (the input cancelling it).
        """
        t0 = time.perf_counter()
        th_aug = self._theta_aug
        theta = self.problem.theta(x0, refs, u_p, perturbation=perturbation, out=th_aug[:-1])
        self._tick += 1
        u = np.empty(self.problem.nu)
        entry = self._query(th_aug, u)
        if entry is not None:
            self._hits += 1
            self._use(entry)
            x_pred = self._predict(entry, th_aug) if self.with_prediction else None
            return Decision(u, "hit", (time.perf_counter() - t0) * 1e6, x_pred)
        if len(self.candidates):
            # with learn_on_miss every candidate is built here; without, only the maps the
            # worker built for proven origins are checked (mat-vecs, no factorisation)
            entry = self._promote(th_aug, u, budget_s=None, build=self.learn_on_miss)
            if entry is not None:  # a fleet candidate, optimal here: exact, no solve
                self._hits += 1
                self._use(entry)
                x_pred = self._predict(entry, th_aug) if self.with_prediction else None
                return Decision(u, "hit", (time.perf_counter() - t0) * 1e6, x_pred)
        self._misses += 1
        if self.learn_on_miss:
            entry = self._learn(th_aug, u)
            if entry is not None:
                self._use(entry)
                return Decision(u, "solved", (time.perf_counter() - t0) * 1e6,
                                self._predict(entry, th_aug))
        elif len(self.pending) < self._max_pending:
            self.pending.append(theta.copy())
        return self._degraded(theta, t0)

    def _predict(self, entry: _Entry, theta_aug: FloatArray) -> FloatArray:
        return self.problem.predict(theta_aug[:-1], entry.map.U @ theta_aug)

    def _candidates(self) -> Iterator[_Entry]:
        entries = self._entries
        last = self._last
        tried: set[int] = set()
        if last is not None and last in entries:
            tried.add(last)
            yield entries[last]
            succ = self._succ.get(last)
            if succ:
                for key in sorted(succ, key=succ.__getitem__, reverse=True):
                    if key not in tried and key in entries:
                        tried.add(key)
                        yield entries[key]
        for key in reversed(entries):
            if key not in tried:
                yield entries[key]

    def query_order(self) -> list[tuple[int, ...]]:
        """Active sets in the order the next query will try them, at most ``max_checks`` of
        them (diagnostics and tests)."""
        order = [e.map.active for e in self._candidates()]
        return order if self.max_checks is None else order[: self.max_checks]

    def _query_slots(self) -> npt.NDArray[np.int64]:
        """The slots of :meth:`_candidates`, cached until the order can have changed (an
        entry added or removed, another controller used, transitions imported)."""
        if self._order is None:
            self._order = np.fromiter(
                (e.slot for e in self._candidates()), dtype=np.int64, count=len(self._entries)
            )
        return self._order

    def _query(self, theta_aug: FloatArray, u_out: FloatArray) -> _Entry | None:
        p = self.problem
        u_min, u_max = p.u_min, p.u_max
        last = self._last
        budget = len(self._entries) if self.max_checks is None else self.max_checks
        checked = 0
        if last is not None:
            # the hot path: the last controller usually still applies
            e = self._entries.get(last)
            if e is not None:
                checked = 1
                if e.map.apply(theta_aug, u_out, u_min, u_max):
                    self.last_query_checks = 1
                    self._checks += 1
                    return e
        order = self._query_slots()
        start = checked  # the last controller, when there is one, is the order's first
        n = min(budget - checked, len(order) - start)
        k = query_maps(*self._slot_lists, self._slot_n_check, order[start:],
                       n, theta_aug, u_out, u_min, u_max) if n > 0 else -1
        checked += n if k < 0 else k + 1
        self.last_query_checks = checked
        self._checks += checked
        if k < 0:
            if len(self._entries) > budget:
                self._budget_exhausted += 1
            return None
        found = self._slot_entry[int(order[start + k])]
        assert found is not None  # the order holds live entries' slots only
        return found

    def _store_slot(self, entry: _Entry) -> None:
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

    def _use(self, entry: _Entry) -> None:
        key = entry.key
        last = self._last
        if last is not None and last in self._entries:
            succ = self._succ.setdefault(last, {})
            succ[key] = succ.get(key, 0) + 1
        entry.importance = float(self._tick)
        entry.uses += 1
        if last != key:
            self._entries.move_to_end(key)
            self._order = None
        self._last = key

    # -- miss path --------------------------------------------------------------------------

    def learn(
        self,
        x0: npt.ArrayLike,
        refs: npt.ArrayLike,
        u_p: npt.ArrayLike | None = None,
        *,
        perturbation: npt.ArrayLike | None = None,
    ) -> LibraryEntry | None:
        """The miss path's full solve for one tick's data, separable from :meth:`step` so a
        worker can run it off the loop. Returns the (possibly pre-existing) entry or None."""
        return self.learn_theta(self.problem.theta(x0, refs, u_p, perturbation=perturbation))

    def learn_theta(self, theta: FloatArray) -> LibraryEntry | None:
        """:meth:`learn` for a parameter vector (nθ,) built by ``problem.theta`` (as queued in
        :attr:`pending`)."""
        theta_aug = np.append(np.asarray(theta, dtype=np.float64), 1.0)
        e = self._learn(theta_aug, np.empty(self.problem.nu))
        return None if e is None else LibraryEntry(e.map.active, e.importance, e.uses)

    def _learn(self, theta_aug: FloatArray, u_out: FloatArray) -> _Entry | None:
        """Solve the full QP, recover and verify its active set, add it.

        Returns the entry, with the exact first input written to ``u_out``, or None when the
        QP is infeasible or no active set passes the check.
        """
        p = self.problem
        theta = theta_aug[:-1]
        h, gamma = p.vectors(theta)
        self._solves += 1
        amap = None
        for attempt in range(2):
            if attempt:  # tighten and retry once: a sharper optimum gives clearer duals
                self._solver.set_tolerances(1e-11, 1e-11, 40000)
            res = self._solver.solve(h, gamma)
            if attempt:
                self._solver.set_tolerances(_EPS, _EPS, _MAX_ITER)
            if res.status not in (QpStatus.SOLVED, QpStatus.INACCURATE):
                logger.debug("full QP not solved: %s", res.status.value)
                break
            amap = self._recover_active_set(theta_aug, res.y, gamma, u_out)
            if amap is not None:
                break
        if amap is None:
            self._learn_failures += 1
            return None
        key = self._by_set.get(amap.active)
        if key is not None:
            return self._entries[key]
        entry = self._add(amap, origin="solved")
        self._new.append(LibraryEntry(amap.active, entry.importance, entry.uses, "solved"))
        return entry

    def covers(self, theta: FloatArray) -> bool:
        """Whether a stored controller passes the KKT check at ``theta`` (nθ,): the query,
        without using it (no importance, transition or counter changes)."""
        theta_aug = np.append(np.asarray(theta, dtype=np.float64), 1.0)
        return self._query(theta_aug, np.empty(self.problem.nu)) is not None

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
            amap = self._validated_map(0, LibraryEntry(tuple(active_set), 0.0, 0))
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
        p = self.problem
        n_check = len(amap.active) + len(self._geom.chk_width)
        if (model_epoch != self.model_epoch or len(amap.width) != n_check
                or amap.M.shape != (n_check + p.nu, p.n_theta + 1)):
            return None
        if origin != "solved":
            self.candidates.take(amap.active)
        return self._admit(np.append(np.asarray(theta, dtype=np.float64), 1.0), amap, origin)

    def map_of(self, active: tuple[int, ...]) -> ActiveSetMap | None:
        """The library's map of ``active`` (None when it holds no such entry)."""
        key = self._by_set.get(active)
        return None if key is None else self._entries[key].map

    def _admit(self, theta_aug: FloatArray, amap: ActiveSetMap, origin: str) -> bool:
        """Add ``amap`` if it passes the KKT check at ``theta_aug`` (the tail of
        :meth:`add_solved` and :meth:`add_built`)."""
        solved = origin == "solved"
        self._solves += solved
        if not amap.apply(theta_aug, np.empty(self.problem.nu), self.problem.u_min,
                          self.problem.u_max):
            self._learn_failures += 1
            return False
        key = self._by_set.get(amap.active)
        if key is not None:
            if self.max_checks is not None and len(self._entries) > self.max_checks:
                # the query's budget did not reach it: make it the most important, so the
                # next query in this region checks it first instead of missing again
                self._entries[key].importance = float(self._tick)
                self._entries.move_to_end(key)
                self._order = None
            return True
        entry = self._add(amap, origin=origin)
        if solved:
            self._new.append(LibraryEntry(amap.active, entry.importance, entry.uses, origin))
        else:
            self._received_shared += 1
        return True

    # -- fleet candidates ---------------------------------------------------------------------

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
        pool = self.candidates
        added = 0
        for n, received in enumerate(entries):
            try:
                e = self._check_entry(n, received)
            except ValueError:
                pool.counters["rejected_malformed"] += 1
                continue
            if e.active_set in self._by_set:
                pool.counters["in_library"] += 1
                continue
            succ = successors.get(e.active_set, ()) if successors is not None else ()
            added += pool.offer(e.active_set, origin, float(e.importance), int(e.uses), succ)
        return added

    def limit_candidates(self, max_size: int, max_per_origin: int, max_backlog: int = 2048,
                         max_backlog_per_origin: int = 512) -> None:
        """Resize the candidate pool (its candidates are dropped: call before any arrive)."""
        self.candidates = CandidatePool(max_size, max_per_origin, max_backlog,
                                        max_backlog_per_origin)

    def focus_candidates(self) -> int:
        """Bring the candidates most likely next after the controller in use into the pool
        (:meth:`CandidatePool.refocus`; bookkeeping only), when that controller changed or
        an origin was proven since; returns how many entered."""
        last = self._entries.get(self._last) if self._last is not None else None
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

    def build_maps(
        self, actives: Sequence[tuple[int, ...]], budget_s: float | None
    ) -> list[tuple[tuple[int, ...], ActiveSetMap | None]]:
        """The worker's half of :meth:`attach_maps`: maps for ``actives`` (None where the
        rows are dependent), reusing the pool's, until ``budget_s`` is spent (at least one)."""
        t0 = time.perf_counter()
        out: list[tuple[tuple[int, ...], ActiveSetMap | None]] = []
        for active in actives:
            if budget_s is not None and out and time.perf_counter() - t0 >= budget_s:
                break
            cand = self.candidates._items.get(active)
            amap = cand.map if cand is not None else None
            if amap is None:
                try:
                    amap = self._make_map(active)
                except DependentActiveSetError:
                    amap = None
            out.append((active, amap))
        return out

    def attach_maps(
        self, built: Iterable[tuple[tuple[int, ...], ActiveSetMap | None]], model_epoch: int
    ) -> int:
        """Take candidate maps built off the loop for model ``model_epoch`` (stale ones are
        ignored): no factorisation here, and the loop checks them before declaring a miss."""
        if model_epoch != self.model_epoch:
            return 0
        p = self.problem
        attached = 0
        for active, amap in built:
            if amap is not None and (amap.active != active or amap.M.shape[1] != p.n_theta + 1):
                continue
            attached += self.candidates.attach(active, amap)
        return attached

    def build_candidates(self, budget_s: float | None) -> int:
        """Build candidate maps for up to ``budget_s`` (None: all); returns how many."""
        return self.candidates.build(self._make_map, budget_s)

    def _make_map(self, active: tuple[int, ...]) -> ActiveSetMap:
        return ActiveSetMap(self.problem, active, self._geom, self.tol)

    def screen_candidates(
        self, theta: FloatArray, budget_s: float | None
    ) -> tuple[tuple[int, ...], str, ActiveSetMap] | None:
        """A candidate that is optimal at ``theta`` (nθ,), taken out of the pool, with its
        origin and map: the worker's half of a promotion (the loop checks it again in
        :meth:`add_built`). Builds for up to ``budget_s`` first."""
        self.build_candidates(budget_s)
        theta_aug = np.append(np.asarray(theta, dtype=np.float64), 1.0)
        p = self.problem
        found = self.candidates.find(theta_aug, np.empty(p.nu), p.u_min, p.u_max)
        if found is None:
            return None
        active, cand = found
        self.candidates.take(active)
        if cand.map is None:  # find() returns built candidates only
            return None
        return active, cand.origin, cand.map

    def _promote(
        self, theta_aug: FloatArray, u_out: FloatArray, budget_s: float | None,
        *, build: bool = True,
    ) -> _Entry | None:
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

    def _recover_active_set(
        self, theta_aug: FloatArray, y: FloatArray, gamma: FloatArray, u_out: FloatArray
    ) -> ActiveSetMap | None:
        """Rebuild the exact solution from OSQP's guess of the active set.

        Start from rows with a clearly positive dual; then, until the KKT check passes:
        drop linearly dependent rows (keeping the larger duals), drop the most negative
        multiplier, add the most violated inactive row (tighten and retry).
        """
        p = self.problem
        scale = max(1.0, float(np.max(np.abs(y))) if y.size else 1.0)
        active = set(np.flatnonzero(y > 1e-6 * scale).tolist())
        weight = {i: float(y[i]) for i in range(len(y))}
        seen: set[tuple[int, ...]] = set()
        for _ in range(4 * p.n_con + 10):
            rows = self._independent(sorted(active, key=lambda i: -weight.get(i, 0.0)))
            aset = tuple(sorted(rows))
            if aset in seen:
                break
            seen.add(aset)
            amap = ActiveSetMap(p, aset, self._geom, self.tol)
            if amap.apply(theta_aug, u_out, p.u_min, p.u_max):
                return amap
            U = amap.U @ theta_aug
            lam = amap.lam @ theta_aug
            slack = gamma - p.G @ U
            if len(aset):
                slack[np.asarray(aset, dtype=np.intp)] = np.inf
            active = set(aset)
            if len(aset) and lam.min() < -self.tol:
                active.discard(aset[int(np.argmin(lam))])
            if p.n_con and slack.min() < -self.tol:
                worst = int(np.argmin(slack))
                active.add(worst)
                weight[worst] = math.inf  # keep the newly tightened row
        logger.debug("active set recovery did not converge at theta=%s", theta_aug[: p.nx])
        return None

    def _independent(self, rows: Sequence[int]) -> list[int]:
        """Greedy linearly independent subset of constraint rows, in the given priority."""
        G = self.problem.G
        kept: list[int] = []
        basis = np.zeros((0, G.shape[1]))
        for i in rows:
            g = G[i]
            resid = g - basis.T @ (basis @ g) if len(kept) else g
            n = float(np.linalg.norm(resid))
            if n > 1e-9 * max(1.0, float(np.linalg.norm(g))):
                basis = np.vstack([basis, resid / n])
                kept.append(i)
        return kept

    def _degraded(self, theta: FloatArray, t0: float) -> Decision:
        u = self._intermediate_qp.solve(theta)
        if u is not None:
            self._intermediate += 1
            return Decision(u, "intermediate", (time.perf_counter() - t0) * 1e6)
        self._fallback += 1
        u = self.problem.hover_input(theta)
        return Decision(u, "fallback", (time.perf_counter() - t0) * 1e6)

    # -- library ----------------------------------------------------------------------------

    def _add(self, amap: ActiveSetMap, importance: float | None = None, uses: int = 0,
             *, least_important: bool = False, origin: str) -> _Entry:
        key = self._next_key
        self._next_key += 1
        entry = _Entry(key, amap, float(self._tick) if importance is None else importance, uses,
                       origin)
        if origin.startswith("shared:"):  # a candidate proven here: its origin earns quota
            self.candidates.promoted(amap.active, origin)
        else:
            self.candidates.take(amap.active)  # in the library now: no longer a candidate
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

    def check_cost_us(self) -> float:
        """Worst-case cost of checking one candidate: the largest map (every input row
        active) evaluated to its last row, at :data:`CHECK_NS_PER_MAC`."""
        p = self.problem
        rows = p.n_u + len(self._geom.chk_rows) + p.nu
        return rows * (p.n_theta + 1) * CHECK_NS_PER_MAC * 1e-3

    def checks_within(self, budget_us: float) -> int:
        """How many candidates a query may check to stay within ``budget_us`` (>= 1)."""
        return max(1, int(budget_us / self.check_cost_us()))

    @property
    def query_counters(self) -> dict[str, int]:
        """Candidates checked over all queries, and queries that ended at the budget with
        entries left unchecked."""
        return {"checks": self._checks, "budget_exhausted": self._budget_exhausted}

    @property
    def stats(self) -> EpcStats:
        return EpcStats(
            hits=self._hits,
            misses=self._misses,
            qp_solves=self._solves,
            size=len(self._entries),
            intermediate=self._intermediate,
            fallback=self._fallback,
            learn_failures=self._learn_failures,
            received_shared=self._received_shared,
            candidates=len(self.candidates),
        )

    def _ordered(self) -> list[_Entry]:
        """Entries most important first."""
        return list(reversed(self._entries.values()))

    def export_library(self) -> list[LibraryEntry]:
        """Entries, most important first; indices of this list key :meth:`export_transitions`."""
        return [
            LibraryEntry(e.map.active, e.importance, e.uses, e.origin) for e in self._ordered()
        ]

    def export_transitions(self) -> dict[tuple[int, int], int]:
        """Transition counts ``(from, to) -> count`` over indices into :meth:`export_library`."""
        index = {e.key: i for i, e in enumerate(self._ordered())}
        return {
            (index[a], index[b]): n
            for a, succ in self._succ.items()
            if a in index
            for b, n in succ.items()
            if b in index
        }

    def contains(self, active_set: tuple[int, ...]) -> bool:
        """Whether the library holds this active set (a cheap test before an import)."""
        return active_set in self._by_set

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
        if len(items) > self.max_size:
            raise ValueError(f"{len(items)} entries exceed the size limit {self.max_size}")
        maps: list[tuple[LibraryEntry, ActiveSetMap]] = []
        for n, e in enumerate(items):
            maps.append((e, self._validated_map(n, e)))
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
            existing = self._by_set.get(amap.active)
            if existing is not None:
                keys[i] = existing
                continue
            keys[i] = self._add(amap, 0.0, 0, least_important=True,
                                origin=e.origin or source).key
            added += 1
        for (a, b), count in (transitions or {}).items():
            ka, kb = keys.get(a), keys.get(b)
            if ka in self._entries and kb in self._entries and ka is not None and kb is not None:
                succ = self._succ.setdefault(ka, {})
                succ[kb] = succ.get(kb, 0) + count
                self._order = None
        if source == "shared":
            self._received_shared += added
        logger.debug("imported %d of %d %s entries", added, len(items), source)
        return added

    def _validated_map(self, n: int, e: LibraryEntry) -> ActiveSetMap:
        entry = self._check_entry(n, e)
        try:
            return self._make_map(entry.active_set)
        except DependentActiveSetError as exc:
            raise ValueError(f"entry {n}: active set rows are linearly dependent") from exc

    def _check_entry(self, n: int, e: LibraryEntry) -> LibraryEntry:
        """Everything about an entry short of its factorisation (ValueError names it): the
        entry as parsed, its active set a tuple in range with at most N nu rows."""
        p = self.problem
        try:
            return parse_entry(
                e.active_set, e.importance, e.uses, e.origin, n_con=p.n_con, max_rows=p.n_u
            )
        except EntryError as exc:
            raise ValueError(f"entry {n}: {exc}") from exc


class _IntermediateQp:
    """Short-horizon QP with slack on the state bounds: always feasible (thesis 3.1.3).

    Variables ``z = [U (Ni nu); s (m_x)]``, cost ``1/2 U'H U + h'U + w/2 |s|² + w 1's``,
    rows ``Gx U - s <= gamma_x``, ``s >= 0``, ``u_min <= U <= u_max``, and the input polytope
    ``Gp U <= gamma_p`` (hard: inputs can always satisfy it).

    Solved on the loop at a miss, so by DAQP (a dual active-set solver for small dense QPs,
    exact at its final active set, hot-started from the previous tick's working set): the
    input box and ``s >= 0`` are its simple bounds, the state and polytope rows its general
    rows. OSQP (ADMM, eps 1e-5) stays as the safe path when DAQP reports a failure.
    """

    def __init__(self, full: MpcProblem, horizon: int, slack_weight: float) -> None:
        self.full = full
        self.problem = full.with_horizon(horizon)
        p = self.problem
        is_x = np.array([r.kind == "x" for r in p.rows], dtype=bool)
        self._is_x = is_x
        n_s = int(is_x.sum())
        n_u = p.n_u
        N = p.horizon
        Gx = p.G[is_x]
        P = sla.block_diag(p.H, slack_weight * np.eye(n_s))
        is_poly = np.array([r.kind == "up" for r in p.rows], dtype=bool)
        Gp = p.G[is_poly]
        rows = np.vstack([  # the general rows: Gx U - s <= gamma_x, Gp U <= gamma_p
            np.hstack([Gx, -np.eye(n_s)]),
            np.hstack([Gp, np.zeros((len(Gp), n_s))]),
        ])
        u_hi, u_lo = np.tile(p.u_max, N), np.tile(p.u_min, N)
        # DAQP: bounds [simple bounds of z (n_u + n_s); general rows (n_s + n_p)]
        self._upper = np.concatenate([u_hi, np.full(n_s, np.inf), np.zeros(n_s),
                                      p.g0[is_poly]])
        lower = np.concatenate([u_lo, np.zeros(n_s), np.full(n_s + len(Gp), -np.inf)])
        self._f = np.concatenate([np.zeros(n_u), np.full(n_s, slack_weight)])
        self._daqp = daqp.Model()
        flag, _ = self._daqp.setup(np.ascontiguousarray(P), self._f,
                                   np.ascontiguousarray(rows), self._upper, lower)
        if flag < 0:
            raise EpcError(f"intermediate QP: DAQP setup failed with exit flag {flag}")
        # OSQP's form of the same QP: every row general, s >= 0 and the input box as rows
        A = np.vstack([
            rows[:n_s],
            np.hstack([np.zeros((n_s, n_u)), np.eye(n_s)]),
            np.hstack([np.eye(n_u), np.zeros((n_u, n_s))]),
            rows[n_s:],
        ])
        self._osqp = OsqpSolver(P, A, polish=False, eps_abs=1e-5, eps_rel=1e-5, max_iter=2000)
        self._l = np.concatenate([np.full(n_s, -np.inf), np.zeros(n_s), u_lo,
                                  np.full(len(Gp), -np.inf)])
        self._u = np.concatenate([np.zeros(n_s), np.full(n_s, np.inf), u_hi, p.g0[is_poly]])
        self._n_s = n_s
        self.daqp_failures = 0  # solves DAQP could not finish (OSQP answered instead)

    def solve(self, theta_full: FloatArray) -> FloatArray | None:
        """The first input (nu,) of the intermediate QP at the full problem's ``theta_full``
        (clipped into the input box), or None when neither solver has an answer."""
        p, f = self.problem, self.full
        nx, nu, N, Nf = p.nx, p.nu, p.horizon, f.horizon
        # the first N stages of the full problem's references and nominal inputs
        theta = np.concatenate([
            theta_full[:nx],
            theta_full[nx : nx + N * nx],
            theta_full[nx + Nf * nx : f.i_up],
            theta_full[f.i_up : f.i_up + N * nu],
        ])
        h, gamma = p.vectors(theta)
        n_u, n_s = p.n_u, self._n_s
        gamma_x = gamma[self._is_x]
        self._f[:n_u] = h
        self._upper[n_u + n_s : n_u + 2 * n_s] = gamma_x
        u0 = self._solve_daqp(nu)
        if u0 is None:
            self.daqp_failures += 1
            u0 = self._solve_osqp(gamma_x, nu)
        if u0 is None or not np.all(np.isfinite(u0)):
            return None
        return p.clip_input(u0)

    def _solve_daqp(self, nu: int) -> FloatArray | None:
        try:
            if self._daqp.update(f=self._f, bupper=self._upper) < 0:
                return None
            z, _, flag, _ = self._daqp.solve()
        except (ValueError, RuntimeError) as exc:
            logger.debug("intermediate QP (DAQP) raised %s", exc)
            return None
        if flag < 1:
            logger.debug("intermediate QP (DAQP) exit flag %d", flag)
            return None
        return np.array(z[:nu], dtype=np.float64)

    def _solve_osqp(self, gamma_x: FloatArray, nu: int) -> FloatArray | None:
        """The same QP by OSQP: the linear cost is DAQP's (``_f``, set for this tick), the
        state rows' bounds ``gamma_x``."""
        self._u[: self._n_s] = gamma_x
        try:
            res = self._osqp.solve(self._f, self._u, self._l)
        except (ValueError, RuntimeError) as exc:
            logger.debug("intermediate QP (OSQP) raised %s", exc)
            return None
        if res.status not in (QpStatus.SOLVED, QpStatus.INACCURATE, QpStatus.MAX_ITER):
            return None
        return np.array(res.x[:nu], dtype=np.float64)


def budgeted_controller(
    problem: MpcProblem, library_size: int, query_budget_us: float, learn_on_miss: bool
) -> ExperienceController:
    """EPC over ``problem`` with a library of ``library_size`` controllers whose queries
    check no more candidates than fit in ``query_budget_us`` of the worst-case model."""
    epc = ExperienceController(problem, max_size=library_size, learn_on_miss=learn_on_miss)
    epc.max_checks = epc.checks_within(query_budget_us)
    return epc
