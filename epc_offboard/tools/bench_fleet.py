"""``epc-offboard bench --fleet --vehicles N``: N vehicles through one router (issue 25, a
first cut).

Each vehicle is a light process of its own running the real sharing stack (FleetSharing and
its fleet helper process, Zenoh client mode) around an ExperienceController on a small
double-integrator problem: no physics, no MAVLink, so the network path is what is measured.
The router is ``epc-offboard fleet router`` (a process). Every vehicle learns one controller
(a solve towards its own target) in its own time slot; each receiver stamps a controller's
arrival as its control process takes it from the helper (CLOCK_MONOTONIC is one clock for
every process on the machine), so propagation = arrival - the publisher's solve, which
includes ``publish_period_s`` (the batching) and the control process's turn.

Reported: discovery (from the last session opened until every vehicle has seen every
other's liveliness token), propagation p50/p99/max over
every (publisher, receiver) pair (and, with replay traffic, over every controller learned:
``every_controller``, with those never delivered counted as lost, and the helpers' drop
and rate-limit counts), and the CPU share of the router, of each vehicle's control
process and of its helper; bytes per vehicle per second, on the wire (the kernel's count of
each vehicle's TCP connection at the router, ``ss -ti``: Zenoh has no byte counters in its
Python API nor, in the pip build, in its admin space) and as payloads (the helper's counts).
The figure: latency, CPU and bytes against N.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import math
import multiprocessing
import os
import re
import signal
import subprocess
import sys
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from epc_offboard.common.children import launched_env
from epc_offboard.common.errors import UsageError
from epc_offboard.common.ports import free_port

_SLOT_S = 0.5  # one vehicle learns in each slot: publications do not overlap
_SETTLE_S = 3.0  # from the last session open to slot 0: discovery has its time
_TAIL_S = 5.0  # after the last slot: the last arrivals
_WAVE = 5  # vehicles started together
_FLEET = "bench"


def _problem() -> Any:
    from epc_offboard.control.models import LinearModel
    from epc_offboard.control.qp import MpcProblem

    dt = 0.1  # a double integrator per axis: x = (p, v), u = a; bounds make active sets
    A = np.eye(6)
    A[:3, 3:] = dt * np.eye(3)
    B = np.vstack([0.5 * dt * dt * np.eye(3), dt * np.eye(3)])
    inf = math.inf
    return MpcProblem(LinearModel(A, B), horizon=8, Q=[10, 10, 10, 1, 1, 1], R=[0.2] * 3,
                      x_min=[-inf] * 3 + [-2.0] * 3, x_max=[inf] * 3 + [2.0] * 3,
                      u_min=[-3.0] * 3, u_max=[3.0] * 3)  # fmt: skip


def _target(k: int, n: int) -> np.ndarray:
    """Vehicle k's target: far (bounds active), in a direction of its own."""
    az = 2 * math.pi * k / n
    el = math.pi * ((k % 3) - 1) / 4
    return 10.0 * np.array([math.cos(az) * math.cos(el), math.sin(az) * math.cos(el),
                            math.sin(el)])  # fmt: skip


@dataclass(frozen=True)
class _VehicleArgs:
    k: int
    n: int
    endpoint: str
    launch_s: float  # time.monotonic() of the bench's start
    # 0: learn one controller (in slot k); else one more every this many seconds after it,
    # from a random state towards a random target (the traffic of a fleet in flight)
    replay_period_s: float = 0.0


def _vehicle_main(args: _VehicleArgs, go_s: Any, end_s: Any, out: Any) -> None:
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    out.put(asyncio.run(_vehicle(args, go_s, end_s, out)))


