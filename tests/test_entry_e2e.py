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
stay inside the 45 deg tilt limit; the randomised re-entries judge every tilt against the
one that holds at rest in the wind blowing then (within 30 deg of it), in any wind.
"""

from __future__ import annotations

import os
import random
from pathlib import Path

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from tests.entry import WINDOW_S, Flight, fly

pytestmark = [pytest.mark.slow, pytest.mark.timeout(1200)]

MAX_ALT_CHANGE_M = 0.2
MAX_TILT_DEG = 30.0
TILT_LIMIT_DEG = 45.0 + 3.0  # the configured limit, and the attitude loop's overshoot


# the randomised re-entries: the tilt within this of the one that holds against the wind
MAX_TILT_FROM_HOLD_DEG = 30.0
COMBOS = [(a, m) for a in ("px4", "ardupilot") for m in ("epc", "autopilot")]
# ArduPilot's EKF origin 2 s after boot, not the real one's 36: the vehicle waits for it on
# the ground, before any entry (34 s of vehicle time a flight; the wait has tests of its own)
EKF_ORIGIN_S = 2.0


def _judge(flight: Flight, entries: int, *, from_hold: bool = False) -> None:
    """The flight's bounds; ``from_hold``: its tilt judged against the wind's hold only."""
    assert flight.exit_code == 0, flight.name
    assert len(flight.entries) == entries, (flight.name, flight.entries, flight.freezes_done)
    for e in flight.entries:
        what = f"{flight.name} entry at {e.t_s:.2f} s: {e}"
        # the whole window judged: the flight (shortened to REENTRY_S past a freeze) and the
        # next freeze never cut it short (the ground truth's samples: 5 ms apart)
        assert e.judged_s >= WINDOW_S - 0.01, what
        assert e.alt_change_m < MAX_ALT_CHANGE_M, what
        assert e.tilt_max_deg < TILT_LIMIT_DEG, what
        if from_hold:
            assert e.tilt_from_hold_deg < MAX_TILT_FROM_HOLD_DEG, what
        elif flight.wind_m_s <= 3.0:
            assert e.tilt_max_deg < MAX_TILT_DEG, what
        else:
            assert e.tilt_change_deg < MAX_TILT_DEG, what


def test_px4_body_rates_3_m_s_entry_and_reentry_after_a_short_freeze(tmp_path):
    """Fails on the old code: a 0.44 m drop at the first entry (the hold captured while
    the takeoff still climbed, flown by PX4 before its heartbeat showed offboard)."""
    _judge(fly(Flight("px4", "epc", 3.0, freezes_s=(0.6,)), tmp_path), entries=2)


@pytest.mark.parametrize("mode", ["epc", "autopilot"])
def test_ardupilot_reentry_in_6_m_s_wind_after_a_short_freeze(tmp_path, mode):
    """The first entry in 6 m/s wind (ArduCopter hands over still climbing out of its
    takeoff, and the estimate started at zero: 1.3 m of altitude change on the old code),
    then the hardest re-entry: 0.6 s of frozen telemetry is a failsafe, LOITER, whose hold
    starts from its own integrators (the vehicle levels and drifts downwind), then offboard
    again at once, tilting up 10 deg into the wind to brake the drift. A thrust sized for
    the target's tilt lifted the vehicle while the tilt lagged: 0.15-0.16 m on the old code
    (seeds 0-2; under the bound: tests/test_entry.py's thrust test is the one that fails
    on it), 0.05-0.08 m now."""
    flight = Flight("ardupilot", mode, 6.0, freezes_s=(0.6,), ekf_origin_s=EKF_ORIGIN_S)
    _judge(fly(flight, Path(tmp_path), seed=1), entries=2, from_hold=True)


@pytest.mark.parametrize(("autopilot", "mode"), COMBOS)
@settings(
    max_examples=int(os.environ.get("ENTRY_EXAMPLES", "1")),
    deadline=None,
    derandomize="ENTRY_EXAMPLES" not in os.environ,  # more examples asked: new ones
    suppress_health_check=[HealthCheck.function_scoped_fixture],
)
@given(draw=st.integers(0, 2**31 - 1))
def test_every_reentry_after_a_random_freeze_is_calm(tmp_path, autopilot, mode, draw):
    """Randomised freezes of the position telemetry (0.4-5 s, a failsafe each), after a
    random time in offboard, in random wind up to 6 m/s, in both personalities and both
    attitude modes: the entry and the re-entry each hold their altitude within 0.2 m and
    their tilt within 30 deg of the wind's over their first 2 s. The case is drawn from
    ``draw`` (hypothesis's minimal example, 0, is then a random case, not the calm corner);
    ENTRY_EXAMPLES=N flies N new cases per personality and mode."""
    rng = random.Random(f"{autopilot}-{mode}-{draw}")
    wind_m_s = rng.uniform(0.0, 6.0)
    freeze_s, settle_s = rng.uniform(0.4, 5.0), rng.uniform(2.0, 6.0)
    seed = rng.randrange(1000)
    flight = Flight(
        autopilot, mode, wind_m_s, freezes_s=(freeze_s,), settle_s=settle_s,
        ekf_origin_s=EKF_ORIGIN_S,
    )  # fmt: skip
    out = Path(tmp_path) / f"{flight.name}-settle{settle_s:.2f}-s{seed}"
    _judge(fly(flight, out, seed=seed), entries=2, from_hold=True)
