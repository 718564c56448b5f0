"""What ``bench --attack`` measured, window by window, and issue 21's targets judged on it.

Pure: arrays and dicts in (the flight log, the ground truth, the service's sent attitude
setpoints from its tlog, the process samples), figures out; the files are read by
:mod:`epc_offboard.tools.bench_attack`. Times: ``t_s`` is the monotonic clock the service's
loops and the bench share; the SITL's ground truth is on vehicle time, mapped with the offset
the flight log gives (each row carries both).
"""

from __future__ import annotations

import math
import struct
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
import numpy.typing as npt

from epc_offboard.common.frames import FloatArray
from epc_offboard.service.loop import STALL_S
from epc_offboard.tools import steal

PX4_OFFBOARD = 6  # PX4 main mode OFFBOARD (vehicle/state.py); the bench flies PX4's personality
SET_ATTITUDE_TARGET = 82
ATTITUDE_IGNORE = 128  # type_mask bit: the attitude is ignored, body rates are flown
_TYPE_MASK_OFFSET = 38  # time_boot_ms, q[4], 3 rates, thrust (36 bytes), target sys, comp
BoolArray = npt.NDArray[np.bool_]
_LATE_PERIODS = 2.0  # an interval between attitude sends this many periods long: a late tick


@dataclass(frozen=True)
class Window:
    """One stretch of the flight: an attack (``kind``) or a calm gap (``"calm"``), in
    ``phase`` ("hover" or "figure8"), from ``t0_s`` to ``t1_s`` on the monotonic clock."""

    phase: str
    kind: str
    t0_s: float
    t1_s: float
    attacker: dict[str, Any]  # the attacker's summary (empty for calm)

    @property
    def attack(self) -> bool:
        return self.kind != "calm"


def attitude_sends(tlog: bytes, system_id: int) -> tuple[FloatArray, BoolArray]:
    """(unix time s, body rates?) of every SET_ATTITUDE_TARGET ``system_id`` sent, from a
    tlog (each frame after a big-endian uint64 of unix microseconds). Scanned by header: a
    pymavlink decode of every frame of a three-minute flight takes longer than the flight's
    analysis."""
    times: list[float] = []
    rates: list[bool] = []
    i, n = 0, len(tlog)
    while i + 9 < n:
        (t_us,) = struct.unpack_from(">Q", tlog, i)
        magic = tlog[i + 8]
        if magic == 0xFD and i + 18 <= n:
            length = tlog[i + 9]
            signed = tlog[i + 10] & 0x01
            sysid = tlog[i + 13]
            msgid = int.from_bytes(tlog[i + 15 : i + 18], "little")
            size = 12 + length + (13 if signed else 0)
            if sysid == system_id and msgid == SET_ATTITUDE_TARGET:
                off = _TYPE_MASK_OFFSET
                mask = tlog[i + 18 + off] if off < length else 0  # trailing zeros truncated
                times.append(t_us * 1e-6)
                rates.append(bool(mask & ATTITUDE_IGNORE))
        elif magic == 0xFE and i + 10 <= n:
            size = 8 + tlog[i + 9]
        else:  # not a frame start: the log is torn here
            break
        i += 8 + size
    return np.asarray(times), np.asarray(rates, dtype=bool)


def _gap_s(times: FloatArray, t0_s: float, t1_s: float) -> float:
    """The longest stretch of [t0, t1] without a tick (the edges count: a loop stopped
    across the whole window has none)."""
    inside = times[(times >= t0_s) & (times <= t1_s)]
    edges = np.concatenate([[t0_s], inside, [t1_s]])
    return float(np.max(np.diff(edges)))


def _sample_at(samples: list[dict[str, Any]], t_s: float) -> dict[str, Any]:
    """The process sample nearest ``t_s``."""
    return min(samples, key=lambda s: abs(s["t_s"] - t_s))


def _cpu_shares(a: dict[str, Any], b: dict[str, Any], names: dict[int, str]) -> dict[str, Any]:
    dt = b["t_s"] - a["t_s"]
    if dt <= 0:
        return {}
    helpers: dict[str, float] = {}
    for pid, cpu_b in b["children_cpu_s"].items():
        cpu_a = a["children_cpu_s"].get(pid, 0.0)
        name = names.get(int(pid), f"pid {pid}")
        helpers[name] = helpers.get(name, 0.0) + (cpu_b - cpu_a) / dt
    return {
        "control_cpu_share": round((b["control_cpu_s"] - a["control_cpu_s"]) / dt, 3),
        "helpers_cpu_share": round(sum(helpers.values()), 3),
        "helpers": {k: round(v, 3) for k, v in sorted(helpers.items())},
    }


def window_figures(
    w: Window,
    flight: dict[str, Any],
    truth: dict[str, Any],
    att_times_s: FloatArray,
    att_rates: BoolArray,
    samples: list[dict[str, Any]],
    names: dict[int, str],
    attitude_period_s: float,
) -> dict[str, Any]:
    """Everything the bench reports of one window (see the module docstring for the clocks).

    ``flight``: the flight log's columns (t_s, vehicle_t_s, ref_pos_*_m, compute_us, phase);
    ``truth``: the ground truth's (t_s on vehicle time, pos_*_m, main_mode);
    ``att_times_s``: attitude sends on the monotonic clock; ``samples``: the process samples.
    """
    t_s, vt_s = flight["t_s"], flight["vehicle_t_s"]
    offset_s = float(np.median(vt_s - t_s))
    rows = (t_s >= w.t0_s) & (t_s <= w.t1_s)
    out: dict[str, Any] = {"phase": w.phase, "kind": w.kind, "t0_s": w.t0_s, "t1_s": w.t1_s,
                           "duration_s": w.t1_s - w.t0_s}  # fmt: skip
    out["position_ticks"] = int(rows.sum())
    # a phase other than offboard here: the service left offboard (a failsafe), and the log
    # has no rows while it streams nothing, so the "gap" below is that, not a stalled loop
    out["phases"] = sorted({str(p) for p in flight["phase"][rows]})
    out["position_max_gap_ms"] = _gap_s(t_s, w.t0_s, w.t1_s) * 1e3
    compute = flight["compute_us"][rows]
    out["position_compute_us_median"] = float(np.median(compute)) if compute.size else None
    out["position_compute_us_p99"] = float(np.percentile(compute, 99)) if compute.size else None
    # attitude: what the service sent (its tlog), one SET_ATTITUDE_TARGET per tick
    att = (att_times_s >= w.t0_s) & (att_times_s <= w.t1_s)
    sends = att_times_s[att]
    intervals = np.diff(np.concatenate([[w.t0_s], sends, [w.t1_s]]))
    out["attitude_rate_hz"] = float(sends.size / (w.t1_s - w.t0_s))
    out["attitude_max_gap_ms"] = float(intervals.max() * 1e3)
    out["attitude_late_ticks"] = int(np.sum(np.diff(sends) > _LATE_PERIODS * attitude_period_s))
    out["attitude_body_rate_fraction"] = float(att_rates[att].mean()) if sends.size else 0.0
    # the vehicle's own view: ground truth against the reference the service flew
    v0, v1 = w.t0_s + offset_s, w.t1_s + offset_s
    span = (truth["t_s"] >= v0) & (truth["t_s"] <= v1)
    tt = truth["t_s"][span]
    if tt.size and rows.sum() > 1:
        ref = np.stack([np.interp(tt, vt_s, flight[f"ref_pos_{a}_m"]) for a in "ned"], axis=1)
        pos = np.stack([truth[f"pos_{a}_m"][span] for a in "ned"], axis=1)
        err = np.linalg.norm(pos - ref, axis=1)
        out["max_error_m"] = float(err.max())
        out["rmse_m"] = float(np.sqrt(np.mean(err**2)))
        out["altitude_loss_m"] = float(max(0.0, np.max(pos[:, 2] - ref[:, 2])))  # NED: down
    else:
        out["max_error_m"] = out["rmse_m"] = out["altitude_loss_m"] = None
    modes = truth["main_mode"][span]
    out["offboard_fraction"] = float(np.mean(modes == PX4_OFFBOARD)) if modes.size else 0.0
    if samples:
        a, b = _sample_at(samples, w.t0_s), _sample_at(samples, w.t1_s)
        out["control_rss_mb"] = [a["control_rss_mb"], b["control_rss_mb"]]
        out.update(_cpu_shares(a, b, names))
        out["load_avg_1min"] = b["load_avg"][0]
    out["attacker"] = w.attacker
    return out