async def _vehicle(a: _VehicleArgs, go_s: Any, end_s: Any, queue: Any) -> dict[str, Any]:
    """``go_s``: a shared double, 0 until every vehicle has its session, then the time slot
    0 starts; this vehicle learns in slot ``k`` (and on, with ``replay_period_s``) and stops
    at ``end_s`` (a shared double, 0 until the bench sets it)."""
    from epc_offboard.common.procstats import process_report
    from epc_offboard.control.epc import ExperienceController
    from epc_offboard.fleet.exchange import candidate_of
    from epc_offboard.fleet.sharing import FleetSharing, SharingConfig

    arrivals: dict[str, float] = {}  # origin -> first arrival (one controller each)
    sets_in: dict[tuple[int, ...], float] = {}  # every controller's first arrival, from anyone

    class _Stamped(FleetSharing):
        def _offer(self, records: Any) -> int:
            now = time.monotonic()
            for row in records:
                entry, origin, _succ = candidate_of(row)
                arrivals.setdefault(origin.removeprefix("shared:"), now)
                sets_in.setdefault(entry.active_set, now)
            return super()._offer(records)

    problem = _problem()
    ctrl = ExperienceController(problem, max_size=64)
    cfg = SharingConfig(enabled=True, fleet=_FLEET, vehicle_id=f"b{a.k}", mode="client",
                        connect=(a.endpoint,), publish_period_s=0.05, candidates_per_s=5000.0,
                        query_timeout_s=5.0, helper_nice=0)  # fmt: skip
    out: dict[str, Any] = {"k": a.k}
    sharing = _Stamped(cfg, [("position", ctrl)])
    try:
        await sharing.open()
    except RuntimeError as exc:  # counted in the report; the bench goes on without it
        queue.put({"opened": a.k, "failed": str(exc)})
        return {**out, "failed": str(exc)}
    with contextlib.closing(sharing):
        out["opened_s"] = time.monotonic()
        queue.put({"opened": a.k})
        task = asyncio.create_task(sharing.run())
        learned = 0
        sets_out: list[tuple[tuple[int, ...], float]] = []  # (controller, when learned here)
        rng = np.random.default_rng(a.k)
        cpu_at_go: tuple[float, float, float] | None = None  # (t, control cpu_s, helper cpu_s)
        bytes_at_go: dict[str, int] = {}
        while end_s.value == 0.0 or time.monotonic() < end_s.value:
            now = time.monotonic()
            if cpu_at_go is None and go_s.value and now >= go_s.value:
                cpu_at_go = (now, _cpu_s(None), _cpu_s(sharing.helper_pid()))
                bytes_at_go = {k: sharing.stats().get(k, 0) for k in _BYTES}
            if "all_peers_s" not in out and sharing.stats().get("peers", 0) >= a.n - 1:
                out["all_peers_s"] = now
            due = go_s.value + a.k * _SLOT_S + learned * a.replay_period_s
            if go_s.value and now >= due and (not learned or a.replay_period_s > 0):
                refs = np.zeros((problem.horizon, problem.nx))
                x0 = np.zeros(problem.nx)
                if learned:  # replaying: somewhere else, going somewhere else
                    x0 = np.concatenate([rng.uniform(-5, 5, 3), rng.uniform(-2, 2, 3)])
                    refs[:, :3] = 10.0 * rng.standard_normal(3)
                else:
                    refs[:, :3] = _target(a.k, a.n)
                before = {e.active_set for e in ctrl.export_library()}
                ctrl.step(x0, refs)
                out.setdefault("learned_s", time.monotonic())  # the first: propagation
                sets_out.extend((e.active_set, time.monotonic()) for e in ctrl.export_library()
                                if e.active_set not in before)  # fmt: skip
                learned += 1
            await asyncio.sleep(0.02)  # arrivals are stamped in _offer, not here
        out["arrivals"] = arrivals
        out["stopped_s"] = time.monotonic()
        out["sets_out"] = [(list(x), t) for x, t in sets_out]
        out["sets_in"] = [(list(x), t) for x, t in sets_in.items()]
        out["stats"] = sharing.stats()
        out["helper"] = sharing.process_stats()
        out["control"] = process_report(os.getpid())
        if cpu_at_go is not None:  # the CPU share while the fleet shares, not over start-up
            window = time.monotonic() - cpu_at_go[0]
            out["control_share"] = (_cpu_s(None) - cpu_at_go[1]) / window
            out["helper_share"] = (_cpu_s(sharing.helper_pid()) - cpu_at_go[2]) / window
            out["payload_bytes_s"] = {k: (out["stats"].get(k, 0) - bytes_at_go[k]) / window
                                      for k in _BYTES}  # fmt: skip
        task.cancel()
    return out


