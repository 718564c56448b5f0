"""State decoding: validation, rejection by reason, ODOMETRY frames, forward prediction."""

from __future__ import annotations

import itertools
import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from pymavlink.dialects.v20 import common as mavlink

from epc_offboard.common import frames
from epc_offboard.vehicle.dialect_px4 import (
    PX4_AUTO_SUB_LOITER,
    PX4_MAIN_MODE_AUTO,
    PX4_MAIN_MODE_OFFBOARD,
    px4_custom_mode,
    px4_modes,
)
from epc_offboard.vehicle.offboard import Inputs, OffboardConfig, OffboardStateMachine, Phase
from epc_offboard.vehicle.state import StateTracker

MAV = mavlink.MAVLink(None, srcSystem=1, srcComponent=1)
OTHER = mavlink.MAVLink(None, srcSystem=7, srcComponent=1)


def decode(msg, mav=MAV):
    """Pack and decode, so the tracker sees exactly what the wire gives."""
    rx = mavlink.MAVLink(None)
    return rx.decode(bytearray(msg.pack(mav)))


def att_q(t_ms, q, rates=(0.0, 0.0, 0.0), mav=MAV):
    return decode(mav.attitude_quaternion_encode(t_ms, *q, *rates), mav)


def lpos(t_ms, pos, vel, mav=MAV):
    return decode(mav.local_position_ned_encode(t_ms, *pos, *vel), mav)


def test_px4_mode_encoding_matches_px4():
    # docs/DESIGN.md: Hold = AUTO.LOITER = 0x03040000
    assert px4_custom_mode(PX4_MAIN_MODE_AUTO, PX4_AUTO_SUB_LOITER) == 0x03040000
    assert px4_modes(0x03040000) == (4, 3)
    assert px4_modes(px4_custom_mode(6)) == (6, 0)


def test_snapshot_needs_both_samples_and_predicts_position_forward():
    tr = StateTracker(system_id=1)
    assert tr.snapshot() is None
    q = frames.euler_to_quat(0.1, -0.2, 0.3)
    assert tr.handle(att_q(1000, q, (0.1, 0.2, 0.3)))
    assert tr.snapshot() is None
    assert tr.handle(lpos(1000, (1.0, 2.0, -3.0), (1.0, 0.0, -0.5)))
    s = tr.snapshot(1.05)
    assert s is not None
    np.testing.assert_allclose(s.pos_ned_m, [1.05, 2.0, -3.025], atol=1e-6)
    # and the attitude rotated on by its body rates over the same 50 ms
    q_pred = frames.quat_integrate_body_rate(q, np.array([0.1, 0.2, 0.3]), 0.05)
    assert frames.angle_between_deg(s.q_ned_frd, q_pred) == pytest.approx(0.0, abs=1e-4)
    assert s.position_age_s == pytest.approx(0.05)
    # prediction is capped at max_predict_s
    s = tr.snapshot(2.0)
    assert s is not None
    np.testing.assert_allclose(s.pos_ned_m[0], 1.0 + tr.limits.max_predict_s, atol=1e-6)
    assert tr.age_s(2.0, vehicle_clock=True) == pytest.approx(1.0)


