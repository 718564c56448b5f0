"""The flap guard never fires on a genuine autopilot's heartbeats (issue 20), and still
catches a forged heartbeat between two genuine ones.

Genuine: PX4 sends a heartbeat every second and shows a mode change only on it (a takeoff
mode may show on a single heartbeat); ArduPilot sends one every second AND one at once on
every mode change. Both arrive late by a jitter, in order (one link). Forged: a heartbeat
from the autopilot's own ids between two genuine ones.
"""

from __future__ import annotations

from dataclasses import dataclass

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from pymavlink.dialects.v20 import common as mavlink

from epc_offboard.vehicle.dialect_px4 import px4_custom_mode
from epc_offboard.vehicle.state import StateTracker
from tests.test_state import heartbeat

APM = mavlink.MAV_AUTOPILOT_ARDUPILOTMEGA
PX4 = mavlink.MAV_AUTOPILOT_PX4
PERIOD_S = 1.0
# (armed, custom_mode): PX4's LOITER / TAKEOFF / OFFBOARD / LAND / POSCTL, ArduCopter's
# STABILIZE 0, GUIDED 4, LOITER 5, LAND 9, BRAKE 17
PX4_MODES = [px4_custom_mode(4, 3), px4_custom_mode(4, 2), px4_custom_mode(6),
             px4_custom_mode(4, 6), px4_custom_mode(3)]  # fmt: skip
APM_MODES = [0, 4, 5, 9, 17]


@dataclass(frozen=True)
class Beat:
    sent_s: float
    armed: bool
    custom: int
    extra: bool = False  # ArduPilot's immediate heartbeat on a mode change


def message(beat: Beat, autopilot: int):
    return heartbeat((beat.armed, 0, 0), autopilot=autopilot, custom=beat.custom)


def genuine_beats(changes, seconds: int, *, ardupilot: bool) -> list[Beat]:
    """Regular heartbeats at every whole second with the mode then; with ``ardupilot`` one
    more at each change of custom mode (arming alone: on the schedule only).
    ``changes``: (time_s, armed, custom) sorted by time, the mode from then on."""
    beats = []
    mode = (False, changes[0][2] if changes else 0)
    pending = list(changes)
    for k in range(seconds):
        while pending and pending[0][0] <= k:
            t, armed, custom = pending.pop(0)
            if ardupilot and custom != mode[1] and t > 0.0:
                beats.append(Beat(t, armed, custom, extra=True))
            mode = (armed, custom)
        beats.append(Beat(float(k), *mode))
    return sorted(beats, key=lambda b: b.sent_s)


def deliver(beats: list[Beat], latencies: list[float]) -> list[tuple[float, Beat]]:
    """Arrival times on one link: each late by its latency, never overtaking another."""
    out, last = [], 0.0
    for i, beat in enumerate(beats):
        last = max(last, beat.sent_s + latencies[i % len(latencies)])
        out.append((last, beat))
    return out


def feed(tracker: StateTracker, arrivals, autopilot: int) -> list[tuple[bool, int]]:
    """Feed the heartbeats; the (armed, custom_mode) held after each."""
    held = []
    for t, beat in arrivals:
        tracker.handle(message(beat, autopilot), received_s=t)
        hb = tracker.heartbeat
        assert hb is not None
        held.append((hb.armed, hb.custom_mode))
    return held


MIN_CHANGE_SPACING_S = 0.7  # no autopilot changes its mode twice within a period less jitter


def spaced(changes):
    """Mode changes at least MIN_CHANGE_SPACING_S apart (later ones too close dropped)."""
    out: list[tuple[float, bool, int]] = []
    for c in sorted(changes):
        if not out or c[0] - out[-1][0] >= MIN_CHANGE_SPACING_S:
            out.append(c)
    return out


change_lists = st.lists(
    st.tuples(st.floats(0.0, 29.0), st.booleans(), st.integers(0, 4)), min_size=1, max_size=25
).map(spaced)


