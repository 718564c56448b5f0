"""The SITL's ArduCopter personality: what the service depends on, behaviour by behaviour
(in-process: the simulation and its endpoint with a recording transport)."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
from pymavlink.dialects.v20 import common as mavlink

from epc_offboard.common.arducopter import (
    BRAKE,
    GUIDED,
    GUIDED_NOGPS,
    LAND,
    LOITER,
    RTL,
    STABILIZE,
)
from epc_offboard.common.frames import quat_to_euler
from sitl.ardupilot import ArduCopter, command_model
from sitl.autopilot import (
    HOLD,
    IGNORE_ATTITUDE,
    OFFBOARD,
    AttitudeSetpoint,
    PositionSetpoint,
    Result,
)
from sitl.endpoint import Counters, SitlEndpoint
from sitl.params import load_sim_config
from sitl.physics import QUAT
from sitl.simulation import Simulation
from tests.sitl.test_endpoint import PEER, TELEMETRY, Peer, RecordingTransport, emitted

LEVEL = (1.0, 0.0, 0.0, 0.0)
PX4_CFG = load_sim_config()


def config(guid_options: int = 0, ekf_origin_s: float = 0.0):
    """The personality, its EKF origin at ``ekf_origin_s`` (at boot by default: arming in
    GUIDED needs it)."""
    cfg = load_sim_config(None, {"sitl": {"autopilot": "ardupilot"}})
    ardupilot = dataclasses.replace(
        cfg.ardupilot, guid_options=guid_options, ekf_origin_after_boot_s=ekf_origin_s
    )
    return dataclasses.replace(cfg, ardupilot=ardupilot)


def sim_ap(guid_options: int = 0) -> tuple[Simulation, ArduCopter]:
    sim = Simulation(config(guid_options), seed=0)
    assert isinstance(sim.autopilot, ArduCopter)
    return sim, sim.autopilot


def fly(sim: Simulation, seconds: float, setpoint: AttitudeSetpoint | None = None) -> None:
    for k in range(round(seconds / sim.config.sitl.lockstep_period_s)):
        if setpoint is not None and k % 4 == 0:  # 50 Hz
            sim.autopilot.on_attitude_setpoint(setpoint, sim.time_s)
        sim.advance_tick()


def sp(thrust=0.5, q=LEVEL, rates=(0.0, 0.0, 0.0), mask=0b111):
    return AttitudeSetpoint(type_mask=mask, q_wxyz=q, rate_frd_rad_s=rates, thrust_norm=thrust)


def airborne(guid_options: int = 8, altitude_m: float = 3.0) -> tuple[Simulation, ArduCopter]:
    sim, ap = sim_ap(guid_options)
    assert ap.set_number(GUIDED, 0.0) == Result.ACCEPTED
    assert ap.arm(True, 0.0) == Result.ACCEPTED
    assert ap.takeoff_command(altitude_m, 0.0, 0.0) == Result.ACCEPTED
    fly(sim, 2.0 + altitude_m / sim.config.autopilot.climb_speed_m_s)
    assert -sim.state[2] == pytest.approx(altitude_m, abs=0.15)
    assert ap.number == GUIDED  # a guided takeoff stays in GUIDED
    return sim, ap


def test_plain_mode_numbers_and_px4s_offboard_is_rtl():
    _sim, ap = sim_ap()
    assert (ap.mav_autopilot, ap.custom_mode) == (3, STABILIZE)
    for number in (GUIDED, LOITER, BRAKE, LAND, STABILIZE):
        assert ap.set_mode_command(number, 0, 0.0) == Result.ACCEPTED
        assert ap.custom_mode == number
    assert ap.set_mode_command(99, 0, 0.0) == Result.UNSUPPORTED
    # what PX4's dialect sends for Offboard: (1, 6, 0) is RTL here, and counted
    assert ap.set_mode_command(6, 0, 0.0) == Result.ACCEPTED
    assert (ap.custom_mode, ap.rtl_count) == (RTL, 1)


def test_arming_needs_guided_and_takeoff_needs_a_finite_altitude():
    sim, ap = sim_ap()
    assert ap.arm(True, 0.0) == Result.DENIED  # STABILIZE: the old service's mistake
    assert ap.status_text is not None
    assert "GUIDED" in ap.status_text
    ap.set_number(GUIDED, 0.0)
    assert ap.takeoff_command(2.5, 0.0, 0.0) == Result.DENIED  # disarmed
    assert ap.arm(True, 0.0) == Result.ACCEPTED
    assert ap.takeoff_command(math.nan, 0.0, 0.0) == Result.DENIED  # the SITL crash, denied
    assert ap.takeoff_command(0.0, 0.0, 0.0) == Result.DENIED
    ap.set_number(LOITER, 0.0)
    assert ap.takeoff_command(2.5, 0.0, 0.0) == Result.DENIED  # not GUIDED
    ap.set_number(GUIDED, 0.0)
    assert ap.takeoff_command(2.5, 0.0, 0.0) == Result.ACCEPTED
    fly(sim, 3.0)
    assert ap.takeoff_command(5.0, 0.0, sim.time_s) == Result.DENIED  # already flying


def test_setpoints_obeyed_only_in_guided_and_rates_all_or_none():
    sim, ap = airborne()
    ap.set_number(LOITER, sim.time_s)
    fly(sim, 0.5, sp(thrust=0.9))  # ignored: LOITER holds
    assert ap.mode == HOLD
    assert ap.ignored_setpoints > 0
    ap.set_number(GUIDED, sim.time_s)
    ignored = ap.ignored_setpoints
    ap.on_attitude_setpoint(sp(mask=IGNORE_ATTITUDE | 0b001), sim.time_s)  # one rate ignored
    assert ap.ignored_setpoints == ignored + 1
    fly(sim, 0.2, sp(thrust=sim.config.vehicle.hover_thrust_norm))
    assert ap.mode == OFFBOARD


@pytest.mark.parametrize("guid_options", [0, 8])
def test_thrust_is_a_climb_rate_or_throttle_by_guid_options(guid_options):
    sim, _ap = airborne(guid_options)
    hover = sim.config.vehicle.hover_thrust_norm
    z0 = float(sim.state[2])
    # 0.5 holds altitude as a climb rate; the hover throttle holds it as throttle
    fly(sim, 3.0, sp(thrust=0.5 if guid_options == 0 else hover))
    assert float(sim.state[2]) == pytest.approx(z0, abs=0.15)
    fly(sim, 2.0, sp(thrust=0.75))  # climb rate: (0.75-0.5)*2*2.5 = 1.25 m/s up
    climb_m_s = -float(sim.state[5])
    if guid_options == 0:
        assert climb_m_s == pytest.approx(1.25, abs=0.2)
    else:
        assert climb_m_s > 2.0  # throttle 0.75 far above hover: accelerating up


def test_throttle_gets_an_angle_boost():
    sim, _ap = airborne(8)
    hover = sim.config.vehicle.hover_thrust_norm
    tilt = 0.3
    q = (math.cos(tilt / 2), math.sin(tilt / 2), 0.0, 0.0)  # rolled 0.3 rad
    fly(sim, 1.0, sp(thrust=hover, q=q))
    # hover throttle at a tilt: ArduCopter divides by cos(tilt), so height is (nearly) held
    assert sim.last_command.thrust_norm == pytest.approx(hover / math.cos(tilt), rel=0.03)


def test_guid_timeout_levels_and_holds_altitude_in_guided_and_setpoints_resume():
    sim, ap = airborne()
    hover = sim.config.vehicle.hover_thrust_norm
    tilt = 0.2
    q = (math.cos(tilt / 2), math.sin(tilt / 2), 0.0, 0.0)
    fly(sim, 1.0, sp(thrust=hover, q=q))  # rolled, moving east
    assert ap.mode == OFFBOARD
    fly(sim, 2.5)  # within GUID_TIMEOUT (3 s): still flying the last setpoint
    assert (ap.mode, ap.failsafe_count) == (OFFBOARD, 0)
    z0, east0_m = float(sim.state[2]), float(sim.state[1])
    fly(sim, 3.0)
    # ArduCopter's timeout: still GUIDED, levelled, climb rate 0 (counted once), no position
    # hold: the speed it had carries it on (only drag slows it)
    assert (ap.number, ap.failsafe_count) == (GUIDED, 1)
    roll, pitch, _ = quat_to_euler(sim.state[QUAT])
    assert abs(roll) < 0.02
    assert abs(pitch) < 0.02
    assert float(sim.state[2]) == pytest.approx(z0, abs=0.3)
    assert float(sim.state[1]) - east0_m > 0.5  # drifted on east: not a position hold
    fly(sim, 0.5, sp(thrust=hover))
    assert ap.mode == OFFBOARD
    assert ap.failsafe_count == 1


def test_land_loiter_and_disarm_on_touchdown():
    sim, ap = airborne()
    assert ap.set_number(LAND, sim.time_s) == Result.ACCEPTED
    fly(sim, 8.0)
    assert not ap.armed
    assert ap.custom_mode == LAND


# -- the endpoint with the ArduCopter personality -------------------------------------------


def make(guid_options: int = 0, ekf_origin_s: float = 0.0, on_offboard=None):
    sim = Simulation(config(guid_options, ekf_origin_s), seed=0)
    ep = SitlEndpoint(sim, 1, [TELEMETRY], Counters(), on_offboard=on_offboard)
    transport = RecordingTransport()
    ep.connection_made(transport)  # type: ignore[arg-type]
    return sim, ep, transport


def test_guided_takes_the_vehicle_over_and_brake_hands_it_back():
    """The lockstep gate's hand-back on ArduCopter: GUIDED is the controller's (offboard),
    the service's REQUEST_HOLD is BRAKE, its LAND at a mission's end LAND."""
    said: list[bool] = []
    _sim, ep, _ = make(on_offboard=said.append)
    peer = Peer()
    custom = mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED

    def set_mode(number: int) -> None:
        ep.datagram_received(peer.pack(peer.mav.set_mode_encode(1, custom, number)), PEER)

    set_mode(GUIDED)
    assert said == [True]
    set_mode(BRAKE)
    assert said == [True, False]
    set_mode(GUIDED)
    set_mode(LAND)
    assert said == [True, False, True, False]


def test_nothing_but_heartbeat_until_asked_and_no_odometry():
    sim, ep, transport = make()
    for _ in range(400):  # 2 s
        sim.advance_tick()
        ep.emit()
    kinds = {m.get_type() for batch in emitted(ep, transport) for m in batch}
    assert kinds == {"HEARTBEAT"}
    hb = next(m for batch in emitted(ep, transport) for m in batch)
    assert (hb.autopilot, hb.custom_mode) == (3, STABILIZE)
    peer = Peer()
    for msg_id, result in ((mavlink.MAVLINK_MSG_ID_ATTITUDE_QUATERNION, 0),
                           (mavlink.MAVLINK_MSG_ID_ODOMETRY, 2)):  # fmt: skip
        ep.datagram_received(
            peer.pack(peer.mav.command_long_encode(1, 1, 511, 0, msg_id, 5000, 0, 0, 0, 0, 0)),
            PEER,
        )
        ack = [m for m in peer.decode(transport) if m.get_type() == "COMMAND_ACK"][-1]
        assert ack.result == result
    transport.sent.clear()
    for _ in range(40):
        sim.advance_tick()
        ep.emit()
    sent = [m.get_type() for batch in emitted(ep, transport) for m in batch]
    assert sent.count("ATTITUDE_QUATERNION") == 40  # 200 Hz, as asked
    assert "ODOMETRY" not in sent


def ask(ep: SitlEndpoint, peer: Peer, command: int, *params: float) -> None:
    msg = peer.mav.command_long_encode(1, 1, command, 0, *params, *[0.0] * (7 - len(params)))
    ep.datagram_received(peer.pack(msg), PEER)


def heartbeats(ep: SitlEndpoint, transport: RecordingTransport) -> list[int]:
    """The custom_mode of each HEARTBEAT sent to telemetry, in order."""
    return [m.custom_mode for t in emitted(ep, transport) for m in t
            if m.get_type() == "HEARTBEAT"]  # fmt: skip


def test_a_mode_change_sends_a_heartbeat_at_once():
    """ArduCopter sends an extra HEARTBEAT as its mode changes (a client must not read it as
    forgery); a command that changes nothing sends none, and the 1 Hz ones go on."""
    sim, ep, transport = make()
    peer = Peer()
    for _ in range(40):
        sim.advance_tick()
        ep.emit()
    assert heartbeats(ep, transport) == [STABILIZE]  # the 1 Hz one at boot
    transport.sent.clear()
    ask(ep, peer, mavlink.MAV_CMD_DO_SET_MODE, 1, GUIDED)
    assert heartbeats(ep, transport) == [GUIDED]  # before any tick has passed
    ask(ep, peer, mavlink.MAV_CMD_DO_SET_MODE, 1, GUIDED)  # no change: no heartbeat
    mode = peer.mav.set_mode_encode(1, mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED, BRAKE)
    ep.datagram_received(peer.pack(mode), PEER)
    assert heartbeats(ep, transport) == [GUIDED, BRAKE]
    for _ in range(200):  # 1 s: the scheduled heartbeat as well
        sim.advance_tick()
        ep.emit()
    assert heartbeats(ep, transport) == [GUIDED, BRAKE, BRAKE]


def test_px4_sends_no_extra_heartbeat_on_a_mode_change():
    sim = Simulation(PX4_CFG, seed=0)
    ep = SitlEndpoint(sim, 1, [TELEMETRY], Counters())
    transport = RecordingTransport()
    ep.connection_made(transport)  # type: ignore[arg-type]
    sim.advance_tick()
    ep.emit()
    transport.sent.clear()
    ask(ep, Peer(), mavlink.MAV_CMD_DO_SET_MODE, 1, 3)  # POSCTL
    assert sim.autopilot.custom_mode != HOLD.custom_mode
    assert heartbeats(ep, transport) == []


def test_no_local_position_until_the_ekf_has_an_origin():
    assert load_sim_config().ardupilot.ekf_origin_after_boot_s == 36.0  # ArduCopter 4.8-dev
    sim, ep, transport = make(ekf_origin_s=1.0)
    peer = Peer()
    ask(ep, peer, mavlink.MAV_CMD_SET_MESSAGE_INTERVAL,
        mavlink.MAVLINK_MSG_ID_LOCAL_POSITION_NED, 10_000)  # fmt: skip
    ask(ep, peer, mavlink.MAV_CMD_SET_MESSAGE_INTERVAL, mavlink.MAVLINK_MSG_ID_ATTITUDE, 10_000)
    acks = [m.result for m in peer.decode(transport) if m.get_type() == "COMMAND_ACK"]
    assert acks == [mavlink.MAV_RESULT_ACCEPTED] * 2  # accepted, then withheld
    stamps: dict[str, list[int]] = {"LOCAL_POSITION_NED": [], "ATTITUDE": []}
    for _ in range(400):  # 2 s
        sim.advance_tick()
        ep.emit()
    for msg in (m for t in emitted(ep, transport) for m in t):
        if msg.get_type() in stamps:
            stamps[msg.get_type()].append(msg.time_boot_ms)
    assert min(stamps["ATTITUDE"]) == 5  # attitude from the first tick
    assert min(stamps["LOCAL_POSITION_NED"]) == 1000  # the origin: at once, then 100 Hz
    assert len(stamps["LOCAL_POSITION_NED"]) == 101


def test_the_lockstep_announcement_sends_no_position_before_the_ekf_origin():
    """While lockstep waits for a controller, the vehicle is announced as it streams: before
    the origin attitude only (an announced position let the service fly, and answer, on a
    position ArduCopter never sends), from the origin on with its position."""
    sim, ep, transport = make(ekf_origin_s=1.0)
    peer = Peer()
    for msg_id in (mavlink.MAVLINK_MSG_ID_LOCAL_POSITION_NED, mavlink.MAVLINK_MSG_ID_ATTITUDE):
        ask(ep, peer, mavlink.MAV_CMD_SET_MESSAGE_INTERVAL, msg_id, 10_000)

    def announced() -> set[str]:
        transport.sent.clear()
        ep.announce()
        return {m.get_type() for t in emitted(ep, transport) for m in t}

    sim.advance_tick()
    ep.emit()
    assert announced() == {"HEARTBEAT", "ATTITUDE"}
    for _ in range(200):  # to 1.005 s: the origin
        sim.advance_tick()
        ep.emit()
    assert announced() == {"HEARTBEAT", "ATTITUDE", "LOCAL_POSITION_NED"}


def test_takeoff_nan_is_denied_on_the_wire_and_params_read_and_set():
    sim, ep, transport = make()
    peer = Peer()
    ep.datagram_received(
        peer.pack(peer.mav.command_long_encode(1, 1, 176, 0, 1, 4, 0, 0, 0, 0, 0)), PEER
    )
    ep.datagram_received(
        peer.pack(peer.mav.command_long_encode(1, 1, 400, 0, 1, 0, 0, 0, 0, 0, 0)), PEER
    )
    nan = [math.nan] * 7
    ep.datagram_received(peer.pack(peer.mav.command_long_encode(1, 1, 22, 0, *nan)), PEER)
    acks = [(m.command, m.result) for m in peer.decode(transport) if m.get_type() == "COMMAND_ACK"]
    assert acks == [(176, 0), (400, 0), (22, mavlink.MAV_RESULT_DENIED)]
    assert sim.autopilot.custom_mode == GUIDED
    transport.sent.clear()
    ep.datagram_received(
        peer.pack(peer.mav.param_request_read_encode(1, 1, b"GUID_OPTIONS", -1)), PEER
    )
    ep.datagram_received(peer.pack(peer.mav.param_set_encode(1, 1, b"GUID_OPTIONS", 8.0, 9)), PEER)
    values = [(m.param_id, m.param_value) for m in peer.decode(transport)
              if m.get_type() == "PARAM_VALUE"]  # fmt: skip
    assert values == [("GUID_OPTIONS", 0.0), ("GUID_OPTIONS", 8.0)]
    assert isinstance(sim.autopilot, ArduCopter)
    assert sim.autopilot.ardupilot.guid_options == 8


def test_a_real_px4_dialect_flight_attempt_fails_here():
    """The old service's ritual (arm in STABILIZE, takeoff of NaNs, DO_SET_MODE(1, 6, 0))
    gets nowhere and selects RTL: the personality can catch the issue's bugs."""
    sim, ap = sim_ap()
    assert ap.arm(True, 0.0) == Result.DENIED
    assert ap.takeoff_command(math.nan, 488.0, 0.0) == Result.DENIED
    ap.set_mode_command(6, 0, 0.0)
    assert ap.custom_mode == RTL
    fly(sim, 1.0)
    assert not ap.armed
    assert np.allclose(sim.state[2], 0.0, atol=0.01)


