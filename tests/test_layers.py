"""The layer rules of the code base, enforced on its import graph (read with ``ast``, so a
deferred import inside a function counts as well as one at the top).

* pure numerics import no I/O: no asyncio, sockets, MAVLink, Zenoh, SQLite or processes,
  and none of the product's I/O modules;
* the control law (``control/``) never imports the vehicle's MAVLink side (``vehicle/``):
  what it exchanges is ``control/types.py``'s, which ``vehicle/`` decodes into; and the inner
  loop (``control/attitude.py``) never imports the outer loop's module;
* the miss worker builds no controller: it loads the learner and the map builder only;
* the plant (``sitl``) never imports the controller;
* the service never imports the tools (sim, compare, benchmarks, figures, db, exporters);
* no import cycle among modules, even counting deferred imports inside functions;
* the compatibility shims (``epc_offboard.mpc``, ``epc_offboard.lwpr``) are for scripts only:
  no module of the product imports them;
* every error the product raises is an ``EpcError`` and the builtin it is a kind of.
"""

from __future__ import annotations

import ast
import functools
import importlib
import inspect
import subprocess
import sys
from collections.abc import Mapping
from pathlib import Path
from types import MappingProxyType

import pytest

from epc_offboard.common.errors import EpcError

ROOT = Path(__file__).resolve().parent.parent
PACKAGES = ("epc_offboard", "sitl")


def _modules() -> dict[str, Path]:
    out = {}
    for pkg in PACKAGES:
        for f in sorted((ROOT / pkg).rglob("*.py")):
            parts = f.relative_to(ROOT).with_suffix("").parts
            out[".".join(parts[:-1] if parts[-1] == "__init__" else parts)] = f
    return out


MODULES = _modules()

def _in(*packages: str) -> tuple[str, ...]:
    """Every module of these packages (and the packages themselves)."""
    return tuple(m for m in MODULES if any(m == p or m.startswith(p + ".") for p in packages))


# control/ is pure numerics as a whole; the vehicle's state machine, dialects and rate
# bookkeeping are too (commands as values: the link sends them)
NUMERICS = (
    *_in("epc_offboard.control"),
    *(f"epc_offboard.vehicle.{m}" for m in (
        "offboard", "dialect", "dialect_px4", "dialect_ardupilot", "autopilots", "rates",
        "state")),
    "epc_offboard.service.timing",
    "epc_offboard.common.errors",
    "epc_offboard.common.frames",
)  # fmt: skip
IO_LIBRARIES = ("asyncio", "socket", "pymavlink", "zenoh", "sqlite3", "subprocess", "serial")
IO_MODULES = (
    "epc_offboard.vehicle.link",
    *_in("epc_offboard.service", "epc_offboard.fleet", "epc_offboard.store"),
    "epc_offboard.tools.db",
    "epc_offboard.tools.sim.orchestrate",
    "epc_offboard.cli",
)
# what the plant may import of the product: the shared package, nothing else
PLANT_MAY_IMPORT = _in("epc_offboard.common")
TOOLS = (*_in("epc_offboard.tools"), "epc_offboard.cli")


@functools.cache  # the sources do not change during a run: each file is parsed once
def _imports(path: Path, *, top_level_only: bool) -> frozenset[str]:
    """Everything a module imports (``from a import b`` counts as ``a`` and ``a.b``)."""
    tree = ast.parse(path.read_text())
    nodes = tree.body if top_level_only else list(ast.walk(tree))
    found: set[str] = set()
    for node in nodes:
        if isinstance(node, ast.Import):
            found.update(a.name for a in node.names)
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            found.add(node.module)
            found.update(f"{node.module}.{a.name}" for a in node.names)
    return frozenset(found)


@functools.cache
def _graph(*, top_level_only: bool) -> Mapping[str, frozenset[str]]:
    return MappingProxyType({
        m: frozenset(d for d in _imports(p, top_level_only=top_level_only)
                     if d in MODULES and d != m)
        for m, p in MODULES.items()
    })  # fmt: skip


