"""A compatibility shim: LWPR's import path that docs/CONTRACTS.md (Python API) promises,
``from epc_offboard.lwpr import LWPR``, kept so scripts written against it keep working.

Re-exports only, and nothing inside the package imports it (``tests/test_layers.py``
checks): the implementation is :mod:`epc_offboard.control.lwpr`, also exported from the
package root (``from epc_offboard import LWPR``).
"""

from __future__ import annotations

from epc_offboard.control.lwpr import LWPR, LwprError

__all__ = ["LWPR", "LwprError"]
