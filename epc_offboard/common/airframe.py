"""The airframe: what both the SITL and the offboard service know of one vehicle.

One file per airframe (``config/vehicles/*.toml``) describes it. The SITL flies its physics
(``[vehicle]``: mass, rotors, drag, motor lag; ``[autopilot]``: the rate loop's dead time
and lag); the service flies within its envelope (``[envelope]``: tilt, thrust and body-rate
limits) at its hover thrust. The service names the file (``[airframe] file``) and reads
these numbers from it, so the sim never copies one into the other's config.

This module holds the shared pieces: the ``[envelope]`` table's schema (the SITL accepts
the table, strictly, and flies its own autopilot's limits) and :class:`Airframe`, the values
the service takes. Plain Python: the plant imports it (it may import ``epc_offboard.common``
only).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

Vec3 = tuple[float, float, float]


@dataclass(frozen=True)
class AirframeEnvelope:
    """A vehicle file's ``[envelope]``: what the offboard controller may command it to do.

    ``hover_thrust_norm``: the measured hover thrust (PX4's MPC_THR_HOVER, ArduPilot's
    MOT_THST_HOVER), for a vehicle known by that figure rather than a rotor model; unset, the
    rotor model's (``[vehicle]``). The SITL always flies its rotor model: a stated figure
    that differs rehearses a mis-set MPC_THR_HOVER, which the estimator learns as a
    vertical disturbance.
    """

    max_tilt_deg: float = 45.0  # PX4's MPC_TILTMAX_AIR default
    min_thrust_norm: float = 0.08
    max_thrust_norm: float = 0.95
    max_rate_frd_rad_s: Vec3 = (4.0, 4.0, 2.0)  # body rates the rate loop can follow
    hover_thrust_norm: float | None = None

    def __post_init__(self) -> None:
        _check_limits(self, self.hover_thrust_norm)


@dataclass(frozen=True)
class Airframe:
    """The airframe as the service flies it (from its vehicle file, :func:`~epc_offboard.
    service.airframe_file.load_airframe`). The defaults are a generic PX4 quad's, for the numerics
    built without a file (tests, benchmarks)."""

    mass_kg: float = 1.5
    hover_thrust_norm: float = 0.5  # PX4's MPC_THR_HOVER default
    max_tilt_deg: float = 45.0
    min_thrust_norm: float = 0.08
    max_thrust_norm: float = 0.95
    max_rate_frd_rad_s: Vec3 = (4.0, 4.0, 2.0)
    drag_coeff_body_n_s_m: Vec3 = (0.0, 0.0, 0.0)  # linear drag per body axis
    motor_time_constant_s: float = 0.0  # first-order lag of the rotors' thrust
    rate_dead_time_s: float = 0.0  # a body-rate command's dead time in the autopilot
    rate_time_constant_s: float = 0.0  # then the rate loop's first-order lag
    source: str = ""  # the file it came from ("": the defaults)

    def __post_init__(self) -> None:
        if not (math.isfinite(self.mass_kg) and self.mass_kg > 0.0):
            raise ValueError(f"mass_kg must be > 0, got {self.mass_kg}")
        _check_limits(self, self.hover_thrust_norm)


def _check_limits(limits: AirframeEnvelope | Airframe, hover_thrust_norm: float | None) -> None:
    """The envelope's range checks, shared by the file's table and the value flown."""
    if not 0.0 < limits.max_tilt_deg < 90.0:
        raise ValueError(f"max_tilt_deg must be in (0, 90), got {limits.max_tilt_deg}")
    if not 0.0 < limits.min_thrust_norm < limits.max_thrust_norm <= 1.0:
        raise ValueError("need 0 < min_thrust_norm < max_thrust_norm <= 1")
    if any(not r > 0.0 for r in limits.max_rate_frd_rad_s):
        raise ValueError(f"max_rate_frd_rad_s must be > 0, got {limits.max_rate_frd_rad_s}")
    hover = hover_thrust_norm
    if hover is not None and not limits.min_thrust_norm < hover < limits.max_thrust_norm:
        raise ValueError(
            f"hover_thrust_norm ({hover}) must lie between min_thrust_norm and max_thrust_norm"
        )
