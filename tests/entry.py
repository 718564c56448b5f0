"""Offboard entry in wind, and re-entry after telemetry freezes: one flight of the bundled
SITL + service (``epc-offboard sim``, lockstep), a ground station that freezes the
position telemetry, and the altitude change and tilt over the first seconds of every
(re-)entry, judged on the SITL's ground truth.

CI flies a few representative cases (tests/test_entry_e2e.py); the whole matrix is

    python -m tests.entry --out out/entry [--json FILE]

(both personalities, both attitude modes, 3 and 6 m/s wind, freezes of 0.6 s and 5 s).
``--checkout DIR`` flies another checkout's service and SITL (e.g. the code before a
change) with the same judge.

An entry is the moment the autopilot starts flying the service's setpoints: the first
ground-truth sample, within a stretch of streamed setpoints (the flight log's rows), at
which the SITL is in the mode that obeys them (PX4 Offboard, ArduCopter GUIDED: the ground
truth writes both in PX4's terms).
"""

from __future__ import annotations

import argparse
import csv
import json
import math
import os
import subprocess
import sys
import threading
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

from pymavlink import mavutil
from pymavlink.dialects.v20 import common as mavlink

from epc_offboard.common.frames import GRAVITY_M_S2
from epc_offboard.common.ports import free_port
from epc_offboard.vehicle.dialect_px4 import PX4_MAIN_MODE_OFFBOARD, px4_modes
from sitl.params import load_sim_config
from tests.rig import early_origin_vehicle

ARDUPILOT_GUIDED = 4
_POSITION_STREAMS = (mavlink.MAVLINK_MSG_ID_LOCAL_POSITION_NED, mavlink.MAVLINK_MSG_ID_ODOMETRY)
_RESTORE_INTERVAL_US = 10_000.0  # 100 Hz: what the service asks for
WINDOW_S = 2.0  # judged over the first WINDOW_S of each entry
SETTLE_S = 4.0  # vehicle seconds between an entry and the next freeze
# vehicle seconds after a freeze's end for the re-entry and its window: the re-entries came
# -0.7..+0.7 s after the freeze's nominal end (CI's seven flights, stop 34), so the flight
# (which ends REENTRY_S + 1 s after it) still flies 2.3 s or more past the re-entry's window;
# was 8 s, the last 4 s of every flight judged by nothing. A window the flight's end cut
# short fails the judge (EntryFigures.judged_s)
REENTRY_S = 4.5
# no ground-station wait lasts longer (a SITL that died; the flight ending stops them all
# first): at load 15 an ArduPilot flight took over 120 s of wall time to reach GUIDED in
# the air (its EKF origin comes 36 s of vehicle time after boot), and the freeze ran
# before the entry
_WALL_LIMIT_S = 600.0


@dataclass(frozen=True)
class EntryFigures:
    t_s: float  # vehicle time of the entry
    alt_change_m: float  # max |altitude - altitude at entry| over the window
    tilt_max_deg: float  # max tilt over the window
    tilt_change_deg: float  # max angle between the thrust axis and the one at entry
    tilt_at_entry_deg: float
    # max angle between the thrust axis and the one that holds at rest against the wind
    # (the SITL's drag of the wind it blows then): the tilt judged relative to the wind's
    tilt_from_hold_deg: float = 0.0
    # the ground truth the window judged, from the entry to its last sample (s): WINDOW_S
    # unless the stretch (the flight, a freeze's failsafe) ended first
    judged_s: float = 0.0


@dataclass
class Flight:
    autopilot: str
    mode: str  # "epc" (body rates) or "autopilot" (quaternion)
    wind_m_s: float
    adaptation: str = "lwpr"
    freezes_s: tuple[float, ...] = ()
    settle_s: float = SETTLE_S  # vehicle seconds from an entry to the next freeze
    # ArduPilot's EKF origin, vehicle seconds after boot (None: the vehicle file's, 36 s);
    # before it the vehicle waits on the ground, which no entry's window sees
    ekf_origin_s: float | None = None
    entries: list[EntryFigures] = field(default_factory=list)
    freezes_done: list[tuple[float, float]] = field(default_factory=list)  # (t, duration)
    exit_code: int | None = None

    @property
    def name(self) -> str:
        freezes = "+".join(f"{f:g}" for f in self.freezes_s) or "none"
        return f"{self.autopilot}-{self.mode}-wind{self.wind_m_s:g}-freeze{freezes}"

    def worst(self) -> tuple[float, float, float, float]:
        """(altitude change m, tilt deg, tilt change deg, tilt from the hold's deg): the
        worst over the entries."""
        if not self.entries:
            return (math.inf, math.inf, math.inf, math.inf)
        return (
            max(e.alt_change_m for e in self.entries),
            max(e.tilt_max_deg for e in self.entries),
            max(e.tilt_change_deg for e in self.entries),
            max(e.tilt_from_hold_deg for e in self.entries),
        )


