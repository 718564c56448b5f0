"""Fleet sharing's settings (``[sharing]``): one place both processes read them from."""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

from epc_offboard.fleet.wire import NAME_RE


@dataclass(frozen=True)
class SharingConfig:
    """Fleet sharing of controller libraries over Eclipse Zenoh (:class:`FleetSharing`).

    The Zenoh session runs in a process of its own (``helper_nice`` below the control
    process); the control process takes at most ``candidates_per_s`` received controllers a
    second from it, already decoded (how many each library holds: ``[candidates]``,
    :class:`~epc_offboard.control.candidate_pool.CandidatePoolConfig`).
    Keys: ``epc/<fleet>/<signature>/{ctl,lib,alive}/<id>``.
    Only vehicles whose problems have identical signatures exchange controllers, and a
    received controller is applied only where the local KKT check passes. For TLS/mTLS,
    user-password and access control give a Zenoh JSON5 file in ``zenoh_config_file``
    (config/zenoh/client-*.json5); ``zenoh_overrides`` and then the keys below are set on top
    of it. ``mode = "client"``: ``connect`` the fleet's routers (``epc-offboard fleet
    router`` or zenohd), no ``listen``.
    """

    enabled: bool = False
    fleet: str = "fleet"  # [A-Za-z0-9_-]{1,32}: one key space per fleet
    vehicle_id: str = ""  # [A-Za-z0-9_-]{1,32}, unique in the fleet; required when used
    mode: Literal["peer", "client", "router"] = "peer"
    listen: tuple[str, ...] = ()  # Zenoh endpoints, e.g. "tcp/0.0.0.0:7447"
    connect: tuple[str, ...] = ()  # e.g. "tcp/192.168.1.12:7447", "tls/router.local:7447"
    scouting_multicast: bool = False  # discover peers by UDP multicast (off: explicit only)
    zenoh_config_file: str = ""  # a Zenoh JSON5 config, loaded first
    # Zenoh config keys set on top of the file (path -> value), e.g. this vehicle's
    # "transport/link/tls/connect_certificate" or "transport/auth/usrpwd/user"
    zenoh_overrides: dict[str, Any] = field(default_factory=dict)
    max_payload_bytes: int = 262_144  # larger payloads are dropped before decoding
    max_messages_per_s: float = 20.0  # per peer, token bucket refill
    burst_messages: int = 40  # per peer, token bucket depth
    fleet_messages_per_s: float = 100.0  # all peers together, checked before decoding
    fleet_burst_messages: int = 200
    queue_size: int = 256  # peer events and frames waiting in the helper; beyond: dropped
    publish_period_s: float = 0.2  # new controllers are batched and published this often
    publish_backlog_entries: int = 4096  # new controllers waiting for a helper with a session
    max_queued_entries: int = 8192  # controllers waiting in the helper; beyond: dropped
    candidates_per_s: float = 200.0  # received controllers the control process takes, at most
    candidate_slice_s: float = 0.005  # worker CPU time per slice of candidate factorisations
    query_timeout_s: float = 3.0  # a library snapshot query gives up after this
    helper_nice: int = 10  # the fleet process runs this much below the control process
    helper_timeout_s: float = 5.0  # a fleet process silent this long is restarted
    helper_restart_max_s: float = 30.0  # the longest wait before restarting it (backoff)

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
                     "candidates_per_s", "candidate_slice_s", "fleet_messages_per_s",
                     "helper_timeout_s", "helper_restart_max_s"):
            if getattr(self, name) <= 0.0:
                raise ValueError(f"{name} must be > 0, got {getattr(self, name)}")
        for name in ("burst_messages", "queue_size", "max_queued_entries",
                     "fleet_burst_messages", "publish_backlog_entries"):
            if getattr(self, name) < 1:
                raise ValueError(f"{name} must be >= 1, got {getattr(self, name)}")
        if not 0 <= self.helper_nice <= 19:
            raise ValueError(f"helper_nice must be in 0..19, got {self.helper_nice}")
        if self.mode == "client" and self.listen:
            raise ValueError("a Zenoh client does not listen: leave listen empty (mode client)")
        import zenoh  # here, not at the top: the config loads without opening anything

        probe = zenoh.Config()
        for path, value in self.zenoh_overrides.items():
            try:  # an unknown Zenoh key is an error now, not when the session opens
                probe.insert_json5(path, json.dumps(value))
            except Exception as exc:  # zenoh's own error type, or a value json cannot write
                raise ValueError(f"zenoh_overrides.{path}: {exc}") from exc
        for ep in (*self.listen, *self.connect):
            if "/" not in ep:
                raise ValueError(f"endpoint {ep!r} must look like PROTOCOL/ADDRESS:PORT")
        if self.zenoh_config_file and not Path(self.zenoh_config_file).is_file():
            raise ValueError(f"zenoh_config_file {self.zenoh_config_file!r} does not exist")