def steal_figures(
    record: dict[str, Any],
    wins: Sequence[Window],
    windows: list[dict[str, Any]],
    flight: dict[str, Any],
    att_times_s: FloatArray,
    attitude_period_s: float,
    stalls: Sequence[dict[str, Any]] = (),
) -> dict[str, Any]:
    """The hypervisor's steal time (:mod:`~epc_offboard.tools.steal`'s samples, ``record``)
    beside each window's figures (``windows``, updated in place: ``steal_ms_per_s``, the
    machine's; ``position_max_gap_steal_ms``, in its longest gap between ticks), and lined
    up with every position-loop gap over ``STALL_S`` and every late attitude tick in the
    windows: a gap the hypervisor made has the steal, one the code made has not.
    ``stalls``: the service's own (its stats' ``stalls``, ``service.loop.Stall``), each
    given the steal in its interval (``steal_ms``; None outside the samples)."""
    cols = steal.Columns.of(record)
    if cols is None:
        return {"sampled": False}
    off = flight["phase"] == "offboard"
    position: list[tuple[float, float]] = []
    late: list[tuple[float, float]] = []
    for w, fig in zip(wins, windows, strict=True):
        rows = (flight["t_s"] >= w.t0_s) & (flight["t_s"] <= w.t1_s)
        position += steal.gaps(flight["t_s"][rows & off], STALL_S)
        sends = att_times_s[(att_times_s >= w.t0_s) & (att_times_s <= w.t1_s)]
        late += steal.gaps(sends, _LATE_PERIODS * attitude_period_s)
        s = cols.stretch(w.t0_s, w.t1_s)
        fig["steal_ms_per_s"] = None if s is None else round(1e3 * s["steal_ms"] / s["ms"], 2)
        t = flight["t_s"][rows]
        i = int(np.argmax(np.diff(t))) if t.size > 1 else -1
        g = cols.stretch(float(t[i]), float(t[i + 1])) if i >= 0 else None
        fig["position_max_gap_steal_ms"] = None if g is None else g["steal_ms"]
    return {
        "sample_s": float(np.median(np.diff(cols.t_s))),
        "cpus": int(cols.steal_s.shape[1]),
        "position_gaps": steal.gap_account(cols, position),
        "attitude_late": steal.gap_account(cols, late),
        "stalls": [_stall_steal(cols, st) for st in stalls],
    }


def _stall_steal(cols: steal.Columns | None, stall: dict[str, Any]) -> dict[str, Any]:
    """``stall`` with the steal in its interval: the machine's (``steal_ms``) and the loops'
    CPU's (``steal_thread_cpu_ms``: the CPUs the loops' thread was seen on); None outside
    the samples. A deadline miss's interval ends with its tick (``loop.Stall``)."""
    end_s = stall["t_s"] + (1e-3 * stall.get("compute_ms", 0.0) if stall.get("deadline_miss")
                            else 0.0)  # fmt: skip
    s = None if cols is None else cols.stretch(end_s - 1e-3 * stall["interval_ms"], end_s)
    return dict(stall, steal_ms=None if s is None else s["steal_ms"],
                steal_thread_cpu_ms=None if s is None else s["steal_thread_cpu_ms"])  # fmt: skip


# -- the machine's floor: the bare loops beside ours (floor_probe) ----------------------------


def grid_lateness_s(times_s: FloatArray, period_s: float, early_q: float = 0.5) -> FloatArray:
    """Each tick's lateness against the grid its loop keeps (due every ``period_s`` at a
    fixed phase: ``Loops.periodic`` plans ``t_next += period`` and skips whole periods), for
    loops that log when a tick ran but not when it was due. The ticks' times modulo the
    period, centred on their circular mean; the phase is the ``early_q`` percentile of them
    (not the earliest: a few ticks logged early of the rest, as the flight log's position
    rows show, would shift every other's lateness). Lateness is over that, 0 at least, and
    within half a period of the centre (a tick later than that counts from the deadline
    after it: 0)."""
    t = np.asarray(times_s, dtype=float)
    if t.size == 0:
        return t
    r = np.mod(t, period_s)
    angle = float(np.angle(np.mean(np.exp(2j * np.pi * r / period_s))))
    centre = angle / (2.0 * np.pi) * period_s
    u = np.mod(r - centre + 0.5 * period_s, period_s) - 0.5 * period_s
    out: FloatArray = np.maximum(u - float(np.percentile(u, early_q)), 0.0)
    return out


def _lateness_ms(late_s: FloatArray) -> dict[str, float | None]:
    if not late_s.size:
        return {"p50": None, "p99": None, "max": None}
    ms = 1e3 * late_s
    return {"p50": round(float(np.percentile(ms, 50)), 3),
            "p99": round(float(np.percentile(ms, 99)), 3), "max": round(float(ms.max()), 3)}


def probe_figures(records: dict[str, FloatArray], t0_s: float, t1_s: float,
                  period_s: float) -> dict[str, Any]:  # fmt: skip
    """A bare loop's (``floor_probe``'s ``COLUMNS``) ticks woken in [t0, t1], judged as the
    loops are: ``misses``, ticks woken more than ``period_s`` (the attitude loop's
    deadline) late or computing longer than it (``timing.LoopTiming``); ``gaps_over_12ms``,
    wake-to-wake intervals over ``STALL_S``, at the probe's 200 Hz and at 100 Hz (its ticks
    due on a 10 ms grid alone, ``gaps_over_12ms_100hz``: the position loop's period, the
    same measure as its gaps); ``skipped``, deadlines passed by; lateness (wake - due)
    percentiles in ms; the compute's wall and thread-CPU time, and the wall beyond the CPU
    summed (``compute_off_cpu_ms``: steal or preemption inside a tick)."""
    due, wake = records["due_s"], records["wake_s"]
    sel = (wake >= t0_s) & (wake <= t1_s)
    late = (wake - due)[sel]
    wall, cpu = records["compute_wall_s"][sel], records["compute_cpu_s"][sel]
    steps = np.rint(np.diff(due[sel]) / period_s) if sel.sum() > 1 else np.zeros(0)
    on_100hz = sel & (np.rint((due - (due[0] if due.size else 0.0)) / period_s) % 2 == 0)
    return {
        "ticks": int(sel.sum()),
        "misses": int(np.sum((late > period_s) | (wall > period_s))),
        "gaps_over_12ms": len(steal.gaps(wake[sel], STALL_S)),
        "gaps_over_12ms_100hz": len(steal.gaps(wake[on_100hz], STALL_S)),
        "max_gap_ms": round(1e3 * _gap_s(wake, t0_s, t1_s), 3) if sel.any() else None,
        "skipped": int(np.sum(np.maximum(steps - 1, 0))),
        "lateness_ms": _lateness_ms(late),
        "compute_wall_us": _percentiles_us(wall),
        "compute_cpu_us": _percentiles_us(cpu),
        "compute_off_cpu_ms": round(1e3 * float(np.sum(np.maximum(wall - cpu, 0.0))), 3),
    }  # fmt: skip