def _reachable(graph: Mapping[str, frozenset[str]], start: str) -> set[str]:
    seen: set[str] = set()
    todo = [start]
    while todo:
        for nxt in graph[todo.pop()]:
            if nxt not in seen:
                seen.add(nxt)
                todo.append(nxt)
    return seen


def test_the_module_lists_name_real_modules():
    for name in (*NUMERICS, *IO_MODULES, *PLANT_MAY_IMPORT, *TOOLS):
        assert name in MODULES, f"{name} is not a module any more: update the layer lists"
    assert len(_in("epc_offboard.control")) >= 10


@pytest.mark.parametrize("module", NUMERICS)
def test_numerics_import_no_io(module):
    graph = _graph(top_level_only=False)
    for m in (module, *_reachable(graph, module)):
        direct = _imports(MODULES[m], top_level_only=False)
        bad = {d for d in direct if d.split(".")[0] in IO_LIBRARIES}
        assert not bad, f"{module} reaches {m}, which imports {sorted(bad)}"
    io = _reachable(graph, module) & set(IO_MODULES)
    assert not io, f"{module} imports the I/O modules {sorted(io)}"


def test_the_control_law_never_imports_the_vehicle_side():
    graph = _graph(top_level_only=False)
    for m in _in("epc_offboard.control"):
        bad = {d for d in _reachable(graph, m) if d.startswith("epc_offboard.vehicle")}
        assert not bad, f"{m} imports the vehicle side: {sorted(bad)}"


def test_the_inner_loop_does_not_import_the_outer_loop():
    reached = _reachable(_graph(top_level_only=False), "epc_offboard.control.attitude")
    assert "epc_offboard.control.position" not in reached


def test_the_miss_worker_loads_no_controller():
    """The worker process imports ``service/miss_solver.py``: it gets the full QP's learner,
    the map builder and the candidate pool, never the controller, the cascade or the loops."""
    bad = _loaded_by(
        "epc_offboard.service.miss_solver",
        "'ExperienceController' in getattr(sys.modules[m], '__dict__', {}) "
        "or m in ('epc_offboard.control.cascade', 'epc_offboard.control.position', "
        "'epc_offboard.control.attitude')",
    )
    assert not bad, f"the miss worker loads {bad}"


def test_the_plant_never_imports_the_controller():
    graph = _graph(top_level_only=False)
    for m in MODULES:
        if m.startswith("sitl"):
            product = {d for d in _reachable(graph, m) if d.startswith("epc_offboard.")}
            bad = product - set(PLANT_MAY_IMPORT)
            assert not bad, f"{m} imports more of the product than epc_offboard.common: {bad}"


def _loaded_by(module: str, condition: str) -> list[str]:
    """The modules (package __init__ files included) that importing ``module`` in a fresh
    interpreter really loads and for which the expression ``condition`` on ``m`` holds."""
    code = (
        f"import sys, {module}\n"
        f"print(','.join(sorted(m for m in sys.modules if {condition})))\n"
    )
    out = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, check=True, cwd=ROOT
    )
    return [m for m in out.stdout.strip().split(",") if m]


def test_the_running_plant_loads_no_controller():
    """What the interpreter really loads when the SITL's command starts: nothing of the
    controller, no numba, no OSQP."""
    bad = _loaded_by(
        "sitl.main",
        "m.startswith(('numba', 'osqp', 'zenoh')) "
        "or (m.startswith('epc_offboard.') and not m.startswith('epc_offboard.common'))",
    )
    assert not bad, f"the SITL loads {bad}"


