"""Fleet sharing over real Zenoh on loopback: explicit tcp/127.0.0.1 endpoints, no multicast.

Each peer is a FleetSharing session with its own ExperienceController on a small position
problem; the tests poll with a deadline rather than sleeping. A received controller is a
candidate (``ctrl.candidates``) until a tick it is optimal for promotes it into the library.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import os
import time
from collections.abc import AsyncIterator, Callable

import numpy as np
import pytest
import zenoh

from epc_offboard.common.ports import free_port
from epc_offboard.control.epc import ExperienceController
from epc_offboard.control.library_types import LibraryEntry
from epc_offboard.fleet import sharing as sharing_module
from epc_offboard.fleet.sharing import FleetSharing, SharingConfig
from epc_offboard.fleet.wire import (
    ControllerMessage,
    MessageKind,
    ReferenceMessage,
    decode_controllers,
    encode_controllers,
    encode_reference,
)
from tests.mpc_cases import hover_refs, position_problem
from tests.slow_start import spend_cpu_at_each_start

pytestmark = pytest.mark.timeout(60)

FLEET = "test"
# targets far enough that input and velocity bounds are active: distinct active sets
TARGETS = ([10.0, 0.0, 0.0], [0.0, -10.0, 0.0], [0.0, 0.0, 10.0], [-10.0, 10.0, 0.0])


def endpoint(port: int) -> str:
    return f"tcp/127.0.0.1:{port}"


def config(vid: str, port: int, others: list[int], **kw) -> SharingConfig:
    base: dict = {
        "enabled": True,
        "fleet": FLEET,
        "vehicle_id": vid,
        "listen": (endpoint(port),),
        "connect": tuple(endpoint(p) for p in others),
        "scouting_multicast": False,
        "publish_period_s": 0.05,
        "query_timeout_s": 2.0,
        # fast enough that a test's flood drains in a second or two (the budget itself is
        # tested on its own, below)
        "candidates_per_s": 5000.0,
        # these tests are about what is shared, not priorities: a helper at nice +10 (the
        # service's default, below the loops) gets a tenth of a core beside two CPU hogs at
        # nice 0, and took over 30 s to start and publish
        "helper_nice": 0,
    }
    base.update(kw)
    return SharingConfig(**base)


def controller(horizon: int = 8) -> ExperienceController:
    return ExperienceController(position_problem(horizon), max_size=50)


def learn(ctrl: ExperienceController, target) -> tuple[int, ...]:
    """One tick from rest towards ``target``: a solve that adds a controller."""
    p = ctrl.problem
    d = ctrl.step(np.zeros(p.nx), hover_refs(p, target))
    assert d.source == "solved", d.source
    return ctrl.export_library()[0].active_set


def used_as_hit(ctrl: ExperienceController, target) -> bool:
    p = ctrl.problem
    solves = ctrl.stats.qp_solves
    d = ctrl.step(np.zeros(p.nx), hover_refs(p, target))
    return d.source == "hit" and ctrl.stats.qp_solves == solves


async def until(cond: Callable[[], bool], what: str, timeout_s: float = 30.0) -> None:
    # the fleet helper is a process of its own (spawned: imports zenoh and numpy); at load
    # 6 on 2 cores its start alone took over 10 s. A bound on "eventually", free when quick
    deadline = time.monotonic() + timeout_s
    while not cond():
        if time.monotonic() > deadline:
            raise AssertionError(f"timed out waiting for {what}")
        await asyncio.sleep(0.02)


@contextlib.asynccontextmanager
async def peer(cfg: SharingConfig, ctrl: ExperienceController) -> AsyncIterator[FleetSharing]:
    async with FleetSharing(cfg, [("position", ctrl)]) as sharing:
        task = asyncio.create_task(sharing.run(), name="library-sharing")
        try:
            yield sharing
        finally:
            task.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await task


def test_a_controller_learned_by_one_peer_is_a_hit_for_the_others():
    async def main() -> None:
        ports = [free_port() for _ in range(3)]
        ctrls = [controller() for _ in range(3)]
        async with contextlib.AsyncExitStack() as stack:
            peers = []
            for i in range(3):
                others = [p for j, p in enumerate(ports) if j != i]
                peers.append(
                    await stack.enter_async_context(
                        peer(config(f"v{i + 1}", ports[i], others), ctrls[i])
                    )
                )
            await until(lambda: all(len(s.stats()) and s.stats()["peers"] == 2 for s in peers),
                        "three peers to see each other")  # fmt: skip
            aset = learn(ctrls[0], TARGETS[0])
            await until(lambda: aset in ctrls[1].candidates and aset in ctrls[2].candidates,
                        "sharing")  # fmt: skip
            for c in ctrls[1:]:
                assert not c.contains(aset)  # a candidate until it proves optimal here
                assert used_as_hit(c, TARGETS[0])
                assert c.contains(aset)
                assert c.export_library()[0].origin == "shared:v1"
                assert c.stats.received_shared == 1
                assert c.stats.qp_solves == 0
            # and back: what peer 3 learns reaches peer 1
            aset3 = learn(ctrls[2], TARGETS[1])
            await until(lambda: aset3 in ctrls[0].candidates, "sharing from peer 3")
            assert used_as_hit(ctrls[0], TARGETS[1])
            assert peers[0].stats()["entries_published"] == 1

    asyncio.run(main())


def test_a_late_joiner_gets_the_snapshot():
    async def main() -> None:
        pa, pc = free_port(), free_port()
        a, c = controller(), controller()
        sets = [learn(a, t) for t in TARGETS[:3]]
        async with peer(config("early", pa, [pc]), a) as sa:
            await until(lambda: sa.stats().get("entries_published", 0) >= 3, "a's batch")
            # nobody heard the batch; the joiner can only learn these from the snapshot
            async with peer(config("late", pc, [pa]), c) as sc:
                await until(lambda: all(s in c.candidates for s in sets), "the snapshot")
                assert sc.stats()["entries_offered"] == 3
                assert all(used_as_hit(c, t) for t in TARGETS[:3])
                assert c.stats.received_shared == 3
                assert c.stats.qp_solves == 0

    asyncio.run(main())


def test_a_peer_with_another_problem_signature_is_ignored():
    async def main() -> None:
        pa, pb, pd = free_port(), free_port(), free_port()
        a, b, d = controller(), controller(), controller(horizon=6)
        assert d.problem.signature() != a.problem.signature()
        async with (
            peer(config("a", pa, [pb, pd]), a) as sa,
            peer(config("b", pb, [pa, pd]), b),
            peer(config("d", pd, [pa, pb]), d) as sd,
        ):
            learn(d, TARGETS[0])
            aset = learn(a, TARGETS[1])
            await until(lambda: aset in b.candidates, "a -> b")
            await until(lambda: sd.stats().get("entries_published", 0) >= 1, "d publishing")
            await asyncio.sleep(0.2)  # several publish periods: d's batch had every chance
            assert a.stats.size == 1
            assert (b.stats.size, b.stats.candidates) == (0, 1)
            assert d.stats.size == 1
            assert a.stats.received_shared == 0
            await until(lambda: sa.stats().get("senders", 0) >= 1, "b's snapshot reply")
            assert sa.stats()["senders"] == 1  # b only: a never subscribed to d's keys
            assert sd.stats().get("messages_received", 0) == 0
            assert sd.stats()["peers"] == 0

    asyncio.run(main())


def test_malformed_truncated_and_oversized_payloads_are_rejected_and_counted():
    async def main() -> None:
        pb, praw = free_port(), free_port()
        b = controller()
        sig = b.problem.signature()
        cfg = config("b", pb, [], max_payload_bytes=512, burst_messages=1000)
        good = encode_controllers(
            ControllerMessage(MessageKind.BATCH, sig, "evil", (LibraryEntry((0, 1, 2)),))
        )
        out_of_range = encode_controllers(
            ControllerMessage(MessageKind.BATCH, sig, "evil", (LibraryEntry((0, 60000)),))
        )
        other_sig = encode_controllers(
            ControllerMessage(MessageKind.BATCH, "f" * 32, "evil", (LibraryEntry((0,)),))
        )
        spoofed = encode_controllers(
            ControllerMessage(MessageKind.BATCH, sig, "b2", (LibraryEntry((0,)),))
        )
        bad = [b"garbage", good[:-1], good[:20], out_of_range, other_sig, spoofed, b""]
        raw_cfg = zenoh.Config()
        raw_cfg.insert_json5("mode", '"peer"')
        raw_cfg.insert_json5("listen/endpoints", json.dumps([endpoint(praw)]))
        raw_cfg.insert_json5("connect/endpoints", json.dumps([endpoint(pb)]))
        raw_cfg.insert_json5("scouting/multicast/enabled", "false")
        key = f"epc/{FLEET}/{sig}/ctl/evil"
        async with peer(cfg, b) as sb:
            with zenoh.open(raw_cfg) as raw:
                # connected once a probe arrives
                async def probe() -> None:
                    while sb.stats().get("rejected_malformed", 0) == 0:
                        raw.put(key, b"probe")
                        await asyncio.sleep(0.05)

                await asyncio.wait_for(probe(), 10.0)
                base = sb.stats()["rejected_malformed"]
                for payload in bad:
                    raw.put(key, payload)
                raw.put(key, b"\0" * 513)
                await until(
                    lambda: (
                        sb.stats()["rejected_malformed"] == base + len(bad)
                        and sb.stats().get("rejected_oversized", 0) == 1
                    ),
                    "every bad payload counted",
                )
                assert b.stats.size == b.stats.candidates == 0
                assert b.stats.received_shared == 0
                # the valid one still goes through the same path
                raw.put(key, good)
                await until(lambda: b.stats.candidates == 1, "the valid payload")
                assert (0, 1, 2) in b.candidates

    asyncio.run(main())


def test_a_flooding_peer_is_rate_limited():
    async def main() -> None:
        pb, praw = free_port(), free_port()
        b = controller()
        sig = b.problem.signature()
        cfg = config("b", pb, [], burst_messages=3, max_messages_per_s=0.01)
        raw_cfg = zenoh.Config()
        raw_cfg.insert_json5("connect/endpoints", json.dumps([endpoint(pb)]))
        raw_cfg.insert_json5("listen/endpoints", json.dumps([endpoint(praw)]))
        raw_cfg.insert_json5("scouting/multicast/enabled", "false")
        async with peer(cfg, b) as sb:
            with zenoh.open(raw_cfg) as raw:
                await until(lambda: sb.stats()["peers"] >= 0, "open")
                sets = [(i,) for i in range(20)]

                async def flood() -> None:
                    i = 0
                    while sb.stats().get("messages_received", 0) < 10:
                        payload = encode_controllers(
                            ControllerMessage(
                                MessageKind.BATCH, sig, "evil", (LibraryEntry(sets[i % 20]),)
                            )
                        )
                        raw.put(f"epc/{FLEET}/{sig}/ctl/evil", payload)
                        i += 1
                        await asyncio.sleep(0.01)

                await asyncio.wait_for(flood(), 10.0)
                await until(lambda: b.stats.candidates == 3, "the burst's three imports")
                stats = sb.stats()
                assert stats["rate_limited"] >= 7
                assert stats["entries_offered"] == 3

    asyncio.run(main())


def test_sharing_survives_a_peer_restart():
    async def main() -> None:
        pa, pb = free_port(), free_port()
        a = controller()
        async with peer(config("a", pa, [pb]), a) as sa:
            b1 = controller()
            async with peer(config("b", pb, [pa]), b1):
                s1 = learn(a, TARGETS[0])
                await until(lambda: s1 in b1.candidates, "first controller")
            await until(lambda: sa.stats()["peers"] == 0, "a to see b leave")
            s2 = learn(a, TARGETS[1])  # learned while b is down
            await until(lambda: sa.stats().get("entries_published", 0) == 2, "a publishing")
            b2 = controller()  # the restarted process starts empty
            async with peer(config("b", pb, [pa]), b2):
                await until(lambda: s1 in b2.candidates and s2 in b2.candidates, "re-fetch")
                s3 = learn(a, TARGETS[2])
                await until(lambda: s3 in b2.candidates, "live batches resume")
                assert all(used_as_hit(b2, t) for t in TARGETS[:3])

    asyncio.run(main())


def test_live_reference_is_received_fresh_then_stale():
    async def main() -> None:
        pa, praw = free_port(), free_port()
        cfg = config("a", pa, [], enabled=False)
        raw_cfg = zenoh.Config()
        raw_cfg.insert_json5("connect/endpoints", json.dumps([endpoint(pa)]))
        raw_cfg.insert_json5("listen/endpoints", json.dumps([endpoint(praw)]))
        raw_cfg.insert_json5("scouting/multicast/enabled", "false")
        async with FleetSharing(cfg, [], share_library=False, reference=True) as sa:
            key = FleetSharing.reference_key(FLEET, "a")
            msg = ReferenceMessage((1.0, 2.0, -3.0), (0.5, 0.0, 0.0), 0.25)
            with zenoh.open(raw_cfg) as raw:

                async def publish() -> None:
                    while sa.live_reference(time.monotonic(), 0.5) is None:
                        raw.put(key, b'{"v": 1, "pos_ned_m": [0, 0, NaN]}')
                        raw.put(key, encode_reference(msg))
                        await asyncio.sleep(0.05)

                await asyncio.wait_for(publish(), 10.0)
            ref = sa.live_reference(time.monotonic(), 0.5)
            assert ref is not None
            assert ref.message == msg
            assert sa.stats()["reference_rejected"] >= 1
            assert sa.live_reference(time.monotonic() + 0.6, 0.5) is None

    asyncio.run(main())


def test_live_reference_horizon_holds_tracks_and_follows_a_path():
    from epc_offboard.control.trajectories import live_reference_horizon

    kw: dict = {"yaw_rad": 0.5, "age_s": 0.1, "dt_s": 0.1, "steps": 4}
    hold = live_reference_horizon((1.0, 2.0, -3.0), None, (), None, **kw).ahead
    assert hold.shape == (4, 9)
    np.testing.assert_allclose(hold[:, :3], np.tile([1.0, 2.0, -3.0], (4, 1)))
    assert not hold[:, 3:].any()
    track = live_reference_horizon((0.0, 0.0, -2.0), (1.0, 0.0, 0.0), (), None, **kw).ahead
    np.testing.assert_allclose(track[:, 0], [0.2, 0.3, 0.4, 0.5])  # age + k dt, at 1 m/s
    np.testing.assert_allclose(track[:, 3], 1.0)
    path = live_reference_horizon(
        (0.0, 0.0, -2.0), None, ((0.2, 0.0, -2.0), (0.2, 0.2, -2.0)), 0.2, **kw
    ).ahead
    # t = 0.2, 0.3, 0.4, 0.5 s along 0 -> (0.2, 0) -> (0.2, 0.2), then held at the end
    np.testing.assert_allclose(path[:, 0], [0.2, 0.2, 0.2, 0.2])
    np.testing.assert_allclose(path[:, 1], [0.0, 0.1, 0.2, 0.2])
    np.testing.assert_allclose(path[:, 4], [1.0, 1.0, 0.0, 0.0])


# -- a hostile or broken peer (issue 16, fault 5) -----------------------------------------


def raw_config(own_port: int, connect_port: int) -> zenoh.Config:
    conf = zenoh.Config()
    conf.insert_json5("mode", '"peer"')
    conf.insert_json5("listen/endpoints", json.dumps([endpoint(own_port)]))
    conf.insert_json5("connect/endpoints", json.dumps([endpoint(connect_port)]))
    conf.insert_json5("scouting/multicast/enabled", "false")
    return conf


def useless_sets(problem, exclude: tuple[int, ...]) -> list[tuple[int, ...]]:
    """Well-formed active sets (in range, sorted, at most N nu rows) that are never the
    optimum of the far-target ticks flown here: one or two rows only."""
    rows = range(problem.n_con)
    sets = [(i,) for i in rows] + [(i, j) for i in rows for j in rows if i < j]
    return [s for s in sets if s != exclude]


async def connected(raw: zenoh.Session, sb: FleetSharing, sig: str) -> None:
    """Probe until the raw peer's puts reach ``sb`` (the route is up)."""

    async def probe() -> None:
        while sb.stats().get("messages_received", 0) == 0:
            raw.put(f"epc/{FLEET}/{sig}/ctl/probe", b"probe")
            await asyncio.sleep(0.05)

    await asyncio.wait_for(probe(), 10.0)


