"""What one ``epc-offboard sim`` run was asked to do, as one typed value.

:func:`sim_options` reads the command line's ``argparse.Namespace`` once, loads the scenario
and checks everything a user can get wrong (UsageError, exit code 2, before any process
starts); below it nothing sees argparse.
"""

from __future__ import annotations

import argparse
import dataclasses
import math
from dataclasses import dataclass, field
from pathlib import Path

from epc_offboard.common.cliargs import MAX_PORT, WindProfile, parse_wind_profile
from epc_offboard.common.configio import ConfigError
from epc_offboard.common.errors import UsageError
from epc_offboard.store.database import library_refusal, store_path_refused
from epc_offboard.tools.sim.scenario import CONFIG_DIR, ScenarioConfig, load_scenario
from epc_offboard.tools.targets import method_name, parse_method

AUTOPILOTS = ("px4", "ardupilot")


def configured_realtime_priority() -> int:
    """The service's configured ``loops.realtime_priority``: config/default.toml's."""
    from epc_offboard.service.config import load_service_config

    return load_service_config(CONFIG_DIR / "default.toml").loops.realtime_priority


@dataclass(frozen=True)
class SimOptions:
    """One ``sim`` run: what to fly, how, how many vehicles, and where to write."""

    scenario_name: str  # as given to --scenario: a name or a path (the report's "scenario")
    scenario: ScenarioConfig  # loaded, --duration applied
    controller: str = "epc"
    adaptation: str = "lwpr"
    vehicles: int = 1
    lockstep: bool = True
    wind_speed_m_s: float = 0.0
    wind_dir_deg: float = 0.0  # towards, counter-clockwise from east (docs/CONTRACTS.md)
    wind_profile: WindProfile = field(default_factory=WindProfile)  # steady by default
    seed: int = 0
    gcs_port: int | None = None  # None: the autopilot's usual ground-station port
    autopilot: str = "px4"
    share: bool = True  # fleet sharing over Zenoh when vehicles > 1
    stagger: bool = False  # vehicle k starts once vehicle k-1 has landed
    fleet_router: str = ""  # share as clients of this Zenoh router ("": peers, fixed ports)
    # > 0: each service's loops and each SITL SCHED_FIFO at this priority (where permitted),
    # as a vehicle whose autopilot is hardware of its own and whose loops are configured so;
    # 0: off; None: as configured (:attr:`fifo_priority`)
    realtime_priority: int | None = None
    out_dir: Path = Path("out")
    json_path: Path | None = None  # also write the report JSON here
    compare: tuple[str, ...] | None = None  # `--compare`: the methods; None: one flight
    figure: bool = True  # draw flight.png (`--no-figure`: not)

    def __post_init__(self) -> None:
        _check_vehicles(self.vehicles)
        if self.realtime_priority is not None and not 0 <= self.realtime_priority <= 99:
            raise ValueError(f"realtime_priority must be 0..99, got {self.realtime_priority}")
        parse_method(self.method)  # ValueError naming a bad controller or adaptation
        if self.autopilot not in AUTOPILOTS:
            raise ValueError(f"autopilot must be one of {AUTOPILOTS}, got {self.autopilot!r}")

    @property
    def fifo_priority(self) -> int:
        """The SCHED_FIFO priority of each service's loops and each SITL (0: none): the one
        given; else in real time the service's configured ``loops.realtime_priority`` (the
        scenario's, or config/default.toml's: 50), as on a vehicle, where a busy companion
        computer must not starve the loops (sim without it: 64 / 85 Hz, 42 failsafes at load
        8-13); lockstep none (its flights do not depend on the scheduler)."""
        if self.realtime_priority is not None:
            return self.realtime_priority
        if self.lockstep:
            return 0
        loops = self.scenario.service.get("loops", {})
        if "realtime_priority" in loops:
            return int(loops["realtime_priority"])
        return configured_realtime_priority()

    @property
    def method(self) -> str:
        """``controller:adaptation``, as targets and ``--compare`` name methods."""
        return method_name(self.controller, self.adaptation)

    @property
    def wind(self) -> tuple[float, float]:
        """(speed m/s, direction deg), as ``--wind`` and the SITL take it."""
        return self.wind_speed_m_s, self.wind_dir_deg

    def flying(self, method: str) -> SimOptions:
        """The options of one flight of ``--compare``: this method, no comparison."""
        controller, adaptation = parse_method(method)
        return dataclasses.replace(self, controller=controller, adaptation=adaptation, compare=None)


def _check_vehicles(n: int) -> None:
    if n < 1:
        raise UsageError("--vehicles must be >= 1")