def _percentiles_us(x_s: FloatArray) -> dict[str, float | None]:
    if not x_s.size:
        return {"p50": None, "p99": None}
    return {"p50": round(float(np.percentile(x_s, 50)) * 1e6, 1),
            "p99": round(float(np.percentile(x_s, 99)) * 1e6, 1)}  # fmt: skip


def loops_floor_figures(flight: dict[str, Any], att_times_s: FloatArray,
                        misses: Sequence[dict[str, Any]], t0_s: float, t1_s: float,
                        attitude_period_s: float,
                        position_period_s: float = 0.01) -> dict[str, Any]:  # fmt: skip
    """The loops' figures in [t0, t1] in the probe's terms: position-loop gaps over
    ``STALL_S`` (its offboard ticks, as ``steal_figures`` counts them), attitude deadline
    misses (the service's ``misses``, its latest ``loop.STALLS_KEPT``), and each loop's
    lateness against its grid (:func:`grid_lateness_s`: the position ticks' start in the
    flight log, the attitude ticks' SET_ATTITUDE_TARGET send in the tlog, a tick's compute
    later than its start)."""
    t = flight["t_s"]
    rows = (t >= t0_s) & (t <= t1_s)
    att = att_times_s[(att_times_s >= t0_s) & (att_times_s <= t1_s)]
    return {
        "position_gaps_over_12ms": len(steal.gaps(t[rows & (flight["phase"] == "offboard")],
                                                  STALL_S)),
        "attitude_misses": sum(1 for m in misses if m["loop"] == "attitude"
                               and t0_s <= m["t_s"] <= t1_s),
        "position_lateness_ms": _lateness_ms(grid_lateness_s(t[rows], position_period_s)),
        "attitude_lateness_ms": _lateness_ms(grid_lateness_s(att, attitude_period_s)),
    }  # fmt: skip


def _ratio(a: float | None, b: float | None) -> float | None:
    return None if a is None or b is None or b <= 0 else round(a / b, 2)


def floor_figures(probes: dict[str, dict[str, FloatArray]], flight: dict[str, Any],
                  att_times_s: FloatArray, misses: Sequence[dict[str, Any]],
                  wins: Sequence[Window], attitude_period_s: float) -> dict[str, Any]:  # fmt: skip
    """The loops beside the bare loops (``probes``: each wake's records), per window and
    over the flight (the first window's start to the last's end), with the ratios
    loops/probe: attitude misses over the probe's misses, position gaps over 12 ms over
    the probe's at 100 Hz, lateness p99 (attitude's over the probe's). A ratio near 1 or
    under: the machine's floor; well over 1: the loops lose more than a bare loop does."""

    def stretch(t0_s: float, t1_s: float) -> dict[str, Any]:
        loops = loops_floor_figures(flight, att_times_s, misses, t0_s, t1_s, attitude_period_s)
        out: dict[str, Any] = {"loops": loops}
        for wake, rec in probes.items():
            fig = probe_figures(rec, t0_s, t1_s, attitude_period_s)
            out[wake] = fig
            out[f"ratio_{wake}"] = {
                "misses": _ratio(loops["attitude_misses"], fig["misses"]),
                "gaps_over_12ms": _ratio(loops["position_gaps_over_12ms"],
                                         fig["gaps_over_12ms_100hz"]),
                "lateness_p99": _ratio(loops["attitude_lateness_ms"]["p99"],
                                       fig["lateness_ms"]["p99"]),
            }  # fmt: skip
        return out

    if not wins:
        return {"probed": sorted(probes), "windows": [], "flight": {}, "shared": {}}
    windows = [dict(phase=w.phase, kind=w.kind, **stretch(w.t0_s, w.t1_s)) for w in wins]
    attacks = [w for w in wins if w.attack]
    return {"probed": sorted(probes), "flight": stretch(wins[0].t0_s, wins[-1].t1_s),
            "shared": shared_events(probes, flight, misses, wins[0].t0_s, wins[-1].t1_s),
            "attack_windows": _sum_counts([w for w, win in zip(windows, wins, strict=True)
                                           if win.attack]) if attacks else {},
            "windows": windows}  # fmt: skip


SHARED_LATE_MS = 2.0  # a bare loop's tick this late: the machine held a SCHED_FIFO thread too
SHIFT_S = 0.5  # the control: the same intervals this much later, where the loops were on time


def shared_events(probes: dict[str, dict[str, FloatArray]], flight: dict[str, Any],
                  misses: Sequence[dict[str, Any]], t0_s: float, t1_s: float,
                  ) -> dict[str, Any]:  # fmt: skip
    """Each of the loops' position gaps over ``STALL_S`` and attitude misses in [t0, t1]
    (its interval: between the two ticks; a miss's from the previous tick's start to its
    own end, ``loop.Stall``) beside each bare loop's latest tick in it (the ticks due
    before its end and woken after its start): ``events`` (``loop``, ``t0_s``, ``t1_s``,
    ``probe_late_ms`` by wake) and, by wake, how many had a probe tick at least
    ``SHARED_LATE_MS`` late (``with_probe_late``): what held the loops held a bare loop at
    the same moment, the machine's; the rest, the loops' alone. The control
    (``by_chance``): the same count over the same intervals ``SHIFT_S`` later, how often a
    bare loop is that late in any stretch that long."""
    t = flight["t_s"]
    on = t[(t >= t0_s) & (t <= t1_s) & (flight["phase"] == "offboard")]
    spans = [("position", a, b) for a, b in steal.gaps(on, STALL_S)]
    for m in misses:
        if m["loop"] == "attitude" and t0_s <= m["t_s"] <= t1_s:
            end_s = m["t_s"] + 1e-3 * float(m.get("compute_ms", 0.0))
            spans.append(("attitude", end_s - 1e-3 * float(m["interval_ms"]), end_s))
    def worst_ms(rec: dict[str, FloatArray], a: float, b: float) -> float | None:
        inside = (rec["due_s"] <= b) & (rec["wake_s"] >= a)
        return (round(1e3 * float(np.max((rec["wake_s"] - rec["due_s"])[inside])), 3)
                if inside.any() else None)  # fmt: skip

    events: list[dict[str, Any]] = []
    for loop, a, b in sorted(spans, key=lambda e: e[1]):
        events.append({"loop": loop, "t0_s": round(a, 4), "t1_s": round(b, 4),
                       "probe_late_ms": {w: worst_ms(r, a, b) for w, r in probes.items()},
                       "shifted_probe_late_ms": {w: worst_ms(r, a + SHIFT_S, b + SHIFT_S)
                                                 for w, r in probes.items()}})  # fmt: skip
    counts: dict[str, Any] = {}
    for loop in ("position", "attitude"):
        mine = [e for e in events if e["loop"] == loop]
        counts[loop] = {"total": len(mine)} | {key: {
            wake: sum(1 for e in mine if (e[field][wake] or 0.0) >= SHARED_LATE_MS)
            for wake in probes} for key, field in (("with_probe_late", "probe_late_ms"),
                                                   ("by_chance", "shifted_probe_late_ms"))}
    return {"late_ms": SHARED_LATE_MS, "shift_s": SHIFT_S, **counts, "events": events}


