"""PX4's dialect: the state machine's intents as PX4 commands. Pure: values in, values out.

What PX4 does with each (observed on PX4 v1.16 / main SITL, see ../shared/DESIGN.md):

* arm: MAV_CMD_COMPONENT_ARM_DISARM(1); refused once right after boot, a retry succeeds;
* takeoff: MAV_CMD_NAV_TAKEOFF, sent as COMMAND_INT in the global frame with the target
  altitude AMSL and the current latitude / longitude and heading, every field finite. With a
  NaN altitude PX4 climbs to the CURRENT altitude + MIS_TAKEOFF_ALT each time it accepts a
  takeoff — a repeated takeoff climbs without limit — so the altitude is always explicit;
* offboard / hold / land: MAV_CMD_DO_SET_MODE with PX4's custom main and sub mode
  (OFFBOARD 6; AUTO 4 with LOITER 3 and LAND 6), as QGroundControl selects them.

Nothing here ever puts a NaN or an infinity into a command: :func:`encode` refuses to.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from epc_offboard.offboard import Action, TakeoffTarget
from epc_offboard.state import (
    PX4_AUTO_SUB_LAND,
    PX4_AUTO_SUB_LOITER,
    PX4_MAIN_MODE_AUTO,
    PX4_MAIN_MODE_OFFBOARD,
)

MAV_CMD_NAV_TAKEOFF = 22
MAV_CMD_DO_SET_MODE = 176
MAV_CMD_COMPONENT_ARM_DISARM = 400
MAV_CMD_SET_MESSAGE_INTERVAL = 511
MAV_MODE_FLAG_CUSTOM_MODE_ENABLED = 1
MAV_FRAME_GLOBAL = 0


@dataclass(frozen=True)
class Position:
    """Where the vehicle is, as the takeoff command needs it (GLOBAL_POSITION_INT units)."""

    lat_e7: int
    lon_e7: int
    yaw_deg: float


@dataclass(frozen=True)
class Command:
    """One MAVLink command. ``int_frame`` set: send as COMMAND_INT with x, y = params[4:6] as
    integers (degE7) and z = params[6]; else COMMAND_LONG."""

    command: int
    params: tuple[float, ...]  # param1..param7
    int_frame: int | None = None


class EncodeError(ValueError):
    """An intent cannot be encoded (a value is missing or not finite): nothing is sent."""


def _command(command: int, *params: float, int_frame: int | None = None) -> Command:
    p = tuple(float(v) for v in params) + (0.0,) * (7 - len(params))
    if not all(math.isfinite(v) for v in p):
        raise EncodeError(f"command {command}: non-finite parameter in {p}")
    return Command(command, p, int_frame)


def set_mode(main_mode: int, sub_mode: int = 0) -> Command:
    return _command(
        MAV_CMD_DO_SET_MODE, MAV_MODE_FLAG_CUSTOM_MODE_ENABLED, main_mode, sub_mode
    )


def encode(
    action: Action, takeoff: TakeoffTarget | None = None, position: Position | None = None
) -> Command:
    """The command for one intent; EncodeError when a takeoff lacks its target or position."""
    if action == Action.ARM:
        return _command(MAV_CMD_COMPONENT_ARM_DISARM, 1.0)
    if action == Action.TAKEOFF:
        if takeoff is None or position is None:
            raise EncodeError("takeoff needs an explicit target altitude and the position")
        return _command(
            MAV_CMD_NAV_TAKEOFF,
            0.0,  # minimum pitch (fixed wing only)
            0.0,
            0.0,
            position.yaw_deg,
            position.lat_e7,
            position.lon_e7,
            takeoff.amsl_m,
            int_frame=MAV_FRAME_GLOBAL,
        )
    if action == Action.REQUEST_OFFBOARD:
        return set_mode(PX4_MAIN_MODE_OFFBOARD)
    if action == Action.REQUEST_HOLD:
        return set_mode(PX4_MAIN_MODE_AUTO, PX4_AUTO_SUB_LOITER)
    if action == Action.LAND:
        return set_mode(PX4_MAIN_MODE_AUTO, PX4_AUTO_SUB_LAND)
    raise EncodeError(f"no PX4 command for {action}")


def message_interval(msg_id: int, rate_hz: float) -> Command:
    """MAV_CMD_SET_MESSAGE_INTERVAL: ``msg_id`` at ``rate_hz``."""
    return _command(MAV_CMD_SET_MESSAGE_INTERVAL, msg_id, 1e6 / rate_hz)
