"""docs/CONTRACTS.md is true: what it names exists, and what exists is named there.

Each check reads the document's tables and compares them with the code, both ways, so a flag,
report field, config key or Zenoh key added or removed without the document fails here with
its name. The `sim` report is built by the same functions `sim` uses (``analyse``,
``make_report``, ``method_targets``, ``flight_failures`` of :mod:`epc_offboard.tools.sim`) from a
short recorded lockstep hover (``tests/data/contracts/``, thinned to the columns the
analysis reads): no flight here, the suite stays fast. Re-record it when the service's
``stats.json`` changes shape::

    epc-offboard sim --scenario hover --duration 4 --gcs-port 0 --out /tmp/hover
    # then copy vehicle1/{stats.json,sitl.log,service.log} and the thinned CSVs

(``stats.json``'s top-level keys are checked on the code itself, so a new one fails here even
before the recording is refreshed.)
"""

from __future__ import annotations

import argparse
import ast
import dataclasses
import json
import re
import sys
import types
import typing
from collections.abc import Iterator
from pathlib import Path
from typing import Any, get_args, get_origin, get_type_hints

import numpy as np
import pytest

from epc_offboard.cli import build_parser
from epc_offboard.common import errors
from epc_offboard.control.library_types import (
    LibraryEntry,
    LibrarySnapshot,
    SignatureSnapshot,
    Transition,
)
from epc_offboard.fleet import keys, wire
from epc_offboard.service.config import ServiceConfig
from epc_offboard.tools import compare
from epc_offboard.tools.bench import run_bench
from epc_offboard.tools.db import snapshot_to_json
from epc_offboard.tools.sim import orchestrate
from epc_offboard.tools.sim.analysis import analyse, read_flight
from epc_offboard.tools.sim.envelope import Envelope
from epc_offboard.tools.sim.options import sim_options
from epc_offboard.tools.sim.report import (
    REPORT_COLUMNS,
    flight_failures,
    make_report,
    method_targets,
    strict_json,
    target_failures,
)
from epc_offboard.tools.sim.scenario import ScenarioConfig
from epc_offboard.tools.targets import TargetConfig
from sitl.main import build_parser as build_sitl_parser
from sitl.params import SimConfig

ROOT = Path(__file__).resolve().parent.parent
DOC_PATH = ROOT / "docs" / "CONTRACTS.md"
DOC = DOC_PATH.read_text()
RECORDED = Path(__file__).resolve().parent / "data" / "contracts"


# -- reading the document ----------------------------------------------------------------------


def section(heading: str) -> str:
    """The text under the heading that starts with ``heading`` (e.g. "### `epc-offboard sim`"),
    up to the next heading of the same or a higher level."""
    level = len(heading) - len(heading.lstrip("#"))
    lines = DOC.splitlines()
    starts = [i for i, line in enumerate(lines) if line.startswith(heading)]
    assert len(starts) == 1, f"docs/CONTRACTS.md: {len(starts)} headings start with {heading!r}"
    out: list[str] = []
    fenced = False  # a code block's comments are not headings
    for line in lines[starts[0] + 1 :]:
        fenced ^= line.startswith("```")
        m = re.match(r"(#+) ", line)
        if m and not fenced and len(m.group(1)) <= level:
            break
        out.append(line)
    return "\n".join(out)


def tables(text: str) -> list[list[list[str]]]:
    """Every markdown table in ``text``: its body rows (header and rule left out), cells
    stripped (``\\|`` inside a cell is kept)."""
    found: list[list[list[str]]] = []
    current: list[list[str]] | None = None
    for line in [*text.splitlines(), ""]:
        if line.startswith("|"):
            cells = [c.strip() for c in re.split(r"(?<!\\)\|", line.strip())[1:-1]]
            if current is None:
                current = []  # the header row
            elif not all(re.fullmatch(r":?-+:?", c) for c in cells):
                current.append(cells)
        elif current is not None:
            found.append(current)
            current = None
    return found


def code_cells(rows: list[list[str]], column: int = 0) -> list[str]:
    """The backticked text of ``column`` in each row that has one."""
    out = []
    for row in rows:
        m = re.fullmatch(r"`([^`]+)`", row[column]) if len(row) > column else None
        if m:
            out.append(m.group(1))
    return out


def first_table(heading: str) -> list[str]:
    found = tables(section(heading))
    assert found, f"docs/CONTRACTS.md: no table under {heading!r}"
    return code_cells(found[0])


