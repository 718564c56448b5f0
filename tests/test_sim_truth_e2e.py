"""`sim`'s report is the truth (issue 22): a flight that went wrong says so and exits 1.

Real lockstep flights (SITL + service processes over UDP MAVLink, no ground-station stream),
each a few seconds of vehicle time: a real corrupt SQLite library, a real socket holding a
fleet vehicle's Zenoh port, a wind beyond the vehicle's authority, a wind that blows it away
before it is ever airborne, and a flight that outlasts its vehicle-time budget. Each of these
ended in "warnings: none" and exit 0 (or never ended) before.
"""

from __future__ import annotations

import json
import os
import socket
import sqlite3
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import pytest

from epc_offboard.tools.sim.orchestrate import ZENOH_BASE_PORT
from epc_offboard.tools.sim.scenario import SCENARIO_DIR
from tests.rig import holding_scenario

pytestmark = pytest.mark.timeout(300)


def sim(
    out: Path, *args: str, figure: bool = False
) -> tuple[dict[str, Any], subprocess.CompletedProcess[str], float]:
    """One `sim` run into ``out``: (report, process, wall seconds); flight.png only if
    ``figure``."""
    t0 = time.monotonic()
    no_figure = () if figure else ("--no-figure",)
    proc = subprocess.run(
        [sys.executable, "-m", "epc_offboard", "sim", "--gcs-port", "0", "--out", str(out),
         *no_figure, *args],
        capture_output=True, text=True, timeout=280, check=False,
    )  # fmt: skip
    wall_s = time.monotonic() - t0
    report: dict[str, Any] = json.loads((out / "report.json").read_text())
    return report, proc, wall_s


def test_a_corrupt_library_moved_aside_fails_the_flight_and_its_error_is_reported(tmp_path):
    out = tmp_path / "out"
    out.mkdir()
    library = out / "library-1.sqlite"
    with sqlite3.connect(library) as db:  # a real SQLite file, then its header destroyed
        db.execute("CREATE TABLE t (x)")
        db.executemany("INSERT INTO t VALUES (?)", [(i,) for i in range(500)])
    db.close()
    data = bytearray(library.read_bytes())
    data[:100] = b"\xa5" * 100
    library.write_bytes(bytes(data))
    # ending holding: the library's error is judged, not the autopilot's landing
    report, proc, _wall = sim(out, "--scenario", str(holding_scenario(tmp_path, "hover")),
                              "--duration", "4")  # fmt: skip
    assert proc.returncode == 1, proc.stdout + proc.stderr
    v = report["vehicles"][0]
    assert v["flew_offboard"]  # the flight itself was fine
    assert v["finished"]
    [aside] = v["library_moved_aside"]
    assert ".corrupt-" in aside
    assert "its library was unusable and moved aside" in proc.stderr
    errors = [k for k in v["warnings"] if k.startswith("service ERROR epc_offboard.store")]
    assert errors, v["warnings"]
    assert "moved aside" in errors[0]
    assert "moved aside to" in v["warning_examples"][errors[0]]
    assert errors[0] in proc.stdout  # printed under the table, not only in report.json
    assert any("moved aside" in f for f in report["failures"])
    # --no-figure (this module's flights but one): no flight.png, and stdout names none
    assert not (out / "flight.png").exists()
    assert "report: " in proc.stdout
    assert "figure:" not in proc.stdout


def hold_port(port: int) -> socket.socket | None:
    """A real listening socket on tcp 127.0.0.1:``port``; None if another process has it.
    SO_REUSEADDR as a server binds it: the TIME_WAIT connections an earlier fleet flight
    left on the port are nobody's (without it, this test skipped after such a flight)."""
    holder = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
    holder.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
    try:
        holder.bind(("127.0.0.1", port))
    except OSError:
        holder.close()
        return None
    holder.listen()
    return holder


# sim --vehicles binds the fixed Zenoh ports 7447..: one at a time (test_suite_ports.py)
@pytest.mark.one_at_a_time("zenoh-fixed-ports")
def test_a_fleet_port_taken_before_start_is_named_before_any_process_starts(tmp_path):
    holder = hold_port(ZENOH_BASE_PORT + 1)  # vehicle 1's Zenoh listening port
    if holder is None:
        pytest.skip(f"port {ZENOH_BASE_PORT + 1} is in use by another process")
    t0 = time.monotonic()
    try:
        proc = subprocess.run(
            [sys.executable, "-m", "epc_offboard", "sim", "--gcs-port", "0",
             "--out", str(tmp_path / "out"), "--vehicles", "2", "--duration", "4"],
            capture_output=True, text=True, timeout=120, check=False,
        )  # fmt: skip
    finally:
        holder.close()
    assert proc.returncode == 1, proc.stdout + proc.stderr
    assert "vehicle 1's fleet sharing" in proc.stderr
    assert f"tcp 127.0.0.1:{ZENOH_BASE_PORT + 1}: already in use" in proc.stderr
    assert "SITL" not in proc.stdout  # no vehicle was started
    assert not (tmp_path / "out" / "report.json").exists()
    assert time.monotonic() - t0 < 60.0  # said before any warm-up


