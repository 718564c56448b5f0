"""The machine's floor beside the loops (bench --attack's bare 200 Hz loops, stop 42): the
probe's analysis on known records, the probe process itself, and the bench's JSON with it.
No timing bound: the records' structure only (real-time figures live in the bench)."""

from __future__ import annotations

import contextlib
import json
import time
from pathlib import Path

import numpy as np
import pytest

from epc_offboard.tools import attack_analysis as aa
from epc_offboard.tools import bench_attack, floor_probe

P = 0.005


def _records(late_ms: dict[int, float], n: int = 200, skip: tuple[int, ...] = (),
             slow: tuple[int, ...] = ()) -> dict[str, np.ndarray]:  # fmt: skip
    """Ticks due every 5 ms from t = 100 s, each woken 0.1 ms late unless ``late_ms`` says;
    ``skip``: deadlines passed by (no tick); ``slow``: ticks whose compute took 6 ms of wall
    time (20 us of CPU)."""
    k = np.array([i for i in range(n) if i not in skip])
    due = 100.0 + k * P
    late = np.array([late_ms.get(int(i), 0.1) for i in k]) * 1e-3
    wall = np.where(np.isin(k, slow), 6e-3, 30e-6)
    return {"due_s": due, "wake_s": due + late, "compute_wall_s": wall,
            "compute_cpu_s": np.full(k.size, 20e-6)}  # fmt: skip


def test_the_probes_misses_gaps_and_lateness_are_those_of_its_known_ticks():
    # tick 50 woken 6 ms late: a miss, no 12 ms gap at 200 Hz (10.9 ms), one at 100 Hz
    # (15.9 ms); tick 100 8 ms late: a miss and a gap at both rates (12.9, 17.9 ms); tick 150
    # computed 6 ms: a miss, no gap; deadline 170 passed by: no gap at 200 Hz (10 ms), a
    # 20 ms one at 100 Hz (an even tick)
    rec = _records({50: 6.0, 100: 8.0, 101: 3.0}, skip=(170,), slow=(150,))
    fig = aa.probe_figures(rec, 99.0, 102.0, P)
    assert fig["ticks"] == 199
    assert fig["misses"] == 3
    assert fig["gaps_over_12ms"] == 1
    assert fig["gaps_over_12ms_100hz"] == 3
    assert fig["skipped"] == 1
    assert fig["lateness_ms"]["p50"] == 0.1
    assert fig["lateness_ms"]["max"] == 8.0
    assert 3.0 < fig["lateness_ms"]["p99"] < 6.0
    assert fig["compute_off_cpu_ms"] == pytest.approx(6.0 - 0.02 + 198 * 0.01, abs=1e-3)
    # a window holds its own ticks only: the first 0.4 s (ticks 0-79: the first miss)
    early = aa.probe_figures(rec, 99.0, 100.0 + 79.5 * P, P)
    assert (early["ticks"], early["misses"], early["gaps_over_12ms"]) == (80, 1, 0)


def test_a_loops_lateness_comes_from_its_grid_even_across_the_periods_edge():
    rng = np.random.default_rng(1)
    late = rng.uniform(0.0, 0.3 * P, 2000)
    late[7] = 0.0  # its best tick: the grid's phase
    late[500] = 0.45 * P  # one late tick, still within half a period of the rest
    for phase in (0.0012, P - 1e-4):  # the ticks' times wrap past the period's edge
        t = 5000.0 + phase + np.arange(2000) * P + late
        got = aa.grid_lateness_s(t, P)
        assert np.allclose(got, late, atol=0.01 * P)  # the phase: the 0.5 % earliest
        t[9] -= 0.2 * P  # one tick logged early of the grid: the phase does not follow it
        assert np.allclose(np.delete(aa.grid_lateness_s(t, P), 9), np.delete(late, 9),
                           atol=0.01 * P)  # fmt: skip