@pytest.mark.parametrize(
    ("msg", "reason"),
    [
        (lpos(10, (math.nan, 0.0, 0.0), (0.0, 0.0, 0.0)), "rejected_nan"),
        (lpos(10, (0.0, 0.0, 0.0), (0.0, math.inf, 0.0)), "rejected_nan"),
        (lpos(10, (2e4, 0.0, 0.0), (0.0, 0.0, 0.0)), "rejected_range"),
        (lpos(10, (0.0, 0.0, 0.0), (300.0, 0.0, 0.0)), "rejected_range"),
        (att_q(10, (0.5, 0.0, 0.0, 0.0)), "rejected_quaternion"),
        (att_q(10, (1.0, 0.0, 0.0, 0.0), (0.0, 0.0, math.nan)), "rejected_nan"),
        (att_q(10, (1.0, 0.0, 0.0, 0.0), (99.0, 0.0, 0.0)), "rejected_range"),
    ],
)
def test_bad_samples_are_rejected_and_keep_the_good_state(msg, reason):
    tr = StateTracker(system_id=1)
    tr.handle(att_q(5, (1.0, 0.0, 0.0, 0.0)))
    tr.handle(lpos(5, (1.0, 1.0, -1.0), (0.0, 0.0, 0.0)))
    before = tr.snapshot()
    assert not tr.handle(msg)
    assert tr.counters[reason] == 1
    after = tr.snapshot()
    assert before is not None
    assert after is not None
    np.testing.assert_array_equal(after.pos_ned_m, before.pos_ned_m)
    np.testing.assert_array_equal(after.q_ned_frd, before.q_ned_frd)


def test_out_of_order_and_foreign_samples_are_ignored():
    tr = StateTracker(system_id=1)
    assert tr.handle(lpos(100, (1.0, 0.0, 0.0), (0.0, 0.0, 0.0)))
    assert not tr.handle(lpos(50, (5.0, 0.0, 0.0), (0.0, 0.0, 0.0)))
    assert tr.counters["rejected_out_of_order"] == 1
    assert not tr.handle(lpos(200, (9.0, 0.0, 0.0), (0.0, 0.0, 0.0), mav=OTHER))
    assert tr.vehicle_time_s == pytest.approx(0.1)


def test_ms_truncated_and_us_stamps_of_one_instant_are_in_order():
    tr = StateTracker(system_id=1)
    q = frames.euler_to_quat(0.0, 0.0, 0.0)
    odo = MAV.odometry_encode(
        4_999,
        mavlink.MAV_FRAME_LOCAL_NED,
        mavlink.MAV_FRAME_BODY_FRD,
        0.0,
        0.0,
        -1.0,
        list(q),
        0.0,
        0.0,
        0.0,
        0.0,
        0.0,
        0.0,
        [math.nan] * 21,
        [math.nan] * 21,
        0,
        0,
        0,
    )
    assert tr.handle(decode(odo))
    assert tr.handle(att_q(4, q))  # 4 ms: the same instant, truncated
    assert tr.counters["rejected_out_of_order"] == 0


def test_odometry_body_velocity_is_rotated_to_ned():
    tr = StateTracker(system_id=1)
    yaw = math.pi / 2  # facing east: body forward = NED east
    q = frames.euler_to_quat(0.0, 0.0, yaw)
    msg = MAV.odometry_encode(
        2_000_000,
        mavlink.MAV_FRAME_LOCAL_NED,
        mavlink.MAV_FRAME_BODY_FRD,
        1.0,
        2.0,
        -3.0,
        list(q),
        2.0,
        0.0,
        0.0,
        0.0,
        0.0,
        0.1,
        [math.nan] * 21,
        [math.nan] * 21,
        0,
        0,
        0,
    )
    assert tr.handle(decode(msg))
    s = tr.snapshot()
    assert s is not None
    np.testing.assert_allclose(s.vel_ned_m_s, [0.0, 2.0, 0.0], atol=1e-6)
    np.testing.assert_allclose(s.rate_frd_rad_s, [0.0, 0.0, 0.1], atol=1e-6)
    assert s.time_s == pytest.approx(2.0)


def test_heartbeat_decodes_armed_and_mode():
    tr = StateTracker(system_id=1)
    hb = MAV.heartbeat_encode(
        mavlink.MAV_TYPE_QUADROTOR,
        mavlink.MAV_AUTOPILOT_PX4,
        mavlink.MAV_MODE_FLAG_SAFETY_ARMED | mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED,
        px4_custom_mode(6),
        mavlink.MAV_STATE_ACTIVE,
    )
    tr.handle(decode(hb))
    assert tr.heartbeat is not None
    assert tr.heartbeat.armed
    assert tr.heartbeat.main_mode == PX4_MAIN_MODE_OFFBOARD


