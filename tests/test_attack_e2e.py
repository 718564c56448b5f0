"""A hostile fleet peer attacks a hovering vehicle, end to end, in real time (issue 21).

Real SITL and service processes over UDP MAVLink; the service shares over a real Zenoh
session on loopback, and a raw Zenoh peer sends 1,000 well-formed, useless controller
batches a second (400 controllers each, the most a message may hold) from rotating vehicle
ids. When Zenoh's callbacks ran in the control
process, rejecting them held the interpreter lock the loops need: the position loop stopped
for ~2 s and a vehicle hovering at 2.5 m fell to 0.7 m. Safety bounds only (they hold on a
loaded 2-core machine); the figures live in the closing report.
"""

from __future__ import annotations

import contextlib
import csv
import itertools
import json
import math
import os
import random
import subprocess
import sys
import threading
import time

import pytest
import zenoh

from epc_offboard.control.cascade import Cascade
from epc_offboard.control.library_types import LibraryEntry
from epc_offboard.fleet.wire import ControllerMessage, MessageKind, encode_controllers
from epc_offboard.service.config import load_service_config
from epc_offboard.vehicle.dialect_px4 import PX4_MAIN_MODE_OFFBOARD
from tests.rig import Rig
from tests.test_flood_e2e import hover_overrides
from tests.test_sharing import free_tcp_port

pytestmark = [pytest.mark.timeout(240), pytest.mark.one_at_a_time("alone")]

FLEET = "attack"
ATTACK_S = 6.0
RATE_PER_S = 1000.0
IDS = 100
ENTRIES = 400  # the position library's size: the most one message may carry


def hostile_peer(
    port: int, signature: str, n_con: int, max_active: int, ready: threading.Event,
    go: threading.Event, stop: threading.Event, sent: list[int],
) -> None:
    """Precomputed batches (the attacker's own CPU is not the test's bottleneck), one from
    each of IDS vehicle ids in turn, RATE_PER_S a second once ``go`` is set."""
    rng = random.Random(0)
    rows = min(12, max_active)
    payloads = []
    for i in range(IDS):
        vid = f"attacker{i}"
        chunk = tuple(
            LibraryEntry(tuple(sorted(rng.sample(range(n_con), rows)))) for _ in range(ENTRIES)
        )
        msg = ControllerMessage(MessageKind.BATCH, signature, vid, chunk)
        payloads.append((f"epc/{FLEET}/{signature}/ctl/{vid}", encode_controllers(msg)))
    conf = zenoh.Config()
    conf.insert_json5("mode", '"peer"')
    conf.insert_json5("connect/endpoints", json.dumps([f"tcp/127.0.0.1:{port}"]))
    conf.insert_json5("scouting/multicast/enabled", "false")
    with zenoh.open(conf) as session:
        ready.set()
        go.wait()
        t0 = time.monotonic()
        k = 0
        while not stop.is_set():
            session.put(*payloads[k % IDS])
            sent[0] += 1
            k += 1
            time.sleep(max(0.0, t0 + k / RATE_PER_S - time.monotonic()))


def wait_offboard(path, settle_s: float, timeout_s: float = 60.0) -> None:
    """Until the service's own flight log shows ``settle_s`` of offboard ticks in a row (the
    autopilot's mode alone says nothing of the service's hover having settled)."""
    end = time.monotonic() + timeout_s
    while time.monotonic() < end:
        with path.open() as fh:
            rows = list(csv.DictReader(fh))
        since = None
        for r in rows:
            since = (since or float(r["t_s"])) if r["phase"] == "offboard" else None
        if since is not None and time.monotonic() - since >= settle_s:
            return
        time.sleep(0.2)
    raise AssertionError(f"no {settle_s} s of offboard in {timeout_s} s")


def flight_window(path, t0_s: float, t1_s: float) -> tuple[list[dict[str, str]], float]:
    """The flight log's rows between loop times t0 and t1 (monotonic), and the largest gap
    between consecutive position ticks there (s)."""
    with path.open() as fh:
        rows = [r for r in csv.DictReader(fh) if t0_s <= float(r["t_s"]) <= t1_s]
    times = [float(r["t_s"]) for r in rows]
    gaps = [b - a for a, b in itertools.pairwise(times)]
    # the window's edges count too: a loop stopped across the whole window has no rows
    edges = [times[0] - t0_s, t1_s - times[-1]] if times else [t1_s - t0_s]
    return rows, max(gaps + edges)


