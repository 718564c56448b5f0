"""The library's writes in a store process of its own (issue 21): saved while flying and at
shutdown, a dead store process restarted, and the flight never waiting on the disk."""

from __future__ import annotations

import asyncio
import contextlib
import os
import signal
import time
from collections import Counter

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



def test_the_estimator_is_serialised_a_model_a_slice_to_the_same_bytes():
    """LWPR's three models took 4-9 ms in one slice on the loops' thread every save (a late
    attitude tick, issue 21): each model is a slice of its own, and the bytes are the same."""
    from epc_offboard.control.cascade import Cascade
    from epc_offboard.control.perturbation import LwprPerturbation
    from epc_offboard.store import experience

    cfg = load_service_config(SITL_SERVICE_CONFIG)
    cascade = Cascade(cfg.position, cfg.attitude, cfg.estimator, 0.01)
    estimator = cascade.position.estimator
    assert isinstance(estimator, LwprPerturbation)
    rng = np.random.default_rng(3)
    for _ in range(200):  # something learned in every model
        estimator.observe(rng.normal(size=estimator.n_z), rng.normal(size=estimator.nx))
    models = len(estimator.models)
    assert models >= 2
    steps = list(experience.estimator_model_steps(cascade))
    assert steps[:-1] == [None] * models
    assert steps[-1] == experience.estimator_models(cascade)
    keeper = LibraryKeeper(StoreConfig(""), cascade, Counter(), published=lambda: False)
    asyncio.run(keeper._sliced_snapshot())
    assert keeper.slices == 2 + models + 1  # the fleet's, a model each, the outer npz, the rest
