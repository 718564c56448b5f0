"""Loopback ports for the processes one command starts (`sim`, the benchmarks, the test rig).

The usual trick, bind port 0, read the number, close, hand the number on, races: until the
process it is handed to binds it, the kernel may give the same number to any socket on the
machine that binds port 0 or connects, because it came from the kernel's ephemeral range.
(Seen in the suite beside two CPU hogs: a service could not bind its UDP port, "already in
use", taken by another test's client socket.)

So a port comes from a window below the ephemeral range (``ip_local_port_range``), where the
kernel never picks numbers on its own, and is reserved among our own processes by a ``flock``
on a file named after it. The lock is held by the process that took the port (a kernel lock:
a killed process frees it) until that process has taken ``HELD_PER_PROCESS`` more, by which
time the flight that used it has ended. A port something else has bound, UDP or TCP, is
skipped.
"""

from __future__ import annotations

import collections
import contextlib
import fcntl
import os
import random
import socket
import tempfile
from pathlib import Path

from epc_offboard.common.errors import EpcError

WINDOW_LOW = 24576  # above the fixed ports people give tools (7447, 14540, 14550, 5760, 18570)
EPHEMERAL_RANGE = Path("/proc/sys/net/ipv4/ip_local_port_range")
DEFAULT_EPHEMERAL_RANGE = (32768, 60999)  # Linux's default, when the range cannot be read
MIN_WINDOW = 256
HELD_PER_PROCESS = 512

_held: collections.deque[int] = collections.deque()  # lock file descriptors, oldest first


class NoFreePortError(EpcError, RuntimeError):
    pass


def ephemeral_range() -> tuple[int, int]:
    """The lowest and highest port the kernel hands out by itself."""
    try:
        low, high = (int(v) for v in EPHEMERAL_RANGE.read_text().split()[:2])
    except (OSError, ValueError):
        return DEFAULT_EPHEMERAL_RANGE
    return low, high


def port_window() -> range:
    """The ports :func:`free_port` chooses from: below the ephemeral range, or when that is
    too low to leave a window, above it."""
    low, high = ephemeral_range()
    if low - WINDOW_LOW >= MIN_WINDOW:
        return range(WINDOW_LOW, low)
    if 65535 - high >= MIN_WINDOW:
        return range(high + 1, 65536)
    raise NoFreePortError(
        f"no port window outside the kernel's ephemeral range "
        f"({EPHEMERAL_RANGE}: {low}..{high}): narrow it to leave {MIN_WINDOW} ports"
    )


def _lock_dir() -> Path:
    path = Path(tempfile.gettempdir()) / f"epc-offboard-ports-{os.getuid()}"
    path.mkdir(exist_ok=True)
    return path


def _bindable(port: int) -> bool:
    for kind in (socket.SOCK_DGRAM, socket.SOCK_STREAM):
        with socket.socket(socket.AF_INET, kind) as s:
            try:
                s.bind(("127.0.0.1", port))
            except OSError:
                return False
    return True


def _reserve(port: int, folder: Path) -> bool:
    fd = os.open(folder / str(port), os.O_RDWR | os.O_CREAT, 0o600)
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except OSError:
        os.close(fd)
        return False
    if not _bindable(port):
        fcntl.flock(fd, fcntl.LOCK_UN)
        os.close(fd)
        return False
    _held.append(fd)
    while len(_held) > HELD_PER_PROCESS:
        with contextlib.suppress(OSError):
            os.close(_held.popleft())  # closing the descriptor drops its lock
    return True


def free_port() -> int:
    """A loopback port free for UDP and TCP that no other process of ours is handed while
    this one holds it, and that the kernel does not hand out to port-0 binds."""
    window = port_window()
    folder = _lock_dir()
    start = random.randrange(len(window))
    for i in range(len(window)):
        port = window[(start + i) % len(window)]
        if _reserve(port, folder):
            return port
    raise NoFreePortError(f"every port in {window.start}..{window.stop - 1} is taken or reserved")
