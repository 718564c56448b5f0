"""A lockstep flight is a function of its config and seed alone, however long a loaded machine
keeps the controller from answering (stop 41, lock-load): the SITL's clock waits for the
answer; only a controller silent for the whole ``lockstep_timeout_s`` x
``lockstep_max_timeouts`` counts as gone.

Two lockstep flights, one of them with the service starved outright for 7 s in the middle
(SIGSTOP, then SIGCONT: what a loaded machine, a swap storm or a slow miss worker do to it
for that long). With the 6 s bound of main the SITL fell back to real-time
pace meanwhile and flew on without the controller's answers: the two flights' ground truth
parted at the stop. Real processes over UDP MAVLink. No CPU hogs beside them: the stop is the
starvation, and hogs only made the test 85 s long (31 s without, load ~7).
"""

from __future__ import annotations

import csv
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from epc_offboard.tools.sim.analysis import flight_warnings, sitl_counters
from epc_offboard.vehicle.dialect_px4 import (
    PX4_AUTO_SUB_LOITER,
    PX4_MAIN_MODE_AUTO,
    PX4_MAIN_MODE_OFFBOARD,
)
from tests.rig import Rig, holding_scenario, processes_with

pytestmark = [pytest.mark.timeout(420)]

STARVED_S = 7.0  # longer than main's whole bound (3 x 2 s), far shorter than the branch's
WALL_CLOCK_COLUMNS = ("compute_us",)


def _rows(path: Path) -> list[list[str]]:
    with path.open(newline="") as fh:
        rows = list(csv.reader(fh))
    keep = [i for i, name in enumerate(rows[0]) if name not in WALL_CLOCK_COLUMNS]
    return [[row[i] for i in keep] for row in rows]


def fly(out: Path, starve_at_row: int | None) -> dict:
    scenario = holding_scenario(out.parent, "circle")
    proc = subprocess.Popen(
        [sys.executable, "-m", "epc_offboard", "sim", "--scenario", str(scenario),
         "--lockstep", "--duration", "8", "--wind", "2,30", "--gcs-port", "0",
         "--out", str(out), "--no-figure"],
        stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
    )  # fmt: skip
    try:
        if starve_at_row is not None:
            flight = out / "vehicle1" / "flight.csv"
            while proc.poll() is None:
                if flight.exists() and flight.read_text().count("\n") > starve_at_row:
                    break
                time.sleep(0.05)
            (pid,) = processes_with(f"{out}/vehicle1/service.toml")
            os.kill(pid, signal.SIGSTOP)
            time.sleep(STARVED_S)
            os.kill(pid, signal.SIGCONT)
        output, _ = proc.communicate(timeout=360)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    assert proc.returncode == 0, output.decode(errors="replace")
    report: dict = json.loads((out / "report.json").read_text())
    assert report["lockstep"] is True
    return report


def test_a_starved_controller_does_not_change_a_lockstep_flight(tmp_path):
    steady = fly(tmp_path / "steady", starve_at_row=None)
    starved = fly(tmp_path / "starved", starve_at_row=150)
    warnings = starved["vehicles"][0]["warnings"]
    assert "lockstep fell back to real time" not in warnings, warnings
    for name in ("flight.csv", "groundtruth.csv"):
        a = _rows(tmp_path / "steady" / "vehicle1" / name)
        b = _rows(tmp_path / "starved" / "vehicle1" / name)
        assert len(a) > 200  # it flew: a real comparison
        first = next((k for k, (x, y) in enumerate(zip(a, b, strict=False)) if x != y), None)
        assert first is None, (
            name,
            first,
            a[first] if first else None,
            b[first] if first else None,
        )
        assert len(a) == len(b), name
    assert steady["vehicles"][0]["tracking"] == starved["vehicles"][0]["tracking"]


# the killed-service test's bound, short so that it runs in seconds: 45 x 0.2 s = 9 s (the
# shipped 45 x 2 s); the bound after a hand-back would be 1 x 0.2 s
TIMEOUT_MS = 200
LONG_BOUND_S = 45 * TIMEOUT_MS / 1000.0


def test_a_killed_controller_is_found_by_the_long_bound_counted_and_warned(tmp_path):
    """A service gone without a word (SIGKILL: no HOLD request, so not handed back) is not
    told from a starved one until the long bound has passed; then the SITL falls back to
    real time, PX4's offboard-loss failsafe holds the vehicle, and the fallback is counted
    (``lockstep_fallbacks``: the report's "lockstep fell back to real time"). Before the
    hand-back was told apart, a fallback no answer followed was not counted: 0, nothing
    said."""
    with Rig(tmp_path, sitl_args=("--lockstep-timeout-ms", str(TIMEOUT_MS))) as rig:
        rig.wait_mode(PX4_MAIN_MODE_OFFBOARD, 0)
        time.sleep(1.0)
        t0 = time.monotonic()
        rig.stop_service(signal.SIGKILL)
        rig.wait_mode(PX4_MAIN_MODE_AUTO, PX4_AUTO_SUB_LOITER, timeout_s=LONG_BOUND_S + 60.0)
        took_s = time.monotonic() - t0
        assert rig.sitl is not None
        rig.sitl.send_signal(signal.SIGTERM)
        assert rig.sitl.wait(timeout=10) == 0
    # the whole long bound was waited (a load only makes it later), not the short one
    assert took_s >= LONG_BOUND_S - 0.5, took_s
    counters = sitl_counters(tmp_path / "sitl.log")
    assert counters["lockstep_fallbacks"] >= 1, counters
    assert counters["offboard_failsafes"] >= 1, counters
    assert flight_warnings({}, counters)["lockstep fell back to real time"] >= 1
