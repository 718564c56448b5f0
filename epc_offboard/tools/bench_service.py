"""`epc-offboard bench --service`: a recorded windy flight replayed through the service's ticks.

The recording is a lockstep ``epc-offboard sim`` flight (by default a figure-8 in the
scenario's 3 m/s wind, flown now): its ``session.tlog`` holds every frame the vehicle sent,
its ``service.toml`` the service's configuration and its ``flight.csv`` when offboard began
and which reference was flown. The replay rebuilds the service's numerics from that
configuration (:class:`~epc_offboard.control.cascade.Cascade`, the miss worker
:class:`~epc_offboard.service.miss_solver.MissSolver`,
:class:`~epc_offboard.vehicle.state.StateTracker`,
the trajectory) and drives them on the recorded vehicle clock, every 5 ms (attitude) and 10 ms
(position) tick of the offboard part, timing each component with ``perf_counter``:

* receive (the service's message callback, between ticks): ``decode`` (the frames received
  since the last 5 ms tick, through the service's receive path, ``vehicle/receive.py``)
  and ``state`` (the tracker takes them);
* attitude tick, as the service's attitude loop times it: ``state`` (the snapshot),
  ``attitude`` (envelope check + attitude EPC), ``encode`` (SET_ATTITUDE_TARGET packed);
* position tick, as the service's position loop times it: ``pump`` (the miss worker's
  answers joined into the library, new misses queued and submitted; the wait for a solve in
  flight, which lockstep adds so that a replay is repeatable, is not timed), ``state`` (the
  snapshot), ``reference`` (the trajectory's horizon),
  ``estimator`` (the estimator's observe / estimate / variation inside the tick), ``epc``
  (the position controller's step), ``cascade_rest`` (the rest of ``position_tick``:
  feedforward, tilt limit, attitude map).

The states are the recorded ones (open loop): the replay's commands do not change them, so
two methods or two versions of the code see identical inputs.
"""

from __future__ import annotations

import csv
import io
import json
import logging
import math
import subprocess
import sys
import tempfile
import time
from collections import Counter
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any, TypeVar

import numpy as np
from pymavlink import mavutil
from pymavlink.dialects.v20 import common as mavlink

from epc_offboard.common.errors import EpcError
from epc_offboard.control.cascade import Cascade
from epc_offboard.control.epc import ExperienceController
from epc_offboard.control.trajectories import Trajectory
from epc_offboard.service.config import load_service_config
from epc_offboard.service.miss_solver import MissSolver
from epc_offboard.tools.sim.scenario import holding_scenario
from epc_offboard.vehicle import commands
from epc_offboard.vehicle.receive import SERVICE_MESSAGE_IDS, FrameReceiver
from epc_offboard.vehicle.state import StateTracker

ATTITUDE_PERIOD_S = 0.005
POSITION_PERIOD_S = 0.01
POSITION_PARTS = ("pump", "state", "reference", "estimator", "epc", "cascade_rest")
ATTITUDE_PARTS = ("state", "attitude", "encode")
RECEIVE_PARTS = ("decode", "state")

_T = TypeVar("_T")


class ServiceBenchError(EpcError, RuntimeError):
    pass


@dataclass(frozen=True)
class Recording:
    """A lockstep flight: the vehicle's frames on its own clock, and how it was flown."""

    frames: list[tuple[float, bytes]]  # (vehicle time s, raw MAVLink frame), in order
    config_path: Path
    offboard_s: tuple[float, float]  # first and last vehicle time of the offboard phase
    ref_pos0_ned_m: np.ndarray  # the reference flown at the first offboard tick


def record_flight(out_dir: Path, duration_s: float, scenario: str = "figure8") -> Path:
    """Fly a lockstep ``sim`` (the real SITL and service processes); returns the run dir.
    The flight ends holding: the replay takes the offboard phase alone, and the autopilot's
    landing after it (8.5 s of vehicle time) was flown for nothing."""
    out_dir.mkdir(parents=True, exist_ok=True)
    holding = holding_scenario(out_dir, scenario)
    cmd = [sys.executable, "-m", "epc_offboard", "sim", "--scenario", str(holding),
           "--lockstep", "--duration", f"{duration_s:g}", "--out", str(out_dir)]
    proc = subprocess.run(cmd, capture_output=True, text=True, check=False)
    run_dir = out_dir / "vehicle1"
    if not (run_dir / "session.tlog").exists():
        raise ServiceBenchError(f"recording flight failed ({proc.returncode}): "
                                f"{proc.stderr[-2000:]}")
    return run_dir


def _vehicle_time_s(msg: Any) -> float | None:
    for name, scale in (("time_usec", 1e-6), ("time_boot_ms", 1e-3)):
        value = getattr(msg, name, None)
        if value:
            return float(value) * scale
    return None


