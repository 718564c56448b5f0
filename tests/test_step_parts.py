"""The control steps timed part by part (``service/step_parts.py``), numba's compiles counted,
and the bench's attribution naming the part of a slow step (issue 21's bursts)."""

from __future__ import annotations

import resource
import threading
import time

import numba
import numpy as np

from epc_offboard.common import jit
from epc_offboard.service.step_parts import CompileCounter, StepParts
from epc_offboard.tools.attack_analysis import slow_parts, slow_steps_summary


def _busy(s: float) -> None:
    """The thread's own CPU for ``s`` (not a sleep: a slow step is CPU)."""
    end = time.thread_time() + s
    while time.thread_time() < end:
        pass


def test_a_slow_step_is_kept_with_its_parts_and_a_fast_one_is_not() -> None:
    parts = StepParts("position", ("state", "pump", "tick"), slow_s=0.004)
    parts.start(1.0)
    parts.part(0)
    parts.part(1)
    parts.part(2)
    assert parts.finish() is None
    assert parts.count == 0
    assert not parts.slow
    parts.start(2.0)
    parts.part(0)
    _busy(0.010)  # the pump's
    parts.part(1)
    parts.part(2)
    step = parts.finish()
    assert step is not None
    assert parts.count == 1
    assert list(parts.slow) == [step]
    assert step.loop == "position"
    assert step.t_s == 2.0
    assert step.slowest_part == "pump"
    assert step.parts_ms["pump"] >= 9.0
    assert step.parts_ms["tick"] < 5.0
    assert step.thread_cpu_ms >= 9.0
    assert step.wall_ms >= step.parts_ms["pump"]
    d = step.as_dict()
    assert set(d) == {"loop", "t_s", "wall_ms", "thread_cpu_ms", "parts_ms", "slowest_part",
                      "compiles", "voluntary_switches", "involuntary_switches",
                      "major_faults"}  # fmt: skip
    assert d["voluntary_switches"] is None  # started without the thread's rusage: not known
    # the next step starts its parts from 0: a part skipped in it (no tick) stays 0
    parts.start(3.0)
    parts.part(0)
    _busy(0.010)
    parts.part(1)
    step = parts.finish()
    assert step is not None
    assert step.parts_ms["tick"] == 0.0
    assert step.parts_ms["state"] < 5.0


def test_a_slow_step_says_whether_the_thread_slept_in_it_or_never_left_its_cpu() -> None:
    """Issue 21: a step's wall time beyond its CPU time is a sleep of ours only if the
    thread switched out voluntarily in it; a step that never switched out lost that time
    to the hypervisor (steal). The switches are counted from the rusage the step started
    with (the loop reads it for each tick), in a real thread that blocks on a real lock."""
    parts = StepParts("position", ("state", "tick"), slow_s=0.002)
    lock = threading.Lock()
    lock.acquire()
    releaser = threading.Timer(0.015, lock.release)
    parts.start(1.0, resource.getrusage(resource.RUSAGE_THREAD))
    parts.part(0)
    releaser.start()
    lock.acquire()  # the thread blocks ~15 ms: a voluntary switch
    parts.part(1)
    slept = parts.finish()
    releaser.join()
    assert slept is not None
    assert slept.voluntary_switches is not None
    assert slept.voluntary_switches >= 1
    assert slept.wall_ms - slept.thread_cpu_ms >= 10.0
    assert slept.major_faults == 0
    # the thread's own CPU, no blocking call: no voluntary switch (a preemption may come)
    parts.start(2.0, resource.getrusage(resource.RUSAGE_THREAD))
    parts.part(0)
    _busy(0.010)
    parts.part(1)
    busy = parts.finish()
    assert busy is not None
    assert busy.voluntary_switches == 0
    assert busy.as_dict()["voluntary_switches"] == 0
    assert slept.as_dict()["voluntary_switches"] == slept.voluntary_switches


def test_kept_steps_are_bounded() -> None:
    parts = StepParts("attitude", ("state",), slow_s=0.0, kept=3)
    for k in range(10):
        parts.start(float(k))
        parts.part(0)
        _busy(1e-4)
        parts.finish()
    assert parts.count == 10
    assert [s.t_s for s in parts.slow] == [7.0, 8.0, 9.0]


