"""A vehicle restarted as a new process asks the fleet only for what is new (issue 25): real
processes (the vehicle's control process with its fleet helper and its library store
process, a router from ``epc-offboard fleet router``), real SQLite, real Zenoh on loopback,
and SIGKILL.

v1 holds a library of several controllers; v2 (a process of its own, ``tests.fleet_vehicle``)
joins and takes them as candidates, its store saves them with the high-water marks; v2 is
killed (SIGKILL, its whole process group) and started again on the same library file. It
must take in none of v1's controllers again and still hold every one (on the old code a new
process asked for, and took in, the whole library). A store whose marks are garbage, or
whose received controllers are missing beside intact marks, costs a whole pull, never a
controller.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import os
import signal
import sqlite3
import subprocess
import sys
import threading
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import asdict
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from epc_offboard.control.cascade import Cascade
from epc_offboard.fleet.sharing import FleetSharing
from epc_offboard.service.config import load_service_config
from tests.fleet_vehicle import REPO
from tests.mpc_cases import hover_refs
from tests.test_fleet_trust import router, vehicle_config
from tests.test_sharing import until

pytestmark = pytest.mark.timeout(600)  # four vehicle starts (a cascade each) under load

N_TARGETS = 6


class Vehicle:
    """``tests.fleet_vehicle`` in a process group of its own; its newest state line."""

    def __init__(self, cfg: dict[str, Any], store: Path, log: Path) -> None:
        arg = json.dumps({"sharing": cfg, "store": str(store)})
        with log.open("a") as err:
            self.proc = subprocess.Popen([sys.executable, "-m", "tests.fleet_vehicle", arg],
                                         stdout=subprocess.PIPE, stderr=err, text=True,
                                         cwd=REPO, start_new_session=True)  # fmt: skip
        self.state: dict[str, Any] = {}
        self._thread = threading.Thread(target=self._read, daemon=True)
        self._thread.start()

    def _read(self) -> None:
        assert self.proc.stdout is not None
        for line in self.proc.stdout:
            self.state = json.loads(line)

    def stat(self, name: str) -> int:
        return int(self.state.get("stats", {}).get(name, 0))

    def holds(self, sets: list[tuple[int, ...]]) -> bool:
        held = {tuple(a) for a in self.state.get("held", [])}
        return all(s in held for s in sets)

    def kill(self) -> None:
        if self.proc.poll() is None:
            os.killpg(self.proc.pid, signal.SIGKILL)  # the helper and the store with it
        self.proc.wait(timeout=30)


@contextmanager
def vehicle(cfg: dict[str, Any], store: Path, log: Path) -> Iterator[Vehicle]:
    v = Vehicle(cfg, store, log)
    try:
        yield v
    finally:
        v.kill()


def saved_marks(store: Path) -> list[Any]:
    """The high-water marks the store holds ([] when none yet)."""
    try:
        with sqlite3.connect(f"file:{store}?mode=ro", uri=True) as conn:
            row = conn.execute("SELECT value FROM meta WHERE key = 'fleet:marks'").fetchone()
    except sqlite3.Error:
        return []
    return list(json.loads(row[0])["held"]) if row else []


def edit_store(store: Path, sql: str) -> None:
    with sqlite3.connect(store) as conn:
        assert conn.execute(sql).rowcount == 1


def test_a_restarted_vehicle_pulls_only_what_is_new_and_never_loses_one(tmp_path):
    cfg = load_service_config(REPO / "config" / "sitl.toml")
    cascade = Cascade(cfg.position, cfg.attitude, cfg.estimator, 0.01)
    ctrl = cascade.experience_controllers()[0][1]
    p = ctrl.problem
    for k in range(N_TARGETS):
        az = 2 * np.pi * k / N_TARGETS
        ctrl.step(np.zeros(p.nx), hover_refs(p, [10 * np.cos(az), 10 * np.sin(az), 0.0]))
    held = [e.active_set for e in ctrl.export_library()]
    assert len(held) >= 4, held
    store = tmp_path / "v2.sqlite"
    log = tmp_path / "v2.log"

    async def main() -> None:
        with router(tmp_path, "router.json5", {}, tls=False) as r:
            sharing = FleetSharing(vehicle_config("v1", r, "client.json5"),
                                   cascade.experience_controllers())  # fmt: skip
            async with sharing as v1:
                task = asyncio.create_task(v1.run())
                cfg2 = asdict(vehicle_config("v2", r, "client.json5"))

                async def restart(what: str, fresh: bool) -> Vehicle:
                    """v2 anew on the same store, until v1 has answered its query."""
                    answered = v1.stats().get("queries_answered", 0)
                    with vehicle(cfg2, store, log) as v2:
                        await until(lambda: v1.stats().get("queries_answered", 0) > answered,
                                    f"v2's query ({what})", 120)  # fmt: skip
                        await until(lambda: v2.holds(held), f"v1's library at v2 ({what})", 60)
                        await asyncio.sleep(2 * v2_query_timeout_s)  # any reply is in
                        got = v2.stat("entries_received")
                        # fresh: asked at start (every peer) and at v1's arrival, both whole
                        assert got >= len(held) if fresh else got == 0, (what, got)
                        return v2

                v2_query_timeout_s = float(cfg2["query_timeout_s"])
                # the first start: the whole library, kept with the marks
                with vehicle(cfg2, store, log) as v2:
                    await until(lambda: v2.holds(held), "v1's library at v2", 120)
                    assert v2.stat("entries_received") >= len(held)
                    # the marks in the store (if it keeps any: the old code did not, and
                    # the restart below then pulls everything again)
                    with contextlib.suppress(AssertionError):
                        await until(lambda: any(m[1] == "v1" for m in saved_marks(store)),
                                    "the marks in v2's store", 30)  # fmt: skip
                    await asyncio.sleep(1.0)  # a save or two more: a kill lands mid-write
                # killed (the context's SIGKILL); a new process on the same store
                up_to_date = v1.stats().get("queries_up_to_date", 0)
                await restart("restarted", fresh=False)
                assert v1.stats()["queries_up_to_date"] > up_to_date
                # garbage marks: a whole pull, every controller still held
                edit_store(store, "UPDATE meta SET value = '{not json' WHERE key = 'fleet:marks'")
                await restart("garbage marks", fresh=True)
                # the received controllers gone, the marks intact: believing them would
                # lose the controllers; a whole pull instead
                assert saved_marks(store)
                key = f"fleet:candidates:{p.signature()}"
                edit_store(store, f"DELETE FROM meta WHERE key = '{key}'")
                await restart("candidates lost", fresh=True)
                task.cancel()

    try:
        asyncio.run(main())
    except BaseException:
        print(log.read_text()[-4000:])
        raise
