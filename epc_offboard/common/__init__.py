"""What the service and the bundled SITL both need: errors, frames and units, strict config
loading, logging, MAVLink signing. Imports no controller.
"""