_BYTES = ("bytes_published", "bytes_answered", "bytes_received")  # the helper's payload counts
_DROPS = ("messages_received", "entries_received", "entries_published", "publish_errors",
          "rate_limited", "fleet_rate_limited", "dropped_queue_full", "entries_duplicate",
          "tasks_dropped", "query_errors", "queries_sent", "queries_gap")  # fmt: skip
_IN_FLIGHT_S = 2.0  # a controller learned this close to the end may still be on its way


def _every_controller(reports: list[dict[str, Any]]) -> dict[str, Any]:
    """Every controller every vehicle learned (with replay traffic, not only the first), at
    every other vehicle: from the solve to its first arrival there from anyone. One the
    receiver held before it was learned (it learned it itself, or another sent it first) is
    not a propagation; one that never arrived is lost."""
    lat: list[float] = []
    held = lost = 0
    end = min((r["stopped_s"] for r in reports), default=0.0) - _IN_FLIGHT_S

    def first(pairs: list[tuple[list[int], float]]) -> dict[tuple[int, ...], float]:
        out: dict[tuple[int, ...], float] = {}
        for a, u in pairs:
            out[tuple(a)] = min(u, out.get(tuple(a), math.inf))
        return out

    own = [first(r["sets_out"]) for r in reports]
    got_in = [first(r["sets_in"]) for r in reports]
    for i, x in enumerate(reports):
        for active, t in x["sets_out"]:
            if t > end:
                continue
            for j in range(len(reports)):
                if j == i:
                    continue
                got = got_in[j].get(tuple(active), math.inf)
                if min(own[j].get(tuple(active), math.inf), got) <= t:
                    held += 1
                elif got < math.inf:
                    lat.append(got - t)
                else:
                    lost += 1
    return {"delivered": len(lat), "held_before": held, "lost": lost, "p50": _pct(lat, 50),
            "p99": _pct(lat, 99), "max": _pct(lat, 100),
            "over_1s": sum(v > 1.0 for v in lat)}  # fmt: skip


def tcp_bytes(port: int) -> dict[str, tuple[int, int]]:
    """The kernel's byte counts of every established TCP connection on local ``port`` (the
    router's side): {peer address: (bytes sent to it, bytes received from it)}, read with
    ``ss -ti`` (tcp_info: payload bytes on the wire, Zenoh's framing included, TCP/IP
    headers not). {} where ``ss`` is missing."""
    try:
        text = subprocess.run(
            ["ss", "-tinH", "state", "established", f"( sport = :{port} )"],
            capture_output=True, text=True, timeout=10, check=False,
        ).stdout  # fmt: skip
    except (OSError, subprocess.SubprocessError):
        return {}
    out: dict[str, tuple[int, int]] = {}
    peer = ""
    for line in text.splitlines():
        if not line[:1].isspace():  # the connection's line: state-less with -H, addresses
            fields = line.split()
            peer = fields[-1] if len(fields) >= 4 else ""
            continue
        sent = re.search(r"bytes_sent:(\d+)", line)
        received = re.search(r"bytes_received:(\d+)", line)
        if peer:
            out[peer] = (int(sent.group(1)) if sent else 0,
                         int(received.group(1)) if received else 0)  # fmt: skip
    return out


def _wire_rates(before: dict[str, tuple[int, int]], after: dict[str, tuple[int, int]],
                window_s: float) -> dict[str, Any]:  # fmt: skip
    """Bytes a second per vehicle connection, down (router -> vehicle) and up, over the window
    (a connection opened inside it counts from 0)."""
    down = [(s - before.get(k, (0, 0))[0]) / window_s for k, (s, _r) in after.items()]
    up = [(r - before.get(k, (0, 0))[1]) / window_s for k, (_s, r) in after.items()]
    return {"connections": len(after),
            "down_p50": _pct(down, 50), "down_max": _pct(down, 100),
            "up_p50": _pct(up, 50), "up_max": _pct(up, 100),
            "router_total": round(sum(down) + sum(up), 1)}  # fmt: skip


