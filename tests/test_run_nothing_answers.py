"""`epc-offboard run` where nothing answers, as a new user meets it (a wrong port, the
autopilot not up yet): the service holds, says after a few seconds what it waits for and what
the link receives, and Ctrl-C in the terminal (SIGINT to the whole process group: the
service, its helpers, the background compile) stops it with exit 0 and no traceback.

A real `run` process on a free UDP port with nothing behind it, on an empty kernel cache (the
background compile's process is up, as on a first start)."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import threading
from pathlib import Path

from epc_offboard.common.ports import free_port
from epc_offboard.service.supervisor import WAITING_WARN_FIRST_S

ROOT = Path(__file__).resolve().parent.parent


def test_nothing_answering_is_said_and_ctrl_c_stops_every_process_without_a_traceback(
    tmp_path: Path,
) -> None:
    port = free_port()
    config = (ROOT / "config" / "sitl.toml").read_text()
    config = config.replace("udpin://127.0.0.1:14540", f"udpin://127.0.0.1:{port}")
    config = config.replace("out/sitl-service/library.sqlite", str(tmp_path / "lib.sqlite"))
    (tmp_path / "service.toml").write_text(config)
    env = dict(os.environ, NUMBA_CACHE_DIR=str(tmp_path / "numba"), PYTHONUNBUFFERED="1")
    env.pop("EPC_OFFBOARD_JIT", None)
    proc = subprocess.Popen(
        [sys.executable, "-m", "epc_offboard", "run", "--config", str(tmp_path / "service.toml")],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env,
        start_new_session=True,  # its own process group, as a terminal's foreground job
    )  # fmt: skip
    lines: list[str] = []
    said = threading.Event()

    def read() -> None:
        assert proc.stderr is not None
        for line in proc.stderr:
            lines.append(line)
            if "no HEARTBEAT from the autopilot" in line:
                said.set()

    reader = threading.Thread(target=read, daemon=True)
    reader.start()
    try:
        # the warm-up on numpy twins, then WAITING_WARN_FIRST_S of silence (load 6: slack)
        assert said.wait(WAITING_WARN_FIRST_S + 110.0), "".join(lines)
        os.killpg(proc.pid, signal.SIGINT)  # Ctrl-C
        code = proc.wait(timeout=30)
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait()
    reader.join(timeout=10)
    err = "".join(lines)
    warning = next(line for line in lines if "no HEARTBEAT from the autopilot" in line)
    assert f"udpin://127.0.0.1:{port}" in warning  # where it listens
    assert "nothing received" in warning  # and what it hears there
    assert " WARNING " in warning
    assert code == 0, err
    assert "Traceback" not in err, err
    assert "KeyboardInterrupt" not in err, err
    assert "stopped, its helpers " in err  # the orderly stop ran