def test_ground_station_over_tcp_gets_telemetry_and_commands_work():
    """A real TCP client on loopback, as MAVProxy connects to ArduPilot SITL's 5760: it gets
    the heartbeat, reads a parameter and sets the mode; a message split across two writes
    is still parsed (a byte stream, not datagrams)."""
    import asyncio

    from sitl.tcp import GcsTcpServer

    async def run() -> list:
        sim, ep, _ = make()
        server = GcsTcpServer(ep)
        port = await server.start("127.0.0.1", 0)
        reader, writer = await asyncio.open_connection("127.0.0.1", port)
        peer = Peer()
        await asyncio.sleep(0.05)  # the server registers the client
        ep.emit()
        msg = peer.pack(peer.mav.param_request_read_encode(1, 1, b"GUID_TIMEOUT", -1))
        writer.write(msg[:5])
        await writer.drain()
        await asyncio.sleep(0.02)
        writer.write(msg[5:] + peer.pack(peer.mav.set_mode_encode(1, 1, GUIDED)))
        await writer.drain()
        got: list = []
        for _ in range(50):
            try:
                data = await asyncio.wait_for(reader.read(4096), 0.1)
            except TimeoutError:
                continue
            got += peer.rx.parse_buffer(data) or []
            if any(m.get_type() == "PARAM_VALUE" for m in got):
                break
        assert sim.autopilot.custom_mode == GUIDED
        assert server.connections == 1
        writer.close()
        await asyncio.sleep(0.05)
        assert ep.stream_peers == {}  # the client left: nothing written to it any more
        server.close()
        return got

    got = asyncio.run(run())
    kinds = [m.get_type() for m in got]
    assert "HEARTBEAT" in kinds
    value = next(m for m in got if m.get_type() == "PARAM_VALUE")
    assert (value.param_id, value.param_value) == ("GUID_TIMEOUT", 3.0)


