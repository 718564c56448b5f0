"""EPC: oracles (LQR, exact QP solutions), the KKT check, library behaviour, import/export."""

from __future__ import annotations

import math
from typing import Any

import numpy as np
import pytest
from hypothesis import HealthCheck, example, given, settings
from hypothesis import strategies as st

import epc_offboard.control.epc.library as library_module
import epc_offboard.control.epc.maps as maps_module
from epc_offboard.control.epc import ExperienceController
from epc_offboard.control.kernels import apply_map_numpy
from epc_offboard.control.library_types import LibraryEntry
from epc_offboard.control.models import (
    LinearModel,
    attitude_model,
    position_model,
    position_model_lagged,
)
from epc_offboard.control.qp import MpcProblem
from tests.mpc_cases import A_MAX, V_MAX, exact_solution, hover_refs, position_problem

FAST = settings(max_examples=25, deadline=None,
                suppress_health_check=[HealthCheck.function_scoped_fixture])


def lqr_first_gain(A, B, Q, R, N):
    """Finite-horizon LQR for sum_k 1/2 x_{k+1}'Q x_{k+1} + 1/2 u_k'R u_k: u_0 = -K_0 x_0."""
    P = np.zeros_like(Q)
    K = None
    for _ in range(N):
        S = Q + P
        K = np.linalg.solve(R + B.T @ S @ B, B.T @ S @ A)
        P = A.T @ S @ (A - B @ K)
    return K


@FAST
@given(x0=st.lists(st.floats(-5, 5), min_size=6, max_size=6))
def test_unconstrained_epc_equals_finite_horizon_lqr(x0):
    p = position_problem(12, constrained=False)
    ctrl = ExperienceController(p)
    K = lqr_first_gain(p.model.A, p.model.B, p.Q, p.R, 12)
    d = ctrl.step(np.array(x0), np.zeros((12, 6)))
    assert d.source in ("hit", "solved")
    assert np.allclose(d.u, -K @ np.array(x0), atol=1e-9, rtol=0)


state = st.lists(st.floats(-3, 3), min_size=6, max_size=6).map(np.array)
target = st.lists(st.floats(-10, 10), min_size=3, max_size=3).map(np.array)
pert = st.lists(st.floats(-0.05, 0.05), min_size=6, max_size=6).map(np.array)


def feasible_state(x0):
    x = x0.copy()
    x[3:] = np.clip(x[3:], -0.8 * V_MAX, 0.8 * V_MAX)
    return x


@settings(max_examples=30, deadline=None)
@given(x0=state, tgt=target, p_hat=pert, shift=st.floats(-0.05, 0.05))
def test_library_hit_equals_a_fresh_exact_solve(x0, tgt, p_hat, shift):
    p = position_problem(8)
    ctrl = ExperienceController(p)
    x0 = feasible_state(x0)
    refs = hover_refs(p, tgt)
    first = ctrl.step(x0, refs, perturbation=p_hat)
    assert first.source == "solved"
    # the same data again and a nearby point: the stored controller, if it applies, is exact
    for x in (x0, x0 + shift):
        d = ctrl.step(x, refs, perturbation=p_hat)
        U = exact_solution(p, p.theta(x, refs, perturbation=p_hat))
        assert d.source in ("hit", "solved")
        assert np.allclose(d.u, np.clip(U[:3], -A_MAX, A_MAX), atol=1e-8, rtol=0)
    assert ctrl.stats.hits >= 1


