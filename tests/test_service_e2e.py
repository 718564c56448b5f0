"""The service end to end: real SITL and service processes over UDP MAVLink, lockstep.

Each test flies a short real flight; together they take well under two minutes on 2 cores.
"""

from __future__ import annotations

import json
import math
import os
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import pytest
from pymavlink.dialects.v20 import common as mavlink

from epc_offboard.store.database import LibraryStore
from epc_offboard.vehicle.dialect_px4 import (
    PX4_AUTO_SUB_LOITER,
    PX4_MAIN_MODE_AUTO,
    PX4_MAIN_MODE_OFFBOARD,
    px4_custom_mode,
)
from tests.rig import Rig, holding_scenario, processes_with
from tests.test_coldstart_e2e import HOVER

pytestmark = pytest.mark.timeout(240)

OFFBOARD = (PX4_MAIN_MODE_OFFBOARD, 0)
HOLD = (PX4_MAIN_MODE_AUTO, PX4_AUTO_SUB_LOITER)


def sim(tmp_path, *args, expect: int = 0, figure: bool = False):
    """One lockstep `sim` into ``tmp_path/out``: (report, out, process). No flight.png unless
    ``figure`` (its drawing, 2-3 s of CPU, judged by one test)."""
    out = tmp_path / "out"
    no_figure = () if figure else ("--no-figure",)
    proc = subprocess.run(
        # (--gcs-port 0: nothing streamed to a ground station's UDP 14550)
        [sys.executable, "-m", "epc_offboard", "sim", "--out", str(out), "--gcs-port", "0",
         *no_figure, *args],
        capture_output=True,
        text=True,
        timeout=220,
        check=False,
    )
    assert proc.returncode == expect, proc.stdout + proc.stderr
    return json.loads((out / "report.json").read_text()), out, proc


def test_sim_hover_holds_within_5_cm_and_fails_with_the_targets_it_missed_named(tmp_path):
    # the bundled hover, judged on one target it meets and one nobody can: sim exits 1 and
    # names the failed one (one flight serves both checks); ending holding: the landing
    # after it (8.5 s of vehicle time) judged nothing (sharing_e2e's and ardupilot_e2e's land)
    scenario = tmp_path / "judged_hover.toml"
    scenario.write_text(
        holding_scenario(tmp_path, "hover").read_text()
        + '\n[[targets]]\ndescription = "max error under 5 cm"\n'
        'method = "epc:none"\nmetric = "max_error_m"\nmax = 0.05\n'
        '\n[[targets]]\ndescription = "RMSE of exactly zero"\n'
        'method = "epc:none"\nmetric = "rmse_m"\nmax = 0.0\n'
    )
    report, out, proc = sim(
        tmp_path, "--scenario", str(scenario), "--duration", "6", "--adaptation", "none",
        expect=1, figure=True,
    )  # fmt: skip
    assert "targets failed: RMSE of exactly zero" in proc.stderr
    assert "max error under 5 cm" not in proc.stderr
    assert "target FAIL: RMSE of exactly zero" in proc.stdout
    assert [t["verdict"] for t in report["targets"]] == ["PASS", "FAIL"]
    v = report["vehicles"][0]
    assert v["tracking"]["max_error_m"] < 0.05
    assert v["constraint_violations"] == 0
    assert v["library"]["hits"] > 0
    assert (out / "flight.png").stat().st_size > 10_000
    assert (out / "vehicle1" / "session.tlog").stat().st_size > 10_000
    assert (out / "vehicle1" / "flight.mcap").stat().st_size > 10_000  # beside flight.csv
    loops = v["loops"]
    assert loops["position"]["rate_hz"] == pytest.approx(100.0, rel=0.05)
    # lockstep: the attitude loop keeps its 200 Hz period on the vehicle's clock, as in real
    # time, though PX4 sends ATTITUDE_QUATERNION at 123 Hz: the SYSTEM_TIME the service asks
    # for ticks the clock between state messages (on state stamps alone: 161.5 Hz, a 10 ms
    # period every 2-3 ticks)
    assert loops["attitude"]["rate_hz"] == pytest.approx(200.0, rel=0.005)
    assert loops["attitude"]["period_jitter_p99_ms"] < 0.5
    # what went wrong is in the report, not only in the logs: here, nothing that matters
    assert "failsafes" not in v["warnings"]
    assert "SITL lockstep timeouts" not in v["warnings"]
    assert [e["phase"] for e in v["phase_events"]][-1] == "done"
    # the offboard entry is where the report's time axis starts (within a supervisor tick)
    assert any(e["phase"] == "offboard" and abs(e["t_s"]) < 0.06 for e in v["phase_events"])