# ---- timestamps from a hostile or rebooting autopilot (issue 16, 1; issue 11, 4) ----------

LEVEL = (1.0, 0.0, 0.0, 0.0)


def odometry(t_us, pos, mav=MAV):
    return decode(
        mav.odometry_encode(
            t_us,
            mavlink.MAV_FRAME_LOCAL_NED,
            mavlink.MAV_FRAME_BODY_FRD,
            *pos,
            list(LEVEL),
            0,
            0,
            0,
            0,
            0,
            0,
            [math.nan] + [0.0] * 20,
            [math.nan] + [0.0] * 20,
            0,
            0,
            0,
        ),
        mav,
    )


def genuine(tr: StateTracker, t_ms: int) -> bool:
    """One tick of genuine telemetry received at t_ms on the receive clock."""
    now = t_ms * 1e-3
    a = tr.handle(att_q(t_ms, LEVEL), received_s=now)
    p = tr.handle(lpos(t_ms, (0.0, 0.0, -2.0), (0.0, 0.0, 0.0)), received_s=now)
    return a and p


def test_one_spoofed_stamp_does_not_lock_out_telemetry():
    tr = StateTracker(system_id=1)
    for t in range(1000, 1100, 10):
        assert genuine(tr, t)
    spoof = lpos(0xFFFFFFF0, (50.0, 0.0, -2.0), (0.0, 0.0, 0.0))
    assert not tr.handle(spoof, received_s=1.1)
    assert tr.vehicle_time_s == pytest.approx(1.09)  # the spoof never became "now"
    for t in range(1100, 1300, 10):
        assert genuine(tr, t)  # every genuine sample after it is accepted
    assert tr.counters["rejected_time_jump"] == 1
    assert tr.counters["rejected_out_of_order"] == 0
    state = tr.snapshot()
    assert state is not None
    assert state.pos_ned_m[0] == 0.0


def test_an_autopilot_reboot_resynchronises_within_a_few_samples():
    tr = StateTracker(system_id=1)
    for t in range(600_000, 600_100, 10):  # ten minutes of uptime
        assert genuine(tr, t)
    # the autopilot reboots: time_boot_ms restarts near 0 while our clock runs on
    accepted_at = None
    for k in range(20):
        t_ms = 10 * k
        now = 600.1 + 0.01 * k
        ok = tr.handle(att_q(t_ms, LEVEL), received_s=now)
        tr.handle(lpos(t_ms, (0.0, 0.0, -2.0), (0.0, 0.0, 0.0)), received_s=now)
        if ok and accepted_at is None:
            accepted_at = k
    assert accepted_at is not None
    assert accepted_at < tr.limits.resync_samples
    assert tr.counters["time_resyncs"] >= 1
    assert tr.vehicle_time_s == pytest.approx(0.19)
    assert tr.snapshot() is not None


def test_px4_odometry_trailing_attitude_is_not_out_of_order():
    """PX4's ODOMETRY carries the estimator's sample time, a few ms behind ATTITUDE's."""
    tr = StateTracker(system_id=1)
    for t in range(1000, 1200, 10):
        now = t * 1e-3
        assert tr.handle(att_q(t, LEVEL), received_s=now)
        assert tr.handle(lpos(t, (1.0, 0.0, -2.0), (0.0, 0.0, 0.0)), received_s=now)
        # the trailing sample is valid, but older than what LOCAL_POSITION_NED gave
        assert not tr.handle(odometry((t - 5) * 1000, (9.0, 0.0, -2.0)), received_s=now)
    assert tr.counters["rejected_out_of_order"] == 0
    state = tr.snapshot()
    assert state is not None
    assert state.pos_ned_m[0] == 1.0  # never replaced by the older sample


