"""What a sim flight achieved, from what it left behind: pure, no printing, no plotting.

Tracking error is measured on ground truth (the SITL's true position, not the noisy
estimate), against the reference the service was tracking at that vehicle time, over the part
of the flight after the scenario's ``settle_s``. The readers at the top read only the files
they are handed; :func:`analyse` works on what they read.
"""

from __future__ import annotations

import csv
import json
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from epc_offboard.common.frames import FloatArray
from epc_offboard.tools.sim.envelope import Envelope, breaches, tilt_deg_of
from epc_offboard.tools.sim.logscan import LogKind, log_kinds
from epc_offboard.tools.sim.scenario import ScenarioConfig

Columns = dict[str, np.ndarray]  # a CSV's columns by header name: floats where they parse

MISS_SOURCES = ("solved", "intermediate", "fallback")  # EPC ticks that were not hits

# What a user must see without opening a log: service counters (stats.json "counters") and
# SITL counters (its closing "counters" line) that mean the flight was not clean.
_SERVICE_WARNINGS = {
    "failsafes": "failsafes",
    "position_loop_errors": "position loop errors",
    "attitude_loop_errors": "attitude loop errors",
    "position_ticks_skipped": "position ticks skipped",
    "attitude_ticks_skipped": "attitude ticks skipped",
    "attitude_late_fallbacks": "late attitude ticks (attitude sent instead of rates)",
    "attitude_envelope_fallbacks": "attitude beyond the rate EPC's envelope (autopilot's loop)",
    "sharing_open_failed": "fleet sharing failed to open (flew alone)",
    "hover_thrust_mismatch": "hover thrust differs from the autopilot's",
    "heartbeats_unknown_autopilot": "heartbeats of an unknown autopilot",
    "attitude_model_fallbacks": "body rates suspended: the rate model did not predict",
    "clock_wait_timeouts": "loop clock waits timed out",
    "non_finite_setpoints_replaced": "non-finite setpoints replaced",
    "commands_not_encoded": "commands not encoded",
    "store_errors": "library store errors",
    "offboard_refused": "offboard requests refused (ArduPilot GUID_OPTIONS)",
    "heartbeats_other_autopilot": "heartbeats of another autopilot than link.autopilot",
    "realtime_priority_refused": "loops' real-time priority refused (normal scheduling)",
    "unready_entries": "offboard entered before the controller was ready (miss worker)",
    "log_lines_dropped": "service log lines dropped (its logged warnings may be incomplete)",
    # the flight log's rows the writer fell behind on: flight.csv has gaps (two lockstep
    # flights of one seed then differ in their files, not in their flight)
    "log_records_dropped": "flight log records dropped (flight.csv has gaps)",
}
# the state tracker's (stats.json "state"): what it would not believe
_STATE_WARNINGS = {
    "heartbeat_flaps": "heartbeat flaps (forged heartbeats?)",
    "state_conflicts": "contradicting state streams (forged telemetry?)",
    "rejected_innovation": "state samples far from the prediction (not flown)",
    "rejected_nan": "state samples not finite (not flown)",
    "rejected_range": "state samples out of range (not flown)",
    "rejected_quaternion": "attitude samples not a unit quaternion (not flown)",
    "rejected_time_jump": "state samples stamped off their stream's timeline (not flown)",
}
_SITL_WARNINGS = {
    "lockstep_timeouts": "SITL lockstep timeouts",
    # counted: a flight that ran on the wall clock for a while is not its seed's alone
    "lockstep_fallbacks": "lockstep fell back to real time",
    "offboard_failsafes": "SITL offboard-loss failsafes",
    "handler_errors": "SITL message handler errors",
    "nan_setpoints": "non-finite setpoints received by the SITL",
    "rtl_entered": "SITL RTLs entered",
    "realtime_priority_refused": "SITL real-time priority refused (normal scheduling)",
}

# -- reading what a flight left behind ----------------------------------------------------------


