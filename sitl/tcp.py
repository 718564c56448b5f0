"""A ground-station link over TCP, as ArduPilot SITL serves one on 5760 + 10 * instance.

Each connected client gets every telemetry message the vehicle sends and may send commands;
its byte stream is parsed by a parser of its own (a TCP read can end mid-message, unlike a
datagram). A client that stops reading loses telemetry, not the vehicle: past
``MAX_BUFFERED_BYTES`` queued its messages are dropped and counted.
"""

from __future__ import annotations

import asyncio
from typing import Any

from pymavlink.dialects.v20 import common as mavlink

from epc_offboard.common.signing import enable_signing
from sitl.endpoint import Address, SitlEndpoint

MAX_BUFFERED_BYTES = 1 << 20


class GcsTcpServer:
    def __init__(self, endpoint: SitlEndpoint, signing_key: bytes | None = None) -> None:
        self.endpoint = endpoint
        self.signing_key = signing_key
        self.dropped_bytes = 0
        self.connections = 0
        self._server: asyncio.Server | None = None

    async def start(self, host: str, port: int) -> int:
        """Listen on ``host:port`` (0: any free port); returns the bound port."""
        self._server = await asyncio.start_server(self._client, host, port)
        return int(self._server.sockets[0].getsockname()[1])

    def close(self) -> None:
        if self._server is not None:
            self._server.close()

    async def _client(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        peer = writer.get_extra_info("peername")
        addr: Address = (str(peer[0]), int(peer[1]))
        parser: Any = mavlink.MAVLink(None, srcSystem=self.endpoint.sysid, srcComponent=1)
        parser.robust_parsing = True
        if self.signing_key is not None:
            enable_signing(parser, self.signing_key)
        self.connections += 1

        def write(data: bytes) -> None:
            if writer.is_closing():
                return
            if writer.transport.get_write_buffer_size() > MAX_BUFFERED_BYTES:
                self.dropped_bytes += len(data)
                return
            writer.write(data)

        self.endpoint.stream_peers[addr] = write
        try:
            while data := await reader.read(65536):
                try:
                    msgs = parser.parse_buffer(data) or []
                except Exception:
                    msgs = []
                    self.endpoint.counters.malformed += 1
                self.endpoint.stream_received(msgs, addr)
        except (ConnectionError, OSError):
            pass
        finally:
            self.endpoint.stream_peers.pop(addr, None)
            writer.close()
