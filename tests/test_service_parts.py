"""The service's parts that decide, one at a time: which reference a position tick flies
(``ReferenceSelector``: pure, and a planner's live reference over real Zenoh on loopback),
what the attitude loop puts on the wire (``SetpointSender``: a real MAVLink link over UDP to a
socket of this test, decoded by pymavlink) and what the supervisor does with the state
machine's phases (``Supervisor``, with systemd's notify socket for real). Each test names the
branch a swap would break."""

from __future__ import annotations

import asyncio
import contextlib
import dataclasses
import json
import socket
import time
from collections import Counter
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import zenoh
from pymavlink.dialects.v20 import common as mavlink

from epc_offboard.common import frames
from epc_offboard.common.logsetup import LogGate
from epc_offboard.common.ports import free_port
from epc_offboard.control.cascade import Cascade
from epc_offboard.control.trajectories import TrajectoryConfig
from epc_offboard.control.types import PositionOutput, VehicleState
from epc_offboard.fleet import keys
from epc_offboard.fleet.sharing import FleetSharing
from epc_offboard.fleet.wire import ReferenceMessage, encode_reference
from epc_offboard.service.autopilot import Autopilot
from epc_offboard.service.clock import WallClock
from epc_offboard.service.config import ServiceConfig, load_service_config
from epc_offboard.service.reference_selector import ReferenceSelector
from epc_offboard.service.setpoints import SetpointSender
from epc_offboard.service.supervisor import Supervisor
from epc_offboard.service.systemd import Systemd
from epc_offboard.vehicle.commands import IGNORE_ATTITUDE, IGNORE_RATES
from epc_offboard.vehicle.offboard import Outputs, Phase
from epc_offboard.vehicle.state import StateTracker
from tests.test_sharing import FLEET, endpoint
from tests.test_sharing import config as sharing_config

SITL_CONFIG = Path(__file__).resolve().parent.parent / "config" / "sitl.toml"
CFG = load_service_config(SITL_CONFIG)


def _state(pos=(0.0, 0.0, -2.5), vel=(0.0, 0.0, 0.0), t_s: float = 10.0) -> VehicleState:
    return VehicleState(
        time_s=t_s,
        pos_ned_m=np.array(pos, dtype=float),
        vel_ned_m_s=np.array(vel, dtype=float),
        q_ned_frd=frames.euler_to_quat(0.0, 0.0, 0.0),
        rate_frd_rad_s=np.zeros(3),
        position_age_s=0.0,
        attitude_age_s=0.0,
    )


# -- ReferenceSelector --------------------------------------------------------------------------


def _selector(shape: str = "circle", altitude_m: float | None = None) -> ReferenceSelector:
    traj = TrajectoryConfig(shape=shape, radius_m=2.0, period_s=10.0)  # type: ignore[arg-type]
    return ReferenceSelector(CFG.position, traj, altitude_m, 0.5, Counter())


def test_before_offboard_the_reference_holds_where_the_vehicle_is_now_not_where_it_was():
    sel = _selector()
    sel.horizon(_state(pos=(0.0, 0.0, -2.0)), 1.0, None, offboard=False)
    ref = sel.horizon(_state(pos=(0.1, 0.2, -2.45)), 1.1, None, offboard=False)
    # every stage holds the newest position, at rest (a stale hold dropped the vehicle)
    np.testing.assert_allclose(ref.pos_ned_m, np.tile([0.1, 0.2, -2.45], (len(ref.pos_ned_m), 1)))
    np.testing.assert_allclose(ref.vel_ned_m_s, 0.0)
    assert len(ref.pos_ned_m) == CFG.position.reference_steps + 1  # the horizon past the dead time


def test_once_offboard_the_trajectory_is_flown_and_its_anchor_kept():
    sel = _selector()
    state = _state(pos=(1.0, -1.0, -2.5))
    sel.start_trajectory(state, None, now_s=0.0)
    late = sel.horizon(state, 30.0, None, offboard=True)  # well past the rejoin and the ramp
    assert sel.rejoin is None  # done: the trajectory itself from here
    # on the circle of radius 2 m about its centre, at the anchor's altitude; not the hold
    assert late.pos_ned_m[0][2] == pytest.approx(-2.5)
    assert not np.allclose(late.pos_ned_m[0], [1.0, -1.0, -2.5])
    assert float(np.linalg.norm(late.vel_ned_m_s[0])) > 0.5
    # a later hold (the position stream going stale before offboard) does not replace it
    again = sel.horizon(_state(pos=(5.0, 5.0, -1.0)), 30.0, None, offboard=False)
    np.testing.assert_allclose(again.pos_ned_m, late.pos_ned_m)


