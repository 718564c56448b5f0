"""A service started beside a streaming autopilot reads no start-up backlog as a time jump.

A real PX4 streams its onboard link from boot. Flown against PX4 main + SIH (issue 20), the
service bound its UDP port and then finished starting (the garbage collector's freeze: 1.1-
1.9 s on a machine at load 40-70) before its loop read anything: the socket queued that much
of PX4's stream, read it as one burst whose stamps ran ahead of their receipt by more than
``max_time_jump_s``, and took the fresh samples after it for a new timeline ("5 consecutive
samples on another timeline ... resynchronised (autopilot reboot or a bad stamp earlier)")
on 7 of 9 starts. Here the freeze is slowed to what that load made it, and a sender streams
PX4's ATTITUDE (stamped with its boot clock) from before the service starts: nothing may be
resynchronised.
"""

from __future__ import annotations

import asyncio
import threading
import time
from pathlib import Path

import pytest
from pymavlink.dialects.v20 import common as mavlink

from epc_offboard.common.ports import free_port
from epc_offboard.service import realtime
from epc_offboard.service.config import load_service_config
from epc_offboard.service.service import Service

pytestmark = pytest.mark.timeout(180)

FREEZE_S = 1.9  # the gc freeze beside a real PX4 at load 40-70 (1.1-1.9 s)


class Px4Stream:
    """HEARTBEAT at 1 Hz, ATTITUDE at 100 Hz stamped with a boot clock and ATTITUDE_TARGET
    at 400 Hz (PX4's onboard link sends about 500 datagrams a second: the socket's default
    buffer, 208 KiB, holds about half a second of them, and drops the newer ones), from
    system 1 to ``port`` (dropped by the kernel until the service binds it, as PX4's are)."""

    def __init__(self, port: int) -> None:
        import socket

        self._sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self._dest = ("127.0.0.1", port)
        self._mav = mavlink.MAVLink(None, srcSystem=1, srcComponent=1)
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="px4-stream", daemon=True)

    def __enter__(self) -> Px4Stream:
        self._thread.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self._stop.set()
        self._thread.join(5.0)
        self._sock.close()

    def _send(self, msg: mavlink.MAVLink_message) -> None:
        self._sock.sendto(msg.pack(self._mav), self._dest)

    def _run(self) -> None:
        boot = time.monotonic()
        next_hb = boot
        while not self._stop.is_set():
            now = time.monotonic()
            if now >= next_hb:
                next_hb += 1.0
                self._send(mavlink.MAVLink_heartbeat_message(
                    mavlink.MAV_TYPE_QUADROTOR, mavlink.MAV_AUTOPILOT_PX4, 0, 0,
                    mavlink.MAV_STATE_STANDBY, 3))  # fmt: skip
            boot_ms = int((now - boot) * 1000.0)
            self._send(mavlink.MAVLink_attitude_message(boot_ms, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0))
            for _ in range(4):
                self._send(mavlink.MAVLink_attitude_target_message(
                    boot_ms, 0, [1.0, 0.0, 0.0, 0.0], 0.0, 0.0, 0.0, 0.5))  # fmt: skip
            time.sleep(0.01)


def test_a_slow_start_reads_no_backlog_as_a_time_jump(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    port = free_port()
    config = tmp_path / "service.toml"
    config.write_text(f'[link]\nurl = "udpin://127.0.0.1:{port}"\n\n[loops]\nclock = "wall"\n')
    cfg = load_service_config(config)

    freeze = realtime.freeze_startup_objects

    def slow_freeze() -> int:  # what a loaded machine made of the collect and freeze
        time.sleep(FREEZE_S)
        return freeze()

    monkeypatch.setattr(realtime, "freeze_startup_objects", slow_freeze)

    async def fly() -> Service:
        service = Service(cfg)
        run = asyncio.create_task(service.run())
        deadline = time.monotonic() + 120.0
        # until ATTITUDE is read (after the start-up and the worker's imports), then 1 s of it
        tracker = service.tracker
        while tracker.vehicle_time_at(time.monotonic(), vehicle_clock=False) is None:
            assert not run.done(), "the service stopped before reading ATTITUDE"
            assert time.monotonic() < deadline, "no ATTITUDE read in 120 s"
            await asyncio.sleep(0.05)
        await asyncio.sleep(1.0)
        service.request_stop()
        await asyncio.wait_for(run, 30.0)
        return service

    with Px4Stream(port):
        service = asyncio.run(fly())
    counters = service.tracker.counters
    assert counters["time_resyncs"] == 0, dict(counters)
    assert counters["rejected_time_jump"] == 0, dict(counters)
