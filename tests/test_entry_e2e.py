"""Entering offboard in wind, and re-entering after a telemetry freeze, flown end to end
(the bundled SITL and the service, lockstep; judged on the SITL's ground truth by
tests/entry.py, which also flies the whole matrix: ``python -m tests.entry``).

On a real PX4 the disturbance estimate started at zero at entry and overshot: a 1.0 m drop
and 57 deg of tilt in 3 m/s wind, a 2.2 m climb in 6 m/s. Now the estimator learns while the
autopilot flies, the command is rate-limited from the first tick of every (re)entry, and
the vehicle is held where it is until offboard is confirmed.

Bounds over the first 2 s of each entry: altitude within 0.2 m of the entry's; tilt under
30 deg in 3 m/s wind. In 6 m/s wind the SITL's drag (SIH's, 1 m/s^2 per m/s) needs 31.5 deg
of tilt just to hold, so there the tilt may change by at most 30 deg from the entry's and
stay inside the 45 deg tilt limit.
"""

from __future__ import annotations

from pathlib import Path

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from tests.entry import Flight, fly

pytestmark = [pytest.mark.slow, pytest.mark.timeout(600)]

MAX_ALT_CHANGE_M = 0.2
MAX_TILT_DEG = 30.0
TILT_LIMIT_DEG = 45.0 + 3.0  # the configured limit, and the attitude loop's overshoot


def _judge(flight: Flight, entries: int) -> None:
    assert flight.exit_code == 0, flight.name
    assert len(flight.entries) == entries, (flight.name, flight.entries, flight.freezes_done)
    for e in flight.entries:
        what = f"{flight.name} entry at {e.t_s:.2f} s: {e}"
        assert e.alt_change_m < MAX_ALT_CHANGE_M, what
        if flight.wind_m_s <= 3.0:
            assert e.tilt_max_deg < MAX_TILT_DEG, what
        else:
            assert e.tilt_change_deg < MAX_TILT_DEG, what
            assert e.tilt_max_deg < TILT_LIMIT_DEG, what


def test_px4_body_rates_3_m_s_entry_and_reentry_after_a_short_freeze(tmp_path):
    """Fails on the old code: a 0.44 m drop at the first entry (the hold captured while
    the takeoff still climbed, flown by PX4 before its heartbeat showed offboard)."""
    _judge(fly(Flight("px4", "epc", 3.0, freezes_s=(0.6,)), tmp_path), entries=2)


def test_ardupilot_quaternion_6_m_s_entry(tmp_path):
    """Fails on the old code: ArduCopter hands over still climbing out of its takeoff, and
    the estimate started at zero: 1.3 m of altitude change. (Re-entries on this personality
    are judged by the bench, python -m tests.entry: its BRAKE holds level and lets the wind
    take the vehicle, so holding after the freeze needs the whole wind's tilt anew.)"""
    _judge(fly(Flight("ardupilot", "autopilot", 6.0), tmp_path), entries=1)


@settings(
    max_examples=2,
    deadline=None,
    derandomize=True,
    suppress_health_check=[HealthCheck.function_scoped_fixture],
)
@given(
    freeze_s=st.floats(0.4, 5.0),
    settle_s=st.floats(2.0, 6.0),
    mode=st.sampled_from(["epc", "autopilot"]),
)
def test_every_reentry_after_a_random_freeze_is_calm(tmp_path, freeze_s, settle_s, mode):
    out = Path(tmp_path) / f"freeze{freeze_s:.2f}-settle{settle_s:.2f}-{mode}"
    flight = Flight("px4", mode, 3.0, freezes_s=(freeze_s,), settle_s=settle_s)
    _judge(fly(flight, out), entries=2)
