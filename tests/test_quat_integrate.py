"""``frames.quat_integrate_body_rate`` against scipy's Rotation (an oracle of its own), for
negative steps too: q ⊗ exp(w dt / 2) is defined for dt < 0 (a sample carried back in time;
the state's innovation gate, its float twin, takes any sign). Before stop 40 a negative dt
returned q unchanged."""

from __future__ import annotations

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

from epc_offboard.common import frames

rates = st.tuples(*[st.floats(-6.0, 6.0)] * 3)


def _scipy(q_wxyz: np.ndarray, rate_frd_rad_s: np.ndarray, dt_s: float) -> np.ndarray:
    """q then the body-frame rotation by the rotation vector w dt (right-multiplied)."""
    r = Rotation.from_quat([*q_wxyz[1:], q_wxyz[0]]) * Rotation.from_rotvec(rate_frd_rad_s * dt_s)
    x, y, z, w = r.as_quat()
    out = np.array([w, x, y, z])
    return -out if out[0] < 0.0 else out


@settings(max_examples=200, deadline=None)
@given(rate=rates, roll=st.floats(-1.0, 1.0), yaw=st.floats(-3.0, 3.0),
       dt=st.floats(-0.5, 0.5))  # fmt: skip
def test_body_rate_integration_matches_scipy_forward_and_back(rate, roll, yaw, dt):
    q = frames.euler_to_quat(roll, 0.2, yaw)
    w = np.array(rate)
    got = frames.quat_integrate_body_rate(q, w, dt)
    want = _scipy(q, w, dt)
    assert min(np.abs(got - want).max(), np.abs(got + want).max()) < 1e-12  # q and -q alike
    assert abs(np.linalg.norm(got) - 1.0) < 1e-12


@settings(max_examples=100, deadline=None)
@given(rate=rates, roll=st.floats(-1.0, 1.0), dt=st.floats(0.0, 0.5))
def test_back_undoes_forward(rate, roll, dt):
    """Round trip: rotated on by dt, then back by -dt, is where it began."""
    q = frames.euler_to_quat(roll, -0.3, 1.0)
    w = np.array(rate)
    there = frames.quat_integrate_body_rate(q, w, dt)
    back = frames.quat_integrate_body_rate(there, w, -dt)
    assert min(np.abs(back - q).max(), np.abs(back + q).max()) < 1e-12
