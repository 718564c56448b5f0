"""Shared problems and the exact oracle for the EPC-core tests."""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from epc_offboard.control.models import position_model
from epc_offboard.control.qp import MpcProblem

V_MAX = 2.0
A_MAX = 3.0


def position_problem(horizon: int = 8, *, constrained: bool = True, dt_s: float = 0.1):
    inf = math.inf
    kw: dict[str, Any] = {}
    if constrained:
        kw = {
            "x_min": [-inf, -inf, -inf, -V_MAX, -V_MAX, -V_MAX],
            "x_max": [inf, inf, inf, V_MAX, V_MAX, V_MAX],
            "u_min": [-A_MAX] * 3,
            "u_max": [A_MAX] * 3,
        }
    return MpcProblem(
        position_model(dt_s), horizon=horizon, Q=[10, 10, 10, 1, 1, 1], R=[0.2] * 3, **kw
    )


def exact_solution(problem: MpcProblem, theta: np.ndarray) -> np.ndarray:
    """The QP's optimum by DAQP (an exact dual active-set solver), stacked inputs U."""
    import daqp

    h, gamma = problem.vectors(theta)
    if problem.n_con == 0:
        return np.linalg.solve(problem.H, -h)
    U, _, flag, _ = daqp.solve(problem.H, h, problem.G, gamma, primal_tol=1e-10)
    assert flag >= 1, f"oracle failed with exit flag {flag}"
    return np.asarray(U)


def hover_refs(problem: MpcProblem, target_ned_m) -> np.ndarray:
    refs = np.zeros((problem.horizon, problem.nx))
    refs[:, :3] = target_ned_m
    return refs
