"""The `epc-offboard` command line (docs/CONTRACTS.md): run, sim, bench, db.

Exit codes: 0 success, 2 bad usage or invalid config, 1 runtime failure. Each subcommand's
implementation lives in its own module and is imported only when used, so `epc-offboard --help`
stays fast and a broken optional piece cannot stop the others.
"""

from __future__ import annotations

import argparse
import importlib
import sys
from collections.abc import Callable, Sequence
from typing import TypeAlias, cast

from epc_offboard.common.cliargs import (
    WIND_PROFILE_HELP,
    bounded_int,
    join_negative_values,
    parse_wind,
    parse_wind_profile,
    port_number,
    positive_number,
)
from epc_offboard.common.configio import ConfigError
from epc_offboard.common.errors import EXIT_RUNTIME, EXIT_USAGE, UsageError
from epc_offboard.tools.db import add_db_arguments

# subcommand -> "module:function(args) -> exit code"
_COMMANDS = {
    "run": "epc_offboard.service.coldstart:run",  # the kernels chosen before they import
    "sim": "epc_offboard.tools.sim.command:run_sim_command",
    "bench": "epc_offboard.tools.bench:run_bench_command",
    "db": "epc_offboard.tools.db:run_db_command",
    "log": "epc_offboard.tools.logexport:run_log_command",
    "figures": "epc_offboard.tools.readme:run_figures_command",
    "fleet": "epc_offboard.fleet.router:run_router_command",
}


class _HelpFormatter(argparse.HelpFormatter):
    """Every flag's help ends with its default, unless it says the default itself or has
    none (a switch, an optional file)."""

    def _get_help_string(self, action: argparse.Action) -> str:
        text = action.help or ""
        shown = action.default not in (None, False, True, argparse.SUPPRESS)
        if shown and "default" not in text and action.option_strings:
            text += " (default: %(default)s)"
        return text


def build_parser() -> argparse.ArgumentParser:
    from epc_offboard import __version__

    fmt = _HelpFormatter
    parser = argparse.ArgumentParser(
        prog="epc-offboard",
        description="MAVLink offboard flight controller running Experience-driven Predictive "
        "Control (EPC) with LWPR model learning.",
        formatter_class=fmt,
    )
    parser.add_argument("--version", action="version", version=f"%(prog)s {__version__}")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")

    run = sub.add_parser("run", help="run the offboard service (daemon)", formatter_class=fmt)
    run.add_argument(
        "--config", required=True, metavar="FILE",
        help="service config TOML, or the name of a bundled one: default (config/default.toml:"
        " a real vehicle), sitl (config/sitl.toml: flies `epc-sitl --instance 0`)",
    )  # fmt: skip
    _add_sim(sub)
    _add_bench(sub)
    db = sub.add_parser(
        "db",
        help="the controller library on disk: info, export, import, merge",
        description="Inspect a library file, export it, import an export or merge other "
        "vehicles' library files into it (same problem signature only).",
        formatter_class=fmt,
    )
    add_db_arguments(db)
    _add_log(sub)
    _add_figures(sub)
    _add_fleet(sub)
    return parser


# the subparsers' action: argparse has no public name for its type
_Subparsers: TypeAlias = "argparse._SubParsersAction[argparse.ArgumentParser]"


