"""A library save's fleet work on the loops' thread does not grow with the peers heard
(issue 21). Under rotating ids the fleet helper's high-water marks change every save; the
control process parsed them (``json.loads``), rebuilt each with its problem's signature
and wrote them out again, on the loops' thread, every save: 2,048 marks (MAX_PEERS per
problem) cost thousands of calls there. The helper now makes the texts the store keeps
(``HighWater.save``), and a save here reads a header and copies them, whole or not at all."""

from __future__ import annotations

import json
import os
import sys
import types
from collections import Counter
from typing import Any

from epc_offboard.control.cascade import Cascade
from epc_offboard.fleet.config import SharingConfig
from epc_offboard.fleet.exchange import MAX_PEERS
from epc_offboard.fleet.session import TEXTS_HEADER, HighWater
from epc_offboard.fleet.sharing import FleetSharing
from epc_offboard.service.config import load_service_config
from tests.test_tick_cost import _CONFIG, _DT_S

EPOCH = 123456789012345


def _sharing() -> tuple[FleetSharing, HighWater]:
    cfg = load_service_config(_CONFIG)
    cascade = Cascade(cfg.position, cfg.attitude, cfg.estimator, _DT_S)
    sharing = FleetSharing(SharingConfig(enabled=True, vehicle_id="me"),
                           cascade.experience_controllers())  # fmt: skip
    # the helper's side, here: its marks and the buffers it writes
    hw = HighWater(len(sharing.specs), b"", [s.signature for s in sharing.specs])
    return sharing, hw


def _hear(hw: HighWater, first: int, n: int, problems: int) -> None:
    for k in range(first, first + n):
        for i in range(problems):
            hw.received(i, f"rotating-{k:08d}", {"e": EPOCH, "s": k + 1}, False)


def _as_running_helper(sharing: FleetSharing, pid: int) -> None:
    sharing._helper = types.SimpleNamespace(process=types.SimpleNamespace(pid=pid))  # type: ignore[assignment]


def test_a_save_with_every_mark_changed_costs_the_loops_thread_the_same_few_calls(monkeypatch):
    from epc_offboard.fleet import sharing as sharing_module

    sharing, hw = _sharing()
    problems = len(sharing.specs)
    _as_running_helper(sharing, os.getpid())
    _hear(hw, 0, MAX_PEERS, problems)  # the table full
    hw.settle(lambda: 0)
    hw.save(sharing._high_water_raw, sharing._texts_raw)
    *_, first = sharing.fleet_state_steps()  # the first save reads them
    _hear(hw, MAX_PEERS, 20, problems)  # 20 new ids per problem since
    hw.settle(lambda: 0)
    hw.save(sharing._high_water_raw, sharing._texts_raw)
    calls: Counter[str] = Counter()
    parsed: Counter[str] = Counter()  # JSON parsed or written on the loops' thread, in bytes

    def profile(frame: Any, event: str, arg: Any) -> None:
        calls[event] += 1

    def counted(name: str) -> Any:
        real = getattr(json, name)

        def call(obj: Any, *args: Any, **kwargs: Any) -> Any:
            out = real(obj, *args, **kwargs)
            parsed[name] += len(obj if name == "loads" else out)
            return out

        return call

    monkeypatch.setattr(sharing_module, "json", types.SimpleNamespace(
        loads=counted("loads"), dumps=counted("dumps")))  # fmt: skip
    sys.setprofile(profile)
    try:
        *_, taken = sharing.fleet_state_steps()  # what the loops' thread does a save
    finally:
        sys.setprofile(None)
    monkeypatch.undo()
    # before: json.loads of every mark (90 kB), a signature put to each and json.dumps of
    # them all again (158 kB), 6.4 ms of the loops' thread a save; now a header and a copy
    assert parsed == {}, parsed
    assert calls["call"] + calls["c_call"] <= 200, dict(calls)
    assert first is not None
    assert taken is not None
    held = json.loads(str(taken["marks"]))["held"]
    assert len(held) == len(hw.held) == MAX_PEERS * problems
    sigs = [s.signature for s in sharing.specs]
    want = sorted([sigs[i], p, e, n] for (i, p), (e, n) in hw.held.items())
    assert sorted(held) == want  # the same marks the control process built before
    assert taken["marks"] != first["marks"]


def test_marks_are_taken_only_from_the_running_helper_once_read_and_only_whole():
    sharing, hw = _sharing()
    _hear(hw, 0, 3, len(sharing.specs))
    hw.settle(lambda: 5)  # settled when the helper had handed out 5 records
    hw.of_library(0, [])
    hw.save(sharing._high_water_raw, sharing._texts_raw)
    none = '{"held":[]}'
    _as_running_helper(sharing, os.getpid() + 1)  # another helper's marks
    assert sharing.fleet_state()["marks"] == none
    _as_running_helper(sharing, os.getpid())
    sharing._read = 4  # one record they cover not read yet
    assert sharing.fleet_state()["marks"] == none
    sharing._read = 5
    marks = sharing.fleet_state()["marks"]
    assert len(json.loads(marks)["held"]) == 3 * len(sharing.specs)
    own = json.loads(sharing.fleet_state()["own"])
    assert own["epoch"] == hw.epoch
    assert own["signatures"] == [s.signature for s in sharing.specs]
    # caught mid-write (a text changed under its header): not believed, the last one kept
    _hear(hw, 3, 1, len(sharing.specs))
    hw.settle(lambda: 5)
    hw.save(sharing._high_water_raw, sharing._texts_raw)
    view = memoryview(sharing._texts_raw).cast("B")
    view[TEXTS_HEADER.size + 2] ^= 0xFF
    assert sharing.fleet_state()["marks"] == marks
    view[TEXTS_HEADER.size + 2] ^= 0xFF  # whole again: read at the next save
    assert len(json.loads(sharing.fleet_state()["marks"])["held"]) == 4 * len(sharing.specs)
