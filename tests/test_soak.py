"""The soak's short form in CI: random faults in a real-time flight, the invariants held.

The full form is ``python -m tests.soak --duration 600`` (see tests/soak.py).
"""

from __future__ import annotations

import math

import pytest

from tests.soak import FAULTS, run_soak

# a real-time flight (alone) with two CPU hogs: never beside another test's
# (test_suite_ports.py)
pytestmark = [pytest.mark.timeout(240), pytest.mark.one_at_a_time("alone", "cpu-hogs")]


def test_random_faults_never_cause_a_takeoff_in_the_air_a_nan_or_a_lockout(tmp_path):
    # ends holding: the autopilot's landing (9 s of real time with the real-time lock held)
    # judges none of the invariants; the full form lands
    result = run_soak(tmp_path, duration_s=16.0, seed=3, land_at_end=False)
    assert sum(result.faults.values()) >= 3, result.faults
    assert len([f for f in FAULTS if result.faults[f]]) >= 2, result.faults
    assert result.setpoints > 500
    # the invariants, from what the service actually sent
    assert result.takeoffs_sent == 1
    assert result.takeoffs_in_air == 0
    assert result.non_finite_setpoints == 0
    # no lockout: back under offboard control by itself once the faults stop
    assert math.isfinite(result.recovered_s)
    assert result.exit_code == 0
    # no climb away, no flip, no ground strike: the mission holds 2.5 m
    assert result.max_altitude_m < 4.0
    assert result.max_tilt_deg < 90.0
    assert result.min_altitude_m > 0.5
