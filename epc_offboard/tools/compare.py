"""`epc-offboard sim --compare`: one scenario flown by several methods, side by side.

Each method (``controller:adaptation``; default: the scenario's ``[compare] methods``) flies
the same scenario, wind and seed, one flight after another, from an empty controller library
and a fresh estimator, so the comparison is reproducible. Written to ``--out``:

* ``compare.json``: ``{"scenario", "methods", "reports": [docs/CONTRACTS.md sim report, ...],
  "targets": [verdict, ...], "all_pass"}`` with the scenario's ``[[targets]]`` evaluated
  (:mod:`epc_offboard.tools.targets`);
* ``compare.png``: in the style of the thesis's figures 3.4-3.7: every method's path against
  the reference, the tracking error over time, the speed against its bound and the tilt
  against its limit;
* one directory per method with that flight's report.json, flight.png (not with
  ``--no-figure``) and logs.

Exit code 0 when every flight completed and no declared target failed; 1 when a flight failed
(:func:`epc_offboard.tools.sim.report.flight_failures`) or a target did (both named on
stderr).
"""

from __future__ import annotations

import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Any, TextIO

import numpy as np

from epc_offboard.common.errors import EXIT_RUNTIME
from epc_offboard.common.frames import FloatArray
from epc_offboard.tools.figures import (
    PHASE_COLOURS,
    flight_title,
    mark_events,
    save_once,
    vehicle_colour,
    vehicle_style,
)
from epc_offboard.tools.sim.analysis import VehicleResult
from epc_offboard.tools.sim.options import SimOptions
from epc_offboard.tools.sim.orchestrate import fly_and_report
from epc_offboard.tools.sim.report import (
    TICK_NOTE,
    cm,
    deadline_misses,
    exit_code,
    flight_failures,
    print_warnings,
    target_failures,
    with_mean_error,
    write_json,
)
from epc_offboard.tools.sim.scenario import ScenarioConfig
from epc_offboard.tools.tables import format_metric, print_table
from epc_offboard.tools.targets import evaluate, method_name


@dataclass(frozen=True)
class MethodRun:
    method: str
    report: dict[str, Any]
    results: list[VehicleResult]


def fly_method(options: SimOptions, method: str, out_dir: Path) -> tuple[MethodRun, FloatArray]:
    """One method's flight into ``out_dir/CONTROLLER-ADAPTATION``, from an empty library;
    (the flight, its velocity bounds m/s (3,) NED)."""
    run_dir = out_dir / method.replace(":", "-")
    run_dir.mkdir(parents=True, exist_ok=True)
    for old in run_dir.glob("library-*.sqlite*"):  # learn from scratch: reproducible
        old.unlink()
    report, results, bounds = fly_and_report(options.flying(method), run_dir, options.scenario_name)
    return MethodRun(method, report, results), bounds


def run_compare(options: SimOptions) -> int:
    """Fly ``options.compare``'s methods one after another, report them side by side and
    judge the scenario's targets; the exit code."""
    scenario, name = options.scenario, options.scenario_name
    methods = options.compare or ()
    out_dir = options.out_dir
    out_dir.mkdir(parents=True, exist_ok=True)
    flown: list[MethodRun] = []
    bounds = np.full(3, np.inf)
    for method in methods:
        print(f"{name}: flying {method}", file=sys.stderr)
        try:
            run, bounds = fly_method(options, method, out_dir)
        except RuntimeError as exc:
            print(f"epc-offboard sim --compare: {method}: {exc}", file=sys.stderr)
            return EXIT_RUNTIME
        flown.append(run)
    reports = {r.method: r.report for r in flown}
    verdicts = evaluate(scenario.targets, reports)
    failures = [f"{r.method}: {f}" for r in flown for f in flight_failures(r.report)]
    summary = {
        "scenario": name,
        "description": scenario.description,
        "note": scenario.note,
        "methods": list(methods),
        "reports": [r.report for r in flown],
        "targets": verdicts,
        "all_pass": all(v["verdict"] == "PASS" for v in verdicts),
        "failures": failures + target_failures(verdicts),
    }
    write_json(summary, out_dir / "compare.json", options.json_path)
    write_compare_figure(flown, bounds, out_dir / "compare.png", scenario, name, options.wind,
                         options.autopilot)  # fmt: skip
    print_compare(summary)
    print(f"report: {out_dir / 'compare.json'}  figure: {out_dir / 'compare.png'}")
    return exit_code(failures, verdicts)


# -- output ---------------------------------------------------------------------------------


COMPARE_COLUMNS = ("method", "RMSE cm", "max cm", "max m/s", "viol.", "hits", "lap-1 misses",
                   "QPs", "pos tick us med", "pos tick us p99", "pos Hz",
                   "att Hz", "deadline misses pos/att")  # fmt: skip