def test_the_trajectory_starts_at_its_altitude_above_home_through_a_rejoin():
    sel = _selector(shape="hover", altitude_m=2.5)
    # 1.5 m above home (NED down -1.5 at home level 0): the anchor goes 1 m higher
    state = _state(pos=(0.0, 0.0, -1.5))
    sel.start_trajectory(state, altitude_m=1.5, now_s=0.0)
    assert sel.trajectory is not None
    np.testing.assert_allclose(sel.trajectory.anchor_ned_m, [0.0, 0.0, -2.5])
    first = sel.horizon(state, 0.0, None, offboard=True)
    # the reference starts where the vehicle is (no step), and closes the gap over time
    assert first.pos_ned_m[0][2] == pytest.approx(-1.5, abs=1e-6)
    assert first.pos_ned_m[-1][2] < -1.5
    assert sel.counters["trajectory_rejoins"] == 1
    settled = sel.horizon(state, 20.0, None, offboard=True)
    assert settled.pos_ned_m[0][2] == pytest.approx(-2.5, abs=1e-3)


def test_a_re_entry_at_speed_closes_its_gap_within_half_the_entry_budget():
    """Re-entering offboard at 1.3 m/s against a circle running the other way: the rejoin
    slows (a longer time constant) until its gap asks for at most half of
    ``entry_max_acc_m_s2``; the fixed 1 s asked for 5 m/s^2, the entry ramp would not fly it
    and the vehicle overshot the reference by 3.9 m (a loaded soak)."""
    sel = _selector()
    sel.start_trajectory(_state(), None, now_s=0.0)
    traj_now = sel.trajectory.sample(7.5)  # type: ignore[union-attr]
    vel = -traj_now.vel_ned_m_s  # flying the other way, at the circle's speed
    assert float(np.linalg.norm(vel)) > 1.0
    sel.start_rejoin(_state(pos=tuple(traj_now.pos_ned_m), vel=tuple(vel), t_s=7.5), 7.5)
    assert sel.rejoin is not None
    budget = 0.5 * CFG.position.entry_max_acc_m_s2
    assert sel.rejoin.max_acc_m_s2() <= budget
    assert sel.rejoin.tau_s > sel.trajectory_cfg.rejoin_tau_s
    first = sel.horizon(_state(pos=tuple(traj_now.pos_ned_m), vel=tuple(vel)), 7.5, None,
                        offboard=True)  # fmt: skip
    np.testing.assert_allclose(first.vel_ned_m_s[0][:2], vel[:2], atol=1e-9)  # bumpless


def test_the_mission_is_complete_only_after_its_duration_on_the_trajectory():
    sel = _selector()
    assert not sel.mission_complete(100.0, 10.0)  # no trajectory yet
    sel.start_trajectory(_state(), None, now_s=5.0)
    assert not sel.mission_complete(14.9, 10.0)
    assert sel.mission_complete(15.0, 10.0)
    assert not sel.mission_complete(1e6, 0.0)  # 0: no end


