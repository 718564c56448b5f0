"""LWPR with the Kalman observer on what it leaves (``[estimator.lwpr] residual_kf``, issue
24's calm row): the observer learns the measured disturbance less LWPR's prediction and its
estimate is added to LWPR's; off by default, and the product's LWPR in the Neural-Fly table
flies without it. Pure numerics: cheap."""

from __future__ import annotations

import tomllib
from dataclasses import replace

import numpy as np
import pytest

from epc_offboard.control.perturbation import EstimatorConfig, LwprPerturbation
from epc_offboard.control.position import PositionControlConfig, PositionLoop
from epc_offboard.control.types import VehicleState
from epc_offboard.tools.neuralfly import product_lwpr_scenario
from epc_offboard.tools.sim.scenario import SCENARIO_DIR

PERIOD_S = 0.01


def _loop(residual: bool) -> PositionLoop:
    est = EstimatorConfig()  # the product's LWPR: a long memory (forgetting 0.999 -> 0.99999)
    est = replace(est, lwpr=replace(est.lwpr, residual_kf=residual))
    return PositionLoop(PositionControlConfig(command_dead_time_s=0.0), est, PERIOD_S)


def _push(loop: PositionLoop, d_north: list[float]) -> np.ndarray:
    """Level flight (the autopilot's thrust holding the height) pushed north by one
    disturbance a tick (m/s^2): the loop observes each tick's velocity; returns the
    disturbance it would fly with at the last velocity, LWPR's plus the observer's."""
    v = 0.0
    for k, d in enumerate(d_north):
        v += d * PERIOD_S
        loop.observe(VehicleState(
            time_s=k * PERIOD_S, pos_ned_m=np.array([0.0, 0.0, -2.5]),
            vel_ned_m_s=np.array([v, 0.0, 0.0]), q_ned_frd=np.array([1.0, 0.0, 0.0, 0.0]),
            rate_frd_rad_s=np.zeros(3), position_age_s=0.0, attitude_age_s=0.0,
        ), ours=False)  # fmt: skip
    z = np.array([v, 0.0, 0.0])
    assert isinstance(loop.estimator, LwprPerturbation)
    lwpr = loop.estimator.predict_raw(z)
    residual = loop._residual
    return lwpr if residual is None else lwpr + residual.kf.x[:, 0]


def test_the_observer_follows_what_lwpr_leaves():
    """A step of 1 m/s^2 north after 2 s of calm: 0.3 s later LWPR (its memory seconds long)
    has learnt part of it; with the observer on its residual, the sum is within 10 %."""
    steps = [0.0] * 200 + [1.0] * 30
    alone = _push(_loop(residual=False), steps)
    both = _push(_loop(residual=True), steps)
    assert both[0] == pytest.approx(1.0, abs=0.1)
    assert abs(alone[0] - 1.0) > 0.2
    assert abs(both[1]) < 1e-6  # nothing east


def test_off_by_default_and_only_with_lwpr():
    assert not EstimatorConfig().lwpr.residual_kf
    assert _loop(residual=False)._residual is None
    kf = replace(EstimatorConfig(kind="kf"), lwpr=replace(EstimatorConfig().lwpr, residual_kf=True))
    assert PositionLoop(PositionControlConfig(), kf, PERIOD_S)._residual is None


def test_the_neuralfly_scenario_flies_it_and_the_product_variant_does_not(tmp_path):
    scenario = tomllib.loads((SCENARIO_DIR / "neuralfly.toml").read_text())
    assert scenario["service"]["estimator"]["lwpr"]["residual_kf"] is True
    product = tomllib.loads(product_lwpr_scenario(tmp_path).read_text())
    assert "residual_kf" not in str(product)