def test_command_line_ports_and_params(capsys):
    from sitl.main import build_parser, gcs_tcp_port, link_addresses, main

    args = build_parser().parse_args(["--instance", "2", "--autopilot", "ardupilot"])
    # ArduPilot SITL's ground station: TCP 5760 + 10 * I; no UDP 14550 for this personality
    assert gcs_tcp_port(args) == 5780
    assert link_addresses(args) == (14582, [("127.0.0.1", 14542)])
    px4 = build_parser().parse_args(["--instance", "2"])
    assert gcs_tcp_port(px4) == 0
    assert link_addresses(px4) == (14582, [("127.0.0.1", 14542), ("127.0.0.1", 14550)])
    assert main(["--listen-port", "0", "--param", "GUID_OPTIONS=8"]) == 2  # px4: none
    assert "GUID_OPTIONS" in capsys.readouterr().err
    assert main(["--autopilot", "ardupilot", "--listen-port", "0", "--param", "NOPE=1"]) == 2
    assert main(["--autopilot", "ardupilot", "--listen-port", "0", "--param", "GUID_OPTIONS"]) == 2
    assert "NAME=VALUE" in capsys.readouterr().err


def test_link_autopilot_is_validated_naming_the_key(tmp_path):
    from epc_offboard.common.configio import ConfigError
    from epc_offboard.service.config import load_service_config

    path = tmp_path / "service.toml"
    path.write_text('[link]\nautopilot = "apm"\n')
    with pytest.raises(ConfigError, match=r"link\.autopilot") as info:
        load_service_config(path)
    assert str(path) in str(info.value)
    path.write_text('[link]\nautopilot = "ardupilot"\nurl = "tcp://127.0.0.1:5762"\n')
    assert load_service_config(path).link.autopilot == "ardupilot"


