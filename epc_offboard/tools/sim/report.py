"""What `sim` hands a user: the CONTRACTS.md report (``report.json``), its table, the
warnings and target verdicts, and the exit code the targets decide. The figures are
:mod:`epc_offboard.tools.figures`."""

from __future__ import annotations

import json
import math
import sys
from pathlib import Path
from typing import Any, TextIO

from epc_offboard.common.errors import EXIT_OK, EXIT_RUNTIME
from epc_offboard.tools.sim.analysis import VehicleResult
from epc_offboard.tools.sim.options import SimOptions
from epc_offboard.tools.tables import format_metric, print_table
from epc_offboard.tools.targets import evaluate

# "fleet rcvd": controllers that arrived from the fleet; "fleet used": those promoted into the
# library (both loops). "pos tick p99 us": wall time of a position tick, see TICK_NOTE
REPORT_COLUMNS = ("id", "RMSE cm", "max cm", "max m/s", "viol.", "hits", "lap-1 misses",
                  "QPs", "fleet rcvd", "fleet used", "pos Hz", "pos tick p99 us",
                  "att Hz")  # fmt: skip
TICK_NOTE = (
    "pos tick: wall time of a position tick, start to end; in lockstep it includes waiting "
    "for the miss worker's QP solve (so runs are repeatable), and on a busy machine time "
    "off the CPU: no compute figure (`epc-offboard bench --service` measures those)"
)


def make_report(options: SimOptions, results: list[VehicleResult]) -> dict[str, Any]:
    """The CONTRACTS.md `sim --json` report of one flight."""
    return {
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
            f"{v['tracking']['rmse_m'] * 100:.2f}",
            f"{v['tracking']['max_error_m'] * 100:.2f}",
            f"{v['max_speed_m_s']:.2f}",
            str(v["constraint_violations"]),
            f"{lib['hit_rate'] * 100:.1f}%" if epc else "-",
            str(lib.get("first_lap_misses", "-")) if epc else "-",
            str(lib["qp_solves"]) if epc else "-",
            *_fleet_cells(v.get("fleet"), epc),
            f"{pos.get('rate_hz', 0.0):.1f}",
            f"{pos.get('compute_us_p99', 0.0):.0f}",
            f"{att.get('rate_hz', 0.0):.1f}",
        ])  # fmt: skip
    return rows


def _fleet_cells(fleet: dict[str, Any] | None, epc: bool) -> list[str]:
    """"fleet rcvd" and "fleet used" ("-" without EPC, or from a report without them)."""
    if not epc or not fleet:
        return ["-", "-"]
    return [str(fleet["controllers_received"]), str(sum(fleet["controllers_used"].values()))]


def print_report(report: dict[str, Any], file: TextIO | None = None) -> None:
    """The report's table (rich on a terminal, plain aligned text when piped), the scenario's
    note when it has one, and each vehicle's warnings."""
    out = file if file is not None else sys.stdout
    title = f"{report['scenario']}: {report['controller']} + {report['adaptation']}"
    print_table(title, REPORT_COLUMNS, report_rows(report), file=out)
    if report.get("note"):
        print(f"note: {report['note']}", file=out)
    print(TICK_NOTE, file=out)
    for v in report["vehicles"]:
        warnings = v.get("warnings", {})
        text = ", ".join(f"{name} {n}" for name, n in warnings.items()) or "none"
        print(f"vehicle {v['id']} warnings: {text}", file=out)


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