def _rows(path: Path) -> list[dict[str, float | str]]:
    with path.open() as fh:
        out: list[dict[str, float | str]] = []
        for row in csv.DictReader(fh):
            parsed: dict[str, float | str] = {}
            for key, value in row.items():
                try:
                    parsed[key] = float(value)
                except (TypeError, ValueError):
                    parsed[key] = value
            out.append(parsed)
        return out


def _axis(row: dict[str, Any]) -> tuple[float, float, float]:
    """Body z (FRD) in NED from the ground truth's quaternion."""
    w, x, y, z = (float(row[k]) for k in ("q_w", "q_x", "q_y", "q_z"))
    return (2 * (x * z + w * y), 2 * (y * z - w * x), 1 - 2 * (x * x + y * y))


def _drag_per_mass_1_s() -> tuple[float, float, float]:
    """The bundled airframe's linear drag per unit mass, per body axis (1/s)."""
    vehicle = load_sim_config().vehicle
    d = vehicle.drag_coeff_body_n_s_m
    return (d[0] / vehicle.mass_kg, d[1] / vehicle.mass_kg, d[2] / vehicle.mass_kg)


def _hold_axis(row: dict[str, Any], drag_1_s: float) -> tuple[float, float, float]:
    """Body z (NED) of a vehicle at rest holding against the wind of ``row``: the thrust
    cancels gravity and the drag, f z_b = g e_z + drag * wind (an isotropic drag)."""
    v = (
        drag_1_s * float(row["wind_n_m_s"]),
        drag_1_s * float(row["wind_e_m_s"]),
        drag_1_s * float(row["wind_d_m_s"]) + GRAVITY_M_S2,
    )
    norm = math.sqrt(sum(c * c for c in v))
    return (v[0] / norm, v[1] / norm, v[2] / norm)


def _angle_deg(a: tuple[float, float, float], b: tuple[float, float, float]) -> float:
    dot = sum(p * q for p, q in zip(a, b, strict=True))
    return math.degrees(math.acos(max(-1.0, min(1.0, dot))))


def entries(vehicle_dir: Path, autopilot: str, window_s: float = WINDOW_S) -> list[EntryFigures]:
    """Every entry of one flight (see the module docstring) with its figures."""
    log = [r for r in _rows(vehicle_dir / "flight.csv") if isinstance(r["vehicle_t_s"], float)]
    truth = _rows(vehicle_dir / "groundtruth.csv")
    # (the ground truth writes both personalities' modes in PX4's terms: GUIDED is 6)
    obey = PX4_MAIN_MODE_OFFBOARD
    # stretches of streamed setpoints: the flight log has a row per streamed position tick
    stretches: list[list[float]] = []
    for r in log:
        t = float(r["vehicle_t_s"])
        if stretches and t - stretches[-1][1] < 0.1:
            stretches[-1][1] = t
        else:
            stretches.append([t, t])
    drag = _drag_per_mass_1_s()
    if max(drag) - min(drag) > 1e-9:
        raise ValueError(f"the hold axis assumes an isotropic drag, got {drag}")
    out = []
    for start, end in stretches:
        entry = next(
            (
                i
                for i, r in enumerate(truth)
                if start <= float(r["t_s"]) <= end
                and int(float(r["main_mode"])) == obey
                and int(float(r["armed"])) == 1
            ),
            None,
        )
        if entry is None:
            continue
        t0 = float(truth[entry]["t_s"])
        window = [r for r in truth[entry:] if float(r["t_s"]) <= min(t0 + window_s, end)]
        alt0 = -float(window[0]["pos_d_m"])
        axis0 = _axis(window[0])
        out.append(
            EntryFigures(
                t_s=t0,
                alt_change_m=max(abs(-float(r["pos_d_m"]) - alt0) for r in window),
                tilt_max_deg=max(_angle_deg(_axis(r), (0.0, 0.0, 1.0)) for r in window),
                tilt_change_deg=max(_angle_deg(_axis(r), axis0) for r in window),
                tilt_at_entry_deg=_angle_deg(axis0, (0.0, 0.0, 1.0)),
                tilt_from_hold_deg=max(
                    _angle_deg(_axis(r), _hold_axis(r, drag[0])) for r in window
                ),
                judged_s=float(window[-1]["t_s"]) - t0,
            )
        )
    return out