@pytest.mark.parametrize("kernel", ["default", "numpy"])
def test_hits_are_exact_on_constrained_closed_loop(kernel, monkeypatch):
    if kernel == "numpy":
        monkeypatch.setattr(maps_module, "apply_map", apply_map_numpy)
    p = position_problem(10)
    ctrl = ExperienceController(p)
    x = np.zeros(6)
    constrained = 0
    for k in range(120):
        tgt = [8.0, -6.0, 3.0] if (k // 40) % 2 == 0 else [0.0, 0.0, 0.0]
        refs = hover_refs(p, tgt)
        d = ctrl.step(x, refs)
        theta = p.theta(x, refs)
        U = exact_solution(p, theta)
        assert np.allclose(d.u, U[:3], atol=1e-8, rtol=0)
        _, gamma = p.vectors(theta)
        constrained += bool(np.any(gamma - p.G @ U < 1e-9))
        x = p.model.step(x, d.u)
    assert ctrl.stats.hits > 30
    assert constrained > 30


def test_an_active_set_not_optimal_here_is_refused():
    p = position_problem(8)
    learner = ExperienceController(p)
    learner.step(np.zeros(6), hover_refs(p, [10.0, 0.0, 0.0]))  # saturating: inputs at bound
    (saturated,) = learner.export_library()
    assert saturated.active_set  # some constraints active
    ctrl = ExperienceController(p)
    assert ctrl.import_entries([saturated], "shared") == 1
    # at rest on the reference the unconstrained law is optimal: the stored set must fail
    d = ctrl.step(np.zeros(6), hover_refs(p, [0.0, 0.0, 0.0]))
    assert d.source == "solved"
    assert np.allclose(d.u, 0.0, atol=1e-12)
    assert ctrl.stats.hits == 0
    # and conversely the unconstrained set is refused where constraints bind
    empty = LibraryEntry(())
    ctrl2 = ExperienceController(p)
    ctrl2.import_entries([empty])
    d = ctrl2.step(np.zeros(6), hover_refs(p, [10.0, 0.0, 0.0]))
    assert d.source == "solved"
    assert ctrl2.stats.hits == 0
    assert d.u[0] == pytest.approx(A_MAX)


@settings(max_examples=40, deadline=None)
@given(x0=st.lists(st.floats(-20, 20), min_size=6, max_size=6).map(np.array), tgt=target,
       p_hat=pert)
def test_inputs_never_violate_bounds_and_predictions_respect_state_bounds(x0, tgt, p_hat):
    p = position_problem(6)
    ctrl = ExperienceController(p, with_prediction=True)
    refs = hover_refs(p, tgt)
    for _ in range(2):
        d = ctrl.step(x0, refs, perturbation=p_hat)
        assert np.all(d.u >= p.u_min)
        assert np.all(d.u <= p.u_max)
        if d.source in ("hit", "solved"):  # the full QP was feasible
            assert d.x_pred is not None
            assert np.all(np.abs(d.x_pred[:, 3:]) <= V_MAX + 1e-7)
        else:
            assert abs(x0[3:]).max() > V_MAX - 0.5  # only far outside the bounds


def test_infeasible_state_degrades_to_intermediate_then_learns_nothing():
    p = position_problem(6)
    ctrl = ExperienceController(p)
    d = ctrl.step(np.array([0, 0, 0, 10.0, 0, 0]), hover_refs(p, [0, 0, 0]))
    assert d.source == "intermediate"
    assert d.u[0] == pytest.approx(-A_MAX, abs=1e-3)  # braking as hard as allowed
    assert ctrl.stats.size == 0
    assert ctrl.stats.intermediate == 1


def sets_for(p, targets):
    """Distinct active sets learned at rest for the given targets."""
    out = []
    for tgt in targets:
        c = ExperienceController(p)
        c.step(np.zeros(6), hover_refs(p, tgt))
        out.extend(c.export_library())
    return out


def test_eviction_removes_the_least_recently_used():
    p = position_problem(6)
    ctrl = ExperienceController(p, max_size=2)
    points = [[0, 0, 0], [10, 0, 0], [0, -10, 0]]
    for tgt in points:
        assert ctrl.step(np.zeros(6), hover_refs(p, tgt)).source == "solved"
    lib = ctrl.export_library()
    assert len(lib) == 2
    assert ctrl.stats.size == 2
    first = sets_for(p, [points[0]])[0].active_set
    assert first not in [e.active_set for e in lib]
    # most important first: the last used leads
    assert lib[0].active_set == sets_for(p, [points[2]])[0].active_set
    # using the older one makes it most important, so the next add evicts the other
    ctrl.step(np.zeros(6), hover_refs(p, points[1]))
    ctrl.step(np.zeros(6), hover_refs(p, [0, 0, 10]))
    kept = [e.active_set for e in ctrl.export_library()]
    assert sets_for(p, [points[1]])[0].active_set in kept
    assert sets_for(p, [points[2]])[0].active_set not in kept


def test_query_order_is_last_then_successors_then_importance():
    p = position_problem(6)
    a, b, c = sets_for(p, [[0, 0, 0], [10, 0, 0], [0, -10, 0]])
    ctrl = ExperienceController(p)
    # entries most important first: c, b, a; a -> b seen 5 times
    ctrl.import_entries([LibraryEntry(c.active_set, 3.0), LibraryEntry(b.active_set, 2.0),
                         LibraryEntry(a.active_set, 1.0)], transitions={(2, 1): 5})
    assert ctrl.query_order() == [c.active_set, b.active_set, a.active_set]
    assert ctrl.step(np.zeros(6), hover_refs(p, [0, 0, 0])).source == "hit"  # uses a
    assert ctrl.query_order() == [a.active_set, b.active_set, c.active_set]
    trans = ctrl.export_transitions()
    lib = ctrl.export_library()
    assert lib[0].active_set == a.active_set
    assert lib[0].uses == 1
    ((i, j), n), = trans.items()
    assert (lib[i].active_set, lib[j].active_set, n) == (a.active_set, b.active_set, 5)


def test_import_rejects_malformed_entries_and_leaves_the_library_unchanged():
    p = position_problem(6)
    ctrl = ExperienceController(p, max_size=3)
    ctrl.step(np.zeros(6), hover_refs(p, [10, 0, 0]))
    before = ctrl.export_library()
    n = p.n_con
    # rows of an input's upper and lower bound together are linearly dependent
    up = next(i for i, r in enumerate(p.rows) if r.kind == "u" and r.upper)
    lo = next(i for i, r in enumerate(p.rows) if r.kind == "u" and not r.upper
              and r.stage == p.rows[up].stage and r.index == p.rows[up].index)
    bad_cases: list[tuple[list[LibraryEntry], dict[str, Any], str]] = [
        ([LibraryEntry((3, 1))], {}, "sorted and unique"),
        ([LibraryEntry((1, 1))], {}, "sorted and unique"),
        ([LibraryEntry((0, n))], {}, "out of range"),
        ([LibraryEntry((-1,))], {}, "out of range"),
        ([LibraryEntry((1.0,))], {}, "tuple of ints"),  # type: ignore[arg-type]
        ([LibraryEntry((up, lo))], {}, "linearly dependent"),
        ([LibraryEntry(()), LibraryEntry((0,), math.nan)], {}, "importance"),
        ([LibraryEntry(())] * 4, {}, "size limit"),
        ([LibraryEntry(())], {"signature": "nope"}, "signature"),
        ([LibraryEntry(())], {"transitions": {(0, 3): 1}}, "transition"),
    ]
    for entries, kw, msg in bad_cases:
        with pytest.raises(ValueError, match=msg):
            ctrl.import_entries(entries, "shared", **kw)
        assert ctrl.export_library() == before
    assert ctrl.import_entries([LibraryEntry(())], signature=p.signature()) == 1


def test_pop_new_entries_returns_each_solve_once():
    p = position_problem(6)
    ctrl = ExperienceController(p)
    ctrl.step(np.zeros(6), hover_refs(p, [10, 0, 0]))
    ctrl.step(np.zeros(6), hover_refs(p, [10, 0, 0]))  # hit, nothing new
    new = ctrl.pop_new_entries()
    assert len(new) == 1
    assert ctrl.pop_new_entries() == []
    imported = ExperienceController(p)
    imported.import_entries(new, "prior")
    assert imported.pop_new_entries() == []


def test_set_model_rebuilds_the_cache_and_keeps_the_library():
    p = position_problem(8)
    ctrl = ExperienceController(p)
    x0 = np.array([0, 0, 0, 1.0, 0, 0])
    for tgt in ([10.0, 0, 0], [0.0, 0, 0], [0.0, 5, 0]):
        ctrl.step(x0, hover_refs(p, tgt))
    ctrl.step(np.zeros(6), hover_refs(p, [0.1, 0, 0]))
    size = ctrl.stats.size
    ctrl.set_model(position_model(0.08))
    assert ctrl.stats.size == size
    # the unconstrained set stays optimal near rest under the new model: a hit, exact
    for x, tgt in ((np.zeros(6), [0.2, 0.0, 0.0]), (x0, [10.0, 0, 0]), (x0, [0.0, 5, 0])):
        refs = hover_refs(ctrl.problem, tgt)
        d = ctrl.step(x, refs)
        U = exact_solution(ctrl.problem, ctrl.problem.theta(x, refs))
        assert np.allclose(d.u, U[:3], atol=1e-8)
    assert ctrl.stats.hits >= 1


def test_perturbation_is_cancelled_by_default_u_p():
    p = position_problem(8, constrained=False)
    ctrl = ExperienceController(p)
    a_wind = np.array([0.4, -0.3, 0.1])
    d = ctrl.step(np.zeros(6), np.zeros((8, 6)), perturbation=p.model.B @ a_wind)
    assert np.allclose(d.u, -a_wind, atol=1e-10)


def test_deferred_learning_applies_intermediate_then_hits():
    p = position_problem(6)
    ctrl = ExperienceController(p, learn_on_miss=False)
    refs = hover_refs(p, [3, 0, 0])
    d = ctrl.step(np.zeros(6), refs)
    assert d.source == "intermediate"
    assert len(ctrl.pending) == 1
    assert ctrl.learn_theta(ctrl.pending.pop()) is not None
    assert ctrl.step(np.zeros(6), refs).source == "hit"
    assert ctrl.learn(np.zeros(6), refs) is not None  # already known: the same entry
    assert ctrl.stats.size == 1


def test_unknown_source_and_bad_arguments_are_rejected():
    p = position_problem(4)
    with pytest.raises(ValueError, match="max_size"):
        ExperienceController(p, max_size=0)
    ctrl = ExperienceController(p)
    with pytest.raises(ValueError, match="source"):
        ctrl.import_entries([], "elsewhere")  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="refs"):
        ctrl.step(np.zeros(6), np.zeros((3, 6)))


