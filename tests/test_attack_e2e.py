"""Hostile peers attack a hovering vehicle, end to end, in real time (issue 21).

Real SITL and service processes over UDP MAVLink; the service shares over a real Zenoh
session on loopback, and a raw Zenoh peer sends 1,000 well-formed, useless controller
batches a second (400 controllers each, the most a message may hold) from rotating vehicle
ids. When Zenoh's callbacks ran in the control
process, rejecting them held the interpreter lock the loops need: the position loop stopped
for ~2 s and a vehicle hovering at 2.5 m fell to 0.7 m. Safety bounds only (they hold on a
loaded 2-core machine); the figures live in the closing report.

Two flights carry the four attacks, one after another with calm between (each takeoff is
7-9 s of real time with the real-time lock held): a MAVLink fuzz then the Zenoh flood, and
replayed messages then liveliness flaps. Each test judges the loops and the vehicle over
its own attack's window, and the counters it reads are ones the other attack of its flight
leaves at zero (the Zenoh attacks send no MAVLink, the fuzz nothing over Zenoh; replay
declares no token, the flaps send no message).
"""

from __future__ import annotations

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
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import pytest
import zenoh

from epc_offboard.common.ports import free_port
from epc_offboard.control.cascade import Cascade
from epc_offboard.control.library_types import LibraryEntry
from epc_offboard.fleet.wire import ControllerMessage, MessageKind, encode_controllers
from epc_offboard.service.config import load_service_config
from epc_offboard.tools.sim.analysis import sitl_counters
from epc_offboard.vehicle.dialect_px4 import PX4_MAIN_MODE_OFFBOARD
from tests.conftest import holding
from tests.rig import Rig, deployed_priority
from tests.test_flood_e2e import hover_overrides

# (a module's first test also waits for its shared flight: up to 70 s of real time, longer
# on a loaded machine)
pytestmark = [pytest.mark.timeout(360), pytest.mark.one_at_a_time("alone")]

FLEET = "attack"
ATTACK_S = 6.0
RATE_PER_S = 1000.0
IDS = 100
ENTRIES = 400  # the position library's size: the most one message may carry
CALM_S = 2.0  # between two attacks in one flight: the fleet helper drains, the vehicle settles


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


@dataclass(frozen=True)
class SharedFlight:
    """One real-time hover that several tests judge, each over its own attack's window."""

    tmp: Path  # the rig's folder: flight.csv, groundtruth.csv, service.log, stats.json
    code: int  # the service's exit code
    stats: dict[str, Any]
    truth: dict[str, list[float]]
    log: str
    windows: dict[str, dict[str, Any]]  # per attack: its times and its attacker's summary


def _fuzz_window(rig: Rig) -> dict[str, Any]:
    """The fuzz's window of a hovering flight: SETTLE_S calm (the service's CPU without an
    attack), then FUZZ_S of fuzzed MAVLink to the service's port."""
    assert rig.service is not None
    cpu0, w0 = _cpu_s(rig.service.pid), time.monotonic()
    time.sleep(SETTLE_S)  # settle on the hover point; the service's CPU without fuzz
    cpu1, w1 = _cpu_s(rig.service.pid), time.monotonic()
    fuzz = _fuzz(rig.offboard_port)
    cpu2, w2 = _cpu_s(rig.service.pid), time.monotonic()
    return {"fuzz": fuzz, "cpu_share": {"quiet": (cpu1 - cpu0) / (w1 - w0),
                                        "fuzz": (cpu2 - cpu1) / (w2 - w1)}}  # fmt: skip


