"""`epc-offboard sim`: the bundled SITL(s) and the service as real processes, a scenario, a report.

For each vehicle k (1..N) it starts ``epc-sitl --instance k-1`` and ``epc-offboard run`` on
loopback UDP, lets the service arm, take off, enter offboard, fly the scenario and land, then
reads the SITL's ground truth and the service's flight log and stats and writes, to ``--out``:
``report.json`` (CONTRACTS.md shape), ``flight.png``, and per vehicle the flight log, the
.tlog, the ground truth and both processes' logs.

Tracking error is measured on ground truth (the SITL's true position, not the noisy estimate),
against the reference the service was tracking at that vehicle time, over the part of the
flight after ``settle_s``.
"""

from __future__ import annotations

import argparse
import csv
import json
import math
import os
import signal
import socket
import subprocess
import sys
import time
import tomllib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, TextIO

import numpy as np

from epc_offboard.common.configio import ConfigError, dump_toml, from_dict, merge_dicts
from epc_offboard.common.frames import FloatArray
from epc_offboard.control.trajectories import TrajectoryConfig
from epc_offboard.tools.figures import write_figure
from epc_offboard.tools.targets import CompareConfig, TargetConfig

CONFIG_DIR = Path(__file__).resolve().parents[2] / "config"
SCENARIO_DIR = CONFIG_DIR / "scenarios"
SITL_SERVICE_CONFIG = CONFIG_DIR / "sitl.toml"


@dataclass(frozen=True)
class ScenarioConfig:
    description: str = ""
    note: str = ""  # printed under the report's table: e.g. why an error is large by design
    duration_s: float = 20.0  # flight under offboard control, from the trajectory's start
    settle_s: float = 3.0  # metrics ignore the first settle_s of the trajectory
    lap_s: float = 0.0  # one lap of the trajectory, for first-lap library figures (0: whole)
    altitude_m: float = 2.5  # the trajectory's altitude above home
    wind_speed_m_s: float = 0.0
    wind_dir_deg: float = 0.0  # towards, counter-clockwise from east (CONTRACTS.md)
    trajectory: TrajectoryConfig = field(default_factory=TrajectoryConfig)
    service: dict[str, Any] = field(default_factory=dict)  # overrides of config/sitl.toml
    compare: CompareConfig = field(default_factory=CompareConfig)  # `sim --compare` methods
    targets: tuple[TargetConfig, ...] = ()  # acceptance targets (epc_offboard.tools.targets)

    def __post_init__(self) -> None:
        if self.duration_s <= 0.0:
            raise ValueError(f"duration_s must be > 0, got {self.duration_s}")
        if not 0.0 <= self.settle_s < self.duration_s:
            raise ValueError("settle_s must be in [0, duration_s)")
        if self.lap_s < 0.0:
            raise ValueError(f"lap_s must be >= 0, got {self.lap_s}")


def load_scenario(name: str) -> ScenarioConfig:
    path = Path(name) if name.endswith(".toml") else SCENARIO_DIR / f"{name}.toml"
    if not path.exists():
        known = sorted(p.stem for p in SCENARIO_DIR.glob("*.toml"))
        raise ConfigError(f"unknown scenario {name!r} (known: {', '.join(known)})")
    with path.open("rb") as fh:
        try:
            raw = tomllib.load(fh)
        except tomllib.TOMLDecodeError as exc:
            raise ConfigError(f"{path}: not valid TOML: {exc}") from exc
    return from_dict(ScenarioConfig, raw, source=str(path))


def _free_udp_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


@dataclass
class VehicleRun:
    vehicle_id: int
    out_dir: Path
    sitl: subprocess.Popen[bytes] | None = None
    service: subprocess.Popen[bytes] | None = None
    offboard_entry_s: float | None = None  # vehicle time offboard began (the progress bar)

    @property
    def groundtruth(self) -> Path:
        return self.out_dir / "groundtruth.csv"

    @property
    def flight_log(self) -> Path:
        return self.out_dir / "flight.csv"

    @property
    def stats(self) -> Path:
        return self.out_dir / "stats.json"


