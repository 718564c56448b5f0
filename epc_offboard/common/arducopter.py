"""ArduCopter's numbers, written once for both sides that speak them: the service's dialect
(:mod:`epc_offboard.vehicle.dialect_ardupilot`) and the bundled SITL's ArduCopter
personality (``sitl/ardupilot.py``, which may import only ``epc_offboard.common``).

HEARTBEAT.custom_mode is a plain mode number (as ArduCopter 4.7 / 4.8-dev SITL sends it);
PX4's DO_SET_MODE(1, 6, 0) would select RTL.
"""

from __future__ import annotations

# flight modes (custom_mode)
STABILIZE = 0
GUIDED = 4
LOITER = 5
RTL = 6
LAND = 9
BRAKE = 17
GUIDED_NOGPS = 20
# SET_ATTITUDE_TARGET is obeyed only in these
GUIDED_MODES = frozenset({GUIDED, GUIDED_NOGPS})

# GUID_OPTIONS bit 3: SET_ATTITUDE_TARGET's thrust is throttle (else a climb rate)
GUID_OPTIONS_THRUST_AS_THROTTLE = 8
