"""The library's writes in a store process of its own (issue 21): saved while flying and at
shutdown, a dead store process restarted, and the flight never waiting on the disk."""

from __future__ import annotations

import asyncio
import contextlib
import io
import os
import signal
import time
from collections import Counter
from typing import Any

import numpy as np
import pytest

from epc_offboard.service.config import StoreConfig, load_service_config
from epc_offboard.service.library_keeper import LibraryKeeper
from epc_offboard.store.database import LibraryStore
from epc_offboard.tools.sim.scenario import SITL_SERVICE_CONFIG
from tests.mpc_cases import hover_refs

pytestmark = pytest.mark.timeout(90)


def stored(path) -> dict[str, dict[str, int]]:
    store = LibraryStore.open_readonly(path)
    try:
        return store.summary()
    finally:
        store.close()


def test_saved_by_the_store_process_which_is_restarted_when_it_dies(tmp_path):
    from epc_offboard.control.cascade import Cascade

    cfg = load_service_config(SITL_SERVICE_CONFIG)
    cascade = Cascade(cfg.position, cfg.attitude, cfg.estimator, 0.01)
    path = tmp_path / "library.sqlite"
    counters: Counter[str] = Counter()
    keeper = LibraryKeeper(StoreConfig(str(path), save_period_s=0.05), cascade, counters,
                           published=lambda: False)  # fmt: skip
    keeper.open()
    ctrl = dict(cascade.experience_controllers())["position"]
    p = ctrl.problem

    async def main() -> None:
        task = asyncio.create_task(keeper.run())
        try:
            ctrl.step(np.zeros(p.nx), hover_refs(p, [5.0, 0.0, 0.0]))  # a solve: learned
            deadline = time.monotonic() + 20
            while keeper.process_stats().get("saves", 0) < 2:
                assert time.monotonic() < deadline, keeper.process_stats()
                await asyncio.sleep(0.05)
            pid = keeper.process_stats()["pid"]
            assert isinstance(pid, int)
            assert pid != os.getpid()
            os.kill(pid, signal.SIGKILL)
            while counters["store_restarts"] < 1:
                assert time.monotonic() < deadline + 20, dict(counters)
                await asyncio.sleep(0.05)
            assert counters["store_failures"] == 1
            assert keeper.process_stats()["pid"] not in (None, pid)
        finally:
            task.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await task

    asyncio.run(main())
    n_position = ctrl.stats.size
    keeper.close()
    summary = stored(path)
    assert summary[p.signature()]["controllers"] == n_position >= 1
    assert summary[p.signature()]["models"] == 1  # the estimator, saved beside them


def test_the_estimator_is_formatted_by_the_store_process_not_on_the_loops_thread(
    tmp_path, monkeypatch
):
    """Issue 21: the estimator's npz (``to_bytes``, numpy's zip entry by entry) took 2-8 ms
    of the loops' thread every save beside two CPU hogs. The saver now pickles it there and
    the store process formats it: what is stored is the same model."""
    from epc_offboard.control.cascade import Cascade
    from epc_offboard.store import experience

    cfg = load_service_config(SITL_SERVICE_CONFIG)
    cascade = Cascade(cfg.position, cfg.attitude, cfg.estimator, 0.01)
    est = cascade.position.estimator
    rng = np.random.default_rng(0)
    for _ in range(200):  # a learned model, not the empty one
        est.observe(rng.normal(size=est.n_z), rng.normal(size=est.nx))
    formatted_here: list[int] = []
    to_bytes: Any = type(est).to_bytes

    def counted(self):
        formatted_here.append(1)
        return to_bytes(self)

    monkeypatch.setattr(type(est), "to_bytes", counted)
    path = tmp_path / "library.sqlite"
    keeper = LibraryKeeper(StoreConfig(str(path), save_period_s=0.05), cascade, Counter(),
                           published=lambda: False)  # fmt: skip
    keeper.open()

    async def main() -> None:
        task = asyncio.create_task(keeper.run())
        try:
            deadline = time.monotonic() + 30
            while keeper.process_stats().get("saves", 0) < 2:
                assert time.monotonic() < deadline, keeper.process_stats()
                await asyncio.sleep(0.05)
        finally:
            task.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await task

    asyncio.run(main())
    assert formatted_here == []  # not once in the flight's process
    assert keeper.process_stats()["loop_slices"] >= 2
    store = LibraryStore.open_readonly(path)
    try:
        blob = store.load_model(experience._estimator_key(cascade),
                                cascade.position.problem.signature())  # fmt: skip
    finally:
        store.close()
    keeper.close()
    assert blob is not None
    with np.load(io.BytesIO(blob)) as saved, np.load(io.BytesIO(to_bytes(est))) as here:
        assert sorted(saved.files) == sorted(here.files)
        for name in here.files:
            a, b = saved[name], here[name]
            if a.dtype.kind in "SUO":
                assert a.tobytes() == b.tobytes(), name
            else:
                np.testing.assert_array_equal(a, b, err_msg=name)