def test_contract_import_path():
    from epc_offboard.mpc import ExperienceController as E
    from epc_offboard.mpc import LinearModel
    from epc_offboard.mpc import MpcProblem as P

    model = LinearModel(np.eye(2), np.eye(2)[:, :1])
    ctrl = E(P(model, horizon=3, Q=[1, 1], R=[1], u_min=[-1], u_max=[1]), max_size=10)
    d = ctrl.step(np.array([1.0, 0.0]), np.zeros((3, 2)), u_p=None)
    assert d.u.shape == (1,)
    assert d.source == "solved"
    assert {"hits", "misses", "qp_solves", "size"} <= set(vars(ctrl.stats))
    assert isinstance(ctrl.problem, MpcProblem)


def test_linearly_dependent_active_constraints_are_dropped_not_fatal():
    # x[k+1] = u[k]: the bound on x[k+1] and the bound on u[k] are the same row of Gamma,
    # so at a saturated optimum both are active and dependent
    model = LinearModel(np.zeros((1, 1)), np.ones((1, 1)))
    p = MpcProblem(model, horizon=3, Q=[1.0], R=[0.01], x_max=[1.0], u_max=[1.0])
    ctrl = ExperienceController(p)
    refs = np.full((3, 1), 5.0)
    first = ctrl.step(np.zeros(1), refs)
    assert first.source == "solved"
    assert first.u[0] == pytest.approx(1.0, abs=1e-12)
    (entry,) = ctrl.export_library()
    rows = [p.rows[i] for i in entry.active_set]
    assert len(rows) == 3  # one of each dependent pair kept
    assert ctrl.step(np.zeros(1), refs).source == "hit"