@pytest.mark.parametrize(
    "module", ["epc_offboard.fleet.wire", "epc_offboard.control.library_types"]
)
def test_the_library_types_and_the_codec_load_no_numerics(module):
    """The library's value types and the fleet's codec are plain Python: a planner (or any
    peer) decoding controller messages loads no numpy, numba, OSQP or scipy."""
    bad = _loaded_by(module, "m.split('.')[0] in ('numpy', 'numba', 'osqp', 'scipy')")
    assert not bad, f"{module} loads {sorted({m.split('.')[0] for m in bad})}"


def test_the_service_never_imports_the_tools():
    bad = _reachable(_graph(top_level_only=False), "epc_offboard.service.service") & set(TOOLS)
    assert not bad, f"the service imports tools: {sorted(bad)}"


def test_no_import_cycle_at_import_time():
    graph = _graph(top_level_only=True)
    for m in graph:
        assert m not in _reachable(graph, m), f"{m} imports itself through a cycle"


def test_no_import_cycle_even_deferred():
    """A deferred import (inside a function) hides a cycle from the interpreter until it runs,
    not from the reader: there is none (the dialect chooser once imported the dialects that
    import it; sim and compare imported each other). compare uses sim's parts, not the
    reverse."""
    graph = _graph(top_level_only=False)
    for m in graph:
        assert m not in _reachable(graph, m), f"{m} imports itself through a cycle"
    assert "epc_offboard.tools.sim.orchestrate" in _reachable(graph, "epc_offboard.tools.compare")


SHIMS = ("epc_offboard.mpc", "epc_offboard.lwpr")


def test_the_compatibility_shims_are_used_by_no_module_of_the_product():
    """The shims keep docs/CONTRACTS.md's import paths for scripts; the product imports the
    real modules, so a shim can change (or go) without the product noticing."""
    for shim in SHIMS:
        assert shim in MODULES
        users = sorted(m for m, p in MODULES.items()
                       if m not in SHIMS and shim in _imports(p, top_level_only=False))  # fmt: skip
        assert not users, f"{users} import the compatibility shim {shim}: import the real module"


def test_every_error_is_an_epc_error_and_a_builtin():
    checked = 0
    for name in MODULES:
        if name.endswith("__main__"):
            continue  # importing it runs the command line
        module = importlib.import_module(name)
        for _, cls in inspect.getmembers(module, inspect.isclass):
            if cls.__module__ != name or not issubclass(cls, Exception):
                continue
            if not cls.__name__.endswith("Error"):
                continue  # control flow (the service's _Stop), not an error
            checked += 1
            assert issubclass(cls, EpcError), f"{name}.{cls.__name__} is not an EpcError"
            builtins = [b for b in cls.__mro__[1:] if b.__module__ == "builtins"]
            assert any(b is not Exception and b is not BaseException for b in builtins), (
                f"{name}.{cls.__name__} subclasses no specific builtin"
            )
    assert checked >= 10


def test_the_fleet_exchange_is_pure_and_the_session_holds_the_io():
    """The fleet's exchange (messages <-> offers, quotas, buckets) imports no I/O library and
    neither the session nor the control process's side; Zenoh is the session's alone (and
    the config's: its validation, deferred, probes the overrides on a zenoh.Config, never
    run by the exchange, hence top-level imports here)."""
    graph = _graph(top_level_only=True)
    exchange = "epc_offboard.fleet.exchange"
    for m in (exchange, *_reachable(graph, exchange)):
        bad = {d for d in _imports(MODULES[m], top_level_only=True)
               if d.split(".")[0] in IO_LIBRARIES}  # fmt: skip
        assert not bad, f"{exchange} reaches {m}, which imports {sorted(bad)}"
    assert not _reachable(graph, exchange) & {"epc_offboard.fleet.session",
                                              "epc_offboard.fleet.sharing"}  # fmt: skip
    zenoh_users = {m for m in _in("epc_offboard.fleet")
                   if "zenoh" in _imports(MODULES[m], top_level_only=True)}  # fmt: skip
    assert zenoh_users <= {"epc_offboard.fleet.session", "epc_offboard.fleet.router"}, zenoh_users