def _sum_counts(windows: Sequence[dict[str, Any]]) -> dict[str, Any]:
    """The attack windows' counts summed (misses, gaps), the loops' and each probe's."""
    keys = {"loops": ("position_gaps_over_12ms", "attitude_misses")}
    out: dict[str, Any] = {}
    for part in windows[0]:
        if part in ("phase", "kind") or part.startswith("ratio_"):
            continue
        names = keys.get(part, ("misses", "gaps_over_12ms", "gaps_over_12ms_100hz", "skipped"))
        out[part] = {k: sum(w[part][k] for w in windows) for k in names}
    return out


# -- every gap over 12 ms and every deadline miss, attributed ---------------------------------

STEAL = "steal"
RUNQUEUE = "run-queue at FIFO"
COLLECTION = "collection"
OUR_STEP = "our step"
GIL_WAIT = "GIL wait"
ASLEEP_IN_STEP = "asleep in a step"
UNATTRIBUTED = "unattributed"
MACHINE_VERDICTS = (STEAL, RUNQUEUE)  # the hypervisor's, the machine's other real-time work
OUR_VERDICTS = (COLLECTION, OUR_STEP, GIL_WAIT, ASLEEP_IN_STEP)  # what the code can still cut
VERDICTS = (*MACHINE_VERDICTS, *OUR_VERDICTS, UNATTRIBUTED)
_DEFAULT_PERIOD_MS = {"position": 10.0, "attitude": 5.0}  # records without ``period_ms``
_TICK_STEPS = ("task position-loop ", "task attitude-loop ")  # the loops' own steps


def attribute(event: dict[str, Any]) -> dict[str, Any]:
    """One stall or deadline miss (``loop.Stall``'s fields, with the steal on the loops'
    CPU in its interval, ``steal_thread_cpu_ms``; None: not sampled, taken as 0) and its
    single verdict. ``excess_ms``: what it took beyond the loop's period (a stall's interval
    over one period; a miss's lateness or its compute over one period). Each cause's share of
    the interval, in ms:

    * ``steal``: the hypervisor ran something else on the loops' virtual CPU: its steal in
      ``/proc/stat`` (in 10 ms ticks, interpolated: a single event's figure is within
      ~10 ms), or, if more, the event-loop steps' wall time beyond the thread's CPU time
      (the thread's clock leaves steal out; a SCHED_FIFO thread is not preempted in a step,
      and no other thread of ours held the interpreter lock when ``GIL wait`` is 0), less
      what the slow control steps slept (``asleep in a step``);
    * ``run-queue at FIFO``: the SCHED_FIFO thread runnable and not run (the kernel's
      schedstat; a wake-up queued on a virtual CPU the hypervisor holds counts here too);
    * ``collection``: the cyclic collector's pauses, no more than the thread's CPU time;
    * ``our step``: the longest event-loop step's time, no more than the thread's own CPU
      time in the interval (a step stretched by steal or a wait is not work), less the
      collections; or, if more, the thread's CPU time beyond its usual share of the
      interval (``usual_cpu_share``: its CPU time over the windows, a fraction of the
      wall; work no step timed, the event loop's own), less the collections;
    * ``GIL wait``: the thread off its CPU and not queued for it while the process's other
      threads ran (their CPU time, no more than that off-CPU time);
    * ``asleep in a step``: the slow control steps' wall time beyond their CPU time in
      those that switched out voluntarily (``slow_steps_slept_ms``: the thread blocked in
      the step, on a lock, a system call or a fault's I/O: a sleep of ours, not steal), no
      more than the event-loop steps' wall time beyond the thread's CPU time.

    The verdict is the largest share if it covers at least half the excess (and 0.5 ms),
    ties to the machine; else ``unattributed`` (e.g. the thread asleep past its timer with
    nothing counted, or steal the 10 ms ticks did not catch)."""
    loop = event["loop"]
    period_ms = event.get("period_ms") or _DEFAULT_PERIOD_MS.get(loop, 10.0)
    interval = float(event["interval_ms"])
    if event.get("deadline_miss"):
        excess = max(float(event.get("late_ms", 0.0)),
                     float(event.get("compute_ms", 0.0)) - period_ms)  # fmt: skip
    else:
        excess = interval - period_ms
    cpu = float(event["thread_cpu_ms"])
    in_steps = max(0.0, float(event.get("steps_ms") or 0.0) - cpu)
    slept = min(in_steps, float(event.get("slow_steps_slept_ms") or 0.0))
    stolen = max(float(event.get("steal_thread_cpu_ms") or 0.0), in_steps - slept)
    queued = float(event["runqueue_ms"])
    gc_ms = float(event["gc_ms"])
    step = float(event.get("longest_step_ms") or 0.0)
    asleep = max(0.0, interval - cpu - queued - stolen)
    shares = {
        STEAL: stolen,
        RUNQUEUE: queued,
        COLLECTION: min(gc_ms, cpu),  # (a collection stretched by steal is no longer)
        OUR_STEP: max(0.0, (min(step, cpu) if step > 0.0 else 0.0) - gc_ms,
                      cpu - float(event.get("usual_cpu_share") or 1.0) * interval - gc_ms),
        GIL_WAIT: min(float(event.get("other_threads_cpu_ms") or 0.0), asleep),
        ASLEEP_IN_STEP: slept,
    }
    verdict = max(shares, key=lambda k: shares[k])  # the first of equals: the machine's
    if shares[verdict] < max(0.5, 0.5 * excess):
        verdict = UNATTRIBUTED
    return {
        "loop": loop, "kind": "miss" if event.get("deadline_miss") else "gap",
        "t_s": event["t_s"], "interval_ms": round(interval, 3), "excess_ms": round(excess, 3),
        "late_ms": event.get("late_ms"), "compute_ms": event.get("compute_ms"),
        "steal_loops_cpu_ms": event.get("steal_thread_cpu_ms"),
        "steps_beyond_cpu_ms": round(in_steps, 3),
        "steal_machine_ms": event.get("steal_ms"), "runqueue_ms": queued, "gc_ms": gc_ms,
        "thread_cpu_ms": cpu, "asleep_ms": round(asleep, 3),
        "other_threads_cpu_ms": event.get("other_threads_cpu_ms"),
        "longest_step_ms": step, "longest_step": event.get("longest_step", ""),
        # a loop's own tick (0.1-1 ms of CPU as a rule): a long one ran what a lockstep tick
        # runs in < 8 ms (stop 36), so its CPU clock ran on a slow virtual CPU, or it was not
        "step_is_tick": str(event.get("longest_step", "")).startswith(_TICK_STEPS),
        "shares_ms": {k: round(v, 3) for k, v in shares.items()},
        "verdict": verdict,
        "cause": "machine" if verdict in MACHINE_VERDICTS else (
            "ours" if verdict in OUR_VERDICTS else UNATTRIBUTED),
    }  # fmt: skip