def test_a_failed_solve_and_intermediate_degrade_to_bounded_hover(monkeypatch):
    p = position_problem(6)
    ctrl = ExperienceController(p)
    monkeypatch.setattr(ctrl._intermediate_qp, "solve", lambda theta: None)
    a = np.array([5.0, 0.0, -0.5])  # more than the input box can cancel
    d = ctrl.step(np.array([0, 0, 0, 10.0, 0, 0]), hover_refs(p, [0, 0, 0]),
                  perturbation=p.model.B @ a)
    assert d.source == "fallback"
    assert np.allclose(d.u, [-A_MAX, 0.0, 0.5])
    assert ctrl.stats.fallback == 1


def intermediate_reference(short: MpcProblem, theta: np.ndarray, w: float):
    """The intermediate QP (thesis 3.1.3) built from its definition and solved by OSQP at
    eps 1e-10, polished where it can (exact at the active set it identifies):
    ``(u0 (nu,), s (m_x,))``.

    ``min 1/2 U'HU + h'U + w/2 |s|^2 + w 1's`` s.t. ``Gx U - s <= gamma_x``, ``s >= 0``,
    every input row of ``G U <= gamma`` hard."""
    from epc_offboard.control.qp import OsqpSolver, QpStatus

    h, gamma = short.vectors(theta)
    is_x = np.array([r.kind == "x" for r in short.rows])
    n_s, n_u = int(is_x.sum()), short.n_u
    P = np.block([[short.H, np.zeros((n_u, n_s))], [np.zeros((n_s, n_u)), w * np.eye(n_s)]])
    S = np.zeros((len(short.rows), n_s))
    S[np.flatnonzero(is_x), np.arange(n_s)] = -1.0
    A = np.vstack([np.hstack([short.G, S]), np.hstack([np.zeros((n_s, n_u)), -np.eye(n_s)])])
    solver = OsqpSolver(P, A, polish=True, eps_abs=1e-10, eps_rel=1e-10, max_iter=200000)
    res = solver.solve(np.concatenate([h, np.full(n_s, w)]), np.concatenate([gamma,
                                                                             np.zeros(n_s)]))
    # unpolished where the active set is degenerate (a row exactly at its bound: hypothesis
    # found pos (-4, 0, 0), vel (1.1, 0, 0), horizon 5); the QP is strictly convex, so the
    # unique optimum at eps 1e-10 is still well within the comparison's 1e-6
    assert res.status == QpStatus.SOLVED, res.status
    return short.clip_input(res.x[: short.nu]), res.x[n_u:]


