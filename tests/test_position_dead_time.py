"""The position loop's command dead time (control/dead_time.py): the prediction over the dead
time against a fine integration of the lagged model, the shifted reference window, and the
position tick flying it (the QP starts from the predicted state)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from epc_offboard.control.dead_time import DeadTimePredictor, default_command_dead_time_s
from epc_offboard.control.perturbation import EstimatorConfig
from epc_offboard.control.position import PositionControlConfig, PositionLoop
from epc_offboard.control.types import ReferenceHorizon, VehicleState

TAU = (0.12, 0.12, 0.03)


def shifted_stages(stages, lead_stages, steps):
    """The oracle for DeadTimePredictor.window: rows ``lead + 1 .. lead + steps`` of
    ``stages``, linear between two stages, the last held, computed afresh each call."""
    if lead_stages <= 0.0:
        return stages[1 : steps + 1]
    whole = round(lead_stages)
    base = whole if abs(lead_stages - whole) < 1e-9 else math.floor(lead_stages)
    frac = max(lead_stages - base, 0.0)
    last = stages.shape[0] - 1
    idx = np.minimum(np.arange(base + 1, base + 1 + steps), last)
    lo = stages[idx]
    if frac < 1e-9:
        return lo
    return lo + frac * (stages[np.minimum(idx + 1, last)] - lo)


def window(stages, lead_stages, steps):
    """DeadTimePredictor.window at a dead time of ``lead_stages`` steps of 0.05 s (on a
    0.005 s tick, so that half steps are whole ticks)."""
    return DeadTimePredictor(TAU, 0.005, lead_stages * 0.05).window(stages, 0.05, steps)


def integrate(x0, commands, d, period_s, tau, substeps=2000):
    """p' = v, v' = a + d, a' = (u - a) / tau: each command held one period, fine Euler."""
    p, v, a = (np.array(x0[i : i + 3], dtype=float) for i in (0, 3, 6))
    tau = np.array(tau)
    h = period_s / substeps
    for u in commands:
        for _ in range(substeps):
            p, v, a = p + h * v, v + h * (a + d), a + h * (np.asarray(u) - a) / tau
    return np.concatenate([p, v, a])


def ahead_and_integrated(pred, rng):
    """(the prediction, a fine integration, x0) from a random x0 over ``pred.steps`` random
    commands sent one a tick, under a constant disturbance."""
    period, n = pred.period_s, pred.steps
    commands = rng.normal(0.0, 2.0, (n, 3))
    for k, u in enumerate(commands):
        pred.sent(k * period, u)
    x0 = rng.normal(0.0, 1.0, 9)
    d = rng.normal(0.0, 0.3, 3)
    return pred.ahead(x0, d, n * period), integrate(x0, commands, d, period, TAU), x0


def test_the_prediction_is_the_model_driven_by_the_commands_in_flight():
    period = 0.01
    pred = DeadTimePredictor(TAU, period, 0.15)
    assert pred.steps == 15
    got, want, x0 = ahead_and_integrated(pred, np.random.default_rng(3))
    np.testing.assert_allclose(got, want, atol=2e-3)
    # without the commands in flight (a model with no dead time) it is far off
    assert np.max(np.abs(x0 - want)) > 0.1


def test_ticks_without_a_command_in_flight_keep_the_acceleration_flown():
    """At an entry (and after a gap of more than three ticks) nothing of ours is in
    flight: the acceleration flown now is held over the dead time."""
    period = 0.01
    pred = DeadTimePredictor(TAU, period, 0.05)
    pred.sent(0.0, np.array([5.0, 5.0, 5.0]))  # long before: not in flight
    x0 = np.array([0.0, 0.0, -2.0, 1.0, 0.0, 0.0, 0.5, -0.2, 0.1])
    got = pred.ahead(x0, np.zeros(3), 1.0)
    want = integrate(x0, [x0[6:9]] * 5, np.zeros(3), period, TAU)
    np.testing.assert_allclose(got, want, atol=1e-3)


def test_no_dead_time_is_the_state_itself():
    pred = DeadTimePredictor(TAU, 0.01, 0.0)
    x0 = np.arange(9.0)
    assert pred.ahead(x0, np.ones(3), 1.0) is x0