def test_guided_position_control_flies_the_circle_as_accurately_as_arducopter():
    """Real ArduCopter flies the sim circle (1.5 m, 8 s) in GUIDED at 6.7-7.3 cm RMSE from
    position, velocity and acceleration targets; the personality must be within 2x of it
    (it was 50 cm: PX4's slow cascade, no velocity feedforward against SIH's drag)."""
    sim, ap = airborne(altitude_m=2.5)
    radius_m, omega_rad_s, ramp_s = 1.5, 2.0 * math.pi / 8.0, 3.0
    centre = sim.state[0:3] - np.array([radius_m, 0.0, 0.0])
    period_s = sim.config.sitl.lockstep_period_s
    errors_m = []
    for k in range(round(18.0 / period_s)):
        t_s = k * period_s
        ramping = t_s < ramp_s  # the angular rate ramps up over ramp_s, as the scenario's
        rate = omega_rad_s * min(t_s / ramp_s, 1.0)
        phase = omega_rad_s * (t_s * t_s / (2.0 * ramp_s) if ramping else t_s - ramp_s / 2.0)
        c, s = math.cos(phase), math.sin(phase)
        pos = centre + radius_m * np.array([c, s, 0.0])
        vel = radius_m * rate * np.array([-s, c, 0.0])
        tangential = omega_rad_s / ramp_s if ramping else 0.0
        acc = radius_m * (
            rate * rate * np.array([-c, -s, 0.0]) + tangential * np.array([-s, c, 0.0])
        )
        if k % 2 == 0:  # 100 Hz, the service's position loop
            ap.on_position_setpoint(
                PositionSetpoint(tuple(pos), tuple(vel), 0.0, tuple(acc)), sim.time_s
            )
        sim.advance_tick()
        if t_s > 6.0:
            errors_m.append(float(np.linalg.norm(sim.state[0:3] - pos)))
    rmse_m = math.sqrt(float(np.mean(np.square(errors_m))))
    assert rmse_m < 0.14