def service_config_for(
    args: argparse.Namespace,
    scenario: ScenarioConfig,
    vehicle_id: int,
    port: int,
    run_dir: Path,
    library_path: Path,
) -> dict[str, Any]:
    """The service config of one vehicle: config/sitl.toml + scenario + command-line flags."""
    with SITL_SERVICE_CONFIG.open("rb") as fh:
        base = tomllib.load(fh)
    traj = {k: v for k, v in vars(scenario.trajectory).items()}
    traj["waypoints_ned_m"] = [list(w) for w in scenario.trajectory.waypoints_ned_m]
    from sitl.params import load_sim_config

    # what PX4 users set as MPC_THR_HOVER, known exactly for the simulated airframe
    hover = load_sim_config().vehicle.hover_thrust_norm
    flags: dict[str, Any] = {
        "link": {"url": f"udpin://127.0.0.1:{port}", "target_system": vehicle_id},
        "loops": {"clock": "vehicle" if args.lockstep else "wall"},
        "position": {"controller": args.controller, "hover_thrust_norm": hover},
        "estimator": {"kind": args.adaptation},
        "trajectory": traj,
        "trajectory_altitude_m": scenario.altitude_m,
        "mission": {"duration_s": scenario.duration_s, "land_at_end": True},
        "store": {"path": str(library_path)},
        "log": {
            "flight_log_path": str(run_dir / "flight.csv"),
            "tlog_path": str(run_dir / "session.tlog"),
            "stats_path": str(run_dir / "stats.json"),
        },
    }
    flags["sharing"] = _sharing_flags(args, vehicle_id)
    if getattr(args, "stagger", False):
        flags["mission"]["linger_after_landing"] = True
    return merge_dicts(merge_dicts(base, scenario.service), flags)


ZENOH_BASE_PORT = 7446  # vehicle k listens on tcp/127.0.0.1:(7446 + k) (CONTRACTS.md)


def _sharing_flags(args: argparse.Namespace, vehicle_id: int) -> dict[str, Any]:
    """Fleet sharing for ``--vehicles N > 1`` unless ``--no-share``: every vehicle listens on
    its own loopback port and connects to all the others (no multicast scouting)."""
    n = int(args.vehicles)
    if n < 2 or getattr(args, "no_share", False):
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


def _start(cmd: list[str], log_path: Path) -> subprocess.Popen[bytes]:
    log_fh = log_path.open("wb")
    env = dict(os.environ, PYTHONUNBUFFERED="1")
    return subprocess.Popen(cmd, stdout=log_fh, stderr=subprocess.STDOUT, env=env)


def _stop(proc: subprocess.Popen[bytes] | None, timeout_s: float = 5.0) -> None:
    if proc is None or proc.poll() is not None:
        return
    proc.send_signal(signal.SIGTERM)
    try:
        proc.wait(timeout=timeout_s)
    except subprocess.TimeoutExpired:
        proc.kill()
        proc.wait()


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


def _gcs_port(args: argparse.Namespace, vehicle_id: int) -> int:
    """The ground-station port of vehicle k's SITL, as PX4 and ArduPilot SITL number them: PX4
    sends UDP to one port (14550 by default) for every vehicle, told apart by system id;
    ArduPilot serves TCP on its own port (base + 10 (k - 1)), only when a base is given (a
    listening port of a concurrent run could clash). 0: no ground-station stream."""
    port = getattr(args, "gcs_port", None)
    if getattr(args, "autopilot", "px4") == "ardupilot":
        return 0 if not port else int(port) + 10 * (vehicle_id - 1)
    return 14550 if port is None else int(port)


