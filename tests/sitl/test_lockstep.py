"""Lockstep: two runs with the same seed and the same scripted replies fly identically."""

from __future__ import annotations

import csv
import math
import time

from pymavlink.dialects.v20 import common as mavlink

from epc_offboard.common.frames import euler_to_quat
from sitl.groundtruth import COLUMNS
from tests.sitl.mavclient import MavClient, counters_from, start_sitl, state_stamp_ms, stop_sitl

DURATION_S = 2.0
ARM_TICK = 100  # well after the first reply has put the SITL into waiting mode
OFFBOARD_TICK = 120


def scripted_flight(tmp_path, name: str) -> tuple[str, float]:
    """Fly one lockstep run answering every tick; returns (ground-truth CSV text, wall s)."""
    client = MavClient()
    gt = tmp_path / f"{name}.csv"
    proc = start_sitl(
        client,
        "--lockstep",
        "--seed",
        "7",
        "--wind",
        "3,-135",
        "--groundtruth",
        str(gt),
        "--duration",
        str(DURATION_S),
    )
    t0 = time.monotonic()
    try:
        while proc.poll() is None and time.monotonic() - t0 < 60:
            msgs = client.poll(0.05)
            stamps = [t for t in map(state_stamp_ms, msgs) if t is not None]
            if not stamps:
                continue
            stamp_ms = max(stamps)  # one datagram is one tick: answer its newest state
            tick = stamp_ms // 5
            if tick == ARM_TICK:
                client.send(
                    client.mav.command_long_encode(
                        1, 1, mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 0, 1, 0, 0, 0, 0, 0, 0
                    )
                )
            if tick == OFFBOARD_TICK:
                client.send(
                    client.mav.command_long_encode(
                        1, 1, mavlink.MAV_CMD_DO_SET_MODE, 0,
                        mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED, 6, 0, 0, 0, 0, 0,
                    )
                )  # fmt: skip
            t = stamp_ms / 1000.0
            # The reply depends on the (noisy, seeded) state too, like a real controller.
            rollspeed = client.last["ATTITUDE"].rollspeed if "ATTITUDE" in client.last else 0.0
            q = euler_to_quat(0.05 * math.sin(2 * t) - 0.2 * rollspeed, 0.03, 0.0)
            thrust = 0.60 + 0.05 * math.sin(3 * t)
            client.attitude_setpoint(thrust, tuple(q), time_boot_ms=stamp_ms)
        wall_s = time.monotonic() - t0
    finally:
        rc, err = stop_sitl(proc)
        client.close()
    assert rc == 0, err
    assert counters_from(err)["lockstep_timeouts"] == 0
    return gt.read_text(), wall_s


def test_same_seed_same_replies_same_ground_truth(tmp_path):
    first, wall_s = scripted_flight(tmp_path, "a")
    second, _ = scripted_flight(tmp_path, "b")
    assert first == second
    rows = list(csv.DictReader(first.splitlines()))
    assert list(rows[0]) == COLUMNS
    assert len(rows) == round(DURATION_S / 0.005)
    assert rows[-1]["t_s"] == f"{DURATION_S:.6f}"
    last = rows[-1]
    assert (last["armed"], last["main_mode"]) == ("1", "6")  # commands landed on their ticks
    assert float(last["pos_d_m"]) < -0.3  # it flew on the scripted thrust
    assert float(last["wind_n_m_s"]) < -2.0  # wind towards south-west
    arm_row = next(r for r in rows if r["armed"] == "1")
    assert arm_row["t_s"] == f"{(ARM_TICK + 1) * 0.005:.6f}"
    print(f"lockstep real-time factor with a scripted Python responder: {DURATION_S / wall_s:.1f}")