def test_a_quaternion_is_approached_critically_damped_as_input_quaternion_shapes_it():
    """AC_AttitudeControl::input_quaternion shapes the error to the quaternion asked with its
    command model: the rate asked is the error over ATC_INPUT_TC less the rate already
    closing it, the acceleration towards it jerk-limited. Both poles at -1/tc: half of a
    small step after 1.68 tc (0.25 s at 0.15 s), not a first-order lag's 0.69 tc (0.10 s; the
    personality was one). Setpoints wait only for the main loop (not body rates' 55 ms)."""
    sim, ap = airborne()
    hover = sim.config.vehicle.hover_thrust_norm
    fly(sim, 1.0, sp(thrust=hover))
    step_rad = 0.1
    q = (math.cos(step_rad / 2), math.sin(step_rad / 2), 0.0, 0.0)
    t0_s = sim.time_s
    rolls = []
    for _ in range(200):  # 1 s at 200 Hz
        ap.on_attitude_setpoint(sp(thrust=hover, q=q), sim.time_s)
        sim.advance_tick()
        rolls.append((sim.time_s - t0_s, quat_to_euler(sim.last_command.q_cmd_wxyz)[0]))
    half_s = next(t for t, roll in rolls if roll >= step_rad / 2)
    assert 0.22 <= half_s <= 0.30
    assert max(roll for _, roll in rolls) <= step_rad * 1.01  # critically damped: no overshoot
    assert rolls[-1][1] == pytest.approx(step_rad, abs=0.01)