def both_ways(what: str, documented: typing.Iterable[str], real: typing.Iterable[str]) -> None:
    documented, real = set(documented), set(real)
    assert not real - documented, (
        f"{what}: in the code, missing from docs/CONTRACTS.md: {sorted(real - documented)}"
    )
    assert not documented - real, (
        f"{what}: in docs/CONTRACTS.md, not in the code: {sorted(documented - real)}"
    )


# -- commands and flags -------------------------------------------------------------------------


def _subparsers() -> dict[str, argparse.ArgumentParser]:
    parser = build_parser()
    sub = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
    return dict(sub.choices)


def _nested(parser: argparse.ArgumentParser) -> dict[str, argparse.ArgumentParser]:
    """A command's own subcommands (``fleet router``), by name."""
    subs = [a for a in parser._actions if isinstance(a, argparse._SubParsersAction)]
    return {name: p for a in subs for name, p in a.choices.items()}


PARSERS = {
    "### `epc-sitl`": build_sitl_parser(),
    **{f"### `epc-offboard {name}`": p for name, p in _subparsers().items()},
    **{
        f"### `epc-offboard {name} {inner}`": q
        for name, p in _subparsers().items()
        for inner, q in _nested(p).items()
    },
}


def test_every_subcommand_has_its_section() -> None:
    documented = re.findall(r"^### `epc-offboard (\w+)`", DOC, flags=re.MULTILINE)
    both_ways("epc-offboard subcommands", documented, _subparsers())


@pytest.mark.parametrize("heading", PARSERS)
def test_every_flag_is_documented_and_every_documented_flag_exists(heading: str) -> None:
    parser = PARSERS[heading]
    options = [a for a in parser._actions if a.option_strings and a.dest != "help"]
    rows = first_table(heading)
    both_ways(f"{heading.strip('# `')} flags", (r.split()[0] for r in rows),
              (s for a in options for s in a.option_strings))  # fmt: skip
    # a flag's choices are written as argparse prints them: --autopilot {px4,ardupilot}
    for action in options:
        if action.choices is None:
            continue
        row = next(r for r in rows if r.split()[0] in action.option_strings)
        written = re.search(r"\{([^}]*)\}", row)
        assert written, f"{heading}: {row!r} does not list its choices {list(action.choices)}"
        both_ways(f"{row.split()[0]} choices", written.group(1).split(","), action.choices)


@pytest.mark.parametrize("heading", PARSERS)
def test_positional_arguments_choices_are_the_documented_ones(heading: str) -> None:
    text = section(heading)
    for action in PARSERS[heading]._actions:
        if not action.option_strings and action.choices and not isinstance(
            action, argparse._SubParsersAction
        ):
            braces = [set(b.split(",")) for b in re.findall(r"\{([^}]*)\}", text)]
            assert set(action.choices) in braces, (
                f"{heading}: the choices of {action.dest}, {sorted(action.choices)}, are not "
                "written in its synopsis"
            )


def test_exit_codes() -> None:
    rows = {int(r[0]): r[1] for r in tables(section("## Exit codes"))[0]}
    assert set(rows) == {errors.EXIT_OK, errors.EXIT_RUNTIME, errors.EXIT_USAGE}
    assert "success" in rows[errors.EXIT_OK]
    assert "runtime" in rows[errors.EXIT_RUNTIME]
    assert "usage" in rows[errors.EXIT_USAGE]
    assert "config" in rows[errors.EXIT_USAGE]


# -- reports ------------------------------------------------------------------------------------


def field_paths(value: Any, documented: set[str], path: str = "") -> Iterator[str]:
    """The paths of a JSON value's fields, in the document's notation: ``a.b`` for an object's
    field, ``a[]`` for the objects of a list, ``a.*`` for an object documented as having
    varying keys (its contents are then named only where the document goes on, as in
    ``signatures.*.controllers[]``). A scalar, null, empty or scalar list is a leaf."""
    wild = f"{path}.*" if path else "*"
    if isinstance(value, dict) and wild in documented:
        yield wild
    elif isinstance(value, dict) and value:
        if any(d.startswith(wild + ".") for d in documented):
            for item in value.values():
                yield from field_paths(item, documented, wild)
            return
        for key, item in value.items():
            yield from field_paths(item, documented, f"{path}.{key}" if path else key)
    elif isinstance(value, list) and value and all(isinstance(v, dict) for v in value):
        for item in value:
            yield from field_paths(item, documented, f"{path}[]")
    else:
        yield path


def check_fields(what: str, documented_list: list[str], *produced: Any) -> None:
    """Every field the values have is documented, and every documented one is produced."""
    documented = set(documented_list)
    real = {p for value in produced for p in field_paths(value, documented)}
    both_ways(what, documented, real)