@pytest.fixture(scope="module")
def fuzz_then_zenoh_flood(tmp_path_factory: pytest.TempPathFactory) -> SharedFlight:
    """The fuzz's window, then, once calm again, the Zenoh flood's (1,000 hostile batches a
    second). In this order: rotating ids leave the candidate pool full, which costs every
    tick after them more compute, and the fuzz was judged on a service without that."""
    tmp = tmp_path_factory.mktemp("fuzz_then_zenoh_flood")
    port = free_port()
    # a long mission: ended by SIGTERM once the last window is over (the service commands
    # Hold and writes its stats)
    overrides = hover_overrides(port, FLEET, 120.0)
    # at the deployed priorities, as the peers' flight below: at normal priority the loops
    # competed with two CPU hogs and the fuzzer (at the service's nice) on equal terms, and
    # the scheduler alone stopped the position loop for 108 ms (about 1 run in 6 at load 4-5)
    overrides["loops"] = {"realtime_priority": 50}  # config/default.toml's, where permitted
    with (
        holding({"alone"}),
        Rig(tmp, lockstep=False, speedup=1.0, service_overrides=overrides) as rig,
    ):
        assert rig.sitl is not None
        cfg = load_service_config(rig.config_path)
        problem = Cascade(cfg.position, cfg.attitude, cfg.estimator, 0.01).position.problem
        ready, go, stop, sent = threading.Event(), threading.Event(), threading.Event(), [0]
        attacker = threading.Thread(
            target=hostile_peer,
            args=(port, problem.signature(), problem.n_con, problem.n_u, ready, go, stop, sent),
        )
        attacker.start()  # it prepares its messages during the takeoff
        rig.wait_mode(PX4_MAIN_MODE_OFFBOARD, timeout_s=90)
        # its preparation done (on a loaded machine it may outlast the takeoff): none of its
        # CPU in the fuzz's window
        peer_ready = ready.wait(timeout=60)
        fuzz = _fuzz_window(rig)
        zenoh_window: dict[str, Any] = {}
        try:
            assert peer_ready, "the hostile peer never got ready"
            time.sleep(CALM_S)
            # (a fuzz that cost offboard fails its own test; this one says it never began)
            wait_offboard(tmp / "flight.csv", settle_s=2.0)
            go.set()
            t0 = time.monotonic() + 0.2  # its first messages have arrived by then
            time.sleep(ATTACK_S)
            zenoh_window = {"t0_s": t0, "t1_s": time.monotonic()}
        except AssertionError as exc:
            zenoh_window = {"not_flown": str(exc)}
        finally:
            stop.set()
            go.set()  # (a peer still waiting for it ends)
            attacker.join(timeout=10)
        zenoh_window["sent"] = sent[0]
        code, _ = rig.stop_service(timeout_s=30)
        stats = rig.stats()
        truth = rig.groundtruth()
        log = rig.log()
    return SharedFlight(tmp, code, stats, truth, log, {"zenoh": zenoh_window, "fuzz": fuzz})


def test_a_hostile_peer_flooding_at_1000_per_s_neither_stops_the_loops_nor_moves_the_vehicle(
    fuzz_then_zenoh_flood: SharedFlight,
):
    flight = fuzz_then_zenoh_flood
    window = flight.windows["zenoh"]
    assert "not_flown" not in window, window
    t0, t1, sent, stats = window["t0_s"], window["t1_s"], window["sent"], flight.stats
    rows, gap_s = flight_window(flight.tmp / "flight.csv", t0, t1 - 0.5)
    assert rows, "no position tick during the attack"
    err = _hover_error_m(rows, flight.truth)
    (flight.tmp / "attack.json").write_text(json.dumps(
        {"t0_s": t0, "t1_s": t1, "max_gap_s": gap_s, "max_error_m": err, "sent": sent,
         "phases": sorted({r["phase"] for r in rows}), "sharing": stats["sharing"],
         "load_avg": os.getloadavg()}
    ))  # fmt: skip
    assert gap_s < 0.100, f"the position loop stopped for {gap_s * 1e3:.0f} ms"
    assert err < 0.3, f"{err:.3f} m off the hover point during the attack"
    assert all(r["phase"] == "offboard" for r in rows), {r["phase"] for r in rows}
    assert flight.code == 0, flight.log
    # a real flood (a put waits while the victim's Zenoh does not read: counted once sent)
    assert sent >= 0.5 * RATE_PER_S * ATTACK_S, sent
    # it reached the victim: the fleet process took batches in. How many is that process's
    # CPU share, not the attack's: it runs below the loops and beside two CPU hogs it took
    # 39-92 of 6,000 (2.9 % of a core; the rest dropped at the sender's Zenoh, or at its own
    # bounded inbox), so "> 100 received" failed on a loaded machine however well the loops
    # flew. An attacker that reaches nobody fails here (0 received).
    sharing = stats["sharing"]
    assert sharing["messages_received"] > 0, sharing
    assert sharing["entries_received"] > 0, sharing
    assert stats["library"]["position"]["received_shared"] == 0  # nothing useless joined


