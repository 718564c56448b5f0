"""The sim's pure analysis (ground truth + flight log -> the report's numbers) against
oracles computed by hand, and its options read from the command line once (no flight)."""

from __future__ import annotations

import dataclasses
import math
from pathlib import Path

import numpy as np
import pytest

from epc_offboard.cli import build_parser
from epc_offboard.common.errors import UsageError
from epc_offboard.tools.sim.analysis import (
    FlightRecord,
    analyse,
    flight_warnings,
    read_csv_columns,
    read_flight,
    sitl_counters,
)
from epc_offboard.tools.sim.envelope import (
    Envelope,
    EnvelopeConfig,
    breaches,
    envelope_for,
    tilt_deg_of,
)
from epc_offboard.tools.sim.logscan import log_kinds
from epc_offboard.tools.sim.options import SimOptions, sim_options
from epc_offboard.tools.sim.report import flight_failures
from epc_offboard.tools.sim.scenario import SCENARIO_DIR, ScenarioConfig, load_scenario

# A flight logged at 1 Hz: streaming at t = 9 s, offboard from 10 s to 14 s, hovering at
# 2 m up (NED d = -2). Scenario: settle 1.5 s (the metrics start at 11.5 s), first lap 2 s.
SCENARIO = ScenarioConfig(duration_s=4.0, settle_s=1.5, lap_s=2.0)
LOG_T_S = np.array([9.0, 10.0, 11.0, 12.0, 13.0, 14.0])
PHASES = np.array(["streaming", "offboard", "offboard", "offboard", "offboard", "offboard"])
SOURCES = np.array(["", "hit", "solved", "hit", "fallback", "hit"])
BOUNDS_M_S = np.array([1.0, 1.0, 1.0])


def _flight() -> dict[str, np.ndarray]:
    return {
        "vehicle_t_s": LOG_T_S,
        "phase": PHASES,
        "source": SOURCES,
        "ref_pos_n_m": np.zeros(6),
        "ref_pos_e_m": np.zeros(6),
        "ref_pos_d_m": np.full(6, -2.0),
    }


def _truth() -> dict[str, np.ndarray]:
    """Ground truth every 0.5 s from 9 s to 15 s: off the reference by 5 m at 10 s and 1 m at
    11 s (inside the settle time), 0.3 m north at 12 s, 0.4 m east at 13 s, on it at 14 s;
    fast (2 m/s N) at 10 s (settling), 1.5 m/s N at 12.5 s and -1.2 m/s E at 13.5 s (both
    over the 1 m/s bound), 3 m/s N at 14.5 s (after the last offboard tick)."""
    t = np.arange(9.0, 15.01, 0.5)
    n, e, d = np.zeros_like(t), np.zeros_like(t), np.full_like(t, -2.0)
    vn, ve, vd = np.zeros_like(t), np.zeros_like(t), np.zeros_like(t)

    def at(t_s: float) -> int:
        return int(np.argmin(np.abs(t - t_s)))

    n[at(10.0)], n[at(11.0)], n[at(12.0)], e[at(13.0)] = 5.0, 1.0, 0.3, 0.4
    vn[at(10.0)], vn[at(12.5)], ve[at(13.5)], vn[at(14.5)] = 2.0, 1.5, -1.2, 3.0
    return {"t_s": t, "pos_n_m": n, "pos_e_m": e, "pos_d_m": d,
            "vel_n_m_s": vn, "vel_e_m_s": ve, "vel_d_m_s": vd}  # fmt: skip


def _record(**stats: object) -> FlightRecord:
    return FlightRecord(3, _flight(), _truth(), dict(stats), {"lockstep_timeouts": 2})


def test_tracking_error_is_measured_on_ground_truth_after_settling() -> None:
    v = analyse(_record(), SCENARIO, BOUNDS_M_S).report
    # errors at 12, 13, 14 s: 0.3, 0.4, 0 m; the settle time's 5 m and 1 m left out
    assert v["tracking"]["rmse_m"] == pytest.approx(math.sqrt((0.3**2 + 0.4**2 + 0.0) / 3))
    assert v["tracking"]["max_error_m"] == pytest.approx(0.4)


