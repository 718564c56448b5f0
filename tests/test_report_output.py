"""What `sim` shows a user: tables (plain text when piped, units as labelled), the progress
labels and the figures, on synthetic flights (pure, no flight)."""

from __future__ import annotations

import io
from pathlib import Path
from typing import Any

import numpy as np

from epc_offboard.tools.compare import MethodRun, print_compare, write_compare_figure
from epc_offboard.tools.figures import events, flight_title, phase_spans, write_figure
from epc_offboard.tools.sim.analysis import VehicleResult
from epc_offboard.tools.sim.orchestrate import VehicleRun, flight_progress
from epc_offboard.tools.sim.report import print_report, print_targets
from epc_offboard.tools.sim.scenario import load_scenario
from epc_offboard.tools.tables import format_metric, render_plain

BOX_CHARS = set("┏┓┗┛┃━│─┡┩╇╋┳┻┼└┘┌┐")
EVENTS = [
    {"t_s": -6.0, "phase": "preflight", "reason": "arming"},
    {"t_s": -2.4, "phase": "streaming", "reason": "airborne"},
    {"t_s": -1.9, "phase": "offboard_requested", "reason": "requesting offboard"},
    {"t_s": 0.0, "phase": "offboard", "reason": "offboard confirmed"},
    {"t_s": 4.2, "phase": "failsafe", "reason": "state stale"},
    {"t_s": 10.0, "phase": "landing", "reason": "mission complete"},
    {"t_s": 19.0, "phase": "done", "reason": "landed"},
]


def vehicle_report(vid: int, rmse_m: float = 0.0043, received: int = 0) -> dict[str, Any]:
    return {
        "id": vid,
        "tracking": {"rmse_m": rmse_m, "max_error_m": 0.0064},
        "max_speed_m_s": 0.01,
        "max_abs_vel_m_s": [0.0, 0.0, 0.0],
        "constraint_violations": 0,
        "library": {"size": 6, "hits": 1228, "misses": 7, "hit_rate": 0.9943, "qp_solves": 6,
                    "received_shared": received, "first_lap_misses": 3},
        "fleet": {"controllers_received": 3 * received,
                  "controllers_used": {"position": received, "attitude": 1 if received else 0}},
        "loops": {"position": {"rate_hz": 100.0, "compute_us_p99": 5353.0,
                               "compute_us_median": 900.0},
                  "attitude": {"rate_hz": 200.0}},
        "warnings": {},
        "phase_events": EVENTS,
    }  # fmt: skip


def sim_report(n: int = 2, note: str = "") -> dict[str, Any]:
    return {
        "scenario": "hover",
        "controller": "epc",
        "adaptation": "lwpr",
        "note": note,
        "vehicles": [vehicle_report(k, received=14 * (k - 1)) for k in range(1, n + 1)],
    }


def synthetic_result(vid: int, path: bool) -> VehicleResult:
    """A flight of 10 s under offboard (from -2.4 s) along a 10 m line, or a hover."""
    t = np.arange(-2.4, 10.0, 0.01)
    if path:
        ref = np.column_stack([np.zeros_like(t), 5.0 * np.sin(0.5 * t), np.full_like(t, -2.5)])
    else:
        ref = np.tile([0.0, 0.0, -2.5], (len(t), 1))
    offset = 0.003 * np.column_stack([np.cos(t), np.sin(t), np.zeros_like(t)])
    pos = ref + offset * (1.0 + 20.0 * (t < 1.0))[:, None] + 0.01 * vid
    vel = np.gradient(pos, t, axis=0)
    sources = np.where(np.arange(len(t)) % 97 == 0, "solved", "hit")
    tt = np.arange(-6.0, 25.0, 0.02)  # truth runs on after landing: not drawn
    truth_pos = np.column_stack([np.interp(tt, t, pos[:, k]) for k in range(3)])
    truth_vel = np.column_stack([np.interp(tt, t, vel[:, k]) for k in range(3)])
    return VehicleResult(
        vid, vehicle_report(vid), t, pos, ref, vel, np.linalg.norm(pos - ref, axis=1), sources,
        truth_t_s=tt, truth_pos_ned_m=truth_pos, truth_vel_ned_m_s=truth_vel,
    )  # fmt: skip


def assert_plain_and_aligned(text: str, header_word: str) -> list[str]:
    assert not BOX_CHARS & set(text), text
    lines = text.splitlines()
    start = next(i for i, line in enumerate(lines) if line.startswith(header_word))
    header, rule = lines[start], lines[start + 1]
    assert set(rule) <= {"-", " "}
    # every column ends where the rule's dashes end: right-aligned numbers line up
    ends = [
        i + 1 for i, c in enumerate(rule) if c == "-" and (i + 1 == len(rule) or rule[i + 1] == " ")
    ]
    # the table's rows: the lines after the rule as long as it (the last column is right-aligned)
    body = []
    for ln in lines[start + 2 :]:
        if len(ln) != len(rule):
            break
        body.append(ln)
    assert body
    rows = [header, *body]
    for row in rows[1:]:
        for end in ends[1:]:
            assert row[end - 1] != " ", f"column ending at {end} misaligned in {row!r}"
    return rows


