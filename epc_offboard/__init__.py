"""epc-offboard: MAVLink offboard flight control by Experience-driven Predictive Control."""

from __future__ import annotations

__version__ = "0.1.0"

__all__ = ["__version__"]
