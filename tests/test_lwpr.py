"""LWPR: learning benchmarks with real thresholds, update/predict consistency, persistence,
and rejection of bad inputs with the model left untouched."""

from __future__ import annotations

import io
import subprocess
import sys
import zipfile
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from epc_offboard.control.lwpr import LWPR, LwprError, LwprReference, warm_up
from epc_offboard.tools.bench_lwpr import DragFlight


def cross(X: np.ndarray) -> np.ndarray:
    """The classic 2-D test function of the LWPR papers."""
    x, y = X[:, 0], X[:, 1]
    out: np.ndarray = np.maximum.reduce(
        [np.exp(-10 * x**2), np.exp(-50 * y**2), 1.25 * np.exp(-5 * (x**2 + y**2))]
    )
    return out


GRID = np.stack(np.meshgrid(np.linspace(-1, 1, 41), np.linspace(-1, 1, 41)), -1).reshape(-1, 2)


def nmse(model: LWPR, X: np.ndarray, y: np.ndarray) -> float:
    pred = np.array([model.predict(x)[0] for x in X])
    return float(np.mean((pred - y) ** 2) / np.var(y))


def cross_epoch(model: LWPR, rng: np.random.Generator) -> None:
    X = rng.uniform(-1, 1, (500, 2))
    Y = cross(X) + 0.1 * rng.standard_normal(500)
    for x, y in zip(X, Y, strict=True):
        model.update(x, [y])


@pytest.fixture(scope="module")
def cross_model() -> tuple[LWPR, list[float]]:
    """20 epochs of 500 noisy samples (the reference library's cross demo settings)."""
    rng = np.random.default_rng(0)
    model = LWPR(2, 1, init_d=50.0, init_alpha=250.0)
    errors = []
    for epoch in range(20):
        cross_epoch(model, rng)
        if epoch in (0, 4, 19):
            errors.append(nmse(model, GRID, cross(GRID)))
    return model, errors


def test_cross_function_is_learned_to_the_reference_accuracy(cross_model):
    model, (after_1, after_5, after_20) = cross_model
    print(f"cross nMSE after 1/5/20 epochs: {after_1:.4f} {after_5:.4f} {after_20:.4f}")
    print(f"receptive fields: {model.num_rfs}")
    assert after_20 <= 0.03
    assert after_20 < after_5 < after_1
    assert 20 <= model.num_rfs[0] <= 80
    assert model.n_updates == 10_000


def test_cross_confidence_is_small_inside_and_absent_far_away(cross_model):
    model, _ = cross_model
    y, conf = model.predict_conf(np.array([0.0, 0.0]))
    assert abs(y[0] - 1.25) < 0.15
    assert 0.0 < conf[0] < 0.3  # about the noise level (0.1)
    y_far, conf_far = model.predict_conf(np.array([5.0, 5.0]))
    assert y_far[0] == 0.0
    assert conf_far[0] == 1e20


@pytest.mark.parametrize(
    ("diag_only", "meta"), [(False, False), (True, True), (False, True)], ids=str
)
def test_full_metric_and_meta_learning_also_learn_the_cross(diag_only, meta):
    rng = np.random.default_rng(1)
    model = LWPR(2, 1, init_d=50.0, init_alpha=250.0, diag_only=diag_only, meta=meta)
    for _ in range(5):
        cross_epoch(model, rng)
    assert nmse(model, GRID, cross(GRID)) < 0.06


def test_sine_1d():
    rng = np.random.default_rng(2)
    model = LWPR(1, 1, init_d=50.0, norm_in=[np.pi])
    for _ in range(3000):
        x = rng.uniform(-np.pi, np.pi)
        model.update([x], [np.sin(x) + 0.05 * rng.standard_normal()])
    xs = np.linspace(-3.0, 3.0, 61)[:, None]
    err = nmse(model, xs, np.sin(xs[:, 0]))
    assert err < 0.01, err
    assert 3 <= model.num_rfs[0] <= 30


