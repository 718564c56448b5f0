"""What a new user meets on a first run (stop 41): Ctrl-C during `sim` says what happened
and leaves nothing running. A real `epc-offboard sim` in a process group of its own, SIGINT
to the group as a terminal sends it.
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
from pathlib import Path


def _group_alive(pgid: int) -> list[str]:
    ps = subprocess.run(["ps", "-o", "pid=,args=", "-g", str(pgid)], capture_output=True,
                        text=True, check=False)  # fmt: skip
    return [line for line in ps.stdout.splitlines() if line.strip()]


def test_ctrl_c_during_sim_says_it_was_interrupted_and_stops_everything(tmp_path: Path) -> None:
    # it exited 1 with nothing at all on stderr: a user could not tell a crash from the key
    proc = subprocess.Popen(
        [sys.executable, "-m", "epc_offboard", "sim", "--out", str(tmp_path / "out"),
         "--gcs-port", "0", "--no-figure"],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, start_new_session=True,
        preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL),
    )  # fmt: skip
    assert proc.stdout is not None
    try:
        assert "SITL (system id 1)" in proc.stdout.readline()  # its processes are started
        os.killpg(proc.pid, signal.SIGINT)
        _out, err = proc.communicate(timeout=60)
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
    assert proc.returncode == 1, err
    assert "epc-offboard sim: interrupted (Ctrl-C)" in err
    assert "Traceback" not in err
    assert _group_alive(proc.pid) == []  # no SITL, service or helper left flying
