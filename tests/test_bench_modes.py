"""`bench --modes`: the scenarios it flies and how it judges them (its flights: the bench)."""

from __future__ import annotations

import tomllib

import pytest

from epc_offboard.cli import build_parser
from epc_offboard.tools.bench_modes import SPECS, compare, scenario_toml, targets


def _flight(flight: str, mode: str, timing: str, rmse_m: float, **extra: object) -> dict:
    return {
        "flight": flight, "mode": mode, "timing": timing, "rmse_m": rmse_m,
        "max_error_m": 2 * rmse_m, "flips": 0, "climbs_over_1m": 0,
        "max_tilt_outside_entry_deg": 10.0, "finished": True, **extra,
    }  # fmt: skip


@pytest.mark.parametrize("mode", ["epc", "autopilot"])
def test_each_flight_is_its_scenario_in_the_mode_without_the_scenarios_targets(mode):
    for spec in SPECS.values():
        data = tomllib.loads(scenario_toml(spec, mode))
        assert data["service"]["attitude"]["mode"] == mode
        assert "targets" not in data
        assert "compare" not in data
        assert data["trajectory"]["shape"] == spec.scenario


def test_ratios_and_targets():
    results = [
        _flight("circle", "epc", "realtime", 0.10),
        _flight("circle", "autopilot", "realtime", 0.05),  # body rates twice as bad
        _flight("circle", "epc", "lockstep", 0.050),
        _flight("circle", "autopilot", "lockstep", 0.049),  # within the slack: no worse
        _flight(
            "figure8-wind",
            "epc",
            "realtime",
            0.066,
            flips=1,
            climbs_over_1m=1,
            max_tilt_outside_entry_deg=50.0,
        ),
        _flight("figure8-wind", "epc", "lockstep", 0.060),
    ]
    ratios = compare(results)
    assert ratios["body_rates_over_quaternion"]["circle/realtime"]["rmse_m"] == 2.0
    assert ratios["realtime_over_lockstep"]["figure8-wind/epc"]["rmse_m"] == 1.1
    got = targets(results, ratios)
    assert got["body_rates_worse_than_quaternion"] == {"circle/realtime": 2.0}
    assert got["flips"] == 1
    assert got["climbs_over_1m"] == 1
    assert got["tilt_over_35_outside_entry"] == ["figure8-wind/epc/realtime"]
    assert got["windy_figure8_within_20_percent"] is True


def test_the_command_line():
    args = build_parser().parse_args(["bench", "--modes", "--hogs", "2", "--timing", "realtime"])
    assert args.modes
    assert args.hogs == 2
    assert args.timing == "realtime"