def test_outputs_have_independent_fields():
    """Each output has its own fields: a two-output model equals two one-output models."""
    rng = np.random.default_rng(3)
    both, first, second = LWPR(1, 2, init_d=50.0), LWPR(1, 1, init_d=50.0), LWPR(1, 1, init_d=50.0)
    for _ in range(1500):
        x = rng.uniform(-1, 1, 1)
        y = [0.5 * x[0], np.sin(6 * x[0])]
        both.update(x, y)
        first.update(x, y[:1])
        second.update(x, y[1:])
    assert both.num_rfs == (first.num_rfs[0], second.num_rfs[0])
    for x in np.linspace(-1, 1, 21)[:, None]:
        np.testing.assert_array_equal(both.predict(x), np.r_[first.predict(x), second.predict(x)])
    y_at = both.predict([0.3])
    assert y_at[0] == pytest.approx(0.15, abs=0.02)
    assert y_at[1] == pytest.approx(np.sin(1.8), abs=0.1)


def test_update_returns_the_prediction_from_before_the_update():
    rng = np.random.default_rng(4)
    model = LWPR(2, 2)
    for _ in range(800):
        x = rng.uniform(-1, 1, 2)
        before = model.predict(x)
        fit = model.update(x, [x[0] * x[1], np.cos(x[0])])
        np.testing.assert_array_equal(fit, before)
    assert np.any(fit != 0.0)  # trusted fields exist, so this compared real predictions


@pytest.mark.parametrize("diag_only", [True, False])
def test_predict_many_equals_predict_row_by_row(diag_only: bool):
    rng = np.random.default_rng(8)
    model = LWPR(2, 2, init_d=25.0, diag_only=diag_only, norm_in=[2.0, 1.0])
    X = rng.uniform(-2.0, 2.0, (30, 2))  # inside and well outside the trained region
    np.testing.assert_array_equal(model.predict_many(X), np.zeros((30, 2)))  # no fields yet
    for _ in range(1500):
        x = rng.uniform(-1, 1, 2)
        model.update(x, [np.sin(3 * x[0]) * x[1], x[0] ** 2])
    assert min(model.num_rfs) > 1
    rows = np.array([model.predict(x) for x in X])
    np.testing.assert_allclose(model.predict_many(X), rows, rtol=0.0, atol=1e-12)
    assert model.predict_many(np.empty((0, 2))).shape == (0, 2)
    with pytest.raises(LwprError, match=r"shape \(m, 2\)"):
        model.predict_many(X[:, :1])
    with pytest.raises(LwprError, match="finite"):
        model.predict_many([[0.0, np.nan]])


def test_max_rfs_caps_the_fields_of_each_output():
    rng = np.random.default_rng(5)
    model = LWPR(2, 1, init_d=200.0, max_rfs=7)
    for _ in range(500):
        x = rng.uniform(-1, 1, 2)
        model.update(x, [x.sum()])
    assert model.num_rfs == (7,)


def trained(seed: int = 6, n: int = 600) -> LWPR:
    rng = np.random.default_rng(seed)
    model = LWPR(3, 2, init_d=[10.0, 20.0, 5.0], norm_out=[2.0, 1.0], diag_only=True)
    for _ in range(n):
        x = rng.uniform(-1, 1, 3)
        model.update(x, [x @ [1.0, -2.0, 0.5], np.sin(2 * x[0]) * x[2]])
    return model


def test_save_load_round_trip_gives_identical_predictions_and_learning(tmp_path: Path):
    model = trained()
    path = tmp_path / "model.npz"
    model.save(path)
    loaded = LWPR.load(path)
    blob_copy = LWPR.from_bytes(model.to_bytes())
    assert loaded.num_rfs == model.num_rfs
    rng = np.random.default_rng(7)
    for x in rng.uniform(-1.2, 1.2, (200, 3)):
        np.testing.assert_array_equal(loaded.predict(x), model.predict(x))
        np.testing.assert_array_equal(blob_copy.predict_conf(x)[1], model.predict_conf(x)[1])
    # The whole state is saved: learning continues identically.
    for x in rng.uniform(-1, 1, (200, 3)):
        y = [x.sum(), x[0] ** 2]
        np.testing.assert_array_equal(loaded.update(x, y), model.update(x, y))
    np.testing.assert_array_equal(loaded.predict([0.1, 0.2, 0.3]), model.predict([0.1, 0.2, 0.3]))


