"""LWPR benchmark: per-tick cost in the drag scenario, and accuracy on the cross function.

    python -m epc_offboard.tools.bench_lwpr [--json FILE] [--ticks N] [--train N]

1. Drag: a double integrator (position loop, state p(3), v(3), input acceleration(3))
   flies between random waypoints in wind with drag a_d = -k (v - v_wind), absent from its
   nominal model; an LWPR estimator (velocity in, the three velocity perturbations out)
   learns it. Then the cost of one control tick, ``update`` at the last query point plus
   ``predict`` at the new one (three outputs), and a prediction along a 20-step horizon, are
   timed at the field counts reached, as median and 99th percentile in microseconds, for the
   compiled LWPR (new) and the numpy reference (old) in the same state, with their ratio.
   Targets: median <= 30 us (update + predict) and <= 20 us (horizon).
2. Cross: the 2-D cross function of the LWPR papers, 500 noisy samples per epoch for 20
   epochs; normalised MSE on a noise-free 41 x 41 grid after each epoch, and field count.
"""

from __future__ import annotations

import argparse
import copy
import itertools
import json
import sys
import time
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt

from epc_offboard.control.lwpr import LWPR, LwprReference, warm_up
from epc_offboard.control.perturbation import EstimatorConfig, LwprPerturbation

FloatArray = npt.NDArray[np.float64]

TARGET_UPDATE_PREDICT_US = 30.0  # per sample, three outputs
TARGET_HORIZON_US = 20.0  # predictions along the horizon, per tick
HORIZON = 20  # steps of the position loop's horizon
# What is timed in each control tick (see _time_one_tick); "<part>_cpu": thread CPU time.
TICK_PARTS = ("update_predict", "horizon", "estimator_tick", "service_tick")
DT_S = 0.01  # the position loop's period (100 Hz)
NX = 6  # p(3), v(3)
NZ = 9  # z = [x; u], u = acceleration (3)
VELOCITY = (3, 4, 5)  # indices of v in x and z


@dataclass
class DragFlight:
    """Ground truth for the drag scenario: x = (p, v), u = a, with
    nominal x+ = (p + dt v, v + dt u) and truth x+ = (p + dt v, v + dt (u - k (v - v_wind)))."""

    seed: int
    k_drag_per_s: float = 0.4
    dt_s: float = DT_S
    x: FloatArray = field(default_factory=lambda: np.zeros(NX))
    target_m: FloatArray = field(default_factory=lambda: np.zeros(3))
    ticks: int = 0

    def __post_init__(self) -> None:
        self.rng = np.random.default_rng(self.seed)

    def step(self, v_wind_m_s: FloatArray) -> tuple[FloatArray, FloatArray]:
        """One tick flying between random waypoints (a new one every 1.5 s): returns the
        query point z = [x; u] and the measured perturbation p = x[k+1] - x_nom[k+1]."""
        if self.ticks % 150 == 0:
            self.target_m = self.rng.uniform(-6.0, 6.0, 3)
        self.ticks += 1
        p, v = self.x[:3], self.x[3:]
        u = np.clip(2.0 * (self.target_m - p) - 1.5 * v, -6.0, 6.0)
        z = np.r_[self.x, u]
        dt = self.dt_s
        nominal = np.r_[p + dt * v, v + dt * u]
        self.x = np.r_[p + dt * v, v + dt * (u - self.k_drag_per_s * (v - v_wind_m_s))]
        return z, self.x - nominal


def drag_estimator(**overrides: Any) -> LwprPerturbation:
    """The LWPR estimator of the drag scenario (velocity in, velocity perturbation out)."""
    settings: dict[str, Any] = {
        "inputs": VELOCITY,
        "outputs": VELOCITY,
        "lowpass_cutoff_hz": 2.0,
        "dt_s": DT_S,
        "norm_z": [1.0] * 3 + [3.0] * 3 + [1.0] * 3,  # velocities within a few m/s
        "norm_p": [1.0] * 3 + [0.01] * 3,  # velocity perturbation per tick ~ 1 cm/s
        "init_d": 4.0,
        "init_lambda": 0.995,
        "final_lambda": 0.999,  # forget on a ~10 s timescale: a changed wind is re-learned
        "tau_lambda": 0.999,
    }
    settings.update(overrides)
    return LwprPerturbation(NX, NZ, **settings)


def _stats_us(samples_s: list[float]) -> dict[str, float]:
    us = np.asarray(samples_s) * 1e6
    return {"median": float(np.median(us)), "p99": float(np.percentile(us, 99))}


