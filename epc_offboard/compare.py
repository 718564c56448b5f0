"""`epc-offboard sim --compare`: one scenario flown by several methods, side by side.

Each method (``controller:adaptation``; default: the scenario's ``[compare] methods``) flies
the same scenario, wind and seed, one flight after another, from an empty controller library
and a fresh estimator, so the comparison is reproducible. Written to ``--out``:

* ``compare.json``: ``{"scenario", "methods", "reports": [CONTRACTS.md sim report, ...],
  "targets": [verdict, ...], "all_pass"}`` with the scenario's ``[[targets]]`` evaluated
  (:mod:`epc_offboard.targets`);
* ``compare.png``: in the style of the thesis's figures 3.4-3.7: every method's path against
  the reference, the tracking error over time, and the velocity against its bound;
* one directory per method with that flight's report.json, flight.png and logs.

Exit code 0 when every flight completed and no declared target failed; 1 when a flight failed
or a target did (the failed targets are named on stderr).
"""

from __future__ import annotations

import argparse
import json
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from epc_offboard.frames import FloatArray
from epc_offboard.sim import (
    ScenarioConfig,
    VehicleResult,
    fly_and_report,
    scenario_for,
    targets_exit_code,
)
from epc_offboard.targets import evaluate, method_name, parse_method


@dataclass(frozen=True)
class MethodRun:
    method: str
    report: dict[str, Any]
    results: list[VehicleResult]


def methods_for(args: argparse.Namespace, scenario: ScenarioConfig) -> tuple[str, ...]:
    """``--compare`` alone: the scenario's methods; ``--compare a:b,c:d``: those."""
    from epc_offboard.errors import UsageError

    text = str(args.compare).strip()
    if not text:
        return scenario.compare.methods
    methods = tuple(m.strip() for m in text.split(",") if m.strip())
    try:
        for m in methods:
            parse_method(m)
    except ValueError as exc:
        raise UsageError(f"--compare: {exc}") from exc
    if len(set(methods)) != len(methods):
        raise UsageError(f"--compare repeats a method: {text}")
    return methods


def fly_method(
    args: argparse.Namespace, scenario: ScenarioConfig, method: str, out_dir: Path
) -> tuple[MethodRun, FloatArray]:
    controller, adaptation = parse_method(method)
    run_args = argparse.Namespace(**{**vars(args), "controller": controller,
                                     "adaptation": adaptation, "compare": None})
    run_dir = out_dir / method.replace(":", "-")
    run_dir.mkdir(parents=True, exist_ok=True)
    for old in run_dir.glob("library-*.sqlite*"):  # learn from scratch: reproducible
        old.unlink()
    report, results, bounds = fly_and_report(
        run_args, scenario, run_dir, f"{args.scenario}: {method}"
    )
    return MethodRun(method, report, results), bounds


def run_compare_command(args: argparse.Namespace) -> int:
    from epc_offboard.errors import EXIT_RUNTIME

    scenario = scenario_for(args)
    methods = methods_for(args, scenario)
    out_dir = Path(args.out)
    out_dir.mkdir(parents=True, exist_ok=True)
    flown: list[MethodRun] = []
    bounds = np.full(3, np.inf)
    for method in methods:
        print(f"{args.scenario}: flying {method}", file=sys.stderr)
        try:
            run, bounds = fly_method(args, scenario, method, out_dir)
        except RuntimeError as exc:
            print(f"epc-offboard sim --compare: {method}: {exc}", file=sys.stderr)
            return EXIT_RUNTIME
        flown.append(run)
    reports = {r.method: r.report for r in flown}
    verdicts = evaluate(scenario.targets, reports)
    summary = {
        "scenario": args.scenario,
        "description": scenario.description,
        "methods": list(methods),
        "reports": [r.report for r in flown],
        "targets": verdicts,
        "all_pass": all(v["verdict"] == "PASS" for v in verdicts),
    }
    (out_dir / "compare.json").write_text(json.dumps(summary, indent=2))
    if args.json:
        Path(args.json).write_text(json.dumps(summary, indent=2))
    wind = args.wind or (scenario.wind_speed_m_s, scenario.wind_dir_deg)
    write_compare_figure(flown, bounds, out_dir / "compare.png", scenario, args.scenario, wind)
    print_compare(summary)
    print(f"report: {out_dir / 'compare.json'}  figure: {out_dir / 'compare.png'}")
    return targets_exit_code(verdicts)


# -- output ---------------------------------------------------------------------------------


