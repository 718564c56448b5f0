"""``epc-sitl`` command line: usage and config errors exit 2 and name the problem."""

from __future__ import annotations

import pytest

from sitl.main import build_parser, link_addresses, main
from sitl.params import DEFAULT_VEHICLE_FILE, load_sim_config


def test_default_vehicle_file_loads_strictly():
    cfg = load_sim_config()
    assert cfg.sitl.physics_steps_per_tick == 5
    assert cfg.autopilot.offboard_loss_timeout_s == 1.0  # COM_OF_LOSS_T
    assert cfg.sitl.autopilot == "px4"


def test_unknown_config_key_exits_2_naming_key_and_file(tmp_path, capsys):
    bad = tmp_path / "v.toml"
    bad.write_text(DEFAULT_VEHICLE_FILE.read_text().replace("mass_kg", "mass_kgs"))
    assert main(["--config", str(bad), "--listen-port", "0"]) == 2
    err = capsys.readouterr().err
    assert "vehicle.mass_kgs" in err
    assert str(bad) in err


def test_lockstep_period_must_be_whole_physics_steps(capsys):
    assert main(["--lockstep-period-ms", "2.5", "--listen-port", "0"]) == 2
    assert "lockstep_period_s" in capsys.readouterr().err


def test_bad_signing_key_and_wind_are_usage_errors(tmp_path, capsys):
    key = tmp_path / "key"
    key.write_bytes(b"short")
    assert main(["--signing-key", str(key), "--listen-port", "0"]) == 2
    assert "32 bytes" in capsys.readouterr().err
    with pytest.raises(SystemExit) as exc:
        main(["--wind", "3"])
    assert exc.value.code == 2


def test_instances_get_px4_sitl_ports_and_overrides_win():
    args = build_parser().parse_args(["--instance", "2"])
    assert link_addresses(args) == (14582, [("127.0.0.1", 14542), ("127.0.0.1", 14550)])
    args = build_parser().parse_args(["--instance", "2", "--gcs-port", "0", "--offboard-port", "9"])
    assert link_addresses(args) == (14582, [("127.0.0.1", 9)])
