"""The suite sends nothing to a ground station's fixed port: every `epc-offboard sim` a test
starts passes --gcs-port 0 (PX4's default streams every vehicle's MAVLink to UDP 14550, where
QGroundControl or another engineer's run listens), unless it flies ArduPilot, whose ground
station is a TCP server only when asked for (--gcs-port PORT; none by default)."""

from __future__ import annotations

import ast
import re
from collections.abc import Callable
from pathlib import Path

from tests.conftest import (
    ALONE,
    REALTIME,
    RealtimeUnit,
    flies_in_real_time,
    in_realtime_unit,
    marked_groups,
)

TESTS = Path(__file__).resolve().parent
_SIM = re.compile(r'(?:"-m",\s*"epc_offboard(?:\.cli)?"|"epc-offboard"),\s*"sim"')


def _command(text: str, at: int) -> str:
    """The bracketed argument list around position ``at``."""
    start = text.rindex("[", 0, at)
    depth = 0
    for i in range(start, len(text)):
        depth += {"[": 1, "]": -1}.get(text[i], 0)
        if depth == 0:
            return text[start : i + 1]
    raise AssertionError("unbalanced brackets")


def test_every_sim_a_test_starts_streams_to_no_ground_station_port() -> None:
    offenders = []
    for path in sorted(TESTS.rglob("*.py")):
        text = path.read_text()
        for match in _SIM.finditer(text):
            command = _command(text, match.start())
            if "--gcs-port" not in command and "ardupilot" not in command:
                offenders.append(f"{path.name}:{text.count(chr(10), 0, match.start()) + 1}")
    assert not offenders, f"sim without --gcs-port 0: {offenders}"


# what a test's own source does -> the group it must be in (pyproject's addopts run the suite
# on two xdist workers; tests/conftest.py runs a group's tests one at a time)
_NEEDS_GROUP: dict[str, Callable[[str], bool]] = {
    # `sim --vehicles N` with sharing binds the fixed Zenoh ports 7447..: two at once collide
    "zenoh-fixed-ports": lambda source: any(
        re.search(r'"--vehicles",\s*"[2-9]', command) and "--no-share" not in command
        for command in (_command(source, m.start()) for m in _SIM.finditer(source))
    ),
    # two CPU hogs each: two such tests at once would load the machine far beyond load 6
    "cpu-hogs": lambda source: re.search(r"\bcpu_hog\(|\brun_soak\(", source) is not None,
}


def test_tests_that_share_a_fixed_port_or_hog_the_cpu_run_one_at_a_time() -> None:
    offenders = []
    for path in sorted(TESTS.glob("test_*.py")):
        text = path.read_text()
        tree = ast.parse(text)
        module_groups: set[str] = set()
        for node in tree.body:
            if isinstance(node, ast.Assign) and any(
                isinstance(t, ast.Name) and t.id == "pytestmark" for t in node.targets
            ):
                module_groups |= marked_groups([node.value])
        for node in tree.body:
            if not (isinstance(node, ast.FunctionDef) and node.name.startswith("test_")):
                continue
            source = ast.get_source_segment(text, node) or ""
            groups = module_groups | marked_groups(node.decorator_list)
            offenders += [
                f"{path.name}::{node.name} not in one_at_a_time({group!r})"
                for group, needs in _NEEDS_GROUP.items()
                if needs(source) and group not in groups
            ]
            # ("lockstep=" + "False": this file, which names it, does not count itself)
            if "lockstep=" + "False" in text and not groups & set(ALONE):  # run alone
                offenders.append(f"{path.name}::{node.name} flies in real time: not alone")
    assert not offenders, offenders


def test_the_real_time_flights_are_one_work_unit_and_the_rest_one_per_module() -> None:
    """xdist's controller hands out RealtimeUnit's scopes: every module of a real-time
    flight, and of CPU hogs, in one (one worker flies them back to back, never two at once,
    and never waits on the other worker for the hogs' lock), every other module its own (its
    module fixtures flown once)."""
    units = RealtimeUnit.__new__(RealtimeUnit)  # (only the scope reading: no controller)
    units.root = TESTS.parent
    realtime = [p.name for p in sorted(TESTS.glob("test_*.py")) if flies_in_real_time(p)]
    assert {"test_attack_e2e.py", "test_soak.py", "test_coldstart_e2e.py"} <= set(realtime)
    unit = [p.name for p in sorted(TESTS.glob("test_*.py")) if in_realtime_unit(p)]
    assert set(unit) == set(realtime) | {"test_lockstep_determinism.py"}
    for name in unit:
        assert units._split_scope(f"tests/{name}::test_x[a::b]") == REALTIME, name
    for name in ("test_scenarios.py", "test_entry_e2e.py", "test_sharing_e2e.py"):
        assert units._split_scope(f"tests/{name}::test_y") == f"tests/{name}"
