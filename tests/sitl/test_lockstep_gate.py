"""The lockstep gate and clock in-process: waiting, timeouts, fallback to real time."""

from __future__ import annotations

import asyncio
import time
import tomllib

from epc_offboard.service.miss_solver import START_TIMEOUT_S, WAIT_TIMEOUT_S
from sitl.lockstep import Clock, LockstepGate
from sitl.params import DEFAULT_VEHICLE_FILE, SitlParams


def run_clock(gate: LockstepGate, ticks: int, on_tick=lambda k: None) -> float:
    async def main() -> float:
        count = 0

        def tick() -> None:
            nonlocal count
            count += 1
            on_tick(count)

        clock = Clock(gate, 0.005, speedup=1.0, answer_due_ms=lambda: count * 5)
        t0 = time.monotonic()
        await clock.run(tick, asyncio.Event(), duration_s=ticks * 0.005)
        return time.monotonic() - t0

    return asyncio.run(main())


def test_answered_ticks_run_faster_than_real_time():
    gate = LockstepGate(enabled=True, timeout_s=1.0, max_timeouts=20)
    gate.on_answer(0)  # the controller has joined
    # the "controller" answers each tick from inside the loop, as a datagram would
    wall = run_clock(
        gate, 400, on_tick=lambda k: asyncio.get_running_loop().call_soon(gate.on_answer, k * 5)
    )
    assert gate.waiting
    assert gate.timeouts == 0
    # 2 s of vehicle time in less than half of it: no pacing by the wall clock (which would
    # take the full 2 s), with room for a loaded machine (idle: ~0.05 s)
    assert wall < 0.5 * 400 * 0.005


def test_silence_times_out_then_falls_back_to_real_time_and_rejoins():
    gate = LockstepGate(enabled=True, timeout_s=0.01, max_timeouts=5)
    gate.on_answer(0)
    log = []

    def on_tick(k: int) -> None:
        log.append(gate.waiting)
        if k == 50:  # the controller comes back
            asyncio.get_running_loop().call_soon(gate.on_answer, k * 5)

    run_clock(gate, 60, on_tick)
    assert gate.timeouts >= 5
    # the 5 consecutive timeouts are all spent waiting on the first tick (physics does not
    # advance without an answer); then the controller counts as gone: real-time pace
    assert log[0] is True
    assert log[1] is False
    assert log[50] is True  # an answer put it back into waiting mode


def test_a_slow_answer_is_waited_for_and_physics_does_not_advance_meanwhile():
    """Under load an answer took longer than the timeout: the clock used to advance a tick
    without it, and two identical lockstep runs differed."""
    gate = LockstepGate(enabled=True, timeout_s=0.01, max_timeouts=50)
    gate.on_answer(0)
    ticks_before_answer = []

    def on_tick(k: int) -> None:
        if k == 1:  # the answer to tick 1 comes only after 4 timeouts
            loop = asyncio.get_running_loop()
            loop.call_later(0.045, gate.on_answer, 5)
            loop.call_later(0.044, lambda: ticks_before_answer.append(k_seen[-1]))
        else:
            asyncio.get_running_loop().call_soon(gate.on_answer, k * 5)
        k_seen.append(k)

    k_seen: list[int] = []
    run_clock(gate, 10, on_tick)
    # counted (4 if the process ran all along; one, at least, if a loaded machine kept it off
    # the CPU past the answer's 45 ms: then the first timeout and the answer are both due)...
    assert gate.timeouts >= 1
    assert ticks_before_answer == [1]  # ...but no tick ran before the answer arrived
    assert gate.waiting  # and the clock is still in lockstep
    assert k_seen == list(range(1, 11))


