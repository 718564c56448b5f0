"""MAVLink 2 over UDP, TCP or serial for asyncio: a sans-IO receive path driven by the loop.

No blocking ``recv_match`` anywhere: datagrams (a DatagramProtocol) or serial bytes (a
non-blocking tty watched by ``loop.add_reader``) arrive on the event loop, are fed to
the receive path of ``vehicle/receive.py`` (every frame judged by its header, CRC and
signature before its payload is decoded; the loops' streams decoded by precompiled ``struct``
layouts, the rest by pymavlink; a budget per sending address) and handed to a callback as
decoded messages. Bad bytes never raise: they are counted here, by reason. pymavlink's codec
encodes and signs what is sent.

Connection URLs (as MAVSDK and mavutil spell them):

* ``udpin://HOST:PORT``  — bind HOST:PORT, reply to the first address that sent us a valid
  message (the usual companion-computer setup: PX4 sends to us on 14540); while it keeps
  talking, valid messages from any other address are counted (``other_sender``) and, on an
  unsigned link, dropped: a second sender can take over neither its setpoints nor its state;
* ``udpout://HOST:PORT`` — send to HOST:PORT from an ephemeral port (we speak first);
* ``serial:///dev/DEVICE:BAUD`` — a UART (PX4's TELEM2 to a companion computer), raw 8N1,
  no flow control; BAUD defaults to 57600 (PX4's SER_TEL2_BAUD). Mind the bandwidth: a
  200 Hz SET_ATTITUDE_TARGET stream alone is about 11 kB/s, so use 921600 for offboard.
  A serial byte stream carries frames split anywhere: partial frames are kept for the next
  read (a datagram's leftover, by contrast, is garbage). Writes never block the loop: what
  the tty cannot take at once is queued (bounded) and written when it is writable. A device
  that goes away (USB unplugged) is reopened every second until it is back.
* ``tcp://HOST:PORT`` — a TCP client (ArduPilot SITL's 5760 + 10 * instance, a MAVProxy or
  mavlink-router TCP output). A byte stream, like serial: partial frames are kept. When the
  connection cannot be made or drops, it is made again every ``TCP_RECONNECT_PERIOD_S``
  (counted, logged); until then sends are dropped and counted. Writes never block: past
  ``TCP_MAX_PENDING_BYTES`` unsent, a frame is dropped (a stale setpoint is worse than none).
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import os
import struct
import termios
import time
import tty
from collections import Counter
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any, BinaryIO, Literal
from urllib.parse import urlsplit

from pymavlink.dialects.v20 import common as mavlink

from epc_offboard.common.configio import ConfigError
from epc_offboard.common.logsetup import LogGate
from epc_offboard.common.signing import SignatureCheck, enable_signing
from epc_offboard.vehicle.receive import (
    ALL_MESSAGE_IDS,
    MAX_FRAMES_PER_DATAGRAM,
    MAX_FRAMES_PER_STRANGER_DATAGRAM,
    FrameReceiver,
    ReceiveBudget,
    SourceGate,
)

log = logging.getLogger(__name__)

MessageHandler = Callable[[Any], None]


SERIAL_DEFAULT_BAUD = 57600
SERIAL_REOPEN_PERIOD_S = 1.0
SERIAL_MAX_PENDING_BYTES = 8192  # ~90 ms at 921600 baud: beyond that, a setpoint is stale
TCP_RECONNECT_PERIOD_S = 1.0
TCP_MAX_PENDING_BYTES = 65536


@dataclass(frozen=True)
class Endpoint:
    mode: Literal["udpin", "udpout", "serial", "tcp"]
    host: str = ""
    port: int = 0
    device: str = ""  # serial only
    baud: int = 0  # serial only


def parse_url(url: str) -> Endpoint:
    """Parse ``udpin://HOST:PORT``, ``udpout://HOST:PORT``, ``tcp://HOST:PORT`` or
    ``serial:///dev/DEV[:BAUD]``; anything else is a ConfigError naming what is wrong."""
    parts = urlsplit(url)
    if parts.scheme == "serial":
        return _parse_serial(url)
    if parts.scheme not in ("udpin", "udpout", "tcp"):
        raise ConfigError(
            f"connection url {url!r}: scheme must be udpin://, udpout://, tcp:// or serial://"
        )
    try:
        port = parts.port
    except ValueError as exc:
        raise ConfigError(f"connection url {url!r}: bad port") from exc
    if not parts.hostname or port is None:
        raise ConfigError(f"connection url {url!r}: expected {parts.scheme}://HOST:PORT")
    if parts.scheme == "tcp":
        return Endpoint("tcp", parts.hostname, port)
    mode: Literal["udpin", "udpout"] = "udpin" if parts.scheme == "udpin" else "udpout"
    return Endpoint(mode, parts.hostname, port)