def print_compare(summary: dict[str, Any], file: TextIO | None = None) -> None:
    """The methods side by side and the targets' verdicts (values in the metric's unit):
    rich tables on a terminal, plain aligned text when piped."""
    rows = []
    for rep in summary["reports"]:
        for v in rep["vehicles"]:
            pos = v.get("loops", {}).get("position", {})
            att = v.get("loops", {}).get("attitude", {})
            name = method_name(rep["controller"], rep["adaptation"])
            if len(rep["vehicles"]) > 1:
                name += f" #{v['id']}"
            lib = v["library"]
            epc = lib["hits"] + lib["misses"] > 0
            rows.append([
                name,
                cm(v["tracking"]["rmse_m"]),
                cm(v["tracking"]["max_error_m"]),
                f"{v['max_speed_m_s']:.2f}",
                str(v["constraint_violations"]),
                f"{lib['hit_rate'] * 100:.1f}%" if epc else "-",
                str(lib.get("first_lap_misses", "-")) if epc else "-",
                str(lib["qp_solves"]),
                f"{pos.get('compute_us_median', 0.0):.0f}",
                f"{pos.get('compute_us_p99', 0.0):.0f}",
                f"{pos.get('rate_hz', 0.0):.1f}",
                f"{att.get('rate_hz', 0.0):.1f}",
                deadline_misses(v.get("loops", {})),
            ])  # fmt: skip
    title = f"{summary['scenario']}: methods side by side (ground truth)"
    columns: tuple[str, ...] = COMPARE_COLUMNS
    vehicles = [v for rep in summary["reports"] for v in rep["vehicles"]]
    if any("mean_error_m" in v["tracking"] for v in vehicles):
        columns, rows = with_mean_error(columns, rows, vehicles, after=0)
    print_table(title, columns, rows, left=1, file=file, min_width=142)
    if summary.get("note"):
        print(f"note: {summary['note']}", file=file)
    print(TICK_NOTE, file=file)
    for rep in summary["reports"]:
        for v in rep["vehicles"]:
            print(f"{method_name(rep['controller'], rep['adaptation'])}: ", end="", file=file)
            print_warnings(v, file if file is not None else sys.stdout)
    if summary["targets"]:
        target_rows = [
            [t["target"], format_metric(t["metric"], t["value"]),
             format_metric(t["metric"], t["bound"]), t["verdict"]]
            for t in summary["targets"]
        ]  # fmt: skip
        print_table("targets", ("target", "value", "bound", "verdict"), target_rows,
                    left=1, file=file)  # fmt: skip


def _speed_m_s(r: VehicleResult) -> FloatArray:
    """(T,) the speed the velocity bound limits: the faster of |v_N| and |v_E| (the bound is
    a box, one bound per axis)."""
    return np.asarray(np.max(np.abs(r.vel_ned_m_s[:, :2]), axis=1))


