"""Scenario targets: parsing, validation and verdicts (pure, no flight)."""

from __future__ import annotations

import pytest

from epc_offboard.common.configio import ConfigError
from epc_offboard.tools.sim.scenario import load_scenario
from epc_offboard.tools.targets import TargetConfig, evaluate, parse_method


def report(rmse: float, max_err: float = 0.0, violations: int = 0) -> dict:
    return {"vehicles": [{"tracking": {"rmse_m": rmse, "max_error_m": max_err},
                          "max_speed_m_s": 1.0, "constraint_violations": violations}]}


def test_absolute_relative_and_missing_targets():
    targets = (
        TargetConfig("epc:lwpr", "max_error_m", max=0.02),
        TargetConfig("epc:lwpr", "rmse_m", vs="epc:none", ratio=0.5),
        TargetConfig("epc:lwpr", "constraint_violations", max=0),
        TargetConfig("epc:lwpr", "rmse_m", vs="mpc:kf"),
    )
    reports = {"epc:lwpr": report(0.01, 0.025, 0), "epc:none": report(0.03)}
    verdicts = [v["verdict"] for v in evaluate(targets, reports)]
    assert verdicts == ["FAIL", "PASS", "PASS", "n/a"]


def test_target_needs_exactly_one_bound_and_known_methods():
    with pytest.raises(ValueError, match="exactly one"):
        TargetConfig("epc:lwpr", "rmse_m")
    with pytest.raises(ValueError, match="exactly one"):
        TargetConfig("epc:lwpr", "rmse_m", max=1.0, vs="pd:none")
    with pytest.raises(ValueError, match="controller"):
        parse_method("lqr:none")
    with pytest.raises(ValueError, match="CONTROLLER:ADAPTATION"):
        parse_method("epc")


@pytest.mark.parametrize("name", ["circle", "zigzag", "figure8"])
def test_thesis_scenarios_declare_methods_and_targets(name):
    sc = load_scenario(name)
    assert sc.targets
    for t in sc.targets:  # every target compares methods the default compare flies
        assert set(t.methods) <= set(sc.compare.methods)


def test_bad_target_in_a_scenario_names_the_file(tmp_path):
    path = tmp_path / "bad.toml"
    path.write_text('[[targets]]\nmethod = "epc:lwpr"\nmetric = "rmse_m"\n')
    with pytest.raises(ConfigError, match=r"bad\.toml"):
        load_scenario(str(path))
