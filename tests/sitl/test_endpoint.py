"""The MAVLink endpoint in-process: a recording transport instead of a socket."""

from __future__ import annotations

import dataclasses
import math
from typing import Any

import pytest
from pymavlink.dialects.v20 import common as mavlink

from sitl.autopilot import HOLD, OFFBOARD
from sitl.endpoint import Counters, SitlEndpoint
from sitl.params import load_sim_config
from sitl.simulation import Simulation

TELEMETRY = ("127.0.0.1", 14999)
PEER = ("127.0.0.1", 40001)


class RecordingTransport:
    def __init__(self) -> None:
        self.sent: list[tuple[bytes, tuple[str, int]]] = []

    def sendto(self, data: bytes, addr: tuple[str, int]) -> None:
        self.sent.append((data, addr))


class Peer:
    def __init__(self, sysid: int = 245) -> None:
        self.mav = mavlink.MAVLink(None, srcSystem=sysid, srcComponent=190)
        self.rx = mavlink.MAVLink(None)

    def pack(self, msg) -> bytes:
        return bytes(msg.pack(self.mav))

    def decode(self, transport: RecordingTransport, addr=PEER) -> list[Any]:
        out: list[Any] = []
        for data, dest in transport.sent:
            if dest == addr:
                out += self.rx.parse_buffer(data) or []
        return out


def make(allowed=(), on_answer=None, arm_refusals=0, on_offboard=None):
    cfg = load_sim_config()
    cfg = dataclasses.replace(
        cfg,
        sitl=dataclasses.replace(cfg.sitl, allowed_source_sysids=tuple(allowed)),
        autopilot=dataclasses.replace(cfg.autopilot, arm_refusals_after_boot=arm_refusals),
    )
    sim = Simulation(cfg, seed=0)
    counters = Counters()
    ep = SitlEndpoint(sim, 1, [TELEMETRY], counters, on_answer=on_answer, on_offboard=on_offboard)
    transport = RecordingTransport()
    ep.connection_made(transport)  # type: ignore[arg-type]
    return sim, ep, transport, counters


def test_replies_go_to_the_sender_and_to_telemetry():
    sim, ep, transport, _ = make(arm_refusals=1)
    peer = Peer()
    arm = peer.pack(peer.mav.command_int_encode(1, 1, 0, 400, 0, 0, 1, 0, 0, 0, 0, 0, 0))
    ep.datagram_received(arm, PEER)  # refused once after boot, as PX4, and says why
    ep.datagram_received(arm, PEER)
    got = peer.decode(transport)
    acks = [m for m in got if m.get_type() == "COMMAND_ACK"]
    assert [(a.command, a.result, a.target_system) for a in acks] == [(400, 2, 245), (400, 0, 245)]
    texts = [m.text for m in got if m.get_type() == "STATUSTEXT"]
    assert len(texts) == 1
    assert texts[0].startswith("Preflight Fail")
    assert any(dest == TELEMETRY for _, dest in transport.sent)
    assert sim.autopilot.armed


def emitted(ep: SitlEndpoint, transport: RecordingTransport) -> list[list[Any]]:
    """Each telemetry datagram, decoded: one per tick."""
    rx = mavlink.MAVLink(None)
    return [rx.parse_buffer(d) or [] for d, dest in transport.sent if dest == TELEMETRY]