def test_second_run_starts_from_the_saved_library(tmp_path):
    # the velocity bound is below the reference speed: active on every sweep, so the library
    # must learn many active sets — what makes a saved library worth loading
    # (both end holding: the landings judged nothing here)
    scenario = holding_scenario(tmp_path, "zigzag_bounded")
    args = ("--scenario", str(scenario), "--duration", "8", "--adaptation", "none")
    first, out, proc = sim(tmp_path, *args)
    tlog = out / "vehicle1" / "session.tlog"
    first_tlog_bytes = tlog.stat().st_size
    assert "vehicle 1: SITL (system id 1) on UDP 127.0.0.1:" in proc.stdout  # where it goes
    second, _, _ = sim(tmp_path, *args)  # same --out: library-1.sqlite is the prior
    # every output of the first run is replaced, the tlog too (it was appended to)
    assert tlog.stat().st_size < 1.5 * first_tlog_bytes
    # the bound holds on the first flight too: the heavier position weights without the
    # jerk bound (position.max_jerk_m_s3) rode it in a limit cycle, 30 violations, 3.11 m/s
    assert first["vehicles"][0]["constraint_violations"] == 0
    assert first["vehicles"][0]["max_abs_vel_m_s"][1] <= 3.0
    m1 = first["vehicles"][0]["library"]["misses"]
    m2 = second["vehicles"][0]["library"]["misses"]
    assert m1 >= 50
    # measured: 253 -> 119, 259 -> 125, 264 -> 147 (the position weights of issue 24 with
    # their jerk bound; 165 -> 48 with the old weights, whose flight never reached the bound
    # in these 8 s: 2.79 m/s). Not ~0: the vehicle never flies exactly the same states twice,
    # and the bound's regions the first flight missed are new to the second
    assert m2 <= 0.6 * m1, (m1, m2)
    assert second["vehicles"][0]["constraint_violations"] == 0


def test_stream_loss_makes_the_vehicle_hold(tmp_path):
    with Rig(tmp_path, sitl_args=("--lockstep-timeout-ms", "20")) as rig:
        rig.wait_mode(*OFFBOARD)
        rig.stop_service(signal.SIGKILL)  # the companion computer dies
        assert rig.wait_mode(*HOLD, timeout_s=20) < 20


@pytest.mark.parametrize("lockstep", [True, False], ids=["lockstep", "real-time"])
def test_system_time_is_asked_for_at_the_attitude_rate_in_lockstep_only(tmp_path, lockstep):
    # lockstep: each SYSTEM_TIME is a tick of the vehicle's clock, the 200 Hz attitude loop's
    # period between the state messages; in real time the wall clock ticks and the autopilot
    # is asked for nothing more (the SITL, as PX4 on its onboard link, sends none unasked)
    with Rig(tmp_path, lockstep=lockstep, speedup=4.0 if lockstep else 1.0) as rig:
        rig.wait_mode(*OFFBOARD)
        system_ms: list[int] = []
        attitude_ms: list[int] = []
        end = time.monotonic() + 2.0
        while time.monotonic() < end:
            msg = rig.gcs.recv_match(
                type=["SYSTEM_TIME", "ATTITUDE_QUATERNION"], blocking=True, timeout=0.5
            )
            if msg is not None:
                seen = system_ms if msg.get_type() == "SYSTEM_TIME" else attitude_ms
                seen.append(msg.time_boot_ms)
    assert len(attitude_ms) > 20  # the link streamed all along
    if not lockstep:
        assert system_ms == []
        return
    assert len(system_ms) > 20, len(system_ms)
    span_s = (system_ms[-1] - system_ms[0]) * 1e-3
    assert (len(system_ms) - 1) / span_s == pytest.approx(200.0, rel=0.02)


