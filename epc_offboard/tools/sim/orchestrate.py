"""The processes of a sim flight: for each vehicle k (1..N) ``epc-sitl --instance k-1`` and
``epc-offboard run`` on loopback UDP, started, watched (a progress bar), stopped.

The service arms, takes off, enters offboard, flies the scenario and lands; what the flight
leaves in each ``vehicleK/`` directory (the flight log, the .tlog, the ground truth, stats and
both processes' logs) is then analysed (:mod:`.analysis`) and reported (:mod:`.report`):
:func:`fly_and_report` does all three.
"""

from __future__ import annotations

import contextlib
import csv
import os
import signal
import subprocess
import sys
import time
import tomllib
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from epc_offboard.common import jit
from epc_offboard.common.children import launched_env
from epc_offboard.common.cliargs import WindProfile, check_port_free
from epc_offboard.common.configio import dump_toml, merge_dicts
from epc_offboard.common.frames import FloatArray
from epc_offboard.common.ports import free_port
from epc_offboard.service.airframe_file import DEFAULT_VEHICLE_FILE, airframe_path, load_airframe
from epc_offboard.tools.figures import flight_title, write_figure
from epc_offboard.tools.sim.analysis import VehicleResult, analyse, read_flight
from epc_offboard.tools.sim.envelope import Envelope, breaches, envelope_for, tilt_deg_of
from epc_offboard.tools.sim.options import SimOptions
from epc_offboard.tools.sim.report import make_report, write_json
from epc_offboard.tools.sim.scenario import SITL_SERVICE_CONFIG

ZENOH_BASE_PORT = 7446  # vehicle k listens on tcp/127.0.0.1:(7446 + k) (docs/CONTRACTS.md)
STOPPED_OUTSIDE = "stopped by sim: it left its envelope"  # how a VehicleRun.stopped begins


@dataclass
class VehicleRun:
    """One vehicle's processes and the directory they write to."""

    vehicle_id: int
    out_dir: Path
    sitl: subprocess.Popen[bytes] | None = None
    service: subprocess.Popen[bytes] | None = None
    offboard_entry_s: float | None = None  # vehicle time offboard began (the progress bar)
    stopped: str = ""  # why sim ended this flight before it finished ("": it did not)
    aside_before: frozenset[Path] = frozenset()  # moved-aside libraries before it started

    @property
    def groundtruth(self) -> Path:
        return self.out_dir / "groundtruth.csv"

    @property
    def flight_log(self) -> Path:
        return self.out_dir / "flight.csv"

    @property
    def stats(self) -> Path:
        return self.out_dir / "stats.json"

    @property
    def tlog(self) -> Path:
        return self.out_dir / "session.tlog"

    @property
    def sitl_log(self) -> Path:
        return self.out_dir / "sitl.log"

    @property
    def service_log(self) -> Path:
        return self.out_dir / "service.log"

    @property
    def service_config(self) -> Path:
        return self.out_dir / "service.toml"

    @property
    def library(self) -> Path:
        return self.out_dir.parent / f"library-{self.vehicle_id}.sqlite"

    def moved_aside(self) -> frozenset[Path]:
        """The library files the service has moved aside as corrupt (``NAME.corrupt-...``)."""
        return frozenset(self.library.parent.glob(f"{self.library.name}.corrupt-*"))

    def stop(self, why: str) -> None:
        """End this flight now, saying why: the service first (it commands Hold and writes
        its stats), then its SITL."""
        if not self.stopped:
            self.stopped = why
        stop_process(self.service)
        stop_process(self.sitl)


