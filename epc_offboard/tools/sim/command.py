"""`epc-offboard sim`: the command line's entry (the only part that sees argparse).

One flight by default; ``--compare`` flies several methods (:mod:`epc_offboard.tools.compare`).
Writes, to ``--out``: ``report.json`` (docs/CONTRACTS.md shape) with the scenario's targets this
method can be judged on, ``flight.png``, and per vehicle the flight log, the .tlog, the ground
truth and both processes' logs. Exit code 0, 1 when a flight or a declared target failed
(:mod:`.report` says what fails a flight), 2 on bad usage.
"""

from __future__ import annotations

import argparse
import sys

from epc_offboard.common import jit
from epc_offboard.common.children import die_with_launcher
from epc_offboard.common.errors import EXIT_RUNTIME
from epc_offboard.tools.sim.options import SimOptions, sim_options
from epc_offboard.tools.sim.orchestrate import check_ports, fly_and_report, stop_on_sigterm
from epc_offboard.tools.sim.report import (
    exit_code,
    flight_failures,
    method_targets,
    print_report,
    print_targets,
    target_failures,
    write_json,
)


def run_sim_command(args: argparse.Namespace) -> int:
    stop_on_sigterm()
    # started by a launcher (`figures neuralfly`): SIGTERM when it dies, which the handler
    # above turns into stopping this sim's SITLs and services (a killed launcher left them
    # flying). After the handler: the signal may come at once
    die_with_launcher()
    options = sim_options(args)
    try:
        check_ports(options)
    except OSError as exc:
        print(f"epc-offboard sim: {exc}", file=sys.stderr)
        return EXIT_RUNTIME
    # the services start with EPC_OFFBOARD_JIT=1 (orchestrate.service_env): on a cold cache
    # each compiles before its first tick, 1-2 min of silence on a fresh install
    jit.announce_cold_compile("sim")
    if options.compare is not None:
        from epc_offboard.tools.compare import run_compare

        return run_compare(options)
    return run_one(options)


def run_one(options: SimOptions) -> int:
    """One flight of one method, reported; the exit code."""
    out_dir = options.out_dir
    out_dir.mkdir(parents=True, exist_ok=True)
    try:
        report, _results, _bounds = fly_and_report(options, out_dir, options.scenario_name)
    except RuntimeError as exc:
        print(f"epc-offboard sim: {exc}", file=sys.stderr)
        return EXIT_RUNTIME
    report["targets"] = method_targets(options, report)
    failures = flight_failures(report)
    report["failures"] = failures + target_failures(report["targets"])
    write_json(report, out_dir / "report.json", options.json_path)
    print_report(report)
    print_targets(report["targets"])
    figure = f"  figure: {out_dir / 'flight.png'}" if options.figure else ""
    print(f"report: {out_dir / 'report.json'}{figure}")
    return exit_code(failures, report["targets"])