async def flood(
    raw: zenoh.Session, sb: FleetSharing, sig: str, sets, ids: list[str], per_message: int
) -> None:
    """One well-formed batch of useless controllers from each id; waits until all arrived
    and the event loop has dealt with them."""
    before = sb.stats().get("messages_received", 0)
    for k, vid in enumerate(ids):
        chunk = [sets[(k * per_message + j) % len(sets)] for j in range(per_message)]
        payload = encode_controllers(
            ControllerMessage(MessageKind.BATCH, sig, vid, tuple(LibraryEntry(s) for s in chunk))
        )
        raw.put(f"epc/{FLEET}/{sig}/ctl/{vid}", payload)
        if k % 100 == 99:
            await asyncio.sleep(0.01)
    await until(lambda: sb.stats().get("messages_received", 0) >= before + len(ids), "the flood")
    await drained(sb)


async def drained(sb: FleetSharing) -> None:
    """Until the helper's candidate inbox is empty, and what was in the pipe offered."""
    await until(lambda: sb.stats().get("candidates_waiting", 0) == 0, "the inbox to drain")
    await asyncio.sleep(0.3)  # the gauge's period, and the last turns


@pytest.fixture
def loop_factorisations(monkeypatch) -> list[int]:
    """Counts ActiveSetMap factorisations done on the main thread (the event loop's)."""
    import threading

    from epc_offboard.control import epc

    count = [0]
    original = epc.ActiveSetMap.__init__

    def counting(self, *args, **kwargs):
        if threading.current_thread() is threading.main_thread():
            count[0] += 1
        original(self, *args, **kwargs)

    monkeypatch.setattr(epc.ActiveSetMap, "__init__", counting)
    return count


