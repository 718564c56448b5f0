"""`epc-offboard figures neuralfly` (issue 24): the README's Neural-Fly table is what its one
command writes. Pure: no flight (the command itself flies 30; its JSON is in tests/results/)."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from epc_offboard.cli import build_parser, main
from epc_offboard.tools import neuralfly
from epc_offboard.tools.readme import README, RESULTS_DIR, rewrite, values_from
from epc_offboard.tools.sim.options import sim_options
from epc_offboard.tools.sim.scenario import load_scenario


def test_every_row_by_every_method_is_a_valid_sim_command_line(tmp_path: Path) -> None:
    product = str(neuralfly.product_lwpr_scenario(tmp_path))
    assert len(neuralfly.ROWS) * len(neuralfly.METHODS) == 30
    seen = set()
    for row in neuralfly.ROWS:
        for m in neuralfly.METHODS:
            argv = neuralfly.sim_argv(row, m, product if m.product_lwpr else "neuralfly", -90.0,
                                      3, tmp_path / row.key / m.key)  # fmt: skip
            o = sim_options(build_parser().parse_args(argv))
            assert o.lockstep
            assert o.gcs_port == 0
            assert o.seed == 3
            assert o.compare is None
            assert (o.wind_speed_m_s, o.wind_dir_deg) == (row.speed_m_s, -90.0)
            assert o.wind_profile.text == row.profile
            assert o.method == m.method
            seen.add(
                (o.wind_speed_m_s, o.wind_profile.text, o.method, "estimator" in o.scenario.service)
            )
    assert len(seen) == 30


def test_the_product_lwpr_variant_differs_from_the_scenario_by_its_lwpr_alone(
    tmp_path: Path,
) -> None:
    scenario = load_scenario("neuralfly")
    product = load_scenario(str(neuralfly.product_lwpr_scenario(tmp_path)))
    assert scenario.service["estimator"]["lwpr"]["final_lambda"] == 0.98  # the forgetting
    assert "estimator" not in product.service
    assert product.service["position"] == scenario.service["position"]
    same = {k: v for k, v in vars(scenario).items() if k != "service"}
    assert same == {k: v for k, v in vars(product).items() if k != "service"}


def _flight(mean_m: float | None, status: str = "flown", hits: float | None = 0.97) -> dict:
    return {"status": status, "mean_error_m": mean_m, "hit_rate_after_first_lap": hits,
            "t_s": [0.0, 0.1], "error_cm": [1.0, 2.0], "lockstep_timeouts": 0}  # fmt: skip


def _table(tmp_path: Path) -> Path:
    methods = [vars(m) for m in neuralfly.METHODS]
    flights = {r.key: {m.key: _flight(0.0123 * (i + 1)) for i, m in enumerate(neuralfly.METHODS)}
               for r in neuralfly.ROWS}  # fmt: skip
    flights["8.5"]["epc-none"] = _flight(0.5, "left", None)
    flights["12.1"]["px4"] = _flight(None, "failed", None)
    targets = {r.key: [{"metric": "mean_error_m", "vs": None, "bound": 0.021, "verdict": "PASS"}]
               for r in neuralfly.ROWS}  # fmt: skip
    data = {"kind": "neuralfly_table", "command": "epc-offboard figures neuralfly --seed 0 "
            "--jobs 2", "seed": 0, "jobs": 2, "commit": "abc1234", "date_utc": "2026-11-26 20:00",
            "load_before": [4.1, 3, 2], "load_after": [5.2, 4, 3], "wall_s": 900.0,
            "cpu_s": 1500.0, "settle_s": 7.3, "rows": [vars(r) for r in neuralfly.ROWS],
            "methods": methods, "flights": flights, "targets": targets,
            "gain": neuralfly._gain(flights)}  # fmt: skip
    results = tmp_path / "results"
    results.mkdir()
    (results / "neuralfly.json").write_text(json.dumps(data))
    return results


def test_the_table_renders_from_its_json_with_the_gain_command_seed_and_load(
    tmp_path: Path,
) -> None:
    results = _table(tmp_path)
    text = neuralfly.render_table(results)
    lines = text.splitlines()
    assert lines[0].startswith("| wind | EPC + LWPR, forgetting (the scenario's) |")
    assert lines[0].endswith("| Neural-Fly | target (½ Neural-Fly) | hits after lap 1 |")
    assert lines[2] == ("| 0 m/s | 1.23 | 2.46 | 3.69 | 4.92 | 6.15 | 7.38 | 2.9 | 2.1 ✔ "
                        "| 97.0 % |")  # fmt: skip
    assert "| 8.5 m/s | 1.23 | 2.46 | 3.69 | left |" in text
    assert "| 12.1 m/s |" in text
    assert "| failed | 8.7 |" in text
    # 1 - 1.23 / 50: the no-adaptation flight left its envelope, so it says so
    assert "**98 %** less error than EPC without adaptation (50.00 → 1.23 cm" in text
    assert "left its envelope" in text
    assert "target ≥ 60 % ✔" in text
    assert "`epc-offboard figures neuralfly --seed 0 --jobs 2` (lockstep, seed 0" in text
    assert "15.0 min" in text
    assert "load 4.1 before and 5.2 after" in text
    # the recipes' numbers are not looked for in it, and the README's markers take it
    assert values_from(results) == {}
    readme = "a\n<!-- table:neuralfly -->\nold\n<!-- /table -->\nb\n"
    assert rewrite(readme, results) == f"a\n<!-- table:neuralfly -->\n{text}<!-- /table -->\nb\n"


def test_the_figure_is_drawn_from_the_json(tmp_path: Path) -> None:
    results = _table(tmp_path)
    neuralfly.write_figure(json.loads((results / "neuralfly.json").read_text()),
                           tmp_path / "nf.png")  # fmt: skip
    assert (tmp_path / "nf.png").stat().st_size > 10_000
    data = json.loads((results / "neuralfly.json").read_text())
    text = neuralfly.dumps(data)
    assert json.loads(text) == data
    assert '"error_cm": [1.0,2.0]' in text  # a series on one line


def test_the_readme_carries_the_table_its_command_and_figure() -> None:
    text = README.read_text()
    assert "<!-- table:neuralfly -->" in text
    assert "epc-offboard figures neuralfly" in text
    assert "tests/results/neuralfly.png" in text
    assert (RESULTS_DIR / "neuralfly.png").exists()
    data = json.loads((RESULTS_DIR / "neuralfly.json").read_text())
    assert {f["status"] for row in data["flights"].values() for f in row.values()} <= {
        "flown", "left"
    }  # fmt: skip


@pytest.mark.parametrize(
    ("argv", "message"),
    [(["--jobs", "3"], "--jobs must be 1..2"), (["circle"], "takes no NAME")],
)
def test_bad_neuralfly_arguments_are_usage_errors(argv: list[str], message: str, capsys) -> None:
    assert main(["figures", "neuralfly", *argv, "--numbers-only"]) == 2
    assert message in capsys.readouterr().err
