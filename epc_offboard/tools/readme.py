"""`epc-offboard figures readme`: the README's figures and quoted numbers, from one command.

Each recipe is an ``epc-offboard sim`` command line; its figure and its report are copied
into ``tests/results/`` (``RECIPE.png`` / ``RECIPE.json``, the names the README links). Every
number the README quotes from a flight sits between markers naming where it comes from::

    EPC + LWPR <!-- n:compare_figure8.epc:lwpr.rmse_cm -->5.14<!-- /n --> cm

and every generated table between ``<!-- table:NAME -->`` and ``<!-- /table -->``. After the
flights the command rewrites those from the reports in ``tests/results/``; with
``--numbers-only`` it only rewrites (no flight). A test checks that the README equals its
rewrite from the results on disk, so a number edited by hand, or a result regenerated
without the README, fails CI: they cannot drift apart.

Keys: ``REPORT.METHOD.FIELD`` for a ``--compare`` report (METHOD as ``controller:adaptation``),
``REPORT.vK.FIELD`` for vehicle K of a single flight's; FIELD is one of :data:`FIELDS`, or
``duration_s``, and ``REPORT.targets`` (PASS or FAIL: every declared target of a
``--compare``); ``REPORT`` is the JSON's name in ``tests/results/`` without ``.json``.
Derived numbers (a percentage between two reports) are in :data:`DERIVED`.
"""

from __future__ import annotations

import argparse
import json
import re
import shutil
import subprocess
import sys
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from epc_offboard.common.errors import EXIT_OK, EXIT_RUNTIME, UsageError

REPO = Path(__file__).resolve().parents[2]
RESULTS_DIR = REPO / "tests" / "results"
README = REPO / "README.md"


@dataclass(frozen=True)
class Recipe:
    """One README result: the `sim` arguments that make it (``--out`` is added)."""

    name: str  # tests/results/NAME.json and NAME.png
    argv: tuple[str, ...]
    minutes: float  # about, on 2 shared cores: what a user is told before it starts


# no ground-station stream: the recipes run beside whatever else the machine flies
_GCS = ("--gcs-port", "0")
_STAGGER = ("--scenario", "zigzag_bounded", "--adaptation", "none", "--vehicles", "2",
            "--stagger", *_GCS)  # fmt: skip
RECIPES = {
    r.name: r
    for r in (
        Recipe("flight_hover", _GCS, 0.5),
        Recipe("compare_circle", ("--scenario", "circle", "--compare", *_GCS), 4.0),
        Recipe("compare_zigzag", ("--scenario", "zigzag", "--compare", *_GCS), 4.0),
        Recipe("compare_figure8", ("--scenario", "figure8", "--compare", *_GCS), 9.0),
        Recipe("stagger_shared", _STAGGER, 3.0),
        Recipe("stagger_alone", (*_STAGGER, "--no-share"), 3.0),
    )
}


def _pct(x: float) -> str:
    return f"{100.0 * x:.1f}"


def _cm(x: float) -> str:
    return f"{100.0 * x:.2f}"


# a vehicle entry's numbers the README may quote, as they are printed
FIELDS: dict[str, Callable[[dict[str, Any]], str]] = {
    "rmse_cm": lambda v: _cm(v["tracking"]["rmse_m"]),
    "max_cm": lambda v: _cm(v["tracking"]["max_error_m"]),
    "max_speed_m_s": lambda v: f"{v['max_speed_m_s']:.2f}",
    "violations": lambda v: str(v["constraint_violations"]),
    "hit_pct": lambda v: _pct(v["library"]["hit_rate"]),
    "qp_solves": lambda v: str(v["library"]["qp_solves"]),
    "first_lap_misses": lambda v: str(v["library"]["first_lap_misses"]),
    "us_median": lambda v: f"{v['loops']['position']['compute_us_median']:.0f}",
    "us_p99": lambda v: f"{v['loops']['position']['compute_us_p99']:.0f}",
    "att_deadline_misses": lambda v: str(v["loops"]["attitude"]["deadline_misses"]),
}


def _fewer_pct(values: dict[str, str], a: str, b: str) -> str:
    return f"{100.0 * (1.0 - float(values[a]) / float(values[b])):.0f}"


