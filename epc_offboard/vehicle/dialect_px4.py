"""PX4's dialect: the state machine's intents as PX4 commands. Pure: values in, values out.

What PX4 does with each (observed on PX4 v1.16 / main SITL, see docs/DESIGN.md):

* arm: MAV_CMD_COMPONENT_ARM_DISARM(1); refused once right after boot, a retry succeeds;
* takeoff: MAV_CMD_NAV_TAKEOFF, sent as COMMAND_INT in the global frame with the target
  altitude AMSL and the current latitude / longitude and heading, every field finite. With a
  NaN altitude PX4 climbs to the CURRENT altitude + MIS_TAKEOFF_ALT each time it accepts a
  takeoff — a repeated takeoff climbs without limit — so the altitude is always explicit;
* offboard / hold / land: MAV_CMD_DO_SET_MODE with PX4's custom main and sub mode
  (OFFBOARD 6; AUTO 4 with LOITER 3 and LAND 6), as QGroundControl selects them;
* heartbeat: custom_mode = main << 16 | sub << 24 (AUTO.TAKEOFF 4/2 is PX4's own takeoff);
* thrust: SET_ATTITUDE_TARGET's thrust is the normalised collective thrust, sent as is.

Nothing here ever puts a NaN or an infinity into a command: :func:`encode` refuses to.
"""

from __future__ import annotations

from epc_offboard.vehicle.dialect import (
    MAV_AUTOPILOT_PX4,
    Action,
    Command,
    Dialect,
    EncodeError,
    FlightMode,
    Heartbeat,
    Position,
    TakeoffTarget,
    command,
    message_interval,
    set_custom_mode,
)

__all__ = [
    "PX4",
    "PX4_AUTO_SUB_LAND",
    "PX4_AUTO_SUB_LOITER",
    "PX4_AUTO_SUB_TAKEOFF",
    "PX4_MAIN_MODE_AUTO",
    "PX4_MAIN_MODE_OFFBOARD",
    "PX4_MAIN_MODE_POSCTL",
    "Command",
    "EncodeError",
    "Position",
    "encode",
    "message_interval",
    "px4_custom_mode",
    "px4_modes",
]

MAV_CMD_NAV_TAKEOFF = 22
MAV_CMD_COMPONENT_ARM_DISARM = 400
MAV_FRAME_GLOBAL = 0

# PX4 custom_mode: main mode in bits 16-23, sub mode in bits 24-31.
PX4_MAIN_MODE_POSCTL = 3
PX4_MAIN_MODE_AUTO = 4
PX4_MAIN_MODE_OFFBOARD = 6
PX4_AUTO_SUB_TAKEOFF = 2
PX4_AUTO_SUB_LOITER = 3
PX4_AUTO_SUB_LAND = 6


def px4_custom_mode(main_mode: int, sub_mode: int = 0) -> int:
    return (main_mode << 16) | (sub_mode << 24)


def px4_modes(custom_mode: int) -> tuple[int, int]:
    """(main_mode, sub_mode) of a PX4 custom_mode."""
    return (custom_mode >> 16) & 0xFF, (custom_mode >> 24) & 0xFF


def set_mode(main_mode: int, sub_mode: int = 0) -> Command:
    return set_custom_mode(main_mode, sub_mode)


def encode(
    action: Action, takeoff: TakeoffTarget | None = None, position: Position | None = None
) -> Command:
    """The command for one intent; EncodeError when a takeoff lacks its target or position."""
    if action == Action.ARM:
        return command(MAV_CMD_COMPONENT_ARM_DISARM, 1.0)
    if action == Action.TAKEOFF:
        if takeoff is None or position is None:
            raise EncodeError("takeoff needs an explicit target altitude and the position")
        return command(
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


def mode(hb: Heartbeat) -> FlightMode:
    """PX4's main / sub mode as the state machine reads it."""
    if hb.main_mode == PX4_MAIN_MODE_OFFBOARD:
        return FlightMode.OFFBOARD
    if hb.main_mode == PX4_MAIN_MODE_AUTO:
        return {
            PX4_AUTO_SUB_TAKEOFF: FlightMode.TAKEOFF,
            PX4_AUTO_SUB_LOITER: FlightMode.HOLD,
            PX4_AUTO_SUB_LAND: FlightMode.LAND,
        }.get(hb.sub_mode, FlightMode.OTHER)
    return FlightMode.OTHER


PX4 = Dialect(
    name="px4",
    autopilot=MAV_AUTOPILOT_PX4,
    offboard_before_arming=False,  # Offboard needs a streaming setpoint, so: after
    extra_streams_hz=(),  # PX4 streams the rest by default
    mode=mode,
    encode=encode,
    wire_thrust=lambda thrust_norm, cos_tilt: thrust_norm,  # no boost on an attitude setpoint
    default_attitude_mode="epc",  # PX4's rate loop is the first-order model identified
    params_to_read=(),
    offboard_refusal=lambda params: "",
)
