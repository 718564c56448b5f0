"""Trajectories: start at the anchor at rest, derivatives consistent, shapes as specified."""

from __future__ import annotations

import math

import numpy as np
import pytest

from epc_offboard.control.trajectories import Trajectory, TrajectoryConfig

ANCHOR = np.array([1.0, -2.0, -2.5])
SHAPES = {
    "hover": TrajectoryConfig(shape="hover"),
    "line": TrajectoryConfig(shape="line", dx_m=3.0, dy_m=1.0, speed_m_s=1.5),
    "circle": TrajectoryConfig(shape="circle", radius_m=2.0, period_s=8.0),
    "figure8": TrajectoryConfig(shape="figure8", size_m=3.0, period_s=12.0),
    "figure8_vertical": TrajectoryConfig(
        shape="figure8_vertical", size_m=1.25, size_z_m=0.75, period_s=2 * math.pi
    ),
    "zigzag": TrajectoryConfig(
        shape="zigzag", amplitude_m=3.0, peak_speed_m_s=3.75, forward_speed_m_s=0.5
    ),
    "waypoints": TrajectoryConfig(
        shape="waypoints", waypoints_ned_m=((2.0, 0.0, 0.0), (2.0, 2.0, -1.0))
    ),
}


@pytest.mark.parametrize("name", SHAPES)
def test_starts_at_anchor_at_rest(name):
    tr = Trajectory(SHAPES[name], ANCHOR, start_s=5.0)
    for t in (0.0, 5.0):
        r = tr.sample(t)
        np.testing.assert_allclose(r.pos_ned_m, ANCHOR, atol=1e-12)
        np.testing.assert_allclose(r.vel_ned_m_s, 0.0, atol=1e-12)
        np.testing.assert_allclose(r.acc_ned_m_s2, 0.0, atol=1e-12)


@pytest.mark.parametrize("name", SHAPES)
def test_velocity_and_acceleration_are_the_derivatives(name):
    tr = Trajectory(SHAPES[name], ANCHOR)
    h = 1e-5
    for t in np.linspace(0.3, 20.0, 37):
        r, rp, rm = tr.sample(t), tr.sample(t + h), tr.sample(t - h)
        np.testing.assert_allclose(
            (rp.pos_ned_m - rm.pos_ned_m) / (2 * h), r.vel_ned_m_s, atol=1e-4
        )
        # every profile is C2 (jerk-limited speed profiles): no acceleration steps anywhere
        np.testing.assert_allclose(
            (rp.vel_ned_m_s - rm.vel_ned_m_s) / (2 * h), r.acc_ned_m_s2, atol=1e-3
        )


@pytest.mark.parametrize(
    ("distance_m", "v_peak"), [(10.0, 3.75), (3.0, math.sqrt(6.0 * 3.0 / 2.0))]
)
def test_speed_profile_is_jerk_limited_rest_to_rest(distance_m, v_peak):
    """Peak acceleration a_max, jerk at most pi a^2 / (2 v) with v the speed actually reached
    (lowered when the distance is too short): what a lagged vehicle can follow without the lag
    inversion spiking its command (see _trapezoid)."""
    from epc_offboard.control.trajectories import _trapezoid

    a_max = 6.0
    prof = _trapezoid(distance_m, 3.75, a_max)
    t_end = prof.duration_s  # type: ignore[attr-defined]
    ts = np.linspace(0.0, t_end + 0.5, 20001)
    x, v, a = np.array([prof(t) for t in ts]).T
    assert x[-1] == pytest.approx(distance_m)
    assert v[-1] == 0.0
    assert np.max(v) == pytest.approx(v_peak, rel=1e-6)
    assert np.max(np.abs(a)) == pytest.approx(a_max, rel=1e-3)
    jerk = np.abs(np.diff(a)) / np.diff(ts)
    assert np.max(jerk) <= math.pi * a_max**2 / (2 * v_peak) * 1.001
    np.testing.assert_allclose(np.gradient(x, ts), v, atol=2e-3)  # consistent x, v
    np.testing.assert_allclose(np.gradient(v, ts), a, atol=2e-2)


def test_circle_has_radius_and_speed_after_ramp():
    cfg = SHAPES["circle"]
    tr = Trajectory(cfg, ANCHOR)
    centre = ANCHOR + np.array([cfg.radius_m, 0.0, 0.0])
    speed = 2 * math.pi * cfg.radius_m / cfg.period_s
    for t in np.linspace(cfg.ramp_s, 30.0, 50):
        r = tr.sample(t)
        assert np.linalg.norm(r.pos_ned_m - centre) == pytest.approx(cfg.radius_m)
        assert np.linalg.norm(r.vel_ned_m_s) == pytest.approx(speed)
        assert r.pos_ned_m[2] == pytest.approx(ANCHOR[2])