def _parse_serial(url: str) -> Endpoint:
    rest = url[len("serial://") :]
    device, sep, baud_text = rest.rpartition(":")
    if not sep:
        device, baud_text = rest, str(SERIAL_DEFAULT_BAUD)
    if not device.startswith("/"):
        raise ConfigError(f"connection url {url!r}: expected serial:///dev/DEVICE:BAUD")
    try:
        baud = int(baud_text)
    except ValueError as exc:
        raise ConfigError(
            f"connection url {url!r}: baud rate {baud_text!r} is not a number"
        ) from exc
    if not hasattr(termios, f"B{baud}"):
        raise ConfigError(f"connection url {url!r}: unsupported baud rate {baud}")
    return Endpoint("serial", device=device, baud=baud)


class TlogWriter:
    """A MAVLink telemetry log (.tlog): each frame prefixed by a big-endian uint64 of unix us.

    This is the format QGroundControl writes and MAVExplorer/mavlogdump read.
    """

    def __init__(self, path: str | Path) -> None:
        # Lives as long as the session, closed by close(): no context manager fits.
        self._fh: BinaryIO | None = Path(path).open("ab")  # noqa: SIM115

    def write(self, frame: bytes, unix_time_s: float | None = None) -> None:
        if self._fh is None:
            return
        t_us = int((time.time() if unix_time_s is None else unix_time_s) * 1e6)
        self._fh.write(struct.pack(">Q", t_us) + frame)

    def flush(self) -> None:
        if self._fh is not None:
            self._fh.flush()

    def close(self) -> None:
        if self._fh is not None:
            self._fh.close()
            self._fh = None


class _Protocol(asyncio.DatagramProtocol):
    def __init__(self, link: MavlinkLink) -> None:
        self._link = link

    def datagram_received(self, data: bytes, addr: tuple[str | Any, int]) -> None:
        self._link._on_datagram(data, addr)

    def error_received(self, exc: Exception) -> None:
        # ICMP port unreachable when the peer is not up yet: expected, not fatal.
        self._link.counters["socket_errors"] += 1
        log.debug("udp error: %s", exc)


class _StreamProtocol(asyncio.Protocol):
    """A TCP connection's bytes to the link (a stream: frames may be split anywhere)."""

    def __init__(self, link: MavlinkLink) -> None:
        self._link = link

    def data_received(self, data: bytes) -> None:
        link = self._link
        link._on_bytes(data, (link.endpoint.host, link.endpoint.port), stream=True)

    def connection_lost(self, exc: Exception | None) -> None:
        self._link._tcp_lost(self, "closed by the peer" if exc is None else str(exc))


