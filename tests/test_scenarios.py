"""The thesis's three flight experiments (3.3) as acceptance tests, flown in lockstep.

Each scenario is flown once per module by ``epc-offboard sim --compare`` (every method the
targets name, side by side, real SITL and service processes over UDP MAVLink), shortened to
about one lap after the settle time; the targets are the scenario TOML's ``[[targets]]``, so
the tests and the README's full-length results check the same thing. Each compare flight
takes tens of seconds on 2 cores; the assertions share it.
"""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path
from typing import Any

import pytest

from epc_offboard.tools.sim.scenario import load_scenario
from tests.rig import holding_scenario

pytestmark = [pytest.mark.slow, pytest.mark.timeout(420)]


def compare(tmp: Path, scenario: str, duration_s: float, methods: str) -> dict[str, Any]:
    out = tmp / scenario
    # ending holding: the autopilot's landing after each method's flight (8 landings in
    # this module) judges no target
    holding = holding_scenario(tmp, scenario)
    proc = subprocess.run(
        [sys.executable, "-m", "epc_offboard", "sim", "--scenario", str(holding),
         "--duration", str(duration_s), "--compare", methods, "--gcs-port", "0",
         "--out", str(out), "--no-figure"],  # (compare.png still drawn: judged below)
        capture_output=True, text=True, timeout=400, check=False,
    )  # fmt: skip
    assert proc.returncode == 0, proc.stdout + proc.stderr
    result: dict[str, Any] = json.loads((out / "compare.json").read_text())
    assert (out / "compare.png").stat().st_size > 10_000
    result["out_dir"] = str(out)  # (not in the file: where the flights' own outputs are)
    return result


def by_method(result: dict[str, Any]) -> dict[str, dict[str, Any]]:
    return {f"{r['controller']}:{r['adaptation']}": r["vehicles"][0] for r in result["reports"]}


def assert_targets(result: dict[str, Any], scenario: str, *, skip: tuple[str, ...] = ()) -> None:
    declared = load_scenario(scenario).targets
    assert len(result["targets"]) == len(declared) >= 1
    failed = [t for t in result["targets"] if t["verdict"] != "PASS" and t["vs"] not in skip]
    assert not failed, json.dumps(failed, indent=2)


@pytest.fixture(scope="module")
def circle(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Any]:
    # settle 6 s + one 8 s lap
    return compare(tmp_path_factory.mktemp("circle"), "circle", 14.0, "epc:lwpr,pd:none")


@pytest.fixture(scope="module")
def zigzag(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Any]:
    # settle 4 s + three full-speed sweeps; EPC alone: the scenario's one target is EPC's, and
    # a PD flight beside it (half a minute of the suite) could only show that PD has no bound
    return compare(tmp_path_factory.mktemp("zigzag"), "zigzag", 14.0, "epc:lwpr")


@pytest.fixture(scope="module")
def zigzag_bounded(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Any]:
    # settle 4 s + the first sweeps riding the 3.0 m/s bound (the reference asks 3.75) with
    # LWPR's drag estimate: the scenario's own targets judge EPC without adaptation, which
    # never reaches the bound (2.81 m/s: no drag compensation)
    return compare(tmp_path_factory.mktemp("zigzag_bounded"), "zigzag_bounded", 14.0,
                   "epc:lwpr")


@pytest.fixture(scope="module")
def figure8(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Any]:
    # settle 6 s + one 12 s lap; px4: the autopilot's own position controller
    return compare(
        tmp_path_factory.mktemp("figure8"),
        "figure8",
        18.0,
        "epc:lwpr,epc:none,pd:none,mpc:kf,px4:none",
    )


def test_sim_circle_tracks(circle: dict[str, Any]) -> None:
    # SIH's drag (1 m/s^2 per m/s) is unmodelled: 23 cm without adaptation, LWPR learns it
    # (was a flight of its own in test_service_e2e; this compare flight already flies it)
    v = by_method(circle)["epc:lwpr"]
    assert v["tracking"]["max_error_m"] < 0.10
    assert v["takeoffs_sent"] == 1
    assert v["library"]["hit_rate"] > 0.9