def test_a_tick_is_one_datagram_with_px4s_streams_and_odometry_a_tick_behind():
    sim, ep, transport, _ = make()
    newest = []
    for _ in range(4):  # 5, 10, 15, 20 ms
        sim.advance_tick()
        ep.emit()
        newest.append(ep.newest_state_stamp_ms)
    ticks = emitted(ep, transport)
    assert len(ticks) == 3  # one datagram per tick that has something due (not 15 ms)
    first = {m.get_type() for m in ticks[0]}
    assert {"HEARTBEAT", "ATTITUDE", "LOCAL_POSITION_NED", "ODOMETRY"} <= first
    assert {"GLOBAL_POSITION_INT", "HOME_POSITION"} <= first
    # PX4's default 100 Hz ATTITUDE on a 200 Hz tick: every other tick only
    assert [m.get_type() for m in ticks[1]] == ["ATTITUDE"]
    assert [m.get_type() for m in ticks[2]][:2] == ["ATTITUDE", "ATTITUDE_QUATERNION"]  # 50 Hz
    assert newest == [5, 10, 10, 20]  # a tick with no new state needs no new answer
    for _ in range(40):
        sim.advance_tick()
        ep.emit()
    lags_ms = [
        max(m.time_boot_ms for m in t if hasattr(m, "time_boot_ms")) - o.time_usec // 1000
        for t in emitted(ep, transport)[1:]
        for o in t
        if o.get_type() == "ODOMETRY"
    ]
    assert lags_ms
    assert set(lags_ms) == {5}


def test_global_position_is_home_plus_the_local_position():
    sim, ep, transport, _ = make()
    cfg = sim.config.sitl
    sim.state[0:3] = [111.2, 0.0, -10.0]  # ~0.001 deg north, 10 m up
    sim.advance_tick()
    ep.emit()
    msgs = [m for t in emitted(ep, transport) for m in t]
    gpi = next(m for m in msgs if m.get_type() == "GLOBAL_POSITION_INT")
    assert gpi.lat * 1e-7 == pytest.approx(cfg.home_lat_deg + 0.001, abs=2e-5)
    assert gpi.lon * 1e-7 == pytest.approx(cfg.home_lon_deg, abs=1e-6)
    assert gpi.relative_alt == pytest.approx(10_000, abs=100)
    assert gpi.alt == pytest.approx((cfg.home_amsl_m + 10.0) * 1e3, abs=100)


def test_takeoff_altitude_is_amsl_and_nan_means_px4s_default():
    sim, ep, _transport, _ = make()
    peer = Peer()
    home = sim.config.sitl.home_amsl_m
    sim.autopilot.arm(True, 0.0)
    takeoff = peer.mav.command_int_encode(
        1, 1, mavlink.MAV_FRAME_GLOBAL, mavlink.MAV_CMD_NAV_TAKEOFF, 0, 0,
        0, 0, 0, 0, 473977420, 85455940, home + 4.0,
    )  # fmt: skip
    ep.datagram_received(peer.pack(takeoff), PEER)
    assert sim.autopilot._takeoff_target_d_m == pytest.approx(-4.0)
    nan_takeoff = peer.mav.command_long_encode(
        1, 1, mavlink.MAV_CMD_NAV_TAKEOFF, 0, *([math.nan] * 7)
    )
    ep.datagram_received(peer.pack(nan_takeoff), PEER)
    default_m = sim.config.autopilot.takeoff_altitude_m
    assert sim.autopilot._takeoff_target_d_m == pytest.approx(-default_m)  # current (0) + 2.5


def test_setpoints_and_system_time_answer_a_lockstep_tick():
    answers: list[int] = []
    _sim, ep, _transport, _ = make(on_answer=answers.append)
    peer = Peer()
    ep.datagram_received(peer.pack(peer.mav.system_time_encode(0, 15)), PEER)
    ep.datagram_received(
        peer.pack(peer.mav.set_attitude_target_encode(20, 1, 1, 7, [1, 0, 0, 0], 0, 0, 0, 0.5)),
        PEER,
    )
    ep.datagram_received(
        peer.pack(
            peer.mav.set_position_target_local_ned_encode(
                25, 1, 1, mavlink.MAV_FRAME_LOCAL_NED, 0, *([0.0] * 11)
            )
        ),
        PEER,
    )
    assert answers == [15, 20, 25]