def test_velocity_bounds_are_checked_on_every_truth_sample_after_settling() -> None:
    v = analyse(_record(), SCENARIO, BOUNDS_M_S).report
    # 12.5 s (N 1.5) and 13.5 s (E -1.2); not 10 s (settling) nor 14.5 s (after offboard)
    assert v["constraint_violations"] == 2
    assert v["max_abs_vel_m_s"] == pytest.approx([1.5, 1.2, 0.0])
    assert v["max_speed_m_s"] == pytest.approx(1.5)
    loose = analyse(_record(), SCENARIO, np.array([1.5, 1.5, 1.5])).report
    assert loose["constraint_violations"] == 0  # at the bound is within it


def test_library_use_first_lap_misses_and_times_since_offboard() -> None:
    stats = {
        "library": {"position": {"hits": 3, "misses": 1, "size": 7, "qp_solves": 2}},
        "phase_events": [{"t_s": 8.5, "phase": "preflight"}, {"t_s": 10.0, "phase": "offboard"}],
    }
    r = analyse(_record(**stats), SCENARIO, BOUNDS_M_S)
    lib = r.report["library"]
    assert lib["hit_rate"] == pytest.approx(0.75)
    # the first lap is 10 s to 12 s: one miss ("solved"); the whole flight has two
    assert lib["first_lap_misses"] == 1
    # after it (12, 13, 14 s): hit, fallback, hit
    assert lib["hit_rate_after_first_lap"] == pytest.approx(2 / 3)
    assert [e["t_s"] for e in r.report["phase_events"]] == [-1.5, 0.0]
    assert r.report["warnings"] == {"SITL lockstep timeouts": 2}
    np.testing.assert_allclose(r.t_s, LOG_T_S - 10.0)
    np.testing.assert_allclose(r.error_m[3:], [0.3, 0.4, 0.0])
    assert r.report["id"] == 3


def test_a_flight_that_never_entered_offboard_is_reported_as_a_failure() -> None:
    flight = {**_flight(), "phase": np.full(6, "streaming")}
    report = {"vehicles": [analyse(FlightRecord(3, flight, _truth()), SCENARIO, BOUNDS_M_S).report]}
    v = report["vehicles"][0]
    assert v["flew_offboard"] is False
    assert math.isnan(v["tracking"]["rmse_m"])
    assert "vehicle 3: never flew under offboard" in flight_failures(report)
    # a service that never streamed at all: a flight log with a header only
    empty = {k: np.zeros(0) for k in _flight()}
    never = analyse(FlightRecord(3, empty, _truth()), SCENARIO, BOUNDS_M_S).report
    assert never["flew_offboard"] is False


ENVELOPE = Envelope(max_error_m=0.35, max_drift_m=1.0, max_tilt_deg=60.0, ceiling_m=3.0,
                    max_flight_s=14.0)  # fmt: skip


def test_the_envelope_is_judged_on_every_truth_sample_and_names_where_it_was_left() -> None:
    # under offboard (10-14 s) the 0.4 m east at 13 s is beyond 0.35 m; before it the 5 m
    # north at 10 s... is at the first offboard tick: 3-D; the drift bound (1 m) is not left
    v = analyse(_record(), SCENARIO, BOUNDS_M_S, ENVELOPE).report
    left = {b["what"]: b for b in v["envelope"]["left"]}
    assert set(left) == {"distance from the reference", "flight time"}
    assert left["distance from the reference"]["worst"] == pytest.approx(5.0)
    assert left["distance from the reference"]["t_s"] == pytest.approx(0.0)  # since offboard
    assert left["flight time"]["worst"] == pytest.approx(15.0)  # the truth runs to 15 s
    assert v["envelope"]["worst"]["altitude_m"] == pytest.approx(2.0)
    failures = flight_failures({"vehicles": [v]})
    assert any("left its envelope: distance from the reference 5 m" in f for f in failures)
    # the same flight inside a wider envelope: nothing to report
    wide = Envelope(max_error_m=6.0, max_drift_m=1.0, max_tilt_deg=60.0, ceiling_m=3.0,
                    max_flight_s=20.0)  # fmt: skip
    ok = analyse(_record(), SCENARIO, BOUNDS_M_S, wide).report
    assert ok["envelope"]["left"] == []
    # the breaches are warnings too (they printed "warnings: none" beside FAILED before)
    assert v["warnings"]["left its envelope: distance from the reference"] == 1
    assert v["warnings"]["left its envelope: flight time"] == 1
    assert not [k for k in ok["warnings"] if "envelope" in k]
    assert flight_failures({"vehicles": [ok]}) == ["vehicle 3: the flight did not finish "
                                                   "(last phase: none)"]  # fmt: skip


