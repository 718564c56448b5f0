"""A hostile fleet peer floods a flying vehicle (issue 16, fault 5), end to end, in real time.

Real SITL and service processes over UDP MAVLink; the service shares over a real Zenoh
session on loopback, and a raw Zenoh peer floods it with well-formed but useless controllers
from rotating vehicle ids. Before the fix the position loop stalled for up to 0.37 s, the
vehicle strayed 6.8 m and the garbage filled the library. Real time, because only real time
shows a stalled event loop.
"""

from __future__ import annotations

import csv
import json
import math
import threading
import time
from typing import Any

import pytest
import zenoh

from epc_offboard.common.ports import free_port
from epc_offboard.control.cascade import Cascade
from epc_offboard.control.library_types import LibraryEntry
from epc_offboard.fleet.wire import ControllerMessage, MessageKind, encode_controllers
from epc_offboard.service.config import load_service_config
from epc_offboard.vehicle.dialect_px4 import PX4_MAIN_MODE_OFFBOARD
from tests.rig import MIN_RATE_FRACTION, Rig

# waits below: safety bounds for a loaded machine
pytestmark = [pytest.mark.timeout(360), pytest.mark.one_at_a_time("alone")]

FLEET = "floodtest"
FLOOD_S = 6.0


def flood(
    port: int, fleet: str, signature: str, n_con: int, stop: threading.Event, sent: list[int],
    rate_per_s: float | None = None,
) -> None:
    """Batches of 20 well-formed, useless controllers from 1,200 rotating ids, at
    ``rate_per_s`` (None: as fast as the loop goes, with a 5 ms rest every 50)."""
    conf = zenoh.Config()
    conf.insert_json5("mode", '"peer"')
    conf.insert_json5("connect/endpoints", json.dumps([f"tcp/127.0.0.1:{port}"]))
    conf.insert_json5("scouting/multicast/enabled", "false")
    sets = [(i, j) for i in range(n_con) for j in range(n_con) if i < j]
    with zenoh.open(conf) as session:
        t0 = time.monotonic()
        k = 0
        while not stop.is_set():
            vid = f"flood{k % 1200}"  # rotating ids
            chunk = tuple(LibraryEntry(sets[(k * 20 + j) % len(sets)]) for j in range(20))
            payload = encode_controllers(
                ControllerMessage(MessageKind.BATCH, signature, vid, chunk)
            )
            session.put(f"epc/{fleet}/{signature}/ctl/{vid}", payload)
            sent[0] += 1
            k += 1
            if rate_per_s is not None:
                time.sleep(max(0.0, t0 + k / rate_per_s - time.monotonic()))
            elif k % 50 == 0:
                time.sleep(0.005)


def hover_overrides(port: int, fleet: str, mission_s: float) -> dict[str, Any]:
    """A hover of ``mission_s`` in offboard, then a hold, and the service exits (the
    autopilot's landing judged nothing in these tests and cost 9 s of real time each);
    sharing on ``port``."""
    return {
        "mission": {"duration_s": mission_s, "land_at_end": False},
        "trajectory": {"shape": "hover"},
        "sharing": {
            "enabled": True, "fleet": fleet, "vehicle_id": "victim",
            "listen": [f"tcp/127.0.0.1:{port}"], "scouting_multicast": False,
        },
    }  # fmt: skip


def test_a_flooding_peer_neither_stalls_the_loops_nor_moves_the_vehicle(tmp_path):
    port = free_port()
    overrides = hover_overrides(port, FLEET, FLOOD_S + 6.0)
    with Rig(tmp_path, lockstep=False, speedup=1.0, service_overrides=overrides) as rig:
        cfg = load_service_config(rig.config_path)
        cascade = Cascade(cfg.position, cfg.attitude, cfg.estimator, 0.01)
        problem = cascade.position.problem
        rig.wait_mode(PX4_MAIN_MODE_OFFBOARD, timeout_s=180)
        time.sleep(2.0)  # settle on the hover point
        stop, sent = threading.Event(), [0]
        flooder = threading.Thread(
            target=flood, args=(port, FLEET, problem.signature(), problem.n_con, stop, sent)
        )
        t_flood = time.monotonic()
        flooder.start()
        time.sleep(FLOOD_S)
        stop.set()
        flooder.join(timeout=10)
        code = rig.wait_exit(timeout_s=120)
        heard_s = time.monotonic() - t_flood  # the most the helper can have heard it for
        log = rig.log()
        stats = rig.stats()
    assert code == 0, log
    assert sent[0] > 1000, sent  # a real flood: tens of thousands of controllers
    sharing = stats["sharing"]
    assert sharing.get("messages_received", 0) > 100, sharing
    # what passed the fleet-wide limit (before decoding) is within it: its burst and its rate
    # over the time the helper could hear the flood. (Not "most was rate-limited": the
    # helper runs below the loops, and on a loaded machine it took in 878 in a run, no more
    # than the limit lets through, so the limit dropped none: the sender's Zenoh did.)
    fleet = cfg.sharing
    admitted = (sharing["messages_received"] - sharing["own_ignored"]
                - sharing["rejected_oversized"] - sharing["fleet_rate_limited"])  # fmt: skip
    limit = fleet.fleet_burst_messages + fleet.fleet_messages_per_s * heard_s
    assert admitted <= limit, (admitted, limit, sharing)
    # nothing useless entered the library: it holds only what this vehicle solved itself
    assert stats["library"]["position"]["received_shared"] == 0
    # the loops kept running through the flood (a safety bound: MIN_RATE_FRACTION)
    assert stats["loops"]["position"]["rate_hz"] >= MIN_RATE_FRACTION * 100.0
    assert stats["loops"]["attitude"]["rate_hz"] >= MIN_RATE_FRACTION * 200.0
    # and the vehicle held its hover point while it lasted (ground truth against the log's
    # reference, over the offboard flight's vehicle time, which holds the whole flood: it
    # starts after Offboard is seen and the mission outlasts it). Not a span counted back
    # from the end by the flood's wall time: that time includes the flooder's session
    # closing (1.8 s when the service runs at the deployed priorities, 0.02 s at normal),
    # and reached back before Offboard into the take-off climb (1.5-2.6 m "errors" from
    # the hover point while the vehicle, in offboard, held it within 15 mm).
    with (tmp_path / "flight.csv").open() as fh:
        rows = [r for r in csv.DictReader(fh) if r["phase"] == "offboard"]
    ref = [float(rows[-1][f"ref_pos_{a}_m"]) for a in "ned"]
    truth = rig.groundtruth()
    t_start, t_end = float(rows[0]["vehicle_t_s"]), float(rows[-1]["vehicle_t_s"])
    assert t_end - t_start >= FLOOD_S, (t_start, t_end)  # the flood inside the window
    span = [i for i, t in enumerate(truth["t_s"]) if t_start <= t <= t_end]
    err = max(
        math.dist([truth[f"pos_{a}_m"][i] for a in "ned"], ref) for i in span
    )
    assert err < 0.25, f"max error {err:.3f} m during the flood"