def test_a_hostile_peer_flooding_at_1000_per_s_neither_stops_the_loops_nor_moves_the_vehicle(
    tmp_path,
):
    port = free_tcp_port()
    overrides = hover_overrides(port, FLEET, ATTACK_S + 8.0)
    with Rig(tmp_path, lockstep=False, speedup=1.0, service_overrides=overrides) as rig:
        cfg = load_service_config(rig.config_path)
        problem = Cascade(cfg.position, cfg.attitude, cfg.estimator, 0.01).position.problem
        ready, go, stop, sent = threading.Event(), threading.Event(), threading.Event(), [0]
        attacker = threading.Thread(
            target=hostile_peer,
            args=(port, problem.signature(), problem.n_con, problem.n_u, ready, go, stop, sent),
        )
        attacker.start()  # it prepares its messages during the takeoff
        rig.wait_mode(PX4_MAIN_MODE_OFFBOARD, timeout_s=90)
        assert ready.wait(timeout=60)
        wait_offboard(tmp_path / "flight.csv", settle_s=2.0)
        go.set()
        t0 = time.monotonic() + 0.2  # its first messages have arrived by then
        time.sleep(ATTACK_S)
        t1 = time.monotonic()
        stop.set()
        attacker.join(timeout=10)
        code = rig.wait_exit(timeout_s=60)
        stats = rig.stats()
        truth = rig.groundtruth()
        log = rig.log()
    rows, gap_s = flight_window(tmp_path / "flight.csv", t0, t1 - 0.5)
    assert rows, "no position tick during the attack"
    ref = [float(rows[0][f"ref_pos_{a}_m"]) for a in "ned"]  # the hover point
    v0, v1 = float(rows[0]["vehicle_t_s"]), float(rows[-1]["vehicle_t_s"])
    span = [i for i, t in enumerate(truth["t_s"]) if v0 <= t <= v1]
    err = max(math.dist([truth[f"pos_{a}_m"][i] for a in "ned"], ref) for i in span)
    (tmp_path / "attack.json").write_text(json.dumps(
        {"t0_s": t0, "t1_s": t1, "max_gap_s": gap_s, "max_error_m": err, "sent": sent[0],
         "phases": sorted({r["phase"] for r in rows})}
    ))  # fmt: skip
    assert gap_s < 0.100, f"the position loop stopped for {gap_s * 1e3:.0f} ms"
    assert err < 0.3, f"{err:.3f} m off the hover point during the attack"
    assert all(r["phase"] == "offboard" for r in rows), {r["phase"] for r in rows}
    assert code == 0, log
    # a real flood (a put waits while the victim's Zenoh does not read: counted once sent)
    assert sent[0] >= 0.5 * RATE_PER_S * ATTACK_S, sent
    assert stats["sharing"]["messages_received"] > 100, stats["sharing"]  # reached the victim
    assert stats["library"]["position"]["received_shared"] == 0  # nothing useless joined


# -- replayed messages and liveliness-token flaps, from a peer process of its own -------------

PEER_ATTACK_S = 6.0


def autopilot_priority(pid: int) -> None:
    """The SITL stands in for an autopilot on a processor of its own: SCHED_FIFO below the
    service's loops where permitted. At normal priority at a load of 25-45 its clock fell
    behind the wall clock and the service failed safe on stale state, attack or none (23
    times in one flight), which is not what these tests are about."""
    with contextlib.suppress(PermissionError, OSError):
        os.sched_setscheduler(pid, os.SCHED_FIFO, os.sched_param(40))


def _hover_error_m(rows: list[dict[str, str]], truth: dict[str, list[float]]) -> float:
    """The largest distance (ground truth) from the hover point over the rows' vehicle time."""
    ref = [float(rows[0][f"ref_pos_{a}_m"]) for a in "ned"]
    v0, v1 = float(rows[0]["vehicle_t_s"]), float(rows[-1]["vehicle_t_s"])
    span = [i for i, t in enumerate(truth["t_s"]) if v0 <= t <= v1]
    return max(math.dist([truth[f"pos_{a}_m"][i] for a in "ned"], ref) for i in span)