@pytest.mark.parametrize("seed", range(20))
def test_no_sequence_of_spoofed_stamps_locks_out_a_steady_stream(seed):
    """Property: spoofed samples at random stamps, interleaved with a genuine 100 Hz stream,
    never keep genuine samples out for longer than the resyncs allow: the timeline's, and
    when a spoof was the first sample of all, the innovation gate's (each resync_samples)."""
    rng = np.random.default_rng(seed)
    tr = StateTracker(system_id=1)
    longest_out = out = 0
    for k in range(400):
        t_ms = 5000 + 10 * k
        now = t_ms * 1e-3
        if rng.random() < 0.3:
            for _ in range(int(rng.integers(1, 4))):
                bad = (0, 0xFFFFFFF0, int(rng.integers(0, 2**32 - 1)))[int(rng.integers(0, 3))]
                tr.handle(lpos(bad, (99.0, 0.0, 0.0), (0.0, 0.0, 0.0)), received_s=now)
        ok = tr.handle(lpos(t_ms, (0.0, 0.0, -2.0), (0.0, 0.0, 0.0)), received_s=now)
        out = 0 if ok else out + 1
        longest_out = max(longest_out, out)
    assert longest_out <= 2 * tr.limits.resync_samples
    assert tr.handle(lpos(5000 + 10 * 400, (0.0, 0.0, -2.0), (0.0, 0.0, 0.0)), received_s=9.0)


@pytest.mark.parametrize("roll", [math.nan, math.inf, 1e30])
def test_a_bad_attitude_is_rejected_before_it_is_converted(roll):
    tr = StateTracker(system_id=1)
    bad = decode(MAV.attitude_encode(1000, roll, 0.0, 0.0, 0.0, 0.0, 0.0))
    assert not tr.handle(bad)  # no exception from the conversion
    assert tr.counters["rejected_nan"] + tr.counters["rejected_range"] == 1


# ---- forged heartbeats (issue 16, 4) -------------------------------------------------------

QUAD, PX4 = mavlink.MAV_TYPE_QUADROTOR, mavlink.MAV_AUTOPILOT_PX4
OFFBOARD_ARMED = (True, 6, 0)  # (armed, PX4 main mode, sub mode)
LOITER_ARMED = (True, 4, 3)
POSCTL_ARMED = (True, 3, 0)
POSCTL_DISARMED = (False, 3, 0)


def heartbeat(mode=OFFBOARD_ARMED, *, comp=1, mav_type=QUAD, autopilot=PX4, base=None, custom=None):
    armed, main, sub = mode
    if base is None:
        base = mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED | (
            mavlink.MAV_MODE_FLAG_SAFETY_ARMED if armed else 0
        )
    mav = mavlink.MAVLink(None, srcSystem=1, srcComponent=comp)
    custom = px4_custom_mode(main, sub) if custom is None else custom
    return decode(mav.heartbeat_encode(mav_type, autopilot, base, custom, 4), mav)


def forged_elsewhere(rng) -> object:
    """A heartbeat from the vehicle's system id with random enums, that is not the
    autopilot's: another component, or component 1 with a type or autopilot no flight
    controller sends (GCS, onboard controller, gimbal..., MAV_AUTOPILOT_INVALID, garbage)."""
    base, custom = int(rng.integers(0, 256)), int(rng.integers(0, 2**32))
    mav_type, autopilot = int(rng.integers(0, 256)), int(rng.integers(0, 256))
    how = int(rng.integers(0, 3))
    if how == 0:  # another component, anything at all
        comp = int(rng.integers(2, 256))
    elif how == 1:  # the autopilot's component, a type that is no flight controller
        comp, mav_type = 1, int(rng.choice([6, 18, 26, 30, 42, 49, 200, 255]))
    else:  # the autopilot's component, MAV_AUTOPILOT_INVALID
        comp, autopilot = 1, mavlink.MAV_AUTOPILOT_INVALID
    return heartbeat(comp=comp, mav_type=mav_type, autopilot=autopilot, base=base, custom=custom)


