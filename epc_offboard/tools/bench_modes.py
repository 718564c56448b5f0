"""`epc-offboard bench --modes`: body rates against quaternion, flown on the strict SITL.

Issue 20's flights, each once per attitude mode in one run, on the bundled SITL's PX4 (or
ArduPilot) personality with its delays, in real time (optionally beside ``--hogs N``
CPU-bound processes, to see what a loaded companion computer does) and in lockstep:

* ``circle``: the circle scenario, no wind;
* ``figure8``: the figure-8 scenario, no wind;
* ``figure8-wind``: the figure-8 in the scenario's 3 m/s wind;
* ``hover-cold``: the hover scenario on a cold kernel cache: the service flies the numpy
  twins of its kernels, as a cold start does (``EPC_OFFBOARD_JIT=0``, an empty
  ``NUMBA_CACHE_DIR``; the cold start's background compile is left out).

Modes: ``epc`` (body rates from the delay-aware attitude EPC, ``attitude.mode = "epc"``) and
``autopilot`` (quaternion + thrust, the autopilot's attitude loop). Each flight is an
``epc-offboard sim`` run (``--gcs-port 0``); judged on the SITL's ground truth:

* tracking RMSE / max error after the scenario's settle time (the sim report's);
* max tilt over offboard outside the entry (the first ``ENTRY_S`` of each stretch of
  offboard: entering into wind takes its tilt, a separate target), flips (tilt over 90 deg
  at any time), the highest altitude above the reference under offboard (a climb over 1 m
  counts);
* failsafes, body-rate ticks that fell back to quaternion, loop rates and deadline misses,
  and the rate response the attitude loop identified.

The JSON holds every flight, the body-rate / quaternion ratio of each (RMSE, max error), the
real time / lockstep ratio of each mode's RMSE, the machine's load (1-minute average, before
and after each flight) and CPU count, and the hogs; the figure (FILE with .png) draws them.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import subprocess
import sys
import tempfile
import time
import tomllib
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from epc_offboard.common.bundled import scenario_dir
from epc_offboard.common.children import launched_env
from epc_offboard.common.configio import dump_toml

MODES = ("epc", "autopilot")  # body rates, quaternion
FLIGHTS = ("circle", "figure8", "figure8-wind", "hover-cold")
TIMINGS = ("realtime", "lockstep")
ENTRY_S = 2.0  # s after each (re-)entry into offboard whose tilt is the entry's
CLIMB_LIMIT_M = 1.0  # issue 20: no climb over 1 m above the reference
TILT_LIMIT_DEG = 35.0  # issue 20: no tilt over 35 deg outside the wind entry
FLIP_DEG = 90.0
# "body rates no worse than quaternion": RMSE within this ratio plus this slack (a few
# millimetres on a hover is noise, not a worse mode)
NO_WORSE_RATIO = 1.2
NO_WORSE_SLACK_M = 0.005
# a core's worth of CPU that ends with its bench, even a SIGKILLed one (a hog left behind
# spins forever beside whatever runs next: the next bench's figures, a flight)
_HOG = ("from epc_offboard.common.children import die_with_launcher\n"
        "die_with_launcher()\n"
        "while True: pass\n")  # fmt: skip


@dataclass(frozen=True)
class FlightSpec:
    name: str
    scenario: str  # the bundled scenario it is made from
    wind: str  # sim --wind
    cold: bool = False  # a cold kernel cache


SPECS = {
    "circle": FlightSpec("circle", "circle", "0,0"),
    "figure8": FlightSpec("figure8", "figure8", "0,0"),
    "figure8-wind": FlightSpec("figure8-wind", "figure8", "3,45"),
    "hover-cold": FlightSpec("hover-cold", "hover", "0,0", cold=True),
}


def add_modes_arguments(bench: argparse.ArgumentParser) -> None:
    """The flags of ``bench --modes`` (on ``bench``'s parser)."""
    bench.add_argument(
        "--modes",
        action="store_true",
        help="instead: body rates against quaternion mode on the strict SITL (circle, "
        "figure-8, figure-8 in 3 m/s wind, hover from a cold start), real time and lockstep; "
        "with --json also a figure (FILE with .png)",
    )
    bench.add_argument(
        "--timing",
        choices=[*TIMINGS, "both"],
        default="both",
        help="with --modes: real time, lockstep or both",
    )
    bench.add_argument(
        "--flights",
        default=",".join(FLIGHTS),
        metavar="NAME,...",
        help=f"with --modes: which flights ({', '.join(FLIGHTS)})",
    )
    bench.add_argument(
        "--autopilot",
        choices=["px4", "ardupilot"],
        default="px4",
        help="with --modes or --attack: the SITL's personality",
    )
    bench.add_argument(
        "--out",
        default="out/bench-modes",
        metavar="DIR",
        help="with --modes: where each flight's sim output goes",
    )


def scenario_toml(spec: FlightSpec, mode: str) -> str:
    """The bundled scenario of ``spec`` flown in attitude ``mode``: its targets and compare
    list left out (one method per flight; the bench judges), the service's mode set."""
    with (scenario_dir() / f"{spec.scenario}.toml").open("rb") as fh:
        data = tomllib.load(fh)
    data.pop("targets", None)
    data.pop("compare", None)
    service = data.setdefault("service", {})
    service.setdefault("attitude", {})["mode"] = mode
    data["description"] = f"bench --modes: {spec.name}, attitude mode {mode}"
    return dump_toml(data)


def judge(vehicle_dir: Path, report: dict[str, Any]) -> dict[str, Any]:
    """One flight's figures (see the module docstring) from its sim output."""
    vehicle = report["vehicles"][0]
    # here, not at the top: the CLI's parser imports this module (add_modes_arguments), and
    # the analysis imports the scenarios' trajectories and numba
    from epc_offboard.tools.sim.analysis import read_csv_columns
    from epc_offboard.tools.sim.envelope import tilt_deg_of

    flight = read_csv_columns(vehicle_dir / "flight.csv", allow_empty=True)
    truth = read_csv_columns(vehicle_dir / "groundtruth.csv")
    tt = truth["t_s"]
    tilt = tilt_deg_of(np.column_stack([truth[f"q_{a}"] for a in "wxyz"]))
    out: dict[str, Any] = {
        "rmse_m": vehicle["tracking"]["rmse_m"],
        "max_error_m": vehicle["tracking"]["max_error_m"],
        "flips": int(np.any(tilt > FLIP_DEG)),
        "max_tilt_offboard_deg": vehicle.get("max_tilt_deg"),
    }
    t_log = np.asarray(flight.get("vehicle_t_s", np.zeros(0)), dtype=np.float64)
    phase = np.asarray(flight.get("phase", np.full(len(t_log), "")))
    offboard = phase == "offboard"
    # stretches of offboard (a failsafe splits them); the first ENTRY_S of each is entry
    tilt_outside, climb = 0.0, -math.inf
    if np.any(offboard):
        t_off = t_log[offboard]
        breaks = np.flatnonzero(np.diff(t_off) > 0.1)
        starts = np.r_[t_off[0], t_off[breaks + 1]]
        ends = np.r_[t_off[breaks], t_off[-1]]
        for start, end in zip(starts, ends, strict=True):
            window = (tt >= start + ENTRY_S) & (tt <= end)
            if np.any(window):
                tilt_outside = max(tilt_outside, float(tilt[window].max()))
        # the altitude above the reference under offboard, on the log's ticks
        alt = -np.interp(t_off, tt, truth["pos_d_m"])
        ref_alt = -np.asarray(flight["ref_pos_d_m"], dtype=np.float64)[offboard]
        climb = float(np.max(alt - ref_alt))
    out["max_tilt_outside_entry_deg"] = tilt_outside
    out["max_climb_above_ref_m"] = climb
    out["climbs_over_1m"] = int(climb > CLIMB_LIMIT_M)
    warnings = vehicle.get("warnings", {})
    out["failsafes"] = int(warnings.get("failsafes", 0))
    loops = vehicle.get("loops", {})
    out["loops"] = {
        name: {k: loops.get(name, {}).get(k) for k in ("rate_hz", "deadline_misses")}
        for name in ("position", "attitude")
    }
    out["attitude_rate_model"] = vehicle.get("attitude_rate_model")
    stats_path = vehicle_dir / "stats.json"
    counters: dict[str, int] = {}
    if stats_path.exists():
        try:
            counters = json.loads(stats_path.read_text()).get("counters", {})
        except ValueError:
            counters = {}
    out["quaternion_fallback_ticks"] = {
        k: int(counters.get(f"attitude_{k}_fallbacks" if k != "model" else
                            "attitude_model_fallback_ticks", 0))
        for k in ("late", "envelope", "model")
    }  # fmt: skip
    out["finished"] = bool(vehicle.get("finished"))
    out["exit_failures"] = report.get("failures", [])
    return out


def fly(
    spec: FlightSpec, mode: str, timing: str, autopilot: str, out: Path, seed: int
) -> dict[str, Any]:
    """One sim flight of ``spec`` in ``mode``; its figures with the load around it."""
    out.mkdir(parents=True, exist_ok=True)
    scenario = out / "scenario.toml"
    scenario.write_text(scenario_toml(spec, mode))
    report_path = out / "report.json"
    cmd = [
        sys.executable, "-m", "epc_offboard", "sim", "--scenario", str(scenario),
        "--autopilot", autopilot, "--wind", spec.wind, "--seed", str(seed),
        "--gcs-port", "0", "--out", str(out / "sim"), "--json", str(report_path),
        "--realtime" if timing == "realtime" else "--lockstep",
    ]  # fmt: skip
    env = dict(os.environ)
    cache = None
    if spec.cold:
        cache = tempfile.TemporaryDirectory(prefix="bench-modes-numba-")
        env.update(EPC_OFFBOARD_JIT="0", NUMBA_CACHE_DIR=cache.name)
    load_before = os.getloadavg()[0]
    t0 = time.monotonic()
    try:
        with (out / "sim.log").open("wb") as log:
            code = subprocess.run(cmd, stdout=log, stderr=subprocess.STDOUT, env=env).returncode
    finally:
        if cache is not None:
            cache.cleanup()
    result: dict[str, Any] = {
        "flight": spec.name, "mode": mode, "timing": timing, "exit_code": code,
        "wall_s": round(time.monotonic() - t0, 1),
        "load_1min": [round(load_before, 2), round(os.getloadavg()[0], 2)],
    }  # fmt: skip
    try:
        report = json.loads(report_path.read_text())
        result.update(judge(out / "sim" / "vehicle1", report))
    except (OSError, ValueError, KeyError, RuntimeError, IndexError) as exc:
        result["error"] = f"{type(exc).__name__}: {exc}"
    return result


def start_hogs(n: int) -> list[subprocess.Popen[bytes]]:
    """``n`` CPU-bound processes (each a core's worth of a loaded companion computer)."""
    env = dict(os.environ, **launched_env())
    return [subprocess.Popen([sys.executable, "-c", _HOG], env=env) for _ in range(n)]


def stop_hogs(hogs: list[subprocess.Popen[bytes]]) -> None:
    for proc in hogs:
        proc.kill()
        proc.wait()


def _ratio(a: Any, b: Any) -> float | None:
    if isinstance(a, float | int) and isinstance(b, float | int) and b > 0 and math.isfinite(a):
        return round(float(a) / float(b), 3)
    return None


def compare(results: list[dict[str, Any]]) -> dict[str, Any]:
    """Body rates / quaternion per flight and timing; real time / lockstep per flight and
    mode (RMSE and max error)."""
    by = {(r["flight"], r["mode"], r["timing"]): r for r in results}
    modes: dict[str, Any] = {}
    timing: dict[str, Any] = {}
    for flight, _mode, t in by:
        rates, quat = by.get((flight, "epc", t)), by.get((flight, "autopilot", t))
        if rates and quat:
            modes[f"{flight}/{t}"] = {
                k: _ratio(rates.get(k), quat.get(k)) for k in ("rmse_m", "max_error_m")
            }
    for flight, mode, _t in by:
        rt, ls = by.get((flight, mode, "realtime")), by.get((flight, mode, "lockstep"))
        if rt and ls:
            timing[f"{flight}/{mode}"] = {
                k: _ratio(rt.get(k), ls.get(k)) for k in ("rmse_m", "max_error_m")
            }
    return {"body_rates_over_quaternion": modes, "realtime_over_lockstep": timing}


def targets(results: list[dict[str, Any]], ratios: dict[str, Any]) -> dict[str, Any]:
    """Issue 20's targets over every flight, and issue 21's real time / lockstep one."""
    ok = [r for r in results if "error" not in r]
    windy = ratios["realtime_over_lockstep"].get("figure8-wind/epc", {}).get("rmse_m")
    quat = {f"{r['flight']}/{r['timing']}": r["rmse_m"] for r in ok if r["mode"] == "autopilot"}
    worse = {
        k: v["rmse_m"]
        for k, v in ratios["body_rates_over_quaternion"].items()
        if v.get("rmse_m") is not None
        and k in quat
        and v["rmse_m"] * quat[k] > NO_WORSE_RATIO * quat[k] + NO_WORSE_SLACK_M
    }
    return {
        "flips": sum(r["flips"] for r in ok),
        "climbs_over_1m": sum(r["climbs_over_1m"] for r in ok),
        "tilt_over_35_outside_entry": [
            f"{r['flight']}/{r['mode']}/{r['timing']}"
            for r in ok
            if r["max_tilt_outside_entry_deg"] > TILT_LIMIT_DEG
        ],
        "body_rates_worse_than_quaternion": worse,
        "windy_figure8_body_rates_realtime_over_lockstep": windy,
        "windy_figure8_within_20_percent": None if windy is None else abs(windy - 1.0) <= 0.2,
        "flights_failed": [
            f"{r['flight']}/{r['mode']}/{r['timing']}"
            for r in results
            if "error" in r or not r.get("finished")
        ],
    }


def _num(value: Any) -> float:
    """A report's figure, NaN when it has none (a flight that never tracked)."""
    return float(value) if isinstance(value, float | int) else math.nan


def format_table(results: list[dict[str, Any]]) -> str:
    head = (
        f"{'flight':13s} {'mode':9s} {'timing':8s} {'rmse cm':>8s} {'max cm':>7s} "
        f"{'tilt*':>6s} {'climb':>6s} {'flip':>4s} {'fs':>3s} {'q-fb':>5s} "
        f"{'att Hz':>6s} {'load':>11s}"
    )
    lines = [head, "-" * len(head)]
    for r in results:
        if "error" in r:
            lines.append(f"{r['flight']:13s} {r['mode']:9s} {r['timing']:8s} {r['error']}")
            continue
        fb = sum(r["quaternion_fallback_ticks"].values())
        att = r["loops"]["attitude"]["rate_hz"]
        rmse, worst = (_num(r[k]) for k in ("rmse_m", "max_error_m"))
        lines.append(
            f"{r['flight']:13s} {r['mode']:9s} {r['timing']:8s} "
            f"{100 * rmse:8.2f} {100 * worst:7.1f} "
            f"{r['max_tilt_outside_entry_deg']:6.1f} {r['max_climb_above_ref_m']:6.2f} "
            f"{r['flips']:4d} {r['failsafes']:3d} {fb:5d} {att or 0:6.1f} "
            f"{r['load_1min'][0]:5.1f}-{r['load_1min'][1]:<5.1f}"
        )
    lines.append("tilt*: max tilt outside the first 2 s of each entry (deg); climb: max "
                 "altitude above the reference (m); fs: failsafes; q-fb: body-rate ticks "
                 "flown as quaternion; load: 1-min load average before-after")  # fmt: skip
    return "\n".join(lines)


def write_figure(report: dict[str, Any], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    results = [r for r in report["flights"] if "error" not in r]
    timings = [t for t in TIMINGS if any(r["timing"] == t for r in results)]
    flights = [f for f in FLIGHTS if any(r["flight"] == f for r in results)]
    fig, axes = plt.subplots(2, len(timings), figsize=(6 * len(timings), 7), squeeze=False)
    width = 0.38
    for col, timing in enumerate(timings):
        for row, (key, scale, label) in enumerate(
            (
                ("rmse_m", 100.0, "RMSE [cm]"),
                ("max_tilt_outside_entry_deg", 1.0, "max tilt outside entry [deg]"),
            )
        ):
            ax = axes[row][col]
            for i, mode in enumerate(MODES):
                values = []
                for flight in flights:
                    r = next((r for r in results if (r["flight"], r["mode"], r["timing"])
                              == (flight, mode, timing)), None)  # fmt: skip
                    values.append(scale * r[key] if r and r.get(key) is not None else np.nan)
                xs = np.arange(len(flights)) + (i - 0.5) * width
                name = "body rates" if mode == "epc" else "quaternion"
                ax.bar(xs, values, width, label=name)
            if key == "max_tilt_outside_entry_deg":
                ax.axhline(TILT_LIMIT_DEG, color="red", lw=0.8, ls="--")
            ax.set_xticks(np.arange(len(flights)), flights)
            ax.set_ylabel(label)
            ax.set_title(f"{timing}")
            ax.legend()
    load = report["machine"]
    fig.suptitle(
        f"bench --modes ({report['autopilot']}): body rates vs quaternion; "
        f"{load['cpus']} CPUs, {report['hogs']} hogs beside real time, load "
        f"{load['load_1min_min']:.1f}-{load['load_1min_max']:.1f}"
    )
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)


def run_modes_bench(args: argparse.Namespace) -> int:
    flights = [f.strip() for f in str(args.flights).split(",") if f.strip()]
    unknown = [f for f in flights if f not in SPECS]
    if unknown or args.hogs < 0:
        print(f"epc-offboard bench --modes: unknown flight(s) {unknown} (known: "
              f"{', '.join(FLIGHTS)}), or --hogs < 0", file=sys.stderr)  # fmt: skip
        return 2
    timings = list(TIMINGS) if args.timing == "both" else [args.timing]
    out = Path(args.out)
    results: list[dict[str, Any]] = []
    for timing in timings:
        hogs = start_hogs(args.hogs) if timing == "realtime" else []
        try:
            for name in flights:
                for mode in MODES:
                    r = fly(SPECS[name], mode, timing, args.autopilot,
                            out / timing / f"{name}-{mode}", seed=0)  # fmt: skip
                    results.append(r)
                    print(format_table([r]).splitlines()[2], flush=True)
        finally:
            stop_hogs(hogs)
    ratios = compare(results)
    loads = [x for r in results for x in r["load_1min"]]
    report = {
        "autopilot": args.autopilot,
        "hogs": args.hogs,
        "machine": {
            "cpus": os.cpu_count(),
            "load_1min_min": min(loads, default=math.nan),
            "load_1min_max": max(loads, default=math.nan),
        },
        "flights": results,
        "ratios": ratios,
        "targets": None,
    }
    report["targets"] = targets(results, ratios)
    print(format_table(results))
    print(json.dumps(ratios, indent=1))
    print(json.dumps(report["targets"], indent=1))
    if args.json:
        path = Path(args.json)
        path.write_text(json.dumps(report, indent=2) + "\n")
        write_figure(report, path.with_suffix(".png"))
    return 0