def test_zigzag_peaks_at_its_speed_and_stays_in_amplitude():
    cfg = SHAPES["zigzag"]
    tr = Trajectory(cfg, ANCHOR)
    ts = np.arange(0.0, 30.0, 0.005)
    vy = np.array([tr.sample(t).vel_ned_m_s[1] for t in ts])
    y = np.array([tr.sample(t).pos_ned_m[1] for t in ts]) - ANCHOR[1]
    assert np.max(np.abs(vy)) == pytest.approx(cfg.peak_speed_m_s)
    assert vy.min() < -3.7
    assert np.max(np.abs(y)) == pytest.approx(cfg.amplitude_m, abs=1e-6)


def test_horizon_rows_are_future_samples():
    tr = Trajectory(SHAPES["figure8"], ANCHOR)
    refs = tr.horizon(3.0, 0.05, 20)
    assert refs.shape == (20, 9)  # [p, v, a]: the position model carries the acceleration
    np.testing.assert_allclose(refs[4, :3], tr.sample(3.25).pos_ned_m)
    np.testing.assert_allclose(refs[19, 3:6], tr.sample(4.0).vel_ned_m_s)
    np.testing.assert_allclose(refs[7, 6:], tr.sample(3.4).acc_ned_m_s2)


def test_config_rejects_bad_values():
    with pytest.raises(ValueError, match="radius_m"):
        TrajectoryConfig(shape="circle", radius_m=0.0)
    with pytest.raises(ValueError, match="waypoints_ned_m"):
        TrajectoryConfig(shape="waypoints")


@pytest.mark.parametrize("shape", ["circle", "figure8", "figure8_vertical", "zigzag", "hover"])
def test_the_tick_horizon_equals_sample_to_the_last_bit(shape):
    # (-0.0: the hover's rows are sample()'s anchor + 0.0, not the anchor's bits)
    traj = Trajectory(TrajectoryConfig(shape=shape, ramp_s=3.0, period_s=12.0, radius_m=1.5),
                      np.array([1.0, -0.0, -2.5]), start_s=6.0)
    for t0 in np.arange(0.0, 30.0, 0.37):  # before the start, in the ramp and after it
        rows = traj.horizon_from_now(t0, 0.05, 20)
        want = [traj.sample(t0 + k * 0.05) for k in range(21)]
        sampled = np.array([[*r.pos_ned_m, *r.vel_ned_m_s, *r.acc_ned_m_s2] for r in want])
        assert np.array_equal(rows, sampled)
        if shape == "hover":  # its own fast path: the same bits, signed zeros included
            assert rows.tobytes() == sampled.tobytes()
        assert np.array_equal(traj.horizon(t0, 0.05, 20), rows[1:])


@pytest.mark.parametrize("shape", ["circle", "figure8", "zigzag", "line"])
def test_the_reference_horizon_holds_the_old_rows_bit_for_bit(shape):
    """ReferenceHorizon round trip: what the tick receives is the (N, 9) rows it used to
    receive, its stage 0 the reference now, its columns the position, velocity and
    acceleration; a rejoin's gap is added to every stage."""
    from epc_offboard.control.trajectories import RefSample, Rejoin
    from epc_offboard.control.types import ReferenceHorizon

    traj = Trajectory(TrajectoryConfig(shape=shape, ramp_s=3.0, period_s=12.0),
                      np.array([1.0, 2.0, -2.5]), start_s=6.0)  # fmt: skip
    rejoin = Rejoin.onto(RefSample(np.zeros(3), np.zeros(3), np.zeros(3)),
                         np.array([0.5, -0.3, 0.2]), np.array([0.1, 0.0, 0.0]), 7.0, 1.0)
    for t0 in np.arange(0.0, 30.0, 0.37):
        rows = traj.horizon_from_now(t0, 0.05, 20)
        ref = traj.reference(t0, 0.05, 20, 0.25)
        assert ref.steps == 20
        assert np.array_equal(ref.ahead, traj.horizon(t0, 0.05, 20))
        assert np.array_equal(ref.stages, rows)
        assert np.array_equal(ref.pos_ned_m, rows[:, 0:3])
        assert np.array_equal(ref.vel_ned_m_s, rows[:, 3:6])
        assert np.array_equal(ref.acc_ned_m_s2, rows[:, 6:9])
        assert np.array_equal(ref.yaw_rad, np.full(21, 0.25))
        joined = traj.reference(t0, 0.05, 20, 0.25, rejoin)
        gap = rejoin.rows(t0 + 0.05 * np.arange(21, dtype=np.float64))
        assert np.array_equal(joined.stages, rows + gap)
    # the hold: the point at rest, at every stage
    hold = ReferenceHorizon.hold([1.0, 2.0, -3.0], 0.5, 4)
    assert np.array_equal(hold.ahead, np.tile([1.0, 2.0, -3.0, 0, 0, 0, 0, 0, 0], (4, 1)))
    assert np.array_equal(hold.stages[0], hold.stages[4])
    with pytest.raises(ValueError, match="reference horizon"):
        ReferenceHorizon(np.zeros((5, 6)), np.zeros(5))
    with pytest.raises(ValueError, match="reference horizon"):
        ReferenceHorizon(np.zeros((5, 9)), np.zeros(4))


