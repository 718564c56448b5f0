"""Clocks and loop timing statistics."""

from __future__ import annotations

import asyncio

import pytest

from epc_offboard.service.clock import VehicleClock, WallClock
from epc_offboard.service.timing import LoopTiming


def test_loop_timing_rate_jitter_and_misses():
    lt = LoopTiming(period_s=0.01)
    t = 0.0
    for k in range(101):
        jitter = 0.002 if k == 50 else 0.0
        compute = 0.02 if k == 70 else 0.001
        lt.record(t + jitter, compute, scheduled_s=t)
        t += 0.01
    rep = lt.report()
    assert rep.ticks == 101
    assert rep.rate_hz == pytest.approx(100.0)
    assert rep.deadline_misses == 1
    assert rep.period_jitter_p99_ms == pytest.approx(2.0, rel=0.05)
    assert rep.compute_us_median == pytest.approx(1000.0)
    assert set(rep.as_dict()) == {
        "rate_hz",
        "deadline_misses",
        "period_jitter_p99_ms",
        "compute_us_median",
        "compute_us_p99",
    }


def test_late_start_counts_as_miss():
    lt = LoopTiming(period_s=0.01)
    lt.record(0.0, 0.001, scheduled_s=0.0)
    lt.record(0.025, 0.001, scheduled_s=0.01)
    assert lt.deadline_misses == 1


async def _vehicle_clock():
    clock = VehicleClock()
    woke: list[float] = []

    async def waiter():
        await clock.wait_until(0.010)
        woke.append(clock.now_s())

    task = asyncio.create_task(waiter())
    await asyncio.sleep(0.01)
    clock.advance(0.005)
    await asyncio.sleep(0.01)
    assert woke == []
    clock.advance(0.004)  # time never runs backwards
    assert clock.now_s() == 0.005
    clock.advance(0.010)
    await asyncio.wait_for(task, 1.0)
    assert woke == [0.010]


def test_vehicle_clock_wakes_only_when_vehicle_time_arrives():
    asyncio.run(_vehicle_clock())


async def _wall_clock():
    clock = WallClock()
    t0 = clock.now_s()
    await clock.wait_until(t0 + 0.02)
    assert clock.now_s() - t0 >= 0.019


def test_wall_clock_waits():
    asyncio.run(_wall_clock())
