"""Session set-up shared by every test module."""

from __future__ import annotations

import os
import subprocess
import sys
import time

import pytest

from epc_offboard.common import jit


@pytest.fixture(scope="session", autouse=True)
def warm_kernel_cache() -> None:
    """Compile the control kernels into numba's cache once, before the first test, when the
    checkout's cache is cold (a fresh clone, an edited kernel).

    On a cold cache every service a test starts flies the numpy twins and starts a background
    compile of its own, which dies with the service: a short flight ends before its compile is
    done, so on a fresh clone the first minutes of flight tests ran several half-done compiles
    beside real-time flights, until one finished and marked the cache warm. One compile here
    (the service's own background compile, run to the end) instead. The cold start itself is
    tested with a cache of its own (tests/test_coldstart_e2e.py); tests that need a cold cache
    set NUMBA_CACHE_DIR.
    """
    if not jit.enabled() or not jit.numba_installed() or jit.cache_warm():
        return
    from epc_offboard.tools.sim.scenario import SITL_SERVICE_CONFIG

    t0 = time.monotonic()
    subprocess.run(
        [sys.executable, "-m", "epc_offboard.service.coldstart", str(SITL_SERVICE_CONFIG),
         str(os.getpid())],
        check=True, timeout=600, env=dict(os.environ, **{jit.ENV: "1"}),
    )  # fmt: skip
    print(f"\nkernel cache warmed in {time.monotonic() - t0:.1f} s", file=sys.stderr)