@dataclass(frozen=True)
class FlightRecord:
    """One vehicle's flight as its files recorded it."""

    vehicle_id: int
    flight: Columns  # the service's per-tick flight log: vehicle_t_s, phase, ref_pos_*_m, source
    truth: Columns  # the SITL's ground truth: t_s, pos_{n,e,d}_m, vel_{n,e,d}_m_s
    stats: dict[str, Any] = field(default_factory=dict)  # the service's stats.json
    sitl_counters: dict[str, int] = field(default_factory=dict)  # see sitl_counters()
    logs: dict[str, str] = field(default_factory=dict)  # each process's log: "service", "sitl"
    sharing_asked: bool = False  # the service was configured to share over Zenoh
    moved_aside: tuple[str, ...] = ()  # library files the service moved aside in this run
    stopped: str = ""  # why the flight was ended before it finished ("": it was not)


def read_csv_columns(path: Path, *, allow_empty: bool = False) -> Columns:
    """A CSV's columns (rows of another length than the header's left out: a torn last line);
    RuntimeError when it has no data (``allow_empty``: empty columns when it has a header)."""
    try:
        with path.open(newline="") as fh:
            rows = list(csv.reader(fh))
    except OSError as exc:
        if allow_empty:
            return {}
        raise RuntimeError(f"{path}: {exc.strerror}") from exc
    if len(rows) < 2 and not (allow_empty and rows):
        raise RuntimeError(f"{path}: no data")
    header, body = rows[0], rows[1:]
    body = [r for r in body if len(r) == len(header)]
    out: Columns = {}
    for i, name in enumerate(header):
        col = [r[i] for r in body]
        try:
            out[name] = np.array([float(v) for v in col])
        except ValueError:
            out[name] = np.array(col)
    return out


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


def _read_text(path: Path | None) -> str:
    try:
        return path.read_text(errors="replace") if path is not None else ""
    except OSError:
        return ""


def read_flight(
    vehicle_id: int,
    *,
    flight_log: Path,
    groundtruth: Path,
    stats: Path,
    sitl_log: Path,
    service_log: Path | None = None,
    **facts: Any,
) -> FlightRecord:
    """Read one vehicle's files (a missing stats file or log reads as empty, a flight log
    with no rows as a flight that never streamed); ``facts``: the other FlightRecord fields
    the caller knows (sharing_asked, moved_aside, stopped)."""
    try:
        stats_json = json.loads(stats.read_text()) if stats.exists() else {}
    except ValueError:  # a service killed while writing it
        stats_json = {}
    return FlightRecord(
        vehicle_id,
        read_csv_columns(flight_log, allow_empty=True),
        read_csv_columns(groundtruth),
        stats_json,
        sitl_counters(sitl_log),
        logs={"service": _read_text(service_log), "sitl": _read_text(sitl_log)},
        **facts,
    )


# -- the numbers --------------------------------------------------------------------------------


@dataclass(frozen=True)
class VehicleResult:
    """One vehicle's flight, analysed. Arrays are per flight-log tick (T rows), times in
    seconds since the vehicle entered offboard (negative: before)."""

    vehicle_id: int
    report: dict[str, Any]  # the vehicle's entry of the docs/CONTRACTS.md report
    t_s: FloatArray  # (T,)
    pos_ned_m: FloatArray  # (T, 3) ground truth at the log's ticks
    ref_ned_m: FloatArray  # (T, 3) the reference the service was tracking
    vel_ned_m_s: FloatArray  # (T, 3) ground truth at the log's ticks
    error_m: FloatArray  # (T,) |pos - ref|
    sources: np.ndarray  # (T,) str: where each tick's control came from (MISS_SOURCES...)
    # the SITL's ground truth over the whole flight (takeoff to landing), t since offboard
    truth_t_s: FloatArray = field(default_factory=lambda: np.zeros(0))
    truth_pos_ned_m: FloatArray = field(default_factory=lambda: np.zeros((0, 3)))
    truth_vel_ned_m_s: FloatArray = field(default_factory=lambda: np.zeros((0, 3)))
    truth_tilt_deg: FloatArray = field(default_factory=lambda: np.zeros(0))


