"""tcp://HOST:PORT links against a real TCP server on loopback: frames split anywhere are
reassembled, sends reach the server, and after the server drops the connection (or before
it listens at all) the link connects again by itself."""

from __future__ import annotations

import asyncio

import pytest
from pymavlink.dialects.v20 import common as mavlink

from epc_offboard.common.configio import ConfigError
from epc_offboard.common.ports import free_port
from epc_offboard.vehicle import link as link_module
from epc_offboard.vehicle.link import Endpoint, MavlinkLink, parse_url

WAIT_S = 5.0  # generous: every wait below ends on an event, not on this


def test_parse_tcp_url():
    assert parse_url("tcp://127.0.0.1:5762") == Endpoint("tcp", "127.0.0.1", 5762)
    for bad in ("tcp://127.0.0.1", "tcp://:5760", "tcpin://127.0.0.1:5760"):
        with pytest.raises(ConfigError, match="url"):
            parse_url(bad)


class _Server:
    """A ground-station-like TCP server: counts connections, records what it receives,
    can send frames (split in two writes) and drop the connection."""

    def __init__(self) -> None:
        self.writers: list[asyncio.StreamWriter] = []
        self.received: list = []
        self.connected = asyncio.Event()
        self.got = asyncio.Event()
        self.mav = mavlink.MAVLink(None, srcSystem=1, srcComponent=1)
        self.rx = mavlink.MAVLink(None)
        self.server: asyncio.Server | None = None
        self.port = 0

    async def start(self, port: int = 0) -> None:
        self.server = await asyncio.start_server(self._client, "127.0.0.1", port)
        self.port = self.server.sockets[0].getsockname()[1]

    async def _client(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        self.writers.append(writer)
        self.connected.set()
        while data := await reader.read(4096):
            self.received += self.rx.parse_buffer(data) or []
            self.got.set()

    async def send_heartbeat(self, custom_mode: int) -> None:
        frame = bytes(
            self.mav.heartbeat_encode(mavlink.MAV_TYPE_QUADROTOR, 3, 0, custom_mode, 3).pack(
                self.mav
            )
        )
        writer = self.writers[-1]
        writer.write(frame[:7])  # a frame split across two TCP segments
        await writer.drain()
        await asyncio.sleep(0.01)
        writer.write(frame[7:])
        await writer.drain()

    async def drop(self) -> None:
        for w in self.writers:
            w.close()
        self.connected.clear()

    async def stop(self) -> None:
        assert self.server is not None
        self.server.close()
        await self.drop()


async def _until(cond, what: str) -> None:
    """Until the link's counters or inbox say so (they have no event to wait on)."""
    async with asyncio.timeout(WAIT_S):
        while not cond():  # noqa: ASYNC110 - polling plain counters
            await asyncio.sleep(0.01)
    assert cond(), what


def test_tcp_round_trip_and_reconnect_after_the_server_drops_it(monkeypatch):
    monkeypatch.setattr(link_module, "TCP_RECONNECT_PERIOD_S", 0.05)

    async def run() -> None:
        server = _Server()
        await server.start()
        got: list = []
        link = MavlinkLink(
            f"tcp://127.0.0.1:{server.port}", system_id=245, component_id=191,
            on_message=got.append,
        )  # fmt: skip
        await link.open()
        await asyncio.wait_for(server.connected.wait(), WAIT_S)
        await server.send_heartbeat(4)
        await _until(lambda: len(got) == 1, "heartbeat received")
        assert got[0].custom_mode == 4
        assert link.send(link.mav.param_request_read_encode(1, 1, b"GUID_OPTIONS", -1))
        await asyncio.wait_for(server.got.wait(), WAIT_S)
        assert server.received[0].get_type() == "PARAM_REQUEST_READ"

        # the server drops the connection: sends fail (counted), then the link is back
        await server.drop()
        await _until(lambda: link.counters["tcp_lost"] == 1, "loss noticed")
        assert not link.send(link.mav.param_request_read_encode(1, 1, b"X", -1))
        await _until(lambda: link.counters["tcp_connects"] == 2, "reconnected")
        await asyncio.wait_for(server.connected.wait(), WAIT_S)
        await server.send_heartbeat(5)
        await _until(lambda: len(got) == 2, "heartbeat after the reconnect")
        assert got[1].custom_mode == 5
        server.got.clear()
        assert link.send(link.mav.param_request_read_encode(1, 1, b"GUID_TIMEOUT", -1))
        await asyncio.wait_for(server.got.wait(), WAIT_S)
        assert server.received[-1].param_id == "GUID_TIMEOUT"
        assert link.counters["send_no_peer"] >= 1
        link.close()
        await server.stop()

    asyncio.run(run())


def test_tcp_link_waits_for_a_server_that_is_not_up_yet(monkeypatch):
    monkeypatch.setattr(link_module, "TCP_RECONNECT_PERIOD_S", 0.05)

    async def run() -> None:
        # a port nobody listens on (for now), reserved: an OS-chosen one closed and bound
        # again later could be any other socket's meanwhile
        port = free_port()
        link = MavlinkLink(
            f"tcp://127.0.0.1:{port}", system_id=245, component_id=191, on_message=lambda m: None
        )
        await link.open()  # not an error: the autopilot may boot after the service
        await _until(lambda: link.counters["tcp_connect_failed"] >= 2, "retrying")
        server = _Server()
        await server.start(port)
        await asyncio.wait_for(server.connected.wait(), WAIT_S)
        assert link.counters["tcp_connects"] == 1
        link.close()
        await server.stop()

    asyncio.run(run())