def test_the_loops_beside_the_probe_give_ratios_and_none_without_a_probe_miss():
    rec = _records({50: 6.0})  # one miss, at 100.256 s
    t = np.arange(99.5, 101.5, 0.01)
    flight = {"t_s": t, "phase": np.full(t.size, "offboard")}
    flight["t_s"] = np.where(t > 100.3, t + 0.004, t)  # one 14 ms gap
    att = np.asarray(99.5 + np.arange(400) * P, dtype=np.float64)
    misses = [{"loop": "attitude", "t_s": x, "interval_ms": 11.0, "compute_ms": 0.2}
              for x in (100.1, 100.2, 100.6, 100.7)]  # fmt: skip
    wins = [aa.Window("hover", "calm", 99.6, 100.4, {}),
            aa.Window("hover", "flood", 100.45, 101.4, {})]  # fmt: skip
    out = aa.floor_figures({"sleep": rec}, flight, att, misses, wins, P)
    calm, flood = out["windows"]
    assert calm["loops"]["attitude_misses"] == 2
    assert calm["sleep"]["misses"] == 1
    assert calm["ratio_sleep"]["misses"] == 2.0
    assert calm["loops"]["position_gaps_over_12ms"] == 1
    assert flood["sleep"]["misses"] == 0
    assert flood["ratio_sleep"]["misses"] is None
    assert out["flight"]["loops"]["attitude_misses"] == 4
    assert out["attack_windows"]["loops"]["attitude_misses"] == 2
    assert out["attack_windows"]["sleep"]["misses"] == 0
    assert "machine floor" in aa.floor_summary(out)


@pytest.fixture(scope="module")
def probe_run(tmp_path_factory: pytest.TempPathFactory) -> dict[str, dict]:
    """Both probes run for real for 1.5 s (~300 ticks each), stopped by SIGTERM as the bench
    stops them (``bench_attack.Probes``), at the lowest SCHED_FIFO priority."""
    run_dir = tmp_path_factory.mktemp("probe")
    probes = bench_attack.Probes(run_dir, priority=1, cpu=None)
    for wake in probes.procs:  # each is up and ticking
        assert probes.wait_ready(wake)["wake"] == wake
    time.sleep(1.5)
    return probes.close()


def test_the_probe_process_ticks_on_deadlines_5_ms_apart_until_stopped(probe_run):
    meta = probe_run
    assert sorted(meta) == sorted(floor_probe.WAKES)
    for wake, m in meta.items():
        assert m["exit"] == 0
        assert m["cpu_s"] > 0.0  # its cost, told
        assert m["ticks"] == floor_probe.read_records(Path(m["path"]))["due_s"].size
        rec = floor_probe.read_records(Path(m["path"]))
        assert sorted(rec) == sorted(floor_probe.COLUMNS)
        assert rec["due_s"].size > 50, wake
        steps = np.diff(rec["due_s"]) / floor_probe.PERIOD_S
        assert np.allclose(steps, np.rint(steps), atol=1e-6)  # on the grid (skips: whole)
        assert np.all(np.rint(steps) >= 1)
        assert np.all(rec["wake_s"] >= rec["due_s"])  # never woken early
        assert np.all(rec["compute_cpu_s"] > 0.0)
        assert np.all(rec["compute_wall_s"] > 0.0)


def test_the_bench_json_has_the_probes_fields(probe_run):
    meta = probe_run
    # the flight starts when both probes tick: each waited ready, but a probe at FIFO 1 may
    # be held off its first tick past the other's first second (the lead's suite run at load
    # 10-17: one probe had no tick in a flight from the earlier one's first: "ticks 0")
    t0 = float(max(floor_probe.read_records(Path(m["path"]))["wake_s"][0]
                   for m in meta.values()))  # fmt: skip
    t = t0 + np.arange(0.0, 1.0, 0.01)
    flight = {"t_s": t, "phase": np.full(t.size, "offboard")}
    wins = [aa.Window("hover", "calm", t0, t0 + 0.5, {}),
            aa.Window("hover", "flood", t0 + 0.5, t0 + 1.0, {})]  # fmt: skip
    report = bench_attack.floor_report(meta, flight, t0 + np.arange(200) * P, [], wins, P)
    assert report is not None
    report = json.loads(json.dumps(report))  # as the bench writes it
    assert sorted(report["probed"]) == sorted(floor_probe.WAKES)
    for wake in floor_probe.WAKES:
        assert isinstance(report["probes"][wake]["fifo_applied"], bool)
        for part in (report["flight"], *report["windows"]):
            assert {"misses", "gaps_over_12ms", "gaps_over_12ms_100hz", "lateness_ms",
                    "compute_wall_us", "compute_cpu_us"} <= set(part[wake])  # fmt: skip
            assert set(part[f"ratio_{wake}"]) == {"misses", "gaps_over_12ms", "lateness_p99"}
        assert report["flight"][wake]["ticks"] > 0
    assert bench_attack.floor_report({}, flight, t, [], wins, P) is None  # --no-probe


