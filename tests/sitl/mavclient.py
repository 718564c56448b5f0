"""Test helpers: start ``python -m sitl.main`` as a subprocess and talk to it with pymavlink.

The client binds an OS-chosen port and passes it as ``--offboard-port``; the SITL listens on
an OS-chosen port (``--listen-port 0``) that it prints on its first line. No fixed ports.
"""

from __future__ import annotations

import re
import socket
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

from pymavlink.dialects.v20 import common as mavlink

REPO = Path(__file__).resolve().parents[2]


class MavClient:
    """A blocking pymavlink client on a UDP socket (sans-IO codec, like a GCS or MAVSDK)."""

    def __init__(
        self, sysid: int = 245, key: bytes | None = None, sign: bool = True, port: int = 0
    ) -> None:
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.bind(("127.0.0.1", port))
        self.port: int = self.sock.getsockname()[1]
        self.out = _Sink()
        self.mav = mavlink.MAVLink(self.out, srcSystem=sysid, srcComponent=190)
        self.mav.robust_parsing = True
        if key is not None:
            self.mav.signing.secret_key = key
            self.mav.signing.timestamp = int((time.time() - 1420070400) * 1e5)
            self.mav.signing.sign_outgoing = sign
        self.target: tuple[str, int] | None = None
        self.last: dict[str, Any] = {}
        self.signed_received = 0

    def close(self) -> None:
        self.sock.close()

    def send(self, msg: Any) -> None:
        assert self.target is not None
        self.mav.send(msg)
        self.sock.sendto(self.out.data, self.target)

    def send_raw(self, data: bytes) -> None:
        assert self.target is not None
        self.sock.sendto(data, self.target)

    def poll(self, timeout_s: float) -> list[Any]:
        """Receive for up to ``timeout_s`` (returns early after the first datagram)."""
        self.sock.settimeout(max(timeout_s, 1e-4))
        try:
            data, _ = self.sock.recvfrom(65535)
        except TimeoutError:
            return []
        if len(data) > 12 and data[0] == 0xFD and data[2] & 0x01:
            self.signed_received += 1
        msgs = [m for m in (self.mav.parse_buffer(data) or []) if m.get_type() != "BAD_DATA"]
        for m in msgs:
            self.last[m.get_type()] = m
        return msgs

    def wait(
        self, mtype: str, cond: Callable[[Any], bool] = lambda m: True, timeout_s: float = 10.0
    ) -> Any:
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            for m in self.poll(deadline - time.monotonic()):
                if m.get_type() == mtype and cond(m):
                    return m
        raise TimeoutError(f"no {mtype} matching within {timeout_s} s")

    def command(self, command: int, *params: float, timeout_s: float = 5.0) -> int:
        p = [*params, *([0.0] * (7 - len(params)))]
        self.send(self.mav.command_long_encode(1, 1, command, 0, *p))
        ack = self.wait("COMMAND_ACK", lambda m: m.command == command, timeout_s)
        return int(ack.result)

    def attitude_setpoint(
        self,
        thrust: float,
        q: tuple[float, float, float, float] = (1.0, 0.0, 0.0, 0.0),
        time_boot_ms: int = 0,
        type_mask: int = 0b00000111,
    ) -> None:
        self.send(
            self.mav.set_attitude_target_encode(
                time_boot_ms, 1, 1, type_mask, list(q), 0.0, 0.0, 0.0, thrust
            )
        )

    def pump(
        self,
        until: Callable[[Any], bool],
        setpoint: Callable[[int], tuple[float, tuple[float, float, float, float]]] | None,
        timeout_s: float = 20.0,
    ) -> Any:
        """Lockstep responder: answer every state message with ``setpoint(time_boot_ms)``
        (thrust, q), stamped with that message's time, until ``until(msg)`` holds for a
        received message. ``setpoint=None`` answers nothing (the controller went silent)."""
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            msgs = self.poll(deadline - time.monotonic())
            stamps = [s for s in map(state_stamp_ms, msgs) if s is not None]
            if setpoint is not None and stamps:  # a datagram is one tick: answer it whole
                thrust, q = setpoint(max(stamps))
                self.attitude_setpoint(thrust, q, time_boot_ms=max(stamps))
            for m in msgs:
                if until(m):
                    return m
        raise TimeoutError(f"condition not met within {timeout_s} s")

    def command_while_pumping(
        self,
        command: int,
        params: tuple[float, ...],
        setpoint: Callable[[int], tuple[float, tuple[float, float, float, float]]] | None,
    ) -> int:
        p = [*params, *([0.0] * (7 - len(params)))]
        self.send(self.mav.command_long_encode(1, 1, command, 0, *p))
        ack = self.pump(lambda m: m.get_type() == "COMMAND_ACK" and m.command == command, setpoint)
        return int(ack.result)


class _Sink:
    data = b""

    def write(self, buf: bytes) -> None:
        self.data = bytes(buf)


def state_stamp_ms(msg: Any) -> int | None:
    """The vehicle time of a state message (what a lockstep answer must reach), else None."""
    mtype = msg.get_type()
    if mtype in ("ATTITUDE", "ATTITUDE_QUATERNION", "LOCAL_POSITION_NED"):
        return int(msg.time_boot_ms)
    if mtype == "ODOMETRY":
        return int(msg.time_usec // 1000)
    return None


def custom_main_sub(hb: Any) -> tuple[int, int]:
    return (hb.custom_mode >> 16) & 0xFF, (hb.custom_mode >> 24) & 0xFF


def start_sitl(client: MavClient, *args: str) -> subprocess.Popen[str]:
    """Start the SITL sending telemetry to ``client``; sets ``client.target`` to its port."""
    proc = subprocess.Popen(
        [
            sys.executable,
            "-m",
            "sitl.main",
            "--listen-port",
            "0",
            "--gcs-port",
            "0",
            "--offboard-port",
            str(client.port),
            *args,
        ],
        cwd=REPO,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    assert proc.stdout is not None
    line = proc.stdout.readline()
    found = re.search(r"listening udp 127\.0\.0\.1:(\d+)", line)
    if found is None:
        proc.kill()
        raise RuntimeError(
            f"SITL did not start: {line!r} {proc.stderr.read() if proc.stderr else ''}"
        )
    client.target = ("127.0.0.1", int(found.group(1)))
    return proc


def stop_sitl(proc: subprocess.Popen[str], timeout_s: float = 10.0) -> tuple[int, str]:
    """SIGTERM, wait, return (exit code, stderr)."""
    if proc.poll() is None:
        proc.terminate()
    _, err = proc.communicate(timeout=timeout_s)
    return proc.returncode, err


def counters_from(stderr: str) -> dict[str, int]:
    line = next(ln for ln in stderr.splitlines() if "counters" in ln)
    return {k: int(v) for k, v in re.findall(r"(\w+)=(\d+)", line)}
