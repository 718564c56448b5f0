"""Integration over real UDP on loopback, against ``python -m sitl.main`` as a subprocess."""

from __future__ import annotations

import itertools
import math

import pytest
from pymavlink.dialects.v20 import common as mavlink

from tests.sitl.mavclient import (
    MavClient,
    counters_from,
    custom_main_sub,
    start_sitl,
    stop_sitl,
)

LEVEL = (1.0, 0.0, 0.0, 0.0)
ARM = mavlink.MAV_CMD_COMPONENT_ARM_DISARM
SET_MODE = mavlink.MAV_CMD_DO_SET_MODE
CUSTOM = mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED


@pytest.fixture
def client():
    c = MavClient()
    yield c
    c.close()


def is_mode(main, sub=0):
    return lambda m: m.get_type() == "HEARTBEAT" and custom_main_sub(m) == (main, sub)


def test_offboard_flight_with_failsafe_to_hold(client):
    """Discover, arm, take off, stream, enter offboard, climb, go silent -> AUTO.LOITER."""
    # --speedup paces the phases without a controller (before the stream, after silence)
    # (250 ms: this Python client answers each tick; on a loaded machine it was once more
    # than 20 ms late, a slow answer the SITL rightly counted)
    proc = start_sitl(
        client, "--lockstep", "--lockstep-timeout-ms", "250", "--seed", "1", "--speedup", "4"
    )
    try:
        hb = client.wait("HEARTBEAT", timeout_s=10)
        assert hb.get_srcSystem() == 1
        assert hb.type == mavlink.MAV_TYPE_QUADROTOR
        assert hb.autopilot == mavlink.MAV_AUTOPILOT_PX4
        assert custom_main_sub(hb) == (4, 3)
        assert client.command(SET_MODE, CUSTOM, 6) != mavlink.MAV_RESULT_ACCEPTED  # no stream

        hover = lambda t_ms: (0.5, LEVEL)  # noqa: E731 - ignored outside offboard
        # as PX4 + SIH: the first arming after boot is accepted
        assert client.command_while_pumping(ARM, (1,), hover) == mavlink.MAV_RESULT_ACCEPTED
        home = client.pump(lambda m: m.get_type() == "GLOBAL_POSITION_INT", hover)
        takeoff = client.command_while_pumping(
            mavlink.MAV_CMD_NAV_TAKEOFF, (0,) * 6 + (home.alt * 1e-3 + 2.0,), hover
        )
        assert takeoff == mavlink.MAV_RESULT_ACCEPTED
        client.pump(is_mode(4, 3), hover)  # takeoff done, holding
        z_hold = client.last["LOCAL_POSITION_NED"].z
        assert z_hold == pytest.approx(-2.0, abs=0.3)

        assert client.command_while_pumping(SET_MODE, (CUSTOM, 6), hover) == 0
        client.pump(is_mode(6), hover)
        climb = lambda t_ms: (0.62, LEVEL)  # noqa: E731
        t_entry = client.last["ATTITUDE"].time_boot_ms
        client.pump(lambda m: m.get_type() == "ATTITUDE" and m.time_boot_ms > t_entry + 1500, climb)
        lpn = client.last["LOCAL_POSITION_NED"]
        assert lpn.z < z_hold - 0.8  # climbed (NED: up is negative)
        assert lpn.vz < -0.5

        t_silent = client.last["ATTITUDE"].time_boot_ms
        hb = client.pump(is_mode(4, 3), None, timeout_s=15)
        t_hold = client.last["ATTITUDE"].time_boot_ms
        assert 1000 <= t_hold - t_silent <= 2100  # COM_OF_LOSS_T 1 s + heartbeat period
        # holding: the climb is arrested
        client.pump(lambda m: m.get_type() == "ATTITUDE" and m.time_boot_ms > t_hold + 2000, None)
        assert abs(client.last["LOCAL_POSITION_NED"].vz) < 0.3
        assert hb.base_mode & mavlink.MAV_MODE_FLAG_SAFETY_ARMED
    finally:
        rc, err = stop_sitl(proc)
    assert rc == 0
    counters = counters_from(err)
    assert counters["offboard_failsafes"] == 1
    # the controller gone (no answer ever again): real-time pace (the hold above came by the
    # clock), and not a stall: its timeouts are not counted (sitl/lockstep.py)
    assert counters["lockstep_timeouts"] == 0


def test_signing_rejects_unsigned_and_wrongly_signed_commands(tmp_path):
    key = bytes(range(32))
    (tmp_path / "key").write_bytes(key)
    c = MavClient(key=key, sign=False)
    proc = start_sitl(c, "--signing-key", str(tmp_path / "key"), "--speedup", "4")
    try:
        hb = c.wait("HEARTBEAT", timeout_s=10)
        assert c.signed_received > 0  # telemetry is signed
        c.send(c.mav.command_long_encode(1, 1, ARM, 0, 1, 0, 0, 0, 0, 0, 0))
        with pytest.raises(TimeoutError):
            c.wait("COMMAND_ACK", timeout_s=0.5)
        c.mav.signing.secret_key = bytes(32)  # the wrong key
        c.mav.signing.sign_outgoing = True
        c.send(c.mav.command_long_encode(1, 1, ARM, 0, 1, 0, 0, 0, 0, 0, 0))
        c.mav.signing.secret_key = key
        with pytest.raises(TimeoutError):
            c.wait("COMMAND_ACK", timeout_s=0.5)
        hb = c.wait("HEARTBEAT", timeout_s=3)
        assert not hb.base_mode & mavlink.MAV_MODE_FLAG_SAFETY_ARMED
        # correctly signed: reaches the autopilot, which arms
        assert c.command(ARM, 1) == mavlink.MAV_RESULT_ACCEPTED
        hb = c.wait("HEARTBEAT", timeout_s=3)
        assert hb.base_mode & mavlink.MAV_MODE_FLAG_SAFETY_ARMED
    finally:
        rc, err = stop_sitl(proc)
        c.close()
    assert rc == 0
    assert counters_from(err)["bad_signature"] >= 2


