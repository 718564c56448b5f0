"""The service configuration: one TOML file, validated on load (unknown keys are errors).

``config/default.toml`` is safe for a real vehicle (no automation); ``config/sitl.toml`` flies
the bundled SITL. Every table below maps to a frozen dataclass; the key names carry units.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal

from epc_offboard.cascade import AttitudeControlConfig, EstimatorConfig, PositionControlConfig
from epc_offboard.configio import load_config
from epc_offboard.logsetup import LogConfig
from epc_offboard.offboard import OffboardConfig
from epc_offboard.state import StateLimits
from epc_offboard.trajectories import TrajectoryConfig


@dataclass(frozen=True)
class LinkConfig:
    url: str = "udpin://0.0.0.0:14540"  # PX4's onboard (offboard API) link
    target_system: int = 1
    target_component: int = 1
    system_id: int = 245  # ours: an onboard computer, as MAVSDK does by default
    component_id: int = 191  # MAV_COMP_ID_ONBOARD_COMPUTER
    signing_key_file: str = ""  # 32-byte key: sign outgoing, reject unsigned ("" = off)

    def __post_init__(self) -> None:
        for name in ("target_system", "system_id"):
            if not 1 <= getattr(self, name) <= 255:
                raise ValueError(f"{name} must be in 1..255, got {getattr(self, name)}")
        for name in ("target_component", "component_id"):
            if not 0 <= getattr(self, name) <= 255:
                raise ValueError(f"{name} must be in 0..255, got {getattr(self, name)}")


@dataclass(frozen=True)
class LoopsConfig:
    position_rate_hz: float = 100.0
    attitude_rate_hz: float = 200.0
    supervisor_rate_hz: float = 20.0
    clock: Literal["wall", "vehicle"] = "wall"  # vehicle: lockstep with the SITL
    watchdog_period_s: float = 0.5

    def __post_init__(self) -> None:
        for name in (
            "position_rate_hz",
            "attitude_rate_hz",
            "supervisor_rate_hz",
            "watchdog_period_s",
        ):
            if getattr(self, name) <= 0.0:
                raise ValueError(f"{name} must be > 0, got {getattr(self, name)}")


@dataclass(frozen=True)
class StoreConfig:
    path: str = ""  # SQLite library file ("" = no persistence)
    save_period_s: float = 5.0

    def __post_init__(self) -> None:
        if self.save_period_s <= 0.0:
            raise ValueError(f"save_period_s must be > 0, got {self.save_period_s}")


@dataclass(frozen=True)
class MissionConfig:
    duration_s: float = 0.0  # > 0: after this long on the trajectory, land and exit
    land_at_end: bool = True


@dataclass(frozen=True)
class ServiceConfig:
    link: LinkConfig = field(default_factory=LinkConfig)
    offboard: OffboardConfig = field(default_factory=OffboardConfig)
    loops: LoopsConfig = field(default_factory=LoopsConfig)
    position: PositionControlConfig = field(default_factory=PositionControlConfig)
    attitude: AttitudeControlConfig = field(default_factory=AttitudeControlConfig)
    estimator: EstimatorConfig = field(default_factory=EstimatorConfig)
    trajectory: TrajectoryConfig = field(default_factory=TrajectoryConfig)
    trajectory_altitude_m: float | None = None  # fly the trajectory at this height above home
    state_limits: StateLimits = field(default_factory=StateLimits)
    store: StoreConfig = field(default_factory=StoreConfig)
    mission: MissionConfig = field(default_factory=MissionConfig)
    log: LogConfig = field(default_factory=LogConfig)


def load_service_config(path: str | Path) -> ServiceConfig:
    return load_config(ServiceConfig, path)
