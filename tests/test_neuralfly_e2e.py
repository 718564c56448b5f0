"""One short lockstep flight of the `neuralfly` scenario (issue 24), real SITL and service
processes over UDP MAVLink: the Neural-Fly-class plant in Neural-Fly's time-varying wind,
reported with its metric. A few seconds of vehicle time: its figures are no comparison
(the README's full-length runs are); what it checks is that the pieces are wired."""

from __future__ import annotations

import contextlib
import csv
import json
import math
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from tests.rig import processes_with

pytestmark = [pytest.mark.slow, pytest.mark.timeout(300)]


def test_neuralfly_flies_its_plant_in_a_sine_wind_and_reports_its_metric(tmp_path: Path) -> None:
    out = tmp_path / "nf"
    proc = subprocess.run(
        [sys.executable, "-m", "epc_offboard", "sim", "--scenario", "neuralfly",
         "--duration", "8", "--wind", "8.5,-90", "--wind-profile", "sine:2.4,1",
         "--gcs-port", "0", "--out", str(out), "--no-figure"],
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
    # 30 deg of tilt to hold (the default vehicle's SIH drag would take 48). Flying the
    # figure's upwind stroke into the gust's peak took it up to 41.5 deg when the sine ran on
    # SITL time: the figure and the sine share their period (2 pi s), so the hand-over time
    # alone set which stroke met the peak (34 deg handed over at 4.0 s, 32 at 4.15 and
    # 10.45 s; 41.4-41.5 at 2.75 and 5.75 s, 40.0 at 6.0 s). The sine now starts at offboard
    # entry (checked below), so the stroke is fixed. 45: the configured limit, still short
    # of the 48 the default plant takes just to hold.
    assert v["max_tilt_deg"] < 45.0
    assert v["constraint_violations"] == 0
    _assert_handed_over_settled(out / "vehicle1")
    _assert_the_sine_starts_at_offboard_entry(out / "vehicle1")


def _assert_the_sine_starts_at_offboard_entry(vehicle_dir: Path) -> None:
    """The sine wind's time starts when the SITL enters offboard (PX4 main mode 6), so the
    figure-8 meets the same gust whenever the hand-over came (issue 24): steady 8.5 m/s
    towards south before it, 8.5 + 2.4 sin(t - entry) after it, on ground truth."""
    with (vehicle_dir / "groundtruth.csv").open() as fh:
        rows = [(float(r["t_s"]), float(r["wind_n_m_s"]), int(r["main_mode"]))
                for r in csv.DictReader(fh)]  # fmt: skip
    entry = next(i for i, (_t, _w, mode) in enumerate(rows) if mode == 6)
    assert all(w == pytest.approx(-8.5, abs=1e-6) for _t, w, _m in rows[:entry])
    t0_s = rows[entry - 1][0]  # the tick flown under offboard ends at rows[entry]'s time
    for t_s, wind_n, _mode in rows[entry:]:
        assert wind_n == pytest.approx(-(8.5 + 2.4 * math.sin(t_s - t0_s)), abs=1e-6), t_s


def _assert_handed_over_settled(vehicle_dir: Path) -> None:
    """The offboard request went only once the vehicle had settled, on the SITL's ground
    truth over the 0.3 s before it (the service's bounds, 0.3 m/s horizontally and 0.4
    vertically, and 0.1 m/s for its estimate's error), or at the settle timeout (counted).
    px4-cold requested it 0.5 s into the stream, the vehicle swinging through zero at up to
    0.51 m/s as PX4's hold flew it back from 2.4 m downwind."""
    stats = json.loads((vehicle_dir / "stats.json").read_text())
    events = {e["phase"]: e["t_s"] for e in reversed(stats["phase_events"])}  # the first
    request_s, streaming_s = events["offboard_requested"], events["streaming"]
    if stats["counters"].get("unsettled_entries", 0):
        assert request_s - streaming_s >= 0.5 + 5.0 - 0.06, events  # min_stream + timeout
        return
    with (vehicle_dir / "groundtruth.csv").open() as fh:
        window = [r for r in csv.DictReader(fh) if request_s - 0.3 <= float(r["t_s"]) <= request_s]
    horizontal = max(math.hypot(float(r["vel_n_m_s"]), float(r["vel_e_m_s"])) for r in window)
    vertical = max(abs(float(r["vel_d_m_s"])) for r in window)
    assert horizontal <= 0.4, (horizontal, events)
    assert vertical <= 0.5, (vertical, events)


def test_a_killed_figures_neuralfly_leaves_no_flight_flying(tmp_path: Path) -> None:
    """`figures neuralfly` flies its table as `sim` children: killed (a timeout, an OOM kill,
    `kill -9`), it left the running `sim`, its SITL and its service flying to the flight's
    end (a minute); they now end with it (`sim` gets SIGTERM and stops its own)."""
    work = tmp_path / "work"
    (tmp_path / "README.md").write_text("# a README for figures to rewrite\n")  # it must exist
    proc = subprocess.Popen(
        [sys.executable, "-m", "epc_offboard", "figures", "neuralfly", "--seed", "0",
         "--jobs", "1", "--work", str(work), "--results", str(tmp_path / "results"),
         "--readme", str(tmp_path / "README.md")],
        stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
    )  # fmt: skip
    marker = str(work)
    try:
        deadline = time.monotonic() + 120
        # figures, its sim, the SITL and the service (their command lines name the work dir)
        while len(processes_with(marker)) < 4 and time.monotonic() < deadline:
            time.sleep(0.2)
        assert len(processes_with(marker)) >= 4, "figures never started a flight"
        proc.kill()
        assert proc.wait(timeout=20) == -signal.SIGKILL
        deadline = time.monotonic() + 20
        while processes_with(marker) and time.monotonic() < deadline:
            time.sleep(0.2)
        assert processes_with(marker) == {}, "a flight outlived figures neuralfly"
        # and none flew on to its end (an orphan's first flight takes 15-60 s: in 20 s it
        # may have ended, with its report)
        assert not list(work.rglob("report.json")), "a flight flew on after figures died"
    finally:
        if proc.poll() is None:
            proc.kill()
        for pid in processes_with(marker):
            with contextlib.suppress(ProcessLookupError):
                os.kill(pid, signal.SIGKILL)