def write_compare_figure(
    flown: list[MethodRun],
    vel_bounds_m_s: FloatArray,
    path: Path,
    scenario: ScenarioConfig,
    name: str,
    wind: tuple[float, float],
    autopilot: str = "px4",
) -> None:
    """Thesis figs. 3.4-3.7 in one: paths vs reference, error over time, and what a pilot
    checks against the vehicle's limits: the speed against its bound and the tilt against its
    limit; the window the RMSE is measured over shaded, one legend for the whole figure."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.patches import Patch

    fig, axes = plt.subplots(2, 2, figsize=(15, 10), layout="constrained")
    (ax_path, ax_err), (ax_speed, ax_tilt) = axes
    first = flown[0].results[0]
    settle = scenario.settle_s
    window_max = 0.0
    outside_max = 0.0
    tilt_peak = 0.0
    curves = [(run, r) for run in flown for r in run.results]
    for i, (run, r) in enumerate(curves):
        after = r.t_s >= settle
        label = run.method if len(run.results) == 1 else f"{run.method} #{r.vehicle_id}"
        label += f": RMSE {r.report['tracking']['rmse_m'] * 100:.2f} cm"
        # colour, dashes and width all differ, each drawn narrower over the earlier ones:
        # identical methods (EPC + KF equals MPC + KF) both stay visible
        colour, ls, lw = vehicle_colour(i), vehicle_style(i), max(0.9, 2.6 - 0.35 * i)
        ax_path.plot(r.pos_ned_m[after, 1], r.pos_ned_m[after, 0], color=colour, ls=ls,
                     lw=lw, label=label)  # fmt: skip
        ax_err.plot(r.t_s, r.error_m * 100.0, color=colour, ls=ls, lw=lw)
        ax_speed.plot(r.t_s, _speed_m_s(r), color=colour, ls=ls, lw=lw)
        if len(r.truth_tilt_deg) == len(r.truth_t_s) and len(r.truth_t_s):
            shown = (r.truth_t_s >= r.t_s[0]) & (r.truth_t_s <= r.t_s[-1])
            ax_tilt.plot(r.truth_t_s[shown], r.truth_tilt_deg[shown], color=colour, ls=ls, lw=lw)
            tilt_peak = max(tilt_peak, float(np.max(r.truth_tilt_deg[shown], initial=0.0)))
        if np.any(after):
            window_max = max(window_max, float(np.max(r.error_m[after])) * 100.0)
        if np.any(~after):
            outside_max = max(outside_max, float(np.max(r.error_m[~after])) * 100.0)
    # the reference last, thin and dashed over the flown paths: seen where they cover it
    after = first.t_s >= settle
    ax_path.plot(first.ref_ned_m[after, 1], first.ref_ned_m[after, 0], color="black",
                 ls=(0, (4, 3)), lw=1.0, zorder=10, label="reference")  # fmt: skip
    # under offboard only: before it the reference is where the vehicle was, and its jump
    # to the trajectory at entry is no speed
    moving = first.t_s > 0.05
    ref_v = np.column_stack([np.gradient(first.ref_ned_m[moving, k], first.t_s[moving])
                             for k in range(2)])  # fmt: skip
    ax_speed.plot(first.t_s[moving], np.max(np.abs(ref_v), axis=1), color="black",
                  ls=(0, (4, 3)), lw=1.0, zorder=10)  # fmt: skip
    ax_path.set(xlabel="east [m]", ylabel="north [m]",
                title="path after settling (top view, ground truth)")  # fmt: skip
    ax_path.set_aspect("equal", adjustable="datalim")
    t_lo = min(float(r.t_s[0]) for _, r in curves)
    t_hi = max(float(r.t_s[-1]) for _, r in curves)
    for ax in (ax_err, ax_speed, ax_tilt):
        if t_lo < 0.0:
            ax.axvspan(t_lo, 0.0, color=PHASE_COLOURS["to offboard"], alpha=0.6, lw=0, zorder=0)
        ax.axvspan(0.0, settle, color=PHASE_COLOURS["settle"], alpha=0.6, lw=0, zorder=0)
        ax.axvspan(settle, t_hi, color=PHASE_COLOURS["RMSE window"], alpha=0.6, lw=0, zorder=0)
        ax.set_xlim(t_lo, t_hi)
    mark_events([ax_err, ax_speed, ax_tilt], [r for _, r in curves])
    top = 1.15 * window_max if window_max > 0 else max(outside_max, 1.0)
    ax_err.set_ylim(0.0, max(top, 1.05 * outside_max) if outside_max <= 1.5 * top else top)
    if outside_max > 1.5 * top:
        ax_err.text(0.99, 0.97, f"clipped at {top:.3g} cm: the settle transient reaches "
                    f"{outside_max:.3g} cm", transform=ax_err.transAxes, ha="right", va="top",
                    fontsize=8, bbox={"fc": "white", "ec": "0.7", "alpha": 0.9})  # fmt: skip
    ax_err.set(xlabel="time since offboard entry [s]", ylabel="|position error| [cm]",
               title="tracking error (ground truth)")  # fmt: skip
    handles, labels = ax_path.get_legend_handles_labels()
    bound = float(np.max(vel_bounds_m_s[:2]))
    if np.isfinite(bound):
        line = ax_speed.axhline(bound, color="r", ls=":", lw=1.4)
        handles.append(line)
        labels.append(f"velocity bound {bound:g} m/s per horizontal axis")
    ax_speed.set_ylim(bottom=0.0)
    ax_speed.set(xlabel="time since offboard entry [s]", ylabel="max(|v_N|, |v_E|) [m/s]",
                 title="speed against its bound (ground truth; dashed: reference)")  # fmt: skip
    bounds = first.report.get("envelope", {}).get("bounds", {})
    limit = float(bounds.get("command_tilt_deg", np.nan))
    if np.isfinite(limit):
        line = ax_tilt.axhline(limit, color="darkred", ls="-.", lw=1.4)
        handles.append(line)
        labels.append(f"tilt limit {limit:g}° (envelope.max_tilt_deg)")
        ax_tilt.set_ylim(0.0, max(1.1 * limit, 1.1 * tilt_peak))
    ax_tilt.set(xlabel="time since offboard entry [s]", ylabel="tilt [deg]",
                title="tilt against its limit (ground truth)")  # fmt: skip
    handles += [Patch(color=PHASE_COLOURS["to offboard"], alpha=0.6),
                Patch(color=PHASE_COLOURS["settle"], alpha=0.6),
                Patch(color=PHASE_COLOURS["RMSE window"], alpha=0.6)]  # fmt: skip
    labels += ["entering offboard", f"settle (first {settle:g} s)", "RMSE window"]
    for ax in (ax_path, ax_err, ax_speed, ax_tilt):
        ax.grid(True, alpha=0.3)
    fig.legend(handles, labels, loc="outside lower center", ncols=min(len(labels), 4),
               fontsize=8, frameon=False)  # fmt: skip
    methods = " vs ".join(run.method for run in flown)
    fig.suptitle(flight_title(name, methods, autopilot, wind))
    save_once(fig, path)
    plt.close(fig)
