"""Soak and fault injection: a long real-time flight with random faults, checked for the
safety invariants. CI runs a short form (tests/test_soak.py); the full form is

    python -m tests.soak --duration 600 --seed 1 --out out/soak

(loopback only, bounded in time: the flight lasts ``--duration`` seconds plus takeoff and
landing; prints the result and writes ``soak.json`` to ``--out``).

The faults are the ones a companion computer meets, injected for real while the vehicle
flies a circle in real time (lockstep would hide the stalls):

* ``stale_state``: the autopilot stops its position streams (a ground station sends
  SET_MESSAGE_INTERVAL -1, as when an estimator drops out) and the service must ask again;
* ``heartbeat_loss``: the SITL (the autopilot) is frozen with SIGSTOP, then resumed;
* ``service_stall``: the service is frozen with SIGSTOP for up to 0.6 s (a CPU stall);
* ``cpu_load``: two processes spin the two cores for a few seconds.

Checked afterwards, from what the service actually sent (its .tlog holds every frame both
ways), the SITL's ground truth and the service's own stats:

* at most one takeoff per flight, never one while airborne;
* never a non-finite value in a setpoint;
* no lockout: once the faults stop, the vehicle is back under offboard control by itself;
* no runaway climb; the service exits 0; its memory after the faults (RSS) is reported.
"""

from __future__ import annotations

import argparse
import bisect
import json
import math
import os
import random
import signal
import subprocess
import sys
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

from pymavlink import mavutil
from pymavlink.dialects.v20 import common as mavlink

from epc_offboard.common.frames import tilt_deg
from epc_offboard.vehicle.dialect_px4 import (
    PX4_AUTO_SUB_LAND,
    PX4_MAIN_MODE_AUTO,
    PX4_MAIN_MODE_OFFBOARD,
    px4_modes,
)
from tests.rig import Rig, cpu_hog

FAULTS = ("stale_state", "heartbeat_loss", "service_stall", "cpu_load")
_POSITION_STREAMS = (mavlink.MAVLINK_MSG_ID_LOCAL_POSITION_NED, mavlink.MAVLINK_MSG_ID_ODOMETRY)
_MAV_CMD_NAV_TAKEOFF = 22
_AUTO, _AUTO_LAND = float(PX4_MAIN_MODE_AUTO), float(PX4_AUTO_SUB_LAND)
_MARGIN_S = 12.0  # the mission's flight after the faults: offboard again within it (no lockout)


@dataclass
class SoakResult:
    duration_s: float
    seed: int
    faults: dict[str, int] = field(default_factory=dict)
    fault_log: list[tuple[float, str]] = field(default_factory=list)  # (wall s from start, fault)
    takeoffs_sent: int = 0  # NAV_TAKEOFF frames from the service in its tlog
    takeoffs_in_air: int = 0  # of those, sent while the ground truth was above 0.5 m
    setpoints: int = 0
    non_finite_setpoints: int = 0
    max_altitude_m: float = 0.0  # above home, ground truth
    min_altitude_m: float = 0.0  # above home, ground truth, between climb-out and landing
    max_tilt_deg: float = 0.0  # ground truth, between climb-out and landing
    recovered_s: float = math.nan  # from the last fault's end to offboard again
    exit_code: int | None = None
    failsafes: int = 0
    rss_kib: list[int] = field(default_factory=list)  # service RSS, sampled through the flight
    stats: dict[str, Any] = field(default_factory=dict)


def _rss_kib(pid: int) -> int:
    try:
        for line in Path(f"/proc/{pid}/status").read_text().splitlines():
            if line.startswith("VmRSS:"):
                return int(line.split()[1])
    except OSError:
        pass
    return 0


def _frozen(proc: subprocess.Popen[bytes], seconds: float) -> None:
    proc.send_signal(signal.SIGSTOP)
    try:
        time.sleep(seconds)
    finally:
        proc.send_signal(signal.SIGCONT)


