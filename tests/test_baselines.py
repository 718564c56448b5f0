"""Baselines: PD (thesis A.1 with feedforward) and MPC every tick; one controller contract."""

from __future__ import annotations

import numpy as np
import pytest

from epc_offboard.control.baselines import MpcController, PdController
from epc_offboard.control.decision import Controller, Decision
from epc_offboard.control.epc import ExperienceController
from tests.mpc_cases import A_MAX, exact_solution, hover_refs, position_problem


def test_pd_is_zero_on_the_reference_and_proportional_off_it():
    p = position_problem(5)
    pd = PdController(p, kp=2.0, kd=[1.0, 1.0, 3.0])
    refs = np.tile([1.0, 2.0, -1.0, 0.5, 0.0, 0.0], (5, 1))
    x = refs[0].copy()
    assert np.allclose(pd.step(x, refs).u, 0.0)
    x[0] -= 0.1
    x[5] = 0.2
    assert np.allclose(pd.step(x, refs).u, [0.2, 0.0, -0.6])


def test_pd_feeds_the_reference_acceleration_forward_and_clips():
    p = position_problem(5)
    pd = PdController(p, kp=1.0, kd=1.0)
    dt = p.model.dt_s
    assert dt is not None
    refs = np.zeros((5, 6))
    refs[:, 3] = 0.7 * dt * np.arange(1, 6)  # accelerating north at 0.7 m/s²
    refs[:, 0] = 0.35 * (dt * np.arange(1, 6)) ** 2
    x = refs[0].copy()
    assert np.allclose(pd.step(x, refs).u, [0.7, 0.0, 0.0])
    far = np.array([-100.0, 0, 0, 0, 0, 0])
    assert pd.step(far, refs).u[0] == pytest.approx(A_MAX)


def test_pd_cancels_a_perturbation():
    p = position_problem(5)
    pd = PdController(p, kp=1.0, kd=1.0)
    a = np.array([0.3, 0.0, -0.2])
    d = pd.step(np.zeros(6), np.zeros((5, 6)), perturbation=p.model.B @ a)
    assert np.allclose(d.u, -a)
    assert d.source == "solved"


def test_mpc_with_inactive_constraints_equals_epc():
    p = position_problem(10)
    mpc, epc = MpcController(p), ExperienceController(p)
    x0 = np.array([0.1, -0.2, 0.0, 0.1, 0.0, 0.0])
    refs = hover_refs(p, [0.2, 0.0, 0.1])
    a, b = mpc.step(x0, refs), epc.step(x0, refs)
    assert np.allclose(a.u, b.u, atol=1e-7)
    assert a.x_pred is not None
    assert a.x_pred.shape == (10, 6)


def test_mpc_matches_the_exact_constrained_solution():
    p = position_problem(10)
    mpc = MpcController(p)
    for tgt in ([8.0, 0, 0], [0, -5.0, 2.0]):
        refs = hover_refs(p, tgt)
        d = mpc.step(np.zeros(6), refs)
        U = exact_solution(p, p.theta(np.zeros(6), refs))
        assert np.allclose(d.u, U[:3], atol=1e-6)


def test_mpc_infeasible_degrades_to_bounded_hover():
    p = position_problem(4)
    d = MpcController(p).step(np.array([0, 0, 0, 10.0, 0, 0]), np.zeros((4, 6)))
    assert d.source == "fallback"
    assert np.allclose(d.u, 0.0)


@pytest.mark.parametrize("make", ["pd", "mpc", "epc"])
def test_every_controller_honours_the_step_contract(make):
    p = position_problem(6)
    ctrl: Controller
    if make == "pd":
        ctrl = PdController(p, 1.0, 1.0)
    elif make == "mpc":
        ctrl = MpcController(p)
    else:
        ctrl = ExperienceController(p)
    d = ctrl.step(np.zeros(6), hover_refs(p, [1.0, 0, 0]), perturbation=np.zeros(6))
    assert isinstance(d, Decision)
    assert d.u.shape == (3,)
    assert d.source in ("hit", "solved", "intermediate", "fallback")
    assert d.compute_us > 0.0
    with pytest.raises(AttributeError):
        d.u = np.zeros(3)  # type: ignore[misc]


def test_the_step_signature_is_written_once():
    """Every controller of the loops takes its ``step`` from the one ``Controller`` (which
    stacks θ) and writes only its ``decide``: the signature cannot drift between them."""
    for cls in (ExperienceController, PdController, MpcController):
        assert Controller in cls.__mro__
        assert "step" not in vars(cls), f"{cls.__name__} writes its own step"
        assert cls.step is Controller.step
        assert "decide" in vars(cls)
