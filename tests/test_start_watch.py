"""A child's start judged by its progress (common/procstats.StartWatch), on real processes:
one running, however long, is starting; one SIGSTOPped is caught within its stall bound;
one gone is said. The bench's attackers' wait uses it (a SIGSTOPped attacker fails the
bench with the cause)."""

from __future__ import annotations

import contextlib
import os
import signal
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path

import pytest

from epc_offboard.common.procstats import StartWatch, progress
from epc_offboard.tools.bench_attack import AttackBenchError, Attackers

BUSY = "import time\nt = time.monotonic()\nwhile time.monotonic() - t < 60: pass\n"


@pytest.fixture
def busy():
    proc = subprocess.Popen([sys.executable, "-c", BUSY])
    yield proc
    proc.kill()
    proc.wait()


def _judge(watch: StartWatch, for_s: float) -> str | None:
    end = time.monotonic() + for_s
    while time.monotonic() < end:
        why = watch.verdict()
        if why is not None:
            return why
        time.sleep(0.05)
    return None


def test_a_running_child_is_starting_past_its_stall_bound_and_a_stopped_one_is_caught(busy):
    watch = StartWatch(busy.pid, stall_s=0.5, cap_s=600.0)
    assert _judge(watch, 2.0) is None  # four stall bounds, every one of them running
    os.kill(busy.pid, signal.SIGSTOP)
    t0 = time.monotonic()
    why = _judge(watch, 10.0)
    assert why is not None
    assert "stopped or wedged" in why, why
    assert time.monotonic() - t0 < 10.0


@contextlib.contextmanager
def _quota(pid: int, cpu_us_per_s: int) -> Iterator[None]:
    """``pid`` in a CPU cgroup of its own allowed ``cpu_us_per_s`` of CPU each second: once
    it has spent that, it waits in its run queue (state R) for the rest of the second, as
    a process queued behind CPU hogs does, without them (v1's cpu controller or v2's
    cpu.max; the test is skipped where neither can be made: not root)."""
    name = f"epc-start-watch-{os.getpid()}"
    v2, v1 = Path("/sys/fs/cgroup"), Path("/sys/fs/cgroup/cpu")
    controllers = v2 / "cgroup.controllers"
    try:
        if controllers.exists() and "cpu" in controllers.read_text().split():
            group = v2 / name
            group.mkdir()
            (group / "cpu.max").write_text(f"{cpu_us_per_s} 1000000")
        else:
            group = v1 / name
            group.mkdir()
            (group / "cpu.cfs_period_us").write_text("1000000")
            (group / "cpu.cfs_quota_us").write_text(str(cpu_us_per_s))
    except OSError as e:
        pytest.skip(f"no CPU cgroup of our own here: {e}")
    try:
        (group / "cgroup.procs").write_text(str(pid))
        yield
    finally:
        with contextlib.suppress(OSError):  # out again (to the parent group), then gone
            (group.parent / "cgroup.procs").write_text(str(pid))
        for _ in range(50):
            with contextlib.suppress(OSError):
                group.rmdir()
                break
            time.sleep(0.02)


def test_a_child_queued_for_a_cpu_past_its_stall_bound_is_starting(busy):
    """A wait in a run queue shows in the child's schedstat only when it ends: beside two
    CPU hogs a busy child went 0.6 s (nice 0) to 2.4 s (nice +10) with none of its
    progress figures changing, in state R all along, and the watch said "no CPU used or
    waited for" (stop 44: test_sharing's 0.5 s stall bound at load 8-12). Here a CPU
    quota holds it queued 0.999 s of each second: it is starting, state R, and a stop is
    still caught."""
    with _quota(busy.pid, 1000):
        watch = StartWatch(busy.pid, stall_s=0.3, cap_s=600.0)
        assert _judge(watch, 3.0) is None  # before: "no CPU used or waited for" at 0.35 s
        os.kill(busy.pid, signal.SIGSTOP)
        why = _judge(watch, 10.0)
        assert why is not None
        assert "stopped or wedged" in why, why


def test_a_running_child_not_up_in_the_cap_is_said(busy):
    watch = StartWatch(busy.pid, stall_s=5.0, cap_s=0.5)
    why = _judge(watch, 10.0)
    assert why is not None
    assert "though running" in why, why


def test_a_child_gone_is_said():
    proc = subprocess.Popen([sys.executable, "-c", "pass"])
    watch = StartWatch(proc.pid, stall_s=5.0, cap_s=600.0)
    proc.wait()
    assert progress(proc.pid) is None
    assert watch.verdict() == "it ended"


def test_a_child_waiting_for_a_starting_peer_is_starting_until_it_is_stopped(busy):
    """An attacker's session waits for the service's fleet helper: blocked, it uses no CPU,
    while the service's tree starts. It is starting while its peer moves; SIGSTOPped, it
    is caught though its peer still moves."""
    waiting = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(60)"])
    try:
        alone = StartWatch(waiting.pid, stall_s=0.5, cap_s=600.0)
        assert _judge(alone, 3.0) is not None  # blocked, no peer: no progress
        watch = StartWatch(waiting.pid, stall_s=0.5, cap_s=600.0, waits_on=busy.pid)
        assert _judge(watch, 2.0) is None
        os.kill(waiting.pid, signal.SIGSTOP)
        why = _judge(watch, 10.0)
        assert why is not None
        assert "stopped or wedged" in why, why
    finally:
        waiting.kill()
        waiting.wait()


def test_a_stopped_attacker_fails_the_bench_with_the_cause(tmp_path: Path):
    """Before stop 41 the wait gave each attacker 120 s on the clock: at load 12-17 their
    imports took longer (5 runs failed, "did not start"), and a stopped one was caught no
    sooner. Now a running one is waited for and a stopped one is said within its stall."""
    config = tmp_path / "service.toml"
    config.write_text("")
    attackers = Attackers(25099, config, tmp_path, ("replay",), window_s=1.0)
    try:
        os.kill(attackers.procs["replay"].pid, signal.SIGSTOP)
        with pytest.raises(AttackBenchError, match="replay attacker did not start: no CPU"):
            attackers.wait_ready(stall_s=1.0, cap_s=600.0)
    finally:
        for proc in attackers.procs.values():
            proc.kill()
            proc.wait()


def test_verdict_every_samples_at_most_so_often_and_says_what_verdict_says():
    """The loops' callers (the miss worker's pump, the fleet's turn) ask every
    WATCH_EVERY_S, not every tick: between two samples it reads no /proc and says nothing;
    a sample says what ``verdict`` says."""
    proc = subprocess.Popen([sys.executable, "-c", "pass"])
    watch = StartWatch(proc.pid, stall_s=5.0, cap_s=600.0)
    proc.wait()
    t0 = time.monotonic()
    assert watch.verdict_every(10.0, t0) == "it ended"
    assert watch.verdict_every(10.0, t0 + 9.9) is None  # not sampled
    assert watch.verdict_every(10.0, t0 + 10.0) == "it ended"