# -- fuzzed MAVLink, in the same flight before the Zenoh flood --------------------------------
#
# Fuzzed MAVLink at 2,000 datagrams/s to the hovering vehicle's service port: a fuzzer process
# (``tools/fuzz_mavlink.py``) sends random bytes, bad-CRC frames, MAVLink 1, valid-CRC frames
# of ids the service does not read, well-formed frames from other systems, and the vehicle's
# own ids with NaN fields and jumped timestamps, for 10 s. Before the receive path judged
# frames by their header, the fuzz cost the loops their period and the vehicle its offboard
# mode (79-93 % of the time at 1,500/s).

FUZZ_S = 10.0
FUZZ_RATE_HZ = 2000.0
SETTLE_S = 4.0


def _cpu_s(pid: int) -> float:
    """CPU seconds (user + system) the process has used so far."""
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def _fuzz(port: int) -> dict[str, float]:
    proc = subprocess.run(
        [sys.executable, "-m", "epc_offboard.tools.fuzz_mavlink", "--port", str(port),
         "--rate", str(FUZZ_RATE_HZ), "--duration", str(FUZZ_S)],
        capture_output=True, text=True, timeout=FUZZ_S + 30, check=True,
        preexec_fn=deployed_priority,  # an attacker as privileged as the service
    )  # fmt: skip
    summary: dict[str, float] = json.loads(proc.stdout)
    return summary


def test_a_mavlink_fuzz_neither_stalls_the_loops_nor_costs_offboard(
    fuzz_then_zenoh_flood: SharedFlight,
):
    flight = fuzz_then_zenoh_flood
    fuzz, stats, truth = flight.windows["fuzz"]["fuzz"], flight.stats, flight.truth
    assert flight.code == 0, flight.log
    t0, t1 = fuzz["start_monotonic_s"], fuzz["start_monotonic_s"] + fuzz["duration_s"]
    with (flight.tmp / "flight.csv").open() as fh:
        rows = [r for r in csv.DictReader(fh) if t0 <= float(r["t_s"]) <= t1]
    assert rows, "no position tick during the fuzz"
    # the position loop kept ticking (t_s is the loop's monotonic clock)
    ticks = [float(r["t_s"]) for r in rows]
    gap_s = max(b - a for a, b in zip([t0, *ticks], [*ticks, t1], strict=True))
    # the vehicle's own view (ground truth) over the same span of vehicle time
    v0, v1 = float(rows[0]["vehicle_t_s"]), float(rows[-1]["vehicle_t_s"])
    span = [i for i, t in enumerate(truth["t_s"]) if v0 <= t <= v1]
    offboard = sum(int(truth["main_mode"][i]) == PX4_MAIN_MODE_OFFBOARD for i in span) / len(span)
    ref = [float(rows[0][f"ref_pos_{a}_m"]) for a in "ned"]
    err_m = max(math.dist([truth[f"pos_{a}_m"][i] for a in "ned"], ref) for i in span)
    # (the SITL's counters span the whole flight: the Zenoh flood sends it nothing)
    sitl = sitl_counters(flight.tmp / "sitl.log")
    report = {
        "offboard_fraction": offboard, "max_gap_ms": gap_s * 1e3, "max_error_m": err_m,
        "service_cpu_share": flight.windows["fuzz"]["cpu_share"],
        "load_avg": os.getloadavg(),
        "fuzz": fuzz, "link": stats["link"], "state": stats["state"],
        "position_loop": stats["loops"]["position"], "sitl": sitl,
    }  # fmt: skip
    (flight.tmp / "fuzz_report.json").write_text(json.dumps(report, indent=1))
    print(json.dumps(report))
    assert fuzz["rate_hz"] > 0.9 * FUZZ_RATE_HZ, report  # a real attack
    assert sitl["nan_setpoints"] == 0, report
    assert offboard >= 0.95, report
    assert gap_s < 0.100, report
    assert err_m < 0.3, report


