"""The bundled SITL quadrotor: physics, a small PX4-like autopilot and its MAVLink endpoint."""