def fly(args: argparse.Namespace, scenario: ScenarioConfig, out_dir: Path) -> list[VehicleRun]:
    """Start every SITL and service, wait for the services to finish, stop the SITLs.

    With ``--stagger`` vehicle k starts once vehicle k-1 has landed (its stats file appears;
    its service lingers, sharing its library) and every service is stopped after the last
    vehicle has landed.
    """
    from rich.progress import BarColumn, Progress, TextColumn, TimeElapsedColumn

    runs: list[VehicleRun] = []
    wind = args.wind or (scenario.wind_speed_m_s, scenario.wind_dir_deg)
    stagger = bool(getattr(args, "stagger", False))

    def start(k: int) -> None:
        run_dir = out_dir / f"vehicle{k}"
        run_dir.mkdir(parents=True, exist_ok=True)
        run = VehicleRun(k, run_dir)
        run.stats.unlink(missing_ok=True)  # with --stagger its appearance means "landed"
        for stale in (run.flight_log, run.groundtruth):  # the progress bar reads their tails
            stale.unlink(missing_ok=True)
        offboard_port = _free_udp_port()
        listen_port = _free_udp_port()
        library = out_dir / f"library-{k}.sqlite"
        cfg = service_config_for(args, scenario, k, offboard_port, run_dir, library)
        (run_dir / "service.toml").write_text(dump_toml(cfg))
        sitl_cmd = [
            sys.executable, "-m", "sitl.main", "--instance", str(k - 1),
            "--listen-port", str(listen_port), "--offboard-port", str(offboard_port),
            "--gcs-port", str(_gcs_port(args, k)), "--groundtruth", str(run.groundtruth),
            "--seed", str(args.seed + k - 1), "--wind", f"{wind[0]},{wind[1]}",
        ]  # fmt: skip
        if args.lockstep:
            sitl_cmd.append("--lockstep")
        autopilot = getattr(args, "autopilot", "px4")
        sitl_cmd += ["--autopilot", autopilot]
        if autopilot == "ardupilot":
            # what the README asks of a real ArduCopter: thrust as throttle, not climb rate
            sitl_cmd += ["--param", "GUID_OPTIONS=8"]
        run.service = _start(
            [
                sys.executable,
                "-m",
                "epc_offboard.cli",
                "run",
                "--config",
                str(run_dir / "service.toml"),
            ],
            run_dir / "service.log",
        )
        run.sitl = _start(sitl_cmd, run_dir / "sitl.log")
        runs.append(run)

    for k in range(1, (1 if stagger else args.vehicles) + 1):
        start(k)
    expected_s = scenario.duration_s + 20.0  # takeoff, offboard entry, landing
    flights = args.vehicles if stagger else 1
    deadline = time.monotonic() + flights * max(120.0, 20.0 * expected_s)
    # the bar counts the scenario's seconds under offboard, the only ones the scenario names;
    # takeoff and landing show as the phase in its label
    total_s = scenario.duration_s * (args.vehicles if stagger else 1)
    try:
        with Progress(
            TextColumn("[bold]{task.description}"),
            BarColumn(),
            TextColumn("{task.completed:.1f}/{task.total:.0f} s offboard"),
            TimeElapsedColumn(),
            transient=False,
            disable=not sys.stderr.isatty(),
        ) as progress:
            task = progress.add_task(f"{args.scenario}: takeoff", total=total_s)
            while any(r.service is not None and r.service.poll() is None for r in runs):
                if time.monotonic() > deadline:
                    raise RuntimeError("the flight did not finish in time (see the vehicle logs)")
                if any(r.sitl is not None and r.sitl.poll() is not None for r in runs):
                    raise RuntimeError("a SITL process exited early (see sitl.log)")
                if stagger and runs[-1].stats.exists():  # the newest vehicle has landed
                    if len(runs) < args.vehicles:
                        start(len(runs) + 1)
                    else:
                        for r in runs:
                            _stop(r.service)
                states = [flight_progress(r, scenario.duration_s) for r in runs]
                done_s = sum(s[1] for s in states) if stagger else min(s[1] for s in states)
                phase = states[-1][0] if stagger else states[0][0]
                who = f" vehicle {len(runs)}/{args.vehicles}" if args.vehicles > 1 else ""
                label = f"{args.scenario}{who}: {phase}"
                progress.update(task, completed=min(done_s, total_s), description=label)
                time.sleep(0.2)
            progress.update(task, completed=total_s, description=f"{args.scenario}: landed")
    finally:
        for r in runs:
            _stop(r.service)
            _stop(r.sitl)
    for r in runs:
        if r.service is not None and r.service.returncode != 0:
            raise RuntimeError(
                f"vehicle {r.vehicle_id}: service exited with {r.service.returncode} "
                f"(see {r.out_dir / 'service.log'})"
            )
    return runs


