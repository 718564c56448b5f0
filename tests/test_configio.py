"""The strict config loader: unknown keys, wrong types and bad ranges name the key and file."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Literal

import pytest

from epc_offboard.common.configio import ConfigError, load_config


@dataclass(frozen=True)
class Motor:
    time_constant_s: float = 0.02
    max_speed_rad_s: float = 1000.0

    def __post_init__(self) -> None:
        if self.time_constant_s <= 0.0:
            raise ValueError(f"time_constant_s must be > 0, got {self.time_constant_s}")


@dataclass(frozen=True)
class Vehicle:
    mass_kg: float
    name: str = "quad"
    mode: Literal["x", "plus"] = "x"
    inertia_kg_m2: tuple[float, float, float] = (0.03, 0.03, 0.05)
    motor: Motor = field(default_factory=Motor)
    rotors: int = 4
    armed: bool = False
    wind_m_s: float | None = None


def write(tmp_path, text):
    p = tmp_path / "v.toml"
    p.write_text(text)
    return p


def test_loads_nested_tables_and_defaults(tmp_path):
    p = write(
        tmp_path, "mass_kg = 1.5\ninertia_kg_m2 = [0.1, 0.2, 0.3]\n[motor]\nmax_speed_rad_s = 900\n"
    )
    v = load_config(Vehicle, p)
    assert v == Vehicle(mass_kg=1.5, inertia_kg_m2=(0.1, 0.2, 0.3), motor=Motor(0.02, 900.0))
    assert isinstance(v.motor.max_speed_rad_s, float)


def test_overrides_merge_into_nested_tables(tmp_path):
    p = write(tmp_path, "mass_kg = 1.5\n[motor]\nmax_speed_rad_s = 900\n")
    v = load_config(Vehicle, p, overrides={"motor": {"time_constant_s": 0.05}})
    assert v.motor == Motor(0.05, 900.0)


@pytest.mark.parametrize(
    ("text", "message"),
    [
        ("mass_kg = 1.5\nmas_kg = 2\n", "unknown key mas_kg"),
        ("mass_kg = 1.5\n[motor]\nspeed = 3\n", "unknown key motor.speed"),
        ("name = 'x'\n", "missing required key `mass_kg`"),
        ("mass_kg = 'heavy'\n", "`mass_kg` must be a number"),
        ("mass_kg = nan\n", "`mass_kg` must be finite"),
        ("mass_kg = 1.0\nrotors = 4.5\n", "`rotors` must be an integer"),
        ("mass_kg = 1.0\narmed = 1\n", "`armed` must be true or false"),
        ("mass_kg = 1.0\nmode = 'h'\n", "`mode` must be one of"),
        ("mass_kg = 1.0\ninertia_kg_m2 = [1, 2]\n", "`inertia_kg_m2` must have 3 elements"),
        ("mass_kg = 1.0\n[motor]\ntime_constant_s = -1\n", "invalid `motor`: time_constant_s"),
        ("mass_kg = = 1\n", "not valid TOML"),
    ],
)
def test_bad_configs_name_key_and_file(tmp_path, text, message):
    p = write(tmp_path, text)
    with pytest.raises(ConfigError, match=message) as info:
        load_config(Vehicle, p)
    assert str(p) in str(info.value)


def test_missing_file(tmp_path):
    with pytest.raises(ConfigError, match="not found"):
        load_config(Vehicle, tmp_path / "nope.toml")


def test_dump_toml_round_trips():
    import tomllib

    from epc_offboard.common.configio import dump_toml

    data = {
        "a": 1, "b": 2.5, "c": "x\"y", "d": True, "e": [1.0, 2.0], "f": float("inf"),
        "t": {"u": {"v": [[1, 2], [3, 4]]}, "w": "z"},
        "waypoints": {"pts": [[0.0, 1.0, -2.0]]},
    }  # fmt: skip
    assert tomllib.loads(dump_toml(data)) == data