def service_config_for(
    options: SimOptions, vehicle_id: int, port: int, run_dir: Path, library_path: Path
) -> dict[str, Any]:
    """The service config of one vehicle: config/sitl.toml + scenario + command-line flags."""
    scenario = options.scenario
    with SITL_SERVICE_CONFIG.open("rb") as fh:
        base = tomllib.load(fh)
    traj = {k: v for k, v in vars(scenario.trajectory).items()}
    traj["waypoints_ned_m"] = [list(w) for w in scenario.trajectory.waypoints_ned_m]
    flags: dict[str, Any] = {
        # the autopilot flown is known: the attitude loop models its body-rate response
        "link": {"url": f"udpin://127.0.0.1:{port}", "target_system": vehicle_id,
                 "autopilot": options.autopilot},
        "loops": {"clock": "vehicle" if options.lockstep else "wall",
                  **({"realtime_priority": options.fifo_priority}
                     if options.fifo_priority else {})},
        "position": {"controller": options.controller},
        "estimator": {"kind": options.adaptation},
        "trajectory": traj,
        "trajectory_altitude_m": scenario.altitude_m,
        # a flight lands, unless its scenario's [service.mission] says it ends holding (the
        # suite's entry flights: the landing judged nothing there); --stagger's vehicles
        # start on the landing before them
        "mission": {"duration_s": scenario.duration_s,
                    "land_at_end": options.stagger
                    or bool(scenario.service.get("mission", {}).get("land_at_end", True))},
        "store": {"path": str(library_path)},
        "log": {
            "flight_log_path": str(run_dir / "flight.csv"),
            "tlog_path": str(VehicleRun(vehicle_id, run_dir).tlog),
            "stats_path": str(run_dir / "stats.json"),
        },
    }
    if scenario.vehicle:  # one airframe file for both: the SITL flies what the service names
        flags["airframe"] = {"file": scenario.vehicle}
    flags["sharing"] = _sharing_flags(options, vehicle_id)
    if options.stagger:
        flags["mission"]["linger_after_landing"] = True
    return merge_dicts(merge_dicts(base, scenario.service), flags)


def _sharing_flags(options: SimOptions, vehicle_id: int) -> dict[str, Any]:
    """Fleet sharing for ``--vehicles N > 1`` unless ``--no-share``: every vehicle listens on
    its own loopback port and connects to all the others (no multicast scouting)."""
    n = options.vehicles
    if options.fleet_router and options.share:  # clients of a router: no fixed port
        return {"enabled": True, "fleet": "sim", "vehicle_id": f"v{vehicle_id}",
                "mode": "client", "connect": [options.fleet_router],
                "scouting_multicast": False}  # fmt: skip
    if n < 2 or not options.share:
        return {"enabled": False}
    return {
        "enabled": True,
        "fleet": "sim",
        "vehicle_id": f"v{vehicle_id}",
        "listen": [f"tcp/127.0.0.1:{ZENOH_BASE_PORT + vehicle_id}"],
        "connect": [
            f"tcp/127.0.0.1:{ZENOH_BASE_PORT + k}" for k in range(1, n + 1) if k != vehicle_id
        ],
        "scouting_multicast": False,
    }


def check_ports(options: SimOptions) -> None:
    """The ports the flight's processes will bind and sim cannot choose (the fleet's Zenoh
    ports, ArduPilot's ground-station TCP ports): PortInUseError naming the port and the
    vehicle now, before any process starts, instead of a service failing after its warm-up."""
    for k in range(1, options.vehicles + 1):
        if options.vehicles > 1 and options.share and not options.fleet_router:
            check_port_free("tcp", "127.0.0.1", ZENOH_BASE_PORT + k,
                            f"vehicle {k}'s fleet sharing (Zenoh; --no-share: none)")  # fmt: skip
        gcs = _gcs_port(options, k)
        if options.autopilot == "ardupilot" and gcs:
            check_port_free("tcp", "127.0.0.1", gcs, f"vehicle {k}'s ground station (--gcs-port)")


def telemetry_routes(
    options: SimOptions, vehicle_id: int, listen_port: int, offboard_port: int
) -> str:
    """Where vehicle k's MAVLink goes, said at start: the ground-station stream is a fixed
    port another SITL or QGroundControl on this machine may be using too."""
    gcs = _gcs_port(options, vehicle_id)
    if options.autopilot == "ardupilot":
        station = f"serves TCP 127.0.0.1:{gcs}" if gcs else "none (--gcs-port PORT to serve one)"
    else:
        station = f"UDP 127.0.0.1:{gcs} (--gcs-port 0: none)" if gcs else "none"
    routes = (
        f"vehicle {vehicle_id}: SITL (system id {vehicle_id}) on UDP 127.0.0.1:{listen_port} "
        f"-> service on UDP 127.0.0.1:{offboard_port}; ground station: {station}"
    )
    if options.fleet_router and options.share:
        routes += f"; fleet sharing: a client of the Zenoh router {options.fleet_router}"
    elif options.vehicles > 1 and options.share:
        routes += f"; fleet sharing: Zenoh tcp/127.0.0.1:{ZENOH_BASE_PORT + vehicle_id}"
    return routes


