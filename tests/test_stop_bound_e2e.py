"""A stop ends within the unit's TimeoutStopSec whatever its helper processes do, and loses
nothing committed to the library, end to end in REAL TIME with real processes.

The service hovers and saves its library (the store process, SQLite); then every helper
process it spawned (the miss worker, the store, the fleet helper, the log writer) is
SIGSTOPped at once, as a helper wedged in a disk wait or starved would be, and the service gets
SIGTERM. Before, each wait of the stop had its own timeout, one after the other (the miss
worker 2 + 1 s, the store's last save 30 s, the log writer 20 s): the stop took ~50 s and
systemd's SIGKILL at 5 s cut it. Now every wait ends by ``service.STOP_BOUND_S`` after the
stop was asked; what is still stopped then is killed, counted, and the library file holds
every save committed before. And the helpers' stop as a whole ends by the bound (stop 40):
before, each helper killed at the bound was waited for after it (``children.KILL_WAIT_S``
each), and the next killed after that.
"""

from __future__ import annotations

import os
import re
import signal
import sqlite3
import time
from pathlib import Path

import pytest

from epc_offboard.common.ports import free_port
from epc_offboard.vehicle.dialect_px4 import PX4_MAIN_MODE_OFFBOARD
from tests.rig import Rig, unit_stop_timeout_s

pytestmark = [pytest.mark.timeout(300), pytest.mark.one_at_a_time("alone")]


def _helpers(pid: int) -> list[int]:
    """The service's children started by multiprocessing (its helper processes)."""
    out = []
    for task in Path(f"/proc/{pid}/task").iterdir():
        for child in (task / "children").read_text().split():
            cmdline = Path(f"/proc/{child}/cmdline").read_bytes()
            if b"multiprocessing.spawn" in cmdline:
                out.append(int(child))
    return out


def _rows(path: Path) -> dict[str, int]:
    """Every table's row count, read from what SQLite has committed (a reader of its own)."""
    with sqlite3.connect(f"file:{path}?mode=ro", uri=True) as db:
        tables = [r[0] for r in db.execute("SELECT name FROM sqlite_master WHERE type='table'")]
        return {t: db.execute(f'SELECT COUNT(*) FROM "{t}"').fetchone()[0] for t in tables}


def _integrity(path: Path) -> str:
    with sqlite3.connect(f"file:{path}?mode=ro", uri=True) as db:
        return str(db.execute("PRAGMA integrity_check").fetchone()[0])


def test_a_stop_with_every_helper_wedged_ends_in_time_and_keeps_the_library(tmp_path):
    from epc_offboard.service.service import STOP_BOUND_S

    overrides = {
        "mission": {"duration_s": 300.0, "land_at_end": True},
        "trajectory": {"shape": "hover"},
        "store": {"save_period_s": 1.0},
        "sharing": {
            "enabled": True, "fleet": "stop-bound", "vehicle_id": "v1",
            "listen": [f"tcp/127.0.0.1:{free_port()}"], "scouting_multicast": False,
        },
    }  # fmt: skip
    library = tmp_path / "library.sqlite"
    stopped: list[int] = []
    with Rig(tmp_path, lockstep=False, speedup=1.0, service_overrides=overrides) as rig:
        try:
            rig.wait_mode(PX4_MAIN_MODE_OFFBOARD, timeout_s=120)
            time.sleep(3.0)  # saves committed meanwhile (one a second)
            assert rig.service is not None
            helpers = _helpers(rig.service.pid)
            assert len(helpers) >= 4, helpers  # miss worker, store, fleet helper, log writer
            for pid in helpers:
                os.kill(pid, signal.SIGSTOP)
                stopped.append(pid)
            before = _rows(library)  # every save committed (the store cannot write now)
            assert sum(before.values()) > 0, before
            code, stop_s = rig.stop_service(timeout_s=90.0)
        finally:
            for pid in stopped:  # one the service did not kill: ended here
                try:
                    os.kill(pid, signal.SIGKILL)
                    os.kill(pid, signal.SIGCONT)
                except ProcessLookupError:
                    pass
        log = rig.log()
    print(f"SIGTERM to exit with every helper SIGSTOPped: {stop_s:.2f} s")
    assert code == 0, log
    assert unit_stop_timeout_s() > STOP_BOUND_S + 1.0  # the kills and the exit fit after it
    assert stop_s < unit_stop_timeout_s(), log  # main: ~50 s
    # the helpers' stop as a whole, on the service's clock: main (stop 39) killed each at or
    # after the bound and waited for it after it
    found = re.search(r"stopped, its helpers ([0-9.]+) s after it was asked", log)
    assert found, log
    helpers_s = float(found.group(1))
    print(f"the helpers stopped {helpers_s:.3f} s after it was asked")
    assert helpers_s < STOP_BOUND_S, log
    stats = rig.stats()
    counters = {**stats["counters"], **stats["miss_worker"]}
    assert counters["store_stop_timeouts"] == 1, counters  # killed at the bound
    assert counters["worker_stop_timeouts"] == 1, counters
    # nothing committed lost: the file whole, every row it held before the stop still there
    assert _integrity(library) == "ok"
    after = _rows(library)
    assert all(after.get(t, 0) >= n for t, n in before.items()), (before, after)
