"""CONTRACTS.md's import path for LWPR (``from epc_offboard.lwpr import LWPR``), kept so scripts
written against it keep working. The implementation is :mod:`epc_offboard.control.lwpr`."""

from __future__ import annotations

from epc_offboard.control.lwpr import LWPR, LwprError

__all__ = ["LWPR", "LwprError"]