def load_recording(run_dir: Path) -> Recording:
    """The vehicle's frames of ``run_dir/session.tlog`` stamped with vehicle time (messages
    without a stamp take the last one seen), and the offboard span of ``flight.csv``."""
    cfg_path = run_dir / "service.toml"
    cfg = load_service_config(cfg_path)
    conn = mavutil.mavlink_connection(str(run_dir / "session.tlog"))
    frames: list[tuple[float, bytes]] = []
    t_last = 0.0
    while (msg := conn.recv_match()) is not None:
        if msg.get_srcSystem() != cfg.link.target_system or msg.get_type() == "BAD_DATA":
            continue
        t = _vehicle_time_s(msg)
        if t is not None:
            t_last = max(t_last, t)
        frames.append((t if t is not None else t_last, bytes(msg.get_msgbuf())))
    conn.close()
    rows = []
    with (run_dir / "flight.csv").open(newline="") as fh:
        rows = [r for r in csv.DictReader(fh) if r["phase"] == "offboard"]
    if not rows or not frames:
        raise ServiceBenchError(f"{run_dir}: no offboard flight in the recording")
    ref0 = np.array([float(rows[0][f"ref_pos_{a}_m"]) for a in ("n", "e", "d")])
    span = (float(rows[0]["vehicle_t_s"]), float(rows[-1]["vehicle_t_s"]))
    return Recording(frames, cfg_path, span, ref0)


class _Timer:
    """Per-component sample lists; ``tick`` collects the parts of the tick in progress."""

    def __init__(self, names: tuple[str, ...]) -> None:
        self.samples: dict[str, list[float]] = {n: [] for n in names}
        self.tick: dict[str, float] = dict.fromkeys(names, 0.0)

    def time(self, name: str, fn: Callable[..., _T], *args: Any, **kw: Any) -> _T:
        t0 = time.perf_counter()
        out = fn(*args, **kw)
        self.tick[name] += time.perf_counter() - t0
        return out

    def close_tick(self) -> float:
        total = 0.0
        for name, value in self.tick.items():
            self.samples[name].append(value)
            total += value
            self.tick[name] = 0.0
        return total


class _Timed:
    """Times every call of ``methods`` on ``inner`` into ``timer``'s component ``name``."""

    def __init__(self, inner: Any, timer: _Timer, name: str, methods: tuple[str, ...]) -> None:
        self._inner = inner
        for m in methods:
            fn = getattr(inner, m)
            setattr(self, m, lambda *a, _fn=fn, **k: timer.time(name, _fn, *a, **k))

    def __getattr__(self, item: str) -> Any:
        return getattr(self._inner, item)


def _encode_setpoint(
    mav: mavlink.MAVLink, to: commands.Target, t_s: float, q: np.ndarray,
    rates: np.ndarray | None, thrust_norm: float, rmax: tuple[float, float, float],
    hover: commands.AttitudeSetpoint,
) -> None:
    """SET_ATTITUDE_TARGET encoded (``vehicle/commands.py``, as the service does) and packed."""
    setpoint = commands.AttitudeSetpoint.of(q, rates, thrust_norm)
    msg, _ = commands.attitude_target(
        to, t_s, setpoint, max_rate_rad_s=rmax, fallback=lambda: hover
    )
    mav.send(msg)


def _wait_for_solves(misses: MissSolver) -> None:
    """Block until the worker's tasks in flight are done (lockstep's wait), untimed."""
    misses.drain()


def _stats_us(samples_s: list[float]) -> dict[str, float]:
    a = np.asarray(samples_s, dtype=np.float64) * 1e6
    if not a.size:
        return {"median_us": math.nan, "p99_us": math.nan, "max_us": math.nan, "mean_us": math.nan}
    return {"median_us": float(np.median(a)), "p99_us": float(np.percentile(a, 99)),
            "max_us": float(a.max()), "mean_us": float(a.mean())}