def _cpu_s(pid: int | None) -> float:
    """CPU seconds of ``pid`` (None: this process)."""
    from epc_offboard.common.procstats import process_report

    return float(process_report(pid if pid is not None else os.getpid()).get("cpu_s", 0.0))


def _pct(values: list[float], q: float) -> float | None:
    return round(float(np.percentile(values, q)), 4) if values else None


def run_fleet_bench(
    n: int, start_timeout_s: float = 600.0, *, replay_period_s: float = 0.0,
    during: Callable[[str], dict[str, Any]] | None = None,
) -> dict[str, Any]:  # fmt: skip
    """N vehicles through one router; returns the report (see the module docstring).

    ``during``: called with the router's endpoint once the vehicles share (slot 0); the
    vehicles run on (with ``replay_period_s``, learning on) until it returns, and what it
    returns joins the report."""
    port = free_port()
    endpoint = f"tcp/127.0.0.1:{port}"
    router = subprocess.Popen(
        [sys.executable, "-m", "epc_offboard", "fleet", "router", "--listen", endpoint,
         "--stats-every", "1"], stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True,
        env={**os.environ, **launched_env()},  # it ends with the bench, even SIGKILLed
    )  # fmt: skip
    assert router.stdout is not None
    json.loads(router.stdout.readline())  # the "started" line: it listens
    ctx = multiprocessing.get_context("spawn")
    results = ctx.Queue()
    go_s = ctx.Value("d", 0.0)
    end_s = ctx.Value("d", 0.0)
    launch = time.monotonic()
    procs = [
        ctx.Process(target=_vehicle_main, name=f"bench-b{k}",
                    args=(_VehicleArgs(k, n, endpoint, launch, replay_period_s), go_s, end_s,
                          results))
        for k in range(n)
    ]  # fmt: skip
    # started in waves, each when the one before has its sessions: 2N processes importing
    # numpy and zenoh at once on a loaded machine miss the helper's start timeout
    finals: list[dict[str, Any]] = []
    for wave in range(0, n, _WAVE):
        for p in procs[wave : wave + _WAVE]:
            p.start()
        started = 0
        while started < len(procs[wave : wave + _WAVE]):
            msg = results.get(timeout=start_timeout_s)
            if "opened" in msg:
                started += 1
            else:  # a vehicle that could not open has already said so, and ended
                finals.append(msg)
    go_s.value = time.monotonic() + _SETTLE_S
    router_cpu_at_go = (go_s.value, _cpu_s(router.pid))
    while time.monotonic() < go_s.value:
        time.sleep(0.01)
    wire_at_go = (time.monotonic(), tcp_bytes(port))
    extra: dict[str, Any] = {}
    if during is None:
        time.sleep(max(0.0, go_s.value + n * _SLOT_S + _TAIL_S - time.monotonic()))
    else:
        try:
            extra = during(endpoint)
        except BaseException:
            end_s.value = time.monotonic()
            router.kill()
            raise
    # the end's count before the vehicles stop (their sessions close at the end)
    wire = _wire_rates(wire_at_go[1], tcp_bytes(port), time.monotonic() - wire_at_go[0])
    end_s.value = time.monotonic() + 0.2
    while len(finals) < n:  # one final report per vehicle (its "opened" came before)
        msg = results.get(timeout=_SETTLE_S + n * _SLOT_S + _TAIL_S + 120.0)
        if "opened" not in msg:
            finals.append(msg)
    reports = finals
    for p in procs:
        p.join(timeout=10)
    router_share = (_cpu_s(router.pid) - router_cpu_at_go[1]) / (time.monotonic()
                                                                    - router_cpu_at_go[0])
    router.send_signal(signal.SIGTERM)
    router_stats: dict[str, Any] = {}
    for line in router.stdout:
        router_stats = json.loads(line)
    router.wait(timeout=10)
    failed = [r for r in reports if "failed" in r]
    reports = [r for r in reports if "failed" not in r]
    learned = {f"b{r['k']}": r["learned_s"] for r in reports if "learned_s" in r}
    lat = [t - learned[o] for r in reports for o, t in r["arrivals"].items() if o in learned]
    pairs = len(reports) * (len(reports) - 1)
    # discovery: from the last session opened to the last vehicle that sees every other
    # (process start-up, which load stretches, is not the network's)
    every = _every_controller(reports)
    seen = [r["all_peers_s"] for r in reports if "all_peers_s" in r]
    opened = max((r["opened_s"] for r in reports), default=launch)
    disc = [max(0.0, t - opened) for t in seen]
    return {
        "vehicles": n,
        "sessions_failed": len(failed),
        "discovered": len(disc),  # vehicles that saw every other
        "startup_s": round(opened - launch, 2),  # the last session open, from the launch
        "discovery_s": {"max": _pct(disc, 100), "p50": _pct(disc, 50)},
        "propagation_s": {"pairs": pairs, "received": len(lat), "p50": _pct(lat, 50),
                          "p99": _pct(lat, 99), "max": _pct(lat, 100)},
        "every_controller": every,
        # what each helper dropped or refused, summed over the vehicles (a lost publication
        # shows as a gap here or nowhere: Zenoh's own drops are not counted by Zenoh)
        "helper_counts": {k: sum(int(r["stats"].get(k, 0)) for r in reports)
                          for k in _DROPS},
        # of one core, from slot 0 to the end (process_report's CPU ticks: 10 ms resolution)
        "cpu_share": {
            "router": round(router_share, 4),
            "control_p50": _pct([r.get("control_share", 0.0) for r in reports], 50),
            "helper_p50": _pct([r.get("helper_share", 0.0) for r in reports], 50),
            "helper_max": _pct([r.get("helper_share", 0.0) for r in reports], 100),
        },
        # bytes a second per vehicle, slot 0 to the end: on the wire (the router's TCP
        # connections, one per vehicle's helper: Zenoh's framing, liveliness and keep-alives
        # included) and the payloads each helper put / answered / took in (medians)
        "bytes_per_vehicle_s": {
            "wire": wire,
            "payload": {k: _pct([r["payload_bytes_s"][k] for r in reports
                                 if "payload_bytes_s" in r], 50) for k in _BYTES},
        },
        "router": router_stats,
        "load_1min": os.getloadavg()[0],
        **extra,
    }


