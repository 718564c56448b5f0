"""The condensed QP against its stage-wise definition, the signature and the OSQP wrapper."""

from __future__ import annotations

import math

import numpy as np
import pytest

from epc_offboard.control.models import position_model
from epc_offboard.control.qp import MpcProblem, OsqpSolver, ProblemError, QpStatus
from tests.mpc_cases import exact_solution, position_problem


def stage_cost(p: MpcProblem, x0, refs, c, u_p, U):
    """Thesis 3.1.2 cost by simulating the model stage by stage."""
    x = np.array(x0, dtype=float)
    total = 0.0
    xs = []
    for k in range(p.horizon):
        u = U[k * p.nu : (k + 1) * p.nu]
        x = p.model.A @ x + p.model.B @ u + c
        xs.append(x)
        e = x - refs[k]
        total += 0.5 * e @ p.Q @ e + 0.5 * (u - u_p) @ p.R @ (u - u_p)
    return total, np.array(xs)


def test_condensed_cost_and_constraints_match_the_stagewise_problem():
    rng = np.random.default_rng(1)
    p = position_problem(6)
    x0 = rng.normal(size=6)
    refs = rng.normal(size=(6, 6))
    pert = rng.normal(size=6) * 0.01
    u_p = p.model.cancelling_input(pert)
    theta = p.theta(x0, refs, perturbation=pert)
    c = p.model.c + pert
    U1, U2 = rng.normal(size=p.n_u), rng.normal(size=p.n_u)
    j1, xs1 = stage_cost(p, x0, refs, c, u_p, U1)
    j2, _ = stage_cost(p, x0, refs, c, u_p, U2)
    # equal up to the constant dropped by condensing
    assert p.cost(theta, U1) - p.cost(theta, U2) == pytest.approx(j1 - j2, rel=1e-10)
    assert np.allclose(p.predict(theta, U1), xs1)
    _, gamma = p.vectors(theta)
    slack = gamma - p.G @ U1
    for row, s in zip(p.rows, slack, strict=True):
        if row.kind == "x":
            v = xs1[row.stage - 1, row.index]
            bound = (p.x_max if row.upper else p.x_min)[row.index]
        else:
            v = U1[row.stage * p.nu + row.index]
            bound = (p.u_max if row.upper else p.u_min)[row.index]
        assert s == pytest.approx(bound - v if row.upper else v - bound, abs=1e-10)


def test_infinite_bounds_drop_rows():
    p = position_problem(5)
    # velocity: 3 upper + 3 lower per stage; inputs: 3 upper + 3 lower per stage
    assert p.n_con == 5 * 6 + 5 * 6
    assert position_problem(5, constrained=False).n_con == 0


def test_signature_covers_the_layout():
    base = position_problem(6).signature()
    assert base == position_problem(6).signature()
    assert base != position_problem(7).signature()
    assert base != position_problem(6, dt_s=0.05).signature()
    assert base != position_problem(6, constrained=False).signature()
    p = position_problem(6)
    assert base != MpcProblem(p.model, horizon=6, Q=p.Q * 2, R=p.R, x_min=p.x_min,
                              x_max=p.x_max, u_min=p.u_min, u_max=p.u_max).signature()
    # bound values are not layout: a stored set stays a candidate, the KKT check decides
    assert base == MpcProblem(p.model, horizon=6, Q=p.Q, R=p.R, x_min=p.x_min * 2,
                              x_max=p.x_max * 2, u_min=p.u_min, u_max=p.u_max).signature()


@pytest.mark.parametrize(
    ("kw", "msg"),
    [
        ({"Q": [-1, 1, 1, 1, 1, 1]}, "Q must be positive semidefinite"),
        ({"R": [0, 1, 1]}, "R must be positive definite"),
        ({"R": [1, 1]}, "R must be"),
        ({"u_min": [1, 1, 1], "u_max": [0, 0, 0]}, "u_min must be <= u_max"),
        ({"x_max": [math.nan] * 6}, "NaN"),
        ({"horizon": 0}, "horizon"),
    ],
)
def test_ill_posed_problems_are_rejected(kw, msg):
    args = {"horizon": 4, "Q": [1] * 6, "R": [1] * 3} | kw
    with pytest.raises(ProblemError, match=msg):
        MpcProblem(position_model(0.1), **args)


def test_theta_rejects_wrong_shapes():
    p = position_problem(4)
    with pytest.raises(ProblemError, match="refs"):
        p.theta(np.zeros(6), np.zeros((3, 6)))


def test_osqp_matches_the_exact_solution_and_is_quiet(capfd):
    p = position_problem(10)
    solver = OsqpSolver(p.H, p.G)
    for target in ([6.0, -3.0, 2.0], [0.0, 0.0, 0.0], [-8.0, 1.0, 0.0]):
        theta = p.theta(np.zeros(6), np.tile([*target, 0, 0, 0], (10, 1)))
        h, gamma = p.vectors(theta)
        res = solver.solve(h, gamma)
        assert res.status is QpStatus.SOLVED
        assert res.ok
        assert np.allclose(res.x, exact_solution(p, theta), atol=1e-6)
    out, err = capfd.readouterr()
    assert out == ""
    assert err == ""


def test_osqp_reports_infeasible_as_a_typed_status():
    p = position_problem(4)
    # flying at 10 m/s with |v| <= 2 and |a| <= 3: no input gets v back in bounds in time
    theta = p.theta(np.array([0, 0, 0, 10.0, 0, 0]), np.zeros((4, 6)))
    res = OsqpSolver(p.H, p.G).solve(*p.vectors(theta))
    assert res.status is QpStatus.INFEASIBLE
    assert not res.ok


def test_per_stage_nominal_inputs_match_the_stagewise_cost():
    # thesis 3.1.2 stacks u_p,0..u_p,N-1: a trajectory's feedforward differs per stage
    rng = np.random.default_rng(3)
    p = position_problem(5)
    x0, refs = rng.normal(size=6), rng.normal(size=(5, 6))
    U_p = rng.normal(size=(5, 3))
    theta = p.theta(x0, refs, U_p)
    assert np.array_equal(p.u_p_stages(theta), U_p)
    assert np.array_equal(p.u_p(theta), U_p[0])
    U1, U2 = rng.normal(size=p.n_u), rng.normal(size=p.n_u)

    def cost(U):
        x, total = x0.copy(), 0.0
        for k in range(5):
            u = U[3 * k : 3 * k + 3]
            x = p.model.A @ x + p.model.B @ u + p.model.c
            e = x - refs[k]
            total += 0.5 * e @ p.Q @ e + 0.5 * (u - U_p[k]) @ p.R @ (u - U_p[k])
        return total

    assert p.cost(theta, U1) - p.cost(theta, U2) == pytest.approx(cost(U1) - cost(U2), rel=1e-10)
    # a single u_p is every stage's
    th1 = p.theta(x0, refs, U_p[2])
    assert np.array_equal(p.u_p_stages(th1), np.tile(U_p[2], (5, 1)))
    with pytest.raises(ProblemError, match="u_p must have shape"):
        p.theta(x0, refs, np.zeros((4, 3)))
