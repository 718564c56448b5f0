"""EPC's miss path (thesis 3.1.3): the full QP and the recovery of its active set, and the
intermediate QP flown meanwhile.

:class:`Learner` solves the full QP by OSQP (polished, so the active set is exact), recovers
the active set from its duals, rebuilds the exact solution from the KKT system and verifies
it by the same KKT check a stored controller passes (:class:`~epc_offboard.control.epc.maps.
ActiveSetMap`). It is all the miss worker (:mod:`epc_offboard.service.miss_solver`) needs
besides the map builder. :class:`IntermediateQp` is the short-horizon QP with slack on the
state bounds: always feasible, applied on the loop at a miss.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Sequence

import daqp
import numpy as np
import scipy.linalg as sla

from epc_offboard.common.errors import EpcError
from epc_offboard.common.frames import FloatArray
from epc_offboard.control.epc.maps import ActiveSetMap, MapBuilder
from epc_offboard.control.qp import MpcProblem, OsqpSolver, QpStatus

logger = logging.getLogger(__name__)

# the full solve's OSQP tolerances; polishing makes the active set exact, these only need to
# make OSQP's duals point at it
_EPS = 1e-8
_MAX_ITER = 10000


class Learner:
    """The full QP of ``builder``'s problem, solved and turned into a verified map."""

    def __init__(self, builder: MapBuilder) -> None:
        self.builder = builder
        self.problem = problem = builder.problem
        self._solver = OsqpSolver(problem.H, problem.G, polish=True, eps_abs=_EPS, eps_rel=_EPS,
                                  max_iter=_MAX_ITER)

    def solve(self, theta_aug: FloatArray, u_out: FloatArray) -> ActiveSetMap | None:
        """Solve the full QP at ``theta_aug`` ([theta; 1]), recover and verify its active set.

        Returns its map, with the exact first input written to ``u_out``, or None when the
        QP is infeasible or no active set passes the check.
        """
        h, gamma = self.problem.vectors(theta_aug[:-1])
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
        return amap

    def _recover_active_set(
        self, theta_aug: FloatArray, y: FloatArray, gamma: FloatArray, u_out: FloatArray
    ) -> ActiveSetMap | None:
        """Rebuild the exact solution from OSQP's guess of the active set.

        Start from rows with a clearly positive dual; then, until the KKT check passes:
        drop linearly dependent rows (keeping the larger duals), drop the most negative
        multiplier, add the most violated inactive row (tighten and retry).
        """
        p = self.problem
        tol = self.builder.tol
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
            amap = self.builder.build(aset)
            if amap.apply(theta_aug, u_out, p.u_min, p.u_max):
                return amap
            U = amap.U @ theta_aug
            lam = amap.lam @ theta_aug
            slack = gamma - p.G @ U
            if len(aset):
                slack[np.asarray(aset, dtype=np.intp)] = np.inf
            active = set(aset)
            if len(aset) and lam.min() < -tol:
                active.discard(aset[int(np.argmin(lam))])
            if p.n_con and slack.min() < -tol:
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


class IntermediateQp:
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
        # soft: the state rows and the lead rows (both depend on x0, which may lie where
        # no input meets them); hard: the input box and polytope, which inputs always meet
        is_x = np.array([r.kind in ("x", "lead") for r in p.rows], dtype=bool)
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