def test_stale_state_commands_hold(tmp_path):
    with Rig(tmp_path) as rig:
        rig.wait_mode(*OFFBOARD)
        rig.heartbeat()
        # the position streams stop, as when the estimator of a real vehicle drops out
        for msg_id in (mavlink.MAVLINK_MSG_ID_LOCAL_POSITION_NED, mavlink.MAVLINK_MSG_ID_ODOMETRY):
            rig.command(mavlink.MAV_CMD_SET_MESSAGE_INTERVAL, float(msg_id), -1.0)
        rig.wait_mode(*HOLD, timeout_s=20)
        assert "state stale" in rig.log()
        # the service asks for the streams again and, with auto_offboard, flies on
        rig.wait_mode(*OFFBOARD, timeout_s=30)


def _unit_stop_timeout_s() -> float:
    """TimeoutStopSec of the systemd unit: after it, systemd SIGKILLs the service and the
    library is not saved. The bound a CI test holds the stop to (it takes ~0.5 s idle; the 2 s
    the unit's comment promises is a figure for an idle machine, not a bound at load 6)."""
    unit = (Path(__file__).resolve().parent.parent / "config" / "epc-offboard.service")
    for line in unit.read_text().splitlines():
        if line.startswith("TimeoutStopSec="):
            return float(line.partition("=")[2])
    raise AssertionError("the unit sets no TimeoutStopSec")


def test_sigterm_holds_saves_and_exits_0_before_systemd_would_kill_it(tmp_path):
    with Rig(tmp_path) as rig:
        rig.wait_mode(*OFFBOARD)
        time.sleep(1.0)
        code, took_s = rig.stop_service(signal.SIGTERM)
        assert code == 0
        assert took_s < _unit_stop_timeout_s()
        rig.wait_mode(*HOLD, timeout_s=10)
        stats = rig.stats()
        size = stats["library"]["position"]["size"]
        assert size > 0
    with LibraryStore.open(tmp_path / "library.sqlite") as store:
        assert sum(v["controllers"] for v in store.summary().values()) >= size


def test_bad_input_is_rejected_and_the_flight_goes_on(tmp_path):
    with Rig(tmp_path) as rig:
        rig.wait_mode(*OFFBOARD)
        intruder = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        target = ("127.0.0.1", rig.offboard_port)
        fake = mavlink.MAVLink(None, srcSystem=1, srcComponent=1)
        stranger = mavlink.MAVLink(None, srcSystem=42, srcComponent=1)
        for _ in range(20):
            intruder.sendto(b"\xfd\x10\x00garbage-not-mavlink", target)
            intruder.sendto(
                stranger.heartbeat_encode(2, 12, 129, px4_custom_mode(4, 3), 4).pack(stranger),
                target,
            )
            nan_pos = fake.local_position_ned_encode(10**9, math.nan, 0.0, -2.0, 0.0, 0.0, 0.0)
            intruder.sendto(nan_pos.pack(fake), target)
            time.sleep(0.02)
        time.sleep(1.0)
        hb = rig.heartbeat()
        assert (hb.custom_mode >> 16) & 0xFF == PX4_MAIN_MODE_OFFBOARD
        assert rig.stop_service()[0] == 0
        stats = rig.stats()
    link = stats["link"]
    # the garbage fails the header check (as a frame, its system id byte is 'r'), counted
    # with the stranger's heartbeats by reason
    assert link.get("bad_data", 0) + link["wrong_system"] >= 40
    assert link["wrong_system"] >= 20
    # the vehicle's own ids from a second address: not delivered while the vehicle talks
    assert link["other_sender"] >= 20