def flight_warnings(
    stats: dict[str, Any], sitl: dict[str, int], logged: list[LogKind] | None = None
) -> dict[str, int]:
    """Everything that went wrong in a flight, by readable name, with its count (0s left out):
    the service's and the SITL's counters, stale-state failsafes on their own, and every kind
    of WARNING/ERROR line a process logged (keyed by :attr:`LogKind.key`)."""
    counters = stats.get("counters", {})
    out = {name: int(counters.get(key, 0)) for key, name in _SERVICE_WARNINGS.items()}
    state = stats.get("state", {})
    out.update({name: int(state.get(key, 0)) for key, name in _STATE_WARNINGS.items()})
    out["stale-state failsafes"] = sum(
        1
        for e in stats.get("phase_events", [])
        if e.get("phase") == "failsafe" and "stale" in str(e.get("reason", ""))
    )
    out.update({name: int(sitl.get(key, 0)) for key, name in _SITL_WARNINGS.items()})
    out.update({kind.key: kind.count for kind in logged or ()})
    return {k: v for k, v in out.items() if v}


def fleet_figures(stats: dict[str, Any]) -> dict[str, Any]:
    """What the fleet gave this vehicle: the controllers that arrived (new to it, both loops'
    problems) and those it used, i.e. promoted into its library once the KKT check proved one
    optimal at a state it flew. They differ: a controller for states this vehicle never
    visits arrives and stays a candidate (with --stagger a landed vehicle still receives the
    later ones'), so "used" alone read 0 while the log showed candidates arriving."""
    libs = stats.get("library", {})
    return {
        "controllers_received": int(stats.get("sharing", {}).get("entries_offered", 0)),
        "controllers_used": {
            loop: int(libs.get(loop, {}).get("received_shared", 0))
            for loop in ("position", "attitude")
        },
    }


def _columns(cols: Columns, names: list[str], rows: int) -> FloatArray:
    """(rows, len(names)) of the named columns, zeros for a missing one."""
    return np.column_stack(
        [np.asarray(cols[n], dtype=np.float64) if n in cols else np.zeros(rows) for n in names]
    )


def _envelope_check(
    record: FlightRecord, envelope: Envelope, start_s: float
) -> tuple[list[dict[str, Any]], dict[str, float]]:
    """(breaches, the worst values) of the flight's ground truth from the SITL's start to
    one second after the service saw it landed (a staggered vehicle's SITL runs on): see
    :mod:`.envelope` for what is judged when."""
    truth, flight = record.truth, record.flight
    tt = np.asarray(truth["t_s"], dtype=np.float64)
    events = record.stats.get("phase_events", [])
    done = [float(e["t_s"]) for e in events if e.get("phase") == "done"]
    keep = tt <= (done[0] + 1.0 if done else np.inf)
    tt = tt[keep]
    pos = _columns(truth, [f"pos_{a}_m" for a in "ned"], len(keep))[keep]
    q = _columns(truth, ["q_w", "q_x", "q_y", "q_z"], len(keep))[keep]
    tilt = tilt_deg_of(q) if "q_w" in truth else np.zeros(len(tt))
    # the reference while the service flew it under offboard; before: home (the autopilot
    # takes off over it), after: the last one (its landing descends where it is)
    offboard = np.asarray(flight.get("phase", ())) == "offboard"
    t_log = np.asarray(flight.get("vehicle_t_s", np.zeros(0)), dtype=np.float64)[offboard]
    ref = np.zeros_like(pos)
    horizontal = np.ones(len(tt), dtype=bool)
    if len(t_log):
        ref_log = _columns(flight, [f"ref_pos_{a}_m" for a in "ned"], len(offboard))[offboard]
        for k in range(3):
            ref[:, k] = np.interp(tt, t_log, ref_log[:, k])
        ref[tt < t_log[0]] = 0.0
        horizontal = (tt < t_log[0]) | (tt > t_log[-1])
    found = breaches(envelope, tt - start_s, pos, tilt, ref, horizontal, flight_s=tt)
    diff = pos - ref
    diff[horizontal, 2] = 0.0
    distance = np.linalg.norm(diff, axis=1)
    worst = {
        "distance_from_reference_m": float(np.max(distance[~horizontal], initial=0.0)),
        "drift_m": float(np.max(distance[horizontal], initial=0.0)),
        "altitude_m": float(np.max(-pos[:, 2], initial=0.0)),
        "tilt_deg": float(np.max(tilt, initial=0.0)),
        "flight_s": float(tt[-1]) if len(tt) else 0.0,
    }
    return [b.as_dict() for b in found], worst


