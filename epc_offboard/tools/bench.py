"""`epc-offboard bench`: EPC against OSQP and DAQP on one replayed closed-loop sequence.

(``bench --service`` replays a recorded flight through the service's ticks instead:
:mod:`epc_offboard.tools.bench_service`.)

The sequence: the position loop (NED double integrator, prediction step 0.05 s) follows a
lap of 500 steps — hover, an 8 m dash north-down (acceleration then velocity bounds
active), a 2.5 m/s circle (velocity bounds active on parts of it), a dash back — under a
constant known wind acceleration, repeated until ``--steps``. EPC flies the loop; its states
and references are recorded and replayed identically through OSQP (set up once, warm-started,
polished) and DAQP (set up once, hot-started from its previous working set). DAQP's solution
is the exact reference for ``max_input_error`` (OSQP's when DAQP is missing).
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from dataclasses import dataclass
from typing import Any

import numpy as np

from epc_offboard.common.errors import EpcError
from epc_offboard.common.frames import FloatArray
from epc_offboard.control.epc import ExperienceController
from epc_offboard.control.models import acceleration_box, position_model
from epc_offboard.control.qp import MpcProblem, OsqpSolver, QpStatus

DT_S = 0.05  # prediction step and replay step
LAP_STEPS = 500
V_MAX_M_S = 2.0
WIND_ACCEL_NED_M_S2 = np.array([0.3, -0.2, 0.0])
SEQUENCE = (
    "position loop NED, dt 0.05 s; lap of 500 steps: hover, 8 m dash N/down (accel+velocity "
    "bounds active), 2.5 m/s circle r=4 m (velocity bounds active), dash back; wind 0.3/-0.2 "
    "m/s^2 known; |v| <= 2 m/s per axis, accel box from 35 deg tilt, thrust 0.1..0.9"
)


class BenchError(EpcError, RuntimeError):
    pass


def reference_state(t_s: float) -> FloatArray:
    """Reference [p_ned (3), v_ned (3)] at time ``t_s`` (periodic with the lap)."""
    t = t_s % (LAP_STEPS * DT_S)
    dash = np.array([8.0, 0.0, -3.0])
    circle_c = dash + np.array([0.0, 4.0, 0.0])
    if t < 3.0:
        return np.zeros(6)
    if t < 8.0:
        return np.concatenate([dash, np.zeros(3)])
    if t < 20.0:
        w = 2.5 / 4.0
        a = w * (t - 8.0)
        p = circle_c + 4.0 * np.array([math.sin(a), -math.cos(a), 0.0])
        v = 2.5 * np.array([math.cos(a), math.sin(a), 0.0])
        return np.concatenate([p, v])
    return np.zeros(6)


def bench_problem(horizon: int) -> MpcProblem:
    box = acceleration_box(math.radians(35.0), 0.1, 0.9, 0.5)
    v = V_MAX_M_S
    return MpcProblem(
        position_model(DT_S),
        horizon=horizon,
        Q=[10.0, 10.0, 10.0, 1.0, 1.0, 1.0],
        R=[0.5, 0.5, 0.5],
        x_min=[-math.inf, -math.inf, -math.inf, -v, -v, -v],
        x_max=[math.inf, math.inf, math.inf, v, v, v],
        u_min=box.u_min,
        u_max=box.u_max,
    )


@dataclass(frozen=True)
class Timing:
    median_us: float
    p99_us: float

    @staticmethod
    def of(samples_s: list[float]) -> Timing:
        a = np.asarray(samples_s) * 1e6
        return Timing(float(np.median(a)), float(np.percentile(a, 99)))


class _DaqpSolver:
    """The condensed QP in DAQP's form: inputs as simple bounds, bounded states as two-sided
    general rows. Set up once; every solve updates f and the bounds and keeps the working set
    of the previous solve (hot start)."""

    def __init__(self, problem: MpcProblem, daqp: Any) -> None:
        p = problem
        self.p = p
        bounded = np.isfinite(p.x_min) | np.isfinite(p.x_max)
        rows = np.array([k * p.nx + i for k in range(p.horizon) for i in range(p.nx)
                         if bounded[i]], dtype=np.intp)
        # offset of the bounded predicted states from x0 and c~, precomputed once
        self.Phi_b = np.ascontiguousarray(p.Phi[rows])
        self.Psi_b = np.ascontiguousarray(p.Psi[rows])
        self.A = np.ascontiguousarray(p.Bbar[rows])
        big = 1e30
        self.xu = np.minimum(np.tile(p.x_max[bounded], p.horizon), big)
        self.xl = np.maximum(np.tile(p.x_min[bounded], p.horizon), -big)
        self.uu = np.minimum(np.tile(p.u_max, p.horizon), big)
        self.ul = np.maximum(np.tile(p.u_min, p.horizon), -big)
        self.model = daqp.Model()
        f = np.zeros(p.n_u)
        bu = np.concatenate([self.uu, self.xu])
        bl = np.concatenate([self.ul, self.xl])
        flag, _ = self.model.setup(np.ascontiguousarray(p.H), f, self.A, bu, bl)
        if flag < 0:
            raise BenchError(f"DAQP setup failed with exit flag {flag}")
        self._bu, self._bl = bu, bl

    def solve(self, theta: FloatArray) -> FloatArray:
        p = self.p
        nx, N = p.nx, p.horizon
        x0 = theta[:nx]
        c = theta[nx + N * nx : 2 * nx + N * nx]
        offset = self.Phi_b @ x0 + self.Psi_b @ c
        nu_all = p.n_u
        self._bu[nu_all:] = self.xu - offset
        self._bl[nu_all:] = self.xl - offset
        self.model.update(f=p.F @ theta, bupper=self._bu, blower=self._bl)
        x, _, flag, _ = self.model.solve()
        if flag < 1:
            raise BenchError(f"DAQP failed with exit flag {flag}")
        return np.asarray(x, dtype=np.float64)


def _replay_osqp(
    p: MpcProblem, thetas: FloatArray, *, polish: bool, eps: float
) -> tuple[FloatArray, list[float]]:
    osqp = OsqpSolver(p.H, p.G, polish=polish, eps_abs=eps, eps_rel=eps)
    times: list[float] = []
    U = np.empty((len(thetas), p.n_u))
    for k, th in enumerate(thetas):
        t0 = time.perf_counter()
        h, g = p.vectors(th)
        res = osqp.solve(h, g)
        times.append(time.perf_counter() - t0)
        if res.status not in (QpStatus.SOLVED, QpStatus.INACCURATE):
            raise BenchError(f"OSQP failed at step {k}: {res.status.value}")
        U[k] = res.x
    return U, times


def run_bench(horizon: int, steps: int) -> dict[str, Any]:
    """Run the benchmark; return the docs/CONTRACTS.md report plus extra fields: ``hit_rate_repeat``
    (hits after the first lap), EPC's solve counts, OSQP's settings, the problem size and
    which solver gave the exact reference."""
    if horizon < 2:
        raise BenchError(f"--horizon must be >= 2, got {horizon}")
    if steps < 1:
        raise BenchError(f"--steps must be >= 1, got {steps}")
    p = bench_problem(horizon)
    model = p.model
    wind = model.B @ WIND_ACCEL_NED_M_S2  # state increment per step from the wind
    # 1) the closed-loop sequence, flown once by an (untimed) EPC controller, which gives the
    #    exact optimum every tick; then every method replays the recorded states and refs
    pilot = ExperienceController(p, max_size=4000)
    x = np.zeros(p.nx)
    thetas = np.empty((steps, p.n_theta))
    states = np.empty((steps, p.nx))
    refs_all = np.empty((steps, horizon, p.nx))
    offsets = DT_S * np.arange(1, horizon + 1)
    for k in range(steps):
        t = k * DT_S
        refs_all[k] = [reference_state(t + o) for o in offsets]
        states[k] = x
        thetas[k] = p.theta(x, refs_all[k], perturbation=wind)
        x = model.step(x, pilot.step(x, refs_all[k], perturbation=wind).u, wind)

    # EPC from an empty library, query + check (+ learn on a miss) every step
    ctrl = ExperienceController(p, max_size=2000)
    u_epc = np.empty((steps, p.nu))
    t_epc: list[float] = []
    sources: list[str] = []
    for k in range(steps):
        x_k, r_k = states[k], refs_all[k]
        t0 = time.perf_counter()
        d = ctrl.step(x_k, r_k, perturbation=wind)
        t_epc.append(time.perf_counter() - t0)
        u_epc[k] = d.u
        sources.append(d.source)

    # 2) OSQP warm-started every step on the same data: polished at the accuracy EPC is held
    #    to, and (for reference) at OSQP's loose defaults without polishing
    U_osqp, t_osqp = _replay_osqp(p, thetas, polish=True, eps=1e-6)
    U_loose, t_loose = _replay_osqp(p, thetas, polish=False, eps=1e-3)

    # 3) DAQP hot-started every step (optional dependency)
    daqp_report: dict[str, Any]
    try:
        import daqp
    except ImportError:
        daqp = None
    if daqp is not None:
        solver = _DaqpSolver(p, daqp)
        t_daqp: list[float] = []
        U_exact = np.empty((steps, p.n_u))
        for k in range(steps):
            t0 = time.perf_counter()
            U_exact[k] = solver.solve(thetas[k])
            t_daqp.append(time.perf_counter() - t0)
        td = Timing.of(t_daqp)
        daqp_report = {"median_us": td.median_us, "p99_us": td.p99_us}
        exact_from = "daqp"
    else:
        daqp_report = {"median_us": None, "p99_us": None,
                       "missing": "daqp is not installed: pip install 'epc-offboard[bench]'"}
        U_exact = U_osqp
        exact_from = "osqp"

    repeat = np.array(sources[LAP_STEPS:]) if steps > LAP_STEPS else np.array([], dtype=str)
    st = ctrl.stats
    te, to, tl = Timing.of(t_epc), Timing.of(t_osqp), Timing.of(t_loose)
    return {
        "horizon": horizon,
        "steps": steps,
        "sequence": SEQUENCE,
        "methods": {
            "epc": {
                "median_us": te.median_us,
                "p99_us": te.p99_us,
                "hit_rate": st.hit_rate,
                "hit_rate_repeat": float(np.mean(repeat == "hit")) if repeat.size else None,
                "library_size": st.size,
                "qp_solves": st.qp_solves,
                "intermediate": st.intermediate,
                "fallback": st.fallback,
            },
            "osqp": {"median_us": to.median_us, "p99_us": to.p99_us,
                     "settings": "polish, eps 1e-6, warm start"},
            "osqp_loose": {"median_us": tl.median_us, "p99_us": tl.p99_us,
                           "settings": "no polish, eps 1e-3, warm start",
                           "max_input_error": float(np.max(np.abs(
                               U_loose[:, : p.nu] - U_exact[:, : p.nu])))},
            "daqp": daqp_report,
        },
        "max_input_error": float(np.max(np.abs(u_epc - U_exact[:, : p.nu]))),
        "active_fraction": active_fractions(p, thetas, U_exact),
        "exact_reference": exact_from,
        "decision_variables": p.n_u,
        "constraint_rows": p.n_con,
    }


def active_fractions(p: MpcProblem, thetas: FloatArray, U: FloatArray) -> dict[str, float]:
    """Fraction of steps whose exact optimum has an active velocity / input bound."""
    vel = acc = 0
    is_x = np.array([r.kind == "x" for r in p.rows], dtype=bool)
    for theta, u in zip(thetas, U, strict=True):
        _, gamma = p.vectors(theta)
        active = gamma - p.G @ u < 1e-7
        vel += bool(np.any(active & is_x))
        acc += bool(np.any(active & ~is_x))
    n = max(len(thetas), 1)
    return {"velocity_bound": vel / n, "input_bound": acc / n}


def format_table(report: dict[str, Any]) -> str:
    m = report["methods"]
    e, o, d = m["epc"], m["osqp"], m["daqp"]
    r = e["hit_rate_repeat"]
    repeat = "n/a, fewer steps than a lap" if r is None else f"{r:.3f}"

    def num(v: float | None) -> str:
        return f"{v:10.1f}" if v is not None else "         -"

    lines = [
        f"horizon {report['horizon']}, {report['steps']} steps, "
        f"{report['decision_variables']} variables, {report['constraint_rows']} rows",
        f"{'method':8s} {'median us':>10s} {'p99 us':>10s}",
        f"{'epc':8s} {num(e['median_us'])} {num(e['p99_us'])}   hit rate "
        f"{e['hit_rate']:.3f} (once repeating: {repeat}), library {e['library_size']}",
        f"{'osqp':8s} {num(o['median_us'])} {num(o['p99_us'])}   ({o['settings']})",
        f"{'osqp*':8s} {num(m['osqp_loose']['median_us'])} {num(m['osqp_loose']['p99_us'])}"
        f"   ({m['osqp_loose']['settings']}; max input error "
        f"{m['osqp_loose']['max_input_error']:.1e})",
        f"{'daqp':8s} {num(d['median_us'])} {num(d['p99_us'])}"
        + (f"   ({d['missing']})" if "missing" in d else ""),
        f"max |u_epc - u_exact| = {report['max_input_error']:.2e} "
        f"(exact: {report['exact_reference']}); steps with an active velocity bound "
        f"{report['active_fraction']['velocity_bound']:.2f}, input bound "
        f"{report['active_fraction']['input_bound']:.2f}",
    ]
    if d.get("median_us"):
        lines.append(
            f"epc/daqp median {e['median_us'] / d['median_us']:.2f} (target <= 1), "
            f"epc/osqp median {e['median_us'] / o['median_us']:.3f} (target <= 0.05)"
        )
    return "\n".join(lines)


def run_bench_command(args: argparse.Namespace) -> int:
    from epc_offboard.common import jit

    if getattr(args, "fleet", False):
        from epc_offboard.tools.bench_fleet import run_fleet_bench_command

        return run_fleet_bench_command(list(args.vehicles), args.json,
                                       getattr(args, "late_joiner", False))
    # every bench but the fleet's (its light vehicles run no kernel) compiles the kernels
    jit.announce_cold_compile("bench")
    if getattr(args, "lwpr", False):
        from epc_offboard.tools import bench_lwpr

        return bench_lwpr.main(["--json", args.json] if args.json else [])
    if getattr(args, "attack", False):
        from epc_offboard.tools.bench_attack import (
            ATTACKS,
            AttackBenchError,
            AttackOptions,
            parse_attacks,
            run_attack_bench,
        )

        try:
            attacks = getattr(args, "attacks", None)
            opts = AttackOptions(
                autopilot=str(getattr(args, "autopilot", "px4")),
                attack_s=float(getattr(args, "attack_s", 10.0)),
                attacks=parse_attacks(attacks) if attacks else ATTACKS,
                signing=bool(getattr(args, "signing", False)),
                forge=bool(getattr(args, "forge", False)),
                freeze=getattr(args, "freeze", None),
                freeze_s=float(getattr(args, "freeze_s", 20.0)),
                probe=bool(getattr(args, "probe", True)),
                probe_priority=int(getattr(args, "probe_priority", 50)),
            )  # fmt: skip
            return run_attack_bench(args.json, int(args.hogs), str(args.attitude_mode),
                                    loops_cpu=getattr(args, "loops_cpu", None),
                                    sitl_cpu=getattr(args, "sitl_cpu", None), opts=opts)
        except AttackBenchError as exc:
            print(f"epc-offboard bench --attack: {exc}", file=sys.stderr)
            return 1
    if getattr(args, "link", False):
        from epc_offboard.tools.bench_link import run_link_bench_command

        return run_link_bench_command(args.json, int(args.steps) * 10)
    if getattr(args, "modes", False):
        from epc_offboard.tools.bench_modes import run_modes_bench

        return run_modes_bench(args)
    if getattr(args, "service", False):
        from epc_offboard.tools.bench_service import ServiceBenchError, run_service_bench

        try:
            return run_service_bench(args.recording, float(args.duration), args.json)
        except ServiceBenchError as exc:
            print(f"epc-offboard bench --service: {exc}", file=sys.stderr)
            return 1
    try:
        report = run_bench(int(args.horizon), int(args.steps))
    except BenchError as exc:
        print(f"epc-offboard bench: {exc}", file=sys.stderr)
        return 2 if "must be" in str(exc) else 1
    print(format_table(report))
    if args.json:
        with open(args.json, "w", encoding="utf-8") as fh:
            json.dump(report, fh, indent=2)
            fh.write("\n")
    return 0