def recorded_sim_report(*flags: str) -> dict[str, Any]:
    """report.json of the recorded hover, as `sim` writes it: analysed with an envelope it
    leaves and a target it is judged on, so that every optional list has members; ``flags``
    of `sim` (a scenario with extra metrics, a wind profile) add the fields they add."""
    argv = ["sim", *flags] if flags else ["sim", "--scenario", "hover", "--duration", "4"]
    args = build_parser().parse_args(argv)
    options = sim_options(args)
    record = read_flight(
        1,
        flight_log=RECORDED / "flight.csv",
        groundtruth=RECORDED / "groundtruth.csv",
        stats=RECORDED / "stats.json",
        sitl_log=RECORDED / "sitl.log",
        service_log=RECORDED / "service.log",
        sharing_asked=False,
        moved_aside=(),
        stopped="",
    )
    tight = Envelope(max_error_m=0.001, max_drift_m=1.0, max_tilt_deg=60.0, ceiling_m=2.0,
                     max_flight_s=100.0)  # fmt: skip
    result = analyse(record, options.scenario, np.array([3.8, 3.8, 2.0]), tight)
    report = make_report(options, [result])
    judged = dataclasses.replace(options, scenario=dataclasses.replace(
        options.scenario, targets=(TargetConfig(method=options.method, metric="rmse_m", max=1.0),)
    ))  # fmt: skip
    report["targets"] = method_targets(judged, report)
    report["failures"] = flight_failures(report) + target_failures(report["targets"])
    parsed: dict[str, Any] = json.loads(json.dumps(strict_json(report), allow_nan=False))
    return parsed


def test_the_sim_report_fields_are_the_documented_ones() -> None:
    report = recorded_sim_report()
    assert report["vehicles"][0]["envelope"]["left"], "the recorded flight should leave it"
    assert report["targets"], "the target should be judged"
    # the fields only some flights have: a varying wind, a scenario's extra metric
    varying = recorded_sim_report("--scenario", "neuralfly", "--wind-profile", "sine:2.4,1")
    assert "mean_error_m" in varying["vehicles"][0]["tracking"]
    check_fields("sim report.json", first_table("## `sim` report"), report, varying)


def test_the_printed_tables_columns_are_the_documented_ones_in_order() -> None:
    sim_tables = tables(section("## `sim` report"))
    assert code_cells(sim_tables[1]) == list(REPORT_COLUMNS)
    compare_tables = tables(section("### `sim --compare`"))
    assert code_cells(compare_tables[1]) == list(compare.COMPARE_COLUMNS)


def _dict_keys(node: ast.Dict) -> list[str]:
    return [k.value for k in node.keys if isinstance(k, ast.Constant) and isinstance(k.value, str)]


def _function(path: Path, qualname: str) -> ast.FunctionDef:
    tree = ast.parse(path.read_text())
    *owners, name = qualname.split(".")
    body: list[ast.stmt] = tree.body
    for owner in owners:
        body = next(n for n in body if isinstance(n, ast.ClassDef) and n.name == owner).body
    return next(n for n in body if isinstance(n, ast.FunctionDef) and n.name == name)


def _returned_keys(path: Path, qualname: str) -> list[str]:
    """The string keys of the dict literal a function returns (spread ``**x`` left out)."""
    func = _function(path, qualname)
    returns = [n for n in ast.walk(func) if isinstance(n, ast.Return)]
    return [k for r in returns if isinstance(r.value, ast.Dict) for k in _dict_keys(r.value)]


def test_stats_json_top_level_keys_are_the_documented_ones() -> None:
    service = ROOT / "epc_offboard" / "service"
    real = [*_returned_keys(service / "service.py", "Service.stats"),
            *_returned_keys(service / "autopilot.py", "Autopilot.stats")]  # fmt: skip
    rows = tables(section("### The service's `stats.json`"))[0]
    both_ways("stats.json keys", code_cells(rows), real)
    recorded = json.loads((RECORDED / "stats.json").read_text())
    both_ways("stats.json keys of the recorded flight", recorded, real)
    # every process the stats name is named in the document's row
    processes = _function(service / "service.py", "Service._process_stats")
    names = {k for d in ast.walk(processes) if isinstance(d, ast.Dict) for k in _dict_keys(d)}
    row = next(r for r in rows if r[0] == "`processes`")[1]
    both_ways("stats.json processes", re.findall(r"`(\w+)`", row), names)


