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


# a group whose tests run with nothing else at all beside them, in any worker: the real-time
# flights (and the CPU hogs' tests) judge the loops' timing, which the other worker's flight
# would load; every other test runs beside any test but these
ALONE = ("alone", "cpu-hogs")


@pytest.fixture(autouse=True)
def one_at_a_time(request: pytest.FixtureRequest) -> Iterator[None]:
    """A test marked ``one_at_a_time(name)`` holds that name's lock while it runs: tests that
    bind the fixed Zenoh ports never run beside another of their kind in the other xdist
    worker (nor in another checkout's suite on this machine: the ports and the cores are the
    machine's). The :data:`ALONE` groups hold the machine's lock exclusively; every other
    test holds it shared, so a real-time flight runs with no other test beside it."""
    mark = request.node.get_closest_marker("one_at_a_time")
    group = mark.args[0] if mark is not None else None
    with contextlib.ExitStack() as stack:
        stack.enter_context(_machine_lock(exclusive=group in ALONE))
        if group is not None:
            stack.enter_context(_lock(f"epc-offboard-tests-{group}.lock"))
        yield


@contextlib.contextmanager
def _machine_lock(exclusive: bool) -> Iterator[None]:
    """A readers-writer lock with a turnstile (flock grants new shared holders while an
    exclusive one waits, so a worker running short tests back to back could starve it): a
    writer closes the turnstile while it waits and runs, readers pass through it first."""
    tmp = Path(tempfile.gettempdir())
    with (tmp / "epc-offboard-tests-turnstile.lock").open("a") as gate, \
            (tmp / "epc-offboard-tests-machine.lock").open("a") as machine:  # fmt: skip
        fcntl.flock(gate, fcntl.LOCK_EX)
        if exclusive:
            fcntl.flock(machine, fcntl.LOCK_EX)  # the turnstile stays closed till the end
            yield
            return
        fcntl.flock(gate, fcntl.LOCK_UN)
        fcntl.flock(machine, fcntl.LOCK_SH)
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


# The longest modules first: on two xdist workers (--dist loadfile, modules handed out in
# collection order) a long module collected last ran alone at the end while the other worker
# idled (the scenarios' compare flights: a minute). Measured on the suite's own durations.
SLOW_FIRST = (
    "test_entry_e2e", "test_scenarios", "test_sim_truth_e2e", "test_service_e2e",
    "test_ardupilot_e2e", "test_neuralfly_e2e", "test_wheel_install", "test_daemon",
    "test_sharing_e2e", "test_bench", "test_soak", "test_attack_e2e", "test_fuzz_e2e",
    "test_flood_e2e", "test_px4_faults_e2e", "test_lockstep_determinism",
)


def pytest_collection_modifyitems(items: list[pytest.Item]) -> None:
    rank = {name: k for k, name in enumerate(SLOW_FIRST)}

    def key(item: pytest.Item) -> int:
        return rank.get(item.path.stem, len(rank))

    items.sort(key=key)  # stable: a module's tests keep their order
