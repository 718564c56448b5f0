"""Session set-up shared by every test module."""

from __future__ import annotations

import ast
import contextlib
import fcntl
import functools
import hashlib
import os
import subprocess
import sys
import tempfile
import time
from collections.abc import Iterable, Iterator
from pathlib import Path

import pytest
from xdist.remote import Producer
from xdist.scheduler import LoadFileScheduling

from epc_offboard.common import jit


def pytest_sessionstart(session: pytest.Session) -> None:
    if not hasattr(session.config, "workerinput"):  # xdist's controller, before its workers
        _write_bytecode()
    _warm_kernels()


# the checkout's packages that the suite's processes import (its services, SITLs, helpers and
# the test modules run as processes: tests.fleet_vehicle)
_PACKAGES = ("epc_offboard", "sitl", "tests")


def _write_bytecode() -> None:
    """Write the checkout's bytecode (``__pycache__``, ignored by git) where the interpreter
    will not (PYTHONDONTWRITEBYTECODE, set on this session's machines): the suite starts
    some 300 Python processes, and each one compiled the ~100 modules of ours it imports from
    source again, 0.05-0.3 CPU-s a process (service, miss worker, log and store helpers,
    SITL, `sim`; docs/MEASUREMENTS.md, stop 37). The bytecode is what the interpreter writes
    itself on any other machine; nothing a test runs changes."""
    if not sys.dont_write_bytecode:
        return
    import compileall

    root = Path(__file__).resolve().parent.parent
    for package in _PACKAGES:
        compileall.compile_dir(root / package, quiet=2)