def attribution(record: dict[str, Any], wins: Sequence[Window],
                stalls: Sequence[dict[str, Any]], misses: Sequence[dict[str, Any]],
                flight: dict[str, Any] | None = None,
                slow_steps: Sequence[dict[str, Any]] = ()) -> dict[str, Any]:  # fmt: skip
    """Every position-loop gap over ``STALL_S`` (the service's position stalls) and every
    deadline miss (its ``misses``), each with the steal in it (``record``: the steal
    samples) and its verdict (:func:`attribute`), the window it fell in ("phase kind", or
    "" outside them), and counted by verdict: over the flight and in the attack windows.
    ``flight``: the flight log's columns; each event then gives the longest position tick
    it holds (``position_tick_max_ms``, the log's ``compute_us``: the controller's tick
    alone, so a long position step with a short tick in it spent its time elsewhere).
    ``slow_steps``: the service's slow control steps (stats ``slow_steps.steps``); each
    event then gives those in its interval, part by part (:func:`slow_parts`)."""
    cols = steal.Columns.of(record)
    share = None
    if cols is not None and wins:
        usual = cols.stretch(max(wins[0].t0_s, float(cols.t_s[0])),
                             min(wins[-1].t1_s, float(cols.t_s[-1])))  # fmt: skip
        share = None if usual is None or not usual["ms"] else usual["thread_cpu_ms"] / usual["ms"]
    events = []
    for ev in [*(s for s in stalls if s["loop"] == "position"), *misses]:
        parts = slow_parts(slow_steps, ev)
        out = attribute(dict(_stall_steal(cols, ev), usual_cpu_share=share, **parts))
        if flight is not None:
            end_s = ev["t_s"] + (1e-3 * ev.get("compute_ms", 0.0) if ev.get("deadline_miss")
                                 else 0.0)  # fmt: skip
            t = flight["t_s"]
            inside = (t >= end_s - 1e-3 * ev["interval_ms"]) & (t <= end_s)
            out["position_tick_max_ms"] = (round(float(np.max(flight["compute_us"][inside]))
                                           * 1e-3, 3) if inside.any() else None)  # fmt: skip
        out.update(parts)
        out["window"] = next((f"{w.phase} {w.kind}" for w in wins
                              if w.t0_s <= ev["t_s"] <= w.t1_s), "")  # fmt: skip
        out["attack"] = bool(out["window"]) and not out["window"].endswith("calm")
        events.append(out)
    events.sort(key=lambda e: e["t_s"])
    groups = {"position_gaps": ("position", "gap"), "attitude_misses": ("attitude", "miss"),
              "position_misses": ("position", "miss")}  # fmt: skip

    def count(pick: list[dict[str, Any]]) -> dict[str, dict[str, int]]:
        out = {}
        for key, (loop, kind) in groups.items():
            mine = [e for e in pick if e["loop"] == loop and e["kind"] == kind]
            out[key] = {"total": len(mine), **{v: sum(e["verdict"] == v for e in mine)
                                               for v in VERDICTS},
                        "machine": sum(e["cause"] == "machine" for e in mine),
                        "ours": sum(e["cause"] == "ours" for e in mine),
                        "our_step_a_tick": sum(e["verdict"] == OUR_STEP and e["step_is_tick"]
                                               for e in mine)}  # fmt: skip
        return out

    return {"sampled": cols is not None, "usual_cpu_share": share, "events": events,
            "flight": count(events),
            "attack_windows": count([e for e in events if e["attack"]])}  # fmt: skip


BURST_CPU_MS = 20.0  # a burst: a step with more of the loops' thread's CPU than this


def slow_parts(slow_steps: Sequence[dict[str, Any]], ev: dict[str, Any]) -> dict[str, Any]:
    """The slow control steps (``StepParts``) that started in a stall's or miss's interval:
    how many (``slow_steps``), their thread CPU (``slow_steps_cpu_ms``), their parts' wall
    time summed by name (``slow_parts_ms``), the part with the most (``slow_part``, "" with
    none) and the compiles in them (``slow_steps_compiles``); their context switches
    (``slow_steps_voluntary_switches``, ``slow_steps_involuntary_switches``; None: the
    service did not count them) and their wall time beyond their CPU time split by how
    the thread left its CPU: in steps that switched out voluntarily (``slow_steps_slept_ms``:
    it slept, ours) and in steps that never switched out (``slow_steps_stolen_ms``: it
    never left its CPU, so the virtual CPU itself stood still: the hypervisor's steal)."""
    end_s = ev["t_s"] + (1e-3 * ev.get("compute_ms", 0.0) if ev.get("deadline_miss") else 0.0)
    start_s = end_s - 1e-3 * ev["interval_ms"]
    mine = [s for s in slow_steps if start_s - 1e-6 <= s["t_s"] <= end_s + 1e-6]
    parts: dict[str, float] = {}
    for step in mine:
        for name, ms in step["parts_ms"].items():
            key = f"{step['loop']}.{name}"
            parts[key] = parts.get(key, 0.0) + ms
    known = [s for s in mine if s.get("voluntary_switches") is not None]

    def off_cpu_ms(pick: Sequence[dict[str, Any]]) -> float:
        off = (float(s["wall_ms"]) - float(s["thread_cpu_ms"]) for s in pick)
        return round(sum(max(0.0, ms) for ms in off), 3)

    return {"slow_steps": len(mine),
            "slow_steps_cpu_ms": round(sum(s["thread_cpu_ms"] for s in mine), 3),
            "slow_steps_voluntary_switches": (sum(s["voluntary_switches"] for s in known)
                                              if known else None),
            "slow_steps_involuntary_switches": (sum(s["involuntary_switches"] for s in known)
                                                if known else None),
            "slow_steps_slept_ms": off_cpu_ms([s for s in known if s["voluntary_switches"]]),
            "slow_steps_stolen_ms": off_cpu_ms([s for s in known if not s["voluntary_switches"]
                                                and not s["involuntary_switches"]]),
            "slow_parts_ms": {k: round(v, 3) for k, v in parts.items() if v >= 0.05},
            "slow_part": max(parts, key=parts.__getitem__) if parts else "",
            "slow_steps_compiles": sum(s.get("compiles", 0) for s in mine)}  # fmt: skip


def attribution_summary(report: dict[str, Any]) -> str:
    """The gaps over 12 ms and the deadline misses by verdict (the report's ``attribution``)."""
    att = report.get("attribution")
    if not att:
        return "attribution: none (no stalls or misses traced by this service)"
    lines = []
    for scope, name in (("flight", "whole flight"), ("attack_windows", "attack windows")):
        parts = []
        for key, label in (("position_gaps", "position gaps > 12 ms"),
                           ("attitude_misses", "attitude misses"),
                           ("position_misses", "position misses")):  # fmt: skip
            c = att[scope][key]
            by = ", ".join(f"{v} {c[v]}" + (f" ({c['our_step_a_tick']} a loop's own tick)"
                                            if v == OUR_STEP and c["our_step_a_tick"] else "")
                           for v in VERDICTS if c[v])  # fmt: skip
            parts.append(f"{label} {c['total']}" + (f" ({by})" if by else ""))
        lines.append(f"attributed, {name}: " + "; ".join(parts))
    if not att["sampled"]:
        lines.append("(steal not sampled: none counted)")
    lines.append(slow_steps_summary(report.get("stats_slow_steps") or {}))
    return "\n".join(lines)


