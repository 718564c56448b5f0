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