def write_figure(runs: list[dict[str, Any]], path: str) -> None:
    """Propagation (p50, p99) and CPU shares against N."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    n = [r["vehicles"] for r in runs]
    fig, (ax1, ax2, ax3) = plt.subplots(1, 3, figsize=(13, 3.4))
    for q in ("p50", "p99"):
        ax1.plot(n, [1e3 * (r["propagation_s"][q] or 0.0) for r in runs], "o-", label=q)
    ax1.set_xlabel("vehicles through one router")
    ax1.set_ylabel("solve -> receiver's control process, ms")
    ax1.legend(fontsize=8)
    for key, label in (("helper_p50", "fleet helper (p50 of vehicles)"),
                       ("control_p50", "control process (p50)"), ("router", "router")):
        ax2.plot(n, [100 * (r["cpu_share"][key] or 0.0) for r in runs], "o-", label=label)
    ax2.set_xlabel("vehicles through one router")
    ax2.set_ylabel("% of one core while sharing")
    ax2.legend(fontsize=8)
    for key, label in (("down_p50", "router -> vehicle (wire, p50)"),
                       ("up_p50", "vehicle -> router (wire, p50)")):  # fmt: skip
        ax3.plot(n, [(r["bytes_per_vehicle_s"]["wire"][key] or 0.0) / 1e3 for r in runs], "o-",
                 label=label)  # fmt: skip
    ax3.plot(n, [(r["bytes_per_vehicle_s"]["payload"]["bytes_received"] or 0.0) / 1e3
                 for r in runs], "s--", label="controller payloads received (p50)")  # fmt: skip
    ax3.set_xlabel("vehicles through one router")
    ax3.set_ylabel("kB per vehicle per second")
    ax3.legend(fontsize=8)
    loads = ", ".join(f"{r['load_1min']:.0f}" for r in runs)
    fig.suptitle(f"bench --fleet (machine load {loads})", fontsize=9)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


# -- the late joiner and the loops beside the fleet (--late-joiner) ---------------------------

_FLYING = 3  # real vehicles (SITL + service) among the N
_REPLAY_PERIOD_S = 2.0  # each light vehicle learns (publishes) a controller this often
_LATE_SCENARIO = ("--scenario", "zigzag_bounded", "--adaptation", "none")  # README's stagger
# the loops' thread and the SITL SCHED_FIFO (where permitted): the autopilot is hardware of
# its own on a real vehicle, and the loops run so where the service is deployed; without it
# the SITL starved beside the light fleet as much as the loops did (19.7 Hz vs 84.8 alone)
_LOOPS_PRIORITY = 50
_LOOPS_SCENARIO = ("--scenario", "circle", "--realtime",
                   "--realtime-priority", str(_LOOPS_PRIORITY))  # fmt: skip
_SIM_TIMEOUT_S = 1800.0


def _sim(args: Sequence[str], out_dir: Path) -> dict[str, Any]:
    """``epc-offboard sim ARGS`` (no ground-station stream) into ``out_dir``; its report (a
    flight that missed a scenario target exits 1 and is reported all the same)."""
    out_dir.mkdir(parents=True, exist_ok=True)
    with (out_dir / "sim.log").open("w") as log:
        subprocess.run([sys.executable, "-m", "epc_offboard", "sim", *args, "--gcs-port", "0",
                        "--out", str(out_dir)], stdout=log, stderr=subprocess.STDOUT,
                       timeout=_SIM_TIMEOUT_S, check=False)  # fmt: skip
    report = out_dir / "report.json"
    if not report.exists():
        raise RuntimeError(f"sim left no report: see {out_dir / 'sim.log'}")
    return dict(json.loads(report.read_text()))


def _loops(report: dict[str, Any], out_dir: Path) -> dict[str, Any]:
    """One real-time flight's loops and tracking (its first vehicle), and how its loops were
    scheduled (the service's own log line)."""
    v = report["vehicles"][0]
    loops = v.get("loops", {})
    log = out_dir / "vehicle1" / "service.log"
    sched = re.search(r"loops: (SCHED_FIFO priority \d+|normal scheduling)",
                      log.read_text(errors="replace") if log.exists() else "")  # fmt: skip
    return {
        "loops_scheduling": sched.group(1) if sched else None,
        "rmse_m": v["tracking"]["rmse_m"],
        **{f"{loop}_{k}": loops.get(loop, {}).get(k)
           for loop in ("position", "attitude")
           for k in ("rate_hz", "deadline_misses", "period_jitter_p99_ms")},
        "load_1min": os.getloadavg()[0],
    }  # fmt: skip


def _late_joiner_beside(out_dir: Path) -> Callable[[str], dict[str, Any]]:
    """What runs beside the light fleet: 3 lockstep vehicles flying the bounded zigzag one
    after another through the same router (vehicle 3, the late joiner, has the fleet's
    library of 1 and 2; vehicle 1 flies with no library to take: its first lap is the
    vehicle alone), then one real-time circle through the router (the loops beside it)."""

    def during(endpoint: str) -> dict[str, Any]:
        late = _sim([*_LATE_SCENARIO, "--vehicles", str(_FLYING), "--stagger",
                     "--fleet-router", endpoint], out_dir / "late_joiner")  # fmt: skip
        laps = [v["library"]["first_lap_misses"] for v in late["vehicles"]]
        loops = _loops(_sim([*_LOOPS_SCENARIO, "--fleet-router", endpoint],
                            out_dir / "loops_fleet"), out_dir / "loops_fleet")  # fmt: skip
        return {
            "late_joiner": {
                "flying": _FLYING, "lockstep": True, "scenario": "zigzag_bounded",
                "first_lap_misses": laps,  # vehicle 1 (alone), 2, 3 (the late joiner)
                "received_shared": [v["library"]["received_shared"] for v in late["vehicles"]],
                "ratio_to_alone": round(laps[-1] / laps[0], 3) if laps[0] else None,
                "load_1min": os.getloadavg()[0],
            },
            "loops_beside_fleet": {"with_fleet": loops},
        }  # fmt: skip

    return during


def write_late_figure(report: dict[str, Any], path: str) -> None:
    """First-lap misses of the three flying vehicles; the real-time loops with the fleet and
    alone."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (ax1, ax2) = plt.subplots(1, 2, figsize=(10, 3.4))
    late = report["late_joiner"]
    labels = ["v1 (alone)"] + [f"v{k}" for k in range(2, len(late["first_lap_misses"]) + 1)]
    labels[-1] += " (late joiner)"
    ax1.bar(labels, late["first_lap_misses"], color=["grey"] + ["tab:blue"] * (len(labels) - 1))
    ax1.set_ylabel("first-lap misses (bounded zigzag, lockstep)")
    ax1.set_title(f"{report['vehicles']} light + {late['flying']} flying through one router",
                  fontsize=9)  # fmt: skip
    loops = report["loops_beside_fleet"]
    # rates and gaps, not deadline misses: a loop starved to 20 Hz has fewer ticks to miss
    keys = ("position_rate_hz", "attitude_rate_hz", "position_period_jitter_p99_ms")
    x = np.arange(len(keys) + 1)
    for i, (name, values) in enumerate(loops.items()):
        heights = [values.get(k) or 0 for k in keys] + [100 * values["rmse_m"]]
        ax2.bar(x + 0.4 * i - 0.2, heights, 0.4,
                label=f"{name.replace('_', ' ')} (load {values['load_1min']:.0f})")  # fmt: skip
    ax2.set_xticks(x, ["position Hz", "attitude Hz", "position period\np99 ms", "RMSE cm"])
    ax2.set_yscale("log")
    ax2.set_title("real-time circle, 30 s", fontsize=9)
    ax2.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def run_late_joiner_command(n: int, json_path: str | None) -> int:
    """``bench --fleet --vehicles N --late-joiner``: N - 3 replaying light vehicles and 3
    flying ones through one router, then the real-time circle alone for comparison."""
    out_dir = Path(os.path.splitext(json_path)[0] if json_path else "out/bench_fleet_late")
    report = run_fleet_bench(n - _FLYING, replay_period_s=_REPLAY_PERIOD_S,
                             during=_late_joiner_beside(out_dir))  # fmt: skip
    report["vehicles_total"] = n
    report["loops_beside_fleet"]["alone"] = _loops(_sim(_LOOPS_SCENARIO, out_dir / "loops_alone"),
                                                   out_dir / "loops_alone")  # fmt: skip
    print(json.dumps({k: v for k, v in report.items() if k != "router"}, indent=2))
    if json_path:
        with open(json_path, "w", encoding="utf-8") as fh:
            json.dump(report, fh, indent=2)
            fh.write("\n")
        figure = os.path.splitext(json_path)[0] + ".png"
        write_late_figure(report, figure)
        print(f"report: {json_path}  figure: {figure}  flights: {out_dir}")
    return 0


def run_fleet_bench_command(
    sizes: list[int], json_path: str | None, late_joiner: bool = False
) -> int:
    """One run per N in ``sizes``; with ``json_path`` the report (one run: its dict; several:
    ``{"runs": [...]}``) and a figure beside it (FILE with .png). ``late_joiner``: see
    :func:`run_late_joiner_command` (one N)."""
    if late_joiner:
        if len(sizes) != 1 or sizes[0] <= _FLYING:
            raise UsageError(f"--late-joiner takes one --vehicles N above {_FLYING}")
        return run_late_joiner_command(sizes[0], json_path)
    runs = []
    for n in sizes:
        report = run_fleet_bench(n)
        print(json.dumps({k: v for k, v in report.items() if k != "router"}, indent=2))
        runs.append(report)
    if json_path:
        with open(json_path, "w", encoding="utf-8") as fh:
            json.dump(runs[0] if len(runs) == 1 else {"runs": runs}, fh, indent=2)
            fh.write("\n")
        figure = os.path.splitext(json_path)[0] + ".png"
        write_figure(runs, figure)
        print(f"report: {json_path}  figure: {figure}")
    return 0
