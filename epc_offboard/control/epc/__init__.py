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

from typing import TYPE_CHECKING, Any

# The public names, imported on first use (PEP 562): the miss worker imports the learner and
# the map builder (``epc_offboard.control.epc.learner``, ``.maps``), which must not load the
# controller with this package.
_PUBLIC = {
    "CHECK_NS_PER_MAC": "maps",
    "MAX_SUCCESSORS": "candidates",
    "ActiveSetMap": "maps",
    "CandidatePool": "candidates",
    "DependentActiveSetError": "maps",
    "EpcStats": "controller",
    "ExperienceController": "controller",
    "IntermediateQp": "learner",
    "Learner": "learner",
    "Library": "library",
    "MapBuilder": "maps",
    "budgeted_controller": "controller",
}

if TYPE_CHECKING:
    from epc_offboard.control.epc.candidates import MAX_SUCCESSORS, CandidatePool
    from epc_offboard.control.epc.controller import (
        EpcStats,
        ExperienceController,
        budgeted_controller,
    )
    from epc_offboard.control.epc.learner import IntermediateQp, Learner
    from epc_offboard.control.epc.library import Library
    from epc_offboard.control.epc.maps import (
        CHECK_NS_PER_MAC,
        ActiveSetMap,
        DependentActiveSetError,
        MapBuilder,
    )


def __getattr__(name: str) -> Any:
    module = _PUBLIC.get(name)
    if module is None:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    import importlib

    return getattr(importlib.import_module(f"{__name__}.{module}"), name)


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