def replay(rec: Recording, *, worker: bool = True) -> dict[str, Any]:
    """Drive the service's ticks over the recording's offboard span; the report (JSON)."""
    cfg = load_service_config(rec.config_path)
    cascade = Cascade(cfg.position, cfg.attitude, cfg.estimator,
                      1.0 / cfg.loops.position_rate_hz, learn_on_miss=False,
                      airframe=cfg.vehicle)
    cascade.warm_up()
    misses = MissSolver(dict(cascade.experience_controllers()),
                        slice_s=cfg.sharing.candidate_slice_s)
    if worker:
        misses.start()
    tracker = StateTracker(system_id=cfg.link.target_system,
                           component_id=cfg.link.target_component, limits=cfg.state_limits)
    mav = mavlink.MAVLink(io.BytesIO(), srcSystem=cfg.link.system_id,
                          srcComponent=cfg.link.component_id)
    # the service's receive path, with the service's header filters
    receiver = FrameReceiver(
        Counter(), accept_ids=SERVICE_MESSAGE_IDS,
        accept_systems=frozenset({cfg.link.target_system}),
        accept_components=(frozenset({cfg.link.target_component})
                           if cfg.link.target_component else None),
        signature=None, decode_other=mavlink.MAVLink(None).decode,
    )  # fmt: skip

    def decode(frame: bytes) -> list[Any]:
        return receiver.datagram(frame)[0]

    t_start, t_end = rec.offboard_s
    probe = Trajectory(cfg.trajectory, np.zeros(3), start_s=t_start)
    traj = Trajectory(cfg.trajectory, rec.ref_pos0_ned_m - probe.sample(t_start).pos_ned_m,
                      start_s=t_start)
    pos_t, att_t, rx_t = _Timer(POSITION_PARTS), _Timer(ATTITUDE_PARTS), _Timer(RECEIVE_PARTS)
    # the estimator's and the controller's calls inside the tick, timed where they are made
    loop = cascade.position
    loop.estimator = _Timed(  # type: ignore[assignment]
        loop.estimator, pos_t, "estimator",
        ("observe", "estimate", "variation", "estimate_along"),
    )
    loop.controller = _Timed(loop.controller, pos_t, "epc", ("step",))
    pos_total: list[float] = []
    miss_total: list[float] = []  # position ticks that missed (intermediate controller)
    rx_total: list[float] = []
    att_total: list[float] = []
    sources: dict[str, int] = {}
    attitude_sources: dict[str, int] = {}
    rmax = cfg.vehicle.max_rate_frd_rad_s
    to = commands.Target(cfg.link.target_system, cfg.link.target_component)
    # (the service's NaN fallback is a level hover at the state's yaw; never taken here)
    hover = commands.AttitudeSetpoint((1.0, 0.0, 0.0, 0.0), None, cfg.vehicle.hover_thrust_norm)
    i_frame = 0
    # the frames before offboard set up the tracker's timelines (its warnings about the
    # recording's own take-off are not the replay's business)
    quiet = logging.getLogger("epc_offboard.vehicle.state")
    level = quiet.level
    quiet.setLevel(logging.ERROR)
    while i_frame < len(rec.frames) and rec.frames[i_frame][0] < t_start - 1.0:
        for msg in decode(rec.frames[i_frame][1]):
            tracker.handle(msg, received_s=rec.frames[i_frame][0])
        i_frame += 1
    quiet.setLevel(level)
    target = None
    n_ticks = math.floor((t_end - t_start) / ATTITUDE_PERIOD_S + 1e-9) + 1
    try:
        for k in range(n_ticks):
            t = t_start + k * ATTITUDE_PERIOD_S
            batch = []
            while i_frame < len(rec.frames) and rec.frames[i_frame][0] <= t + 1e-9:
                batch.append(rec.frames[i_frame])
                i_frame += 1
            for t_rx, frame in batch:
                msgs = rx_t.time("decode", decode, frame)
                for msg in msgs:
                    rx_t.time("state", tracker.handle, msg, received_s=t_rx)
            if batch:
                rx_total.append(rx_t.close_tick())
            if k % 2 == 0:  # the position loop's tick at the same vehicle time
                if worker:
                    _wait_for_solves(misses)  # lockstep's wait: not the tick's work
                state = pos_t.time("state", tracker.snapshot)
                pos_t.time("pump", misses.pump)
                if state is None:
                    raise ServiceBenchError("no state at the start of the offboard phase")
                reference = pos_t.time("reference", traj.reference, t, loop.config.dt_s,
                                       loop.config.horizon, loop.config.yaw_rad)
                t0 = time.perf_counter()
                target = cascade.position_tick(state, reference, learn=True)
                whole = time.perf_counter() - t0
                pos_t.tick["cascade_rest"] += whole - pos_t.tick["estimator"] - pos_t.tick["epc"]
                sources[target.source] = sources.get(target.source, 0) + 1
                pos_total.append(pos_t.close_tick())
                if target.source != "hit":
                    miss_total.append(pos_total[-1])
            state = att_t.time("state", tracker.snapshot)
            if state is None or target is None:  # (the first tick is a position tick)
                raise ServiceBenchError("no state at the start of the offboard phase")
            if att_t.time("attitude", cascade.rates_trusted, state, target):
                out = att_t.time("attitude", cascade.attitude_tick, state, target, t)
            else:
                out = att_t.time("attitude", cascade.attitude_fallback, state, target, t)
            attitude_sources[out.source] = attitude_sources.get(out.source, 0) + 1
            att_t.time("encode", _encode_setpoint, mav, to, t, target.q_target,
                       out.rates_frd_rad_s, out.thrust_norm, rmax, hover)
            att_total.append(att_t.close_tick())
        if worker:
            misses.pump(wait=True)
    finally:
        misses.close()
    epc_pos = loop.controller._inner if isinstance(loop.controller, _Timed) else None
    stats = epc_pos.stats if isinstance(epc_pos, ExperienceController) else None
    return {
        "recording": {"config": str(rec.config_path), "frames": len(rec.frames),
                      "offboard_s": [t_start, t_end]},
        "position_ticks": len(pos_total),
        "attitude_ticks": len(att_total),
        "position": {"tick": _stats_us(pos_total),
                     "components": {n: _stats_us(v) for n, v in pos_t.samples.items()}},
        "position_on_misses": _stats_us(miss_total),
        "attitude": {"tick": _stats_us(att_total),
                     "components": {n: _stats_us(v) for n, v in att_t.samples.items()}},
        "receive": {"tick": _stats_us(rx_total),
                    "components": {n: _stats_us(v) for n, v in rx_t.samples.items()}},
        "sources": sources,
        "attitude_sources": attitude_sources,
        "epc": {
            "hits": stats.hits if stats else 0,
            "misses": stats.misses if stats else 0,
            "library_size": stats.size if stats else 0,
            "worker_solves": int(misses.counters.get("solves_returned", 0)),
            "query": epc_pos.query_counters if isinstance(epc_pos, ExperienceController)
            else {},
            "max_checks": epc_pos.max_checks if isinstance(epc_pos, ExperienceController)
            else None,
            "worker_counters": dict(misses.counters),
        },
        "samples_us": {
            "position_tick": [v * 1e6 for v in pos_total],
            "attitude_tick": [v * 1e6 for v in att_total],
            **{f"position.{n}": [v * 1e6 for v in s] for n, s in pos_t.samples.items()},
            **{f"attitude.{n}": [v * 1e6 for v in s] for n, s in att_t.samples.items()},
            **{f"receive.{n}": [v * 1e6 for v in s] for n, s in rx_t.samples.items()},
        },
    }