@pytest.mark.one_at_a_time("zenoh-fixed-ports")
def test_a_fleet_whose_sharing_cannot_open_fails_and_says_so(tmp_path):
    # The port is free when sim checks it and taken (by a real socket) before vehicle 1's fleet
    # helper opens its session: another program won the race, and the session cannot open.
    probe = hold_port(ZENOH_BASE_PORT + 1)
    if probe is None:
        pytest.skip(f"port {ZENOH_BASE_PORT + 1} is in use by another process")
    probe.close()
    out = tmp_path / "out"
    # ending holding: the sessions are judged, not two landings (8.5 s of vehicle time each,
    # with the fixed ports' lock held)
    proc = subprocess.Popen(
        [sys.executable, "-m", "epc_offboard", "sim", "--gcs-port", "0", "--out", str(out),
         "--scenario", str(holding_scenario(tmp_path, "hover")), "--vehicles", "2",
         "--duration", "4"],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
        env=dict(os.environ, PYTHONUNBUFFERED="1"),
    )  # fmt: skip
    holder = None
    lines: list[str] = []
    try:
        assert proc.stdout is not None
        for line in proc.stdout:  # vehicle 1's route is printed once its processes started,
            lines.append(line)  # a second or more before its helper opens the session
            if line.startswith("vehicle 1: SITL"):
                holder = hold_port(ZENOH_BASE_PORT + 1)
                break
        assert holder is not None, "".join(lines)
        stdout, stderr = proc.communicate(timeout=280)
    finally:
        if holder is not None:
            holder.close()
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    stdout = "".join(lines) + stdout
    assert proc.returncode == 1, stdout + stderr
    report = json.loads((out / "report.json").read_text())
    v1, v2 = report["vehicles"]
    assert v1["sharing"] == {"asked": True, "open": False}
    assert v2["sharing"] == {"asked": True, "open": True}
    assert "vehicle 1: fleet sharing was asked for and is unavailable" in stderr
    assert "vehicle 2: fleet sharing" not in stderr
    kinds = [k for k in v1["warnings"] if "fleet sharing unavailable" in k]
    assert kinds, v1["warnings"]
    assert kinds[0].startswith("service ERROR")


def test_a_wind_beyond_the_vehicles_authority_ends_the_flight_outside_its_envelope(tmp_path):
    # 15 m/s of wind on SIH's drag needs 15 m/s^2 of horizontal acceleration: 57 deg of tilt,
    # beyond the 45 deg limit. Before: RMSE 20.7 m, exit 0, "warnings: none".
    report, proc, wall_s = sim(tmp_path / "out", "--duration", "4", "--wind", "15,45")
    assert proc.returncode == 1, proc.stdout + proc.stderr
    v = report["vehicles"][0]
    assert v["envelope"]["left"], v["envelope"]
    assert v["stopped"].startswith("stopped by sim: it left its envelope")
    assert not v["finished"]
    assert "left its envelope" in proc.stderr
    assert "FAILED: vehicle 1 left its envelope" in proc.stdout
    assert "warnings: none" not in proc.stdout  # it was, beside FAILED
    assert [k for k in v["warnings"] if k.startswith("left its envelope: ")], v["warnings"]
    assert v["warnings"]["stopped by sim before it finished"] == 1
    assert wall_s < 150.0


def test_a_vehicle_blown_away_before_it_is_airborne_is_stopped_in_bounded_time(tmp_path):
    # 300 m/s: the service never trusts the state (too fast to be plausible) and waited for it
    # while the vehicle drifted 89 km of vehicle time; sim never ended
    report, proc, wall_s = sim(
        tmp_path / "out", "--duration", "4", "--wind", "300,45", figure=True
    )
    assert proc.returncode == 1, proc.stdout + proc.stderr
    v = report["vehicles"][0]
    assert not v["flew_offboard"]
    assert v["stopped"]
    assert v["envelope"]["worst"]["drift_m"] > v["envelope"]["bounds"]["max_drift_m"]
    assert v["envelope"]["worst"]["flight_s"] < v["envelope"]["bounds"]["max_flight_s"]
    assert wall_s < 150.0
    assert (tmp_path / "out" / "flight.png").stat().st_size > 10_000  # drawn all the same


def test_a_flight_that_outlasts_its_vehicle_time_budget_is_stopped_and_failed(tmp_path):
    # a budget no takeoff can meet: the flight-time bound, not the distance, ends it
    scenario = tmp_path / "tight.toml"
    scenario.write_text(
        (SCENARIO_DIR / "hover.toml").read_text()
        + "\n[envelope]\ntakeoff_budget_s = 0.5\nlanding_budget_s = 0.5\n"
    )
    report, proc, _wall = sim(tmp_path / "out", "--scenario", str(scenario), "--duration", "4")
    assert proc.returncode == 1, proc.stdout + proc.stderr
    v = report["vehicles"][0]
    assert v["envelope"]["bounds"]["max_flight_s"] == pytest.approx(5.0)
    assert [b["what"] for b in v["envelope"]["left"]] == ["flight time"]
    assert "flight time" in v["stopped"]
    assert v["envelope"]["worst"]["flight_s"] < 5.0 + 5.0  # stopped soon after the bound