def _inject(rig: Rig, fault: str, rng: random.Random) -> None:
    assert rig.sitl is not None
    assert rig.service is not None
    if fault == "stale_state":
        for msg_id in _POSITION_STREAMS:
            rig.command(mavlink.MAV_CMD_SET_MESSAGE_INTERVAL, float(msg_id), -1.0)
        time.sleep(rng.uniform(0.5, 2.0))  # the service asks for them again by itself
    elif fault == "heartbeat_loss":
        _frozen(rig.sitl, rng.uniform(0.5, 4.0))
    elif fault == "service_stall":
        _frozen(rig.service, rng.uniform(0.05, 0.6))
    elif fault == "cpu_load":
        hogs = [cpu_hog(10.0), cpu_hog(10.0)]
        try:
            time.sleep(rng.uniform(1.0, 4.0))
        finally:
            for h in hogs:
                h.kill()
                h.wait()
    else:
        raise ValueError(f"unknown fault {fault!r}")


def _wait_offboard(rig: Rig, timeout_s: float) -> float:
    """Seconds until the SITL's heartbeat says offboard (inf if it does not)."""
    t0 = time.monotonic()
    while time.monotonic() - t0 < timeout_s:
        msg = rig.gcs.recv_match(type="HEARTBEAT", blocking=True, timeout=1.0)
        if msg is not None and px4_modes(msg.custom_mode)[0] == PX4_MAIN_MODE_OFFBOARD:
            return time.monotonic() - t0
    return math.inf


def _drain(rig: Rig) -> None:
    while rig.gcs.recv_match(blocking=False) is not None:
        pass


def _check_tlog(path: Path, service_sysid: int, truth: dict[str, list[float]], r: SoakResult):
    """Takeoffs and setpoints as the service sent them, judged against ground truth."""
    tlog = mavutil.mavlink_connection(str(path), dialect="common")
    # vehicle time of the ground truth at each tlog frame: the newest ATTITUDE stamp seen
    vehicle_t_s = 0.0
    t_truth, alt_truth = truth["t_s"], [-d for d in truth["pos_d_m"]]
    while True:
        msg = tlog.recv_match()
        if msg is None:
            break
        mtype = msg.get_type()
        if mtype in ("ATTITUDE", "ATTITUDE_QUATERNION", "LOCAL_POSITION_NED"):
            vehicle_t_s = max(vehicle_t_s, msg.time_boot_ms * 1e-3)
        if msg.get_srcSystem() != service_sysid:
            continue
        if mtype in ("COMMAND_LONG", "COMMAND_INT") and msg.command == _MAV_CMD_NAV_TAKEOFF:
            r.takeoffs_sent += 1
            i = max(0, min(len(t_truth) - 1, bisect.bisect_left(t_truth, vehicle_t_s)))
            if alt_truth[i] > 0.5:
                r.takeoffs_in_air += 1
        elif mtype == "SET_ATTITUDE_TARGET":
            r.setpoints += 1
            values = (*msg.q, msg.body_roll_rate, msg.body_pitch_rate, msg.body_yaw_rate,
                      msg.thrust)  # fmt: skip
            if not all(math.isfinite(v) for v in values):
                r.non_finite_setpoints += 1
    tlog.close()


