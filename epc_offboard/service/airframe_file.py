"""The service's airframe: read from the vehicle file its config names (``[airframe] file``).

The same file the SITL flies (``config/vehicles/*.toml``), loaded with the SITL's schema,
strictly (an unknown or misspelt key anywhere in it is an error naming the key and the
file), so one number has one home: the mass, the rotor model's hover thrust, the drag and
the motor lag from ``[vehicle]``, the rate loop's dead time and lag from ``[autopilot]``,
the tilt, thrust and body-rate limits from ``[envelope]``.
"""

from __future__ import annotations

from pathlib import Path

from epc_offboard.common.airframe import Airframe
from epc_offboard.common.bundled import bundled_config

# ``[airframe] file``'s default (``service.config.AirframeConfig``); here, so that `sim`
# finds it without importing the service's config and with it the control stack
DEFAULT_VEHICLE_FILE = "quad_x_1500g"


def airframe_path(name_or_path: str) -> Path:
    """A vehicle file given as a path, or as the name of a bundled one (``quad_x_1500g``)."""
    return bundled_config(name_or_path, "vehicles")


def load_airframe(name_or_path: str) -> Airframe:
    """The airframe of the vehicle file ``name_or_path`` (ConfigError naming the key and the
    file when it is not valid)."""
    from sitl.params import load_sim_config  # the file's one schema: the plant's

    path = airframe_path(name_or_path)
    sim = load_sim_config(path)
    vehicle, envelope = sim.vehicle, sim.envelope
    hover = envelope.hover_thrust_norm
    if hover is None:  # not measured: the rotor model's
        hover = vehicle.hover_thrust_norm
    return Airframe(
        mass_kg=vehicle.mass_kg,
        hover_thrust_norm=hover,
        max_tilt_deg=envelope.max_tilt_deg,
        min_thrust_norm=envelope.min_thrust_norm,
        max_thrust_norm=envelope.max_thrust_norm,
        max_rate_frd_rad_s=envelope.max_rate_frd_rad_s,
        drag_coeff_body_n_s_m=vehicle.drag_coeff_body_n_s_m,
        motor_time_constant_s=vehicle.motor_time_constant_s,
        rate_dead_time_s=sim.autopilot.rate_dead_time_s,
        rate_time_constant_s=sim.autopilot.rate_time_constant_s,
        source=str(path),
    )