def test_malformed_unknown_and_mistargeted_traffic_is_counted_and_ignored(client):
    proc = start_sitl(client)
    try:
        client.wait("HEARTBEAT", timeout_s=10)
        good = client.mav.command_long_encode(1, 1, ARM, 0, 1, 0, 0, 0, 0, 0, 0).pack(client.mav)
        client.send_raw(b"\x00garbage\xff" * 10)  # 1 malformed
        client.send_raw(good[:-5])  # truncated: 1 malformed
        client.send_raw(good[:-2] + bytes([good[-2] ^ 0xFF, good[-1]]))  # bad CRC: 1 malformed
        # a well-formed frame with a message id the dialect does not know: 1 unknown
        client.send_raw(bytes([0xFD, 1, 0, 0, 0, 245, 190, 0x39, 0x30, 0x00, 0x00, 0x12, 0x34]))
        client.send(client.mav.command_long_encode(7, 1, ARM, 0, 1, 0, 0, 0, 0, 0, 0))  # not us
        client.send(
            client.mav.set_attitude_target_encode(0, 1, 1, 0b111, [1, 0, 0, 0], 0, 0, 0, math.nan)
        )
        assert client.command(12345) == mavlink.MAV_RESULT_UNSUPPORTED  # still alive, answers
        hb = client.wait("HEARTBEAT", timeout_s=3)
        assert not hb.base_mode & mavlink.MAV_MODE_FLAG_SAFETY_ARMED  # the mistargeted ARM
    finally:
        rc, err = stop_sitl(proc)
    assert rc == 0
    counters = counters_from(err)
    assert counters["malformed"] >= 3
    assert counters["unknown"] == 1
    assert counters["wrong_target"] == 1
    assert counters["nan_setpoints"] == 1
    assert counters["commands"] == 1


def test_telemetry_rates_intervals_and_requests(client):
    """Rates are measured in vehicle time (time_boot_ms), so machine load cannot skew them."""
    proc = start_sitl(client, "--speedup", "4")
    try:
        client.wait("HEARTBEAT", timeout_s=10)
        stamps: dict[str, list[int]] = {"ATTITUDE": [], "LOCAL_POSITION_NED": []}
        client.wait("ATTITUDE")
        t_end = client.last["ATTITUDE"].time_boot_ms + 2000

        def collect(m):
            if m.get_type() in stamps:
                stamps[m.get_type()].append(m.time_boot_ms)
            return m.get_type() == "ATTITUDE" and m.time_boot_ms >= t_end

        client.pump(collect, None)
        # PX4's onboard-link defaults, until SET_MESSAGE_INTERVAL raises them
        for name, hz in (("ATTITUDE", 100.0), ("LOCAL_POSITION_NED", 30.0)):
            s = stamps[name]
            rate = (len(s) - 1) / ((s[-1] - s[0]) / 1000.0)
            assert rate == pytest.approx(hz, rel=0.05), name
        odo = client.last["ODOMETRY"]
        assert odo.frame_id == mavlink.MAV_FRAME_LOCAL_NED
        assert odo.child_frame_id == mavlink.MAV_FRAME_BODY_FRD

        def intervals_after_request(name: str, msg_id: int, interval_us: int) -> set[int]:
            assert client.command(mavlink.MAV_CMD_SET_MESSAGE_INTERVAL, msg_id, interval_us) == 0
            client.wait(name)  # the one due under the old rate
            seen: list[int] = []

            def ten_samples(m):
                if m.get_type() == name:
                    seen.append(m.time_boot_ms)
                return len(seen) == 10

            client.pump(ten_samples, None)
            return {b - a for a, b in itertools.pairwise(seen)}

        lpn_id = mavlink.MAVLINK_MSG_ID_LOCAL_POSITION_NED
        assert intervals_after_request("LOCAL_POSITION_NED", lpn_id, 40000) == {40}  # 25 Hz
        att_id = mavlink.MAVLINK_MSG_ID_ATTITUDE
        assert intervals_after_request("ATTITUDE", att_id, 5000) == {5}  # 200 Hz

        version_id = mavlink.MAVLINK_MSG_ID_AUTOPILOT_VERSION
        assert client.command(mavlink.MAV_CMD_REQUEST_MESSAGE, version_id) == 0
        version = client.wait("AUTOPILOT_VERSION", timeout_s=3)
        assert version.capabilities & mavlink.MAV_PROTOCOL_CAPABILITY_MAVLINK2
        client.send(client.mav.timesync_encode(0, 123456789))
        ts = client.wait("TIMESYNC", lambda m: m.ts1 == 123456789, timeout_s=3)
        assert ts.tc1 == pytest.approx(client.last["ATTITUDE"].time_boot_ms * 1e6, abs=0.1e9)
    finally:
        rc, _ = stop_sitl(proc)
    assert rc == 0
