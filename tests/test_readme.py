"""The README quotes no number from a flight that `epc-offboard figures readme` would not
write there from the reports in tests/results/ (issue 22: they had drifted, 81 vs 346
first-lap misses quoted where 75 vs 347 were measured). Pure: no flight."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from epc_offboard.common.errors import UsageError
from epc_offboard.tools.readme import README, RECIPES, RESULTS_DIR, rewrite, values_from


def test_the_readme_is_its_own_rewrite_from_the_results_on_disk() -> None:
    text = README.read_text()
    assert "<!-- n:compare_figure8.epc:lwpr.rmse_cm -->" in text  # the markers are there
    assert rewrite(text, RESULTS_DIR) == text, (
        "README.md quotes numbers its results do not give: run "
        "`epc-offboard figures readme --numbers-only` (or fly the recipes)"
    )


def test_every_linked_figure_is_one_a_recipe_writes() -> None:
    text = README.read_text()
    for name in ("flight_hover", "compare_circle", "compare_zigzag", "compare_figure8"):
        assert f"tests/results/{name}.png" in text
        assert name in RECIPES
    assert "epc-offboard figures readme" in text


def _report(rmse_m: float, first_lap: int) -> dict[str, object]:
    vehicle = {"id": 2, "tracking": {"rmse_m": rmse_m, "max_error_m": 0.1},
               "max_speed_m_s": 1.0, "constraint_violations": 0,
               "library": {"hit_rate": 0.5, "qp_solves": 9, "first_lap_misses": first_lap},
               "loops": {"position": {"compute_us_median": 100.4, "compute_us_p99": 900.6},
                         "attitude": {"deadline_misses": 3}}}  # fmt: skip
    return {"duration_s": 30.0, "controller": "epc", "adaptation": "none", "vehicles": [vehicle]}


def test_a_number_changed_by_hand_or_a_new_result_is_rewritten(tmp_path: Path) -> None:
    (tmp_path / "stagger_shared.json").write_text(json.dumps(_report(0.0123, 75)))
    (tmp_path / "stagger_alone.json").write_text(json.dumps(_report(0.02, 347)))
    values = values_from(tmp_path)
    assert values["stagger_shared.v2.rmse_cm"] == "1.23"
    assert values["stagger.fewer_first_lap_misses_pct"] == "78"
    text = ("**<!-- n:stagger_shared.v2.first_lap_misses -->81<!-- /n --> vs "
            "<!-- n:stagger_alone.v2.first_lap_misses -->346<!-- /n -->**")  # fmt: skip
    assert rewrite(text, tmp_path) == (
        "**<!-- n:stagger_shared.v2.first_lap_misses -->75<!-- /n --> vs "
        "<!-- n:stagger_alone.v2.first_lap_misses -->347<!-- /n -->**"
    )
    with pytest.raises(UsageError, match=r"no number in .*: nowhere\.v1\.rmse_cm"):
        rewrite("<!-- n:nowhere.v1.rmse_cm -->1<!-- /n -->", tmp_path)


def test_the_command_rewrites_a_readme_from_results_without_flying(tmp_path: Path, capsys) -> None:
    from epc_offboard.cli import main

    results = tmp_path / "results"
    results.mkdir()
    (results / "stagger_shared.json").write_text(json.dumps(_report(0.0123, 75)))
    readme = tmp_path / "README.md"
    readme.write_text("shared: <!-- n:stagger_shared.v2.first_lap_misses -->81<!-- /n -->\n")
    argv = ["figures", "readme", "--numbers-only", "--results", str(results),
            "--readme", str(readme)]  # fmt: skip
    assert main(argv) == 0
    assert "first_lap_misses -->75<!-- /n -->" in readme.read_text()
    assert main(["figures", "readme", "nope", "--results", str(results)]) == 2
    assert "unknown recipe nope" in capsys.readouterr().err