def test_a_flood_from_rotating_ids_takes_no_library_slot_no_loop_time_and_locks_nobody_out(
    loop_factorisations,
):
    """1,200 vehicle ids each send a batch of well-formed, useless controllers; then a real
    peer joins. The library stays empty, the event loop factorises nothing, the candidate
    pool and the rate-limit state stay bounded, and the new peer is heard."""

    async def main() -> None:
        pb, praw, plegit = free_port(), free_port(), free_port()
        b = ExperienceController(position_problem(8), max_size=50, learn_on_miss=False)
        sig = b.problem.signature()
        legit = controller()
        legit_set = learn(legit, TARGETS[0])
        sets = useless_sets(b.problem, legit_set)
        loop_factorisations[0] = 0  # the teacher's own solve above is not b's
        async with peer(config("b", pb, []), b) as sb:
            with zenoh.open(raw_config(praw, pb)) as raw:
                await connected(raw, sb, sig)
                await flood(raw, sb, sig, sets, [f"evil{k}" for k in range(1200)], 20)
                stats = sb.stats()
                # past the queue (256 messages; beyond: dropped), far more than a pool holds
                assert stats["entries_received"] > 4000
                assert b.stats.size == 0, "unproven controllers took library slots"
                assert loop_factorisations[0] == 0, "the event loop factorised received sets"
                assert stats["senders"] <= 1024
                assert len(b.candidates) == b.candidates.max_size  # full, and no more
                assert stats["rate_buckets"] <= 1024
            # a legitimate vehicle joining now is heard, not rate-limited for good
            async with peer(config("legit", plegit, [pb]), legit):
                await until(lambda: legit_set in b.candidates, "the new peer's controller")
            assert b.stats.size == 0
            assert len(b.candidates) <= b.candidates.max_size

    asyncio.run(main())