def analyse(
    record: FlightRecord,
    scenario: ScenarioConfig,
    vel_bounds_m_s: FloatArray,
    envelope: Envelope | None = None,
) -> VehicleResult:
    """The vehicle's report entry and its curves; ``vel_bounds_m_s`` (3,) NED, the state
    constraint the violations are counted against; ``envelope``: the bounds the flight is
    judged sane within (None: not judged).

    A vehicle that never flew under offboard is reported too (no tracking figures, times
    since its SITL started): what it did instead is the report's point."""
    flight, truth, stats = record.flight, record.truth, record.stats
    rows = len(flight.get("vehicle_t_s", ()))
    t_vehicle = np.asarray(flight.get("vehicle_t_s", np.zeros(0)), dtype=np.float64)
    phase = np.asarray(flight.get("phase", np.full(rows, "")))
    source = np.asarray(flight.get("source", np.full(rows, "")))
    tracking = phase == "offboard"
    flew_offboard = bool(np.any(tracking))
    start = float(t_vehicle[tracking][0]) if flew_offboard else 0.0
    end = float(t_vehicle[tracking][-1]) if flew_offboard else -np.inf
    use = tracking & (t_vehicle >= start + scenario.settle_s)
    tt = truth["t_s"]
    pos = np.column_stack([np.interp(t_vehicle, tt, truth[f"pos_{a}_m"]) for a in "ned"])
    vel = np.column_stack([np.interp(t_vehicle, tt, truth[f"vel_{a}_m_s"]) for a in "ned"])
    ref = _columns(flight, [f"ref_pos_{a}_m" for a in "ned"], rows).reshape(rows, 3)
    pos, vel = pos.reshape(rows, 3), vel.reshape(rows, 3)
    err = np.linalg.norm(pos - ref, axis=1)
    # velocity bound checks on every ground-truth sample after settling, not only at log ticks
    truth_use = (tt >= start + scenario.settle_s) & (tt <= end)
    tvel = np.column_stack([truth[f"vel_{a}_m_s"][truth_use] for a in "ned"])
    violations = int(np.sum(np.any(np.abs(tvel) > vel_bounds_m_s + 1e-9, axis=1)))
    # tilt over the whole offboard phase (entry included): an attitude loop that oscillates
    # shows here first; cos(tilt) = 1 - 2 (qx² + qy²)
    offboard = (tt >= start) & (tt <= end)
    max_tilt_deg = math.nan  # (a ground truth without the attitude says nothing)
    if "q_x" in truth and "q_y" in truth and np.any(offboard):
        qx, qy = truth["q_x"][offboard], truth["q_y"][offboard]
        cos_tilt = np.clip(1.0 - 2.0 * (qx * qx + qy * qy), -1.0, 1.0)
        max_tilt_deg = float(np.degrees(np.arccos(cos_tilt.min())))
    lib = stats.get("library", {}).get("position", {})
    hits, misses = int(lib.get("hits", 0)), int(lib.get("misses", 0))
    # what a vehicle had to solve on its first lap: the measure of what a prior library (its
    # own from an earlier flight, or the fleet's) spares it
    lap_s = scenario.lap_s or scenario.duration_s
    first_lap = tracking & (t_vehicle < start + lap_s)
    first_lap_misses = int(np.sum(np.isin(source[first_lap], MISS_SOURCES)))
    # and once it has seen a lap: the share of EPC's ticks the library answered
    later = tracking & (t_vehicle >= start + lap_s) & np.isin(source, ("hit", *MISS_SOURCES))
    later_hits = int(np.sum(source[later] == "hit"))
    logged = [k for process, text in record.logs.items() for k in log_kinds(text, process)]
    events = stats.get("phase_events", [])
    sharing_open = bool(stats.get("sharing")) and not stats.get("counters", {}).get(
        "sharing_open_failed", 0
    )
    report = {
        "id": record.vehicle_id,
        "flew_offboard": flew_offboard,
        "tracking": {
            "rmse_m": float(np.sqrt(np.mean(err[use] ** 2))) if np.any(use) else math.nan,
            "max_error_m": float(np.max(err[use])) if np.any(use) else math.nan,
        },
        "max_speed_m_s": float(np.max(np.linalg.norm(tvel, axis=1))) if len(tvel) else 0.0,
        "max_abs_vel_m_s": [float(v) for v in np.max(np.abs(tvel), axis=0)]
        if len(tvel)
        else [0.0] * 3,
        "constraint_violations": violations,
        "max_tilt_deg": max_tilt_deg,
        "library": {
            "size": int(lib.get("size", 0)),
            "hits": hits,
            "misses": misses,
            "hit_rate": hits / (hits + misses) if hits + misses else 0.0,
            "qp_solves": int(lib.get("qp_solves", 0)),
            "received_shared": int(lib.get("received_shared", 0)),
            "first_lap_misses": first_lap_misses,
            "hit_rate_after_first_lap": later_hits / int(np.sum(later)) if np.any(later) else None,
        },
        "fleet": fleet_figures(stats),
        "loops": stats.get("loops", {}),
        # what the autopilot actually streamed (the service asks for the loops' rates) and
        # how many takeoffs the service commanded (one per flight, never in the air)
        "received_rates_hz": stats.get("rates_hz", {}),
        "takeoffs_sent": int(stats.get("takeoffs_sent", 0)),
        "autopilot": stats.get("autopilot"),
        "attitude_mode": stats.get("attitude_mode"),
        "attitude_rate_model": stats.get("attitude_rate_model", {}),
        "miss_worker": stats.get("miss_worker", {}),
        "warnings": flight_warnings(stats, record.sitl_counters, logged),
        # the first line of each kind of logged warning or error, by its key in "warnings"
        "warning_examples": {k.key: k.first for k in logged},
        "sharing": {"asked": record.sharing_asked, "open": record.sharing_asked and sharing_open},
        "library_moved_aside": list(record.moved_aside),
        # the flight ended as flights do (landed and disarmed), or why it did not
        "finished": not record.stopped and any(e.get("phase") == "done" for e in events),
        "stopped": record.stopped or None,
        # phase transitions, seconds since offboard was entered (negative: before; without
        # offboard, since the SITL started)
        "phase_events": [{**e, "t_s": round(float(e["t_s"]) - start, 3)} for e in events],
    }
    if "mean_error_m" in scenario.metrics:  # Neural-Fly's figure: mean |p - p_d|
        report["tracking"]["mean_error_m"] = float(np.mean(err[use])) if np.any(use) else math.nan
    if envelope is not None:
        found, worst = _envelope_check(record, envelope, start)
        report["envelope"] = {"bounds": envelope.as_dict(), "worst": worst, "left": found}
        # sim's own judgements are warnings too: never "warnings: none" beside a FAILED
        report["warnings"].update({f"left its envelope: {b['what']}": 1 for b in found})
    if record.stopped:
        report["warnings"]["stopped by sim before it finished"] = 1
    every = slice(None, None, max(1, len(tt) // 4000))  # enough samples to draw
    q = _columns(truth, ["q_w", "q_x", "q_y", "q_z"], len(tt))
    return VehicleResult(
        record.vehicle_id, report, t_vehicle - start, pos, ref, vel, err, source,
        truth_t_s=tt[every] - start,
        truth_pos_ned_m=np.column_stack([truth[f"pos_{a}_m"][every] for a in "ned"]),
        truth_vel_ned_m_s=np.column_stack([truth[f"vel_{a}_m_s"][every] for a in "ned"]),
        truth_tilt_deg=tilt_deg_of(q[every]) if "q_w" in truth else np.zeros(len(tt[every])),
    )  # fmt: skip
