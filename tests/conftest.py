"""Session set-up shared by every test module."""

from __future__ import annotations

import contextlib
import fcntl
import hashlib
import os
import subprocess
import sys
import tempfile
import time
from collections.abc import Iterator
from pathlib import Path

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

    # pytest-xdist runs this in every worker: the first compiles under the lock, the others
    # wait for it and find the cache warm (two compiles at once wrote the same cache files)
    with _warm_up_lock():
        if jit.cache_warm():
            return
        t0 = time.monotonic()
        subprocess.run(
            [sys.executable, "-m", "epc_offboard.service.coldstart", str(SITL_SERVICE_CONFIG),
             str(os.getpid())],
            check=True, timeout=600, env=dict(os.environ, **{jit.ENV: "1"}),
        )  # fmt: skip
    print(f"\nkernel cache warmed in {time.monotonic() - t0:.1f} s", file=sys.stderr)


@pytest.fixture(autouse=True)
def one_at_a_time(request: pytest.FixtureRequest) -> Iterator[None]:
    """A test marked ``one_at_a_time(name)`` holds that name's lock while it runs: tests that
    bind the fixed Zenoh ports or start two CPU hogs never run beside another of their kind
    in the other xdist worker (nor in another checkout's suite on this machine: the ports and
    the cores are the machine's)."""
    mark = request.node.get_closest_marker("one_at_a_time")
    if mark is None:
        yield
        return
    with _lock(f"epc-offboard-tests-{mark.args[0]}.lock"):
        yield


def _warm_up_lock() -> contextlib.AbstractContextManager[None]:
    """This checkout's (or NUMBA_CACHE_DIR's) kernel cache's lock."""
    cache = str(jit.cache_dir() or Path(jit.__file__).resolve().parent.parent)
    return _lock(f"epc-offboard-warm-{hashlib.sha256(cache.encode()).hexdigest()[:12]}.lock")


@contextlib.contextmanager
def _lock(name: str) -> Iterator[None]:
    """An exclusive lock, released when its holder ends, however it ends (flock)."""
    with (Path(tempfile.gettempdir()) / name).open("a") as fh:
        fcntl.flock(fh, fcntl.LOCK_EX)
        yield
