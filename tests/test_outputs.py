"""What `sim` and `db` hand a user says what it measures (issue 22, items 7 and 10): rounded
loop figures, strict JSON, the fleet's controllers received and used, where the telemetry
goes, each signature's loop in `db info`, options anywhere on the `db` command line.
"""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any

import pytest

from epc_offboard.cli import build_parser, main
from epc_offboard.control.library_types import LibraryEntry
from epc_offboard.service.timing import LoopTiming
from epc_offboard.store.database import LibraryStore
from epc_offboard.tools.sim.analysis import fleet_figures
from epc_offboard.tools.sim.options import sim_options
from epc_offboard.tools.sim.orchestrate import telemetry_routes
from epc_offboard.tools.sim.report import write_json
from tests.test_db import CFG, OTHER, SIG, _library


def test_loop_figures_are_rounded_to_what_they_mean() -> None:
    lt = LoopTiming(period_s=0.01)
    t = 0.0
    for _ in range(1001):
        lt.record(t, 0.00123456789, scheduled_s=t)
        t += 0.01  # float steps: 99.99999999999999 Hz and ~1e-12 ms of jitter, unrounded
    raw = lt.report()
    assert raw.rate_hz != 100.0  # the noise this rounds away is real
    shown = raw.as_dict()
    assert shown["rate_hz"] == 100.0
    assert shown["period_jitter_p99_ms"] == 0.0
    assert shown["compute_us_median"] == 1234.6


def _strict(text: str) -> Any:
    def reject(name: str) -> None:
        raise ValueError(f"not JSON: {name}")

    return json.loads(text, parse_constant=reject)


def test_report_json_is_strict_with_null_for_no_figure(tmp_path: Path) -> None:
    report = {"vehicles": [{"tracking": {"rmse_m": math.nan, "max_error_m": math.inf},
                            "max_abs_vel_m_s": [0.1, math.nan, 0.0]}]}  # fmt: skip
    write_json(report, tmp_path / "report.json", tmp_path / "copy.json")
    for name in ("report.json", "copy.json"):
        got = _strict((tmp_path / name).read_text())
        assert got["vehicles"][0]["tracking"] == {"rmse_m": None, "max_error_m": None}
        assert got["vehicles"][0]["max_abs_vel_m_s"] == [0.1, None, 0.0]


def test_fleet_controllers_received_and_used_are_told_apart() -> None:
    # a vehicle whose log shows peers' controllers arriving but which flew no state where one
    # proved optimal: "received" read 0, as if nothing had arrived
    stats = {
        "sharing": {"entries_received": 79, "entries_offered": 71},
        "library": {"position": {"received_shared": 0}, "attitude": {"received_shared": 2}},
    }
    fleet = fleet_figures(stats)
    assert fleet["controllers_received"] == 71  # new to this vehicle
    assert fleet["controllers_used"] == {"position": 0, "attitude": 2}
    assert fleet_figures({})["controllers_received"] == 0  # alone: no sharing section


def test_sim_says_where_each_vehicles_telemetry_goes() -> None:
    def options(*argv: str):
        return sim_options(build_parser().parse_args(["sim", *argv]))

    px4 = telemetry_routes(options(), 1, 50001, 50002)
    assert "UDP 127.0.0.1:50001" in px4
    assert "service on UDP 127.0.0.1:50002" in px4
    assert "ground station: UDP 127.0.0.1:14550" in px4  # PX4 SITL's, where QGC listens
    assert "ground station: none" in telemetry_routes(options("--gcs-port", "0"), 1, 1, 2)
    fleet = telemetry_routes(options("--vehicles", "2", "--autopilot", "ardupilot",
                                     "--gcs-port", "20400"), 2, 1, 2)  # fmt: skip
    assert "ground station: serves TCP 127.0.0.1:20410" in fleet
    assert "Zenoh tcp/127.0.0.1:7448" in fleet


def test_db_info_names_each_signatures_loop(tmp_path: Path, capsys) -> None:
    lib = _library(tmp_path / "lib.sqlite", [LibraryEntry((1,), 1.0, 1)])
    with LibraryStore.open(lib) as store:
        store.save_controllers(OTHER, [LibraryEntry((2,), 1.0, 1)])
        store.save_controllers("0" * 32, [LibraryEntry((3,), 1.0, 1)])
    assert main(["db", "info", str(lib)]) == 0
    out = capsys.readouterr().out
    # no labels in this file: the bundled configs' problems name the loops it can
    assert f"position loop  {SIG}: 1 controllers" in out
    assert f"attitude loop  {OTHER}: 1 controllers" in out
    assert f"unknown loop   {'0' * 32}: 1 controllers" in out
    with LibraryStore.open(lib) as store:  # as the service records them when it opens a file
        store.label_loops({"0" * 32: "attitude"})
    assert main(["db", "info", str(lib)]) == 0
    assert f"attitude loop  {'0' * 32}" in capsys.readouterr().out


def test_db_import_and_merge_label_the_loops_they_write(tmp_path: Path, capsys) -> None:
    src = _library(tmp_path / "v1.sqlite", [LibraryEntry((1,), 1.0, 1)])
    dst = tmp_path / "v2.sqlite"
    assert main(["db", "merge", str(dst), str(src), *CFG]) == 0
    with LibraryStore.open_readonly(dst) as store:
        assert store.loop_labels() == {SIG: "position", OTHER: "attitude"}


@pytest.mark.parametrize("where", ["before", "between", "after"])
def test_db_options_go_anywhere(tmp_path: Path, capsys, where: str) -> None:
    src = _library(tmp_path / "v1.sqlite", [LibraryEntry((1,), 1.0, 1)])
    out = tmp_path / "v1.json"
    assert main(["db", "export", str(src), str(out)]) == 0
    dst = str(tmp_path / "v2.sqlite")
    argv = {
        "before": ["db", "import", *CFG, dst, str(out)],
        "between": ["db", "import", dst, *CFG, str(out)],
        "after": ["db", "import", dst, str(out), *CFG],
    }[where]
    assert main(argv) == 0, capsys.readouterr().err
    with LibraryStore.open_readonly(dst) as store:
        assert len(store.load_controllers(SIG)) == 1


def test_unknown_arguments_are_still_errors(capsys) -> None:
    with pytest.raises(SystemExit) as exc:
        main(["db", "info", "lib.sqlite", "--bogus"])
    assert exc.value.code == 2
    assert "unrecognized arguments: --bogus" in capsys.readouterr().err
