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


class SlowAutopilot:
    """An autopilot whose clock runs at ``rate`` times ours (a simulator at a real-time factor
    under 1), booted at local ``THETA_S``: its samples at 100 Hz of its time, each delivered
    ``delay_s`` after it was measured, and a TIMESYNC round trip every ``period_s`` of ours,
    the answer read ``rtt_s(k)`` after the request at a point ``split(k)`` of it."""

    def __init__(self, rate: float, period_s: float = 0.5) -> None:
        self.rate, self.period_s = rate, period_s

    def stamp_s(self, local_s: float) -> float:
        return (local_s - THETA_S) * self.rate

    def fly(self, clock: AutopilotClock, t0_s: float, t1_s: float, rtts, splits, delay_s=0.001):
        """Local ``t0_s`` .. ``t1_s``: yields (local time, the age the clock gives the newest
        sample, its true age) after every sample."""
        next_sync, k, stamp = t0_s, 0, math.ceil(self.stamp_s(t0_s) * 100.0) / 100.0
        while True:
            measured = THETA_S + stamp / self.rate
            received = measured + delay_s
            if received > t1_s:
                return
            while next_sync <= received:
                rtt = rtts[k % len(rtts)]
                tc1 = self.stamp_s(next_sync + rtt * splits[k % len(splits)])
                clock.timesync(next_sync, tc1, next_sync + rtt)
                next_sync, k = next_sync + self.period_s, k + 1
            clock.observe(stamp, received)
            mapped = clock.to_local(stamp, received)
            assert mapped is not None
            yield received, received - mapped, received - measured
            stamp = round(stamp + 0.01, 6)


@settings(max_examples=40, deadline=None)
@given(
    rate=st.floats(0.5, 1.2),
    rtts=st.lists(st.floats(0.0005, 0.005), min_size=1, max_size=12),
    splits=st.lists(st.floats(0.0, 1.0), min_size=1, max_size=12),
)
def test_an_autopilot_clock_slower_than_ours_is_followed_between_round_trips(rate, rtts, splits):
    """A simulator at a real-time factor of 0.5-1.2 (Gazebo at 0.9 is common; the bundled
    SITL at --speedup 0.7 here): its fresh samples are fresh. (Faster than ours, the stream
    bound follows it: the skew carried on is never negative.) The offset stood still between
    round trips: at 0.9 a sample looked up to 50 ms old before the next one (the attitude
    loop's bound is 20 ms), and a flight at --speedup 0.7 flew 9,407 of its attitude ticks
    as late (no body rates) against 13 with the skew. Within a few ms, whatever the answers'
    delays (at most 5 ms round trips here, split anyhow)."""
    clock = AutopilotClock()
    ap = SlowAutopilot(rate)
    worst = 0.0
    for now, age, truth in ap.fly(clock, THETA_S, THETA_S + 12.0, rtts, splits):
        if now > THETA_S + 6.0:  # after 8 round trips
            worst = max(worst, abs(age - truth))
    # each offset within half a round trip of the truth (2.5 ms); the skew's error, from
    # slopes of such offsets 0.5 s apart, over the half second to the next round trip
    assert worst <= 0.0025 + 0.5 * (2 * 0.0025 / 0.5) + 1e-6, (worst, clock.skew)


def learnt_at_0_8() -> tuple[AutopilotClock, SlowAutopilot, float]:
    """A clock that has followed an autopilot at rate 0.8 for 8 s of round trips every
    0.5 s (2 ms each): its skew learnt, 0.2. Returns it, the autopilot and the local time."""
    clock = AutopilotClock(skew_horizon_s=1.0)
    ap = SlowAutopilot(0.8)
    end = THETA_S + 8.0
    for _ in ap.fly(clock, THETA_S, end, [0.002], [0.5]):
        pass
    assert clock.skew == pytest.approx(0.2, abs=0.01)
    return clock, ap, end