def _add_sim(sub: _Subparsers) -> None:
    from epc_offboard.common.bundled import scenario_dir

    fmt = _HelpFormatter
    sim = sub.add_parser(
        "sim", help="fly the bundled SITL with the service and report", formatter_class=fmt
    )
    scenarios = ", ".join(sorted(p.stem for p in scenario_dir().glob("*.toml")))
    sim.add_argument(
        "--scenario", default="hover", metavar="NAME",
        help=f"one of {scenarios} (config/scenarios/NAME.toml), or a path to a scenario TOML",
    )  # fmt: skip
    # None when not given: --compare names its methods itself and rejects these
    sim.add_argument(
        "--controller",
        choices=["epc", "pd", "mpc", "px4"],
        default=None,
        help="position controller: epc (the default), pd (thesis A.1), mpc (OSQP every tick), "
        "px4 (a baseline: the autopilot's own position controller fed position, velocity and "
        "acceleration setpoints)",
    )
    sim.add_argument(
        "--adaptation", choices=["lwpr", "kf", "none"], default=None,
        help="disturbance estimate: LWPR (thesis 3.1.1, the default), a Kalman observer, or "
        "none",
    )  # fmt: skip
    sim.add_argument(
        "--vehicles", type=bounded_int(1), default=1, metavar="N",
        help="N SITLs and N services, sharing their libraries over Zenoh",
    )  # fmt: skip
    mode = sim.add_mutually_exclusive_group()
    mode.add_argument(
        "--lockstep", dest="lockstep", action="store_true", default=True,
        help="the SITL advances only when the controller has answered: deterministic "
        "(the default)",
    )  # fmt: skip
    mode.add_argument(
        "--realtime", dest="lockstep", action="store_false",
        help="real time, for timing measurements",
    )  # fmt: skip
    sim.add_argument(
        "--wind", type=parse_wind, default=None, metavar="SPEED_M_S,DIR_DEG",
        help="wind speed towards DIR degrees, counter-clockwise from east (default: the "
        "scenario's)",
    )  # fmt: skip
    sim.add_argument(
        "--wind-profile", type=parse_wind_profile, default=None, metavar="SPEC",
        help=WIND_PROFILE_HELP + " (default: the scenario's, steady)",
    )  # fmt: skip
    sim.add_argument(
        "--seed", type=bounded_int(0), default=0, help="noise and gust seed"
    )
    sim.add_argument(
        "--gcs-port", type=port_number, default=None, metavar="PORT",
        help="where QGroundControl or MAVProxy watch the flight (udpin:127.0.0.1:PORT): the "
        "SITLs send their ground-station stream there, as PX4 SITL does to 14550 (default "
        "with --autopilot px4); with ardupilot, vehicle k serves TCP on PORT + 10 (k - 1) "
        "(default: none); 0: no stream",
    )  # fmt: skip
    sim.add_argument(
        "--autopilot", choices=["px4", "ardupilot"], default="px4",
        help="the SITL's autopilot personality; ardupilot starts it with GUID_OPTIONS=8 "
        "(thrust as throttle), as the README asks of a real ArduCopter",
    )  # fmt: skip
    sim.add_argument(
        "--duration", type=positive_number, default=None, metavar="S",
        help="seconds on the trajectory (default: the scenario's duration_s)",
    )  # fmt: skip
    sim.add_argument(
        "--no-share",
        action="store_true",
        help="with --vehicles N > 1: no library sharing over Zenoh (by default vehicle k "
        "listens on tcp/127.0.0.1:(7446+k) and connects to the others)",
    )
    sim.add_argument(
        "--fleet-router",
        metavar="ENDPOINT",
        help="share through this Zenoh router (e.g. tcp/127.0.0.1:24447, an `epc-offboard "
        "fleet router` or zenohd) as its clients instead of as peers on the fixed ports; "
        "shares with --vehicles 1 too",
    )
    sim.add_argument(
        "--realtime-priority", type=int, default=None, metavar="P",
        help="each service's loops (loops.realtime_priority) and each SITL SCHED_FIFO at P "
        "(1..99; needs CAP_SYS_NICE: a refusal is said in the report and the flight goes on), "
        "as an autopilot on hardware of its own; 0: off. Default: with --realtime the "
        "configured loops.realtime_priority (config/default.toml: 50), in lockstep off",
    )  # fmt: skip
    sim.add_argument(
        "--stagger",
        action="store_true",
        help="start vehicle k only after vehicle k-1 has flown the whole scenario and "
        "landed; landed vehicles stay up, answering library queries, until the last lands. "
        "Measures what a vehicle joining after others have flown gains from their library",
    )
    sim.add_argument(
        "--out", default="out", metavar="DIR",
        help="report.json, flight.png and per-vehicle logs, tlogs and libraries",
    )  # fmt: skip
    sim.add_argument(
        "--json", default=None, metavar="FILE", help="also write the report JSON here"
    )
    sim.add_argument(
        "--no-figure", action="store_true",
        help="no flight.png (flights judged on report.json alone: its drawing takes 2-3 s "
        "of CPU a flight); --compare still draws compare.png",
    )  # fmt: skip
    sim.add_argument(
        "--compare",
        nargs="?",
        const="",
        default=None,
        metavar="CTRL:ADAPT,...",
        help="fly several methods side by side (default: the scenario's [compare] methods), "
        "e.g. --compare epc:lwpr,pd:none; writes compare.json and compare.png",
    )



