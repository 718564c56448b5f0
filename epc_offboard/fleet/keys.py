"""The fleet's Zenoh key expressions, in one place.

Every key the product uses starts with ``epc/``. ``<signature>`` is
``MpcProblem.signature()``: one set of keys per shared problem (the position and the attitude
loop have different signatures), so a vehicle hears only the problems it flies. A planner
publishing live references, or an outside tool joining a fleet, builds its keys from these
templates; docs/CONTRACTS.md (Zenoh) lists them and ``tests/test_contracts.py`` keeps the two
the same. A leaf module (no imports): a peer may read it without Zenoh or numpy.
"""

from __future__ import annotations

ROOT = "epc"
# each batch of new controllers (wire.MessageKind.BATCH), published by <vehicle>
CONTROLLERS = "epc/{fleet}/{signature}/ctl/{vehicle}"
# queryable: <vehicle>'s whole library for the problem (wire.MessageKind.SNAPSHOT)
LIBRARY = "epc/{fleet}/{signature}/lib/{vehicle}"
# liveliness token: <vehicle> shares the problem now (a new one is queried for its library)
ALIVE = "epc/{fleet}/{signature}/alive/{vehicle}"
# live references for one vehicle, from a planner (wire.ReferenceMessage, JSON)
REFERENCE = "epc/{fleet}/{vehicle}/reference"

KEYS = {"controllers": CONTROLLERS, "library": LIBRARY, "alive": ALIVE, "reference": REFERENCE}

ANY = "*"  # Zenoh's wildcard for one chunk: every vehicle


def problem_key(template: str, fleet: str, signature: str, vehicle: str) -> str:
    """One of the per-problem keys (CONTROLLERS, LIBRARY, ALIVE); ``vehicle`` may be ANY."""
    return template.format(fleet=fleet, signature=signature, vehicle=vehicle)


def reference_key(fleet: str, vehicle: str) -> str:
    """Where a planner publishes ``vehicle``'s live references."""
    return REFERENCE.format(fleet=fleet, vehicle=vehicle)