def slow_steps_summary(slow: dict[str, Any]) -> str:
    """The service's slow control steps (stats ``slow_steps``): how many per loop, the
    compiles after warm-up, the largest parts, and bursts (steps with over 20 ms of CPU)."""
    if not slow:
        return "slow control steps: not traced by this service"
    steps = slow.get("steps", [])
    by: dict[str, list[float]] = {}
    for step in steps:
        by.setdefault(f"{step['loop']}.{step['slowest_part']}", []).append(
            step["thread_cpu_ms"])
    parts = ", ".join(f"{k} {len(v)} (max {max(v):.1f} ms CPU)"
                      for k, v in sorted(by.items(), key=lambda kv: -max(kv[1])))
    bursts = sum(step["thread_cpu_ms"] > BURST_CPU_MS for step in steps)
    return (f"slow control steps (kept {len(steps)}): position {slow.get('position', 0)}, "
            f"attitude {slow.get('attitude', 0)}; compiles after warm-up "
            f"{slow.get('compiles_after_warm_up', 0)}; over {BURST_CPU_MS:g} ms of CPU "
            f"{bursts}; slowest part: {parts or 'none'}")  # fmt: skip


def error_series(
    flight: dict[str, Any], truth: dict[str, Any], every: int = 10
) -> tuple[FloatArray, FloatArray]:
    """(monotonic t s, error m) of every ``every``-th ground-truth sample under offboard
    control (for the figure)."""
    t_s, vt_s = flight["t_s"], flight["vehicle_t_s"]
    offset_s = float(np.median(vt_s - t_s))
    off = flight["phase"] == "offboard"
    lo, hi = vt_s[off].min(), vt_s[off].max()
    span = (truth["t_s"] >= lo) & (truth["t_s"] <= hi)
    tt = truth["t_s"][span][::every]
    ref = np.stack([np.interp(tt, vt_s, flight[f"ref_pos_{a}_m"]) for a in "ned"], axis=1)
    pos = np.stack([truth[f"pos_{a}_m"][span][::every] for a in "ned"], axis=1)
    return tt - offset_s, np.linalg.norm(pos - ref, axis=1)


# -- issue 21's targets ------------------------------------------------------------------------


@dataclass(frozen=True)
class Verdict:
    target: str
    measured: str
    met: bool | None  # None: not judged by this run (said why in ``measured``)


def _worst(windows: Sequence[dict[str, Any]], key: str, fn: Any = max) -> float:
    """The worst of ``key`` over ``windows`` (NaN when none has it: judged not met)."""
    values = [w[key] for w in windows if w.get(key) is not None]
    return float(fn(values)) if values else math.nan


def _text(value: float, fmt: str) -> str:
    return "no data" if math.isnan(value) else fmt.format(value)


def figure8_rmse_m(windows: Sequence[dict[str, Any]]) -> float:
    """The real-time figure-8's RMSE over all its windows (calm and attacks), by duration."""
    ws = [w for w in windows if w["phase"] == "figure8" and w.get("rmse_m") is not None]
    total_s = sum(w["duration_s"] for w in ws)
    if not total_s:
        return math.nan
    return math.sqrt(sum(w["rmse_m"] ** 2 * w["duration_s"] for w in ws) / total_s)


def body_rate_verdict(report: dict[str, Any]) -> Verdict:
    """Body rates in real time beside the hogs against the same figure-8 in lockstep
    (``report["lockstep_rmse_m"]``); judged in body-rate mode only."""
    target = "body-rate figure-8 RMSE = lockstep's +-20 % (two hogs)"
    rmse = figure8_rmse_m(report["windows"])
    lockstep = report.get("lockstep_rmse_m")
    if report["attitude_mode"] != "rates" or lockstep is None or math.isnan(rmse):
        why = "body-rate mode and its lockstep flight only: --attitude-mode rates"
        return Verdict(target, f"real time {_text(rmse, '{:.3f} m')}; not judged ({why})", None)
    ratio = rmse / lockstep
    return Verdict(target, f"real time {rmse:.4f} m, lockstep {lockstep:.4f} m: x{ratio:.2f}",
                   abs(ratio - 1.0) <= 0.20)  # fmt: skip


def judge(report: dict[str, Any]) -> list[Verdict]:
    """Issue 21's targets against the attack windows of ``report`` (see :func:`window_figures`)."""
    attacks = [w for w in report["windows"] if w["kind"] != "calm"]
    hover = [w for w in attacks if w["phase"] == "hover"]
    quaternion = report["attitude_mode"] == "quaternion"
    fifo = report["fifo_applied"]
    out = []
    gap = _worst(attacks, "position_max_gap_ms")
    out.append(Verdict("no position-loop gap over 20 ms", _text(gap, "{:.1f} ms"), gap <= 20.0))
    strict = "... none over 12 ms (quaternion mode, FIFO)"
    if quaternion and fifo:
        out.append(Verdict(strict, _text(gap, "{:.1f} ms"), gap <= 12.0))
    else:
        why = "body-rate mode" if not quaternion else "FIFO not applied"
        out.append(Verdict(strict, f"not judged ({why})", None))
    rate = _worst(attacks, "attitude_rate_hz", min)
    late = sum(w["attitude_late_ticks"] for w in attacks)
    misses = report["stats_loops"].get("attitude", {}).get("deadline_misses")
    text = (f"{_text(rate, '{:.1f} Hz')} (slowest window), {late} late ticks in the windows; "
            f"{misses} deadline misses in the whole flight")  # fmt: skip
    if quaternion:
        out.append(Verdict("attitude loop >= 199 Hz, 0 deadline misses (quaternion mode)", text,
                           rate >= 199.0 and late == 0))  # fmt: skip
    else:
        out.append(Verdict("attitude loop >= 199 Hz, 0 deadline misses (quaternion mode)",
                           f"{text} (body-rate mode: not judged)", None))  # fmt: skip
    err = _worst(hover, "max_error_m")
    out.append(Verdict("hover error during every attack <= 0.10 m", _text(err, "{:.3f} m"),
                       err <= 0.10))  # fmt: skip
    loss = _worst(attacks, "altitude_loss_m")
    out.append(Verdict("no loss of altitude over 0.1 m", _text(loss, "{:.3f} m"), loss <= 0.1))
    held = _worst(attacks, "offboard_fraction", min)
    out.append(Verdict("offboard held >= 99.9 % under invalid traffic",
                       _text(100.0 * held, "{:.2f} %"), held >= 0.999))  # fmt: skip
    fuzz_err = _worst([w for w in hover if "fuzz" in w["kind"].split("+")], "max_error_m")
    out.append(Verdict("no excursion over 0.10 m from implausible MAVLink (hover, fuzz)",
                       _text(fuzz_err, "{:.3f} m"), fuzz_err <= 0.10))  # fmt: skip
    med, p99 = report["attack_compute_us"]["median"], report["attack_compute_us"]["p99"]
    out.append(Verdict("position tick compute median <= 300 us (real time)",
                       _text(med, "{:.0f} us"), med <= 300.0))  # fmt: skip
    out.append(Verdict("position tick compute p99 <= 1 ms", _text(p99, "{:.0f} us"),
                       p99 <= 1000.0))  # fmt: skip
    rss = report["control_rss"]
    if rss["samples"]:
        out.append(Verdict("control process RSS flat (+-5 %) through the attacks",
                           f"{rss['start_mb']:.1f} -> {rss['end_mb']:.1f} MB, widest "
                           f"{100 * rss['max_deviation']:+.1f} %",
                           abs(rss["max_deviation"]) <= 0.05))  # fmt: skip
    out.append(body_rate_verdict(report))
    return out