def test_the_command_model_is_critically_damped_and_bounded():
    """The shaping alone: a 0.1 rad step closes as 1 - (1 + t/tc) e^(-t/tc) while linear; a
    large one is bounded by ATC_ACC_R_MAX, its acceleration's change by that over tc."""
    dt_s, tc_s, accel_max = 0.0025, 0.15, 19.2
    target, state = 0.0, (0.0, 0.0)
    for _ in range(round(0.3 / dt_s)):
        state = command_model(0.1 - target, 0.0, state, accel_max, tc_s, dt_s)
        target += state[0] * dt_s
    ideal = 1.0 - (1.0 + 0.3 / tc_s) * math.exp(-0.3 / tc_s)  # 0.594
    assert target / 0.1 == pytest.approx(ideal, abs=0.06)
    state, jerks, accels = (0.0, 0.0), [], []
    for _ in range(40):
        before = state[1]
        state = command_model(1.5, 0.0, state, accel_max, tc_s, dt_s)
        jerks.append(abs(state[1] - before) / dt_s)
        accels.append(abs(state[1]))
    assert max(accels) <= accel_max + 1e-9
    assert max(jerks) <= accel_max / tc_s + 1e-6


def test_arming_in_guided_and_armed_position_modes_wait_for_the_ekf_origin():
    """AP_Arming_Copter's mandatory position check: GUIDED needs a position, so arming is
    refused until the EKF has an origin (GUIDED_NOGPS does not need one); armed, GUIDED,
    LOITER, BRAKE and RTL are refused without a position, LAND is not."""
    sim = Simulation(config(ekf_origin_s=2.0), seed=0)
    ap = sim.autopilot
    assert isinstance(ap, ArduCopter)
    assert ap.set_number(GUIDED, 0.0) == Result.ACCEPTED  # disarmed: any mode
    assert ap.arm(True, 0.0) == Result.DENIED
    assert ap.status_text == "PreArm: Need Position Estimate"
    assert ap.set_number(GUIDED_NOGPS, 0.0) == Result.ACCEPTED
    assert ap.arm(True, 0.0) == Result.ACCEPTED
    for number in (GUIDED, LOITER, BRAKE, RTL):
        assert ap.set_number(number, 1.0) == Result.DENIED
        assert ap.number == GUIDED_NOGPS
    assert ap.set_number(GUIDED, 2.0) == Result.ACCEPTED  # the origin: a position
    assert ap.arm(False, 2.0) == Result.ACCEPTED
    assert ap.arm(True, 2.0) == Result.ACCEPTED


