"""A cold start's own cost, judged on what load does not change: what the service process
imports and compiles, its CPU seconds, and the scheduling class of its background compile
(the flight itself: tests/test_coldstart_e2e.py)."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import time
from pathlib import Path

import pytest

from epc_offboard.common import jit
from epc_offboard.service import coldstart
from epc_offboard.tools.sim.scenario import SITL_SERVICE_CONFIG
from tests.rig import Rig
from tests.test_coldstart_e2e import fifo_permitted

pytestmark = pytest.mark.timeout(120)

SCHED_IDLE = 5  # Linux's SCHED_IDLE, /proc/<pid>/stat's policy field

# What a cold start's service process does up to its first tick, as a probe prints it:
# choose the kernels, build the service's cascade and warm it up
_PROBE = """
import json, sys, time
from epc_offboard.service import coldstart
mode = coldstart.choose()
from epc_offboard.control.cascade import Cascade, compiled_signatures
from epc_offboard.service.config import load_service_config
cfg = load_service_config(sys.argv[1])
cascade = Cascade(cfg.position, cfg.attitude, cfg.estimator, 0.01, learn_on_miss=False,
                  airframe=cfg.vehicle)
cpu_before_warm_s = time.process_time()
cascade.warm_up()
print(json.dumps({"mode": mode, "numba_imported": "numba" in sys.modules,
                  "signatures": compiled_signatures(),
                  "warm_up_cpu_s": time.process_time() - cpu_before_warm_s}))
"""


def _cold_env(cache: Path) -> dict[str, str]:
    env = {k: v for k, v in os.environ.items() if k != jit.ENV}
    env["NUMBA_CACHE_DIR"] = str(cache)
    return env


def test_a_cold_start_neither_imports_nor_compiles_numba(tmp_path: Path):
    """On a cold cache the service flies the numpy twins and must not even import numba.
    The body-rate identifier's kernel ignored the choice: every cold start imported numba
    (0.2 s) and compiled that kernel inside the warm-up (0.5 s of CPU, more than half the
    service's own start-up), several seconds of wall clock on a loaded companion computer."""
    out = subprocess.run(
        [sys.executable, "-c", _PROBE, str(SITL_SERVICE_CONFIG)],
        env=_cold_env(tmp_path / "numba-cache"), capture_output=True, text=True, timeout=100,
    )  # fmt: skip
    assert out.returncode == 0, out.stderr
    probe = json.loads(out.stdout.splitlines()[-1])
    assert probe["mode"] == "numpy-cold"
    assert not probe["numba_imported"], probe
    assert probe["signatures"] == 0, probe


def test_the_background_compile_runs_at_idle_priority(tmp_path: Path):
    """The cold start's compile (10-30 s of CPU) takes only CPU nobody else wants: at nice 10
    it still took a share of the service's start-up and first ticks."""
    env_before = dict(os.environ)
    os.environ.update(_cold_env(tmp_path / "numba-cache"))
    try:
        child = coldstart.start_background_compile(str(SITL_SERVICE_CONFIG))
    finally:
        os.environ.clear()
        os.environ.update(env_before)
    try:
        deadline = time.monotonic() + 10.0
        policy = None
        while policy is None and time.monotonic() < deadline:
            text = Path(f"/proc/{child.pid}/stat").read_text()
            fields = text[text.rindex(")") + 2 :].split()
            # field 41 of stat (policy) is fields[38] after "pid (comm)"; read once the child
            # has exec'd (its preexec set it before)
            policy = int(fields[38])
        assert policy == SCHED_IDLE, f"policy {policy}"
    finally:
        child.kill()
        child.wait()


_MARK = """
import os, sys
from epc_offboard.common import jit
if sys.argv[1] == "mark":
    jit.mark_cache_warm()
elif sys.argv[1] == "touch":
    kernels = os.path.join(os.path.dirname(jit.__file__), "..", "control", "kernels.py")
    stat = os.stat(kernels)
    os.utime(kernels, (stat.st_atime, stat.st_mtime + 10.0))
print(jit.cache_warm())
"""


def _package_copy(folder: Path) -> Path:
    import shutil

    import epc_offboard

    source = Path(epc_offboard.__file__).resolve().parent
    shutil.copytree(source, folder / "epc_offboard", ignore=shutil.ignore_patterns("__pycache__"))
    return folder  # copytree's copy2 keeps the sources' modification times


def _cache_warm_in(copy: Path, cache: Path, action: str) -> bool:
    env = _cold_env(cache) | {"PYTHONPATH": str(copy)}
    out = subprocess.run([sys.executable, "-c", _MARK, action], env=env, cwd=copy,
                         capture_output=True, text=True, timeout=60)  # fmt: skip
    assert out.returncode == 0, out.stderr
    return out.stdout.split()[-1] == "True"


def test_the_warm_mark_vouches_only_for_the_sources_numba_cached(tmp_path: Path):
    """numba's cache is keyed by each kernel source's path, modification time and size; the
    mark was keyed by their contents alone, so an upgraded or re-cloned package with the same
    kernels was called warm and compiled every kernel before its link opened (12.7 s on a
    real PX4 beside two CPU hogs)."""
    cache = tmp_path / "numba-cache"
    first = _package_copy(tmp_path / "first")
    assert _cache_warm_in(first, cache, "mark")
    assert not _cache_warm_in(_package_copy(tmp_path / "second"), cache, "check")  # moved
    assert _cache_warm_in(first, cache, "check")
    assert not _cache_warm_in(first, cache, "touch")  # the same path, a newer kernels.py


def test_the_start_up_runs_at_the_loops_priority_from_before_the_heavy_imports(tmp_path: Path):
    """With loops.realtime_priority set, the start-up runs SCHED_FIFO from before the service's
    imports: at normal priority, beside a real PX4 at load 10-15, its 0.6-1.3 s of CPU took
    2.4-5 s of wall clock before the first command (offboard 12-15 s after a cold start)."""
    if not fifo_permitted():
        pytest.skip("SCHED_FIFO not permitted here")
    # (no autopilot, nothing flown: its start-up runs beside other tests, as this file's do;
    # it was in tests/test_coldstart_e2e.py, whose real-time flight runs alone)
    rig = Rig(tmp_path, service_overrides={"loops": {"realtime_priority": 10}})
    try:
        rig.start_service()  # no autopilot: it waits for one, and is stopped
        deadline = time.monotonic() + 60.0
        while "epc-offboard running" not in rig.log() and time.monotonic() < deadline:
            time.sleep(0.2)
        code, _ = rig.stop_service()
    finally:
        rig.__exit__()
    assert code == 0, rig.log()
    marks = list(rig.stats()["startup"]["milestones"])
    assert marks[:4] == ["entry", "start_up_priority", "kernels_chosen", "config"], marks