def test_loading_a_wrong_or_corrupt_file_raises_a_clear_error(tmp_path: Path):
    good = trained(n=100).to_bytes()
    bad_files = {
        "random.npz": bytes(np.random.default_rng(8).integers(0, 256, 500, dtype=np.uint8)),
        "truncated.npz": good[: len(good) // 2],
        "empty.npz": b"",
    }
    other = tmp_path / "other.npz"
    np.savez(other, a=np.zeros(3))
    for name, data in bad_files.items():
        (tmp_path / name).write_bytes(data)
    for path in [*(tmp_path / name for name in bad_files), other]:
        with pytest.raises(LwprError, match=str(path.name)):
            LWPR.load(path)
    with pytest.raises(LwprError, match="missing `format`"):
        LWPR.load(other)


def test_loading_another_format_version_is_refused(tmp_path: Path):
    path = tmp_path / "v99.npz"
    with np.load(io.BytesIO(trained(n=50).to_bytes())) as z:
        arrays = {k: z[k] for k in z.files}
    arrays["version"] = np.array(99)
    np.savez(path, **arrays)
    with pytest.raises(LwprError, match="version 99"):
        LWPR.load(path)
    assert zipfile.is_zipfile(path)


@pytest.mark.parametrize(
    ("x", "y", "message"),
    [
        ([np.nan, 0.0, 0.0], [0.0, 0.0], "x must be finite"),
        ([0.0, np.inf, 0.0], [0.0, 0.0], "x must be finite"),
        ([0.0, 0.0, 0.0], [0.0, np.nan], "y must be finite"),
        ([0.0, 0.0], [0.0, 0.0], r"x must have shape \(3,\), got \(2,\)"),
        ([[0.0, 0.0, 0.0]], [0.0, 0.0], r"x must have shape \(3,\), got \(1, 3\)"),
        ([0.0, 0.0, 0.0], 1.0, r"y must have shape \(2,\), got \(\)"),
        ([0.0, 0.0, 0.0], ["a", "b"], "y must be a numeric array"),
    ],
)
def test_bad_inputs_are_rejected_and_the_model_is_unchanged(x, y, message):
    model = trained(n=300)
    before = model.to_bytes()
    with pytest.raises(LwprError, match=message):
        model.update(x, y)
    if np.shape(x) != (3,) or not np.all(np.isfinite(x)):
        with pytest.raises(LwprError, match=message):
            model.predict(x)
    assert model.to_bytes() == before


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        ({"init_d": [[1.0, 2.0], [2.0, 1.0]], "diag_only": False}, "positive definite"),
        ({"init_d": [[2.0, 0.5], [0.5, 2.0]]}, "diagonal when diag_only"),
        ({"init_d": [1.0, 2.0, 3.0]}, r"init_d must be a scalar, \(2,\)"),
        ({"w_gen": 1.5}, "w_gen must be in"),
        ({"final_lambda": 0.0}, "final_lambda must be in"),
        ({"norm_in": [1.0, 0.0]}, "norm_in must be finite and > 0"),
        ({"max_rfs": 0}, "max_rfs"),
    ],
)
def test_bad_settings_are_rejected(kwargs, message):
    with pytest.raises(LwprError, match=message):
        LWPR(2, 1, **kwargs)


def test_unknown_settings_are_rejected():
    with pytest.raises(TypeError):
        LWPR(2, 1, init_D=25.0)  # type: ignore[call-arg]


@settings(max_examples=15, deadline=None)
@given(
    scale=st.floats(min_value=1e-3, max_value=1e3),
    x=st.lists(st.floats(min_value=-2.0, max_value=2.0), min_size=2, max_size=2),
)
def test_normalisation_makes_the_learner_unit_free(scale, x):
    """Inputs scaled by s with norm_in scaled by s learn the same function."""
    rng = np.random.default_rng(9)
    X = rng.uniform(-1, 1, (100, 2))
    a = LWPR(2, 1, init_d=5.0)
    b = LWPR(2, 1, init_d=5.0, norm_in=[scale, scale], norm_out=[scale])
    for xi in X:
        yi = np.sin(xi[0]) + xi[1]
        a.update(xi, [yi])
        b.update(xi * scale, [yi * scale])
    pa = a.predict(np.array(x))
    pb = b.predict(np.array(x) * scale)
    assert np.all(np.isfinite(pa))
    np.testing.assert_allclose(pb, pa * scale, rtol=1e-6, atol=1e-9 * scale)