def test_tilt_and_altitude_beyond_the_envelope_are_breaches() -> None:
    t = np.array([0.0, 1.0, 2.0])
    pos = np.array([[0.0, 0.0, -2.0], [0.0, 0.0, -3.5], [0.0, 0.0, -2.0]])
    # 70 deg about x at 2 s: w = cos(35 deg), x = sin(35 deg)
    q = np.array([[1.0, 0, 0, 0], [1.0, 0, 0, 0], [math.cos(0.6109), math.sin(0.6109), 0, 0]])
    tilt = tilt_deg_of(q)
    assert tilt == pytest.approx([0.0, 0.0, 70.0], abs=0.01)
    found = {b.what: b for b in breaches(ENVELOPE, t, pos, tilt, pos, np.zeros(3, bool),
                                          flight_s=t)}  # fmt: skip
    assert set(found) == {"altitude", "tilt"}
    assert (found["altitude"].t_s, found["altitude"].worst) == (1.0, 3.5)
    assert found["tilt"].t_s == 2.0
    # drift while the autopilot flies alone is judged horizontally, against its own bound
    far = pos + np.array([0.0, 0.8, -5.0])  # 5 m higher: the ceiling is still judged
    alone = breaches(ENVELOPE, t, far, np.zeros(3), pos, np.ones(3, bool), flight_s=t)
    assert [b.what for b in alone] == ["altitude"]  # 0.8 m of drift is within 1 m


def test_the_scenario_envelope_is_derived_from_it_and_the_service_limits() -> None:
    env = envelope_for(EnvelopeConfig(), altitude_m=2.5, climb_m=1.0, duration_s=20.0,
                       max_tilt_deg=45.0)  # fmt: skip
    assert (env.max_error_m, env.max_drift_m, env.max_tilt_deg) == (2.0, 10.0, 60.0)
    assert env.ceiling_m == pytest.approx(5.5)
    assert env.max_flight_s == pytest.approx(140.0)
    with pytest.raises(ValueError, match="max_error_m must be > 0"):
        EnvelopeConfig(max_error_m=0.0)


SERVICE_LOG = "\n".join([
    "2026-11-26 00:16:34,633 INFO    epc_offboard.service: control kernels compiled",
    "2026-11-26 00:16:35,001 ERROR   epc_offboard.store.database: library "
    "/tmp/a/library-1.sqlite is unusable (file is not a database): moved aside to "
    "/tmp/a/library-1.sqlite.corrupt-20261126T001635, starting empty",
    *(f"2026-11-26 00:16:3{n},145 WARNING epc_offboard.vehicle.state: heartbeat mode/arming "
      f"flapping ({n} flaps so far): forged heartbeats? a mode change now needs 1.0 s to be "
      "believed" for n in (1, 2)),
    '{"ts": 1.0, "level": "error", "logger": "epc_offboard.fleet.sharing", "msg": "fleet '
    'sharing unavailable, flying without it: address 127.0.0.1:7447 in use"}',
    '{"ts": 1.0, "level": "info", "logger": "epc_offboard.service", "msg": "running"}',
    "/x/y.py:12: RuntimeWarning: overflow encountered in exp",
    "Traceback (most recent call last):",
    '  File "x.py", line 1, in <module>',
    "ValueError: bad thing 42",
])  # fmt: skip