# -- replayed messages and liveliness-token flaps, from a peer process of its own -------------

PEER_ATTACK_S = 6.0


def _hover_error_m(rows: list[dict[str, str]], truth: dict[str, list[float]]) -> float:
    """The largest distance (ground truth) from the hover point over the rows' vehicle time."""
    ref = [float(rows[0][f"ref_pos_{a}_m"]) for a in "ned"]
    v0, v1 = float(rows[0]["vehicle_t_s"]), float(rows[-1]["vehicle_t_s"])
    span = [i for i, t in enumerate(truth["t_s"]) if v0 <= t <= v1]
    return max(math.dist([truth[f"pos_{a}_m"][i] for a in "ned"], ref) for i in span)


# the order they are flown in: the replay's preparation (1,200 QP solves) is over when it says
# ready, before either window; the flaps' needs nothing
PEER_KINDS = ("replay", "flap")


def _attacker(kind: str, port: int, config_path: Path) -> subprocess.Popen[str]:
    return subprocess.Popen(
        [sys.executable, "-m", "epc_offboard.tools.zenoh_attack", kind,
         "--connect", f"tcp/127.0.0.1:{port}", "--fleet", FLEET,
         "--config", str(config_path), "--rate", str(RATE_PER_S),
         "--duration", str(PEER_ATTACK_S)],
        stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True,
    )  # fmt: skip


@pytest.fixture(scope="module")
def replay_then_flap(tmp_path_factory: pytest.TempPathFactory) -> SharedFlight:
    """One hover at the deployed priorities for the two peer-process attacks, in turn."""
    tmp = tmp_path_factory.mktemp("replay_then_flap")
    port = free_port()
    # a long mission: the fixture ends the flight itself once the attacks are over (SIGTERM:
    # the service commands Hold and writes its stats), however long they took to prepare
    overrides = hover_overrides(port, FLEET, 120.0)
    overrides["loops"] = {"realtime_priority": 50}  # config/default.toml's, where permitted
    summaries: dict[str, dict[str, Any]] = {}
    rig = Rig(tmp, lockstep=False, speedup=1.0, service_overrides=overrides)
    # The attackers prepare before the flight, beside other tests as any test may (the
    # replay's 1,200 QP solves, 7-10 s of CPU: a peer's own machine's), and say ready once
    # their sessions are open; each connects to the victim when it listens (Zenoh retries
    # within 4 s; the attacks begin 10 s or more after). Prepared during the takeoff, they
    # loaded it, and the hover waited for them with the machine's lock held (18 s at load 8).
    attackers: dict[str, subprocess.Popen[str]] = {}
    try:
        with holding(set()):
            for kind in PEER_KINDS:
                attackers[kind] = _attacker(kind, port, rig.config_path)
            for attacker in attackers.values():
                assert attacker.stdout is not None
                assert attacker.stdout.readline().strip() == "ready"
        with holding({"alone"}), rig:
            assert rig.sitl is not None
            rig.wait_mode(PX4_MAIN_MODE_OFFBOARD, timeout_s=90)
            wait_offboard(tmp / "flight.csv", settle_s=2.0)
            for kind, attacker in attackers.items():
                assert attacker.stdin is not None
                assert attacker.stdout is not None
                attacker.stdin.write("go\n")
                attacker.stdin.flush()
                summaries[kind] = json.loads(attacker.stdout.readline())
                time.sleep(CALM_S if kind != PEER_KINDS[-1] else 0.5)
            code, _ = rig.stop_service(timeout_s=30)
            stats = rig.stats()
            truth = rig.groundtruth()
            log = rig.log()
    finally:
        for attacker in attackers.values():
            if attacker.stdin is not None:
                attacker.stdin.close()
            attacker.wait(timeout=20)
    return SharedFlight(tmp, code, stats, truth, log, summaries)