def test_a_fresh_live_reference_is_flown_in_offboard_only_and_a_stale_one_hands_back():
    """A planner's live reference, over real Zenoh on loopback to the fleet helper: it
    overrides the trajectory under offboard (never before: the autopilot may still be
    climbing out of its takeoff); once older than the timeout the trajectory is back, and the
    hand-back is counted."""

    async def main() -> None:
        port, planner_port = free_port(), free_port()
        planner = zenoh.Config()
        planner.insert_json5("connect/endpoints", json.dumps([endpoint(port)]))
        planner.insert_json5("listen/endpoints", json.dumps([endpoint(planner_port)]))
        planner.insert_json5("scouting/multicast/enabled", "false")
        sel, state = _selector(), _state()
        sel.start_trajectory(state, None, now_s=0.0)
        flown = sel.horizon(state, 30.0, None, offboard=True)
        cfg = sharing_config("a", port, [], enabled=False)
        async with FleetSharing(cfg, [], share_library=False, reference=True) as fleet:
            msg = ReferenceMessage((1.0, 2.0, -3.0), None, 0.25)
            with zenoh.open(planner) as session:
                while fleet.live_reference(time.monotonic(), 0.5) is None:
                    session.put(keys.reference_key(FLEET, "a"), encode_reference(msg))
                    await asyncio.sleep(0.05)
            before = sel.horizon(state, 30.0, fleet, offboard=False)
            np.testing.assert_allclose(before.stages, flown.stages)
            live = sel.horizon(state, 30.0, fleet, offboard=True)
            np.testing.assert_allclose(live.pos_ned_m[0], [1.0, 2.0, -3.0], atol=1e-9)
            assert live.yaw_rad[0] == pytest.approx(0.25)
            assert sel.counters["live_reference_stale"] == 0
            await asyncio.sleep(0.6)  # older than the selector's 0.5 s
            back = sel.horizon(state, 30.0, fleet, offboard=True)
            np.testing.assert_allclose(back.stages, flown.stages)
            assert sel.counters["live_reference_stale"] == 1

    asyncio.run(asyncio.wait_for(main(), 60.0))


# -- SetpointSender -----------------------------------------------------------------------------


class _Wire:
    """A UDP socket the service's link sends to; what arrives, decoded."""

    def __init__(self) -> None:
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.bind(("127.0.0.1", 0))
        self.sock.setblocking(False)
        self.port = self.sock.getsockname()[1]
        self.codec = mavlink.MAVLink(None)

    async def messages(self, kind: str, count: int = 1) -> list[Any]:
        out: list[Any] = []
        for _ in range(200):
            try:
                data = self.sock.recv(65536)
            except BlockingIOError:
                await asyncio.sleep(0.01)
                continue
            out += [m for m in self.codec.parse_buffer(data) or [] if m.get_type() == kind]
            if len(out) >= count:
                return out
        raise AssertionError(f"{kind}: {len(out)} of {count} arrived")


def _target(state: VehicleState, cascade: Cascade, *, thrust: float = 0.55) -> PositionOutput:
    out = cascade.hover(state)
    return dataclasses.replace(out, thrust_norm=thrust)


async def _sender(mode: str) -> tuple[SetpointSender, Autopilot, _Wire, Counter[str]]:
    wire = _Wire()
    cfg = dataclasses.replace(
        CFG,
        link=dataclasses.replace(CFG.link, url=f"udpout://127.0.0.1:{wire.port}", autopilot="px4"),
        attitude=dataclasses.replace(CFG.attitude, mode=mode),  # type: ignore[arg-type]
    )
    counters: Counter[str] = Counter()
    autopilot = Autopilot(cfg, WallClock(), StateTracker(system_id=1), counters, LogGate())
    await autopilot.link.open()
    cascade = Cascade(cfg.position, cfg.attitude, cfg.estimator, 0.01)
    errors: list[Exception] = []
    sender = SetpointSender(cascade, autopilot, cfg.vehicle.max_rate_frd_rad_s, counters,
                            lambda loop, exc: errors.append(exc))  # fmt: skip
    return sender, autopilot, wire, counters


def _rates_flown(msg: Any) -> bool:
    """Whether a SET_ATTITUDE_TARGET carries body rates (else the attitude quaternion)."""
    if msg.type_mask & IGNORE_RATES == IGNORE_RATES:
        return False
    assert msg.type_mask & IGNORE_ATTITUDE == IGNORE_ATTITUDE
    return True


Act = Callable[[SetpointSender, VehicleState], None]


async def _send(mode: str, act: Act, kind: str = "SET_ATTITUDE_TARGET") -> tuple[Any, Counter[str]]:
    """What one call of the sender (``act``) puts on the wire, and the counters after it."""
    sender, autopilot, wire, counters = await _sender(mode)
    try:
        act(sender, _state(pos=(1.0, 2.0, -3.0)))
        (msg,) = await wire.messages(kind)
        return msg, counters
    finally:
        autopilot.link.close()
        wire.sock.close()


