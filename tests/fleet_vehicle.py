"""A vehicle's control process without its autopilot link, for tests that kill and restart
it: the service's cascade (``config/sitl.toml``'s problems), its fleet sharing and its
library store, wired as ``Service.run`` wires them (the store's fleet state restored before
the session opens, saved with the library by the store process). Prints one JSON line of
its state every 0.2 s: the fleet stats, the store's saves, and every active set the
position controller holds (library and received candidates), and its library alone.
``learn``: hover targets [n, e, d] m the position controller solves before the session
opens (controllers of its own, published and in its library).

    python -m tests.fleet_vehicle '{"sharing": {...SharingConfig...}, "store": PATH,
                                    "learn": [[n, e, d], ...]}'
"""

from __future__ import annotations

import asyncio
import json
import sys
from collections import Counter
from pathlib import Path
from typing import Any

import numpy as np

from epc_offboard.control.cascade import Cascade
from epc_offboard.fleet.sharing import FleetSharing, SharingConfig
from epc_offboard.service.config import StoreConfig, load_service_config
from epc_offboard.service.library_keeper import LibraryKeeper
from tests.mpc_cases import hover_refs

SAVE_PERIOD_S = 0.3
REPO = Path(__file__).resolve().parents[1]


def sharing_config(d: dict[str, Any]) -> SharingConfig:
    fields: dict[str, Any] = {k: tuple(v) if isinstance(v, list) else v for k, v in d.items()}
    return SharingConfig(**fields)


async def main(args: dict[str, Any]) -> None:
    cfg = load_service_config(REPO / "config" / "sitl.toml")
    cascade = Cascade(cfg.position, cfg.attitude, cfg.estimator,
                      1.0 / cfg.loops.position_rate_hz)  # fmt: skip
    sharing = FleetSharing(sharing_config(args["sharing"]), cascade.experience_controllers(),
                           candidates=cfg.candidates)  # fmt: skip
    # (a build without them, e.g. the code before issue 25's restart: it starts afresh)
    restart = hasattr(sharing, "fleet_state")
    keep: dict[str, Any] = {}
    if hasattr(sharing, "fleet_state_steps"):  # taken in slices (issue 21)
        keep = {"fleet_steps": sharing.fleet_state_steps}
    elif restart:
        keep = {"fleet_state": sharing.fleet_state}
    keeper = LibraryKeeper(StoreConfig(args["store"], SAVE_PERIOD_S), cascade, Counter(),
                           published=lambda: True, **keep)  # fmt: skip
    keeper.open()
    ctrl = cascade.experience_controllers()[0][1]
    for target_ned_m in args.get("learn", []):
        ctrl.step(np.zeros(ctrl.problem.nx), hover_refs(ctrl.problem, target_ned_m))
    if restart:
        sharing.restore(keeper.fleet_saved)
    await sharing.open()
    tasks = [asyncio.create_task(sharing.run()), asyncio.create_task(keeper.run())]
    while all(not t.done() for t in tasks):
        held = [e.active_set for e in ctrl.export_library()]
        pool = ctrl.candidates
        held += ([e.active_set for e, _ in pool.known()] if restart
                 else [a for a, _ in pool.items()])  # fmt: skip
        print(json.dumps({"stats": sharing.stats(), "saves": keeper.process_stats().get("saves"),
                          "held": sorted(held), "library": len(ctrl.export_library())}),
              flush=True)  # fmt: skip
        await asyncio.sleep(0.2)
    for t in tasks:
        t.result()  # a task that ended raised: say why


if __name__ == "__main__":
    asyncio.run(main(json.loads(sys.argv[1])))