def _gcs_port(options: SimOptions, vehicle_id: int) -> int:
    """The ground-station port of vehicle k's SITL, as PX4 and ArduPilot SITL number them: PX4
    sends UDP to one port (14550 by default) for every vehicle, told apart by system id;
    ArduPilot serves TCP on its own port (base + 10 (k - 1)), only when a base is given (a
    listening port of a concurrent run could clash). 0: no ground-station stream."""
    port = options.gcs_port
    if options.autopilot == "ardupilot":
        return 0 if not port else int(port) + 10 * (vehicle_id - 1)
    return 14550 if port is None else int(port)


def _start(
    cmd: list[str], log_path: Path, extra_env: dict[str, str] | None = None
) -> subprocess.Popen[bytes]:
    log_fh = log_path.open("wb")
    env = dict(os.environ, PYTHONUNBUFFERED="1", **launched_env(), **(extra_env or {}))
    return subprocess.Popen(cmd, stdout=log_fh, stderr=subprocess.STDOUT, env=env)


def service_env() -> dict[str, str]:
    """The simulated services fly compiled kernels (compiling at start on a cold cache, as
    every start did before the cold start on the numpy twins), unless EPC_OFFBOARD_JIT is
    set: on the twins a position tick took 6 ms (median) instead of 0.75 ms, 400 of 1800
    ticks missed their deadline, and each service's background compile (killed with it
    before it marked the cache warm) took a core from the flight, so no compare flight
    ever measured what the README's figures are."""
    return {} if jit.ENV in os.environ else {jit.ENV: "1"}


def stop_process(proc: subprocess.Popen[bytes] | None, timeout_s: float = 5.0) -> None:
    """SIGTERM, then SIGKILL after ``timeout_s``; nothing if it is gone already."""
    if proc is None or proc.poll() is not None:
        return
    proc.send_signal(signal.SIGTERM)
    try:
        proc.wait(timeout=timeout_s)
    except subprocess.TimeoutExpired:
        proc.kill()
        proc.wait()


class _Deferral:
    """A SIGTERM that arrives while sim starts a process is taken when the start is over:
    raised inside Popen (after the fork, before it returned), it left that SITL flying,
    unknown to the ``finally`` that stops every process sim started."""

    depth = 0
    signum = 0


def stop_on_sigterm() -> None:
    """SIGTERM (systemd, a test harness, `kill`) ends sim as Ctrl-C does: through the
    ``finally`` that stops every SITL and service it started (the default action killed sim
    alone and left its children flying)."""

    def handler(signum: int, _frame: object) -> None:
        if _Deferral.depth:
            _Deferral.signum = signum
            return
        raise SystemExit(128 + signum)

    signal.signal(signal.SIGTERM, handler)


@contextlib.contextmanager
def signals_deferred() -> Iterator[None]:
    """SIGTERM held (not blocked: a blocked mask is inherited by the processes started) until
    the block is over."""
    _Deferral.depth += 1
    try:
        yield
    finally:
        _Deferral.depth -= 1
        if not _Deferral.depth and _Deferral.signum:
            signum, _Deferral.signum = _Deferral.signum, 0
            raise SystemExit(128 + signum)


def _last_row(path: Path) -> tuple[list[str], list[str]]:
    """(header, last complete row) of a growing CSV; empty lists when none yet."""
    try:
        with path.open("rb") as fh:
            header = fh.readline().decode(errors="replace").strip().split(",")
            fh.seek(0, os.SEEK_END)
            size = fh.tell()
            fh.seek(max(0, size - 4096))
            tail = fh.read().decode(errors="replace").splitlines()
    except OSError:
        return [], []
    rows = [r.split(",") for r in tail[1:] if r.count(",") == len(header) - 1]
    return (header, rows[-1]) if rows and rows[-1] != header else (header, [])