def _warm_kernels() -> None:
    """Compile the control kernels into numba's cache once, before collection, when the
    checkout's cache is cold (a fresh clone, an edited kernel). (Not a session fixture: that
    ran inside the first test's timeout, which a compile of 4 minutes at load 16 outlasted,
    failing the first test of each worker.)

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


# the real-time flights' group: they judge the loops' timing, so no two of them ever fly at
# once (in either worker, nor in another checkout's suite on this machine). They are one
# xdist work unit (pytest_collection_modifyitems below), flown back to back by one worker
# while the other runs the rest of the suite beside them: their bounds are safety bounds that
# hold at load 6 (a lockstep flight beside them is about one core; the suite beside two CPU
# hogs, load up to 5.7, passed them all), and their loops run at the deployed nice (-5) and,
# where they judge the attitude loop's timing, at SCHED_FIFO. Beside the other worker's
# lockstep flights the machine's two cores are both at work, where the exclusive block left
# one idle for a third of the suite. A test may name several groups (the real-time flights
# beside CPU hogs: one_at_a_time("alone", "cpu-hogs")); every alone test holds "cpu-hogs"
# too, so the lockstep determinism flight's two hogs never run beside a real-time flight.
ALONE = ("alone",)
CPU_HOGS = "cpu-hogs"


@pytest.fixture(autouse=True)
def one_at_a_time(request: pytest.FixtureRequest) -> Iterator[None]:
    """A test marked ``one_at_a_time(name, ...)`` holds each name's lock while it runs: tests
    that bind the fixed Zenoh ports never run beside another of their kind in the other xdist
    worker (nor in another checkout's suite on this machine: the ports and the cores are the
    machine's); two real-time flights (:data:`ALONE`) never fly at once."""
    with holding(_groups(request.node)):
        yield


@contextlib.contextmanager
def holding(groups: set[str]) -> Iterator[None]:
    """The locks of ``groups`` (see :func:`one_at_a_time`), for a module fixture that flies
    a flight its tests share: module fixtures are set up before the tests' own locks."""
    if groups & set(ALONE):
        groups = groups | {CPU_HOGS}  # no other test's hogs beside a real-time flight
    with contextlib.ExitStack() as stack:
        for group in sorted(groups):  # one order everywhere: no two tests wait on each other
            stack.enter_context(_lock(f"epc-offboard-tests-{group}.lock"))
        yield


def _groups(item: pytest.Item) -> set[str]:
    """The names a test's ``one_at_a_time`` mark gives (none: an empty set)."""
    mark = item.get_closest_marker("one_at_a_time")
    return set(mark.args) if mark is not None else set()


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


# The xdist work units and the order the workers take them in. Each module is a unit
# (--dist loadfile in pyproject's addopts: a module's tests on one worker, its module
# fixtures, the compare flights, flown once), but the modules of real-time flights (an ALONE
# test) are one unit together (RealtimeUnit), so that one worker flies them back to back while
# the other runs the rest beside them. (Not --dist loadgroup with xdist_group marks: xdist
# 3.8 names a test's group by rewriting its item's _nodeid, which pytest 9.2 no longer reads.)
# Units go out in collection order (--no-loadscope-reorder: by default xdist re-sorts them by
# their number of tests):
# 1. REALTIME first: the longest unit (6-7 minutes of real-time flights, waits included;
#    test_lockstep_determinism's hog flights at its end).
# 2. The longest modules, so that neither worker ends on one while the other idles (the
#    scenarios' compare flights, collected last, once took a minute alone); the light unit
#    modules fill in at the end. Ranked by the suite's own module times (issue 22).
REALTIME = "realtime-flights"
SLOW_FIRST = (  # stop 39 and 40's suites beside two hogs, the mean of each module's sum (s)
    "test_scenarios", "test_entry_e2e", "test_service_e2e", "test_lwpr",  # 432 374 229 137
    "test_sim_truth_e2e", "test_miss_solver", "test_perturbation", "test_mavproxy_e2e",
    "test_neuralfly_e2e", "test_position_dead_time", "test_fleet_restart", "test_bench",
    "test_position_state_filter", "test_ardupilot_e2e", "test_wheel_install", "test_sharing",
    "test_rate_response", "test_sharing_e2e", "test_heartbeat_request_e2e", "test_ardupilot",
    "test_fleet_trust", "test_library_keeper", "test_tick_cost", "test_flight_logs_e2e",
    "test_aero", "test_report_output", "test_attitude_delay_e2e", "test_receive",
    "test_neuralfly_table", "test_attitude_delay", "test_fleet_rejoin",  # ... 24 s
)  # fmt: skip


def marked_groups(nodes: Iterable[ast.AST]) -> set[str]:
    """The group names of the ``pytest.mark.one_at_a_time("name", ...)`` calls in these
    syntax trees (decorators, a module's pytestmark, a whole module)."""
    return {
        str(arg.value)
        for tree in nodes
        for node in ast.walk(tree)
        if isinstance(node, ast.Call)
        and isinstance(node.func, ast.Attribute)
        and node.func.attr == "one_at_a_time"
        for arg in node.args
        if isinstance(arg, ast.Constant)
    }


@functools.cache
def _module_groups(module: Path) -> frozenset[str]:
    return frozenset(marked_groups([ast.parse(module.read_text())]))


def flies_in_real_time(module: Path) -> bool:
    """Whether a test module marks a test one_at_a_time("alone"), read from its syntax:
    xdist's controller schedules node ids, it collects no items (pytest_collection_modifyitems
    checks this reading against the marks the workers collect)."""
    return bool(_module_groups(module) & set(ALONE))


def in_realtime_unit(module: Path) -> bool:
    """Whether a test module is flown in the REALTIME unit: a real-time flight, or a test
    that runs CPU hogs (one_at_a_time("cpu-hogs"): test_lockstep_determinism). Every alone
    test holds "cpu-hogs" too, so a hog test in the other worker held the real-time worker
    idle at its lock for the hogs' whole flight (stop 40's suite: 25-72 s setups of
    test_attack_e2e, test_stop_bound_e2e, test_px4_faults_e2e); in one unit, one worker flies
    them back to back and neither waits."""
    return bool(_module_groups(module) & {*ALONE, CPU_HOGS})


class RealtimeUnit(LoadFileScheduling):  # type: ignore[misc]  # (xdist: untyped)
    """--dist loadfile, with the modules of real-time flights in one unit (see above)."""

    def __init__(self, config: pytest.Config, log: Producer | None = None) -> None:
        super().__init__(config, log)
        self.root = config.rootpath

    def _split_scope(self, nodeid: str) -> str:
        module = super()._split_scope(nodeid)
        return REALTIME if in_realtime_unit(self.root / module) else module


@pytest.hookimpl(optionalhook=True)
def pytest_xdist_make_scheduler(config: pytest.Config, log: Producer) -> RealtimeUnit | None:
    return RealtimeUnit(config, log) if config.getvalue("dist") == "loadfile" else None


def _alone(item: pytest.Item) -> bool:
    return bool(_groups(item) & set(ALONE))


def pytest_collection_modifyitems(items: list[pytest.Item]) -> None:
    alone = {item.path for item in items if _alone(item)}
    unit = {path for path in {item.path for item in items} if in_realtime_unit(path)}
    rank = {name: k for k, name in enumerate(SLOW_FIRST)}
    for path in {item.path for item in items}:
        if (path in alone) != flies_in_real_time(path):
            raise pytest.UsageError(
                f"{path.name}: its one_at_a_time marks and their reading from its source "
                "disagree (write the group's name as a literal: \"alone\")"
            )

    def key(item: pytest.Item) -> tuple[int, int]:
        if item.path in unit:  # the real-time flights first, the hogs' flights after them
            return (0, 0 if item.path in alone else 1)
        return (1, rank.get(item.path.stem, len(rank)))

    items.sort(key=key)  # stable: a module's tests keep their order