# -- the report ---------------------------------------------------------------------------


def _read_csv(path: Path) -> dict[str, np.ndarray]:
    with path.open(newline="") as fh:
        rows = list(csv.reader(fh))
    if len(rows) < 2:
        raise RuntimeError(f"{path}: no data")
    header, body = rows[0], rows[1:]
    body = [r for r in body if len(r) == len(header)]
    out: dict[str, np.ndarray] = {}
    for i, name in enumerate(header):
        col = [r[i] for r in body]
        try:
            out[name] = np.array([float(v) for v in col])
        except ValueError:
            out[name] = np.array(col)
    return out


@dataclass(frozen=True)
class VehicleResult:
    vehicle_id: int
    report: dict[str, Any]
    t_s: FloatArray
    pos_ned_m: FloatArray
    ref_ned_m: FloatArray
    vel_ned_m_s: FloatArray
    error_m: FloatArray
    sources: np.ndarray
    # the SITL's ground truth over the whole flight (takeoff to landing), t since offboard
    truth_t_s: FloatArray = field(default_factory=lambda: np.zeros(0))
    truth_pos_ned_m: FloatArray = field(default_factory=lambda: np.zeros((0, 3)))
    truth_vel_ned_m_s: FloatArray = field(default_factory=lambda: np.zeros((0, 3)))


_MISS_SOURCES = ("solved", "intermediate", "fallback")  # EPC ticks that were not hits

# What a user must see without opening a log: service counters (stats.json "counters") and
# SITL counters (its closing "counters" line) that mean the flight was not clean.
_SERVICE_WARNINGS = {
    "failsafes": "failsafes",
    "position_loop_errors": "position loop errors",
    "attitude_loop_errors": "attitude loop errors",
    "position_ticks_skipped": "position ticks skipped",
    "attitude_ticks_skipped": "attitude ticks skipped",
    "attitude_late_fallbacks": "late attitude ticks (attitude sent instead of rates)",
    "clock_wait_timeouts": "loop clock waits timed out",
    "non_finite_setpoints_replaced": "non-finite setpoints replaced",
    "commands_not_encoded": "commands not encoded",
    "store_errors": "library store errors",
    "offboard_refused": "offboard requests refused (ArduPilot GUID_OPTIONS)",
    "heartbeats_other_autopilot": "heartbeats of another autopilot than link.autopilot",
}
_SITL_WARNINGS = {
    "lockstep_timeouts": "SITL lockstep timeouts",
    "offboard_failsafes": "SITL offboard-loss failsafes",
    "handler_errors": "SITL message handler errors",
    "nan_setpoints": "non-finite setpoints received by the SITL",
    "rtl_entered": "SITL RTLs entered",
}


def sitl_counters(log_path: Path) -> dict[str, int]:
    """The counters the SITL prints when it stops (``epc-sitl: counters k=v ...``)."""
    try:
        lines = log_path.read_text(errors="replace").splitlines()
    except OSError:
        return {}
    for line in reversed(lines):
        if line.startswith("epc-sitl: counters "):
            pairs = (kv.split("=", 1) for kv in line.split()[2:] if "=" in kv)
            return {k: int(v) for k, v in pairs if v.lstrip("-").isdigit()}
    return {}