@pytest.mark.parametrize("kind", PEER_KINDS)
def test_a_peer_replaying_messages_or_flapping_tokens_neither_stops_the_loops_nor_moves_the_vehicle(
    replay_then_flap: SharedFlight, kind: str
):
    """``replay``: valid controllers of the victim's problem (solved by the attacker as a
    peer would have), recorded once as 8 peers' batches and sent again, 1,000 a second.
    ``flap``: liveliness tokens of rotating ids declared and undeclared, 1,000 changes a
    second; each arrival makes the victim query that peer's library. The attacker is
    ``tools/zenoh_attack.py``, a process of its own with its own Zenoh session, at normal
    priority: a peer's CPU is its own machine's; here it shares ours, and at the service's
    priority its preparation (1,200 QP solves) starved the takeoff at load 20."""
    flight = replay_then_flap
    summary, stats, tmp = flight.windows[kind], flight.stats, flight.tmp
    t0 = summary["start_monotonic_s"] + 0.2  # its first messages have arrived by then
    t1 = summary["start_monotonic_s"] + summary["duration_s"]
    rows, gap_s = flight_window(tmp / "flight.csv", t0, t1)
    assert rows, "no position tick during the attack"
    err = _hover_error_m(rows, flight.truth)
    (tmp / f"attack-{kind}.json").write_text(json.dumps(
        {"attacker": summary, "max_gap_s": gap_s, "max_error_m": err,
         "sharing": stats["sharing"], "loops": stats["loops"], "load_avg": os.getloadavg()}
    ))  # fmt: skip
    assert gap_s < 0.100, f"the position loop stopped for {gap_s * 1e3:.0f} ms"
    assert err < 0.3, f"{err:.3f} m off the hover point during the attack"
    assert all(r["phase"] == "offboard" for r in rows), {r["phase"] for r in rows}
    assert flight.code == 0, flight.log
    assert summary["sent"] >= 0.5 * RATE_PER_S * PEER_ATTACK_S, summary  # a real attack
    # it reached the victim (the flight's counters: the other attack leaves these at 0).
    # replay: the recorded batches came again, their entries known already (the fleet
    # process, at its lower priority, sheds what it cannot take: 48 of 6,000 handled at load
    # 5.7 beside a lockstep flight, the rest dropped at its bounded queue); flap: arrivals
    if kind == "replay":
        sharing = stats["sharing"]
        assert sharing["messages_received"] > 2 * summary["payloads"], sharing
        assert sharing["entries_duplicate"] > 0, sharing
    else:
        assert stats["sharing"]["peer_joins"] > 50, stats["sharing"]
    if kind == "flap":  # every arrival counted; queries and log lines within the fleet budget
        budget = 20 + 10.0 * (PEER_ATTACK_S + 10.0)  # burst + 10/s over the attack and after
        assert stats["sharing"]["queries_sent"] <= budget, stats["sharing"]
        lines = (tmp / "service.log").read_text(errors="replace")
        assert lines.count(" joined (") + lines.count(" left (") <= 2 * budget
