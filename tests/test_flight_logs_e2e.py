"""The logs of a real flight open in the tools pilots use: the .tlog in pymavlink's
mavlogdump.py, the per-tick flight log (as MCAP) in mcap's reader.

One short lockstep hover (`epc-offboard sim`, real SITL and service processes over UDP)
serves both tests.
"""

from __future__ import annotations

import csv
import itertools
import json
import math
import subprocess
import sys
import time
from pathlib import Path

import pytest
from pymavlink.dialects.v20 import common as mavlink

from epc_offboard.cli import main
from tests.rig import holding_scenario
from tests.test_logexport import read_mcap
from tests.test_service_e2e import sim

pytestmark = pytest.mark.timeout(240)

MAVLOGDUMP = Path(sys.executable).with_name("mavlogdump.py")
CHECKED = ("HEARTBEAT", "ATTITUDE_QUATERNION", "LOCAL_POSITION_NED", "SET_ATTITUDE_TARGET")


@pytest.fixture(scope="module")
def flight(tmp_path_factory):
    """(vehicle1 directory, unix time before the flight, unix time after it)."""
    started = time.time()
    # ending holding: the logs are judged, not the autopilot's landing (8.5 s of vehicle time)
    tmp = tmp_path_factory.mktemp("flight")
    _, out, _ = sim(tmp, "--scenario", str(holding_scenario(tmp, "hover")), "--duration", "4",
                 "--adaptation", "none")  # fmt: skip
    return out / "vehicle1", started, time.time()


def _quat_norm(q):
    return math.sqrt(sum(c * c for c in q))


def test_tlog_decodes_with_mavlogdump(flight):
    run_dir, started, ended = flight
    proc = subprocess.run(
        [sys.executable, str(MAVLOGDUMP), "--format", "json", str(run_dir / "session.tlog")],
        capture_output=True, text=True, timeout=60, check=False, stdin=subprocess.DEVNULL,
    )  # fmt: skip
    assert proc.returncode == 0, proc.stderr
    records = [json.loads(line) for line in proc.stdout.splitlines() if line.strip()]
    by_type: dict[str, list[dict]] = {}
    for r in records:
        by_type.setdefault(r["meta"]["type"], []).append(r["data"])
    assert not [t for t in by_type if t.startswith("BAD") or t.startswith("UNKNOWN")]
    for name in CHECKED:
        assert len(by_type.get(name, [])) >= 5, (name, sorted(by_type))

    # the tlog's timestamps: unix time of the flight, never going back
    stamps = [r["meta"]["timestamp"] for r in records]
    assert all(b >= a for a, b in itertools.pairwise(stamps))
    assert started - 1.0 < stamps[0] < stamps[-1] < ended + 1.0

    # the right types, with their fields meaning what they should
    for hb in by_type["HEARTBEAT"]:
        assert hb["type"] == mavlink.MAV_TYPE_QUADROTOR
        assert hb["autopilot"] == mavlink.MAV_AUTOPILOT_PX4
    for q in by_type["ATTITUDE_QUATERNION"]:
        assert _quat_norm([q["q1"], q["q2"], q["q3"], q["q4"]]) == pytest.approx(1.0, abs=1e-3)
    boot_ms = [m["time_boot_ms"] for m in by_type["LOCAL_POSITION_NED"]]
    assert all(b >= a for a, b in itertools.pairwise(boot_ms))
    # it took off (NED: up is negative)
    assert min(m["z"] for m in by_type["LOCAL_POSITION_NED"]) < -0.5
    for sp in by_type["SET_ATTITUDE_TARGET"]:  # what the service commanded
        assert 0.0 <= sp["thrust"] <= 1.0
        assert sp["target_system"] == 1


def test_flight_log_exports_to_mcap_with_the_same_ticks(flight, tmp_path):
    run_dir, _, _ = flight
    src, out = run_dir / "flight.csv", tmp_path / "flight.mcap"
    assert main(["log", "mcap", str(src), str(out)]) == 0
    with src.open(newline="") as fh:
        rows = list(csv.DictReader(fh))
    got = read_mcap(out)
    assert len(rows) > 100
    assert len(got) == len(rows)
    for row, (_, channel, log_time_ns, message) in zip(rows, got, strict=True):
        assert channel.topic == "/flight"
        assert message["phase"] == row["phase"]
        assert message["pos_d_m"] == float(row["pos_d_m"])
        assert message["thrust_norm"] == float(row["thrust_norm"])
        assert log_time_ns == round(float(row["vehicle_t_s"]) * 1e9)