def _time_one_tick(
    times: dict[str, list[float]],
    model: LWPR,
    drag_est: LwprPerturbation,
    service_est: LwprPerturbation,
    z: FloatArray,
    p: FloatArray,
    z_next: FloatArray,
    horizon: FloatArray,
) -> None:
    """Time one control tick of each kind (seconds, appended to ``times``): ``model`` (a copy
    of the drag estimator's learner) learns (z, p) and predicts at z_next, then along the
    horizon (rows of velocity); then each estimator's tick on the same sample."""
    vel = list(VELOCITY)
    zi, zn, pi = z[vel], z_next[vel], p[vel]
    # wall-clock and this thread's CPU time (the cost without time lost to other processes)
    wall, cpu = time.perf_counter, time.thread_time
    stamps = [(wall(), cpu())]
    model.update(zi, pi)
    model.predict(zn)
    stamps.append((wall(), cpu()))
    model.predict_many(horizon)
    stamps.append((wall(), cpu()))
    drag_est.observe(z, p)
    drag_est.estimate(z_next)
    stamps.append((wall(), cpu()))
    service_est.observe(zi, pi / DT_S)
    service_est.estimate(zn)
    service_est.variation(zn, horizon)
    stamps.append((wall(), cpu()))
    for key, (w0, c0), (w1, c1) in zip(TICK_PARTS, stamps[:-1], stamps[1:], strict=True):
        times[key].append(w1 - w0)
        times[key + "_cpu"].append(c1 - c0)


def _with_reference_models(est: LwprPerturbation) -> LwprPerturbation:
    """A copy of ``est`` whose learners are the numpy reference (the old LWPR), in the same
    learned state."""
    old = copy.deepcopy(est)
    old.models = [LwprReference.from_bytes(m.to_bytes()) for m in est.models]
    return old


def _service_estimator() -> LwprPerturbation:
    """The position loop's estimator as the cascade builds it by default: z = velocity,
    p = acceleration disturbance, one 1-D LWPR per axis."""
    cfg = replace(EstimatorConfig().lwpr, dt_s=DT_S)
    return LwprPerturbation.from_config(3, 3, cfg)


def bench_tick(train_ticks: int, timed_ticks: int, seed: int = 0) -> dict[str, Any]:
    """After ``train_ticks`` of learning, the compiled LWPR ("new") and a copy of it in the
    numpy reference implementation ("old") are timed on the same following samples, each
    learning them in turn: median / p99 of update + predict (three outputs), of a prediction
    along a 20-step horizon (``predict_many``, as ``LwprPerturbation.variation``), of the
    whole drag estimator tick (observe + estimate), and of the service's default estimator
    tick (observe + estimate + variation along the horizon; three 1-D learners)."""
    est, service = drag_estimator(), _service_estimator()
    flight = DragFlight(seed)
    wind = np.array([2.0, -1.0, 0.0])
    vel = list(VELOCITY)
    errors, truth = [], []
    for _ in range(train_ticks):
        z, p = flight.step(wind)
        errors.append(est.predict_raw(z)[vel] - p[vel])
        truth.append(p[vel])
        est.observe(z, p)
        service.observe(z[vel], p[vel] / DT_S)
    learner = est.models[0].to_bytes()
    pairs = {
        "new": (LWPR.from_bytes(learner), est, service),
        "old": (
            LwprReference.from_bytes(learner),
            _with_reference_models(est),
            _with_reference_models(service),
        ),
    }
    times: dict[str, dict[str, list[float]]] = {
        k: {part + cpu: [] for part in TICK_PARTS for cpu in ("", "_cpu")} for k in pairs
    }
    steps = np.arange(1, HORIZON + 1)[:, None] * DT_S
    samples = [flight.step(wind) for _ in range(timed_ticks + 1)]
    # One implementation after the other on the same samples (interleaved, each would run
    # with the caches the other left).
    for name, (model, drag_est, service_est) in pairs.items():
        for (z, p), (z_next, _) in itertools.pairwise(samples):
            horizon = z_next[vel] + steps * z_next[6:9]  # velocities at constant input
            _time_one_tick(times[name], model, drag_est, service_est, z, p, z_next, horizon)
    half = len(errors) // 2
    figures = {name: {k: _stats_us(v) for k, v in t.items()} for name, t in times.items()}
    return {
        "fields_per_output": list(est.models[0].num_rfs),
        "service_fields_per_axis": [m.num_rfs[0] for m in service.models],
        "train_ticks": train_ticks,
        "timed_ticks": timed_ticks,
        "horizon_steps": HORIZON,
        "compiled": LWPR.compiled,
        **figures,
        "ratio_old_over_new": {
            k: figures["old"][k]["median"] / figures["new"][k]["median"] for k in figures["new"]
        },
        "target_us": {"update_predict": TARGET_UPDATE_PREDICT_US, "horizon": TARGET_HORIZON_US},
        # one-step-ahead, online: each prediction made before its sample was learned
        "drag_nmse_second_half_of_training": float(
            np.mean(np.square(errors[half:])) / np.var(truth[half:])
        ),
    }


