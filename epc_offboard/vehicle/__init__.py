"""The vehicle side: the MAVLink link, state decoding, each autopilot's dialect, the offboard state
machine, stream rates.
"""