def sim_options(args: argparse.Namespace) -> SimOptions:
    """The options of ``epc-offboard sim``'s parsed command line; UsageError if bad."""
    _check_vehicles(args.vehicles)
    _check_combinations(args)
    scenario = _scenario(args.scenario, args.duration)
    wind = args.wind or (scenario.wind_speed_m_s, scenario.wind_dir_deg)
    profile = args.wind_profile or parse_wind_profile(scenario.wind_profile)
    compare = None if args.compare is None else _compare_methods(args.compare, scenario)
    _check_outputs(Path(args.out), Path(args.json) if args.json else None)
    _check_libraries(Path(args.out), args.vehicles, compare)
    return SimOptions(
        scenario_name=args.scenario,
        scenario=scenario,
        controller=args.controller or "epc",
        adaptation=args.adaptation or "lwpr",
        vehicles=args.vehicles,
        lockstep=args.lockstep,
        wind_speed_m_s=wind[0],
        wind_dir_deg=wind[1],
        wind_profile=profile,
        seed=args.seed,
        gcs_port=args.gcs_port,
        autopilot=args.autopilot,
        share=not args.no_share,
        stagger=args.stagger,
        fleet_router=args.fleet_router or "",
        realtime_priority=args.realtime_priority,
        out_dir=Path(args.out),
        json_path=Path(args.json) if args.json else None,
        compare=compare,
        figure=not args.no_figure,
    )


def _check_combinations(args: argparse.Namespace) -> None:
    """Flags another flag makes meaningless are errors, not silently ignored."""
    if args.fleet_router and args.no_share:
        raise UsageError("--fleet-router with --no-share: give one (a router is for sharing)")
    if args.vehicles == 1:
        for flag, given in (("--stagger", args.stagger), ("--no-share", args.no_share)):
            if given:
                raise UsageError(f"{flag} needs --vehicles N > 1: one vehicle has no fleet")
    if args.compare is not None:
        for flag, given in (("--controller", args.controller), ("--adaptation", args.adaptation)):
            if given is not None:
                raise UsageError(
                    f"{flag} {given} with --compare: --compare flies the methods it names "
                    f"(e.g. --compare {args.controller or 'epc'}:{args.adaptation or 'lwpr'},"
                    "pd:none); give them there"
                )
    if args.gcs_port and args.autopilot == "ardupilot":
        last = args.gcs_port + 10 * (args.vehicles - 1)  # vehicle k serves PORT + 10 (k - 1)
        if last > MAX_PORT:
            raise UsageError(
                f"--gcs-port {args.gcs_port} with --vehicles {args.vehicles}: vehicle "
                f"{args.vehicles} would serve TCP {last}, above {MAX_PORT}"
            )


def _check_outputs(out_dir: Path, json_path: Path | None) -> None:
    """Where the results go must take them: found out now, not after the flight."""
    if out_dir.exists() and not out_dir.is_dir():
        raise UsageError(f"--out {out_dir}: exists and is not a folder")
    if json_path is not None:
        if json_path.is_dir():
            raise UsageError(f"--json {json_path}: is a folder")
        if not json_path.parent.is_dir():
            raise UsageError(f"--json {json_path}: no folder {json_path.parent}")


def _check_libraries(out_dir: Path, vehicles: int, compare: tuple[str, ...] | None) -> None:
    """Each vehicle's library (``store.path`` DIR/library-K.sqlite, DIR the ``--out`` or,
    with ``--compare``, each method's folder in it) must be one the service can open: a
    directory or another application's file there is refused now, nothing moved, not found
    by the service and moved aside as corrupt."""
    dirs = [out_dir] if compare is None else [out_dir / m.replace(":", "-") for m in compare]
    for folder in dirs:
        for k in range(1, vehicles + 1):
            path = folder / f"library-{k}.sqlite"
            reason = library_refusal(path)
            if reason is not None:
                raise UsageError(store_path_refused(f"--out {out_dir}", path, reason))


def _scenario(name: str, duration_s: float | None) -> ScenarioConfig:
    """The scenario named by ``--scenario`` with ``--duration`` applied."""
    try:
        scenario = load_scenario(name)
    except ConfigError as exc:
        raise UsageError(str(exc)) from exc
    if duration_s is not None:
        if not math.isfinite(duration_s) or duration_s <= scenario.settle_s:
            raise UsageError(
                f"--duration must be finite and exceed the scenario's settle time "
                f"{scenario.settle_s} s, got {duration_s}"
            )
        scenario = dataclasses.replace(scenario, duration_s=duration_s)
    return scenario


def _compare_methods(text: str, scenario: ScenarioConfig) -> tuple[str, ...]:
    """``--compare`` alone: the scenario's methods; ``--compare a:b,c:d``: those."""
    text = text.strip()
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