def test_overlapping_fields_are_pruned_and_learning_goes_on():
    rng = np.random.default_rng(10)
    model = LWPR(2, 1, init_d=50.0, w_prune=0.5)
    reference = LWPR(2, 1, init_d=50.0)
    for _ in range(3000):
        x = rng.uniform(-1, 1, 2)
        y = [np.sin(3 * x[0]) * x[1]]
        model.update(x, y)
        reference.update(x, y)
    assert model.n_pruned[0] > 0
    assert reference.n_pruned[0] == 0
    assert model.num_rfs[0] < reference.num_rfs[0]
    X = rng.uniform(-1, 1, (300, 2))
    assert nmse(model, X, np.sin(3 * X[:, 0]) * X[:, 1]) < 0.02


@pytest.mark.filterwarnings("ignore::RuntimeWarning")
def test_fields_whose_statistics_overflow_are_dropped_not_kept():
    rng = np.random.default_rng(11)
    model = LWPR(2, 1, init_d=50.0)
    for _ in range(500):
        x = rng.uniform(-1, 1, 2)
        model.update(x, [x.sum()])
    before = model.num_rfs[0]
    model.update([0.1, 0.1], [1e300])  # finite, but beyond what the statistics can hold
    assert 0 < model.n_dropped <= before
    assert model.num_rfs[0] == before - model.n_dropped
    for x in rng.uniform(-1, 1, (50, 2)):
        assert np.all(np.isfinite(model.predict(x)))
    for _ in range(300):  # and it learns again where the fields were dropped
        x = rng.uniform(-0.3, 0.5, 2)
        model.update(x, [x.sum()])
    assert model.predict([0.1, 0.1])[0] == pytest.approx(0.2, abs=0.05)


# ------------------------------------------------ the compiled learner against numpy's


def cross_stream(n: int, seed: int = 0):
    """(x, y) samples of the cross demo: uniform in [-1, 1]^2, noise 0.1."""
    rng = np.random.default_rng(seed)
    for _ in range(n):
        x = rng.uniform(-1, 1, 2)
        yield x, cross(x[None])[0:1] + 0.1 * rng.standard_normal(1)


def drag_stream(n: int):
    """(velocity, velocity perturbation per tick) of bench_lwpr's drag flight in wind."""
    flight = DragFlight(seed=0)
    wind = np.array([2.0, -1.0, 0.0])
    for _ in range(n):
        z, p = flight.step(wind)
        yield z[3:6], p[3:6]


DRAG = {
    "init_d": 4.0,
    "init_lambda": 0.995,
    "final_lambda": 0.999,
    "tau_lambda": 0.999,
    "norm_in": [3.0] * 3,
    "norm_out": [0.01] * 3,
}
CROSS = {"init_d": 50.0, "init_alpha": 250.0}
ORACLE_CASES: dict[str, tuple[int, int, Callable[[], Iterator[Any]], dict[str, Any]]] = {
    "cross": (2, 1, lambda: cross_stream(10_000), CROSS),
    "cross-full-metric": (2, 1, lambda: cross_stream(2000, 1), {**CROSS, "diag_only": False}),
    "cross-meta": (2, 1, lambda: cross_stream(2000, 2), {**CROSS, "meta": True}),
    "cross-full-meta-pruning": (
        2, 1, lambda: cross_stream(2000, 3),
        {**CROSS, "diag_only": False, "meta": True, "w_prune": 0.5},
    ),
    "cross-fixed-metric-capped": (
        2, 1, lambda: cross_stream(2000, 4), {**CROSS, "update_d": False, "max_rfs": 12},
    ),
    "drag": (3, 3, lambda: drag_stream(3000), DRAG),
    "drag-per-axis": (1, 1, lambda: ((x[:1], y[:1]) for x, y in drag_stream(3000)), DRAG | {
        "norm_in": [3.0], "norm_out": [0.01]}),
}  # fmt: skip