def _fly(target: Callable[[PositionOutput], PositionOutput] = lambda t: t, **kwargs: Any) -> Act:
    """Send the attitude setpoint of a hover target (changed by ``target``) at tick 10 s."""
    return lambda sender, state: sender.attitude(
        state, target(_target(state, sender.cascade)), 10.0, **kwargs
    )


def test_an_on_time_tick_in_the_envelope_flies_body_rates():
    msg, counters = asyncio.run(_send("epc", _fly()))
    assert _rates_flown(msg)
    assert msg.target_system == CFG.link.target_system
    assert msg.thrust == pytest.approx(0.55, abs=1e-6)  # PX4: thrust as sent
    assert not counters["attitude_late_fallbacks"]


def test_a_late_tick_sends_the_attitude_not_stale_rates():
    msg, counters = asyncio.run(_send("epc", _fly(late=True)))
    assert not _rates_flown(msg)
    np.testing.assert_allclose(msg.q, frames.euler_to_quat(0.0, 0.0, 0.0), atol=1e-6)
    assert counters["attitude_late_fallbacks"] == 1


def test_attitude_mode_autopilot_always_sends_the_attitude_and_counts_no_fallback():
    msg, counters = asyncio.run(_send("autopilot", _fly()))
    assert not _rates_flown(msg)
    assert not counters["attitude_late_fallbacks"]
    assert not counters["attitude_envelope_fallbacks"]


def test_a_target_beyond_the_rate_envelope_is_left_to_the_autopilots_attitude_loop():
    far_rad = np.radians(CFG.attitude.rates_max_error_deg + 20.0)
    tilted = _fly(lambda t: dataclasses.replace(t, q_target=frames.euler_to_quat(far_rad, 0, 0)))
    msg, counters = asyncio.run(_send("epc", tilted))
    assert not _rates_flown(msg)
    assert counters["attitude_envelope_fallbacks"] == 1


def test_a_non_finite_target_never_reaches_the_wire():
    msg, counters = asyncio.run(
        _send("epc", _fly(lambda t: dataclasses.replace(t, thrust_norm=float("nan"))))
    )
    assert np.all(np.isfinite([*msg.q, msg.thrust, msg.body_roll_rate]))
    assert not _rates_flown(msg)  # level at hover thrust
    assert counters["non_finite_setpoints_replaced"] == 1


def test_the_px4_baseline_sends_the_reference_now_to_the_position_controller():
    """Position, velocity and acceleration of the reference's stage 0, each in its field: on
    a circle flown at speed all three differ (velocity along it, acceleration to its centre)."""
    sel = _selector()
    sel.start_trajectory(_state(), None, now_s=0.0)
    ref = sel.now(_state(), 20.0)

    def send(sender: SetpointSender, state: VehicleState) -> None:
        sender.position_target(state, ref)

    msg, _ = asyncio.run(_send("epc", send, "SET_POSITION_TARGET_LOCAL_NED"))
    assert float(np.linalg.norm(ref.vel_ned_m_s[0])) > 0.5
    assert float(np.linalg.norm(ref.acc_ned_m_s2[0])) > 0.3
    np.testing.assert_allclose([msg.x, msg.y, msg.z], ref.pos_ned_m[0], atol=1e-5)
    np.testing.assert_allclose([msg.vx, msg.vy, msg.vz], ref.vel_ned_m_s[0], atol=1e-5)
    np.testing.assert_allclose([msg.afx, msg.afy, msg.afz], ref.acc_ned_m_s2[0], atol=1e-5)
    assert msg.coordinate_frame == mavlink.MAV_FRAME_LOCAL_NED


# -- Supervisor ---------------------------------------------------------------------------------


