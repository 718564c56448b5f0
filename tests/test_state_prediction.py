"""The attitude between samples: predicted with the measured body rates (issue 20, 4).

PX4 delivers ATTITUDE_QUATERNION at ~123 Hz to a 200 Hz attitude loop: on ~40 % of its
ticks the loop saw the previous sample. The snapshot now rotates it on to the tick's time.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from epc_offboard.common import frames
from epc_offboard.vehicle.state import StateTracker
from tests.test_state import att_q, lpos

rates = st.tuples(*[st.floats(-6.0, 6.0)] * 3)


@settings(max_examples=100, deadline=None)
@given(rate=rates, roll=st.floats(-1.0, 1.0), yaw=st.floats(-3.0, 3.0), dt=st.floats(0, 0.2))
def test_body_rate_integration_is_exact_and_composes(rate, roll, yaw, dt):
    """Oracle: a constant rate integrated over dt equals two halves of it, stays unit, and
    for small dt its derivative is q' = 1/2 q ⊗ [0, w]."""
    q = frames.euler_to_quat(roll, 0.2, yaw)
    w = np.array(rate)
    whole = frames.quat_integrate_body_rate(q, w, dt)
    half = frames.quat_integrate_body_rate(q, w, dt / 2)
    halves = frames.quat_integrate_body_rate(half, w, dt / 2)
    assert np.linalg.norm(whole) == pytest.approx(1.0)
    assert frames.angle_between_deg(whole, halves) == pytest.approx(0.0, abs=1e-5)
    h = 1e-6
    numeric = (frames.quat_integrate_body_rate(q, w, h) - q) / h
    analytic = 0.5 * frames.quat_multiply(q, (0.0, *rate))
    np.testing.assert_allclose(numeric, analytic, atol=1e-4)


def test_attitude_is_rotated_on_to_the_tick_and_bounded():
    tr = StateTracker(system_id=1)
    q0 = frames.euler_to_quat(0.0, 0.0, 0.3)
    tr.handle(att_q(1000, q0, (0.0, 0.0, 1.0)), received_s=1.0)  # yaw rate 1 rad/s
    tr.handle(lpos(1000, (0.0, 0.0, -2.0), (0.0, 0.0, 0.0)), received_s=1.0)
    s = tr.snapshot(1.008)  # a tick 8 ms after the sample (PX4's 123 Hz)
    assert s is not None
    assert s.yaw_rad == pytest.approx(0.308, abs=1e-6)
    assert s.attitude_age_s == pytest.approx(0.008)
    far = tr.snapshot(5.0)  # prediction stops at max_predict_s: beyond it, hold
    assert far is not None
    assert far.yaw_rad == pytest.approx(0.3 + tr.limits.max_predict_s, abs=1e-6)
    assert math.isfinite(far.attitude_age_s)