def test_the_window_starts_at_the_dead_time():
    stages = np.arange(24.0)[:, None] * np.ones((1, 9))  # stage k holds k
    np.testing.assert_array_equal(window(stages, 0.0, 20)[:, 0], np.arange(1.0, 21.0))
    np.testing.assert_array_equal(window(stages, 3.0, 20)[:, 0], np.arange(4.0, 24.0))
    np.testing.assert_allclose(window(stages, 2.5, 20)[:, 0], np.arange(3.5, 23.5))
    short = window(stages[:21], 3.0, 20)[:, 0]  # a horizon without the lead: held
    assert short[-1] == 20.0
    assert short[0] == 4.0


def test_a_state_latency_carries_the_state_but_does_not_shift_the_reference():
    """A state 20 ms old on arrival (its stamp says now) and a 30 ms command dead time: x0
    is carried over both, 50 ms of commands, but the plan's window starts at the dead time
    alone. A dead time of 50 ms in its place shifted the reference by the latency too, and
    the vehicle led the reference by it (Neural-Fly's plant: 15 ms, 2 cm at 1.3 m/s)."""
    period = 0.01
    pred = DeadTimePredictor(TAU, period, 0.03, latency_s=0.02)
    assert pred.steps == 5
    assert pred.dead_time_s == pytest.approx(0.03)
    got, want, _ = ahead_and_integrated(pred, np.random.default_rng(5))
    np.testing.assert_allclose(got, want, atol=2e-3)
    stages = np.arange(24.0)[:, None] * np.ones((1, 9))
    window = pred.window(stages.copy(), 0.05, 20)[:, 0]  # 30 ms of 50 ms stages: 0.6
    np.testing.assert_allclose(window, np.arange(1.6, 21.6))
    # latency alone: the window is the reference's own
    only = DeadTimePredictor(TAU, period, 0.0, latency_s=0.015)
    assert only.steps == 2
    assert only.dead_time_s == 0.0
    np.testing.assert_array_equal(only.window(stages, 0.05, 20)[:, 0], np.arange(1.0, 21.0))


@pytest.mark.parametrize(("dead_time_s", "latency_s"), [(0.0, 0.015), (0.05, 0.013)])
def test_a_span_between_ticks_is_carried_exactly(dead_time_s, latency_s):
    """15 ms of state latency on 10 ms ticks (Neural-Fly's plant's telemetry delay) is the
    oldest command in flight over the last 5 ms of its tick, then the newest over one whole
    tick: rounded to two ticks, the state was carried 5 ms too far."""
    period = 0.01
    pred = DeadTimePredictor(TAU, period, dead_time_s, latency_s=latency_s)
    span = (dead_time_s + latency_s) / period
    n = math.ceil(span)
    assert pred.steps == n
    rng = np.random.default_rng(7)
    commands = rng.normal(0.0, 2.0, (n, 3))
    for k, u in enumerate(commands):
        pred.sent(k * period, u)
    x0 = rng.normal(0.0, 1.0, 9)
    d = rng.normal(0.0, 0.3, 3)
    got = pred.ahead(x0, d, n * period)
    first = integrate(x0, commands[:1], d, (span - (n - 1)) * period, TAU)
    want = integrate(first, commands[1:], d, period, TAU)
    np.testing.assert_allclose(got, want, atol=2e-3)
    assert np.max(np.abs(integrate(x0, commands, d, period, TAU) - want)) > 5e-3


def test_the_loop_flies_the_configured_state_latency():
    cfg = PositionControlConfig(command_dead_time_s=None, state_latency_s=0.015)
    loop = PositionLoop(cfg, EstimatorConfig(kind="none"), 0.01)
    loop.use_attitude_path("px4", "epc")
    assert loop.dead_time.steps == 7
    assert loop.dead_time.dead_time_s == pytest.approx(0.05)
    with pytest.raises(ValueError, match="state_latency_s"):
        PositionControlConfig(state_latency_s=-0.01)


def test_defaults_per_autopilot_and_mode():
    assert default_command_dead_time_s("px4", "autopilot") == pytest.approx(0.15)
    assert default_command_dead_time_s("px4", "epc") == pytest.approx(0.05)
    assert default_command_dead_time_s("ardupilot", "autopilot") == pytest.approx(0.2)
    assert default_command_dead_time_s("auto", "autopilot") == pytest.approx(0.15)