def test_set_mode_message_and_position_setpoints_enter_offboard():
    sim, ep, _transport, counters = make()
    peer = Peer()
    for _k in range(5):
        sim.advance_tick()
        ep.datagram_received(
            peer.pack(
                peer.mav.set_position_target_local_ned_encode(
                    sim.time_ms,
                    1,
                    1,
                    mavlink.MAV_FRAME_LOCAL_NED,
                    0b110111111000,
                    0.0,
                    0.0,
                    -3.0,
                    0,
                    0,
                    0,
                    0,
                    0,
                    0,
                    0,
                    0,
                )
            ),
            PEER,
        )
    custom = mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED
    ep.datagram_received(peer.pack(peer.mav.set_mode_encode(1, custom, 6 << 16)), PEER)
    assert sim.autopilot.mode == OFFBOARD
    assert counters.setpoints == 5
    ep.datagram_received(peer.pack(peer.mav.set_mode_encode(1, custom, 0x03040000)), PEER)
    assert sim.autopilot.mode == HOLD


def test_a_request_out_of_offboard_hands_the_vehicle_back_and_a_failsafe_does_not():
    """The lockstep gate learns that the controller left from the intended mode its peer's
    requests set (the service's HOLD at its stop), not from PX4's own offboard-loss failsafe
    (a starved controller: the vehicle is still meant to be in offboard)."""
    said: list[bool] = []
    sim, ep, _transport, _ = make(on_offboard=said.append)
    peer = Peer()
    custom = mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED

    def set_mode(main: int, sub: int = 0) -> None:
        ep.datagram_received(
            peer.pack(peer.mav.command_long_encode(
                1, 1, mavlink.MAV_CMD_DO_SET_MODE, 0, custom, main, sub, 0, 0, 0, 0)),
            PEER,
        )  # fmt: skip

    sim.advance_tick()
    ep.datagram_received(
        peer.pack(peer.mav.set_position_target_local_ned_encode(
            sim.time_ms, 1, 1, mavlink.MAV_FRAME_LOCAL_NED, 0b110111111000,
            0.0, 0.0, -3.0, 0, 0, 0, 0, 0, 0, 0, 0)),
        PEER,
    )  # fmt: skip
    assert said == []  # a setpoint alone takes nothing over (PX4: the mode is asked for)
    set_mode(6)
    assert said == [True]
    sim.autopilot._setpoints_lost(sim.time_s)  # PX4's failsafe: flies HOLD, meant OFFBOARD
    assert sim.autopilot.mode == HOLD
    ep.datagram_received(peer.pack(peer.mav.heartbeat_encode(6, 8, 0, 0, 0)), PEER)
    assert said == [True]  # not handed back: the controller may only be slow
    set_mode(4, 3)  # the service's REQUEST_HOLD (AUTO.LOITER)
    assert said == [True, False]
    set_mode(4, 3)
    assert said == [True, False]  # said once


def test_unexpected_source_system_is_ignored_when_restricted():
    sim, ep, transport, counters = make(allowed=(255,))
    stranger = Peer(sysid=42)
    arm = stranger.mav.command_long_encode(1, 1, 400, 0, 1, 0, 0, 0, 0, 0, 0)
    ep.datagram_received(stranger.pack(arm), PEER)
    assert counters.unexpected_sysid == 1
    assert not sim.autopilot.armed
    assert transport.sent == []
    gcs = Peer(sysid=255)
    ep.datagram_received(
        gcs.pack(gcs.mav.command_long_encode(1, 1, 400, 0, 1, 0, 0, 0, 0, 0, 0)), PEER
    )
    assert sim.autopilot.armed


