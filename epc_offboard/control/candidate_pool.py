"""``[candidates]``: how many controllers received from the fleet each EPC library holds
while they prove optimal here (:meth:`ExperienceController.limit_candidates`).

They configure the libraries (position and attitude alike), not the transport: fleet
sharing only delivers the controllers, and its helper's inbox keeps no more from one vehicle
than a library's backlog would take.
"""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class CandidatePoolConfig:
    pool_size: int = 64  # received controllers waiting to prove optimal here
    per_peer: int = 16  # of those, at most this many from one vehicle (until proven)
    backlog_size: int = 2048  # received controllers kept as tuples, maps unbuilt
    backlog_per_peer: int = 512  # of those, at most this many from one vehicle

    def __post_init__(self) -> None:
        for name in ("pool_size", "per_peer"):
            if getattr(self, name) < 1:
                raise ValueError(f"{name} must be >= 1, got {getattr(self, name)}")
        if self.backlog_size < self.pool_size or self.backlog_per_peer < self.per_peer:
            raise ValueError(
                "backlog_size / backlog_per_peer must be >= pool_size / per_peer "
                "(the backlog holds the pool's too)"
            )