# How far the compiled learner may drift from the numpy reference, from the arithmetic: both do
# the same operations in a different order (numba loops vs numpy reductions, FMA or not, per
# CPU and BLAS), so each update leaves each learned quantity with a relative rounding error of
# at most about OPS_PER_UPDATE * eps (OPS_PER_UPDATE: the longest sum an update forms, over
# the fields' projections, inputs and regressions, is below 100 terms in these cases). The
# forgetting factors (lambda < 1) damp old errors, so adding them up over k updates, linearly,
# is the worst case. A prediction is an activation-weighted mean of field predictions, so its
# error is that relative error times the output's magnitude (in normalised units, >= 1).
OPS_PER_UPDATE = 100
EPS = float(np.finfo(float).eps)


def prediction_tolerance(n_updates: int, y_norm: np.ndarray) -> np.ndarray:
    """The largest difference the rounding argument above allows, normalised output units."""
    return (n_updates + 1) * OPS_PER_UPDATE * EPS * np.maximum(1.0, np.abs(y_norm))  # type: ignore[no-any-return]


def confidence_tolerance(n_updates: int, y_norm: np.ndarray, conf_norm: np.ndarray,
                         cutoff: float) -> np.ndarray:
    """The confidence bound is sqrt(swc + swyy - swy * y) / sw: the square root of a
    cancellation (it is ~0 where the fields agree and are sure). An absolute error delta in
    the difference becomes sqrt(delta) / sw in the bound, whatever its size; delta is the
    relative rounding error times the terms' magnitude, sw * (conf^2 * sw + 2 y^2) <= sw * 3
    scale^2, and sw >= cutoff (no field below it is used), so the bound may move by
    sqrt(3 * relative error / cutoff) * scale. A 1e-17 cancellation residue alone is 3e-9."""
    scale2 = np.maximum(1.0, np.maximum(conf_norm, np.abs(y_norm))) ** 2
    rel = (n_updates + 1) * OPS_PER_UPDATE * EPS
    return np.sqrt(3.0 * rel * scale2 / cutoff)  # type: ignore[no-any-return]


@pytest.mark.skipif(not LWPR.compiled, reason="numba is not installed: LWPR is the reference")
@pytest.mark.parametrize("case", ORACLE_CASES)
def test_compiled_learner_follows_the_numpy_reference(case: str):
    """Same stream into both: every prediction-before-update, the fields, and predictions
    on a grid (predict, predict_many, predict_conf) agree all along, to what rounding in a
    different order allows (prediction_tolerance, confidence_tolerance)."""
    n_in, n_out, stream, kwargs = ORACLE_CASES[case]
    assert not LwprReference.compiled
    fast, ref = LWPR(n_in, n_out, **kwargs), LwprReference(n_in, n_out, **kwargs)
    norm_in = np.asarray(kwargs.get("norm_in", np.ones(n_in)))
    norm_out = np.asarray(kwargs.get("norm_out", np.ones(n_out)))
    probe = np.random.default_rng(12).uniform(-1.5, 1.5, (20, n_in)) * norm_in
    worst = 0.0  # the largest difference as a fraction of its tolerance

    def agree(a: np.ndarray, b: np.ndarray, tol: np.ndarray | None = None) -> float:
        """The difference as a fraction of its tolerance (prediction_tolerance by default);
        fails above 1."""
        diff = np.abs(a - b) / norm_out
        if tol is None:
            tol = prediction_tolerance(ref.n_updates, b / norm_out)
        ratio = float(np.max(diff / tol, initial=0.0))
        assert ratio <= 1.0, (float(np.max(diff)), float(np.min(tol)), ref.n_updates)
        return ratio

    for k, (x, y) in enumerate(stream()):
        worst = max(worst, agree(fast.update(x, y), ref.update(x, y)))
        if k % 500 == 499:
            assert fast.num_rfs == ref.num_rfs
            np.testing.assert_array_equal(fast._nreg[: fast._n], ref._nreg[: ref._n])
            worst = max(worst, agree(fast.predict_many(probe), ref.predict_many(probe)))
            for xp in probe[:5]:
                worst = max(worst, agree(fast.predict(xp), ref.predict(xp)))
                (y_fast, conf_fast), (y_ref, conf_ref) = fast.predict_conf(xp), ref.predict_conf(xp)
                agree(y_fast, y_ref)
                conf_tol = confidence_tolerance(
                    ref.n_updates, y_ref / norm_out, conf_ref / norm_out, ref.cutoff
                )
                worst = max(worst, agree(conf_fast, conf_ref, conf_tol))
    print(f"{case}: largest difference {worst:.1e} of its tolerance")
    assert fast.n_updates == ref.n_updates
    np.testing.assert_array_equal(fast.n_pruned, ref.n_pruned)
    assert any(fast.num_rfs)
    assert np.any(fast.predict_many(probe) != 0.0)
    if "w_prune" in kwargs:
        assert fast.n_pruned.sum() > 0  # the pruning path ran, and agreed
    if "max_rfs" in kwargs:
        assert fast.num_rfs == (kwargs["max_rfs"],)  # the cap was reached, and agreed