@pytest.mark.parametrize(
    ("command", "params", "result"),
    [
        (mavlink.MAV_CMD_DO_SET_MODE, (1, 4, 0), mavlink.MAV_RESULT_UNSUPPORTED),  # AUTO, no sub
        (mavlink.MAV_CMD_DO_SET_MODE, (0, 6, 0), mavlink.MAV_RESULT_UNSUPPORTED),  # no custom flag
        (mavlink.MAV_CMD_NAV_TAKEOFF, (0,) * 7, mavlink.MAV_RESULT_DENIED),  # disarmed
        (mavlink.MAV_CMD_REQUEST_MESSAGE, (9999,), mavlink.MAV_RESULT_DENIED),
        (mavlink.MAV_CMD_NAV_RETURN_TO_LAUNCH, (), mavlink.MAV_RESULT_UNSUPPORTED),
        (mavlink.MAV_CMD_SET_MESSAGE_INTERVAL, (math.nan, 1000), mavlink.MAV_RESULT_DENIED),
        (mavlink.MAV_CMD_SET_MESSAGE_INTERVAL, (math.inf, 1000), mavlink.MAV_RESULT_DENIED),
    ],
)
def test_command_results(command, params, result):
    _, ep, transport, _ = make()
    peer = Peer()
    p = [*params, *([0.0] * (7 - len(params)))]
    ep.datagram_received(peer.pack(peer.mav.command_long_encode(1, 1, command, 0, *p)), PEER)
    acks = [m for m in peer.decode(transport) if m.get_type() == "COMMAND_ACK"]
    assert [(a.command, a.result) for a in acks] == [(command, result)]


def test_ground_station_ritual_params_and_empty_mission():
    sim, ep, transport, _ = make()
    peer = Peer()
    ep.datagram_received(peer.pack(peer.mav.param_request_list_encode(1, 1)), PEER)
    ep.datagram_received(
        peer.pack(peer.mav.param_request_read_encode(1, 1, b"COM_OF_LOSS_T", -1)), PEER
    )
    ep.datagram_received(peer.pack(peer.mav.mission_request_list_encode(1, 1)), PEER)
    got = peer.decode(transport)
    values = [m for m in got if m.get_type() == "PARAM_VALUE"]
    assert len(values) == values[0].param_count + 1
    loss = [m.param_value for m in values if m.param_id == "COM_OF_LOSS_T"]
    assert loss == [sim.config.autopilot.offboard_loss_timeout_s] * 2
    assert [m.count for m in got if m.get_type() == "MISSION_COUNT"] == [0]


@pytest.mark.parametrize(("autopilot", "delivered_hz"), [("px4", 123.0), ("ardupilot", 200.0)])
def test_attitude_quaternion_is_capped_near_what_px4_delivers(autopilot, delivered_hz):
    """PX4 accepts SET_MESSAGE_INTERVAL at 200 Hz for ATTITUDE_QUATERNION and delivers about
    123 Hz; ArduCopter delivers the 200 Hz. ATTITUDE is not capped on either."""
    cfg = load_sim_config(None, {"sitl": {"autopilot": autopilot}})
    sim = Simulation(cfg, seed=0)
    ep = SitlEndpoint(sim, 1, [TELEMETRY], Counters())
    transport = RecordingTransport()
    ep.connection_made(transport)  # type: ignore[arg-type]
    peer = Peer()
    for msg_id in (mavlink.MAVLINK_MSG_ID_ATTITUDE_QUATERNION, mavlink.MAVLINK_MSG_ID_ATTITUDE):
        ask = peer.mav.command_long_encode(1, 1, 511, 0, msg_id, 5000, 0, 0, 0, 0, 0)
        ep.datagram_received(peer.pack(ask), PEER)
    acks = [m for m in peer.decode(transport) if m.get_type() == "COMMAND_ACK"]
    assert [a.result for a in acks] == [mavlink.MAV_RESULT_ACCEPTED] * 2
    transport.sent.clear()
    seconds = 2.0
    for _ in range(round(seconds / cfg.sitl.lockstep_period_s)):
        sim.advance_tick()
        ep.emit()
    types = [m.get_type() for t in emitted(ep, transport) for m in t]
    assert types.count("ATTITUDE_QUATERNION") / seconds == pytest.approx(delivered_hz, abs=2.0)
    assert types.count("ATTITUDE") / seconds == pytest.approx(200.0, abs=1.0)
