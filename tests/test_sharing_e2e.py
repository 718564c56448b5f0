"""Fleet sharing end to end: two SITL + service pairs in lockstep, sharing over Zenoh.

`sim --vehicles 2 --stagger`: vehicle 2 starts after vehicle 1 has landed (its service stays
up), fetches its library over Zenoh on loopback (tcp/127.0.0.1:7447-7448) and flies the
same hover without a QP solve of its own for the position loop.
"""

from __future__ import annotations

import json
import subprocess
import sys

import pytest

# sim --vehicles binds the fixed Zenoh ports 7447..: one at a time (test_suite_ports.py)
pytestmark = [pytest.mark.timeout(240), pytest.mark.slow,
              pytest.mark.one_at_a_time("zenoh-fixed-ports")]


def test_a_vehicle_joining_after_another_flies_on_its_library(tmp_path):
    out = tmp_path / "out"
    proc = subprocess.run(
        [sys.executable, "-m", "epc_offboard", "sim", "--out", str(out), "--scenario", "hover",
         "--duration", "5", "--adaptation", "none", "--vehicles", "2", "--stagger",
         "--gcs-port", "0", "--no-figure"],
        capture_output=True, text=True, timeout=220, check=False,
    )  # fmt: skip
    assert proc.returncode == 0, proc.stdout + proc.stderr
    v1, v2 = json.loads((out / "report.json").read_text())["vehicles"]
    assert v1["library"]["qp_solves"] >= 1
    assert v2["library"]["received_shared"] >= 1
    assert v2["library"]["qp_solves"] == 0, v2["library"]
    assert v2["tracking"]["max_error_m"] < 0.05
    log2 = (out / "vehicle2" / "service.log").read_text()
    assert "vehicle v1 joined" in log2
    assert "new controllers from vehicle v1 (snapshot" in log2