def test_compiles_are_counted_and_calls_of_compiled_functions_are_not() -> None:
    @numba.njit(cache=False)
    def twice(x):
        return 2.0 * x

    counter = CompileCounter()
    assert counter.install()
    try:
        before = counter.count
        twice(np.ones(3))  # compiled now: counted
        assert counter.count == before + 1
        assert counter.longest_ms >= 0.5
        for _ in range(100):  # compiled: the lock is not taken
            twice(np.ones(3))
        # jit.entry_point of a compiled signature takes the lock for microseconds: no compile
        jit.entry_point(twice, np.ones(3))
        assert counter.count == before + 1
        twice(np.ones((2, 2)))  # a new signature met: a compile
        assert counter.count == before + 2
        # a step that meets it says so, and is kept whatever its time
        parts = StepParts("position", ("tick",), slow_s=10.0, compiles=counter)
        parts.start(0.0)
        twice(np.ones((2, 2, 2)))
        parts.part(0)
        step = parts.finish()
        assert step is not None
        assert step.compiles == 1
    finally:
        counter.uninstall()
    twice(np.ones(4, dtype=np.int64))  # uninstalled: not counted
    assert counter.count == before + 3


def test_the_attribution_names_the_part_of_the_slow_steps_in_an_interval() -> None:
    steps = [
        {"loop": "position", "t_s": 10.00, "thread_cpu_ms": 30.0, "compiles": 0,
         "parts_ms": {"state": 0.1, "pump": 25.0, "tick": 4.0}},
        {"loop": "attitude", "t_s": 10.02, "thread_cpu_ms": 6.0, "compiles": 1,
         "parts_ms": {"state": 0.1, "command": 6.0}},
        {"loop": "position", "t_s": 11.00, "thread_cpu_ms": 9.0, "compiles": 0,
         "parts_ms": {"state": 0.1, "pump": 0.0, "tick": 9.0}},
    ]  # fmt: skip
    # a miss: its interval runs from the previous tick's start to its own end
    ev = {"t_s": 10.03, "interval_ms": 50.0, "compute_ms": 5.0, "deadline_miss": True}
    out = slow_parts(steps, ev)
    assert out["slow_steps"] == 2
    assert out["slow_steps_cpu_ms"] == 36.0
    assert out["slow_part"] == "position.pump"
    assert out["slow_steps_compiles"] == 1
    assert out["slow_parts_ms"] == {"position.state": 0.1, "position.pump": 25.0,
                                    "position.tick": 4.0, "attitude.state": 0.1,
                                    "attitude.command": 6.0}  # fmt: skip
    none = slow_parts(steps, {"t_s": 20.0, "interval_ms": 15.0})
    assert none["slow_steps"] == 0
    assert none["slow_part"] == ""
    # steps of a service that did not count switches: none known, nothing slept or stolen
    assert out["slow_steps_voluntary_switches"] is None
    assert out["slow_steps_slept_ms"] == out["slow_steps_stolen_ms"] == 0.0


def test_the_attribution_splits_a_steps_off_cpu_time_by_how_the_thread_left_its_cpu() -> None:
    """The wall time beyond the CPU time of a step that switched out voluntarily is slept
    (ours); of one that never switched out, stolen (the hypervisor's); a step preempted
    (involuntary only) is neither: its run-queue wait is the stall's."""
    def step(t_s: float, wall: float, cpu: float, vol: int, invol: int) -> dict[str, object]:
        return {"loop": "position", "t_s": t_s, "wall_ms": wall, "thread_cpu_ms": cpu,
                "compiles": 0, "parts_ms": {"tick": wall}, "voluntary_switches": vol,
                "involuntary_switches": invol, "major_faults": 0}  # fmt: skip

    steps = [step(10.000, 6.0, 0.7, 1, 0), step(10.010, 5.5, 0.5, 0, 0),
             step(10.020, 4.0, 1.0, 0, 2)]  # fmt: skip
    out = slow_parts(steps, {"t_s": 10.025, "interval_ms": 40.0})
    assert out["slow_steps"] == 3
    assert out["slow_steps_voluntary_switches"] == 1
    assert out["slow_steps_involuntary_switches"] == 2
    assert out["slow_steps_slept_ms"] == 5.3
    assert out["slow_steps_stolen_ms"] == 5.0


