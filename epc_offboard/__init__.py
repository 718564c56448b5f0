"""epc-offboard: MAVLink offboard flight control by Experience-driven Predictive Control."""

from __future__ import annotations

import os
from typing import TYPE_CHECKING, Any

# Every matrix in the control loops is small (<= 240 x 136): BLAS threads only add
# synchronisation, and on a loaded companion computer their spin-waiting made EPC's miss path
# 20x slower. Set before numpy loads (any import of this package comes first); an explicit
# environment setting still wins.
for _var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

# numba's on-disk kernel cache: under systemd, the unit's StateDirectory (systemd sets
# STATE_DIRECTORY), which the service's User= can write; the default location beside the
# installed package usually is not, and then every start compiles afresh. Set before numba
# loads; an explicit NUMBA_CACHE_DIR still wins.
if "STATE_DIRECTORY" in os.environ:
    _state_dir = os.environ["STATE_DIRECTORY"].split(":")[0]
    os.environ.setdefault("NUMBA_CACHE_DIR", os.path.join(_state_dir, "numba-cache"))

__version__ = "0.1.0"

# The public API, imported on first use (PEP 562): the bundled SITL imports
# ``epc_offboard.common`` and must not pull in the controller (numba, OSQP) with it.
_PUBLIC = {
    "ExperienceController": "epc_offboard.control.epc",
    "LibraryEntry": "epc_offboard.control.library_types",
    "LinearModel": "epc_offboard.control.models",
    "MpcProblem": "epc_offboard.control.qp",
    "LWPR": "epc_offboard.control.lwpr",
    "EpcError": "epc_offboard.common.errors",
}

if TYPE_CHECKING:
    from epc_offboard.common.errors import EpcError
    from epc_offboard.control.epc import ExperienceController
    from epc_offboard.control.library_types import LibraryEntry
    from epc_offboard.control.lwpr import LWPR
    from epc_offboard.control.models import LinearModel
    from epc_offboard.control.qp import MpcProblem


def __getattr__(name: str) -> Any:
    module = _PUBLIC.get(name)
    if module is None:
        raise AttributeError(f"module 'epc_offboard' has no attribute {name!r}")
    import importlib

    return getattr(importlib.import_module(module), name)


__all__ = [
    "LWPR",
    "EpcError",
    "ExperienceController",
    "LibraryEntry",
    "LinearModel",
    "MpcProblem",
    "__version__",
]
