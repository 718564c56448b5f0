"""A tiny benchmark run: the CONTRACTS report shape and exactness."""

from __future__ import annotations

import argparse
import json

from epc_offboard.bench import run_bench, run_bench_command


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
