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


# the group whose tests run with nothing else at all beside them, in any worker: the real-time
# flights judge the loops' timing, which the other worker's flight would load; every other
# test runs beside any test but these. A test may name several groups (the real-time flights
# beside CPU hogs: one_at_a_time("alone", "cpu-hogs")); the lockstep determinism flight
# beside its hogs is "cpu-hogs" only: lockstep judges no timing, so the other worker's
# lockstep flights run on beside it (slower), where the alone lock idled a core for 29 s
ALONE = ("alone",)


@pytest.fixture(autouse=True)
def one_at_a_time(request: pytest.FixtureRequest) -> Iterator[None]:
    """A test marked ``one_at_a_time(name, ...)`` holds each name's lock while it runs: tests
    that bind the fixed Zenoh ports never run beside another of their kind in the other xdist
    worker (nor in another checkout's suite on this machine: the ports and the cores are the
    machine's). The :data:`ALONE` group holds the machine's lock exclusively; every other
    test holds it shared, so a real-time flight runs with no other test beside it."""
    with holding(_groups(request.node)):
        yield


@contextlib.contextmanager
def holding(groups: set[str]) -> Iterator[None]:
    """The locks of ``groups`` (see :func:`one_at_a_time`), for a module fixture that flies
    a flight its tests share: module fixtures are set up before the tests' own locks."""
    with contextlib.ExitStack() as stack:
        stack.enter_context(_machine_lock(exclusive=bool(groups & set(ALONE))))
        for group in sorted(groups):  # one order everywhere: no two tests wait on each other
            stack.enter_context(_lock(f"epc-offboard-tests-{group}.lock"))
        yield


def _groups(item: pytest.Item) -> set[str]:
    """The names a test's ``one_at_a_time`` mark gives (none: an empty set)."""
    mark = item.get_closest_marker("one_at_a_time")
    return set(mark.args) if mark is not None else set()


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


# The order the two xdist workers take the modules in: --dist loadfile hands them out in
# collection order (pyproject's addopts pass --no-loadscope-reorder: by default xdist re-sorts
# them by their number of tests, which undid this order and put the one-test real-time
# flights last, strewn among the long lockstep modules).
# 1. The modules of the ALONE group, back to back. While one worker flies one alone, the
#    other waits for the lock holding nothing. Strewn among the lockstep modules, each of
#    them first waited for the other worker's current test to end (a lockstep flight of up
#    to 40 s) with its own core idle: replayed through xdist's hand-out and this lock, the
#    suite's measured test times gave the workers 86 s less idle time this way.
# 2. A module of many short tests (AFTER_ALONE): the worker that leaves the alone block first
#    then holds nothing long while the other flies the block's last test.
# 3. The longest modules first, so that neither worker ends on one while the other idles
#    (the scenarios' compare flights, collected last, once took a minute alone); the light
#    unit modules fill in at the end. Ranked by the suite's own module times (issue 22).
AFTER_ALONE = ("test_layers",)
SLOW_FIRST = (
    "test_entry_e2e", "test_scenarios", "test_sim_truth_e2e", "test_service_e2e", "test_bench",
    "test_wheel_install", "test_fleet_trust", "test_sharing_e2e", "test_ardupilot_e2e",
    "test_flight_logs_e2e", "test_sharing", "test_fleet_rejoin", "test_miss_solver",
    "test_cascade", "test_attitude_delay_e2e", "test_neuralfly_e2e", "test_lockstep_determinism",
    "test_lwpr", "test_daemon",
)


def _alone(item: pytest.Item) -> bool:
    return bool(_groups(item) & set(ALONE))


def pytest_collection_modifyitems(items: list[pytest.Item]) -> None:
    alone = {item.path for item in items if _alone(item)}
    rank = {name: k for k, name in enumerate(SLOW_FIRST)}

    def key(item: pytest.Item) -> tuple[int, int]:
        if item.path in alone:
            return (0, 0)
        if item.path.stem in AFTER_ALONE:
            return (1, 0)
        return (2, rank.get(item.path.stem, len(rank)))

    items.sort(key=key)  # stable: a module's tests keep their order