def format_table(report: dict[str, Any]) -> str:
    keys = [("position_max_gap_ms", "gap ms", "{:.1f}"),
            ("attitude_rate_hz", "att Hz", "{:.1f}"),
            ("attitude_late_ticks", "late", "{:d}"),
            ("max_error_m", "err m", "{:.3f}"),
            ("altitude_loss_m", "alt loss", "{:.3f}"),
            ("offboard_fraction", "offb %", "{:.4f}"),
            ("position_compute_us_median", "med us", "{:.0f}"),
            ("position_compute_us_p99", "p99 us", "{:.0f}"),
            ("helpers_cpu_share", "helpers", "{:.2f}"),
            ("load_avg_1min", "load", "{:.1f}"),
            ("steal_ms_per_s", "steal", "{:.1f}")]  # fmt: skip
    kind_w = max([7, *(len(w["kind"]) for w in report["windows"])])  # "flood+fuzz": 10
    head = f"{'phase':8s} {'window':{kind_w}s}" + "".join(f" {k[1]:>9s}" for k in keys)
    lines = [head]
    for w in report["windows"]:
        cells = []
        for key, _, fmt in keys:
            v = w.get(key)
            if key == "offboard_fraction" and v is not None:
                v = 100.0 * v
                fmt = "{:.2f}"
            cells.append(f" {fmt.format(v) if v is not None else '-':>9s}")
        lines.append(f"{w['phase']:8s} {w['kind']:{kind_w}s}" + "".join(cells))
    lines.append("")
    lines.append(f"autopilot {report.get('autopilot', 'px4')}; MAVLink signing "
                 f"{'on' if report.get('signing') else 'off'}; attacks of "
                 f"{report.get('window_s', 10.0):g} s"
                 + ("; the fuzzer forges state" if report.get("forge") else "")
                 + _freeze_text(report.get("freeze")))  # fmt: skip
    refused = report.get("link_refused") or {}
    if report.get("fuzz_datagrams_sent"):
        lines.append(f"MAVLink: the fuzzer sent {report['fuzz_datagrams_sent']} datagrams; the "
                     f"link refused {refused.get('total', 0)} (throttled "
                     f"{refused.get('throttled', 0)}, bad signature "
                     f"{refused.get('bad_signature', 0)}, other sender "
                     f"{refused.get('other_sender', 0)})")  # fmt: skip
    load = report["load_avg"]
    lines.append(f"machine load (1/5/15 min): start {load['start']}, end {load['end']}; "
                 f"{report['cpus']} CPUs; {report['hogs']} CPU hogs; attitude mode "
                 f"{report['attitude_mode']}; loops SCHED_FIFO "
                 f"{'applied' if report['fifo_applied'] else 'NOT applied'}; SITL (the autopilot) "
                 f"{'SCHED_FIFO' if report.get('sitl_fifo') else 'normal scheduling'}")  # fmt: skip
    lines.append(stall_summary(report))
    lines.append(steal_summary(report))
    lines.append(attribution_summary(report))
    lines.append(floor_summary(report.get("floor_probe")))
    lines.append(f"{'issue 21 target':62s} {'verdict':9s} measured")
    for v in judge(report):
        verdict = "n/a" if v.met is None else ("met" if v.met else "NOT MET")
        lines.append(f"{v.target:62s} {verdict:9s} {v.measured}")
    return "\n".join(lines)


def floor_summary(floor: dict[str, Any] | None) -> str:
    """The loops beside the bare loops (``floor_figures``), over the flight and the attacks."""
    if not floor:
        return "machine floor: not probed (--no-probe)"
    lines = []
    meta = floor.get("probes", {})
    how = ", ".join(f"{w} " + (f"SCHED_FIFO {m.get('priority')}" if m.get("fifo_applied")
                               else "NOT SCHED_FIFO") for w, m in sorted(meta.items()))
    lines.append(f"machine floor (bare 200 Hz loops beside the service: {how}):")
    for scope in ("flight", "attack_windows"):
        part = floor.get(scope) or {}
        if not part:
            continue
        loops = part["loops"]
        text = (f"  {scope.replace('_', ' ')}: loops: position gaps > 12 ms "
                f"{loops['position_gaps_over_12ms']}, attitude misses {loops['attitude_misses']}")
        if scope == "flight":
            text += (f", lateness ms p50/p99/max position "
                     f"{_triple(loops['position_lateness_ms'])}, attitude "
                     f"{_triple(loops['attitude_lateness_ms'])}")
        for wake in floor.get("probed", []):
            p = part[wake]
            text += (f"; {wake}: misses {p['misses']}, gaps > 12 ms {p['gaps_over_12ms']} "
                     f"(at 100 Hz {p['gaps_over_12ms_100hz']})")
            if scope == "flight":
                text += f", lateness {_triple(p['lateness_ms'])}"
        lines.append(text)
    shared = floor.get("shared") or {}
    if shared:
        lines.append("  the loops' gaps > 12 ms and attitude misses with a bare loop's tick "
                     f">= {shared['late_ms']:g} ms late in them: " + "; ".join(
                         f"{loop} {shared[loop]['total']}: " + ", ".join(
                             f"{w} {n} (by chance {shared[loop]['by_chance'][w]})"
                             for w, n in shared[loop]["with_probe_late"].items())
                         for loop in ("position", "attitude")))  # fmt: skip
    return "\n".join(lines)


def _triple(late: dict[str, float | None]) -> str:
    return "/".join("-" if late[k] is None else f"{late[k]:.2f}" for k in ("p50", "p99", "max"))


def _freeze_text(freeze: dict[str, Any] | None) -> str:
    """``--freeze``'s line part: which helper, for how long, and whether it was found."""
    if not freeze:
        return ""
    found = sum(1 for e in freeze["events"] if e.get("pid"))
    return (f"; helper '{freeze['helper']}' SIGSTOPped {freeze['seconds']:g} s, "
            f"{found} of {len(freeze['events'])} times found")


def steal_summary(report: dict[str, Any]) -> str:
    """The hypervisor's steal (ms a second, all CPUs) over the run and in the gaps."""
    st = report.get("steal", {})
    if not st.get("position_gaps", {}).get("sampled"):
        return "steal time: not sampled"
    parts = []
    for key, name in (("position_gaps", "position-loop gaps > 12 ms"),
                      ("attitude_late", "late attitude ticks")):  # fmt: skip
        a = st[key]
        rate = a["steal_in_gaps_ms_per_s"]
        parts.append(f"{name}: {len(a['gaps'])}, {a['gaps_with_steal']} with steal, "
                     f"{_text(math.nan if rate is None else rate, '{:.0f}')} ms/s in them")
    return (f"steal time (ms a second, {st['cpus']} CPUs, column 'steal'): over the run "
            f"{st['position_gaps']['steal_ms_per_s']:.1f}; " + "; ".join(parts))


