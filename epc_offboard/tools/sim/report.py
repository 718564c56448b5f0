"""What `sim` hands a user: the docs/CONTRACTS.md report (``report.json``), its table, the
warnings, target verdicts and failures, and the exit code they decide. The figures are
:mod:`epc_offboard.tools.figures`.

The exit code is 1 when any flight failed, not only a declared target (issue 22): a vehicle
that left its envelope, a flight that did not finish (stopped by sim, a process that died),
a library moved aside as corrupt, fleet sharing asked for and unavailable. Each is named, on
stdout under the table and on stderr, and listed in the report's ``failures``."""

from __future__ import annotations

import json
import math
import sys
from pathlib import Path
from typing import Any, TextIO

from epc_offboard.common.cliargs import WindProfile
from epc_offboard.common.errors import EXIT_OK, EXIT_RUNTIME
from epc_offboard.tools.sim.analysis import VehicleResult
from epc_offboard.tools.sim.options import SimOptions
from epc_offboard.tools.tables import format_metric, print_table
from epc_offboard.tools.targets import evaluate

# "fleet rcvd": controllers that arrived from the fleet; "fleet used": those promoted into the
# library (both loops). "pos tick p99 us": wall time of a position tick, see TICK_NOTE
REPORT_COLUMNS = ("id", "RMSE cm", "max cm", "max m/s", "viol.", "hits", "lap-1 misses",
                  "QPs", "fleet rcvd", "fleet used", "pos Hz", "pos tick p99 us",
                  "att Hz", "deadline misses pos/att")  # fmt: skip
TICK_NOTE = (
    "pos tick: wall time of a position tick, start to end; in lockstep it includes waiting "
    "for the miss worker's QP solve (so runs are repeatable), and on a busy machine time "
    "off the CPU: no compute figure (`epc-offboard bench --service` measures those)"
)


def make_report(options: SimOptions, results: list[VehicleResult]) -> dict[str, Any]:
    """The docs/CONTRACTS.md `sim --json` report of one flight."""
    report: dict[str, Any] = {
        "scenario": options.scenario_name,
        "controller": options.controller,
        "adaptation": options.adaptation,
        "wind": {"speed_m_s": options.wind_speed_m_s, "dir_deg": options.wind_dir_deg},
        "duration_s": options.scenario.duration_s,
        "seed": options.seed,
        "note": options.scenario.note,
        "lockstep": bool(options.lockstep),
        "vehicles": [r.report for r in results],
    }
    if options.wind_profile != WindProfile():
        report["wind"]["profile"] = options.wind_profile.text
    # why the flights failed (the targets' verdicts are added by the caller that judges them)
    report["failures"] = flight_failures(report)
    return report


