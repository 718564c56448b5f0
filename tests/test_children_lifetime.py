"""`epc-offboard fleet router` (and a test rig's SITL and service) end with whoever started
them, and the router on SIGTERM, with real processes: at stop 39 a router outlived a dead
pytest and ignored SIGTERM (its handler set a threading.Event whose lock the main thread could
hold in ``Event.wait``; nothing tied it to its launcher)."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from epc_offboard.common.children import launched_env
from epc_offboard.common.ports import free_port
from tests.test_children import _alive

pytestmark = pytest.mark.timeout(120)

REPO = Path(__file__).resolve().parents[1]

# a router that has not ended this long after its parent's death or its SIGTERM does not
# end with it (it ends in well under a second alone; ample at load 6)
_BOUND_S = 20.0

_LAUNCHER = """
import os, subprocess, sys, time
from epc_offboard.common.children import launched_env
router = subprocess.Popen(
    [sys.executable, "-m", "epc_offboard", "fleet", "router", "--listen", sys.argv[1],
     "--stats-every", "0.2"], env={**os.environ, **launched_env()}, stdout=sys.stdout,
)
time.sleep(600)
"""


def _started(stdout) -> None:
    """Wait for the router's first JSON line ("started"): it listens."""
    line = stdout.readline()
    assert line, "the router did not start"
    assert json.loads(line)["event"] == "started", line


def test_the_router_dies_with_its_launcher_sigkilled():
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    launcher = subprocess.Popen([sys.executable, "-c", _LAUNCHER, endpoint],
                                stdout=subprocess.PIPE, text=True)  # fmt: skip
    try:
        assert launcher.stdout is not None
        _started(launcher.stdout)
        routers = _children(launcher.pid)
        assert len(routers) == 1, routers
        assert not _left_after_killing(launcher, routers), "the router outlived its launcher"
    finally:
        if launcher.poll() is None:
            launcher.kill()
            launcher.wait()


def _left_after_killing(launcher: subprocess.Popen[str], pids: set[int]) -> set[int]:
    """SIGKILL ``launcher``; those of ``pids`` still running ``_BOUND_S`` later (killed here,
    after the fact, so that a failure leaves none behind)."""
    os.kill(launcher.pid, signal.SIGKILL)
    launcher.wait(timeout=10)
    deadline = time.monotonic() + _BOUND_S
    while _alive(pids) and time.monotonic() < deadline:
        time.sleep(0.1)
    left = _alive(pids)
    for pid in left:
        os.kill(pid, signal.SIGKILL)
    return left


def test_the_router_exits_0_on_sigterm():
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    router = subprocess.Popen(
        [sys.executable, "-m", "epc_offboard", "fleet", "router", "--listen", endpoint,
         "--stats-every", "0.05"], stdout=subprocess.PIPE, text=True,
        env={**os.environ, **launched_env()},
    )  # fmt: skip
    try:
        assert router.stdout is not None
        _started(router.stdout)
        for _ in range(5):  # some stats lines: the main loop at work when the signal lands
            assert json.loads(router.stdout.readline())["event"] == "stats"
        router.send_signal(signal.SIGTERM)
        code = router.wait(timeout=_BOUND_S)
        assert code == 0
        last = [json.loads(line) for line in router.stdout.read().splitlines()]
        assert last[-1]["event"] == "stopped", last
    finally:
        if router.poll() is None:
            router.kill()
            router.wait()


def _children(pid: int) -> set[int]:
    out: set[int] = set()
    for task in os.listdir(f"/proc/{pid}/task"):
        with open(f"/proc/{pid}/task/{task}/children") as fh:
            out.update(int(c) for c in fh.read().split())
    return out


_RIG_LAUNCHER = """
import sys, time
from pathlib import Path
from tests.rig import Rig
rig = Rig(Path(sys.argv[1]))
rig.start_sitl()
rig.start_service()
print(rig.sitl.pid, rig.service.pid, flush=True)
time.sleep(600)
"""


def test_a_test_rigs_sitl_and_service_die_with_pytest_sigkilled(tmp_path):
    """tests/rig.py's SITL and service (every end-to-end test's) end with the test process:
    before stop 40 a SIGKILLed pytest (a CI timeout) left both running."""
    launcher = subprocess.Popen([sys.executable, "-c", _RIG_LAUNCHER, str(tmp_path)],
                                stdout=subprocess.PIPE, text=True, cwd=REPO)  # fmt: skip
    try:
        assert launcher.stdout is not None
        pids = {int(p) for p in launcher.stdout.readline().split()}
        assert len(pids) == 2, pids
        left = _left_after_killing(launcher, pids)
        assert not left, "the rig's processes outlived the test process"
    finally:
        if launcher.poll() is None:
            launcher.kill()
            launcher.wait()
