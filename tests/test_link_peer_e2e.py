"""The autopilot falls silent mid-flight while a fuzzer talks to the service's port.

Real SITL and service processes over UDP MAVLink, lockstep, and the MAVLink fuzzer
(``tools/fuzz_mavlink.py``) as a process of its own at 2,000 datagrams/s. The SITL is frozen
(SIGSTOP) for 4 s, longer than the link's ``peer_timeout_s`` (3 s): on main 0239a5e the link
handed the peer to the fuzzer (whose well-formed frames of the vehicle's ids qualified), sent
the setpoints there, and dropped the autopilot's own frames, back, as a second sender's for
as long as the fuzz lasted; the lockstep vehicle, waiting for setpoints, never flew on
(vehicle time stuck at 14.3 s of a 51 s flight, load 21). Loose bounds: the flight goes on
while the fuzz lasts, and the peer never moves.
"""

from __future__ import annotations

import csv
import os
import signal
import subprocess
import sys
import time

import pytest

from epc_offboard.vehicle.dialect_px4 import PX4_MAIN_MODE_OFFBOARD
from tests.rig import Rig

pytestmark = pytest.mark.timeout(180)

FUZZ_S = 30.0  # outlasts the test: the autopilot must be regained while it runs
FROZEN_S = 4.0  # > the link's peer_timeout_s (3 s)
FLY_ON_S = 1.0  # of vehicle time, after the thaw, within ...
WITHIN_S = 15.0  # ... this much wall time (lockstep at a load of 20: ~0.3 s a second)


def _vehicle_time_s(flight_csv) -> float:
    with flight_csv.open() as fh:
        rows = list(csv.DictReader(fh))
    return float(rows[-1]["vehicle_t_s"]) if rows else 0.0


def test_a_silent_autopilot_is_regained_while_a_fuzzer_talks(tmp_path):
    with Rig(tmp_path) as rig:
        rig.wait_mode(PX4_MAIN_MODE_OFFBOARD, timeout_s=120)
        fuzz = subprocess.Popen(
            [sys.executable, "-m", "epc_offboard.tools.fuzz_mavlink", "--port",
             str(rig.offboard_port), "--rate", "2000", "--duration", str(FUZZ_S)],
            stdout=subprocess.DEVNULL,
        )  # fmt: skip
        try:
            time.sleep(1.0)  # the fuzz under way, the vehicle flying
            assert rig.sitl is not None
            os.kill(rig.sitl.pid, signal.SIGSTOP)
            time.sleep(FROZEN_S)
            os.kill(rig.sitl.pid, signal.SIGCONT)
            thawed_s = _vehicle_time_s(tmp_path / "flight.csv")
            deadline = time.monotonic() + WITHIN_S
            flown_s = 0.0
            while time.monotonic() < deadline and flown_s < FLY_ON_S:
                time.sleep(0.5)
                flown_s = _vehicle_time_s(tmp_path / "flight.csv") - thawed_s
            fuzzing = fuzz.poll() is None
        finally:
            fuzz.kill()
            fuzz.wait()
        assert rig.stop_service()[0] == 0
        stats = rig.stats()
    log = (tmp_path / "service.log").read_text(errors="replace")
    assert fuzzing  # (judged while the fuzz lasted)
    assert flown_s >= FLY_ON_S, (flown_s, stats["link"])
    assert "MAVLink peer moved" not in log, stats["link"]
    assert stats["link"]["other_sender"] + stats["link"]["throttled"] > 0  # the fuzz arrived
