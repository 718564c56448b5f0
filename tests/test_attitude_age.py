"""The attitude loop's start from a sample that is not fresh (issue 21: body rates in real time).

The state tracker carries the attitude sample on to the tick at the sample's body rates (a
sample is 0-8 ms old at PX4's ~123 Hz ATTITUDE_QUATERNION in real time; 0 or 5 ms in
lockstep). The body-rate loop then predicts from the SAMPLE over its age and the dead time
with the commands in flight. Carried twice, the age was flown twice: the loop believed the
vehicle further on than it was, by the rate times the age.
"""

from __future__ import annotations

import numpy as np
import pytest

from epc_offboard.common import frames
from epc_offboard.control.attitude import AttitudeControlConfig, AttitudeLoop
from epc_offboard.vehicle.state import StateTracker
from tests.attitude_plant import TICK_S, target
from tests.test_state import att_q, lpos

SAMPLE_S = 10.0


def predicted_start(loop: AttitudeLoop, state, now_s: float) -> np.ndarray:
    """The state (6,) the loop's QP starts from at this tick: the real controller runs, its
    input is recorded."""
    seen: list[np.ndarray] = []
    step = loop.controller.step

    def recording(x0: np.ndarray, refs: np.ndarray) -> object:
        seen.append(np.array(x0))
        return step(x0, refs)

    setattr(loop.controller, "step", recording)  # noqa: B010 (an instance attribute, undone)
    try:
        loop.attitude_tick(state, target(0.0), now_s)
    finally:
        del loop.controller.step
    return seen[0]


@pytest.mark.parametrize("age_ms", [0.0, 2.5, 5.0, 8.0, 11.0])
@pytest.mark.parametrize("axis", [0, 1])
def test_a_samples_age_is_flown_once(age_ms: float, axis: int) -> None:
    """Oracle: a vehicle rolling (or pitching) steadily at w, the commands w / K for longer
    than the model remembers: when the command sent now starts to act, the angle is the
    sample's plus w (age + dead time), whatever the sample's age (the model's own closed
    form: its rate stays w). Before, an 8 ms old sample started the QP 10 ms too far on."""
    w, roll0, pitch0 = 0.5, 0.1, -0.05
    loop = AttitudeLoop(AttitudeControlConfig(identify=False, model_check=False), autopilot="px4")
    response = loop.predictor.response
    rate = np.zeros(3)
    rate[axis] = w
    for k in range(loop.history.capacity + 10):  # steady commands, one a tick, up to the sample
        loop.history.push(SAMPLE_S - (loop.history.capacity + 10 - k) * TICK_S,
                          rate / response.gain, valid=True)  # fmt: skip
    tracker = StateTracker(system_id=1)
    q = frames.euler_to_quat(roll0, pitch0, 0.0)
    t_ms = round(SAMPLE_S * 1e3)
    assert tracker.handle(att_q(t_ms, q, tuple(rate)), received_s=SAMPLE_S)
    assert tracker.handle(lpos(t_ms, (0.0, 0.0, -2.0), (0.0, 0.0, 0.0)), received_s=SAMPLE_S)
    now_s = SAMPLE_S + age_ms * 1e-3
    state = tracker.snapshot(now_s)
    assert state is not None
    assert state.attitude_age_s == pytest.approx(age_ms * 1e-3)
    x0 = predicted_start(loop, state, now_s)
    expected = np.array([roll0, pitch0])
    expected[axis] += w * (age_ms * 1e-3 + response.dead_time_s)
    np.testing.assert_allclose(x0[:2], expected, atol=2e-5)  # (pitch's Euler rate: cos roll)
    np.testing.assert_allclose(x0[3:], rate, atol=1e-9)


def test_a_state_not_carried_starts_where_its_sample_is() -> None:
    """A state whose attitude is the sample's own (``attitude_carried_s`` 0, as a caller that
    builds it directly gives) is not un-carried: the prediction starts from it."""
    loop = AttitudeLoop(AttitudeControlConfig(identify=False, model_check=False), autopilot="px4")
    tracker = StateTracker(system_id=1)
    q = frames.euler_to_quat(0.2, 0.0, 0.0)
    t_ms = round(SAMPLE_S * 1e3)
    tracker.handle(att_q(t_ms, q, (0.0, 0.0, 0.0)), received_s=SAMPLE_S)
    tracker.handle(lpos(t_ms, (0.0, 0.0, -2.0), (0.0, 0.0, 0.0)), received_s=SAMPLE_S)
    state = tracker.snapshot(SAMPLE_S)
    assert state is not None
    assert state.attitude_carried_s == 0.0
    x0 = predicted_start(loop, state, SAMPLE_S)
    assert x0[0] == pytest.approx(0.2, abs=1e-6)  # (float32 on the wire)