def test_the_clock_holds_at_its_first_tick_announcing_until_a_controller_answers():
    async def main() -> tuple[int, int, int]:
        gate = LockstepGate(enabled=True, timeout_s=0.01, max_timeouts=1)
        announced: list[int] = []
        count = 0

        def tick() -> None:
            nonlocal count
            count += 1

        clock = Clock(gate, 0.005, 1.0, answer_due_ms=lambda: count * 5,
                      announce=lambda: announced.append(count))  # fmt: skip
        stop = asyncio.Event()
        runner = asyncio.create_task(clock.run(tick, stop, duration_s=1.0))
        await asyncio.sleep(1.2)  # no controller: no physics, whatever the wall clock says
        held, n_announced, timeouts = count, len(announced), gate.timeouts
        gate.on_answer(5)  # a controller joins and answers the first tick
        await asyncio.sleep(0.05)
        stop.set()
        await runner
        assert count > held  # and the clock moves on
        return held, n_announced, timeouts

    held, n_announced, timeouts = asyncio.run(main())
    assert held == 1
    assert n_announced >= 2  # every ANNOUNCE_PERIOD_S
    assert timeouts == 0  # waiting to be joined is not a timeout


def test_a_tick_without_new_state_needs_no_new_answer():
    timeout_s = 0.5
    gate = LockstepGate(enabled=True, timeout_s=timeout_s, max_timeouts=20)
    gate.on_answer(10)
    # the state sent so far is stamped 10 ms (e.g. a 100 Hz stream on a 200 Hz tick)
    wall = run_clock(gate, 1, on_tick=lambda k: None)
    assert gate.timeouts == 0
    assert wall < timeout_s  # it did not wait for an answer (idle: ~5 ms, the tick's pace)


def test_future_stamps_do_not_starve_the_event_loop():
    gate = LockstepGate(enabled=True, timeout_s=1.0, max_timeouts=20)
    gate.on_answer(2**32 - 1)
    seen: list[int] = []
    seen_by_last_tick: list[int] = []

    def on_tick(k: int) -> None:
        if k == 1:
            asyncio.get_running_loop().call_soon(seen.append, k)
        if k == 5:
            seen_by_last_tick.extend(seen)

    run_clock(gate, 5, on_tick)
    assert seen_by_last_tick == [1]


def test_a_controller_that_leaves_is_not_counted_as_lockstep_timeouts():
    """At the end of a flight the service stops answering while it saves its library and
    exits, and the SITL waits until sim stops it: those timeouts were reported as "SITL
    lockstep timeouts", a stall warning after a healthy flight. Only a timeout an answer
    follows (a slow controller) counts."""
    gate = LockstepGate(enabled=True, timeout_s=0.01, max_timeouts=3)
    gate.on_answer(0)

    def on_tick(k: int) -> None:
        if k <= 5:  # then the controller is gone
            asyncio.get_running_loop().call_soon(gate.on_answer, k * 5)

    run_clock(gate, 20, on_tick)
    assert not gate.waiting  # it did time out, into real-time pace...
    assert gate.timeouts == 0  # ...and that is not a stall

    slow = LockstepGate(enabled=True, timeout_s=0.01, max_timeouts=50)
    slow.on_answer(0)

    def on_slow_tick(k: int) -> None:
        delay_s = 0.035 if k == 2 else 0.0  # tick 2's answer after 3 timeouts
        asyncio.get_running_loop().call_later(delay_s, slow.on_answer, k * 5)

    run_clock(slow, 5, on_slow_tick)
    assert slow.timeouts >= 1  # a slow answer is still counted


def test_a_fallback_is_counted_unless_the_controller_handed_the_vehicle_back_and_left():
    """Real-time pace in the middle of a lockstep flight (a controller slow past the bound,
    then back; or one gone while commanding: a SIGKILLed service) makes the flight depend on
    the wall clock: counted (``fallbacks``, the report's "lockstep fell back to real time").
    A controller that handed the vehicle back and left at the end is not; one that handed it
    back and answers again after the fallback is."""
    back = LockstepGate(enabled=True, timeout_s=0.01, max_timeouts=2)
    back.on_answer(0)

    def on_tick(k: int) -> None:
        if k >= 30:  # the slow controller answers again, every tick
            asyncio.get_running_loop().call_soon(back.on_answer, k * 5)

    run_clock(back, 40, on_tick)
    assert back.fallbacks == 1
    assert back.waiting  # and lockstep resumed

    gone = LockstepGate(enabled=True, timeout_s=0.01, max_timeouts=2)
    gone.on_answer(0)
    run_clock(gone, 20)
    assert not gone.waiting
    assert gone.fallbacks == 1  # gone while commanding: said (before: 0, silent)

    left = LockstepGate(enabled=True, timeout_s=0.01, max_timeouts=2)
    left.on_answer(0)
    left.on_offboard(True)
    left.on_offboard(False)  # its HOLD request
    run_clock(left, 20)
    assert not left.waiting
    assert left.fallbacks == 0


