"""The SITL's real-time timing, as a PX4 on its own clock keeps it (issue 21): a tick runs when
its time has come (its state goes out when measured, not a tick early), TIMESYNC answers the
time now, a setpoint is stamped at its arrival and reaches the rate loop at the physics step
its delay ends in. Lockstep keeps the tick's time for all of it."""

from __future__ import annotations

import asyncio
import dataclasses
import os
import statistics
import time
from collections.abc import Callable
from typing import Any

import pytest

from sitl.autopilot import OFFBOARD, AttitudeSetpoint
from sitl.lockstep import Clock, LockstepGate
from sitl.params import load_sim_config
from sitl.simulation import Simulation
from tests.sitl.mavclient import (
    MavClient,
    counters_from,
    start_sitl,
    state_stamp_ms,
    stop_sitl,
)
from tests.sitl.test_endpoint import PEER, Peer, make

PERIOD_S = 0.005
RATES_ONLY = 0b10000000  # SET_ATTITUDE_TARGET: body rates and thrust, no attitude


def test_a_real_time_tick_runs_when_its_time_has_come_not_a_tick_early():
    """Tick k (vehicle time k periods) runs no earlier than k periods after the start: its
    state is stamped with the time it was measured. (It ran a period early: tick, then sleep.)"""

    async def main() -> tuple[list[float], float, list[int]]:
        gate = LockstepGate(enabled=False, timeout_s=1.0, max_timeouts=1)
        clock = Clock(gate, PERIOD_S, speedup=1.0, answer_due_ms=lambda: 0)
        walls: list[float] = []
        since: list[int] = []
        t0 = time.monotonic()
        def tick() -> None:
            walls.append(time.monotonic())
            since.append(clock.since_tick_us())

        await clock.run(
            tick,
            asyncio.Event(),
            duration_s=20 * PERIOD_S,
        )
        return walls, t0, since

    walls, t0, since = asyncio.run(main())
    assert len(walls) == 20
    for k, wall in enumerate(walls, start=1):
        assert wall - t0 >= k * PERIOD_S - 0.5e-3, f"tick {k} ran {wall - t0:.4f} s in"
    assert all(0 <= s < PERIOD_S * 1e6 for s in since)


def test_between_ticks_the_vehicle_time_runs_on_with_the_wall_clock_within_the_tick():
    async def main() -> list[int]:
        gate = LockstepGate(enabled=False, timeout_s=1.0, max_timeouts=1)
        clock = Clock(gate, PERIOD_S, speedup=1.0, answer_due_ms=lambda: 0)
        seen: list[int] = []

        def tick() -> None:
            if len(seen) == 0:  # the event loop held in a tick: the time runs on
                seen.append(clock.since_tick_us())
                time.sleep(0.002)
                seen.append(clock.since_tick_us())
                time.sleep(0.010)  # past the next tick's due time: held within the tick
                seen.append(clock.since_tick_us())

        await clock.run(tick, asyncio.Event(), duration_s=3 * PERIOD_S)
        return seen

    s0, s1, s2 = asyncio.run(main())
    assert s1 >= min(s0 + 1500, 4999)  # the 2 ms slept (clamped to the tick)
    assert s2 == round(PERIOD_S * 1e6) - 1


def test_lockstep_vehicle_time_is_the_ticks():
    gate = LockstepGate(enabled=True, timeout_s=1.0, max_timeouts=1)
    clock = Clock(gate, PERIOD_S, speedup=1.0, answer_due_ms=lambda: 0)
    assert clock.since_tick_us() == 0
    sim = make()[0]
    sim.since_tick_us = clock.since_tick_us
    sim.advance_tick()
    assert sim.now_us() == sim.time_us == 5000