@settings(max_examples=150, deadline=None)
@given(
    changes=change_lists,
    latencies=st.lists(st.floats(0.0, 0.3), min_size=1, max_size=40),
    ardupilot=st.booleans(),
)
def test_genuine_heartbeats_never_flap_and_every_change_is_believed_at_once(
    changes, latencies, ardupilot
):
    """Property, both personalities, mode and arming changes at any phase (commanded by
    the service or not, held for one heartbeat or reverted at once), heartbeats late by up
    to 0.3 s: no flap, and the mode held is always the one the last heartbeat said."""
    modes = APM_MODES if ardupilot else PX4_MODES
    timed = sorted((t, armed, modes[m]) for t, armed, m in changes)
    beats = genuine_beats(timed, 30, ardupilot=ardupilot)
    tracker = StateTracker(system_id=1)
    held = feed(tracker, deliver(beats, latencies), APM if ardupilot else PX4)
    assert tracker.counters["heartbeat_flaps"] == 0
    assert tracker.counters["heartbeat_changes_held"] == 0
    assert held == [(b.armed, b.custom) for b in beats]


@settings(max_examples=150, deadline=None)
@given(
    changes=change_lists,
    latency_s=st.floats(0.0, 0.1),
    second=st.integers(2, 27),
    after_s=st.floats(0.02, 0.68),
    forged_mode=st.integers(0, 4),
    forged_armed=st.booleans(),
    ardupilot=st.booleans(),
)
def test_a_forged_heartbeat_between_two_genuine_ones_is_a_flap(
    changes, latency_s, second, after_s, forged_mode, forged_armed, ardupilot
):
    """Property: A, forged B, A within a heartbeat period (B inside the period less the
    jitter, where no genuine heartbeat is due) is caught, whatever the genuine autopilot
    was doing before and after, as long as the vehicle itself does not change its mode
    around the forgery (a period before, two after: the flap is judged on the heartbeat
    after the second A)."""
    modes = APM_MODES if ardupilot else PX4_MODES
    timed = sorted((t, armed, modes[m]) for t, armed, m in changes)
    quiet = [c for c in timed if not second - 1.0 <= c[0] <= second + 2.0]
    beats = genuine_beats(quiet, 30, ardupilot=ardupilot)
    arrivals = deliver(beats, [latency_s])
    genuine_at = next(t for t, b in arrivals if b.sent_s == float(second) and not b.extra)
    mode_then = next((b.armed, b.custom) for t, b in arrivals if t == genuine_at)
    forged = (forged_armed, modes[forged_mode])
    if forged == mode_then:
        return  # (a heartbeat that says what the vehicle says changes nothing)
    fake = (genuine_at + after_s, Beat(-1.0, *forged))
    arrivals = sorted([*arrivals, fake], key=lambda a: a[0])
    tracker = StateTracker(system_id=1)
    feed(tracker, arrivals, APM if ardupilot else PX4)
    assert tracker.counters["heartbeat_flaps"] >= 1


def test_px4_takeoff_shown_on_one_heartbeat_is_not_a_flap():
    """What every healthy PX4 flight logged as forgery (epc-offboard sim --gcs-port 0, the
    session's tlog): LOITER, TAKEOFF on a single heartbeat, LOITER again, at 1 Hz. The old
    guard read a change undone within 1.5 s as a forged heartbeat."""
    loiter, takeoff, offboard = px4_custom_mode(4, 3), px4_custom_mode(4, 2), px4_custom_mode(6)
    seq = [(False, loiter), (False, loiter), (True, loiter), (True, takeoff), (True, loiter),
           (True, offboard), (True, offboard)]  # fmt: skip
    tracker = StateTracker(system_id=1)
    arrivals = [(0.995 + k, Beat(float(k), *m)) for k, m in enumerate(seq)]
    assert feed(tracker, arrivals, PX4) == seq
    assert tracker.counters["heartbeat_flaps"] == 0