def fly(genuine_modes, forged, *, steps_per_s=20):
    """Genuine heartbeats at 1 Hz carrying ``genuine_modes[s]`` at second s, the ``forged``
    (time_s, message) between them, the state machine stepped at 20 Hz on fresh state in
    the air; returns the tracker and the phase at every step."""
    tr = StateTracker(system_id=1)
    sm = OffboardStateMachine(OffboardConfig())
    forged = sorted(forged, key=lambda e: e[0])
    phases = []
    for k in range(len(genuine_modes) * steps_per_s):
        t = k / steps_per_s
        if k % steps_per_s == 0:
            tr.handle(heartbeat(genuine_modes[k // steps_per_s]), received_s=t)
        while forged and forged[0][0] <= t:
            tr.handle(forged.pop(0)[1], received_s=t)
        out = sm.step(
            Inputs(t, tr.heartbeat, 0.01, pos_down_m=-2.5, relative_alt_m=2.5, amsl_m=490.0)
        )
        phases.append(out.phase)
    return tr, phases


@pytest.mark.parametrize("seed", range(5))
def test_heartbeats_of_other_components_and_kinds_do_not_change_the_phase(seed):
    rng = np.random.default_rng(seed)
    forged = [(0.05 + 0.1 * k, forged_elsewhere(rng)) for k in range(300)]  # 10 Hz
    tr, phases = fly([OFFBOARD_ARMED] * 30, forged)
    assert set(phases[phases.index(Phase.OFFBOARD) :]) == {Phase.OFFBOARD}
    assert tr.heartbeat is not None
    assert (tr.heartbeat.armed, tr.heartbeat.main_mode) == (True, 6)
    assert tr.counters["heartbeat_ignored"] > 0


@settings(max_examples=40, deadline=None)
@given(
    modes=st.lists(
        st.sampled_from([OFFBOARD_ARMED, LOITER_ARMED, POSCTL_ARMED, POSCTL_DISARMED]),
        min_size=3,
        max_size=25,
    ),
    times=st.lists(st.floats(0.0, 25.0), max_size=120),
    seed=st.integers(0, 2**32 - 1),
)
def test_forged_heartbeats_interleaved_with_genuine_ones_never_flap_the_phase(modes, times, seed):
    """Property: whatever the genuine autopilot does, heartbeats that are not its own,
    at random moments, leave the phase exactly as it is without them."""
    rng = np.random.default_rng(seed)
    _, clean = fly(modes, [])
    _, attacked = fly(modes, [(t, forged_elsewhere(rng)) for t in times])
    assert attacked == clean


def test_forged_autopilot_heartbeats_flap_the_phase_at_most_once():
    """Forged heartbeats even from the autopilot's own component and kind (without signing
    they cannot be told apart): a calm link adopts a genuine change at once; once a change
    is undone within a heartbeat, changes need confirming, so a 3 Hz forger among the 1 Hz
    genuine heartbeats flips the phase once and back, not on every forgery."""
    rng = np.random.default_rng(16)
    modes = [LOITER_ARMED] * 3 + [OFFBOARD_ARMED] * 57
    forged = [
        (10.2 + k / 3, heartbeat((bool(rng.integers(0, 2)), int(rng.integers(0, 8)), 0)))
        for k in range(90)  # 30 s at 3 Hz
    ]
    tr, phases = fly(modes, forged)
    steps = 20
    assert phases[3 * steps] == Phase.OFFBOARD  # the genuine change: adopted at once
    during = phases[10 * steps : 45 * steps]
    assert sum(a != b for a, b in itertools.pairwise(during)) <= 2
    assert set(phases[45 * steps :]) == {Phase.OFFBOARD}
    assert tr.counters["heartbeat_flaps"] >= 1
    assert tr.counters["heartbeat_changes_held"] >= 1