def flight_progress(run: VehicleRun, duration_s: float) -> tuple[str, float]:
    """(phase label, seconds flown under offboard) of a running vehicle, from the tails of its
    growing flight log and ground truth: "takeoff" until the service streams, "offboard
    3.2/10 s", "landing" once the offboard part is over (the log stops while the vehicle's
    clock runs on), "landed" when its stats are written."""
    if run.stats.exists():
        return "landed", duration_s
    header, last = _last_row(run.flight_log)
    if not last or "phase" not in header or "vehicle_t_s" not in header:
        return "takeoff", 0.0
    phase, t_s = last[header.index("phase")], float(last[header.index("vehicle_t_s")])
    if phase != "offboard":
        if run.offboard_entry_s is not None:  # offboard is over
            return "landing", duration_s
        return "entering offboard", 0.0
    if run.offboard_entry_s is None:  # the first offboard row, read once
        with run.flight_log.open(newline="") as fh:
            for row in csv.DictReader(fh):
                if row.get("phase") == "offboard":
                    run.offboard_entry_s = float(row["vehicle_t_s"])
                    break
    done_s = min(max(t_s - (run.offboard_entry_s or t_s), 0.0), duration_s)
    truth_header, truth_last = _last_row(run.groundtruth)
    truth_t_s = float(truth_last[0]) if truth_last and truth_header[0] == "t_s" else t_s
    if done_s >= duration_s - 0.05 or truth_t_s > t_s + 2.0:  # the log has stopped
        return "landing", duration_s
    return f"offboard {done_s:.1f}/{duration_s:g} s", done_s


def vehicle_file(service_cfg: dict[str, Any]) -> Path:
    """The vehicle file a service config names (``[airframe] file``): its SITL flies the
    same one, so the service's hover thrust and limits are the simulated airframe's."""
    return airframe_path(str(service_cfg.get("airframe", {}).get("file", DEFAULT_VEHICLE_FILE)))


def flight_envelope(options: SimOptions, service_cfg: dict[str, Any]) -> Envelope:
    """The envelope a flight of ``options`` is judged sane within (:mod:`.envelope`)."""
    scenario = options.scenario
    return envelope_for(
        scenario.envelope,
        altitude_m=scenario.altitude_m,
        climb_m=scenario.climb_m,
        duration_s=scenario.duration_s,
        max_tilt_deg=load_airframe(str(vehicle_file(service_cfg))).max_tilt_deg,
    )


def _float_row(header: list[str], row: list[str]) -> dict[str, float]:
    out = {}
    for name, cell in zip(header, row, strict=False):
        try:
            out[name] = float(cell)
        except ValueError:
            continue
    return out


def _watch(run: VehicleRun, envelope: Envelope) -> str:
    """Why this flight must end now ("" if it need not): its ground truth's newest sample is
    outside the envelope (against the reference the service is tracking now, or the last one
    it tracked, or home before it streamed: see :mod:`.envelope`), or its SITL has exited."""
    if run.stopped or run.service is None or run.service.poll() is not None:
        return ""
    if run.sitl is not None and run.sitl.poll() is not None:
        return f"its SITL exited early with {run.sitl.returncode} (see {run.sitl_log})"
    if run.stats.exists():  # landed (a lingering staggered service)
        return ""
    truth = _float_row(*_last_row(run.groundtruth))
    if "t_s" not in truth or "pos_d_m" not in truth:
        return ""
    header, last = _last_row(run.flight_log)
    flight = _float_row(header, last)
    phase = dict(zip(header, last, strict=False)).get("phase", "")
    pos = np.array([[truth.get(f"pos_{a}_m", 0.0) for a in "ned"]])
    ref = np.zeros((1, 3))  # before offboard: home
    under_offboard = False
    if run.offboard_entry_s is not None and "ref_pos_n_m" in flight:
        ref = np.array([[flight.get(f"ref_pos_{a}_m", 0.0) for a in "ned"]])
        # the log grows under offboard; after it, the last reference is where it landed
        under_offboard = phase == "offboard" and truth["t_s"] <= flight["vehicle_t_s"] + 0.5
    q = np.array([[truth.get(f"q_{a}", 0.0) for a in "wxyz"]])
    found = breaches(envelope, np.array([truth["t_s"]]), pos, tilt_deg_of(q), ref,
                     np.array([not under_offboard]), flight_s=np.array([truth["t_s"]]))  # fmt: skip
    if not found:
        return ""
    return f"{STOPPED_OUTSIDE} ({found[0].describe()} of vehicle time)"


