"""MAVProxy, the ground station pilots script, sees `epc-sitl` as it sees a PX4 SITL.

Real processes, real UDP: `epc-sitl` sends its ground-station stream to the port MAVProxy
listens on (`--master=udpin:...`, as QGroundControl on 14550); MAVProxy runs headless
(`--non-interactive`, stdin closed, as in CI) and prints what it decodes. The test plays a
second operator on the SITL's command port (arm, take off) and reads MAVProxy's output for
the vehicle, its PX4 mode by name and its position.
"""

from __future__ import annotations

import math
import os
import queue
import re
import shutil
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Iterable
from pathlib import Path

import pytest
from pymavlink import mavutil
from pymavlink.dialects.v20 import common as mavlink

from epc_offboard.common.ports import free_port
from epc_offboard.tools.sim.orchestrate import stop_process
from tests.rig import holding_scenario

MAVPROXY = shutil.which("mavproxy.py", path=str(Path(sys.executable).parent))

# The deadlines are waits for processes to come up (MAVProxy's start, its imports 1-2 CPU-s;
# the SITL's boot; `sim`'s service, takeoff and Offboard), not what these tests judge (that
# MAVProxy names what it sees): at load 12-14 a 45 s wait for Offboard and a 60 s timeout
# failed 4 runs in 8, so they are sized for a loaded machine, and the timeout covers them.
pytestmark = [
    pytest.mark.timeout(240),
    pytest.mark.skipif(MAVPROXY is None, reason="MAVProxy not installed (pip install -e '.[dev]')"),
]

_ANNOUNCE_HOLDOFF_S = 2.5
_POSITION = re.compile(r"LOCAL_POSITION_NED \{.*\bz : (?P<z>-?[\d.e+-]+)")


class _Lines:
    """MAVProxy's stdout, line by line, read on a thread (no blocking read in the test)."""

    def __init__(self, proc: subprocess.Popen[bytes]) -> None:
        self.seen: list[str] = []
        self._queue: queue.Queue[str] = queue.Queue()
        assert proc.stdout is not None
        threading.Thread(target=self._read, args=(proc.stdout,), daemon=True).start()

    def _read(self, stdout: Iterable[bytes]) -> None:
        for line in stdout:
            self._queue.put(line.decode(errors="replace"))

    def wait_for(self, pattern: str, deadline: float) -> re.Match[str]:
        regex = re.compile(pattern)
        for line in self.seen:
            if m := regex.search(line):
                return m
        while time.monotonic() < deadline:
            try:
                line = self._queue.get(timeout=0.2)
            except queue.Empty:
                continue
            self.seen.append(line)
            if m := regex.search(line):
                return m
        shown = [s for s in self.seen if "LOCAL_POSITION_NED {" not in s] + self.seen[-3:]
        raise AssertionError(f"MAVProxy never printed {pattern!r}; it printed:\n{''.join(shown)}")