def stall_summary(report: dict[str, Any]) -> str:
    """The service's own account of its real-time stalls (its stats' ``stalls``, the latest
    ones kept) and of the garbage collector in the loops' thread."""
    stalls = report.get("stats_stalls", [])
    gc = report.get("stats_gc", {})
    parts = []
    for loop in ("position", "attitude"):
        mine = [s for s in stalls if s["loop"] == loop]
        if not mine:
            parts.append(f"{loop} 0")
            continue
        on_cpu = sum(s["thread_cpu_ms"] >= 0.5 * s["interval_ms"] for s in mine)
        gc_ms = max(s["gc_ms"] for s in mine)
        parts.append(f"{loop} {report['stats_counters'].get(f'{loop}_stalls', len(mine))} "
                     f"(of the latest {len(mine)}: {on_cpu} on the loops' own CPU, "
                     f"longest {max(s['interval_ms'] for s in mine):.1f} ms, "
                     f"collections <= {gc_ms:.1f} ms of one)")  # fmt: skip
    text = "stalls (ticks later than 12 ms or two periods): " + "; ".join(parts)
    named = sorted((s for s in stalls if s.get("longest_step")),
                   key=lambda s: -s["interval_ms"])[:3]  # fmt: skip
    if named:
        text += "\nthe longest stalls' longest event-loop step: " + "; ".join(
            f"{s['interval_ms']:.1f} ms {s['loop']}: {s['longest_step_ms']:.1f} ms "
            f"{s['longest_step']}" for s in named)  # fmt: skip
    if gc:
        text += (f"\ngarbage collector in the loops' thread: collections by generation "
                 f"{gc.get('loop_thread_collections')}, longest "
                 f"{gc.get('loop_thread_max_pause_ms')} ms (all threads "
                 f"{gc.get('collections')}, longest {gc.get('max_pause_ms')} ms)")
    return text


def write_figure(report: dict[str, Any], series: dict[str, FloatArray], path: Any) -> None:
    """Position-loop gaps and tracking error against time, the attack windows shaded."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    t_zero = report["windows"][0]["t0_s"]
    probed = sorted(k[len("probe_"):-len("_t_s")] for k in series
                    if k.startswith("probe_") and k.endswith("_t_s"))  # fmt: skip
    fig, axes = plt.subplots(4 if probed else 3, 1, figsize=(10, 9 if probed else 7),
                             sharex=True)  # fmt: skip
    ax_gap, ax_att, ax_err = axes[0], axes[1], axes[-1]
    ax_gap.plot(series["pos_t_s"][1:] - t_zero, np.diff(series["pos_t_s"]) * 1e3, lw=0.5,
                color="tab:blue")  # fmt: skip
    ax_gap.axhline(20.0, color="k", lw=0.6, ls="--")
    ax_gap.set_ylabel("position tick\ninterval, ms")
    ax_gap.set_yscale("log")
    att = series["att_t_s"]
    ax_att.plot(att[1:] - t_zero, np.diff(att) * 1e3, lw=0.4, color="tab:purple")
    ax_att.set_ylabel("attitude send\ninterval, ms")
    ax_att.set_yscale("log")
    if probed:  # the bare loops' lateness, the loops' gaps over 12 ms marked on it
        ax_probe = axes[2]
        for wake, colour in zip(probed, ("tab:olive", "tab:brown", "tab:gray"), strict=False):
            late = np.maximum(series[f"probe_{wake}_late_ms"], 1e-3)
            ax_probe.plot(series[f"probe_{wake}_t_s"] - t_zero, late, lw=0.4, color=colour,
                          label=f"probe ({wake}) lateness")  # fmt: skip
        pos = series["pos_t_s"]
        big = np.flatnonzero(np.diff(pos) > STALL_S)
        if big.size:
            ax_probe.scatter(pos[big + 1] - t_zero, np.diff(pos)[big] * 1e3, s=10,
                             color="tab:blue", marker="v", zorder=3,
                             label=f"loops' position gaps > 12 ms ({big.size}), ms")  # fmt: skip
        ax_probe.axhline(5.0, color="k", lw=0.6, ls="--")
        ax_probe.set_yscale("log")
        ax_probe.set_ylabel("bare loop\nlateness, ms")
        ax_probe.legend(fontsize=6, loc="lower right", ncol=3)
    ax_err.plot(series["err_t_s"] - t_zero, series["err_m"], lw=0.6, color="tab:red")
    ax_err.axhline(0.10, color="k", lw=0.6, ls="--")
    ax_err.set_ylabel("error to the\nreference, m")
    ax_err.set_xlabel("s since the first window")
    colours = {"flood": "tab:orange", "rotate": "tab:green", "replay": "tab:cyan",
               "flap": "tab:pink", "fuzz": "tab:gray"}  # fmt: skip
    for w in report["windows"]:
        if w["kind"] == "calm":
            continue
        for ax in axes:
            ax.axvspan(w["t0_s"] - t_zero, w["t1_s"] - t_zero,
                       color=colours.get(w["kind"], "tab:brown"),
                       alpha=0.25, lw=0)  # fmt: skip
        ax_gap.text((w["t0_s"] + w["t1_s"]) / 2 - t_zero, ax_gap.get_ylim()[1], w["kind"],
                    ha="center", va="top", fontsize=7)  # fmt: skip
    marks = {STEAL: ("tab:red", "v"), RUNQUEUE: ("tab:orange", "v"),
             COLLECTION: ("tab:green", "o"), OUR_STEP: ("tab:blue", "o"),
             GIL_WAIT: ("tab:purple", "o"), UNATTRIBUTED: ("k", "x")}  # fmt: skip
    events = (report.get("attribution") or {}).get("events", [])
    for verdict, (colour, marker) in marks.items():
        for ax, loop, kind in ((ax_gap, "position", "gap"), (ax_att, "attitude", "miss")):
            mine = [e for e in events
                    if e["verdict"] == verdict and e["loop"] == loop and e["kind"] == kind]
            if mine:
                ax.scatter([e["t_s"] - t_zero for e in mine],
                           [e["interval_ms"] for e in mine], s=14, color=colour,
                           marker=marker, zorder=3,
                           label=f"{verdict} ({len(mine)})")  # fmt: skip
    for ax in (ax_gap, ax_att):
        if ax.get_legend_handles_labels()[0]:
            ax.legend(fontsize=6, loc="lower right", ncol=3, title_fontsize=6,
                      title="gaps > 12 ms" if ax is ax_gap else "deadline misses")  # fmt: skip
    split = [w["t0_s"] for w in report["windows"] if w["phase"] == "figure8"]
    if split:
        for ax in axes:
            ax.axvline(split[0] - t_zero, color="k", lw=0.8)
    load = report["load_avg"]
    fig.suptitle(f"bench --attack: hover, then the windy figure-8 ({report['attitude_mode']} "
                 f"mode, {report['hogs']} CPU hogs, load {load['start'][0]:.1f}-"
                 f"{load['end'][0]:.1f})", fontsize=9)  # fmt: skip
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