intermediate_case = st.fixed_dictionaries({
    "tilt": st.booleans(),
    "pos_m": st.lists(st.floats(-8, 8), min_size=3, max_size=3).map(np.array),
    # beyond the bounds by more than one step's braking: the state bounds cannot all hold
    "vel_m_s": st.lists(st.floats(-9, 9), min_size=3, max_size=3).map(np.array),
    "tgt": target,
    "p_hat": st.lists(st.floats(-0.3, 0.3), min_size=3, max_size=3).map(np.array),
    "horizon": st.integers(1, 6),
})


@settings(max_examples=60, deadline=None)
@given(case=intermediate_case)
@example(case={"tilt": False, "pos_m": np.array([-4.0, 0.0, 0.0]),  # OSQP cannot polish it
               "vel_m_s": np.array([1.1, 0.0, 0.0]), "tgt": np.zeros(3), "p_hat": np.zeros(3),
               "horizon": 5})  # fmt: skip
def test_intermediate_input_equals_an_exact_reference_solve(case):
    """DAQP's intermediate input (a miss tick's) equals the intermediate QP's optimum solved
    independently, also where the state bounds cannot all hold and slack takes them."""
    full = tilt_problem(10) if case["tilt"] else position_problem(10)
    nx = full.nx
    x0 = np.zeros(nx)
    x0[:3], x0[3:6] = case["pos_m"], case["vel_m_s"]
    pert = np.zeros(nx)
    pert[3:6] = 0.1 * case["p_hat"]  # a wind's velocity change per step, m/s
    refs = hover_refs(full, case["tgt"])
    w = 1e3
    ctrl = ExperienceController(full, intermediate_horizon=case["horizon"], slack_weight=w,
                                learn_on_miss=False)
    qp = ctrl._intermediate_qp
    qp.solve(full.theta(np.zeros(nx), refs))  # hot start from another tick's working set
    u = qp.solve(full.theta(x0, refs, perturbation=pert))
    short = full.with_horizon(case["horizon"])
    u_ref, slack = intermediate_reference(
        short, short.theta(x0, refs[: case["horizon"]], perturbation=pert), w
    )
    assert u is not None
    assert np.allclose(u, u_ref, atol=1e-6, rtol=0), (u, u_ref, slack.max())
    assert qp.daqp_failures == 0
    v_max = 3.0 if case["tilt"] else V_MAX
    if np.abs(case["vel_m_s"]).max() > v_max + 0.8:  # one step brakes < 0.3 m/s in both
        assert slack.max() > 1e-3  # the slack was active: no input holds every bound


def test_intermediate_falls_back_to_osqp_when_daqp_fails():
    p = position_problem(6)
    ctrl = ExperienceController(p)
    qp = ctrl._intermediate_qp
    qp._daqp.settings = {"iter_limit": 1}  # DAQP stops with exit flag -4 (iteration limit)
    d = ctrl.step(np.array([0, 0, 0, 10.0, 0, 0]), hover_refs(p, [0, 0, 0]))
    assert qp.daqp_failures == 1
    assert d.source == "intermediate"
    assert d.u[0] == pytest.approx(-A_MAX, abs=1e-3)  # OSQP answered: braking as hard


def test_offset_only_model_change_keeps_the_maps():
    p = position_problem(6)
    ctrl = ExperienceController(p)
    ctrl.step(np.zeros(6), hover_refs(p, [1.0, 0, 0]))
    c = np.array([0, 0, 0, 0.01, 0, 0])
    ctrl.set_model(p.model.with_offset(c))
    assert np.array_equal(ctrl.problem.model.c, c)
    assert ctrl.problem.H is p.H  # nothing rebuilt
    refs = hover_refs(p, [1.0, 0, 0])
    d = ctrl.step(np.zeros(6), refs)
    U = exact_solution(ctrl.problem, ctrl.problem.theta(np.zeros(6), refs))
    assert np.allclose(d.u, U[:3], atol=1e-8)


