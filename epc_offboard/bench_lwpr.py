"""LWPR benchmark: per-tick cost in the drag scenario, and accuracy on the cross function.

    python -m epc_offboard.bench_lwpr [--json FILE] [--ticks N] [--train N]

1. Drag: a double integrator (position loop, state p(3), v(3), input acceleration(3))
   flies between random waypoints in wind with drag a_d = -k (v - v_wind), absent from its
   nominal model; an LWPR estimator (velocity in, the three velocity perturbations out)
   learns it. Then the cost of one control tick, ``update`` at the last query point plus
   ``predict`` at the new one (three outputs), is timed at the field counts reached, as
   median and 99th percentile in microseconds. Target: median <= 300 us.
2. Cross: the 2-D cross function of the LWPR papers, 500 noisy samples per epoch for 20
   epochs; normalised MSE on a noise-free 41 x 41 grid after each epoch, and field count.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt

from epc_offboard.lwpr import LWPR
from epc_offboard.perturbation import LwprPerturbation

FloatArray = npt.NDArray[np.float64]

TARGET_MEDIAN_US = 300.0
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


def bench_tick(train_ticks: int, timed_ticks: int, seed: int = 0) -> dict[str, Any]:
    """Median / p99 cost of update + predict (three outputs) after ``train_ticks`` of
    learning, and of the whole estimator tick (observe + low-pass filtered estimate)."""
    est = drag_estimator()
    flight = DragFlight(seed)
    wind = np.array([2.0, -1.0, 0.0])
    errors, truth = [], []
    for _ in range(train_ticks):
        z, p = flight.step(wind)
        errors.append(est.predict_raw(z)[list(VELOCITY)] - p[list(VELOCITY)])
        truth.append(p[list(VELOCITY)])
        est.observe(z, p)
    model = est.models[0]
    vel = list(VELOCITY)
    lwpr_us, lwpr_cpu_us, estimator_us = [], [], []
    z, p = flight.step(wind)
    for _ in range(timed_ticks):  # the learner alone: what the target is about
        z_next, p_next = flight.step(wind)
        zi, zn, pi = z[vel], z_next[vel], p[vel]
        c0, t0 = time.thread_time(), time.perf_counter()
        model.update(zi, pi)
        model.predict(zn)
        t1, c1 = time.perf_counter(), time.thread_time()
        lwpr_us.append((t1 - t0) * 1e6)
        lwpr_cpu_us.append((c1 - c0) * 1e6)
        z, p = z_next, p_next
    for _ in range(timed_ticks):  # then the whole estimator tick, on the following samples
        z_next, p_next = flight.step(wind)
        t0 = time.perf_counter()
        est.observe(z, p)
        est.estimate(z_next)
        estimator_us.append((time.perf_counter() - t0) * 1e6)
        z, p = z_next, p_next
    half = len(errors) // 2
    return {
        "fields_per_output": list(model.num_rfs),
        "train_ticks": train_ticks,
        "timed_ticks": timed_ticks,
        "update_predict_us": {
            "median": float(np.median(lwpr_us)),
            "p99": float(np.percentile(lwpr_us, 99)),
        },
        # CPU time of this thread: the cost without time lost to other processes
        "update_predict_cpu_us": {
            "median": float(np.median(lwpr_cpu_us)),
            "p99": float(np.percentile(lwpr_cpu_us, 99)),
        },
        "estimator_tick_us": {
            "median": float(np.median(estimator_us)),
            "p99": float(np.percentile(estimator_us, 99)),
        },
        "target_median_us": TARGET_MEDIAN_US,
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


def bench_cross(epochs: int = 20, seed: int = 0) -> dict[str, Any]:
    """nMSE on the 41 x 41 grid after each epoch (the reference library's demo settings)."""
    rng = np.random.default_rng(seed)
    axis = np.linspace(-1.0, 1.0, 41)
    grid = np.stack(np.meshgrid(axis, axis), -1).reshape(-1, 2)
    truth = cross(grid)
    model = LWPR(2, 1, init_d=50.0, init_alpha=250.0)
    nmse = []
    t0 = time.perf_counter()
    for _ in range(epochs):
        X = rng.uniform(-1.0, 1.0, (500, 2))
        Y = cross(X) + 0.1 * rng.standard_normal(500)
        for x, y in zip(X, Y, strict=True):
            model.update(x, [y])
        pred = np.array([model.predict(g)[0] for g in grid])
        nmse.append(float(np.mean((pred - truth) ** 2) / np.var(truth)))
    return {
        "epochs": epochs,
        "nmse_per_epoch": nmse,
        "fields": model.num_rfs[0],
        "seconds": time.perf_counter() - t0,
    }


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog="python -m epc_offboard.bench_lwpr",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument("--json", type=Path, help="also write the figures to this file")
    parser.add_argument("--ticks", type=int, default=2000, help="timed control ticks")
    parser.add_argument("--train", type=int, default=3000, help="drag learning ticks first")
    args = parser.parse_args(argv)
    tick = bench_tick(args.train, args.ticks)
    cross_result = bench_cross()
    report = {"drag_tick": tick, "cross": cross_result}
    up, est = tick["update_predict_us"], tick["estimator_tick_us"]
    print(f"drag: fields per output {tick['fields_per_output']} after {args.train} ticks")
    print(
        f"  update + predict, 3 outputs: median {up['median']:.0f} us, p99 {up['p99']:.0f} us "
        f"(target median <= {TARGET_MEDIAN_US:.0f} us); thread CPU time median "
        f"{tick['update_predict_cpu_us']['median']:.0f} us"
    )
    print(
        f"  estimator tick (observe + estimate): median {est['median']:.0f} us, "
        f"p99 {est['p99']:.0f} us; drag nMSE {tick['drag_nmse_second_half_of_training']:.4f}"
    )
    print(f"cross: {cross_result['fields']} fields; nMSE per epoch:")
    print("  " + " ".join(f"{e:.4f}" for e in cross_result["nmse_per_epoch"]))
    if args.json:
        args.json.write_text(json.dumps(report, indent=2) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
