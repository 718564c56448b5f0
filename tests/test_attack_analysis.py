"""bench --attack's pure analysis: the attitude sends read from a tlog, a window's figures."""

from __future__ import annotations

import struct

import numpy as np
from pymavlink.dialects.v20 import common as mavlink

from epc_offboard.tools import attack_analysis as aa


def _frame(mav: mavlink.MAVLink, msg: mavlink.MAVLink_message, t_s: float) -> bytes:
    frame: bytes = msg.pack(mav)
    return struct.pack(">Q", int(t_s * 1e6)) + frame


def test_attitude_sends_are_read_from_a_tlog_by_header_with_their_mode():
    ours = mavlink.MAVLink(None, srcSystem=245, srcComponent=191)
    vehicle = mavlink.MAVLink(None, srcSystem=1, srcComponent=1)
    q = [1.0, 0.0, 0.0, 0.0]
    body_rates = ours.set_attitude_target_encode(0, 1, 1, aa.ATTITUDE_IGNORE, q, 0.1, 0.0, 0.0,
                                                 0.5)  # fmt: skip
    quaternion = ours.set_attitude_target_encode(0, 1, 1, 7, q, 0.0, 0.0, 0.0, 0.5)
    state = vehicle.attitude_quaternion_encode(0, 1.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0)
    tlog = b"".join([
        _frame(ours, body_rates, 10.000), _frame(vehicle, state, 10.001),
        _frame(ours, quaternion, 10.005), _frame(ours, body_rates, 10.010),
    ])  # fmt: skip
    times, rates = aa.attitude_sends(tlog + b"\x00\x01", 245)  # a torn end is ignored
    assert np.allclose(times, [10.000, 10.005, 10.010])
    assert rates.tolist() == [True, False, True]


def test_a_window_without_ticks_is_one_gap_and_a_failsafe_shows_in_its_phases():
    t = np.arange(0.0, 2.0, 0.01)
    keep = (t < 0.5) | (t > 1.2)  # no row while the service streamed nothing
    n = int(keep.sum())
    flight = {
        "t_s": t[keep], "vehicle_t_s": t[keep] + 100.0, "compute_us": np.full(n, 300.0),
        "phase": np.where(t[keep] > 1.2, "streaming", "offboard"),
        **{f"ref_pos_{a}_m": np.zeros(n) for a in "ned"},
    }  # fmt: skip
    tt = np.arange(100.0, 102.0, 0.005)
    truth = {"t_s": tt, "pos_n_m": np.full(tt.size, 0.05), "pos_e_m": np.zeros(tt.size),
             "pos_d_m": np.full(tt.size, 0.02), "main_mode": np.full(tt.size, 6.0)}  # fmt: skip
    att = np.arange(0.0, 2.0, 0.005)
    w = aa.Window("hover", "flood", 0.2, 1.8, {})
    out = aa.window_figures(w, flight, truth, att, np.zeros(att.size, dtype=bool), [], {}, 0.005)
    assert 0.70 < out["position_max_gap_ms"] / 1e3 < 0.73
    assert out["phases"] == ["offboard", "streaming"]
    assert abs(out["max_error_m"] - np.hypot(0.05, 0.02)) < 1e-9
    assert abs(out["altitude_loss_m"] - 0.02) < 1e-9
    assert abs(out["attitude_rate_hz"] - 200.0) < 1.0
    assert out["attitude_late_ticks"] == 0


def test_the_body_rate_target_is_judged_against_lockstep_only_in_body_rate_mode():
    windows = [{"phase": "figure8", "kind": k, "rmse_m": e, "duration_s": d}
               for k, e, d in (("calm", 0.05, 4.0), ("flood", 0.07, 10.0))]  # fmt: skip
    rmse = aa.figure8_rmse_m(windows)
    assert abs(rmse - ((0.05**2 * 4 + 0.07**2 * 10) / 14) ** 0.5) < 1e-12
    def verdict(mode: str, lockstep: float | None) -> bool | None:
        report = {"windows": windows, "attitude_mode": mode, "lockstep_rmse_m": lockstep}
        return aa.body_rate_verdict(report).met

    assert verdict("rates", rmse / 1.19) is True
    assert verdict("rates", rmse / 1.25) is False
    assert verdict("quaternion", rmse) is None
    assert verdict("rates", None) is None


def test_the_table_tells_the_services_stalls_and_its_collections_in_the_loops_thread():
    """Issue 21: what the service counted of its stalls and collections is in the printout,
    not only in the JSON."""
    stall = {"loop": "position", "t_s": 1.0, "interval_ms": 14.0, "thread_cpu_ms": 12.0,
             "gc_ms": 1.5}  # fmt: skip
    text = aa.stall_summary({
        "stats_stalls": [stall, {**stall, "thread_cpu_ms": 2.0, "interval_ms": 13.0}],
        "stats_counters": {"position_stalls": 5},
        "stats_gc": {"loop_thread_collections": [39, 3, 0], "loop_thread_max_pause_ms": 2.1,
                     "collections": [40, 3, 0], "max_pause_ms": 2.1},
    })  # fmt: skip
    assert "position 5 (of the latest 2: 1 on the loops' own CPU, longest 14.0 ms" in text
    assert "attitude 0" in text
    assert "[39, 3, 0], longest 2.1 ms" in text