def run_soak(
    out: Path,
    duration_s: float,
    seed: int = 0,
    attitude_mode: str = "autopilot",
    land_at_end: bool = True,
) -> SoakResult:
    """Fly a circle for ``duration_s`` of faults (plus recovery and landing) in real time.

    ``attitude_mode``: as config/default.toml flies a real vehicle ("autopilot": quaternion
    + thrust), or "epc" (body rates), which no companion that can stall for longer than a
    few ticks should fly: PX4 holds the last body-rate setpoint until COM_OF_LOSS_T.
    ``land_at_end`` False: the mission ends holding and the service exits (the autopilot's
    landing, 9 s of real time, judges none of the invariants)."""
    rng = random.Random(seed)
    result = SoakResult(duration_s, seed, faults=dict.fromkeys(FAULTS, 0))
    overrides = {
        # the mission outlasts the faults by _MARGIN_S: offboard must be regained by then
        "mission": {"duration_s": duration_s + _MARGIN_S, "land_at_end": land_at_end},
        "trajectory": {"shape": "circle", "radius_m": 1.5, "period_s": 8.0},
        "log": {"tlog_path": str(out / "session.tlog")},
        "attitude": {"mode": attitude_mode},
    }
    out.mkdir(parents=True, exist_ok=True)
    with Rig(out, lockstep=False, speedup=1.0, service_overrides=overrides) as rig:
        assert rig.service is not None
        if _wait_offboard(rig, 90.0) == math.inf:
            raise AssertionError(f"never reached offboard:\n{rig.log()}")
        t_end = time.monotonic() + duration_s
        while time.monotonic() < t_end:
            fault = rng.choice(FAULTS)
            result.fault_log.append((round(time.monotonic() - t_end + duration_s, 2), fault))
            _inject(rig, fault, rng)
            result.faults[fault] += 1
            result.rss_kib.append(_rss_kib(rig.service.pid))
            time.sleep(rng.uniform(1.0, 3.0))
        _drain(rig)
        result.recovered_s = _wait_offboard(rig, _MARGIN_S)
        result.exit_code = rig.wait_exit(timeout_s=_MARGIN_S + 60.0)
        truth = rig.groundtruth()
        from epc_offboard.service.config import LinkConfig

        sysid = int(rig.config["link"].get("system_id", LinkConfig.system_id))
        result.stats = rig.stats()
    _check_tlog(out / "session.tlog", sysid, truth, result)
    alt = [-d for d in truth["pos_d_m"]]
    result.max_altitude_m = max(alt)
    # from climb-out to the mission's landing (the autopilot's LAND mode), or the end: a
    # vehicle that hit the ground before it never climbs back to count as landed
    first = next((i for i, a in enumerate(alt) if a > 2.0), len(alt))
    landing = next(
        (i for i in range(first, len(alt))
         if (truth["main_mode"][i], truth["sub_mode"][i]) == (_AUTO, _AUTO_LAND)),
        len(alt),
    )  # fmt: skip
    span = range(first, landing)
    result.min_altitude_m = min((alt[i] for i in span), default=0.0)
    result.max_tilt_deg = max(
        (tilt_deg((truth["q_w"][i], truth["q_x"][i], truth["q_y"][i], truth["q_z"][i]))
         for i in span),
        default=0.0,
    )  # fmt: skip
    result.failsafes = int(result.stats.get("counters", {}).get("failsafes", 0))
    return result


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(
        prog="python -m tests.soak", description=__doc__.split("\n\n")[0] if __doc__ else None
    )
    ap.add_argument("--duration", type=float, default=600.0, help="seconds of faults")
    ap.add_argument("--seed", type=int, default=0, help="fault schedule seed")
    ap.add_argument("--out", default="out/soak", help="logs, tlog and soak.json")
    ap.add_argument(
        "--attitude-mode", default="autopilot", choices=["autopilot", "epc"],
        help="autopilot: quaternion + thrust, as config/default.toml flies a real vehicle; "
        "epc: body rates",
    )  # fmt: skip
    args = ap.parse_args(argv)
    out = Path(args.out)
    result = run_soak(out, args.duration, args.seed, args.attitude_mode)
    (out / "soak.json").write_text(json.dumps(asdict(result), indent=2))
    rss = [v for v in result.rss_kib if v]
    growth = (rss[-1] - rss[len(rss) // 2]) / rss[len(rss) // 2] if len(rss) > 2 else 0.0
    print(
        f"faults {result.faults}; takeoffs {result.takeoffs_sent} "
        f"(in the air {result.takeoffs_in_air}); non-finite setpoints "
        f"{result.non_finite_setpoints}/{result.setpoints}; failsafes {result.failsafes}; "
        f"max tilt {result.max_tilt_deg:.0f} deg; min altitude {result.min_altitude_m:.2f} m; "
        f"back in offboard {result.recovered_s:.1f} s after the last fault; max altitude "
        f"{result.max_altitude_m:.2f} m; RSS {rss[0] if rss else 0} -> "
        f"{rss[-1] if rss else 0} KiB ({growth * 100:+.1f} % over the second half); "
        f"exit {result.exit_code}"
    )
    ok = (
        result.takeoffs_sent <= 1
        and result.takeoffs_in_air == 0
        and result.non_finite_setpoints == 0
        and math.isfinite(result.recovered_s)
        and result.exit_code == 0
        and result.max_tilt_deg < 90.0
        and result.min_altitude_m > 0.5
    )
    return 0 if ok else 1


if __name__ == "__main__":
    os.environ.setdefault("PYTHONUNBUFFERED", "1")
    sys.exit(main())