def test_climb_rate_scale_is_wp_spd_up_and_dn():
    """SET_ATTITUDE_TARGET's thrust as a climb rate is scaled by WP_SPD_UP / WP_SPD_DN (the
    waypoint navigator's default speeds), which the personality names and lets be set."""
    _sim, ap = sim_ap()
    names = dict(ap.parameters())
    assert (names["WP_SPD_UP"], names["WP_SPD_DN"]) == (2.5, 1.5)
    assert "PILOT_SPEED_UP" not in names


def test_loiter_follows_the_pilots_stick_and_brake_holds_altitude():
    """ModeLoiter's climb rate is the pilot's throttle stick's: ArduCopter SITL's simulated
    RC sits at the bottom, and a real ArduCopter 4.8-dev SITL put in LOITER by the service's
    hold descended at full PILOT_SPD_UP and hit the ground at 2.49 m/s 1.9 s later. BRAKE
    holds position and altitude whatever the sticks say; mid stick, LOITER holds too."""
    for number, stick, expect_m in ((LOITER, 0.0, -0.5), (BRAKE, 0.0, 0.0), (LOITER, 0.5, 0.0)):
        sim, ap = airborne(altitude_m=3.0)
        ap.ardupilot = dataclasses.replace(ap.ardupilot, rc_throttle_norm=stick)
        z0_m = -float(sim.state[2])
        assert ap.set_number(number, sim.time_s) == Result.ACCEPTED
        fly(sim, 1.0)
        change_m = -float(sim.state[2]) - z0_m
        if expect_m < 0.0:
            assert change_m < expect_m, (number, stick, change_m)  # descending
        else:
            assert abs(change_m) < 0.1, (number, stick, change_m)
