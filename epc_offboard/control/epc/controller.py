"""Experience-driven Predictive Control, the hot path (thesis algorithm 1): query the library
by the KKT check; on a miss try the fleet's candidates, then learn (or queue θ for a worker)
and apply the intermediate controller meanwhile; a bounded hover when nothing answers.

The parts, each in its module as the thesis explains them: the active-set map
(:mod:`~epc_offboard.control.epc.maps`), the library (:mod:`~epc_offboard.control.epc.
library`), the fleet's candidates (:mod:`~epc_offboard.control.epc.candidates`), the full QP
and the intermediate QP (:mod:`~epc_offboard.control.epc.learner`); what the controller
trades with the store, the fleet and the miss worker is :mod:`~epc_offboard.control.epc.
exchange`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np
import numpy.typing as npt

from epc_offboard.common import jit
from epc_offboard.common.frames import FloatArray
from epc_offboard.control.decision import Controller, Decision, elapsed_us
from epc_offboard.control.epc.candidates import CandidatePool
from epc_offboard.control.epc.exchange import LibraryExchange
from epc_offboard.control.epc.learner import IntermediateQp, Learner
from epc_offboard.control.epc.library import Entry, Library
from epc_offboard.control.epc.maps import MapBuilder
from epc_offboard.control.kernels import stack_theta, theta_check
from epc_offboard.control.library_types import LibraryEntry
from epc_offboard.control.models import LinearModel
from epc_offboard.control.qp import MpcProblem

_F64 = np.dtype(np.float64)  # (an array's dtype is this object: the fused call's check)


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


class ExperienceController(LibraryExchange, Controller):
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
        self.library = Library(max_size, max_checks)
        if not (tol > 0.0 and math.isfinite(tol)):
            raise ValueError(f"tol must be a positive finite number, got {tol}")
        if intermediate_horizon < 1:
            raise ValueError(f"intermediate_horizon must be >= 1, got {intermediate_horizon}")
        self.tol = tol
        self.learn_on_miss = learn_on_miss
        self.with_prediction = with_prediction
        self._int_horizon = min(intermediate_horizon, problem.horizon)
        self._slack_weight = slack_weight
        self._max_pending = max_pending
        self.pending: list[FloatArray] = []
        self._new: list[LibraryEntry] = []
        self._hits = self._misses = self._solves = 0
        self._intermediate = self._fallback = self._learn_failures = 0
        self._received_shared = 0
        self.candidates = CandidatePool(max_candidates, max_candidates_per_origin,
                                        max_candidate_backlog, max_candidate_backlog_per_origin)
        self.model_epoch = 0  # counts changes of A or B: maps built before are stale
        # (root, promotions) of the last refocus
        self._focus_state: tuple[tuple[int, ...] | None, int] | None = None
        self._setup(problem)

    @property
    def max_size(self) -> int:
        return self.library.max_size

    @property
    def max_checks(self) -> int | None:
        """The most candidates one query checks (None: the whole library)."""
        return self.library.max_checks

    @max_checks.setter
    def max_checks(self, value: int | None) -> None:
        self.library.max_checks = value

    @property
    def last_query_checks(self) -> int:
        return self.library.last_query_checks

    # -- model ------------------------------------------------------------------------------

    def _setup(self, problem: MpcProblem) -> None:
        self.problem = problem
        self.builder = MapBuilder(problem, self.tol)
        self.learner = Learner(self.builder)
        # theta_aug = [theta; 1]: the maps carry their constant as a last column
        self._theta_aug = np.zeros(problem.n_theta + 1)
        self._theta_aug[-1] = 1.0
        self._theta_cols = self.builder.compact(self._theta_aug)  # what the maps read of it
        self._cols_stacked = False  # theta_compiled wrote _theta_cols for this tick
        # theta_compiled's check of the last controller (the tick's u, its answer: None,
        # not made) for decide, and the fused kernel's entry point for this problem's sizes
        self._u_checked: FloatArray | None = None
        self._last_hit: bool | None = None
        self._theta_check: Any = None
        if theta_check is not None:
            p = problem
            self._no_map = (np.zeros((1, 1)), np.zeros(1))
            self._theta_check = jit.entry_point(
                theta_check, np.zeros(p.nx), np.zeros((p.horizon, p.nx)),
                np.zeros((p.horizon, p.nu)), p.model.c, np.zeros(p.nx), self._theta_aug,
                self.builder.geom.cols, self._theta_cols, *self._no_map, 0, np.empty(p.nu),
                p.u_min, p.u_max)  # fmt: skip
        self._intermediate_qp = IntermediateQp(problem, self._int_horizon, self._slack_weight)

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
        self.library.rebuild(self.builder.build)

    # -- the loop ---------------------------------------------------------------------------

    def theta_buffer(self) -> FloatArray:
        return self._theta_aug[:-1]

    def theta_compiled(
        self,
        x0: npt.ArrayLike,
        refs: npt.ArrayLike,
        u_p: npt.ArrayLike | None,
        perturbation: npt.ArrayLike | None,
    ) -> FloatArray | None:
        """The position tick's arguments (arrays, a perturbation, a nominal input per stage)
        stacked into θ, and the maps' columns of it, in one compiled call."""
        if not (stack_theta is not None and type(u_p) is np.ndarray and u_p.ndim == 2
                and type(x0) is np.ndarray and type(refs) is np.ndarray
                and type(perturbation) is np.ndarray):  # fmt: skip
            return None
        fused = self._theta_check
        if (fused is not None and x0.dtype is _F64 and refs.dtype is _F64
                and u_p.dtype is _F64 and perturbation.dtype is _F64 and x0.ndim == 1
                and refs.ndim == 2 and perturbation.ndim == 1 and x0.flags.c_contiguous
                and refs.flags.c_contiguous and u_p.flags.c_contiguous
                and perturbation.flags.c_contiguous):  # fmt: skip
            # the types its entry point was compiled for: θ and the last controller's
            # check (the query's first try) in one compiled call (issue 21)
            check = self.check_args()
            assert check is not None  # (made with the entry point)
            return self.checked(fused(x0, refs, u_p, check[0], perturbation, *check[1:]),
                                check)
        if not stack_theta(x0, refs, u_p, self.problem.model.c, perturbation,
                           self._theta_aug, self.builder.geom.cols, self._theta_cols):
            return None  # (arrays of another shape: problem.theta raises its error)
        self._cols_stacked = True
        return self._theta_aug[:-1]

    def check_args(self) -> tuple[Any, ...] | None:
        """What ``kernels.theta_check`` takes after x0, refs and u_p (the model's offset,
        then after the perturbation: [θ; 1], the maps' columns and their buffer, the last
        controller's map, its row count to check (-1: none), a new input buffer, the input
        bounds), for a compiled call that stacks θ and checks the last controller
        (``kernels.plan_step`` in the position tick); None: not compiled. Hand its answer
        to :meth:`checked`."""
        if self._theta_check is None:
            return None
        p = self.problem
        last = self.library.last
        amap = None if last is None else last.map
        M, width = self._no_map if amap is None else (amap.M, amap.width)
        return (p.model.c, self._theta_aug, self.builder.geom.cols, self._theta_cols, M,
                width, -1 if amap is None else amap.n_check, np.empty(p.nu), p.u_min,
                p.u_max)  # fmt: skip

    def checked(self, hit: int, check: tuple[Any, ...]) -> FloatArray | None:
        """θ as a compiled call with :meth:`check_args`' ``check`` stacked it, its check's
        answer ``hit`` kept for :meth:`decide` (``kernels.theta_check``'s: 1 passed, its
        input in the buffer; 0 failed or not asked; -1 shapes that do not fit, None: θ not
        stacked, ``problem.theta`` raises its error)."""
        if hit < 0:
            return None
        if check[6] >= 0:  # (a last controller was checked)
            self._u_checked, self._last_hit = check[7], hit == 1
        self._cols_stacked = True
        return self._theta_aug[:-1]

    def decide(self, theta: FloatArray, t0: float) -> Decision:
        """Algorithm 1's body at θ (written into ``_theta_aug`` by :meth:`step`; the maps'
        columns of it too when :meth:`theta_compiled` stacked it)."""
        th_aug = self._theta_aug
        p = self.problem
        self.library.tick += 1
        th_cols = self._theta_cols
        if not self._cols_stacked:
            th_aug.take(self.builder.geom.cols, out=th_cols)
        self._cols_stacked = False
        u, last_hit = self._u_checked, self._last_hit
        if u is None:
            u = np.empty(p.nu)
        else:
            self._u_checked = self._last_hit = None
        entry = self.library.query(th_cols, u, p.u_min, p.u_max, last_hit=last_hit)
        if entry is not None:
            return self._hit(entry, u, th_aug, t0)
        if len(self.candidates):
            # with learn_on_miss every candidate is built here; without, only the maps the
            # worker built for proven origins are checked (mat-vecs, no factorisation)
            entry = self._promote(th_aug, u, budget_s=None, build=self.learn_on_miss)
            if entry is not None:  # a fleet candidate, optimal here: exact, no solve
                return self._hit(entry, u, th_aug, t0)
        self._misses += 1
        if self.learn_on_miss:
            entry = self._learn(th_aug, u)
            if entry is not None:
                self.library.use(entry)
                return Decision(u, "solved", elapsed_us(t0), self._predict(entry, th_aug))
        elif len(self.pending) < self._max_pending:
            self.pending.append(theta.copy())
        return self._degraded(theta, t0)

    def _hit(self, entry: Entry, u: FloatArray, theta_aug: FloatArray, t0: float) -> Decision:
        self._hits += 1
        self.library.use(entry)
        x_pred = self._predict(entry, theta_aug) if self.with_prediction else None
        return Decision(u, "hit", elapsed_us(t0), x_pred)

    def _predict(self, entry: Entry, theta_aug: FloatArray) -> FloatArray:
        return self.problem.predict(theta_aug[:-1], entry.map.U @ theta_aug)

    def _degraded(self, theta: FloatArray, t0: float) -> Decision:
        """The miss's answer this tick: the intermediate QP, else a bounded hover."""
        u = self._intermediate_qp.solve(theta)
        if u is not None:
            self._intermediate += 1
            return Decision(u, "intermediate", elapsed_us(t0))
        self._fallback += 1
        return Decision(self.problem.hover_input(theta), "fallback", elapsed_us(t0))

    def _learn(self, theta_aug: FloatArray, u_out: FloatArray) -> Entry | None:
        """Solve the full QP, recover and verify its active set, add it (the exact first
        input written to ``u_out``); None when the QP is infeasible or no active set passes
        the check."""
        self._solves += 1
        amap = self.learner.solve(theta_aug, u_out)
        if amap is None:
            self._learn_failures += 1
            return None
        entry = self.library.get(amap.active)
        if entry is not None:
            return entry
        entry = self._add(amap, origin="solved")
        self._new.append(LibraryEntry(amap.active, entry.importance, entry.uses, "solved"))
        return entry

    @property
    def stats(self) -> EpcStats:
        return EpcStats(
            hits=self._hits,
            misses=self._misses,
            qp_solves=self._solves,
            size=len(self.library),
            intermediate=self._intermediate,
            fallback=self._fallback,
            learn_failures=self._learn_failures,
            received_shared=self._received_shared,
            candidates=len(self.candidates),
        )


def budgeted_controller(
    problem: MpcProblem, library_size: int, query_budget_us: float, learn_on_miss: bool
) -> ExperienceController:
    """EPC over ``problem`` with a library of ``library_size`` controllers whose queries
    check no more candidates than fit in ``query_budget_us`` of the worst-case model."""
    epc = ExperienceController(problem, max_size=library_size, learn_on_miss=learn_on_miss)
    epc.max_checks = epc.checks_within(query_budget_us)
    return epc