def _add_bench(sub: _Subparsers) -> None:
    fmt = _HelpFormatter
    bench = sub.add_parser(
        "bench", help="compute benchmark: EPC vs OSQP vs DAQP", formatter_class=fmt
    )
    bench.add_argument("--horizon", type=int, default=20, metavar="N", help="QP horizon")
    bench.add_argument(
        "--steps", type=int, default=2000, metavar="K", help="length of the replayed sequence"
    )
    bench.add_argument("--json", default=None, metavar="FILE", help="write the report JSON here")
    bench.add_argument(
        "--service",
        action="store_true",
        help="instead: replay a recorded windy lockstep flight through the service's whole "
        "position and attitude ticks (decode, state, estimator, EPC, encode); prints median / "
        "p99 / max per component, hits, misses and worker solves; with --json also a "
        "histogram figure (FILE with .png)",
    )
    bench.add_argument(
        "--recording",
        default=None,
        metavar="DIR",
        help="with --service: a sim run's vehicle directory (session.tlog, service.toml, "
        "flight.csv) to replay (default: fly a lockstep figure-8 in 3 m/s wind now)",
    )
    bench.add_argument(
        "--duration",
        type=float,
        default=12.0,
        metavar="S",
        help="with --service: seconds of offboard flight to record (default: 12, one lap)",
    )
    bench.add_argument(
        "--link",
        action="store_true",
        help="instead: the MAVLink receive path's cost per datagram, genuine and fuzzed, "
        "pymavlink's parser against the header-first path (ratios printed)",
    )
    bench.add_argument(
        "--attack",
        action="store_true",
        help="instead: issue 21's attacks (Zenoh flood, rotating ids, replay, token flaps, "
        "fuzzed MAVLink), 10 s each, on one real-time SITL flight (hover, then the windy "
        "figure-8); prints each window and issue 21's targets with verdicts; with --json also "
        "a figure (FILE with .png) and the flight's files (FILE without suffix)",
    )
    bench.add_argument(
        "--hogs", type=bounded_int(0), default=0, metavar="N",
        help="with --attack or --modes: N CPU hogs beside the real-time flights",
    )  # fmt: skip
    bench.add_argument(
        "--attitude-mode", choices=["quaternion", "rates"], default="quaternion",
        help="with --attack: quaternion (config/default.toml's) or body rates (config/sitl.toml's)",
    )  # fmt: skip
    bench.add_argument(
        "--loops-cpu", type=bounded_int(0), default=None, metavar="CPU",
        help="with --attack: the service's loops pinned to CPU (loops.cpu_affinity)",
    )  # fmt: skip
    bench.add_argument(
        "--sitl-cpu", type=bounded_int(0), default=None, metavar="CPU",
        help="with --attack: the SITL (the autopilot) pinned to CPU",
    )  # fmt: skip
    bench.add_argument(
        "--attack-s", type=float, default=10.0, metavar="S",
        help="with --attack: each attack's length in seconds (default 10)",
    )  # fmt: skip
    bench.add_argument(
        "--attacks", default=None, metavar="A[,A...]",
        help="with --attack: which attacks, in order: flood, rotate, replay, flap, fuzz, or "
        "two joined by '+' run at once, e.g. flood+fuzz (default: the five, one by one)",
    )  # fmt: skip
    bench.add_argument(
        "--signing", action="store_true",
        help="with --attack: MAVLink 2 signing on (a fresh key for the service and the SITL; "
        "the fuzzer has none)",
    )  # fmt: skip
    bench.add_argument(
        "--forge", action="store_true",
        help="with --attack: the fuzzer also forges a coherent state stream from the "
        "vehicle's own ids (fuzz_mavlink --forge)",
    )  # fmt: skip
    bench.add_argument(
        "--freeze", choices=["fleet", "store", "miss", "log", "pump", "sitl"], default=None,
        help="with --attack: SIGSTOP this helper process (fleet session, store writer, miss "
        "worker, flight-log writer, log pump) or the SITL (the autopilot's link silent) for "
        "--freeze-s from each phase's first attack, then SIGCONT",
    )  # fmt: skip
    bench.add_argument(
        "--freeze-s", type=float, default=20.0, metavar="S",
        help="with --freeze: seconds the helper stays stopped (default 20)",
    )  # fmt: skip
    bench.add_argument(
        "--no-probe", dest="probe", action="store_false",
        help="with --attack: no bare 200 Hz loops beside the service (the machine's floor, "
        "measured by default: floor_probe)",
    )  # fmt: skip
    bench.add_argument(
        "--probe-priority", type=int, default=50, metavar="P",
        help="with --attack: the machine probe's SCHED_FIFO priority (default 50, the loops')",
    )  # fmt: skip
    bench.add_argument(
        "--fleet",
        action="store_true",
        help="instead: N light vehicles (the real sharing stack, no physics) through one "
        "`fleet router`: discovery, propagation p50/p99, CPU shares",
    )
    bench.add_argument("--vehicles", type=_sizes, default=[5], metavar="N[,N...]",
                       help="with --fleet: vehicles, e.g. 5,10,25,50 (one run each)")  # fmt: skip
    bench.add_argument(
        "--late-joiner", action="store_true",
        help="with --fleet --vehicles N: 3 flying vehicles (lockstep, staggered) among N - 3 "
        "replaying light ones: the late joiner's first-lap misses, then a real-time flight's "
        "loops beside the fleet and alone (FILE without suffix: the flights)",
    )  # fmt: skip
    bench.add_argument(
        "--lwpr",
        action="store_true",
        help="instead: LWPR's cost per control tick, compiled against the numpy reference "
        "(ratios printed), and its learning curves",
    )
    from epc_offboard.tools.bench_modes import add_modes_arguments

    add_modes_arguments(bench)


