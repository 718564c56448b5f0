"""State that contradicts itself is not flown (issue 21).

A fuzzer's well-formed messages from the vehicle's own ids were taken as its state: the
flight log showed the hover point while the vehicle was 14 m away. A forged time jump
forced a timeline resync that wiped the state, and the supervisor failed safe 3 ms later.
Each sample now passes an innovation gate against the held state's prediction, as an EKF's
measurements do.
"""

from __future__ import annotations

import logging

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from epc_offboard.common import frames
from epc_offboard.vehicle.state import StateTracker
from tests.test_state import LEVEL, att_q, lpos

HOVER = (0.0, 0.0, -2.5)
STILL = (0.0, 0.0, 0.0)


def hover_tick(tr: StateTracker, t_ms: int) -> None:
    now = 100.0 + t_ms * 1e-3
    tr.handle(att_q(t_ms, LEVEL), received_s=now)
    tr.handle(lpos(t_ms, HOVER, STILL), received_s=now)


def test_forged_positions_interleaved_with_genuine_ones_are_not_flown(caplog):
    tr = StateTracker(system_id=1)
    for k in range(100):
        hover_tick(tr, 10 * k)
    caplog.set_level(logging.WARNING)
    worst_m = 0.0
    for k in range(100, 400):
        t_ms = 10 * k
        hover_tick(tr, t_ms)
        # a fuzzer's well-formed sample from the vehicle's ids, 14 m off, a ms later
        tr.handle(lpos(t_ms + 1, (14.0, 3.0, -2.5), STILL), received_s=100.0 + t_ms * 1e-3)
        state = tr.snapshot()
        assert state is not None
        worst_m = max(worst_m, float(np.linalg.norm(state.pos_ned_m - HOVER)))
    assert worst_m < 0.01  # today: 14.3 m
    assert tr.counters["rejected_innovation"] >= 290
    assert tr.counters["state_conflicts"] >= 1
    warnings = [r.getMessage() for r in caplog.records if "contradict" in r.getMessage()]
    assert len(warnings) == 1
    assert "signing" in warnings[0]


def test_forged_attitudes_interleaved_with_genuine_ones_are_not_flown():
    tr = StateTracker(system_id=1)
    flipped = frames.euler_to_quat(3.0, 0.0, 0.0)
    for k in range(300):
        t_ms = 10 * k
        hover_tick(tr, t_ms)
        tr.handle(att_q(t_ms + 1, flipped), received_s=100.0 + t_ms * 1e-3)
        state = tr.snapshot()
        assert state is not None
        assert frames.tilt_deg(state.q_ned_frd) < 1.0


def test_the_vehicles_own_estimator_reset_is_adopted():
    """A position that jumps and stays (PX4's EKF resetting on a GPS glitch) is the
    vehicle's: adopted after resync_samples samples, no conflict."""
    tr = StateTracker(system_id=1)
    for k in range(100):
        hover_tick(tr, 10 * k)
    jumped = (3.0, -1.0, -2.5)
    for k in range(100, 120):
        t_ms = 10 * k
        tr.handle(lpos(t_ms, jumped, STILL), received_s=100.0 + t_ms * 1e-3)
    state = tr.snapshot()
    assert state is not None
    np.testing.assert_allclose(state.pos_ned_m, jumped, atol=1e-9)
    assert tr.counters["estimator_resets"] == 1
    assert tr.counters["state_conflicts"] == 0


def test_an_estimator_reset_with_a_trailing_sample_of_the_old_estimate_is_adopted():
    """PX4's ODOMETRY trails LOCAL_POSITION_NED by a few ms: one sample of the estimate
    before the reset may come after the first one after it. Not a second stream."""
    tr = StateTracker(system_id=1)
    for k in range(100):
        hover_tick(tr, 10 * k)
    jumped = (3.0, -1.0, -2.5)
    tr.handle(lpos(1000, jumped, STILL), received_s=101.0)
    tr.handle(lpos(998, HOVER, STILL), received_s=101.001)  # the old estimate, trailing
    for k in range(101, 110):
        tr.handle(lpos(10 * k, jumped, STILL), received_s=100.0 + k * 0.01)
    state = tr.snapshot()
    assert state is not None
    np.testing.assert_allclose(state.pos_ned_m, jumped, atol=1e-9)
    assert tr.counters["state_conflicts"] == 0


def test_a_resync_after_a_forged_time_jump_keeps_the_last_good_state():
    """The resync wiped the state and the supervisor failed safe 3 ms later with "state
    stale (inf s)". Now the held state is kept, on the new timeline, with its true age."""
    tr = StateTracker(system_id=1)
    for k in range(100):
        hover_tick(tr, 10 * k)
    now = 100.0 + 0.99
    assert tr.age_s(now, vehicle_clock=False) < 0.01
    # five consistent attitude samples 500 s ahead: a new timeline, adopted
    for j in range(5):
        t_ms = 500_000 + 10 * j
        tr.handle(att_q(t_ms, LEVEL), received_s=now + 0.001 * j)
    assert tr.counters["time_resyncs"] == 1
    state = tr.snapshot()
    assert state is not None
    np.testing.assert_allclose(state.pos_ned_m, HOVER, atol=1e-6)
    assert tr.age_s(now + 0.005, vehicle_clock=False) < 0.05  # today: inf


@settings(max_examples=60, deadline=None)
@given(
    accels=st.lists(st.tuples(*[st.floats(-8.0, 8.0)] * 3), min_size=1, max_size=6),
    rates=st.lists(st.tuples(*[st.floats(-3.0, 3.0)] * 3), min_size=1, max_size=6),
    hz=st.sampled_from([30.0, 50.0, 100.0, 123.0]),
)
def test_genuine_manoeuvres_pass_the_gates(accels, rates, hz):
    """Property: a vehicle accelerating up to 8 m/s^2 per axis and turning at up to 3 rad/s
    per axis, changing both every second, sampled at PX4's rates, is never gated out."""
    tr = StateTracker(system_id=1)
    dt = 1.0 / hz
    pos, vel = np.array(HOVER), np.zeros(3)
    q = np.array(LEVEL)
    for k in range(round(6.0 * hz)):
        t = k * dt
        acc = np.array(accels[int(t) % len(accels)])
        rate = np.array(rates[int(t) % len(rates)])
        t_ms = round(t * 1000)
        assert tr.handle(att_q(t_ms, q, tuple(rate)), received_s=t)
        assert tr.handle(lpos(t_ms, tuple(pos), tuple(vel)), received_s=t)
        pos = pos + vel * dt + 0.5 * acc * dt * dt
        vel = vel + acc * dt
        q = frames.quat_integrate_body_rate(q, rate, dt)
    assert tr.counters["rejected_innovation"] == 0


def test_innovation_limits_are_validated():
    from epc_offboard.vehicle.state import StateLimits

    with pytest.raises(ValueError, match="max_innovation_m"):
        StateLimits(max_innovation_m=0.0)