@pytest.mark.parametrize("kind", ["replay", "flap"])
def test_a_peer_replaying_messages_or_flapping_tokens_neither_stops_the_loops_nor_moves_the_vehicle(
    tmp_path, kind
):
    """``replay``: valid controllers of the victim's problem (solved by the attacker as a
    peer would have), recorded once as 8 peers' batches and sent again, 1,000 a second.
    ``flap``: liveliness tokens of rotating ids declared and undeclared, 1,000 changes a
    second; each arrival makes the victim query that peer's library. The attacker is
    ``tools/zenoh_attack.py``, a process of its own with its own Zenoh session, at normal
    priority: a peer's CPU is its own machine's; here it shares ours, and at the service's
    priority its preparation (1,200 QP solves) starved the takeoff at load 20."""
    port = free_tcp_port()
    # a long mission: the test ends the flight itself once the attack is over (SIGTERM: the
    # service commands Hold and writes its stats), however long the attacker took to prepare
    overrides = hover_overrides(port, FLEET, 120.0)
    overrides["loops"] = {"realtime_priority": 50}  # config/default.toml's, where permitted
    with Rig(tmp_path, lockstep=False, speedup=1.0, service_overrides=overrides) as rig:
        assert rig.sitl is not None
        autopilot_priority(rig.sitl.pid)
        attacker = subprocess.Popen(
            [sys.executable, "-m", "epc_offboard.tools.zenoh_attack", kind,
             "--connect", f"tcp/127.0.0.1:{port}", "--fleet", FLEET,
             "--config", str(rig.config_path), "--rate", str(RATE_PER_S),
             "--duration", str(PEER_ATTACK_S)],
            stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True,
        )  # fmt: skip
        try:
            rig.wait_mode(PX4_MAIN_MODE_OFFBOARD, timeout_s=90)
            assert attacker.stdout is not None
            assert attacker.stdin is not None
            assert attacker.stdout.readline().strip() == "ready"
            wait_offboard(tmp_path / "flight.csv", settle_s=2.0)
            attacker.stdin.write("go\n")
            attacker.stdin.flush()
            summary = json.loads(attacker.stdout.readline())
            time.sleep(0.5)
            code, _ = rig.stop_service(timeout_s=30)
        finally:
            if attacker.stdin is not None:
                attacker.stdin.close()
            attacker.wait(timeout=20)
        stats = rig.stats()
        truth = rig.groundtruth()
        log = rig.log()
    t0 = summary["start_monotonic_s"] + 0.2  # its first messages have arrived by then
    t1 = summary["start_monotonic_s"] + summary["duration_s"]
    rows, gap_s = flight_window(tmp_path / "flight.csv", t0, t1)
    assert rows, "no position tick during the attack"
    err = _hover_error_m(rows, truth)
    (tmp_path / "attack.json").write_text(json.dumps(
        {"attacker": summary, "max_gap_s": gap_s, "max_error_m": err,
         "sharing": stats["sharing"], "loops": stats["loops"], "load_avg": os.getloadavg()}
    ))  # fmt: skip
    assert gap_s < 0.100, f"the position loop stopped for {gap_s * 1e3:.0f} ms"
    assert err < 0.3, f"{err:.3f} m off the hover point during the attack"
    assert all(r["phase"] == "offboard" for r in rows), {r["phase"] for r in rows}
    assert code == 0, log
    assert summary["sent"] >= 0.5 * RATE_PER_S * PEER_ATTACK_S, summary  # a real attack
    reached = "messages_received" if kind == "replay" else "peer_joins"
    assert stats["sharing"][reached] > 50, stats["sharing"]  # it reached the victim
    if kind == "flap":  # every arrival counted; queries and log lines within the fleet budget
        budget = 20 + 10.0 * (PEER_ATTACK_S + 10.0)  # burst + 10/s over the attack and after
        assert stats["sharing"]["queries_sent"] <= budget, stats["sharing"]
        lines = (tmp_path / "service.log").read_text(errors="replace")
        assert lines.count(" joined (") + lines.count(" left (") <= 2 * budget
