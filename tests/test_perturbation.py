"""Perturbation estimators: a drag-like perturbation learned from flown trajectories and
re-learned after it changes, the low-pass step response, the Kalman observer, the factory,
configs from TOML and the persistence of the learned state."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from epc_offboard.common.configio import ConfigError, load_config
from epc_offboard.control.perturbation import (
    KalmanPerturbation,
    LowPassFilter,
    LwprPerturbation,
    NoPerturbation,
    PerturbationConfig,
    make_estimator,
)
from epc_offboard.tools import bench_lwpr as bench

NX, NZ, DT_S = bench.NX, bench.NZ, bench.DT_S  # position loop: x = p(3), v(3); u = a(3)
VEL = list(bench.VELOCITY)
DoubleIntegrator = bench.DragFlight  # flies between waypoints in wind, with drag
drag_estimator = bench.drag_estimator


def fly(est: LwprPerturbation, sim: DoubleIntegrator, v_wind: np.ndarray, steps: int) -> float:
    """Online one-step-ahead nMSE of the raw velocity estimate over ``steps`` ticks."""
    err, truth = [], []
    for _ in range(steps):
        z, p = sim.step(v_wind)
        err.append(est.predict_raw(z)[VEL] - p[VEL])
        truth.append(p[VEL])
        est.observe(z, p)
    return float(np.mean(np.square(err)) / np.var(truth))


def test_drag_is_learned_and_relearned_after_the_wind_changes():
    est = drag_estimator()
    sim = DoubleIntegrator(seed=1)
    wind_1, wind_2 = np.array([2.0, -1.0, 0.0]), np.array([-1.0, 2.0, 0.5])
    first_seconds = fly(est, sim, wind_1, 1000)
    learned = fly(est, sim, wind_1, 2000)
    just_after_change = fly(est, sim, wind_2, 500)
    fly(est, sim, wind_2, 1500)
    recovered = fly(est, sim, wind_2, 1000)
    print(
        f"drag nMSE: first 10 s {first_seconds:.4f}, 10-30 s {learned:.4f}, "
        f"5 s after the wind change {just_after_change:.4f}, 20-30 s after {recovered:.4f}; "
        f"fields {est.models[0].num_rfs}"
    )
    assert learned < 0.03
    assert just_after_change > 5 * learned  # the change is visible ...
    assert recovered < 0.05  # ... and forgetting re-learns it
    assert est.predict_raw(np.r_[np.zeros(3), wind_2, np.zeros(3)])[VEL] == pytest.approx(
        np.zeros(3), abs=2e-3
    )  # no drag at the wind speed
    assert all(3 <= n <= 60 for n in est.models[0].num_rfs)
    # Elements not learned stay exactly zero; the filtered estimate is finite.
    p_hat = est.estimate(np.r_[np.zeros(3), [1.0, 1.0, 1.0], np.zeros(3)])
    assert np.all(p_hat[:3] == 0.0)
    assert np.all(np.isfinite(p_hat))


def test_per_output_input_subspaces():
    """Each velocity's drag depends on that velocity only: one 1-D learner per output."""
    est = LwprPerturbation(
        NX,
        NZ,
        inputs=[[3], [4], [5]],
        outputs=VEL,
        lowpass_cutoff_hz=2.0,
        dt_s=DT_S,
        norm_z=[3.0] * NZ,
        norm_p=[0.01] * NX,
        init_d=4.0,
    )
    assert [(m.n_in, m.n_out) for m in est.models] == [(1, 1)] * 3
    same = LwprPerturbation(NX, NZ, inputs=np.array(VEL), lowpass_cutoff_hz=1.0, dt_s=DT_S)
    assert same.groups == [(tuple(VEL), tuple(range(NX)))]  # an index array: one subspace
    sim = DoubleIntegrator(seed=2)
    fly(est, sim, np.zeros(3), 1000)
    assert fly(est, sim, np.zeros(3), 1000) < 0.03