def test_a_received_controller_joins_the_library_only_when_optimal_for_a_tick_here(
    loop_factorisations,
):
    """Useless controllers flood in beside a real one. In flight (the miss worker screens
    the candidates), only the real one is promoted, at the tick it is optimal for, with its
    origin; the flood never enters the library."""
    from epc_offboard.service.miss_solver import MissSolver

    async def main() -> None:
        pb, praw, plegit = free_port(), free_port(), free_port()
        b = ExperienceController(position_problem(8), max_size=50, learn_on_miss=False)
        p = b.problem
        sig = p.signature()
        legit = controller()
        legit_set = learn(legit, TARGETS[0])
        loop_factorisations[0] = 0  # the teacher's own solve above is not b's
        async with peer(config("b", pb, []), b) as sb:
            # after FleetSharing sized the pool; slices long enough that the worker screens
            # every candidate before the solve however loaded the machine (the slice's
            # time bound is tested elsewhere)
            solver = MissSolver({"position": b}, slice_s=30.0)
            solver.start()
            try:
                with zenoh.open(raw_config(praw, pb)) as raw:
                    await connected(raw, sb, sig)
                    sets = useless_sets(p, legit_set)
                    await flood(raw, sb, sig, sets, ["junk1", "junk2", "junk3"] * 10, 20)
                async with peer(config("legit", plegit, [pb]), legit):
                    await until(lambda: legit_set in b.candidates, "the real controller")
                    await drained(sb)
                assert b.stats.size == 0, "unproven controllers took library slots"
                # 16 a peer (3 junk ids) and the real one
                assert len(b.candidates) == 3 * 16 + 1
                assert legit_set in b.candidates
                solver.pump()  # the candidates go to the worker
                d = b.step(np.zeros(p.nx), hover_refs(p, TARGETS[0]))
                assert d.source == "intermediate"  # a miss: nothing proven here yet
                solver.pump(wait=True)
                assert solver.pump(wait=True) == 1
                assert solver.counters["candidates_found"] == 1
                assert used_as_hit(b, TARGETS[0])
                assert [(e.active_set, e.origin) for e in b.export_library()] == [
                    (legit_set, "shared:legit")
                ]
                assert b.stats.qp_solves == 0
                assert b.stats.received_shared == 1
                # elsewhere the flood is no answer either: the worker solves
                b.step(np.zeros(p.nx), hover_refs(p, TARGETS[1]))
                solver.pump(wait=True)
                assert solver.pump(wait=True) == 1
                assert b.stats.qp_solves == 1
                assert sorted(e.origin for e in b.export_library()) == ["shared:legit", "solved"]
                assert not any(b.contains(s) for s in sets)
                # the worker shipped the maps of the two it promoted or added (the loop only
                # checked them) and the flood's stayed there: the loop built none
                assert loop_factorisations[0] == 0
            finally:
                solver.close()

    asyncio.run(main())


