"""The loopback ports `sim`, the benchmarks and the test rig hand to the processes they start.

The suite beside two CPU hogs once failed because a service could not bind the UDP port the
rig had probed free: between the probe and the bind, the kernel gave the same number to
another test's port-0 socket. Ports now come from outside the kernel's ephemeral range and
are reserved among our processes (real processes, real sockets, a real SIGKILL here).
"""

from __future__ import annotations

import random
import signal
import socket
import subprocess
import sys

import pytest

from epc_offboard.common import ports
from epc_offboard.common.ports import free_port, port_window


def test_the_kernel_never_hands_our_ports_to_a_port_zero_socket():
    low, high = (int(v) for v in ports.EPHEMERAL_RANGE.read_text().split())
    for _ in range(50):
        port = free_port()
        assert not low <= port <= high, f"{port} is in the ephemeral range {low}..{high}"
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
            s.bind(("127.0.0.1", port))  # free for UDP
        with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
            s.bind(("127.0.0.1", port))  # and for TCP (Zenoh)


CHOOSE = (
    "import sys\n"
    "from epc_offboard.common.ports import free_port\n"
    "print(*(free_port() for _ in range(int(sys.argv[1]))), flush=True)\n"
    "sys.stdin.read()\n"  # holds its reservations until told to end
)


def _chooser(count: int) -> subprocess.Popen[str]:
    return subprocess.Popen(
        [sys.executable, "-c", CHOOSE, str(count)],
        stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True,
    )  # fmt: skip


def _chosen(proc: subprocess.Popen[str]) -> list[int]:
    assert proc.stdout is not None
    return [int(v) for v in proc.stdout.readline().split()]


def test_processes_choosing_at_once_get_different_ports():
    procs = [_chooser(300) for _ in range(3)]
    try:
        chosen = [set(_chosen(p)) for p in procs]
    finally:
        for p in procs:
            p.communicate(timeout=30)
    assert [len(c) for c in chosen] == [300, 300, 300]
    assert not chosen[0] & chosen[1]
    assert not chosen[0] & chosen[2]
    assert not chosen[1] & chosen[2]


def _start_at(monkeypatch: pytest.MonkeyPatch, port: int) -> None:
    index = port_window().index(port)
    monkeypatch.setattr(random, "randrange", lambda n: index)


@pytest.mark.parametrize("kind", [socket.SOCK_DGRAM, socket.SOCK_STREAM])
def test_a_port_something_else_has_bound_is_skipped(monkeypatch, kind):
    chooser = _chooser(1)
    (target,) = _chosen(chooser)
    chooser.communicate(timeout=30)  # free, and its reservation ended with its process
    with socket.socket(socket.AF_INET, kind) as stranger:
        stranger.bind(("127.0.0.1", target))
        _start_at(monkeypatch, target)
        assert free_port() != target


def test_a_reservation_holds_until_its_process_is_killed(monkeypatch):
    holder = _chooser(1)
    try:
        (held,) = _chosen(holder)
        _start_at(monkeypatch, held)
        assert free_port() != held  # reserved by a live process
        holder.send_signal(signal.SIGKILL)
        holder.wait(timeout=10)
        _start_at(monkeypatch, held)
        assert free_port() == held  # a killed process frees what it held
    finally:
        holder.kill()
        holder.communicate()