def flight_warnings(stats: dict[str, Any], sitl: dict[str, int]) -> dict[str, int]:
    """Everything that went wrong in a flight, by readable name, with its count (0s left out);
    stale-state failsafes are named on their own."""
    counters = stats.get("counters", {})
    out = {name: int(counters.get(key, 0)) for key, name in _SERVICE_WARNINGS.items()}
    out["stale-state failsafes"] = sum(
        1
        for e in stats.get("phase_events", [])
        if e.get("phase") == "failsafe" and "stale" in str(e.get("reason", ""))
    )
    out.update({name: int(sitl.get(key, 0)) for key, name in _SITL_WARNINGS.items()})
    return {k: v for k, v in out.items() if v}


def analyse(run: VehicleRun, scenario: ScenarioConfig, vel_bounds_m_s: FloatArray) -> VehicleResult:
    flight = _read_csv(run.flight_log)
    truth = _read_csv(run.groundtruth)
    stats = json.loads(run.stats.read_text()) if run.stats.exists() else {}
    tracking = flight["phase"] == "offboard"
    t_vehicle = flight["vehicle_t_s"]
    if not np.any(tracking):
        raise RuntimeError(f"vehicle {run.vehicle_id}: never flew in offboard (see service.log)")
    start = float(t_vehicle[tracking][0])
    use = tracking & (t_vehicle >= start + scenario.settle_s)
    tt = truth["t_s"]
    pos = np.column_stack([np.interp(t_vehicle, tt, truth[f"pos_{a}_m"]) for a in "ned"])
    vel = np.column_stack([np.interp(t_vehicle, tt, truth[f"vel_{a}_m_s"]) for a in "ned"])
    ref = np.column_stack([flight[f"ref_pos_{a}_m"] for a in "ned"])
    err = np.linalg.norm(pos - ref, axis=1)
    # velocity bound checks on every ground-truth sample after settling, not only at log ticks
    truth_use = (tt >= start + scenario.settle_s) & (tt <= float(t_vehicle[tracking][-1]))
    tvel = np.column_stack([truth[f"vel_{a}_m_s"][truth_use] for a in "ned"])
    violations = int(np.sum(np.any(np.abs(tvel) > vel_bounds_m_s + 1e-9, axis=1)))
    lib = stats.get("library", {}).get("position", {})
    hits, misses = int(lib.get("hits", 0)), int(lib.get("misses", 0))
    # what a vehicle had to solve on its first lap: the measure of what a prior library (its
    # own from an earlier flight, or the fleet's) spares it
    lap_s = scenario.lap_s or scenario.duration_s
    first_lap = tracking & (t_vehicle < start + lap_s)
    first_lap_misses = int(np.sum(np.isin(flight["source"][first_lap], _MISS_SOURCES)))
    report = {
        "id": run.vehicle_id,
        "tracking": {
            "rmse_m": float(np.sqrt(np.mean(err[use] ** 2))) if np.any(use) else math.nan,
            "max_error_m": float(np.max(err[use])) if np.any(use) else math.nan,
        },
        "max_speed_m_s": float(np.max(np.linalg.norm(tvel, axis=1))) if len(tvel) else 0.0,
        "max_abs_vel_m_s": [float(v) for v in np.max(np.abs(tvel), axis=0)]
        if len(tvel)
        else [0.0] * 3,
        "constraint_violations": violations,
        "library": {
            "size": int(lib.get("size", 0)),
            "hits": hits,
            "misses": misses,
            "hit_rate": hits / (hits + misses) if hits + misses else 0.0,
            "qp_solves": int(lib.get("qp_solves", 0)),
            "received_shared": int(lib.get("received_shared", 0)),
            "first_lap_misses": first_lap_misses,
        },
        "loops": stats.get("loops", {}),
        # what the autopilot actually streamed (the service asks for the loops' rates) and
        # how many takeoffs the service commanded (one per flight, never in the air)
        "received_rates_hz": stats.get("rates_hz", {}),
        "takeoffs_sent": int(stats.get("takeoffs_sent", 0)),
        "autopilot": stats.get("autopilot"),
        "attitude_mode": stats.get("attitude_mode"),
        "miss_worker": stats.get("miss_worker", {}),
        "warnings": flight_warnings(stats, sitl_counters(run.out_dir / "sitl.log")),
        # phase transitions, seconds since offboard was entered (negative: before)
        "phase_events": [
            {**e, "t_s": round(float(e["t_s"]) - start, 3)} for e in stats.get("phase_events", [])
        ],
    }
    every = slice(None, None, max(1, len(tt) // 4000))  # enough samples to draw
    return VehicleResult(
        run.vehicle_id, report, t_vehicle - start, pos, ref, vel, err, flight["source"],
        truth_t_s=tt[every] - start,
        truth_pos_ned_m=np.column_stack([truth[f"pos_{a}_m"][every] for a in "ned"]),
        truth_vel_ned_m_s=np.column_stack([truth[f"vel_{a}_m_s"][every] for a in "ned"]),
    )  # fmt: skip


REPORT_COLUMNS = ("id", "RMSE cm", "max cm", "max m/s", "viol.", "hits", "lap-1 misses",
                  "QPs", "received", "pos Hz", "pos p99 us", "att Hz")  # fmt: skip


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
            str(lib.get("received_shared", 0)) if epc else "-",
            f"{pos.get('rate_hz', 0.0):.1f}",
            f"{pos.get('compute_us_p99', 0.0):.0f}",
            f"{att.get('rate_hz', 0.0):.1f}",
        ])  # fmt: skip
    return rows


