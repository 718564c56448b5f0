"""A trajectory's configuration (``[trajectory]``), apart from the trajectories themselves.

Here, not in :mod:`epc_offboard.control.trajectories`, so that what reads a scenario or a
config (``epc-offboard sim``'s own process, config checks) does not import numba with the
trajectories' compiled kernels: some 0.4 CPU-s a start (stop 44, suite-cpu).
:mod:`epc_offboard.control.trajectories` re-exports both names.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Literal

Shape = Literal["hover", "line", "circle", "figure8", "figure8_vertical", "zigzag", "waypoints"]


@dataclass(frozen=True)
class TrajectoryConfig:
    shape: Shape = "hover"
    ramp_s: float = 2.0  # progress speed ramps 0 -> 1 over this time
    radius_m: float = 2.0  # circle
    period_s: float = 10.0  # circle, figure8
    size_m: float = 3.0  # figure8 half-width
    size_z_m: float = 0.75  # figure8_vertical half-height
    amplitude_m: float = 3.0  # zigzag
    peak_speed_m_s: float = 3.75  # zigzag
    accel_m_s2: float = 6.0  # zigzag and waypoint speed profiles
    forward_speed_m_s: float = 0.0  # zigzag
    speed_m_s: float = 1.0  # line and waypoints cruise speed
    dx_m: float = 4.0  # line
    dy_m: float = 0.0
    dz_m: float = 0.0
    waypoints_ned_m: tuple[tuple[float, float, float], ...] = field(default_factory=tuple)
    # rejoining a trajectory that ran on while the autopilot held (a failsafe, a pilot):
    # the gap to it closes as a critically damped second-order response of this time constant
    rejoin_tau_s: float = 1.0

    def __post_init__(self) -> None:
        positive = ("ramp_s", "radius_m", "period_s", "size_m", "size_z_m", "amplitude_m",
                    "peak_speed_m_s", "accel_m_s2", "speed_m_s", "rejoin_tau_s")  # fmt: skip
        for name in positive:
            if getattr(self, name) <= 0.0:
                raise ValueError(f"{name} must be > 0, got {getattr(self, name)}")
        if self.shape == "waypoints" and len(self.waypoints_ned_m) < 1:
            raise ValueError("waypoints_ned_m needs at least one waypoint for shape 'waypoints'")
