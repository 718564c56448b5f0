"""The suite sends nothing to a ground station's fixed port: every `epc-offboard sim` a test
starts passes --gcs-port 0 (PX4's default streams every vehicle's MAVLink to UDP 14550, where
QGroundControl or another engineer's run listens), unless it flies ArduPilot, whose ground
station is a TCP server only when asked for (--gcs-port PORT; none by default)."""

from __future__ import annotations

import ast
import re
from collections.abc import Callable
from pathlib import Path

from tests.conftest import ALONE

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


def _groups(decorators: list[ast.expr]) -> set[str]:
    """The names of the ``pytest.mark.one_at_a_time("name", ...)`` marks among ``decorators``."""
    return {
        str(arg.value)
        for deco in decorators
        for node in ast.walk(deco)
        if isinstance(node, ast.Call)
        and isinstance(node.func, ast.Attribute)
        and node.func.attr == "one_at_a_time"
        for arg in node.args
        if isinstance(arg, ast.Constant)
    }


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
                module_groups |= _groups([node.value])
        for node in tree.body:
            if not (isinstance(node, ast.FunctionDef) and node.name.startswith("test_")):
                continue
            source = ast.get_source_segment(text, node) or ""
            groups = module_groups | _groups(node.decorator_list)
            offenders += [
                f"{path.name}::{node.name} not in one_at_a_time({group!r})"
                for group, needs in _NEEDS_GROUP.items()
                if needs(source) and group not in groups
            ]
            # ("lockstep=" + "False": this file, which names it, does not count itself)
            if "lockstep=" + "False" in text and not groups & set(ALONE):  # run alone
                offenders.append(f"{path.name}::{node.name} flies in real time: not alone")
    assert not offenders, offenders
