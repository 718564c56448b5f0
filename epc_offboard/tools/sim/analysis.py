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
    "clock_wait_timeouts": "loop clock waits timed out",
    "non_finite_setpoints_replaced": "non-finite setpoints replaced",
    "commands_not_encoded": "commands not encoded",
    "store_errors": "library store errors",
    "offboard_refused": "offboard requests refused (ArduPilot GUID_OPTIONS)",
    "heartbeats_other_autopilot": "heartbeats of another autopilot than link.autopilot",
    "realtime_priority_refused": "loops' real-time priority refused (normal scheduling)",
}
# the state tracker's (stats.json "state"): what it would not believe
_STATE_WARNINGS = {
    "heartbeat_flaps": "heartbeat flaps (forged heartbeats?)",
    "state_conflicts": "contradicting state streams (forged telemetry?)",
    "rejected_innovation": "state samples far from the prediction (not flown)",
}
_SITL_WARNINGS = {
    "lockstep_timeouts": "SITL lockstep timeouts",
    "offboard_failsafes": "SITL offboard-loss failsafes",
    "handler_errors": "SITL message handler errors",
    "nan_setpoints": "non-finite setpoints received by the SITL",
    "rtl_entered": "SITL RTLs entered",
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


def read_csv_columns(path: Path) -> Columns:
    """A CSV's columns (rows of another length than the header's left out: a torn last line);
    RuntimeError when it has no data."""
    with path.open(newline="") as fh:
        rows = list(csv.reader(fh))
    if len(rows) < 2:
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


def read_flight(
    vehicle_id: int, *, flight_log: Path, groundtruth: Path, stats: Path, sitl_log: Path
) -> FlightRecord:
    """Read one vehicle's files (a missing stats file or SITL log reads as empty)."""
    return FlightRecord(
        vehicle_id,
        read_csv_columns(flight_log),
        read_csv_columns(groundtruth),
        json.loads(stats.read_text()) if stats.exists() else {},
        sitl_counters(sitl_log),
    )


# -- the numbers --------------------------------------------------------------------------------


@dataclass(frozen=True)
class VehicleResult:
    """One vehicle's flight, analysed. Arrays are per flight-log tick (T rows), times in
    seconds since the vehicle entered offboard (negative: before)."""

    vehicle_id: int
    report: dict[str, Any]  # the vehicle's entry of the CONTRACTS.md report
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


def flight_warnings(stats: dict[str, Any], sitl: dict[str, int]) -> dict[str, int]:
    """Everything that went wrong in a flight, by readable name, with its count (0s left out);
    stale-state failsafes are named on their own."""
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
    return {k: v for k, v in out.items() if v}


def analyse(
    record: FlightRecord, scenario: ScenarioConfig, vel_bounds_m_s: FloatArray
) -> VehicleResult:
    """The vehicle's report entry and its curves; ``vel_bounds_m_s`` (3,) NED, the state
    constraint the violations are counted against. RuntimeError if it never flew offboard."""
    flight, truth, stats = record.flight, record.truth, record.stats
    tracking = flight["phase"] == "offboard"
    t_vehicle = flight["vehicle_t_s"]
    if not np.any(tracking):
        raise RuntimeError(f"vehicle {record.vehicle_id}: never flew in offboard (see service.log)")
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
    first_lap_misses = int(np.sum(np.isin(flight["source"][first_lap], MISS_SOURCES)))
    report = {
        "id": record.vehicle_id,
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
        "warnings": flight_warnings(stats, record.sitl_counters),
        # phase transitions, seconds since offboard was entered (negative: before)
        "phase_events": [
            {**e, "t_s": round(float(e["t_s"]) - start, 3)} for e in stats.get("phase_events", [])
        ],
    }
    every = slice(None, None, max(1, len(tt) // 4000))  # enough samples to draw
    return VehicleResult(
        record.vehicle_id, report, t_vehicle - start, pos, ref, vel, err, flight["source"],
        truth_t_s=tt[every] - start,
        truth_pos_ned_m=np.column_stack([truth[f"pos_{a}_m"][every] for a in "ned"]),
        truth_vel_ned_m_s=np.column_stack([truth[f"vel_{a}_m_s"][every] for a in "ned"]),
    )  # fmt: skip
