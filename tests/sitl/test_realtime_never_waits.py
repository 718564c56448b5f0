"""In real time (no ``--lockstep``) the SITL never waits for its controller, as PX4 never
waits for a companion computer: a controller that stops (SIGSTOP) finds, when it resumes,
that the vehicle's clock and telemetry went on without it. A ground station watching the
same SITL sees the streams flow, stamps advancing with the wall clock, through the stop."""

from __future__ import annotations

import itertools
import os
import signal
import subprocess
import sys
import textwrap
import time

import pytest

from epc_offboard.common.ports import free_port
from tests.sitl.mavclient import REPO, MavClient, counters_from, start_sitl, stop_sitl

pytestmark = pytest.mark.timeout(60)

# The controller: reads its telemetry and streams a hover setpoint at 50 Hz, forever.
CONTROLLER = textwrap.dedent(
    """
    import socket, sys, time
    from pymavlink.dialects.v20 import common as mavlink
    class Sink:
        data = b""
        def write(self, buf): self.data = bytes(buf)
    own_port, sitl_port = int(sys.argv[1]), int(sys.argv[2])
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    sock.bind(("127.0.0.1", own_port))
    sock.setblocking(False)
    sink = Sink()
    mav = mavlink.MAVLink(sink, srcSystem=245, srcComponent=190)
    print("up", flush=True)
    while True:
        try:
            while True:
                sock.recvfrom(65535)
        except BlockingIOError:
            pass
        mav.send(mav.set_attitude_target_encode(0, 1, 1, 0b111, [1, 0, 0, 0], 0, 0, 0, 0.5))
        sock.sendto(sink.data, ("127.0.0.1", sitl_port))
        time.sleep(0.02)
    """
)


def test_real_time_streams_on_while_the_controller_is_stopped():
    observer = MavClient()  # a ground station on the SITL's GCS port
    controller_port = free_port()
    # (the last --offboard-port wins: the offboard link goes to the controller)
    sitl = start_sitl(observer, "--offboard-port", str(controller_port),
                      "--gcs-port", str(observer.port))  # fmt: skip
    assert observer.target is not None
    controller = subprocess.Popen(
        [sys.executable, "-c", CONTROLLER, str(controller_port), str(observer.target[1])],
        cwd=REPO, stdout=subprocess.PIPE, text=True,
    )  # fmt: skip
    try:
        assert controller.stdout is not None
        assert controller.stdout.readline().strip() == "up"
        observer.wait("ATTITUDE", timeout_s=10.0)
        time.sleep(0.5)  # the controller streaming
        while observer.poll(0.0):  # what was sent before the stop is not evidence
            pass
        os.kill(controller.pid, signal.SIGSTOP)
        stopped_s = 1.5
        arrivals: list[tuple[float, int]] = []  # (wall s, time_boot_ms) of each ATTITUDE
        deadline = time.monotonic() + stopped_s
        while time.monotonic() < deadline:
            for m in observer.poll(deadline - time.monotonic()):
                if m.get_type() == "ATTITUDE":
                    arrivals.append((time.monotonic(), int(m.time_boot_ms)))
        os.kill(controller.pid, signal.SIGCONT)
    finally:
        controller.kill()
        controller.wait(timeout=10)
        code, err = stop_sitl(sitl)
        observer.close()
    assert code == 0, err
    assert counters_from(err)["lockstep_timeouts"] == 0
    # safety bounds for a loaded 2-core machine: ATTITUDE is 100 Hz by default
    assert len(arrivals) >= 0.3 * 100 * stopped_s
    walls = [w for w, _ in arrivals]
    assert max(b - a for a, b in itertools.pairwise(walls)) < 0.5  # never held
    stamps = [t for _, t in arrivals]
    assert all(b > a for a, b in itertools.pairwise(stamps))
    vehicle_s = (stamps[-1] - stamps[0]) / 1000.0
    assert vehicle_s > 0.5 * (walls[-1] - walls[0])  # the vehicle's clock ran on