def test_the_bench_summary_names_the_slow_parts_and_the_bursts() -> None:
    slow = {"position": 3, "attitude": 1, "compiles_after_warm_up": 0, "steps": [
        {"loop": "position", "t_s": 1.0, "thread_cpu_ms": 25.0, "slowest_part": "pump_offer"},
        {"loop": "position", "t_s": 2.0, "thread_cpu_ms": 3.0, "slowest_part": "tick"},
        {"loop": "attitude", "t_s": 3.0, "thread_cpu_ms": 1.5, "slowest_part": "send"},
    ]}  # fmt: skip
    line = slow_steps_summary(slow)
    assert "position 3, attitude 1" in line
    assert "over 20 ms of CPU 1" in line
    assert line.endswith("position.pump_offer 1 (max 25.0 ms CPU), position.tick 1 (max 3.0 ms "
                         "CPU), attitude.send 1 (max 1.5 ms CPU)")  # fmt: skip
    assert "not traced" in slow_steps_summary({})


def test_the_service_marks_each_part_by_its_name_never_by_a_number() -> None:
    """``Service``'s steps mark their parts through indices named from ``POSITION_PARTS`` /
    ``ATTITUDE_PARTS``: each name maps to its own index, the pump's three phases follow its
    first in order, no step marks a part by a bare number, and every part is marked."""
    import ast
    import inspect

    from epc_offboard.service import service as svc

    position = {"state": svc._P_STATE, "pump_collect": svc._P_PUMP,
                "rate_gate": svc._P_RATE_GATE, "reference": svc._P_REFERENCE,
                "tick": svc._P_TICK, "log_row": svc._P_LOG_ROW, "hand_over": svc._P_HAND_OVER}
    attitude = {"state": svc._A_STATE, "command": svc._A_COMMAND, "send": svc._A_SEND}
    for name, i in position.items():
        assert svc.POSITION_PARTS[i] == name
    for name, i in attitude.items():
        assert svc.ATTITUDE_PARTS[i] == name
    pump = svc.POSITION_PARTS[svc._P_PUMP:svc._P_PUMP + 3]
    assert pump == ("pump_collect", "pump_offer", "pump_submit")  # MissSolver.pump's phases
    tree = ast.parse(inspect.getsource(svc))
    args = [c.args[0] for c in ast.walk(tree) if isinstance(c, ast.Call)
            and isinstance(c.func, ast.Attribute) and c.func.attr == "part"]  # fmt: skip
    assert args
    names = {n.id for a in args for n in ast.walk(a) if isinstance(n, ast.Name)}
    assert all(not isinstance(a, ast.Constant) and any(isinstance(n, ast.Name)
               for n in ast.walk(a)) for a in args), "a part marked by a number"  # fmt: skip
    marked_p = {getattr(svc, n) for n in names if n.startswith("_P_")}
    marked_p |= {svc._P_PUMP + k for k in range(3)}
    marked_a = {getattr(svc, n) for n in names if n.startswith("_A_")}
    assert marked_p == set(range(len(svc.POSITION_PARTS)))
    assert marked_a == set(range(len(svc.ATTITUDE_PARTS)))


def test_a_hold_of_the_compiler_lock_preempted_or_waiting_is_not_a_compile() -> None:
    """A lookup of a compiled signature holds numba's compiler lock for microseconds; on a
    busy host its thread can be preempted in the hold for milliseconds (CI counted one
    such hold as a compile). A hold counts by the CPU its thread ran in it, as a compile
    or a cache load does, not by its wall time. The holds here are numba's own events."""
    from numba.core import event

    counter = CompileCounter()
    assert counter.install()
    try:
        event.start_event("numba:compiler_lock")
        time.sleep(0.020)  # off the CPU 20 ms in the hold: not a compile
        event.end_event("numba:compiler_lock")
        assert counter.count == 0
        event.start_event("numba:compiler_lock")
        _busy(0.005)  # 5 ms of the thread's CPU: a compile's
        event.end_event("numba:compiler_lock")
        assert counter.count == 1
        assert counter.longest_ms >= 5.0
    finally:
        counter.uninstall()
