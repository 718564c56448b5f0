"""The service configuration: one TOML file, validated on load (unknown keys are errors).

``config/default.toml`` is safe for a real vehicle (no automation); ``config/sitl.toml`` flies
the bundled SITL. Every table below maps to a frozen dataclass; the key names carry units.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal

from epc_offboard.common.configio import load_config
from epc_offboard.common.logsetup import LogConfig
from epc_offboard.control.attitude import AttitudeControlConfig
from epc_offboard.control.perturbation import EstimatorConfig
from epc_offboard.control.position import PositionControlConfig
from epc_offboard.control.trajectories import TrajectoryConfig
from epc_offboard.fleet.wire import NAME_RE
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
    # after landing, stay up (answering the fleet's library queries) until stopped
    linger_after_landing: bool = False


@dataclass(frozen=True)
class SharingConfig:
    """Fleet sharing of controller libraries over Eclipse Zenoh (see ``sharing.py``).

    Keys: ``epc/<fleet>/<signature>/{ctl,lib,alive}/<vehicle_id>``. Only vehicles whose
    problems have identical signatures exchange controllers, and a received controller is
    applied only where the local KKT check passes. For TLS/mTLS and access control give a
    Zenoh JSON5 file in ``zenoh_config_file``; the keys below are set on top of it.
    """

    enabled: bool = False
    fleet: str = "fleet"  # [A-Za-z0-9_-]{1,32}: one key space per fleet
    vehicle_id: str = ""  # [A-Za-z0-9_-]{1,32}, unique in the fleet; required when used
    mode: Literal["peer", "client", "router"] = "peer"
    listen: tuple[str, ...] = ()  # Zenoh endpoints, e.g. "tcp/0.0.0.0:7447"
    connect: tuple[str, ...] = ()  # e.g. "tcp/192.168.1.12:7447", "tls/router.local:7447"
    scouting_multicast: bool = False  # discover peers by UDP multicast (off: explicit only)
    zenoh_config_file: str = ""  # a Zenoh JSON5 config, loaded first
    max_payload_bytes: int = 262_144  # larger payloads are dropped before decoding
    max_messages_per_s: float = 20.0  # per peer, token bucket refill
    burst_messages: int = 40  # per peer, token bucket depth
    fleet_messages_per_s: float = 100.0  # all peers together, checked before decoding
    fleet_burst_messages: int = 200
    queue_size: int = 256  # inbound messages waiting for the event loop; beyond: dropped
    publish_period_s: float = 0.2  # new controllers are batched and published this often
    import_slice_s: float = 0.002  # event-loop time per slice of received controllers
    max_queued_entries: int = 8192  # controllers waiting in the inbound queue; beyond: dropped
    candidate_pool_size: int = 64  # received controllers waiting to prove optimal here
    candidates_per_peer: int = 16  # of those, at most this many from one vehicle (until proven)
    candidate_backlog_size: int = 2048  # received controllers kept as tuples, maps unbuilt
    candidate_backlog_per_peer: int = 512  # of those, at most this many from one vehicle
    candidate_slice_s: float = 0.005  # worker CPU time per slice of candidate factorisations
    query_timeout_s: float = 3.0  # a library snapshot query gives up after this

    def __post_init__(self) -> None:
        if not NAME_RE.fullmatch(self.fleet):
            raise ValueError(f"fleet must be 1..32 characters of [A-Za-z0-9_-], got {self.fleet!r}")
        if self.vehicle_id and not NAME_RE.fullmatch(self.vehicle_id):
            raise ValueError(
                f"vehicle_id must be 1..32 characters of [A-Za-z0-9_-], got {self.vehicle_id!r}"
            )
        if self.enabled and not self.vehicle_id:
            raise ValueError("vehicle_id must be set when sharing is enabled")
        if self.max_payload_bytes < 64:
            raise ValueError(f"max_payload_bytes must be >= 64, got {self.max_payload_bytes}")
        for name in ("max_messages_per_s", "publish_period_s", "query_timeout_s",
                     "import_slice_s", "candidate_slice_s", "fleet_messages_per_s"):
            if getattr(self, name) <= 0.0:
                raise ValueError(f"{name} must be > 0, got {getattr(self, name)}")
        for name in ("burst_messages", "queue_size", "max_queued_entries",
                     "candidate_pool_size", "candidates_per_peer", "fleet_burst_messages"):
            if getattr(self, name) < 1:
                raise ValueError(f"{name} must be >= 1, got {getattr(self, name)}")
        if (self.candidate_backlog_size < self.candidate_pool_size
                or self.candidate_backlog_per_peer < self.candidates_per_peer):
            raise ValueError(
                "candidate_backlog_size / candidate_backlog_per_peer must be >= "
                "candidate_pool_size / candidates_per_peer (the backlog holds the pool's too)"
            )
        for ep in (*self.listen, *self.connect):
            if "/" not in ep:
                raise ValueError(f"endpoint {ep!r} must look like PROTOCOL/ADDRESS:PORT")
        if self.zenoh_config_file and not Path(self.zenoh_config_file).is_file():
            raise ValueError(f"zenoh_config_file {self.zenoh_config_file!r} does not exist")


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
    sharing: SharingConfig = field(default_factory=SharingConfig)
    reference: ReferenceConfig = field(default_factory=ReferenceConfig)

    def __post_init__(self) -> None:
        if self.reference.source == "zenoh" and not self.sharing.vehicle_id:
            raise ValueError("reference.source = 'zenoh' needs sharing.vehicle_id (the key)")


def load_service_config(path: str | Path) -> ServiceConfig:
    return load_config(ServiceConfig, path)