def print_table(report: dict[str, Any], file: TextIO | None = None) -> None:
    """The report's table (rich on a terminal, plain aligned text when piped), the scenario's
    note when it has one, and each vehicle's warnings."""
    from epc_offboard.tools.tables import print_table as print_any_table

    out = file if file is not None else sys.stdout
    title = f"{report['scenario']}: {report['controller']} + {report['adaptation']}"
    print_any_table(title, REPORT_COLUMNS, report_rows(report), file=out)
    if report.get("note"):
        print(f"note: {report['note']}", file=out)
    for v in report["vehicles"]:
        warnings = v.get("warnings", {})
        text = ", ".join(f"{name} {n}" for name, n in warnings.items()) or "none"
        print(f"vehicle {v['id']} warnings: {text}", file=out)


def print_targets(verdicts: list[dict[str, Any]], file: TextIO | None = None) -> None:
    """One line per target verdict, values in the metric's unit (errors in cm)."""
    from epc_offboard.tools.tables import format_metric

    for t in verdicts:
        value = format_metric(t["metric"], t["value"])
        bound = format_metric(t["metric"], t["bound"])
        print(f"target {t['verdict']}: {t['target']} ({value} <= {bound})", file=file)


def make_report(
    args: argparse.Namespace, scenario: ScenarioConfig, results: list[VehicleResult]
) -> dict[str, Any]:
    """The CONTRACTS.md `sim --json` report of one flight."""
    wind = args.wind or (scenario.wind_speed_m_s, scenario.wind_dir_deg)
    return {
        "scenario": args.scenario,
        "controller": args.controller,
        "adaptation": args.adaptation,
        "wind": {"speed_m_s": wind[0], "dir_deg": wind[1]},
        "duration_s": scenario.duration_s,
        "seed": args.seed,
        "note": scenario.note,
        "lockstep": bool(args.lockstep),
        "vehicles": [r.report for r in results],
    }