def test_token_buckets_expire_and_never_refuse_a_new_sender():
    from epc_offboard.fleet.exchange import TokenBuckets

    buckets = TokenBuckets(rate_per_s=1.0, burst=2)
    assert all(buckets.allow(f"evil{k}", 0.0) for k in range(1200))  # one burst each
    assert len(buckets) <= 1024
    assert buckets.allow("legit", 0.5)  # a new peer, mid-flood
    assert buckets.allow("legit", 0.5)
    assert not buckets.allow("legit", 0.5)  # its own quota still holds
    assert buckets.allow("late", 10.0)  # after the refill time: every old bucket expired
    assert len(buckets) == 1


def test_origin_is_kept_through_the_store_and_db_info(tmp_path, capsys):
    """A fleet candidate promoted in flight is stored as shared:<vehicle>, loads back as
    such, and `db info` does not count it as this vehicle's own solve."""
    from epc_offboard.cli import main as cli_main
    from epc_offboard.control.cascade import Cascade
    from epc_offboard.control.types import VehicleState
    from epc_offboard.service.config import load_service_config
    from epc_offboard.store import experience
    from epc_offboard.store.database import LibraryStore

    cfg = load_service_config("config/sitl.toml")

    def cascade() -> Cascade:
        return Cascade(cfg.position, cfg.attitude, cfg.estimator, 0.01)

    state = VehicleState(
        time_s=0.0,
        pos_ned_m=np.array([0.0, 0.0, -2.5]),
        vel_ned_m_s=np.array([1.5, 0.0, 0.0]),
        q_ned_frd=np.array([1.0, 0.0, 0.0, 0.0]),
        rate_frd_rad_s=np.zeros(3),
        position_age_s=0.0,
        attitude_age_s=0.0,
    )
    teacher, pupil = cascade(), cascade()
    teacher.position_tick(state, teacher.position.hold(state.pos_ned_m), learn=True)
    (taught,) = [e.active_set for e in dict(teacher.experience_controllers())["position"]
                 .export_library()]  # fmt: skip
    pupil_pos = dict(pupil.experience_controllers())["position"]

    async def receive() -> None:  # from vehicle v7, over Zenoh, as in flight
        pp, praw = free_port(), free_port()
        sig = pupil.position.problem.signature()
        async with peer(config("pupil", pp, []), pupil_pos) as sp:
            with zenoh.open(raw_config(praw, pp)) as raw:
                await connected(raw, sp, sig)
                await flood(raw, sp, sig, [taught], ["v7"], 1)

    asyncio.run(receive())
    pupil.position_tick(state, pupil.position.hold(state.pos_ned_m), learn=True)
    assert pupil_pos.stats.qp_solves == 0  # the fleet's controller, not a solve here
    path = tmp_path / "lib.sqlite"
    with LibraryStore.open(path) as store:
        experience.save(pupil, store)
        sig = pupil.position.problem.signature()
        assert [(c.active_set, c.origin) for c in store.load_controllers(sig)] == [
            (taught, "shared:v7")
        ]
        again = cascade()
        experience.load(again, store)
    again_pos = dict(again.experience_controllers())["position"]
    assert [(e.active_set, e.origin) for e in again_pos.export_library()] == [
        (taught, "shared:v7")
    ]
    capsys.readouterr()
    assert cli_main(["db", "info", str(path)]) == 0
    out = capsys.readouterr().out
    assert "shared 1" in out
    assert "solved" not in out.split(sig)[1].splitlines()[0]