def test_compare_json_fields_are_the_documented_ones() -> None:
    func = _function(ROOT / "epc_offboard" / "tools" / "compare.py", "run_compare")
    summary = next(
        n.value for n in ast.walk(func)
        if isinstance(n, ast.Assign) and isinstance(n.value, ast.Dict)
        and any(isinstance(t, ast.Name) and t.id == "summary" for t in n.targets)
    )  # fmt: skip
    both_ways("compare.json", first_table("### `sim --compare`"), _dict_keys(summary))


def test_the_bench_report_fields_are_the_documented_ones(monkeypatch: pytest.MonkeyPatch) -> None:
    with_daqp = run_bench(horizon=3, steps=20)
    monkeypatch.setitem(sys.modules, "daqp", None)  # import daqp -> ImportError
    without = run_bench(horizon=3, steps=20)
    check_fields("bench --json", first_table("## `bench --json FILE` report"), with_daqp, without)


def test_the_db_export_fields_are_the_documented_ones() -> None:
    part = SignatureSnapshot(
        controllers=(LibraryEntry((0, 3), importance=2.0, uses=1, origin="solved"),),
        transitions=(Transition((0, 3), (1,), 2),),
        models={"lwpr": b"\x00\x01"},
    )
    exported = snapshot_to_json(LibrarySnapshot({"abc": part}), "library.sqlite")
    check_fields("db export", first_table("## `db export` file"), exported)


# -- Zenoh --------------------------------------------------------------------------------------


def test_zenoh_keys_are_the_fleets_templates() -> None:
    rows = tables(section("## Zenoh"))
    documented = {r[0]: code_cells([r], 1)[0] for r in rows[0]}
    assert documented == keys.KEYS
    assert all(t.startswith(keys.ROOT + "/") for t in keys.KEYS.values())
    both_ways("live reference fields", code_cells(rows[1]), wire._REFERENCE_KEYS)
    port = re.search(r"tcp/127\.0\.0\.1:\((\d+)\+k\)", section("## Zenoh"))
    assert port
    assert int(port.group(1)) == orchestrate.ZENOH_BASE_PORT


def test_the_key_templates_build_the_keys_the_session_uses() -> None:
    assert keys.problem_key(keys.CONTROLLERS, "f", "sig", keys.ANY) == "epc/f/sig/ctl/*"
    assert keys.problem_key(keys.LIBRARY, "f", "sig", "v1") == "epc/f/sig/lib/v1"
    assert keys.problem_key(keys.ALIVE, "f", "sig", "v1") == "epc/f/sig/alive/v1"
    assert keys.reference_key("f", "v1") == "epc/f/v1/reference"


# -- Python API ---------------------------------------------------------------------------------


def test_the_python_api_example_runs() -> None:
    blocks = re.findall(r"```python\n(.*?)```", section("## Python API"), flags=re.DOTALL)
    assert len(blocks) == 1
    exec(compile(blocks[0], "docs/CONTRACTS.md (Python API)", "exec"), {})


def test_the_package_root_exports_what_the_document_says() -> None:
    import epc_offboard

    text = section("## Python API").split("```")[0]
    exported = re.findall(r"`(\w+)`", text.split("The compatibility paths")[0])
    both_ways("package root exports", exported, set(epc_offboard.__all__) - {"__version__"})
    for name in exported:
        assert getattr(epc_offboard, name) is not None


# -- config keys --------------------------------------------------------------------------------


def _dataclass_in(tp: Any) -> tuple[Any, str]:
    """(the dataclass a field holds, "[]" when an array of them) or (None, "")."""
    args = get_args(tp)
    if isinstance(tp, type) and dataclasses.is_dataclass(tp):
        return tp, ""
    if get_origin(tp) is tuple and args and dataclasses.is_dataclass(args[0]):
        return args[0], "[]"
    if get_origin(tp) in (typing.Union, types.UnionType):
        inner = [a for a in args if dataclasses.is_dataclass(a)]
        if inner:
            return inner[0], ""
    return None, ""


def config_keys(cls: Any, prefix: str = "") -> Iterator[str]:
    """The dotted keys a config file may hold (``a[].b`` inside an array of tables)."""
    hints = get_type_hints(cls)
    for f in dataclasses.fields(cls):
        inner, suffix = _dataclass_in(hints[f.name])
        if inner is None:
            yield prefix + f.name
        else:
            yield from config_keys(inner, f"{prefix}{f.name}{suffix}.")


@pytest.mark.parametrize(
    ("heading", "config"),
    [("### Service config", ServiceConfig), ("### SITL vehicle file", SimConfig),
     ("### Scenario", ScenarioConfig)],
)  # fmt: skip
def test_every_config_key_is_documented_and_every_documented_key_exists(
    heading: str, config: type
) -> None:
    both_ways(f"{heading.strip('# ')} keys", first_table(heading), config_keys(config))