def fly_and_report(
    args: argparse.Namespace, scenario: ScenarioConfig, out_dir: Path, title: str
) -> tuple[dict[str, Any], list[VehicleResult], FloatArray]:
    """Fly, analyse on ground truth, write ``report.json`` and ``flight.png`` to ``out_dir``;
    returns (report, results, velocity bounds m/s). RuntimeError if a flight failed."""
    runs = fly(args, scenario, out_dir)
    cfg_text = (runs[0].out_dir / "service.toml").read_text()
    bounds = np.array(tomllib.loads(cfg_text)["position"]["max_vel_m_s"], dtype=np.float64)
    results = [analyse(r, scenario, bounds) for r in runs]
    from epc_offboard.tools.logexport import flight_csv_to_mcap

    for r in runs:  # the per-tick log for Foxglove Studio and PlotJuggler, beside the CSV
        flight_csv_to_mcap(r.flight_log, r.flight_log.with_suffix(".mcap"))
    report = make_report(args, scenario, results)
    (out_dir / "report.json").write_text(json.dumps(report, indent=2))
    write_figure(results, bounds, out_dir / "flight.png", title, settle_s=scenario.settle_s)
    return report, results, bounds


def scenario_for(args: argparse.Namespace) -> ScenarioConfig:
    """The scenario named by ``--scenario`` with ``--duration`` applied (UsageError if bad)."""
    from epc_offboard.common.errors import UsageError

    if args.vehicles < 1:
        raise UsageError("--vehicles must be >= 1")
    try:
        scenario = load_scenario(args.scenario)
    except ConfigError as exc:
        raise UsageError(str(exc)) from exc
    if args.duration is not None:
        if args.duration <= scenario.settle_s:
            raise UsageError(
                f"--duration must exceed the scenario's settle time {scenario.settle_s} s"
            )
        scenario = ScenarioConfig(**{**vars(scenario), "duration_s": args.duration})
    return scenario


def _stop_on_sigterm() -> None:
    """SIGTERM (systemd, a test harness, `kill`) ends sim as Ctrl-C does: through the
    ``finally`` that stops every SITL and service it started (the default action killed sim
    alone and left its children flying)."""

    def handler(signum: int, _frame: object) -> None:
        raise SystemExit(128 + signum)

    signal.signal(signal.SIGTERM, handler)


def run_sim_command(args: argparse.Namespace) -> int:
    from epc_offboard.common.errors import EXIT_RUNTIME

    _stop_on_sigterm()
    if getattr(args, "compare", None) is not None:
        from epc_offboard.tools.compare import run_compare_command

        return run_compare_command(args)
    scenario = scenario_for(args)
    out_dir = Path(args.out)
    out_dir.mkdir(parents=True, exist_ok=True)
    try:
        report, _results, _bounds = fly_and_report(
            args, scenario, out_dir, f"{args.scenario}: {args.controller} + {args.adaptation}"
        )
    except RuntimeError as exc:
        print(f"epc-offboard sim: {exc}", file=sys.stderr)
        return EXIT_RUNTIME
    from epc_offboard.tools.targets import evaluate, method_name

    # the scenario's declared targets that this one method can be judged on
    method = method_name(args.controller, args.adaptation)
    report["targets"] = [
        v for v in evaluate(scenario.targets, {method: report}) if v["verdict"] != "n/a"
    ]
    (out_dir / "report.json").write_text(json.dumps(report, indent=2))
    if args.json:
        Path(args.json).write_text(json.dumps(report, indent=2))
    print_table(report)
    print_targets(report["targets"])
    print(f"report: {out_dir / 'report.json'}  figure: {out_dir / 'flight.png'}")
    return targets_exit_code(report["targets"])


def targets_exit_code(verdicts: list[dict[str, Any]]) -> int:
    """0 when no declared target failed, else 1 (named on stderr)."""
    from epc_offboard.common.errors import EXIT_OK, EXIT_RUNTIME

    failed = [v["target"] for v in verdicts if v["verdict"] == "FAIL"]
    if failed:
        print(f"epc-offboard sim: targets failed: {'; '.join(failed)}", file=sys.stderr)
        return EXIT_RUNTIME
    return EXIT_OK
