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
from collections.abc import AsyncIterator, Coroutine, Iterator
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

    def __init__(self, cfg: dict[str, Any], store: Path, log: Path,
                 learn: list[list[float]] | None = None) -> None:  # fmt: skip
        arg = json.dumps({"sharing": cfg, "store": str(store), "learn": learn or []})
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
def vehicle(cfg: dict[str, Any], store: Path, log: Path,
            learn: list[list[float]] | None = None) -> Iterator[Vehicle]:  # fmt: skip
    v = Vehicle(cfg, store, log, learn)
    try:
        yield v
    finally:
        v.kill()


@contextlib.asynccontextmanager
async def v1_through_a_router(
    tmp_path: Path, cascade: Cascade
) -> AsyncIterator[tuple[FleetSharing, dict[str, Any]]]:
    """A router, v1 sharing ``cascade``'s controllers through it (in this process, its task
    running), and v2's sharing config for ``tests.fleet_vehicle``."""
    with router(tmp_path, "router.json5", {}, tls=False) as r:
        sharing = FleetSharing(vehicle_config("v1", r, "client.json5"),
                               cascade.experience_controllers())  # fmt: skip
        async with sharing as v1:
            task = asyncio.create_task(v1.run())
            try:
                yield v1, asdict(vehicle_config("v2", r, "client.json5"))
            finally:
                task.cancel()


def run_showing(main: Coroutine[Any, Any, None], log: Path) -> None:
    """Run ``main``; on a failure, v2's log's tail first."""
    try:
        asyncio.run(main)
    except BaseException:
        print(log.read_text()[-4000:])
        raise


def saved_meta(store: Path, key: str) -> Any:
    """The store's fleet state row ``key`` read as JSON (None when none yet)."""
    try:
        with sqlite3.connect(f"file:{store}?mode=ro", uri=True) as conn:
            row = conn.execute("SELECT value FROM meta WHERE key = ?", (key,)).fetchone()
    except sqlite3.Error:
        return None
    return json.loads(row[0]) if row else None


def saved_marks(store: Path) -> list[Any]:
    """The high-water marks the store holds ([] when none yet)."""
    marks = saved_meta(store, "fleet:marks")
    return list(marks["held"]) if marks else []


def saved_own(store: Path) -> int:
    """How many of its library's controllers the store keeps the vehicle's numbers of."""
    own = saved_meta(store, "fleet:own")
    return sum(len(rows) for rows in own["numbers"]) if own else 0


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
        async with v1_through_a_router(tmp_path, cascade) as (v1, cfg2):
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

    run_showing(main(), log)


def test_a_restarted_vehicle_is_not_taken_whole_again_by_its_peers(tmp_path):
    """The other side of a restart: v2 learns controllers of its own and v1 takes them; v2
    is killed (SIGKILL) and started again on its store. v1 queries v2 as it comes back, and
    is answered nothing: it holds v2's library already (the old code answered the whole
    library again: a new process numbers under a new epoch, and v1's mark was of the old)."""
    cfg = load_service_config(REPO / "config" / "sitl.toml")
    cascade = Cascade(cfg.position, cfg.attitude, cfg.estimator, 0.01)  # v1: no library
    learn = [[8 * np.cos(az), 8 * np.sin(az), -1.0]
             for az in np.linspace(0.0, 2 * np.pi, N_TARGETS, endpoint=False)]  # fmt: skip
    store = tmp_path / "v2.sqlite"
    log = tmp_path / "v2.log"

    async def main() -> None:
        async with v1_through_a_router(tmp_path, cascade) as (v1, cfg2):
            with vehicle(cfg2, store, log, learn) as v2:
                await until(lambda: v2.state.get("library", 0) >= 4, "v2's library", 120)
                library = v2.state["library"]
                await until(lambda: v1.stats().get("entries_received", 0) >= library,
                            "v2's controllers at v1", 60)  # fmt: skip
                # its numbering of them in the store (the old code kept none: the
                # restart below then answers v1 with the whole library)
                with contextlib.suppress(AssertionError):
                    await until(lambda: saved_own(store) >= library, "v2's numbers", 30)
                await asyncio.sleep(1.0)  # a save or two more: a kill lands mid-write
            received = v1.stats()["entries_received"]
            up_to_date = v1.stats().get("replies_up_to_date", 0)
            queries = v1.stats()["queries_sent"]
            with vehicle(cfg2, store, log) as v2:
                # v1 asks v2 as its token comes back; v2 answers (empty, or entries)
                await until(lambda: v1.stats()["queries_sent"] > queries
                            and (v1.stats().get("replies_up_to_date", 0) > up_to_date
                                 or v1.stats()["entries_received"] > received),
                            "v1's query of v2 answered", 120)  # fmt: skip
                await asyncio.sleep(2 * float(cfg2["query_timeout_s"]))  # any reply in
                assert v2.state["library"] == library  # every controller kept
                assert v1.stats()["entries_received"] == received, (library, received)
                assert v2.stat("restored_numbers") >= library

    run_showing(main(), log)


def test_a_saved_numbering_is_believed_only_whole_and_for_a_problem_flown():
    """``fleet:own`` read back by a restart: garbage, or a numbering of other problems only,
    is not believed (the peers then take the library whole: never a controller lost)."""
    from tests.test_sharing import config, controller

    def former(own: str) -> Any:
        sharing = FleetSharing(config("v2", 0, []), [("position", controller())])
        sharing.restore({"own": own})
        raw = bytes(sharing._high_water_raw.raw).rstrip(b"\0")
        return json.loads(raw).get("former"), sharing.stats().get("restored_numbers", 0)

    sig = FleetSharing(config("v2", 0, []), [("position", controller())]).specs[0].signature
    good = {"epoch": 5, "numbers": [[[0, 3, 1], [1, 2]]], "signatures": [sig]}
    assert former(json.dumps(good)) == ({"epoch": 5, "numbers": [[[0, 3, 1], [1, 2]]]}, 2)
    assert former("{not json") == (None, 0)
    assert former(json.dumps({**good, "signatures": ["another problem"]})) == (None, 0)
    assert former(json.dumps({**good, "numbers": [[["x", 1]]]})) == (None, 0)