# -- citations ----------------------------------------------------------------------------------


CITATION = re.compile(r"(\S*?)\b(CONTRACTS|DESIGN|STYLE)\b(\.md)?")


def test_every_cited_document_is_in_the_repository() -> None:
    """The code cites docs/CONTRACTS.md and docs/DESIGN.md by that path, and they exist:
    never a document outside the repository (``../shared/DESIGN.md``) or a bare name."""
    bad = []
    for pkg in ("epc_offboard", "sitl", "tests"):
        for path in sorted((ROOT / pkg).rglob("*.py")):
            if path == Path(__file__).resolve():
                continue  # its patterns name them
            for n, line in enumerate(path.read_text().splitlines(), 1):
                for m in CITATION.finditer(line):
                    cited = f"docs/{m.group(2)}.md"
                    by_path = m.group(1).endswith("docs/") and m.group(3)
                    if not by_path or not (ROOT / cited).exists():
                        bad.append(f"{path.relative_to(ROOT)}:{n}: {line.strip()}")
    assert not bad, "citations of documents not in the repository:\n" + "\n".join(bad)


# -- a fleet message, file by file (docs/DESIGN.md) ------------------------------------------


def _fleet_path_section() -> str:
    text = (ROOT / "docs" / "DESIGN.md").read_text()
    return text.split("## A fleet message, file by file", 1)[1].split("\n## ", 1)[0]


def _defined_names(path: Path) -> set[str]:
    """Every function, class and class field of ``path``, bare and as ``Class.name``."""
    out: set[str] = set()

    def walk(body: list[ast.stmt], prefix: str) -> None:
        for node in body:
            if isinstance(node, ast.FunctionDef | ast.AsyncFunctionDef | ast.ClassDef):
                out.update({node.name, prefix + node.name})
                walk(node.body, prefix + node.name + "." if isinstance(node, ast.ClassDef)
                     else prefix)  # fmt: skip
            elif isinstance(node, ast.AnnAssign) and isinstance(node.target, ast.Name):
                out.update({node.target.id, prefix + node.target.id})

    walk(ast.parse(path.read_text()).body, "")
    return out


def test_the_fleet_message_path_names_at_most_four_files_and_real_code() -> None:
    """The path a received fleet message takes, as docs/DESIGN.md tells it: at most four
    files, each existing, and every function, class or field it names defined in the
    package (a renamed one fails here, not in a reader's five minutes)."""
    section = _fleet_path_section()
    files = re.findall(r"^\d+\. `(epc_offboard/[\w/]+\.py)`", section, re.M)
    assert 1 <= len(files) <= 4, files
    defined: set[str] = set()
    for path in (ROOT / "epc_offboard").rglob("*.py"):
        defined |= _defined_names(path)
    for rel in files:
        assert (ROOT / rel).is_file(), rel
    names = [t for t in re.findall(r"`([A-Za-z_][\w.]*)`", section)
             if not t.endswith(".py") and not t.startswith("epc_offboard")]  # fmt: skip
    assert names
    missing = sorted({n for n in names if n not in defined})
    assert not missing, f"named in docs/DESIGN.md's fleet path, defined nowhere: {missing}"


@pytest.mark.parametrize(
    ("rel", "qualname", "callee"),
    [
        ("epc_offboard/fleet/session.py", "FleetSession._on_batch", "receive"),
        ("epc_offboard/fleet/sharing.py", "FleetSharing.poll", "offer_slice"),
        ("epc_offboard/fleet/sharing.py", "FleetSharing.offer_slice", "_offer"),
        ("epc_offboard/fleet/sharing.py", "FleetSharing._offer", "offer_records"),
        ("epc_offboard/fleet/exchange.py", "offer_records", "offer"),
        ("epc_offboard/control/epc/exchange.py", "FleetPort.offer", "offer_candidates"),
    ],
)
def test_each_step_of_the_fleet_path_calls_the_next(rel: str, qualname: str, callee: str) -> None:
    """Each hop docs/DESIGN.md names calls the next one it names."""
    section = _fleet_path_section()
    assert f"`{qualname}`" in section
    assert f"`{rel}`" in section
    func = _function(ROOT / rel, qualname)
    called = {
        n.func.attr if isinstance(n.func, ast.Attribute) else getattr(n.func, "id", "")
        for n in ast.walk(func) if isinstance(n, ast.Call)
    }  # fmt: skip
    assert callee in called, f"{qualname} does not call {callee}"
