"""The service's process ends after "stopped", whatever its teardown waits for: a real
process whose teardown never ends (a non-daemon thread that waits forever, as a helper's
pipe once held a `sim`'s service for minutes) exits 1 within the grace, and its stderr (the
service's log) names where every thread was."""

from __future__ import annotations

import subprocess
import sys
import time

HANGS = """
import threading
from epc_offboard.service.service import bounded_exit

def stuck_in_teardown():
    threading.Event().wait()

threading.Thread(target=stuck_in_teardown, name="stuck").start()  # joined at exit: forever
bounded_exit(1.0)
"""


def test_a_teardown_that_hangs_ends_in_the_grace_with_every_threads_stack():
    t0 = time.monotonic()
    proc = subprocess.run([sys.executable, "-c", HANGS], capture_output=True, text=True,
                          timeout=120)  # fmt: skip
    took_s = time.monotonic() - t0
    assert proc.returncode == 1, proc.stderr
    assert "Timeout (0:00:01)!" in proc.stderr
    assert "in stuck_in_teardown" in proc.stderr  # the hanging thread, by its line
    assert took_s < 60.0  # the grace, the imports at load 6; without it: the 120 s timeout


def test_a_process_that_ends_in_time_is_not_touched():
    ends = "from epc_offboard.service.service import bounded_exit\nbounded_exit(30.0)\n"
    proc = subprocess.run([sys.executable, "-c", ends], capture_output=True, text=True,
                          timeout=120)  # fmt: skip
    assert proc.returncode == 0, proc.stderr
    assert "Timeout" not in proc.stderr