def test_every_logged_warning_and_error_is_counted_by_kind_with_its_first_line() -> None:
    kinds = {k.key: k for k in log_kinds(SERVICE_LOG, "service")}
    flap = ("service WARNING epc_offboard.vehicle.state: heartbeat mode/arming flapping "
            "(<n> flaps so far): forged heartbeats? a mode change now needs <n> s to be "
            "believed")  # fmt: skip
    assert kinds[flap].count == 2
    assert "(1 flaps so far)" in kinds[flap].first
    aside = ("service ERROR epc_offboard.store.database: library <path> is unusable (file is not "
             "a database): moved aside to <path>, starting empty")  # fmt: skip
    assert kinds[aside].count == 1
    assert "library-1.sqlite.corrupt-20261126T001635" in kinds[aside].first
    assert kinds["service ERROR epc_offboard.fleet.sharing: fleet sharing unavailable, flying "
                 "without it: address <n>.<n>:<n> in use"].count == 1  # fmt: skip
    assert kinds["service WARNING RuntimeWarning: overflow encountered in exp"].count == 1
    assert kinds["service ERROR traceback: ValueError: bad thing <n>"].count == 1
    assert len(kinds) == 5  # the INFO lines are not warnings
    # a service whose teardown hung (bounded_exit): faulthandler's headline, one kind
    hung = log_kinds('Timeout (0:00:10)!\nThread 0x00007f (most recent call first):\n'
                     '  File "x.py", line 3 in wait\n', "service")  # fmt: skip
    assert [k.key for k in hung] == ["service ERROR faulthandler: did not end within "
                                     "<n>:<n>:<n> of stopping (every thread's stack follows "
                                     "in the log)"]  # fmt: skip
    sitl = log_kinds("epc-sitl: instance 0\nepc-sitl: [Errno 98] in use\nepc-sitl: counters a=1\n",
                     "sitl")  # fmt: skip
    assert [k.key for k in sitl] == ["sitl ERROR epc-sitl: [Errno <n>] in use"]
    # in the report: counted among the warnings, the first line beside them
    record = FlightRecord(3, _flight(), _truth(), {}, {}, logs={"service": SERVICE_LOG})
    v = analyse(record, SCENARIO, BOUNDS_M_S).report
    assert v["warnings"][flap] == 2
    assert v["warning_examples"][flap] == kinds[flap].first


def test_the_files_read_back_as_the_columns_written(tmp_path: Path) -> None:
    flight, truth = _flight(), _truth()
    for name, cols in (("flight.csv", flight), ("groundtruth.csv", truth)):
        rows = [",".join(cols)] + [",".join(str(c[i]) for c in cols.values())
                                   for i in range(len(next(iter(cols.values()))))]  # fmt: skip
        (tmp_path / name).write_text("\n".join(rows) + "\n9.9,torn")  # a torn last line
    record = read_flight(
        3,
        flight_log=tmp_path / "flight.csv",
        groundtruth=tmp_path / "groundtruth.csv",
        stats=tmp_path / "missing.json",
        sitl_log=tmp_path / "missing.log",
    )
    assert record.stats == {}
    assert record.sitl_counters == {}
    np.testing.assert_array_equal(record.flight["phase"], PHASES)
    np.testing.assert_allclose(record.truth["pos_n_m"], truth["pos_n_m"])
    in_memory = analyse(_record(), SCENARIO, BOUNDS_M_S).report["tracking"]
    assert analyse(record, SCENARIO, BOUNDS_M_S).report["tracking"] == in_memory
    (tmp_path / "empty.csv").write_text("t_s\n")
    with pytest.raises(RuntimeError, match="no data"):
        read_csv_columns(tmp_path / "empty.csv")


def test_flight_warnings_name_what_went_wrong_and_leave_out_zeros():

    stats = {
        "counters": {"failsafes": 2, "position_ticks_skipped": 0, "store_errors": 1,
                     "realtime_priority_refused": 1},
        "phase_events": [
            {"t_s": 1.0, "phase": "failsafe", "reason": "state stale (0.40 s)"},
            {"t_s": 2.0, "phase": "failsafe", "reason": "heartbeat lost"},
        ],
    }
    got = flight_warnings(stats, {"lockstep_timeouts": 3, "handler_errors": 0})
    assert got == {
        "failsafes": 2,
        "library store errors": 1,
        "loops' real-time priority refused (normal scheduling)": 1,
        "stale-state failsafes": 1,
        "SITL lockstep timeouts": 3,
    }
    assert flight_warnings({}, {}) == {}


