"""A lockstep SITL whose controller is gone without a word (SIGKILL) finds it by the long
bound ``lockstep_timeout_s`` x ``lockstep_max_timeouts``, falls back to real time, counts it
and warns. (That a controller starved for less than the bound changes nothing of a lockstep
flight: tests/test_lockstep_determinism.py, against the quiet flight it flies anyway.) Real
processes over UDP MAVLink.
"""

from __future__ import annotations

import signal
import time

import pytest

from epc_offboard.tools.sim.analysis import flight_warnings, sitl_counters
from epc_offboard.vehicle.dialect_px4 import (
    PX4_AUTO_SUB_LOITER,
    PX4_MAIN_MODE_AUTO,
    PX4_MAIN_MODE_OFFBOARD,
)
from tests.rig import Rig

pytestmark = [pytest.mark.timeout(420)]

# the killed-service test's bound, short so that it runs in seconds: 45 x 0.2 s = 9 s (the
# shipped 45 x 2 s); the bound after a hand-back would be 1 x 0.2 s
TIMEOUT_MS = 200
LONG_BOUND_S = 45 * TIMEOUT_MS / 1000.0


def test_a_killed_controller_is_found_by_the_long_bound_counted_and_warned(tmp_path):
    """A service gone without a word (SIGKILL: no HOLD request, so not handed back) is not
    told from a starved one until the long bound has passed; then the SITL falls back to
    real time, PX4's offboard-loss failsafe holds the vehicle, and the fallback is counted
    (``lockstep_fallbacks``: the report's "lockstep fell back to real time"). Before the
    hand-back was told apart, a fallback no answer followed was not counted: 0, nothing
    said."""
    with Rig(tmp_path, sitl_args=("--lockstep-timeout-ms", str(TIMEOUT_MS))) as rig:
        rig.wait_mode(PX4_MAIN_MODE_OFFBOARD, 0)
        time.sleep(1.0)
        t0 = time.monotonic()
        rig.stop_service(signal.SIGKILL)
        rig.wait_mode(PX4_MAIN_MODE_AUTO, PX4_AUTO_SUB_LOITER, timeout_s=LONG_BOUND_S + 60.0)
        took_s = time.monotonic() - t0
        assert rig.sitl is not None
        rig.sitl.send_signal(signal.SIGTERM)
        assert rig.sitl.wait(timeout=10) == 0
    # the whole long bound was waited (a load only makes it later), not the short one
    assert took_s >= LONG_BOUND_S - 0.5, took_s
    counters = sitl_counters(tmp_path / "sitl.log")
    assert counters["lockstep_fallbacks"] >= 1, counters
    assert counters["offboard_failsafes"] >= 1, counters
    assert flight_warnings({}, counters)["lockstep fell back to real time"] >= 1