def fly(options: SimOptions, out_dir: Path) -> list[VehicleRun]:
    """Start every SITL and service, wait for the services to finish, stop the SITLs.

    With ``--stagger`` vehicle k starts once vehicle k-1 has landed (its stats file appears;
    its service lingers, sharing its library) and every service is stopped after the last
    vehicle has landed.
    """
    from rich.progress import BarColumn, Progress, TextColumn, TimeElapsedColumn

    runs: list[VehicleRun] = []
    scenario, name, vehicles, stagger = (
        options.scenario, options.scenario_name, options.vehicles, options.stagger
    )  # fmt: skip

    def start(k: int) -> None:
        run = VehicleRun(k, out_dir / f"vehicle{k}")
        run.out_dir.mkdir(parents=True, exist_ok=True)
        run.stats.unlink(missing_ok=True)  # with --stagger its appearance means "landed"
        # a re-run into the same --out replaces every file of the last one; the service
        # appends to its tlog (a restarted daemon keeps its earlier sessions), so it goes too
        for stale in (run.flight_log, run.groundtruth, run.tlog):  # the bar reads the first two
            stale.unlink(missing_ok=True)
        offboard_port = free_port()
        listen_port = free_port()
        run.aside_before = run.moved_aside()
        cfg = service_config_for(options, k, offboard_port, run.out_dir, run.library)
        run.service_config.write_text(dump_toml(cfg))
        sitl_cmd = [
            sys.executable, "-m", "sitl.main", "--instance", str(k - 1),
            "--listen-port", str(listen_port), "--offboard-port", str(offboard_port),
            "--gcs-port", str(_gcs_port(options, k)), "--groundtruth", str(run.groundtruth),
            "--seed", str(options.seed + k - 1), "--config", str(vehicle_file(cfg)),
            "--wind", f"{options.wind_speed_m_s},{options.wind_dir_deg}",
        ]  # fmt: skip
        if options.wind_profile != WindProfile():
            sitl_cmd += ["--wind-profile", options.wind_profile.text]
        if options.lockstep:
            sitl_cmd.append("--lockstep")
        if options.fifo_priority:  # (where permitted; a refusal is counted in its report)
            sitl_cmd += ["--realtime-priority", str(options.fifo_priority)]
        sitl_cmd += ["--autopilot", options.autopilot]
        if options.autopilot == "ardupilot":
            # what the README asks of a real ArduCopter: thrust as throttle, not climb rate
            sitl_cmd += ["--param", "GUID_OPTIONS=8"]
        runs.append(run)  # before its processes: a SIGTERM from here on stops them
        with signals_deferred():
            # `-m epc_offboard` (its __main__), not `-m epc_offboard.cli`: each helper the
            # service spawns (miss worker, logs, store, fleet) imports its parent's main module
            # again unless it is a package's __main__ (multiprocessing's spawn), 0.05-0.08
            # CPU-s a helper for a module it never uses
            run.service = _start(
                [sys.executable, "-m", "epc_offboard", "run", "--config",
                 str(run.service_config)],
                run.service_log,
                service_env(),
            )  # fmt: skip
            run.sitl = _start(sitl_cmd, run.sitl_log)
        print(telemetry_routes(options, k, listen_port, offboard_port), flush=True)

    try:  # from the first start: a SIGTERM (sim's SystemExit) anywhere stops what started
        for k in range(1, (1 if stagger else vehicles) + 1):
            start(k)
        envelope = flight_envelope(options, tomllib.loads(runs[0].service_config.read_text()))
        flights = vehicles if stagger else 1
        # wall time: lockstep flies faster than real time even at load 6; a SITL that stops
        # advancing (its vehicle time is bounded by the envelope) is caught here
        wall_budget_s = flights * max(120.0, 4.0 * envelope.max_flight_s)
        deadline = time.monotonic() + wall_budget_s
        # the bar counts the scenario's seconds under offboard, the only ones the scenario names;
        # takeoff and landing show as the phase in its label
        total_s = scenario.duration_s * (vehicles if stagger else 1)
        with Progress(
            TextColumn("[bold]{task.description}"),
            BarColumn(),
            TextColumn("{task.completed:.1f}/{task.total:.0f} s offboard"),
            TimeElapsedColumn(),
            transient=False,
            disable=not sys.stderr.isatty(),
        ) as progress:
            task = progress.add_task(f"{name}: takeoff", total=total_s)
            while any(r.service is not None and r.service.poll() is None for r in runs):
                if time.monotonic() > deadline:
                    for r in runs:
                        if r.service is not None and r.service.poll() is None:
                            r.stop(f"stopped by sim: not finished after {wall_budget_s:.0f} s "
                                   "of wall time")  # fmt: skip
                    break
                for r in runs:
                    why = _watch(r, envelope)
                    if why:
                        r.stop(why)
                if stagger and runs[-1].stats.exists():  # the newest vehicle has landed
                    if len(runs) < vehicles:
                        start(len(runs) + 1)
                    else:
                        for r in runs:
                            stop_process(r.service)
                states = [flight_progress(r, scenario.duration_s) for r in runs]
                done_s = sum(s[1] for s in states) if stagger else min(s[1] for s in states)
                phase = states[-1][0] if stagger else states[0][0]
                who = f" vehicle {len(runs)}/{vehicles}" if vehicles > 1 else ""
                progress.update(task, completed=min(done_s, total_s),
                                description=f"{name}{who}: {phase}")  # fmt: skip
                time.sleep(0.2)
            progress.update(task, completed=total_s, description=f"{name}: landed")
    finally:
        for r in runs:
            stop_process(r.service)
            stop_process(r.sitl)
    for r in runs:
        code = r.service.returncode if r.service is not None else None
        if code not in (0, None) and not r.stopped:
            r.stopped = f"its service exited with {code} (see {r.service_log})"
    return runs


