"""Experience-driven Predictive Control (thesis chapter 3), one module per part of the
algorithm as the thesis explains it:

* :mod:`~epc_offboard.control.epc.maps` — a controller as an active set's affine map, its KKT
  check (3.5-3.8) and the problem geometry every map shares;
* :mod:`~epc_offboard.control.epc.library` — entries, importance, eviction, transitions and
  the bounded query (algorithm 1, lines 6-13 and 18-21);
* :mod:`~epc_offboard.control.epc.learner` — the full QP, the recovery of its active set and
  the intermediate QP (lines 15-17);
* :mod:`~epc_offboard.control.epc.candidates` — controllers received from the fleet, proven
  here before they join the library;
* :mod:`~epc_offboard.control.epc.controller` — ``step``: the hot path;
* :mod:`~epc_offboard.control.epc.exchange` — what the controller trades with the store, the
  miss worker and the fleet.

``from epc_offboard.control.epc import ExperienceController`` is the public entry point.
"""

from __future__ import annotations

from epc_offboard.control.epc.candidates import MAX_SUCCESSORS, CandidatePool
from epc_offboard.control.epc.controller import EpcStats, ExperienceController, budgeted_controller
from epc_offboard.control.epc.learner import IntermediateQp, Learner
from epc_offboard.control.epc.library import Library
from epc_offboard.control.epc.maps import (
    CHECK_NS_PER_MAC,
    ActiveSetMap,
    DependentActiveSetError,
    MapBuilder,
)

__all__ = [
    "CHECK_NS_PER_MAC",
    "MAX_SUCCESSORS",
    "ActiveSetMap",
    "CandidatePool",
    "DependentActiveSetError",
    "EpcStats",
    "ExperienceController",
    "IntermediateQp",
    "Learner",
    "Library",
    "MapBuilder",
    "budgeted_controller",
]
