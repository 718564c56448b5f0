"""No orphans (issue 22, item 4): every process the service starts dies with it, however it
dies. A real `epc-offboard run` process with its helpers started (miss worker, fleet session,
multiprocessing's resource tracker), SIGKILLed; /proc is read for what is left."""

from __future__ import annotations

import contextlib
import os
import signal
import time

import pytest

from epc_offboard.common.children import descendants
from epc_offboard.common.ports import free_port
from tests.rig import Rig
from tests.test_daemon import wait_log

pytestmark = pytest.mark.timeout(90)


def _alive(pids: set[int]) -> set[int]:
    """Those of ``pids`` still running (zombies, dead but not reaped, are not running)."""
    out = set()
    for pid in pids:
        try:
            with open(f"/proc/{pid}/stat") as fh:
                state = fh.read().rsplit(")", 1)[1].split()[0]
        except OSError:
            continue
        if state not in ("Z", "X"):
            out.add(pid)
    return out


def _cmdlines(pids: set[int]) -> list[str]:
    out = []
    for pid in pids:
        try:
            with open(f"/proc/{pid}/cmdline", "rb") as fh:
                cmd = fh.read().replace(b"\0", b" ").decode()
            out.append(f"{pid}: {cmd[:160]}")
        except OSError:
            pass
    return out


def test_a_sigkilled_service_leaves_no_process_behind(tmp_path):
    port = free_port()
    overrides = {
        "sharing": {
            "enabled": True, "fleet": "orphans", "vehicle_id": "v1",
            "listen": [f"tcp/127.0.0.1:{port}"], "scouting_multicast": False,
        },
    }  # fmt: skip
    rig = Rig(tmp_path, service_overrides=overrides)  # no SITL: the helpers start anyway
    try:
        rig.start_service()
        assert rig.service is not None
        wait_log(rig, "epc-offboard running", timeout_s=60)
        time.sleep(0.5)
        children = descendants(rig.service.pid)
        # the miss worker and the resource tracker at least (and the fleet helper, if any)
        assert len(children) >= 2, _cmdlines(children)
        os.kill(rig.service.pid, signal.SIGKILL)
        rig.service.wait(timeout=10)
        deadline = time.monotonic() + 10.0
        while _alive(children) and time.monotonic() < deadline:
            time.sleep(0.1)
        left = _alive(children)
        for pid in left:  # clean up after a failure, then report it
            os.kill(pid, signal.SIGKILL)
        assert not left, f"orphans: {_cmdlines(left)}"
    finally:
        rig.__exit__()


def test_the_benchs_cpu_hogs_end_with_a_killed_bench() -> None:
    """`bench --attack --hogs N` and `bench --modes --hogs N` start CPU hogs; a SIGKILLed
    bench (a test's timeout, an OOM kill) left them spinning for ever beside whatever ran
    next. A real bench stand-in starts two with ``start_hogs`` and is SIGKILLed."""
    import subprocess
    import sys

    bench = subprocess.Popen(
        [sys.executable, "-c",
         "import time\n"
         "from epc_offboard.tools.bench_modes import start_hogs\n"
         "print(*(p.pid for p in start_hogs(2)), flush=True)\n"
         "time.sleep(60)\n"],
        stdout=subprocess.PIPE, text=True)  # fmt: skip
    assert bench.stdout is not None
    hogs = {int(p) for p in bench.stdout.readline().split()}
    try:
        assert len(hogs) == 2
        assert _alive(hogs) == hogs
        bench.kill()
        bench.wait()
        deadline = time.monotonic() + 30.0
        while _alive(hogs) and time.monotonic() < deadline:
            time.sleep(0.05)
        assert _alive(hogs) == set(), "a CPU hog outlived its bench"
    finally:
        for pid in hogs:
            with contextlib.suppress(ProcessLookupError):
                os.kill(pid, signal.SIGKILL)