def test_report_table_is_plain_aligned_text_when_not_a_tty() -> None:
    out = io.StringIO()  # not a TTY, as a pipe or a file
    print_report(sim_report(2, note="large by design"), file=out)
    text = out.getvalue()
    rows = assert_plain_and_aligned(text, "id")
    assert "lap-1 misses" in rows[0]
    assert "fleet rcvd" in rows[0]
    assert "fleet used" in rows[0]
    assert "pos tick p99 us" in rows[0]  # a tick's wall time, not compute (the note says)
    assert "pos tick: wall time" in text
    assert rows[1].split()[0] == "1"
    assert rows[2].split()[0] == "2"
    assert rows[2].split()[8] == "42"  # vehicle 2 received 42 controllers from the fleet
    assert rows[2].split()[9] == "15"  # and used 14 + 1 of them (position, attitude)
    assert rows[1].split()[6] == "3"  # first-lap misses
    assert "note: large by design" in text
    assert "vehicle 2 warnings: none" in text


def test_report_table_prints_errors_in_cm() -> None:
    out = io.StringIO()
    print_report(sim_report(1), file=out)
    row = assert_plain_and_aligned(out.getvalue(), "id")[1].split()
    assert row[1] == "0.43"
    assert row[2] == "0.64"


def test_targets_print_in_the_metric_unit() -> None:
    assert format_metric("rmse_m", 0.0074) == "0.74 cm"
    assert format_metric("max_error_m", 0.05) == "5.00 cm"
    assert format_metric("max_speed_m_s", 2.5) == "2.50 m/s"
    assert format_metric("constraint_violations", 0) == "0"
    verdict = {"target": "EPC+LWPR RMSE <= 10 cm", "metric": "rmse_m", "value": 0.0074,
               "bound": 0.10, "verdict": "PASS"}  # fmt: skip
    out = io.StringIO()
    print_targets([verdict], file=out)
    assert out.getvalue().strip() == "target PASS: EPC+LWPR RMSE <= 10 cm (0.74 cm <= 10.00 cm)"
    summary = {"scenario": "figure8", "reports": [sim_report(1)], "targets": [verdict]}
    out = io.StringIO()
    print_compare(summary, file=out)
    text = out.getvalue()
    assert_plain_and_aligned(text, "method")
    line = next(ln for ln in text.splitlines() if ln.startswith("EPC+LWPR"))
    assert line.split()[-5:] == ["0.74", "cm", "10.00", "cm", "PASS"]


def test_render_plain_alignment() -> None:
    text = render_plain("t", ["name", "value"], [["a", "1.5"], ["long name", "12.25"]], left=1)
    assert text.splitlines()[1:] == [
        "name       value",
        "---------  -----",
        "a            1.5",
        "long name  12.25",
    ]


def test_the_zigzag_bounded_note_says_why_its_error_is_large() -> None:
    note = load_scenario("zigzag_bounded").note
    assert "by design" in note
    assert "3.75" in note
    assert "3.0" in note


def test_progress_labels_the_phases(tmp_path: Path) -> None:
    run = VehicleRun(1, tmp_path)
    assert flight_progress(run, 10.0) == ("takeoff", 0.0)
    header = "t_s,vehicle_t_s,phase,source\n"
    run.flight_log.write_text(header + "3.65,3.65,streaming,hit\n")
    assert flight_progress(run, 10.0) == ("entering offboard", 0.0)
    rows = "".join(f"{t:.2f},{t:.2f},offboard,hit\n" for t in np.arange(6.0, 9.205, 0.01))
    run.flight_log.write_text(header + "3.65,3.65,streaming,hit\n" + rows)
    label, done_s = flight_progress(run, 10.0)
    assert label == "offboard 3.2/10 s"
    assert abs(done_s - 3.2) < 0.02
    rows = "".join(f"{t:.2f},{t:.2f},offboard,hit\n" for t in np.arange(6.0, 16.0, 0.01))
    run.flight_log.write_text(header + rows)
    assert flight_progress(run, 10.0)[0] == "landing"
    # the log stopped short of the duration while the vehicle's clock ran on: landing
    rows = "".join(f"{t:.2f},{t:.2f},offboard,hit\n" for t in np.arange(6.0, 12.0, 0.01))
    run.flight_log.write_text(header + rows)
    run.groundtruth.write_text("t_s,pos_n_m\n11.99,0\n")
    assert flight_progress(run, 10.0)[0] == "offboard 6.0/10 s"
    run.groundtruth.write_text("t_s,pos_n_m\n11.99,0\n14.5,0\n")
    assert flight_progress(run, 10.0)[0] == "landing"
    run.stats.write_text("{}")
    assert flight_progress(run, 10.0) == ("landed", 10.0)