def test_rejoin_starts_at_the_vehicle_and_closes_the_gap_smoothly():
    from epc_offboard.control.trajectories import RefSample, Rejoin

    traj = RefSample(np.array([3.0, -1.0, -2.5]), np.array([1.2, 0.0, 0.0]), np.zeros(3))
    pos, vel = np.array([0.0, 0.5, -2.0]), np.zeros(3)
    rj = Rejoin.onto(traj, pos, vel, t_s=10.0, tau_s=1.0)
    start = rj.rows([10.0])[0]
    # trajectory + gap = where the vehicle is, at the speed it has: no jump at all
    np.testing.assert_allclose(traj.pos_ned_m + start[:3], pos, atol=1e-12)
    np.testing.assert_allclose(traj.vel_ned_m_s + start[3:6], vel, atol=1e-12)
    # the derivatives are those of the gap (central differences)
    t = np.linspace(10.0, 16.0, 601)
    rows, h = rj.rows(t), t[1] - t[0]
    np.testing.assert_allclose(np.gradient(rows[:, 0:3], h, axis=0)[1:-1], rows[1:-1, 3:6],
                               atol=2e-3)  # fmt: skip
    np.testing.assert_allclose(np.gradient(rows[:, 3:6], h, axis=0)[1:-1], rows[1:-1, 6:9],
                               atol=2e-3)  # fmt: skip
    # critically damped: it closes without overshooting the trajectory on any axis
    gap0 = rj.gap_ned_m
    assert np.all(rows[:, 0:3] * np.sign(gap0) >= -1e-12)
    assert np.all(np.abs(rj.rows([25.0 + 1e-9])[0]) < 1e-4)
    assert rj.done(25.5)
    assert not rj.done(24.0)


def test_a_rejoin_asks_no_more_acceleration_than_its_budget():
    """A soak re-entered offboard at 1.3 m/s north while the circle ran 1.2 m/s south: the
    gap's fixed 1 s time constant asked for 5 m/s^2 at once, the entry ramp (rightly) would
    not command it, and the vehicle flew 3.9 m past the reference, then climbed 0.9 m."""
    from epc_offboard.control.trajectories import RefSample, Rejoin

    traj = RefSample(np.array([0.0, 0.0, -2.5]), np.array([-1.2, 0.9, 0.0]), np.zeros(3))
    fast = Rejoin.onto(traj, traj.pos_ned_m, np.array([1.33, 0.62, 0.0]), t_s=5.0, tau_s=1.0)
    assert fast.max_acc_m_s2() > 4.5  # the old ask: 2 |dv| / tau
    gentle = fast.within(1.25)
    assert gentle.max_acc_m_s2() <= 1.25
    assert gentle.tau_s > fast.tau_s
    t = 5.0 + np.linspace(0.0, 40.0, 4001)
    assert np.linalg.norm(gentle.rows(t)[:, 6:9], axis=1).max() <= 1.25 + 1e-9
    # still bumpless: it starts where the vehicle is, at its speed
    np.testing.assert_allclose(gentle.rows([5.0])[0][:6], fast.rows([5.0])[0][:6], atol=1e-12)
    # a gap that is gentle already keeps its time constant (never shortened), and a hopeless
    # one stops at the longest
    calm = Rejoin.onto(traj, traj.pos_ned_m + 0.05, traj.vel_ned_m_s, t_s=5.0, tau_s=1.0)
    assert calm.within(1.25) == calm
    assert fast.within(1e-6, max_tau_s=8.0).tau_s == 8.0


def test_vertical_figure8_is_neural_flys():
    """north = 1.25 sin t, up = 0.75 sin 2t after the ramp (which lags progress by ramp/2),
    east fixed; about 1.95 m/s at its fastest."""
    cfg = SHAPES["figure8_vertical"]
    tr = Trajectory(cfg, ANCHOR)
    lag_s = cfg.ramp_s / 2
    speeds = []
    for t in np.linspace(cfg.ramp_s, cfg.ramp_s + 2 * math.pi, 400):
        r = tr.sample(t)
        s = t - lag_s
        np.testing.assert_allclose(
            r.pos_ned_m - ANCHOR, [1.25 * math.sin(s), 0.0, -0.75 * math.sin(2 * s)], atol=1e-12
        )
        speeds.append(float(np.linalg.norm(r.vel_ned_m_s)))
    assert max(speeds) == pytest.approx(math.hypot(1.25, 1.5), abs=1e-3)
    assert max(speeds) == pytest.approx(1.95, abs=0.01)
