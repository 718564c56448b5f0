"""The suite sends nothing to a ground station's fixed port: every `epc-offboard sim` a test
starts passes --gcs-port 0 (PX4's default streams every vehicle's MAVLink to UDP 14550, where
QGroundControl or another engineer's run listens), unless it flies ArduPilot, whose ground
station is a TCP server only when asked for (--gcs-port PORT; none by default)."""

from __future__ import annotations

import re
from pathlib import Path

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
