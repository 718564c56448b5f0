"""Autopilot dialects: what the state machine's intents mean to PX4 and to ArduPilot.

The offboard state machine (``offboard.py``) decides *what* to do — arm, take off to an
altitude, start offboard control, hold, land — and reads the heartbeat as one of a few
:class:`FlightMode` values. A dialect (``dialect_px4.py``, ``dialect_ardupilot.py``) says
*how*: the command for each intent and how a heartbeat's custom_mode decodes. Dialects are
pure (values in, values out) and never put a NaN or an infinity into a command.

    dialect = autopilots.choose("auto", heartbeat.autopilot)   # or choose("ardupilot", ...)
    cmd = dialect.encode(Action.TAKEOFF, target, position)

The intents and their values live here, so the state machine and the dialects share them
without importing each other; ``autopilots.py`` is the registry that knows every dialect
(here it would make an import cycle: each dialect imports this module).
"""

from __future__ import annotations

import enum
import math
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import Literal, Protocol

from epc_offboard.common.errors import EpcError

# MAV_AUTOPILOT
MAV_AUTOPILOT_ARDUPILOTMEGA = 3
MAV_AUTOPILOT_INVALID = 8
MAV_AUTOPILOT_PX4 = 12

MAV_CMD_NAV_TAKEOFF = 22
MAV_CMD_DO_SET_MODE = 176
MAV_CMD_COMPONENT_ARM_DISARM = 400
MAV_CMD_SET_MESSAGE_INTERVAL = 511
MAV_MODE_FLAG_CUSTOM_MODE_ENABLED = 1

AutopilotSetting = Literal["auto", "px4", "ardupilot"]
AUTOPILOT_SETTINGS: tuple[str, ...] = ("auto", "px4", "ardupilot")


@dataclass(frozen=True)
class Heartbeat:
    """A HEARTBEAT as the state tracker decodes it (vehicle/state.py) and the dialects read
    it: armed, the mode as sent, and who sent it."""

    system_id: int
    armed: bool
    main_mode: int  # PX4's main and sub mode of custom_mode (dialect_px4.px4_modes)
    sub_mode: int
    received_s: float  # local monotonic time
    custom_mode: int = 0  # as sent: ArduPilot's plain mode number (PX4's is main/sub above)
    autopilot: int = 12  # MAV_AUTOPILOT: 12 PX4, 3 ArduPilot



class Action(enum.Enum):
    """The state machine's intents."""

    ARM = "arm"
    TAKEOFF = "takeoff"
    REQUEST_OFFBOARD = "request_offboard"  # PX4 Offboard, ArduCopter GUIDED
    REQUEST_HOLD = "request_hold"
    LAND = "land"


class FlightMode(enum.Enum):
    """What a heartbeat's mode means to the state machine."""

    OFFBOARD = "offboard"  # our setpoints are obeyed (PX4 Offboard, ArduCopter GUIDED)
    TAKEOFF = "takeoff"  # the autopilot's own takeoff
    HOLD = "hold"  # holding position (PX4 AUTO.LOITER, ArduCopter BRAKE / LOITER)
    LAND = "land"  # the autopilot is landing
    OTHER = "other"  # a pilot's mode, RTL, a mission: not ours


@dataclass(frozen=True)
class TakeoffTarget:
    """The one takeoff of a flight: height above home, and the same height AMSL."""

    above_home_m: float
    amsl_m: float


@dataclass(frozen=True)
class Position:
    """Where the vehicle is, as a takeoff command may need it (GLOBAL_POSITION_INT units)."""

    lat_e7: int
    lon_e7: int
    yaw_deg: float


@dataclass(frozen=True)
class Command:
    """One MAVLink command. ``int_frame`` set: send as COMMAND_INT with x, y = params[4:6] as
    integers (degE7) and z = params[6]; else COMMAND_LONG."""

    command: int
    params: tuple[float, ...]  # param1..param7, all finite
    int_frame: int | None = None


class EncodeError(EpcError, ValueError):
    """An intent cannot be encoded (a value is missing or not finite): nothing is sent."""


def command(cmd: int, *params: float, int_frame: int | None = None) -> Command:
    """A command with params 1..len(params) given and the rest 0; EncodeError on a NaN or an
    infinity anywhere (ArduCopter's SITL crashed on a takeoff of NaNs)."""
    p = tuple(float(v) for v in params) + (0.0,) * (7 - len(params))
    if len(p) != 7 or not all(math.isfinite(v) for v in p):
        raise EncodeError(f"command {cmd}: non-finite or too many parameters in {p}")
    return Command(cmd, p, int_frame)


def set_custom_mode(custom_mode: int, sub_mode: int = 0) -> Command:
    """MAV_CMD_DO_SET_MODE with a custom mode (PX4: main and sub; ArduPilot: the number)."""
    return command(MAV_CMD_DO_SET_MODE, MAV_MODE_FLAG_CUSTOM_MODE_ENABLED, custom_mode, sub_mode)


def message_interval(msg_id: int, rate_hz: float) -> Command:
    """MAV_CMD_SET_MESSAGE_INTERVAL: ``msg_id`` at ``rate_hz`` (both autopilots honour it)."""
    return command(MAV_CMD_SET_MESSAGE_INTERVAL, msg_id, 1e6 / rate_hz)


class Encoder(Protocol):
    """The command for an intent; EncodeError when it cannot be sent with finite parameters."""

    def __call__(
        self,
        action: Action,
        takeoff: TakeoffTarget | None = None,
        position: Position | None = None,
    ) -> Command: ...


@dataclass(frozen=True)
class Dialect:
    """One autopilot's meaning of the intents: pure functions and facts, no state."""

    name: str
    autopilot: int  # MAV_AUTOPILOT of its heartbeat
    # ArduCopter: GUIDED must be selected before arming (it cannot take off from STABILIZE);
    # the takeoff then happens in GUIDED, so GUIDED + armed on the ground is not yet
    # "flying offboard"
    offboard_before_arming: bool
    # (message id, rate) to ask for besides the loops' state streams
    extra_streams_hz: tuple[tuple[int, float], ...]
    mode: Callable[[Heartbeat], FlightMode]
    encode: Encoder
    # SET_ATTITUDE_TARGET's thrust for a collective thrust ``thrust_norm`` (already divided
    # by the tilt's cosine) at the current tilt's cosine
    wire_thrust: Callable[[float, float], float]
    # attitude.mode "auto" resolves to this ("epc": body rates; "autopilot": quaternion)
    default_attitude_mode: Literal["epc", "autopilot"]
    # parameters read (PARAM_REQUEST_READ) once the link is up
    params_to_read: tuple[str, ...]
    # why offboard (GUIDED) must not be requested nor setpoints sent, given the parameters
    # read so far ("" when they may)
    offboard_refusal: Callable[[Mapping[str, float]], str]