def test_a_controller_that_handed_the_vehicle_back_is_waited_for_by_the_short_bound():
    """The service's stop asks for HOLD, then sends nothing: with the long bound alone the
    SITL stood still for it 90 s (test_service_e2e's HOLD never showed). Handed back, its
    silence ends the wait after ``left_max_timeouts``; a controller still meant to fly
    offboard (starved: SIGSTOP, load) keeps the whole ``max_timeouts``. Counted in timeouts
    (the answer at tick 50 follows them), not timed: the fallback comes at that count."""

    def spent(gate: LockstepGate, hand_back_at: int | None) -> int:
        gate.on_answer(0)
        gate.on_offboard(True)

        def on_tick(k: int) -> None:
            if hand_back_at is not None and k == hand_back_at:
                gate.on_offboard(False)
            if k <= 5 or k >= 50:  # silent from tick 6 to 49, as SIGSTOPped or gone
                asyncio.get_running_loop().call_soon(gate.on_answer, k * 5)

        run_clock(gate, 60, on_tick)
        return gate.timeouts

    assert spent(LockstepGate(True, 0.01, max_timeouts=8, left_max_timeouts=2), None) == 8
    left = LockstepGate(True, 0.01, max_timeouts=8, left_max_timeouts=2)
    assert spent(left, hand_back_at=5) == 2
    assert left.fallbacks == 1  # it answered again after: the flight ran on the wall clock
    # back in offboard, the long bound again
    again = LockstepGate(True, 0.01, max_timeouts=8, left_max_timeouts=2)
    again.on_offboard(False)
    assert spent(again, None) == 8


def test_the_shipped_bound_outlasts_the_services_own_longest_lockstep_wait():
    """The SITL falls back only after the service's miss worker, waited for in lockstep up to
    ``WAIT_TIMEOUT_S``, would have been declared wedged and restarted: a loaded machine that
    slows the worker must not turn a lockstep flight into a real-time one (3 x 2 s did,
    stop 41)."""
    default = SitlParams()
    shipped = [
        tomllib.loads(p.read_text())["sitl"] for p in DEFAULT_VEHICLE_FILE.parent.glob("*.toml")
    ]
    assert shipped  # the vehicle files were found
    bounds = {"default": default.lockstep_timeout_s * default.lockstep_max_timeouts}
    for i, sitl in enumerate(shipped):
        bounds[str(i)] = sitl["lockstep_timeout_s"] * sitl["lockstep_max_timeouts"]
    assert min(bounds.values()) > WAIT_TIMEOUT_S + START_TIMEOUT_S, bounds


def test_an_answer_releases_the_wait_at_the_next_pass_of_the_loop_without_a_task_of_its_own():
    """The lockstep handshake is paid every tick: waiting for the answer runs no task beside
    the clock's, and the answer's datagram releases the clock at the very next pass of the
    event loop (an ``asyncio.wait_for`` on an Event ran a task per tick and took three)."""

    async def main() -> tuple[int, int, bool]:
        gate = LockstepGate(enabled=True, timeout_s=1.0, max_timeouts=20)
        gate.on_answer(0)
        waiting = asyncio.create_task(gate.wait_for(5, lambda: None, asyncio.Event()))
        for _ in range(3):  # the wait settles: its futures, timers (and any task) are set up
            await asyncio.sleep(0)
        tasks = len(asyncio.all_tasks())  # this test's and the wait's own
        gate.on_answer(5)  # the answer, as the datagram's handler delivers it
        passes = 0
        while not waiting.done() and passes < 10:
            await asyncio.sleep(0)
            passes += 1
        return tasks, passes, gate.newest_stamp_ms == 5

    tasks, passes, answered = asyncio.run(main())
    assert answered
    assert tasks == 2
    assert passes == 1