def test_variation_is_what_the_learned_model_says_elsewhere():
    est = drag_estimator()
    sim = DoubleIntegrator(seed=3)
    fly(est, sim, np.array([1.5, -0.5, 0.0]), 2000)
    rng = np.random.default_rng(0)
    z = rng.uniform(-1, 1, NZ)
    zs = rng.uniform(-2, 2, (7, NZ))
    expected = np.array([est.predict_raw(row) - est.predict_raw(z) for row in zs])
    np.testing.assert_allclose(est.variation(z, zs), expected, rtol=0.0, atol=1e-12)
    assert np.abs(expected[:, VEL]).max() > 1e-3  # drag depends on the velocity
    filtered = est.filter.state.copy()
    est.variation(z, zs)
    np.testing.assert_array_equal(est.filter.state, filtered)  # no filter step
    # estimators whose estimate does not depend on z know no variation
    for other in (NoPerturbation(NX, NZ), KalmanPerturbation(NX, NZ)):
        other.observe(z, np.ones(NX))
        np.testing.assert_array_equal(other.variation(z, zs), np.zeros((7, NX)))
        with pytest.raises(ValueError, match="zs"):
            other.variation(z, zs[:, :2])
    with pytest.raises(ValueError, match="zs"):
        est.variation(z, zs[0])


def test_lowpass_step_response_is_first_order():
    cutoff_hz, dt_s = 2.0, 0.01
    lpf = LowPassFilter(2, cutoff_hz, dt_s)
    out = np.array([lpf.step(np.array([1.0, -2.0])) for _ in range(200)])
    t_s = dt_s * np.arange(1, 201)
    expected = 1.0 - np.exp(-2.0 * math.pi * cutoff_hz * t_s)
    np.testing.assert_allclose(out[:, 0], expected, rtol=1e-12)
    np.testing.assert_allclose(out[:, 1], -2.0 * expected, rtol=1e-12)
    tau_steps = round(1.0 / (2.0 * math.pi * cutoff_hz) / dt_s)  # ~8 ticks
    assert out[tau_steps - 1, 0] == pytest.approx(1.0 - math.exp(-1.0), abs=0.03)
    lpf.reset()
    assert np.all(lpf.step(np.zeros(2)) == 0.0)


def test_estimate_is_the_lowpass_of_the_raw_prediction():
    est = drag_estimator()
    sim = DoubleIntegrator(seed=3)
    fly(est, sim, np.zeros(3), 600)
    z = np.r_[np.zeros(3), [2.0, 0.0, -1.0], np.zeros(3)]
    raw = est.predict_raw(z)
    gain = 1.0 - math.exp(-2.0 * math.pi * 2.0 * DT_S)
    np.testing.assert_allclose(est.estimate(z), gain * raw)
    np.testing.assert_allclose(est.estimate(z), (1.0 - (1.0 - gain) ** 2) * raw)


def test_kalman_observer_converges_to_a_constant_disturbance():
    rng = np.random.default_rng(4)
    d = np.array([0.0, 0.0, 0.0, 0.02, -0.01, 0.005])
    est = KalmanPerturbation(
        NX, NZ, outputs=VEL, process_noise=1e-9, measurement_noise=1e-4, initial_variance=1e-2
    )
    z = np.zeros(NZ)
    for _ in range(2000):
        est.observe(z, d + 0.01 * rng.standard_normal(NX))
    p_hat = est.estimate(z)
    assert np.all(p_hat[:3] == 0.0)
    np.testing.assert_allclose(p_hat[VEL], d[VEL], atol=1.5e-3)  # noise sd 0.01 per sample
    assert np.abs(p_hat[VEL] - d[VEL]).max() < np.abs(d[VEL]).max() / 5


def test_kalman_observer_follows_a_step_in_the_disturbance():
    est = KalmanPerturbation(NX, NZ, process_noise=1e-8, measurement_noise=1e-6)
    z = np.zeros(NZ)
    step = np.full(NX, 0.01)
    for _ in range(300):
        est.observe(z, step)
    np.testing.assert_allclose(est.estimate(z), step, rtol=0.02)


def test_none_estimator_returns_zeros():
    est = make_estimator("none", NX, NZ)
    assert isinstance(est, NoPerturbation)
    est.observe(np.ones(NZ), np.ones(NX))
    p_hat = est.estimate(np.ones(NZ))
    assert p_hat.shape == (NX,)
    assert np.all(p_hat == 0.0)


def test_factory_builds_each_kind_from_config():
    cfg = PerturbationConfig()
    assert isinstance(make_estimator("lwpr", NX, NZ, cfg), LwprPerturbation)
    assert isinstance(make_estimator("kf", NX, NZ, cfg), KalmanPerturbation)
    with pytest.raises(ValueError, match="unknown estimator kind 'gp'"):
        make_estimator("gp", NX, NZ, cfg)  # type: ignore[arg-type]


