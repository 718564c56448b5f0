"""`epc-offboard figures neuralfly`: issue 24's Neural-Fly table, flown by one command.

Every wind row (:data:`ROWS`: 0, 4.2, 8.5, 12.1 m/s and 8.5 + 2.4 sin t, blowing in the
figure's plane as Neural-Fly's fan array did) by every method (:data:`METHODS`: EPC + LWPR
as the ``neuralfly`` scenario configures it, EPC + LWPR as the product ships it, the Kalman
observer, no adaptation, PD and PX4's own position controller) is one lockstep
``epc-offboard sim --scenario neuralfly`` flight from an empty library per seed (``--seed N``,
or ``--seeds N,N,...``: the held-out seeds the scenario was not tuned on), at most ``--jobs``
(<= 2) at once. Each ``sim`` ends with this command (:func:`~epc_offboard.common.children.
die_with_launcher`), and its SITL and service with it. Written:

* ``RESULTS/neuralfly.json``: per row and method the mean over the seeds of its mean error
  after the first lap (Neural-Fly's metric), their spread, RMSE, max, max tilt, hit rate
  after the first lap, whether sim stopped it, its error against time at 10 Hz (averaged
  over the seeds), and each seed's figures; per row the scenario's targets judged on the
  means; the learning's gain at 8.5 m/s; the seeds, the machine's load before and after,
  the wall and CPU time, the commit;
* ``RESULTS/neuralfly.png``: error against time per wind, ours and the baselines, and the
  means beside Neural-Fly's and the targets;

then the README's table between ``<!-- table:neuralfly -->`` and ``<!-- /table -->`` is
rewritten from that JSON (:func:`render_table`, through :mod:`.readme`, so ``figures readme
--numbers-only`` and the README test read it too). Each flight's full output stays in
``--out``/seedN/ROW/METHOD.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import re
import resource
import shutil
import subprocess
import sys
import time
import tomllib
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import numpy as np

from epc_offboard.common.children import launched_env
from epc_offboard.common.errors import EXIT_OK, EXIT_RUNTIME, UsageError
from epc_offboard.tools.sim.scenario import SCENARIO_DIR, ScenarioConfig, load_scenario
from epc_offboard.tools.targets import evaluate

SCENARIO = "neuralfly"
RESULT_NAME = "neuralfly"  # RESULTS/neuralfly.json and .png, the README's table key
MAX_JOBS = 2  # flights at once: the machine has 2 cores, each flight is 2-3 busy processes
SERIES_DT_S = 0.1  # the error series' step in the JSON (what the figure draws)


@dataclass(frozen=True)
class Row:
    """One wind of Neural-Fly's table (O'Connell et al., Science Robotics 2022, Table 1:
    mean |p - p_d| after the first lap of real flights, cm)."""

    key: str  # directory and JSON key
    label: str
    speed_m_s: float
    neural_fly_cm: float
    profile: str = "steady"


ROWS = (
    Row("0", "0 m/s", 0.0, 2.9),
    Row("4.2", "4.2 m/s", 4.2, 4.2),
    Row("8.5", "8.5 m/s", 8.5, 5.5),
    Row("12.1", "12.1 m/s", 12.1, 8.7),
    Row("8.5sin", "8.5 + 2.4 sin t", 8.5, 7.7, "sine:2.4,1"),
)
GAIN_ROW = "8.5"  # issue 24: the learning's gain, at 8.5 m/s, >= 60 % less error
GAIN_TARGET_PCT = 60.0
# The gain's comparison flight (EPC without adaptation at GAIN_ROW) is judged against a wider
# envelope than the scenario's 2 m from the reference (figures only, never `sim`'s default):
# without integral action it is blown 2 m off within its first lap on seeds 3 and 4, which
# `sim` stops as not sane, and left no error after the first lap to compare with. Flown on,
# it settles about that far off and its mean error after the first lap is measured
COMPARISON_MAX_ERROR_M = 10.0


@dataclass(frozen=True)
class Method:
    key: str  # directory and JSON key
    label: str  # the README's column
    method: str  # controller:adaptation
    ours: bool = False  # drawn solid: the product's controller with learning
    product_lwpr: bool = False  # the service's LWPR defaults, not the scenario's forgetting
    # the gain's baseline: at GAIN_ROW flown within COMPARISON_MAX_ERROR_M of the reference
    gain_baseline: bool = False


METHODS = (
    Method("epc-lwpr", "EPC + LWPR, forgetting (the scenario's)", "epc:lwpr", ours=True),
    Method("epc-lwpr-default", "EPC + LWPR (product default)", "epc:lwpr", True, True),
    Method("epc-kf", "EPC, Kalman observer", "epc:kf"),
    Method("epc-none", "EPC, no adaptation", "epc:none", gain_baseline=True),
    Method("pd", "PD", "pd:none"),
    Method("px4", "PX4's own (`px4:none`)", "px4:none"),
)
SCORED = METHODS[0]  # the row's "ours": its targets and hit rate


def product_lwpr_scenario(directory: Path) -> Path:
    """The ``neuralfly`` scenario without its ``[service.estimator.lwpr]`` override, written
    to ``directory``: EPC + LWPR as the product ships it. Checked on its parse: the only
    difference from the scenario is that table (RuntimeError otherwise)."""
    source = SCENARIO_DIR / f"{SCENARIO}.toml"
    text = source.read_text()
    # the table runs from its header to the next header (or the end); its comment block
    # above it stays, harmless
    cut = re.sub(r"(?ms)^\[service\.estimator\.lwpr\]\n.*?(?=^\[|\Z)", "", text)
    want = tomllib.loads(text)
    service = want.get("service", {})
    service.get("estimator", {}).pop("lwpr", None)
    if "estimator" in service and not service["estimator"]:
        del service["estimator"]
    if tomllib.loads(cut) != want or cut == text:
        raise RuntimeError(f"{source}: could not take [service.estimator.lwpr] out alone")
    directory.mkdir(parents=True, exist_ok=True)
    path = directory / f"{SCENARIO}_product_lwpr.toml"
    path.write_text(f"# {source} without its LWPR override (epc-offboard figures neuralfly)\n"
                    + cut)  # fmt: skip
    return path


def comparison_scenario(directory: Path, max_error_m: float = COMPARISON_MAX_ERROR_M) -> Path:
    """The ``neuralfly`` scenario with ``[envelope] max_error_m`` widened to ``max_error_m``,
    written to ``directory``: the learning's gain's baseline flight (figures only). Checked
    on its parse: the only difference from the scenario is that bound (RuntimeError
    otherwise)."""
    source = SCENARIO_DIR / f"{SCENARIO}.toml"
    text = source.read_text()
    want = tomllib.loads(text)
    if "envelope" in want:
        raise RuntimeError(f"{source}: has its own [envelope]; widen it there")
    wide = text + f"\n[envelope]\nmax_error_m = {max_error_m!r}\n"
    want["envelope"] = {"max_error_m": max_error_m}
    if tomllib.loads(wide) != want:
        raise RuntimeError(f"{source}: could not add [envelope] alone")
    directory.mkdir(parents=True, exist_ok=True)
    path = directory / f"{SCENARIO}_comparison_envelope.toml"
    path.write_text(f"# {source} with a {max_error_m:g} m envelope: the learning's gain's "
                    "baseline (epc-offboard figures neuralfly)\n" + wide)  # fmt: skip
    return path


def sim_argv(row: Row, method: Method, scenario_arg: str, dir_deg: float, seed: int,
             out: Path) -> list[str]:  # fmt: skip
    """The ``epc-offboard sim`` command line of one flight (lockstep, no GCS stream)."""
    controller, adaptation = method.method.split(":")
    return ["sim", "--scenario", scenario_arg, "--controller", controller,
            "--adaptation", adaptation, "--wind", f"{row.speed_m_s:g},{dir_deg:g}",
            "--wind-profile", row.profile, "--seed", str(seed), "--gcs-port", "0",
            "--out", str(out)]  # fmt: skip


def scenario_arg(row: Row, method: Method, product: str, wide: str) -> str:
    """The scenario ``method`` flies ``row`` in: the product's LWPR variant (``product``),
    the gain's baseline at GAIN_ROW in the comparison envelope (``wide``), else the
    scenario itself."""
    if method.product_lwpr:
        return product
    if method.gain_baseline and row.key == GAIN_ROW:
        return wide
    return SCENARIO


def _fly(argv: list[str], out: Path) -> tuple[int, float]:
    """One flight as its own process, its output to ``out/sim.log``; (exit code, wall s).
    The process ends with this one (SIGTERM when it dies, even SIGKILLed: ``sim`` then stops
    its SITL and service), from the thread that waits for it: a killed table left its
    running flight flying to its end."""
    if out.exists():  # from an empty library, as a first flight: reproducible
        shutil.rmtree(out)
    out.mkdir(parents=True)
    start = time.monotonic()
    with (out / "sim.log").open("w") as log:
        log.write("epc-offboard " + " ".join(argv) + "\n")
        log.flush()
        code = subprocess.run([sys.executable, "-m", "epc_offboard", *argv], stdout=log,
                              stderr=subprocess.STDOUT, env={**os.environ, **launched_env()},
                              check=False).returncode  # fmt: skip
    return code, time.monotonic() - start


def _error_series(vehicle_dir: Path, scenario: ScenarioConfig) -> tuple[list[float], list[float]]:
    """(t_s since offboard entry, |error| cm) at SERIES_DT_S under offboard, on ground truth
    (:func:`~epc_offboard.tools.sim.analysis.analyse`'s); empty when it never flew it."""
    from epc_offboard.tools.sim.analysis import analyse, read_flight

    try:
        record = read_flight(
            1,
            flight_log=vehicle_dir / "flight.csv",
            groundtruth=vehicle_dir / "groundtruth.csv",
            stats=vehicle_dir / "stats.json",
            sitl_log=vehicle_dir / "sitl.log",
        )
        r = analyse(record, scenario, np.full(3, np.inf))  # fmt: skip
    except (RuntimeError, KeyError, ValueError):
        return [], []
    keep = r.t_s >= 0.0
    if not r.report["flew_offboard"] or np.sum(keep) < 2:
        return [], []
    t, err_cm = r.t_s[keep], 100.0 * r.error_m[keep]
    grid = np.arange(0.0, float(t[-1]), SERIES_DT_S)
    err_grid = np.interp(grid, t, err_cm)
    return [round(float(x), 2) for x in grid], [round(float(e), 3) for e in err_grid]


def _flight_entry(out: Path, code: int, wall_s: float, scenario: ScenarioConfig) -> dict[str, Any]:
    """What the table and the figure need of one flight, from its report and logs."""
    from epc_offboard.tools.sim.orchestrate import STOPPED_OUTSIDE

    entry: dict[str, Any] = {"exit_code": code, "wall_s": round(wall_s, 1)}
    report_path = out / "report.json"
    if not report_path.exists():
        return {**entry, "status": "failed", "why": f"no report: see {out / 'sim.log'}"}
    report = json.loads(report_path.read_text())
    v = report["vehicles"][0]
    stopped = v.get("stopped") or ""
    status = ("left" if stopped.startswith(STOPPED_OUTSIDE) else
              "flown" if v["flew_offboard"] and v["finished"] else "failed")  # fmt: skip
    t_s, err_cm = _error_series(out / "vehicle1", scenario)
    lib = v["library"]
    return {
        **entry,
        "status": status,
        "why": stopped or "; ".join(report.get("failures", [])),
        "mean_error_m": v["tracking"].get("mean_error_m"),
        "rmse_m": v["tracking"]["rmse_m"],
        "max_error_m": v["tracking"]["max_error_m"],
        "max_tilt_deg": v["max_tilt_deg"],
        "constraint_violations": v["constraint_violations"],
        "hit_rate": lib["hit_rate"] if lib["hits"] + lib["misses"] else None,
        "hit_rate_after_first_lap": lib.get("hit_rate_after_first_lap"),
        "first_lap_misses": lib["first_lap_misses"],
        "lockstep_timeouts": v.get("warnings", {}).get("SITL lockstep timeouts", 0),
        "report": report,
        "t_s": t_s,
        "error_cm": err_cm,
    }


def dumps(data: dict[str, Any]) -> str:
    """The table's JSON, indented, each list of numbers (the error series) on one line."""
    text = json.dumps(data, indent=1)
    return re.sub(r"\[[-0-9.,\se]+\]", lambda m: re.sub(r"\s+", "", m[0]), text) + "\n"


def _commit() -> str:
    try:
        out = subprocess.run(["git", "-C", str(Path(__file__).parent), "describe", "--always",
                              "--dirty"], capture_output=True, text=True, check=False)  # fmt: skip
    except OSError:
        return ""
    return out.stdout.strip()


def _cpu_s(usage: resource.struct_rusage) -> float:
    return usage.ru_utime + usage.ru_stime


def _load() -> list[float]:
    return [round(x, 2) for x in os.getloadavg()]


def _gain(flights: dict[str, dict[str, Any]]) -> dict[str, Any]:
    """The learning's gain at GAIN_ROW: 1 - mean(EPC + LWPR) / mean(EPC, no adaptation),
    the latter flown in the comparison envelope (``without_max_error_m`` from the
    reference: COMPARISON_MAX_ERROR_M)."""
    ours = flights[GAIN_ROW][SCORED.key].get("mean_error_m")
    none = flights[GAIN_ROW]["epc-none"].get("mean_error_m")
    gain: dict[str, Any] = {"row": GAIN_ROW, "with_lwpr_m": ours, "without_m": none,
                            "target_pct": GAIN_TARGET_PCT, "pct": None, "pass": False,
                            "without_max_error_m": COMPARISON_MAX_ERROR_M}  # fmt: skip
    if ours is not None and none and math.isfinite(ours) and math.isfinite(none):
        gain["pct"] = 100.0 * (1.0 - ours / none)
        gain["pass"] = gain["pct"] >= GAIN_TARGET_PCT
    gain["without_left"] = flights[GAIN_ROW]["epc-none"]["status"] == "left"
    return gain


def _mean(values: list[Any]) -> float | None:
    """The mean of ``values``; None when one is missing or not finite."""
    if not values or any(v is None or not math.isfinite(v) for v in values):
        return None
    return float(np.mean(values))


def _mean_series(entries: list[dict[str, Any]]) -> tuple[list[float], list[float]]:
    """The seeds' error series averaged over the time all of them flew (same 10 Hz grid)."""
    n = min((len(e["t_s"]) for e in entries), default=0)
    if n < 2:
        return [], []
    err_cm = np.mean([e["error_cm"][:n] for e in entries], axis=0)
    return entries[0]["t_s"][:n], [round(float(e), 3) for e in err_cm]


# a seed's figures the table keeps beside the mean (its series only in the mean)
_PER_SEED = ("status", "why", "exit_code", "wall_s", "mean_error_m", "rmse_m", "max_error_m",
             "max_tilt_deg", "constraint_violations", "hit_rate_after_first_lap",
             "first_lap_misses", "lockstep_timeouts")  # fmt: skip


def combine_seeds(by_seed: dict[int, dict[str, Any]]) -> dict[str, Any]:
    """One row and method over its seeds' flights: the means (None when a seed has none),
    the mean error's spread (min, max, standard deviation), the worst of the max error, tilt
    and violations, the status of the worst flight (failed, then left), the mean series,
    and each seed's figures under ``seeds``."""
    entries = list(by_seed.values())
    statuses = {e["status"] for e in entries}
    means = [e.get("mean_error_m") for e in entries]
    spread = [m for m in means if m is not None and math.isfinite(m)]

    def worst(key: str) -> Any:
        values = [e.get(key) for e in entries]
        return None if None in values else max(v for v in values if v is not None)

    t_s, err_cm = _mean_series(entries)
    return {
        "status": next((s for s in ("failed", "left") if s in statuses), "flown"),
        "why": "; ".join(f"seed {s}: {e['why']}" for s, e in by_seed.items() if e.get("why")),
        "mean_error_m": _mean(means),
        "mean_error_min_m": min(spread, default=None),
        "mean_error_max_m": max(spread, default=None),
        "mean_error_std_m": float(np.std(spread)) if len(spread) == len(means) else None,
        "rmse_m": _mean([e.get("rmse_m") for e in entries]),
        "max_error_m": worst("max_error_m"),
        "max_tilt_deg": worst("max_tilt_deg"),
        "constraint_violations": worst("constraint_violations"),
        "hit_rate_after_first_lap": _mean([e.get("hit_rate_after_first_lap") for e in entries]),
        "lockstep_timeouts": sum(e.get("lockstep_timeouts", 0) for e in entries),
        "wall_s": round(sum(e.get("wall_s", 0.0) for e in entries), 1),
        "t_s": t_s,
        "error_cm": err_cm,
        "seeds": {str(s): {k: e.get(k) for k in _PER_SEED} for s, e in by_seed.items()},
    }


def combine_verdicts(per_seed: list[list[dict[str, Any]]]) -> list[dict[str, Any]]:
    """The scenario's targets judged on the seeds' means: each target's value and bound
    averaged over the seeds (a ratio's bound, ratio times the other method's value, is
    linear in it: its mean is the ratio times the mean), with each seed's value kept."""
    out = []
    for rows in zip(*per_seed, strict=True):
        # (no figure as null: JSON has no NaN)
        values = [r["value"] if _mean([r["value"]]) is not None else None for r in rows]
        row = {**rows[0], "values": values}
        if all(r["verdict"] != "n/a" for r in rows):
            value, bound = _mean(values), _mean([r["bound"] for r in rows])
            ok = value is not None and bound is not None and value <= bound
            row.update(value=value, bound=bound, verdict="PASS" if ok else "FAIL")
        else:
            row.update(value=None, bound=None, verdict="n/a")
        out.append(row)
    return out


def fly_table(out_dir: Path, results_dir: Path, seeds: tuple[int, ...], jobs: int,
              command: str) -> dict[str, Any]:  # fmt: skip
    """Fly every row by every method on every seed (``jobs`` at once) into ``out_dir``; the
    table's JSON (``command``: what flew it), also written with its figure to
    ``results_dir``."""
    scenario = load_scenario(SCENARIO)
    product = str(product_lwpr_scenario(out_dir))
    wide = str(comparison_scenario(out_dir))
    plan = [(seed, row, m, out_dir / f"seed{seed}" / row.key / m.key)
            for seed in seeds for row in ROWS for m in METHODS]  # fmt: skip
    load_before, wall_start, commit = _load(), time.monotonic(), _commit()
    cpu_before = resource.getrusage(resource.RUSAGE_CHILDREN)
    print(f"epc-offboard figures neuralfly: {len(plan)} lockstep flights, {jobs} at once, "
          f"seed{'s' * (len(seeds) > 1)} {','.join(map(str, seeds))}, into {out_dir} (about "
          f"{len(plan) * 0.6 / jobs:.0f}-{len(plan) * 1.2 / jobs:.0f} min on 2 shared cores)",
          file=sys.stderr)  # fmt: skip
    done = 0

    def one(item: tuple[int, Row, Method, Path]) -> tuple[int, float]:
        nonlocal done
        seed, row, m, out = item
        argv = sim_argv(row, m, scenario_arg(row, m, product, wide), scenario.wind_dir_deg,
                        seed, out)  # fmt: skip
        code, wall_s = _fly(argv, out)
        done += 1
        print(f"[{done}/{len(plan)}] seed {seed}, {row.label}, {m.method}"
              f"{' (product LWPR)' * m.product_lwpr}: exit {code} in {wall_s:.0f} s",
              file=sys.stderr)  # fmt: skip
        return code, wall_s

    with ThreadPoolExecutor(max_workers=jobs) as pool:
        outcomes = list(pool.map(one, plan))
    cpu_after = resource.getrusage(resource.RUSAGE_CHILDREN)
    flights, verdicts = tabulate(plan, outcomes, seeds, scenario)
    data = {
        "kind": "neuralfly_table",
        "command": command,
        "scenario": SCENARIO,
        "seeds": list(seeds),
        "jobs": jobs,
        "lockstep": True,
        "commit": commit,  # the code flown
        "date_utc": datetime.now(UTC).strftime("%Y-%m-%d %H:%M"),
        "load_before": load_before,
        "load_after": _load(),
        "wall_s": round(time.monotonic() - wall_start, 1),
        "cpu_s": round(_cpu_s(cpu_after) - _cpu_s(cpu_before), 1),
        "settle_s": scenario.settle_s,
        "rows": [vars(r) for r in ROWS],
        "methods": [vars(m) for m in METHODS],
        "flights": flights,
        "targets": verdicts,
        "gain": _gain(flights),
    }
    results_dir.mkdir(parents=True, exist_ok=True)
    (results_dir / f"{RESULT_NAME}.json").write_text(dumps(data))
    write_figure(data, results_dir / f"{RESULT_NAME}.png")
    return data


def tabulate(
    plan: list[tuple[int, Row, Method, Path]], outcomes: list[tuple[int, float]],
    seeds: tuple[int, ...], scenario: ScenarioConfig,
) -> tuple[dict[str, dict[str, Any]], dict[str, list[dict[str, Any]]]]:
    """The flown ``plan`` (seed, row, method, out dir) with each flight's (exit code, wall
    s): per row and method its seeds combined (:func:`combine_seeds`), and per row the
    scenario's targets judged on the means (:func:`combine_verdicts`)."""
    by_seed: dict[str, dict[str, dict[int, dict[str, Any]]]] = {
        row.key: {m.key: {} for m in METHODS} for row in ROWS
    }
    for (seed, row, m, out), (code, wall_s) in zip(plan, outcomes, strict=True):
        by_seed[row.key][m.key][seed] = _flight_entry(out, code, wall_s, scenario)
    verdicts = {}
    for row in ROWS:
        per_seed = []
        for seed in seeds:
            flown = {m.method: by_seed[row.key][m.key][seed] for m in METHODS
                     if not m.product_lwpr}  # fmt: skip
            reports = {k: e["report"] for k, e in flown.items() if "report" in e}
            per_seed.append(evaluate(scenario.targets, reports) if reports else [])
        verdicts[row.key] = (combine_verdicts(per_seed)
                             if len({len(v) for v in per_seed}) == 1 else [])  # fmt: skip
    flights = {r: {m: combine_seeds(s) for m, s in ms.items()} for r, ms in by_seed.items()}
    return flights, verdicts


# -- the README's table ---------------------------------------------------------------------


def _seeds_text(data: dict[str, Any]) -> str:
    """``seed 0`` or ``seeds 3, 4`` (a table of one seed may be older than ``seeds``)."""
    seeds = data.get("seeds") or [data["seed"]]
    return f"seed{'s' * (len(seeds) > 1)} {', '.join(map(str, seeds))}"


def _cell(entry: dict[str, Any], spread: bool = True) -> str:
    """A flight's mean error (cm); over several seeds, with its range when ``spread``."""
    mean = entry.get("mean_error_m")
    if entry["status"] == "flown" and mean is not None and math.isfinite(mean):
        lo, hi = entry.get("mean_error_min_m"), entry.get("mean_error_max_m")
        if spread and lo is not None and hi is not None and len(entry.get("seeds", ())) > 1:
            return f"{100.0 * mean:.2f} ({100.0 * lo:.2f}–{100.0 * hi:.2f})"
        return f"{100.0 * mean:.2f}"
    return "left" if entry["status"] == "left" else "failed"


def _target_cell(verdicts: list[dict[str, Any]]) -> str:
    for v in verdicts:
        if v["metric"] == "mean_error_m" and v["vs"] is None and v["bound"] is not None:
            return f"{100.0 * v['bound']:.1f} {'✔' if v['verdict'] == 'PASS' else '✘'}"
    return "–"


def render_table(results_dir: Path) -> str:
    """The README's Neural-Fly table and the lines under it, from ``neuralfly.json``."""
    path = results_dir / f"{RESULT_NAME}.json"
    if not path.exists():
        return "(not flown yet: `epc-offboard figures neuralfly`)\n"
    data = json.loads(path.read_text())
    methods = [Method(**m) for m in data["methods"]]
    head = ["wind", *(m.label for m in methods), "Neural-Fly", "target (½ Neural-Fly)",
            "hits after lap 1"]  # fmt: skip
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for row in (Row(**r) for r in data["rows"]):
        flights = data["flights"][row.key]
        hits = flights[SCORED.key].get("hit_rate_after_first_lap")
        cells = [row.label, *(_cell(flights[m.key]) for m in methods), f"{row.neural_fly_cm:g}",
                 _target_cell(data["targets"][row.key]),
                 "–" if hits is None else f"{100.0 * hits:.1f} %"]  # fmt: skip
        lines.append("| " + " | ".join(cells) + " |")
    g = data["gain"]
    gain_row = next(r for r in data["rows"] if r["key"] == g["row"])["label"]
    if g["pct"] is None and g.get("without_left"):
        gain = (f"not measured (at {gain_row} EPC without adaptation left its envelope "
                "before its first lap ended)")  # fmt: skip
    elif g["pct"] is None:
        gain = f"not measured (a flight failed at {gain_row})"
    else:
        left = " (no adaptation left its envelope: its mean over what it flew)" * bool(
            g["without_left"]
        )
        wide = g.get("without_max_error_m")
        wide_text = (f", no adaptation flown within {wide:g} m of the reference, not `sim`'s "
                     "2 m: figures only" if wide else "")  # fmt: skip
        gain = (f"**{g['pct']:.0f} %** less error than EPC without adaptation "
                f"({100.0 * g['without_m']:.2f} → {100.0 * g['with_lwpr_m']:.2f} cm{left}"
                f"{wide_text}; target ≥ {g['target_pct']:g} % "
                f"{'✔' if g['pass'] else '✘'})")  # fmt: skip
    timeouts = sum(f.get("lockstep_timeouts", 0) for r in data["flights"].values()
                   for f in r.values())  # fmt: skip
    lines += [
        "",
        f"The learning's gain at {gain_row}: {gain}. \"hits after lap 1\": the share of the "
        "scenario's EPC + LWPR ticks the library answered after the first lap."
        + (" Each cell: the mean over the seeds, their lowest and highest in brackets; the "
           "targets are judged on the means." if len(data.get("seeds", ())) > 1 else ""),
        "",
        f"Flown by `{data['command']}` (lockstep, {_seeds_text(data)}, {data['jobs']} flights "
        f"at once) on {data['commit'] or 'an unknown commit'}, {data['date_utc']} UTC: "
        f"{data['wall_s'] / 60.0:.1f} min, {data['cpu_s'] / 60.0:.1f} min of CPU, load "
        f"{data['load_before'][0]:g} before and {data['load_after'][0]:g} after"
        + (f"; {timeouts} SITL lockstep timeouts" if timeouts else "") + ".",
    ]  # fmt: skip
    return "\n".join(lines) + "\n"


# -- the figure -----------------------------------------------------------------------------

_COLOURS = ("tab:blue", "tab:cyan", "tab:green", "tab:orange", "tab:red", "tab:purple")


def write_figure(data: dict[str, Any], path: Path) -> None:
    """Error against time per wind (one panel a row, log scale: the baselines' metres and
    our centimetres on one axis), ours solid, the baselines dashed, the first lap (not
    scored) shaded; the last panel: every mean beside Neural-Fly's and the target."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from epc_offboard.tools.figures import save_once

    rows = [Row(**r) for r in data["rows"]]
    methods = [Method(**m) for m in data["methods"]]
    fig, axes = plt.subplots(3, 2, figsize=(15, 13), layout="constrained")
    panels = list(axes.ravel())
    for ax, row in zip(panels, rows, strict=False):
        ax.axvspan(0.0, data["settle_s"], color="0.9", lw=0, zorder=0)
        for i, m in enumerate(methods):
            f = data["flights"][row.key][m.key]
            if not f.get("t_s"):
                continue
            what = _cell(f, spread=False) + (" cm" if f["status"] == "flown" else "")
            ax.plot(f["t_s"], np.maximum(f["error_cm"], 0.01), color=_COLOURS[i],
                    ls="-" if m.ours else "--", lw=1.4 if m.ours else 1.0,
                    label=f"{m.label.replace('`', '')}: {what}")  # fmt: skip
        bound = next((v["bound"] for v in data["targets"][row.key]
                      if v["metric"] == "mean_error_m" and v["vs"] is None), None)  # fmt: skip
        if bound is not None:
            ax.axhline(100.0 * bound, color="black", ls=":", lw=1.0,
                       label=f"target mean {100.0 * bound:.1f} cm")  # fmt: skip
        ax.set_yscale("log")
        ax.set_ylim(0.1, 1e4)  # the top decades for the legend: errors stay under 3 m
        ax.set(title=f"wind {row.label} (mean error after the first lap)",
               xlabel="time since offboard entry [s] (shaded: first lap, not scored)",
               ylabel="|position error| [cm], ground truth")  # fmt: skip
        ax.grid(True, which="both", alpha=0.3)
        ax.legend(fontsize=7, loc="upper right", ncols=2, framealpha=0.9)
    ax = panels[len(rows)]
    width = 0.8 / (len(methods) + 1)
    x = np.arange(len(rows))
    for i, m in enumerate(methods):
        means = [data["flights"][r.key][m.key].get("mean_error_m") for r in rows]
        cm = [100.0 * v if v is not None and math.isfinite(v) else np.nan for v in means]
        ax.bar(x + i * width, cm, width, color=_COLOURS[i], label=m.label.replace("`", ""),
               hatch="" if m.ours else "//", alpha=0.9)  # fmt: skip
    ax.bar(x + len(methods) * width, [r.neural_fly_cm for r in rows], width, color="0.4",
           label="Neural-Fly (real flights)")  # fmt: skip
    ax.set_xticks(x + 0.4 - width / 2, [r.label for r in rows])
    ax.set_yscale("log")
    ax.set_ylim(bottom=1.0)
    ax.set(ylabel="mean error after the first lap [cm]",
           title="means (no bar: sim stopped it, 2 m off, in its first lap)")  # fmt: skip
    ax.grid(True, axis="y", which="both", alpha=0.3)
    ax.legend(fontsize=7)
    fig.suptitle(f"Neural-Fly's figure-8 on the bundled SITL (PX4 personality), lockstep, "
                 f"{_seeds_text(data)} (their mean): EPC + LWPR against the baselines, per "
                 "wind")  # fmt: skip
    save_once(fig, path)
    plt.close(fig)


def run(args: argparse.Namespace, rewrite: Callable[[str, Path], str]) -> int:
    """``epc-offboard figures neuralfly``: fly (unless ``--numbers-only``), write, rewrite
    the README with ``rewrite`` (``tools.readme``'s, passed in: that module renders this
    one's table, so importing it here would be a cycle)."""
    if args.names:
        raise UsageError("figures neuralfly flies the whole table: it takes no NAME")
    if not 1 <= args.jobs <= MAX_JOBS:
        raise UsageError(f"--jobs must be 1..{MAX_JOBS} (the machine's cores), got {args.jobs}")
    results_dir, readme = Path(args.results), Path(args.readme)
    code = EXIT_OK
    table = results_dir / f"{RESULT_NAME}.json"
    if args.numbers_only and table.exists():  # the figure too, from the JSON
        write_figure(json.loads(table.read_text()), results_dir / f"{RESULT_NAME}.png")
    if not args.numbers_only:
        seeds = args.seeds or (args.seed or 0,)
        command = (f"epc-offboard figures neuralfly {'--seeds' if args.seeds else '--seed'} "
                   f"{','.join(map(str, seeds))} --jobs {args.jobs}")  # fmt: skip
        data = fly_table(Path(args.work) / SCENARIO, results_dir, seeds, args.jobs, command)
        failed = [f"{r}/{m}" for r, fl in data["flights"].items() for m, f in fl.items()
                  if f["status"] == "failed"]  # fmt: skip
        if failed:
            print(f"epc-offboard figures neuralfly: failed flights: {', '.join(failed)}",
                  file=sys.stderr)  # fmt: skip
            code = EXIT_RUNTIME
    text = readme.read_text()
    new = rewrite(text, results_dir)
    if new != text:
        readme.write_text(new)
        print(f"{readme}: rewritten from {results_dir}", file=sys.stderr)
    return code
