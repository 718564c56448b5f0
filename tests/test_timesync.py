"""The autopilot's clock on ours: state age by when a sample was measured (issue 20, 2)."""

from __future__ import annotations

import math

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from epc_offboard.vehicle.state import StateTracker
from epc_offboard.vehicle.timesync import AutopilotClock
from tests.test_state import LEVEL, att_q, lpos

THETA_S = 1234.5  # local monotonic time at the autopilot's boot


def stream(clock: AutopilotClock, t0_s: float, t1_s: float, delay_s: float, hz: float = 100.0):
    """Samples stamped t0..t1 (autopilot time), each received ``delay_s`` after it was
    measured (plus THETA_S: the clocks' offset)."""
    n = round((t1_s - t0_s) * hz)
    for k in range(n):
        stamp = t0_s + k / hz
        clock.observe(stamp, stamp + THETA_S + delay_s)
    return t1_s


def test_a_delay_that_appears_mid_flight_is_age_not_offset():
    clock = AutopilotClock()
    t = stream(clock, 0.0, 10.0, delay_s=0.002)
    # the service now reads everything 1 s late, for 30 s: a sample measured at t is
    # still a second old when it arrives, however long it lasts
    t = stream(clock, t, t + 30.0, delay_s=1.0)
    stamp = t - 0.01
    now = stamp + THETA_S + 1.0
    measured = clock.to_local(stamp, now)
    assert measured is not None
    assert now - measured == pytest.approx(1.0, abs=0.05)


def test_one_forged_early_stamp_does_not_age_every_genuine_sample():
    clock = AutopilotClock()
    t = stream(clock, 0.0, 5.0, delay_s=0.002)
    clock.observe(t + 0.9, t + THETA_S)  # a stamp 0.9 s ahead of the truth, once
    t = stream(clock, t, t + 1.0, delay_s=0.002)
    theta = clock.offset_s(t + THETA_S)
    assert theta is not None
    assert theta == pytest.approx(THETA_S + 0.002, abs=0.01)


def test_timesync_round_trips_long_enough_to_hide_a_late_reader_are_not_trusted():
    clock = AutopilotClock(max_rtt_s=0.05)
    t = stream(clock, 0.0, 5.0, delay_s=0.002)
    # a late reader reads the answer late too: round trip 1.0 s, rejected
    assert not clock.timesync(t + THETA_S, (t + THETA_S + 0.5) - THETA_S, t + THETA_S + 1.0)
    assert clock.counters["timesync_rejected_rtt"] == 1
    assert clock.timesync(t + THETA_S, t + 0.005, t + THETA_S + 0.01)
    theta = clock.offset_s(t + THETA_S + 0.01)
    assert theta == pytest.approx(THETA_S, abs=0.006)


def test_a_simulator_that_falls_behind_is_followed_by_timesync_not_called_stale():
    """The bundled SITL re-anchors when more than 0.5 s behind real time: its stamps step
    back against our clock. The stream bound alone would call everything 0.5 s old for
    500 s; a trusted round trip moves the offset up at once."""
    clock = AutopilotClock()
    t = stream(clock, 0.0, 5.0, delay_s=0.001)
    slipped = THETA_S + 0.6  # the autopilot's time now lags ours by 0.6 s more
    for k in range(100):
        clock.observe(t + k / 100, t + k / 100 + slipped + 0.001)
    now = t + 1.0 + slipped
    assert clock.timesync(now - 0.004, t + 1.0 - 0.002, now)
    measured = clock.to_local(t + 0.99, now)
    assert measured is not None
    assert now - measured == pytest.approx(0.01, abs=0.005)


@settings(max_examples=60, deadline=None)
@given(
    delays=st.lists(st.floats(0.0005, 0.05), min_size=20, max_size=200),
    late_s=st.floats(0.3, 3.0),
)
def test_age_never_hides_a_late_delivery(delays, late_s):
    """Property: whatever the genuine delivery jitter, a sample delivered ``late_s`` later
    than the slowest delivery seen is at least ``late_s`` old by the mapped clock, less
    what the drift allowance grants over the stream's span."""
    clock = AutopilotClock()
    t = 0.0
    for d in delays:
        clock.observe(t, t + THETA_S + d)
        t += 0.01
    now = t + THETA_S + max(delays) + late_s
    measured = clock.to_local(t, now)
    assert measured is not None
    assert now - measured >= late_s - clock.max_drift * (now - THETA_S) - 1e-9


def test_reset_forgets_the_old_timeline():
    clock = AutopilotClock()
    stream(clock, 100.0, 101.0, delay_s=0.001)
    clock.reset()
    assert clock.offset_s(0.0) is None
    stream(clock, 0.0, 1.0, delay_s=0.001)  # the autopilot rebooted: stamps from 0
    assert clock.offset_s(THETA_S + 1.0) == pytest.approx(THETA_S + 0.001, abs=1e-4)


def test_tracker_judges_a_late_read_sample_stale_in_real_time():
    """The service read PX4's messages 2.4 s late and flew them as fresh (receipt time).
    Now the tracker's age is by the autopilot's stamp on our clock."""
    tr = StateTracker(system_id=1)
    for k in range(200):  # 2 s of genuine telemetry, delivered in 1 ms
        t_ms = k * 10
        rx = THETA_S + t_ms * 1e-3 + 0.001
        tr.handle(att_q(t_ms, LEVEL), received_s=rx)
        tr.handle(lpos(t_ms, (0.0, 0.0, -2.0), (0.0, 0.0, 0.0)), received_s=rx)
    assert tr.age_s(THETA_S + 1.995, vehicle_clock=False) < 0.01
    # then the reader falls behind: each sample read 0.8 s after it was measured
    for k in range(200, 400):
        t_ms = k * 10
        rx = THETA_S + t_ms * 1e-3 + 0.8
        tr.handle(att_q(t_ms, LEVEL), received_s=rx)
        tr.handle(lpos(t_ms, (0.0, 0.0, -2.0), (0.0, 0.0, 0.0)), received_s=rx)
        age = tr.age_s(rx, vehicle_clock=False)
        assert age == pytest.approx(0.8, abs=0.01)
    # and the state is predicted to when it is used, no further than max_predict_s
    at = tr.vehicle_time_at(rx, vehicle_clock=False)
    assert at is not None
    s = tr.snapshot(at)
    assert s is not None
    assert s.position_age_s == pytest.approx(0.8, abs=0.01)
    # lockstep: the loop's clock is the vehicle's (the newest sample's time, or a SYSTEM_TIME
    # tick after it), so the state is predicted to that time itself, no mapping
    assert tr.vehicle_time_at(rx, vehicle_clock=True) == rx


def test_clock_limits_are_validated():
    with pytest.raises(ValueError, match="max_drift"):
        AutopilotClock(max_drift=-1.0)
    with pytest.raises(ValueError, match="max_rtt_s"):
        AutopilotClock(max_rtt_s=0.0)
    assert math.isinf(StateTracker(system_id=1).age_s(0.0, vehicle_clock=False))
