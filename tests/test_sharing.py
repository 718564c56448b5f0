"""Fleet sharing over real Zenoh on loopback: explicit tcp/127.0.0.1 endpoints, no multicast.

Each peer is a FleetSharing session with its own ExperienceController on a small position
problem; the tests poll with a deadline rather than sleeping.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import socket
import time
from collections.abc import AsyncIterator, Callable

import numpy as np
import pytest
import zenoh

from epc_offboard.config import SharingConfig
from epc_offboard.epc import ExperienceController, LibraryEntry
from epc_offboard.sharing import FleetSharing
from epc_offboard.wire import (
    ControllerMessage,
    MessageKind,
    ReferenceMessage,
    encode_controllers,
    encode_reference,
)
from tests.mpc_cases import hover_refs, position_problem

pytestmark = pytest.mark.timeout(60)

FLEET = "test"
# targets far enough that input and velocity bounds are active: distinct active sets
TARGETS = ([10.0, 0.0, 0.0], [0.0, -10.0, 0.0], [0.0, 0.0, 10.0], [-10.0, 10.0, 0.0])


def free_tcp_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


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


async def until(cond: Callable[[], bool], what: str, timeout_s: float = 10.0) -> None:
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
        ports = [free_tcp_port() for _ in range(3)]
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
            await until(lambda: ctrls[1].contains(aset) and ctrls[2].contains(aset), "sharing")
            for c in ctrls[1:]:
                assert used_as_hit(c, TARGETS[0])
                assert c.stats.received_shared == 1
                assert c.stats.qp_solves == 0
            # and back: what peer 3 learns reaches peer 1
            aset3 = learn(ctrls[2], TARGETS[1])
            await until(lambda: ctrls[0].contains(aset3), "sharing from peer 3")
            assert used_as_hit(ctrls[0], TARGETS[1])
            assert peers[0].stats()["entries_published"] == 1

    asyncio.run(main())


def test_a_late_joiner_gets_the_snapshot():
    async def main() -> None:
        pa, pc = free_tcp_port(), free_tcp_port()
        a, c = controller(), controller()
        sets = [learn(a, t) for t in TARGETS[:3]]
        async with peer(config("early", pa, [pc]), a) as sa:
            await until(lambda: sa.stats().get("entries_published", 0) == 3, "a's batch")
            # nobody heard the batch; the joiner can only learn these from the snapshot
            async with peer(config("late", pc, [pa]), c) as sc:
                await until(lambda: all(c.contains(s) for s in sets), "the snapshot")
                assert sc.stats()["entries_accepted"] == 3
                assert c.stats.received_shared == 3
                assert all(used_as_hit(c, t) for t in TARGETS[:3])
                assert c.stats.qp_solves == 0

    asyncio.run(main())


def test_a_peer_with_another_problem_signature_is_ignored():
    async def main() -> None:
        pa, pb, pd = free_tcp_port(), free_tcp_port(), free_tcp_port()
        a, b, d = controller(), controller(), controller(horizon=6)
        assert d.problem.signature() != a.problem.signature()
        async with (
            peer(config("a", pa, [pb, pd]), a) as sa,
            peer(config("b", pb, [pa, pd]), b),
            peer(config("d", pd, [pa, pb]), d) as sd,
        ):
            learn(d, TARGETS[0])
            aset = learn(a, TARGETS[1])
            await until(lambda: b.contains(aset), "a -> b")
            await until(lambda: sd.stats().get("entries_published", 0) == 1, "d publishing")
            await asyncio.sleep(0.2)  # several publish periods: d's batch had every chance
            assert a.stats.size == 1
            assert b.stats.size == 1
            assert d.stats.size == 1
            assert a.stats.received_shared == 0
            assert "d" not in sa.received_from  # a and b never subscribed to d's keys
            assert sa.received_from["b"] >= 1
            assert sd.stats().get("messages_received", 0) == 0
            assert sd.stats()["peers"] == 0

    asyncio.run(main())


def test_malformed_truncated_and_oversized_payloads_are_rejected_and_counted():
    async def main() -> None:
        pb, praw = free_tcp_port(), free_tcp_port()
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
                assert b.stats.size == 0
                assert b.stats.received_shared == 0
                # the valid one still goes through the same path
                raw.put(key, good)
                await until(lambda: b.stats.size == 1, "the valid payload")
                assert b.contains((0, 1, 2))

    asyncio.run(main())


def test_a_flooding_peer_is_rate_limited():
    async def main() -> None:
        pb, praw = free_tcp_port(), free_tcp_port()
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
                await until(lambda: b.stats.size == 3, "the burst's three imports")
                stats = sb.stats()
                assert stats["rate_limited"] >= 7
                assert stats["entries_accepted"] == 3

    asyncio.run(main())


def test_sharing_survives_a_peer_restart():
    async def main() -> None:
        pa, pb = free_tcp_port(), free_tcp_port()
        a = controller()
        async with peer(config("a", pa, [pb]), a) as sa:
            b1 = controller()
            async with peer(config("b", pb, [pa]), b1):
                s1 = learn(a, TARGETS[0])
                await until(lambda: b1.contains(s1), "first controller")
            await until(lambda: sa.stats()["peers"] == 0, "a to see b leave")
            s2 = learn(a, TARGETS[1])  # learned while b is down
            await until(lambda: sa.stats().get("entries_published", 0) == 2, "a publishing")
            b2 = controller()  # the restarted process starts empty
            async with peer(config("b", pb, [pa]), b2):
                await until(lambda: b2.contains(s1) and b2.contains(s2), "re-fetch")
                s3 = learn(a, TARGETS[2])
                await until(lambda: b2.contains(s3), "live batches resume")
                assert all(used_as_hit(b2, t) for t in TARGETS[:3])

    asyncio.run(main())


def test_live_reference_is_received_fresh_then_stale():
    async def main() -> None:
        pa, praw = free_tcp_port(), free_tcp_port()
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
    from epc_offboard.trajectories import live_reference_horizon

    kw: dict = {"age_s": 0.1, "dt_s": 0.1, "steps": 4, "width": 9}
    hold = live_reference_horizon((1.0, 2.0, -3.0), None, (), None, **kw)
    assert hold.shape == (4, 9)
    np.testing.assert_allclose(hold[:, :3], np.tile([1.0, 2.0, -3.0], (4, 1)))
    assert not hold[:, 3:].any()
    track = live_reference_horizon((0.0, 0.0, -2.0), (1.0, 0.0, 0.0), (), None, **kw)
    np.testing.assert_allclose(track[:, 0], [0.2, 0.3, 0.4, 0.5])  # age + k dt, at 1 m/s
    np.testing.assert_allclose(track[:, 3], 1.0)
    path = live_reference_horizon(
        (0.0, 0.0, -2.0), None, ((0.2, 0.0, -2.0), (0.2, 0.2, -2.0)), 0.2, **kw
    )
    # t = 0.2, 0.3, 0.4, 0.5 s along 0 -> (0.2, 0) -> (0.2, 0.2), then held at the end
    np.testing.assert_allclose(path[:, 0], [0.2, 0.2, 0.2, 0.2])
    np.testing.assert_allclose(path[:, 1], [0.0, 0.1, 0.2, 0.2])
    np.testing.assert_allclose(path[:, 4], [1.0, 1.0, 0.0, 0.0])