class MavlinkLink:
    """One MAVLink 2 connection over UDP, TCP or serial.

    ``on_message`` is called on the event loop for every valid message that passed the
    header filters: ``accept_system_ids``, ``accept_component_ids`` (None accepts any) and
    ``accept_message_ids`` (default: every id of pymavlink's common dialect; the service
    gives the few it reads). ``counters`` counts what was received, sent and rejected, by
    reason. ``budget``: what header-check failures a UDP sender other than the peer may cost.
    """

    def __init__(
        self,
        url: str,
        *,
        system_id: int,
        component_id: int,
        on_message: MessageHandler,
        accept_system_ids: frozenset[int] | None = None,
        accept_component_ids: frozenset[int] | None = None,
        accept_message_ids: frozenset[int] = ALL_MESSAGE_IDS,
        signing_key: bytes | None = None,
        tlog: TlogWriter | None = None,
        peer_timeout_s: float = 3.0,
        budget: ReceiveBudget | None = None,
    ) -> None:
        self.endpoint = parse_url(url)
        self._on_message = on_message
        self._tlog = tlog
        self._transport: asyncio.DatagramTransport | None = None
        self._peer: tuple[str, int] | None = (
            (self.endpoint.host, self.endpoint.port) if self.endpoint.mode == "udpout" else None
        )
        self._fd: int | None = None  # serial
        self._tcp: asyncio.Transport | None = None  # tcp, while connected
        self._tcp_protocol: _StreamProtocol | None = None
        self._tcp_task: asyncio.Task[None] | None = None
        self._pending = bytearray()  # serial bytes the tty has not taken yet
        self._reopen: asyncio.TimerHandle | None = None
        self._loop: asyncio.AbstractEventLoop | None = None
        self._closed = False
        self._peer_timeout_s = peer_timeout_s
        self._peer_heard = -float("inf")
        self.counters: Counter[str] = Counter()
        self._log_gate = LogGate()
        self.mav = mavlink.MAVLink(_SendFile(self), srcSystem=system_id, srcComponent=component_id)
        self.signature: SignatureCheck | None = None
        if signing_key is not None:
            self.signature = enable_signing(self.mav, signing_key)
        # pymavlink decodes the accepted messages that have no fast layout, after the
        # receiver's checks: unsigned, so that it neither checks nor records a signature twice
        decoder = mavlink.MAVLink(None)
        self.receiver = FrameReceiver(
            self.counters,
            accept_ids=accept_message_ids,
            accept_systems=accept_system_ids,
            accept_components=accept_component_ids,
            signature=self.signature,
            decode_other=decoder.decode,
            on_mavlink1=self._warn_mavlink1,
        )
        self.gate = SourceGate(budget or ReceiveBudget())

    @property
    def peer(self) -> tuple[str, int] | None:
        return self._peer

    @property
    def local_address(self) -> tuple[str, int]:
        if self._transport is None:
            raise RuntimeError("link is not open")
        addr: tuple[str, int] = self._transport.get_extra_info("sockname")[:2]
        return addr

    async def open(self) -> None:
        """Bind or open the link; OSError names the address or device that failed."""
        loop = asyncio.get_running_loop()
        self._loop = loop
        self._closed = False
        if self.endpoint.mode == "serial":
            self._open_serial(loop)
            return
        if self.endpoint.mode == "tcp":
            # an autopilot not up yet is not an error: the link connects when it is
            await self._connect_tcp()
            return
        if self.endpoint.mode == "udpin":
            transport, _ = await loop.create_datagram_endpoint(
                lambda: _Protocol(self), local_addr=(self.endpoint.host, self.endpoint.port)
            )
        else:
            transport, _ = await loop.create_datagram_endpoint(
                lambda: _Protocol(self), local_addr=("0.0.0.0", 0)
            )
        self._transport = transport

    def close(self) -> None:
        self._closed = True
        if self._transport is not None:
            self._transport.close()
            self._transport = None
        if self._reopen is not None:
            self._reopen.cancel()
            self._reopen = None
        if self._tcp_task is not None:
            self._tcp_task.cancel()
            self._tcp_task = None
        if self._tcp is not None:
            self._tcp.close()
            self._tcp = None
        self._close_serial()
        if self._tlog is not None:
            self._tlog.flush()

    def send(self, msg: Any) -> bool:
        """Encode and send ``msg``; False (and counted) when there is no peer or socket yet."""
        if self.endpoint.mode == "serial":
            if self._fd is None:
                self.counters["send_no_peer"] += 1
                return False
        elif self.endpoint.mode == "tcp":
            if self._tcp is None:
                self.counters["send_no_peer"] += 1
                return False
        elif self._transport is None or self._peer is None:
            self.counters["send_no_peer"] += 1
            return False
        self.mav.send(msg)
        return True

    def _write_frame(self, frame: bytes) -> None:
        if self.endpoint.mode == "serial":
            if not self._write_serial(frame):
                return
        elif self.endpoint.mode == "tcp":
            if self._tcp is None or self._tcp.is_closing():
                return
            if self._tcp.get_write_buffer_size() + len(frame) > TCP_MAX_PENDING_BYTES:
                self.counters["send_dropped"] += 1  # the peer does not read: drop, never block
                return
            self._tcp.write(frame)
        else:
            if self._transport is None or self._peer is None:
                return
            self._transport.sendto(frame, self._peer)
        self.counters["sent"] += 1
        if self._tlog is not None:
            self._tlog.write(frame)

    # -- serial ---------------------------------------------------------------------------

    def _open_serial(self, loop: asyncio.AbstractEventLoop) -> None:
        dev, baud = self.endpoint.device, self.endpoint.baud
        fd = os.open(dev, os.O_RDWR | os.O_NOCTTY | os.O_NONBLOCK)
        try:
            tty.setraw(fd)  # 8 bits, no echo, no line editing, no signals
            attrs = termios.tcgetattr(fd)
            attrs[2] = (attrs[2] | termios.CLOCAL | termios.CREAD) & ~termios.CRTSCTS
            attrs[4] = attrs[5] = getattr(termios, f"B{baud}")
            termios.tcsetattr(fd, termios.TCSANOW, attrs)
        except termios.error as exc:
            os.close(fd)
            raise OSError(f"{dev}: cannot configure the serial port: {exc}") from exc
        self._fd = fd
        self._pending.clear()
        self._peer = (dev, baud)
        loop.add_reader(fd, self._on_serial_readable)
        log.info("serial link open: %s at %d baud", dev, baud)

    def _close_serial(self) -> None:
        if self._fd is None:
            return
        if self._loop is not None and not self._loop.is_closed():
            self._loop.remove_reader(self._fd)
            self._loop.remove_writer(self._fd)
        with contextlib.suppress(OSError):
            os.close(self._fd)
        self._fd = None
        self._pending.clear()

    def _on_serial_readable(self) -> None:
        if self._fd is None:
            return
        try:
            data = os.read(self._fd, 4096)
        except BlockingIOError:
            return
        except OSError as exc:
            self._serial_lost(str(exc))
            return
        if not data:
            self._serial_lost("end of file")
            return
        self._on_bytes(data, (self.endpoint.device, self.endpoint.baud), stream=True)

    def _write_serial(self, frame: bytes) -> bool:
        if self._fd is None:
            return False
        if len(self._pending) + len(frame) > SERIAL_MAX_PENDING_BYTES:
            self.counters["send_dropped"] += 1  # the link is saturated: drop, never block
            return False
        if self._pending:
            self._pending += frame
            return True
        try:
            n = os.write(self._fd, frame)
        except BlockingIOError:
            n = 0
        except OSError as exc:
            self._serial_lost(str(exc))
            return False
        if n < len(frame):
            self._pending += frame[n:]
            assert self._loop is not None
            self._loop.add_writer(self._fd, self._flush_serial)
        return True

    def _flush_serial(self) -> None:
        if self._fd is None:
            return
        try:
            n = os.write(self._fd, self._pending)
        except BlockingIOError:
            return
        except OSError as exc:
            self._serial_lost(str(exc))
            return
        del self._pending[:n]
        if not self._pending and self._loop is not None:
            self._loop.remove_writer(self._fd)

    def _serial_lost(self, why: str) -> None:
        self.counters["serial_lost"] += 1
        log.error("serial link %s lost (%s): reopening", self.endpoint.device, why)
        self._close_serial()
        self._schedule_reopen()

    def _schedule_reopen(self) -> None:
        if self._closed or self._loop is None:
            return
        self._reopen = self._loop.call_later(
            SERIAL_REOPEN_PERIOD_S, self._try_reopen, self._loop
        )

    def _try_reopen(self, loop: asyncio.AbstractEventLoop) -> None:
        self._reopen = None
        try:
            self._open_serial(loop)
        except OSError as exc:
            self.counters["serial_reopen_failed"] += 1
            log.debug("serial reopen failed: %s", exc)
            self._schedule_reopen()

    # -- tcp ------------------------------------------------------------------------------

    async def _connect_tcp(self) -> None:
        """One connection attempt; on failure the next is scheduled."""
        loop = asyncio.get_running_loop()
        host, port = self.endpoint.host, self.endpoint.port
        try:
            transport, protocol = await loop.create_connection(
                lambda: _StreamProtocol(self), host, port
            )
        except OSError as exc:
            self.counters["tcp_connect_failed"] += 1
            if self.counters["tcp_connect_failed"] == 1:
                log.warning("tcp %s:%d: cannot connect (%s): retrying", host, port, exc)
            self._schedule_tcp_connect()
            return
        if self._closed:
            transport.close()
            return
        self._reset_parser()  # a stream cut mid-frame: the old connection's bytes are void
        self._tcp, self._tcp_protocol = transport, protocol
        self._peer = (host, port)
        self.counters["tcp_connects"] += 1
        log.info("tcp link connected to %s:%d", host, port)

    def _schedule_tcp_connect(self) -> None:
        if self._closed or self._loop is None:
            return

        def start() -> None:
            if not self._closed:
                self._tcp_task = asyncio.ensure_future(self._connect_tcp())

        self._reopen = self._loop.call_later(TCP_RECONNECT_PERIOD_S, start)

    def _tcp_lost(self, protocol: _StreamProtocol, why: str) -> None:
        if protocol is not self._tcp_protocol:
            return  # an old connection's late notice
        self._tcp = self._tcp_protocol = None
        if self._closed:
            return
        self.counters["tcp_lost"] += 1
        host, port = self.endpoint.host, self.endpoint.port
        log.error("tcp link to %s:%d lost (%s): reconnecting", host, port, why)
        self._schedule_tcp_connect()

    def _reset_parser(self) -> None:
        self.receiver.reset_stream()

    # -- receiving ------------------------------------------------------------------------

    def _on_datagram(self, data: bytes, addr: tuple[Any, int]) -> None:
        self.counters["datagrams"] += 1
        source = (addr[0], addr[1])
        now = time.monotonic()
        if source == self._peer:  # the autopilot: never throttled (its garbage noted)
            self._deliver(self._receive(data, None, now, soiled_by=source), addr)
            return
        gate = self.gate
        if not gate.admits(source, now):
            self.counters["throttled"] += 1
            return
        # one datagram a callback (asyncio's datagram transport reads one per readiness):
        # from a second address while the peer talks, few of its frames are read
        stranger = self._peer_live(now)
        frames = MAX_FRAMES_PER_STRANGER_DATAGRAM if stranger else MAX_FRAMES_PER_DATAGRAM
        msgs = self._receive(data, source, now, frames)
        if not msgs:
            return
        if stranger:
            # The autopilot is talking to us from its address: on an unsigned link, a second
            # address sending well-formed frames of its ids is a forger (or a stray route),
            # and what it says is neither flown nor worth the tracker's time. Charged like
            # garbage. (Signed frames prove themselves, whatever their route: delivered.)
            self.counters["other_sender"] += len(msgs)
            gate.charge(source, len(msgs), now)
            return
        gate.delivered(source, now)
        self._deliver(msgs, addr)

    def _peer_live(self, now: float) -> bool:
        """Whether messages from an address other than the peer are dropped: an unsigned
        udpin link whose peer has spoken within peer_timeout_s and sends no malformed frames
        (a peer that does, a fuzzer that spoke first, lets a clean sender be heard)."""
        return (
            self.endpoint.mode == "udpin"
            and self.signature is None
            and self._peer is not None
            and now - self._peer_heard <= self._peer_timeout_s
            and self.gate.clean(self._peer, now)
        )

    def _receive(
        self, data: bytes, source: tuple[Any, int] | None = None, now: float = 0.0,
        max_frames: int = MAX_FRAMES_PER_DATAGRAM, *, soiled_by: tuple[Any, int] | None = None,
    ) -> list[Any]:
        """The messages of one datagram (at most ``max_frames`` frames read); its failures
        are charged to ``source`` (None: the peer, not charged), its malformed frames noted
        against ``source`` or ``soiled_by`` (:meth:`SourceGate.soiled`)."""
        counters = self.counters
        malformed = counters["bad_data"]
        try:
            msgs, failures = self.receiver.datagram(data, max_frames)
        except Exception as exc:  # the receive path must never take the loop down
            self.counters["bad_data"] += 1
            self.counters["decode_errors"] += 1
            log.debug("undecodable datagram: %s", exc)
            return []
        if failures:
            if source is not None:
                self.gate.charge(source, failures, now)
            if (noted := source or soiled_by) is not None:
                self.gate.soiled(noted, counters["bad_data"] - malformed, now)
        return msgs

    def _on_bytes(self, data: bytes, addr: tuple[Any, int], *, stream: bool) -> None:
        """A byte stream's next bytes (serial, TCP; ``stream`` False: one datagram)."""
        if not stream:
            self._deliver(self._receive(data), addr)
            return
        try:
            msgs = self.receiver.stream(data)
        except Exception as exc:  # the receive path must never take the loop down
            self.counters["bad_data"] += 1
            self.counters["decode_errors"] += 1
            self.receiver.reset_stream()
            log.debug("undecodable bytes from %s: %s", addr, exc)
            return
        self._deliver(msgs, addr)

    def _deliver(self, msgs: list[Any], addr: tuple[Any, int]) -> None:
        for msg in msgs:
            try:
                self._dispatch(msg, addr)
            except Exception as exc:  # one bad message costs one counted drop, not the rest
                self.counters["dispatch_errors"] += 1
                if self._log_gate.open("dispatch", 1.0):
                    log.warning(
                        "%s dropped: %s: %s (%d so far)",
                        msg.get_type(), type(exc).__name__, exc, self.counters["dispatch_errors"],
                    )  # fmt: skip

    def _warn_mavlink1(self) -> None:
        if self._log_gate.open("mavlink1", 10.0):
            log.warning(
                "MAVLink 1 frames received and dropped (%d so far): this link speaks MAVLink "
                "2 only; set the autopilot's link to MAVLink 2 (ArduPilot SERIALn_PROTOCOL = "
                "2, PX4 MAV_PROTO_VER = 2)", self.counters["mavlink1"],
            )  # fmt: skip

    def _dispatch(self, msg: Any, addr: tuple[Any, int]) -> None:
        """One message that passed the receiver's checks: the peer's bookkeeping, the tlog,
        the callback."""
        if self.endpoint.mode == "udpin":
            # The peer is the first address that spoke; it only moves once it has been silent
            # for peer_timeout_s (the autopilot restarted on another port). A second sender
            # can neither redirect our setpoints nor feed us state while the vehicle talks.
            # Never to a sender of malformed frames (SourceGate.clean): a fuzzer talking while
            # the autopilot was silent for peer_timeout_s took the peer, and the autopilot's
            # frames, back, were dropped as a second sender's while the fuzz lasted; nor is
            # such a sender's state flown while the peer is silent (unsigned). A peer that
            # sends malformed frames (a fuzzer that spoke first) yields to a clean sender.
            sender = (str(addr[0]), int(addr[1]))
            now = time.monotonic()
            gate = self.gate
            if sender == self._peer:
                self._peer_heard = now
            elif (clean := gate.clean(sender, now)) and (
                self._peer is None
                or now - self._peer_heard > self._peer_timeout_s
                or not gate.clean(self._peer, now)
            ):
                if self._peer is not None:
                    log.warning("MAVLink peer moved from %s:%d to %s:%d", *self._peer, *sender)
                self._peer, self._peer_heard = sender, now
            else:
                self.counters["other_sender"] += 1
                if self._peer_live(now) or (self.signature is None and not clean):
                    return
        self.counters["received"] += 1
        if self._tlog is not None:
            self._tlog.write(bytes(msg.get_msgbuf()))
        self._on_message(msg)


class _SendFile:
    """The file-like pymavlink writes packed frames to."""

    def __init__(self, link: MavlinkLink) -> None:
        self._link = link

    def write(self, frame: bytes) -> None:
        self._link._write_frame(bytes(frame))