def format_report(report: dict[str, Any]) -> str:
    lines = [f"replayed {report['position_ticks']} position and {report['attitude_ticks']} "
             f"attitude ticks of {report['recording']['config']}",
             f"{'component':24s} {'median us':>10s} {'p99 us':>10s} {'max us':>10s}"]
    for loop in ("position", "attitude", "receive"):
        part = report[loop]
        for name, s in [*part["components"].items(), ("TICK", part["tick"])]:
            label = f"{loop}.{name}" if name != "TICK" else f"{loop} tick (sum)"
            lines.append(f"{label:24s} {s['median_us']:10.1f} {s['p99_us']:10.1f} "
                         f"{s['max_us']:10.1f}")
    m = report["position_on_misses"]
    lines.append(f"{'position tick, misses':24s} {m['median_us']:10.1f} {m['p99_us']:10.1f} "
                 f"{m['max_us']:10.1f}")
    e = report["epc"]
    lines.append(f"position EPC: {e['hits']} hits, {e['misses']} misses, "
                 f"{e['worker_solves']} worker solves, library {e['library_size']}; "
                 f"sources {report['sources']}")
    return "\n".join(lines)


def write_figure(report: dict[str, Any], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    samples = report["samples_us"]
    names = [n for n in samples if samples[n] and max(samples[n]) > 0]
    fig, axes = plt.subplots(len(names), 1, figsize=(7, 1.3 * len(names)), sharex=True)
    bins = np.logspace(0, 5, 120)
    for ax, name in zip(np.atleast_1d(axes), names, strict=True):
        a = np.maximum(np.asarray(samples[name]), 1.0)
        ax.hist(a, bins=bins, color="tab:red" if name.endswith("_tick") else "tab:blue")
        ax.axvline(float(np.median(a)), color="k", lw=0.8)
        ax.set_xscale("log")
        ax.set_ylabel(name, rotation=0, ha="right", fontsize=8)
        ax.tick_params(labelsize=7)
    np.atleast_1d(axes)[-1].set_xlabel("compute per tick, us (line: median)")
    fig.suptitle("service ticks replayed from a lockstep windy figure-8", fontsize=9)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def run_service_bench(tlog_dir: str | None, duration_s: float, json_path: str | None,
                      *, worker: bool = True) -> int:
    with tempfile.TemporaryDirectory(prefix="epc-bench-") as tmp:
        run_dir = Path(tlog_dir) if tlog_dir else record_flight(Path(tmp), duration_s)
        report = replay(load_recording(run_dir), worker=worker)
    print(format_report(report))
    if json_path:
        out = Path(json_path)
        out.write_text(json.dumps(report, indent=1) + "\n", encoding="utf-8")
        fig = out.with_suffix(".png")
        write_figure(report, fig)
        print(f"report: {out}  figure: {fig}")
    return 0