@pytest.mark.parametrize("gap_s", [0.05, 0.3, 0.6])
def test_ardupilot_immediate_heartbeat_on_a_mode_change_is_believed_at_once(gap_s):
    """ArduCopter sends a HEARTBEAT at once on every mode change: the old guard called one
    less than 0.5 s after the last a forgery, then believed every change 1 s late for 10 s
    (ARM and LAND sent 2-3 times, takeoff 2.2 s late)."""
    tracker = StateTracker(system_id=1)
    stabilize, guided, land = (False, 0), (False, 4), (True, 9)
    arrivals = [
        (0.0, Beat(0.0, *stabilize)),
        (1.0, Beat(1.0, *stabilize)),
        (1.0 + gap_s, Beat(1.0 + gap_s, *guided, extra=True)),  # set GUIDED
        (2.0, Beat(2.0, True, 4)),  # armed (no extra for arming)
        (2.0 + gap_s, Beat(2.0 + gap_s, *land, extra=True)),  # LAND
        (3.0, Beat(3.0, *land)),
    ]
    assert feed(tracker, arrivals, APM) == [(b.armed, b.custom) for _, b in arrivals]
    assert tracker.counters["heartbeat_flaps"] == 0
    assert tracker.counters["heartbeat_changes_held"] == 0


def test_heartbeats_on_a_clock_that_stands_still_are_no_flood():
    """Lockstep: vehicle time stands at 0 until state streams, and the ArduPilot
    personality, streaming nothing until asked, repeats its heartbeat meanwhile (with
    sitl-timing's immediate heartbeat, a sim flight warned of forgery at start)."""
    tracker = StateTracker(system_id=1)
    beats = [Beat(0.0, False, 0)] * 4 + [Beat(0.0, False, 4, extra=True)]
    arrivals = [(0.0, b) for b in beats] + [(0.995 + k, Beat(1.0 + k, False, 4)) for k in range(3)]
    feed(tracker, arrivals, APM)
    assert tracker.counters["heartbeat_flaps"] == 0


def test_a_flood_of_forged_heartbeats_is_a_flap():
    tracker = StateTracker(system_id=1)
    arrivals = [(0.0, Beat(0.0, True, 4)), (1.0, Beat(1.0, True, 4))]
    arrivals += [(1.1 + 0.15 * k, Beat(-1.0, k % 2 == 0, 9)) for k in range(4)]
    feed(tracker, arrivals, APM)
    assert tracker.counters["heartbeat_flaps"] >= 1


def test_a_change_and_back_we_commanded_within_a_period_is_no_flap():
    """PX4 armed in LOITER (A); we ask OFFBOARD, accepted, and the heartbeat we ask for after
    the ack shows it (B); our state goes stale, streaming stops, and the vehicle is back in
    LOITER by its next regular heartbeat: A, B, A within a period, every change the
    vehicle's own at our asking (test_coldstart_e2e beside four hogs, load 9-12: one flap,
    'forged heartbeats?' warned, mode changes held back for 10 s). Told of the accepted
    command, the tracker sees no flap; a forged B a few periods later is still one."""
    loiter, offboard = (True, PX4_MODES[0]), (True, PX4_MODES[2])
    arrivals = [(0.0, loiter), (0.35, offboard), (1.0, loiter), (2.0, loiter), (3.0, loiter)]
    forged = [(3.4, offboard), (4.0, loiter), (5.0, loiter)]

    def flaps(told: bool, beats: list) -> int:
        tracker = StateTracker(system_id=1)
        for t, (armed, custom) in beats:
            if told and t == 0.35:
                tracker.change_commanded(0.25)  # OFFBOARD's COMMAND_ACK, before it shows
            tracker.handle(message(Beat(t, armed, custom), PX4), received_s=t)
        return tracker.counters["heartbeat_flaps"]

    assert flaps(False, arrivals) == 1  # untold: the guard's premise (one change a period)
    assert flaps(True, arrivals) == 0
    assert flaps(True, arrivals + forged) == 1
