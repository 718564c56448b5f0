"""The flight log and tlog written by a process of their own (issue 21): the control process
packs, the writer formats and writes; a full pipe drops and counts, never blocks; a dead
writer is restarted and its files continued."""

from __future__ import annotations

import csv
import os
import signal
import struct
import time
from collections import Counter

import numpy as np
import pytest

from epc_offboard.common.logsetup import LogConfig
from epc_offboard.control.types import PositionOutput, ReferenceHorizon, VehicleState
from epc_offboard.service.flightlog import FLIGHT_LOG_COLUMNS, pack_row
from epc_offboard.service.logwriter import LogWriter

pytestmark = pytest.mark.timeout(60)


def state(t_s: float) -> VehicleState:
    return VehicleState(
        t_s, np.array([1.0, -2.0, -2.5]), np.array([0.1, 0.0, -0.05]),
        np.array([1.0, 0.0, 0.0, 0.0]), np.zeros(3), 0.004, 0.002,
    )  # fmt: skip


OUT = PositionOutput(
    np.array([1.0, 0.0, 0.0, 0.0]), (0.0, 0.0, 0.0), 0.512345678,
    np.array([0.25, -0.125, 0.0]), np.array([0.0, 0.0, -0.3]), "hit", 123.456,
)  # fmt: skip


def old_row(t_s: float, phase: str, s: VehicleState, ref: ReferenceHorizon) -> list[str]:
    """The row as FlightLog.write formatted it in the control process before."""
    return (
        [f"{t_s:.4f}", f"{s.time_s:.4f}", phase]
        + [f"{v:.5f}" for v in (*s.pos_ned_m, *s.vel_ned_m_s)]
        + [f"{v:.5f}" for v in (*ref.pos_ned_m[0], *ref.vel_ned_m_s[0])]
        + [f"{v:.5f}" for v in (*OUT.acc_cmd_ned_m_s2, *OUT.p_hat_ned_m_s2, OUT.thrust_norm)]
        + [OUT.source, f"{OUT.compute_us:.1f}"]
    )


def read_rows(path) -> list[list[str]]:
    with path.open(newline="") as fh:
        return list(csv.reader(fh))


def wait_for(cond, what: str, timeout_s: float = 10.0) -> None:
    end = time.monotonic() + timeout_s
    while not cond():
        assert time.monotonic() < end, f"timed out waiting for {what}"
        time.sleep(0.02)


def test_rows_and_frames_reach_their_files_as_before(tmp_path):
    counters: Counter[str] = Counter()
    logs = LogWriter(str(tmp_path / "flight.csv"), str(tmp_path / "s.tlog"), LogConfig(),
                     counters)  # fmt: skip
    logs.start()
    ref = ReferenceHorizon.hold([1.5, -2.0, -2.5], 0.0, 3)
    frames = [bytes([0xFD, 9, 0, 0, k % 256]) + bytes(range(k % 40)) for k in range(300)]
    expected = []
    for k in range(200):
        t = 100.0 + 0.01 * k
        assert logs.tlog is not None
        for frame in frames[k % 3 :: 97]:
            logs.tlog.write(frame, 1.7e9 + t)
        logs.flight_row(pack_row(t, "offboard", state(t), ref, OUT))
        expected.append(old_row(t, "offboard", state(t), ref))
    logs.close()
    rows = read_rows(tmp_path / "flight.csv")
    assert rows[0] == FLIGHT_LOG_COLUMNS
    assert rows[1:] == expected
    data = (tmp_path / "s.tlog").read_bytes()
    want = b"".join(
        struct.pack(">Q", int((1.7e9 + 100.0 + 0.01 * k) * 1e6)) + frame
        for k in range(200)
        for frame in frames[k % 3 :: 97]
    )
    assert data == want
    assert counters["log_records_dropped"] == 0


def test_a_wedged_writer_costs_drops_not_time_and_a_dead_one_is_restarted(tmp_path):
    counters: Counter[str] = Counter()
    logs = LogWriter(str(tmp_path / "flight.csv"), "", LogConfig(), counters)
    logs.start()
    ref = ReferenceHorizon.hold([0.0, 0.0, -2.0], 0.0, 3)
    row = pack_row(1.0, "offboard", state(1.0), ref, OUT)
    pid = logs.pid()
    assert pid is not None
    logs.flight_row(row)
    os.kill(pid, signal.SIGSTOP)  # wedged: the pipe fills, then rows are dropped
    try:
        t0 = time.perf_counter()
        worst = 0.0
        for _ in range(20000):  # ~4 MB of rows: more than the pipe holds
            t = time.perf_counter()
            logs.flight_row(row)
            worst = max(worst, time.perf_counter() - t)
        # they all returned with the reader stopped: a blocking write would hang here for
        # good; the bound only allows for this process being preempted on a loaded machine
        assert counters["log_records_dropped"] > 0
        assert worst < 1.0, f"a row took {worst * 1e3:.1f} ms"
        assert time.perf_counter() - t0 < 20.0
        stats = logs.process_stats()
        assert isinstance(stats["queued_bytes"], int)
        assert stats["queued_bytes"] > 0
    finally:
        os.kill(pid, signal.SIGKILL)  # then dead

    def ticking(name: str):  # rows keep coming, as the position loop's would
        def cond() -> bool:
            logs.flight_row(row)
            return counters[name] == 1

        return cond

    wait_for(ticking("log_writer_failures"), "the death")
    wait_for(ticking("log_writer_restarts"), "a restart")
    assert logs.pid() not in (None, pid)
    for _ in range(5):
        logs.flight_row(pack_row(2.0, "landing", state(2.0), ref, OUT))
    logs.close()
    rows = read_rows(tmp_path / "flight.csv")
    assert rows[0] == FLIGHT_LOG_COLUMNS
    assert FLIGHT_LOG_COLUMNS not in rows[1:]  # continued, not started over
    assert [r[2] for r in rows[-5:]] == ["landing"] * 5
