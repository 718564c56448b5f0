"""Command-line values both commands take (``epc-offboard sim``, ``epc-sitl``), checked where
argparse reads them: a bad value is exit code 2 with a message naming the flag and the value
(argparse prefixes ``argument --flag:``), before any process starts or socket opens.
"""

from __future__ import annotations

import argparse
import errno
import math
import socket
from collections.abc import Callable, Sequence
from dataclasses import dataclass

from epc_offboard.common.errors import EpcError

MAX_PORT = 65535


def parse_wind(text: str) -> tuple[float, float]:
    """Parse ``SPEED_M_S,DIR_DEG`` (docs/CONTRACTS.md) into (speed_m_s, dir_deg)."""
    parts = text.split(",")
    if len(parts) != 2:
        raise argparse.ArgumentTypeError(f"expects SPEED_M_S,DIR_DEG, got {text!r}")
    try:
        speed, direction = float(parts[0]), float(parts[1])
    except ValueError as exc:
        raise argparse.ArgumentTypeError(f"expects two numbers, got {text!r}") from exc
    if not (math.isfinite(speed) and math.isfinite(direction)):
        raise argparse.ArgumentTypeError(f"wants finite numbers, got {text!r}")
    if speed < 0.0:
        # the direction says where it blows: a negative speed is the opposite direction
        raise argparse.ArgumentTypeError(
            f"the speed must be >= 0, got {text!r} (the wind blows towards DIR_DEG: "
            f"{-speed:g},{(direction + 180.0) % 360.0:g} is that wind)"
        )
    return speed, direction


@dataclass(frozen=True)
class WindProfile:
    """How the wind varies about ``--wind`` (its speed and direction): a sinusoid on the
    speed, ``amplitude sin(rate t + phase)`` (Neural-Fly's 8.5 + 2.4 sin t: amplitude 2.4,
    rate 1; t from the vehicle's offboard entry, sitl.params.EnvironmentParams), and
    Gauss-Markov gusts (standard deviation per horizontal axis, time constant).
    The default is steady wind."""

    sine_amplitude_m_s: float = 0.0
    sine_rate_rad_s: float = 1.0
    sine_phase_rad: float = 0.0
    gust_std_m_s: float = 0.0
    gust_time_constant_s: float = 2.0

    @property
    def text(self) -> str:
        """The canonical ``--wind-profile`` spelling (``parse_wind_profile`` reads it back)."""
        parts = []
        if self.sine_amplitude_m_s > 0.0:
            phase = f",{self.sine_phase_rad:g}" if self.sine_phase_rad else ""
            parts.append(f"sine:{self.sine_amplitude_m_s:g},{self.sine_rate_rad_s:g}{phase}")
        if self.gust_std_m_s > 0.0:
            parts.append(f"gusts:{self.gust_std_m_s:g},{self.gust_time_constant_s:g}")
        return "+".join(parts) or "steady"

    def environment(self) -> dict[str, float]:
        """The SITL's ``[environment]`` keys this profile sets."""
        return {
            "wind_sine_amplitude_m_s": self.sine_amplitude_m_s,
            "wind_sine_rate_rad_s": self.sine_rate_rad_s,
            "wind_sine_phase_rad": self.sine_phase_rad,
            "gust_std_m_s": self.gust_std_m_s,
            "gust_time_constant_s": self.gust_time_constant_s,
        }


WIND_PROFILE_HELP = (
    "how the wind varies about --wind: 'sine:AMP_M_S,RATE_RAD_S[,PHASE_RAD]' (the speed "
    "swings by AMP sin(RATE t + PHASE) along the wind's direction, t from the vehicle's "
    "offboard entry, when the trajectory starts; steady at t = 0 before it), "
    "'gusts:STD_M_S,TAU_S' "
    "(Gauss-Markov gusts), both joined by '+', or 'steady'; e.g. --wind 8.5,-90 "
    "--wind-profile sine:2.4,1 is Neural-Fly's 8.5 + 2.4 sin t m/s"
)


