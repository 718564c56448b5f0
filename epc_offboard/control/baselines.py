"""The baselines EPC is compared against, behind the same ``step`` interface.

* :class:`PdController` — thesis appendix A.1, ``u = -Kp e - Kd e'`` on a
  position/velocity state, plus the reference's acceleration as feedforward.
* :class:`MpcController` — the same condensed QP as EPC solved every tick by OSQP
  (warm-started), what a user would otherwise run.
"""

from __future__ import annotations

import numpy as np
import numpy.typing as npt

from epc_offboard.common.frames import FloatArray
from epc_offboard.control.decision import Controller, Decision, elapsed_us
from epc_offboard.control.qp import MpcProblem, OsqpSolver, QpStatus


class PdController(Controller):
    """PD on ``x = [p (n), v (n), ...]`` with acceleration input ``u`` (n,).

    Further states (the lagged acceleration of the position model) are not fed back.

    ``u = a_ff + kp (r_p - p) + kd (r_v - v) + u_p``, clipped to ``[u_min, u_max]``; the
    error is taken against ``refs[0]`` (the reference one prediction step ahead, the nearest
    the horizon holds) and ``a_ff = (r_v[1] - r_v[0]) / dt_s``. With a perturbation p^ (the
    state increment per step) and no ``u_p``, ``u_p = -pinv(B) p^`` as for EPC. PD has no
    library: every decision's source is "solved" (its law was evaluated).
    """

    def __init__(
        self,
        problem: MpcProblem,
        kp: npt.ArrayLike,
        kd: npt.ArrayLike,
    ) -> None:
        nx, nu = problem.nx, problem.nu
        if nx < 2 * nu:
            raise ValueError(f"PD needs x = [p (n), v (n), ...] with n = nu; got nx={nx}, nu={nu}")
        dt_s = problem.model.dt_s
        if dt_s is None:
            raise ValueError("PD needs the model's prediction step dt_s for its feedforward")
        self.problem = problem
        self.dt_s = dt_s
        self.kp = np.broadcast_to(np.asarray(kp, dtype=np.float64), (nu,)).copy()
        self.kd = np.broadcast_to(np.asarray(kd, dtype=np.float64), (nu,)).copy()

    def decide(self, theta: FloatArray, t0: float) -> Decision:
        p = self.problem
        n = p.nu
        x = theta[: p.nx]
        r = theta[p.nx : p.nx + p.horizon * p.nx].reshape(p.horizon, p.nx)
        v = slice(n, 2 * n)
        a_ff = (r[1, v] - r[0, v]) / self.dt_s if p.horizon > 1 else np.zeros(n)
        u = a_ff + self.kp * (r[0, :n] - x[:n]) + self.kd * (r[0, v] - x[v]) + p.u_p(theta)
        return Decision(p.clip_input(u), "solved", elapsed_us(t0))


class MpcController(Controller):
    """Linear MPC solved every tick with OSQP (set up once, warm-started, polished).

    Source "solved" on success; a failed solve degrades to the bounded hover input
    ``clip(u_p)`` with source "fallback".
    """

    def __init__(self, problem: MpcProblem, *, polish: bool = True,
                 eps_abs: float = 1e-8, eps_rel: float = 1e-8) -> None:
        self.problem = problem
        self._solver = OsqpSolver(problem.H, problem.G, polish=polish, eps_abs=eps_abs,
                                  eps_rel=eps_rel)
        self._theta = np.zeros(problem.n_theta)
        self.failures = 0

    def theta_buffer(self) -> FloatArray:
        return self._theta

    def decide(self, theta: FloatArray, t0: float) -> Decision:
        p = self.problem
        h, gamma = p.vectors(theta)
        res = self._solver.solve(h, gamma)
        if res.status in (QpStatus.SOLVED, QpStatus.INACCURATE):
            u = p.clip_input(res.x[: p.nu])
            return Decision(u, "solved", elapsed_us(t0), p.predict(theta, res.x))
        self.failures += 1
        return Decision(p.hover_input(theta), "fallback", elapsed_us(t0))
