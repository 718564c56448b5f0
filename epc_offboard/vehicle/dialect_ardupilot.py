"""ArduCopter's dialect: the state machine's intents as ArduPilot commands. Pure.

What ArduCopter does (4.7 / 4.8-dev SITL, default copter parameters; see docs/DESIGN.md):

* heartbeat: autopilot 3, custom_mode a plain mode number: STABILIZE 0, GUIDED 4, LOITER 5,
  RTL 6, LAND 9, BRAKE 17, GUIDED_NOGPS 20. PX4's DO_SET_MODE(1, 6, 0) would select RTL;
* the ritual: select GUIDED, arm (ArduCopter cannot take off from STABILIZE), then
  MAV_CMD_NAV_TAKEOFF as COMMAND_LONG with the altitude ABOVE HOME in param7 and every other
  parameter 0. A takeoff of NaNs crashed the SITL (floating point exception), so nothing here
  ever sends a NaN: every parameter is finite or the intent is not encoded;
* offboard = GUIDED (SET_ATTITUDE_TARGET is obeyed only in GUIDED / GUIDED_NOGPS),
  hold = BRAKE (LOITER also reads as a hold: its altitude is the pilot's stick), land = LAND;
* thrust: with GUID_OPTIONS bit 3 (8) SET_ATTITUDE_TARGET's thrust is throttle, to which
  ArduCopter adds its own angle boost (it divides by the cosine of the tilt); without it the
  thrust is a CLIMB RATE (0.5 holds altitude). The service divides by the tilt's cosine
  already, so it sends ``thrust * cos(tilt)`` and the tilt is compensated once; and it flies
  only with bit 3 set (:func:`guided_refusal`);
* streams: nothing but HEARTBEAT until SET_MESSAGE_INTERVAL; ODOMETRY never comes.
"""

from __future__ import annotations

import math

from epc_offboard.common.arducopter import (  # ArduCopter's mode numbers, GUID_OPTIONS bits
    BRAKE,
    GUID_OPTIONS_THRUST_AS_THROTTLE,
    GUIDED,
    GUIDED_NOGPS,
    LAND,
    LOITER,
)
from epc_offboard.vehicle.dialect import (
    MAV_AUTOPILOT_ARDUPILOTMEGA,
    Action,
    Command,
    Dialect,
    EncodeError,
    FlightMode,
    Heartbeat,
    Position,
    TakeoffTarget,
    command,
    set_custom_mode,
)

MAV_CMD_NAV_TAKEOFF = 22
MAV_CMD_COMPONENT_ARM_DISARM = 400
MSG_GLOBAL_POSITION_INT = 33
MSG_EXTENDED_SYS_STATE = 245

GUID_OPTIONS = "GUID_OPTIONS"
MOT_THST_HOVER = "MOT_THST_HOVER"
PARAMS_READ_AT_LINK_UP = (GUID_OPTIONS, MOT_THST_HOVER)

_MODES = {
    GUIDED: FlightMode.OFFBOARD,
    GUIDED_NOGPS: FlightMode.OFFBOARD,
    LOITER: FlightMode.HOLD,
    BRAKE: FlightMode.HOLD,
    LAND: FlightMode.LAND,
}


def mode(hb: Heartbeat) -> FlightMode:
    """ArduCopter's mode number as the state machine reads it (no takeoff mode: a GUIDED
    takeoff stays in GUIDED)."""
    return _MODES.get(hb.custom_mode, FlightMode.OTHER)


def encode(
    action: Action, takeoff: TakeoffTarget | None = None, position: Position | None = None
) -> Command:
    """The command for one intent (``position`` is not needed: ArduCopter takes off above
    where it stands); EncodeError when a takeoff has no finite altitude."""
    if action == Action.ARM:
        return command(MAV_CMD_COMPONENT_ARM_DISARM, 1.0)
    if action == Action.TAKEOFF:
        if takeoff is None:
            raise EncodeError("takeoff needs an explicit target altitude above home")
        if not (math.isfinite(takeoff.above_home_m) and takeoff.above_home_m > 0.0):
            raise EncodeError(f"takeoff altitude {takeoff.above_home_m} m is not a climb")
        # param1..6 0 (pitch, -, horizontal nav, yaw: ArduCopter ignores them), param7 the
        # altitude above home
        return command(MAV_CMD_NAV_TAKEOFF, 0, 0, 0, 0, 0, 0, takeoff.above_home_m)
    if action == Action.REQUEST_OFFBOARD:
        return set_custom_mode(GUIDED)
    if action == Action.REQUEST_HOLD:
        # BRAKE, not LOITER: LOITER's altitude follows the pilot's throttle stick, and with
        # none (ArduCopter SITL's simulated RC sits at the bottom) it descended at 2.5 m/s
        # and hit the ground 2 s after a hold; BRAKE holds position and altitude whatever
        # the sticks say. A pilot still takes over with the mode switch.
        return set_custom_mode(BRAKE)
    if action == Action.LAND:
        return set_custom_mode(LAND)
    raise EncodeError(f"no ArduPilot command for {action}")


def guided_refusal(guid_options: float | None) -> str:
    """Why the service must not fly GUIDED with this GUID_OPTIONS ("" when it may).

    Without bit 3 ArduCopter reads our thrust (0.3..0.7 around hover) as a climb rate: the
    vehicle would climb or sink whatever the controller meant. Refusing is the safe choice.
    """
    if guid_options is None:
        return f"{GUID_OPTIONS} not read yet (PARAM_REQUEST_READ sent)"
    if not math.isfinite(guid_options) or not int(guid_options) & GUID_OPTIONS_THRUST_AS_THROTTLE:
        return (
            f"{GUID_OPTIONS} is {guid_options:g}: bit 3 (value 8) must be set for "
            "SET_ATTITUDE_TARGET thrust to be throttle, not a climb rate; set GUID_OPTIONS=8"
        )
    return ""


def wire_thrust(thrust_norm: float, cos_tilt: float) -> float:
    """ArduCopter divides throttle by the tilt's cosine (angle boost, floored at 0.1, as its
    attitude controller does): undone here, so the tilt is compensated once."""
    return thrust_norm * min(max(cos_tilt, 0.1), 1.0)


ARDUPILOT = Dialect(
    name="ardupilot",
    autopilot=MAV_AUTOPILOT_ARDUPILOTMEGA,
    offboard_before_arming=True,  # GUIDED, then arm, then takeoff (in GUIDED)
    # ArduCopter streams nothing by default: the takeoff needs GLOBAL_POSITION_INT (height
    # above home), the landing EXTENDED_SYS_STATE (landed state)
    extra_streams_hz=((MSG_GLOBAL_POSITION_INT, 10.0), (MSG_EXTENDED_SYS_STATE, 2.0)),
    mode=mode,
    encode=encode,
    wire_thrust=wire_thrust,
    # ArduCopter shapes body-rate targets (ATC_INPUT_TC, acceleration limits) and integrates
    # them into its attitude controller: its rate response is much slower than the rate model
    # the attitude EPC is built on, and body-rate mode diverged by metres within seconds.
    # Quaternion + thrust to its attitude controller flew (hover 2.5 cm, circle 3.1 cm).
    default_attitude_mode="autopilot",
    params_to_read=PARAMS_READ_AT_LINK_UP,
    offboard_refusal=lambda params: guided_refusal(params.get(GUID_OPTIONS)),
)