def test_a_loops_gap_is_shared_when_a_bare_loop_was_late_inside_it():
    rec = _records({60: 3.0})  # due 100.300 s, woken 100.303 s
    t = np.arange(99.5, 101.5, 0.01)
    flight = {"t_s": np.where(t > 100.295, t + 0.004, t),  # a 14 ms gap: 100.29-100.304
              "phase": np.full(t.size, "offboard")}  # fmt: skip
    misses = [{"loop": "attitude", "t_s": 100.7, "interval_ms": 10.0, "compute_ms": 0.2}]
    out = aa.shared_events({"sleep": rec}, flight, misses, 99.6, 101.4)
    assert out["position"] == {"total": 1, "with_probe_late": {"sleep": 1},
                               "by_chance": {"sleep": 0}}  # fmt: skip
    assert out["attitude"] == {"total": 1, "with_probe_late": {"sleep": 0},
                               "by_chance": {"sleep": 0}}  # fmt: skip
    # the control: a bare loop late 0.5 s after the attitude miss counts by chance
    late = aa.shared_events({"sleep": _records({60: 3.0, 239: 4.0}, n=300)}, flight, misses, 99.6,
                            101.4)  # fmt: skip
    assert late["attitude"]["by_chance"] == {"sleep": 1}
    position, attitude = out["events"]
    assert position["probe_late_ms"]["sleep"] == pytest.approx(3.0)
    assert attitude["probe_late_ms"]["sleep"] == pytest.approx(0.1)
    assert (attitude["t0_s"], attitude["t1_s"]) == (100.6902, 100.7002)


def test_the_probes_end_with_a_killed_bench_and_leave_their_records(tmp_path: Path) -> None:
    # a probe at the loops' SCHED_FIFO priority outlived a SIGKILLed bench (up to its
    # --seconds, an hour), waking 200 times a second beside whatever ran next
    import os
    import signal
    import subprocess
    import sys

    bench = subprocess.Popen(
        [sys.executable, "-c",
         "import sys, time\n"
         "from pathlib import Path\n"
         "from epc_offboard.tools import bench_attack\n"
         "probes = bench_attack.Probes(Path(sys.argv[1]), priority=1, cpu=None)\n"
         "print(*(probes.wait_ready(w)['pid'] for w in probes.procs), flush=True)\n"
         "time.sleep(60)\n", str(tmp_path)],
        stdout=subprocess.PIPE, text=True)  # fmt: skip
    assert bench.stdout is not None
    pids = [int(p) for p in bench.stdout.readline().split()]
    try:
        assert len(pids) == len(floor_probe.WAKES)
        bench.kill()
        bench.wait()
        deadline = time.monotonic() + 30.0
        alive = pids
        while alive and time.monotonic() < deadline:
            time.sleep(0.05)
            alive = [p for p in pids if Path(f"/proc/{p}").exists()
                     and Path(f"/proc/{p}/stat").read_text().split()[2] != "Z"]  # fmt: skip
        assert alive == [], "a probe outlived its bench"
    finally:
        for pid in pids:
            with contextlib.suppress(ProcessLookupError):
                os.kill(pid, signal.SIGKILL)
    for wake in floor_probe.WAKES:  # SIGTERM, not a kill: each wrote what it measured
        assert floor_probe.read_records(tmp_path / f"probe-{wake}.f64")["due_s"].size > 0, wake