# numbers computed from others: key -> a function of the other values
DERIVED: dict[str, Callable[[dict[str, str]], str]] = {
    "stagger.fewer_first_lap_misses_pct": lambda v: _fewer_pct(
        v, "stagger_shared.v2.first_lap_misses", "stagger_alone.v2.first_lap_misses"
    ),
}

_NUMBER = re.compile(r"<!-- n:(?P<key>[^ ]+) -->(?P<old>.*?)<!-- /n -->")
_TABLE = re.compile(r"(<!-- table:(?P<key>[^ ]+) -->\n)(?P<old>.*?)(<!-- /table -->)", re.S)


def _method(report: dict[str, Any]) -> str:
    return f"{report['controller']}:{report['adaptation']}"


def values_from(results_dir: Path) -> dict[str, str]:
    """Every quotable number of the reports in ``results_dir`` by key (see the module)."""
    out: dict[str, str] = {}
    for path in sorted(results_dir.glob("*.json")):
        data = json.loads(path.read_text())
        if data.get("kind") == "neuralfly_table":
            continue  # no sim report: its table renders it (tools.neuralfly)
        name = path.stem
        reports = data.get("reports", [data])
        if "all_pass" in data:  # a --compare: its declared targets' verdict
            out[f"{name}.targets"] = "PASS" if data["all_pass"] else "FAIL"
        for report in reports:
            out[f"{name}.duration_s"] = f"{report['duration_s']:g}"
            for v in report["vehicles"]:
                who = _method(report) if "reports" in data else f"v{v['id']}"
                for field, get in FIELDS.items():
                    try:
                        out[f"{name}.{who}.{field}"] = get(v)
                    except (KeyError, TypeError):
                        continue  # a field a method does not have (no library: PD)
    for key, derive in DERIVED.items():
        try:
            out[key] = derive(out)
        except (KeyError, ValueError, ZeroDivisionError):
            continue
    return out


# the generated tables: name -> rows from the values (a report and its methods)
_SCENARIO_NAMES = {"figure8": "figure-8", "zigzag": "zig-zag"}
_METHOD_NAMES = {
    "epc:lwpr": "EPC + LWPR",
    "epc:none": "EPC, no adaptation",
    "epc:kf": "EPC + KF",
    "pd:none": "PD",
    "mpc:kf": "MPC + KF",
    "px4:none": "PX4's own position controller",
}


