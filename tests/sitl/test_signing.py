"""MAVLink 2 signing against ``python -m sitl.main`` over real UDP on loopback."""

from __future__ import annotations

from pymavlink.dialects.v20 import common as mavlink

from tests.sitl.mavclient import MavClient, counters_from, custom_main_sub, start_sitl, stop_sitl
from tests.test_link import forged_now

KEY = bytes(range(32))
LEVEL = (1.0, 0.0, 0.0, 0.0)
ARM = mavlink.MAV_CMD_COMPONENT_ARM_DISARM
SET_MODE = mavlink.MAV_CMD_DO_SET_MODE
CUSTOM = mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED
OFFBOARD = (6, 0)


def test_a_forged_timestamp_does_not_knock_the_sitl_out_of_offboard(tmp_path):
    """One wrong-key frame stamped "now" on the controller's own stream: the SITL must keep
    accepting the controller's signed setpoints, and so stay in offboard."""
    (tmp_path / "key").write_bytes(KEY)
    c = MavClient(key=KEY)
    proc = start_sitl(
        c, "--signing-key", str(tmp_path / "key"), "--lockstep", "--lockstep-timeout-ms", "20",
        "--speedup", "4",
    )  # fmt: skip
    climb = lambda t_ms: (0.6, LEVEL)  # noqa: E731 - a gentle climb: never landed
    heartbeats: list = []

    def offboard_heartbeats(m) -> bool:
        if m.get_type() == "HEARTBEAT":
            heartbeats.append(custom_main_sub(m))
        return False

    try:
        c.wait("HEARTBEAT", timeout_s=10)
        assert c.command_while_pumping(ARM, (1,), climb) == mavlink.MAV_RESULT_ACCEPTED
        assert c.command_while_pumping(SET_MODE, (CUSTOM, 6), climb) == 0
        c.pump(lambda m: m.get_type() == "HEARTBEAT" and custom_main_sub(m) == OFFBOARD, climb)
        c.send_raw(forged_now(c.mav.srcSystem, c.mav.srcComponent, c.mav.signing.link_id))
        t0 = c.last["ATTITUDE"].time_boot_ms
        # well past COM_OF_LOSS_T (1 s) and two heartbeats: rejected setpoints would show
        c.pump(
            lambda m: (
                offboard_heartbeats(m)
                or (m.get_type() == "ATTITUDE" and m.time_boot_ms > t0 + 3000)
            ),
            climb,
        )
    finally:
        rc, err = stop_sitl(proc)
        c.close()
    assert rc == 0
    assert len(heartbeats) >= 2
    assert set(heartbeats) == {OFFBOARD}
    counters = counters_from(err)
    assert counters["bad_signature"] == 1
    assert counters["offboard_failsafes"] == 0