def test_timesync_and_setpoints_are_stamped_with_the_time_now_between_ticks():
    sim, ep, transport, _ = make()
    for _ in range(3):
        sim.advance_tick()
    sim.since_tick_us = lambda: 2300  # the wall clock 2.3 ms past the tick's due time
    peer = Peer()
    ep.datagram_received(peer.pack(peer.mav.timesync_encode(0, 42)), PEER)
    answer = next(m for m in peer.decode(transport) if m.get_type() == "TIMESYNC")
    assert answer.tc1 == (sim.time_us + 2300) * 1000
    rates = peer.mav.set_attitude_target_encode(0, 1, 1, RATES_ONLY, [1, 0, 0, 0], 0.1, 0, 0, 0.5)
    ep.datagram_received(peer.pack(rates), PEER)
    # PX4's commander sees the stream's setpoint at its arrival
    assert sim.autopilot._setpoint_times_s[-1] == pytest.approx(sim.time_s + 0.0023, abs=1e-9)


def _offboard_body_rates(between: bool) -> tuple[Simulation, float]:
    """A PX4 SITL in offboard body rates (on the ground, level), and the setpoints' delay."""
    cfg = load_sim_config()
    cfg = dataclasses.replace(
        cfg, autopilot=dataclasses.replace(cfg.autopilot, arm_refusals_after_boot=0)
    )
    sim = Simulation(cfg, seed=0)
    sim.setpoints_between_ticks = between
    ap = sim.autopilot
    hover = AttitudeSetpoint(RATES_ONLY, (1.0, 0.0, 0.0, 0.0), (0.0, 0.0, 0.0), 0.3)
    assert ap.arm(True, sim.time_s).name == "ACCEPTED"
    for _ in range(20):
        ap.on_attitude_setpoint(hover, sim.time_s)
        sim.advance_tick()
    assert ap.set_mode(OFFBOARD, sim.time_s).name == "ACCEPTED"
    for _ in range(20):
        ap.on_attitude_setpoint(hover, sim.time_s)
        sim.advance_tick()
    return sim, ap.params.setpoint_delay_s(cfg.vehicle)


@pytest.mark.parametrize("between", [True, False])
def test_a_setpoint_reaches_the_rate_loop_at_the_physics_step_its_delay_ends_in(between):
    """Real time: a body-rate setpoint arriving 1 ms into a tick is flown from the physics
    step (1 ms) its delay ends in, within the tick; lockstep (``between`` False) keeps the
    tick's delivery, at the next tick."""
    sim, delay_s = _offboard_body_rates(between)
    ap = sim.autopilot
    arrival_s = sim.time_s + 0.001
    ap.on_attitude_setpoint(
        AttitudeSetpoint(RATES_ONLY, (1.0, 0.0, 0.0, 0.0), (0.2, 0.0, 0.0), 0.3), arrival_s
    )
    due_s = arrival_s + delay_s
    # the ticks that end before the setpoint is due fly the old rates
    while sim.time_s + PERIOD_S <= due_s:
        sim.advance_tick()
        assert sim.last_command.rate_cmd_frd_rad_s[0] == 0.0
    assert sim.time_s < due_s <= sim.time_s + PERIOD_S - 0.001  # (due before the last step)
    sim.advance_tick()  # the tick the delay ends in
    assert sim.last_command.rate_cmd_frd_rad_s[0] == (0.2 if between else 0.0)
    sim.advance_tick()
    assert sim.last_command.rate_cmd_frd_rad_s[0] == 0.2


def _ts1_is(ts1: int) -> Callable[[Any], bool]:
    return lambda m: bool(m.ts1 == ts1)