# -- the fleet in a process of its own (issue 21) ------------------------------------------


def test_the_control_process_takes_at_most_its_budget_of_candidates_a_second():
    """A flood decoded in the helper reaches the controllers at candidates_per_s at most,
    whatever the peer sends, and all of it (within the inbox's bounds) in time."""

    async def main() -> None:
        pb, praw = free_port(), free_port()
        b = controller()
        sig = b.problem.signature()
        cfg = config("b", pb, [], candidates_per_s=40.0, burst_messages=1000)
        async with peer(cfg, b) as sb:
            with zenoh.open(raw_config(praw, pb)) as raw:
                await connected(raw, sb, sig)
                sets = useless_sets(b.problem, ())
                ids = [f"junk{k}" for k in range(30)]
                await until(lambda: sb.stats()["candidates_taken"] == 0, "nothing yet")
                before = sb.stats().get("messages_received", 0)
                for k, vid in enumerate(ids):
                    chunk = tuple(LibraryEntry(sets[k * 20 + j]) for j in range(20))
                    raw.put(f"epc/{FLEET}/{sig}/ctl/{vid}",
                            encode_controllers(ControllerMessage(MessageKind.BATCH, sig, vid,
                                                                 chunk)))  # fmt: skip
                await until(
                    lambda: sb.stats().get("messages_received", 0) >= before + len(ids), "all"
                )
                t0 = time.monotonic()
                taken0 = sb.stats()["candidates_taken"]
                await asyncio.sleep(1.5)
                taken = sb.stats()["candidates_taken"] - taken0
                elapsed = time.monotonic() - t0
                # a turn's worth (2) of slack either side of 40/s
                assert taken <= 40.0 * elapsed + 4, (taken, elapsed)
                assert taken >= 20, taken  # and it does flow (a loaded machine: half)
                assert sb.stats()["candidates_waiting"] > 400  # the rest waits in the helper

    asyncio.run(main())


def counted(sharing: FleetSharing, name: str, n: int) -> Callable[[], bool]:
    return lambda: sharing.stats().get(name, 0) == n


def test_a_wedged_or_killed_fleet_helper_is_restarted_and_sharing_resumes():
    import signal

    async def main() -> None:
        pa, pb = free_port(), free_port()
        a, b = controller(), controller()
        cfg_b = config("b", pb, [pa], helper_timeout_s=1.0)
        async with peer(config("a", pa, [pb]), a), peer(cfg_b, b) as sb:
            s1 = learn(a, TARGETS[0])
            await until(lambda: s1 in b.candidates, "first controller")
            for k, sig in enumerate((signal.SIGSTOP, signal.SIGKILL)):  # wedged, then dead
                pid = sb.helper_pid()
                assert pid is not None
                failures = sb.stats().get("helper_failures", 0)
                os.kill(pid, sig)
                # seen and replaced: flying on without the fleet until the restart (which at
                # load may already have come by the time the wait looks again)
                def replaced(p: int = pid, f: int = failures) -> bool:
                    return sb.stats().get("helper_failures", 0) > f and sb.helper_pid() != p

                await until(replaced, "the failure seen", 30)
                await until(lambda: sb.helper_pid() is not None, "the restart", 60)
                assert sb.stats().get("helper_restarts", 0) >= k + 1
                assert sb.helper_pid() != pid
            s2 = learn(a, TARGETS[1])
            await until(lambda: s2 in b.candidates, "sharing after the restarts", timeout_s=60)

    asyncio.run(main())


def learn_new(ctrl: ExperienceController, target) -> tuple[int, ...]:
    """Like :func:`learn`, returning the one active set the tick added."""
    before = {e.active_set for e in ctrl.export_library()}
    learn(ctrl, target)
    (new,) = {e.active_set for e in ctrl.export_library()} - before
    return new


