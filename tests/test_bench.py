"""A tiny benchmark run: the docs/CONTRACTS.md report shape and exactness."""

from __future__ import annotations

import argparse
import json

from epc_offboard.tools.bench import run_bench, run_bench_command


def test_tiny_bench_reports_the_contract_shape(tmp_path, capsys):
    out = tmp_path / "bench.json"
    code = run_bench_command(argparse.Namespace(horizon=5, steps=80, json=str(out)))
    assert code == 0
    report = json.loads(out.read_text())
    assert report["horizon"] == 5
    assert report["steps"] == 80
    assert isinstance(report["sequence"], str)
    for method in ("epc", "osqp", "daqp"):
        assert report["methods"][method]["median_us"] > 0
        assert report["methods"][method]["p99_us"] >= report["methods"][method]["median_us"]
    epc = report["methods"]["epc"]
    assert 0.0 <= epc["hit_rate"] <= 1.0
    assert epc["library_size"] >= 1
    assert report["max_input_error"] <= 1e-6
    assert "epc" in capsys.readouterr().out


def test_bench_measures_the_hit_rate_once_the_sequence_repeats():
    report = run_bench(horizon=4, steps=620)
    assert report["methods"]["epc"]["hit_rate_repeat"] > 0.9


def test_bad_horizon_is_a_usage_error(capsys):
    assert run_bench_command(argparse.Namespace(horizon=1, steps=10, json=None)) == 2
    assert "horizon" in capsys.readouterr().err


def test_bench_says_clearly_when_daqp_is_missing(monkeypatch, capsys):
    import sys

    monkeypatch.setitem(sys.modules, "daqp", None)  # import daqp -> ImportError
    report = run_bench(horizon=3, steps=20)
    assert "not installed" in report["methods"]["daqp"]["missing"]
    assert report["exact_reference"] == "osqp"


def test_service_bench_replays_a_recorded_flight_through_every_tick_component(tmp_path, capsys):
    """A short lockstep figure-8 (just past its 6 s settle time) recorded and replayed: the
    report's shape, and components that add up to their ticks (not timings: those are the
    benchmark's business)."""
    out = tmp_path / "service.json"
    args = argparse.Namespace(horizon=20, steps=0, json=str(out), service=True,
                              recording=None, duration=6.5)
    assert run_bench_command(args) == 0
    report = json.loads(out.read_text())
    assert (tmp_path / "service.png").stat().st_size > 0
    assert report["position_ticks"] >= 600  # 6.5 s at 100 Hz
    assert report["attitude_ticks"] >= 2 * report["position_ticks"] - 2
    for loop, parts in (("position", {"pump", "state", "reference", "estimator", "epc",
                                      "cascade_rest"}),
                        ("attitude", {"state", "attitude", "encode"}),
                        ("receive", {"decode", "state"})):
        comps = report[loop]["components"]
        assert set(comps) == parts
        for s in (*comps.values(), report[loop]["tick"]):
            assert set(s) == {"median_us", "p99_us", "max_us", "mean_us"}
            assert 0.0 <= s["median_us"] <= s["p99_us"] <= s["max_us"]
        # each tick is the sum of its components: so are the means
        total = sum(c["mean_us"] for c in comps.values())
        assert abs(total - report[loop]["tick"]["mean_us"]) <= 1e-6 * total + 1e-6
        assert report[loop]["tick"]["mean_us"] > 0
    epc = report["epc"]
    assert epc["hits"] + epc["misses"] == report["position_ticks"]
    assert sum(report["sources"].values()) == report["position_ticks"]
    assert epc["worker_solves"] >= 0
    assert epc["library_size"] >= 1
    assert epc["max_checks"] >= 1
    assert len(report["samples_us"]["position_tick"]) == report["position_ticks"]
    assert "position tick" in capsys.readouterr().out
