"""The bundled SITL quadrotor: physics, a small PX4-like autopilot and its MAVLink endpoint."""

from sitl.groundtruth import COLUMNS as GROUNDTRUTH_COLUMNS
from sitl.params import DEFAULT_VEHICLE_FILE, SimConfig, load_sim_config
from sitl.simulation import Simulation, StateEstimate

__all__ = [
    "DEFAULT_VEHICLE_FILE",
    "GROUNDTRUTH_COLUMNS",
    "SimConfig",
    "Simulation",
    "StateEstimate",
    "load_sim_config",
]