def test_the_sitl_answers_timesync_with_the_time_now_in_real_time():
    """A real-time SITL process answers TIMESYNC with the time now, not its last tick's (a
    multiple of the 5 ms tick, every one): within a tick (median of 20) of the vehicle time
    its state messages tell about then, the least delayed of those received within 30 ms
    either side mapping the wall clock. (That mapping carries the link's delay, 1-2 ms at
    load 12; the in-process tests above hold the time to the microsecond.)"""
    client = MavClient()
    proc = start_sitl(client)
    try:

        def offsets(duration_s: float) -> list[float]:
            """wall clock - vehicle time, per state datagram received"""
            out = []
            end = time.monotonic() + duration_s
            while time.monotonic() < end:
                msgs = client.poll(end - time.monotonic())
                wall = time.monotonic()
                stamps = [s for s in map(state_stamp_ms, msgs) if s is not None]
                if stamps:
                    out.append(wall - max(stamps) / 1000.0)
            return out

        offsets(0.5)
        errors_ms: list[float] = []
        on_tick = 0  # answers on a tick's time
        for k in range(20):
            around = offsets(0.03 + 0.0011 * k)  # at another phase of the tick each time
            sent = time.monotonic()
            client.send(client.mav.timesync_encode(0, k + 1))
            answer = client.wait("TIMESYNC", _ts1_is(k + 1), timeout_s=3)
            got = time.monotonic()
            around += offsets(0.03)
            vehicle_mid_s = (sent + got) / 2.0 - min(around)
            errors_ms.append((answer.tc1 / 1e9 - vehicle_mid_s) * 1000.0)
            on_tick += answer.tc1 % 5_000_000 == 0
    finally:
        rc, _ = stop_sitl(proc)
        client.close()
    assert rc == 0
    assert on_tick <= 5, errors_ms
    assert abs(statistics.median(errors_ms)) <= 2.5, errors_ms


def test_the_sitl_runs_sched_fifo_where_permitted_and_counts_a_refusal():
    """``epc-sitl --realtime-priority P`` (what ``sim --realtime`` passes by default): the
    process runs SCHED_FIFO at P where permitted; a refusal is counted and it runs on."""
    client = MavClient()
    proc = start_sitl(client, "--realtime-priority", "1")  # the lowest: competes with none
    try:
        client.wait("HEARTBEAT", timeout_s=10)
        policy = os.sched_getscheduler(proc.pid)
    finally:
        rc, err = stop_sitl(proc)
        client.close()
    assert rc == 0
    refused = counters_from(err)["realtime_priority_refused"]
    assert (policy, refused) in ((os.SCHED_FIFO, 0), (os.SCHED_OTHER, 1))
    if os.geteuid() == 0:  # permitted here: it took
        assert policy == os.SCHED_FIFO


def test_timesync_is_answered_to_the_requester_by_its_ids_as_px4_does():
    """PX4 main answers a TIMESYNC request with common.xml's extension fields set to the
    requester's ids (mavlink_timesync.cpp: target_system, target_component): an 18-byte
    payload, where pymavlink's dialect knows 16. The personality answers so (it sent 16),
    and the service's receive path takes the answer and its clock trusts the round trip
    (on a real PX4 it refused every answer as too long: bad_length, no round trip trusted)."""
    from collections import Counter

    from epc_offboard.vehicle.receive import SERVICE_MESSAGE_IDS, FrameReceiver
    from epc_offboard.vehicle.timesync import AutopilotClock

    sim, ep, transport, _ = make()
    for _ in range(3):
        sim.advance_tick()
    peer = Peer()  # system 245, component 190
    ep.datagram_received(peer.pack(peer.mav.timesync_encode(0, 42_000_000)), PEER)
    frames = [data for data, dest in transport.sent if dest == PEER and data[7] == 111]
    assert len(frames) == 1
    frame = frames[0]
    assert frame[1] == 18  # payload length: tc1, ts1, target_system, target_component
    assert (frame[10 + 16], frame[10 + 17]) == (245, 190)
    counters: Counter[str] = Counter()
    rx = FrameReceiver(counters, accept_ids=SERVICE_MESSAGE_IDS, accept_systems=frozenset({1}),
                       accept_components=frozenset({1}), signature=None,
                       decode_other=peer.rx.decode)  # fmt: skip
    msgs, failures = rx.datagram(frame)
    assert (failures, counters["bad_length"]) == (0, 0), counters
    (answer,) = msgs
    assert (answer.tc1, answer.ts1) == (sim.now_us() * 1000, 42_000_000)
    clock = AutopilotClock()
    assert clock.timesync(0.042, answer.tc1 * 1e-9, 0.045)
    assert clock.counters["timesync_accepted"] == 1
