"""A cold start (numba's kernel cache empty) reaches offboard in seconds, in real time.

The service compiled every kernel before its loops started: 10-30 s on a busy companion
computer, and a real vehicle reached offboard 30-52 s after the service started. Now a cold
cache flies the numpy twins of the kernels at once (numba is not even imported: nothing can
compile on the control loop) while a background process compiles them into the cache for the
next start (epc_offboard/service/coldstart.py).
"""

from __future__ import annotations

import subprocess
import sys
import time
from pathlib import Path

import pytest

from epc_offboard.vehicle.dialect_px4 import PX4_MAIN_MODE_OFFBOARD
from tests.rig import MIN_RATE_FRACTION, Rig

pytestmark = [pytest.mark.timeout(240), pytest.mark.one_at_a_time("alone")]

# Loose: holds at load 6 on 2 cores (measured on such a machine: 8-12 s, against 30-50 s
# before, when the compile ran first).
MAX_COLD_START_TO_OFFBOARD_S = 25.0

MAX_CPU_TO_LINK_S = 1.5

HOVER = {
    # then a hold, and the service exits: the autopilot's landing judges nothing here
    "mission": {"duration_s": 3.0, "land_at_end": False},
    "trajectory": {"shape": "hover"},
}


def fifo_permitted() -> bool:
    """Whether a process of this user may run SCHED_FIFO (root, CAP_SYS_NICE, RLIMIT_RTPRIO)."""
    probe = "import os; os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(1))"
    return subprocess.run([sys.executable, "-c", probe], check=False).returncode == 0


def cold_start_to_offboard_s(rig: Rig) -> float:
    """Start the service (the SITL already up) and time it until the SITL says offboard."""
    rig.start_sitl()
    rig.heartbeat(timeout_s=30.0)
    t0 = time.monotonic()
    rig.start_service()
    rig.wait_mode(PX4_MAIN_MODE_OFFBOARD, 0, timeout_s=120.0)
    return time.monotonic() - t0


def test_cold_start_flies_the_numpy_twins_and_reaches_offboard_in_seconds(tmp_path: Path):
    cache = tmp_path / "numba-cache"
    cache.mkdir()
    fifo = fifo_permitted()
    # config/default.toml's loops priority (a real vehicle's), where this machine permits it
    loops = {"loops": {"realtime_priority": 10}} if fifo else {}
    rig = Rig(
        tmp_path,
        lockstep=False,
        speedup=1.0,
        service_overrides={**HOVER, **loops},
        service_env={"NUMBA_CACHE_DIR": str(cache)},
    )
    try:
        elapsed = cold_start_to_offboard_s(rig)
        code = rig.wait_exit(timeout_s=60)
    finally:
        rig.__exit__()
    log = rig.log()
    print(f"cold start to offboard: {elapsed:.1f} s")
    assert code == 0, log
    assert elapsed < MAX_COLD_START_TO_OFFBOARD_S, log
    assert "numpy twins" in (tmp_path / "service.log").read_text()  # (log: its end only)
    stats = rig.stats()
    # the hot path never compiled: no kernel of the service process has a compiled signature
    assert stats["kernels"] == {"mode": "numpy", "signatures_after_warm_up": 0, "signatures": 0}
    # numba compiled its kernel inside the first control tick (0.2-1 s on the loop): the
    # supervisor saw stale state and failed safe on every start with a cold cache (a real PX4
    # exposed it; this flight was also flown as such in test_px4_faults_e2e). Judged on the
    # loops' own longest tick, under the stale bound, not on the failsafe it caused: at load
    # 12-14 the SITL (an ordinary process beside 14 hogs) was starved itself and its state
    # came 0.252 s late, a failsafe the loops had no part in (stop 41). A compile injected in
    # the first position tick fails this (that tick 0.43 s; stop 42, lock-leave)
    stale_us = rig.config["offboard"]["max_state_age_s"] * 1e6
    longest_us = {name: loop["compute_us_max"] for name, loop in stats["loops"].items()}
    assert max(longest_us.values()) < stale_us, (longest_us, log)
    assert stats["takeoffs_sent"] == 1
    assert stats["counters"].get("takeoffs_sent") == 1
    # where the start went, timed from the process's own start (stats.json "startup")
    startup = stats["startup"]
    marks = startup["milestones"]
    order = ["entry", "config", "service_built", "kernels_warm", "link_open", "ready",
             "preflight", "streaming", "offboard"]  # fmt: skip
    if fifo:  # the start-up at the loops' priority from before its heavy imports
        order.insert(1, "start_up_priority")
    assert [m for m in marks if m in order] == order, marks
    # the first hand-over waited for the miss worker (issue 21: at load 16 it came up 7 s
    # after entry, and the ticks until then flew the intermediate controller)
    assert marks["miss_worker_up"]["t_s"] <= marks["offboard_requested"]["t_s"], marks
    # the arm's and the mode's changes were seen on heartbeats asked for, not on the 1 Hz
    # schedule (tests/test_heartbeat_request_e2e.py times them), and nothing looked forged
    assert stats["counters"].get("heartbeat_requests", 0) >= 2, stats["counters"]
    assert "heartbeat_flaps" not in stats["state"], stats["state"]
    # the process started after t0, and the SITL's offboard (what ``elapsed`` ends on) came
    # after our first request of it (/proc's process age: 10 ms ticks). Not the service's
    # own "offboard": at load its confirmation may come seconds after the SITL's switch, a
    # failsafe between (a starved SITL's stale state; stop 43, load 12-13: 18.54 s against
    # 16.52 s, failed)
    assert marks["offboard_requested"]["t_s"] <= elapsed + 0.05, (marks, elapsed)
    assert startup["offboard_s"] >= marks["offboard_requested"]["t_s"], marks
    # The service's own CPU up to its link, which load does not stretch: 0.64-0.79 s on an
    # earlier machine at load 2-18 (imports 0.5 s); 1.22 s there before, when a cold start
    # still imported numba (0.4 s of CPU) and compiled the rate identifier's kernel in the
    # warm-up. A slower machine (stop 32) takes 1.06-1.23 s, main and merge alike, idle:
    # numba's import on top of that still fails it
    assert marks["link_open"]["cpu_s"] < MAX_CPU_TO_LINK_S, marks
    # the rates the loops need were asked for at link-up and are what arrives
    rates = stats["rates_hz"]
    # PX4 delivers ATTITUDE_QUATERNION at 123 Hz of the 200 asked (its default: 50)
    assert rates["ATTITUDE_QUATERNION"] >= MIN_RATE_FRACTION * 123.0
    assert rates["LOCAL_POSITION_NED"] >= MIN_RATE_FRACTION * 100.0  # PX4's default: 30


# (its warm twin, a flight on compiled kernels, is lockstep: tests/test_service_e2e.py)
