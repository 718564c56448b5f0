"""The registry of autopilot dialects: which one speaks to a vehicle.

Every dialect imports ``dialect.py`` for the intents and the :class:`Dialect` type; this
module imports every dialect, so nothing imports in a circle.
"""

from __future__ import annotations

from epc_offboard.vehicle.dialect import AUTOPILOT_SETTINGS, Dialect
from epc_offboard.vehicle.dialect_ardupilot import ARDUPILOT
from epc_offboard.vehicle.dialect_px4 import PX4

DIALECTS: dict[str, Dialect] = {"px4": PX4, "ardupilot": ARDUPILOT}  # by link.autopilot


def choose(setting: str, heartbeat_autopilot: int | None) -> Dialect | None:
    """The dialect for ``link.autopilot`` (``auto``: from HEARTBEAT.autopilot; None while
    unknown or not an autopilot we speak). Raises ValueError on an unknown setting."""
    if setting not in AUTOPILOT_SETTINGS:
        known = ", ".join(AUTOPILOT_SETTINGS)
        raise ValueError(f"autopilot must be one of {known}, got {setting!r}")
    if setting in DIALECTS:
        return DIALECTS[setting]
    return next((d for d in DIALECTS.values() if d.autopilot == heartbeat_autopilot), None)