def strict_json(value: Any) -> Any:
    """``value`` with every non-finite float as None: JSON has no NaN or Infinity (Python
    writes a bare ``NaN`` that strict parsers reject), and null says "no figure" (a vehicle
    with no tracking window has no RMSE)."""
    if isinstance(value, float):
        return value if math.isfinite(value) else None
    if isinstance(value, dict):
        return {k: strict_json(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [strict_json(v) for v in value]
    return value


def write_json(report: dict[str, Any], *paths: Path | None) -> None:
    """The report, indented, to each path given (None: skipped); strict JSON."""
    text = json.dumps(strict_json(report), indent=2, allow_nan=False)
    for path in paths:
        if path is not None:
            path.write_text(text)


def method_targets(options: SimOptions, report: dict[str, Any]) -> list[dict[str, Any]]:
    """The scenario's declared targets that this one flight's method can be judged on."""
    verdicts = evaluate(options.scenario.targets, {options.method: report})
    return [v for v in verdicts if v["verdict"] != "n/a"]


def flight_failures(report: dict[str, Any]) -> list[str]:
    """Why the flights of a report failed, one sentence each (none: they did not)."""
    out = []
    for v in report["vehicles"]:
        who = f"vehicle {v['id']}"
        left = v.get("envelope", {}).get("left", [])
        for b in left:
            out.append(f"{who} left its envelope: {b['text']}")
        if v.get("stopped") and not (left and "left its envelope" in v["stopped"]):
            out.append(f"{who}: {v['stopped']}")
        elif not v.get("finished", True) and not v.get("stopped"):
            events = v.get("phase_events") or [{"phase": "none"}]
            out.append(f"{who}: the flight did not finish (last phase: {events[-1]['phase']})")
        if not v.get("flew_offboard", True) and not v.get("stopped"):
            out.append(f"{who}: never flew under offboard")
        if left and v.get("stopped"):
            out.append(f"{who}: {v['stopped'].split(' (')[0]}")
        for path in v.get("library_moved_aside", []):
            out.append(f"{who}: its library was unusable and moved aside to {path} (the "
                       "flight started with an empty library)")  # fmt: skip
        sharing = v.get("sharing", {})
        if sharing.get("asked") and not sharing.get("open"):
            out.append(f"{who}: fleet sharing was asked for and is unavailable (flew alone: "
                       "see its service.log)")  # fmt: skip
    return out


def target_failures(verdicts: list[dict[str, Any]]) -> list[str]:
    return [f"target failed: {v['target']}" for v in verdicts if v["verdict"] == "FAIL"]


def cm(value_m: float | None) -> str:
    """A length in metres as the tables print it: centimetres, "-" when not measured."""
    return "-" if value_m is None or not math.isfinite(value_m) else f"{value_m * 100:.2f}"


def report_rows(report: dict[str, Any]) -> list[list[str]]:
    """One row per vehicle of REPORT_COLUMNS: errors in cm, as the columns say."""
    rows = []
    for v in report["vehicles"]:
        loops = v.get("loops", {})
        pos, att = loops.get("position", {}), loops.get("attitude", {})
        lib = v["library"]
        epc = lib["hits"] + lib["misses"] > 0
        rows.append([
            str(v["id"]),
            cm(v["tracking"]["rmse_m"]),
            cm(v["tracking"]["max_error_m"]),
            f"{v['max_speed_m_s']:.2f}",
            str(v["constraint_violations"]),
            f"{lib['hit_rate'] * 100:.1f}%" if epc else "-",
            str(lib.get("first_lap_misses", "-")) if epc else "-",
            str(lib["qp_solves"]) if epc else "-",
            *_fleet_cells(v.get("fleet"), epc),
            f"{pos.get('rate_hz', 0.0):.1f}",
            f"{pos.get('compute_us_p99', 0.0):.0f}",
            f"{att.get('rate_hz', 0.0):.1f}",
            deadline_misses(loops),
        ])  # fmt: skip
    return rows


def with_mean_error(
    columns: tuple[str, ...], rows: list[list[str]], vehicles: list[dict[str, Any]], after: int
) -> tuple[tuple[str, ...], list[list[str]]]:
    """``columns`` and ``rows`` (one per vehicle) with "mean cm" (mean |p - p_d|, the
    scenario's extra metric) inserted after column ``after``."""
    cells = [cm(v["tracking"].get("mean_error_m")) for v in vehicles]
    return (
        (*columns[: after + 1], "mean cm", *columns[after + 1 :]),
        [[*r[: after + 1], c, *r[after + 1 :]] for r, c in zip(rows, cells, strict=True)],
    )


def _fleet_cells(fleet: dict[str, Any] | None, epc: bool) -> list[str]:
    """"fleet rcvd" and "fleet used" ("-" without EPC, or from a report without them)."""
    if not epc or not fleet:
        return ["-", "-"]
    return [str(fleet["controllers_received"]), str(sum(fleet["controllers_used"].values()))]


def deadline_misses(loops: dict[str, Any]) -> str:
    """ "position/attitude" ticks that missed their deadline ("-" for a loop not reported)."""
    return "/".join(str(loops.get(k, {}).get("deadline_misses", "-"))
                    for k in ("position", "attitude"))  # fmt: skip


def print_warnings(v: dict[str, Any], file: TextIO) -> None:
    """A vehicle's warnings: the counters on one line, each kind of logged line on its own
    (count, then its key: process, level, logger, message with variable parts masked)."""
    warnings = v.get("warnings", {})
    logged = v.get("warning_examples", {})
    counted = ", ".join(f"{name} {n}" for name, n in warnings.items() if name not in logged)
    if not warnings:
        print(f"vehicle {v['id']} warnings: none", file=file)
        return
    print(f"vehicle {v['id']} warnings:{' ' + counted if counted else ''}", file=file)
    for key in logged:
        print(f"  {warnings.get(key, 0)}x {key}", file=file)


def print_report(report: dict[str, Any], file: TextIO | None = None) -> None:
    """The report's table (rich on a terminal, plain aligned text when piped), the scenario's
    note when it has one, and each vehicle's warnings."""
    out = file if file is not None else sys.stdout
    title = f"{report['scenario']}: {report['controller']} + {report['adaptation']}"
    columns: tuple[str, ...] = REPORT_COLUMNS
    rows = report_rows(report)
    if any("mean_error_m" in v["tracking"] for v in report["vehicles"]):
        columns, rows = with_mean_error(columns, rows, report["vehicles"], after=1)
    print_table(title, columns, rows, file=out)
    if report.get("note"):
        print(f"note: {report['note']}", file=out)
    print(TICK_NOTE, file=out)
    for v in report["vehicles"]:
        print_warnings(v, out)


def exit_code(
    failures: list[str], verdicts: list[dict[str, Any]], file: TextIO | None = None
) -> int:
    """Each flight failure on stdout (``FAILED: ...``), them and the failed targets on
    stderr; the exit code (1 when any)."""
    for f in failures:
        print(f"FAILED: {f}", file=file)
    if failures:
        print(f"epc-offboard sim: failed: {'; '.join(failures)}", file=sys.stderr)
    targets = targets_exit_code(verdicts)
    return EXIT_RUNTIME if failures else targets


def print_targets(verdicts: list[dict[str, Any]], file: TextIO | None = None) -> None:
    """One line per target verdict, values in the metric's unit (errors in cm)."""
    for t in verdicts:
        value = format_metric(t["metric"], t["value"])
        bound = format_metric(t["metric"], t["bound"])
        print(f"target {t['verdict']}: {t['target']} ({value} <= {bound})", file=file)


def targets_exit_code(verdicts: list[dict[str, Any]]) -> int:
    """0 when no declared target failed, else 1 (named on stderr)."""
    failed = [v["target"] for v in verdicts if v["verdict"] == "FAIL"]
    if failed:
        print(f"epc-offboard sim: targets failed: {'; '.join(failed)}", file=sys.stderr)
        return EXIT_RUNTIME
    return EXIT_OK