def test_flight_warnings_name_what_the_state_tracker_would_not_believe():
    stats = {"state": {"heartbeat_flaps": 1, "state_conflicts": 2, "rejected_innovation": 40,
                       "timesync_accepted": 9}}  # fmt: skip
    assert flight_warnings(stats, {}) == {
        "heartbeat flaps (forged heartbeats?)": 1,
        "contradicting state streams (forged telemetry?)": 2,
        "state samples far from the prediction (not flown)": 40,
    }


def test_rejected_state_and_dropped_log_lines_reach_the_warnings():
    # an autopilot sending NaN or absurd estimates, a reboot's stamps, a full log pipe: each
    # was counted in stats.json only, and the report said "warnings: none"
    stats = {"state": {"rejected_nan": 5, "rejected_range": 1, "rejected_quaternion": 2,
                       "rejected_time_jump": 3},
             "counters": {"log_lines_dropped": 7}}  # fmt: skip
    assert flight_warnings(stats, {}) == {
        "service log lines dropped (its logged warnings may be incomplete)": 7,
        "state samples not finite (not flown)": 5,
        "state samples out of range (not flown)": 1,
        "attitude samples not a unit quaternion (not flown)": 2,
        "state samples stamped off their stream's timeline (not flown)": 3,
    }


def test_a_flight_stopped_by_sim_says_so_in_its_warnings():
    stopped = FlightRecord(3, _flight(), _truth(), stopped="stopped by sim: it left its envelope")
    v = analyse(stopped, SCENARIO, BOUNDS_M_S).report
    assert v["warnings"]["stopped by sim before it finished"] == 1
    assert "stopped by sim before it finished" not in analyse(_record(), SCENARIO,
                                                              BOUNDS_M_S).report["warnings"]


def test_sitl_counters_are_read_from_its_closing_line(tmp_path):

    log = tmp_path / "sitl.log"
    log.write_text(
        "epc-sitl: instance 0, sysid 1\n"
        "epc-sitl: counters received=10 lockstep_timeouts=4 offboard_failsafes=1\n"
    )
    assert sitl_counters(log) == {"received": 10, "lockstep_timeouts": 4, "offboard_failsafes": 1}
    assert sitl_counters(tmp_path / "missing.log") == {}


def _options(*argv: str) -> SimOptions:
    return sim_options(build_parser().parse_args(["sim", *argv]))


def test_options_are_read_once_from_the_command_line() -> None:
    o = _options("--scenario", "circle", "--wind", "3,90", "--vehicles", "2", "--no-share",
                 "--json", "r.json", "--realtime")  # fmt: skip
    assert (o.scenario_name, o.vehicles, o.share, o.lockstep) == ("circle", 2, False, False)
    assert o.wind == (3.0, 90.0)
    assert o.json_path == Path("r.json")
    assert o.compare is None
    assert o.scenario == load_scenario("circle")
    with pytest.raises(dataclasses.FrozenInstanceError):
        o.vehicles = 3  # type: ignore[misc]
    calm = _options("--duration", "7.5")
    assert calm.wind == (calm.scenario.wind_speed_m_s, calm.scenario.wind_dir_deg)
    assert calm.scenario.duration_s == 7.5


def test_compare_options_name_the_methods_flown() -> None:
    assert _options("--scenario", "circle", "--compare").compare == (
        load_scenario("circle").compare.methods
    )
    o = _options("--compare", "pd:none, epc:kf")
    assert o.compare == ("pd:none", "epc:kf")
    one = o.flying("epc:kf")
    assert (one.controller, one.adaptation, one.method, one.compare) == (
        "epc", "kf", "epc:kf", None)  # fmt: skip


