"""What a systemd user relies on, end to end: Type=notify readiness, STATUS= lines, watchdog
pings while the control loop runs, SIGHUP reloads without dropping the loops (and refuses a
bad config), SIGTERM says STOPPING=1 and exits 0. Real SITL and service processes, lockstep,
a real NOTIFY_SOCKET (a unix datagram socket, as systemd gives the service).
"""

from __future__ import annotations

import contextlib
import csv
import signal
import socket
import threading
import time

import pytest

from epc_offboard.common.configio import dump_toml, merge_dicts
from epc_offboard.vehicle.dialect_px4 import PX4_MAIN_MODE_OFFBOARD, px4_modes
from tests.rig import Rig

pytestmark = pytest.mark.timeout(180)

OFFBOARD = (PX4_MAIN_MODE_OFFBOARD, 0)


class Notify:
    """systemd's side of NOTIFY_SOCKET. A reader thread drains it all the time, as systemd
    does: a unix datagram queue holds only net.unix.max_dgram_qlen messages (10 here), and
    the service, rightly, drops a notification rather than block its loop on a full one."""

    def __init__(self, path):
        self.sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
        self.sock.bind(str(path))
        self.sock.settimeout(0.05)
        self.lines: list[str] = []
        self._received: list[str] = []
        self._lock = threading.Lock()
        self._closed = threading.Event()
        self._reader = threading.Thread(target=self._read, daemon=True)
        self._reader.start()

    def _read(self) -> None:
        while not self._closed.is_set():
            with contextlib.suppress(TimeoutError, OSError):
                lines = self.sock.recv(4096).decode().splitlines()
                with self._lock:
                    self._received += lines

    def pump(self, seconds: float) -> list[str]:
        """Everything received so far plus for ``seconds`` more (added to ``lines``)."""
        time.sleep(seconds)
        with self._lock:
            got, self._received = self._received, []
        self.lines += got
        return got

    def close(self):
        self._closed.set()
        self._reader.join(timeout=1.0)
        self.sock.close()


def wait_log(rig: Rig, text: str, timeout_s: float = 20.0) -> None:
    end = time.monotonic() + timeout_s
    while text not in rig.log():
        assert rig.service is not None
        assert rig.service.poll() is None, rig.log()
        assert time.monotonic() < end, f"{text!r} not logged:\n{rig.log()}"
        time.sleep(0.1)


def refs_since(path, t_s: float) -> list[tuple[float, float]]:
    with path.open(newline="") as fh:
        rows = [r for r in csv.DictReader(fh) if r.get("phase") == "offboard"]
    return [
        (float(r["ref_pos_n_m"]), float(r["ref_pos_e_m"]))
        for r in rows
        if r["t_s"] and float(r["t_s"]) >= t_s
    ]


def test_notify_watchdog_and_sighup_reload(tmp_path, monkeypatch):
    notify = Notify(tmp_path / "notify.sock")
    monkeypatch.setenv("NOTIFY_SOCKET", str(tmp_path / "notify.sock"))
    try:
        with Rig(tmp_path, service_overrides={"loops": {"watchdog_period_s": 0.2}}) as rig:
            rig.wait_mode(*OFFBOARD)
            notify.pump(1.5)
            assert "READY=1" in notify.lines
            assert any(x.startswith("STATUS=offboard") for x in notify.lines), notify.lines
            assert notify.lines.count("WATCHDOG=1") >= 3  # 0.2 s period over 1.5 s

            # reload: a circle instead of the hover, without dropping the loops
            circle = {"trajectory": {"shape": "circle", "radius_m": 0.6, "period_s": 6.0}}
            rig.config_path.write_text(dump_toml(merge_dicts(rig.config, circle)))
            assert rig.service is not None
            rig.service.send_signal(signal.SIGHUP)
            wait_log(rig, "SIGHUP: trajectory, mission and offboard settings reloaded")
            pings = notify.pump(3.0).count("WATCHDOG=1")
            assert pings >= 8  # the loops never stopped
            mode = rig.heartbeat()
            assert px4_modes(mode.custom_mode) == OFFBOARD

            # a bad config on SIGHUP is refused, naming the key; the flight goes on
            bad = merge_dicts(rig.config, {"trajectory": {"radius_mm": 3.0}})
            rig.config_path.write_text(dump_toml(bad))
            rig.service.send_signal(signal.SIGHUP)
            wait_log(rig, "config not reloaded")
            assert "trajectory.radius_mm" in rig.log()
            assert notify.pump(1.0).count("WATCHDOG=1") >= 3
            assert px4_modes(rig.heartbeat().custom_mode) == OFFBOARD

            code, _ = rig.stop_service(signal.SIGTERM)
            assert code == 0
            notify.pump(0.3)
            assert "STOPPING=1" in notify.lines
    finally:
        notify.close()
    # the reference the service tracked after the reload went round the circle
    refs = refs_since(tmp_path / "flight.csv", 0.0)
    north = [n for n, _ in refs]
    assert max(north) - min(north) > 0.8  # a 0.6 m radius spans 1.2 m; the hover spans 0