class _GroundStation:
    """Watches the SITL's ground-station stream and freezes the position telemetry on
    cue, by vehicle time (lockstep: wall time says nothing)."""

    def __init__(self, autopilot: str, port: int) -> None:
        self.autopilot = autopilot
        self.port = port
        self.conn: Any = None
        self.vehicle_s = 0.0
        self.controlled = False
        self.airborne = False  # above 2 m: ArduCopter is GUIDED and armed before takeoff
        self._guided = False

    def connect(self, deadline: float) -> None:
        while time.monotonic() < deadline:
            try:
                url = (
                    f"udpin:127.0.0.1:{self.port}"
                    if self.autopilot == "px4"
                    else f"tcp:127.0.0.1:{self.port}"
                )
                self.conn = mavutil.mavlink_connection(
                    url, source_system=250, source_component=190, retries=0
                )
                return
            except OSError:
                time.sleep(0.2)
        raise TimeoutError("no ground-station link to the SITL")

    def pump(self, timeout_s: float = 0.05) -> None:
        msg = self.conn.recv_match(blocking=True, timeout=timeout_s)
        while msg is not None:
            kind = msg.get_type()
            if kind in ("ATTITUDE", "LOCAL_POSITION_NED", "ATTITUDE_QUATERNION"):
                self.vehicle_s = max(self.vehicle_s, msg.time_boot_ms / 1000.0)
            if kind == "LOCAL_POSITION_NED":
                self.airborne = msg.z < -2.0
            if kind == "HEARTBEAT" and msg.get_srcSystem() == 1:
                if self.autopilot == "px4":
                    self.controlled = px4_modes(msg.custom_mode)[0] == PX4_MAIN_MODE_OFFBOARD
                else:
                    armed = bool(msg.base_mode & mavlink.MAV_MODE_FLAG_SAFETY_ARMED)
                    self._guided = armed and msg.custom_mode == ARDUPILOT_GUIDED
            if self.autopilot != "px4":
                self.controlled = self._guided and self.airborne
            msg = self.conn.recv_match(blocking=False)

    def _set_interval(self, interval_us: float) -> None:
        for msg_id in _POSITION_STREAMS:
            self.conn.mav.command_long_send(
                1, 1, mavlink.MAV_CMD_SET_MESSAGE_INTERVAL, 0, float(msg_id), interval_us,
                0, 0, 0, 0, 0,
            )  # fmt: skip

    def wait_vehicle(self, until_s: float, stop: threading.Event) -> None:
        deadline = time.monotonic() + _WALL_LIMIT_S
        while self.vehicle_s < until_s and not stop.is_set() and time.monotonic() < deadline:
            self.pump()

    def freeze(self, duration_s: float, stop: threading.Event) -> float:
        """Stop the position streams for ``duration_s`` of vehicle time (asking again and
        again: the service re-requests its rates); returns the vehicle time it began."""
        t0 = self.vehicle_s
        deadline = time.monotonic() + _WALL_LIMIT_S
        while (
            self.vehicle_s < t0 + duration_s and not stop.is_set() and time.monotonic() < deadline
        ):
            self._set_interval(-1.0)
            self.pump(0.02)
        self._set_interval(_RESTORE_INTERVAL_US)
        return t0

    def close(self) -> None:
        if self.conn is not None:
            self.conn.close()


def _script(gcs: _GroundStation, flight: Flight, stop: threading.Event) -> None:
    try:
        gcs.connect(time.monotonic() + _WALL_LIMIT_S)
        deadline = time.monotonic() + _WALL_LIMIT_S
        while not gcs.controlled and not stop.is_set() and time.monotonic() < deadline:
            gcs.pump()
        gcs.wait_vehicle(gcs.vehicle_s + flight.settle_s, stop)
        for duration in flight.freezes_s:
            if stop.is_set():
                return
            t0 = gcs.freeze(duration, stop)
            flight.freezes_done.append((t0, duration))
            gcs.wait_vehicle(gcs.vehicle_s + REENTRY_S, stop)
        # nothing more to do: the sim ends holding and exits (a dead TCP link must not be read:
        # pymavlink prints a line per read at its EOF)
    except Exception as exc:  # the judge reports a flight without its freezes
        print(f"ground station: {exc!r}", file=sys.stderr)