@pytest.mark.timeout(240)  # three helpers' starts, two restart waits: on a loaded machine
def test_controllers_handed_while_no_helper_has_its_session_are_published_once_one_has():
    """Issue 21's gap: a controller learned while the helper is starting, dead, or wedged
    with it unread in its pipe, reaches the fleet once a helper has its session."""
    import signal

    async def main() -> None:
        pa, praw = free_port(), free_port()
        a = controller()
        sig = a.problem.signature()
        heard: set[tuple[int, ...]] = set()

        def on_batch(sample: zenoh.Sample) -> None:
            msg = decode_controllers(sample.payload.to_bytes(), max_payload_bytes=1 << 20,
                                     expect_signature=sig)  # fmt: skip
            heard.update(e.active_set for e in msg.entries)

        raw_cfg = zenoh.Config()
        raw_cfg.insert_json5("listen/endpoints", json.dumps([endpoint(praw)]))
        raw_cfg.insert_json5("scouting/multicast/enabled", "false")
        # a connects to the listener: every helper of a's dials it as its session opens
        cfg = config("a", pa, [praw], helper_timeout_s=2.0, helper_restart_max_s=4.0)
        with zenoh.open(raw_cfg) as raw:
            raw.declare_subscriber(f"epc/{FLEET}/{sig}/ctl/a", on_batch)
            sharing = FleetSharing(cfg, [("position", a)])
            opening = asyncio.create_task(sharing.open())
            try:
                # 1. handed before the first session opens
                await asyncio.sleep(0)
                assert not sharing.helper_running()
                s1 = learn_new(a, TARGETS[0])
                assert sharing.publish_new() == 1
                await opening
                task = asyncio.create_task(sharing.run(), name="library-sharing")
                await until(lambda: s1 in heard, "the controller learned while starting")
                # 2. learned while the helper is dead, before the next one has a session
                pid = sharing.helper_pid()
                assert pid is not None
                os.kill(pid, signal.SIGKILL)
                await until(lambda: not sharing.helper_running(), "the death seen")
                s2 = learn_new(a, TARGETS[1])
                await until(lambda: s2 in heard, "the controller learned while dead", 60)
                # 3. handed to a wedged helper (in its pipe, unread) that is then replaced
                await until(sharing.helper_running, "the restarted helper")
                pid = sharing.helper_pid()
                assert pid is not None
                os.kill(pid, signal.SIGSTOP)
                s3 = learn_new(a, TARGETS[2])
                await until(lambda: sharing.helper_pid() != pid, "the wedged helper replaced")
                await until(lambda: s3 in heard, "the controller handed to the wedged one", 60)
                stats = sharing.stats()
                assert stats["publish_dropped"] == 0
                assert stats["publish_requeued"] >= 1  # s3, taken back from the wedged one
                assert stats["helper_restarts"] >= 2
                task.cancel()
                with contextlib.suppress(asyncio.CancelledError):
                    await task
            finally:
                sharing.close()

    asyncio.run(main())


def test_the_publish_backlog_is_bounded_drops_the_oldest_and_requeues_in_order():
    from epc_offboard.fleet.sharing import PublishBacklog

    log = PublishBacklog(max_entries=3)
    e = [LibraryEntry((k,)) for k in range(6)]
    log.add(0, e[:2])
    log.add(1, e[2:4])  # 4 > 3: e[0] dropped
    assert (len(log), log.dropped) == (3, 1)
    sent: list[tuple] = []

    def take(frame: tuple) -> bool:
        sent.append(frame)
        return True

    assert log.hand_off(take) == 3
    assert [(f[1], f[2], f[3]) for f in sent] == [(0, [e[1]], 1), (1, e[2:4], 2)]
    log.done(1)  # the helper handled frame 1, then died
    assert log.requeue() == 2
    log.add(0, e[4:6])  # 4 > 3: the oldest (e[2]) goes
    assert log.dropped == 2
    sent.clear()
    assert log.hand_off(lambda f: False) == 0  # refused (a full pipe): kept
    log.hand_off(take)
    assert [(f[1], f[2], f[3]) for f in sent] == [(1, [e[3]], 3), (0, e[4:6], 4)]


def _held_sentinel(proc) -> int:
    """A write end of ``proc``'s sentinel pipe, opened through /proc: while we hold it, the
    process's exit does not show on its sentinel (as when its teardown is slow: a killed
    helper at nice +10 beside CPU hogs took 1.3 s to exit), so a join waits its whole
    timeout."""
    from pathlib import Path

    inode = os.fstat(proc.sentinel).st_ino
    for fd in Path(f"/proc/{proc.pid}/fd").iterdir():
        if os.readlink(fd) == f"pipe:[{inode}]":
            return os.open(fd, os.O_WRONLY | os.O_NONBLOCK)
    raise AssertionError("the helper's sentinel pipe not found")


async def _kill_a_wedged_helper() -> float:
    cfg = config("a", free_port(), [])
    sharing = FleetSharing(cfg, [("position", controller())])
    await sharing.open()
    try:
        helper = sharing._helper
        assert helper is not None
        held = _held_sentinel(helper.process)
        try:
            t0 = time.monotonic()
            sharing._stop_helper(kill=True)  # what _watch does to a silent or dead helper
            took_s = time.monotonic() - t0
        finally:
            os.close(held)
        await until(lambda: not helper.process.is_alive(), "the killed helper reaped")
        return took_s
    finally:
        sharing.close()