def test_mavproxy_shows_the_vehicle_its_mode_and_position(tmp_path):
    gcs_port, listen_port, offboard_port = free_port(), free_port(), free_port()
    sitl = subprocess.Popen(
        [sys.executable, "-m", "sitl.main", "--gcs-port", str(gcs_port),
         "--listen-port", str(listen_port), "--offboard-port", str(offboard_port),
         "--speedup", "1"],
        stdout=(tmp_path / "sitl.log").open("wb"), stderr=subprocess.STDOUT,
        stdin=subprocess.DEVNULL,
    )  # fmt: skip
    assert MAVPROXY is not None
    mavproxy = subprocess.Popen(
        [sys.executable, MAVPROXY, f"--master=udpin:127.0.0.1:{gcs_port}", "--non-interactive",
         "--cmd", "watch LOCAL_POSITION_NED"],
        cwd=tmp_path, stdin=subprocess.DEVNULL, stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT, env=dict(os.environ, PYTHONUNBUFFERED="1"),
    )  # fmt: skip
    operator = mavutil.mavlink_connection(
        f"udpout:127.0.0.1:{listen_port}", source_system=245, source_component=190
    )
    try:
        out = _Lines(mavproxy)
        deadline = time.monotonic() + 60.0
        out.wait_for(r"Detected vehicle 1:1 on link 0", deadline)
        out.wait_for(r"Mode LOITER", deadline)  # PX4's Hold (AUTO_LOITER) at boot, by name
        # MAVProxy announces a mode at most every 2 s: let the next one through
        time.sleep(_ANNOUNCE_HOLDOFF_S)

        # the first arming after boot is accepted (as PX4 + SIH)
        operator.mav.command_long_send(
            1, 1, mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 0, 1, 0, 0, 0, 0, 0, 0
        )
        out.wait_for(r"^ARMED", deadline)
        operator.mav.command_long_send(
            1, 1, mavlink.MAV_CMD_NAV_TAKEOFF, 0, 0, 0, 0, math.nan, math.nan, math.nan, math.nan
        )
        out.seen.clear()
        out.wait_for(r"Mode TAKEOFF", deadline)
        out.seen.clear()
        while True:  # its position climbing (NED: up is negative)
            z = float(out.wait_for(_POSITION.pattern, deadline)["z"])
            out.seen.clear()
            if z < -1.0:
                break
        out.wait_for(r"Mode LOITER", deadline)  # Hold again at the takeoff altitude
    finally:
        operator.close()
        for proc in (mavproxy, sitl):
            stop_process(proc)


def test_mavproxy_watches_a_running_sim_fly_offboard(tmp_path):
    """`epc-offboard sim --gcs-port P` streams to a ground station as PX4 SITL does to 14550:
    MAVProxy sees the vehicle, the service's takeoff and its Offboard flight, by name."""
    gcs_port = free_port()
    mavproxy = subprocess.Popen(
        [sys.executable, str(MAVPROXY), f"--master=udpin:127.0.0.1:{gcs_port}",
         "--non-interactive"],
        cwd=tmp_path, stdin=subprocess.DEVNULL, stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT, env=dict(os.environ, PYTHONUNBUFFERED="1"),
    )  # fmt: skip
    sim = subprocess.Popen(
        # MAVProxy names a mode it finds at its own pace (a new one at most every 2 s of its
        # wall clock), and lockstep flies as fast as the host computes: a 6 s hover's
        # Offboard took 1.2 s of wall time idle here and MAVProxy missed it once; a 20 s one
        # 10.9 s at load 3, and on a host some times faster than ours it would last less
        # than MAVProxy's 2 s (stop 44). So the hover lasts until MAVProxy has named it (an
        # hour of vehicle time, on any host far longer than that), then sim is stopped.
        # Ending holding: MAVProxy is judged on the takeoff and Offboard, not on the landing
        [sys.executable, "-m", "epc_offboard", "sim", "--scenario",
         str(holding_scenario(tmp_path, "hover")), "--duration", "3600",
         "--adaptation", "none", "--gcs-port", str(gcs_port), "--out", str(tmp_path / "out"),
         "--no-figure"],
        stdin=subprocess.DEVNULL, stdout=(tmp_path / "sim.log").open("wb"),
        stderr=subprocess.STDOUT,
    )  # fmt: skip
    try:
        out = _Lines(mavproxy)
        deadline = time.monotonic() + 90.0
        out.wait_for(r"Detected vehicle 1:1 on link 0", deadline)
        out.wait_for(r"Mode OFFBOARD", deadline)  # the service flying, by PX4's mode name
        assert sim.poll() is None, (tmp_path / "sim.log").read_text()  # named in flight
        sim.send_signal(signal.SIGTERM)  # the flight has shown what it had to
        sim.wait(timeout=120)
        assert "Traceback" not in (tmp_path / "sim.log").read_text()
    finally:
        for proc in (sim, mavproxy):
            stop_process(proc)