def print_compare(summary: dict[str, Any]) -> None:
    from rich.console import Console
    from rich.table import Table

    console = Console(width=max(Console().width, 118))  # the table is wider than 80 columns
    table = Table(title=f"{summary['scenario']}: methods side by side (ground truth)")
    for col in ("method", "RMSE cm", "max cm", "max m/s", "viol.", "hits", "QPs",
                "us med", "us p99", "pos Hz", "att Hz"):  # fmt: skip
        table.add_column(col, justify="right")
    for rep in summary["reports"]:
        for v in rep["vehicles"]:
            pos = v.get("loops", {}).get("position", {})
            att = v.get("loops", {}).get("attitude", {})
            name = method_name(rep["controller"], rep["adaptation"])
            if len(rep["vehicles"]) > 1:
                name += f" #{v['id']}"
            lib = v["library"]
            table.add_row(
                name,
                f"{v['tracking']['rmse_m'] * 100:.2f}",
                f"{v['tracking']['max_error_m'] * 100:.2f}",
                f"{v['max_speed_m_s']:.2f}",
                str(v["constraint_violations"]),
                f"{lib['hit_rate'] * 100:.1f}%" if lib["hits"] + lib["misses"] else "-",
                str(lib["qp_solves"]),
                f"{pos.get('compute_us_median', 0.0):.0f}",
                f"{pos.get('compute_us_p99', 0.0):.0f}",
                f"{pos.get('rate_hz', 0.0):.1f}",
                f"{att.get('rate_hz', 0.0):.1f}",
            )
    console.print(table)
    if summary["targets"]:
        tt = Table(title="targets")
        for col in ("target", "value", "bound", "verdict"):
            tt.add_column(col, justify="left" if col == "target" else "right")
        for t in summary["targets"]:
            fmt = "{:.0f}" if t["metric"] == "constraint_violations" else "{:.4f}"
            value = "-" if t["value"] is None else fmt.format(t["value"])
            bound = "-" if t["bound"] is None else fmt.format(t["bound"])
            style = {"PASS": "green", "FAIL": "bold red"}.get(t["verdict"], "yellow")
            tt.add_row(t["target"], value, bound, f"[{style}]{t['verdict']}[/{style}]")
        console.print(tt)


def write_compare_figure(
    flown: list[MethodRun],
    vel_bounds_m_s: FloatArray,
    path: Path,
    scenario: ScenarioConfig,
    name: str,
    wind: tuple[float, float],
) -> None:
    """Thesis figs. 3.4-3.7 in one: paths vs reference, error over time, velocity vs bound."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (ax_path, ax_err, ax_vel) = plt.subplots(1, 3, figsize=(16, 4.8))
    # the horizontal axis the reference moves along most: the velocity panel's axis
    first = flown[0].results[0]
    axis = int(np.argmax(np.ptp(first.ref_ned_m[:, :2], axis=0)))
    axis_name = "NE"[axis]
    ref_drawn = False
    for run in flown:
        for r in run.results:
            after = r.t_s >= scenario.settle_s
            if not ref_drawn:
                ax_path.plot(r.ref_ned_m[after, 1], r.ref_ned_m[after, 0], "k--", lw=1.2,
                             label="reference")
                ref_v = np.gradient(r.ref_ned_m[:, axis], r.t_s)
                ax_vel.plot(r.t_s, ref_v, "k--", lw=1, label="reference")
                ref_drawn = True
            label = run.method if len(run.results) == 1 else f"{run.method} #{r.vehicle_id}"
            ax_path.plot(r.pos_ned_m[after, 1], r.pos_ned_m[after, 0], lw=1.3, label=label)
            ax_err.plot(r.t_s, r.error_m * 100.0, lw=1, label=label)
            ax_vel.plot(r.t_s, r.vel_ned_m_s[:, axis], lw=1, label=label)
    ax_path.set(xlabel="east [m]", ylabel="north [m]", title="path after settling (top view)")
    ax_path.set_aspect("equal", adjustable="datalim")
    ax_err.axvline(scenario.settle_s, color="grey", ls=":", lw=1)
    ax_err.set(xlabel="time since offboard [s]", ylabel="|position error| [cm]",
               title="tracking error (ground truth)")
    top = max(float(np.percentile(r.error_m[r.t_s >= scenario.settle_s], 99.5))
              for run in flown for r in run.results if np.any(r.t_s >= scenario.settle_s))
    ax_err.set_ylim(0.0, 1.3 * top * 100.0)
    bound = float(vel_bounds_m_s[axis])
    if np.isfinite(bound):
        for b in (bound, -bound):
            ax_vel.axhline(b, color="r", ls=":", lw=1.2)
        ax_vel.text(0.0, bound, f" bound {bound:g} m/s", color="r", va="bottom", fontsize=8)
    ax_vel.set(xlabel="time since offboard [s]", ylabel=f"v_{axis_name} [m/s]",
               title=f"{axis_name} velocity vs state constraint (ground truth)")
    for ax in (ax_path, ax_err, ax_vel):
        ax.grid(True, alpha=0.3)
        ax.legend(fontsize=7)
    wind_text = f", wind {wind[0]:g} m/s towards {wind[1]:g} deg" if wind[0] > 0 else ", no wind"
    fig.suptitle(f"{name}{wind_text}")
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)
