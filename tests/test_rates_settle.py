"""Rates that settle (issue 20, 4): the rate an autopilot grants is accepted after a few
requests, logged once; a stream it withholds is asked for less and less often.

PX4 delivers ATTITUDE_QUATERNION at ~123 Hz against 200 asked for, and the service asked
again every 2 s for the whole flight (25-30 INFO lines); ArduPilot sends no position until
its EKF has an origin (~36 s after boot), and the service asked every 2 s meanwhile.
Driven through the service's own Autopilot (its link unopened: what it would send is
counted, not sent).
"""

from __future__ import annotations

import logging
from collections import Counter

from epc_offboard.common.logsetup import LogGate
from epc_offboard.service.autopilot import Autopilot
from epc_offboard.service.clock import WallClock
from epc_offboard.service.config import ServiceConfig
from epc_offboard.vehicle.rates import RateMonitor
from epc_offboard.vehicle.state import StateTracker

STEP_S = 0.05  # the supervisor's 20 Hz


def fly(streams_hz, duration_s: float, caplog) -> tuple[Autopilot, int, list[str]]:
    """The supervisor's rate management over ``duration_s`` while the autopilot streams
    ``streams_hz(t)`` (type -> Hz); returns the autopilot, the rate requests it made and
    its INFO lines about rates."""
    cfg = ServiceConfig()
    counters: Counter[str] = Counter()
    tracker = StateTracker(system_id=1)
    autopilot = Autopilot(cfg, WallClock(), tracker, counters, LogGate())
    per_request = 2  # ATTITUDE_QUATERNION and LOCAL_POSITION_NED (no dialect yet)
    owed: dict[str, float] = {}
    caplog.set_level(logging.INFO, logger="epc_offboard.service")
    for k in range(round(duration_s / STEP_S)):
        t = k * STEP_S
        for name, hz in streams_hz(t).items():
            owed[name] = owed.get(name, 0.0) + hz * STEP_S
            while owed[name] >= 1.0:
                owed[name] -= 1.0
                autopilot.rates.record(name)
        autopilot.manage(t, link_up=True)
    lines = [
        r.getMessage()
        for r in caplog.records
        if "Hz" in r.getMessage() or "not streamed" in r.getMessage()
    ]
    return autopilot, counters["commands_sent"] // per_request, lines


def test_px4s_123_hz_attitude_is_accepted_after_a_few_requests(caplog):
    autopilot, requests, lines = fly(
        lambda t: {"ATTITUDE_QUATERNION": 123.0, "LOCAL_POSITION_NED": 100.0}, 60.0, caplog
    )
    assert requests <= 3, lines  # today: one every 2 s, the whole flight
    assert len(lines) <= 3, lines
    accepted = autopilot.stats()["rates_accepted_hz"]
    assert 115.0 <= accepted["ATTITUDE_QUATERNION"] <= 130.0
    assert "LOCAL_POSITION_NED" not in accepted  # it came as asked


def test_ardupilots_withheld_position_is_asked_for_less_and_less_often(caplog):
    def streams(t: float) -> dict[str, float]:
        position = 100.0 if t >= 36.0 else 0.0  # the EKF has an origin at 36 s
        return {"ATTITUDE_QUATERNION": 200.0, "LOCAL_POSITION_NED": position}

    autopilot, requests, lines = fly(streams, 60.0, caplog)
    assert requests <= 8, lines  # today: 18 in the first 36 s
    assert sum("not streamed" in line for line in lines) == 1, lines
    assert autopilot.stats()["rates_accepted_hz"] == {}


def test_an_accepted_stream_that_stops_is_asked_for_again():
    rates = RateMonitor({"A": 100.0}, settle_requests=2)
    assert rates.plan(0.0, 1.0, measured=False).ask  # link-up
    rates.rates_hz = {"A": 50.0}
    assert rates.plan(2.0, 1.0, measured=True).ask  # short: asked again (2 of 2)
    plan = rates.plan(4.0, 1.0, measured=True)
    assert not plan.ask
    assert plan.accepted_hz == {"A": 50.0}
    assert not rates.plan(6.0, 1.0, measured=True).ask  # accepted: not asked again
    rates.rates_hz = {"A": 0.0}
    plan = rates.plan(8.0, 1.0, measured=True)
    assert plan.ask
    assert plan.withheld == ("A",)
    assert "A" not in rates.accepted_hz
