"""The active-set map: one stored controller as one affine map of the parameters, and the
per-problem geometry every map shares (thesis 3.1.2, eqs. 3.5-3.8).

A controller is an active set ``a`` of the condensed QP (:mod:`~epc_offboard.control.qp`).
For a fixed model its KKT system (thesis 3.5-3.8)::

    [H    Ga'] [U  ]   [-F theta        ]
    [Ga   0  ] [lam] = [g0_a + S_a theta]

is solved once, symbolically in ``theta``, into ONE stacked affine map ``w = M [theta; 1]``
whose rows are: the active multipliers, every finite bound of the inputs and predicted states
as a shifted slack, and the first input. Applying and checking a stored controller is then
one mat-vec with ``0 <= w <= width`` tests (:mod:`epc_offboard.control.kernels`, compiled by
numba, with an early exit on the first failed row). Checking every bound row (active ones
included, whose slack is zero by construction) is the thesis's "every inactive constraint
holds" without gathering rows.

:class:`MapBuilder` builds maps for one problem (the geometry factored once) and judges an
active set received from elsewhere (a prior, the fleet) against the problem's layout.
"""

from __future__ import annotations

import numpy as np
import scipy.linalg as sla

from epc_offboard.common.errors import EpcError
from epc_offboard.common.frames import FloatArray
from epc_offboard.control.kernels import apply_map
from epc_offboard.control.library_types import EntryError, LibraryEntry, parse_entry
from epc_offboard.control.qp import MpcProblem

# Cholesky pivots of Ga H^-1 Ga' below this fraction of the largest mean cond > ~1e12:
# the rows are treated as linearly dependent.
_DEPENDENCE_RTOL = 1e-6
# Worst-case cost of one KKT check in the compiled scan, per multiply-add of its map (a
# candidate refused only at its last row): measured 0.13-0.21 ns on the 2-core development
# machine under load (`epc-offboard bench --service` prints the scan's cost); a query budget
# in us is turned into a number of candidates with it, so the bound holds in the worst case.
CHECK_NS_PER_MAC = 0.2


class DependentActiveSetError(EpcError, ValueError):
    """The active set's constraint rows are linearly dependent (no unique multipliers)."""


