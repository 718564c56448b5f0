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


def test_the_gain_baseline_alone_flies_the_wider_comparison_envelope(tmp_path: Path) -> None:
    # issue 24: EPC without adaptation at 8.5 m/s is blown 2 m off within its first lap
    # (seeds 3 and 4), which sim stops: the gain's comparison flies it in a figures-only
    # envelope, the scenario and sim's default unchanged
    scenario = load_scenario("neuralfly")
    wide_path = neuralfly.comparison_scenario(tmp_path)
    wide = load_scenario(str(wide_path))
    assert scenario.envelope.max_error_m == 2.0
    assert wide.envelope.max_error_m == neuralfly.COMPARISON_MAX_ERROR_M > 2.0
    assert {k: v for k, v in vars(wide).items() if k != "envelope"} == {
        k: v for k, v in vars(scenario).items() if k != "envelope"}
    product = str(neuralfly.product_lwpr_scenario(tmp_path))
    flown = {(r.key, m.key): neuralfly.scenario_arg(r, m, product, str(wide_path))
             for r in neuralfly.ROWS for m in neuralfly.METHODS}  # fmt: skip
    assert [k for k, v in flown.items() if v == str(wide_path)] == [("8.5", "epc-none")]
    assert flown[("8.5", "epc-lwpr")] == flown[("12.1", "epc-none")] == "neuralfly"
    assert flown[("8.5", "epc-lwpr-default")] == product
    argv = neuralfly.sim_argv(neuralfly.ROWS[2], neuralfly.METHODS[3], flown[("8.5", "epc-none")],
                              -90.0, 3, tmp_path / "o")  # fmt: skip
    o = sim_options(build_parser().parse_args(argv))
    assert o.scenario.envelope.max_error_m == neuralfly.COMPARISON_MAX_ERROR_M
    assert o.method == "epc:none"
    assert o.wind_speed_m_s == 8.5


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
    assert "no adaptation flown within 10 m of the reference, not `sim`'s 2 m" in text
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


def _seed_flight(mean_m: float | None, status: str = "flown", hits: float | None = 0.97,
                 n: int = 3) -> dict:  # fmt: skip
    return {**_flight(mean_m, status, hits), "t_s": [0.1 * i for i in range(n)],
            "error_cm": [100.0 * (mean_m or 0.0)] * n, "rmse_m": mean_m, "max_error_m": mean_m,
            "max_tilt_deg": 20.0, "constraint_violations": 0, "wall_s": 40.0, "why": "",
            "exit_code": 0, "first_lap_misses": 5}  # fmt: skip


def test_seeds_combine_into_their_mean_spread_and_worst_status() -> None:
    both = neuralfly.combine_seeds({3: _seed_flight(0.0166), 4: _seed_flight(0.0183, n=2)})
    assert both["status"] == "flown"
    assert both["mean_error_m"] == pytest.approx(0.01745)
    assert (both["mean_error_min_m"], both["mean_error_max_m"]) == (0.0166, 0.0183)
    assert both["mean_error_std_m"] == pytest.approx(0.00085)
    assert both["error_cm"] == pytest.approx([1.745, 1.745])  # the time both flew
    assert set(both["seeds"]) == {"3", "4"}
    assert both["seeds"]["4"]["mean_error_m"] == 0.0183
    assert "t_s" not in both["seeds"]["3"]  # the series only in the mean
    left = neuralfly.combine_seeds({3: _seed_flight(0.0166), 4: _seed_flight(0.5, "left")})
    assert left["status"] == "left"
    failed = neuralfly.combine_seeds({3: _seed_flight(None, "failed", None),
                                      4: _seed_flight(0.5, "left")})  # fmt: skip
    assert failed["status"] == "failed"
    assert failed["mean_error_m"] is None
    assert failed["hit_rate_after_first_lap"] is None


def test_targets_over_seeds_are_judged_on_the_means() -> None:
    def verdict(value: float, bound: float) -> list[dict]:
        ok = "PASS" if value <= bound else "FAIL"
        return [{"target": "t", "method": "epc:lwpr", "metric": "mean_error_m", "value": value,
                 "bound": bound, "vs": None, "verdict": ok}]  # fmt: skip

    # one seed passes, the other fails: the mean (1.55 cm) fails the 1.5 cm bound
    combined = neuralfly.combine_verdicts([verdict(0.014, 0.015), verdict(0.017, 0.015)])
    assert combined[0]["verdict"] == "FAIL"
    assert combined[0]["value"] == pytest.approx(0.0155)
    assert combined[0]["values"] == [0.014, 0.017]
    # a ratio's bound (0.4 x the other method's value) averages to 0.4 x its mean
    combined = neuralfly.combine_verdicts([verdict(0.03, 0.4 * 0.1), verdict(0.05, 0.4 * 0.2)])
    assert combined[0]["bound"] == pytest.approx(0.4 * 0.15)
    assert combined[0]["verdict"] == "PASS"


def test_a_table_of_several_seeds_gives_each_mean_and_its_range(tmp_path: Path) -> None:
    results = _table(tmp_path)
    data = json.loads((results / "neuralfly.json").read_text())
    del data["seed"]
    data["seeds"] = [3, 4]
    data["command"] = "epc-offboard figures neuralfly --seeds 3,4 --jobs 2"
    data["flights"]["0"]["epc-lwpr"] = neuralfly.combine_seeds(
        {3: _seed_flight(0.0166), 4: _seed_flight(0.0183)}
    )
    (results / "neuralfly.json").write_text(json.dumps(data))
    text = neuralfly.render_table(results)
    assert "| 0 m/s | 1.75 (1.66–1.83) | 2.46 |" in text
    assert "the mean over the seeds, their lowest and highest in brackets" in text
    assert "(lockstep, seeds 3, 4, 2 flights at once)" in text
    neuralfly.write_figure(data, tmp_path / "nf.png")


@pytest.mark.parametrize(
    ("argv", "message"),
    [(["--seed", "3", "--seeds", "3,4"], "not allowed with argument"),
     (["--seeds", "3,3"], "distinct"), (["--seeds", "3,x"], "expected N")],
)  # fmt: skip
def test_bad_seeds_are_usage_errors(argv: list[str], message: str, capsys) -> None:
    with pytest.raises(SystemExit) as exc:
        main(["figures", "neuralfly", *argv, "--numbers-only"])
    assert exc.value.code == 2
    assert message in capsys.readouterr().err
