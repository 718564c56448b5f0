"""The service configuration: one TOML file, validated on load (unknown keys are errors).

``config/default.toml`` is safe for a real vehicle (no automation); ``config/sitl.toml`` flies
the bundled SITL. Every table below maps to a frozen dataclass; the key names carry units.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from functools import cached_property
from pathlib import Path
from typing import Literal

from epc_offboard.common.airframe import Airframe
from epc_offboard.common.configio import ConfigError, load_config
from epc_offboard.common.logsetup import LogConfig
from epc_offboard.control.attitude import AttitudeControlConfig
from epc_offboard.control.candidate_pool import CandidatePoolConfig
from epc_offboard.control.perturbation import EstimatorConfig
from epc_offboard.control.position import PositionControlConfig
from epc_offboard.control.trajectory_config import TrajectoryConfig
from epc_offboard.fleet.config import SharingConfig
from epc_offboard.service.airframe_file import DEFAULT_VEHICLE_FILE, load_airframe
from epc_offboard.vehicle.offboard import OffboardConfig
from epc_offboard.vehicle.state import StateLimits


@dataclass(frozen=True)
class LinkConfig:
    url: str = "udpin://0.0.0.0:14540"  # PX4's onboard (offboard API) link
    target_system: int = 1
    target_component: int = 1
    system_id: int = 245  # ours: an onboard computer, as MAVSDK does by default
    component_id: int = 191  # MAV_COMP_ID_ONBOARD_COMPUTER
    signing_key_file: str = ""  # 32-byte key: sign outgoing, reject unsigned ("" = off)
    # the autopilot's dialect: "auto" reads it from HEARTBEAT.autopilot (12 PX4, 3 ArduPilot)
    autopilot: Literal["auto", "px4", "ardupilot"] = "auto"

    def __post_init__(self) -> None:
        for name in ("target_system", "system_id"):
            if not 1 <= getattr(self, name) <= 255:
                raise ValueError(f"{name} must be in 1..255, got {getattr(self, name)}")
        for name in ("target_component", "component_id"):
            if not 0 <= getattr(self, name) <= 255:
                raise ValueError(f"{name} must be in 0..255, got {getattr(self, name)}")
        from epc_offboard.vehicle.link import parse_url  # (pymavlink: only when validated)

        try:  # checked on load, so the message names link.url and the file
            parse_url(self.url)
        except ConfigError as exc:
            raise ValueError(f"url: {exc}") from exc


@dataclass(frozen=True)
class LoopsConfig:
    position_rate_hz: float = 100.0
    attitude_rate_hz: float = 200.0
    supervisor_rate_hz: float = 20.0
    clock: Literal["wall", "vehicle"] = "wall"  # vehicle: lockstep with the SITL
    watchdog_period_s: float = 0.5
    # > 0: the loops' thread runs SCHED_FIFO at this priority (1-99), so other processes
    # cannot delay a tick (service/realtime.py); needs CAP_SYS_NICE, else logged and ignored
    realtime_priority: int = 0
    # CPUs the loops' thread is pinned to ([] = wherever the OS schedules it): with the
    # kernel's isolcpus= keeping other work off them, its caches stay its own
    # (service/realtime.py); a CPU this machine does not offer is logged and ignored
    cpu_affinity: tuple[int, ...] = ()
    # real time: the cyclic collector's collections run after a tick, when the next is far
    # enough, not wherever an allocation crosses a threshold (service/realtime.py's
    # SlackCollector); false: the interpreter's automatic collections
    collect_in_slack: bool = True

    def __post_init__(self) -> None:
        prio = self.realtime_priority
        if isinstance(prio, bool) or not isinstance(prio, int) or not 0 <= prio <= 99:
            raise ValueError(f"realtime_priority must be an integer 0..99, got {prio!r}")
        if not isinstance(self.collect_in_slack, bool):
            raise ValueError(f"collect_in_slack must be true or false, got "
                             f"{self.collect_in_slack!r}")  # fmt: skip
        cpus = self.cpu_affinity
        if any(isinstance(c, bool) or not isinstance(c, int) or c < 0 for c in cpus):
            raise ValueError(f"cpu_affinity must list CPU numbers >= 0, got {list(cpus)!r}")
        if len(set(cpus)) != len(cpus):
            raise ValueError(f"cpu_affinity lists a CPU twice: {list(cpus)!r}")
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
    # after landing, stay up (answering the fleet's library queries) until stopped
    linger_after_landing: bool = False


@dataclass(frozen=True)
class ReferenceConfig:
    """Where the position loop's reference comes from.

    ``zenoh``: a planner publishes live references (``wire.ReferenceMessage``, JSON) on
    ``epc/<fleet>/<vehicle_id>/reference``; while the newest is younger than ``timeout_s``
    it overrides the built-in trajectory (hold or track), when stale the service goes back
    to the trajectory (or holds).
    """

    source: Literal["trajectory", "zenoh"] = "trajectory"
    timeout_s: float = 0.5  # wall time

    def __post_init__(self) -> None:
        if self.timeout_s <= 0.0:
            raise ValueError(f"timeout_s must be > 0, got {self.timeout_s}")


@dataclass(frozen=True)
class AirframeConfig:
    """``[airframe]``: the vehicle file the service flies (the one the SITL simulates): a
    path (relative to the working directory), or the name of a bundled one
    (``config/vehicles/NAME.toml``). The service takes the hover thrust, the tilt, thrust
    and body-rate limits, the mass, drag and lags from it (:class:`Airframe`); the service
    config cannot set them too (they are not its keys: one number, one home)."""

    file: str = DEFAULT_VEHICLE_FILE


# service-config keys that moved to the vehicle file: their "unknown key" error says where
MOVED_TO_AIRFRAME = {
    "position.hover_thrust_norm": "[vehicle]'s rotor model, or [envelope] hover_thrust_norm",
    "position.max_tilt_deg": "[envelope] max_tilt_deg",
    "position.min_thrust_norm": "[envelope] min_thrust_norm",
    "position.max_thrust_norm": "[envelope] max_thrust_norm",
    "attitude.max_rate_rad_s": "[envelope] max_rate_frd_rad_s",
}


@dataclass(frozen=True)
class ServiceConfig:
    link: LinkConfig = field(default_factory=LinkConfig)
    airframe: AirframeConfig = field(default_factory=AirframeConfig)
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
    sharing: SharingConfig = field(default_factory=SharingConfig)
    candidates: CandidatePoolConfig = field(default_factory=CandidatePoolConfig)
    reference: ReferenceConfig = field(default_factory=ReferenceConfig)

    def __post_init__(self) -> None:
        if self.reference.source == "zenoh" and not self.sharing.vehicle_id:
            raise ValueError("reference.source = 'zenoh' needs sharing.vehicle_id (the key)")
        self.vehicle  # noqa: B018 -- load (and so validate) the vehicle file with the config

    @cached_property
    def vehicle(self) -> Airframe:
        """The airframe of ``airframe.file``, loaded once."""
        return load_airframe(self.airframe.file)


def load_service_config(path: str | Path) -> ServiceConfig:
    try:
        return load_config(ServiceConfig, path)
    except ConfigError as exc:
        unknown = str(exc).split(" (known:")[0]
        moved = [f"{k} is now the vehicle file's {v}" for k, v in MOVED_TO_AIRFRAME.items()
                 if k in unknown]  # fmt: skip
        if moved:
            raise ConfigError(f"{exc}; {'; '.join(moved)} (airframe.file names it)") from exc
        raise