def test_without_fresh_round_trips_the_skew_stops_carrying_the_offset():
    """Learnt at a rate of 0.8 (skew 0.2), then no answer is trusted (a late reader reads the
    answers late too): the skew carries the offset on for ``skew_horizon_s`` and no further,
    and a sample read 1 s late is 1 s old, less what the horizon's skew granted."""
    clock, ap, end = learnt_at_0_8()
    # the answers now come 1 s late: rejected
    assert not clock.timesync(end + 0.5, ap.stamp_s(end + 0.5), end + 1.5)
    late = end + 30.0
    stamp = ap.stamp_s(late - 1.0)  # measured 1 s before it is read
    clock.observe(stamp, late)
    mapped = clock.to_local(stamp, late)
    assert mapped is not None
    # a 0.8 clock moves the true offset 0.2 s/s: 30 s without evidence is 6 s of it, of
    # which the skew carried at most 0.2 s (its horizon); the sample looks older, not younger
    assert late - mapped >= 1.0
    assert clock.offset_s(late) == pytest.approx(clock.offset_s(end + 2.0), abs=0.04)


def test_one_step_of_the_autopilot_clock_or_one_forged_answer_does_not_set_the_skew():
    """The bundled SITL re-anchors 0.5 s behind when starved (a step of its clock), and an
    unsigned link may carry one forged answer: each is one slope of eight, and the median
    stays the clock's rate."""
    clock = AutopilotClock()
    t = THETA_S
    for k in range(9):
        t = THETA_S + 0.5 * k
        step = 0.5 if k >= 4 else 0.0  # its clock falls 0.5 s behind at the fifth
        tc1 = (t + 0.001 - THETA_S) - step
        if k == 6:
            tc1 += 3.0  # a forged answer
        assert clock.timesync(t, tc1, t + 0.002)
    assert abs(clock.skew) < 1e-9
    assert clock.offset_s(t + 0.4) == pytest.approx(THETA_S + 0.5, abs=0.002)


@settings(max_examples=60, deadline=None)
@given(
    rtts=st.lists(st.floats(0.0, 0.05), min_size=9, max_size=30),
    splits=st.lists(st.floats(0.0, 1.0), min_size=9, max_size=30),
    late_s=st.floats(0.3, 3.0),
)
def test_trusted_answers_however_delayed_hide_no_more_lateness_than_their_bound(
    rtts, splits, late_s
):
    """Property: an autopilot on our clock's rate whose trusted answers (round trips up to
    max_rtt_s, each split anyhow: a one-way delay that grows, shrinks, is chosen to mislead)
    give a skew of at most (max_rtt_s / 2) / SKEW_MIN_GAP_S; a sample read ``late_s`` late
    looks at least ``late_s`` old, less half a round trip and that skew over the horizon."""
    clock = AutopilotClock()
    t = THETA_S
    for k, (rtt, split) in enumerate(zip(rtts, splits, strict=False)):
        t = THETA_S + 0.5 * k
        assert clock.timesync(t, t + rtt * split - THETA_S, t + rtt)
        clock.observe(t - THETA_S, t + 0.001)
    skew_bound = 0.5 * clock.max_rtt_s / 0.25
    assert 0.0 <= clock.skew <= skew_bound + 1e-9
    now = t + 0.3
    stamp = now - late_s - THETA_S
    clock.observe(stamp, now)
    mapped = clock.to_local(stamp, now)
    assert mapped is not None
    hidden = 0.5 * clock.max_rtt_s + skew_bound * (clock.skew_horizon_s + 0.5 * clock.max_rtt_s)
    assert now - mapped >= late_s - hidden - 1e-9


def test_a_request_unanswered_past_the_longest_trusted_round_trip_stops_the_skew():
    """A late reader reads the answer late: from ``max_rtt_s`` after a request without a
    trusted answer, the skew carries the offset no further (the horizon alone would carry it
    on for two request periods: lateness that appears then would be hidden by the skew)."""
    clock, ap, _ = learnt_at_0_8()
    last = clock.last_round_trip
    assert last is not None
    asked = last.received_s + 0.1
    clock.requested(asked)
    held = clock.offset_s(asked + clock.max_rtt_s)
    assert held is not None
    assert clock.offset_s(asked + 0.5) == pytest.approx(held, abs=1e-9)
    # answered in time, it is carried on again
    assert clock.timesync(asked, ap.stamp_s(asked + 0.001), asked + 0.002)
    moving = clock.offset_s(asked + 0.3)
    assert moving is not None
    assert moving > held + 0.03