@pytest.fixture
def notify_socket(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Iterator[socket.socket]:
    """systemd's notify socket, for real: what the supervisor tells systemd arrives here."""
    sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    sock.bind(str(tmp_path / "notify"))
    sock.setblocking(False)
    monkeypatch.setenv("NOTIFY_SOCKET", str(tmp_path / "notify"))
    yield sock
    sock.close()


def _told(sock: socket.socket) -> list[str]:
    out = []
    with contextlib.suppress(BlockingIOError):
        while True:
            out.append(sock.recv(4096).decode())
    return out


def _supervisor(cfg: ServiceConfig) -> tuple[Supervisor, asyncio.Event, list[int], Counter[str]]:
    counters: Counter[str] = Counter()
    tracker = StateTracker(system_id=1)
    autopilot = Autopilot(cfg, WallClock(), tracker, counters, LogGate())
    stopping = asyncio.Event()
    writes: list[int] = []
    sup = Supervisor(cfg, WallClock(), tracker, autopilot, Systemd(0.5), counters, stopping,
                     lambda: writes.append(1))  # fmt: skip
    return sup, stopping, writes, counters


def _outputs(phase: Phase, reason: str = "because") -> Outputs:
    return Outputs(phase, False, (), reason)


def test_a_failsafe_is_counted_told_and_kept_and_other_phases_are_not_failsafes(
    notify_socket: socket.socket,
) -> None:
    sup, _, _, counters = _supervisor(CFG)
    sup._phase_changed(1.0, _outputs(Phase.OFFBOARD, "offboard confirmed"))
    assert counters["failsafes"] == 0
    sup._phase_changed(2.0, _outputs(Phase.FAILSAFE, "state stale"))
    assert counters["failsafes"] == 1
    assert [e["phase"] for e in sup.phase_events] == ["offboard", "failsafe"]
    assert sup.phase_events[-1] == {"t_s": 2.0, "phase": "failsafe", "reason": "state stale"}
    assert _told(notify_socket) == ["STATUS=offboard: offboard confirmed",
                                    "STATUS=failsafe: state stale"]  # fmt: skip


def test_at_the_missions_end_the_service_stops_unless_it_lingers_for_the_fleet():
    sup, stopping, writes, _ = _supervisor(CFG)
    sup._mission_over()
    assert stopping.is_set()
    assert not writes
    lingering = dataclasses.replace(
        CFG, mission=dataclasses.replace(CFG.mission, linger_after_landing=True)
    )
    sup, stopping, writes, _ = _supervisor(lingering)
    sup._mission_over()
    sup._mission_over()  # the next supervisor step: once only
    assert not stopping.is_set()
    assert writes == [1]  # the flight's figures written at once


def test_a_link_gone_silent_is_a_lost_heartbeat_and_nothing_is_commanded(
    notify_socket: socket.socket,
) -> None:
    """One heartbeat: the state machine waits for state. Then nothing more arrives for longer
    than the heartbeat timeout: it has no heartbeat again (whatever the tracker last saw),
    commands nothing, and systemd is not told READY (no state ever flowed)."""
    sup, stopping, _, _ = _supervisor(CFG)
    codec = mavlink.MAVLink(None, srcSystem=1, srcComponent=1)
    frame = codec.heartbeat_encode(mavlink.MAV_TYPE_QUADROTOR, mavlink.MAV_AUTOPILOT_PX4, 0,
                                   (4 << 16) | (3 << 24), mavlink.MAV_STATE_STANDBY).pack(codec)
    sup.autopilot.on_message(codec.decode(bytearray(frame)))
    now = time.monotonic()
    assert sup.step(now, mission_complete=False).outputs.phase == Phase.WAIT_STATE
    sup.autopilot.last_rx_wall_s = now - 2.0 * CFG.offboard.heartbeat_timeout_s
    step = sup.step(now + 0.05, mission_complete=False)
    assert step.outputs.phase == Phase.WAIT_HEARTBEAT
    assert not step.outputs.actions
    assert sup.sm.takeoffs_sent == 0  # (stream rates were asked for: not a flight command)
    assert "READY=1" not in _told(notify_socket)
    assert not stopping.is_set()


def test_the_command_dead_time_is_decided_when_the_dialect_is_adopted_not_each_tick():
    """link.autopilot and attitude.mode "auto": until a heartbeat names the autopilot, PX4's
    body rates (0.05 s of command dead time); ArduPilot's heartbeat makes it quaternion mode, whose
    0.2 s the position loop flies from then on, without a position tick asking again."""
    from epc_offboard.service.service import Service

    cfg = dataclasses.replace(
        CFG, link=dataclasses.replace(CFG.link, autopilot="auto"),
        attitude=dataclasses.replace(CFG.attitude, mode="auto"),
        log=dataclasses.replace(CFG.log, flight_log_path="", tlog_path=""),
    )  # fmt: skip
    service = Service(cfg)
    position = service.cascade.position
    assert position.dead_time.dead_time_s == pytest.approx(0.05)
    codec = mavlink.MAVLink(None, srcSystem=1, srcComponent=1)
    frame = codec.heartbeat_encode(mavlink.MAV_TYPE_QUADROTOR, mavlink.MAV_AUTOPILOT_ARDUPILOTMEGA,
                                   0, 4, mavlink.MAV_STATE_STANDBY).pack(codec)  # fmt: skip
    service.autopilot.on_message(codec.decode(bytearray(frame)))
    assert position.dead_time.dead_time_s == pytest.approx(0.2)
    assert service.autopilot.attitude_path == ("ardupilot", "autopilot")


def test_while_the_rate_gate_suspends_body_rates_the_position_loop_flies_the_quaternion_dead_time():
    """PX4 body rates: 0.05 s of command dead time. When the rate model's gate suspends body rates,
    PX4's attitude loop answers the position loop's commands 0.275 s late: the position loop
    flies quaternion mode's dead time (0.15 s) until body rates fly again (ardu-rates found
    the fallback planned as body rates, tilted to 76 deg)."""
    from epc_offboard.service.service import Service

    cfg = dataclasses.replace(
        CFG, link=dataclasses.replace(CFG.link, autopilot="px4"),
        attitude=dataclasses.replace(CFG.attitude, mode="epc"),
        position=dataclasses.replace(CFG.position, command_dead_time_s=None),
        log=dataclasses.replace(CFG.log, flight_log_path="", tlog_path=""),
    )  # fmt: skip
    service = Service(cfg)
    position = service.cascade.position
    gate = service.cascade.attitude.gate
    state = VehicleState(
        time_s=10.0, pos_ned_m=np.array([0.0, 0.0, -2.5]), vel_ned_m_s=np.zeros(3),
        q_ned_frd=np.array([1.0, 0.0, 0.0, 0.0]), rate_frd_rad_s=np.zeros(3),
        position_age_s=0.0, attitude_age_s=0.0,
    )  # fmt: skip
    service._position_tick(state, 10.0)
    assert position.dead_time.dead_time_s == pytest.approx(0.05)
    for k in range(gate.min_checks + 1):  # the rates measured far from the model's
        gate.check(10.0 + 0.005 * k, np.full(3, 3.0), np.full(3, 0.1))
    assert not gate.use_rates(10.1)
    service._position_tick(dataclasses.replace(state, time_s=10.1), 10.1)
    assert position.dead_time.dead_time_s == pytest.approx(0.15)
    later = gate.until_s + 0.01  # the hold over: body rates on probation
    service._position_tick(dataclasses.replace(state, time_s=later), later)
    assert position.dead_time.dead_time_s == pytest.approx(0.05)
    assert service.counters["position_dead_time_switches"] == 2


def test_ready_is_marked_before_the_phase_the_same_step_starts(
    notify_socket: socket.socket, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The heartbeat in first, then the first state: one supervisor step sees both and leaves
    for preflight. systemd's READY and the start-up's "ready" milestone come before that
    phase's (the cold-start flight test saw "preflight" before "ready" when the heartbeat
    happened to arrive first: the milestones' order is part of stats.json)."""
    from epc_offboard.service import supervisor as supervisor_module
    from epc_offboard.service.startup import Timeline

    timeline = Timeline()
    monkeypatch.setattr(supervisor_module, "TIMELINE", timeline)
    sup, _, _, _ = _supervisor(CFG)
    codec = mavlink.MAVLink(None, srcSystem=1, srcComponent=1)
    frames = [
        codec.heartbeat_encode(mavlink.MAV_TYPE_QUADROTOR, mavlink.MAV_AUTOPILOT_PX4, 0,
                               (4 << 16) | (3 << 24), mavlink.MAV_STATE_STANDBY),
        codec.attitude_quaternion_encode(1000, 1.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0),
        codec.local_position_ned_encode(1000, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0),
    ]  # fmt: skip
    for msg in frames:
        sup.autopilot.on_message(codec.decode(bytearray(msg.pack(codec))))
    step = sup.step(time.monotonic(), mission_complete=False)
    assert step.outputs.phase == Phase.PREFLIGHT
    marks = list(timeline.report()["milestones"])
    assert marks == ["ready", "preflight"], marks
    assert _told(notify_socket)[0] == "READY=1"


def test_a_fleet_turn_waits_for_room_between_the_loops_ticks():
    """A turn of the library-sharing task (candidates, publications, snapshots: 2-3 ms of
    the loops' thread, up to 7) started whenever its sleep ended and came between two ticks
    due: 100 of 135 position-loop gaps over 12 ms beside bench --attack (issue 21). It waits
    for ``Loops.room`` before any of its work."""
    from epc_offboard.fleet.sharing import FleetSharing

    class Waited(Exception):  # noqa: N818 - the room was asked first
        pass

    async def room() -> None:
        raise Waited

    fleet = FleetSharing(sharing_config("a", free_port(), [], enabled=False), [],
                         share_library=False, reference=True, room=room)  # fmt: skip
    with pytest.raises(Waited):
        asyncio.run(fleet.run())
    assert fleet.counters["helper_restarts"] == 0  # no turn's work ran before it


def _fleet_turn_offers(monkeypatch: pytest.MonkeyPatch,
                       ahead_s: float | None) -> list[object]:  # fmt: skip
    """A fleet turn's ten candidates waiting, offered by ``run``: the events, in order
    ("room" asked, then each ``_offer``'s count); ``room`` gives the deadline ``ahead_s``
    from now (None: none, as in lockstep)."""
    from epc_offboard.fleet.sharing import FleetSharing

    class Done(Exception):  # noqa: N818 - the test's end
        pass

    events: list[object] = []

    async def room() -> float | None:
        events.append("room")
        if events.count("room") > 12:
            raise Done
        return None if ahead_s is None else time.monotonic() + ahead_s

    fleet = FleetSharing(sharing_config("a", free_port(), [], enabled=False), [],
                         share_library=False, reference=True, room=room)  # fmt: skip
    # no helper: the turn's candidates are these, read before
    monkeypatch.setattr(fleet, "poll", lambda now_s, deadline_s=None: 0)
    fleet._to_offer = np.zeros(10, dtype=fleet.candidate_dtype)

    def offer(records: np.ndarray) -> int:
        events.append(len(records))
        return 0

    monkeypatch.setattr(fleet, "_offer", offer)
    with pytest.raises(Done):
        asyncio.run(fleet.run())
    return events


def test_a_fleet_turn_offers_its_candidates_a_slice_at_a_time_with_room_between(monkeypatch):
    """A turn's candidates (ten at 200 a second) offered at once took the loops' thread 2-6
    ms, the longest step of most turns beside bench --attack's replay (issue 21, the event
    loop's steps timed). They are offered a few at a time, each slice after ``Loops.room``
    (with no deadline, lockstep's: a count)."""
    from epc_offboard.fleet import sharing as sharing_module

    events = _fleet_turn_offers(monkeypatch, None)
    per = sharing_module._OFFERS_PER_SLICE
    sizes = [e for e in events if isinstance(e, int)]
    assert sizes == [per] * (10 // per) + ([10 % per] if 10 % per else [])
    assert all(events[i - 1] == "room" for i, e in enumerate(events) if isinstance(e, int))


@pytest.mark.parametrize("ahead_s", [-1.0, 60.0])
def test_a_fleet_slice_offers_candidates_until_its_deadline(monkeypatch, ahead_s: float) -> None:
    """Issue 21: three candidates a slice still took the loops' thread up to 10 ms in one
    step beside two hogs (stop 37's bench --attack, before late ticks): a count is no
    bound on time. A slice now offers one candidate at a time until the deadline
    ``Loops.room`` gives has passed: a deadline already past, one a slice; one far off,
    all in the first (counted, not timed)."""
    events = _fleet_turn_offers(monkeypatch, ahead_s)
    sizes = [e for e in events if isinstance(e, int)]
    assert sizes == [1] * 10
    if ahead_s < 0:  # each slice after its own room
        assert all(events[i - 1] == "room" for i, e in enumerate(events) if isinstance(e, int))
    else:
        assert events[2:12] == [1] * 10  # the turn's room, the slice's, then all


def test_a_publication_is_handed_over_a_frame_a_slice_by_its_deadline():
    """Issue 21: a publication's frames (up to 512 controllers each) were all pickled and
    written in the one step that queued them. Handed over until a deadline: one past, one
    frame a call; none (lockstep, a shutdown), all."""
    from epc_offboard.fleet.sharing import _FRAME_ENTRIES, PublishBacklog

    entries = [object()] * (3 * _FRAME_ENTRIES)
    sent: list[int] = []

    def send(frame: tuple[Any, ...]) -> bool:
        sent.append(len(frame[2]))
        return True

    backlog = PublishBacklog(10 * _FRAME_ENTRIES)
    backlog.add(0, entries)  # type: ignore[arg-type]
    past = time.monotonic() - 1.0
    assert backlog.hand_off(send, past) == _FRAME_ENTRIES
    assert backlog.waiting == 2 * _FRAME_ENTRIES
    assert sent == [_FRAME_ENTRIES]
    assert backlog.hand_off(send, past) == _FRAME_ENTRIES
    assert backlog.hand_off(send) == _FRAME_ENTRIES
    assert backlog.waiting == 0
    assert not backlog.refused
    backlog.add(0, entries)  # type: ignore[arg-type]
    assert backlog.hand_off(send, None) == 3 * _FRAME_ENTRIES
    assert backlog.hand_off(lambda frame: False) == 0


def test_sighup_reads_the_config_off_the_loops_thread_and_applies_it_on_it(tmp_path, monkeypatch):
    """Issue 21: SIGHUP's read and validation of the configuration held the loops' thread
    14-19 ms (bench --attack: a 24-27 ms position-loop gap, named by the event loop's steps
    timed). It is read in a thread of its own; what it changes is applied on the loops'
    thread, as before."""
    import threading

    from epc_offboard.service import service as service_module
    from epc_offboard.service.service import Service

    cfg = dataclasses.replace(CFG, log=dataclasses.replace(CFG.log, flight_log_path="",
                                                          tlog_path=""))  # fmt: skip
    service = Service(cfg, str(tmp_path / "service.toml"))
    read_in: list[threading.Thread] = []
    new = dataclasses.replace(cfg, mission=dataclasses.replace(cfg.mission, duration_s=123.0))

    def load(path: str) -> object:
        read_in.append(threading.current_thread())
        return new

    monkeypatch.setattr(service_module, "load_service_config", load)

    async def main() -> None:
        service._reload()
        await asyncio.gather(*service._reloads)

    asyncio.run(main())
    assert read_in
    assert read_in[0] is not threading.main_thread()
    assert service.cfg.mission.duration_s == 123.0


def test_sighups_config_is_merged_off_the_loops_thread(tmp_path, monkeypatch):
    """Issue 21: after the read moved to a thread, the reload's apply still held the loops'
    thread 5-7 ms under bench --attack: merging the new settings into the config
    (``dataclasses.replace``) validates the whole config again, the vehicle file read and
    parsed among it. The merge is made in the reader's thread; the loops' thread only
    assigns what it made."""
    import threading

    from epc_offboard.service import config as config_module
    from epc_offboard.service.service import Service

    cfg = dataclasses.replace(CFG, log=dataclasses.replace(CFG.log, flight_log_path="",
                                                          tlog_path=""))  # fmt: skip
    path = tmp_path / "service.toml"
    path.write_text(SITL_CONFIG.read_text().replace(
        "[trajectory]", "[trajectory]\nperiod_s = 17.0", 1))  # fmt: skip
    service = Service(cfg, str(path))
    airframe_read_in: list[threading.Thread] = []
    load_airframe = config_module.load_airframe  # type: ignore[attr-defined]

    def counted(file: str) -> Any:
        airframe_read_in.append(threading.current_thread())
        return load_airframe(file)

    monkeypatch.setattr(config_module, "load_airframe", counted)

    async def main() -> None:
        service._reload()
        await asyncio.gather(*service._reloads)

    asyncio.run(main())
    assert service.cfg.trajectory.period_s == 17.0
    assert airframe_read_in  # the file and the merge validated...
    assert threading.main_thread() not in airframe_read_in  # ... none of it on the loops'