def test_config_loads_from_toml_with_both_input_forms(tmp_path: Path):
    path = tmp_path / "perturbation.toml"
    path.write_text(
        "[lwpr]\noutputs = [3, 4, 5]\ninputs = [3, 4, 5]\nlowpass_cutoff_hz = 1.5\n"
        "final_lambda = 0.999\nnorm_z = [1, 1, 1, 3, 3, 3, 1, 1, 1]\n"
        "[kf]\nprocess_noise = 1e-7\n"
    )
    cfg = load_config(PerturbationConfig, path)
    assert cfg.lwpr.inputs == (3, 4, 5)
    est = make_estimator("lwpr", NX, NZ, cfg)
    assert isinstance(est, LwprPerturbation)
    assert est.groups == [((3, 4, 5), (3, 4, 5))]
    assert est.models[0].final_lambda == 0.999
    assert est.filter.cutoff_hz == 1.5

    path.write_text("[lwpr]\noutputs = [3, 4]\ninputs = [[3], [4, 0]]\n")
    cfg = load_config(PerturbationConfig, path)
    est = make_estimator("lwpr", NX, NZ, cfg)
    assert isinstance(est, LwprPerturbation)
    assert est.groups == [((3,), (3,)), ((4, 0), (4,))]

    path.write_text("[lwpr]\nlowpass_cutof_hz = 1.0\n")
    with pytest.raises(ConfigError, match=r"unknown key lwpr\.lowpass_cutof_hz"):
        load_config(PerturbationConfig, path)
    path.write_text("[kf]\nprocess_noise = -1.0\n")
    with pytest.raises(ConfigError, match="process_noise must be > 0"):
        load_config(PerturbationConfig, path)
    path.write_text("[lwpr]\nlowpass_cutoff_hz = 0.0\n")
    with pytest.raises(ConfigError, match="lowpass_cutoff_hz must be > 0"):
        load_config(PerturbationConfig, path)


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        ({"outputs": [3, 3]}, "outputs must be distinct indices"),
        ({"inputs": [9]}, r"inputs must be distinct indices in \[0, 9\)"),
        ({"inputs": [[3], [4]], "outputs": VEL}, "inputs has 2 subspaces for 3 outputs"),
        ({"norm_p": [1.0] * 5}, r"norm_p must have shape \(6,\)"),
        ({"w_gen": 2.0}, "w_gen must be in"),
    ],
)
def test_bad_lwpr_estimator_settings_are_rejected(kwargs, message):
    with pytest.raises(ValueError, match=message):
        LwprPerturbation(NX, NZ, lowpass_cutoff_hz=2.0, dt_s=DT_S, **kwargs)


def test_bad_observations_are_rejected_and_change_nothing():
    est = drag_estimator()
    fly(est, DoubleIntegrator(seed=5), np.zeros(3), 300)
    before = est.to_bytes()
    with pytest.raises(ValueError, match="p_measured must be finite"):
        est.observe(np.zeros(NZ), np.r_[np.zeros(5), np.nan])
    with pytest.raises(ValueError, match=r"z must have shape \(9,\), got \(6,\)"):
        est.observe(np.zeros(NX), np.zeros(NX))
    with pytest.raises(ValueError, match=r"z must have shape \(9,\)"):
        est.estimate(np.zeros(NX))
    assert est.to_bytes() == before


@pytest.mark.parametrize("kind", ["lwpr", "kf", "none"])
def test_state_round_trips_through_bytes(kind):
    cfg = PerturbationConfig()
    est = make_estimator(kind, NX, NZ, cfg)
    sim = DoubleIntegrator(seed=6)
    for _ in range(400):
        est.observe(*sim.step(np.array([1.0, 0.0, 0.0])))
        est.estimate(sim.x.tolist() + [0.0] * 3)
    copy = make_estimator(kind, NX, NZ, cfg)
    copy.load_bytes(est.to_bytes())
    for _ in range(20):
        z, p = sim.step(np.zeros(3))
        np.testing.assert_array_equal(copy.estimate(z), est.estimate(z))
        copy.observe(z, p)
        est.observe(z, p)