def _add_log(sub: _Subparsers) -> None:
    log_cmd = sub.add_parser(
        "log",
        help="export a per-tick flight log for plotting tools",
        description="Write a flight log (the service's flight_log_path CSV; sim: "
        "DIR/vehicleK/flight.csv) as MCAP with a JSON schema, which Foxglove Studio and "
        "PlotJuggler open.",
        formatter_class=_HelpFormatter,
    )
    log_cmd.add_argument("format", choices=["mcap"], help="the output format")
    log_cmd.add_argument("flight_csv", metavar="FLIGHT.csv", help="the per-tick flight log")
    log_cmd.add_argument("out", metavar="OUT.mcap", help="the file to write (replaced)")


def _add_figures(sub: _Subparsers) -> None:
    from epc_offboard.tools.readme import README, RECIPES, RESULTS_DIR

    figures = sub.add_parser(
        "figures",
        help="regenerate the README's figures and the numbers it quotes",
        description="Fly the README's recipes (each an `epc-offboard sim` command), copy "
        "their figures and reports into tests/results/, and rewrite every number the README "
        "quotes from those reports.",
        formatter_class=_HelpFormatter,
    )
    figures.add_argument(
        "what", choices=["readme", "neuralfly"],
        help="readme: the recipes' figures and numbers; neuralfly: issue 24's Neural-Fly "
        "table, every wind by every method (30 lockstep flights a seed, 10-25 min on 2 shared "
        "cores)",
    )  # fmt: skip
    figures.add_argument("names", nargs="*", metavar="NAME",
                         help=f"recipes to fly (default: all): {', '.join(RECIPES)}")  # fmt: skip
    figures.add_argument("--numbers-only", action="store_true",
                         help="fly nothing: rewrite the README from the results")  # fmt: skip
    figures.add_argument("--results", default=str(RESULTS_DIR), metavar="DIR",
                         help="where the figures and reports go")  # fmt: skip
    figures.add_argument("--readme", default=str(README), metavar="FILE",
                         help="the README to rewrite")  # fmt: skip
    figures.add_argument("--work", "--out", default="out/readme", metavar="DIR",
                         help="where the flights write their full output")  # fmt: skip
    seeds = figures.add_mutually_exclusive_group()
    seeds.add_argument("--seed", type=bounded_int(0), default=None,
                       help="neuralfly: the flights' noise seed (default 0)")  # fmt: skip
    seeds.add_argument("--seeds", type=_seeds, default=None, metavar="N,N,...",
                       help="neuralfly: fly every flight on each seed; the table gives the "
                       "mean over them and their spread")  # fmt: skip
    figures.add_argument("--jobs", type=bounded_int(1), default=2, metavar="N",
                         help="neuralfly: flights at once (at most 2)")  # fmt: skip


def _seeds(text: str) -> tuple[int, ...]:
    """``3,4``: distinct seeds >= 0."""
    try:
        seeds = tuple(int(part) for part in text.split(","))
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected N or N,N,...: {text!r}") from None
    if min(seeds) < 0 or len(set(seeds)) != len(seeds):
        raise argparse.ArgumentTypeError(f"seeds must be distinct and >= 0: {text!r}")
    return seeds


def _sizes(text: str) -> list[int]:
    """``5`` or ``5,10,25,50``: fleet sizes of at least 2."""
    try:
        sizes = [int(part) for part in text.split(",")]
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected N or N,N,...: {text!r}") from None
    if not sizes or min(sizes) < 2:
        raise argparse.ArgumentTypeError(f"fleet sizes must be >= 2: {text!r}")
    return sizes