def fly_and_report(
    options: SimOptions, out_dir: Path, title: str
) -> tuple[dict[str, Any], list[VehicleResult], FloatArray]:
    """Fly, analyse on ground truth, write ``report.json`` and ``flight.png`` (``title``: the
    scenario's name as the figure names it; none with ``options.figure`` false) to ``out_dir``;
    returns (report, results, velocity bounds m/s (3,) NED). A flight that failed is reported
    all the same (its ``stopped``, the report's ``failures``); RuntimeError only when a
    vehicle left nothing to report (no ground truth)."""
    runs = fly(options, out_dir)
    cfg = tomllib.loads(runs[0].service_config.read_text())
    bounds = np.array(cfg["position"]["max_vel_m_s"], dtype=np.float64)
    envelope = flight_envelope(options, cfg)
    results = [
        analyse(
            read_flight(r.vehicle_id, flight_log=r.flight_log, groundtruth=r.groundtruth,
                        stats=r.stats, sitl_log=r.sitl_log, service_log=r.service_log,
                        sharing_asked=bool(_sharing_flags(options, r.vehicle_id)["enabled"]),
                        moved_aside=tuple(str(p) for p in sorted(r.moved_aside() - r.aside_before)),
                        stopped=r.stopped),
            options.scenario,
            bounds,
            envelope,
        )
        for r in runs
    ]  # fmt: skip
    from epc_offboard.tools.logexport import flight_csv_to_mcap

    for r in runs:  # the per-tick log for Foxglove Studio and PlotJuggler, beside the CSV
        flight_csv_to_mcap(r.flight_log, r.flight_log.with_suffix(".mcap"))
    report = make_report(options, results)
    write_json(report, out_dir / "report.json")
    title = flight_title(title, options.method, options.autopilot, options.wind,
                         options.vehicles)  # fmt: skip
    if options.figure:
        write_figure(results, bounds, out_dir / "flight.png", title,
                     settle_s=options.scenario.settle_s)  # fmt: skip
    return report, results, bounds