def test_loading_another_estimators_state_is_refused():
    lwpr = make_estimator("lwpr", NX, NZ)
    kf = make_estimator("kf", NX, NZ)
    with pytest.raises(ValueError, match="state is for a 'kf' estimator, not 'lwpr'"):
        lwpr.load_bytes(kf.to_bytes())
    with pytest.raises(ValueError, match=r"dims \[6, 9\], expected \[6, 7\]"):
        make_estimator("kf", NX, 7).load_bytes(kf.to_bytes())
    with pytest.raises(ValueError, match="unreadable npz"):
        kf.load_bytes(b"not an npz")


def test_reset_forgets_what_was_learned():
    est = drag_estimator()
    fly(est, DoubleIntegrator(seed=7), np.zeros(3), 500)
    z = np.r_[np.zeros(3), [2.0, 0.0, 0.0], np.zeros(3)]
    assert np.any(est.predict_raw(z) != 0.0)
    est.reset()
    assert np.all(est.predict_raw(z) == 0.0)
    assert np.all(est.estimate(z) == 0.0)


@pytest.mark.parametrize(("inputs", "diag_only"), [
    ([[3], [4], [5]], True),  # the position loop's: one 1-D learner per velocity
    ([[3, 4], [4, 5], [3, 5]], False),  # 2-D subspaces, full metrics
    ([3, 4, 5], True),  # one learner of every output
])  # fmt: skip
def test_the_models_learn_and_predict_in_one_call_with_the_same_bits(inputs, diag_only):
    """The compiled pass over all the models at once (the position tick's observation and
    prediction along the horizon) is each model's own update and ``predict_many`` to the last
    bit (the lockstep flights stay identical), through learning that adds and prunes fields
    and reallocates their store."""
    kwargs = dict(outputs=VEL, lowpass_cutoff_hz=2.0, dt_s=DT_S, norm_z=[3.0] * NZ,
                  norm_p=[0.01] * NX, init_d=4.0, diag_only=diag_only)  # fmt: skip
    grouped = LwprPerturbation(NX, NZ, inputs=inputs, **kwargs)
    one_by_one = LwprPerturbation(NX, NZ, inputs=inputs, **kwargs)
    if not grouped.models[0].compiled:
        pytest.skip("numba's kernels are not in use (EPC_OFFBOARD_JIT=0)")
    sim = DoubleIntegrator(seed=5)
    rng = np.random.default_rng(5)
    for k in range(1500):
        z, p = sim.step(np.array([1.5, -1.0, 0.0]) * (k > 700))
        grouped.observe(z, p)  # contiguous arrays: one call
        for model, (ins, outs) in zip(one_by_one.models, one_by_one._index, strict=True):
            model.update_finite(z[ins], p[outs])
        if k % 50 == 0:
            zs = z + rng.normal(scale=0.5, size=(21, NZ))
            fast = grouped.predict_raw_many(zs)
            slow = one_by_one.predict_raw_many(np.asfortranarray(zs))  # model by model
            assert fast.tobytes() == slow.tobytes()
    assert all(sum(m.num_rfs) >= 3 for m in grouped.models)
    if len(grouped.models) == 1:  # 42 fields: the store grew twice (16 -> 64) on the way
        assert grouped.models[0]._out.shape[0] > 16
    for a, b in zip(grouped.models, one_by_one.models, strict=True):
        assert a.to_bytes() == b.to_bytes()
        assert a.n_updates == b.n_updates == 1500
    with pytest.raises(ValueError, match="finite"):  # as before
        grouped.predict_raw_many(np.full((2, NZ), np.nan))


def test_an_estimator_copies_after_its_compiled_calls_and_the_copy_learns_alone():
    """The models' arguments are packed for the compiled calls (numba typed lists, which do
    not copy): a deep copy (bench --lwpr's reference estimator) packs its own from its own
    models, so it predicts the same and learns without touching the original."""
    import copy

    est = bench._service_estimator()
    for i in range(30):
        est.observe(np.array([0.1 * i, 0.2, 0.0]), np.array([0.3, 0.1 * i, 0.0]))
        est.estimate_along(np.zeros((5, 3)))
    twin = copy.deepcopy(est)
    zs = np.full((5, 3), 0.3)
    assert np.array_equal(twin.estimate_along(zs)[1], est.estimate_along(zs)[1])
    before = [{k: v.copy() for k, v in m._store.items()} for m in est.models]
    for i in range(5):
        twin.observe(np.array([0.5 + i, 0.2, 0.0]), np.array([0.3, 0.1, 0.0]))
    for model, stored in zip(est.models, before, strict=True):
        for key, value in stored.items():
            assert np.array_equal(model._store[key], value, equal_nan=True), key