def fly(
    flight: Flight,
    out: Path,
    *,
    seed: int = 0,
    timeout_s: float = 900.0,
    checkout: Path | None = None,
) -> Flight:
    """Fly ``flight`` with ``epc-offboard sim`` into ``out`` and judge its entries
    (``checkout``: the service and SITL of that source tree instead of this one)."""
    out.mkdir(parents=True, exist_ok=True)
    scenario = out / "entry_scenario.toml"
    duration = flight.settle_s + sum(f + REENTRY_S for f in flight.freezes_s) + 1.0
    vehicle = ""  # "": the default vehicle
    if flight.autopilot == "ardupilot" and flight.ekf_origin_s is not None:
        vehicle = str(early_origin_vehicle(out, flight.ekf_origin_s))
    scenario.write_text(
        'description = "hover, entered in wind"\n'
        f"vehicle = {json.dumps(vehicle)}\n"
        f"duration_s = {duration}\nsettle_s = 1.0\naltitude_m = 2.5\n"
        '[trajectory]\nshape = "hover"\n'
        f'[service.attitude]\nmode = "{flight.mode}"\n'
        # ends holding: the autopilot's landing (8.5 s of vehicle time) judges no entry
        "[service.mission]\nland_at_end = false\n"
    )
    port = free_port()
    cmd = [
        sys.executable, "-m", "epc_offboard", "sim", "--scenario", str(scenario),
        "--autopilot", flight.autopilot, "--wind", f"{flight.wind_m_s},0",
        "--adaptation", flight.adaptation, "--seed", str(seed), "--gcs-port", str(port),
        "--out", str(out / "sim"), "--no-figure",  # judged on the ground truth alone
    ]  # fmt: skip
    gcs = _GroundStation(flight.autopilot, port)
    stop = threading.Event()
    script = threading.Thread(target=_script, args=(gcs, flight, stop), daemon=True)
    with (out / "sim.log").open("wb") as log:
        env = dict(os.environ)
        if checkout is not None:  # (python -m puts the working directory first on the path)
            env["PYTHONPATH"] = str(checkout)
        proc = subprocess.Popen(
            cmd, stdout=log, stderr=subprocess.STDOUT, env=env, cwd=checkout or Path.cwd()
        )
        script.start()
        try:
            flight.exit_code = proc.wait(timeout=timeout_s)
        finally:
            stop.set()
            if proc.poll() is None:
                proc.terminate()
                proc.wait(timeout=20)
            script.join(timeout=5)
            gcs.close()
    flight.entries = entries(out / "sim" / "vehicle1", flight.autopilot)
    return flight


def matrix() -> list[Flight]:
    return [
        Flight(autopilot, mode, wind, freezes_s=(0.6, 5.0))
        for autopilot in ("px4", "ardupilot")
        for mode in ("epc", "autopilot")
        for wind in (3.0, 6.0)
    ]


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m tests.entry", description=__doc__)
    ap.add_argument("--out", type=Path, default=Path("out/entry"))
    ap.add_argument("--json", type=Path)
    ap.add_argument("--only", help="fly only the flights whose name contains this")
    ap.add_argument("--checkout", type=Path, help="fly this source tree's service and SITL")
    args = ap.parse_args(argv)
    results = []
    for flight in matrix():
        if args.only and args.only not in flight.name:
            continue
        fly(flight, args.out / flight.name, checkout=args.checkout)
        alt, tilt, dtilt, dhold = flight.worst()
        print(
            f"{flight.name:44s} entries {len(flight.entries)}  worst alt {alt:.2f} m  "
            f"tilt {tilt:.1f} deg  tilt change {dtilt:.1f} deg  from the hold's {dhold:.1f} "
            f"deg  exit {flight.exit_code}",
            flush=True,
        )
        for e in flight.entries:
            print(
                f"    t {e.t_s:6.2f}  alt {e.alt_change_m:.3f} m  tilt {e.tilt_max_deg:.1f} deg "
                f"(entry {e.tilt_at_entry_deg:.1f}, change {e.tilt_change_deg:.1f}, from the "
                f"hold's {e.tilt_from_hold_deg:.1f})"
            )
        results.append({**asdict(flight), "name": flight.name})
    if args.json:
        args.json.write_text(json.dumps(results, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
