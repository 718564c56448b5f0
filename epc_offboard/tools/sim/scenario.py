"""Scenarios: the flights ``epc-offboard sim`` knows by name (``config/scenarios/NAME.toml``).

A scenario says what to fly (trajectory, altitude, duration, wind), how to judge it (the
settle time the metrics skip, the first lap, the acceptance targets) and which methods
``sim --compare`` flies side by side.
"""

from __future__ import annotations

import argparse
import tomllib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from epc_offboard.common.bundled import bundled_dir, scenario_dir
from epc_offboard.common.cliargs import parse_wind_profile
from epc_offboard.common.configio import ConfigError, from_dict
from epc_offboard.control.trajectory_config import TrajectoryConfig
from epc_offboard.service.airframe_file import airframe_path
from epc_offboard.tools.sim.envelope import EnvelopeConfig
from epc_offboard.tools.targets import CompareConfig, TargetConfig

CONFIG_DIR = bundled_dir()  # the checkout's config/, shipped in the wheel
SCENARIO_DIR = scenario_dir()
VEHICLE_DIR = CONFIG_DIR / "vehicles"
EXTRA_METRICS = ("mean_error_m",)  # what a scenario may add to its report's tracking
SITL_SERVICE_CONFIG = CONFIG_DIR / "sitl.toml"


@dataclass(frozen=True)
class ScenarioConfig:
    description: str = ""
    note: str = ""  # printed under the report's table: e.g. why an error is large by design
    duration_s: float = 20.0  # flight under offboard control, from the trajectory's start
    settle_s: float = 3.0  # metrics ignore the first settle_s of the trajectory
    lap_s: float = 0.0  # one lap of the trajectory, for first-lap library figures (0: whole)
    altitude_m: float = 2.5  # the trajectory's altitude above home
    wind_speed_m_s: float = 0.0
    wind_dir_deg: float = 0.0  # towards, counter-clockwise from east (docs/CONTRACTS.md)
    wind_profile: str = "steady"  # how the wind varies (sim --wind-profile's syntax)
    # the SITL's airframe: a file of config/vehicles/ by name ("": the default vehicle)
    vehicle: str = ""
    # figures reported beyond rmse_m and max_error_m ("mean_error_m": mean |p - p_d|)
    metrics: tuple[str, ...] = ()
    trajectory: TrajectoryConfig = field(default_factory=TrajectoryConfig)
    service: dict[str, Any] = field(default_factory=dict)  # overrides of config/sitl.toml
    compare: CompareConfig = field(default_factory=CompareConfig)  # `sim --compare` methods
    targets: tuple[TargetConfig, ...] = ()  # acceptance targets (epc_offboard.tools.targets)
    envelope: EnvelopeConfig = field(default_factory=EnvelopeConfig)  # where a flight is sane

    @property
    def climb_m(self) -> float:
        """How far the trajectory's reference climbs above ``altitude_m`` at most."""
        traj = self.trajectory
        vertical = traj.size_z_m if traj.shape == "figure8_vertical" else 0.0
        return max([0.0, -traj.dz_m, vertical, *(-w[2] for w in traj.waypoints_ned_m)])

    def __post_init__(self) -> None:
        if self.duration_s <= 0.0:
            raise ValueError(f"duration_s must be > 0, got {self.duration_s}")
        if not 0.0 <= self.settle_s < self.duration_s:
            raise ValueError("settle_s must be in [0, duration_s)")
        if self.lap_s < 0.0:
            raise ValueError(f"lap_s must be >= 0, got {self.lap_s}")
        for metric in self.metrics:
            if metric not in EXTRA_METRICS:
                raise ValueError(f"metrics: unknown {metric!r} (known: {', '.join(EXTRA_METRICS)})")
        if self.vehicle and not airframe_path(self.vehicle).is_file():
            known = ", ".join(sorted(p.stem for p in VEHICLE_DIR.glob("*.toml")))
            raise ValueError(f"vehicle: no {self.vehicle!r} in {VEHICLE_DIR} (known: {known})")
        try:
            parse_wind_profile(self.wind_profile)
        except argparse.ArgumentTypeError as exc:
            raise ValueError(f"wind_profile: {exc}") from exc


def load_scenario(name: str) -> ScenarioConfig:
    """A scenario by name (``config/scenarios/NAME.toml``) or by path (``*.toml``);
    ConfigError naming the file and key when it is unknown or invalid."""
    path = Path(name) if name.endswith(".toml") else SCENARIO_DIR / f"{name}.toml"
    if not path.exists():
        known = sorted(p.stem for p in SCENARIO_DIR.glob("*.toml"))
        raise ConfigError(f"unknown scenario {name!r} (known: {', '.join(known)})")
    with path.open("rb") as fh:
        try:
            raw = tomllib.load(fh)
        except tomllib.TOMLDecodeError as exc:
            raise ConfigError(f"{path}: not valid TOML: {exc}") from exc
    return from_dict(ScenarioConfig, raw, source=str(path))


def holding_scenario(folder: Path, name: str) -> Path:
    """A copy of the shipped scenario ``name`` in ``folder`` whose flights end holding (the
    service exits; ``sim`` flies no landing): for flights that judge nothing of the
    autopilot's landing (the suite's lockstep flights, ``bench --service``'s recording,
    which replays the offboard phase alone), 8.5 s of vehicle time each."""
    path = folder / f"{name}.toml"
    shipped = (SCENARIO_DIR / f"{name}.toml").read_text()
    path.write_text(shipped + "\n[service.mission]\nland_at_end = false\n")
    return path