@pytest.mark.parametrize("bad", [-0.01, 0.6, math.nan])
def test_a_dead_time_out_of_range_is_refused(bad):
    with pytest.raises(ValueError, match="command_dead_time_s"):
        PositionControlConfig(command_dead_time_s=bad)


def test_the_reference_carries_the_window_past_the_dead_time():
    assert PositionControlConfig(command_dead_time_s=0.0).reference_steps == 20
    assert PositionControlConfig(command_dead_time_s=0.15).reference_steps == 23
    assert PositionControlConfig(command_dead_time_s=0.12).reference_steps == 23
    assert PositionControlConfig().reference_steps == 24  # the longest default: 0.2 s


def _state(t_s, vel):
    return VehicleState(
        time_s=t_s, pos_ned_m=np.array([0.0, 0.0, -2.5]), vel_ned_m_s=np.array(vel),
        q_ned_frd=np.array([1.0, 0.0, 0.0, 0.0]), rate_frd_rad_s=np.zeros(3),
        position_age_s=0.0, attitude_age_s=0.0,
    )  # fmt: skip


def test_a_moving_vehicle_is_braked_from_where_it_will_be():
    """The vehicle moves at 1 m/s towards a hold: with the dead time the QP starts 0.15 s
    further on, so it commands harder braking than one that believes the vehicle is here."""
    free = {"controller": "mpc", "entry_jerk_m_s3": 1e6, "entry_max_acc_m_s2": 100.0,
            "max_jerk_m_s3": 0.0}  # no bound that would clip both commands alike
    cfg = PositionControlConfig(**free, command_dead_time_s=0.15)  # type: ignore[arg-type]
    est = EstimatorConfig(kind="none")
    without = PositionLoop(
        PositionControlConfig(**free, command_dead_time_s=0.0), est  # type: ignore[arg-type]
    )
    with_dead = PositionLoop(cfg, est)
    with_dead.use_attitude_path("px4", "autopilot")
    assert with_dead.dead_time.steps == 15
    ref = ReferenceHorizon.hold(np.array([0.0, 0.0, -2.5]), 0.0, cfg.reference_steps)
    a0 = without.position_tick(_state(0.0, [1.0, 0.0, 0.0]), ref).acc_cmd_ned_m_s2
    a1 = with_dead.position_tick(_state(0.0, [1.0, 0.0, 0.0]), ref).acc_cmd_ned_m_s2
    assert a1[0] < a0[0] < 0.0


@pytest.mark.slow
@pytest.mark.timeout(400)
def test_the_quaternion_circle_on_px4_flies_within_its_target(tmp_path):
    """Lockstep (deterministic), the PX4 personality that answers a quaternion setpoint
    0.275 s later as PX4 main + SIH did: issue 20's circle target (<= 5 cm RMSE). Without
    the command dead time the position EPC flew it at 6.32 cm (seed 0)."""
    from epc_offboard.tools.bench_modes import SPECS, fly

    result = fly(SPECS["circle"], "autopilot", "lockstep", "px4", tmp_path, seed=0)
    assert result["exit_code"] == 0, result
    assert result["flips"] == 0
    assert result["rmse_m"] <= 0.05


def test_a_prediction_leaves_the_commands_in_flight_as_they_were_sent():
    """``ahead`` fills the ticks without a command in flight with the acceleration flown now
    in a copy: the ring keeps what was sent (a prediction is no write)."""
    predictor = DeadTimePredictor((0.12, 0.12, 0.03), 0.01, 0.05)
    predictor.sent(1.0, np.array([1.0, 2.0, 3.0]))
    ring = predictor._sent.copy()
    x0 = np.arange(9.0)
    first = predictor.ahead(x0, np.zeros(3), 1.01)
    assert predictor._sent.tobytes() == ring.tobytes()
    np.testing.assert_array_equal(predictor.ahead(x0, np.zeros(3), 1.01), first)


def test_the_window_is_shifted_stages_to_the_last_bit():
    rng = np.random.default_rng(3)
    stages = rng.normal(size=(25, 9))
    for dead_s in (0.0, 0.1, 0.15, 0.2, 0.25, 0.33):
        predictor = DeadTimePredictor((0.12, 0.12, 0.03), 0.01, dead_s)
        for _ in range(2):  # the indices computed, then reused
            window = predictor.window(stages, 0.05, 20)
            want = shifted_stages(stages, predictor.dead_time_s / 0.05, 20)
            assert window.tobytes() == want.tobytes()

