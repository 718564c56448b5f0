"""A standard client flies the SITL: MAVSDK's offboard plugin, as users fly PX4 with it.

MAVSDK's own ritual, unchanged: connect, arm (accepted at once, as PX4 + SIH did), send
one attitude setpoint, start offboard (its plugin then streams the setpoint at 20 Hz),
climb, stop offboard -> Hold. This is what caught the SITL denying MAVSDK's arm (NaN in the
unused command params, as MAVSDK sends them) and its one-setpoint offboard entry (accepted
by PX4).
"""

from __future__ import annotations

import asyncio
import time

import mavsdk.asyncio as mavsdk

from epc_offboard.common.ports import free_port
from tests.sitl.mavclient import MavClient, start_sitl, stop_sitl

MAVSDK_OFFBOARD = 7  # mavsdk FlightMode.OFFBOARD
MAVSDK_HOLD = 3  # mavsdk FlightMode.HOLD


def test_mavsdk_offboard_plugin_arms_climbs_and_stops_to_hold():
    from mavsdk.asyncio.plugins.action import ActionAsync
    from mavsdk.asyncio.plugins.offboard import OffboardAsync
    from mavsdk.asyncio.plugins.telemetry import TelemetryAsync
    from mavsdk.plugins.offboard import Attitude

    # the port MAVSDK will listen on: reserved, and outside the range port-0 binds draw from
    # (an OS-chosen port closed and handed on could be any other socket's meanwhile)
    port = free_port()
    port_holder = MavClient(port=port)  # only to name it to the SITL
    port_holder.close()
    proc = start_sitl(port_holder)

    async def fly() -> dict[str, float]:
        cfg = mavsdk.Configuration.create_with_component_type(mavsdk.ComponentType.GROUND_STATION)
        async with mavsdk.Mavsdk(cfg) as m:
            await m.add_any_connection(f"udpin://127.0.0.1:{port}")
            system = await m.first_autopilot(timeout_s=10.0)
            assert system is not None, "MAVSDK did not discover the SITL's autopilot"
            action, offboard = ActionAsync(system), OffboardAsync(system)
            telemetry = TelemetryAsync(system)
            await action.arm()  # the first arming after boot, accepted as PX4 + SIH did
            climb = Attitude(0.0, 0.0, 0.0, 0.65)
            await offboard.set_attitude(climb)
            await offboard.start()
            t_end = time.monotonic() + 2.0
            while time.monotonic() < t_end:
                await offboard.set_attitude(climb)
                await asyncio.sleep(0.05)
            out = {
                "mode_offboard": float(await telemetry.flight_mode()),
                "down_m": (await telemetry.position_velocity_ned()).position.down_m,
                "armed": float(await telemetry.armed()),
            }
            await offboard.stop()
            deadline = time.monotonic() + 3.0  # the mode shows in the next 1 Hz heartbeat
            while (mode := await telemetry.flight_mode()) != MAVSDK_HOLD:
                if time.monotonic() > deadline:
                    break
                await asyncio.sleep(0.1)
            out["mode_after"] = float(mode)
            return out

    try:
        got = asyncio.run(asyncio.wait_for(fly(), timeout=40.0))
    finally:
        rc, err = stop_sitl(proc)
    assert rc == 0, err
    assert got["armed"] == 1.0
    assert got["mode_offboard"] == MAVSDK_OFFBOARD
    assert got["down_m"] < -1.0  # it climbed on MAVSDK's thrust
    assert got["mode_after"] == MAVSDK_HOLD