def test_attitude_loop_is_exact_too():
    inf = math.inf
    p = MpcProblem(
        attitude_model(0.01, 0.04),
        horizon=10,
        Q=[50, 50, 20, 1, 1, 1],
        R=[0.05] * 3,
        x_min=[-0.4, -0.4, -inf, -inf, -inf, -inf],
        x_max=[0.4, 0.4, inf, inf, inf, inf],
        u_min=[-2.0] * 3,
        u_max=[2.0] * 3,
    )
    ctrl = ExperienceController(p)
    x = np.zeros(6)
    for k in range(150):
        refs = np.zeros((10, 6))
        refs[:, :3] = [0.6, -0.2, 0.5] if (k // 50) % 2 == 0 else [0.0, 0.1, 0.0]
        d = ctrl.step(x, refs)
        U = exact_solution(p, p.theta(x, refs))
        assert np.allclose(d.u, U[:3], atol=1e-8)
        x = p.model.step(x, d.u)
        assert abs(x[0]) <= 0.4 + 1e-7  # the roll bound holds in closed loop
    assert ctrl.stats.hits > 50


def tilt_problem(horizon: int) -> MpcProblem:
    """The position loop's problem: lagged model, velocity bounds and the tilt polygon."""
    from epc_offboard.control.models import acceleration_limits, position_model_lagged
    from epc_offboard.control.position import PositionControlConfig

    pc = PositionControlConfig()
    lim = acceleration_limits(math.radians(45.0), 0.08, 0.95, 0.5)
    return MpcProblem(
        position_model_lagged(pc.dt_s, pc.tau_acc_s),
        horizon=horizon,
        Q=np.concatenate([pc.q_pos, pc.q_vel, pc.q_acc]),
        R=np.array(pc.r_acc),
        x_min=[-np.inf] * 3 + [-3.0] * 3 + [-np.inf] * 3,
        x_max=[np.inf] * 3 + [3.0] * 3 + [np.inf] * 3,
        u_min=lim.u_min,
        u_max=lim.u_max,
        u_poly=(lim.P, lim.p),
    )


def test_hits_are_exact_with_the_tilt_polygon():
    """Input polytope rows (the position loop's tilt polygon) are constraint rows like any
    other: hits and solves equal the exact optimum, and every input satisfies P u <= p."""
    p = tilt_problem(8)
    lim_P, lim_p = p.u_poly_P, p.u_poly_p
    assert sum(r.kind == "up" for r in p.rows) == 8 * len(lim_p)
    ctrl = ExperienceController(p)
    rng = np.random.default_rng(3)
    active_poly = 0
    for _ in range(60):
        x0 = np.concatenate([rng.uniform(-6, 6, 3), rng.uniform(-2, 2, 3), np.zeros(3)])
        refs = np.zeros((p.horizon, p.nx))
        d = ctrl.step(x0, refs)
        if d.source not in ("hit", "solved"):
            continue
        U = exact_solution(p, p.theta(x0, refs))
        assert np.allclose(d.u, U[:3], atol=1e-7, rtol=0)
        assert np.all(lim_P @ d.u <= lim_p + 1e-7)
        active_poly += bool(np.any(lim_P @ d.u >= lim_p - 1e-6))
    assert active_poly >= 5  # the polygon was what limited those commands
    assert ctrl.stats.hits >= 1


# -- fleet candidates (issue 16, fault 5) ---------------------------------------------------


def test_candidates_enter_the_library_only_where_they_are_optimal():
    p = position_problem(8)
    learner = ExperienceController(p)
    learner.step(np.zeros(6), hover_refs(p, [10.0, 0.0, 0.0]))
    (saturated,) = learner.export_library()
    ctrl = ExperienceController(p)
    junk = [LibraryEntry((i,)) for i in range(10)]
    assert ctrl.offer_candidates([saturated, *junk], "shared:v2") == 11
    assert ctrl.stats.size == 0
    assert ctrl.stats.candidates == 11
    # at rest the saturated set is not optimal, nor any junk: the tick solves, nothing promoted
    d = ctrl.step(np.zeros(6), hover_refs(p, [0.0, 0.0, 0.0]))
    assert d.source == "solved"
    assert [e.origin for e in ctrl.export_library()] == ["solved"]
    assert ctrl.stats.received_shared == 0
    # where it is optimal it is promoted, exact, without a solve
    d = ctrl.step(np.zeros(6), hover_refs(p, [10.0, 0.0, 0.0]))
    assert d.source == "hit"
    U = exact_solution(p, p.theta(np.zeros(6), hover_refs(p, [10.0, 0.0, 0.0])))
    assert np.allclose(d.u, U[:3], atol=1e-8)
    assert ctrl.stats.qp_solves == 1
    assert ctrl.stats.received_shared == 1
    assert saturated.active_set not in ctrl.candidates
    lib = {e.active_set: e.origin for e in ctrl.export_library()}
    assert lib[saturated.active_set] == "shared:v2"
    assert all(not ctrl.contains(e.active_set) for e in junk)


def test_the_candidate_pool_is_bounded_in_total_and_per_origin():
    p = position_problem(8)
    ctrl = ExperienceController(p, max_candidates=10, max_candidates_per_origin=4)
    sets = [(i,) for i in range(40)]
    assert ctrl.offer_candidates([LibraryEntry(s) for s in sets], "shared:flood") == 40
    assert ctrl.candidates.items() == [(s, "shared:flood") for s in sets[-4:]]  # its newest
    for k in range(30):  # rotating ids: the pool stays at its size
        assert ctrl.offer_candidates([LibraryEntry((50 + k,))], f"shared:id{k}") == 1
        assert len(ctrl.candidates) <= 10
    ctrl.offer_candidates([LibraryEntry((0, 1))], "shared:legit")
    assert ((0, 1), "shared:legit") in ctrl.candidates.items()  # a newcomer gets in
    # malformed (out of range, unsorted, too many rows) is counted, never pooled
    bad = [LibraryEntry((p.n_con,)), LibraryEntry((2, 1)), LibraryEntry(tuple(range(p.n_u + 1)))]
    assert ctrl.offer_candidates(bad, "shared:x") == 0
    assert ctrl.candidates.counters["rejected_malformed"] == 3
    assert ctrl.stats.size == 0


def test_candidate_maps_are_built_in_slices_bounded_by_time(monkeypatch):
    """A slice stops when its time budget is spent (at least one map, so slices progress);
    the clock is the module's, replaced here by one that advances 1 ms per reading."""
    p = position_problem(8)
    ctrl = ExperienceController(p)
    ctrl.offer_candidates([LibraryEntry((i,)) for i in range(12)], "shared:v2")
    fake_now = [0.0]

    def thread_time() -> float:  # the worker's CPU time, as the slice is budgeted
        fake_now[0] += 1e-3
        return fake_now[0]

    monkeypatch.setattr("epc_offboard.control.epc.candidates.time.thread_time", thread_time)
    assert ctrl.build_candidates(0.0) == 1
    # start at t0; after each map a reading: t0 + 1 and + 2 ms go on, + 3 ms stops it
    assert ctrl.build_candidates(2.5e-3) == 3
    assert ctrl.candidates.unbuilt == 8
    monkeypatch.undo()
    assert ctrl.build_candidates(None) == 8
    assert ctrl.candidates.unbuilt == 0
    assert ctrl.stats.size == 0  # built is not promoted


@pytest.mark.parametrize("kernel", ["compiled", "numpy"])
def test_a_query_checks_at_most_its_budget_likely_successors_first(kernel, monkeypatch):
    from epc_offboard.control import kernels

    if kernel == "numpy":
        monkeypatch.setattr(library_module, "query_maps", kernels.query_maps_numpy)
    p = position_problem(6)
    x, a = sets_for(p, [[0, 0, 0], [10, 0, 0]])
    assert x.active_set != a.active_set
    # a large library of controllers optimal nowhere near hover: single and paired rows
    filler = [(i,) for i in range(p.n_con)] + [(i, i + 1) for i in range(0, 2 * p.n_u, 2)]
    filler = [s for s in filler if s not in (x.active_set, a.active_set)][:80]
    entries = [LibraryEntry(x.active_set, 100.0)]
    entries += [LibraryEntry(s, 50.0 - 0.1 * k) for k, s in enumerate(filler)]
    entries.append(LibraryEntry(a.active_set, 0.0))  # least important: last in the scan
    ctrl = ExperienceController(p, max_size=200, max_checks=10)
    assert ctrl.import_entries(entries) == len(entries)
    assert len(ctrl.query_order()) == 10  # the budget bounds what a query may try

    # without a transition, a lies beyond the budget: a miss after exactly 10 checks
    assert ctrl.step(np.zeros(6), hover_refs(p, [0, 0, 0])).source == "hit"  # x
    assert ctrl.last_query_checks == 1
    assert ctrl.step(np.zeros(6), hover_refs(p, [10, 0, 0])).source != "hit"
    assert ctrl.last_query_checks == 10
    assert ctrl.query_counters["budget_exhausted"] == 1

    # with x -> a counted, a is tried right after x: a hit at the second check
    ctrl2 = ExperienceController(p, max_size=200, max_checks=10)
    ctrl2.import_entries(entries, transitions={(0, len(entries) - 1): 3})
    assert ctrl2.step(np.zeros(6), hover_refs(p, [0, 0, 0])).source == "hit"
    assert ctrl2.query_order()[:2] == [x.active_set, a.active_set]
    assert ctrl2.step(np.zeros(6), hover_refs(p, [10, 0, 0])).source == "hit"
    assert ctrl2.last_query_checks == 2
    assert ctrl2.stats.misses == 0


def test_the_query_budget_in_us_becomes_a_count():
    p = position_problem(6)
    ctrl = ExperienceController(p)
    cost = ctrl.check_cost_us()
    assert cost > 0
    assert ctrl.checks_within(10 * cost + 1e-9) == 10
    assert ctrl.checks_within(0.1 * cost) == 1  # at least the last controller
    with pytest.raises(ValueError, match="max_checks"):
        ExperienceController(p, max_checks=0)


def lead_problem(horizon: int, lead_m_s2: float, stages: int | None = None) -> MpcProblem:
    """The position problem with the inner loop's lag (x = p, v, a; u = the commanded a):
    the velocity and input bounds, and the lead rows |u_k - a_k| <= lead_m_s2 (a jerk bound)
    horizontally."""
    inf = math.inf
    return MpcProblem(
        position_model_lagged(0.05, (0.12, 0.12, 0.03)), horizon=horizon,
        Q=[80, 80, 120, 6, 6, 6, 0, 0, 0], R=[0.3] * 3,
        x_min=[-inf] * 3 + [-V_MAX] * 3 + [-inf] * 3, x_max=[inf] * 3 + [V_MAX] * 3 + [inf] * 3,
        u_min=[-A_MAX] * 3, u_max=[A_MAX] * 3,
        lead=((6, 7, 8), [lead_m_s2, lead_m_s2, inf]), lead_stages=stages,
    )  # fmt: skip


@pytest.mark.parametrize("stages", [None, 4])
def test_lead_rows_bound_the_plan_and_hits_stay_exact(stages):
    """The lead rows bound |u_k - a_k| (a_0 measured, a_k predicted) on their stages (all, or
    the first 4); a plan without them swings the command across the input box; a hit
    equals the exact solve. On the first stages only, a plan counts on a jerk it will not
    have later and can run into the velocity bound where no input keeps it (the full QP
    infeasible): those ticks fly the intermediate QP; on every stage, none does."""
    lead_m_s2 = 1.5
    p = lead_problem(10, lead_m_s2, stages)
    k_lead = p.lead_stages
    free = lead_problem(10, 1e3)
    ctrl = ExperienceController(p)
    x = np.zeros(9)
    lead_active = swing_free = 0
    for k in range(160):
        tgt = [3.0, -2.0, 1.0] if (k // 40) % 2 == 0 else [0.0, 0.0, 0.0]
        refs = hover_refs(p, tgt)
        d = ctrl.step(x, refs)
        x_next = p.model.step(x, d.u)
        if d.source == "intermediate" and stages is not None:
            x = x_next
            continue
        theta = p.theta(x, refs)
        U = exact_solution(p, theta)
        assert d.source in ("hit", "solved")
        assert np.allclose(d.u, U[:3], atol=1e-8, rtol=0)
        a = np.vstack([x[6:9], p.predict(theta, U)[:-1, 6:9]])
        lead = np.abs(U.reshape(-1, 3) - a)[:k_lead, :2]
        assert lead.max() <= lead_m_s2 + 1e-7
        lead_active += bool(lead.max() > lead_m_s2 - 1e-7)
        U_free = exact_solution(free, free.theta(x, refs))
        a_free = np.vstack([x[6:9], free.predict(free.theta(x, refs), U_free)[:-1, 6:9]])
        swing_free += bool(np.abs(U_free.reshape(-1, 3) - a_free)[:, :2].max() > 2 * lead_m_s2)
        x = x_next
    assert ctrl.stats.hits > 30
    assert lead_active > 20
    assert swing_free > 10


def test_lead_rows_from_an_acceleration_beyond_them_are_soft_in_the_intermediate():
    """A measured acceleration the inputs cannot lead within the bound (beyond the input box
    by more than it): the full QP is infeasible, the intermediate takes the lead rows with
    slack and steers towards it instead of falling back to hover."""
    p = lead_problem(6, 1.0)
    ctrl = ExperienceController(p)
    x = np.zeros(9)
    x[6] = A_MAX + 3.0
    d = ctrl.step(x, hover_refs(p, [0.0, 0.0, 0.0]))
    assert d.source == "intermediate"
    assert d.u[0] == pytest.approx(A_MAX, abs=1e-3)  # as close to a_0 as the box allows
