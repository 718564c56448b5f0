"""A vehicle that rejoins the fleet pulls only what is new (issue 25): real processes, real
Zenoh on loopback (a router from ``epc-offboard fleet router``, vehicles its clients).

v1 holds a library of several controllers; v2 joins fresh and gets them all. Then the
fleet is rejoined three ways — the router restarts, v2's fleet helper is killed (restarted),
v2's helper is wedged past its timeout — and v2 must take in nothing it holds already
(on the old code each rejoin pulled v1's whole snapshot again: ``entries_received`` grew
by the library's size), while a controller v1 learned during the outage still arrives.
"""

from __future__ import annotations

import asyncio
import json
import os
import signal
from dataclasses import replace

import numpy as np

from epc_offboard.control.epc import ExperienceController
from epc_offboard.fleet.sharing import FleetSharing
from tests.mpc_cases import hover_refs
from tests.test_fleet_trust import router, vehicle_config
from tests.test_sharing import TARGETS, controller, learn_new, until
from tests.test_sharing import peer as vehicle


def library_of(n_targets: int) -> tuple[ExperienceController, list[tuple[int, ...]]]:
    """A controller that has learned towards ``n_targets`` distinct directions."""
    ctrl = controller()
    p = ctrl.problem
    for k in range(n_targets):
        az = 2 * np.pi * k / n_targets
        ctrl.step(np.zeros(p.nx), hover_refs(p, [10 * np.cos(az), 10 * np.sin(az), 0.0]))
    return ctrl, [e.active_set for e in ctrl.export_library()]


async def answered(v1: FleetSharing, v2: FleetSharing, what: str, before: int) -> None:
    """v1 answered another query of v2's (a rejoin) than the ``before`` it had answered, and
    its reply has had time to arrive. (``before`` is read before the rejoin: a router back
    at once has the query answered, with one reply, before this could read it.)"""
    await until(lambda: v1.stats().get("queries_answered", 0) > before, what, 60)
    await asyncio.sleep(v2.cfg.query_timeout_s)  # the reply, if any, is in by then


def test_a_rejoining_vehicle_pulls_only_what_is_new(tmp_path):
    async def main() -> None:
        a, held = library_of(6)
        assert len(held) >= 4, held
        b = controller()
        with router(tmp_path, "router.json5", {}, tls=False) as r:
            async with vehicle(vehicle_config("v1", r, "client.json5"), a) as v1:
                cfg2 = replace(vehicle_config("v2", r, "client.json5"), helper_timeout_s=1.0)
                async with vehicle(cfg2, b) as v2:
                    # a fresh join: the whole library
                    await until(lambda: all(s in b.candidates for s in held), "the snapshot")
                    fresh = v2.stats()["entries_received"]
                    assert fresh >= len(held)
                    # 1. the router restarts: every vehicle's token comes back, each queried
                    got = v2.stats()["entries_received"]
                    queries = v1.stats().get("queries_answered", 0)
                    r.proc.send_signal(signal.SIGTERM)
                    r.proc.wait(timeout=10)
                    await asyncio.sleep(0.5)
                    with router(tmp_path, "router.json5", {}, tls=False, port=r.port):
                        await answered(v1, v2, "v2's query after the router's restart", queries)
                        assert v2.stats()["entries_received"] == got, "re-pulled on rejoin"
                        # a controller learned now is new: it alone travels
                        s_new = learn_new(a, TARGETS[2])  # vertical: none of the library's
                        await until(lambda: s_new in b.candidates, "the new controller")
                        got = v2.stats()["entries_received"]
                        assert got == fresh + 1
                        # 2. v2's helper is killed: the next one queries lib/* with the marks
                        # the dead one saved
                        for sig in (signal.SIGKILL, signal.SIGSTOP):  # dead, then wedged
                            pid = v2.helper_pid()
                            assert pid is not None
                            queries = v1.stats().get("queries_answered", 0)
                            # the helper saves its marks on its turn (0.1 s, later under
                            # load): a kill before that loses the newest, and what arrived
                            # since travels again
                            await asyncio.sleep(2.0)
                            os.kill(pid, sig)

                            def replaced(p: int = pid) -> bool:
                                return v2.helper_pid() not in (None, p)

                            def queried(q: int = queries) -> bool:
                                return v1.stats()["queries_answered"] > q

                            await until(replaced, "v2's helper replaced", 60)
                            await until(queried, "the new helper's query", 60)
                            await asyncio.sleep(v2.cfg.query_timeout_s)
                            assert v2.stats()["entries_received"] == got, "re-pulled"
                        up_to_date = v1.stats()["queries_up_to_date"]
                        assert up_to_date >= 3  # the router's restart, the two helpers'
                        # answered with an empty reply, taken as such (silence would be asked
                        # again, and a repeat racing a publication pulled it twice: CI)
                        assert v2.stats()["replies_up_to_date"] >= 1
                        assert v1.stats()["bytes_answered"] > 0
                        assert v2.stats()["bytes_received"] > 0

    asyncio.run(main())