def test_circle_meets_its_targets(circle: dict[str, Any]) -> None:
    assert_targets(circle, "circle")
    epc = by_method(circle)["epc:lwpr"]
    # thesis fig. 3.5: below 2 cm, now with SIH's drag too (this shortened flight: main
    # 2.06 cm, with the disturbance along the horizon in the model 0.77)
    assert epc["tracking"]["max_error_m"] < 0.02
    assert epc["library"]["hit_rate"] > 0.9


def test_zigzag_epc_keeps_the_velocity_bound(zigzag: dict[str, Any]) -> None:
    assert_targets(zigzag, "zigzag")
    epc = by_method(zigzag)["epc:lwpr"]
    assert epc["constraint_violations"] == 0
    assert epc["max_abs_vel_m_s"][1] <= 3.8
    # the reference really runs at the bound (3.75 m/s): the constraint is exercised
    assert epc["max_abs_vel_m_s"][1] > 3.6
    assert epc["library"]["qp_solves"] > 0  # constrained phases were solved, then reused


def test_bounded_zigzag_with_lwpr_keeps_the_velocity_bound(
    zigzag_bounded: dict[str, Any],
) -> None:
    """Riding the 3.0 m/s bound against LWPR's 4 m/s^2 of drag compensation, a plan whose
    model answers a command at once (no command dead time on PX4 body rates) braked just in
    time for its model, while the vehicle's acceleration answered ~50 ms later: 3.06 m/s,
    221 ticks over on the full flight (seed 0), 71 on this shortened one."""
    epc = by_method(zigzag_bounded)["epc:lwpr"]
    assert epc["attitude_mode"] == "epc"  # body rates: the path this dead time is for
    assert epc["constraint_violations"] == 0
    assert epc["max_abs_vel_m_s"][1] <= 3.0
    # the bound is ridden, not avoided: within 0.1 m/s of it
    assert epc["max_abs_vel_m_s"][1] > 2.9


def test_compare_flights_fly_compiled_kernels(zigzag: dict[str, Any]) -> None:
    # the figures are those of the compiled kernels: a cold cache's numpy twins took 6 ms
    # a position tick (0.75 ms compiled) with a background compile beside the flight
    stats = json.loads(
        (Path(zigzag["out_dir"]) / "epc-lwpr" / "vehicle1" / "stats.json").read_text()
    )
    assert stats["kernels"]["mode"] == "compiled"
    assert stats["kernels"]["signatures"] == stats["kernels"]["signatures_after_warm_up"] > 0


def test_figure8_lwpr_beats_no_adaptation_and_pd(figure8: dict[str, Any]) -> None:
    assert_targets(figure8, "figure8", skip=("mpc:kf",))
    m = by_method(figure8)
    lwpr = m["epc:lwpr"]["tracking"]["rmse_m"]
    assert lwpr <= 0.5 * m["epc:none"]["tracking"]["rmse_m"]
    assert lwpr <= m["pd:none"]["tracking"]["rmse_m"]
    # issue 11: in 3 m/s wind on SIH's drag, within 10 cm and far below PX4's own controller
    assert lwpr <= 0.10
    assert lwpr <= 0.5 * m["px4:none"]["tracking"]["rmse_m"]


def test_figure8_lwpr_beats_mpc_with_kf(figure8: dict[str, Any]) -> None:
    # EPC+KF equals MPC+KF, so this is LWPR's d(v) (also known along the horizon, at each
    # stage's reference velocity) against the KF's time-lagged constant disturbance
    m = by_method(figure8)
    assert m["epc:lwpr"]["tracking"]["rmse_m"] <= m["mpc:kf"]["tracking"]["rmse_m"]