def _results_table(values: dict[str, str], results_dir: Path) -> str:
    """The README's per-method table of the three thesis experiments."""
    lines = [
        "| scenario | method | RMSE cm | max cm | max m/s | viol. | hits | QP solves | "
        "compute median / p99 µs |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for scenario in ("circle", "zigzag", "figure8"):
        path = results_dir / f"compare_{scenario}.json"
        if not path.exists():
            continue
        name = path.stem
        for i, method in enumerate(json.loads(path.read_text())["methods"]):
            key = f"{name}.{method}"
            epc = method.startswith("epc:")
            cells = [
                "" if i else _SCENARIO_NAMES.get(scenario, scenario),
                _METHOD_NAMES.get(method, method),
                values[f"{key}.rmse_cm"],
                values[f"{key}.max_cm"],
                values[f"{key}.max_speed_m_s"],
                values[f"{key}.violations"],
                f"{values[f'{key}.hit_pct']} %" if epc else "–",
                values[f"{key}.qp_solves"] if epc else
                ("every tick" if method.startswith("mpc:") else "–"),
                f"{values[f'{key}.us_median']} / {values[f'{key}.us_p99']}",
            ]  # fmt: skip
            lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def _neuralfly_table(_values: dict[str, str], results_dir: Path) -> str:
    from epc_offboard.tools.neuralfly import render_table

    return render_table(results_dir)


TABLES: dict[str, Callable[[dict[str, str], Path], str]] = {
    "results": _results_table,
    "neuralfly": _neuralfly_table,  # `epc-offboard figures neuralfly`
}


def rewrite(text: str, results_dir: Path) -> str:
    """``text`` (the README) with every marked number and table rewritten from the reports
    in ``results_dir``; UsageError naming a marker whose key no report gives."""
    values = values_from(results_dir)
    unknown = sorted({m["key"] for m in _NUMBER.finditer(text)} - values.keys())
    unknown += sorted({m["key"] for m in _TABLE.finditer(text)} - TABLES.keys())
    if unknown:
        raise UsageError(
            f"README markers with no number in {results_dir}: {', '.join(unknown)} "
            "(fly their recipe: epc-offboard figures readme NAME)"
        )
    text = _NUMBER.sub(lambda m: f"<!-- n:{m['key']} -->{values[m['key']]}<!-- /n -->", text)
    return _TABLE.sub(
        lambda m: m.group(1) + TABLES[m["key"]](values, results_dir) + m.group(4), text
    )


def _warn_if_not_lockstep(recipe: Recipe, data: dict[str, Any]) -> None:
    """Say so when a flight's SITL advanced without the controller's answer (the machine was
    too loaded for lockstep): such a result may not be what a quiet machine reproduces."""
    timeouts = sum(
        v.get("warnings", {}).get("SITL lockstep timeouts", 0)
        for report in data.get("reports", [data])
        for v in report["vehicles"]
    )
    if timeouts:
        print(f"epc-offboard figures: {recipe.name}: {timeouts} SITL lockstep timeouts (the "
              "machine was too loaded for lockstep): fly it again on a quieter machine for a "
              "reproducible result", file=sys.stderr)  # fmt: skip


def fly(recipe: Recipe, work_dir: Path, results_dir: Path) -> int:
    """Fly one recipe into ``work_dir/NAME`` and copy its report and figure to
    ``results_dir``; sim's exit code."""
    out = work_dir / recipe.name
    if out.exists():  # from an empty library, as a first flight: reproducible
        for old in out.glob("**/library-*.sqlite*"):
            old.unlink()
    argv = ["sim", *recipe.argv, "--out", str(out)]
    print(f"epc-offboard {' '.join(argv)}   (about {recipe.minutes:g} min)", file=sys.stderr)
    # the command line a user runs, as its own process (its output passes through)
    code = subprocess.run([sys.executable, "-m", "epc_offboard", *argv], check=False).returncode
    compare = "--compare" in recipe.argv
    report = out / ("compare.json" if compare else "report.json")
    figure = out / ("compare.png" if compare else "flight.png")
    if report.exists():
        shutil.copyfile(report, results_dir / f"{recipe.name}.json")
        _warn_if_not_lockstep(recipe, json.loads(report.read_text()))
    if figure.exists() and not recipe.name.startswith("stagger"):
        shutil.copyfile(figure, results_dir / f"{recipe.name}.png")
    return code


def run_figures_command(args: argparse.Namespace) -> int:
    """``epc-offboard figures readme [NAME ...] [--numbers-only]``, or ``figures neuralfly``
    (:mod:`epc_offboard.tools.neuralfly`)."""
    if not Path(args.readme).is_file():  # said before half an hour of flights, not after
        raise UsageError(
            f"--readme {args.readme}: no such file: `figures` rewrites a checkout's README "
            "(an installed wheel has none): run it in a checkout installed with "
            "`pip install -e .`, or give --readme FILE and --results DIR"
        )
    if args.what == "neuralfly":
        from epc_offboard.tools.neuralfly import run

        return run(args, rewrite)
    results_dir = Path(args.results)
    readme = Path(args.readme)
    names = args.names or ([] if args.numbers_only else list(RECIPES))
    unknown = [n for n in names if n not in RECIPES]
    if unknown:
        raise UsageError(f"unknown recipe {', '.join(unknown)} (known: {', '.join(RECIPES)})")
    results_dir.mkdir(parents=True, exist_ok=True)
    failed = []
    for name in names:
        if fly(RECIPES[name], Path(args.work), results_dir) != EXIT_OK:
            failed.append(name)
    text = readme.read_text()
    new = rewrite(text, results_dir)
    if new != text:
        readme.write_text(new)
        print(f"{readme}: numbers rewritten from {results_dir}", file=sys.stderr)
    if failed:
        print(f"epc-offboard figures: failed flights (results copied all the same): "
              f"{', '.join(failed)}", file=sys.stderr)  # fmt: skip
        return EXIT_RUNTIME
    return EXIT_OK
