"""A start longer than a stall bound, made by the test on any host: every Python process
spawned after ``spend_cpu_at_each_start`` (a multiprocessing ``spawn`` child, a subprocess)
runs a ``sitecustomize`` on the PYTHONPATH it inherits that spends ``cpu_s`` of its own CPU
before anything else. A start is running throughout it (never a stall), and takes at least
``cpu_s`` of wall time however fast the host: a claim about a start longer than a bound
then holds on CI's faster host (stop 43: a fleet helper's own start took 1-1.6 s here and
0.26 s there), not only on ours."""

from __future__ import annotations

import os
from pathlib import Path

import pytest


def spend_cpu_at_each_start(monkeypatch: pytest.MonkeyPatch, directory: Path,
                            cpu_s: float) -> None:  # fmt: skip
    (directory / "sitecustomize.py").write_text(
        "import time\n"
        f"_end = time.process_time() + {cpu_s!r}\n"
        "while time.process_time() < _end:\n"
        "    pass\n"
    )
    inherited = os.environ.get("PYTHONPATH")
    monkeypatch.setenv("PYTHONPATH",
                       os.pathsep.join(p for p in (str(directory), inherited) if p))  # fmt: skip
