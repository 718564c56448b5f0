"""One short lockstep flight of the `neuralfly` scenario (issue 24), real SITL and service
processes over UDP MAVLink: the Neural-Fly-class plant in Neural-Fly's time-varying wind,
reported with its metric. A few seconds of vehicle time: its figures are no comparison
(the README's full-length runs are); what it checks is that the pieces are wired."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

pytestmark = [pytest.mark.slow, pytest.mark.timeout(300)]


def test_neuralfly_flies_its_plant_in_a_sine_wind_and_reports_its_metric(tmp_path: Path) -> None:
    out = tmp_path / "nf"
    proc = subprocess.run(
        [sys.executable, "-m", "epc_offboard", "sim", "--scenario", "neuralfly",
         "--duration", "8", "--wind", "8.5,-90", "--wind-profile", "sine:2.4,1",
         "--gcs-port", "0", "--out", str(out)],
        capture_output=True, text=True, timeout=280, check=False,
    )  # fmt: skip
    report = json.loads((out / "report.json").read_text())
    # a short flight may miss the 8.5 + 2.4 sin t row's bound (exit 1); nothing else may fail
    failures = [f for f in report["failures"] if not f.startswith("target failed")]
    assert not failures, proc.stdout + proc.stderr
    assert proc.returncode in (0, 1), proc.stdout + proc.stderr
    assert report["wind"] == {"speed_m_s": 8.5, "dir_deg": -90.0, "profile": "sine:2.4,1"}
    v = report["vehicles"][0]
    assert v["flew_offboard"]
    assert v["finished"]
    mean_m = v["tracking"]["mean_error_m"]
    assert 0.0 < mean_m <= v["tracking"]["rmse_m"] <= v["tracking"]["max_error_m"] < 0.5
    assert "mean cm" in proc.stdout
    # its row's target, and only its row's, was judged
    judged = [t for t in report["targets"] if t["metric"] == "mean_error_m"]
    assert [t["bound"] for t in judged] == [0.039]
    # the Neural-Fly plant, not the default: in up to 10.9 m/s of wind its drag takes under
    # 30 deg of tilt (the default vehicle's SIH drag would take 48)
    assert v["max_tilt_deg"] < 40.0
    assert v["constraint_violations"] == 0