class ActiveSetMap:
    """The cached affine map of one active set, checked and applied by one mat-vec.

    With ``theta_aug = [theta; 1]``, ``w = M theta_aug[cols]`` has rows:

    * the active multipliers plus ``tol`` (must be >= 0);
    * one row per finite-bounded component of ``[U; X]``, shifted (and, for rows bounded
      only above, negated) so that its bounds widened by ``tol`` become ``0 <= w <= width``;
    * ``u_0`` (nu), the first input, as is.

    The first ``n_check`` rows are the KKT check (thesis 3.5-3.8: multipliers >= -tol and every
    bound within tol; an active row's slack is zero by construction, so checking all rows is
    checking the inactive ones). :func:`epc_offboard.control.kernels.apply_map` evaluates it.

    ``M`` holds only the columns ``cols`` of θ a map can depend on (the problem's
    :attr:`ProblemGeometry.cols`): with ``q_acc`` 0 the references' accelerations are not
    weighed, and their 60 columns were zeros that every check read (a map is read whole at
    each hit: 520 -> 400 kB, cold in real time, issue 21). The map is the same; only the
    rounding of the check's sum changes with its terms, far inside ``tol``.
    """

    __slots__ = ("M", "U", "active", "cols", "lam", "n_check", "width")

    def __init__(self, problem: MpcProblem, active: tuple[int, ...], geom: ProblemGeometry,
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
        full = np.vstack([lam_chk, chk, U_aug[: problem.nu]])
        if full[:, geom.unused].any():  # (structurally zero: see ProblemGeometry.cols)
            raise EpcError(f"active set {active}: a map depends on a parameter its problem "
                           "does not weigh")  # fmt: skip
        self.M = np.ascontiguousarray(full[:, geom.cols])
        self.cols = geom.cols
        self.width = np.concatenate([np.full(len(active), np.inf), geom.chk_width])
        self.n_check = len(self.width)
        self.U = U_aug
        self.lam = L_aug
        self.active = active

    def apply(self, theta_aug: FloatArray, u_out: FloatArray, u_min: FloatArray,
              u_max: FloatArray) -> bool:
        """KKT-check at ``theta_aug``; if it passes write the clipped first input to
        ``u_out`` and return True."""
        return self.check(theta_aug[self.cols], u_out, u_min, u_max)

    def check(self, theta_cols: FloatArray, u_out: FloatArray, u_min: FloatArray,
              u_max: FloatArray) -> bool:
        """:meth:`apply` at ``theta_cols``, the columns :attr:`cols` of ``theta_aug``
        (:meth:`MapBuilder.compact`)."""
        return apply_map(self.M, self.width, theta_cols, self.n_check, u_out, u_min, u_max)


class ProblemGeometry:
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
        # bounded X rows as affine maps of theta_aug (through x0 and c~) and of U; then the
        # lead rows u_k,i - x_k,j (x_0 = theta's x0, x_k a prediction), bounded by +-b_i
        c0 = nx + N * nx
        lead = [(k, i, int(problem.lead_state[i])) for k in range(problem.lead_stages)
                for i in range(problem.nu) if np.isfinite(problem.lead_max[i])]
        xt = np.zeros((len(rows) + len(lead), problem.n_theta + 1))
        xt[: len(rows), :nx] = problem.Phi[rows]
        xt[: len(rows), c0 : c0 + nx] = problem.Psi[rows]
        xu = np.zeros((len(rows) + len(lead), problem.n_u))
        xu[: len(rows)] = problem.Bbar[rows]
        for n, (k, i, j) in enumerate(lead, start=len(rows)):
            xu[n, k * problem.nu + i] = 1.0
            if k == 0:
                xt[n, j] = -1.0
            else:
                r = (k - 1) * nx + j
                xt[n, :nx] = -problem.Phi[r]
                xt[n, c0 : c0 + nx] = -problem.Psi[r]
                xu[n] -= problem.Bbar[r]
        self.xb_aug = xt
        self.xb_bbar = xu
        # the columns of [theta; 1] a map can depend on: through F and S (the multipliers,
        # U) and the bounded states' rows; the constant always. The others (the references
        # an unweighed state is held to) are zero in every map, and left out of M
        used = (problem.F.any(axis=0) | problem.S.any(axis=0)) | xt[:, :-1].any(axis=0)
        self.cols = np.append(np.flatnonzero(used), problem.n_theta).astype(np.intp)
        self.unused = np.flatnonzero(~used).astype(np.intp)
        lead_max = np.array([problem.lead_max[i] for _, i, _ in lead])
        # the input polytope's rows per stage, P u_k <= p: bounded above only
        self.poly = np.kron(np.eye(N), problem.u_poly_P)
        self._poly_stage = np.ascontiguousarray(problem.u_poly_P)
        n_poly = self.poly.shape[0]
        lo = np.concatenate([np.tile(problem.u_min, N), np.tile(problem.x_min[bounded], N),
                             -lead_max, np.full(n_poly, -np.inf)])
        hi = np.concatenate([np.tile(problem.u_max, N), np.tile(problem.x_max[bounded], N),
                             lead_max, np.tile(problem.u_poly_p, N)])
        lo_f, hi_f = np.isfinite(lo), np.isfinite(hi)
        self.chk_rows = np.flatnonzero(lo_f | hi_f)
        lo, hi, lo_f = lo[self.chk_rows], hi[self.chk_rows], lo_f[self.chk_rows]
        # w = v - (lo - tol) in [0, hi - lo + 2 tol]; rows bounded only above: w = hi + tol - v
        self.chk_sign = np.where(lo_f, 1.0, -1.0)
        self.chk_offset = np.where(lo_f, -(lo - tol), hi + tol)
        with np.errstate(invalid="ignore"):
            self.chk_width = np.where(lo_f, hi - lo + 2.0 * tol, np.inf)


class MapBuilder:
    """Builds the maps of one problem (its geometry factored once) with the KKT check's
    tolerance ``tol``, and judges active sets against the problem's constraint layout."""

    def __init__(self, problem: MpcProblem, tol: float) -> None:
        self.problem = problem
        self.tol = tol
        self.geom = ProblemGeometry(problem, tol)

    def build(self, active: tuple[int, ...]) -> ActiveSetMap:
        """The map of ``active`` (DependentActiveSetError when its rows are dependent)."""
        return ActiveSetMap(self.problem, active, self.geom, self.tol)

    def fits(self, amap: ActiveSetMap) -> bool:
        """Whether ``amap`` has this problem's layout (a map built elsewhere, e.g. by the
        miss worker, for a problem of another shape does not)."""
        p = self.problem
        n_check = len(amap.active) + len(self.geom.chk_width)
        return (len(amap.width) == n_check
                and amap.M.shape == (n_check + p.nu, len(self.geom.cols))
                and np.array_equal(amap.cols, self.geom.cols))  # fmt: skip

    def compact(self, theta_aug: FloatArray, out: FloatArray | None = None) -> FloatArray:
        """The columns of ``theta_aug`` the maps read (:attr:`ProblemGeometry.cols`)."""
        return theta_aug.take(self.geom.cols, out=out)

    def check_entry(self, n: int, e: LibraryEntry) -> LibraryEntry:
        """Everything about an entry short of its factorisation (ValueError names it): the
        entry as parsed, its active set a tuple in range with at most N nu rows."""
        p = self.problem
        try:
            return parse_entry(
                e.active_set, e.importance, e.uses, e.origin, n_con=p.n_con, max_rows=p.n_u
            )
        except EntryError as exc:
            raise ValueError(f"entry {n}: {exc}") from exc

    def validated(self, n: int, e: LibraryEntry) -> ActiveSetMap:
        """The map of entry number ``n`` once :meth:`check_entry` passes (ValueError names
        the entry when its rows are dependent)."""
        entry = self.check_entry(n, e)
        try:
            return self.build(entry.active_set)
        except DependentActiveSetError as exc:
            raise ValueError(f"entry {n}: active set rows are linearly dependent") from exc

    def check_cost_us(self) -> float:
        """Worst-case cost of checking one candidate: the largest map (every input row
        active) evaluated to its last row, at :data:`CHECK_NS_PER_MAC`."""
        p = self.problem
        rows = p.n_u + len(self.geom.chk_rows) + p.nu
        return rows * len(self.geom.cols) * CHECK_NS_PER_MAC * 1e-3