def parse_wind_profile(text: str) -> WindProfile:
    """Parse ``--wind-profile`` (see WIND_PROFILE_HELP) into a WindProfile."""
    values: dict[str, float] = {}
    terms = [t.strip() for t in text.strip().split("+")]
    if terms == ["steady"]:
        return WindProfile()
    wants = {"sine": (2, 3), "gusts": (2, 2)}
    for term in terms:
        kind, sep, args = term.partition(":")
        if not sep or kind not in wants:
            raise argparse.ArgumentTypeError(
                f"{text!r}: each term is sine:AMP_M_S,RATE_RAD_S[,PHASE_RAD] or "
                f"gusts:STD_M_S,TAU_S (or the whole is 'steady'), got {term!r}"
            )
        if f"{kind}_seen" in values:
            raise argparse.ArgumentTypeError(f"{text!r}: {kind} is given twice")
        values[f"{kind}_seen"] = 1.0
        try:
            nums = [float(a) for a in args.split(",")]
        except ValueError as exc:
            raise argparse.ArgumentTypeError(f"{text!r}: {term!r} wants numbers") from exc
        low, high = wants[kind]
        if not low <= len(nums) <= high or not all(math.isfinite(v) for v in nums):
            raise argparse.ArgumentTypeError(
                f"{text!r}: {kind} takes {low}{'' if low == high else f'-{high}'} finite "
                f"numbers, got {term!r}"
            )
        if nums[0] < 0.0 or nums[1] <= 0.0:
            raise argparse.ArgumentTypeError(
                f"{text!r}: {kind}'s first number must be >= 0 and its second > 0"
            )
        if kind == "sine":
            values.update(sine_amplitude_m_s=nums[0], sine_rate_rad_s=nums[1])
            values["sine_phase_rad"] = nums[2] if len(nums) == 3 else 0.0
        else:
            values.update(gust_std_m_s=nums[0], gust_time_constant_s=nums[1])
    return WindProfile(**{k: v for k, v in values.items() if not k.endswith("_seen")})


def port_number(text: str) -> int:
    """A UDP/TCP port, 0-65535 (0: none, or any free one, as the flag says)."""
    try:
        port = int(text)
    except ValueError as exc:
        raise argparse.ArgumentTypeError(f"not a port number: {text!r}") from exc
    if not 0 <= port <= MAX_PORT:
        raise argparse.ArgumentTypeError(f"a port is 0-{MAX_PORT}, got {text!r}")
    return port


def positive_number(text: str) -> float:
    """A finite number > 0: a duration, a rate, a speed-up (``nan`` and ``inf`` are none)."""
    try:
        value = float(text)
    except ValueError as exc:
        raise argparse.ArgumentTypeError(f"not a number: {text!r}") from exc
    if not (math.isfinite(value) and value > 0.0):
        raise argparse.ArgumentTypeError(f"must be finite and > 0, got {text!r}")
    return value


def bounded_int(low: int, high: int | None = None) -> Callable[[str], int]:
    """An integer in [low, high] (no upper bound with ``high`` None)."""

    def parse(text: str) -> int:
        try:
            value = int(text)
        except ValueError as exc:
            raise argparse.ArgumentTypeError(f"not an integer: {text!r}") from exc
        if value < low or (high is not None and value > high):
            span = f">= {low}" if high is None else f"in {low}..{high}"
            raise argparse.ArgumentTypeError(f"must be {span}, got {text!r}")
        return value

    parse.__name__ = "integer"
    return parse


def join_negative_values(argv: Sequence[str], flags: Sequence[str]) -> list[str]:
    """``--wind -3,45`` as ``--wind=-3,45``: argparse takes a value starting with ``-`` that is
    not a plain number for an option and answers "expected one argument", which names neither
    the value nor what is wrong with it; joined, the flag's own check says."""
    out: list[str] = []
    items = list(argv)
    i = 0
    while i < len(items):
        item = items[i]
        nxt = items[i + 1] if i + 1 < len(items) else ""
        if item in flags and len(nxt) > 1 and nxt[0] == "-" and (nxt[1].isdigit() or nxt[1] == "."):
            out.append(f"{item}={nxt}")
            i += 2
            continue
        out.append(item)
        i += 1
    return out


class PortInUseError(EpcError, OSError):
    """A port a command must bind is taken: the message names the port and who wants it."""


def check_port_free(kind: str, host: str, port: int, what: str) -> None:
    """Bind ``host:port`` (``kind`` "udp" or "tcp") for a moment; PortInUseError naming the
    port and ``what`` needs it if that fails. Done before slow start-up work (kernel warm-up,
    starting processes), so a taken port is reported at once, not seconds later."""
    if port == 0:
        return
    sock_type = socket.SOCK_DGRAM if kind == "udp" else socket.SOCK_STREAM
    with socket.socket(socket.AF_INET, sock_type) as probe:
        if kind == "tcp":  # as a server binds it: a closing connection's TIME_WAIT is no owner
            probe.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            probe.bind((host, port))
        except OSError as exc:
            reason = "already in use" if exc.errno == errno.EADDRINUSE else exc.strerror
            raise PortInUseError(f"{what}: cannot bind {kind} {host}:{port}: {reason}") from exc