@pytest.mark.parametrize(
    ("argv", "message"),
    [
        (("--scenario", "nowhere"), "unknown scenario 'nowhere'"),
        (("--duration", "3"), "--duration must be finite and exceed the scenario's settle "
                              "time 3.0 s, got 3.0"),
        (("--compare", "epc:lwpr,epc:lwpr"), "--compare repeats a method"),
        (("--compare", "epc:magic"), "--compare: method 'epc:magic'"),
    ],
)
def test_bad_options_are_usage_errors(argv: tuple[str, ...], message: str) -> None:
    with pytest.raises(UsageError, match=message):
        _options(*argv)


def test_options_built_in_code_are_checked_too() -> None:
    with pytest.raises(UsageError, match="--vehicles must be >= 1"):
        SimOptions("hover", load_scenario("hover"), vehicles=0)
    with pytest.raises(ValueError, match="controller must be one of"):
        SimOptions("hover", load_scenario("hover"), controller="lqr")


def test_realtime_priority_reaches_the_services_loops_and_the_sitl(tmp_path) -> None:
    """``sim --realtime-priority P``: the loops' thread (loops.realtime_priority) and the SITL
    process SCHED_FIFO at P, as an autopilot on hardware of its own (issue 25: beside a
    light fleet the SITL starved as much as the loops). Without it, real time takes the
    service's configured priority (issue 21: 63.8 / 85 Hz and 42 failsafes at load 8-13
    without), 0 turns it off, and lockstep has none unless asked."""
    from epc_offboard.tools.sim.options import configured_realtime_priority
    from epc_offboard.tools.sim.orchestrate import service_config_for

    def loops(o: SimOptions) -> dict[str, object]:
        section = service_config_for(o, 1, 14999, tmp_path, tmp_path / "lib.sqlite")["loops"]
        assert isinstance(section, dict)
        return section

    o = _options("--scenario", "circle", "--realtime", "--realtime-priority", "20")
    assert o.fifo_priority == loops(o)["realtime_priority"] == 20
    o = _options("--scenario", "circle", "--realtime")
    assert configured_realtime_priority() == 50  # config/default.toml's
    assert o.fifo_priority == loops(o)["realtime_priority"] == 50
    o = _options("--scenario", "circle", "--realtime", "--realtime-priority", "0")
    assert o.fifo_priority == 0
    assert "realtime_priority" not in loops(o)
    assert _options().fifo_priority == 0  # lockstep
    assert "realtime_priority" not in loops(_options())
    assert _options("--realtime-priority", "30").fifo_priority == 30
    with pytest.raises(ValueError, match="realtime_priority"):
        _options("--realtime-priority", "100")


def test_a_scenario_may_end_its_flights_holding(tmp_path) -> None:
    """A flight lands unless its scenario's [service.mission] says land_at_end = false (the
    suite's entry and compare flights: the landing judged nothing there); --stagger always
    lands: its vehicles start on the landing before them."""
    from epc_offboard.tools.sim.orchestrate import service_config_for

    def land_at_end(*argv: str) -> bool:
        cfg = service_config_for(_options(*argv), 1, 14999, tmp_path, tmp_path / "l.sqlite")
        return bool(cfg["mission"]["land_at_end"])

    holding = tmp_path / "holding.toml"
    shipped = load_scenario("hover")
    holding.write_text(
        (SCENARIO_DIR / "hover.toml").read_text() + "\n[service.mission]\nland_at_end = false\n"
    )
    assert load_scenario(str(holding)).service["mission"] == {"land_at_end": False}
    assert shipped.service.get("mission") is None
    assert land_at_end("--scenario", "hover")
    assert not land_at_end("--scenario", str(holding))
    assert land_at_end("--scenario", str(holding), "--vehicles", "2", "--stagger")


def test_wall_clock_departures_of_a_lockstep_flight_reach_the_warnings():
    # what makes two lockstep flights of one seed differ on a loaded machine (stop 41): the
    # SITL ran on the wall clock for a while, or the flight log's writer fell behind (the
    # files differ, not the flight); each counted, neither said in the report
    stats = {"counters": {"log_records_dropped": 12}}
    assert flight_warnings(stats, {"lockstep_fallbacks": 2}) == {
        "flight log records dropped (flight.csv has gaps)": 12,
        "lockstep fell back to real time": 2,
    }
