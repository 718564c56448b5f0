"""The position loop's state filter (control/state_filter.py): the measured position and
velocity fused with the model's acceleration against an EKF2-like estimate error, smooth
and not white (Neural-Fly's plant: 5 mm, 3 cm/s, correlated over 0.25 s)."""

from __future__ import annotations

import math
from typing import Any

import numpy as np
import pytest

from epc_offboard.control.position import PositionControlConfig
from epc_offboard.control.state_filter import StateFilter, StateFilterConfig
from epc_offboard.tools.sim.scenario import load_scenario

DT_S = 0.01
MATCHED = StateFilterConfig(position_noise_m=0.005, velocity_noise_m_s=0.03,
                            correlation_s=0.25, acc_noise_m_s2=0.7)  # fmt: skip


def gauss_markov(rng: np.random.Generator, n: int, std: float, tau_s: float) -> np.ndarray:
    phi = math.exp(-DT_S / tau_s)
    out = np.empty((n, 3))
    e = std * rng.standard_normal(3)
    for k in range(n):
        out[k] = e
        e = phi * e + std * math.sqrt(1.0 - phi * phi) * rng.standard_normal(3)
    return out


def flight(seed: int, n: int = 3000):
    """A figure-8-like motion (true p, v, a), its measurements with the correlated error,
    and a model acceleration off by 0.3 m/s^2 of white error."""
    rng = np.random.default_rng(seed)
    t = np.arange(n) * DT_S
    w = np.array([1.0, 2.0, 1.5])
    amp = np.array([1.25, 0.75, 0.3])
    p = amp * np.sin(np.outer(t, w))
    v = amp * w * np.cos(np.outer(t, w))
    a = -amp * w * w * np.sin(np.outer(t, w))
    p_meas = p + gauss_markov(rng, n, 0.005, 0.25)
    v_meas = v + gauss_markov(rng, n, 0.03, 0.25)
    a_model = a + 0.3 * rng.standard_normal((n, 3))
    return t, p, v, p_meas, v_meas, a_model


def rms(e: np.ndarray) -> float:
    return float(np.sqrt(np.mean(e[500:] ** 2)))  # after the first 5 s: converged


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_the_fused_velocity_has_less_error_than_the_measured_one(seed: int) -> None:
    t, p, v, p_meas, v_meas, a_model = flight(seed)
    f = StateFilter(MATCHED, DT_S)
    fused = [f.update(t[k], p_meas[k], v_meas[k], a_model[k], np.zeros(3)) for k in range(len(t))]
    p_f = np.array([x[0] for x in fused])
    v_f = np.array([x[1] for x in fused])
    # the error it is matched to: well below the measured velocity's (a low-pass filter of
    # an error this slow only lags the vehicle), and the position no worse
    assert rms(v_f - v) < 0.8 * rms(v_meas - v)
    assert rms(p_f - p) < 1.05 * rms(p_meas - p)


def test_unset_the_measured_state_is_flown_as_is() -> None:
    f = StateFilter(StateFilterConfig(), DT_S)
    p, v = np.array([1.0, 2.0, -3.0]), np.array([0.1, 0.2, 0.3])
    p_out, v_out = f.update(0.0, p, v, np.ones(3), np.zeros(3))
    assert np.array_equal(p_out, p)
    assert np.array_equal(v_out, v)
    assert PositionControlConfig().state_filter == StateFilterConfig()


def test_a_gap_restarts_from_the_measurement() -> None:
    f = StateFilter(MATCHED, DT_S)
    for k in range(100):
        f.update(k * DT_S, np.zeros(3), np.zeros(3), np.zeros(3), np.zeros(3))
    p = np.array([5.0, -1.0, -2.0])
    v = np.array([1.0, 0.0, 0.5])
    p_out, v_out = f.update(100 * DT_S + 0.5, p, v, np.zeros(3), np.zeros(3))
    assert np.array_equal(p_out, p)
    assert np.array_equal(v_out, v)
    # a repeated sample (the same time) changes nothing
    p_again, v_again = f.update(100 * DT_S + 0.5, p + 1.0, v + 1.0, np.ones(3), np.zeros(3))
    assert np.array_equal(p_again, p)
    assert np.array_equal(v_again, v)


@pytest.mark.parametrize("key", ["position_noise_m", "velocity_noise_m_s", "correlation_s",
                                 "acc_noise_m_s2"])  # fmt: skip
def test_the_config_is_checked(key: str) -> None:
    bad: dict[str, Any] = {key: -1.0}
    with pytest.raises(ValueError, match=key):
        StateFilterConfig(**bad)


def test_the_neuralfly_scenario_flies_it_and_a_misspelt_key_is_named() -> None:
    from epc_offboard.common.configio import from_dict

    cfg = from_dict(PositionControlConfig, {"state_filter": {"position_noise_m": 0.005,
                                                             "velocity_noise_m_s": 0.03}})
    assert cfg.state_filter.enabled
    assert not cfg.state_filter.feed_estimator  # the product's: the measured velocity
    with pytest.raises(Exception, match="velocity_noise"):
        from_dict(PositionControlConfig, {"state_filter": {"velocity_noise": 0.03}})
    scenario = load_scenario("neuralfly").service["position"]
    cfg = from_dict(PositionControlConfig, scenario)
    assert cfg.state_filter.enabled
    assert cfg.state_filter.feed_estimator  # the disturbance learnt at the fused velocity


@pytest.mark.slow
@pytest.mark.timeout(300)
def test_neuralfly_in_calm_air_tracks_within_1_6_cm_through_its_estimate_noise(tmp_path) -> None:
    """The whole `neuralfly` 0 m/s row, lockstep (repeatable), on a seed the filter was not
    tuned on: the QP answered the estimate's velocity error as motion, 2.21 cm mean after the
    first lap without the filter; 1.66 with it, the disturbance still learnt and looked up at
    the measured velocity (a forgetting LWPR followed its error); 1.53 at the fused one."""
    import json
    import subprocess
    import sys

    out = tmp_path / "nf"
    proc = subprocess.run(
        [sys.executable, "-m", "epc_offboard", "sim", "--scenario", "neuralfly",
         "--wind", "0,-90", "--seed", "3", "--gcs-port", "0", "--out", str(out),
         "--no-figure"],
        capture_output=True, text=True, timeout=280, check=False,
    )  # fmt: skip
    v = json.loads((out / "report.json").read_text())["vehicles"][0]
    assert v["finished"], proc.stdout + proc.stderr
    assert v["constraint_violations"] == 0
    assert v["tracking"]["mean_error_m"] <= 0.016, proc.stdout