def cross(X: FloatArray) -> FloatArray:
    """max(exp(-10 x^2), exp(-50 y^2), 1.25 exp(-5 (x^2 + y^2))) for rows (x, y) of X."""
    x, y = X[:, 0], X[:, 1]
    a, b, c = np.exp(-10 * x**2), np.exp(-50 * y**2), 1.25 * np.exp(-5 * (x**2 + y**2))
    out: FloatArray = np.maximum(np.maximum(a, b), c)
    return out


def bench_cross(
    epochs: int = 20, seed: int = 0, learner: type[LWPR] = LWPR
) -> dict[str, Any]:
    """nMSE on the 41 x 41 grid after each epoch (the reference library's demo settings),
    and the median cost of one update (one 2-D sample)."""
    rng = np.random.default_rng(seed)
    axis = np.linspace(-1.0, 1.0, 41)
    grid = np.stack(np.meshgrid(axis, axis), -1).reshape(-1, 2)
    truth = cross(grid)
    model = learner(2, 1, init_d=50.0, init_alpha=250.0)
    nmse, update_s = [], []
    t0 = time.perf_counter()
    for _ in range(epochs):
        X = rng.uniform(-1.0, 1.0, (500, 2))
        Y = cross(X) + 0.1 * rng.standard_normal(500)
        for x, y in zip(X, Y, strict=True):
            t_update = time.perf_counter()
            model.update(x, [y])
            update_s.append(time.perf_counter() - t_update)
        pred = model.predict_many(grid)[:, 0]
        nmse.append(float(np.mean((pred - truth) ** 2) / np.var(truth)))
    return {
        "epochs": epochs,
        "nmse_per_epoch": nmse,
        "fields": model.num_rfs[0],
        "update_us": _stats_us(update_s),
        "seconds": time.perf_counter() - t0,
    }


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog="epc-offboard bench --lwpr",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument("--json", type=Path, help="also write the figures to this file")
    parser.add_argument("--ticks", type=int, default=2000, help="timed control ticks")
    parser.add_argument("--train", type=int, default=3000, help="drag learning ticks first")
    args = parser.parse_args(argv)
    warm_up()  # compile (or load) the kernels before anything is timed
    tick = bench_tick(args.train, args.ticks)
    cross_result = bench_cross()
    cross_old = bench_cross(learner=LwprReference)
    report = {"drag_tick": tick, "cross": cross_result, "cross_old": cross_old}
    labels = {
        "update_predict": "update + predict, 3 outputs",
        "horizon": f"predict_many along {HORIZON} steps, 3 outputs",
        "estimator_tick": "drag estimator tick (observe + estimate)",
        "service_tick": f"service estimator tick (3 x 1-D: observe, estimate, {HORIZON} steps)",
    }
    targets = {"update_predict": TARGET_UPDATE_PREDICT_US, "horizon": TARGET_HORIZON_US}
    print(
        f"drag: fields per output {tick['fields_per_output']} after {args.train} ticks "
        f"(service estimator: {tick['service_fields_per_axis']} per axis); LWPR compiled: "
        f"{tick['compiled']}. Median / p99 in us, old (numpy) -> new (compiled):"
    )
    for key, label in labels.items():
        old, new = tick["old"][key], tick["new"][key]
        cpu_old, cpu_new = tick["old"][key + "_cpu"], tick["new"][key + "_cpu"]
        target = f" (target median <= {targets[key]:.0f})" if key in targets else ""
        print(
            f"  {label}{target}:\n    wall {old['median']:.1f} / {old['p99']:.1f} -> "
            f"{new['median']:.1f} / {new['p99']:.1f}, "
            f"{tick['ratio_old_over_new'][key]:.1f}x; thread CPU median "
            f"{cpu_old['median']:.1f} -> {cpu_new['median']:.1f}, "
            f"{tick['ratio_old_over_new'][key + '_cpu']:.1f}x"
        )
    print(f"  drag nMSE {tick['drag_nmse_second_half_of_training']:.4f}")
    print(f"cross: {cross_result['fields']} fields; nMSE per epoch:")
    print("  " + " ".join(f"{e:.4f}" for e in cross_result["nmse_per_epoch"]))
    old_us, new_us = cross_old["update_us"], cross_result["update_us"]
    nmse_gap = np.subtract(cross_old["nmse_per_epoch"], cross_result["nmse_per_epoch"])
    print(
        f"  update, one 2-D sample: {old_us['median']:.1f} / {old_us['p99']:.1f} -> "
        f"{new_us['median']:.1f} / {new_us['p99']:.1f} us, "
        f"{old_us['median'] / new_us['median']:.1f}x; largest nMSE difference to the numpy "
        f"reference {np.max(np.abs(nmse_gap)):.1e}"
    )
    if args.json:
        args.json.write_text(json.dumps(report, indent=2) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