def test_a_killed_helper_is_not_joined_on_the_loops_thread():
    """A failed fleet helper (silent, dead, not started) is SIGKILLed on the event loop's
    thread, which is the loops' thread. Its exit is the machine's to schedule: joined there
    (2 s, then 1 s more), a helper SIGSTOPped 20 s and killed beside two CPU hogs held the
    loops 1.26 s and the vehicle left offboard (`bench --attack --freeze fleet`). The kill
    returns at once; the helper is reaped meanwhile."""
    took_s = asyncio.run(_kill_a_wedged_helper())
    # a join of the helper waits at least its timeout, its exit unseen while the sentinel is
    # held (main 0239a5e: 2.0 s); the kill and the reaper's start took ms. Judged against the
    # join's time on any host, not against a guess of the host's speed (a 0.5 s bound met
    # a preemption at load)
    assert took_s < sharing_module._STOP_TIMEOUT_S, took_s


STALL_S = 0.5  # the helper's start's stall bound in these tests
START_CPU_S = 3 * STALL_S  # CPU every helper start spends in these tests (slow_starts)


@pytest.fixture
def slow_starts(monkeypatch, tmp_path):
    """Every helper spawned in the test spends ``START_CPU_S`` of CPU before its own start
    (a ``sitecustomize`` on the PYTHONPATH it inherits): a start longer than the stall bound
    that runs throughout, on any machine. The helper's own start took 1-1.6 s on an idle
    host and 0.26 s on CI (stop 43's CI failure: the claim needs it longer than the bound)."""
    spend_cpu_at_each_start(monkeypatch, tmp_path, START_CPU_S)
    monkeypatch.setattr(sharing_module, "_START_TIMEOUT_S", STALL_S)


def test_a_helper_start_longer_than_its_stall_bound_but_running_is_waited_for(slow_starts):
    """Stop 42: the fleet helper's start (imports, the session's open) had 30 s on the
    clock, and at load 12-17 such starts took 93-156 s, every second running or queued (the
    miss worker's, stop 41). It is judged by progress now: a start far longer than its
    stall bound, never that long without CPU, opens its session."""

    async def main() -> None:
        sharing = FleetSharing(config("a", free_port(), []), [("position", controller())])
        t0 = time.monotonic()
        try:
            await sharing.open()  # on the clock: "did not open" at 0.5 s
            assert time.monotonic() - t0 > START_CPU_S
            assert sharing.helper_running()
        finally:
            sharing.close()

    asyncio.run(main())


@pytest.mark.timeout(180)  # three helpers' starts and two restart waits, on a loaded machine
def test_a_helper_stopped_in_its_start_is_caught_said_and_a_running_one_restarted(
    slow_starts, caplog
):
    """SIGSTOP in its start: ``open`` says so within its stall bound (the service then flies
    alone); in flight the failure is seen, said and the helper restarted, while the loops
    fly on without the fleet. A restarted helper that runs is waited for however long its
    start: on the clock each restart took longer than the bound, was killed, and the
    fleet never came back."""
    import logging
    import signal

    async def main() -> None:
        cfg = config("a", free_port(), [])
        sharing = FleetSharing(cfg, [("position", controller())])
        opening = asyncio.create_task(sharing.open())
        await asyncio.sleep(0)  # spawned: open now waits for its session
        pid = sharing.helper_pid()
        assert pid is not None
        os.kill(pid, signal.SIGSTOP)
        with pytest.raises(RuntimeError, match=r"no CPU used or waited for in 0\.5 s"):
            await opening
        assert sharing.helper_pid() is None
        sharing.close()

        sharing = FleetSharing(cfg, [("position", controller())])
        await sharing.open()
        task = asyncio.create_task(sharing.run(), name="library-sharing")
        try:
            first = sharing.helper_pid()
            assert first is not None
            os.kill(first, signal.SIGKILL)
            await until(lambda: sharing.helper_pid() not in (None, first), "a restart", 60)
            starting = sharing.helper_pid()
            assert starting is not None
            os.kill(starting, signal.SIGSTOP)
            assert sharing._slot("state") == 0  # stopped in its start
            await until(lambda: sharing.helper_pid() != starting, "the stopped one caught", 60)
            assert sharing.stats()["helper_failures"] == 2
            await until(sharing.helper_running, "a restarted helper's session", 120)
            stats = sharing.stats()
            assert stats["helper_failures"] == 2, stats  # the third start, however long
            assert stats["helper_restarts"] == 2, stats
        finally:
            task.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await task
            sharing.close()

    with caplog.at_level(logging.WARNING, logger="epc_offboard.fleet.sharing"):
        asyncio.run(main())
    said = [r.getMessage() for r in caplog.records if "did not start" in r.getMessage()]
    assert len(said) == 1, said
    assert "no CPU used or waited for in 0.5 s" in said[0], said
