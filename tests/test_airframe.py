"""One airframe file, read by the SITL and by the service (issue 23, item 5).

The service config names a vehicle file (``[airframe] file``); the service takes its hover
thrust, tilt, thrust and body-rate limits from it, and ``sim`` gives its SITL the same file
instead of copying numbers from one config into the other.
"""

from __future__ import annotations

import math
import tomllib
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from epc_offboard.common.bundled import bundled_config
from epc_offboard.common.configio import ConfigError, dump_toml, merge_dicts
from epc_offboard.control.candidate_pool import CandidatePoolConfig
from epc_offboard.control.cascade import Cascade
from epc_offboard.control.epc import ExperienceController
from epc_offboard.control.models import acceleration_limits
from epc_offboard.fleet.config import SharingConfig
from epc_offboard.fleet.sharing import FleetSharing
from epc_offboard.service.airframe_file import airframe_path, load_airframe
from epc_offboard.service.config import load_service_config
from epc_offboard.tools.sim.options import SimOptions
from epc_offboard.tools.sim.orchestrate import flight_envelope, service_config_for, vehicle_file
from epc_offboard.tools.sim.scenario import load_scenario
from sitl.params import DEFAULT_VEHICLE_FILE, load_sim_config
from tests.mpc_cases import position_problem


def _toml(path: Path) -> dict[str, Any]:
    with path.open("rb") as fh:
        return tomllib.load(fh)


def _vehicle_file(tmp: Path, envelope: dict[str, Any]) -> Path:
    """The bundled vehicle file with ``envelope`` merged into its [envelope]."""
    path = tmp / "my_quad.toml"
    path.write_text(dump_toml(merge_dicts(_toml(DEFAULT_VEHICLE_FILE), {"envelope": envelope})))
    return path


def _service_config(tmp: Path, table: dict[str, Any]) -> Path:
    path = tmp / "service.toml"
    path.write_text(dump_toml(merge_dicts(_toml(bundled_config("sitl")), table)))
    return path


def test_the_service_flies_the_envelope_of_the_vehicle_file_it_names(tmp_path: Path) -> None:
    frame_file = _vehicle_file(tmp_path, {"max_tilt_deg": 30.0, "hover_thrust_norm": 0.6,
                                          "max_rate_frd_rad_s": [3.0, 3.0, 1.5]})  # fmt: skip
    cfg = load_service_config(_service_config(tmp_path, {"airframe": {"file": str(frame_file)}}))
    frame = cfg.vehicle
    assert (frame.max_tilt_deg, frame.hover_thrust_norm) == (30.0, 0.6)
    assert frame.mass_kg == load_sim_config(frame_file).vehicle.mass_kg
    cascade = Cascade(cfg.position, cfg.attitude, cfg.estimator, airframe=frame)
    expected = acceleration_limits(math.radians(30.0), 0.08, 0.95, 0.6)
    assert np.allclose(cascade.position.acc_limits.u_max, expected.u_max)
    assert np.allclose(cascade.attitude.problem.u_max, [3.0, 3.0, 1.5])
    assert cascade.position.hover(_level_state()).thrust_norm == 0.6


def _level_state() -> Any:
    from epc_offboard.control.types import VehicleState

    return VehicleState(time_s=0.0, pos_ned_m=np.zeros(3), vel_ned_m_s=np.zeros(3),
                        q_ned_frd=np.array([1.0, 0.0, 0.0, 0.0]), rate_frd_rad_s=np.zeros(3),
                        position_age_s=0.0, attitude_age_s=0.0)  # fmt: skip


def test_the_sitl_config_hovers_at_the_simulated_airframes_thrust() -> None:
    """`run --config sitl` (and every sim flight) flies the rotor model's hover thrust: no
    longer 0.5 in the service config and 0.52 in the SITL."""
    cfg = load_service_config(bundled_config("sitl"))
    assert cfg.vehicle.hover_thrust_norm == load_sim_config().vehicle.hover_thrust_norm
    assert Path(cfg.vehicle.source) == DEFAULT_VEHICLE_FILE


@pytest.mark.parametrize(
    ("table", "where"),
    [
        ({"position": {"hover_thrust_norm": 0.5}}, "[envelope] hover_thrust_norm"),
        ({"position": {"max_tilt_deg": 40.0}}, "[envelope] max_tilt_deg"),
        ({"attitude": {"max_rate_rad_s": [4.0, 4.0, 2.0]}}, "[envelope] max_rate_frd_rad_s"),
    ],
)
def test_a_service_config_that_sets_the_airframes_numbers_is_refused(
    tmp_path: Path, table: dict[str, Any], where: str
) -> None:
    with pytest.raises(ConfigError) as err:
        load_service_config(_service_config(tmp_path, table))
    key = next(f"{t}.{k}" for t, v in table.items() for k in v)
    message = str(err.value)
    assert key in message
    assert where in message  # where it went
    assert "service.toml" in message


def test_an_unknown_key_in_the_vehicle_file_is_an_error_naming_it(tmp_path: Path) -> None:
    frame_file = _vehicle_file(tmp_path, {"max_tilt": 30.0})
    with pytest.raises(ConfigError, match=r"envelope\.max_tilt\b") as err:
        load_service_config(_service_config(tmp_path, {"airframe": {"file": str(frame_file)}}))
    assert str(frame_file) in str(err.value)


def test_a_vehicle_file_is_named_by_path_or_bundled_name() -> None:
    assert airframe_path("quad_x_1500g") == DEFAULT_VEHICLE_FILE
    assert load_airframe("quad_x_1500g") == load_airframe(str(DEFAULT_VEHICLE_FILE))
    with pytest.raises(ConfigError, match=r"no_such_quad.*not found"):
        load_airframe("no_such_quad")


def test_sim_gives_its_sitl_the_vehicle_file_its_service_names(tmp_path: Path) -> None:
    options = SimOptions("zigzag_bounded", load_scenario("zigzag_bounded"))
    cfg = service_config_for(options, 1, 14999, tmp_path, tmp_path / "lib.sqlite")
    assert "hover_thrust_norm" not in cfg["position"]  # nothing copied by hand
    assert cfg["position"]["library"]["size"] == 800  # the scenario's, in its new table
    assert vehicle_file(cfg) == DEFAULT_VEHICLE_FILE
    frame_file = _vehicle_file(tmp_path, {"max_tilt_deg": 30.0})
    cfg["airframe"] = {"file": str(frame_file)}
    assert vehicle_file(cfg) == frame_file
    assert flight_envelope(options, cfg).command_tilt_deg == 30.0


def test_the_candidate_pool_sizes_reach_every_shared_library(tmp_path: Path) -> None:
    cfg = load_service_config(_service_config(
        tmp_path, {"candidates": {"pool_size": 3, "per_peer": 2, "backlog_size": 10,
                                  "backlog_per_peer": 5}}))  # fmt: skip
    assert cfg.candidates == CandidatePoolConfig(3, 2, 10, 5)
    ctrls = [(n, ExperienceController(position_problem(4), max_size=10)) for n in ("a", "b")]
    FleetSharing(SharingConfig(vehicle_id="v1", fleet="t"), ctrls, candidates=cfg.candidates)
    for _name, ctrl in ctrls:  # no session is opened: only the pools are sized
        pool = ctrl.candidates
        sizes = (pool.max_size, pool.max_per_origin, pool.max_backlog, pool.max_backlog_per_origin)
        assert sizes == (3, 2, 10, 5)
    with pytest.raises(ConfigError, match="backlog_size"):
        load_service_config(_service_config(tmp_path, {"candidates": {"backlog_size": 8}}))
