"""A late joiner flies on the fleet's library through the candidate pool (no shortcut into the
library), and the pool's backlog stays bounded against a flood."""

from __future__ import annotations

import numpy as np

from epc_offboard.control.epc import CandidatePool, ExperienceController
from epc_offboard.fleet.exchange import snapshot_payload
from epc_offboard.fleet.sharing import FleetSharing, SharingConfig
from epc_offboard.fleet.wire import decode_controllers
from epc_offboard.service.miss_solver import MissSolver
from tests import test_sharing
from tests.mpc_cases import position_problem

loop_factorisations = test_sharing.loop_factorisations  # the fixture, shared

TICKS = 240
DT_S = 0.1  # position_problem's step


def zigzag_refs(problem, k: int) -> np.ndarray:
    """References for x_1..x_N at tick k: north at 1.5 m/s while sweeping east and back
    over 10 m every 4 s, i.e. 2.5 m/s — beyond the 2 m/s bound, so the velocity and
    acceleration constraints switch on and off along the way (many active sets)."""
    t = (k + 1 + np.arange(problem.horizon)) * DT_S
    phase = (t % 8.0) / 4.0
    refs = np.zeros((problem.horizon, problem.nx))
    refs[:, 0] = 1.5 * t
    refs[:, 1] = np.where(phase < 1.0, phase, 2.0 - phase) * 10.0 - 5.0
    return refs


def fly(ctrl: ExperienceController, solver: MissSolver | None = None) -> int:
    """The zigzag in closed loop on the problem's own model; returns the ticks that missed."""
    p = ctrl.problem
    x = np.zeros(p.nx)
    misses = 0
    for k in range(TICKS):
        if solver is not None:
            solver.pump(wait=True)  # lockstep: the worker's answers join at fixed ticks
        d = ctrl.step(x, zigzag_refs(p, k))
        misses += d.source != "hit"
        x = p.model.A @ x + p.model.B @ d.u
    return misses


def sharing(ctrl: ExperienceController, vehicle: str) -> FleetSharing:
    # no session is opened: only the import path is used
    return FleetSharing(SharingConfig(vehicle_id=vehicle, fleet="test"), [("position", ctrl)])


def test_a_late_joiner_flies_on_the_fleets_library(loop_factorisations):
    """A flies the zigzag and learns; B, joining later, gets A's snapshot (encoded, decoded
    and imported as a fleet query's answer is: into the candidate pool, not the library) and
    flies the same zigzag with the miss worker. B misses far less than a vehicle alone, and
    the controllers it takes from A cost its loop no factorisation."""
    p = position_problem(8)
    a = ExperienceController(p, max_size=200)
    assert fly(a) >= 20  # A's own first flight: a library worth sharing
    payload = snapshot_payload(p.signature(), "a", a.export_library(), a.export_transitions(),
                               262_144)  # fmt: skip
    snapshot = decode_controllers(payload, max_payload_bytes=262_144, n_con=p.n_con)
    assert len(snapshot.entries) == a.stats.size
    assert snapshot.transitions

    alone = ExperienceController(p, max_size=200, learn_on_miss=False)
    solver = MissSolver({"position": alone})
    solver.start()
    try:
        misses_alone = fly(alone, solver)
    finally:
        solver.close()

    b = ExperienceController(p, max_size=200, learn_on_miss=False)
    sb = sharing(b, "b")
    sb.offer_message("position", snapshot)
    assert b.stats.size == 0  # candidates, not library entries
    assert len(b.candidates) == b.candidates.max_per_origin  # A is not proven here yet
    assert len(b.candidates) + b.candidates.backlog == len(snapshot.entries)
    solver = MissSolver({"position": b})
    solver.start()
    loop_factorisations[0] = 0
    try:
        misses_shared = fly(b, solver)
    finally:
        solver.close()

    assert misses_alone >= 30
    assert misses_shared <= 0.35 * misses_alone, (misses_shared, misses_alone)
    assert b.stats.received_shared >= 15
    origins = {e.origin for e in b.export_library()}
    assert origins <= {"solved", "shared:a"}
    # what the worker solved or found at a miss comes with the map it built (add_built
    # checks it again), and every other promotion used a map the worker built: the loop
    # factorised nothing
    assert b.stats.qp_solves + solver.counters["candidates_found"] > 0
    assert loop_factorisations[0] == 0
    assert loop_factorisations[0] < b.stats.received_shared


def test_the_backlog_is_bounded_and_a_proven_origin_keeps_its_earned_share():
    pool = CandidatePool(8, 2, max_backlog=20, max_backlog_per_origin=10)
    for i in range(30):  # one origin's whole snapshot: only its bound is kept, as tuples
        pool.offer((i,), "shared:a", importance=float(i), uses=i)
    assert len(pool) == 2
    assert pool.backlog == 8
    assert pool.unbuilt == 2  # no map for anything in the backlog
    assert set(pool._known["shared:a"]) == {(i,) for i in range(20, 30)}  # its most used
    # proven: a earns quota, the refocus fills it from the backlog
    pool.promoted((29,), "shared:a")
    assert pool.quota("shared:a") == 4  # 2 x (1 + 1 promotion), at most 8 - 2
    pool.refocus(None)
    mine = [a for a, o in pool.items() if o == "shared:a"]
    assert len(mine) == 4
    known = set(pool._known["shared:a"])
    for k in range(40):  # then a flood from rotating ids: the bounds hold ...
        pool.offer((100 + k,), f"shared:id{k}")
        assert len(pool) <= 8
        assert pool._known_total <= 20
    # ... and it takes neither a's pool slots nor its backlog
    assert [a for a, o in pool.items() if o == "shared:a"] == mine
    assert set(pool._known["shared:a"]) == known
    assert pool.wanted(10) == sorted(mine, key=lambda a: pool._rank[a])
    pool.offer((300,), "shared:new")  # a newcomer still gets in
    assert ((300,), "shared:new") in pool.items()


def test_refocus_follows_the_sender():
    """A proven origin's quota (4 here) goes to the controller in use's successors in the
    sender's transitions, then to what the sender used after it, then to its most used."""
    pool = CandidatePool(6, 2, max_backlog=50, max_backlog_per_origin=40)
    chain = [(i,) for i in range(20)]
    for i, a in enumerate(chain):  # the sender flew 0 -> 1 -> ... -> 19, and 5 -> 17 often
        succ = ((17,), (6,)) if i == 5 else ((chain[i + 1],) if i + 1 < len(chain) else ())
        pool.offer(a, "shared:a", importance=float(i), uses=50 if i == 0 else 1,
                   successors=succ)
    pool.promoted((5,), "shared:a")
    pool.refocus((5,))
    assert [a for a, _ in pool.items() if a in pool._rank] == sorted(
        [(17,), (6,), (7,), (0,)], key=lambda a: pool._rank[a])
    assert [pool._rank[a] for a in [(17,), (6,), (7,), (0,)]] == [0, 1, 2, 3]
    pool.promoted((17,), "shared:a")
    pool.refocus((17,))  # after the sender's last it wraps to its first; then its most used
    assert sorted(a for a, _ in pool.items()) == [(0,), (16,), (18,), (19,)]
    pool.refocus((99,))  # a local controller: the window stays where the sender's was
    assert sorted(a for a, _ in pool.items()) == [(0,), (16,), (18,), (19,)]