def test_phase_spans_from_the_events() -> None:
    spans = {s.name: (s.start_s, s.end_s) for s in phase_spans(EVENTS, 3.0, -6.5, 25.0)}
    assert spans == {"takeoff": (-6.0, -2.4), "to offboard": (-2.4, 0.0), "settle": (0.0, 3.0),
                     "RMSE window": (3.0, 10.0), "landing": (10.0, 19.0)}  # fmt: skip
    assert [s.name for s in phase_spans([], 3.0, -1.0, 10.0)] == [
        "takeoff",
        "settle",
        "RMSE window",
    ]


def test_flight_figure_for_one_and_two_vehicles(tmp_path: Path) -> None:
    bounds = np.array([3.8, 3.8, 2.0])
    hover = [synthetic_result(1, path=False)]
    fleet = [synthetic_result(1, path=True), synthetic_result(2, path=True)]
    for results, name in ((hover, "hover.png"), (fleet, "fleet.png")):
        path = tmp_path / name
        write_figure(results, bounds, path, "synthetic", settle_s=3.0)
        assert path.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
        assert path.stat().st_size > 10_000


def test_flight_and_compare_figures_are_drawn_once(tmp_path: Path, monkeypatch) -> None:
    """savefig with the constrained layout engine drew every figure twice (~1 s of CPU a sim);
    laid out first, each is drawn once (the same PNG bytes as before, compared when changed)."""
    from matplotlib.figure import Figure

    draws: list[int] = []
    real_draw = Figure.draw

    def counted(self: Figure, renderer: Any) -> None:
        draws.append(1)
        real_draw(self, renderer)

    monkeypatch.setattr(Figure, "draw", counted)
    write_figure([synthetic_result(1, path=True)], np.array([3.8, 3.8, 2.0]),
                 tmp_path / "flight.png", "synthetic", settle_s=3.0)  # fmt: skip
    assert len(draws) == 1
    flown = [MethodRun("epc:lwpr", sim_report(1), [synthetic_result(1, True)])]
    write_compare_figure(flown, np.array([3.0, 3.0, 2.0]), tmp_path / "compare.png",
                         load_scenario("zigzag"), "zigzag", (1.5, -135.0))  # fmt: skip
    assert len(draws) == 2


def test_compare_figure(tmp_path: Path) -> None:
    flown = [
        MethodRun(m, sim_report(1), [synthetic_result(1, True)]) for m in ("epc:lwpr", "pd:none")
    ]
    path = tmp_path / "compare.png"
    write_compare_figure(flown, np.array([3.0, 3.0, 2.0]), path, load_scenario("zigzag"), "zigzag",
                         (1.5, -135.0))  # fmt: skip
    assert path.stat().st_size > 10_000


def test_only_failsafes_and_stops_are_drawn_red_not_a_healthy_start() -> None:
    # ArduPilot's normal start waits for a fresh state (its EKF) before arming: a healthy
    # phase, drawn red like a failsafe before
    r = synthetic_result(1, path=False)
    healthy = [{"t_s": -30.0, "phase": "wait_heartbeat"}, {"t_s": -29.0, "phase": "wait_state"},
               *EVENTS[:4], *EVENTS[5:]]  # fmt: skip
    r.report["phase_events"] = healthy
    assert events(r) == []
    faulty = [*healthy[:6], {"t_s": 4.2, "phase": "failsafe"}, {"t_s": 5.0, "phase": "wait_state"},
              {"t_s": 6.0, "phase": "pilot"}, *healthy[6:]]  # fmt: skip
    r.report["phase_events"] = faulty
    assert events(r) == [(4.2, "failsafe", "red"), (5.0, "wait_state", "darkorange"),
                         (6.0, "pilot", "darkorange")]  # fmt: skip
    r.report["stopped"] = "stopped by sim: it left its envelope"
    assert events(r)[-1] == (float(r.truth_t_s[-1]), "stopped by sim", "red")


def test_every_title_names_the_wind_the_autopilot_and_the_controller() -> None:
    title = flight_title("figure8", "epc:lwpr", "ardupilot", (3.0, 45.0))
    assert title == ("figure8: epc + lwpr, bundled SITL as ArduPilot, wind 3 m/s towards 45° "
                     "(CCW from east)")  # fmt: skip
    assert "no wind" in flight_title("hover", "pd:none", "px4", (0.0, 0.0))
    assert "2 vehicles" in flight_title("circle", "epc:lwpr", "px4", (0.0, 0.0), vehicles=2)


def test_deadline_misses_and_logged_warnings_are_printed_with_the_table() -> None:
    report = sim_report(1)
    v = report["vehicles"][0]
    v["loops"]["position"]["deadline_misses"] = 2
    v["loops"]["attitude"]["deadline_misses"] = 344
    key = "service WARNING epc_offboard.x: something odd (<n> so far)"
    v["warnings"] = {"failsafes": 1, key: 3}
    v["warning_examples"] = {key: "2026-11-26 00:00:00,000 WARNING epc_offboard.x: odd (1)"}
    buf = io.StringIO()
    print_report(report, file=buf)
    text = buf.getvalue()
    rows = assert_plain_and_aligned(text, "id")
    assert rows[0].endswith("deadline misses pos/att")
    assert rows[1].endswith("2/344")
    assert "vehicle 1 warnings: failsafes 1" in text
    assert f"  3x {key}" in text