@pytest.mark.skipif(not LWPR.compiled, reason="numba is not installed: LWPR is the reference")
def test_compiled_and_reference_models_share_the_file_format():
    """A model saved by either loads into the other and goes on learning the same way."""
    fast = LWPR(3, 2, init_d=[10.0, 20.0, 5.0], norm_out=[2.0, 1.0])
    rng = np.random.default_rng(13)
    for _ in range(400):
        x = rng.uniform(-1, 1, 3)
        fast.update(x, [x @ [1.0, -2.0, 0.5], np.sin(2 * x[0]) * x[2]])
    ref = LwprReference.from_bytes(fast.to_bytes())
    assert isinstance(ref, LwprReference)
    assert ref.num_rfs == fast.num_rfs
    for x in rng.uniform(-1, 1, (300, 3)):
        y = [x.sum(), x[0] ** 2]
        y_ref = ref.update(x, y)
        tol = prediction_tolerance(ref.n_updates, y_ref / ref.norm_out) * ref.norm_out
        assert np.all(np.abs(fast.update(x, y) - y_ref) <= tol)
    back = LWPR.from_bytes(ref.to_bytes())
    X = rng.uniform(-1, 1, (50, 3))
    y_fast = fast.predict_many(X)
    tol = prediction_tolerance(fast.n_updates, y_fast / fast.norm_out) * fast.norm_out
    assert np.all(np.abs(back.predict_many(X) - y_fast) <= tol)


def test_warm_up_compiles_the_kernels_and_leaves_lwpr_usable():
    took_s = warm_up()
    assert took_s > 0.0 if LWPR.compiled else took_s == 0.0
    if LWPR.compiled:
        from epc_offboard.control import lwpr_kernels

        model = trained(n=200)  # inputs in other layouts reuse the compiled kernels
        X = np.random.default_rng(14).uniform(-1, 1, (20, 3))
        np.testing.assert_array_equal(model.predict_many(np.asfortranarray(X)),
                                      model.predict_many(X))  # fmt: skip
        np.testing.assert_array_equal(model.predict(X.T.copy().T[0]), model.predict(X[0]))
        model.update(X[:, ::-1][0], np.ones(2))
        for kernel in (lwpr_kernels.update, lwpr_kernels.predict_many):
            assert len(kernel.signatures) == 1  # type: ignore[union-attr]



@pytest.mark.skipif(not LWPR.compiled, reason="numba is not installed: nothing to compile")
def test_the_cascade_warm_up_compiles_every_lwpr_kernel_before_the_first_tick():
    """In a fresh interpreter (this one has compiled them already): after Cascade.warm_up,
    the service's READY point, update and predict_many need no compilation (the scratch
    ticks alone would not learn, and leave update to the first tick in flight)."""
    code = (
        "from epc_offboard.control import lwpr_kernels as k\n"
        "from epc_offboard.control.attitude import AttitudeControlConfig\n"
        "from epc_offboard.control.cascade import Cascade\n"
        "from epc_offboard.control.perturbation import EstimatorConfig\n"
        "from epc_offboard.control.position import PositionControlConfig\n"
        "c = Cascade(PositionControlConfig(), AttitudeControlConfig(), EstimatorConfig())\n"
        "before = (len(k.update.signatures), len(k.predict_many.signatures))\n"
        "c.warm_up()\n"
        "print(*before, len(k.update.signatures), len(k.predict_many.signatures))\n"
    )
    done = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, timeout=240, check=True
    )
    assert done.stdout.split() == ["0", "0", "1", "1"]