def test_unknown_config_key_exits_2_naming_key_and_file(tmp_path):
    cfg = tmp_path / "bad.toml"
    cfg.write_text("[offboard]\nauto_arn = true\n")
    proc = subprocess.run(
        [sys.executable, "-m", "epc_offboard", "run", "--config", str(cfg)],
        capture_output=True,
        text=True,
        timeout=60,
        check=False,
    )
    assert proc.returncode == 2
    assert "offboard.auto_arn" in proc.stderr
    assert str(cfg) in proc.stderr


def test_truncated_library_is_moved_aside_and_the_service_flies(tmp_path):
    lib = tmp_path / "library.sqlite"
    with LibraryStore.open(lib) as store:
        from epc_offboard.control.library_types import LibraryEntry

        store.save_controllers("x", [LibraryEntry((i,), 1.0, 1) for i in range(300)])
    lib.write_bytes(lib.read_bytes()[:2000])
    with Rig(tmp_path) as rig:
        rig.wait_mode(*OFFBOARD)
        assert "moved aside" in rig.log()
    assert list(tmp_path.glob("library.sqlite.corrupt-*"))


@pytest.mark.parametrize("sig", [signal.SIGTERM, signal.SIGKILL])
def test_sigterm_to_sim_stops_every_process_it_started(tmp_path, sig):
    """`kill` of a running sim used to end sim alone and leave its SITL and service flying;
    `kill -9` (a test's timeout, an OOM kill) still did: they now end with it (SIGTERM from
    the parent-death signal, so the service still holds and saves)."""
    out = tmp_path / "out"
    proc = subprocess.Popen(
        [sys.executable, "-m", "epc_offboard", "sim", "--scenario", "hover", "--duration", "30",
         "--adaptation", "none", "--gcs-port", "0", "--out", str(out)],
        stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
    )  # fmt: skip
    marker = str(out / "vehicle1")

    def children() -> dict[int, str]:
        return processes_with(marker)

    try:
        deadline = time.monotonic() + 60
        while len(children()) < 2 and time.monotonic() < deadline:  # SITL and service up
            time.sleep(0.2)
        assert len(children()) >= 2, "sim never started its SITL and service"
        proc.send_signal(sig)
        assert proc.wait(timeout=20) == (128 + sig if sig == signal.SIGTERM else -sig)
        deadline = time.monotonic() + 10
        while children() and time.monotonic() < deadline:
            time.sleep(0.2)
        assert children() == {}, "sim's SITL or service outlived it"
    finally:
        if proc.poll() is None:
            proc.kill()
        for pid in children():
            os.kill(pid, signal.SIGKILL)


def test_compiled_kernels_never_compile_on_the_control_loop(tmp_path):
    """With compiled kernels (warmed before READY) a flight adds no compiled signature: the
    first use of every kernel on the loop found it compiled. (Lockstep: it runs beside other
    tests; its cold twin, in real time, is tests/test_coldstart_e2e.py.)"""
    with Rig(tmp_path, service_overrides=HOVER, service_env={"EPC_OFFBOARD_JIT": "1"}) as rig:
        assert rig.wait_exit(timeout_s=180) == 0, rig.log()
    stats = rig.stats()
    kernels = stats["kernels"]
    assert kernels["mode"] == "compiled"
    assert kernels["signatures"] == kernels["signatures_after_warm_up"] > 0
    # ... nor does any numba function (numba's own typed-list methods included), compiled
    # or loaded from its cache: none of the loops' steps met a compile (issue 21's bursts)
    assert stats["slow_steps"]["compiles_after_warm_up"] == 0, stats["slow_steps"]
    assert not [s for s in stats["slow_steps"]["steps"] if s["compiles"]]