def test_high_water_marks_follow_on_and_survive_in_the_shared_buffer():
    """The bookkeeping alone: a publication advances a mark only from where it stands, a
    snapshot reply sets it, and a new helper reads both tables from the buffer."""
    import ctypes

    from epc_offboard.control.library_types import LibraryEntry
    from epc_offboard.fleet.session import HighWater

    a = HighWater(1)
    lib = [LibraryEntry((i,)) for i in range(5)]
    assert a.number(0, lib[:3]) == (0, 3)
    assert a.number(0, lib[1:4]) == (3, 4)  # only (3,) is new
    b = HighWater(1)
    b.received(0, "a", {"e": a.epoch, "p": 0, "s": 3}, True)  # follows on from nothing
    b.received(0, "a", {"e": a.epoch, "p": 4, "s": 5}, True)  # a gap: not advanced
    assert b.held[(0, "a")] == (a.epoch, 3)
    query = json.loads(b.query(0, "*"))
    assert a.since(query, "a") == (3, False)
    assert [e.active_set for e in a.newer(0, lib, 3)] == [(3,)]
    assert a.since(query, "other") == (0, False)
    assert a.since({"h": {"a": [a.epoch + 1, 3]}}, "a") == (0, False)
    b.received(0, "a", {"e": a.epoch, "s": 4}, False)  # a snapshot reply sets it
    buf = (ctypes.c_char * 4096)()
    b.save(buf)
    c = HighWater(1, bytes(buf.raw))
    assert c.held == {(0, "a"): (a.epoch, 4)}
    assert c.epoch == b.epoch
    assert HighWater(2, bytes(buf.raw)).held == {}  # another set of problems: start afresh
    assert HighWater(1, b"\xff garbage").held == {}
    many = [LibraryEntry((i, i + 1)) for i in range(100)]
    a.number(0, many)
    a.forget(0, lib[:2], keep=10)  # the library's two and the newest ten others
    assert set(a.numbers[0]) == {(0,), (1,)} | {e.active_set for e in many[-10:]}
    assert a.number(0, [LibraryEntry((2,))]) == (104, 105)  # forgotten: numbered anew


def test_a_new_process_answers_a_mark_of_its_former_epoch_with_what_it_does_not_cover():
    """A restarted vehicle numbers under a new epoch; its library's numbers under the old
    one (``own``, as the store kept them) come back as ``former``. A query with a mark of
    the old epoch gets only what that numbering does not cover up to the mark, an
    unnumbered one too (learned after the last save); a mark of neither epoch, everything."""
    import ctypes

    from epc_offboard.control.library_types import LibraryEntry
    from epc_offboard.fleet.session import HighWater

    old = HighWater(1)
    lib = [LibraryEntry((i,)) for i in range(5)]
    old.number(0, lib[:4])
    old.of_library(0, lib[:3])  # the snapshot's library: (3,) was published, then evicted
    buf = (ctypes.c_char * 4096)()
    old.save(buf)
    own = json.loads(bytes(buf.raw).rstrip(b"\0"))["own"]
    assert own == {"epoch": old.epoch, "numbers": [[[0, 1], [1, 2], [2, 3]]]}
    new = HighWater(1, json.dumps({"epoch": 7, "numbers": [[]], "held": [],
                                   "former": own}).encode())  # fmt: skip
    assert new.epoch == 7
    assert new.former is not None
    since, former = new.since({"h": {"a": [old.epoch, 2]}}, "a")
    assert (since, former) == (2, True)
    # (2,) above the mark; (3,) and (4,) not in the saved library's numbering: they go too
    assert [e.active_set for e in new.newer(0, lib, since, former)] == [(2,), (3,), (4,)]
    assert new.newer(0, lib[:2], since, former) == []
    assert new.since({"h": {"a": [old.epoch + 1, 2]}}, "a") == (0, False)
    new.save(buf)  # kept for a restarted helper
    assert HighWater(1, bytes(buf.raw)).former == new.former
    assert HighWater(1, json.dumps({"epoch": 7, "numbers": [[]], "held": [],
                                    "former": {"epoch": "x"}}).encode()).former is None