def _add_fleet(sub: _Subparsers) -> None:
    fleet = sub.add_parser(
        "fleet",
        help="fleet infrastructure: a Zenoh router the vehicles connect to as clients",
        formatter_class=_HelpFormatter,
    )
    what = fleet.add_subparsers(dest="fleet_command", required=True, metavar="WHAT")
    router = what.add_parser(
        "router",
        help="run a Zenoh router (any Zenoh client can use it); stats as JSON lines",
        description="A Zenoh session in router mode (TLS, mTLS, user-password and access "
        "control from its JSON5 config). Prints one JSON line of stats (sessions, refusals, "
        "CPU) every --stats-every seconds and answers them on epc/router/<zid>/stats.",
        formatter_class=_HelpFormatter,
    )
    router.add_argument("--listen", action="append", metavar="ENDPOINT",
                        help="e.g. tcp/0.0.0.0:7447 or tls/0.0.0.0:7447 (repeatable)")  # fmt: skip
    router.add_argument("--config", metavar="FILE", help="a Zenoh JSON5 config, loaded first")
    router.add_argument("--cfg", action="append", metavar="PATH:VALUE",
                        help="set one Zenoh config key (JSON5 value), as zenohd's --cfg, e.g. "
                        "'transport/auth/usrpwd/dictionary_file:\"/etc/zenoh/pw\"'")  # fmt: skip
    router.add_argument("--stats-every", type=positive_number, default=10.0, metavar="S",
                        help="seconds between stats lines")  # fmt: skip
    router.add_argument("--multicast-scouting", action="store_true",
                        help="answer and send UDP multicast scouting (off: explicit endpoints)")


def _subparser(parser: argparse.ArgumentParser, command: str) -> argparse.ArgumentParser:
    """The parser of ``command`` (its usage line is the one a mistyped flag wants)."""
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            found = action.choices.get(command)
            if isinstance(found, argparse.ArgumentParser):
                return found
    return parser


def _unrecognized(parser: argparse.ArgumentParser, command: str, extra: list[str]) -> str:
    """'unrecognized arguments: ...', with the command's closest flag for each mistyped one
    (a PX4 user's `sim --scenaro` got the top-level usage and no hint)."""
    import difflib

    flags = [o for a in _subparser(parser, command)._actions for o in a.option_strings]
    hints = []
    for word in extra:
        if word.startswith("--"):
            close = difflib.get_close_matches(word.split("=")[0], flags, n=1)
            if close:
                hints.append(f"{word.split('=')[0]}: did you mean {close[0]}?")
    return f"unrecognized arguments: {' '.join(extra)}" + (f" ({'; '.join(hints)})"
                                                          if hints else "")  # fmt: skip


def main(argv: Sequence[str] | None = None) -> int:
    if list(sys.argv[1:] if argv is None else argv)[:1] == ["run"]:
        # compiled kernels or their numpy twins, chosen before anything imports them (the
        # parser's scenario list does): service/coldstart.py
        from epc_offboard.service import coldstart

        coldstart.choose()
    parser = build_parser()
    argv = sys.argv[1:] if argv is None else argv
    args, extra = parser.parse_known_args(join_negative_values(argv, ("--wind",)))
    if extra and args.command == "db" and not any(e.startswith("-") for e in extra):
        # `db import --config X LIB EXP`: argparse fills the PATH list once, with what stands
        # before the first option, and leaves later paths over; they are the same list
        args.paths += extra
    elif extra:
        _subparser(parser, args.command).error(_unrecognized(parser, args.command, extra))
    module_name, func_name = _COMMANDS[args.command].split(":")
    try:
        module = importlib.import_module(module_name)
    except ModuleNotFoundError as exc:
        if exc.name != module_name:
            raise
        print(f"epc-offboard: `{args.command}` is not implemented yet", file=sys.stderr)
        return EXIT_RUNTIME
    command = cast(Callable[[argparse.Namespace], int], getattr(module, func_name))
    try:
        return command(args)
    except (UsageError, ConfigError) as exc:
        print(f"epc-offboard: {exc}", file=sys.stderr)
        return EXIT_USAGE
    except KeyboardInterrupt:  # Ctrl-C: said (it ended silently), what it started stopped
        print(f"epc-offboard {args.command}: interrupted (Ctrl-C)", file=sys.stderr)
        return EXIT_RUNTIME


if __name__ == "__main__":
    sys.exit(main())  # prefer `python -m epc_offboard`
